"""The IMU ingestion core: known answers, faults, and chunked == one-shot."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bac_imu.ingest import (
    ERROR,
    GRAVITY,
    NS,
    OK,
    STALE,
    WARN,
    ImuIngestor,
    IngestConfig,
    IngestError,
    IngestOutput,
    diagnose,
    ingest_all,
    roll_pitch_from_gravity,
    rotation_matrix,
)

T0 = 1_700_000_000 * NS  # a plausible ROS time


def stream(
    n: int,
    fs: float = 500.0,
    seed: int = 0,
    jitter_ns: int = 0,
    az: np.ndarray | None = None,
    q: np.ndarray | None = None,
    noise: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A raw stream in a level sensor: gravity on z plus ``az``; pitch rate ``q``."""
    rng = np.random.default_rng(seed)
    t = T0 + np.round(np.arange(n) * NS / fs).astype(np.int64)
    if jitter_ns:
        t = t + rng.integers(-jitter_ns, jitter_ns + 1, n)
    acc = noise * rng.standard_normal((n, 3))
    acc[:, 2] += GRAVITY + (az if az is not None else 0.0)
    gyr = noise * 0.1 * rng.standard_normal((n, 3))
    if q is not None:
        gyr[:, 1] += q
    return t, acc, gyr


def chunked(cfg: IngestConfig, t, acc, gyr, seed: int, max_chunk: int = 200, recv=None) -> IngestOutput:
    ing = ImuIngestor(cfg)
    rng = np.random.default_rng(seed)
    parts, i = [], 0
    while i < len(t):
        k = int(rng.integers(1, max_chunk))
        r = None if recv is None else recv[i : i + k]
        parts.append(ing.push(t[i : i + k], acc[i : i + k], gyr[i : i + k], r))
        i += k
    parts.append(ing.flush())
    return IngestOutput.concatenate([p for p in parts if len(p)])


def same(a: IngestOutput, b: IngestOutput) -> None:
    assert np.array_equal(a.stamp_ns, b.stamp_ns)
    assert np.array_equal(a.accel, b.accel, equal_nan=True), np.argwhere(~((a.accel == b.accel) | np.isnan(a.accel)))[
        :5
    ]
    assert np.array_equal(a.gyro, b.gyro, equal_nan=True)


# --- known answers ---------------------------------------------------------------------------------


def test_sinusoid_passes_through_with_gravity_removed_and_fixed_rate() -> None:
    fs, n = 500.0, 10_000
    k = np.arange(n)
    t, acc, gyr = stream(n, fs, az=1.5 * np.sin(2 * np.pi * 3.0 * k / fs), q=0.2 * np.cos(2 * np.pi * 1.0 * k / fs))
    out, health = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0))
    assert np.all(np.diff(out.stamp_ns) == 5_000_000)
    assert out.stamp_ns[0] == t[0]
    # steady state (skip the filter's first second): RMS = A / sqrt(2), gravity gone
    az, q = out.accel_z[200:], out.pitch_rate[200:]
    assert abs(np.mean(az)) < 0.01
    assert np.sqrt(np.mean(az**2)) == pytest.approx(1.5 / math.sqrt(2), rel=2e-3)
    assert np.sqrt(np.mean(q**2)) == pytest.approx(0.2 / math.sqrt(2), rel=2e-3)
    assert health.rate_hz == pytest.approx(500.0, rel=1e-6)
    assert health.gaps == 0 and health.nonfinite == 0 and health.samples_out_nan == 0


def test_anti_alias_filter_removes_what_would_fold_and_keeps_the_band() -> None:
    """1 kHz in, 200 Hz out: a 160 Hz tone would alias to 40 Hz; it must be gone, 10 Hz must stay."""
    fs, n = 1000.0, 20_000
    k = np.arange(n)
    t, acc, gyr = stream(n, fs, az=np.sin(2 * np.pi * 160.0 * k / fs))
    out, _ = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0))
    assert np.sqrt(np.mean(out.accel_z[400:] ** 2)) < 0.01  # without the filter: 0.707
    t, acc, gyr = stream(n, fs, az=np.sin(2 * np.pi * 10.0 * k / fs))
    out, _ = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0))
    assert np.sqrt(np.mean(out.accel_z[400:] ** 2)) == pytest.approx(1 / math.sqrt(2), rel=5e-3)


def test_same_rate_stream_is_passed_unchanged() -> None:
    fs, n = 200.0, 1000
    rng = np.random.default_rng(3)
    az = rng.standard_normal(n)
    t, acc, gyr = stream(n, fs, az=az)
    out, _ = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0))
    assert np.array_equal(out.stamp_ns, t)
    np.testing.assert_allclose(out.accel_z, az, atol=1e-12)


@pytest.mark.parametrize("roll,pitch,yaw", [(3.2, -4.7, 0.0), (-12.0, 8.5, 30.0), (0.4, 0.3, -90.0)])
def test_tilted_mount_recovered_from_standstill_within_half_a_degree(roll: float, pitch: float, yaw: float) -> None:
    fs = 200.0
    rng = np.random.default_rng(7)
    n_still, n_move = 400, 2000
    n = n_still + n_move
    # vehicle frame: standstill, then driving (vertical motion, pitch, surge)
    v_acc = np.zeros((n, 3))
    v_acc[:, 2] = GRAVITY
    k = np.arange(n_move)
    v_acc[n_still:, 2] += 2.0 * np.sin(2 * np.pi * 1.3 * k / fs)
    v_acc[n_still:, 0] += 0.8 * np.sin(2 * np.pi * 0.2 * k / fs)
    v_gyr = np.zeros((n, 3))
    v_gyr[n_still:, 1] = 0.1 * np.sin(2 * np.pi * 1.1 * k / fs)
    v_acc += 0.03 * rng.standard_normal((n, 3))  # sensor noise
    bias = np.array([0.004, -0.006, 0.002])
    R = rotation_matrix(roll, pitch, yaw)
    s_acc = v_acc @ R  # sensor frame: s = R.T v  (row vectors: v @ R)
    s_gyr = v_gyr @ R + bias
    t = T0 + np.arange(n) * 5_000_000
    cfg = IngestConfig(output_rate_hz=200.0, mount_source="standstill", bias_source="standstill", mount_yaw_deg=yaw)
    out, health = ingest_all(t, s_acc, s_gyr, cfg)
    r_est, p_est, y_est = health.mount_rpy_deg
    assert abs(r_est - roll) < 0.5 and abs(p_est - pitch) < 0.5, health.mount_rpy_deg
    assert y_est == yaw
    assert health.mount_source == "standstill" and health.bias_source == "standstill"
    assert health.standstill_window_ns is not None and health.standstill_window_ns[1] <= t[n_still]
    # vehicle-frame signals recovered: vertical motion without gravity, pitch rate without bias
    np.testing.assert_allclose(out.accel_z[n_still:], v_acc[n_still:, 2] - GRAVITY, atol=0.15)
    np.testing.assert_allclose(out.pitch_rate[n_still:], v_gyr[n_still:, 1], atol=0.01)
    assert np.sqrt(np.mean((out.pitch_rate - v_gyr[:, 1]) ** 2)) < 2e-3


def test_roll_pitch_from_gravity_inverts_rotation_matrix() -> None:
    for roll, pitch in [(10.0, 20.0), (-35.0, 5.0), (0.0, -60.0)]:
        g_sensor = np.array([0.0, 0.0, GRAVITY]) @ rotation_matrix(roll, pitch, 17.0)
        r, p = roll_pitch_from_gravity(g_sensor)
        assert r == pytest.approx(roll, abs=1e-9) and p == pytest.approx(pitch, abs=1e-9)


def test_no_standstill_falls_back_to_configured_mount_and_says_so() -> None:
    fs, n = 100.0, 4000
    k = np.arange(n)
    t, acc, gyr = stream(n, fs, az=3.0 * np.sin(2 * np.pi * 1.0 * k / fs))
    cfg = IngestConfig(
        output_rate_hz=100.0,
        mount_source="standstill",
        standstill_fallback="config",
        standstill_timeout_s=10.0,
        mount_roll_deg=1.0,
    )
    ing = ImuIngestor(cfg)
    first = ing.push(t[:900], acc[:900], gyr[:900])
    assert len(first) == 0 and not ing.started  # still looking within the first 10 s
    rest = ing.push(t[900:], acc[900:], gyr[900:])
    h = ing.health()
    assert ing.started and len(rest) > 3000
    assert h.mount_source == "config (no standstill found)" and h.mount_rpy_deg == (1.0, 0.0, 0.0)
    assert any(e.kind == "no_standstill" for e in h.events)


def test_no_standstill_takes_roll_and_pitch_from_the_long_run_mean_of_the_accelerometer() -> None:
    """The default fallback: gravity from the mean over the searched span; chunked == one shot."""
    fs, n = 100.0, 4000
    k = np.arange(n)
    t, acc, gyr = stream(n, fs, az=3.0 * np.sin(2 * np.pi * 1.0 * k / fs))
    R = rotation_matrix(-90.0, 4.0, 0.0)  # y axis up, a little pitched
    acc_s, gyr_s = acc @ R, gyr @ R  # sensor = R.T @ vehicle
    cfg = IngestConfig(output_rate_hz=100.0, mount_source="standstill", standstill_timeout_s=10.0)
    out, h = ingest_all(t, acc_s, gyr_s, cfg)
    assert h.mount_source.startswith("mean accelerometer over 10.0 s")
    assert h.mount_rpy_deg[0] == pytest.approx(-90.0, abs=0.5) and h.mount_rpy_deg[1] == pytest.approx(4.0, abs=0.5)
    assert abs(h.mean_accel_mps2[2]) < 0.05 and h.gravity_problem() == ""
    ing = ImuIngestor(cfg)
    parts = [ing.push(t[i : i + 333], acc_s[i : i + 333], gyr_s[i : i + 333]) for i in range(0, n, 333)]
    chunked = IngestOutput.concatenate([p for p in [*parts, ing.flush()] if len(p)])
    assert np.array_equal(chunked.accel, out.accel) and np.array_equal(chunked.gyro, out.gyro)


# --- faults -------------------------------------------------------------------------------------------


def test_nan_and_half_second_gap_are_reported_and_leave_holes() -> None:
    fs, n = 500.0, 5000
    t, acc, gyr = stream(n, fs, noise=0.01)
    acc[1000, 1] = np.nan  # one NaN sample at 2.0 s
    keep = np.ones(n, bool)
    keep[2500:2750] = False  # 0.5 s without data from 5.0 s
    t, acc, gyr = t[keep], acc[keep], gyr[keep]
    ing = ImuIngestor(IngestConfig(output_rate_hz=200.0))
    out = ing.push(t, acc, gyr)
    h = ing.health()
    assert h.nonfinite == 1
    assert h.gaps == 1
    assert h.longest_gap_s == pytest.approx(0.502, abs=1e-9)  # from the last sample before to the first after
    kinds = {e.kind: e for e in h.events}
    assert kinds["nonfinite"].start_ns == T0 + 2 * NS
    assert kinds["gap"].start_ns == T0 + round(4.998 * NS) and kinds["gap"].end_ns == T0 + 5_500_000_000
    # holes on the output grid: around the NaN sample, and the whole gap
    t_out = (out.stamp_ns - T0) / NS
    nan = np.isnan(out.accel_z)
    assert np.all(nan[(t_out > 1.9985) & (t_out < 2.0015)])
    assert np.all(nan[(t_out > 4.999) & (t_out < 5.4995)])
    assert np.count_nonzero(nan) == h.samples_out_nan
    assert 99 <= np.count_nonzero(nan) <= 103
    assert not np.any(nan[(t_out > 2.01) & (t_out < 4.99)])  # the filter restarts cleanly after the hole
    d = diagnose(h)
    assert d.level == ERROR
    assert "1 gap" in d.message and "1 NaN/inf sample" in d.message
    values = dict(d.values)
    assert values["gaps"] == "1" and values["nonfinite"] == "1" and float(values["longest_gap_s"]) > 0.5


def test_duplicated_and_out_of_order_stamps_are_dropped_and_counted() -> None:
    fs, n = 200.0, 400
    t, acc, gyr = stream(n, fs)
    order = np.arange(n)
    order[[100, 101]] = order[[101, 100]]  # swapped: the second arrives late
    order = np.insert(order, 200, 199)  # a duplicate
    out, h = ingest_all(t[order], acc[order], gyr[order], IngestConfig(output_rate_hz=200.0))
    assert h.duplicates == 1 and h.out_of_order == 1
    assert np.all(np.diff(out.stamp_ns) == 5_000_000)
    assert np.count_nonzero(np.isnan(out.accel_z)) == 0  # one dropped sample is interpolated, not a gap
    assert diagnose(h).level == WARN


def test_saturation_marks_samples_bad() -> None:
    fs, n = 200.0, 400
    t, acc, gyr = stream(n, fs)
    acc[150:153, 2] = 16 * 9.81  # at full scale
    out, h = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0, accel_range=16 * 9.81))
    assert h.saturated == 3
    assert np.count_nonzero(np.isnan(out.accel_z)) == 3
    assert any(e.kind == "saturation" for e in h.events)


def test_backward_clock_jump_restarts_the_grid() -> None:
    fs, n = 200.0, 800
    t, acc, gyr = stream(n, fs)
    t[400:] -= 10 * NS  # the driver's clock stepped back 10 s
    out, h = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0))
    assert h.clock_jumps == 1 and h.out_of_order == 0
    assert out.stamp_ns[400] == t[400]  # new grid anchored at the first sample after the jump
    assert np.count_nonzero(np.isnan(out.accel_z)) == 0


def test_forward_jump_with_receive_clock_is_a_clock_jump_not_a_gap() -> None:
    fs, n = 200.0, 800
    t, acc, gyr = stream(n, fs)
    recv = t.copy()
    t[400:] += 30 * NS  # stamps jump forward by 30 s, the data kept coming
    out, h = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0), recv_ns=recv)
    assert h.clock_jumps == 1 and h.gaps == 0
    out2, h2 = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0))  # no receive times: a long gap
    assert h2.clock_jumps == 0 and h2.gaps == 0 and h2.restarts == 1  # a stream that stopped and resumed
    assert any(e.kind == "restart" and "resumed after 30.005 s" in e.detail for e in h2.events)
    assert diagnose(h2).level == WARN
    assert len(out) == len(out2) == n


def test_rate_and_jitter_are_measured() -> None:
    t, acc, gyr = stream(3000, 400.0, jitter_ns=200_000)  # uniform +-0.2 ms: std of a step = 0.2/sqrt(6)*2 ms
    _, h = ingest_all(t, acc, gyr, IngestConfig(output_rate_hz=200.0))
    assert h.rate_hz == pytest.approx(400.0, rel=0.01)
    assert h.jitter_ms == pytest.approx(0.2 * 2 / math.sqrt(6), rel=0.1)
    assert "jitter" in h.summary() and "no gaps" in h.summary()


# --- streaming ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_chunked_output_equals_one_shot_output(seed: int) -> None:
    """Faults, a standstill search and a filter: any chunking gives bit-for-bit the same stream."""
    fs, n = 500.0, 12_000
    rng = np.random.default_rng(seed)
    t, acc, gyr = stream(n, fs, seed=seed, jitter_ns=100_000, noise=0.02)
    acc[1000:, 2] += rng.standard_normal(n - 1000)  # standstill for 2 s, then driving
    acc[3000, 0] = np.inf
    gyr[3001, 2] = np.nan
    keep = np.ones(n, bool)
    keep[5000:5300] = False
    order = np.flatnonzero(keep)
    order = np.insert(order, 4000, order[3990])  # duplicate / out of order
    t, acc, gyr = t[order], acc[order], gyr[order]
    t[9000:] -= 5 * NS  # a clock jump
    cfg = IngestConfig(
        output_rate_hz=200.0,
        mount_source="standstill",
        bias_source="standstill",
        highpass_hz=0.2,
        rate_probe_samples=30,
    )
    one, h1 = ingest_all(t, acc, gyr, cfg)
    many = chunked(cfg, t, acc, gyr, seed)
    same(one, many)
    if seed == 1:  # one sample per push, as a node without batching would do
        singles = chunked(cfg, t[:3200], acc[:3200], gyr[:3200], seed, max_chunk=2)
        same(ingest_all(t[:3200], acc[:3200], gyr[:3200], cfg)[0], singles)
    assert (
        h1.gaps == 1
        and h1.nonfinite == 2
        and h1.out_of_order == 1
        and h1.clock_jumps == 1
        and h1.mount_source == "standstill"
    )


def test_diagnose_levels() -> None:
    assert diagnose(ImuIngestor().health()).level == STALE
    t, acc, gyr = stream(500, 200.0)
    ing = ImuIngestor(IngestConfig(output_rate_hz=200.0))
    ing.push(t, acc, gyr)
    h = ing.health()
    assert diagnose(h).level == OK
    assert diagnose(h, silent_s=3.0).level == STALE
    assert diagnose(h, expected_rate_hz=400.0).level == WARN  # half the expected rate
    assert diagnose(h, before=h).level == OK


def test_faults_followed_by_silence_are_still_reported() -> None:
    t, acc, gyr = stream(500, 200.0)
    acc[100, 0] = np.nan
    keep = (t < t[300]) | (t >= t[300] + 500_000_000)  # a 0.5 s gap
    ing = ImuIngestor(IngestConfig(output_rate_hz=200.0))
    before = ing.health()
    ing.push(t[keep], acc[keep], gyr[keep])
    h = ing.health()
    d = diagnose(h, before, silent_s=3.0)  # the stream stopped right after the faults
    assert d.level == ERROR and "gap" in d.message and "NaN/inf" in d.message and "no IMU data" in d.message
    assert diagnose(h, h, silent_s=3.0).level == STALE  # the next report: only the silence


def test_bad_configuration_is_refused_with_reasons() -> None:
    with pytest.raises(IngestError, match="output_rate_hz"):
        IngestConfig(output_rate_hz=0.0)
    with pytest.raises(IngestError, match="mount_source"):
        IngestConfig(mount_source="guess")
    with pytest.raises(IngestError, match=r"accel \(n, 3\)"):
        ImuIngestor().push([1, 2], np.zeros((2, 2)), np.zeros((2, 3)))


def test_config_from_node_parameters() -> None:
    cfg = IngestConfig.from_params({"output_rate_hz": 250, "mount_source": "standstill", "qos_depth": 10})
    assert cfg.output_rate_hz == 250.0 and isinstance(cfg.output_rate_hz, float)
    assert cfg.mount_source == "standstill"


def test_a_sensor_that_measures_no_gravity_is_called_dead_not_upside_down() -> None:
    # outside review 2026-11-29: an all-zero IMU was diagnosed "the IMU is upside down ... roll 180"
    fs, n = 100.0, 2000
    t, acc, gyr = stream(n, fs)
    dead = ingest_all(t, np.zeros_like(acc), np.zeros_like(gyr), IngestConfig(output_rate_hz=100.0))[1]
    problem = dead.gravity_problem()
    assert "measures 0.00 m/s^2 of gravity in all" in problem and "dead or unpowered" in problem
    assert "upside down" not in problem
    flipped = ingest_all(t, -acc, gyr, IngestConfig(output_rate_hz=100.0))[1]  # a sensor mounted upside down
    assert "the IMU is upside down" in flipped.gravity_problem()
