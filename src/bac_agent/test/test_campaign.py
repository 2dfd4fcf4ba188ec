"""The campaign state machine (no ROS): rules of algorithm 1 and resume from the journal."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from bac_agent.bo import Engine, EngineConfig
from bac_agent.bo.baselines import GridStrategy
from bac_agent.campaign import (
    RECOMMENDATION_NAME,
    Apply,
    AwaitRun,
    Campaign,
    CampaignConfig,
    Finish,
    Kind,
    Log,
    Publish,
    State,
)
from bac_agent.journal import Journal

SPACE = {"damping_front": (0.0, 1.0), "damping_rear": (0.0, 1.0)}


def j_of(p: dict[str, float]) -> float:
    return 1.0 + (p["damping_front"] - 0.3) ** 2 + (p["damping_rear"] - 0.6) ** 2


class Driver:
    """Plays the bridge and the chain for a Campaign, recording what it was asked to do."""

    def __init__(self, camp: Campaign) -> None:
        self.c = camp
        self.applies: list[Apply] = []
        self.runs: list[AwaitRun] = []
        self.published: list[Any] = []
        self.finish: Finish | None = None
        self.confirmed: dict[int, dict[str, float]] = {}

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

    def ok_apply(self) -> None:
        a = self.applies[-1]
        self.confirmed[a.trial_id] = a.params
        self.feed(self.c.on_apply_result(a.trial_id, a.apply_try, True, applied=a.params))

    def fail_apply(self, code: int = 3, message: str = "value out of range") -> None:
        a = self.applies[-1]
        self.feed(self.c.on_apply_result(a.trial_id, a.apply_try, False, code, message))

    def score(self, valid: bool = True, j: float | None = None, reason: str = "") -> None:
        r = self.runs[-1]
        p = self.confirmed[r.trial_id]
        self.feed(self.c.on_score("c1", r.trial_id, r.attempt, valid, j_of(p) if j is None else j, reason))

    def states(self) -> list[State]:
        return [s.state for s in self.published]


def make(tmp_path: Path, **kw: Any) -> tuple[Campaign, Driver, Engine]:
    budget = kw.pop("budget", 5)
    eng = Engine(SPACE, budget=budget, seed=1)
    cfg = CampaignConfig(campaign_id="c1", budget=budget, **kw)
    camp = Campaign(eng, Journal(tmp_path), cfg, clock=lambda: 12.5)
    d = Driver(camp)
    d.feed(camp.start())
    return camp, d, eng


def events(tmp_path: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in (tmp_path / "journal.jsonl").read_text().splitlines()]


def test_full_campaign_scores_every_trial_and_recommends(tmp_path: Path) -> None:
    _camp, d, eng = make(tmp_path, budget=5)
    for _ in range(5):
        d.ok_apply()
        d.score()
    assert d.finish is not None and d.finish.code == 0
    assert d.states()[:4] == [State.PROPOSED, State.APPLYING, State.READY_TO_DRIVE, State.SCORED]
    assert d.published[-1].state == State.DONE
    assert d.published[-1].params == d.finish.recommendation.params  # type: ignore[union-attr]
    assert len(eng.observations) == 5
    rec = json.loads((tmp_path / RECOMMENDATION_NAME).read_text())
    assert rec["campaign_id"] == "c1" and rec["trials_done"] == 5
    assert math.isclose(rec["predicted_j"], d.finish.recommendation.predicted_j)  # type: ignore[union-attr]
    kinds = [e["event"] for e in events(tmp_path)]
    assert kinds[0] == "campaign_started" and kinds[-1] == "campaign_done"
    assert kinds.count("trial_scored") == 5
    st = d.published[3]
    assert st.trials_done == 1 and st.last_j == st.best_j and st.best_trial_id == 1 and st.stamp == 12.5


def test_invalid_run_is_driven_again_then_trial_fails(tmp_path: Path) -> None:
    camp, d, eng = make(tmp_path, budget=3, max_attempts=2)
    d.ok_apply()
    d.score(valid=False, reason="speed 41 km/h, target 30")
    assert d.published[-1].state == State.READY_TO_DRIVE
    assert d.runs[-1].attempt == 2 and d.runs[-1].trial_id == 1
    assert d.published[-2].state == State.REJECTED and "speed" in d.published[-2].reason
    assert len(d.applies) == 1  # the same calibration stays on the ECU: no new apply
    d.score(valid=True, j=float("nan"))  # a NaN J counts as invalid
    assert d.published[-1].trial_id == 2  # trial 1 given up after 2 runs, trial 2 proposed
    assert any(s.state == State.FAILED and s.trial_id == 1 for s in d.published)
    assert len(eng.failures) == 1 and not eng.observations
    assert camp.trials_done == 1


def test_stale_and_foreign_scores_are_ignored(tmp_path: Path) -> None:
    camp, d, eng = make(tmp_path)
    a = d.applies[-1]
    # a score before the ECU confirmed: never booked
    d.feed(camp.on_score("c1", 1, 0, True, 1.0))
    d.feed(camp.on_score("c1", 1, 1, True, 1.0))
    assert not eng.observations
    d.ok_apply()
    d.feed(camp.on_score("other", 1, 1, True, 1.0))
    d.feed(camp.on_score("c1", 1, 2, True, 1.0))
    d.feed(camp.on_score("c1", 7, 1, True, 1.0))
    assert not eng.observations
    d.feed(camp.on_score("c1", 1, 1, True, 1.25))
    assert [o.value for o in eng.observations] == [1.25]
    assert eng.observations[0].params == a.params
    ignored = [e for e in events(tmp_path) if e["event"] == "score_ignored"]
    assert len(ignored) == 4


def test_failed_apply_is_retried_then_never_driven(tmp_path: Path) -> None:
    camp, d, eng = make(tmp_path, budget=2, apply_retries=1)
    d.fail_apply()
    assert len(d.applies) == 2 and d.applies[-1].apply_try == 2 and not d.runs
    d.fail_apply()
    assert not d.runs  # never READY_TO_DRIVE on an unconfirmed calibration
    assert len(eng.failures) == 1 and "ECU apply failed (error 3)" in eng.failures[0].reason
    # a score for the failed trial is refused
    d.feed(camp.on_score("c1", 1, 1, True, 0.5))
    assert not eng.observations
    # the next trial proceeds
    assert d.applies[-1].trial_id == 2
    d.feed(camp.on_apply_timeout(2, 1, "service ecu_bridge/apply_calibration not available"))
    assert d.applies[-1].trial_id == 2 and d.applies[-1].apply_try == 2


def test_busy_ecu_is_asked_again_later_without_failing(tmp_path: Path) -> None:
    now = [100.0]
    eng = Engine(SPACE, budget=3, seed=1)
    cfg = CampaignConfig("c1", budget=3, apply_retries=0, busy_retry_s=2.0, busy_timeout_s=30.0)
    camp = Campaign(eng, Journal(tmp_path), cfg, clock=lambda: now[0])
    d = Driver(camp)
    d.feed(camp.start())
    for _ in range(5):  # the vehicle is still rolling out of the last run: busy for 20 s
        d.fail_apply(4, "busy: vehicle moving")
        now[0] += 4.0
    assert len(d.applies) == 6 and all(a.delay_s == 2.0 for a in d.applies[1:])
    assert d.published[-1].state == State.APPLYING and "Stop the vehicle" in d.published[-1].instruction
    assert not eng.failures and not d.runs
    d.ok_apply()  # standstill: accepted
    assert d.runs[-1].trial_id == 1
    d.score()
    # busy for longer than busy_timeout_s: that is a failed try (apply_retries = 0: the trial fails)
    for _ in range(9):
        d.fail_apply(4, "busy: vehicle moving")
        now[0] += 4.0
    assert len(eng.failures) == 1 and "error 4" in eng.failures[0].reason
    assert not any(r.trial_id == 2 for r in d.runs)


def test_run_timeout_counts_as_invalid(tmp_path: Path) -> None:
    camp, d, _ = make(tmp_path, run_timeout_s=30.0)
    d.ok_apply()
    assert d.runs[-1].timeout_s == 30.0
    d.feed(camp.on_run_timeout(1, 1))
    assert d.published[-2].state == State.REJECTED and "run_timeout_s" in d.published[-2].reason
    assert d.runs[-1].attempt == 2
    d.feed(camp.on_run_timeout(1, 1))  # stale timer: nothing happens
    assert d.runs[-1].attempt == 2


def test_consecutive_failures_end_the_campaign(tmp_path: Path) -> None:
    _camp, d, _ = make(tmp_path, budget=10, apply_retries=0, max_consecutive_failures=2)
    d.fail_apply()
    d.fail_apply()
    assert d.finish is not None and d.finish.code == 1  # nothing scored: no recommendation


def test_confirmation_run(tmp_path: Path) -> None:
    camp, d, eng = make(tmp_path, budget=3, confirmation_run=True)
    for _ in range(3):
        d.ok_apply()
        d.score()
    assert d.finish is None
    assert d.published[-1].kind == Kind.CONFIRMATION and d.applies[-1].trial_id == 4
    rec = camp.recommendation
    assert rec is not None and d.applies[-1].params == rec.params
    d.ok_apply()
    d.score(j=1.01)
    assert d.finish is not None and d.finish.code == 0
    assert len(eng.observations) == 3  # the confirmation is not told to the optimizer
    assert json.loads((tmp_path / RECOMMENDATION_NAME).read_text())["confirmation_j"] == 1.01


def test_resume_after_a_crash_reapplies_the_interrupted_trial(tmp_path: Path) -> None:
    camp, d, _eng = make(tmp_path, budget=4)
    for _ in range(2):
        d.ok_apply()
        d.score()
    d.ok_apply()  # trial 3 is on the ECU and being driven: crash now
    inflight = d.applies[-1].params
    camp.journal.close()

    eng2 = Engine(SPACE, budget=4, seed=1)
    camp2 = Campaign(eng2, Journal(tmp_path), CampaignConfig(campaign_id="c1", budget=4), clock=lambda: 0.0)
    d2 = Driver(camp2)
    d2.feed(camp2.start())
    assert len(eng2.observations) == 2
    assert d2.applies[-1].trial_id == 3 and d2.applies[-1].params == inflight  # applied again
    assert not d2.runs
    # the interrupted run's late score (attempt 1) is refused; the new run is attempt 2
    d2.feed(camp2.on_score("c1", 3, 1, True, 0.1))
    assert len(eng2.observations) == 2
    d2.ok_apply()
    assert d2.runs[-1].attempt == 2
    d2.score()
    d2.ok_apply()
    d2.score()
    assert d2.finish is not None and d2.finish.code == 0
    ev = events(tmp_path)
    scored = [e["trial_id"] for e in ev if e["event"] == "trial_scored"]
    assert scored == [1, 2, 3, 4]
    assert any(e["event"] == "campaign_resumed" and e["in_flight"] == [3] for e in ev)
    # resuming a finished campaign just reports DONE again
    camp3 = Campaign(Engine(SPACE, budget=4, seed=1), Journal(tmp_path), CampaignConfig("c1", budget=4), lambda: 0.0)
    d3 = Driver(camp3)
    d3.feed(camp3.start())
    assert d3.finish is not None and d3.finish.code == 0 and d3.published[-1].state == State.DONE


def test_grid_strategy_through_the_campaign(tmp_path: Path) -> None:
    grid = GridStrategy(SPACE, size=3)
    camp = Campaign(grid, Journal(tmp_path), CampaignConfig("c1", budget=9, strategy="grid"), lambda: 0.0)
    d = Driver(camp)
    d.feed(camp.start())
    for _ in range(9):
        assert d.published[-1].kind == Kind.GRID
        d.ok_apply()
        d.score()
    assert d.finish is not None and d.finish.recommendation is not None
    assert d.finish.recommendation.params == {"damping_front": 0.5, "damping_rear": 0.5}


@pytest.mark.slow
def test_outcome_limits_are_modelled_and_a_broken_one_is_booked_and_shown(tmp_path: Path) -> None:
    """issue 23: a run's outcomes reach the optimizer and the journal; a run that broke a limit is not hidden."""

    def travel(p: dict[str, float]) -> float:
        return 80.0 - 40.0 * p["damping_front"]  # soft front dampers travel far

    limits = ("max_travel_mm<=60",)
    eng = Engine(SPACE, EngineConfig(budget=6, constraints=limits))
    camp = Campaign(eng, Journal(tmp_path), CampaignConfig("c1", budget=6, outcome_limits=limits), lambda: 1.0)
    d = Driver(camp)
    d.feed(camp.start())
    logs: list[str] = []
    for _ in range(6):
        d.ok_apply()
        r = d.runs[-1]
        p = d.confirmed[r.trial_id]
        acts = camp.on_score("c1", r.trial_id, r.attempt, True, j_of(p), "", None, {"max_travel_mm": travel(p)})
        logs += [a.text for a in acts if isinstance(a, Log)]
        d.feed(acts)
    assert d.finish is not None and d.finish.code == 0
    assert all(o.outcomes["max_travel_mm"] == travel(o.params) for o in eng.observations)
    scored = [e for e in events(tmp_path) if e["event"] == "trial_scored"]
    broken = [e for e in scored if travel(e["params"]) > 60.0]
    assert all(e["outcomes"] == {"max_travel_mm": travel(e["params"])} for e in scored)
    assert all(e["violations"] == [f"max_travel_mm <= 60 (measured {travel(e['params']):.4g})"] for e in broken)
    assert all(e["violations"] == [] for e in scored if e not in broken)
    assert sum("broke an outcome limit" in t for t in logs) == len(broken) == len(camp.violated_trials)
    rec = json.loads((tmp_path / RECOMMENDATION_NAME).read_text())
    assert travel(rec["params"]) <= 60.0 and rec["violated_trials"] == camp.violated_trials
    assert rec["predicted_outcomes"]["max_travel_mm <= 60"]["p_violation_true"] <= 0.05
    # a resumed agent tells the optimizer the outcomes again
    camp.journal.close()
    eng2 = Engine(SPACE, EngineConfig(budget=6, constraints=limits))
    camp2 = Campaign(eng2, Journal(tmp_path), CampaignConfig("c1", budget=6, outcome_limits=limits), lambda: 1.0)
    camp2.start()
    assert [o.outcomes for o in eng2.observations] == [o.outcomes for o in eng.observations]
    assert camp2.violated_trials == camp.violated_trials


def test_a_malformed_outcome_limit_is_refused_before_anything_is_journaled(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="NAME<=VALUE"):
        CampaignConfig("c1", outcome_limits=("travel < 60",))
    assert not (tmp_path / "journal.jsonl").exists()
