"""vehicle_sim's ECU on CAN: the bridge's protocol over udp_multicast, busy while driving, next-run rule."""

from __future__ import annotations

import re
import subprocess
import sys
from typing import Any

import pytest

from bac_common.rosnode import QOS_LATCHED
from bac_msgs.msg import Trial

from conftest import wait_for

pytestmark = pytest.mark.integration


def test_calibration_written_over_can_applies_from_the_next_run(
    procs: Any, ros_context: Any, in_private_netns: bool, ros_env: dict[str, str]
) -> None:
    if not in_private_netns:
        pytest.skip("udp_multicast CAN only inside a private network namespace: run scripts/pytest.sh")
    group, port = "239.74.99.21", "43561"
    procs.python(
        "vehicle_sim",
        ["-m", "bac_sim.vehicle_sim_node", "--ros-args", "-p", "scenario:=bump", "-p", "can.interface:=udp_multicast",
         "-p", f"can.channel:={group}", "-p", f"can.port:={port}", "-p", "realtime_factor:=1.0"],
    )  # fmt: skip
    wait_for(lambda: "vehicle_sim ready" in procs.log("vehicle_sim"), 30, what="vehicle_sim")
    bus = ["--definition", "controller_i", "--interface", "udp_multicast", "--channel", group, "--port", port]

    def apply(*values: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "bac_ecu_bridge", "apply", *bus, *values],
            check=False,
            capture_output=True,
            text=True,
            timeout=60,
            env=ros_env,
        )

    r = apply("damping_front=0.2", "damping_rear=0.9")
    assert r.returncode == 0, r.stderr
    node = ros_context.node("probe")
    pub = node.create_publisher(Trial, "bac/trial", QOS_LATCHED)
    wait_for(lambda: node.count_subscribers("bac/trial") > 0, 30, what="vehicle_sim's trial subscription")

    def ready(trial: int) -> None:
        t = Trial()
        t.campaign_id = "ecu"
        t.trial_id = trial
        t.attempt = 1
        t.state = Trial.STATE_READY_TO_DRIVE
        pub.publish(t)

    ready(1)
    wait_for(lambda: "driving trial 1 attempt 1" in procs.log("vehicle_sim"), 60, what="the first run")
    line = re.search(r"driving trial 1 attempt 1.*", procs.log("vehicle_sim"))
    assert line is not None and "damping_front=0.2, damping_rear=0.9" in line.group(0)
    # the car is moving: the ECU refuses to commit
    r = apply("damping_front=0.7", "damping_rear=0.3")
    assert "run of trial 1 attempt 1 published" not in procs.log("vehicle_sim"), "the run ended too early for the test"
    assert r.returncode == 4 and "ECU_BUSY" in r.stderr
    wait_for(lambda: "run of trial 1 attempt 1 published" in procs.log("vehicle_sim"), 60, what="the end of the run")
    r = apply("damping_front=0.7", "damping_rear=0.3")
    assert r.returncode == 0, r.stderr
    ready(2)
    wait_for(lambda: "driving trial 2 attempt 1" in procs.log("vehicle_sim"), 60, what="the second run")
    line = re.search(r"driving trial 2 attempt 1.*", procs.log("vehicle_sim"))
    assert line is not None and "damping_front=0.7, damping_rear=0.3" in line.group(0)
