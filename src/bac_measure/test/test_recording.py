"""Trial bags: metadata as ros2 bag record (Jazzy) writes it, the offered QoS that parse back, old bags still read."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosHistory, QosLiveliness, QosReliability
from rosbags.rosbag2 import StoragePlugin, Writer

from bac_measure.bagio import offered_qos, read_trials
from bac_measure.recording import (
    OFFERED_QOS,
    QOS_INFINITE,
    RECORDED_TOPICS,
    TrialBagWriter,
    bac_typestore,
    playback_qos,
    read_metadata,
)

INFINITE = {"sec": 9223372036, "nsec": 854775807}
# one profile as rosbag2 (Jazzy, format version 9) writes it for a publisher offering reliable + transient local
# with the default deadline, lifespan and liveliness (rosbag2_storage/src/rosbag2_storage/qos.cpp)
JAZZY_PROFILE = {
    "history": "unknown",
    "depth": 0,
    "reliability": "reliable",
    "durability": "transient_local",
    "deadline": INFINITE,
    "lifespan": INFINITE,
    "liveliness": "automatic",
    "liveliness_lease_duration": INFINITE,
    "avoid_ros_namespace_conventions": False,
}


def trial_cdr(trial_id: int, state: int) -> bytes:
    from rclpy.serialization import serialize_message

    from bac_msgs.msg import Trial

    m = Trial(campaign_id="c", trial_id=trial_id, attempt=1, state=state)
    m.stamp.sec = 10 + trial_id
    return bytes(serialize_message(m))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_metadata_is_what_ros2_bag_record_writes(tmp_path: Path, storage: str) -> None:
    bag = tmp_path / "trial_0001"
    with TrialBagWriter(bag, storage=storage) as w:
        w.write("bac/trial", 11_000_000_000, trial_cdr(1, 3))
    text = (bag / "metadata.yaml").read_text()
    info = yaml.safe_load(text)["rosbag2_bagfile_information"]
    assert info == read_metadata(bag)
    assert info["version"] == 9 and info["ros_distro"] == "jazzy"
    # rosbag2's field order (yaml-cpp keeps the order the encoder set)
    assert list(info)[:6] == [
        "version", "storage_identifier", "duration", "starting_time", "message_count", "topics_with_message_count",
    ]  # fmt: skip
    assert list(info)[-2:] == ["custom_data", "ros_distro"]
    (topic,) = info["topics_with_message_count"]
    meta = topic["topic_metadata"]
    assert list(meta) == ["name", "type", "serialization_format", "offered_qos_profiles", "type_description_hash"]
    assert meta["name"] == "/bac/trial" and meta["type"] == "bac_msgs/msg/Trial"
    # a YAML list of profiles (format version 9), each field in rosbag2's order
    assert meta["offered_qos_profiles"] == [JAZZY_PROFILE]
    assert list(meta["offered_qos_profiles"][0]) == list(JAZZY_PROFILE)
    assert list(meta["offered_qos_profiles"][0]["deadline"]) == ["sec", "nsec"]
    assert "          - history: unknown\n            depth: 0\n" in text  # block style, as yaml-cpp writes it


def test_offered_qos_parse_back_to_what_was_intended(tmp_path: Path) -> None:
    bag = tmp_path / "trial_0002"
    with TrialBagWriter(bag) as w:
        for topic in RECORDED_TOPICS:
            if topic == "bac/trial":
                w.write(topic, 12_000_000_000, trial_cdr(2, 3))
    # rosbags parses metadata.yaml and, for a bare .mcap, the channel's copy: both give the intended profile
    for path in (bag, next(bag.glob("*.mcap"))):
        got = offered_qos(path)
        assert got == {"/bac/trial": [OFFERED_QOS]}, path
    (q,) = offered_qos(bag)["/bac/trial"]
    assert q.reliability == QosReliability.RELIABLE and q.durability == QosDurability.TRANSIENT_LOCAL
    assert q.liveliness == QosLiveliness.AUTOMATIC and q.deadline == QOS_INFINITE
    # what ros2 bag play offers from it: the recorded policies, keep last 10
    play = playback_qos([q])
    assert play is not None and play.history == QosHistory.KEEP_LAST and play.depth == 10
    assert (play.reliability, play.durability) == (QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL)
    # the mcap channel carries the same profile as a YAML string (rosbag2_storage_mcap)
    with AnyReader([next(bag.glob("*.mcap"))], default_typestore=bac_typestore()) as r:
        (conn,) = r.connections
        assert conn.ext.offered_qos_profiles == [OFFERED_QOS]


def test_playback_qos_of_mixed_or_no_profiles_is_rosbag2s_default() -> None:
    assert playback_qos([]) is None
    best_effort = OFFERED_QOS._replace(reliability=QosReliability.BEST_EFFORT)
    assert playback_qos([OFFERED_QOS, best_effort]) is None
    # history and depth do not decide compatibility: profiles differing only there agree
    assert playback_qos([OFFERED_QOS, OFFERED_QOS._replace(depth=7)]) == OFFERED_QOS._replace(
        history=QosHistory.KEEP_LAST, depth=10
    )


def test_a_bag_without_profiles_still_reads(tmp_path: Path) -> None:
    """Bags bac wrote before (rosbags' writer: no profiles, ros_distro rosbags) read as before."""
    bag = tmp_path / "old"
    store = bac_typestore()
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/bac/trial", "bac_msgs/msg/Trial", typestore=store)
        w.write(conn, 13_000_000_000, trial_cdr(3, 3))
    assert read_metadata(bag)["ros_distro"] == "rosbags"
    assert offered_qos(bag) == {"/bac/trial": []}
    assert playback_qos(offered_qos(bag)["/bac/trial"]) is None
    (event,) = read_trials(bag)
    assert (event.trial_id, event.state) == (3, 3)
