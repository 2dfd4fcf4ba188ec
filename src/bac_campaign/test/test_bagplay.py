"""bac's bag player reads trial bags with offered QoS profiles (since 2026-11-24) and without (before) alike."""

from __future__ import annotations

from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer

from bac_campaign.bagplay import BagMessage, iter_bag_messages
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


def test_a_trial_message_plays_at_its_stamp_after_the_samples_before_it(tmp_path: Path) -> None:
    """A recorder whose clock lagged wrote a run's SCORED message (stamp 7 s) at bag time 5 s, before the run's
    last IMU samples (6 s, 6.5 s): played in event order, it comes after them; ties keep the recorded order."""
    from rclpy.serialization import serialize_message

    from bac_campaign.bagplay import in_event_order
    from bac_measure.bagio import IMU_TYPE
    from bac_msgs.msg import Trial

    scored = Trial(campaign_id="c", trial_id=3, attempt=1, state=Trial.STATE_SCORED)
    scored.stamp.sec = 7
    unstamped = Trial(campaign_id="c", trial_id=3, attempt=1, state=Trial.STATE_PROPOSED)
    imu = b"\x00\x01\x00\x00" + bytes(8)  # only the bag time matters to the order of a stream sample
    s = 1_000_000_000
    with TrialBagWriter(tmp_path / "b") as w:
        w.write("bac/trial", 1 * s, trial_cdr(3))  # READY_TO_DRIVE, stamp 3 s: plays at 3 s
        w.write("bac/trial", 2 * s, bytes(serialize_message(unstamped)))  # no stamp: keeps its bag time
        w.write("bac/trial", 5 * s, bytes(serialize_message(scored)))
    msgs = list(iter_bag_messages(tmp_path / "b", ["bac/trial"]))
    msgs += [BagMessage("imu/data_raw", IMU_TYPE, t, imu) for t in (2 * s, 6 * s, 6_500_000_000)]
    got = [(m.topic, m.time_ns) for m in in_event_order(msgs)]
    assert got == [
        ("bac/trial", 2 * s),  # the unstamped PROPOSED, before the sample at the same time (recorded first)
        ("imu/data_raw", 2 * s),
        ("bac/trial", 3 * s),
        ("imu/data_raw", 6 * s),
        ("imu/data_raw", 6_500_000_000),
        ("bac/trial", 7 * s),
    ]
    assert [m.cdr for m in in_event_order(msgs) if m.topic == "bac/trial"][-1] == msgs[2].cdr


def test_the_bags_of_one_launch_play_as_one_timeline(tmp_path: Path) -> None:
    """A resumed campaign: trials 1-2 from one launch, trial 2 again and 3 from a second (sim time restarted), then
    a bag no index names. Consecutive bags of one launch form a group; each other bag stands alone."""
    from bac_campaign.bagplay import launch_groups
    from bac_campaign.launches import LaunchIndex

    bags = tmp_path / "c" / "bags"
    names = ["trial_0001", "trial_0002", "trial_0002.r1", "trial_0003", "trial_0004"]
    for n in names:
        (bags / n).mkdir(parents=True)
    first = LaunchIndex(tmp_path / "c")
    first.bag_opened(bags / names[0], 1, 10)
    first.bag_opened(bags / names[1], 2, 20)
    first.close()
    second = LaunchIndex(tmp_path / "c")
    second.bag_opened(bags / names[2], 2, 5)
    second.bag_opened(bags / names[3], 3, 15)
    second.close()
    other = tmp_path / "other.mcap"
    paths = [bags / n for n in names] + [other]
    assert launch_groups(paths) == [
        [bags / "trial_0001", bags / "trial_0002"],
        [bags / "trial_0002.r1", bags / "trial_0003"],
        [bags / "trial_0004"],  # not in the index (recorded before it existed)
        [other],
    ]
    # a launch's bags given out of order are not merged across the other launch's bags
    assert launch_groups([paths[0], paths[2], paths[1]]) == [[paths[0]], [paths[2]], [paths[1]]]
