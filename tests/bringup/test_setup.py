"""The one setup path is idempotent and quick when nothing changed."""

from __future__ import annotations

import subprocess
import time

from conftest import ROOT


def test_second_setup_run_does_nothing_and_is_quick() -> None:
    # make test has just run setup: a second run must find every stamp fresh
    t0 = time.monotonic()
    proc = subprocess.run([str(ROOT / "scripts" / "setup.sh")], capture_output=True, text=True, check=False)
    elapsed = time.monotonic() - t0
    assert proc.returncode == 0, proc.stderr
    lines = [x for x in proc.stdout.splitlines() if x.startswith("[setup]")]
    assert lines == [f"[setup] ready: {ROOT / '.venv'}"], proc.stdout
    assert elapsed < 10.0, f"setup with nothing changed took {elapsed:.1f} s"


def test_setup_stamps_cover_every_input() -> None:
    """Each step's stamp exists, so a changed input is noticed (the steps hash their inputs)."""
    stamps = ROOT / ".venv" / ".bac"
    for step in ("deps", "bac_msgs", "packages"):
        assert (stamps / step).read_text().strip(), step
