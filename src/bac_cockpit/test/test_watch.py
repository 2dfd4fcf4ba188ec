"""``bac watch``: the terminal view of the same state, from a running cockpit (its events) or a campaign folder."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from campaign_maker import make_campaign
from rich.console import Console

from bac_cockpit.server import CockpitServer
from bac_cockpit.state import CockpitState, TrialView
from bac_cockpit.watch import FolderSource, HttpSource, main, render, sparkline


def screen(snapshot: dict, connected: bool = True) -> str:
    console = Console(width=200, record=True, color_system=None)
    console.print(render(snapshot, "test", connected))
    return console.export_text()


def trial(state: int, trial_id: int = 3, reason: str = "") -> TrialView:
    return TrialView("c1", trial_id, 2, state, 1, {"damping_front": 0.2, "damping_rear": 0.3}, 8, 2, 0.97, 0.95, 1,
                     0.96, 0.01, "Drive the segment now at the target speed", reason, 12.0)  # fmt: skip


def test_the_screen_says_what_the_driver_must_do() -> None:
    st = CockpitState()
    st.set_speed_config(8.3333, "event", None)
    st.on_trial(trial(3, reason="too slow: 6.1 m/s"))
    text = screen(st.snapshot())
    assert "READY TO DRIVE" in text and "trial 3 of 8" in text and "run 2" in text
    assert "target speed 30 km/h" in text and "last run rejected: too slow: 6.1 m/s" in text
    # a live view that lost its cockpit never keeps showing READY TO DRIVE
    lost = screen(st.snapshot(), connected=False)
    assert "NO CONNECTION" in lost and "READY TO DRIVE" not in lost


def test_a_campaign_folder_is_shown_offline(tmp_path: Path) -> None:
    folder = tmp_path / "camp"
    make_campaign(folder, budget=5, reject={3: "alignment 0.2 below 0.5"})
    src = FolderSource(folder)
    src.start()
    text = screen(src.snapshot())
    assert "CAMPAIGN DONE" in text and "recommendation:" in text and "5 of 5 trials done" in text
    assert "run 1: alignment 0.2 below 0.5" in text
    rec = src.snapshot()["recommendation"]["params"]
    assert f"damping_front={rec['damping_front']:.3g}" in text
    assert main([str(folder), "--once"]) == 0


def test_a_running_cockpit_is_followed_through_its_events() -> None:
    srv = CockpitServer(CockpitState(), port=0)
    srv.start()
    src = HttpSource(f"http://127.0.0.1:{srv.bound.port}/")
    src.start()
    try:
        deadline = time.monotonic() + 20
        while not src.connected and time.monotonic() < deadline:
            time.sleep(0.02)
        assert src.connected
        srv.apply(lambda st: st.on_trial(trial(2)))
        while (src.snapshot().get("trial") or {}).get("state_name") != "APPLYING" and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "DO NOT DRIVE" in screen(src.snapshot())
    finally:
        src.stop()
        srv.stop()


def test_sparkline() -> None:
    assert sparkline([3.0, 2.0, 1.0]) == "█▅▁"
    assert sparkline([]) == ""


def test_a_damaged_journal_is_named_by_watch_and_cockpit_not_called_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # outside review 2026-11-29: both said "has no campaign journal" where bac report names the damaged line
    from bac_cockpit.cli import cockpit_main

    folder = tmp_path / "camp"
    make_campaign(folder, budget=4)
    journal = folder / "journal.jsonl"
    lines = journal.read_text().splitlines(keepends=True)
    journal.write_text("".join([*lines[:2], "garbage\n", *lines[2:]]))
    assert cockpit_main([str(folder), "--port", "0"]) == 2
    assert "line 3 is not a journal event" in capsys.readouterr().err
    assert main([str(folder), "--once", "--timeout", "0.3"]) == 1
    out = capsys.readouterr().out
    assert "line 3 is not a journal event" in " ".join(out.split()) and "has no campaign journal" not in out
