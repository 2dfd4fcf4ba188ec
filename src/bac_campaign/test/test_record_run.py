"""record_run writes bags the measurement chain can read, with their truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bac_campaign.record_run import main
from bac_sim.run import simulate_run


def test_a_recorded_run_reads_back_identical(tmp_path: Path) -> None:
    from bac_measure.bagio import read_imu, read_odom

    out = tmp_path / "bump"
    assert (
        main([str(out), "--scenario", "bump", "--set", "damping_front=0.8", "--seed", "3", "--start-time", "50"]) == 0
    )
    rec = simulate_run({"damping_front": 0.8, "damping_rear": 0.5}, "bump", seed=3)
    imu = read_imu(out)
    odom = read_odom(out)
    assert len(imu) == rec.t.size and len(odom) == rec.odom_t.size
    np.testing.assert_allclose(imu.accel, rec.accel)
    np.testing.assert_allclose(imu.stamp_ns * 1e-9, 50.0 + rec.t, atol=1e-9)
    np.testing.assert_allclose(odom.distance_m, rec.distance)
    truth = json.loads((out / "truth.json").read_text())
    assert truth["j_true"] == rec.j_true
    assert truth["window_start_s"] == 50.0 + rec.window_start_s
    # imu at rest reads +g on z (the IMU frame is nearly the vehicle frame)
    assert 9.7 < float(np.median(imu.accel[:, 2])) < 9.9


def test_out_of_bounds_values_write_nothing(tmp_path: Path) -> None:
    out = tmp_path / "bad"
    assert main([str(out), "--scenario", "bump", "--set", "damping_front=1.5"]) == 2
    assert not out.exists()
