"""KPI scoring: the pure core of ``kpi_scorer`` (paper eq. 1 and ISO 2631-1 variants).

``J = w_az * A + w_q * Q`` over the aligned window of a :class:`~bac_measure.segmentation.Segment`:

* ``kpi = "rms"`` (the paper, eq. 1, with w_az = w_q = 1): A = RMS(a_z);
* ``kpi = "iso_wk_rms"``: A = the ISO 2631-1 Wk frequency-weighted RMS of a_z;
* ``kpi = "vdv"``: A = the vibration dose value of Wk-weighted a_z (m/s^1.75);

and Q = RMS(pitch rate) in every case. Every part is computed whatever the
KPI (the report shows them all), with Welch spectra of both signals, and the
outcomes a calibration engineer sets limits on (:data:`OUTCOMES`: the peak
vertical acceleration and pitch rate of the window).

:func:`score` is a pure function of the segment and the configuration: the
live node and an offline rescoring of the same segment give the same J, bit
for bit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import signal

from bac_common.errors import BacError
from bac_measure.iso2631 import vibration_dose_value, wk_filter
from bac_measure.segmentation import RunId, Segment, from_params

FloatArray = npt.NDArray[np.float64]
KPIS = ("rms", "iso_wk_rms", "vdv")
# the sample rates an IMU stream can have after ingestion (imu_ingest's output_rate_hz, 1 Hz up): outside them, a time
# base in the wrong unit (an outside review's 1e15 Hz asked the spectrum for 256 PiB, 1e-9 Hz scored valid)
MIN_SAMPLE_RATE_HZ = 1.0
MAX_SAMPLE_RATE_HZ = 20_000.0


class KpiError(BacError, ValueError):
    """A bad KPI configuration."""


@dataclass(frozen=True)
class KpiConfig:
    """What J is (the kpi_scorer node's parameters, same names)."""

    kpi: str = "rms"  # "rms" (paper eq. 1), "iso_wk_rms", "vdv"
    weight_accel_z: float = 1.0  # w_az
    weight_pitch_rate: float = 1.0  # w_q
    detrend: bool = False  # remove each signal's mean over the window before the RMS (eq. 1 does not)
    psd_segment_s: float = 2.0  # Welch segment length, s (capped at the window)
    psd_max_hz: float = 50.0  # spectra are kept up to this frequency, Hz
    # plausibility: a car body's RMS over a run stays far below these; beyond them the run is invalid (a gyro in deg/s
    # or an accelerometer in mm/s^2 labelled rad/s, m/s^2 gave a valid J 5x too high, outside review 2026-11-29);
    # 0 = no check (a rig that shakes harder than a car)
    max_rms_accel_z: float = 50.0  # m/s^2 (5 g RMS)
    max_rms_pitch_rate: float = 1.0  # rad/s (57 deg/s RMS; a car pitching ±3 deg at 1.5 Hz: 0.35 rad/s)

    def __post_init__(self) -> None:
        p = []
        if self.kpi not in KPIS:
            p.append(f"kpi must be one of {KPIS}, got {self.kpi!r}")
        for name in ("weight_accel_z", "weight_pitch_rate"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                p.append(f"{name} must be finite and >= 0, got {v}")
        if self.weight_accel_z == 0 and self.weight_pitch_rate == 0:
            p.append("at least one weight must be > 0")
        if not (0.05 <= self.psd_segment_s <= 600):
            p.append(f"psd_segment_s must be in [0.05, 600], got {self.psd_segment_s}")
        if not self.psd_max_hz > 0:
            p.append("psd_max_hz must be > 0")
        for name in ("max_rms_accel_z", "max_rms_pitch_rate"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                p.append(f"{name} must be finite and >= 0 (0: no check), got {v}")
        if p:
            raise KpiError("invalid KPI configuration: " + "; ".join(p))

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> KpiConfig:
        """Build from a node's parameters (``ros__parameters`` of kpi_scorer); unknown keys are ignored."""
        config: KpiConfig = from_params(cls, params)
        return config


@dataclass(frozen=True)
class Score:
    """The KPI of one run (the content of a bac_msgs/RunScore)."""

    run: RunId
    window_start_ns: int
    j: float  # NaN when invalid
    rms_accel_z: float
    rms_pitch_rate: float
    weighted_rms_accel_z: float
    vdv_accel_z: float
    kpi: str
    weight_accel_z: float
    weight_pitch_rate: float
    psd_frequency_hz: FloatArray = field(repr=False)
    psd_accel_z: FloatArray = field(repr=False)
    psd_pitch_rate: FloatArray = field(repr=False)
    valid: bool
    reason: str
    # measured besides J, for outcome limits (RunScore.outcome_names / outcome_values): see OUTCOMES
    outcomes: Mapping[str, float] = field(default_factory=dict)


# what score_signals measures besides J, from the same window of the same IMU signals (before any detrending)
OUTCOMES = {
    "peak_accel_z": "largest |vertical acceleration| in the window, m/s^2",
    "peak_pitch_rate": "largest |pitch rate| in the window, rad/s",
}


def rms(x: npt.ArrayLike) -> float:
    """Root mean square; NaN for an empty signal."""
    a = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a))) if a.size else math.nan


def welch_psd(x: FloatArray, fs: float, segment_s: float, max_hz: float) -> tuple[FloatArray, FloatArray]:
    """One-sided Welch PSD (Hann, 50 % overlap), frequencies up to ``max_hz``."""
    nper = max(8, min(x.size, round(segment_s * fs)))
    if x.size < 8:
        return np.zeros(0), np.zeros(0)
    f, p = signal.welch(x, fs=fs, nperseg=nper, detrend="constant")
    keep = f <= max_hz
    return np.asarray(f[keep], dtype=np.float64), np.asarray(p[keep], dtype=np.float64)


def score_signals(
    accel_z: npt.ArrayLike,
    pitch_rate: npt.ArrayLike,
    sample_rate_hz: float,
    config: KpiConfig | None = None,
    run: RunId | None = None,
    window_start_ns: int = 0,
    pre_roll_accel_z: npt.ArrayLike | None = None,
) -> Score:
    """Score aligned signals (vertical acceleration m/s^2, pitch rate rad/s) sampled at ``sample_rate_hz``.

    ``pre_roll_accel_z``: a_z just before the window (same rate), run through the Wk filter first so that the
    weighted parts (Wk RMS, VDV) are those of the window inside the recording, not from rest. RMS(a_z) and
    RMS(pitch rate) are of the window alone."""
    c = config or KpiConfig()
    az = np.asarray(accel_z, dtype=np.float64).reshape(-1)
    q = np.asarray(pitch_rate, dtype=np.float64).reshape(-1)
    empty = np.zeros(0)

    def invalid(reason: str) -> Score:
        return Score(
            run=run or RunId(),
            window_start_ns=window_start_ns,
            j=math.nan,
            rms_accel_z=math.nan,
            rms_pitch_rate=math.nan,
            weighted_rms_accel_z=math.nan,
            vdv_accel_z=math.nan,
            kpi=c.kpi,
            weight_accel_z=c.weight_accel_z,
            weight_pitch_rate=c.weight_pitch_rate,
            psd_frequency_hz=empty,
            psd_accel_z=empty,
            psd_pitch_rate=empty,
            valid=False,
            reason=reason,
        )

    if az.shape != q.shape:
        return invalid(f"a_z and pitch rate differ in length ({az.size} vs {q.size})")
    if az.size < 2:
        return invalid(f"window too short to score ({az.size} samples)")
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        return invalid(f"bad sample rate {sample_rate_hz}")
    if not MIN_SAMPLE_RATE_HZ <= sample_rate_hz <= MAX_SAMPLE_RATE_HZ:
        return invalid(
            f"sample rate {sample_rate_hz:g} Hz outside the {MIN_SAMPLE_RATE_HZ:g}-{MAX_SAMPLE_RATE_HZ:g} Hz of an "
            "IMU stream: check the recording's time base (its unit) or resample"
        )
    bad = int(np.count_nonzero(~np.isfinite(az)) + np.count_nonzero(~np.isfinite(q)))
    if bad:
        return invalid(f"{bad} non-finite sample(s) in the window")
    outcomes = {"peak_accel_z": float(np.max(np.abs(az))), "peak_pitch_rate": float(np.max(np.abs(q)))}
    pre = np.zeros(0) if pre_roll_accel_z is None else np.asarray(pre_roll_accel_z, dtype=np.float64).reshape(-1)
    pre = pre[int(np.flatnonzero(~np.isfinite(pre))[-1]) + 1 :] if pre.size and not np.all(np.isfinite(pre)) else pre
    if c.detrend:
        mean_az = az.mean()
        az = az - mean_az
        pre = pre - mean_az
        q = q - q.mean()
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is judged below, as the run's reason
        rms_az = rms(az)
        rms_q = rms(q)
        aw = wk_filter(az, sample_rate_hz, pre)
        wrms = rms(aw)
        vdv = vibration_dose_value(aw, sample_rate_hz)
        a_term = {"rms": rms_az, "iso_wk_rms": wrms, "vdv": vdv}[c.kpi]
        j = c.weight_accel_z * a_term + c.weight_pitch_rate * rms_q
    if not all(math.isfinite(v) for v in (j, rms_az, rms_q, wrms, vdv)):
        # finite samples whose squares overflow (e.g. 1e200 m/s^2): no car measures that, and an infinite J told
        # to the optimizer would be taken for a very bad calibration
        return invalid(
            f"the KPI overflows (largest |a_z| {outcomes['peak_accel_z']:.3g} m/s^2, |pitch rate| "
            f"{outcomes['peak_pitch_rate']:.3g} rad/s): these are not a vehicle's signals"
        )
    if c.max_rms_pitch_rate > 0 and rms_q > c.max_rms_pitch_rate:
        return invalid(
            f"RMS pitch rate {rms_q:.3g} rad/s is beyond a car body's (max_rms_pitch_rate {c.max_rms_pitch_rate:g}): "
            f"a gyro in deg/s read as rad/s would give this ({rms_q:.3g} deg/s are {math.radians(rms_q):.3g} rad/s); "
            "check the channel's unit (channel map) or the IMU driver"
        )
    if c.max_rms_accel_z > 0 and rms_az > c.max_rms_accel_z:
        return invalid(
            f"RMS a_z {rms_az:.3g} m/s^2 is beyond a car body's (max_rms_accel_z {c.max_rms_accel_z:g}): is the "
            "accelerometer in mm/s^2? Check the channel's unit (channel map) or the IMU driver"
        )
    f, p_az = welch_psd(az, sample_rate_hz, c.psd_segment_s, c.psd_max_hz)
    _, p_q = welch_psd(q, sample_rate_hz, c.psd_segment_s, c.psd_max_hz)
    return Score(
        run=run or RunId(),
        window_start_ns=window_start_ns,
        j=float(j),
        rms_accel_z=rms_az,
        rms_pitch_rate=rms_q,
        weighted_rms_accel_z=wrms,
        vdv_accel_z=vdv,
        kpi=c.kpi,
        weight_accel_z=c.weight_accel_z,
        weight_pitch_rate=c.weight_pitch_rate,
        psd_frequency_hz=f,
        psd_accel_z=p_az,
        psd_pitch_rate=p_q,
        valid=True,
        reason="",
        outcomes=outcomes,
    )


def score(segment: Segment, config: KpiConfig | None = None) -> Score:
    """Score one segment. An invalid segment gives an invalid score with the segment's reason."""
    c = config or KpiConfig()
    if not segment.valid:
        s = score_signals(np.zeros(0), np.zeros(0), 1.0, c, segment.run, segment.window_start_ns)
        return _replace_reason(s, f"segment invalid: {segment.reason or 'no reason given'}")
    return score_signals(
        segment.accel_z,
        segment.pitch_rate,
        segment.sample_rate_hz,
        c,
        segment.run,
        segment.window_start_ns,
        segment.pre_roll_accel_z,
    )


def _replace_reason(s: Score, reason: str) -> Score:
    return replace(s, reason=reason)
