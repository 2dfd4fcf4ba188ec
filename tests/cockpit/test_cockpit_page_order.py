"""The cockpit page in a real browser: a new J waits for the heavy drawing in progress, never for the next one.

The page draws the banner, the cards, the J plot and the table as soon as a change arrives, and the heavy plots
(the GP contour, the signals, the spectra) one per task after it. A change that arrives while a heavy drawing runs
must be drawn before the next heavy drawing starts. (In a clean-clone CI run a J took 0.508 s to show, 0.3 s of it
after the page's script had the message: most likely behind two heavy drawings, the one in progress and the next.)

The cockpit's own server (:class:`bac_cockpit.server.CockpitServer`) sends scripted parts of a campaign's state to
headless Chromium; each heavy plot's ``Plotly.react`` is made to last HEAVY_MS more (a busy loop put in the page),
so that a J sent JITTER_S after the heavy parts lands inside the first heavy drawing, with the next two still to
come. The page's own ordered log (``bacCockpit.log``: each patch as its handler runs, each drawing's start and
end) says what came first; order, not wall time, is asserted.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.browser import chromium, page_errors, wait_js

from bac_cockpit.server import CockpitServer
from bac_cockpit.state import CockpitState

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]
HEAVY = ("renderGP", "renderSignals", "renderSpectra")
HEAVY_MS = 2000  # each heavy plot's drawing made this much longer
JITTER_S = 1.15  # the J is sent this long after the heavy parts: in the middle of the first heavy drawing (0.15-2.15 s)
ROUNDS = 3
SLOW_PLOTS = f"""
const react = Plotly.react;
Plotly.react = function (el, ...rest) {{
  const out = react.call(this, el, ...rest);
  if (['gpplot', 'sigplot', 'specplot'].includes(el.id)) {{
    const t = performance.now();
    while (performance.now() - t < {HEAVY_MS}) {{}}
  }}
  return out;
}};
return true;
"""
NAMES = ("damping_front", "damping_rear")


class ScriptedState(CockpitState):
    """A cockpit state whose parts the test sets (the server sends them as it sends a campaign's)."""

    def __init__(self) -> None:
        super().__init__("live")
        self.parts: dict[str, Any] = {}

    def put(self, **parts: Any) -> list[str]:
        self.parts.update(parts)
        return self._bump(list(parts))

    def part(self, key: str) -> Any:
        return self.parts[key] if key in self.parts else super().part(key)


def row(trial_id: int) -> dict[str, Any]:
    x = (0.1 + 0.05 * trial_id) % 1.0
    return {"trial_id": trial_id, "kind": "bo", "params": {NAMES[0]: x, NAMES[1]: 1.0 - x},
            "j": 1.0 + 0.2 * math.sin(trial_id), "predicted_j": 1.05, "predicted_std": 0.05, "attempts": 1,
            "status": "scored", "reason": "", "rejected": []}  # fmt: skip


def run_view(trial_id: int, label: str, freq: bool) -> dict[str, Any]:
    """A run's signals (2,000 points, the cockpit's most) or spectra, as the state sends them."""
    n = 1025 if freq else 2000
    axis = [i * (0.1 if freq else 0.005) for i in range(n)]
    wave = [math.sin(0.05 * i + trial_id) * math.exp(-0.001 * i) for i in range(n)]
    view = {"label": f"{label}: trial {trial_id}", "trial_id": trial_id, "attempt": 1, "valid": True, "reason": "",
            "j": 1.0, "mode": "event", "source": "welch", "accel_z": [abs(w) + 1e-4 for w in wave],
            "pitch_rate": [0.1 * abs(w) + 1e-5 for w in wave]}  # fmt: skip
    view["f" if freq else "t"] = axis
    return view


def model(n_runs: int) -> dict[str, Any]:
    grid = [i / 40 for i in range(41)]
    mean = [[(x - 0.3) ** 2 + (y - 0.6) ** 2 + 0.01 * n_runs for x in grid] for y in grid]
    return {"kind": "contour", "dims": [{"name": n, "lower": 0.0, "upper": 1.0} for n in NAMES], "x": grid,
            "y": grid, "mean": mean, "status": f"GP posterior mean after {n_runs} runs", "n_runs": n_runs,
            "fixed": {}, "trials": [{"trial_id": i, "params": row(i)["params"]} for i in range(1, n_runs + 1)],
            "failed": [], "recommendation": {"params": {NAMES[0]: 0.3, NAMES[1]: 0.6}, "final": False}}  # fmt: skip


def heavy(trial_id: int) -> dict[str, Any]:
    return {
        "signals": {"last": run_view(trial_id, "last run", False), "best": run_view(1, "best run", False)},
        "spectra": {"last": run_view(trial_id, "last run", True), "best": run_view(1, "best run", True)},
        "model": model(trial_id),
    }


@pytest.fixture
def page(tmp_path: Path) -> Iterator[tuple[Any, CockpitServer]]:
    state = ScriptedState()
    state.put(trials=[row(1)])
    server = CockpitServer(state, host="127.0.0.1", port=0)
    server.start()
    driver = chromium(1400, 1560, tmp_path / "chromedriver.log")
    try:
        driver.get(server.url)
        wait_js(driver, "return document.getElementById('conn').textContent === 'connected'", 60, "the page connected")
        yield driver, server
        assert not page_errors(driver)
    finally:
        driver.quit()
        server.stop()


def test_a_new_j_waits_for_the_heavy_drawing_in_progress_at_most(page: tuple[Any, CockpitServer]) -> None:
    driver, server = page
    wait_js(driver, "return window.bacCockpit.log.some((e) => e[1] === 'renderSpectra')", 60, "the first drawing")
    driver.execute_script(SLOW_PLOTS)
    rows = [row(1)]
    marks = []
    for trial in range(2, 2 + ROUNDS):  # the heavy parts, then a J that lands during their first drawing
        marks.append(driver.execute_script("return window.bacCockpit.log.length"))
        server.apply(lambda st, t=trial: st.put(**heavy(t)))
        time.sleep(JITTER_S)  # not a wait for a condition: when the J is sent (the page cannot answer meanwhile)
        rows = [*rows, row(trial)]
        server.apply(lambda st, r=rows: st.put(trials=r))
        wait_js(driver, f"""const L = window.bacCockpit.log.slice({marks[-1]});
            return +document.getElementById('jplot').dataset.points === {len(rows)}
                && L.filter((e) => e[1] === 'renderSpectra').length > 0;""", 60, f"round {trial - 1}")  # fmt: skip
    log = driver.execute_script("return window.bacCockpit.log")
    seq = " ".join(f"{e[1]}@{e[2]:.0f}" + (f"+{e[3] - e[2]:.0f}" if e[0] == "draw" else "") for e in log)

    for n, (lo, hi) in enumerate(zip(marks, [*marks[1:], len(log)], strict=True), start=1):
        part = log[lo:hi]
        at = next((i for i, e in enumerate(part) if e[0] == "patch" and "trials" in e[1].split(",")), None)
        assert at is not None, f"round {n}: the page never had its J's message\n{seq}"
        drawn = next((e for e in part[at:] if e[0] == "draw" and e[1] == "renderJ"), None)
        assert drawn is not None, f"round {n}: its J was never drawn\n{seq}"
        # the case under test: the J's message waited for a heavy drawing, and more were queued behind it
        before = part[at - 1] if at > 0 else None
        assert before is not None and before[0] == "draw" and before[1] in HEAVY, (
            f"round {n}: the J did not arrive during a heavy drawing (the case was not made)\n{seq}"
        )
        assert any(e[0] == "draw" and e[1] in HEAVY for e in part[at:]), f"round {n}: nothing heavy left\n{seq}"
        t_in = part[at][2]
        started = [e[1] for e in part[at:] if e[0] == "draw" and e[1] in HEAVY and t_in <= e[2] < drawn[2]]
        assert not started, f"round {n}: the J waited for {started}, started after it came\n{seq}"
