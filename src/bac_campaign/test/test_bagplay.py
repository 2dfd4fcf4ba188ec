"""bac's bag player reads trial bags with offered QoS profiles (since 2026-11-24) and without (before) alike."""

from __future__ import annotations

from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer

from bac_campaign.bagplay import iter_bag_messages
from bac_measure.recording import TrialBagWriter, bac_typestore


def trial_cdr(trial_id: int) -> bytes:
    from rclpy.serialization import serialize_message

    from bac_msgs.msg import Trial

    m = Trial(campaign_id="c", trial_id=trial_id, attempt=1, state=Trial.STATE_READY_TO_DRIVE)
    m.stamp.sec = trial_id
    return bytes(serialize_message(m))


def test_new_and_old_bags_play_the_same_messages(tmp_path: Path) -> None:
    data = [trial_cdr(1), trial_cdr(2)]
    new = tmp_path / "new"
    with TrialBagWriter(new) as w:
        for i, d in enumerate(data):
            w.write("bac/trial", (i + 1) * 1_000_000_000, d)
    old = tmp_path / "old"
    with Writer(old, version=9, storage_plugin=StoragePlugin.MCAP) as w:  # no profiles, as bac wrote them before
        conn = w.add_connection("/bac/trial", "bac_msgs/msg/Trial", typestore=bac_typestore())
        for i, d in enumerate(data):
            w.write(conn, (i + 1) * 1_000_000_000, d)
    for bag in (new, old):
        got = list(iter_bag_messages(bag, ["bac/trial"]))
        assert [(m.topic, m.time_ns, m.cdr) for m in got] == [
            ("bac/trial", 1_000_000_000, data[0]),
            ("bac/trial", 2_000_000_000, data[1]),
        ], bag
