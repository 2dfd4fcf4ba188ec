"""The pytest markers of bac's unit tests, declared wherever pytest runs them (a pytest plugin: entry point
``pytest11`` of bac_common; pytest loads it by itself, nothing else imports it).

In the repository pyproject.toml declares them too; in a colcon workspace (src/ only, no pyproject.toml) this is
what keeps ``colcon test`` free of unknown-marker warnings and lets ``--pytest-args -m "not slow"`` (the quick unit
tests) run with ``--strict-markers``. No pytest import: the module is plain Python.

Its reach: pytest loads it in every process where bac_common is installed (a sourced workspace, a released
/opt/ros), so ``slow`` is declared there for other packages' tests too; ``PYTEST_DISABLE_PLUGIN_AUTOLOAD=1`` turns it
off, and then ``--strict-markers`` refuses bac's tests (pass ``-p bac_common.pytest_markers``). A ``conftest.py`` per
package would not do: the repository's integration tests import their helpers ``from conftest import ...``, and
the packages' conftest modules took that name's place in one pytest run.
"""

from __future__ import annotations

from typing import Any

# the same text as the repository's pyproject.toml
MARKERS = (
    "slow: an integration test of more than ~20 s, a unit test of more than a few seconds "
    "(colcon's workspace test skips those)",
)


def pytest_configure(config: Any) -> None:
    for line in MARKERS:
        config.addinivalue_line("markers", line)
