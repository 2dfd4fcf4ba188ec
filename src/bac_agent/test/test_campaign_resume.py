"""Resume = replay of the journal through the live campaign's reducer.

A whole campaign (failed and busy applies, invalid runs, a run timeout, stale scores, a trial given up, a
confirmation run) runs in-process against the Campaign state machine with a fake clock and fake scores. Its
journal is then cut after every line in turn (and in the middle of some lines: a torn write); each cut is resumed
by a fresh Campaign with a fresh engine and finished with the same fake bridge and chain: the trials, their
scores, the optimizer's tells and the recommendation (every field) are those of the uninterrupted campaign.
"""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from bac_agent.bo import Engine, EngineConfig, GPConfig
from bac_agent.bo.baselines import GridStrategy
from bac_agent.bo.prior import SourceSurface
from bac_agent.campaign import (
    ERROR_BUS,
    ERROR_ECU_BUSY,
    RECOMMENDATION_NAME,
    Apply,
    AwaitRun,
    Campaign,
    CampaignConfig,
    CampaignError,
    Finish,
    Publish,
)
from bac_agent.journal import JOURNAL_NAME, Journal

CID = "resume-test"
SPACE = [("damping_front", 0.0, 1.0, 0.001), ("damping_rear", 0.0, 1.0, 0.001)]
PARAMETERS: list[dict[str, Any]] = [{"name": n, "lower": lo, "upper": hi} for n, lo, hi, _ in SPACE]
DEFINITION: dict[str, Any] = {"name": "test", "parameters": PARAMETERS}
BUDGET = 8


def j_of(p: dict[str, float]) -> float:
    return 1.0 + (p["damping_front"] - 0.3) ** 2 + 0.5 * (p["damping_rear"] - 0.6) ** 2


# what the fake bridge answers to a trial's n-th apply (by the apply results the journal already holds for the
# trial), and what the fake chain makes of its n-th run (by the rejections the journal holds): so an apply or a
# run cut short by a crash is answered as the uninterrupted campaign's was
APPLY_SCRIPT = {
    1: ["fail", "ok"],
    2: ["busy", "busy", "ok"],
    4: ["timeout", "fail", "fail"],  # three failed tries with apply_retries 2: trial 4 given up
    5: ["link", "link", "link", "ok"],  # the CAN link down for 3 tries (within link_timeout_s): paused, no failure
    7: ["busy"] * 40,  # busy for longer than busy_timeout_s, every try: given up
}
RUN_SCRIPT = {
    2: ["invalid", "valid"],
    3: ["timeout", "nan", "valid"],
    6: ["invalid", "invalid", "invalid"],  # max_attempts 3: trial 6 given up
    9: ["invalid", "valid"],  # the confirmation run
}


def config(**over: Any) -> CampaignConfig:
    kw: dict[str, Any] = dict(
        campaign_id=CID,
        budget=BUDGET,
        seed=3,
        max_attempts=3,
        apply_retries=2,
        run_timeout_s=30.0,
        confirmation_run=True,
        max_consecutive_failures=3,
        busy_retry_s=1.0,
        busy_timeout_s=1.5,
        link_retry_s=1.0,
        link_timeout_s=10.0,
        extra={
            "n_initial": 3,
            "grid_size": 4,
            "definition_file": "test.yaml",
            "acquisition": "nei",
            "recommend_beta": 0.0,
            "gp_mean": "bowl",
            "bowl_runs": 6,
            "output_warp": "yeo-johnson",
            "design_margin": 0.25,
            "start_from": "design",
            "initial_points": [],
        },
    )
    kw.update(over)
    return CampaignConfig(**kw)


def _engine(seed: int) -> Engine:
    # the campaign's model (bowl prior mean, output warp, noisy EI), with fewer candidates and restarts to keep
    # the test short
    cfg = EngineConfig(
        budget=BUDGET,
        n_initial=3,
        seed=seed,
        n_candidates=64,
        n_local=16,
        acq_restarts=2,
        nei_samples=8,
        gp=GPConfig(bowl_centres=32, draws=2),
    )
    return Engine(SPACE, cfg)


_PRISTINE = {3: _engine(3)}  # building the initial design (an optimized Latin hypercube) takes ~1 s


def engine(seed: int = 3) -> Engine:
    """A fresh engine, as a new agent process builds it."""
    if seed not in _PRISTINE:
        _PRISTINE[seed] = _engine(seed)
    return copy.deepcopy(_PRISTINE[seed])


class Clock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class Chain:
    """Plays the ECU bridge and the measurement chain for a Campaign, following the scripts."""

    def __init__(
        self, camp: Campaign, clock: Clock, outcomes: Callable[[dict[str, float]], dict[str, float]] | None = None
    ) -> None:
        self.c = camp
        self.clock = clock
        self.outcomes = outcomes
        self.pending: Apply | AwaitRun | None = None
        self.finish: Finish | None = None
        self.published: list[Any] = []

    def feed(self, acts: list[Any]) -> None:
        for a in acts:
            if isinstance(a, Apply | AwaitRun):
                self.pending = a
            elif isinstance(a, Finish):
                self.finish = a
                self.pending = None
            elif isinstance(a, Publish):
                self.published.append(a.status)

    def _count(self, event: str, trial_id: int) -> int:
        return sum(1 for e in self.c.journal.events if e["event"] == event and e.get("trial_id") == trial_id)

    def step(self) -> None:
        self.clock.t += 1.0
        a = self.pending
        assert a is not None
        if isinstance(a, Apply):
            n = self._count("apply_result", a.trial_id)
            script = APPLY_SCRIPT.get(a.trial_id, [])
            what = script[n] if n < len(script) else ("busy" if script and script[-1] == "busy" else "ok")
            if what == "ok":
                self.feed(self.c.on_apply_result(a.trial_id, a.apply_try, True, applied={"raw": 1.0}, latency_s=0.1))
            elif what == "fail":
                self.feed(self.c.on_apply_result(a.trial_id, a.apply_try, False, 3, "value out of range"))
            elif what == "busy":
                self.feed(self.c.on_apply_result(a.trial_id, a.apply_try, False, ERROR_ECU_BUSY, "vehicle moving"))
            elif what == "link":
                self.feed(self.c.on_apply_result(a.trial_id, a.apply_try, False, ERROR_BUS, "can0 is down"))
            else:
                self.feed(self.c.on_apply_timeout(a.trial_id, a.apply_try, "no answer"))
            return
        n = self._count("run_rejected", a.trial_id)
        script = RUN_SCRIPT.get(a.trial_id, [])
        what = script[n] if n < len(script) else "valid"
        if a.attempt > 1:  # a late score of an earlier run, and one of another campaign: both ignored
            self.feed(self.c.on_score(CID, a.trial_id, a.attempt - 1, True, 0.5))
            self.feed(self.c.on_score("other", a.trial_id, a.attempt, True, 0.5))
        params = self.c.trials[a.trial_id].params
        if what == "valid":
            j = j_of(params) + (0.01 if a.trial_id == 9 else 0.0)
            measured = self.outcomes(params) if self.outcomes is not None else None
            self.feed(self.c.on_score(CID, a.trial_id, a.attempt, True, j, details={"kpi": "rms"}, outcomes=measured))
        elif what == "invalid":
            self.feed(self.c.on_score(CID, a.trial_id, a.attempt, False, math.nan, "too slow"))
        elif what == "nan":
            self.feed(self.c.on_score(CID, a.trial_id, a.attempt, True, math.inf))
        else:
            self.feed(self.c.on_run_timeout(a.trial_id, a.attempt))

    def run(self, limit: int = 500) -> None:
        for _ in range(limit):
            if self.finish is not None:
                return
            self.step()
        raise AssertionError("the campaign did not finish")


def start(
    campaign_dir: Path,
    clock: Clock,
    cfg: CampaignConfig | None = None,
    eng: Any = None,
    outcomes: Callable[[dict[str, float]], dict[str, float]] | None = None,
) -> Chain:
    camp = Campaign(
        eng if eng is not None else engine(),
        Journal(campaign_dir),
        cfg or config(),
        clock,
        definition=DEFINITION,
    )
    chain = Chain(camp, clock, outcomes)
    chain.feed(camp.start())
    return chain


def outcome(campaign_dir: Path, chain: Chain) -> dict[str, Any]:
    """What must not depend on where the campaign was interrupted."""
    events = [json.loads(x) for x in (campaign_dir / JOURNAL_NAME).read_text().splitlines()]
    trials = {}
    for e in events:
        if e["event"] == "trial_proposed":
            trials[e["trial_id"]] = {k: e[k] for k in ("kind", "params", "predicted_j", "predicted_std", "reason")}
            trials[e["trial_id"]]["optimizer_state"] = e.get("optimizer_state")
        elif e["event"] == "trial_scored":
            trials[e["trial_id"]]["j"] = e["j"]
        elif e["event"] == "trial_failed":
            trials[e["trial_id"]]["failed"] = e["reason"]
    (rec_event,) = [{k: v for k, v in e.items() if k not in ("seq", "wall_time", "stamp")}
                    for e in events if e["event"] == "recommendation"]  # fmt: skip
    camp = chain.c
    eng = camp.opt
    assert isinstance(eng, Engine)
    assert chain.finish is not None
    return {
        "trials": trials,
        "recommendation_event": rec_event,
        "recommendation_json": json.loads((campaign_dir / RECOMMENDATION_NAME).read_text()),
        "finish": (chain.finish.code, chain.finish.recommendation),
        "told": [(o.params, o.value, dict(o.outcomes)) for o in eng.observations],
        "violated": list(camp.violated_trials),
        "failures": [(f.params, f.reason) for f in eng.failures],
        "state": (camp.trials_done, camp.best_j, camp.best_trial_id, camp.last_j, camp.confirmation_j),
        "done": [e["event"] for e in events].count("campaign_done"),
    }


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    d = tmp_path_factory.mktemp("live")
    clock = Clock()
    chain = start(d, clock)
    chain.run()
    chain.c.journal.close()
    return d, outcome(d, chain)


def test_the_scripted_campaign_goes_through_every_rule(live: tuple[Path, dict[str, Any]]) -> None:
    d, out = live
    kinds = [json.loads(x)["event"] for x in (d / JOURNAL_NAME).read_text().splitlines()]
    assert out["finish"][0] == 0
    assert sorted(t for t, v in out["trials"].items() if "failed" in v) == [4, 6, 7]
    assert "after 3 failed tries" in out["trials"][4]["failed"]
    assert "3 invalid runs" in out["trials"][6]["failed"]
    assert "error 4" in out["trials"][7]["failed"] and "after 3 failed tries" in out["trials"][7]["failed"]
    assert out["trials"][9]["kind"] == 2
    assert out["trials"][9]["j"] == j_of(out["trials"][9]["params"]) + 0.01
    assert out["state"][0] == BUDGET and len(out["told"]) == 5 and len(out["failures"]) == 3
    assert kinds.count("score_ignored") >= 4 and kinds.count("run_rejected") == 7 and kinds.count("campaign_done") == 1
    assert [t["reason"] for t in out["trials"].values()][:4] == ["initial", "initial", "initial", "optimized"]
    rec = out["recommendation_json"]
    assert rec["best_observed_params"] is not None and rec["best_observed_j"] == min(t[1] for t in out["told"])
    assert rec["confirmation_j"] == out["trials"][9]["j"]
    assert "j" in out["trials"][5] and kinds.count("link_lost") == 1  # the outage paused trial 5, failed nothing


@pytest.mark.slow
def test_every_cut_of_the_journal_resumes_to_the_same_campaign(
    live: tuple[Path, dict[str, Any]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(os, "fsync", lambda fd: None)  # durability is tested in test_journal; ~120 resumes here
    src, expected = live
    raw = (src / JOURNAL_NAME).read_bytes()
    lines = raw.splitlines(keepends=True)
    cuts: list[tuple[str, bytes]] = [(f"line {k}", b"".join(lines[:k])) for k in range(1, len(lines) + 1)]
    # a write cut in its middle by the crash (a torn line), every seventh line
    cuts += [(f"torn {k}", b"".join(lines[:k]) + lines[k][: len(lines[k]) // 2]) for k in range(1, len(lines), 7)]
    for name, data in cuts:
        d = tmp_path / name.replace(" ", "_")
        d.mkdir()
        (d / JOURNAL_NAME).write_bytes(data)
        if data == raw:  # the campaign had finished: its recommendation.json was written before campaign_done
            shutil.copy(src / RECOMMENDATION_NAME, d / RECOMMENDATION_NAME)
        last = json.loads(data.splitlines()[-1]) if not name.startswith("torn") else None
        clock = Clock(100.0 + (last["stamp"] if last else 0.0))  # another launch: another clock
        chain = start(d, clock)
        chain.run()
        got = outcome(d, chain)
        for key, value in expected.items():
            assert got[key] == value, f"cut after {name}: {key} differs"


def test_a_crash_after_the_recommendation_keeps_every_field_of_it(
    live: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    """Regression: the resumed campaign wrote recommendation.json with best_observed_params/j null."""
    src, expected = live
    lines = (src / JOURNAL_NAME).read_text().splitlines(keepends=True)
    k = next(i for i, x in enumerate(lines) if json.loads(x)["event"] == "recommendation")
    (tmp_path / JOURNAL_NAME).write_text("".join(lines[: k + 1]))
    chain = start(tmp_path, Clock())
    chain.run()
    rec = json.loads((tmp_path / RECOMMENDATION_NAME).read_text())
    assert rec["best_observed_params"] is not None and rec["best_observed_j"] is not None
    assert rec == expected["recommendation_json"]


def test_counters_are_restored_not_restarted(tmp_path: Path) -> None:
    """Trial 1's first apply failed, the second is in flight: the resumed agent sends try 3, and one more failed
    try still leaves it a retry (apply_retries 2) as it would have live."""
    clock = Clock()
    chain = start(tmp_path, clock)
    chain.step()  # try 1 fails; try 2 requested
    assert isinstance(chain.pending, Apply) and chain.pending.apply_try == 2
    chain.c.journal.close()
    again = start(tmp_path, clock)
    assert isinstance(again.pending, Apply) and (again.pending.trial_id, again.pending.apply_try) == (1, 3)
    t = again.c.trials[1]
    assert (t.failed_applies, t.apply_try, t.attempt, t.rejections) == (1, 3, 0, 0)


def test_the_resumed_engine_asks_what_the_uninterrupted_one_would(tmp_path: Path) -> None:
    """The optimizer's random state and last fit are journaled with each proposal: replayed tells plus the restored
    ask give the next calibration of the uninterrupted campaign, past the initial design (the GP and its
    random draws in play)."""
    live_dir = tmp_path / "live"
    chain = start(live_dir, Clock())
    chain.run()
    events = [json.loads(x) for x in (live_dir / JOURNAL_NAME).read_text().splitlines()]
    proposals = [e for e in events if e["event"] == "trial_proposed" and e["kind"] == 1]
    assert len(proposals) >= 3
    eng = engine()
    by_id = {e["trial_id"]: e for e in events if e["event"] == "trial_proposed"}
    for e in events:
        if e["event"] == "trial_proposed" and e["kind"] != 2:
            if e["kind"] == 1:
                # what a fresh engine fed the same tells asks here
                assert eng.ask_with_info().params == e["params"]
                eng.pending.clear()
            eng.restore_ask(e["params"], e["optimizer_state"])
        elif e["event"] == "trial_scored" and e["kind"] != 2:
            eng.tell(e["params"], e["j"])
        elif e["event"] == "trial_failed" and e["kind"] != 2:
            eng.tell_failed(by_id[e["trial_id"]]["params"], e["reason"])


# --- with outcome limits and a transfer prior (issue 23) --------------------------------------------------------

LIMIT = "max_travel_mm <= 60"
# the simulator's J: its optimum near the car's
SOURCE = SourceSurface.from_function(
    lambda U: 1.0 + (U[:, 0] - 0.35) ** 2 + 0.5 * (U[:, 1] - 0.55) ** 2, 2, 32, label="sim", seed=0
).to_dict()


def travel(p: dict[str, float]) -> dict[str, float]:
    """The travel breaks the limit at the unconstrained optimum (front 0.3: 68 mm); kept from front 0.5 on."""
    return {"max_travel_mm": 40.0 + 40.0 * (1.0 - p["damping_front"]) + 2.0 * p["damping_rear"]}


def config_limits(**over: Any) -> CampaignConfig:
    extra = {**config().extra, "prior": SOURCE, "prior_weight": 0.5, "constraints": [LIMIT], "constraint_level": 0.05}
    kw: dict[str, Any] = {"outcome_limits": (LIMIT,), "extra": extra}
    kw.update(over)
    return config(**kw)


def _engine_limits() -> Engine:
    cfg = EngineConfig(
        budget=BUDGET,
        n_initial=3,
        seed=3,
        n_candidates=64,
        n_local=16,
        acq_restarts=2,
        nei_samples=8,
        gp=GPConfig(bowl_centres=32, draws=2),
        prior=SOURCE,
        constraints=(LIMIT,),
    )
    return Engine(SPACE, cfg)


_PRISTINE_LIMITS: list[Engine] = []


def engine_limits() -> Engine:
    if not _PRISTINE_LIMITS:
        _PRISTINE_LIMITS.append(_engine_limits())
    return copy.deepcopy(_PRISTINE_LIMITS[0])


def start_limits(campaign_dir: Path, clock: Clock) -> Chain:
    return start(campaign_dir, clock, config_limits(), engine_limits(), travel)


@pytest.fixture(scope="module")
def live_limits(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    d = tmp_path_factory.mktemp("live_limits")
    chain = start_limits(d, Clock())
    chain.run()
    chain.c.journal.close()
    return d, outcome(d, chain)


@pytest.mark.slow
def test_the_campaign_with_limits_and_a_prior_uses_both(live_limits: tuple[Path, dict[str, Any]]) -> None:
    d, out = live_limits
    events = [json.loads(x) for x in (d / JOURNAL_NAME).read_text().splitlines()]
    assert events[0]["config"]["outcome_limits"] == [LIMIT] and events[0]["config"]["prior"] == SOURCE
    reasons = [t["reason"] for t in out["trials"].values()]
    assert reasons[0] == "prior"  # the simulator's optimum first
    states = [t["optimizer_state"] for t in out["trials"].values() if t["optimizer_state"]]
    # the outcome model's last fit is journaled with each proposal once it has been fitted
    assert any(st.get("outcomes") and st["outcomes"][0] is not None for st in states)
    assert out["violated"] and all(
        travel(t[0])["max_travel_mm"] > 60 for t in out["told"] if t[2]["max_travel_mm"] > 60
    )
    rec = out["recommendation_event"]
    assert travel(rec["params"])["max_travel_mm"] <= 60.0
    assert LIMIT in rec["predicted_outcomes"] and "transfer_weight" in rec["transfer"]
    assert out["recommendation_json"]["violated_trials"] == out["violated"]


@pytest.mark.slow
def test_every_cut_of_a_journal_with_limits_and_a_prior_resumes_to_the_same_campaign(
    live_limits: tuple[Path, dict[str, Any]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The outcome models' last fits are restored with the asks (and a failure drops their cached fit, as the
    objective's): cut anywhere, the resumed campaign proposes, books (violations included) and recommends
    (predicted outcomes, transfer weight) what the uninterrupted one did."""
    monkeypatch.setattr(os, "fsync", lambda fd: None)
    src, expected = live_limits
    raw = (src / JOURNAL_NAME).read_bytes()
    lines = raw.splitlines(keepends=True)
    for k in range(1, len(lines) + 1):
        d = tmp_path / f"line_{k}"
        d.mkdir()
        (d / JOURNAL_NAME).write_bytes(b"".join(lines[:k]))
        if k == len(lines):
            shutil.copy(src / RECOMMENDATION_NAME, d / RECOMMENDATION_NAME)
        last = json.loads(lines[k - 1])
        chain = start_limits(d, Clock(100.0 + last["stamp"]))
        chain.run()
        got = outcome(d, chain)
        for key, value in expected.items():
            assert got[key] == value, f"cut after line {k}: {key} differs"


# --- with an outcome limit and a safe start, nothing known of the outcome before run 1 (issue 23) -----------------

SAFE = {"damping_front": 0.8, "damping_rear": 0.5}  # keeps the limit: 40 + 8 + 1 = 49 mm


def config_safe() -> CampaignConfig:
    extra = {**config().extra, "constraints": [LIMIT], "constraint_level": 0.05, "safe_start": SAFE}
    return config(outcome_limits=(LIMIT,), extra=extra)


_PRISTINE_SAFE: list[Engine] = []


def engine_safe() -> Engine:
    if not _PRISTINE_SAFE:
        cfg = EngineConfig(
            budget=BUDGET,
            n_initial=3,
            seed=3,
            n_candidates=64,
            n_local=16,
            acq_restarts=2,
            nei_samples=8,
            gp=GPConfig(bowl_centres=32, draws=2),
            constraints=(LIMIT,),
            safe_start=SAFE,
        )
        _PRISTINE_SAFE.append(Engine(SPACE, cfg))
    return copy.deepcopy(_PRISTINE_SAFE[0])


def start_safe(campaign_dir: Path, clock: Clock) -> Chain:
    return start(campaign_dir, clock, config_safe(), engine_safe(), travel)


@pytest.fixture(scope="module")
def live_safe(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    d = tmp_path_factory.mktemp("live_safe")
    chain = start_safe(d, Clock())
    chain.run()
    chain.c.journal.close()
    return d, outcome(d, chain)


@pytest.mark.slow
def test_every_cut_of_a_journal_with_a_safe_start_resumes_to_the_same_campaign(
    live_safe: tuple[Path, dict[str, Any]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Trial 1 is the safe calibration (reason ``safe``, journaled with the start), the design grows from it; cut
    anywhere, the resumed campaign proposes, books and recommends what the uninterrupted one did."""
    monkeypatch.setattr(os, "fsync", lambda fd: None)
    src, expected = live_safe
    events = [json.loads(x) for x in (src / JOURNAL_NAME).read_text().splitlines()]
    assert events[0]["config"]["safe_start"] == SAFE
    first = next(e for e in events if e["event"] == "trial_proposed")
    assert first["reason"] == "safe" and first["kind"] == 0 and first["params"] == SAFE
    raw = (src / JOURNAL_NAME).read_bytes()
    lines = raw.splitlines(keepends=True)
    for k in range(1, len(lines) + 1):
        d = tmp_path / f"line_{k}"
        d.mkdir()
        (d / JOURNAL_NAME).write_bytes(b"".join(lines[:k]))
        if k == len(lines):
            shutil.copy(src / RECOMMENDATION_NAME, d / RECOMMENDATION_NAME)
        last = json.loads(lines[k - 1])
        chain = start_safe(d, Clock(100.0 + last["stamp"]))
        chain.run()
        got = outcome(d, chain)
        for key, value in expected.items():
            assert got[key] == value, f"cut after line {k}: {key} differs"


LIMITS_REFUSED: dict[str, tuple[str, Callable[[], CampaignConfig]]] = {
    "limit": (
        'config.outcome_limits[0]: journaled "max_travel_mm <= 60", this agent "max_travel_mm <= 55"',
        lambda: config_limits(outcome_limits=("max_travel_mm <= 55",)),
    ),
    "no limit": (
        "config.outcome_limits: journaled [",
        lambda: config_limits(outcome_limits=()),
    ),
    "level": (
        "config.constraint_level: journaled 0.05, this agent 0.1",
        lambda: config_limits(extra={**config_limits().extra, "constraint_level": 0.1}),
    ),
    "prior": (
        "config.prior: journaled {",
        lambda: config_limits(extra={**config_limits().extra, "prior": None}),
    ),
    "prior weight": (
        "config.prior_weight: journaled 0.5, this agent 0.9",
        lambda: config_limits(extra={**config_limits().extra, "prior_weight": 0.9}),
    ),
    "transfer prior's model average": (
        # a journal from before prior_average ran the model with the prior alone (campaign.ADDED_LATER)
        "config.prior_average: journaled false, this agent true",
        lambda: config_limits(extra={**config_limits().extra, "prior_average": True}),
    ),
    "transfer prior's model without the source over both lengthscale priors": (
        # a journal from before prior_average_ls ran that model as one fit (campaign.ADDED_LATER)
        "config.prior_average_ls: journaled false, this agent true",
        lambda: config_limits(extra={**config_limits().extra, "prior_average_ls": True}),
    ),
    "the retreat's trend": (
        # a journal from before limit_trend ran without it (campaign.ADDED_LATER)
        "config.limit_trend: journaled false, this agent true",
        lambda: config_limits(extra={**config_limits().extra, "limit_trend": True}),
    ),
    "the limit models widened far from the runs": (
        # a journal from before limit_far_sd ran without it (campaign.ADDED_LATER)
        "config.limit_far_sd: journaled 0.0, this agent 2.0",
        lambda: config_limits(extra={**config_limits().extra, "limit_far_sd": 2.0}),
    ),
    "the trend judging the far calibrations": (
        # a journal from before limit_trend_far was a bo_agent parameter ran without it (campaign.ADDED_LATER)
        "config.limit_trend_far: journaled 0.0, this agent 0.2",
        lambda: config_limits(extra={**config_limits().extra, "limit_trend_far": 0.2}),
    ),
    "the reach around the runs that kept the limits": (
        # (the same for limit_reach)
        "config.limit_reach: journaled 0.0, this agent 0.15",
        lambda: config_limits(extra={**config_limits().extra, "limit_reach": 0.15}),
    ),
}


@pytest.mark.parametrize("what", list(LIMITS_REFUSED))
def test_a_resume_with_other_limits_or_another_prior_is_refused(what: str, tmp_path: Path) -> None:
    message, make = LIMITS_REFUSED[what]
    chain = start_limits(tmp_path, Clock())
    for _ in range(4):
        chain.step()
    chain.c.journal.close()
    camp = Campaign(engine_limits(), Journal(tmp_path), make(), Clock(), definition=DEFINITION)
    with pytest.raises(CampaignError) as err:
        camp.start()
    assert message in str(err.value)
    assert "cannot resume" in str(err.value)


def test_a_journal_with_limits_from_before_the_opt_in_limit_distances_resumes_with_them_off(tmp_path: Path) -> None:
    """A campaign with limits journaled before limit_trend_far and limit_reach were bo_agent parameters (no such keys)
    ran without them: an agent that journals them off (0, the default) resumes it (campaign.ADDED_LATER)."""
    chain = start_limits(tmp_path, Clock())
    for _ in range(4):
        chain.step()
    chain.c.journal.close()
    started = chain.c.journal.events[0]["config"]
    assert started["constraints"] and "limit_reach" not in started and "limit_trend_far" not in started
    cfg = config_limits(extra={**config_limits().extra, "limit_trend_far": 0.0, "limit_reach": 0.0})
    again = start(tmp_path, Clock(), cfg, engine_limits(), travel)
    assert again.pending is not None
    (resumed,) = [e for e in again.c.journal.events if e["event"] == "campaign_resumed"]
    assert resumed["changed"] == []


# --- refused configurations ---------------------------------------------------------------------------------------

Refusal = Callable[[], tuple[Any, CampaignConfig, dict[str, Any]]]


def _extra(**over: Any) -> dict[str, Any]:
    return {**config().extra, **over}


REFUSED: dict[str, tuple[str, Refusal]] = {
    "seed": ("seed: journaled 3, this agent 4", lambda: (engine(4), config(seed=4), DEFINITION)),
    "budget": ("budget: journaled 8, this agent 9", lambda: (engine(), config(budget=9), DEFINITION)),
    "strategy": (
        'strategy: journaled "bo", this agent "grid"',
        lambda: (GridStrategy(SPACE, 3), config(strategy="grid", budget=BUDGET), DEFINITION),
    ),
    "design": (
        "config.n_initial: journaled 3, this agent 5",
        lambda: (engine(), config(extra=_extra(n_initial=5)), DEFINITION),
    ),
    "design margin": (
        "config.design_margin: journaled 0.25, this agent 0.1",
        lambda: (engine(), config(extra=_extra(design_margin=0.1)), DEFINITION),
    ),
    "GP mean": (
        'config.gp_mean: journaled "bowl", this agent "constant"',
        lambda: (engine(), config(extra=_extra(gp_mean="constant")), DEFINITION),
    ),
    "bowl length": (
        "config.bowl_runs: journaled 6, this agent 10",
        lambda: (engine(), config(extra=_extra(bowl_runs=10)), DEFINITION),
    ),
    "output warp": (
        'config.output_warp: journaled "yeo-johnson", this agent "none"',
        lambda: (engine(), config(extra=_extra(output_warp="none")), DEFINITION),
    ),
    "recommendation rule": (
        # a journal from before the rule was configurable ran with "mean" (campaign.ADDED_LATER)
        'config.recommend_rule: journaled "mean", this agent "observed"',
        lambda: (engine(), config(extra=_extra(recommend_rule="observed")), DEFINITION),
    ),
    "transfer prior's runs": (
        # a journal from before prior_runs and outcome_priors ran with no limit and none (campaign.ADDED_LATER)
        "config.prior_runs: journaled 0, this agent 6",
        lambda: (engine(), config(extra=_extra(prior_runs=6)), DEFINITION),
    ),
    "bowl checked by leave-one-out": (
        # a journal from before gp_bowl_loo ran the bowl unchecked (campaign.ADDED_LATER)
        "config.gp_bowl_loo: journaled false, this agent true",
        lambda: (engine(), config(extra=_extra(gp_bowl_loo=True)), DEFINITION),
    ),
    "model average over two lengthscale priors": (
        # a journal from before gp_ls_average ran one fit (campaign.ADDED_LATER)
        "config.gp_ls_average: journaled 0.0, this agent 0.5",
        lambda: (engine(), config(extra=_extra(gp_ls_average=0.5)), DEFINITION),
    ),
    "exploration along the faces": (
        # a journal from before face_explore ran without it (campaign.ADDED_LATER)
        "config.face_explore: journaled 0, this agent 1",
        lambda: (engine(), config(extra=_extra(face_explore=1)), DEFINITION),
    ),
    "acquisition": (
        'config.acquisition: journaled "nei", this agent "ei"',
        lambda: (engine(), config(extra=_extra(acquisition="ei")), DEFINITION),
    ),
    "start_from": (
        'config.start_from: journaled "design", this agent "guess"',
        lambda: (engine(), config(extra=_extra(start_from="guess")), DEFINITION),
    ),
    "best guess": (
        "config.initial_points: journaled [], this agent",
        lambda: (engine(), config(extra=_extra(initial_points=[{"damping_front": 0.3}])), DEFINITION),
    ),
    "definition": (
        "definition.parameters[1].upper: journaled 1.0, this agent 2.0",
        lambda: (
            engine(),
            config(),
            {**DEFINITION, "parameters": [PARAMETERS[0], {**PARAMETERS[1], "upper": 2.0}]},
        ),
    ),
    "dimensions": (
        'names: journaled ["damping_front", "damping_rear"], this agent ["x"]',
        lambda: (Engine({"x": (0.0, 1.0)}, budget=BUDGET), config(), DEFINITION),
    ),
    "campaign id": (
        'campaign_id: journaled "resume-test", this agent "other"',
        lambda: (engine(), config(campaign_id="other"), DEFINITION),
    ),
    "max_attempts": (
        "config.max_attempts: journaled 3, this agent 5",
        lambda: (engine(), config(max_attempts=5), DEFINITION),
    ),
    "confirmation": (
        "config.confirmation_run: journaled true, this agent false",
        lambda: (engine(), config(confirmation_run=False), DEFINITION),
    ),
}


@pytest.mark.parametrize("what", list(REFUSED))
def test_a_resume_with_another_configuration_is_refused(what: str, tmp_path: Path) -> None:
    message, make = REFUSED[what]
    chain = start(tmp_path, Clock())
    for _ in range(4):
        chain.step()
    chain.c.journal.close()
    before = (tmp_path / JOURNAL_NAME).read_bytes()
    eng, cfg, definition = make()
    camp = Campaign(eng, Journal(tmp_path), cfg, Clock(), definition=definition)
    with pytest.raises(CampaignError) as err:
        camp.check_resume()
    text = str(err.value)
    assert message in text, text
    assert "new campaign" in text and "campaign_dir" in text
    assert text.count("\n  - ") == 1  # only the difference made is named
    with pytest.raises(CampaignError):
        camp.start()
    camp.journal.close()
    assert (tmp_path / JOURNAL_NAME).read_bytes() == before  # nothing written


def test_a_resume_may_change_time_limits_and_says_so(tmp_path: Path) -> None:
    chain = start(tmp_path, Clock())
    for _ in range(3):
        chain.step()
    chain.c.journal.close()
    again = start(tmp_path, Clock(), cfg=config(run_timeout_s=60.0, apply_timeout_s=20.0))
    assert again.pending is not None
    (resumed,) = [e for e in again.c.journal.events if e["event"] == "campaign_resumed"]
    assert "config.run_timeout_s: journaled 30.0, this agent 60.0" in resumed["changed"]
    assert "config.apply_timeout_s: journaled 10.0, this agent 20.0" in resumed["changed"]


def test_a_journal_from_before_the_recommendation_rule_resumes_with_the_rule_it_ran_with(tmp_path: Path) -> None:
    """campaign_started without recommend_rule (journaled before it was a parameter): the agent with the rule
    those campaigns used (mean) resumes it; with another rule it is refused (the case above)."""
    chain = start(tmp_path, Clock())
    for _ in range(3):
        chain.step()
    chain.c.journal.close()
    started = chain.c.journal.events[0]
    assert "recommend_rule" not in started["config"]
    again = start(tmp_path, Clock(), cfg=config(extra=_extra(recommend_rule="mean")))
    assert again.pending is not None
    (resumed,) = [e for e in again.c.journal.events if e["event"] == "campaign_resumed"]
    assert resumed["changed"] == []


def test_a_journal_from_before_the_safe_start_resumes_without_one(tmp_path: Path) -> None:
    """campaign_started without safe_start (journaled before it existed) ran without one: the agent without one
    (``{}``) resumes it (campaign.ADDED_LATER), an agent with one is refused."""
    chain = start(tmp_path, Clock())
    for _ in range(3):
        chain.step()
    chain.c.journal.close()
    assert "safe_start" not in chain.c.journal.events[0]["config"]
    camp = Campaign(engine(), Journal(tmp_path), config(extra=_extra(safe_start={})), Clock(), definition=DEFINITION)
    assert camp.check_resume() == []
    camp.journal.close()
    safe = {"damping_front": 0.5, "damping_rear": 0.5}
    camp = Campaign(engine(), Journal(tmp_path), config(extra=_extra(safe_start=safe)), Clock(), definition=DEFINITION)
    with pytest.raises(CampaignError, match=r"config\.safe_start\.damping_front"):
        camp.check_resume()
    camp.journal.close()


def test_the_bowl_length_does_not_refuse_a_resume_without_the_bowl(tmp_path: Path) -> None:
    """bowl_runs is journaled whatever the prior mean; without the bowl (gp_mean constant or zero) its length
    changes nothing, so a campaign journaled with another (the default before 2026-11-24: 10) resumes."""
    chain = start(tmp_path, Clock(), cfg=config(extra=_extra(gp_mean="constant", bowl_runs=10)))
    for _ in range(3):
        chain.step()
    chain.c.journal.close()
    again = start(tmp_path, Clock(), cfg=config(extra=_extra(gp_mean="constant", bowl_runs=6)))
    assert again.pending is not None
    (resumed,) = [e for e in again.c.journal.events if e["event"] == "campaign_resumed"]
    assert resumed["changed"] == []


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("prior_average", True),
        ("prior_average_ls", True),
        ("limit_trend", True),
        ("limit_far_sd", 2.0),
        ("limit_trend_far", 0.2),
        ("limit_reach", 0.15),
    ],
)
def test_a_key_that_changes_nothing_here_does_not_refuse_a_resume(tmp_path: Path, key: str, value: object) -> None:
    """prior_average and limit_trend are journaled whatever the prior and the limits; without a prior, without
    limits, they change nothing, so a campaign journaled before they existed (no key: ADDED_LATER's false) resumes
    with the default (true) (outside review D2: every such journal was refused)."""
    chain = start(tmp_path, Clock())
    for _ in range(3):
        chain.step()
    chain.c.journal.close()
    again = start(tmp_path, Clock(), cfg=config(extra=_extra(**{key: value})))
    assert again.pending is not None
    (resumed,) = [e for e in again.c.journal.events if e["event"] == "campaign_resumed"]
    assert resumed["changed"] == []


def test_an_identical_configuration_resumes_even_after_it_finished(tmp_path: Path) -> None:
    chain = start(tmp_path, Clock())
    chain.run()
    chain.c.journal.close()
    again = start(tmp_path, Clock())
    assert again.finish is not None and again.finish.code == 0
    assert again.finish.recommendation == chain.finish.recommendation  # type: ignore[union-attr]
    assert again.published[-1].state == 7 and again.published[-1].best_trial_id == chain.c.best_trial_id


def test_a_failed_campaign_stays_failed_on_resume(tmp_path: Path) -> None:
    cfg = config(apply_retries=0, max_consecutive_failures=1)
    camp = Campaign(engine(), Journal(tmp_path), cfg, Clock(), definition=DEFINITION)
    acts = camp.start()
    a = next(x for x in acts if isinstance(x, Apply))
    fin = [x for x in camp.on_apply_result(a.trial_id, a.apply_try, False, 3, "no") if isinstance(x, Finish)]
    assert fin and fin[0].code == 1
    camp.journal.close()
    again = Campaign(engine(), Journal(tmp_path), cfg, Clock(), definition=DEFINITION)
    fin2 = [x for x in again.start() if isinstance(x, Finish)]
    assert fin2 and fin2[0].code == 1
    kinds = [e["event"] for e in again.journal.events]
    assert kinds.count("campaign_failed") == 1 and kinds.count("trial_proposed") == 1


def test_a_campaign_paused_for_a_lost_ecu_link_resumes_the_same_trial(tmp_path: Path) -> None:
    """The link stays down beyond link_timeout_s: the agent stops with 2 (campaign_paused), no trial failed; a
    relaunch on the folder applies the same trial again and goes on, still without a failed try."""
    clock = Clock()
    cfg = config(link_timeout_s=3.0)
    camp = Campaign(engine(), Journal(tmp_path), cfg, clock, definition=DEFINITION)
    chain = Chain(camp, clock)
    chain.feed(camp.start())
    for _ in range(10):
        a = chain.pending
        assert isinstance(a, Apply) and a.trial_id == 1
        clock.t += 1.0
        chain.feed(camp.on_apply_result(a.trial_id, a.apply_try, False, ERROR_BUS, "can0 is down"))
        if chain.finish is not None:
            break
    assert chain.finish is not None and chain.finish.code == 2
    kinds = [e["event"] for e in camp.journal.events]
    assert kinds.count("link_lost") == 1 and kinds[-1] == "campaign_paused" and "trial_failed" not in kinds
    assert camp.trials[1].failed_applies == 0
    camp.journal.close()
    clock2 = Clock(5.0)  # a new launch: another clock
    again = start(tmp_path, clock2, cfg=config(link_timeout_s=30.0))  # a waiting limit may change
    assert isinstance(again.pending, Apply) and again.pending.trial_id == 1 and again.finish is None
    (resumed,) = [e for e in again.c.journal.events if e["event"] == "campaign_resumed"]
    assert resumed["in_flight"] == [1]
    assert "config.link_timeout_s: journaled 3.0, this agent 30.0" in resumed["changed"]
    again.run()
    assert again.finish is not None and again.finish.code == 0
    evs = again.c.journal.events
    assert not [e for e in evs if e["event"] == "trial_failed" and e["trial_id"] == 1]
    assert any(e["event"] == "trial_scored" and e["trial_id"] == 1 for e in evs)
