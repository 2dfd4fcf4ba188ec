"""What the cockpit shows, as one JSON-able state built from the graph's messages and the campaign journal.

Pure Python (no rclpy, no web library): the node, the offline server (``bac cockpit CAMPAIGN``) and the
terminal view (``bac watch``) all feed and read the same :class:`CockpitState`.

Inputs are converted from any object with the contract's attribute names (an rclpy message or a rosbags
message alike) by the ``*_from_msg`` functions, so a live graph and a campaign's bags give the same views.
Each ``on_*`` method returns the top-level keys of the snapshot it changed; the server sends those keys to
the browsers as a patch.

Snapshot keys (``CockpitState.snapshot()``):

* ``campaign``: id, folder, definition (tuned dimensions and bounds), strategy, budget, status sentence;
* ``trial``: the latest ``bac/trial`` with its state's headline and tone (READY TO DRIVE, DO NOT DRIVE, ...);
* ``speed``: the target speed (the segmenter's configuration, then each run's segment) and the last run's;
* ``trials``: one row per trial (the journal's, as ``bac report`` reads it; or built from ``bac/trial``
  when there is no journal), ``best``: the best scored trial, ``recommendation``: the final one;
* ``signals`` / ``spectra``: the last run's aligned a_z and pitch rate and the best run's, with their Welch
  spectra (the scorer's, else computed with :func:`bac_measure.kpi.welch_psd`);
* ``ecu``: the ECU link's diagnostics, the last apply (journal) and the calibration the ECU holds
  (``bac/calibration``); ``imu``: the IMU stream's diagnostics; ``diagnostics``: every status seen;
* ``model``: the GP view (:mod:`bac_cockpit.model`), computed apart and set with :meth:`CockpitState.set_model`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# bac_msgs/Trial STATE_* and KIND_* (the contract; the numbers are checked against the message in the tests)
STATE_NAMES = {
    0: "IDLE",
    1: "PROPOSED",
    2: "APPLYING",
    3: "READY_TO_DRIVE",
    4: "SCORED",
    5: "REJECTED",
    6: "FAILED",
    7: "DONE",
}
STATE_READY_TO_DRIVE = 3
STATE_DONE = 7
KIND_NAMES = {0: "initial", 1: "optimized", 2: "confirmation", 3: "grid", 4: "manual"}
KIND_CONFIRMATION = 2
# what the driver reads at a glance: (headline, tone); the tone picks the colour (page) and style (terminal)
HEADLINES = {
    0: ("WAITING FOR THE CAMPAIGN", "idle"),
    1: ("WAIT", "wait"),
    2: ("DO NOT DRIVE", "wait"),
    3: ("READY TO DRIVE", "go"),
    4: ("RUN SCORED", "info"),
    5: ("RUN REJECTED", "warn"),
    6: ("TRIAL FAILED", "error"),
    7: ("CAMPAIGN DONE", "done"),
}
DIAG_LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
# keys of the two health cards (the rest of a status is listed below them)
ECU_KEYS = (
    "ecu",
    "bus_state",
    "interface",
    "channel",
    "last_confirmed_trial",
    "last_confirmed_crc32",
    "applies_ok",
    "applies_failed",
    "retransmissions",
    "step_timeouts",
    "last_error",
)
IMU_KEYS = (
    "rate_hz",
    "nominal_rate_hz",
    "jitter_ms",
    "gaps",
    "longest_gap_s",
    "saturated",
    "nonfinite",
    "samples_in",
    "samples_out_without_data",
    "clock_jumps",
)
MAX_SIGNAL_POINTS = 2000


def finite_or_none(x: Any) -> float | None:
    """A float for JSON: None when missing or not finite."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _f(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


# --- message views -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrialView:
    """``bac/trial``."""

    campaign_id: str
    trial_id: int
    attempt: int
    state: int
    kind: int
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
    stamp_s: float


@dataclass(frozen=True)
class SegmentView:
    """``bac/run_segment`` (the aligned signals)."""

    campaign_id: str
    trial_id: int
    attempt: int
    mode: int
    sample_rate_hz: float
    mean_speed_mps: float
    target_speed_mps: float
    alignment_score: float
    coverage: float
    accel_z: FloatArray
    pitch_rate: FloatArray
    valid: bool
    reason: str


@dataclass(frozen=True)
class ScoreView:
    """``bac/run_score``."""

    campaign_id: str
    trial_id: int
    attempt: int
    j: float
    rms_accel_z: float
    rms_pitch_rate: float
    kpi: str
    psd_frequency_hz: FloatArray
    psd_accel_z: FloatArray
    psd_pitch_rate: FloatArray
    valid: bool
    reason: str


@dataclass(frozen=True)
class CalibrationView:
    """``bac/calibration``: what the ECU confirmed it holds."""

    trial_id: int
    params: dict[str, float]
    crc32: int


@dataclass(frozen=True)
class DiagView:
    """One ``diagnostic_msgs/DiagnosticStatus`` of ``/diagnostics``."""

    name: str
    level: int
    message: str
    hardware_id: str
    values: dict[str, str]


def _arr(x: Any) -> FloatArray:
    return np.asarray(x if x is not None else (), dtype=np.float64).ravel()


def _stamp_s(stamp: Any) -> float:
    return float(getattr(stamp, "sec", 0)) + 1e-9 * float(getattr(stamp, "nanosec", 0))


def trial_from_msg(m: Any) -> TrialView:
    cal = m.calibration
    return TrialView(
        campaign_id=str(m.campaign_id),
        trial_id=int(m.trial_id),
        attempt=int(m.attempt),
        state=int(m.state),
        kind=int(m.kind),
        params={str(n): float(v) for n, v in zip(cal.names, cal.values, strict=False)},
        budget=int(m.budget),
        trials_done=int(m.trials_done),
        last_j=float(m.last_j),
        best_j=float(m.best_j),
        best_trial_id=int(m.best_trial_id),
        predicted_j=float(m.predicted_j),
        predicted_j_std=float(m.predicted_j_std),
        instruction=str(m.instruction),
        reason=str(m.reason),
        stamp_s=_stamp_s(m.stamp),
    )


def segment_from_msg(m: Any) -> SegmentView:
    return SegmentView(
        campaign_id=str(m.campaign_id),
        trial_id=int(m.trial_id),
        attempt=int(m.attempt),
        mode=int(m.mode),
        sample_rate_hz=float(m.sample_rate_hz),
        mean_speed_mps=float(m.mean_speed_mps),
        target_speed_mps=float(m.target_speed_mps),
        alignment_score=float(m.alignment_score),
        coverage=float(m.coverage),
        accel_z=_arr(m.accel_z),
        pitch_rate=_arr(m.pitch_rate),
        valid=bool(m.valid),
        reason=str(m.reason),
    )


def score_from_msg(m: Any) -> ScoreView:
    return ScoreView(
        campaign_id=str(m.campaign_id),
        trial_id=int(m.trial_id),
        attempt=int(m.attempt),
        j=float(m.j),
        rms_accel_z=float(m.rms_accel_z),
        rms_pitch_rate=float(m.rms_pitch_rate),
        kpi=str(m.kpi),
        psd_frequency_hz=_arr(m.psd_frequency_hz),
        psd_accel_z=_arr(m.psd_accel_z),
        psd_pitch_rate=_arr(m.psd_pitch_rate),
        valid=bool(m.valid),
        reason=str(m.reason),
    )


def calibration_from_msg(m: Any) -> CalibrationView:
    return CalibrationView(
        trial_id=int(m.trial_id),
        params={str(n): float(v) for n, v in zip(m.names, m.values, strict=False)},
        crc32=int(m.crc32),
    )


def diagnostics_from_msg(m: Any) -> list[DiagView]:
    out = []
    for st in m.status:
        level = st.level
        level_i = level[0] if isinstance(level, bytes | bytearray) else int(level)
        out.append(
            DiagView(
                name=str(st.name),
                level=int(level_i),
                message=str(st.message),
                hardware_id=str(st.hardware_id),
                values={str(kv.key): str(kv.value) for kv in st.values},
            )
        )
    return out


# --- helpers ----------------------------------------------------------------------------------------------------


def decimate(x: FloatArray, max_points: int = MAX_SIGNAL_POINTS) -> tuple[FloatArray, int]:
    """At most ``max_points`` samples for a plot, peaks kept: the min and max of each bucket, in order.
    Returns (samples, stride in input samples per output pair) -- stride 1 when nothing was dropped."""
    n = x.size
    if n <= max_points:
        return x, 1
    pairs = max(1, max_points // 2)
    stride = math.ceil(n / pairs)
    pad = (-n) % stride
    xp = np.concatenate([x, np.full(pad, np.nan)]) if pad else x
    blocks = xp.reshape(-1, stride)
    with np.errstate(all="ignore"):
        lo_i = np.nanargmin(np.where(np.isnan(blocks), np.inf, blocks), axis=1)
        hi_i = np.nanargmax(np.where(np.isnan(blocks), -np.inf, blocks), axis=1)
    first = np.minimum(lo_i, hi_i)
    second = np.maximum(lo_i, hi_i)
    rows = np.arange(blocks.shape[0])
    out = np.empty(2 * blocks.shape[0])
    out[0::2] = blocks[rows, first]
    out[1::2] = blocks[rows, second]
    return out, stride


def _round(values: Iterable[float] | FloatArray, digits: int = 6) -> list[float | None]:
    """JSON numbers with ``digits`` significant digits, each its own (spectra span decades); non-finite: None."""
    x = np.asarray(values, dtype=np.float64).ravel()
    finite = np.isfinite(x)
    with np.errstate(all="ignore"):
        mag = np.floor(np.log10(np.where(finite & (x != 0.0), np.abs(x), 1.0)))
        scale = 10.0 ** (digits - 1 - mag)
        r = np.where(finite, np.round(x * scale) / scale, 0.0)
    out: list[float | None] = r.tolist()
    if not finite.all():
        for i in np.flatnonzero(~finite):
            out[int(i)] = None
    return out


def signal_view(seg: SegmentView, j: float | None, label: str, max_points: int = MAX_SIGNAL_POINTS) -> dict[str, Any]:
    """The aligned signals of one run for a plot: time in the window (s) and both channels, decimated alike."""
    rate = seg.sample_rate_hz if seg.sample_rate_hz > 0 else 1.0
    az, stride = decimate(seg.accel_z, max_points)
    q, _ = decimate(seg.pitch_rate, max_points)
    if stride == 1:
        t = np.arange(seg.accel_z.size) / rate
    else:  # each (min, max) pair sits at its bucket's start and middle
        starts = np.arange(0, seg.accel_z.size, stride, dtype=float)
        t = np.empty(2 * starts.size)
        t[0::2] = starts
        t[1::2] = starts + stride / 2
        t = t[: az.size] / rate
    return {
        "label": label,
        "trial_id": seg.trial_id,
        "attempt": seg.attempt,
        "valid": seg.valid,
        "reason": seg.reason,
        "j": finite_or_none(j),
        "rate_hz": finite_or_none(seg.sample_rate_hz),
        "mode": "distance" if seg.mode == 1 else "event",
        "mean_speed_mps": finite_or_none(seg.mean_speed_mps),
        "alignment_score": finite_or_none(seg.alignment_score),
        "t": _round(t, 6),
        "accel_z": _round(az, 5),
        "pitch_rate": _round(q, 5),
        "decimated": stride > 1,
    }


def spectrum_view(score: ScoreView | None, seg: SegmentView | None, label: str) -> dict[str, Any] | None:
    """Welch spectra of a run: the scorer's when it sent them, else computed from the aligned signals."""
    f: FloatArray
    pa: FloatArray
    pq: FloatArray
    source = "kpi_scorer"
    if score is not None and score.psd_frequency_hz.size > 1:
        f, pa, pq = score.psd_frequency_hz, score.psd_accel_z, score.psd_pitch_rate
    elif seg is not None and seg.valid and seg.accel_z.size > 8 and seg.sample_rate_hz > 0:
        from bac_measure.kpi import welch_psd

        seg_s = min(2.0, seg.accel_z.size / seg.sample_rate_hz)
        f, pa = welch_psd(seg.accel_z, seg.sample_rate_hz, seg_s, 50.0)
        _, pq = welch_psd(seg.pitch_rate, seg.sample_rate_hz, seg_s, 50.0)
        source = "welch_psd"
    else:
        return None
    keep = f > 0  # a log axis: the DC bin is left out
    trial_id = score.trial_id if score is not None else (seg.trial_id if seg is not None else 0)
    return {
        "label": label,
        "trial_id": trial_id,
        "source": source,
        "f": _round(f[keep], 6),
        "accel_z": _round(pa[keep], 5),
        "pitch_rate": _round(pq[keep], 5),
    }


# --- the state ------------------------------------------------------------------------------------------------


@dataclass
class TrialRow:
    """One trial as the page lists it (the same fields as ``bac_campaign.report.TrialRow``)."""

    trial_id: int
    kind: int
    params: dict[str, float]
    j: float = math.nan
    predicted_j: float = math.nan
    predicted_std: float = math.nan
    attempts: int = 0
    status: str = "proposed"  # proposed / scored / failed
    reason: str = ""
    rejected: list[tuple[int, str]] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        return {
            "trial_id": self.trial_id,
            "kind": KIND_NAMES.get(self.kind, str(self.kind)),
            "params": {k: finite_or_none(v) for k, v in self.params.items()},
            "j": finite_or_none(self.j),
            "predicted_j": finite_or_none(self.predicted_j),
            "predicted_std": finite_or_none(self.predicted_std),
            "attempts": self.attempts,
            "status": self.status,
            "reason": self.reason,
            "rejected": [[a, r] for a, r in self.rejected],
        }


class CockpitState:
    """The cockpit's state (see the module doc). Not thread-safe: one owner feeds it (the server's loop)."""

    def __init__(self, mode: str = "live", max_signal_points: int = MAX_SIGNAL_POINTS) -> None:
        self.mode = mode
        self.max_signal_points = max_signal_points
        self.version = 0
        self.campaign: dict[str, Any] = {}
        self.trial: TrialView | None = None
        self.trial_received_wall = math.nan
        self.rows: dict[int, TrialRow] = {}
        self.rows_from_journal = False
        self.recommendation: dict[str, Any] | None = None
        self.target_speed_mps = math.nan
        self.segment_mode = ""
        self.section_m: tuple[float, float] | None = None
        self.segments: dict[int, SegmentView] = {}  # the last valid segment of each trial
        self.last_segment: SegmentView | None = None
        self.scores: dict[tuple[int, int], ScoreView] = {}
        self.calibration: CalibrationView | None = None
        self.last_apply: dict[str, Any] | None = None
        self.diag: dict[str, tuple[DiagView, float]] = {}
        self.model: dict[str, Any] | None = None
        self._signals_key: tuple[Any, ...] = ()
        self._views: dict[tuple[Any, ...], dict[str, Any] | None] = {}  # signal and spectrum views, by run

    # --- inputs ---------------------------------------------------------------------------------------------
    def set_campaign_info(self, info: Mapping[str, Any]) -> list[str]:
        if dict(info) == self.campaign:
            return []
        self.campaign = dict(info)
        return self._bump(["campaign"])

    def set_speed_config(self, target_speed_mps: float, mode: str, section_m: tuple[float, float] | None) -> list[str]:
        self.target_speed_mps = float(target_speed_mps)
        self.segment_mode = mode
        self.section_m = section_m
        return self._bump(["speed"])

    def set_rows(
        self,
        rows: Sequence[TrialRow],
        recommendation: Mapping[str, Any] | None,
        last_apply: Mapping[str, Any] | None = None,
    ) -> list[str]:
        """The trials as the journal has them (the journal is the record: it replaces what the topics built)."""
        new = {r.trial_id: r for r in rows}
        changed: list[str] = []
        if not self.rows_from_journal or _rows_json(new) != _rows_json(self.rows):
            self.rows = new
            self.rows_from_journal = True
            changed.append("trials")
        rec = dict(recommendation) if recommendation else None
        if rec != self.recommendation:
            self.recommendation = rec
            changed.append("recommendation")
        if last_apply is not None and dict(last_apply) != self.last_apply:
            self.last_apply = dict(last_apply)
            changed.append("ecu")
        if "trials" in changed:
            changed += self._refresh_signals()
        return self._bump(changed)

    def on_trial(self, t: TrialView, wall: float | None = None) -> list[str]:
        self.trial = t
        self.trial_received_wall = time.time() if wall is None else wall
        changed = ["trial"]
        if t.trial_id > 0:  # at once from the message; the journal (read after it) is the record that confirms it
            changed += self._row_from_trial(t)
        if t.state == STATE_DONE and t.params:
            rec = {
                "params": dict(t.params),
                "predicted_j": finite_or_none(t.predicted_j),
                "predicted_std": finite_or_none(t.predicted_j_std),
            }
            if self.recommendation is None:
                self.recommendation = rec
                changed.append("recommendation")
        return self._bump(changed)

    def _row_from_trial(self, t: TrialView) -> list[str]:
        """The trial's row as bac/trial tells it (the whole table when there is no journal)."""
        row = self.rows.get(t.trial_id)
        if t.state == STATE_DONE:
            return []
        before = row.as_json() if row is not None else None
        if row is None:
            row = TrialRow(
                t.trial_id, t.kind, dict(t.params), predicted_j=t.predicted_j, predicted_std=t.predicted_j_std
            )
            self.rows[t.trial_id] = row
        name = STATE_NAMES.get(t.state, "")
        # each field as the journal has it at that point (the journal, read next, then finds nothing to change)
        if name == "READY_TO_DRIVE":
            row.attempts = max(row.attempts, t.attempt)
        elif name == "SCORED":
            # the run's own score when it came (a confirmation run's J is not the message's last_j)
            sc = self.scores.get((t.trial_id, t.attempt))
            j = sc.j if sc is not None and sc.valid else (t.last_j if t.kind != KIND_CONFIRMATION else math.nan)
            if math.isfinite(j):
                row.j, row.status = j, "scored"
        elif name == "REJECTED" and (t.attempt, t.reason) not in row.rejected:
            row.rejected.append((t.attempt, t.reason))
        elif name == "FAILED":
            row.status, row.reason = "failed", t.reason
        if row.as_json() == before:
            return []
        return ["trials", *self._refresh_signals()]

    def on_segment(self, s: SegmentView) -> list[str]:
        if self.campaign.get("campaign_id") and s.campaign_id and s.campaign_id != self.campaign["campaign_id"]:
            return []
        self.last_segment = s
        if s.valid and s.accel_z.size:
            self.segments[s.trial_id] = s
        changed = []
        if s.target_speed_mps > 0 and s.target_speed_mps != self.target_speed_mps:
            self.target_speed_mps = s.target_speed_mps
        changed.append("speed")
        changed += self._refresh_signals(force=True)
        return self._bump(changed)

    def on_score(self, s: ScoreView) -> list[str]:
        if self.campaign.get("campaign_id") and s.campaign_id and s.campaign_id != self.campaign["campaign_id"]:
            return []
        self.scores[(s.trial_id, s.attempt)] = s
        return self._bump(self._refresh_signals(force=True))

    def on_calibration(self, c: CalibrationView) -> list[str]:
        self.calibration = c
        return self._bump(["ecu"])

    def on_diagnostics(self, statuses: Iterable[DiagView], wall: float | None = None) -> list[str]:
        now = time.time() if wall is None else wall
        changed = False
        for st in statuses:
            changed = True
            self.diag[st.name] = (st, now)
        return self._bump(["ecu", "imu", "diagnostics"] if changed else [])

    def set_model(self, model: Mapping[str, Any] | None) -> list[str]:
        self.model = dict(model) if model is not None else None
        return self._bump(["model"])

    # --- derived --------------------------------------------------------------------------------------------
    def scored_rows(self, include_confirmation: bool = False) -> list[TrialRow]:
        return [
            r
            for r in sorted(self.rows.values(), key=lambda r: r.trial_id)
            if r.status == "scored" and math.isfinite(r.j) and (include_confirmation or r.kind != KIND_CONFIRMATION)
        ]

    def best_row(self) -> TrialRow | None:
        scored = self.scored_rows()
        return min(scored, key=lambda r: r.j) if scored else None

    def _refresh_signals(self, force: bool = False) -> list[str]:
        best = self.best_row()
        last = self.last_segment
        key = (
            best.trial_id if best else 0,
            (last.trial_id, last.attempt) if last else None,
            len(self.scores),
            best.trial_id in self.segments if best else False,
        )
        if key == self._signals_key and not force:
            return []
        self._signals_key = key
        return ["signals", "spectra"]

    def _score_of(self, seg: SegmentView | None) -> ScoreView | None:
        return self.scores.get((seg.trial_id, seg.attempt)) if seg is not None else None

    def _cached(self, key: tuple[Any, ...], make: Any) -> Any:
        if key not in self._views:
            if len(self._views) > 64:
                self._views.clear()
            self._views[key] = make()
        return self._views[key]

    def _signals(self) -> dict[str, Any]:
        last = self.last_segment
        best_row = self.best_row()
        best = self.segments.get(best_row.trial_id) if best_row else None
        out: dict[str, Any] = {"last": None, "best": None}
        if last is not None:
            sc = self._score_of(last)
            label = f"last run: trial {last.trial_id}" + (f" run {last.attempt}" if last.attempt > 1 else "")
            if not last.valid:
                label += " (rejected)"
            j = sc.j if sc is not None and sc.valid else None
            out["last"] = self._cached(
                ("sig", *_run_key(last), label, j), lambda: signal_view(last, j, label, self.max_signal_points)
            )
        if best is not None and best_row is not None:
            label_b, jb = f"best run: trial {best.trial_id}", best_row.j
            out["best"] = self._cached(
                ("sig", *_run_key(best), label_b, jb), lambda: signal_view(best, jb, label_b, self.max_signal_points)
            )
        return out

    def _spectra(self) -> dict[str, Any]:
        last = self.last_segment
        best_row = self.best_row()
        best = self.segments.get(best_row.trial_id) if best_row else None
        out: dict[str, Any] = {"last": None, "best": None}
        for key, seg, label in (("last", last, "last run"), ("best", best, "best run")):
            if seg is None:
                continue
            sc = self._score_of(seg)
            text = f"{label}: trial {seg.trial_id}"
            out[key] = self._cached(
                ("spec", *_run_key(seg), text, sc is not None),
                lambda sc=sc, seg=seg, text=text: spectrum_view(sc, seg, text),
            )
        return out

    def _diag_json(self, d: DiagView, wall: float, keys: Sequence[str] = ()) -> dict[str, Any]:
        shown = {k: d.values[k] for k in keys if k in d.values} if keys else dict(d.values)
        return {
            "name": d.name,
            "level": DIAG_LEVELS.get(d.level, str(d.level)),
            "message": d.message,
            "hardware_id": d.hardware_id,
            "values": shown,
            "age_s": max(0.0, time.time() - wall),
            "received_wall": wall,
        }

    def _find_diag(self, want: str) -> tuple[DiagView, float] | None:
        for name, item in self.diag.items():
            if (want == "ecu" and name.startswith("ecu_bridge")) or (want == "imu" and "imu" in name):
                return item
        return None

    def _ecu(self) -> dict[str, Any]:
        d = self._find_diag("ecu")
        cal = self.calibration
        return {
            "link": self._diag_json(*d, keys=ECU_KEYS) if d else None,
            "last_apply": self.last_apply,
            "holds": {"trial_id": cal.trial_id, "params": dict(cal.params), "crc32": f"0x{cal.crc32:08X}"}
            if cal is not None
            else None,
        }

    def _imu(self) -> dict[str, Any]:
        d = self._find_diag("imu")
        return {"stream": self._diag_json(*d, keys=IMU_KEYS) if d else None}

    def _trial(self) -> dict[str, Any] | None:
        t = self.trial
        if t is None:
            headline, tone = HEADLINES[0]
            return {"state": 0, "state_name": "IDLE", "headline": headline, "tone": tone, "trial_id": 0}
        headline, tone = HEADLINES.get(t.state, (STATE_NAMES.get(t.state, str(t.state)), "info"))
        confirmation = t.kind == KIND_CONFIRMATION
        return {
            "campaign_id": t.campaign_id,
            "trial_id": t.trial_id,
            "attempt": t.attempt,
            "state": t.state,
            "state_name": STATE_NAMES.get(t.state, str(t.state)),
            "headline": headline,
            "tone": tone,
            "kind": KIND_NAMES.get(t.kind, str(t.kind)),
            "confirmation": confirmation,
            "params": {k: finite_or_none(v) for k, v in t.params.items()},
            "budget": t.budget,
            "trials_done": t.trials_done,
            "last_j": finite_or_none(t.last_j),
            "best_j": finite_or_none(t.best_j),
            "best_trial_id": t.best_trial_id,
            "predicted_j": finite_or_none(t.predicted_j),
            "predicted_j_std": finite_or_none(t.predicted_j_std),
            "instruction": t.instruction,
            "reason": t.reason,
            "stamp_s": t.stamp_s,
            "received_wall": self.trial_received_wall,
        }

    def _speed(self) -> dict[str, Any]:
        last = self.last_segment
        return {
            "target_mps": finite_or_none(self.target_speed_mps),
            "target_kmh": finite_or_none(self.target_speed_mps * 3.6),
            "mode": self.segment_mode or (("distance" if last.mode == 1 else "event") if last else ""),
            "section_m": list(self.section_m) if self.section_m else None,
            "last_mean_kmh": finite_or_none(last.mean_speed_mps * 3.6) if last is not None else None,
            "last_trial_id": last.trial_id if last is not None else None,
            "last_valid": last.valid if last is not None else None,
            "last_reason": last.reason if last is not None else "",
        }

    def _best(self) -> dict[str, Any] | None:
        b = self.best_row()
        return {"trial_id": b.trial_id, "j": finite_or_none(b.j), "params": dict(b.params)} if b else None

    def part(self, key: str) -> Any:
        if key == "campaign":
            return self.campaign
        if key == "trial":
            return self._trial()
        if key == "speed":
            return self._speed()
        if key == "trials":
            return [r.as_json() for r in sorted(self.rows.values(), key=lambda r: r.trial_id)]
        if key == "best":
            return self._best()
        if key == "recommendation":
            return self.recommendation
        if key == "signals":
            return self._signals()
        if key == "spectra":
            return self._spectra()
        if key == "ecu":
            return self._ecu()
        if key == "imu":
            return self._imu()
        if key == "diagnostics":
            return [self._diag_json(d, w) for d, w in self.diag.values()]
        if key == "model":
            return self.model
        raise KeyError(key)

    KEYS = (
        "campaign",
        "trial",
        "speed",
        "trials",
        "best",
        "recommendation",
        "signals",
        "spectra",
        "ecu",
        "imu",
        "diagnostics",
        "model",
    )

    def patch(self, keys: Iterable[str]) -> dict[str, Any]:
        """The given top-level keys (``best`` goes with ``trials``), with the version and the mode."""
        ks = set(keys)
        if "trials" in ks:
            ks.add("best")
        out: dict[str, Any] = {k: self.part(k) for k in self.KEYS if k in ks}
        out["version"] = self.version
        out["mode"] = self.mode
        out["server_wall"] = time.time()
        return out

    def snapshot(self) -> dict[str, Any]:
        return self.patch(self.KEYS)

    def _bump(self, changed: list[str]) -> list[str]:
        out = list(dict.fromkeys(changed))
        if out:
            self.version += 1
        return out


def _run_key(seg: SegmentView) -> tuple[Any, ...]:
    return (seg.campaign_id, seg.trial_id, seg.attempt, seg.valid, seg.accel_z.size)


def _rows_json(rows: Mapping[int, TrialRow]) -> list[dict[str, Any]]:
    return [rows[k].as_json() for k in sorted(rows)]


__all__ = [
    "HEADLINES",
    "STATE_NAMES",
    "CalibrationView",
    "CockpitState",
    "DiagView",
    "ScoreView",
    "SegmentView",
    "TrialRow",
    "TrialView",
    "calibration_from_msg",
    "decimate",
    "diagnostics_from_msg",
    "finite_or_none",
    "score_from_msg",
    "segment_from_msg",
    "signal_view",
    "spectrum_view",
    "trial_from_msg",
]
