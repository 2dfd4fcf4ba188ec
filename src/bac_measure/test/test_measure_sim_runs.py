"""The measurement chain on runs of the simulated vehicle (bac_sim.run), checked against its ground truth.

The simulator's IMU is mounted with a small rotation, has biases, noise, quantization and its own rate
(400 Hz); its driver starts each run metres apart and drives with a cruise-control error. The chain
must still cut every run at the same road position and find the simulator's true J.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bac_imu.ingest import IngestConfig, ingest_all
from bac_measure.kpi import score
from bac_measure.segmentation import ImuSeries, OdomSeries, Reference, SegmentConfig, cut_run

sim_run = pytest.importorskip("bac_sim.run")
NS = 1_000_000_000
T0 = 1_000 * NS
# the simulated IMU's mount (bac_sim.run.ImuSpec), configured as it would be for a real car
INGEST = IngestConfig(output_rate_hz=200.0, mount_roll_deg=0.8, mount_pitch_deg=-1.2, mount_yaw_deg=0.5)
ROAD = SegmentConfig(
    mode="distance", target_speed_mps=60 / 3.6, distance_start_m=100.0, distance_end_m=1600.0, max_shift_m=20.0
)
BUMP = SegmentConfig(mode="event", target_speed_mps=30 / 3.6, trigger_threshold_mps2=1.0)


def chain(rec, cfg: SegmentConfig, ref: Reference | None = None):
    t = T0 + np.round(rec.t * NS).astype(np.int64)
    out, health = ingest_all(t, rec.accel, rec.gyro, INGEST)
    odom = OdomSeries(T0 + np.round(rec.odom_t * NS).astype(np.int64), rec.distance, rec.speed)
    seg = cut_run(ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate), odom, cfg, T0, ref)
    # where the front axle really was when the window started (the simulator's truth)
    x0 = float(np.interp((seg.window_start_ns - T0) / NS, rec.t, rec.truth["front_axle_m"])) if seg.valid else np.nan
    return seg, score(seg), x0, health


def test_road_runs_are_cut_at_the_same_road_position_and_score_the_true_j() -> None:
    recs = [
        sim_run.simulate_run({"damping_front": 0.5, "damping_rear": 0.5}, "road", seed=1),
        sim_run.simulate_run({"damping_front": 0.1, "damping_rear": 0.9}, "road", seed=2),
    ]
    seg0, s0, x00, health = chain(recs[0], ROAD)
    assert seg0.valid, seg0.reason
    assert health.rate_hz == pytest.approx(400.0, rel=1e-3) and health.gaps == 0
    ref = Reference.from_segment(seg0, ROAD)
    seg1, s1, x01, _ = chain(recs[1], ROAD, ref)
    assert seg1.valid, seg1.reason
    # the two drivers started metres apart; the windows start at the same road position (one grid step)
    start_offset = recs[1].distance[0] - recs[0].distance[0]
    assert abs(x01 - x00) < seg1.distance_step_m, (x00, x01, start_offset)
    assert seg1.alignment_score > 0.7
    for s, rec in ((s0, recs[0]), (s1, recs[1])):
        assert s.j == pytest.approx(rec.j_true, rel=0.005), (s.j, rec.j_true)


def test_bump_runs_score_the_true_j_and_a_slow_run_is_rejected() -> None:
    cals = [(0.5, 0.5), (0.0, 1.0), (1.0, 0.2)]
    recs = [
        sim_run.simulate_run({"damping_front": f, "damping_rear": r}, "bump", seed=10 + i)
        for i, (f, r) in enumerate(cals)
    ]
    ref = None
    xs = []
    for rec in recs:
        seg, s, x0, _ = chain(rec, BUMP, ref)
        assert seg.valid, seg.reason
        ref = ref or Reference.from_segment(seg, BUMP)
        assert s.j == pytest.approx(rec.j_true, rel=0.01), (s.j, rec.j_true)
        xs.append(x0)
    # windows at the same place relative to the bump, whatever the damping (a few centimetres at 30 km/h)
    assert np.ptp(xs) < 0.35, xs
    trigger_only = replace(BUMP, align_signal="none")
    xs_t = [
        chain(rec, trigger_only, Reference.from_segment(chain(recs[0], trigger_only)[0], trigger_only))[2]
        for rec in recs
    ]
    assert np.ptp(xs_t) < 0.2, xs_t
    slow = sim_run.simulate_run(
        {"damping_front": 0.5, "damping_rear": 0.5},
        "bump",
        seed=20,
        driver=sim_run.DriverModel(bad_run_probability=1.0),
    )
    seg, s, _, _ = chain(slow, BUMP, ref)
    assert slow.bad_run and not seg.valid and seg.reason.startswith("too slow") and not s.valid
