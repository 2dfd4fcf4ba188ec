"""``bac replay`` of a recording bac did not make (a real robot's ROS 1 bag, shipped in bac_measure/test/data):
without a topic map it says what the bag holds and how to map it, instead of playing nothing; mapped, the live
chain ingests the 50 Hz IMU at its own rate (the replay profile is made for the simulator's 400 Hz IMU: every
step was a gap) and scores the run with the same verdict as ``bac rescore``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

pytestmark = [pytest.mark.integration]
REAL_BAG = ROOT / "src" / "bac_measure" / "test" / "data" / "robot_localization_test2.bag"
MAP = ["--topic-map", "/imu/data:=imu/data_raw", "--topic-map", "/jackal_velocity_controller/odom:=vehicle/odom"]


def replay(ros_env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "bac_bringup.cli", "replay", str(REAL_BAG), *args]
    return subprocess.run(cmd, env=ros_env, capture_output=True, text=True, timeout=180, check=False)


def test_a_foreign_bag_without_a_topic_map_is_refused_with_the_map_to_give(ros_env: dict[str, str]) -> None:
    p = replay(ros_env)
    text = p.stdout + p.stderr
    assert p.returncode == 2, text
    assert "bac replay: nothing to play:" in text and "its topics: /imu/data (sensor_msgs/msg/Imu)" in text, text
    assert "--topic-map /imu/data:=imu/data_raw --topic-map /jackal_velocity_controller/odom:=vehicle/odom" in text
    assert "Traceback" not in text and "starting" not in text  # refused before any node started


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_a_mapped_foreign_bag_is_ingested_at_its_own_rate(
    ros_env: dict[str, str], tmp_path: Path, mode: list[str]
) -> None:
    out = tmp_path / "replay.json"
    p = replay(ros_env, *MAP, "--rate", "20", "--output", str(out), *mode)
    text = p.stdout + p.stderr
    assert p.returncode == 0, text[-6000:]
    assert "the IMU is 50.0 Hz; imu_ingest measures its input rate and outputs 50.0 Hz" in text, text[-6000:]
    assert "ingesting imu/data_raw -> imu/vehicle at 50 Hz" in text
    assert " gap" not in text, text[-6000:]  # imu_ingest warned of hundreds of gaps at the profile's 400 Hz
    (run,) = json.loads(out.read_text())["runs"]
    # bac rescore's verdict on the same recording (tests/campaign/test_campaign_graph.py): a robot at ~3 km/h is
    # no 30 km/h bump run; nothing else is wrong with it
    assert not run["valid"] and run["reason"].startswith("segment invalid: too slow: mean speed"), run
    # and the report is logged once
    assert text.count("replayed runs:") == 1, text[-6000:]
