"""The car profile by configuration alone: a real CAN link to an ECU, an IMU driver's best-effort stream.

No simulated vehicle in the graph: a separate ECU process on the CAN bus stands in for the car's ECU and
the test publishes like an IMU driver (best effort, a standstill first, as after switching the car on).
The campaign must get its first calibration confirmed by that ECU and tell the driver to drive; on Ctrl-C
the graph stops cleanly and the ECU is left on the safe baseline.
"""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bac_common.rosnode import QOS_LATCHED, QOS_SENSOR
from bac_msgs.msg import Calibration, Trial

from conftest import ROOT, wait_for

pytestmark = pytest.mark.integration
DEFINITION = ROOT / "ros_ws" / "config" / "calibrations" / "controller_i.yaml"
CHANNEL = "239.74.163.9"


def test_car_profile_reaches_the_ecu_and_the_driver(
    procs: Any, ros_context: Any, ros_env: dict[str, str], tmp_path: Path
) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu

    procs.python("ecu", ["-m", "bac_sim.ecu", "--interface", "udp_multicast", "--channel", CHANNEL,
                         "--definition", str(DEFINITION)])  # fmt: skip
    camp = tmp_path / "camp"
    launcher = procs.python("car", ["-m", "bac_bringup.cli", "launch", "car", "--campaign-dir", str(camp),
                                    "-p", "ecu_bridge.can.interface:=udp_multicast",
                                    "-p", f"ecu_bridge.can.channel:={CHANNEL}"])  # fmt: skip
    node = ros_context.node("car_test")
    trials: list[Trial] = []
    confirmed: list[Calibration] = []
    node.create_subscription(Trial, "bac/trial", trials.append, QOS_LATCHED)
    node.create_subscription(Calibration, "bac/calibration", confirmed.append, QOS_LATCHED)
    vehicle: list[Imu] = []
    node.create_subscription(
        Imu, "imu/vehicle", vehicle.append,
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE),
    )  # fmt: skip
    imu_pub = node.create_publisher(Imu, "imu/data_raw", QOS_SENSOR)
    wait_for(lambda: imu_pub.get_subscription_count() > 0, 60, what="imu_ingest subscribing imu/data_raw")

    # an IMU driver: 200 Hz, a standstill (the car just switched on), slightly tilted on the seat rail
    rng = np.random.default_rng(1)
    tilt = math.radians(2.0)
    t0 = node.get_clock().now().nanoseconds

    def sample(i: int) -> Imu:
        m = Imu()
        t = t0 + i * 5_000_000
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 1_000_000_000)
        m.header.frame_id = "imu_link"
        m.linear_acceleration.x = -9.80665 * math.sin(tilt) + rng.normal(0, 0.02)
        m.linear_acceleration.z = 9.80665 * math.cos(tilt) + rng.normal(0, 0.02)
        m.angular_velocity.y = 0.001 + rng.normal(0, 0.002)
        return m

    i = 0

    def publish_some() -> bool:
        nonlocal i
        for _ in range(20):
            imu_pub.publish(sample(i))
            i += 1
        return bool(vehicle) and any(t.state == Trial.STATE_READY_TO_DRIVE for t in trials)

    wait_for(publish_some, 90, interval=0.1, what="imu/vehicle flowing and trial 1 ready to drive")
    ready = next(t for t in trials if t.state == Trial.STATE_READY_TO_DRIVE)
    assert ready.trial_id == 1 and ready.instruction
    # the ECU confirmed exactly the trial's calibration before the driver was told to drive
    wait_for(lambda: confirmed, 10, what="bac/calibration")
    conf = confirmed[-1]
    assert conf.trial_id == 1 and conf.crc32 != 0
    assert list(conf.values) != [0.5, 0.5]  # not the baseline: restoring it at the end is visible
    assert dict(zip(conf.names, conf.values, strict=True)) == pytest.approx(
        dict(zip(ready.calibration.names, ready.calibration.values, strict=True)), abs=1e-4
    )
    # the standstill gave the mount's tilt: the vehicle-frame stream holds no gravity
    az = np.array([m.linear_acceleration.z for m in vehicle[-100:]])
    assert abs(float(np.nanmean(az))) < 0.05

    launcher.send_signal(signal.SIGINT)
    rc = launcher.wait(timeout=60)
    assert rc == 0, procs.ending("car", rc)
    # the bridge restored the safe baseline on the ECU as it stopped
    read = subprocess.run(
        [sys.executable, "-m", "bac_ecu_bridge", "read", "--interface", "udp_multicast", "--channel", CHANNEL,
         "--definition", str(DEFINITION)],
        env=ros_env, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert read.returncode == 0, read.stdout + read.stderr
    values = {k.strip(): float(v) for k, v in (line.split("=") for line in read.stdout.splitlines() if " = " in line)}
    assert values == {"damping_front": 0.5, "damping_rear": 0.5}


class RecordedCar:
    """Plays a car's IMU (200 Hz, best effort) and cumulative odometry (50 Hz, reliable) in real time from a
    timeline of standstills and recorded (simulated) bump runs, stamped with the wall clock as a driver would."""

    def __init__(self, node: Any) -> None:
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import Imu

        from bac_common.rosnode import QOS_STREAM_INPUT

        self.Imu, self.Odometry = Imu, Odometry
        self.node = node
        self.imu_pub = node.create_publisher(Imu, "imu/data_raw", QOS_SENSOR)
        self.odom_pub = node.create_publisher(Odometry, "vehicle/odom", QOS_STREAM_INPUT)
        self.rng = np.random.default_rng(3)
        self.distance = 0.0
        self.drives: list[tuple[int, int, float]] = []  # (a drive's first and last stamp, its true J)

    def _imu(self, t: int, acc: np.ndarray, gyr: np.ndarray) -> None:
        m = self.Imu()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 1_000_000_000)
        m.header.frame_id = "imu_link"
        m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = (float(v) for v in acc)
        m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = (float(v) for v in gyr)
        self.imu_pub.publish(m)

    def _odom(self, t: int, distance: float, speed: float) -> None:
        o = self.Odometry()
        o.header.stamp.sec, o.header.stamp.nanosec = divmod(t, 1_000_000_000)
        o.header.frame_id = "odom"
        o.pose.pose.position.x = distance
        o.twist.twist.linear.x = speed
        self.odom_pub.publish(o)

    def _play(self, t_rel: np.ndarray, acc: np.ndarray, gyr: np.ndarray, o_rel: np.ndarray, dist: np.ndarray,
              speed: np.ndarray) -> int:  # fmt: skip
        """Publish the samples at their times (s, from now), paced by the wall clock; return the start stamp."""
        import time

        t0 = self.node.get_clock().now().nanoseconds
        w0 = time.monotonic()
        i = k = 0
        while i < t_rel.size or k < o_rel.size:
            now = time.monotonic() - w0
            while i < t_rel.size and t_rel[i] <= now:
                self._imu(t0 + round(t_rel[i] * 1e9), acc[i], gyr[i])
                i += 1
            while k < o_rel.size and o_rel[k] <= now:
                self._odom(t0 + round(o_rel[k] * 1e9), float(dist[k]), float(speed[k]))
                k += 1
            time.sleep(0.002)  # pacing of the player, not a wait for a condition
        return t0

    def stand(self, seconds: float) -> None:
        n = round(seconds * 200)
        acc = np.tile([0.0, 0.0, 9.80665], (n, 1)) + self.rng.normal(0, 0.01, (n, 3))
        gyr = self.rng.normal(0, 0.001, (n, 3))
        m = round(seconds * 50)
        self._play(np.arange(n) / 200, acc, gyr, np.arange(m) / 50, np.full(m, self.distance), np.zeros(m))

    @staticmethod
    def record(damping: float, seed: int) -> Any:
        """A bump drive, simulated ahead of the timeline (the first simulation in a process compiles the
        simulator's kernels: seconds the timeline must not lose)."""
        from bac_sim.run import ImuSpec, simulate_run

        imu = ImuSpec(rate_hz=200.0, mount_rpy_deg=(0.0, 0.0, 0.0), accel_bias=(0, 0, 0), gyro_bias=(0, 0, 0))
        return simulate_run({"damping_front": damping, "damping_rear": damping}, "bump", seed=seed, imu=imu,
                            run_in_s=2.0, run_out_s=1.0, odom_rate_hz=50.0)  # fmt: skip

    def drive(self, rec: Any) -> None:
        """Play a recorded drive from here on; remember its first stamp, its last stamp and its true J."""
        t0 = self._play(rec.t - rec.t[0], rec.accel, rec.gyro, rec.odom_t, self.distance + rec.distance, rec.speed)
        t_end = t0 + round(max(float(rec.t[-1] - rec.t[0]), float(rec.odom_t[-1])) * 1e9)
        self.drives.append((t0, t_end, rec.j_true))
        self.distance += float(rec.distance[-1])


def test_car_profile_retry_waits_for_a_new_drive(
    procs: Any, ros_context: Any, ros_env: dict[str, str], tmp_path: Path
) -> None:
    """The driver needs longer than the run timeout to come back round: attempt 1 times out while the car is on
    its way to the bump, and the recorded drive goes on after attempt 2 was announced (its data arrives after
    the timeout). Attempt 2 must not be scored on it: the car stops, moves off again, and that drive is scored."""
    import json

    channel = "239.74.163.11"
    procs.python("ecu", ["-m", "bac_sim.ecu", "--interface", "udp_multicast", "--channel", channel,
                         "--definition", str(DEFINITION)])  # fmt: skip
    camp = tmp_path / "camp"
    launcher = procs.python("car", ["-m", "bac_bringup.cli", "launch", "car", "--campaign-dir", str(camp),
                                    "-p", "ecu_bridge.can.interface:=udp_multicast",
                                    "-p", f"ecu_bridge.can.channel:={channel}",
                                    "-p", "bo_agent.budget:=1", "-p", "bo_agent.confirmation_run:=false",
                                    "-p", "run_segmenter.run_timeout_s:=12.0",
                                    "-p", "run_segmenter.distance_origin:=run_start",
                                    "-p", "run_segmenter.distance_source:=position_x"])  # fmt: skip
    node = ros_context.node("car_driver")
    trials: list[Trial] = []
    node.create_subscription(Trial, "bac/trial", trials.append, QOS_LATCHED)
    car = RecordedCar(node)
    wait_for(lambda: car.imu_pub.get_subscription_count() > 0, 60, what="imu_ingest subscribing imu/data_raw")

    def ready(attempt: int) -> bool:
        return any(t.state == Trial.STATE_READY_TO_DRIVE and t.attempt == attempt for t in trials)

    def standing() -> bool:
        car.stand(0.2)
        return ready(1)

    soft, firm = car.record(0.1, seed=1), car.record(0.9, seed=2)  # before the timeline starts
    wait_for(standing, 90, interval=0.0, what="trial 1 ready to drive (the car standing still)")
    car.stand(10.3)  # the driver is late: attempt 1 times out 12 s after it was announced, 1.5 s into drive 1
    car.drive(soft)  # its bump comes 0.8 s after attempt 2 was announced
    assert ready(2), "attempt 1 did not time out during the first drive"
    retry = next(t for t in trials if t.attempt == 2 and t.state == Trial.STATE_READY_TO_DRIVE)
    assert "Go back before the start" in retry.instruction
    # the premise: the retry was announced while drive 1 was under way (else drive 1 is a new drive for it)
    announced = retry.stamp.sec * 1_000_000_000 + retry.stamp.nanosec
    first, last, _ = car.drives[0]
    assert first < announced < last, f"attempt 2 announced {(announced - first) / 1e9:.2f} s into a drive of " \
        f"{(last - first) / 1e9:.2f} s: not during drive 1"  # fmt: skip
    car.stand(1.0)  # back at the start, stopped
    car.drive(firm)  # a very different J
    car.stand(1.0)
    rc = launcher.wait(timeout=60)
    assert rc == 0, procs.ending("car", rc)

    events = [json.loads(x) for x in (camp / "journal.jsonl").read_text().splitlines()]
    rejected = [e for e in events if e["event"] == "run_rejected"]
    assert [(e["attempt"], "run timeout" in e["reason"]) for e in rejected] == [(1, True)], rejected
    (scored,) = [e for e in events if e["event"] == "trial_scored"]
    assert scored["attempt"] == 2
    (_, _, j1), (_, _, j2) = car.drives
    assert abs(j1 - j2) > 0.1 * j1  # the two drives are told apart by their J (measured: 1.01 and 1.19)
    assert scored["j"] == pytest.approx(j2, rel=0.03) and abs(scored["j"] - j1) > 0.1 * j1
