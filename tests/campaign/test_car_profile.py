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
    assert launcher.wait(timeout=60) == 0, procs.log("car")
    # the bridge restored the safe baseline on the ECU as it stopped
    read = subprocess.run(
        [sys.executable, "-m", "bac_ecu_bridge", "read", "--interface", "udp_multicast", "--channel", CHANNEL,
         "--definition", str(DEFINITION)],
        env=ros_env, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert read.returncode == 0, read.stdout + read.stderr
    values = {k.strip(): float(v) for k, v in (line.split("=") for line in read.stdout.splitlines() if " = " in line)}
    assert values == {"damping_front": 0.5, "damping_rear": 0.5}
