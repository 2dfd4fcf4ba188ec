"""IMU ingestion: the pure core of the ``imu_ingest`` node (no rclpy).

:class:`ImuIngestor` turns a raw IMU stream (driver frame, gravity included,
irregular stamps, possibly broken) into the stream the measurement chain uses:

1. **Sanity** of every sample: duplicated and out-of-order stamps are dropped,
   NaN/inf and saturated samples are marked bad, a gap longer than
   ``gap_threshold_s`` is a hole, a jump of the stamps by more than
   ``clock_jump_s`` backwards, or forwards while the receive clock did not
   move as much, is a clock jump; a longer silence is a stream restart
   (the stream stopped and resumed). Both restart the output grid.
2. **Mounting**: the rotation ``R`` from the sensor frame to the vehicle frame
   (x forward, y left, z up) comes from the configured roll/pitch/yaw, or
   roll and pitch are estimated from gravity over the first standstill window
   (yaw is not observable from gravity and stays configured).
3. **Bias and gravity**: gravity (the standstill's measured magnitude, else
   the nominal ``gravity``) is removed from the vertical axis; the gyro bias
   is the standstill mean (else zero). An optional high-pass removes slow
   drift from every axis.
4. **Resampling** to ``output_rate_hz`` on a grid anchored at the first
   sample: a causal Butterworth anti-alias low-pass at
   ``antialias_ratio`` of the output Nyquist frequency when the input is
   faster than the output, then linear interpolation. Grid points inside a
   hole (gap, NaN, saturation) are NaN: the output keeps its fixed rate and
   says honestly where no data is.

The core is streaming with explicit state: pushing a recording in chunks of
any size gives bit-for-bit the output of pushing it at once
(tests/imu/test_ingest.py checks it), so a bag replayed offline reproduces
the live stream.

Stamps are integer nanoseconds (ROS time), values SI units (m/s^2, rad/s).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import signal

from bac_common.errors import BacError

GRAVITY = 9.80665  # m/s^2, standard gravity
NS = 1_000_000_000

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

MOUNT_SOURCES = ("config", "standstill")
STANDSTILL_FALLBACKS = ("mean", "config")
BIAS_SOURCES = ("none", "standstill")
OFFSET_WARN_MPS2 = 0.1  # a mean a_z beyond this without a standstill bias: an offset that goes into RMS(a_z)
MOUNT_CHECK_S = 2.0  # the mean a_z is judged once this much output holds data


class IngestError(BacError, ValueError):
    """Bad configuration or malformed input arrays for the IMU ingestion."""


@dataclass(frozen=True)
class IngestConfig:
    """Everything the ingestion does, by configuration (the node's parameters, same names)."""

    output_rate_hz: float = 200.0  # rate of imu/vehicle, Hz
    input_rate_hz: float = 0.0  # nominal rate of imu/data_raw, Hz; 0 = measured from the first samples
    rate_probe_samples: int = 50  # samples used to measure the input rate when input_rate_hz = 0
    mount_source: str = "config"  # "config": mount_*_deg; "standstill": roll/pitch from gravity at standstill
    # without a standstill: "mean": what needs one (mount roll/pitch, bias) from the long-run mean of the
    # accelerometer and gyro over standstill_timeout_s; "config": the configured mount, nominal gravity, no gyro bias
    standstill_fallback: str = "mean"
    mount_roll_deg: float = 0.0  # sensor frame relative to the vehicle frame, intrinsic z-y-x (yaw, pitch, roll)
    mount_pitch_deg: float = 0.0
    mount_yaw_deg: float = 0.0
    bias_source: str = "none"  # "none": nominal gravity, no gyro bias; "standstill": both from the standstill
    standstill_s: float = 1.0  # length of the standstill window, s
    standstill_timeout_s: float = 30.0  # look for a standstill over this much data, then fall back, s
    standstill_accel_std: float = 0.08  # max std of each accelerometer axis at standstill, m/s^2
    standstill_gyro_std: float = 0.02  # max std of each gyro axis at standstill, rad/s
    gravity: float = GRAVITY  # nominal gravity removed from the vertical axis without a standstill, m/s^2
    accel_range: float = 156.9  # accelerometer full scale (a sample at or beyond it is saturated), m/s^2; 0 = off
    gyro_range: float = 34.9  # gyro full scale, rad/s; 0 = off
    gap_threshold_s: float = 0.0  # a stamp step above this is a gap; 0 = 2.5 nominal input periods
    clock_jump_s: float = 2.0  # a stamp jump beyond this is a clock jump (or a restart): the grid restarts
    antialias_ratio: float = 0.8  # anti-alias cutoff as a fraction of the output Nyquist frequency
    antialias_order: int = 8  # Butterworth order of the anti-alias filter (-48 dB an octave above the cutoff)
    highpass_hz: float = 0.0  # optional 2nd-order high-pass on every axis (drift), Hz; 0 = off
    health_window: int = 1000  # recent stamp steps used for rate and jitter; 0 = all (offline: the whole recording)
    max_mean_accel_z: float = 1.0  # |mean a_z| after gravity removal beyond this: gravity is not removed, m/s^2

    def __post_init__(self) -> None:
        problems = []
        if not (math.isfinite(self.output_rate_hz) and 1.0 <= self.output_rate_hz <= 10_000.0):
            problems.append(f"output_rate_hz must be in [1, 10000], got {self.output_rate_hz}")
        if not (self.input_rate_hz == 0.0 or 1.0 <= self.input_rate_hz <= 100_000.0):
            problems.append(f"input_rate_hz must be 0 (measure) or in [1, 100000], got {self.input_rate_hz}")
        if self.rate_probe_samples < 5:
            problems.append(f"rate_probe_samples must be >= 5, got {self.rate_probe_samples}")
        if self.mount_source not in MOUNT_SOURCES:
            problems.append(f"mount_source must be one of {MOUNT_SOURCES}, got {self.mount_source!r}")
        if self.standstill_fallback not in STANDSTILL_FALLBACKS:
            problems.append(
                f"standstill_fallback must be one of {STANDSTILL_FALLBACKS}, got {self.standstill_fallback!r}"
            )
        if self.bias_source not in BIAS_SOURCES:
            problems.append(f"bias_source must be one of {BIAS_SOURCES}, got {self.bias_source!r}")
        for name in ("mount_roll_deg", "mount_pitch_deg", "mount_yaw_deg"):
            if not (-180.0 <= getattr(self, name) <= 180.0):
                problems.append(f"{name} must be in [-180, 180] degrees")
        if not self.standstill_s > 0 or not self.standstill_timeout_s >= self.standstill_s:
            problems.append("standstill_s must be > 0 and standstill_timeout_s >= standstill_s")
        if not (self.standstill_accel_std > 0 and self.standstill_gyro_std > 0):
            problems.append("standstill_accel_std and standstill_gyro_std must be > 0")
        if not 5.0 <= self.gravity <= 15.0:
            problems.append(f"gravity must be in [5, 15] m/s^2, got {self.gravity}")
        if self.accel_range < 0 or self.gyro_range < 0:
            problems.append("accel_range and gyro_range must be >= 0 (0 = no saturation check)")
        if self.gap_threshold_s < 0:
            problems.append("gap_threshold_s must be >= 0 (0 = automatic)")
        if not self.clock_jump_s > 0:
            problems.append("clock_jump_s must be > 0")
        if not 0.05 <= self.antialias_ratio <= 0.95:
            problems.append(f"antialias_ratio must be in [0.05, 0.95], got {self.antialias_ratio}")
        if not 1 <= self.antialias_order <= 10:
            problems.append("antialias_order must be in [1, 10]")
        if self.highpass_hz < 0 or self.highpass_hz >= self.output_rate_hz / 4:
            problems.append("highpass_hz must be >= 0 and below a quarter of output_rate_hz")
        if self.health_window != 0 and self.health_window < 10:
            problems.append("health_window must be 0 (all) or >= 10")
        if not self.max_mean_accel_z > 0:
            problems.append("max_mean_accel_z must be > 0")
        if problems:
            raise IngestError("invalid IMU ingestion configuration: " + "; ".join(problems))

    @property
    def needs_standstill(self) -> bool:
        return self.mount_source == "standstill" or self.bias_source == "standstill"

    @classmethod
    def from_params(cls, params: dict[str, Any]) -> IngestConfig:
        """Build from a node's parameters (``ros__parameters`` of imu_ingest); unknown keys are ignored, a value
        of the wrong type raises :class:`IngestError` naming it."""
        known = {f.name: f for f in fields(cls)}
        kwargs: dict[str, Any] = {}
        for k, v in params.items():
            if k in known:
                try:
                    kwargs[k] = typed_value(k, v, known[k].default)
                except ValueError as exc:
                    raise IngestError(f"imu_ingest: {exc}") from exc
        return cls(**kwargs)


def typed_value(name: str, value: Any, default: Any) -> Any:
    """``value`` as the type of ``default`` (a parameter's declared type), strictly: a bool is true/false, a
    number a number (an int for an int parameter), a string a string; ValueError naming ``name`` otherwise."""
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            return value.strip().lower() == "true"
        raise ValueError(f"{name} must be true or false, got {value!r}")
    if isinstance(default, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if isinstance(default, float):
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                pass
        raise ValueError(f"{name} must be a number, got {value!r}")
    if isinstance(default, str):
        if isinstance(value, str):
            return value
        raise ValueError(f"{name} must be a string, got {value!r}")
    return value


def rotation_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> FloatArray:
    """Rotation taking sensor-frame vectors to the vehicle frame: ``v = R @ s``.

    The sensor frame is the vehicle frame rotated by yaw about z, then pitch
    about the new y, then roll about the new x (intrinsic z-y-x, ISO 8855).
    """
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return np.asarray(rz @ ry @ rx, dtype=np.float64)


def roll_pitch_from_gravity(accel_mean: npt.ArrayLike) -> tuple[float, float]:
    """Mount roll and pitch (degrees) from the mean accelerometer reading at standstill (sensor frame).

    At rest the sensor reads ``R.T @ (0, 0, g)`` = g * (-sin p, cos p sin r, cos p cos r).
    """
    a = np.asarray(accel_mean, dtype=np.float64)
    roll = math.atan2(float(a[1]), float(a[2]))
    pitch = math.atan2(-float(a[0]), math.hypot(float(a[1]), float(a[2])))
    return math.degrees(roll), math.degrees(pitch)


def _tilt_deg(v: FloatArray) -> float:
    """Angle between ``v`` and the +z axis, degrees."""
    n = float(np.linalg.norm(v))
    return math.degrees(math.acos(max(-1.0, min(1.0, float(v[2]) / n)))) if n > 0 else math.nan


def _rotate(R: FloatArray, x: FloatArray) -> FloatArray:
    """Rotate the accel and gyro triples of (n, 6) rows by R.

    Written out element-wise rather than with ``@``: BLAS sums in an order that depends on the
    number of rows, which would make a chunked stream differ from a one-shot one in the last bit.
    """
    v = np.empty_like(x)
    for base in (0, 3):
        for i in range(3):
            v[:, base + i] = R[i, 0] * x[:, base] + R[i, 1] * x[:, base + 1] + R[i, 2] * x[:, base + 2]
    return v


@dataclass(frozen=True)
class IngestOutput:
    """Samples on the output grid: vehicle frame, gravity removed from z, NaN where there is no data."""

    stamp_ns: IntArray  # (n,) int64, uniform step except across a restart
    accel: FloatArray  # (n, 3) m/s^2; accel[:, 2] = vertical acceleration without gravity
    gyro: FloatArray  # (n, 3) rad/s; gyro[:, 1] = pitch rate

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])

    @property
    def accel_z(self) -> FloatArray:
        return self.accel[:, 2]

    @property
    def pitch_rate(self) -> FloatArray:
        return self.gyro[:, 1]

    @staticmethod
    def empty() -> IngestOutput:
        return IngestOutput(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))

    @staticmethod
    def concatenate(parts: list[IngestOutput]) -> IngestOutput:
        if not parts:
            return IngestOutput.empty()
        return IngestOutput(
            np.concatenate([p.stamp_ns for p in parts]),
            np.concatenate([p.accel for p in parts]),
            np.concatenate([p.gyro for p in parts]),
        )


@dataclass(frozen=True)
class StreamEvent:
    """A fault of the raw stream, for the health report."""

    kind: str  # "gap", "nonfinite", "saturation", "duplicate", "out_of_order", "clock_jump", "restart", "no_standstill"
    start_ns: int  # stamp where it starts
    end_ns: int  # stamp where it ends (== start_ns for a single sample)
    detail: str

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / NS


@dataclass
class StreamHealth:
    """Cumulative health of the raw stream (a snapshot; see :meth:`ImuIngestor.health`)."""

    samples_in: int = 0  # messages received
    samples_used: int = 0  # samples that entered the output
    samples_out: int = 0  # output grid samples emitted (NaN ones included)
    samples_out_nan: int = 0  # output samples without data (holes)
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    nominal_rate_hz: float = 0.0  # the rate the filter was designed for (configured or measured at start)
    output_rate_hz: float = 0.0
    rate_hz: float = 0.0  # measured over the recent window (median step)
    jitter_ms: float = 0.0  # std of the recent stamp steps, ms
    max_step_ms: float = 0.0  # largest recent step (gaps excluded), ms
    arrival_jitter_ms: float = math.nan  # std of the recent receive-time steps, ms (NaN: no receive times)
    latency_ms: float = math.nan  # median of recent (receive time - stamp), ms (NaN: no receive times)
    gaps: int = 0
    gap_total_s: float = 0.0
    longest_gap_s: float = 0.0
    lost_samples: int = 0  # samples the nominal rate says are missing between received stamps (gaps included)
    nonfinite: int = 0
    saturated: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    clock_jumps: int = 0
    restarts: int = 0
    mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mount_source: str = "config"  # where R came from: "config", "standstill", "config (no standstill found)"
    gravity_mps2: float = GRAVITY
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bias_source: str = "none"
    standstill_window_ns: tuple[int, int] | None = None
    # gravity at standstill (or in the long-run mean) in the vehicle frame with the mount used: along +z when
    # the mount is right; NaN without either
    gravity_tilt_deg: float = math.nan
    mean_accel_mps2: tuple[float, float, float] = (math.nan, math.nan, math.nan)  # mean of the output (with data)
    mean_samples: int = 0  # output samples with data in that mean
    max_mean_accel_z: float = 1.0  # the limit of |mean a_z| (IngestConfig.max_mean_accel_z)
    health_window: int = 1000  # steps the rate and jitter figures cover (0: the whole stream)
    started: bool = False  # False while waiting for the rate probe or the standstill
    events: list[StreamEvent] = field(default_factory=list)  # most recent faults (bounded)

    @property
    def samples_expected(self) -> int:
        """Samples the nominal rate says should have arrived between the first and last stamp (restarts apart)."""
        return self.samples_in - self.duplicates - self.out_of_order + self.lost_samples

    @property
    def loss_pct(self) -> float:
        return 100.0 * self.lost_samples / self.samples_expected if self.samples_expected else 0.0

    def gravity_problem(self) -> str:
        """Why the output still holds gravity, naming the likely cause; "" when it does not (or too little
        output to tell)."""
        out_rate = self.output_rate_hz or 1.0
        mz = self.mean_accel_mps2[2]
        tilt = self.gravity_tilt_deg
        mount = f"mount roll {self.mount_rpy_deg[0]:.1f} pitch {self.mount_rpy_deg[1]:.1f} deg from {self.mount_source}"
        fix = (
            "give the mount (mount_roll_deg, mount_pitch_deg: the sensor's rotation in the vehicle frame, e.g. "
            "roll 180 for an IMU upside down, roll 90 for its y axis up, -90 for it down), or set mount_source "
            "standstill and record a standstill of a few seconds"
        )
        if math.isfinite(tilt) and tilt > 20.0:
            return (
                f"gravity is {tilt:.0f} deg off the vehicle's z axis with the {mount}: the mount is wrong, the "
                f"vertical acceleration and pitch rate are other axes; {fix}"
            )
        if self.mean_samples >= MOUNT_CHECK_S * out_rate and math.isfinite(mz) and abs(mz) > self.max_mean_accel_z:
            mx, my = self.mean_accel_mps2[0], self.mean_accel_mps2[1]
            g = np.array([mx, my, mz + self.gravity_mps2])
            if float(np.linalg.norm(g)) < 0.3 * GRAVITY:
                # no mount turns gravity away: the sensor does not measure it (outside review 2026-11-29: an all-zero
                # IMU was called upside down)
                return (
                    f"mean a_z {mz:+.2f} m/s^2 after gravity removal (limit {self.max_mean_accel_z:g}) and the "
                    f"accelerometer measures {float(np.linalg.norm(g)):.2f} m/s^2 of gravity in all (9.81 expected): "
                    "a dead or unpowered sensor, a channel in the wrong unit or the wrong channels; check the IMU and "
                    "its channels, not the mount"
                )
            axis = ["x", "y", "z"][int(np.argmax(np.abs(g)))]
            sign = "+" if g["xyz".index(axis)] > 0 else "-"
            where = (
                "the IMU is upside down"
                if axis == "z" and sign == "-"
                else f"gravity is on the vehicle's {sign}{axis} axis"
                if axis != "z"
                else "gravity is removed too little (a wrong gravity value or a large accelerometer offset)"
            )
            sensor = rotation_matrix(*self.mount_rpy_deg).T @ g
            roll, pitch = roll_pitch_from_gravity(sensor)
            return (
                f"mean a_z {mz:+.2f} m/s^2 after gravity removal (limit {self.max_mean_accel_z:g}): {where} with the "
                f"{mount} (the mean acceleration says roll {round(roll) + 0:d} pitch {round(pitch) + 0:d} deg); J "
                f"would measure gravity, not the ride; {fix}"
            )
        return ""

    def offset_warning(self) -> str:
        """An offset of the vertical acceleration that goes into RMS(a_z) (no standstill bias); "" when none."""
        mz = self.mean_accel_mps2[2]
        if (
            self.bias_source != "standstill"
            and self.mean_samples >= MOUNT_CHECK_S * (self.output_rate_hz or 1.0)
            and math.isfinite(mz)
            and OFFSET_WARN_MPS2 < abs(mz) <= self.max_mean_accel_z
        ):
            return (
                f"mean a_z {mz:+.3f} m/s^2 without a standstill to measure the bias: an accelerometer offset goes "
                "straight into RMS(a_z) (set bias_source standstill and record a standstill, or kpi detrend)"
            )
        return ""

    @property
    def span_s(self) -> float:
        if self.first_stamp_ns is None or self.last_stamp_ns is None:
            return 0.0
        return (self.last_stamp_ns - self.first_stamp_ns) / NS

    @property
    def upsampling(self) -> bool:
        return self.nominal_rate_hz > 0 and self.output_rate_hz > 1.05 * self.nominal_rate_hz

    @property
    def faults(self) -> int:
        return (
            self.gaps
            + self.nonfinite
            + self.saturated
            + self.duplicates
            + self.out_of_order
            + self.clock_jumps
            + self.restarts
        )

    def copy(self) -> StreamHealth:
        return replace(self, events=list(self.events))

    def summary(self) -> str:
        """One paragraph naming what was found: rate, jitter, gaps and every other fault."""
        parts = [
            f"{self.samples_in} samples over {self.span_s:.1f} s",
            f"rate {self.rate_hz:.2f} Hz (nominal {self.nominal_rate_hz:.2f} Hz)",
            f"jitter {self.jitter_ms:.3f} ms (largest step {self.max_step_ms:.2f} ms"
            + (
                ", over the whole stream)"
                if self.health_window == 0
                else f", over the last {self.health_window} steps)"
            ),
        ]
        if math.isfinite(self.arrival_jitter_ms):
            parts.append(f"arrival jitter {self.arrival_jitter_ms:.3f} ms, latency {self.latency_ms:.3f} ms")
        if self.upsampling:
            parts.append(
                f"upsampled {self.nominal_rate_hz:.1f} -> {self.output_rate_hz:.1f} Hz: interpolation attenuates "
                "the content near the input Nyquist frequency (set output_rate_hz <= the IMU rate)"
            )
        parts.append(
            f"{self.samples_expected} samples expected at the nominal rate, {self.samples_in} received, "
            f"{self.lost_samples} lost ({self.loss_pct:.2f} %)"
        )
        if self.gaps:
            parts.append(f"{self.gaps} gap(s), {self.gap_total_s:.3f} s in total, longest {self.longest_gap_s:.3f} s")
        else:
            parts.append("no gaps")
        for name, n in (
            ("NaN/inf sample(s)", self.nonfinite),
            ("saturated sample(s)", self.saturated),
            ("duplicated stamp(s)", self.duplicates),
            ("out-of-order stamp(s)", self.out_of_order),
            ("clock jump(s)", self.clock_jumps),
            ("stream restart(s)", self.restarts),
        ):
            parts.append(f"{n} {name}" if n else f"no {name.replace('(s)', 's')}")
        r, p, y = self.mount_rpy_deg
        parts.append(f"mount roll {r:.2f} deg pitch {p:.2f} deg yaw {y:.2f} deg from {self.mount_source}")
        parts.append(f"gravity {self.gravity_mps2:.4f} m/s^2, gyro bias from {self.bias_source}")
        if self.mean_samples:
            mx, my, mz = self.mean_accel_mps2
            parts.append(f"mean acceleration after gravity removal x {mx:+.3f} y {my:+.3f} z {mz:+.3f} m/s^2")
        return "; ".join(parts)


@dataclass
class _Startup:
    stamp_ns: list[IntArray] = field(default_factory=list)
    data: list[FloatArray] = field(default_factory=list)  # (n, 6): accel, gyro (sensor frame)
    bad: list[BoolArray] = field(default_factory=list)

    def arrays(self) -> tuple[IntArray, FloatArray, BoolArray]:
        if not self.stamp_ns:
            return np.zeros(0, np.int64), np.zeros((0, 6)), np.zeros(0, bool)
        return np.concatenate(self.stamp_ns), np.concatenate(self.data), np.concatenate(self.bad)


class ImuIngestor:
    """Streaming IMU ingestion with explicit state (see the module docstring)."""

    MAX_EVENTS = 100

    def __init__(self, config: IngestConfig | None = None) -> None:
        self.config = config or IngestConfig()
        c = self.config
        self._step_ns = round(NS / c.output_rate_hz)
        self._health = StreamHealth(
            mount_rpy_deg=(c.mount_roll_deg, c.mount_pitch_deg, c.mount_yaw_deg),
            mount_source="config",
            gravity_mps2=c.gravity,
            bias_source="none",
            max_mean_accel_z=c.max_mean_accel_z,
            health_window=c.health_window,
        )
        self._acc_sum = np.zeros(3)  # sum of the output's accelerations with data (the mean a_z check)
        self._acc_n = 0
        self._events: deque[StreamEvent] = deque(maxlen=self.MAX_EVENTS)
        self._steps: deque[IntArray] = deque()  # recent stamp steps (ns), for rate and jitter
        self._steps_len = 0
        # sanity state
        self._max_stamp: int | None = None  # largest stamp accepted so far
        self._last_recv: int | None = None
        self._recv: deque[IntArray] = deque()  # recent (receive time, stamp) pairs
        self._recv_len = 0
        self._mark_pending = False  # a bad sample or a gap since the last good sample
        self._last_stamp: int | None = None  # last accepted stamp after startup
        # startup
        self._startup: _Startup | None = _Startup()
        self._nominal_rate = c.input_rate_hz
        self._R = rotation_matrix(c.mount_roll_deg, c.mount_pitch_deg, c.mount_yaw_deg)
        self._offset = np.zeros(6)  # subtracted after rotation: accel (0, 0, g), gyro bias
        self._offset[2] = c.gravity
        self._sos: FloatArray | None = None
        self._sos_zi0: FloatArray | None = None
        # running state after startup
        self._zi: FloatArray | None = None
        self._anchor: int | None = None  # stamp of grid index 0
        self._next_n = 0  # next grid index to emit
        self._prev_t: int | None = None  # last processed good sample (filtered)
        self._prev_x: FloatArray | None = None

    # --- public API -------------------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self._startup is None

    @property
    def rotation(self) -> FloatArray:
        return self._R.copy()

    @property
    def gap_threshold_ns(self) -> int:
        if self.config.gap_threshold_s > 0:
            return round(self.config.gap_threshold_s * NS)
        rate = self._nominal_rate or self.config.output_rate_hz
        return round(2.5 * NS / rate)

    def push(
        self,
        stamp_ns: npt.ArrayLike,
        accel: npt.ArrayLike,
        gyro: npt.ArrayLike,
        recv_ns: npt.ArrayLike | None = None,
    ) -> IngestOutput:
        """Feed raw samples (in arrival order); return the output grid samples now complete.

        ``stamp_ns``: (n,) int stamps (ns); ``accel``, ``gyro``: (n, 3) sensor frame, SI units;
        ``recv_ns``: optional (n,) receive times (ns) used to tell a clock jump from a restart.
        """
        t = np.asarray(stamp_ns, dtype=np.int64).reshape(-1)
        a = np.asarray(accel, dtype=np.float64)
        w = np.asarray(gyro, dtype=np.float64)
        n = t.shape[0]
        if a.shape != (n, 3) or w.shape != (n, 3):
            raise IngestError(
                f"expected stamps (n,), accel (n, 3) and gyro (n, 3); got {t.shape}, {a.shape}, {w.shape}"
            )
        r = None if recv_ns is None else np.asarray(recv_ns, dtype=np.int64).reshape(-1)
        if r is not None and r.shape != (n,):
            raise IngestError(f"recv_ns must have shape ({n},), got {r.shape}")
        if n == 0:
            return IngestOutput.empty()
        self._health.samples_in += n
        if self._health.first_stamp_ns is None:
            self._health.first_stamp_ns = int(t[0])
        x = np.hstack([a, w])
        outputs: list[IngestOutput] = []
        start = 0
        while start < n:
            stop = self._next_jump(t, start)
            outputs.append(self._sanitize(t[start:stop], x[start:stop]))
            if stop < n:  # clock jump or restart at `stop`: begin a new grid there
                if r is not None:
                    recv_step = int(r[stop]) - (int(r[stop - 1]) if stop > 0 else (self._last_recv or int(r[stop])))
                else:
                    recv_step = None
                outputs.append(self._restart(int(t[stop]), recv_step))
            start = stop
        if r is not None:
            self._last_recv = int(r[-1])
            self._recv.append(np.column_stack([r, t]))
            self._recv_len += n
            while self.config.health_window and self._recv_len - self._recv[0].shape[0] > self.config.health_window:
                self._recv_len -= self._recv.popleft().shape[0]
        return IngestOutput.concatenate([o for o in outputs if len(o)])

    def flush(self) -> IngestOutput:
        """End of stream: finish the startup with what was buffered (no standstill: configured mount)."""
        if self._startup is None:
            return IngestOutput.empty()
        return self._finish_startup(force=True)

    def health(self) -> StreamHealth:
        """A snapshot of the stream's health so far."""
        h = self._health.copy()
        h.events = list(self._events)
        h.started = self.started
        h.nominal_rate_hz = self._nominal_rate
        h.output_rate_hz = self.config.output_rate_hz
        if self._acc_n:
            m = self._acc_sum / self._acc_n
            h.mean_accel_mps2 = (float(m[0]), float(m[1]), float(m[2]))
            h.mean_samples = self._acc_n
        if self._recv:
            w = self.config.health_window
            pairs = np.concatenate(list(self._recv))
            pairs = pairs[-w - 1 :] if w else pairs
            if pairs.shape[0] > 2:
                h.arrival_jitter_ms = float(np.std(np.diff(pairs[:, 0]))) / 1e6
            h.latency_ms = float(np.median(pairs[:, 0] - pairs[:, 1])) / 1e6
        if self._steps_len:
            steps = np.concatenate(list(self._steps))
            steps = steps[-self.config.health_window :] if self.config.health_window else steps
            med = float(np.median(steps))
            h.rate_hz = NS / med if med > 0 else 0.0
            h.jitter_ms = float(np.std(steps)) / 1e6
            h.max_step_ms = float(np.max(steps)) / 1e6
        return h

    # --- sanity ---------------------------------------------------------------------------------
    def _event(self, kind: str, start: int, end: int, detail: str) -> None:
        self._events.append(StreamEvent(kind, start, end, detail))

    def _prev_max(self, t: IntArray) -> IntArray:
        """For each sample, the largest stamp accepted before it."""
        if self._max_stamp is None:
            head = np.maximum.accumulate(t)[:-1]
            return np.concatenate([[t[0] - 1], head]).astype(np.int64)
        return np.maximum.accumulate(np.concatenate([[self._max_stamp], t]))[:-1].astype(np.int64)

    def _next_jump(self, t: IntArray, start: int) -> int:
        """Index of the next clock jump / restart at or after ``start`` (or len(t))."""
        jump = round(self.config.clock_jump_s * NS)
        seg = t[start:]
        prev_max = self._prev_max(seg)
        hit = (seg < prev_max - jump) | (seg > prev_max + jump)
        if self._max_stamp is None:
            hit[0] = False
        # prev_max inside the segment must stop at the first hit: later samples are judged after the restart
        hits = np.flatnonzero(hit)
        return start + int(hits[0]) if hits.size else len(t)

    def _restart(self, stamp: int, recv_step: int | None) -> IngestOutput:
        """The stamps jumped at ``stamp``: close the current grid and start a new one there."""
        out = IngestOutput.empty()
        if self._startup is not None:
            out = self._finish_startup(force=True)
        prev = self._max_stamp if self._max_stamp is not None else stamp
        jump_s = (stamp - prev) / NS
        h = self._health
        if jump_s > 0 and (recv_step is None or recv_step >= (stamp - prev) / 2):
            # the stream stopped that long and resumed (a simulator between runs, a driver restarted):
            # STALE while it lasted; not a gap inside a stream, the output grid restarts
            h.restarts += 1
            self._event(
                "restart", prev, stamp, f"stream resumed after {jump_s:.3f} s without data: output grid restarted"
            )
        else:
            h.clock_jumps += 1
            self._event("clock_jump", prev, stamp, f"stamps jumped by {jump_s:+.3f} s: output grid restarted")
        self._max_stamp = None
        self._last_stamp = None
        self._mark_pending = False
        self._anchor = None
        self._next_n = 0
        self._prev_t = None
        self._prev_x = None
        self._zi = None
        return out

    def _sanitize(self, t: IntArray, x: FloatArray) -> IngestOutput:
        """Drop duplicated / out-of-order stamps, mark NaN/inf and saturated samples; feed the good ones on."""
        n = t.shape[0]
        c = self.config
        if n == 0:
            return IngestOutput.empty()
        prev_max = self._prev_max(t)
        dup = t == prev_max
        ooo = t < prev_max
        accepted = ~(dup | ooo)
        finite = np.all(np.isfinite(x), axis=1)
        sat = np.zeros(n, bool)
        if c.accel_range > 0:
            sat |= np.any(np.abs(x[:, :3]) >= c.accel_range, axis=1)
        if c.gyro_range > 0:
            sat |= np.any(np.abs(x[:, 3:]) >= c.gyro_range, axis=1)
        sat &= finite
        bad = accepted & (~finite | sat)
        self._max_stamp = int(max(int(t.max()), self._max_stamp if self._max_stamp is not None else int(t[0])))
        h = self._health
        h.last_stamp_ns = self._max_stamp
        for kind, mask, what in (
            ("duplicate", dup, "duplicated stamp(s) dropped"),
            ("out_of_order", ooo, "out-of-order stamp(s) dropped"),
            ("nonfinite", accepted & ~finite, "NaN/inf sample(s)"),
            ("saturation", accepted & sat, "saturated sample(s)"),
        ):
            k = int(np.count_nonzero(mask))
            if k:
                idx = np.flatnonzero(mask)
                self._event(kind, int(t[idx[0]]), int(t[idx[-1]]), f"{k} {what}")
        h.duplicates += int(np.count_nonzero(dup))
        h.out_of_order += int(np.count_nonzero(ooo))
        h.nonfinite += int(np.count_nonzero(accepted & ~finite))
        h.saturated += int(np.count_nonzero(accepted & sat))
        if not np.any(accepted):
            return IngestOutput.empty()
        return self._feed(t[accepted], x[accepted], bad[accepted])

    # --- startup: rate probe, standstill ----------------------------------------------------------
    def _feed(self, t: IntArray, x: FloatArray, bad: BoolArray) -> IngestOutput:
        """Accepted samples (increasing stamps), ``bad`` = NaN/inf or saturated."""
        if self._startup is None:
            return self._run(t, x, bad)
        s = self._startup
        s.stamp_ns.append(t)
        s.data.append(x)
        s.bad.append(bad)
        return self._finish_startup(force=False)

    def _finish_startup(self, force: bool) -> IngestOutput:
        s = self._startup
        assert s is not None
        c = self.config
        t, x, bad = s.arrays()
        if t.size == 0:
            if force:
                self._startup = None
                if not self._nominal_rate:
                    self._nominal_rate = c.output_rate_hz
                self._design_filter()
            return IngestOutput.empty()
        if not self._nominal_rate:
            if t.size <= c.rate_probe_samples and not force:
                return IngestOutput.empty()
            steps = np.diff(t[: c.rate_probe_samples + 1])
            self._nominal_rate = NS / float(np.median(steps)) if steps.size else c.output_rate_hz
        if c.needs_standstill:
            holes = bad | np.concatenate([[False], np.diff(t) > self.gap_threshold_ns])
            found = self._find_standstill(t, x, holes)
            if found is None:
                timed_out = (int(t[-1]) - int(t[0])) > round(c.standstill_timeout_s * NS)
                if not (timed_out or force):
                    return IngestOutput.empty()
                self._no_standstill(t, x, bad)
            else:
                self._use_standstill(t, x, *found)
        self._design_filter()
        self._startup = None
        return self._run(t, x, bad)

    def _find_standstill(self, t: IntArray, x: FloatArray, hole: BoolArray) -> tuple[int, int] | None:
        c = self.config
        win = max(2, round(c.standstill_s * self._nominal_rate))
        limit = int(t[0]) + round(c.standstill_timeout_s * NS)
        if t.size < win:
            return None
        xf = np.where(np.isfinite(x), x, 0.0)  # bad samples are excluded below, keep the sums finite
        cs = np.cumsum(np.vstack([np.zeros((1, 6)), xf]), axis=0)
        cs2 = np.cumsum(np.vstack([np.zeros((1, 6)), xf * xf]), axis=0)
        hc = np.cumsum(np.concatenate([[0], hole.astype(np.int64)]))
        ends = np.arange(win, t.size + 1)  # window = [end - win, end)
        sums = cs[ends] - cs[ends - win]
        sums2 = cs2[ends] - cs2[ends - win]
        mean = sums / win
        var = np.maximum(sums2 / win - mean * mean, 0.0)
        std = np.sqrt(var)
        g = np.linalg.norm(mean[:, :3], axis=1)
        ok = (
            (np.max(std[:, :3], axis=1) <= c.standstill_accel_std)
            & (np.max(std[:, 3:], axis=1) <= c.standstill_gyro_std)
            & (np.abs(g - c.gravity) <= 1.5)
            & (hc[ends] - hc[ends - win] == 0)  # no bad sample or gap inside the window
            & (t[ends - 1] <= limit)
        )
        hits = np.flatnonzero(ok)
        if hits.size == 0:
            return None
        end = int(ends[hits[0]])
        return end - win, end

    def _use_standstill(self, t: IntArray, x: FloatArray, i0: int, i1: int) -> None:
        c = self.config
        mean = x[i0:i1].mean(axis=0)
        h = self._health
        h.standstill_window_ns = (int(t[i0]), int(t[i1 - 1]))
        if c.mount_source == "standstill":
            roll, pitch = roll_pitch_from_gravity(mean[:3])
            self._R = rotation_matrix(roll, pitch, c.mount_yaw_deg)
            h.mount_rpy_deg = (roll, pitch, c.mount_yaw_deg)
            h.mount_source = "standstill"
        h.gravity_tilt_deg = _tilt_deg(self._R @ mean[:3])
        if c.bias_source == "standstill":
            v = self._R @ mean[:3]
            gyro_bias = self._R @ mean[3:]
            self._offset = np.concatenate([[v[0], v[1], v[2]], gyro_bias])
            if c.mount_source == "standstill":
                self._offset[0:2] = 0.0  # gravity is exactly on z with the estimated mount
            h.gravity_mps2 = float(v[2])
            h.gyro_bias = (float(gyro_bias[0]), float(gyro_bias[1]), float(gyro_bias[2]))
            h.bias_source = "standstill"

    def _no_standstill(self, t: IntArray, x: FloatArray, bad: BoolArray) -> None:
        c = self.config
        h = self._health
        used = "configured mount, nominal gravity and no gyro bias used (an accelerometer offset stays in a_z)"
        if c.mount_source == "standstill":
            h.mount_source = "config (no standstill found)"
        if c.bias_source == "standstill":
            h.bias_source = "none (no standstill found)"
        # the long-run mean: the car's own accelerations average out over a drive, gravity (and the sensor's
        # offsets) stay; over the searched span only, so that a stream pushed in chunks gives the same result
        inside = (t <= int(t[0]) + round(c.standstill_timeout_s * NS)) & ~bad if t.size else np.zeros(0, bool)
        if c.standstill_fallback == "mean" and np.count_nonzero(inside) >= 2:
            mean = x[inside].mean(axis=0)
            span = (int(t[inside][-1]) - int(t[inside][0])) / NS
            if abs(float(np.linalg.norm(mean[:3])) - c.gravity) <= 0.25 * c.gravity:
                what = f"mean accelerometer over {span:.1f} s (no standstill found)"
                parts = []
                if c.mount_source == "standstill":
                    roll, pitch = roll_pitch_from_gravity(mean[:3])
                    self._R = rotation_matrix(roll, pitch, c.mount_yaw_deg)
                    h.mount_rpy_deg = (roll, pitch, c.mount_yaw_deg)
                    h.mount_source = what
                    parts.append("roll and pitch")
                if c.bias_source == "standstill":
                    v = self._R @ mean[:3]
                    gyro_bias = self._R @ mean[3:]
                    gyro_bias[2] = 0.0  # the mean yaw rate is the drive's turns, not a bias
                    self._offset = np.concatenate([[v[0], v[1], v[2]], gyro_bias])
                    if c.mount_source == "standstill":
                        self._offset[0:2] = 0.0
                    h.gravity_mps2 = float(v[2])
                    h.gyro_bias = (float(gyro_bias[0]), float(gyro_bias[1]), 0.0)
                    h.bias_source = f"long-run mean over {span:.1f} s (no standstill found)"
                    parts.append("gravity and the roll/pitch gyro bias")
                h.gravity_tilt_deg = _tilt_deg(self._R @ mean[:3])
                if parts:
                    used = f"{', '.join(parts)} from the long-run mean over {span:.1f} s"
        self._event(
            "no_standstill",
            int(h.first_stamp_ns or 0),
            int(h.last_stamp_ns or 0),
            f"no standstill of {c.standstill_s} s within the first {c.standstill_timeout_s} s: {used}",
        )

    def _design_filter(self) -> None:
        c = self.config
        fs = self._nominal_rate
        sos_parts = []
        cutoff = c.antialias_ratio * c.output_rate_hz / 2
        if fs > 1.05 * c.output_rate_hz:  # downsampling: without it, content above the output Nyquist folds
            sos_parts.append(signal.butter(c.antialias_order, cutoff, btype="low", fs=fs, output="sos"))
        if c.highpass_hz > 0:
            sos_parts.append(signal.butter(2, c.highpass_hz, btype="high", fs=fs, output="sos"))
        if sos_parts:
            self._sos = np.vstack(sos_parts).astype(np.float64)
            self._sos_zi0 = np.asarray(signal.sosfilt_zi(self._sos), dtype=np.float64)

    # --- running: rotate, remove bias, filter, resample ------------------------------------------
    def _run(self, t: IntArray, x: FloatArray, bad: BoolArray) -> IngestOutput:
        if t.size == 0:
            return IngestOutput.empty()
        good, hole = self._holes(t, bad)
        if not np.any(good):
            return IngestOutput.empty()
        t, x = t[good], x[good]
        v = _rotate(self._R, x)
        v -= self._offset
        y = self._filter(v, hole)
        self._health.samples_used += int(t.size)
        return self._resample(t, y, hole)

    def _holes(self, t: IntArray, bad: BoolArray) -> tuple[BoolArray, BoolArray]:
        """Find gaps (stamp steps above the threshold) among accepted samples.

        Returns the mask of good samples and, for each good sample, whether a hole (a gap or a
        bad sample) lies between it and the previous good sample. Keeps the steps for rate and
        jitter.
        """
        h = self._health
        first = self._last_stamp is None
        prev = np.concatenate([[t[0] if first else self._last_stamp], t[:-1]]).astype(np.int64)
        steps = t - prev
        gap = steps > self.gap_threshold_ns
        period = NS / (self._nominal_rate or self.config.output_rate_hz)
        missing = np.rint(steps / period).astype(np.int64) - 1
        h.lost_samples += int(np.sum(missing[missing > 0]))
        for i in np.flatnonzero(gap):
            gs = int(steps[i]) / NS
            h.gaps += 1
            h.gap_total_s += gs
            h.longest_gap_s = max(h.longest_gap_s, gs)
            self._event("gap", int(prev[i]), int(t[i]), f"no data for {gs:.3f} s")
        ok = steps[~gap][1:] if first else steps[~gap]
        if ok.size:
            self._steps.append(ok)
            self._steps_len += int(ok.size)
            while self.config.health_window and self._steps_len - self._steps[0].size >= self.config.health_window:
                self._steps_len -= self._steps.popleft().size
        self._last_stamp = int(t[-1])
        # a mark = a bad sample, or a gap just before a sample; a good sample after a mark starts anew
        mark = bad | gap
        good = ~bad
        gi = np.flatnonzero(good)
        if gi.size == 0:
            self._mark_pending = self._mark_pending or bool(np.any(mark))
            return good, np.zeros(0, bool)
        mc = np.cumsum(mark)
        before = mc[gi]  # marks up to and including each good sample
        hole = np.diff(np.concatenate([[0], before])) > 0
        hole[0] = bool(before[0] > 0) or self._mark_pending or self._prev_t is None
        self._mark_pending = bool(mc[-1] - mc[gi[-1]] > 0)
        return good, hole

    def _filter(self, v: FloatArray, hole: BoolArray) -> FloatArray:
        if self._sos is None:
            return v
        assert self._sos_zi0 is not None
        y = np.empty_like(v)
        starts = np.flatnonzero(hole)
        bounds = np.concatenate([[0], starts[starts > 0], [v.shape[0]]])
        for a, b in itertools.pairwise(bounds.tolist()):
            if hole[a] or self._zi is None:
                self._zi = self._sos_zi0[:, :, None] * v[a]
            y[a:b], self._zi = signal.sosfilt(self._sos, v[a:b], axis=0, zi=self._zi)
        return y

    def _resample(self, t: IntArray, y: FloatArray, hole: BoolArray) -> IngestOutput:
        step = self._step_ns
        if self._anchor is None:
            self._anchor = int(t[0])
            self._next_n = 0
        if self._prev_t is not None and self._prev_x is not None:
            T = np.concatenate([[self._prev_t], t])
            Y = np.vstack([self._prev_x[None, :], y])
            H = np.concatenate([[False], hole])
        else:
            T, Y, H = t, y, hole
        last_n = (int(T[-1]) - self._anchor) // step
        self._prev_t = int(t[-1])
        self._prev_x = y[-1].copy()
        if last_n < self._next_n:
            return IngestOutput.empty()
        n = np.arange(self._next_n, last_n + 1, dtype=np.int64)
        self._next_n = last_n + 1
        g = self._anchor + n * step
        idx = np.searchsorted(T, g, side="left")  # T[idx-1] < g <= T[idx]
        idx = np.clip(idx, 1, T.size - 1) if T.size > 1 else np.zeros_like(idx)
        out = np.empty((g.size, 6))
        if T.size == 1:
            out[:] = Y[0]
        else:
            t0 = T[idx - 1]
            t1 = T[idx]
            wgt = ((g - t0) / (t1 - t0)).astype(np.float64)[:, None]
            out[:] = Y[idx - 1] + wgt * (Y[idx] - Y[idx - 1])
            exact = g == t1
            out[exact] = Y[idx[exact]]
            inside_hole = H[idx] & ~exact
            out[inside_hole] = np.nan
        self._health.samples_out += int(g.size)
        have = ~np.isnan(out[:, 2])
        self._health.samples_out_nan += int(g.size - np.count_nonzero(have))
        if have.any():
            a = out[have, :3]
            self._acc_sum += (a[:, 0].sum(), a[:, 1].sum(), a[:, 2].sum())
            self._acc_n += int(a.shape[0])
        return IngestOutput(g.astype(np.int64), out[:, :3].copy(), out[:, 3:].copy())


@dataclass(frozen=True)
class Diagnosis:
    """What a diagnostics message says about the stream: level, one line, key values."""

    level: int  # 0 OK, 1 WARN, 2 ERROR, 3 STALE (diagnostic_msgs/DiagnosticStatus levels)
    message: str
    values: list[tuple[str, str]]


OK, WARN, ERROR, STALE = 0, 1, 2, 3


def diagnose(
    now: StreamHealth,
    before: StreamHealth | None = None,
    expected_rate_hz: float = 0.0,
    silent_s: float = 0.0,
    stale_after_s: float = 1.0,
) -> Diagnosis:
    """Compare two health snapshots: what happened since ``before`` decides the level.

    ``silent_s``: time since the last sample arrived (receive clock); beyond
    ``stale_after_s`` the stream is STALE (nothing arrives).
    """
    b = before or StreamHealth()
    new = {
        "gap": now.gaps - b.gaps,
        "NaN/inf sample": now.nonfinite - b.nonfinite,
        "saturated sample": now.saturated - b.saturated,
        "duplicated stamp": now.duplicates - b.duplicates,
        "out-of-order stamp": now.out_of_order - b.out_of_order,
        "clock jump": now.clock_jumps - b.clock_jumps,
        "stream restart": now.restarts - b.restarts,
    }
    problems = [f"{n} {k}{'s' if n > 1 else ''}" for k, n in new.items() if n > 0]
    lost = now.lost_samples - b.lost_samples
    if lost > 0 and not new["gap"]:
        problems.append(f"{lost} lost sample{'s' if lost > 1 else ''} ({now.loss_pct:.2f} % of the stream)")
    level = OK
    if problems:
        level = ERROR if (new["gap"] or new["NaN/inf sample"] or new["saturated sample"] or new["clock jump"]) else WARN
    gravity = now.gravity_problem()
    if gravity:
        problems.insert(0, gravity)
        level = ERROR
    elif now.offset_warning():
        problems.append(now.offset_warning())
        level = max(level, WARN)
    expected = expected_rate_hz or now.nominal_rate_hz
    if expected > 0 and now.rate_hz > 0 and abs(now.rate_hz - expected) > 0.1 * expected:
        problems.append(f"rate {now.rate_hz:.1f} Hz, expected {expected:.1f} Hz")
        level = max(level, WARN)
    if now.started and now.upsampling:
        problems.append(f"output {now.output_rate_hz:.0f} Hz above the IMU's {now.nominal_rate_hz:.1f} Hz")
        level = max(level, WARN)
    if now.samples_in == 0:
        level, message = STALE, "waiting for IMU data"
    elif silent_s > stale_after_s and level == ERROR:
        # faults since the last report are never swallowed by a silence that follows them (they are counted
        # against this report only): the faults first, the silence said beside them, STALE from the next report
        message = "since last report: " + ", ".join(problems) + f"; then no IMU data for {silent_s:.1f} s"
    elif silent_s > stale_after_s:
        level, message = STALE, f"no IMU data for {silent_s:.1f} s"
    elif not now.started:
        level = max(level, OK)
        message = "starting: measuring the input rate / looking for a standstill"
        if problems:
            message += "; " + ", ".join(problems)
    elif problems:
        message = "since last report: " + ", ".join(problems)
    else:
        message = f"OK, {now.rate_hz:.1f} Hz, jitter {now.jitter_ms:.2f} ms"
    r, p, y = now.mount_rpy_deg
    values = [
        ("rate_hz", f"{now.rate_hz:.3f}"),
        ("nominal_rate_hz", f"{now.nominal_rate_hz:.3f}"),
        ("jitter_ms", f"{now.jitter_ms:.4f}"),
        ("max_step_ms", f"{now.max_step_ms:.3f}"),
        ("arrival_jitter_ms", f"{now.arrival_jitter_ms:.4f}"),
        ("latency_ms", f"{now.latency_ms:.3f}"),
        ("output_rate_hz", f"{now.output_rate_hz:.3f}"),
        ("samples_in", str(now.samples_in)),
        ("samples_out", str(now.samples_out)),
        ("samples_out_without_data", str(now.samples_out_nan)),
        ("samples_expected", str(now.samples_expected)),
        ("lost_samples", str(now.lost_samples)),
        ("gaps", str(now.gaps)),
        ("gap_total_s", f"{now.gap_total_s:.4f}"),
        ("longest_gap_s", f"{now.longest_gap_s:.4f}"),
        ("nonfinite", str(now.nonfinite)),
        ("saturated", str(now.saturated)),
        ("duplicates", str(now.duplicates)),
        ("out_of_order", str(now.out_of_order)),
        ("clock_jumps", str(now.clock_jumps)),
        ("restarts", str(now.restarts)),
        ("mount_roll_deg", f"{r:.3f}"),
        ("mount_pitch_deg", f"{p:.3f}"),
        ("mount_yaw_deg", f"{y:.3f}"),
        ("mount_source", now.mount_source),
        ("gravity_mps2", f"{now.gravity_mps2:.5f}"),
        ("gyro_bias_rad_s", ", ".join(f"{v:.5f}" for v in now.gyro_bias)),
        ("bias_source", now.bias_source),
        ("mean_accel_z_mps2", f"{now.mean_accel_mps2[2]:.4f}"),
        ("gravity_tilt_deg", f"{now.gravity_tilt_deg:.2f}"),
        ("started", str(now.started).lower()),
        ("first_stamp_ns", str(now.first_stamp_ns if now.first_stamp_ns is not None else "")),
        ("last_stamp_ns", str(now.last_stamp_ns if now.last_stamp_ns is not None else "")),
    ]
    if now.events:
        e = now.events[-1]
        values.append(("last_fault", f"{e.kind} at {e.start_ns / NS:.3f} s: {e.detail}"))
    return Diagnosis(level, message, values)


@dataclass(frozen=True)
class Clipping:
    """A sensor axis that sits flat at its extreme: the sensor's range was reached (clipped), whatever range
    is configured."""

    axis: str  # "accel_z", "gyro_x", ...
    level: float  # the value it is flat at (m/s^2 or rad/s)
    samples: int  # samples at that value
    longest_run: int  # longest run of consecutive samples at it

    def describe(self) -> str:
        unit = "m/s^2" if self.axis.startswith("accel") else "rad/s"
        extra = f" ({abs(self.level) / GRAVITY:.2f} g)" if self.axis.startswith("accel") else ""
        return (
            f"{self.axis} clipped at {self.level:+.4g} {unit}{extra}: {self.samples} samples flat at the recording's "
            f"extreme, up to {self.longest_run} in a row"
        )


def find_clipping(accel: npt.ArrayLike, gyro: npt.ArrayLike, min_samples: int = 3) -> list[Clipping]:
    """Axes whose recording sits flat at its maximum or minimum: a clipped sensor.

    A natural peak passes through the levels just below it at least as often as it sits at its top (and a float
    signal never repeats its maximum); a clipped one piles samples on one value: at least ``min_samples`` at the
    extreme, two of them in a row, more than twice as many as at the next value below, and the extreme far from
    the bulk of the signal (beyond 5 robust standard deviations from the median). Vectorized over each axis.
    """
    out: list[Clipping] = []
    a = np.asarray(accel, dtype=np.float64)
    w = np.asarray(gyro, dtype=np.float64)
    for prefix, x in (("accel", a), ("gyro", w)):
        for i, name in enumerate("xyz"):
            col = x[:, i] if x.ndim == 2 and x.shape[1] > i else np.zeros(0)
            col = col[np.isfinite(col)]
            if col.size < 10:
                continue
            med = float(np.median(col))
            spread = 1.4826 * float(np.median(np.abs(col - med)))
            for level in (float(col.max()), float(col.min())):
                if abs(level - med) <= max(5.0 * spread, 1e-12):
                    continue
                at = np.asarray(np.asarray(x[:, i]) == level)
                n_at = int(np.count_nonzero(at))
                if n_at < min_samples:
                    continue
                others = col[col != level]
                nearest = others.max() if level > med else others.min()
                if n_at <= 2 * int(np.count_nonzero(col == nearest)):
                    continue
                runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], at.astype(np.int8), [0]]))))[::2]
                longest = int(runs.max()) if runs.size else 0
                if longest >= 2:
                    out.append(Clipping(f"{prefix}_{name}", level, n_at, longest))
    return out


def ingest_all(
    stamp_ns: npt.ArrayLike,
    accel: npt.ArrayLike,
    gyro: npt.ArrayLike,
    config: IngestConfig | None = None,
    recv_ns: npt.ArrayLike | None = None,
) -> tuple[IngestOutput, StreamHealth]:
    """One-shot ingestion of a whole recording (offline): output and health."""
    ing = ImuIngestor(config)
    out = ing.push(stamp_ns, accel, gyro, recv_ns)
    rest = ing.flush()
    return IngestOutput.concatenate([o for o in (out, rest) if len(o)]), ing.health()
