"""The campaign state machine of algorithm 1, without ROS.

propose → apply (ECU bridge) → ready to drive → score → update, until the budget;
then recommend (and optionally drive a confirmation run of the recommendation).

The node feeds it events (:meth:`Campaign.on_apply_result`, :meth:`on_apply_timeout`,
:meth:`on_score`, :meth:`on_run_timeout`) and executes the actions it returns, in
order (:class:`Publish`, :class:`Apply`, :class:`AwaitRun`, :class:`Finish`,
:class:`Log`).

Every decision is an event, journaled (durably) before it is acted on, and the
campaign's state changes only by applying journaled events, through one reducer
(:meth:`Campaign._reduce`): live, each event is journaled and then applied; a
resumed campaign (:meth:`Campaign.start` on a journal) applies every event of the
journal in order through the same function, so it holds exactly what the live
one held (trials, attempt and apply-try counters, rejections, failures in a row,
best so far, the recommendation, the confirmation) and tells the optimizer the
same results in the same order. Each proposal journals the optimizer's random
state and last fit (``Optimizer.ask_state``), restored on replay, so the resumed
campaign proposes what the uninterrupted one would have. A trial that was being
applied or driven is applied again and driven again with a new attempt number, so
a late score of the interrupted run is never booked against a calibration this
process has not seen the ECU confirm. A journal started with another
configuration (seed, budget, strategy, design, model, definition, ...) is refused
(:meth:`Campaign.check_resume`), naming each difference.

The rules:

* a score counts only if it carries the current (campaign_id, trial_id, attempt),
  arrives while the agent waits for that run, and the ECU confirmed the calibration;
* an invalid run (or none within ``run_timeout_s``) → REJECTED, the same calibration is
  driven again (attempt + 1) up to ``max_attempts`` runs, then the trial FAILED;
* a failed apply (success = false, any error, or no answer within the timeout) is
  retried ``apply_retries`` times, then the trial FAILED; it is never driven;
* failed trials count in the budget; ``max_consecutive_failures`` in a row end the
  campaign early (the ECU or the car needs a human).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any, Protocol

from bac_agent.bo.constraints import OutcomeLimit, parse_limits, violations
from bac_agent.bo.engine import (
    KIND_GRID,
    KIND_GUESS,
    KIND_INITIAL,
    KIND_OPTIMIZED,
    KIND_PRIOR,
    KIND_SAFE,
    Recommendation,
    Suggestion,
)
from bac_agent.journal import SCHEMA_VERSION, Journal, JournalError, strict_json, write_json_atomic
from bac_common.errors import BacError

RECOMMENDATION_NAME = "recommendation.json"
ERROR_ECU_BUSY = 4  # bac_msgs/srv/ApplyCalibration ERROR_ECU_BUSY: the ECU refuses while the vehicle moves
ERROR_BUS = 8  # bac_msgs/srv/ApplyCalibration ERROR_BUS: the CAN link to the ECU is down (adapter missing, failed)
# apply_result.outcome: what the agent made of the bridge's answer
APPLY_CONFIRMED = "confirmed"  # the ECU holds the calibration: the trial is driven
APPLY_BUSY = "busy"  # the ECU was busy (vehicle moving) within busy_timeout_s: asked again, not a failed try
APPLY_LINK_DOWN = "link_down"  # the CAN link is down (ERROR_BUS) within link_timeout_s: paused, not a failed try
APPLY_FAILED = "failed"  # a failed try (retried up to apply_retries times)


class CampaignError(BacError):
    """The campaign cannot go on (a journal from another campaign, nothing scored, ...)."""


class State(IntEnum):
    """Mirrors bac_msgs/Trial STATE_*."""

    IDLE = 0
    PROPOSED = 1
    APPLYING = 2
    READY_TO_DRIVE = 3
    SCORED = 4
    REJECTED = 5
    FAILED = 6
    DONE = 7


class Kind(IntEnum):
    """Mirrors bac_msgs/Trial KIND_*."""

    INITIAL = 0
    OPTIMIZED = 1
    CONFIRMATION = 2
    GRID = 3
    MANUAL = 4


_KIND_OF_SUGGESTION = {
    KIND_INITIAL: Kind.INITIAL,
    KIND_GUESS: Kind.INITIAL,
    KIND_PRIOR: Kind.INITIAL,
    KIND_SAFE: Kind.INITIAL,
    KIND_OPTIMIZED: Kind.OPTIMIZED,
    KIND_GRID: Kind.GRID,
}


class Optimizer(Protocol):
    """What the campaign needs of an optimizer (Engine, GridStrategy, RandomStrategy)."""

    @property
    def names(self) -> tuple[str, ...]: ...
    @property
    def n_trials(self) -> int: ...
    def ask_with_info(self) -> Suggestion: ...
    def tell(self, params: Mapping[str, float], value: float, outcomes: Mapping[str, float] | None = None) -> None: ...
    def tell_failed(self, params: Mapping[str, float], reason: str) -> None: ...
    def recommend(self) -> Recommendation: ...
    def predict(self, params: Mapping[str, float]) -> tuple[float, float]: ...
    def ask_state(self) -> dict[str, Any]: ...
    def restore_ask(self, params: Mapping[str, float], state: Mapping[str, Any] | None) -> None: ...


@dataclass(frozen=True)
class CampaignConfig:
    campaign_id: str
    budget: int = 15
    strategy: str = "bo"
    seed: int = 0
    max_attempts: int = 3  # runs per trial (invalid runs are repeated up to this count)
    apply_retries: int = 2  # further apply tries after a failed one
    apply_timeout_s: float = 10.0  # per apply try (given to the bridge too)
    run_timeout_s: float = 3600.0  # ROS time from READY_TO_DRIVE to a score (a backstop: the segmenter decides)
    confirmation_run: bool = False
    max_consecutive_failures: int = 3
    busy_retry_s: float = 2.0  # an ECU that answers "busy" (vehicle moving) is asked again after this long
    busy_timeout_s: float = 120.0  # ... until it has been busy this long (ROS time): then a failed try
    link_retry_s: float = 2.0  # the CAN link is down (ERROR_BUS): the campaign pauses and asks again after this long
    link_timeout_s: float = 600.0  # ... until it has been down this long (ROS time): then the campaign stops, resumable
    extra: Mapping[str, Any] = field(default_factory=dict)  # journaled with the start (n_initial, grid_size, ...)
    # limits on a run's outcomes besides J ("max_travel_mm<=60"): a run that breaks one is booked and shown (the
    # optimizer models them when it can: EngineConfig.constraints)
    outcome_limits: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.campaign_id:
            raise CampaignError("campaign_id must not be empty")
        if self.budget < 1 or self.max_attempts < 1 or self.apply_retries < 0:
            raise CampaignError("budget and max_attempts must be >= 1, apply_retries >= 0")
        parse_limits(self.outcome_limits)  # a malformed limit is refused before anything is journaled

    @property
    def limits(self) -> tuple[OutcomeLimit, ...]:
        return parse_limits(self.outcome_limits)


@dataclass(frozen=True)
class TrialStatus:
    """What bac/trial shows (a bac_msgs/Trial without ROS)."""

    campaign_id: str
    trial_id: int
    attempt: int
    state: State
    kind: Kind
    params: dict[str, float]
    budget: int
    trials_done: int
    last_j: float
    best_j: float
    best_trial_id: int
    predicted_j: float
    predicted_j_std: float
    instruction: str
    reason: str
    stamp: float


# --- actions the node executes ------------------------------------------------------------
@dataclass(frozen=True)
class Publish:
    status: TrialStatus


@dataclass(frozen=True)
class Apply:
    trial_id: int
    apply_try: int
    params: dict[str, float]
    timeout_s: float
    delay_s: float = 0.0  # wait this long (wall) before calling the bridge


@dataclass(frozen=True)
class AwaitRun:
    trial_id: int
    attempt: int
    timeout_s: float


@dataclass(frozen=True)
class Finish:
    code: int
    recommendation: Recommendation | None


@dataclass(frozen=True)
class Log:
    level: str  # "info" | "warn" | "error"
    text: str


Action = Publish | Apply | AwaitRun | Finish | Log


@dataclass
class _Trial:
    trial_id: int
    kind: Kind
    params: dict[str, float]
    predicted_j: float = math.nan
    predicted_std: float = math.nan
    attempt: int = 0  # last attempt number used (the next run is attempt + 1)
    rejections: int = 0
    apply_try: int = 0  # apply requests sent (each answer is matched to its request)
    failed_applies: int = 0  # failed tries (an ECU busy within busy_timeout_s is not one)
    busy_since: float = math.nan
    link_since: float = math.nan  # the CAN link went down while applying this trial (the campaign is paused)
    link_lost_journaled: bool = False  # link_lost journaled for this outage
    confirmed: bool = False
    phase: State = State.PROPOSED
    last_reason: str = ""
    apply_outcome: str = ""  # of the last apply_result (APPLY_*), "" once another apply is requested
    apply_message: str = ""  # of the last apply_result


def fmt_params(params: Mapping[str, float], limit: int = 6) -> str:
    items = list(params.items())
    text = " ".join(f"{k}={v:.4g}" for k, v in items[:limit])
    return text + (f" (+{len(items) - limit} more)" if len(items) > limit else "")


class Campaign:
    """Algorithm 1 as a state machine (see the module doc)."""

    def __init__(
        self,
        optimizer: Optimizer,
        journal: Journal,
        config: CampaignConfig,
        clock: Callable[[], float],
        definition: Mapping[str, Any] | None = None,
        verify_applied: Callable[[Mapping[str, float], Mapping[str, float]], str | None] | None = None,
    ) -> None:
        self.opt = optimizer
        self.journal = journal
        self.cfg = config
        self.clock = clock
        self.definition = dict(definition) if definition else None
        self.verify_applied = verify_applied
        # the state: changed only by _reduce (live and on resume alike)
        self.trials: dict[int, _Trial] = {}
        self.current: _Trial | None = None
        self.next_trial_id = 1
        self.trials_done = 0
        self.consecutive_failures = 0
        self.last_j = math.nan
        self.best_j = math.nan
        self.best_trial_id = 0
        self.recommendation: Recommendation | None = None
        self.confirmation_j = math.nan
        self.confirmation_closed = False  # the confirmation trial was scored or given up
        self.finished = False
        self.exit_code: int | None = None  # 0 done, 1 ended without a recommendation, 2 paused (ECU link down)
        self.paused = False  # stopped by campaign_paused (the ECU link stayed down): a resume goes on
        self.resumed = False
        self.violated_trials: list[int] = []  # trials whose run broke an outcome limit (booked, shown)
        self.resumes = 0  # campaign_resumed events so far

    # --- helpers -----------------------------------------------------------------------------
    @property
    def campaign_dir(self) -> Path:
        return self.journal.dir

    def _status(self, state: State, instruction: str, reason: str = "", t: _Trial | None = None) -> Publish:
        t = t if t is not None else self.current
        params = dict(t.params) if t else {}
        if state == State.DONE and self.recommendation is not None:
            params = dict(self.recommendation.params)
        return Publish(
            TrialStatus(
                campaign_id=self.cfg.campaign_id,
                trial_id=t.trial_id if t else 0,
                attempt=max(t.attempt, 1) if t else 0,
                state=state,
                kind=t.kind if t else Kind.OPTIMIZED,
                params=params,
                budget=self.cfg.budget,
                trials_done=self.trials_done,
                last_j=self.last_j,
                best_j=self.best_j,
                best_trial_id=self.best_trial_id,
                predicted_j=self.recommendation.predicted_j
                if state == State.DONE and self.recommendation
                else (t.predicted_j if t else math.nan),
                predicted_j_std=self.recommendation.predicted_std
                if state == State.DONE and self.recommendation
                else (t.predicted_std if t else math.nan),
                instruction=instruction,
                reason=reason,
                stamp=self.clock(),
            )
        )

    def _record(self, event: str, stamp: float | None = None, **fields: Any) -> dict[str, Any]:
        """Journal an event (durably), then apply it to the state through :meth:`_reduce`, the function a
        resume replays the journal with: what the live campaign knows is what its journal says."""
        rec = self.journal.append(
            event, campaign_id=self.cfg.campaign_id, stamp=self.clock() if stamp is None else stamp, **fields
        )
        self._reduce(rec, replay=False)
        return rec

    # --- the reducer -------------------------------------------------------------------------------
    def _trial_of(self, ev: Mapping[str, Any]) -> _Trial:
        tid = int(ev.get("trial_id") or 0)
        t = self.trials.get(tid)
        if t is None:
            raise CampaignError(
                f"{self.journal.path}: event {ev.get('seq')} ({ev.get('event')}) names trial {tid}, which was "
                "never proposed: the journal is inconsistent (edited by hand?); keep a copy and start a new "
                "campaign_dir"
            )
        return t

    def _reduce(self, ev: Mapping[str, Any], replay: bool) -> None:
        """Apply one journaled event to the campaign's state. The live campaign calls it right after
        journaling each event, a resume calls it on every event of the journal in order: the state (counters,
        trials, best so far, the optimizer's tells) cannot differ between the two. The one difference: a
        replayed proposal restores the optimizer's ask (live, the ask made the proposal)."""
        kind = ev.get("event")
        if kind == "trial_proposed":
            tid = int(ev["trial_id"])
            t = _Trial(
                tid,
                Kind(int(ev["kind"])),
                {str(k): float(v) for k, v in ev["params"].items()},
                _f(ev.get("predicted_j")),
                _f(ev.get("predicted_std")),
            )
            self.trials[tid] = t
            self.current = t
            self.next_trial_id = max(self.next_trial_id, tid + 1)
            if replay and t.kind != Kind.CONFIRMATION:
                self.opt.restore_ask(t.params, ev.get("optimizer_state"))
        elif kind == "apply_requested":
            t = self._trial_of(ev)
            t.apply_try = int(ev["apply_try"])
            t.apply_outcome = ""
            t.confirmed = False
            t.phase = State.APPLYING
        elif kind == "apply_result":
            t = self._trial_of(ev)
            outcome = ev.get("outcome") or self._legacy_apply_outcome(t, ev)
            t.apply_outcome = str(outcome)
            t.apply_message = str(ev.get("message") or "")
            if outcome != APPLY_LINK_DOWN:
                t.link_since = math.nan
                t.link_lost_journaled = False
            if outcome == APPLY_CONFIRMED:
                t.confirmed = True
                t.busy_since = math.nan
            elif outcome == APPLY_BUSY:
                if math.isnan(t.busy_since):
                    t.busy_since = _f(ev.get("stamp"))
            elif outcome == APPLY_LINK_DOWN:  # paused: not a failed try
                if math.isnan(t.link_since):
                    t.link_since = _f(ev.get("stamp"))
            else:
                t.failed_applies += 1
                t.busy_since = math.nan
        elif kind == "link_lost":
            self._trial_of(ev).link_lost_journaled = True
        elif kind == "campaign_paused":
            # the link stayed down for link_timeout_s: the agent stopped (exit 2); a resume goes on with the trial
            self.finished = True
            self.exit_code = 2
            self.paused = True
        elif kind == "run_ready":
            t = self._trial_of(ev)
            t.attempt = int(ev["attempt"])
            t.phase = State.READY_TO_DRIVE
        elif kind == "run_rejected":
            t = self._trial_of(ev)
            t.rejections += 1
            t.last_reason = str(ev.get("reason", ""))
            t.phase = State.REJECTED
        elif kind == "trial_scored":
            t = self._trial_of(ev)
            t.phase = State.SCORED
            j = float(ev["j"])
            if t.kind == Kind.CONFIRMATION:
                self.confirmation_j = j
                self.confirmation_closed = True
            else:
                outcomes = {str(k): float(v) for k, v in (ev.get("outcomes") or {}).items() if v is not None}
                self.opt.tell(t.params, j, outcomes)
                if ev.get("violations"):
                    self.violated_trials.append(t.trial_id)
                self.trials_done += 1
                self.consecutive_failures = 0
                self.last_j = j
                if not (self.best_j <= j):
                    self.best_j = j
                    self.best_trial_id = t.trial_id
        elif kind == "trial_failed":
            t = self._trial_of(ev)
            t.phase = State.FAILED
            t.last_reason = str(ev.get("reason", ""))
            if t.kind == Kind.CONFIRMATION:
                self.confirmation_closed = True
            else:
                self.opt.tell_failed(t.params, t.last_reason)
                self.trials_done += 1
                self.consecutive_failures += 1
        elif kind == "recommendation":
            best = ev.get("best_observed_params")
            self.recommendation = Recommendation(
                {str(k): float(v) for k, v in ev["params"].items()},
                _f(ev.get("predicted_j")),
                _f(ev.get("predicted_std")),
                int(ev.get("n_observations") or 0),
                {str(k): float(v) for k, v in best.items()} if isinstance(best, Mapping) else None,
                _f(ev.get("best_observed_j")),
                dict(ev.get("predicted_outcomes") or {}),
                {str(k): float(v) for k, v in (ev.get("transfer") or {}).items()},
                str(ev.get("rule") or "mean"),
            )
        elif kind == "campaign_done":
            self.finished = True
            self.exit_code = 0
            self.current = None
        elif kind == "campaign_failed":
            self.finished = True
            self.exit_code = 1
            self.current = None
        elif kind == "campaign_resumed":
            self.resumes += 1
            if self.paused:  # a campaign stopped for a lost ECU link goes on
                self.finished = False
                self.exit_code = None
                self.paused = False
            open_trial = self._open_trial()
            if open_trial is not None:
                # the ECU's state is unknown to a new process: the trial is applied again, and a busy ECU's
                # window starts again (the ROS clock of a new launch, sim time, cannot be compared with the
                # journaled stamps)
                open_trial.confirmed = False
                open_trial.busy_since = math.nan
                open_trial.link_since = math.nan
                open_trial.link_lost_journaled = False
        # campaign_started, score_ignored: nothing to change

    def _legacy_apply_outcome(self, t: _Trial, ev: Mapping[str, Any]) -> str:
        """The outcome of an apply_result journaled without one (schema 1), as the agent decided it then."""
        if ev.get("success"):
            return APPLY_CONFIRMED
        if int(ev.get("error_code") or 0) == ERROR_ECU_BUSY:
            now = _f(ev.get("stamp"))
            since = now if math.isnan(t.busy_since) else t.busy_since
            if now - since < self.cfg.busy_timeout_s:
                return APPLY_BUSY
        return APPLY_FAILED

    def _open_trial(self) -> _Trial | None:
        t = self.current
        if t is None or t.phase in (State.SCORED, State.FAILED) or (self.finished and not self.paused):
            return None
        return t

    # --- start / resume ------------------------------------------------------------------------
    def started_record(self) -> dict[str, Any]:
        """The fields of this agent's ``campaign_started`` event (its configuration)."""
        return {
            "schema": SCHEMA_VERSION,
            "names": list(self.opt.names),
            "strategy": self.cfg.strategy,
            "budget": self.cfg.budget,
            "seed": self.cfg.seed,
            "config": {
                "max_attempts": self.cfg.max_attempts,
                "apply_retries": self.cfg.apply_retries,
                "apply_timeout_s": self.cfg.apply_timeout_s,
                "run_timeout_s": self.cfg.run_timeout_s,
                "confirmation_run": self.cfg.confirmation_run,
                "max_consecutive_failures": self.cfg.max_consecutive_failures,
                "busy_retry_s": self.cfg.busy_retry_s,
                "busy_timeout_s": self.cfg.busy_timeout_s,
                "link_retry_s": self.cfg.link_retry_s,
                "link_timeout_s": self.cfg.link_timeout_s,
                **dict(self.cfg.extra),
                # the limits runs are booked against (issue 23); absent without limits, as before them
                **({"outcome_limits": list(self.cfg.outcome_limits)} if self.cfg.outcome_limits else {}),
            },
            "definition": self.definition,
        }

    def check_resume(self) -> list[str]:
        """Raise :class:`CampaignError` when the journal cannot be resumed by this agent (another campaign or
        configuration, naming each difference); return the time limits that changed (allowed, journaled with
        the resume). Nothing to check for an empty journal."""
        events = self.journal.events
        if not events:
            return []
        first = events[0]
        if first.get("event") != "campaign_started":
            raise CampaignError(f"{self.journal.path}: the first event is {first.get('event')!r}, not campaign_started")
        schema = first.get("schema")
        if not isinstance(schema, int) or schema > SCHEMA_VERSION:
            raise CampaignError(
                f"{self.journal.path} has journal schema {schema!r}; this agent reads schema <= {SCHEMA_VERSION} "
                "(a newer bac wrote it): resume it with that version, or use a new campaign_dir"
            )
        journaled = {"campaign_id": first.get("campaign_id"), **{k: first.get(k) for k in _STARTED_KEYS}}
        rec = self.started_record()
        mine = {"campaign_id": self.cfg.campaign_id, **{k: rec[k] for k in _STARTED_KEYS}}
        for side in (journaled, mine):
            conf = side.get("config")
            if isinstance(conf, Mapping):
                side["config"] = {**ADDED_LATER, **conf}
        confs = [side.get("config") for side in (journaled, mine)]
        for inert, keys in INERT_UNLESS:  # keys that change nothing on both sides: not a reason to refuse
            if all(isinstance(c, dict) and inert(c) for c in confs):
                for c in confs:
                    for k in keys:
                        c.pop(k, None)  # type: ignore[union-attr]
        problems, changed = config_differences(journaled, mine)
        if problems:
            raise CampaignError(
                f"cannot resume the campaign in {self.journal.path}: it was started with another configuration "
                f"than this agent's:\n  - "
                + "\n  - ".join(problems)
                + "\nA resumed campaign must go on as the interrupted one would have. To resume it, launch the "
                "agent with the journaled values; to run this configuration, start a new campaign: use a new "
                "campaign_dir (bac launch --campaign-dir NEW_DIR, or bo_agent's campaign_dir parameter)."
            )
        return changed

    def start(self) -> list[Action]:
        """Begin a new campaign, or resume the one in the journal."""
        acts: list[Action] = []
        if self.journal.torn:
            acts.append(
                Log(
                    "warn",
                    f"journal {self.journal.path}: the last line was torn ({len(self.journal.torn)} bytes, "
                    "a write cut by a crash); it was moved to journal.jsonl.torn, earlier events kept",
                )
            )
        events = self.journal.events
        if not events:
            self._record("campaign_started", **self.started_record())
            acts.append(Log("info", f"campaign '{self.cfg.campaign_id}' started: budget {self.cfg.budget}"))
            return acts + self._next_trial()
        return acts + self._resume(events)

    def _resume(self, events: list[dict[str, Any]]) -> list[Action]:
        changed = self.check_resume()
        self.resumed = True
        for ev in events:
            self._reduce(ev, replay=True)
        acts: list[Action] = []
        if events[0].get("schema") != SCHEMA_VERSION:
            acts.append(
                Log(
                    "warn",
                    f"{self.journal.path} has journal schema {events[0].get('schema')} (an older bac): it does not "
                    "hold the optimizer's random state, so the next calibrations will not be those the "
                    "uninterrupted campaign would have proposed",
                )
            )
        if changed:
            acts.append(Log("warn", "resumed with other time limits than journaled: " + "; ".join(changed)))
        t = self._open_trial()
        self._record(
            "campaign_resumed",
            trials_done=self.trials_done,
            in_flight=[t.trial_id] if t is not None else [],
            torn_bytes=len(self.journal.torn),
            changed=changed,
        )
        acts.append(
            Log(
                "info",
                f"campaign '{self.cfg.campaign_id}' resumed from {self.journal.path}: "
                f"{self.trials_done}/{self.cfg.budget} trials done"
                + (f", trial {t.trial_id} interrupted: applying it again" if t is not None else ""),
            )
        )
        if self.finished:
            if self.exit_code == 0:
                return [*acts, self._status(State.DONE, self._done_text()), Finish(0, self.recommendation)]
            return [*acts, Log("error", "the campaign had ended without any scored run"), Finish(1, None)]
        if t is not None:
            return acts + self._continue(t)
        return acts + self._next_trial()

    def _continue(self, t: _Trial) -> list[Action]:
        """Go on with the trial that was open when the agent stopped: a decision the journal holds the grounds of
        but not the result (a failed try or a rejection that used up the trial's tries, journaled just before a
        crash) is taken now, by the live code; otherwise the calibration is applied again (the ECU's state is
        unknown to this process) and then driven with the next attempt number."""
        if t.phase == State.APPLYING and t.apply_outcome == APPLY_FAILED:
            return self._apply_failed(t, t.apply_message)
        if t.phase == State.REJECTED and t.rejections >= self.cfg.max_attempts:
            return self._after_reject(t, [])
        return self._apply(t)

    # --- the loop ------------------------------------------------------------------------------
    def _next_trial(self) -> list[Action]:
        if self.trials_done >= self.cfg.budget:
            return self._wrap_up()
        if self.consecutive_failures >= self.cfg.max_consecutive_failures:
            return [
                Log(
                    "error",
                    f"{self.consecutive_failures} trials failed in a row: stopping the campaign early "
                    "(check the ECU bridge, the CAN adapter and the run chain)",
                ),
                *self._wrap_up(),
            ]
        s = self.opt.ask_with_info()
        tid = self.next_trial_id
        extra: dict[str, Any] = {"model": dict(s.info)} if s.info else {}
        self._record(
            "trial_proposed",
            trial_id=tid,
            kind=int(_KIND_OF_SUGGESTION.get(s.kind, Kind.OPTIMIZED)),
            params=dict(s.params),
            predicted_j=s.predicted_j,
            predicted_std=s.predicted_std,
            reason=s.kind,
            optimizer_state=self.opt.ask_state(),
            **extra,
        )
        t = self.trials[tid]
        acts: list[Action] = []
        for key in ("safe_start_broke", "no_safe_candidate"):
            if key in s.info:
                acts.append(Log("warn", f"trial {tid}: {s.info[key]}"))
        return [
            *acts,
            self._status(State.PROPOSED, f"Wait: trial {tid} calibration chosen ({s.kind})."),
            *self._apply(t),
        ]

    def _apply(self, t: _Trial, delay_s: float = 0.0, instruction: str = "") -> list[Action]:
        self._record(
            "apply_requested", trial_id=t.trial_id, apply_try=t.apply_try + 1, params=t.params, delay_s=delay_s
        )
        return [
            self._status(
                State.APPLYING,
                instruction or f"Do not drive: writing trial {t.trial_id}'s calibration to the ECU.",
            ),
            Apply(t.trial_id, t.apply_try, dict(t.params), self.cfg.apply_timeout_s, delay_s),
        ]

    def on_apply_result(
        self,
        trial_id: int,
        apply_try: int,
        success: bool,
        error_code: int = 0,
        message: str = "",
        applied: Mapping[str, float] | None = None,
        latency_s: float = math.nan,
        attempts: int = 0,
    ) -> list[Action]:
        """The bridge answered an Apply (``attempts``: the bridge's CAN transactions for it; 0 = not told)."""
        t = self.current
        if t is None or t.trial_id != trial_id or t.apply_try != apply_try or t.phase != State.APPLYING:
            return [Log("warn", f"ignored an apply answer for trial {trial_id} try {apply_try}: not awaited")]
        reason = "" if success else f"ECU apply failed (error {error_code}): {message}"
        if success and self.verify_applied is not None:
            problem = self.verify_applied(t.params, applied or {})
            if problem:
                success, reason = False, f"the ECU echoed other values than requested: {problem}"
        now = self.clock()
        outcome = APPLY_CONFIRMED if success else APPLY_FAILED
        if not success and error_code == ERROR_ECU_BUSY:
            since = now if math.isnan(t.busy_since) else t.busy_since
            if now - since < self.cfg.busy_timeout_s:
                outcome = APPLY_BUSY
        elif not success and error_code == ERROR_BUS:
            # the campaign pauses (no trial fails) until the link is back, for link_timeout_s (_link_down)
            outcome = APPLY_LINK_DOWN
        self._record(
            "apply_result",
            stamp=now,
            trial_id=trial_id,
            apply_try=apply_try,
            success=bool(success),
            error_code=int(error_code),
            message=message if success else reason,
            applied=dict(applied or {}),
            latency_s=latency_s,
            attempts=int(attempts),
            outcome=outcome,
        )
        if outcome == APPLY_CONFIRMED:
            return self._ready(t)
        if outcome == APPLY_LINK_DOWN:
            return self._link_down(t, message)
        if outcome == APPLY_BUSY:
            return [
                Log("info", f"trial {t.trial_id}: the ECU is busy (vehicle moving); asking again"),
                *self._apply(
                    t,
                    self.cfg.busy_retry_s,
                    "Stop the vehicle: the ECU takes a new calibration only at standstill.",
                ),
            ]
        return self._apply_failed(t, reason)

    def _link_down(self, t: _Trial, message: str) -> list[Action]:
        """The CAN link to the ECU is down: the campaign pauses (no trial fails) until it is back, within bounds."""
        now = self.clock()
        if not t.link_lost_journaled:
            self._record("link_lost", stamp=now, trial_id=t.trial_id, message=message)
        down = now - t.link_since
        if down < self.cfg.link_timeout_s:
            return [
                Log("warn", f"trial {t.trial_id}: the ECU link is down ({message}); paused, asking again"),
                *self._apply(
                    t,
                    self.cfg.link_retry_s,
                    f"Wait: the campaign is paused, the CAN link to the ECU is down ({message[:200]}). Check that "
                    "the adapter is plugged in and its interface up; the campaign goes on by itself.",
                ),
            ]
        self._record("campaign_paused", stamp=now, trial_id=t.trial_id, down_s=down, message=message)
        text = (
            f"The ECU link stayed down for {down:.0f} s ({message[:200]}): the campaign stops here, no trial failed. "
            f"Fix the link and launch again with the same campaign folder ({self.campaign_dir}) to resume it."
        )
        return [Log("error", text), self._status(State.IDLE, text, message), Finish(2, None)]

    def on_apply_timeout(self, trial_id: int, apply_try: int, reason: str) -> list[Action]:
        """No answer from the bridge within the time limit (or the service is not there)."""
        t = self.current
        if t is None or t.trial_id != trial_id or t.apply_try != apply_try or t.phase != State.APPLYING:
            return []
        self._record(
            "apply_result",
            trial_id=trial_id,
            apply_try=apply_try,
            success=False,
            error_code=-1,
            message=reason,
            outcome=APPLY_FAILED,
        )
        return self._apply_failed(t, reason)

    def _apply_failed(self, t: _Trial, reason: str) -> list[Action]:
        # the failed try was counted by the reducer (apply_result)
        if t.failed_applies <= self.cfg.apply_retries:
            return [Log("warn", f"trial {t.trial_id}: {reason}; retrying the apply"), *self._apply(t)]
        return self._fail(t, f"{reason} (after {t.failed_applies} failed tries)")

    def _ready(self, t: _Trial) -> list[Action]:
        self._record("run_ready", trial_id=t.trial_id, attempt=t.attempt + 1)
        what = "confirmation run of the recommendation" if t.kind == Kind.CONFIRMATION else f"trial {t.trial_id}"
        if t.attempt > 1:
            text = (
                f"Go back before the start of the segment, then drive it again at the target speed ({what}, run "
                f"{t.attempt}): only a new drive counts, the rest of the last run is not used."
            )
        else:
            text = f"Drive the segment now at the target speed ({what}, run {t.attempt})."
        return [
            self._status(State.READY_TO_DRIVE, text, t.last_reason),
            AwaitRun(t.trial_id, t.attempt, self.cfg.run_timeout_s),
        ]

    def on_score(
        self,
        campaign_id: str,
        trial_id: int,
        attempt: int,
        valid: bool,
        j: float,
        reason: str = "",
        details: Mapping[str, Any] | None = None,
        outcomes: Mapping[str, float] | None = None,
    ) -> list[Action]:
        """A RunScore arrived; booked only if it is the run the agent is waiting for. ``outcomes``: what the run
        measured besides J (RunScore.outcome_names / outcome_values), checked against the outcome limits."""
        t = self.current
        why = ""
        if campaign_id != self.cfg.campaign_id:
            why = f"campaign '{campaign_id}' is not this campaign"
        elif t is None or t.trial_id != trial_id or t.attempt != attempt:
            cur = f"{t.trial_id}/{t.attempt}" if t else "none"
            why = f"trial/attempt {trial_id}/{attempt} is not the current run ({cur})"
        elif t.phase != State.READY_TO_DRIVE or not t.confirmed:
            why = f"trial {trial_id} is not waiting for a run (state {t.phase.name}, ECU confirmed: {t.confirmed})"
        if why:
            if campaign_id == self.cfg.campaign_id:
                self._record("score_ignored", trial_id=trial_id, attempt=attempt, reason=why)
            return [Log("warn", f"score ignored: {why}")]
        assert t is not None
        if valid and not math.isfinite(j):
            valid, reason = False, f"J is not finite ({j!r})"
        if not valid:
            return self._reject(t, reason or "invalid run (no reason given)")
        measured = {str(k): float(v) for k, v in (outcomes or {}).items()}
        broken = violations(self.cfg.limits, measured)
        self._record(
            "trial_scored",
            trial_id=t.trial_id,
            attempt=attempt,
            kind=int(t.kind),
            params=t.params,
            j=float(j),
            predicted_j=t.predicted_j,
            predicted_std=t.predicted_std,
            details=dict(details or {}),
            outcomes=measured,
            violations=broken,
        )
        note: list[Action] = []
        if broken:
            note.append(Log("warn", f"trial {t.trial_id} broke an outcome limit: {'; '.join(broken)}"))
        if t.kind == Kind.CONFIRMATION:
            return [
                *note,
                Log("info", f"confirmation run of the recommendation: J={j:.4g}"),
                self._status(State.SCORED, f"Confirmation run scored J={j:.4g}.", "; ".join(broken), t=t),
                *self._done(),
            ]
        line = (
            f"trial {self.trials_done}/{self.cfg.budget} {fmt_params(t.params)} J={j:.4g} "
            f"best={self.best_j:.4g} (trial {self.best_trial_id})"
        )
        text = f"Run scored J={j:.4g}; wait for the next calibration."
        if broken:
            text = (
                f"Run scored J={j:.4g} but broke an outcome limit ({'; '.join(broken)}); wait for the next calibration."
            )
        return [
            *note,
            Log("info", line),
            self._status(State.SCORED, text, "; ".join(broken), t=t),
            *self._next_trial(),
        ]

    def on_run_timeout(self, trial_id: int, attempt: int) -> list[Action]:
        t = self.current
        if t is None or t.trial_id != trial_id or t.attempt != attempt or t.phase != State.READY_TO_DRIVE:
            return []
        return self._reject(t, f"no valid score within run_timeout_s = {self.cfg.run_timeout_s:g} s")

    def _reject(self, t: _Trial, reason: str) -> list[Action]:
        self._record("run_rejected", trial_id=t.trial_id, attempt=t.attempt, reason=reason)
        return self._after_reject(
            t,
            [
                Log("warn", f"trial {t.trial_id} run {t.attempt} rejected: {reason}"),
                self._status(State.REJECTED, f"Run rejected: {reason}. The same calibration is driven again.", reason),
            ],
        )

    def _after_reject(self, t: _Trial, acts: list[Action]) -> list[Action]:
        if t.rejections >= self.cfg.max_attempts:
            return acts + self._fail(t, f"{t.rejections} invalid runs, the last: {t.last_reason}")
        return acts + self._ready(t)

    def _fail(self, t: _Trial, reason: str) -> list[Action]:
        self._record("trial_failed", trial_id=t.trial_id, kind=int(t.kind), params=t.params, reason=reason)
        acts: list[Action] = [
            Log("warn", f"trial {t.trial_id} failed: {reason}"),
            self._status(State.FAILED, f"Trial {t.trial_id} given up: {reason}", reason, t=t),
        ]
        if t.kind == Kind.CONFIRMATION:
            return acts + self._done()
        return acts + self._next_trial()

    # --- the end -----------------------------------------------------------------------------------
    def _wrap_up(self) -> list[Action]:
        if self.recommendation is None:
            try:
                made = self.opt.recommend()
            except BacError as exc:
                self._record("campaign_failed", reason=f"no recommendation: {exc}")
                return [
                    Log("error", f"campaign ended without any scored run: {exc}"),
                    Finish(1, None),
                ]
            extra: dict[str, Any] = {}
            if made.predicted_outcomes:
                extra["predicted_outcomes"] = dict(made.predicted_outcomes)
            if made.transfer:
                extra["transfer"] = dict(made.transfer)
            self._record(
                "recommendation",
                params=made.params,
                predicted_j=made.predicted_j,
                predicted_std=made.predicted_std,
                n_observations=made.n_observations,
                best_observed_params=made.best_observed_params,
                best_observed_j=made.best_observed_j,
                rule=made.rule,
                **extra,
            )
        rec = self.recommendation
        assert rec is not None
        acts: list[Action] = [
            Log(
                "info",
                f"recommendation after {self.trials_done} trials: {fmt_params(rec.params)} "
                f"predicted J={rec.predicted_j:.4g} ± {rec.predicted_std:.2g}",
            )
        ]
        if self.cfg.confirmation_run and not self.confirmation_closed:
            tid = self.next_trial_id
            self._record(
                "trial_proposed",
                trial_id=tid,
                kind=int(Kind.CONFIRMATION),
                params=dict(rec.params),
                predicted_j=rec.predicted_j,
                predicted_std=rec.predicted_std,
                reason="confirmation",
            )
            return [
                *acts,
                self._status(State.PROPOSED, "Wait: confirmation run of the recommendation next."),
                *self._apply(self.trials[tid]),
            ]
        return acts + self._done()

    def _done_text(self) -> str:
        rec = self.recommendation
        if rec is None:
            return "Campaign done."
        return (
            f"Campaign done. Recommended calibration {fmt_params(rec.params)} "
            f"(predicted J={rec.predicted_j:.4g}). You can stop."
        )

    def recommendation_record(self) -> dict[str, Any]:
        """What ``recommendation.json`` holds (from the campaign's state)."""
        rec = self.recommendation
        assert rec is not None
        return {
            "campaign_id": self.cfg.campaign_id,
            "strategy": self.cfg.strategy,
            "params": rec.params,
            "predicted_j": rec.predicted_j,
            "predicted_std": rec.predicted_std,
            "rule": rec.rule,  # how it was chosen (bo_agent's recommend_rule)
            "n_observations": rec.n_observations,
            "trials_done": self.trials_done,
            "best_observed_params": rec.best_observed_params,
            "best_observed_j": rec.best_observed_j,
            "best_trial_id": self.best_trial_id,
            "confirmation_j": self.confirmation_j,
            "predicted_outcomes": dict(rec.predicted_outcomes),
            "transfer": dict(rec.transfer),
            "violated_trials": list(self.violated_trials),
        }

    def _done(self) -> list[Action]:
        rec = self.recommendation
        assert rec is not None
        write_json_atomic(self.campaign_dir / RECOMMENDATION_NAME, self.recommendation_record())
        self._record("campaign_done", trials_done=self.trials_done, confirmation_j=self.confirmation_j)
        return [self._status(State.DONE, self._done_text()), Finish(0, rec)]


# the fields of campaign_started compared on resume (with campaign_id)
_STARTED_KEYS = ("names", "strategy", "budget", "seed", "config", "definition")
# config entries a resume may change: waiting limits, which change neither what the optimizer is told nor what a
# run measures (the journal keeps the new values in campaign_resumed.changed); definition_file is the spelling of a
# path, the definition itself is compared
RESUME_MAY_CHANGE = frozenset(
    {
        "apply_timeout_s",
        "run_timeout_s",
        "busy_retry_s",
        "busy_timeout_s",
        "link_retry_s",
        "link_timeout_s",
        "link_wait_s",
        "definition_file",
    }
)
# configuration keys added after campaigns were journaled without them, with the value such a campaign ran with: a
# journal without the key is compared as if it held that value, so it resumes when the agent keeps it (issue 23,
# 2026-11-24: no outcome priors, no limit on the transfer prior's runs, no safe start, no model average, the bowl
# unchecked by leave-one-out; 2026-11-25: the outcome limits' least risky calibrations and design without the
# retreat's trend, one GP fit without the model average over two lengthscale priors, no exploration along the faces;
# neither limit_trend_far (opt-in) nor limit_reach (the default since 2026-11-25), journaled since they became
# bo_agent parameters)
ADDED_LATER: Mapping[str, Any] = {
    "recommend_rule": "mean",
    "outcome_priors": {},
    "prior_runs": 0,
    "safe_start": {},
    "prior_average": False,
    "gp_bowl_loo": False,
    "limit_trend": False,
    "gp_ls_average": 0.0,
    "limit_far_sd": 0.0,
    "prior_average_ls": False,
    "face_explore": 0,
    "limit_trend_far": 0.0,
    "limit_reach": 0.0,
}
# configuration keys that change nothing where what they act on is absent, with the test for that absence: a
# difference in them does not refuse a resume (the bowl's length and leave-one-out check without the bowl; the model
# average without a transfer prior, outside review D2; the retreat's trend and the limits' other options without
# outcome limits)
INERT_UNLESS: tuple[tuple[Callable[[Mapping[str, Any]], bool], tuple[str, ...]], ...] = (
    (lambda c: c.get("gp_mean", "bowl") != "bowl", ("bowl_runs", "gp_bowl_loo")),
    (lambda c: not c.get("prior"), ("prior_average", "prior_average_ls")),
    (lambda c: not c.get("constraints"), ("limit_trend", "limit_far_sd", "limit_trend_far", "limit_reach")),
)
_MISSING = object()


def _json_form(value: Any) -> Any:
    """``value`` as it reads back from the journal (strict JSON: tuples are lists, NaN is null)."""
    return json.loads(json.dumps(strict_json(value), allow_nan=False))


def _show(value: Any) -> str:
    if value is _MISSING:
        return "(not journaled: an older bac)"
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 80 else text[:77] + "..."


def _diff_paths(a: Any, b: Any, path: str, out: list[tuple[str, Any, Any]]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in list(a) + [k for k in b if k not in a]:
            _diff_paths(a.get(k, _MISSING), b.get(k, _MISSING), f"{path}.{k}" if path else str(k), out)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _diff_paths(x, y, f"{path}[{i}]", out)
    elif a != b or (type(a) is not type(b) and not (isinstance(a, int | float) and isinstance(b, int | float))):
        out.append((path, a, b))


def config_differences(journaled: Mapping[str, Any], mine: Mapping[str, Any]) -> tuple[list[str], list[str]]:
    """(differences that forbid a resume, time limits that changed), each as ``what: journaled X, this agent
    Y``; both configurations as ``campaign_started`` holds them (with ``campaign_id``)."""
    diffs: list[tuple[str, Any, Any]] = []
    _diff_paths(_json_form(dict(journaled)), _json_form(dict(mine)), "", diffs)
    problems: list[str] = []
    changed: list[str] = []
    shown_definition = 0
    for path, a, b in diffs:
        line = f"{path}: journaled {_show(a)}, this agent {_show(b)}"
        if path.startswith("config.") and path.split(".")[1] in RESUME_MAY_CHANGE:
            changed.append(line)
        elif path.startswith("definition"):
            shown_definition += 1
            if shown_definition <= 5:
                problems.append(line)
            elif shown_definition == 6:
                problems.append("definition: more differences")
        else:
            problems.append(line)
    return problems, changed


def _f(v: Any) -> float:
    return math.nan if v is None else float(v)


__all__ = [
    "RECOMMENDATION_NAME",
    "Action",
    "Apply",
    "AwaitRun",
    "Campaign",
    "CampaignConfig",
    "CampaignError",
    "Finish",
    "JournalError",
    "Kind",
    "Log",
    "Optimizer",
    "Publish",
    "State",
    "TrialStatus",
]
