"""The campaign state machine of algorithm 1, without ROS.

propose → apply (ECU bridge) → ready to drive → score → update, until the budget;
then recommend (and optionally drive a confirmation run of the recommendation).

The node feeds it events (:meth:`Campaign.on_apply_result`, :meth:`on_apply_timeout`,
:meth:`on_score`, :meth:`on_run_timeout`) and executes the actions it returns, in
order (:class:`Publish`, :class:`Apply`, :class:`AwaitRun`, :class:`Finish`,
:class:`Log`). Every decision is journaled before it is acted on, so a campaign
killed at any moment resumes from its journal (:meth:`Campaign.start`): scored and
failed trials are replayed into the optimizer, a trial that was being applied or
driven is applied again and driven again with a new attempt number, so a late
score of the interrupted run is never booked against a calibration this process
has not seen the ECU confirm.

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
    Recommendation,
    Suggestion,
)
from bac_agent.journal import SCHEMA_VERSION, Journal, JournalError, write_json_atomic
from bac_common.errors import BacError

RECOMMENDATION_NAME = "recommendation.json"
ERROR_ECU_BUSY = 4  # bac_msgs/srv/ApplyCalibration ERROR_ECU_BUSY: the ECU refuses while the vehicle moves


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
    confirmed: bool = False
    phase: State = State.PROPOSED
    last_reason: str = ""


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
        self.resumed = False
        self.violated_trials: list[int] = []  # trials whose run broke an outcome limit (booked, shown)

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

    def _j(self, event: str, **fields: Any) -> dict[str, Any]:
        return self.journal.append(event, campaign_id=self.cfg.campaign_id, stamp=self.clock(), **fields)

    # --- start / resume ------------------------------------------------------------------------
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
            self._j(
                "campaign_started",
                schema=SCHEMA_VERSION,
                names=list(self.opt.names),
                strategy=self.cfg.strategy,
                budget=self.cfg.budget,
                seed=self.cfg.seed,
                config={
                    "max_attempts": self.cfg.max_attempts,
                    "apply_retries": self.cfg.apply_retries,
                    "apply_timeout_s": self.cfg.apply_timeout_s,
                    "run_timeout_s": self.cfg.run_timeout_s,
                    "confirmation_run": self.cfg.confirmation_run,
                    "max_consecutive_failures": self.cfg.max_consecutive_failures,
                    "busy_retry_s": self.cfg.busy_retry_s,
                    "busy_timeout_s": self.cfg.busy_timeout_s,
                    **dict(self.cfg.extra),
                },
                definition=self.definition,
            )
            acts.append(Log("info", f"campaign '{self.cfg.campaign_id}' started: budget {self.cfg.budget}"))
            return acts + self._next_trial()
        return acts + self._resume(events)

    def _resume(self, events: list[dict[str, Any]]) -> list[Action]:
        first = events[0]
        if first.get("event") != "campaign_started":
            raise CampaignError(f"{self.journal.path}: the first event is {first.get('event')!r}, not campaign_started")
        if list(first.get("names", [])) != list(self.opt.names) or first.get("strategy") != self.cfg.strategy:
            raise CampaignError(
                f"{self.journal.path} belongs to a campaign over {first.get('names')} with strategy "
                f"{first.get('strategy')!r}; this agent optimizes {list(self.opt.names)} with {self.cfg.strategy!r}. "
                "Use a new campaign_dir, or the same definition and strategy to resume."
            )
        if first.get("campaign_id") != self.cfg.campaign_id:
            raise CampaignError(
                f"{self.journal.path} belongs to campaign {first.get('campaign_id')!r}, not {self.cfg.campaign_id!r}"
            )
        self.resumed = True
        trials: dict[int, _Trial] = {}
        closed: set[int] = set()
        done_event: dict[str, Any] | None = None
        for ev in events[1:]:
            kind = ev.get("event")
            tid = int(ev.get("trial_id") or 0)
            if kind == "trial_proposed":
                trials[tid] = _Trial(
                    tid,
                    Kind(int(ev["kind"])),
                    {str(k): float(v) for k, v in ev["params"].items()},
                    _f(ev.get("predicted_j")),
                    _f(ev.get("predicted_std")),
                )
                self.next_trial_id = max(self.next_trial_id, tid + 1)
            elif kind == "run_ready" and tid in trials:
                trials[tid].attempt = max(trials[tid].attempt, int(ev["attempt"]))
            elif kind == "run_rejected" and tid in trials:
                trials[tid].rejections += 1
            elif kind == "trial_scored" and tid in trials:
                closed.add(tid)
                t = trials[tid]
                j = float(ev["j"])
                if t.kind == Kind.CONFIRMATION:
                    self.confirmation_j = j
                    self.confirmation_closed = True
                else:
                    outcomes = {str(k): float(v) for k, v in (ev.get("outcomes") or {}).items() if v is not None}
                    self.opt.tell(t.params, j, outcomes)
                    self._book_score(tid, j)
                    if ev.get("violations"):
                        self.violated_trials.append(tid)
            elif kind == "trial_failed" and tid in trials:
                closed.add(tid)
                t = trials[tid]
                if t.kind == Kind.CONFIRMATION:
                    self.confirmation_closed = True
                else:
                    self.opt.tell_failed(t.params, str(ev.get("reason", "")))
                    self.trials_done += 1
                    self.consecutive_failures += 1
            elif kind == "recommendation":
                self.recommendation = Recommendation(
                    {str(k): float(v) for k, v in ev["params"].items()},
                    _f(ev.get("predicted_j")),
                    _f(ev.get("predicted_std")),
                    int(ev.get("n_observations", 0)),
                )
            elif kind == "campaign_done":
                done_event = ev
        open_trials = [t for tid, t in trials.items() if tid not in closed]
        self._j(
            "campaign_resumed",
            trials_done=self.trials_done,
            in_flight=[t.trial_id for t in open_trials],
            torn_bytes=len(self.journal.torn),
        )
        acts: list[Action] = [
            Log(
                "info",
                f"campaign '{self.cfg.campaign_id}' resumed from {self.journal.path}: "
                f"{self.trials_done}/{self.cfg.budget} trials done"
                + (f", trial {open_trials[-1].trial_id} interrupted: applying it again" if open_trials else ""),
            )
        ]
        if done_event is not None:
            self.finished = True
            return [*acts, self._status(State.DONE, self._done_text()), Finish(0, self.recommendation)]
        if open_trials:
            t = open_trials[-1]
            self.current = t
            return acts + self._apply(t)
        return acts + self._next_trial()

    # --- the loop ------------------------------------------------------------------------------
    def _book_score(self, trial_id: int, j: float) -> None:
        self.trials_done += 1
        self.consecutive_failures = 0
        self.last_j = j
        if not (self.best_j <= j):
            self.best_j = j
            self.best_trial_id = trial_id

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
        self.next_trial_id += 1
        t = _Trial(tid, _KIND_OF_SUGGESTION.get(s.kind, Kind.OPTIMIZED), dict(s.params), s.predicted_j, s.predicted_std)
        self.current = t
        extra: dict[str, Any] = {"model": dict(s.info)} if s.info else {}
        self._j(
            "trial_proposed",
            trial_id=tid,
            kind=int(t.kind),
            params=t.params,
            predicted_j=t.predicted_j,
            predicted_std=t.predicted_std,
            reason=s.kind,
            **extra,
        )
        acts: list[Action] = []
        if "no_safe_candidate" in s.info:
            acts.append(Log("warn", f"trial {tid}: {s.info['no_safe_candidate']}"))
        return [
            *acts,
            self._status(State.PROPOSED, f"Wait: trial {tid} calibration chosen ({s.kind})."),
            *self._apply(t),
        ]

    def _apply(self, t: _Trial, delay_s: float = 0.0, instruction: str = "") -> list[Action]:
        t.apply_try += 1
        t.confirmed = False
        t.phase = State.APPLYING
        self._j("apply_requested", trial_id=t.trial_id, apply_try=t.apply_try, params=t.params, delay_s=delay_s)
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
    ) -> list[Action]:
        """The bridge answered an Apply."""
        t = self.current
        if t is None or t.trial_id != trial_id or t.apply_try != apply_try or t.phase != State.APPLYING:
            return [Log("warn", f"ignored an apply answer for trial {trial_id} try {apply_try}: not awaited")]
        reason = "" if success else f"ECU apply failed (error {error_code}): {message}"
        if success and self.verify_applied is not None:
            problem = self.verify_applied(t.params, applied or {})
            if problem:
                success, reason = False, f"the ECU echoed other values than requested: {problem}"
        self._j(
            "apply_result",
            trial_id=trial_id,
            apply_try=apply_try,
            success=bool(success),
            error_code=int(error_code),
            message=message if success else reason,
            applied=dict(applied or {}),
            latency_s=latency_s,
        )
        if success:
            t.confirmed = True
            t.busy_since = math.nan
            return self._ready(t)
        if error_code == ERROR_ECU_BUSY:
            now = self.clock()
            if math.isnan(t.busy_since):
                t.busy_since = now
            if now - t.busy_since < self.cfg.busy_timeout_s:
                return [
                    Log("info", f"trial {t.trial_id}: the ECU is busy (vehicle moving); asking again"),
                    *self._apply(
                        t,
                        self.cfg.busy_retry_s,
                        "Stop the vehicle: the ECU takes a new calibration only at standstill.",
                    ),
                ]
        return self._apply_failed(t, reason)

    def on_apply_timeout(self, trial_id: int, apply_try: int, reason: str) -> list[Action]:
        """No answer from the bridge within the time limit (or the service is not there)."""
        t = self.current
        if t is None or t.trial_id != trial_id or t.apply_try != apply_try or t.phase != State.APPLYING:
            return []
        self._j("apply_result", trial_id=trial_id, apply_try=apply_try, success=False, error_code=-1, message=reason)
        return self._apply_failed(t, reason)

    def _apply_failed(self, t: _Trial, reason: str) -> list[Action]:
        t.failed_applies += 1
        t.busy_since = math.nan
        if t.failed_applies <= self.cfg.apply_retries:
            return [Log("warn", f"trial {t.trial_id}: {reason}; retrying the apply"), *self._apply(t)]
        return self._fail(t, f"{reason} (after {t.failed_applies} failed tries)")

    def _ready(self, t: _Trial) -> list[Action]:
        t.attempt += 1
        t.phase = State.READY_TO_DRIVE
        self._j("run_ready", trial_id=t.trial_id, attempt=t.attempt)
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
                self._j("score_ignored", trial_id=trial_id, attempt=attempt, reason=why)
            return [Log("warn", f"score ignored: {why}")]
        assert t is not None
        if valid and not math.isfinite(j):
            valid, reason = False, f"J is not finite ({j!r})"
        if not valid:
            return self._reject(t, reason or "invalid run (no reason given)")
        measured = {str(k): float(v) for k, v in (outcomes or {}).items()}
        broken = violations(self.cfg.limits, measured)
        self._j(
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
        t.phase = State.SCORED
        if t.kind == Kind.CONFIRMATION:
            self.confirmation_j = float(j)
            self.confirmation_closed = True
            return [
                *note,
                Log("info", f"confirmation run of the recommendation: J={j:.4g}"),
                self._status(State.SCORED, f"Confirmation run scored J={j:.4g}.", "; ".join(broken), t=t),
                *self._done(),
            ]
        self.opt.tell(t.params, float(j), measured)
        self._book_score(t.trial_id, float(j))
        if broken:
            self.violated_trials.append(t.trial_id)
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
        t.rejections += 1
        t.last_reason = reason
        self._j("run_rejected", trial_id=t.trial_id, attempt=t.attempt, reason=reason)
        acts: list[Action] = [
            Log("warn", f"trial {t.trial_id} run {t.attempt} rejected: {reason}"),
            self._status(State.REJECTED, f"Run rejected: {reason}. The same calibration is driven again.", reason),
        ]
        if t.rejections >= self.cfg.max_attempts:
            return acts + self._fail(t, f"{t.rejections} invalid runs, the last: {reason}")
        return acts + self._ready(t)

    def _fail(self, t: _Trial, reason: str) -> list[Action]:
        t.phase = State.FAILED
        self._j("trial_failed", trial_id=t.trial_id, kind=int(t.kind), params=t.params, reason=reason)
        acts: list[Action] = [
            Log("warn", f"trial {t.trial_id} failed: {reason}"),
            self._status(State.FAILED, f"Trial {t.trial_id} given up: {reason}", reason, t=t),
        ]
        if t.kind == Kind.CONFIRMATION:
            self.confirmation_closed = True
            return acts + self._done()
        self.opt.tell_failed(t.params, reason)
        self.trials_done += 1
        self.consecutive_failures += 1
        return acts + self._next_trial()

    # --- the end -----------------------------------------------------------------------------------
    def _wrap_up(self) -> list[Action]:
        if self.recommendation is None:
            try:
                rec = self.opt.recommend()
            except BacError as exc:
                self._j("campaign_failed", reason=f"no recommendation: {exc}")
                self.finished = True
                return [
                    Log("error", f"campaign ended without any scored run: {exc}"),
                    Finish(1, None),
                ]
            self.recommendation = rec
            extra: dict[str, Any] = {}
            if rec.predicted_outcomes:
                extra["predicted_outcomes"] = dict(rec.predicted_outcomes)
            if rec.transfer:
                extra["transfer"] = dict(rec.transfer)
            self._j(
                "recommendation",
                params=rec.params,
                predicted_j=rec.predicted_j,
                predicted_std=rec.predicted_std,
                n_observations=rec.n_observations,
                best_observed_params=rec.best_observed_params,
                best_observed_j=rec.best_observed_j,
                **extra,
            )
        rec = self.recommendation
        acts: list[Action] = [
            Log(
                "info",
                f"recommendation after {self.trials_done} trials: {fmt_params(rec.params)} "
                f"predicted J={rec.predicted_j:.4g} ± {rec.predicted_std:.2g}",
            )
        ]
        if self.cfg.confirmation_run and not self.confirmation_closed:
            tid = self.next_trial_id
            self.next_trial_id += 1
            t = _Trial(tid, Kind.CONFIRMATION, dict(rec.params), rec.predicted_j, rec.predicted_std)
            self.current = t
            self._j(
                "trial_proposed",
                trial_id=tid,
                kind=int(t.kind),
                params=t.params,
                predicted_j=t.predicted_j,
                predicted_std=t.predicted_std,
                reason="confirmation",
            )
            return [
                *acts,
                self._status(State.PROPOSED, "Wait: confirmation run of the recommendation next."),
                *self._apply(t),
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

    def _done(self) -> list[Action]:
        rec = self.recommendation
        assert rec is not None
        write_json_atomic(
            self.campaign_dir / RECOMMENDATION_NAME,
            {
                "campaign_id": self.cfg.campaign_id,
                "strategy": self.cfg.strategy,
                "params": rec.params,
                "predicted_j": rec.predicted_j,
                "predicted_std": rec.predicted_std,
                "n_observations": rec.n_observations,
                "trials_done": self.trials_done,
                "best_observed_params": rec.best_observed_params,
                "best_observed_j": rec.best_observed_j,
                "best_trial_id": self.best_trial_id,
                "confirmation_j": self.confirmation_j,
                "predicted_outcomes": dict(rec.predicted_outcomes),
                "transfer": dict(rec.transfer),
                "violated_trials": list(self.violated_trials),
            },
        )
        self._j("campaign_done", trials_done=self.trials_done, confirmation_j=self.confirmation_j)
        self.finished = True
        self.current = None
        return [self._status(State.DONE, self._done_text()), Finish(0, rec)]


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
