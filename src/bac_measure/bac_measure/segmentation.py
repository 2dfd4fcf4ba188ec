"""Run segmentation: "cut & align" of paper algorithm 1 (pure core of ``run_segmenter``).

A run is the IMU stream (``imu/vehicle``: vertical acceleration without
gravity, pitch rate, fixed rate) and the odometry (``vehicle/odom``, any
nav_msgs/Odometry: the pose's position, the forward speed ``twist.linear.x``)
buffered from the moment its trial became ready to drive. :func:`cut_run` cuts the segment of interest out of
it and aligns it with a reference run:

* **event** mode (a speed bump): the impact is the first sample whose
  ``|a_z|`` reaches ``trigger_threshold_mps2``; the window starts
  ``pre_trigger_s`` before it and lasts ``window_s``;
* **distance** mode (a test road): the section ``[distance_start_m,
  distance_end_m]`` of odometry, resampled on a distance grid (step
  ``distance_step_m``, by default the distance travelled at the target speed
  in one IMU sample), so that a run driven a little faster or slower is not
  stretched against the reference.

**The distance** is what ``distance_source`` says: ``path_length`` (the length of the path of the
pose, the sum of ``|Δ position|`` in x, y, z: any odometry after REP 105, wheel odometry,
robot_localization, a GNSS/INS driver), ``speed_integral`` (the integral of the forward speed
``twist.linear.x`` over the stamps: what a speed-only source gives) or ``position_x``
(``pose.position.x`` read as an odometer: bac's convention before 2026-11-24, a trip or cumulative
odometer). Path length and speed integral have no origin of their own: a drive's distance counts from
its start (``distance_origin`` applies to ``position_x`` only). Each drive's distance is summed from its
own first sample, so the live node and an offline tool given the same drive get the same distances,
bit for bit, whatever else they buffered.

**A run is one drive.** The odometry is split into drives: a drive begins where the distance
counter resets, where the odometry was silent for ``odom_gap_s``, or where the vehicle speeds up
through ``new_drive_speed_fraction`` of the target speed after being slower (a standstill, a turn:
the drive begins at its slowest point). For ``path_length`` a jump of the pose (a
step longer than ``ODOM_RESET_M`` plus twice what the speed allows: a reset of the odometry) also begins
a drive, and the jump is not counted. The run of an attempt is cut from the first drive that
holds the whole window after the attempt became ready to drive: for a first attempt that may be
the drive in progress (a rolling start), for a **retry** (``retry=True``) only a drive that began
after it, so the tail of an earlier run is never taken for the new one. A drive that began past
the section start, or ended before the window did, is passed over: the cut waits for the next
drive. In event mode the impact must also have a clean approach (no impact in the
``pre_trigger_s + max_lag_s`` before it, all within the drive and the attempt), so the second axle
or the ringing of an earlier impact is never a trigger.

Then the cut is refined by normalized cross-correlation with the reference
(the first valid run of the campaign, or a stored template) over
``+-max_lag_s`` (event) or ``+-max_shift_m`` (distance), to sub-sample lag
(parabolic peak), and the signals are re-sampled at the aligned positions
(cubic spline). The run is **invalid**, with its reason, when the IMU data
does not cover the window (gaps, NaN: ``min_coverage``), the mean speed is
off the target by more than ``speed_tolerance``, the alignment correlation
is below ``min_alignment`` or its peak sits at the edge of the search range,
or the window is not complete (what is awaited: :func:`run_status`).

:func:`cut_run` is a pure function of (buffered arrays, run start, config,
reference): the node calls it as soon as :func:`run_status` says the window
is complete, and an offline tool calling it on the whole recording gets the
same segment, bit for bit (``tests/measure/test_segmentation.py``).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import ndimage, signal

from bac_common.errors import BacError

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

NS = 1_000_000_000
MODE_EVENT = 0  # bac_msgs/RunSegment.MODE_EVENT
MODE_DISTANCE = 1  # bac_msgs/RunSegment.MODE_DISTANCE
MODES = {"event": MODE_EVENT, "distance": MODE_DISTANCE}
ALIGN_SIGNALS = ("accel_z", "pitch_rate", "both", "none")
DISTANCE_ORIGINS = ("odom", "run_start")
DISTANCE_SOURCES = ("position_x", "path_length", "speed_integral")
ODOM_RESET_M = 1.0  # a drop of pose.x (position_x), or a pose jump beyond what the speed allows (path_length), larger
# than this is a reset (a new drive)
SPLINE_MARGIN = 16  # samples around a re-sampled window (the cubic prefilter's support, to 1e-9)
RATE_PROBE = 200  # stamp steps used to measure the IMU rate when it is not configured


class SegmentationError(BacError, ValueError):
    """Bad configuration, malformed arrays, or a reference that does not fit the configuration."""


@dataclass(frozen=True)
class RunId:
    """A run: one attempt of one trial of a campaign (RunSegment / RunScore carry it)."""

    campaign_id: str = ""
    trial_id: int = 0
    attempt: int = 0

    def __str__(self) -> str:
        return f"{self.campaign_id or '-'}/trial {self.trial_id}/attempt {self.attempt}"


@dataclass(frozen=True)
class ImuSeries:
    """``imu/vehicle`` samples: stamps (ns), vertical acceleration (m/s^2), pitch rate (rad/s)."""

    stamp_ns: IntArray
    accel_z: FloatArray
    pitch_rate: FloatArray

    def __post_init__(self) -> None:
        t = np.asarray(self.stamp_ns, dtype=np.int64).reshape(-1)
        az = np.asarray(self.accel_z, dtype=np.float64).reshape(-1)
        q = np.asarray(self.pitch_rate, dtype=np.float64).reshape(-1)
        if not (t.shape == az.shape == q.shape):
            raise SegmentationError(f"IMU arrays differ in length: {t.shape}, {az.shape}, {q.shape}")
        object.__setattr__(self, "stamp_ns", t)
        object.__setattr__(self, "accel_z", az)
        object.__setattr__(self, "pitch_rate", q)

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])

    @staticmethod
    def empty() -> ImuSeries:
        return ImuSeries(np.zeros(0, np.int64), np.zeros(0), np.zeros(0))


@dataclass(frozen=True)
class OdomSeries:
    """``vehicle/odom`` samples (nav_msgs/Odometry): stamps (ns), ``pose.pose.position`` x, y, z (m) and the
    forward speed ``twist.twist.linear.x`` (m/s). ``distance_m`` is the position's x (bac's odometer with
    ``distance_source: position_x``); y and z default to 0."""

    stamp_ns: IntArray
    distance_m: FloatArray
    speed_mps: FloatArray
    position_y_m: FloatArray | None = None
    position_z_m: FloatArray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.stamp_ns, dtype=np.int64).reshape(-1)
        d = np.asarray(self.distance_m, dtype=np.float64).reshape(-1)
        v = np.asarray(self.speed_mps, dtype=np.float64).reshape(-1)
        y = np.zeros(t.shape) if self.position_y_m is None else np.asarray(self.position_y_m, np.float64).reshape(-1)
        z = np.zeros(t.shape) if self.position_z_m is None else np.asarray(self.position_z_m, np.float64).reshape(-1)
        if not (t.shape == d.shape == v.shape == y.shape == z.shape):
            raise SegmentationError(
                f"odometry arrays differ in length: {t.shape}, {d.shape}, {v.shape}, {y.shape}, {z.shape}"
            )
        object.__setattr__(self, "stamp_ns", t)
        object.__setattr__(self, "distance_m", d)
        object.__setattr__(self, "speed_mps", v)
        object.__setattr__(self, "position_y_m", y)
        object.__setattr__(self, "position_z_m", z)

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])

    @property
    def position(self) -> FloatArray:
        """(n, 3) pose positions, m."""
        y, z = self.position_y_m, self.position_z_m
        assert y is not None and z is not None  # set by __post_init__
        return np.column_stack([self.distance_m, y, z])

    @staticmethod
    def empty() -> OdomSeries:
        return OdomSeries(np.zeros(0, np.int64), np.zeros(0), np.zeros(0))


@dataclass(frozen=True)
class SegmentConfig:
    """How runs are cut, aligned and checked (the run_segmenter node's parameters, same names)."""

    mode: str = "event"  # "event" (speed bump) or "distance" (test road)
    target_speed_mps: float = 30.0 / 3.6  # the speed the run must be driven at, m/s
    speed_tolerance: float = 0.05  # accepted relative deviation of the mean speed from the target
    imu_rate_hz: float = 0.0  # rate of imu/vehicle, Hz; 0 = measured from its stamps
    align_signal: str = "both"  # cross-correlated with the reference: accel_z, pitch_rate, both, none (no refinement)
    min_alignment: float = 0.5  # minimum normalized cross-correlation with the reference
    min_coverage: float = 1.0  # minimum fraction of the window with valid IMU samples (1 = every sample)
    max_mean_accel_z: float = 1.0  # |mean a_z| over the window beyond this: gravity is in it (wrong mount), m/s^2
    pre_roll_s: float = 5.0  # a_z before the window kept for the scorer's Wk filter (not from rest), s; 0 = none
    # event mode
    trigger_threshold_mps2: float = 1.0  # |a_z| that marks the impact, m/s^2
    trigger_after_m: float = 0.0  # ignore impacts before this odometry distance, m
    pre_trigger_s: float = 0.3  # the window starts this long before the impact, s
    window_s: float = 2.5  # window length, s
    max_lag_s: float = 0.25  # alignment search range, +- s
    # distance mode
    distance_start_m: float = 100.0  # section start s0, odometry m
    distance_end_m: float = 1600.0  # section end s1, odometry m
    distance_step_m: float = 0.0  # distance grid step, m; 0 = target speed / IMU rate
    max_shift_m: float = 15.0  # alignment search range, +- m (covers the driver's start offset)
    distance_source: str = "position_x"  # position_x (pose.x as an odometer), path_length, speed_integral
    distance_origin: str = "odom"  # position_x: "odom": pose.x is the distance since the run started; "run_start":
    # subtract its value at the drive's start (path_length and speed_integral always count from the drive's start)
    # drives (a retry is a new drive)
    new_drive_speed_fraction: float = 0.5  # a drive begins where the speed rises through this fraction of the target
    odom_gap_s: float = 1.0  # odometry silent this long (stamps): what follows is a new drive

    def __post_init__(self) -> None:
        p = []
        if self.mode not in MODES:
            p.append(f"mode must be one of {tuple(MODES)}, got {self.mode!r}")
        if not (0.1 <= self.target_speed_mps <= 100.0):
            p.append(f"target_speed_mps must be in [0.1, 100], got {self.target_speed_mps}")
        if not (0.0 < self.speed_tolerance < 1.0):
            p.append(f"speed_tolerance must be in (0, 1), got {self.speed_tolerance}")
        if not (self.imu_rate_hz == 0.0 or 1.0 <= self.imu_rate_hz <= 10_000.0):
            p.append(f"imu_rate_hz must be 0 (measure) or in [1, 10000], got {self.imu_rate_hz}")
        if self.align_signal not in ALIGN_SIGNALS:
            p.append(f"align_signal must be one of {ALIGN_SIGNALS}, got {self.align_signal!r}")
        if not (-1.0 <= self.min_alignment <= 1.0):
            p.append(f"min_alignment must be in [-1, 1], got {self.min_alignment}")
        if not (0.0 < self.min_coverage <= 1.0):
            p.append(f"min_coverage must be in (0, 1], got {self.min_coverage}")
        if not self.max_mean_accel_z > 0:
            p.append(f"max_mean_accel_z must be > 0, got {self.max_mean_accel_z}")
        if not (0.0 <= self.pre_roll_s <= 60.0):
            p.append(f"pre_roll_s must be in [0, 60], got {self.pre_roll_s}")
        if not self.trigger_threshold_mps2 > 0:
            p.append("trigger_threshold_mps2 must be > 0")
        if not (0.0 <= self.pre_trigger_s < self.window_s):
            p.append("pre_trigger_s must be >= 0 and shorter than window_s")
        if not (0.0 < self.window_s <= 600.0):
            p.append(f"window_s must be in (0, 600], got {self.window_s}")
        if not (0.0 <= self.max_lag_s <= 10.0):
            p.append(f"max_lag_s must be in [0, 10], got {self.max_lag_s}")
        if not (0.0 <= self.distance_start_m < self.distance_end_m):
            p.append("distance_start_m must be >= 0 and below distance_end_m")
        if self.distance_step_m < 0:
            p.append("distance_step_m must be >= 0 (0 = automatic)")
        if not (0.0 <= self.max_shift_m <= 1000.0):
            p.append(f"max_shift_m must be in [0, 1000], got {self.max_shift_m}")
        if self.distance_source not in DISTANCE_SOURCES:
            p.append(f"distance_source must be one of {DISTANCE_SOURCES}, got {self.distance_source!r}")
        if self.distance_origin not in DISTANCE_ORIGINS:
            p.append(f"distance_origin must be one of {DISTANCE_ORIGINS}, got {self.distance_origin!r}")
        if not (0.0 < self.new_drive_speed_fraction < 1.0):
            p.append(f"new_drive_speed_fraction must be in (0, 1), got {self.new_drive_speed_fraction}")
        if not (self.odom_gap_s > 0.0):
            p.append(f"odom_gap_s must be > 0, got {self.odom_gap_s}")
        if p:
            raise SegmentationError("invalid segmentation configuration: " + "; ".join(p))

    @property
    def mode_id(self) -> int:
        return MODES[self.mode]

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> SegmentConfig:
        """Build from a node's parameters (``ros__parameters`` of run_segmenter); unknown keys are ignored."""
        config: SegmentConfig = from_params(cls, params)
        return config


def from_params(cls: Any, params: Mapping[str, Any]) -> Any:
    """Build the dataclass ``cls`` from a mapping of node parameters (same names; others ignored). A value of
    the wrong type (``detrend: "no"``, ``window_s: fast``) raises :class:`SegmentationError` naming it."""
    from bac_imu.ingest import typed_value

    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        if f.name in params:
            try:
                kwargs[f.name] = typed_value(f.name, params[f.name], f.default)
            except ValueError as exc:
                raise SegmentationError(f"{cls.__name__}: {exc}") from exc
    return cls(**kwargs)


@dataclass(frozen=True)
class Segment:
    """One run cut and aligned (the content of a bac_msgs/RunSegment)."""

    run: RunId
    mode: int  # MODE_EVENT or MODE_DISTANCE
    window_start_ns: int  # start of the window, ROS time (ns)
    window_length_s: float
    distance_start_m: float
    distance_step_m: float
    sample_rate_hz: float
    lag_s: float
    alignment_score: float
    mean_speed_mps: float
    target_speed_mps: float
    coverage: float
    accel_z: FloatArray = field(repr=False)
    pitch_rate: FloatArray = field(repr=False)
    valid: bool
    reason: str
    # a_z just before the window on the same grid (up to pre_roll_s, data of the same drive only): what the
    # scorer's Wk filter runs through first, so the window does not start from rest; may be empty
    pre_roll_accel_z: FloatArray = field(default_factory=lambda: np.zeros(0), repr=False)

    @property
    def window_start_s(self) -> float:
        return self.window_start_ns / NS

    def __len__(self) -> int:
        return int(self.accel_z.shape[0])


@dataclass(frozen=True)
class Progress:
    """Whether the buffered data holds everything the cut needs, and if not, what is awaited."""

    complete: bool
    waiting_for: str = ""


# --- the reference run -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Reference:
    """The aligned signals of the reference run (first valid run of a campaign, or a stored template)."""

    mode: int
    sample_rate_hz: float  # rate of the signals (distance mode: equivalent rate at the target speed)
    distance_step_m: float  # distance mode: grid step, m; event mode: 0
    accel_z: FloatArray = field(repr=False)
    pitch_rate: FloatArray = field(repr=False)
    run: RunId = RunId()
    key: Mapping[str, float] = field(default_factory=dict)  # settings a run must share to be aligned with it

    @staticmethod
    def key_for(config: SegmentConfig, sample_rate_hz: float, step_m: float) -> dict[str, float]:
        if config.mode == "event":
            return {
                "mode": MODE_EVENT,
                "sample_rate_hz": round(sample_rate_hz, 6),
                "samples": round(config.window_s * sample_rate_hz),
                "pre_trigger_s": config.pre_trigger_s,
            }
        return {
            "mode": MODE_DISTANCE,
            "distance_step_m": round(step_m, 9),
            "distance_start_m": config.distance_start_m,
            "distance_end_m": config.distance_end_m,
        }

    @classmethod
    def from_segment(cls, seg: Segment, config: SegmentConfig) -> Reference:
        if not seg.valid:
            raise SegmentationError(f"run {seg.run} is invalid ({seg.reason}); it cannot be a reference")
        return cls(
            mode=seg.mode,
            sample_rate_hz=seg.sample_rate_hz,
            distance_step_m=seg.distance_step_m,
            accel_z=seg.accel_z.copy(),
            pitch_rate=seg.pitch_rate.copy(),
            run=seg.run,
            key=cls.key_for(config, seg.sample_rate_hz, seg.distance_step_m),
        )

    def check(self, config: SegmentConfig, sample_rate_hz: float, step_m: float) -> None:
        """Raise :class:`SegmentationError` unless runs cut with ``config`` can be aligned with this reference."""
        want = self.key_for(config, sample_rate_hz, step_m)
        diff = {k: (self.key.get(k), v) for k, v in want.items() if self.key.get(k) != v}
        if diff:
            shown = ", ".join(f"{k}: reference {a}, now {b}" for k, (a, b) in diff.items())
            raise SegmentationError(
                f"the reference run ({self.run}) was cut with other settings ({shown}); "
                "delete the reference file or restore the settings"
            )

    def save(self, path: str | Path) -> None:
        """Write atomically (a crash never leaves half a reference)."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            "mode": self.mode,
            "sample_rate_hz": self.sample_rate_hz,
            "distance_step_m": self.distance_step_m,
            "run": [self.run.campaign_id, self.run.trial_id, self.run.attempt],
            "key": dict(self.key),
        }
        fd, tmp = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=p.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, accel_z=self.accel_z, pitch_rate=self.pitch_rate, meta=np.array(json.dumps(meta)))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | Path) -> Reference:
        p = Path(path)
        try:
            with np.load(p, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                az = np.asarray(data["accel_z"], dtype=np.float64)
                q = np.asarray(data["pitch_rate"], dtype=np.float64)
            run = RunId(str(meta["run"][0]), int(meta["run"][1]), int(meta["run"][2]))
            return cls(
                mode=int(meta["mode"]),
                sample_rate_hz=float(meta["sample_rate_hz"]),
                distance_step_m=float(meta["distance_step_m"]),
                accel_z=az,
                pitch_rate=q,
                run=run,
                key={str(k): float(v) for k, v in meta["key"].items()},
            )
        except FileNotFoundError as exc:
            raise SegmentationError(f"reference file not found: {p}") from exc
        except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
            raise SegmentationError(f"{p} is not a bac reference run file: {exc}") from exc


class ReferenceStore:
    """The reference of each campaign: the first valid run, kept in memory and, when a path is given, on disk.

    ``path`` may contain ``{campaign_id}``. A ``template`` (a stored reference) is used for every campaign
    and never replaced.
    """

    def __init__(self, path: str = "", template: Reference | None = None) -> None:
        self.path = path
        self.template = template
        self._refs: dict[str, Reference] = {}

    def file_for(self, campaign_id: str) -> Path | None:
        if not self.path:
            return None
        return Path(self.path.replace("{campaign_id}", campaign_id or "default"))

    def get(self, campaign_id: str) -> Reference | None:
        if self.template is not None:
            return self.template
        if campaign_id in self._refs:
            return self._refs[campaign_id]
        f = self.file_for(campaign_id)
        if f is not None and f.exists():
            self._refs[campaign_id] = Reference.load(f)
            return self._refs[campaign_id]
        return None

    def offer(self, seg: Segment, config: SegmentConfig) -> Reference | None:
        """Make ``seg`` the campaign's reference if it is valid and there is none yet; return it if so."""
        if not seg.valid or self.get(seg.run.campaign_id) is not None:
            return None
        ref = Reference.from_segment(seg, config)
        self._refs[seg.run.campaign_id] = ref
        f = self.file_for(seg.run.campaign_id)
        if f is not None:
            ref.save(f)
        return ref


# --- signal helpers -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Grid:
    """The IMU stream on a uniform time grid (NaN where no sample arrived)."""

    t0_ns: int
    step_ns: int
    az: FloatArray
    q: FloatArray

    @property
    def rate_hz(self) -> float:
        return NS / self.step_ns

    @property
    def n(self) -> int:
        return int(self.az.shape[0])

    def pos(self, t_ns: npt.ArrayLike) -> FloatArray:
        return np.asarray((np.asarray(t_ns, dtype=np.float64) - self.t0_ns) / self.step_ns, dtype=np.float64)

    def time_ns(self, pos: float) -> int:
        return self.t0_ns + round(pos * self.step_ns)


def imu_rate(imu: ImuSeries, configured_hz: float = 0.0) -> float:
    """The IMU rate: configured, else 1 / median of the first stamp steps."""
    if configured_hz > 0:
        return configured_hz
    steps = np.diff(np.sort(imu.stamp_ns[: RATE_PROBE + 1]))
    steps = steps[steps > 0]
    if steps.size == 0:
        raise SegmentationError("cannot measure the IMU rate: fewer than two distinct stamps")
    return NS / float(np.median(steps))


def _grid(imu: ImuSeries, rate_hz: float) -> _Grid:
    step = round(NS / rate_hz)
    order = np.argsort(imu.stamp_ns, kind="stable")
    t = imu.stamp_ns[order]
    t0 = int(t[0])
    idx = np.rint((t - t0) / step).astype(np.int64)
    n = int(idx[-1]) + 1
    az = np.full(n, np.nan)
    q = np.full(n, np.nan)
    az[idx] = imu.accel_z[order]
    q[idx] = imu.pitch_rate[order]
    return _Grid(t0, step, az, q)


def _fill_nan(y: FloatArray) -> FloatArray:
    """Linear interpolation over NaN (constant at the ends); all-NaN stays NaN."""
    bad = ~np.isfinite(y)
    if not bad.any() or bad.all():
        return y
    k = np.arange(y.size)
    out = y.copy()
    out[bad] = np.interp(k[bad], k[~bad], y[~bad])
    return out


def _resample(y: FloatArray, pos: FloatArray, fill: bool) -> FloatArray:
    """Cubic-spline values of the uniform signal ``y`` at fractional positions ``pos``."""
    lo = max(math.floor(float(pos.min())) - SPLINE_MARGIN, 0)
    hi = min(math.ceil(float(pos.max())) + SPLINE_MARGIN + 1, y.size)
    seg = y[lo:hi]
    if fill:
        seg = _fill_nan(seg)
    if not np.all(np.isfinite(seg)):
        # no spline across missing data: linear, NaN where a neighbour is missing
        k = np.arange(lo, hi, dtype=np.float64)
        return np.asarray(np.interp(pos, k, seg), dtype=np.float64)
    return np.asarray(ndimage.map_coordinates(seg, [pos - lo], order=3, mode="nearest"), dtype=np.float64)


def _linear(y: FloatArray, pos: FloatArray) -> FloatArray:
    k = np.arange(y.size, dtype=np.float64)
    return np.asarray(np.interp(pos, k, _fill_nan(y)), dtype=np.float64)


def normalized_xcorr(x: FloatArray, r: FloatArray) -> FloatArray:
    """Normalized cross-correlation of ``r`` (length N) with every window ``x[k:k+N]``.

    Returns len(x) - N + 1 values in [-1, 1] (NaN where a window or ``r`` is constant).
    """
    n = r.size
    r0 = r - r.mean()
    rn = math.sqrt(_dot(r0, r0))
    num = signal.correlate(x, r0, mode="valid", method="fft" if x.size * n > 200_000 else "direct")
    c1 = np.cumsum(np.concatenate([[0.0], x]))
    c2 = np.cumsum(np.concatenate([[0.0], x * x]))
    s1 = c1[n:] - c1[:-n]
    s2 = c2[n:] - c2[:-n]
    var = s2 - s1 * s1 / n
    den = rn * np.sqrt(np.maximum(var, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(den > 1e-12 * max(rn, 1e-300), num / den, np.nan)
    return np.asarray(out, dtype=np.float64)


def _peak(c: FloatArray) -> tuple[float, bool]:
    """Sub-sample position of the maximum (parabolic), and whether it lies on the search edge."""
    if not np.any(np.isfinite(c)):
        return math.nan, True
    k = int(np.nanargmax(c))
    if k == 0 or k == c.size - 1:
        return float(k), True
    a, b, d = float(c[k - 1]), float(c[k]), float(c[k + 1])
    den = a - 2 * b + d
    delta = 0.5 * (a - d) / den if den < 0 else 0.0
    return k + min(max(delta, -0.5), 0.5), False


def _dot(x: FloatArray, y: FloatArray) -> float:
    """Dot product without BLAS: OpenBLAS threads make np.dot 100x slower on a loaded 2-core machine."""
    return float(np.einsum("i,i->", x, y))


def _corr(x: FloatArray, y: FloatArray) -> float:
    x0, y0 = x - x.mean(), y - y.mean()
    den = math.sqrt(_dot(x0, x0) * _dot(y0, y0))
    return _dot(x0, y0) / den if den > 0 else math.nan


def _alignment_curves(config: SegmentConfig, pairs: list[tuple[FloatArray, FloatArray]]) -> FloatArray:
    """Average normalized cross-correlation over the chosen signals: pairs of (run, reference)."""
    names = ["accel_z", "pitch_rate"]
    use = [i for i, nme in enumerate(names) if config.align_signal in (nme, "both")]
    curves = [normalized_xcorr(pairs[i][0], pairs[i][1]) for i in use]
    return np.asarray(np.mean(curves, axis=0), dtype=np.float64)


def _align_peak(
    config: SegmentConfig, g: _Grid, pos: FloatArray, ref: Reference, half: int, reasons: list[str], at_edge: str
) -> float:
    """The run's samples at grid positions ``pos`` (``2 * half + n``) against the reference: the best offset
    (``half`` = none); a flat or missing signal, or a peak at the edge of the search, is added to ``reasons``."""
    curve = _alignment_curves(config, [(_linear(g.az, pos), ref.accel_z), (_linear(g.q, pos), ref.pitch_rate)])
    k, edge = _peak(curve)
    if not math.isfinite(k):
        reasons.append("alignment failed: the signals are flat or missing")
        return float(half)
    if edge and half > 0:
        reasons.append(at_edge)
    return k


def _final_score(config: SegmentConfig, az: FloatArray, q: FloatArray, ref: Reference) -> float:
    scores = []
    if config.align_signal in ("accel_z", "both", "none"):
        scores.append(_corr(az, ref.accel_z))
    if config.align_signal in ("pitch_rate", "both", "none"):
        scores.append(_corr(q, ref.pitch_rate))
    return float(np.mean(scores))


# --- odometry: drives ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Drive:
    """One drive as the odometry shows it, from where the run may use it."""

    t: FloatArray  # stamps (ns, as float), increasing, none before the run's start
    d: FloatArray  # distance (m), non-decreasing: the odometer's (origin odom) or since the drive's origin
    v: FloatArray  # speed (m/s)
    t_begin: float  # the run may use data from this stamp on (the run's start, or the drive's first sample)
    ended: bool  # a later drive began: no more data of this one will come
    rolling: bool  # it began before the run's start (a first attempt may use it from there)


def drive_starts(
    t: IntArray, d: FloatArray, v: FloatArray, config: SegmentConfig, resets: IntArray | None = None
) -> IntArray:
    """Indices (into time-sorted odometry) where a drive begins; 0 is always one.

    A drive begins at a reset of the distance counter (``resets``; by default where ``d``, pose.x, drops by more
    than ``ODOM_RESET_M``), after odometry silent for ``odom_gap_s``, or at the slowest point (smallest
    ``|speed|``: a standstill, also between reversing and driving off) before the speed rises through
    ``new_drive_speed_fraction`` of the target speed.
    """
    n = t.size
    if n == 0:
        return np.zeros(0, np.int64)
    starts = {0}
    dt = np.diff(t)
    if resets is None:
        resets = np.flatnonzero(np.diff(d) < -ODOM_RESET_M) + 1
    starts.update(np.asarray(resets, np.int64).tolist())
    starts.update((np.flatnonzero(dt > config.odom_gap_s * NS) + 1).tolist())
    thr = config.new_drive_speed_fraction * config.target_speed_mps
    speed = np.abs(v)
    slow = speed < thr
    rises = np.flatnonzero(slow[:-1] & ~slow[1:]) + 1
    if rises.size:
        # the slow stretch before each rise begins after the last fast sample before it
        fast = np.flatnonzero(~slow)
        for i in rises.tolist():  # one per slowdown, not per sample
            k = int(np.searchsorted(fast, i)) - 1
            j = int(fast[k]) + 1 if k >= 0 else 0
            seg = speed[j:i]
            starts.add(j + int(seg.size - 1 - np.argmin(seg[::-1])))  # the last of its slowest samples
    return np.array(sorted(starts), dtype=np.int64)


def odometry_steps(
    odom: OdomSeries, config: SegmentConfig
) -> tuple[IntArray, FloatArray, FloatArray, IntArray, FloatArray]:
    """The odometry in stamp order as (stamps, pose.x, speed, resets) and the distance of each step ``i -> i + 1``
    by ``distance_source`` (n - 1 values; 0 across a silence of ``odom_gap_s`` and across a reset)::

        t, x, v, resets, steps = odometry_steps(odom, config)     # (t, x, v, resets) as sorted; steps: m

    ``position_x``: the steps of pose.x (resets: where it drops by more than ``ODOM_RESET_M``);
    ``path_length``: ``|Δ position|`` (resets: pose jumps longer than ``ODOM_RESET_M`` + twice the distance the
    speed allows); ``speed_integral``: the trapezoid of ``twist.linear.x`` over the stamps (no resets).
    """
    order = np.argsort(odom.stamp_ns, kind="stable")
    t, x, v = odom.stamp_ns[order], odom.distance_m[order], odom.speed_mps[order]
    if t.size < 2:
        return t, x, v, np.zeros(0, np.int64), np.zeros(0)
    dt_s = np.diff(t) / NS
    gap = dt_s > config.odom_gap_s
    src = config.distance_source
    if src == "position_x":
        steps = np.diff(x)
        reset = steps < -ODOM_RESET_M
    elif src == "path_length":
        steps = np.linalg.norm(np.diff(odom.position[order], axis=0), axis=1)
        reach = 2.0 * np.maximum(np.abs(v[:-1]), np.abs(v[1:])) * dt_s
        reset = steps > ODOM_RESET_M + reach
    else:
        steps = 0.5 * (v[:-1] + v[1:]) * dt_s
        reset = np.zeros(steps.shape, bool)
    steps = np.where(gap | reset, 0.0, steps)
    return t, x, v, np.asarray(np.flatnonzero(reset) + 1, dtype=np.int64), np.asarray(steps, dtype=np.float64)


def _drives(odom: OdomSeries, start_ns: int, config: SegmentConfig, retry: bool) -> list[_Drive]:
    """The drives a run starting at ``start_ns`` may be cut from, in order (see the module doc)."""
    t, x, v, resets, steps = odometry_steps(odom, config)
    starts = drive_starts(t, x, v, config, resets)
    bounds = [*starts.tolist(), int(t.size)]
    out: list[_Drive] = []
    for k in range(len(bounds) - 1):
        a, b = bounds[k], bounds[k + 1]
        if t[b - 1] < start_ns:
            continue  # over before the run started
        rolling = bool(t[a] < start_ns)
        if rolling and retry:
            continue  # a retry is a new drive: not the one in progress when it was announced
        first = int(np.searchsorted(t[a:b], start_ns)) + a if rolling else a
        if config.distance_source == "position_x":
            dd = x[first:b]
            if config.distance_origin == "run_start":
                dd = dd - dd[0]
        else:  # summed from the drive's (or the run's) first sample: the same whatever was buffered before
            dd = np.concatenate([[0.0], np.cumsum(steps[first : b - 1])])
        out.append(
            _Drive(
                t=t[first:b].astype(np.float64),
                d=np.maximum.accumulate(dd),
                v=v[first:b],
                t_begin=float(start_ns) if rolling else float(t[a]),
                ended=b < t.size,
                rolling=rolling,
            )
        )
    return out


def _distance_to_time(t: FloatArray, d: FloatArray, s: FloatArray) -> FloatArray:
    """Stamps (ns, float) at which the odometry reached distances ``s`` (linear between samples)."""
    keep = np.concatenate([[True], np.diff(d) > 0])  # strictly increasing distance for the inverse
    return np.asarray(np.interp(s, d[keep], t[keep]), dtype=np.float64)


# --- the cut -----------------------------------------------------------------------------------------


@dataclass
class _Plan:
    """What the cut needs, or what is missing, or why this drive cannot be the run (``skip``)."""

    missing: str = ""
    reasons: list[str] = field(default_factory=list)
    segment: Segment | None = None
    skip: str = ""


def _speed_reason(config: SegmentConfig, mean_speed: float) -> str:
    target = config.target_speed_mps
    if not math.isfinite(mean_speed):
        return "no odometry over the window: the mean speed is unknown"
    rel = mean_speed / target - 1.0
    if abs(rel) <= config.speed_tolerance:
        return ""
    word = "too slow" if rel < 0 else "too fast"
    return (
        f"{word}: mean speed {mean_speed * 3.6:.1f} km/h ({mean_speed:.2f} m/s) is {abs(rel) * 100:.1f} % "
        f"{'below' if rel < 0 else 'above'} the target {target * 3.6:.1f} km/h "
        f"(tolerance {config.speed_tolerance * 100:.0f} %)"
    )


def _coverage(g: _Grid, lo: float, hi: float) -> tuple[float, str]:
    """Fraction of IMU grid samples with data in [lo, hi] (positions), and where the holes are."""
    a = max(math.floor(lo), 0)
    b = min(math.ceil(hi) + 1, g.n)
    if b <= a:
        return 0.0, "no IMU samples in the window"
    ok = np.isfinite(g.az[a:b]) & np.isfinite(g.q[a:b])
    cov = float(np.count_nonzero(ok)) / (b - a)
    if cov >= 1.0:
        return 1.0, ""
    missing = np.flatnonzero(~ok)
    t_first = g.time_ns(a + int(missing[0])) / NS
    t_last = g.time_ns(a + int(missing[-1])) / NS
    return cov, (
        f"IMU data missing or invalid (gap, NaN/inf or saturation; see imu_ingest diagnostics) for "
        f"{missing.size / g.rate_hz:.3f} s of the window, between t = {t_first:.3f} s and {t_last:.3f} s"
    )


def _pre_roll(g: _Grid, pos: FloatArray) -> FloatArray:
    """a_z at the positions ``pos`` (increasing, before a window) where the grid has data: the finite samples
    after the last hole, cubic-spline re-sampled like the window."""
    pos = pos[pos >= 0.0]
    if pos.size < 2:
        return np.zeros(0)
    y = _resample(g.az, pos, fill=False)
    bad = np.flatnonzero(~np.isfinite(y))
    if bad.size:
        y = y[int(bad[-1]) + 1 :]
    return np.asarray(y, dtype=np.float64)


def _gravity_reason(config: SegmentConfig, az: FloatArray) -> str:
    m = float(np.nanmean(az)) if az.size and np.any(np.isfinite(az)) else 0.0
    if abs(m) <= config.max_mean_accel_z:
        return ""
    return (
        f"mean a_z {m:+.2f} m/s^2 over the window (limit {config.max_mean_accel_z:g}): gravity is in the vertical "
        "acceleration, the IMU's mount is wrong (see imu_ingest's /diagnostics: give the mount or record a "
        "standstill)"
    )


def _cut_event(g: _Grid, drive: _Drive, config: SegmentConfig, ref: Reference | None) -> _Plan:
    fs = g.rate_hz
    n = round(config.window_s * fs)
    pre = round(config.pre_trigger_s * fs)
    lag_max = round(config.max_lag_s * fs) if ref is not None else 0
    approach = pre + lag_max  # samples before the impact the window needs: they must be quiet and in the drive
    ot, od = drive.t, drive.d
    p_begin = max(float(g.pos(drive.t_begin)), 0.0)
    p_stop = float(g.pos(ot[-1])) if drive.ended else math.inf
    hits = np.abs(np.nan_to_num(g.az, nan=0.0)) >= config.trigger_threshold_mps2
    k = np.arange(g.n, dtype=np.float64)
    hits &= (k >= p_begin) & (k <= p_stop)
    trig = np.flatnonzero(hits)
    # a clean approach: no impact in the `approach` samples before it, all of them within the drive
    prev = np.concatenate([[-np.inf], trig[:-1].astype(np.float64)])
    clean = (trig - prev > approach) & (trig - approach >= p_begin)
    if config.trigger_after_m > 0 and trig.size:
        d_at = np.interp(g.t0_ns + trig * float(g.step_ns), ot, od, left=-math.inf, right=-math.inf)
        clean &= d_at >= config.trigger_after_m
    good = trig[clean]
    if good.size == 0:
        covered = g.n - 1 >= p_stop
        what = f"the impact (|a_z| >= {config.trigger_threshold_mps2:g} m/s^2) with a clean approach"
        if trig.size:
            what += (
                f" (the impact at t = {g.time_ns(int(trig[0])) / NS:.3f} s came too soon after the drive began or "
                "after another impact: the window needs "
                f"{config.pre_trigger_s + config.max_lag_s:.2f} s before it)"
            )
        if drive.ended and covered:
            return _Plan(skip=f"the drive ended without {what}")
        return _Plan(missing=what)
    i_trig = int(good[0])
    # sub-sample crossing of the threshold (linear between the samples around it)
    frac = 0.0
    if i_trig > 0:
        a0, a1 = abs(float(np.nan_to_num(g.az[i_trig - 1]))), abs(float(g.az[i_trig]))
        if a1 > a0:
            frac = min(max((config.trigger_threshold_mps2 - a0) / (a1 - a0), 0.0), 1.0) - 1.0
    i0 = i_trig + frac - pre  # fractional grid position of the nominal window start
    need = math.ceil(i0) + n + lag_max + SPLINE_MARGIN + 2
    t_end_needed = g.t0_ns + (i0 + n + lag_max) * float(g.step_ns)
    if drive.ended and ot[-1] < t_end_needed:
        return _Plan(skip=f"the drive ended {(t_end_needed - ot[-1]) / NS:.2f} s before the end of the window")
    if g.n < need:
        return _Plan(missing=f"IMU data up to t = {g.time_ns(need) / NS:.3f} s (end of the window)")
    if ot.size == 0 or ot[-1] < t_end_needed:
        return _Plan(missing=f"odometry up to t = {t_end_needed / NS:.3f} s (end of the window)")
    reasons: list[str] = []
    lag = 0.0
    score = 1.0
    if ref is not None:
        ref.check(config, fs, 0.0)
    if ref is not None and config.align_signal != "none":
        span = i0 - lag_max + np.arange(n + 2 * lag_max, dtype=np.float64)
        kk = _align_peak(
            config, g, span, ref, lag_max, reasons,
            f"alignment peak at the edge of the +-{config.max_lag_s:g} s search range: the run does not "
            "match the reference (increase max_lag_s if the impact detection is that uncertain)",
        )  # fmt: skip
        lag = kk - lag_max
    start = i0 + lag
    cov, hole = _coverage(g, start, start + n - 1)
    if cov < config.min_coverage:
        reasons.insert(0, hole)
    pos = start + np.arange(n, dtype=np.float64)
    az = _resample(g.az, pos, fill=cov >= config.min_coverage)
    q = _resample(g.q, pos, fill=cov >= config.min_coverage)
    k_pre = start - np.arange(round(config.pre_roll_s * fs), 0, -1, dtype=np.float64)
    pre_roll = _pre_roll(g, k_pre[k_pre >= p_begin])
    if ref is not None:
        score = _final_score(config, az, q, ref)
        if not (score >= config.min_alignment) and not any(r.startswith("alignment") for r in reasons):
            reasons.append(
                f"alignment correlation {score:.3f} below {config.min_alignment:.3f}: the run does not match "
                "the reference (another event, or a very different response)"
            )
    gravity = _gravity_reason(config, az)
    if gravity:
        reasons.append(gravity)
    t_start = g.t0_ns + start * g.step_ns
    t_end = t_start + n * g.step_ns
    d0, d1 = np.interp([t_start, t_end], ot, od)
    mean_speed = (d1 - d0) / (n / fs)
    speed = _speed_reason(config, mean_speed)
    if speed:
        reasons.append(speed)
    seg = Segment(
        run=RunId(),
        mode=MODE_EVENT,
        window_start_ns=round(t_start),
        window_length_s=n / fs,
        distance_start_m=float(d0),
        distance_step_m=0.0,
        sample_rate_hz=fs,
        lag_s=lag / fs,
        alignment_score=score,
        mean_speed_mps=float(mean_speed),
        target_speed_mps=config.target_speed_mps,
        coverage=cov,
        accel_z=az,
        pitch_rate=q,
        valid=not reasons,
        reason="; ".join(reasons),
        pre_roll_accel_z=pre_roll,
    )
    return _Plan(segment=seg)


def distance_step(config: SegmentConfig, imu_rate_hz: float) -> float:
    """The distance grid step, m: configured, else the distance covered at the target speed in one IMU sample."""
    return config.distance_step_m or config.target_speed_mps / imu_rate_hz


def _cut_distance(g: _Grid, drive: _Drive, config: SegmentConfig, ref: Reference | None) -> _Plan:
    ds = distance_step(config, g.rate_hz)
    fs_eq = config.target_speed_mps / ds
    n = round((config.distance_end_m - config.distance_start_m) / ds)
    m = round(config.max_shift_m / ds) if ref is not None else 0
    ot, od = drive.t, drive.d
    s0 = config.distance_start_m
    if od[0] > s0 - m * ds:
        return _Plan(
            skip=f"the drive {'in progress' if drive.rolling else 'that began'} at odometry {od[0]:.1f} m is past "
            f"the section start {s0 - m * ds:.1f} m (distance_start_m - max_shift_m)"
        )
    s_need = s0 + (n + m) * ds
    if ot.size < 2 or od[-1] < s_need:
        now = f"{od[-1]:.1f} m" if ot.size else "none yet"
        if drive.ended:
            return _Plan(skip=f"the drive ended at odometry {now}, before {s_need:.1f} m (the section end)")
        return _Plan(missing=f"odometry up to {s_need:.1f} m (now {now})")
    t_need = _distance_to_time(ot, od, np.array([s_need]))[0]
    p_need = (t_need - g.t0_ns) / g.step_ns + SPLINE_MARGIN + 2
    if g.n < p_need:
        return _Plan(missing=f"IMU data up to t = {g.time_ns(p_need) / NS:.3f} s (end of the section)")
    if (_distance_to_time(ot, od, np.array([s0 - m * ds]))[0] - g.t0_ns) / g.step_ns < 0:
        return _Plan(reasons=["the IMU stream starts after the section start: no data before the section"])
    reasons: list[str] = []
    shift = 0.0
    score = 1.0
    if ref is not None:
        ref.check(config, fs_eq, ds)
    if ref is not None and config.align_signal != "none":
        s_coarse = s0 + (np.arange(n + 2 * m, dtype=np.float64) - m) * ds
        p_coarse = (_distance_to_time(ot, od, s_coarse) - g.t0_ns) / g.step_ns
        k = _align_peak(
            config, g, p_coarse, ref, m, reasons,
            f"alignment peak at the edge of the +-{config.max_shift_m:g} m search range: the run does not "
            "match the reference, or the start offset is larger (increase max_shift_m)",
        )  # fmt: skip
        shift = (k - m) * ds
    s_fine = s0 + shift + np.arange(n, dtype=np.float64) * ds
    t_fine = _distance_to_time(ot, od, s_fine)
    pos = (t_fine - g.t0_ns) / g.step_ns
    cov, hole = _coverage(g, float(pos[0]), float(pos[-1]))
    if cov < config.min_coverage:
        reasons.insert(0, hole)
    az = _resample(g.az, pos, fill=cov >= config.min_coverage)
    q = _resample(g.q, pos, fill=cov >= config.min_coverage)
    s_pre = s_fine[0] - np.arange(round(config.pre_roll_s * fs_eq), 0, -1, dtype=np.float64) * ds
    s_pre = s_pre[s_pre >= od[0]]
    pre_roll = _pre_roll(g, (_distance_to_time(ot, od, s_pre) - g.t0_ns) / g.step_ns) if s_pre.size else np.zeros(0)
    if ref is not None:
        score = _final_score(config, az, q, ref)
        if not (score >= config.min_alignment) and not any(r.startswith("alignment") for r in reasons):
            reasons.append(
                f"alignment correlation {score:.3f} below {config.min_alignment:.3f}: the run does not match "
                f"the reference (wrong road section, or a start offset beyond the +-{config.max_shift_m:g} m "
                "of max_shift_m)"
            )
    gravity = _gravity_reason(config, az)
    if gravity:
        reasons.append(gravity)
    duration = (float(t_fine[-1]) - float(t_fine[0])) / NS
    mean_speed = (n - 1) * ds / duration if duration > 0 else math.nan
    speed = _speed_reason(config, mean_speed)
    if speed:
        reasons.append(speed)
    seg = Segment(
        run=RunId(),
        mode=MODE_DISTANCE,
        window_start_ns=round(float(t_fine[0])),
        window_length_s=duration + 1 / fs_eq,
        distance_start_m=float(s_fine[0]),
        distance_step_m=ds,
        sample_rate_hz=fs_eq,
        lag_s=shift / config.target_speed_mps,
        alignment_score=score,
        mean_speed_mps=float(mean_speed),
        target_speed_mps=config.target_speed_mps,
        coverage=cov,
        accel_z=az,
        pitch_rate=q,
        valid=not reasons,
        reason="; ".join(reasons),
        pre_roll_accel_z=pre_roll,
    )
    return _Plan(segment=seg)


def _plan(
    imu: ImuSeries,
    odom: OdomSeries,
    config: SegmentConfig,
    start_ns: int | None,
    ref: Reference | None,
    retry: bool = False,
) -> _Plan:
    if start_ns is not None:
        keep = imu.stamp_ns >= start_ns
        if not np.all(keep):
            imu = ImuSeries(imu.stamp_ns[keep], imu.accel_z[keep], imu.pitch_rate[keep])
    if len(imu) < 2:
        return _Plan(missing="IMU data (imu/vehicle)")
    if np.any(np.diff(imu.stamp_ns) < 0):
        return _Plan(reasons=["IMU stamps went backwards during the run (clock jump)"])
    g = _grid(imu, imu_rate(imu, config.imu_rate_hz))
    t0 = int(imu.stamp_ns[0]) if start_ns is None else start_ns
    drives = _drives(odom, t0, config, retry)
    passed: list[str] = []
    for drive in drives:
        plan = _cut_event(g, drive, config, ref) if config.mode == "event" else _cut_distance(g, drive, config, ref)
        if not plan.skip:
            return plan
        passed.append(plan.skip)
    if config.mode == "distance":
        what = "odometry of a drive from before the section start"
    else:
        what = f"the impact (|a_z| >= {config.trigger_threshold_mps2:g} m/s^2) in a drive"
    if retry:
        what += " begun after this retry was announced (the tail of an earlier run is not used)"
    if passed:
        what += f"; passed over: {passed[-1]}"
    elif not drives:
        what += "; no odometry of such a drive yet"
    return _Plan(missing=what)


def run_status(
    imu: ImuSeries,
    odom: OdomSeries,
    config: SegmentConfig,
    start_ns: int | None = None,
    reference: Reference | None = None,
    retry: bool = False,
) -> Progress:
    """Whether the buffered run holds all the data :func:`cut_run` needs (then cut it: nothing more changes it).

    ``retry``: the run is a retry of a trial (attempt > 1): it must come from a drive that began after
    ``start_ns``."""
    plan = _plan(imu, odom, config, start_ns, reference, retry)
    return Progress(complete=not plan.missing, waiting_for=plan.missing)


def cut_run(
    imu: ImuSeries,
    odom: OdomSeries,
    config: SegmentConfig,
    start_ns: int | None = None,
    reference: Reference | None = None,
    run: RunId | None = None,
    retry: bool | None = None,
) -> Segment:
    """Cut and align one run (see the module docstring). Never raises for bad data: the segment says why.

    ``start_ns``: the run start (the trial became ready to drive); samples before it are ignored, except
    that the odometry before it tells whether a drive was already in progress.
    ``reference``: align with it (None: this run is not aligned, lag 0, alignment score 1).
    ``retry``: the run must come from a drive that began after ``start_ns`` (default: ``run.attempt > 1``).
    Raises :class:`SegmentationError` only when ``reference`` does not fit ``config``.
    """
    if retry is None:
        retry = run is not None and run.attempt > 1
    plan = _plan(imu, odom, config, start_ns, reference, retry)
    rid = run or RunId()
    if plan.segment is not None:
        return _with_run(plan.segment, rid)
    reason = "; ".join(plan.reasons) or f"incomplete run: still waiting for {plan.missing}"
    return Segment(
        run=rid,
        mode=config.mode_id,
        window_start_ns=int(start_ns or (imu.stamp_ns[0] if len(imu) else 0)),
        window_length_s=0.0,
        distance_start_m=config.distance_start_m if config.mode == "distance" else 0.0,
        distance_step_m=0.0,
        sample_rate_hz=config.imu_rate_hz,
        lag_s=0.0,
        alignment_score=math.nan,
        mean_speed_mps=math.nan,
        target_speed_mps=config.target_speed_mps,
        coverage=0.0,
        accel_z=np.zeros(0),
        pitch_rate=np.zeros(0),
        valid=False,
        reason=reason,
    )


def _with_run(seg: Segment, run: RunId) -> Segment:
    return replace(seg, run=run)


def invalid_segment(config: SegmentConfig, run: RunId, start_ns: int, reason: str) -> Segment:
    """An invalid segment with only a reason (e.g. a run that timed out or was cancelled)."""
    seg = cut_run(ImuSeries.empty(), OdomSeries.empty(), config, start_ns=start_ns, run=run)
    return replace(seg, reason=reason)


def window_segment(
    imu: ImuSeries,
    start_ns: int | None = None,
    end_ns: int | None = None,
    imu_rate_hz: float = 0.0,
    run: RunId | None = None,
    min_coverage: float = 1.0,
) -> Segment:
    """A plain time window of an IMU stream as a segment (no alignment, no speed check): for scoring
    any recording, e.g. a bag that was not driven as a bac run.

    ``min_coverage`` as in :class:`SegmentConfig`: below it the segment is invalid, naming where the data is
    missing; at or above it the holes are bridged by linear interpolation (as :func:`cut_run` does)."""
    t = imu.stamp_ns
    keep = np.ones(t.shape, bool)
    if start_ns is not None:
        keep &= t >= start_ns
    if end_ns is not None:
        keep &= t <= end_ns
    sub = ImuSeries(t[keep], imu.accel_z[keep], imu.pitch_rate[keep])
    if len(sub) < 2:
        raise SegmentationError("the window holds fewer than two IMU samples")
    g = _grid(sub, imu_rate(sub, imu_rate_hz))
    cov, hole = _coverage(g, 0, g.n - 1)
    ok = cov >= min_coverage
    az, q = (_fill_nan(g.az), _fill_nan(g.q)) if ok else (g.az, g.q)
    if ok and hole:
        hole = ""
    return Segment(
        run=run or RunId(),
        mode=MODE_EVENT,
        window_start_ns=g.t0_ns,
        window_length_s=g.n / g.rate_hz,
        distance_start_m=0.0,
        distance_step_m=0.0,
        sample_rate_hz=g.rate_hz,
        lag_s=0.0,
        alignment_score=math.nan,
        mean_speed_mps=math.nan,
        target_speed_mps=math.nan,
        coverage=cov,
        accel_z=az,
        pitch_rate=q,
        valid=ok,
        reason="" if ok else f"{hole} (coverage {cov:.3f} below min_coverage {min_coverage:g})",
    )
