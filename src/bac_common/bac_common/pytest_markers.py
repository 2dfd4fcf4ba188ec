"""The pytest markers of bac's unit tests, declared wherever pytest runs them (a pytest plugin: entry point
``pytest11`` of bac_common; pytest loads it by itself, nothing else imports it).

In the repository pyproject.toml declares them too; in a colcon workspace (src/ only, no pyproject.toml) this is
what keeps ``colcon test`` free of unknown-marker warnings and lets ``--pytest-args -m "not slow"`` (the quick unit
tests) run with ``--strict-markers``. No pytest import: the module is plain Python.
"""

from __future__ import annotations

from typing import Any

MARKERS = ("slow: a unit test of a few seconds or more (colcon test --pytest-args -m 'not slow' skips them)",)


def pytest_configure(config: Any) -> None:
    for line in MARKERS:
        config.addinivalue_line("markers", line)
