"""vehicle_sim as a real process: trial in, every IMU sample out, /clock, the ECU snapshot."""

from __future__ import annotations

import re
import threading
from typing import Any

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu

from bac_common.rosnode import QOS_LATCHED, QOS_STREAM
from bac_msgs.msg import Trial
from bac_sim.run import simulate_run

from conftest import wait_for

pytestmark = pytest.mark.integration

# vehicle_sim runs here with imu_reliability reliable (as in the sim profile): "every sample" is then a promise
# of the transport, not luck on a loaded machine (a best-effort stream may drop samples, like a real IMU's)
QOS_IMU_IN = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=20000, reliability=ReliabilityPolicy.RELIABLE)


class Listener:
    def __init__(self, node: Any) -> None:
        self.lock = threading.Lock()
        self.imu: list[Imu] = []
        self.odom: list[Odometry] = []
        self.clock: list[float] = []
        node.create_subscription(Imu, "imu/data_raw", self._imu, QOS_IMU_IN)
        node.create_subscription(Odometry, "vehicle/odom", self._odom, QOS_STREAM)
        node.create_subscription(Clock, "/clock", self._clock, 10)
        self.trial_pub = node.create_publisher(Trial, "bac/trial", QOS_LATCHED)

    def _imu(self, m: Imu) -> None:
        with self.lock:
            self.imu.append(m)

    def _odom(self, m: Odometry) -> None:
        with self.lock:
            self.odom.append(m)

    def _clock(self, m: Clock) -> None:
        with self.lock:
            self.clock.append(m.clock.sec + 1e-9 * m.clock.nanosec)

    def ready(self, trial: int, attempt: int) -> None:
        t = Trial()
        t.campaign_id = "test"
        t.trial_id = trial
        t.attempt = attempt
        t.state = Trial.STATE_READY_TO_DRIVE
        self.trial_pub.publish(t)


def test_a_ready_trial_is_driven_and_every_sample_arrives(procs: Any, ros_context: Any) -> None:
    seed = 7
    procs.python(
        "vehicle_sim",
        [
            "-m",
            "bac_sim.vehicle_sim_node",
            "--ros-args",
            "-p",
            "scenario:=bump",
            "-p",
            f"seed:={seed}",
            "-p",
            "imu_reliability:=reliable",
        ],
    )
    node = ros_context.node("probe")
    lis = Listener(node)
    wait_for(lambda: len(lis.clock) > 5, 30, what="/clock while idle")
    with lis.lock:
        idle0 = lis.clock[-1]
    wait_for(lambda: lis.clock[-1] > idle0 + 0.2, 10, what="/clock advancing while idle")
    wait_for(lambda: node.count_subscribers("bac/trial") > 0 and node.count_publishers("imu/data_raw") > 0, 30)
    lis.ready(1, 1)
    # the same run, computed here: seeded runs are deterministic
    expected = simulate_run({"damping_front": 0.5, "damping_rear": 0.5}, "bump", seed=seed)
    wait_for(lambda: len(lis.odom) >= expected.odom_t.size, 60, what="all odometry of the run")
    try:
        wait_for(lambda: len(lis.imu) >= expected.t.size, 10, what="all IMU samples of the run")
    finally:
        print(f"received {len(lis.imu)} of {expected.t.size} IMU samples")
    with lis.lock:
        imu = list(lis.imu)
        odom = list(lis.odom)
    assert len(imu) == expected.t.size  # not one sample lost at the default realtime factor
    acc = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in imu])
    gyro = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in imu])
    np.testing.assert_allclose(acc, expected.accel, atol=1e-9)
    np.testing.assert_allclose(gyro, expected.gyro, atol=1e-9)
    stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in imu])
    np.testing.assert_allclose(np.diff(stamps), 1 / 400.0, atol=2e-6)
    assert imu[0].header.frame_id == "imu_link"
    # standard odometry (REP 105): the pose in odom (its origin where the first run started, the road along +x),
    # the forward speed in base_link
    assert {(o.header.frame_id, o.child_frame_id) for o in odom} == {("odom", "base_link")}
    dist = np.array([o.pose.pose.position.x for o in odom])
    assert dist[0] == pytest.approx(0.0) and np.all(np.diff(dist) > 0)
    assert dist[-1] == pytest.approx(expected.distance[-1])
    assert all(o.pose.pose.position.y == 0.0 and o.pose.pose.orientation.w == 1.0 for o in odom)
    speed = np.array([o.twist.twist.linear.x for o in odom])
    assert speed.mean() == pytest.approx(30 / 3.6, rel=0.05)
    # the clock covered the run in sim time
    wait_for(lambda: lis.clock[-1] >= stamps[-1], 10, what="/clock past the run")
    # the same trial again is not a new run; the next attempt is
    n_before = len(lis.imu)
    lis.ready(1, 1)
    lis.ready(1, 2)
    wait_for(lambda: "run of trial 1 attempt 2 published" in procs.log("vehicle_sim"), 60, what="the second attempt")
    log = procs.log("vehicle_sim")
    published = int(re.search(r"attempt 2 published \((\d+) IMU", log).group(1))  # type: ignore[union-attr]
    assert published > 0 and n_before == expected.t.size
    assert log.count("driving trial 1 attempt 1") == 1
    # the second run's pose continues from where the car is: it came back to the start (at 60 km/h, unpublished)
    second = simulate_run({"damping_front": 0.5, "damping_rear": 0.5}, "bump", seed=seed + 1)
    wait_for(lambda: len(lis.odom) >= len(odom) + second.odom_t.size, 30, what="the second run's odometry")
    with lis.lock:
        odom2 = list(lis.odom)[len(odom) :]
    x2 = np.array([o.pose.pose.position.x for o in odom2])
    np.testing.assert_allclose(x2, second.start_m - expected.start_m + second.distance, atol=1e-9)
    t_end1 = odom[-1].header.stamp.sec + 1e-9 * odom[-1].header.stamp.nanosec
    t_start2 = odom2[0].header.stamp.sec + 1e-9 * odom2[0].header.stamp.nanosec
    back = float(dist[-1] - x2[0])
    assert back > 30.0 and t_start2 - t_end1 >= back / (60 / 3.6) - 1e-6, (back, t_start2 - t_end1)
    assert "the car comes back" in log
