"""The simulated car's odometry track: a continuous pose in the odom frame, the way back taking its time."""

from __future__ import annotations

import numpy as np
import pytest

from bac_sim.odometry import OdomTrack
from bac_sim.run import RunRecording


def rec(start_m: float, length_m: float, speed: float = 10.0, rate: float = 100.0) -> RunRecording:
    t = np.arange(0.0, length_m / speed, 1 / rate)
    return RunRecording(
        scenario="test", calibration={}, seed=0, t=t, accel=np.zeros((t.size, 3)), gyro=np.zeros((t.size, 3)),
        odom_t=t, distance=speed * t, speed=np.full(t.size, speed), start_m=start_m,
    )  # fmt: skip


def test_runs_continue_from_where_the_car_is() -> None:
    track = OdomTrack(way_back_speed_mps=20.0)
    a = track.place(rec(start_m=37.0, length_m=50.0), earliest_t0=10.0)
    # the odom frame's origin is where the first run started: the road along +x from there
    assert a.t0 == 10.0 and a.x[0] == 0.0 and a.way_back_m == 0.0
    np.testing.assert_allclose(a.x, 10.0 * np.arange(a.x.size) / 100.0)
    track.driven(a.t0 + 4.99, float(a.x[-1]))
    # the next run starts 3 m further down the road: the car drove back 46.9 m at 20 m/s first
    b = track.place(rec(start_m=40.0, length_m=50.0), earliest_t0=a.t0 + 5.0)
    assert b.x[0] == pytest.approx(3.0) and b.way_back_m == pytest.approx(49.9 - 3.0)
    assert b.t0 == pytest.approx(a.t0 + 4.99 + (49.9 - 3.0) / 20.0)
    # when the agent took longer than the way back, the run starts when it is asked for
    track.driven(b.t0 + 4.99, float(b.x[-1]))
    c = track.place(rec(start_m=35.0, length_m=50.0), earliest_t0=b.t0 + 60.0)
    assert c.t0 == b.t0 + 60.0 and c.x[0] == pytest.approx(-2.0)


def test_a_bad_way_back_speed_is_refused() -> None:
    with pytest.raises(ValueError, match="way-back speed"):
        OdomTrack(0.0)
