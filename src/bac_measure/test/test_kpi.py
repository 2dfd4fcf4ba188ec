"""KPI core: known answers (RMS, ISO 2631-1 Wk gains, VDV, PSD) and validity."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from bac_measure.iso2631 import WK_TABLE, vibration_dose_value, weighted_rms, wk_filter, wk_response
from bac_measure.kpi import KPIS, KpiConfig, KpiError, rms, score, score_signals
from bac_measure.segmentation import MODE_EVENT, RunId, Segment


def sine(freq: float, amp: float, fs: float, seconds: float, phase: float = 0.3) -> np.ndarray:
    t = np.arange(round(seconds * fs)) / fs
    return amp * np.sin(2 * np.pi * freq * t + phase)


@pytest.mark.parametrize("amp,freq,fs", [(1.0, 2.0, 200.0), (0.37, 5.0, 500.0), (3.2, 1.25, 100.0)])
def test_rms_of_a_sinusoid_is_amplitude_over_sqrt2(amp: float, freq: float, fs: float) -> None:
    x = sine(freq, amp, fs, 4.0)  # whole number of periods
    assert rms(x) == pytest.approx(amp / math.sqrt(2), rel=1e-12)


def test_j_is_rms_az_plus_rms_pitch_rate() -> None:
    fs = 200.0
    az, q = sine(2.0, 1.5, fs, 5.0), sine(1.0, 0.2, fs, 5.0, phase=1.0)
    s = score_signals(az, q, fs)
    assert s.valid and s.kpi == "rms"
    assert s.rms_accel_z == pytest.approx(1.5 / math.sqrt(2), rel=1e-12)
    assert s.rms_pitch_rate == pytest.approx(0.2 / math.sqrt(2), rel=1e-12)
    assert s.j == pytest.approx((1.5 + 0.2) / math.sqrt(2), rel=1e-12)
    w = score_signals(az, q, fs, KpiConfig(weight_accel_z=2.0, weight_pitch_rate=0.5))
    assert w.j == pytest.approx(2.0 * 1.5 / math.sqrt(2) + 0.5 * 0.2 / math.sqrt(2), rel=1e-12)


@pytest.mark.parametrize("freq,expected", [(1.0, 0.482), (6.3, 1.054), (12.5, 0.902)])
@pytest.mark.parametrize("fs", [200.0, 500.0])
def test_wk_gain_matches_iso2631_table_within_1_percent(freq: float, expected: float, fs: float) -> None:
    """Measured on a filtered sinusoid in steady state (band limiting included)."""
    x = sine(freq, 1.0, fs, 40.0)
    y = wk_filter(x, fs)
    steady = slice(round(15 * fs), None)
    gain = rms(y[steady]) / rms(x[steady])
    assert gain == pytest.approx(expected, rel=0.01)
    assert abs(wk_response(freq)) == pytest.approx(expected, rel=0.01)


@pytest.mark.parametrize("freq,expected", [(1.0, 0.482), (6.3, 1.054), (12.5, 0.902)])
@pytest.mark.parametrize("fs", [200.0, 500.0])
def test_wk_gain_on_a_2_5_s_window_with_the_pre_roll(freq: float, expected: float, fs: float) -> None:
    """The paper's 2.5 s window of a longer run: the Wk filter runs through the 5 s before it (the segment's
    pre-roll) and the window's weighted RMS gives the table's factor within 1 % at every phase; from rest the
    0.4 Hz band limit has not settled (1 Hz: up to -4 %, the review's 0.4627 instead of 0.4825)."""
    n, pre = round(2.5 * fs), round(5.0 * fs)
    from_rest, with_pre = [], []
    for phase in np.linspace(0, 2 * np.pi, 12, endpoint=False):
        x = sine(freq, 1.0, fs, 7.5, phase=float(phase))
        window = x[pre:]
        assert window.size == n
        s0 = score_signals(window, np.zeros(n), fs, KpiConfig(kpi="iso_wk_rms"))
        s1 = score_signals(window, np.zeros(n), fs, KpiConfig(kpi="iso_wk_rms"), pre_roll_accel_z=x[:pre])
        from_rest.append(s0.weighted_rms_accel_z * math.sqrt(2))
        with_pre.append(s1.weighted_rms_accel_z * math.sqrt(2))
        assert s1.j == s1.weighted_rms_accel_z and s1.rms_accel_z == s0.rms_accel_z  # RMS: the window alone
    assert max(abs(g / expected - 1) for g in with_pre) < 0.01, with_pre
    if freq == 1.0:
        assert max(abs(g / expected - 1) for g in from_rest) > 0.03, from_rest  # what the pre-roll fixes


def test_the_segmenter_hands_the_pre_roll_to_the_scorer() -> None:
    """Through cut_run (distance mode, a 2.5 s section driven at constant speed): the segment carries the 5 s
    of a_z before the window, and the Wk RMS of a 1 Hz sine on the window is the table's 0.482 within 1 %."""
    from bac_measure.segmentation import ImuSeries, OdomSeries, SegmentConfig, cut_run

    fs, v = 200.0, 10.0
    cfg = SegmentConfig(
        mode="distance", target_speed_mps=v, imu_rate_hz=fs, distance_start_m=100.0, distance_end_m=125.0
    )
    t = np.arange(round(20 * fs)) / fs
    stamps = 1_000_000_000_000 + np.round(t * 1e9).astype(np.int64)
    imu = ImuSeries(stamps, np.sin(2 * np.pi * 1.0 * t + 2.2), np.zeros(t.size))
    odom = OdomSeries(stamps[::4], v * t[::4], np.full(t[::4].size, v))
    seg = cut_run(imu, odom, cfg, int(stamps[0]))
    assert seg.valid, seg.reason
    assert len(seg) == 500 and seg.pre_roll_accel_z.size == 1000
    np.testing.assert_allclose(seg.pre_roll_accel_z, np.sin(2 * np.pi * (t[1000:2000]) + 2.2), atol=1e-6)
    sc = score(seg, KpiConfig(kpi="iso_wk_rms"))
    assert sc.weighted_rms_accel_z * math.sqrt(2) == pytest.approx(0.482, rel=0.01)
    # the message round trip keeps it (a bag recorded before the field existed gives an empty one)
    bare = score(replace(seg, pre_roll_accel_z=np.zeros(0)), KpiConfig(kpi="iso_wk_rms"))
    assert abs(bare.weighted_rms_accel_z * math.sqrt(2) / 0.4825 - 1) > 0.01
    no_pre = cut_run(imu, odom, replace(cfg, pre_roll_s=0.0), int(stamps[0]))
    assert no_pre.pre_roll_accel_z.size == 0 and np.array_equal(no_pre.accel_z, seg.accel_z)


def test_an_event_cut_carries_the_a_z_before_its_window() -> None:
    """Event mode: the pre-roll is the run's a_z just before the window (from the run start on), on its grid."""
    from bac_measure.segmentation import SegmentConfig, cut_run
    from bac_measure.synthetic import bump_run

    run = bump_run(lead_s=0.5, bump_at_m=40.0, duration_s=10.0)  # the impact ~4.8 s after the run start
    cfg = SegmentConfig(imu_rate_hz=200.0)
    seg = cut_run(run.imu, run.odom, cfg, run.start_ns)
    assert seg.valid, seg.reason
    available = (seg.window_start_ns - run.start_ns) / 1e9  # the run starts at the trial: no data before it
    assert seg.pre_roll_accel_z.size == pytest.approx(min(5.0, available) * 200, abs=2)
    t_pre = seg.window_start_ns - np.arange(seg.pre_roll_accel_z.size, 0, -1) * 5_000_000
    want = np.interp(t_pre, run.imu.stamp_ns, run.imu.accel_z)
    np.testing.assert_allclose(seg.pre_roll_accel_z, want, atol=0.05)
    short = cut_run(run.imu, run.odom, replace(cfg, pre_roll_s=1.0), run.start_ns)
    assert short.pre_roll_accel_z.size == 200
    np.testing.assert_allclose(short.pre_roll_accel_z, seg.pre_roll_accel_z[-200:], atol=1e-6)


def test_wk_response_follows_the_whole_table() -> None:
    for f, w in WK_TABLE.items():
        assert abs(wk_response(f)) == pytest.approx(w, rel=0.005), f


def test_weighted_rms_and_vdv_of_a_sinusoid() -> None:
    fs, amp, f = 500.0, 2.0, 6.3
    x = sine(f, amp, fs, 60.0)
    assert weighted_rms(x, fs) == pytest.approx(amp / math.sqrt(2) * 1.054, rel=0.01)
    # VDV of an (already weighted) sinusoid: (A^4 * 3T/8)^(1/4)
    assert vibration_dose_value(x, fs) == pytest.approx(amp * (3 * 60.0 / 8) ** 0.25, rel=1e-6)


def test_kpi_variants_pick_their_vertical_term() -> None:
    fs = 500.0
    az, q = sine(6.3, 1.0, fs, 30.0), sine(1.0, 0.1, fs, 30.0)
    rms_s = score_signals(az, q, fs, KpiConfig(kpi="rms"))
    wk_s = score_signals(az, q, fs, KpiConfig(kpi="iso_wk_rms"))
    vdv_s = score_signals(az, q, fs, KpiConfig(kpi="vdv"))
    assert wk_s.j == pytest.approx(wk_s.weighted_rms_accel_z + wk_s.rms_pitch_rate, rel=1e-12)
    assert vdv_s.j == pytest.approx(vdv_s.vdv_accel_z + vdv_s.rms_pitch_rate, rel=1e-12)
    assert rms_s.weighted_rms_accel_z == wk_s.weighted_rms_accel_z  # every part is always computed
    assert wk_s.weighted_rms_accel_z > rms_s.rms_accel_z  # Wk > 1 at 6.3 Hz


def test_psd_peaks_at_the_tone_and_integrates_to_the_variance() -> None:
    fs = 200.0
    az, q = sine(3.0, 1.0, fs, 20.0), sine(1.0, 0.1, fs, 20.0)
    s = score_signals(az, q, fs, KpiConfig(psd_segment_s=4.0, psd_max_hz=100.0))
    f = s.psd_frequency_hz
    assert f[np.argmax(s.psd_accel_z)] == pytest.approx(3.0, abs=0.25)
    assert f[np.argmax(s.psd_pitch_rate)] == pytest.approx(1.0, abs=0.25)
    df = f[1] - f[0]
    assert np.sum(s.psd_accel_z) * df == pytest.approx(0.5, rel=0.02)
    assert f.max() <= 100.0
    cut = score_signals(az, q, fs, KpiConfig(psd_max_hz=20.0))
    assert cut.psd_frequency_hz.max() <= 20.0


def _segment(az: np.ndarray, q: np.ndarray, valid: bool = True, reason: str = "") -> Segment:
    return Segment(
        run=RunId("c1", 3, 2),
        mode=MODE_EVENT,
        window_start_ns=123,
        window_length_s=az.size / 200.0,
        distance_start_m=0.0,
        distance_step_m=0.0,
        sample_rate_hz=200.0,
        lag_s=0.0,
        alignment_score=1.0,
        mean_speed_mps=8.3,
        target_speed_mps=8.3,
        coverage=1.0,
        accel_z=az,
        pitch_rate=q,
        valid=valid,
        reason=reason,
    )


def test_invalid_segment_gives_invalid_score_with_its_reason() -> None:
    seg = _segment(np.ones(10), np.ones(10), valid=False, reason="too slow: 27 km/h")
    s = score(seg)
    assert not s.valid and math.isnan(s.j)
    assert s.reason == "segment invalid: too slow: 27 km/h"
    assert s.run == RunId("c1", 3, 2) and s.window_start_ns == 123


def test_nan_in_a_valid_segment_is_refused() -> None:
    az = np.ones(100)
    az[40] = np.nan
    s = score(_segment(az, np.zeros(100)))
    assert not s.valid and "1 non-finite" in s.reason and math.isnan(s.j)


def test_score_of_segment_equals_score_of_its_signals() -> None:
    rng = np.random.default_rng(0)
    az, q = rng.standard_normal(500), 0.1 * rng.standard_normal(500)
    s = score(_segment(az, q))
    assert s.j == score_signals(az, q, 200.0).j
    assert s.run.trial_id == 3


def test_bad_kpi_configuration_is_refused() -> None:
    with pytest.raises(KpiError, match="kpi must be one of"):
        KpiConfig(kpi="comfort")
    with pytest.raises(KpiError, match="at least one weight"):
        KpiConfig(weight_accel_z=0.0, weight_pitch_rate=0.0)
    assert KpiConfig.from_params({"kpi": "vdv", "weight_accel_z": 2, "unrelated": 1}).weight_accel_z == 2.0


def test_outcomes_are_the_peaks_of_the_window_before_detrending() -> None:
    fs = 200.0
    az = sine(2.0, 1.5, fs, 5.0) + 0.4  # an offset: the peak counts it, the detrended RMS does not
    q = sine(1.0, 0.2, fs, 5.0, phase=1.0)
    az[300] = -4.0  # one jolt
    for cfg in (KpiConfig(), KpiConfig(detrend=True)):
        s = score_signals(az, q, fs, cfg)
        assert s.outcomes["peak_accel_z"] == pytest.approx(4.0)
        assert s.outcomes["peak_pitch_rate"] == pytest.approx(0.2, rel=1e-3)
    assert score(_segment(np.ones(10), np.ones(10), valid=False)).outcomes == {}


def test_outcomes_travel_in_the_run_score_message() -> None:
    from bac_measure.messages import score_to_msg

    s = score_signals(sine(2.0, 1.5, 200.0, 5.0), sine(1.0, 0.2, 200.0, 5.0), 200.0)
    m = score_to_msg(s)
    got = dict(zip(m.outcome_names, m.outcome_values, strict=True))
    assert got == pytest.approx(dict(s.outcomes))


def test_signals_no_vehicle_gives_are_an_invalid_run_with_the_reason_never_a_number() -> None:
    # outside review 2026-11-29: 1e200 m/s^2 scored valid with J = inf; 1e15 Hz ran out of memory; 1e-9 Hz was valid
    rng = np.random.default_rng(0)
    for kpi in KPIS:
        s = score_signals(np.full(1000, 1e200), np.zeros(1000), 200.0, KpiConfig(kpi=kpi))
        assert not s.valid and math.isnan(s.j) and "overflows" in s.reason and "1e+200" in s.reason, kpi
    for fs in (1e15, 1e-9, 0.5, 20_001.0):
        s = score_signals(rng.standard_normal(1000), np.zeros(1000), fs)
        assert not s.valid and math.isnan(s.j) and "outside the 1-20000 Hz" in s.reason, fs
    for fs in (1.0, 20_000.0):  # the limits themselves are an IMU stream's (imu_ingest's output_rate_hz from 1 Hz)
        assert score_signals(rng.standard_normal(1000), np.zeros(1000), fs).valid, fs


def test_a_gyro_in_deg_s_or_an_accelerometer_in_mm_s2_is_an_invalid_run_not_a_larger_j() -> None:
    # outside review 2026-11-29: deg/s labelled rad/s scored valid, J 5x too high
    fs = 200.0
    az, q = sine(2.0, 1.5, fs, 5.0), sine(1.0, 0.08, fs, 5.0)
    good = score_signals(az, q, fs)
    assert good.valid and good.rms_pitch_rate == pytest.approx(0.08 / math.sqrt(2), rel=1e-2)
    deg = score_signals(az, np.degrees(q), fs)
    assert not deg.valid and math.isnan(deg.j)
    assert "RMS pitch rate 3.24 rad/s is beyond a car body's" in deg.reason and "0.0566 rad/s" in deg.reason
    mm = score_signals(az * 1000.0, q, fs)
    assert not mm.valid and "RMS a_z 1.06e+03 m/s^2 is beyond" in mm.reason
    # 0 turns the checks off (a rig), and the limits are validated
    assert score_signals(az * 1000.0, np.degrees(q), fs, KpiConfig(max_rms_accel_z=0, max_rms_pitch_rate=0)).valid
    with pytest.raises(KpiError, match="max_rms_pitch_rate must be finite and >= 0"):
        KpiConfig(max_rms_pitch_rate=-1.0)
