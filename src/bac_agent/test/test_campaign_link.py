"""The campaign pauses while the CAN link to the ECU is down (ERROR_BUS): no trial fails, then it resumes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from bac_agent.bo import Engine
from bac_agent.campaign import ERROR_BUS, Apply, AwaitRun, Campaign, CampaignConfig, Finish, Publish, State
from bac_agent.journal import Journal

SPACE = {"damping_front": (0.0, 1.0), "damping_rear": (0.0, 1.0)}
NO_ADAPTER = "cannot open CAN interface socketcan:can0: No such device; is the adapter plugged in and 'can0' up?"


class Driver:
    def __init__(self, camp: Campaign) -> None:
        self.c = camp
        self.applies: list[Apply] = []
        self.runs: list[AwaitRun] = []
        self.published: list[Any] = []
        self.finish: Finish | None = None

    def feed(self, acts: list[Any]) -> None:
        for a in acts:
            if isinstance(a, Publish):
                self.published.append(a.status)
            elif isinstance(a, Apply):
                self.applies.append(a)
            elif isinstance(a, AwaitRun):
                self.runs.append(a)
            elif isinstance(a, Finish):
                self.finish = a

    def answer(self, success: bool, code: int = 0, message: str = "") -> None:
        a = self.applies[-1]
        self.feed(self.c.on_apply_result(a.trial_id, a.apply_try, success, code, message, a.params if success else {}))


def events(tmp_path: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in (tmp_path / "journal.jsonl").read_text().splitlines()]


def make(tmp_path: Path, now: list[float]) -> tuple[Campaign, Driver, Engine]:
    eng = Engine(SPACE, budget=3, seed=1)
    cfg = CampaignConfig("c1", budget=3, apply_retries=0, link_retry_s=2.0, link_timeout_s=60.0)
    camp = Campaign(eng, Journal(tmp_path), cfg, clock=lambda: now[0])
    d = Driver(camp)
    d.feed(camp.start())
    return camp, d, eng


def test_a_lost_link_pauses_the_campaign_without_failing_a_trial(tmp_path: Path) -> None:
    now = [100.0]
    camp, d, eng = make(tmp_path, now)
    for _ in range(10):  # the adapter was unplugged for 40 s: apply_retries = 0 would have failed the trial at once
        d.answer(False, ERROR_BUS, NO_ADAPTER)
        now[0] += 4.0
    assert len(d.applies) == 11 and all(a.trial_id == 1 and a.delay_s == 2.0 for a in d.applies[1:])
    assert d.published[-1].state == State.APPLYING
    assert "paused" in d.published[-1].instruction and "adapter plugged in" in d.published[-1].instruction
    assert not eng.failures and not d.runs and camp.consecutive_failures == 0
    d.answer(True)  # plugged in again
    assert d.runs[-1].trial_id == 1
    ev = events(tmp_path)
    assert [e["event"] for e in ev].count("link_lost") == 1
    assert not [e for e in ev if e["event"] == "trial_failed"]


def test_a_link_down_for_too_long_stops_the_campaign_resumable_and_no_trial_fails(tmp_path: Path) -> None:
    now = [100.0]
    camp, d, eng = make(tmp_path, now)
    while d.finish is None:
        d.answer(False, ERROR_BUS, NO_ADAPTER)
        now[0] += 10.0
    assert d.finish.code == 2 and not eng.failures
    assert d.published[-1].state == State.IDLE and "resume" in d.published[-1].instruction
    assert [e["event"] for e in events(tmp_path)][-1] == "campaign_paused"
    camp.journal.close()
    # launched again with the same folder: the interrupted trial is applied again
    eng2 = Engine(SPACE, budget=3, seed=1)
    camp2 = Campaign(eng2, Journal(tmp_path), camp.cfg, clock=lambda: now[0])
    d2 = Driver(camp2)
    d2.feed(camp2.start())
    assert d2.applies[-1].trial_id == 1 and camp2.trials_done == 0


def test_other_errors_still_count_as_failed_tries(tmp_path: Path) -> None:
    now = [100.0]
    _camp, d, eng = make(tmp_path, now)
    d.answer(False, ERROR_BUS, NO_ADAPTER)
    d.answer(False, 7, "no valid answer to BEGIN")  # the link is back but the ECU does not answer: a failed try
    assert len(eng.failures) == 1
