"""A recorded trial bag played as ``ros2 bag play`` plays it gives the recorded J back.

A one-trial campaign on the simulated car records its bag (campaign_recorder). Then the measurement chain
(imu_ingest, run_segmenter, kpi_scorer, real processes on sim time, the campaign's parameters) is fed from the
bag by a player that builds its publishers from the bag's ``offered_qos_profiles`` exactly as rosbag2's player
does (``tests/helpers/rosbag2_play.py``): the readers of the graph match them, transient-local ones included,
and the chain scores the run to the J recorded live. A bag without profiles (as bac wrote them before) is played
reliable + volatile: the transient-local readers never match it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from helpers.rosbag2_play import Rosbag2Player, rclpy_qos
from rosbags.interfaces import QosDurability, QosReliability

from bac_measure.bagio import offered_qos, read_messages
from bac_measure.recording import RECORDED_TOPICS, playback_qos, read_metadata

from conftest import fresh_domain, wait_for

pytestmark = pytest.mark.integration
PLAYED = ("imu/data_raw", "vehicle/odom", "bac/trial")


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    camp = tmp_path_factory.mktemp("bagplay") / "c"
    env = {**os.environ, "ROS_DOMAIN_ID": str(fresh_domain()), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    cmd = [
        sys.executable, "-m", "bac_bringup.cli", "launch", "sim", "--campaign-dir", str(camp),
        "--log-dir", str(camp / "logs"), "--timeout", "240",
        "-p", "bo_agent.budget:=1", "-p", "bo_agent.seed:=3", "-p", "vehicle_sim.seed:=3",
        "-p", "bo_agent.confirmation_run:=false",
    ]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=360, check=False)
    if proc.returncode != 0:
        logs = "\n".join(f"--- {f.name}\n{f.read_text()[-3000:]}" for f in sorted((camp / "logs").glob("*.log")))
        pytest.fail(f"campaign failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{logs}")
    return camp


def test_the_bag_says_jazzy_and_offers_reliable_transient_local(campaign: Path) -> None:
    bag = campaign / "bags" / "trial_0001"
    info = read_metadata(bag)
    assert info["version"] == 9 and info["ros_distro"] == "jazzy"
    recorded = offered_qos(bag)
    assert {"/" + t for t in RECORDED_TOPICS} <= set(recorded)
    for topic, profiles in recorded.items():
        assert len(profiles) == 1, topic
        q = playback_qos(profiles)
        assert q is not None and q.reliability == QosReliability.RELIABLE, topic
        assert q.durability == QosDurability.TRANSIENT_LOCAL and q.depth == 10, topic


def test_ros2_bag_play_of_a_trial_bag_gives_the_recorded_j(campaign: Path, procs: Any, ros_context: Any) -> None:
    from sensor_msgs.msg import Imu

    from bac_common.rosnode import QOS_EVENTS
    from bac_msgs.msg import RunScore, RunSegment, Trial

    bag = campaign / "bags" / "trial_0001"
    ((_, recorded),) = read_messages(bag, "bac/run_score")
    assert recorded.valid
    params = ["--params-file", str(campaign / "config" / "00_common.yaml"),
              "--params-file", str(campaign / "config" / "01_sim.yaml")]  # fmt: skip
    for name, module in (
        ("imu_ingest", "bac_imu.ingest_node"),
        ("run_segmenter", "bac_measure.segmenter_node"),
        ("kpi_scorer", "bac_measure.scorer_node"),
    ):
        procs.python(name, ["-m", module, "--ros-args", *params, "-p", "use_sim_time:=true"])
    node = ros_context.node("bag_play_test")
    lock = threading.Lock()
    scores: list[Any] = []

    def on_score(m: Any) -> None:
        with lock:
            scores.append(m)

    node.create_subscription(RunScore, "bac/run_score", on_score, QOS_EVENTS)
    player = Rosbag2Player(node, bag, PLAYED, rate=2.0)
    for topic in PLAYED:  # the chain's readers match the bag's offers
        pub = player.pubs[topic]
        wait_for(lambda pub=pub: pub.get_subscription_count() >= 1, 60, what=f"a reader matching {topic}")
    wait_for(lambda: node.count_publishers("bac/run_score") >= 1, 60, what="kpi_scorer")
    # every reader of the chain matches the bag's offer, the transient-local ones included; rosbag2's default
    # offer (a bag without profiles: reliable + volatile) matches none of those
    for topic, cls in (("bac/trial", Trial), ("imu/vehicle", Imu), ("bac/run_segment", RunSegment)):
        recorded_qos = rclpy_qos(playback_qos(player.recorded_qos["/" + topic]))
        probe = node.create_publisher(cls, topic, recorded_qos)
        old = node.create_publisher(cls, topic, rclpy_qos(None))
        wait_for(lambda p=probe: p.get_subscription_count() >= 1, 60, what=f"the chain's reader of {topic}")
        assert old.get_subscription_count() == 0, topic
        node.destroy_publisher(probe)
        node.destroy_publisher(old)

    def scored() -> list[Any]:
        with lock:
            return [s for s in scores if (s.campaign_id, s.trial_id, s.attempt) == (recorded.campaign_id, 1, 1)]

    def hold(m: Any) -> bool:
        # a trial message that leaves READY_TO_DRIVE waits for the run's score (the live agent moved on only then)
        from rclpy.serialization import deserialize_message

        return (
            m.topic == "bac/trial"
            and deserialize_message(m.cdr, Trial).state > Trial.STATE_READY_TO_DRIVE
            and (not scored())
        )

    assert player.play(hold=hold) == sum(1 for m in player.messages if m.topic in PLAYED)
    (got,) = wait_for(scored, 60, what="the score of the replayed run")
    assert got.valid, got.reason
    assert abs(got.j - recorded.j) <= 1e-9, (got.j, recorded.j)
    assert abs(got.rms_accel_z - recorded.rms_accel_z) <= 1e-9
