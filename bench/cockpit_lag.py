"""How far the cockpit page is behind the graph: ``bac demo`` at 10x real time followed in headless Chromium (issue 22).

Runs ``tests/cockpit/test_cockpit_browser.py::test_the_page_follows_the_graph`` ``--runs``
times with ``BAC_COCKPIT_LAG_BOUND=1``, which makes it assert the 0.5 s bound on every update (``make test`` only
asserts that the page follows at all: the bound is a speed figure, and speed is measured here, by hand, not in
timed tests). Each run's figure (``cockpit_update_lag_s`` max and median, what the page drew while the worst update
waited) is read from ``build/test-output/cockpit_update_lag.txt``; the test's conditions are in its docstring and
in docs/cockpit.md (the demo's load-making nodes at nice 10, one screenshot's time left out). Run it on a machine
with nothing else running: the figure is the scheduler's as much as the page's.

LAST lines: ``cockpit_update_lag_s_max <seconds>`` (the worst over the runs, goal < 0.5 s) and
``runs_within_bound <k>/<n>``. An absolute figure, not a ratio against a baseline (the developers' guide's rule
for speed benchmarks): the goal is issue 22's bound, in seconds.

    .venv/bin/python bench/cockpit_lag.py [--runs 3]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIGURE = ROOT / "build" / "test-output" / "cockpit_update_lag.txt"
TEST = "tests/cockpit/test_cockpit_browser.py::test_the_page_follows_the_graph"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="runs of the demo with the browser (about 1 min each)")
    args = ap.parse_args()
    if args.runs < 1:
        ap.error("--runs must be at least 1")
    worst, met = 0.0, 0
    for k in range(1, args.runs + 1):
        FIGURE.unlink(missing_ok=True)
        t0 = time.monotonic()
        proc = subprocess.run(
            [str(ROOT / "scripts" / "pytest.sh"), "-p", "no:xdist", "-q", "-p", "no:cacheprovider", TEST],
            env={**os.environ, "BAC_COCKPIT_LAG_BOUND": "1"},
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=False,
        )
        if not FIGURE.exists():
            print(f"run {k}: no figure (pytest exit {proc.returncode}):\n{proc.stdout[-3000:]}{proc.stderr[-2000:]}")
            return 2
        text = FIGURE.read_text()
        m = re.search(r"cockpit_update_lag_s max ([0-9.]+)", text)
        if m is None:
            print(f"run {k}: the figure file holds no figure:\n{text}")
            return 2
        v = re.search(r"updates_over_[0-9.]+_s (\d+) of (\d+)", text)
        if v is None:
            print(f"run {k}: the figure file holds no verdict:\n{text}")
            return 2
        worst = max(worst, float(m.group(1)))
        within = int(v.group(1)) == 0
        met += within
        verdict = "bound met" if within else f"bound missed by {v.group(1)} of {v.group(2)} updates"
        if within != (proc.returncode == 0):  # the test failed otherwise, or passed without the bound
            verdict += f" (the test itself: pytest exit {proc.returncode}: see its output)"
        print(f"run {k} ({time.monotonic() - t0:.0f} s, {verdict}):")
        print("  " + "\n  ".join(text.strip().splitlines()))
        sys.stdout.flush()
    print(f"cockpit_update_lag_s_max {worst:.3f}")
    print(f"runs_within_bound {met}/{args.runs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
