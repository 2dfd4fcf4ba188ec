"""bac's bag player reads trial bags with offered QoS profiles (since 2026-11-24) and without (before) alike."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
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


def _campaign_bags(root: Path, launches: list[list[str]]) -> Path:
    """A campaign folder whose bags (empty folders) were opened by one recorder process per list."""
    from bac_campaign.launches import LaunchIndex

    bags = root / "bags"
    for names in launches:
        index = LaunchIndex(root)
        for n in names:
            (bags / n).mkdir(parents=True)
            index.bag_opened(bags / n, int(n[6:10]), 0)
        index.close()
    return bags


def test_the_bags_of_one_launch_are_one_group(tmp_path: Path) -> None:
    """A resumed campaign: trials 1-2 from one launch, trial 2 again and 3 from a second (sim time restarted), then
    a bag no index names. Consecutive bags of one launch form a group; each other bag stands alone."""
    from bac_campaign.bagplay import launch_groups

    bags = _campaign_bags(tmp_path / "c", [["trial_0001", "trial_0002"], ["trial_0002.r1", "trial_0003"]])
    (bags / "trial_0004").mkdir()  # recorded before the index existed
    paths = [bags / n for n in ("trial_0001", "trial_0002", "trial_0002.r1", "trial_0003", "trial_0004")]
    paths.append(tmp_path / "other.mcap")
    got = launch_groups(paths)
    assert [(g.positions, g.indexed) for g in got] == [([0, 1], True), ([2, 3], True), ([4], False), ([5], False)]
    # a launch's bags given out of order are not merged across the other launch's bags
    assert [g.positions for g in launch_groups([paths[0], paths[2], paths[1]])] == [[0], [1], [2]]
    # a campaign given twice: the second pass is a group of its own, not merged into the first
    assert [g.positions for g in launch_groups([paths[0], paths[1], paths[0], paths[1]])] == [[0, 1], [2, 3]]
    # an unreadable index: named, and its bags are not indexed
    (tmp_path / "c" / "launches.jsonl").write_text("{not json\n{damaged\n")  # damaged before its end
    notes: list[str] = []
    assert all(not g.indexed for g in launch_groups(paths[:2], notes))
    assert len(notes) == 1 and "launches.jsonl is unreadable" in notes[0]


def test_a_runs_late_samples_in_the_next_trials_bag_play_before_that_trial(tmp_path: Path) -> None:
    """The recorder lagged: trial 2's READY_TO_DRIVE (stamp 10 s) sits in its bag at 7 s, and trial 1's last
    samples (9 s, 9.5 s) arrived after trial 1's bag closed, so they are in trial 2's bag, while run 1's SCORED
    (stamp 9.8 s) is in trial 1's. One launch's bags play as one timeline: those samples before run 1's SCORED and
    trial 2's start. A bag of no campaign plays as recorded."""
    from rclpy.serialization import serialize_message

    from bac_campaign.bagplay import play_timeline
    from bac_measure.bagio import IMU_TYPE
    from bac_msgs.msg import Trial

    s = 1_000_000_000
    bags = _campaign_bags(tmp_path / "c", [["trial_0001", "trial_0002"]])
    ready2 = Trial(campaign_id="c", trial_id=2, attempt=1, state=Trial.STATE_READY_TO_DRIVE)
    ready2.stamp.sec = 10
    imu = b"\x00\x01\x00\x00" + bytes(8)

    def sample(t: int) -> BagMessage:
        return BagMessage("imu/data_raw", IMU_TYPE, t, imu)

    scored1 = Trial(campaign_id="c", trial_id=1, attempt=1, state=Trial.STATE_SCORED)
    scored1.stamp.sec, scored1.stamp.nanosec = 9, 800_000_000
    bag1 = [BagMessage("bac/trial", "bac_msgs/msg/Trial", 1 * s, trial_cdr(1)), sample(2 * s), sample(8 * s)]
    bag1.append(BagMessage("bac/trial", "bac_msgs/msg/Trial", 8 * s, bytes(serialize_message(scored1))))
    bag2 = [BagMessage("bac/trial", "bac_msgs/msg/Trial", 7 * s, bytes(serialize_message(ready2)))]
    bag2 += [sample(9 * s), sample(9_500_000_000), sample(11 * s)]
    notes: list[str] = []
    got = play_timeline([bags / "trial_0001", bags / "trial_0002"], [bag1, bag2], notes)
    assert [(m.topic, m.time_ns) for m in got] == [
        ("bac/trial", 1 * s),
        ("imu/data_raw", 2 * s),
        ("imu/data_raw", 8 * s),
        ("imu/data_raw", 9 * s),
        ("imu/data_raw", 9_500_000_000),
        ("bac/trial", 9_800_000_000),  # run 1's SCORED after its late samples: each bag sorted alone would not
        ("bac/trial", 10 * s),
        ("imu/data_raw", 11 * s),
    ]
    assert notes == []
    # the same messages as bags of no campaign: as recorded (their bag times may be arrival times), the clock
    # jumping back at the second bag's start
    got = play_timeline([tmp_path / "a.mcap", tmp_path / "b.mcap"], [bag1, bag2], notes)
    assert got == bag1 + bag2
    assert notes == [f"{tmp_path / 'b.mcap'} starts before the previous bag ends: the clock will jump back"]


def _foreign_bag(path: Path, rate_hz: float, n: int, with_trial: bool = False) -> None:
    """A rosbag2 of another recorder: sensor_msgs/Imu on /imu/data at ``rate_hz`` (stamps), nothing of bac's."""
    store = bac_typestore()
    types = store.types
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=store)
        for i in range(n):
            t = 5_000_000_000 + round(i * 1e9 / rate_hz)
            stamp = types["builtin_interfaces/msg/Time"](sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
            v = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81)
            q = types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
            cov = np.zeros(9)
            msg = types["sensor_msgs/msg/Imu"](
                header=types["std_msgs/msg/Header"](stamp=stamp, frame_id="imu"),
                orientation=q, orientation_covariance=cov, angular_velocity=v, angular_velocity_covariance=cov,
                linear_acceleration=v, linear_acceleration_covariance=cov,
            )  # fmt: skip
            w.write(conn, t + 3_000_000, bytes(store.serialize_cdr(msg, "sensor_msgs/msg/Imu")))
        if with_trial:
            tc = w.add_connection("/bac/trial", "bac_msgs/msg/Trial", typestore=store)
            w.write(tc, 5_000_000_000, trial_cdr(1))


def test_a_topic_the_bag_does_not_hold_gives_nothing(tmp_path: Path) -> None:
    """rosbags reads every message when asked for no connection: a bag without the wanted topics gave all of its
    own (a foreign bag's /imu/data came out under its own name, and the player then played nothing, silently)."""
    from bac_campaign.bagplay import nothing_to_play

    _foreign_bag(tmp_path / "b", 50.0, 20)
    assert list(iter_bag_messages(tmp_path / "b", ["imu/data_raw", "vehicle/odom", "bac/trial"])) == []
    got = list(iter_bag_messages(tmp_path / "b", ["imu/data_raw"], {"/imu/data": "imu/data_raw"}))
    assert len(got) == 20 and {m.topic for m in got} == {"imu/data_raw"}
    why = nothing_to_play(tmp_path / "b", ("imu/data_raw", "vehicle/odom", "bac/trial"))
    assert "its topics: /imu/data (sensor_msgs/msg/Imu)" in why and "--topic-map /imu/data:=imu/data_raw" in why


def test_the_imu_rate_of_a_foreign_recording_is_measured_from_its_stamps(tmp_path: Path) -> None:
    from bac_campaign.bagplay import imu_rate_hz, is_bac_recording

    _foreign_bag(tmp_path / "b50", 50.0, 200)
    _foreign_bag(tmp_path / "bac", 400.0, 50, with_trial=True)
    remap = {"/imu/data": "imu/data_raw"}
    assert imu_rate_hz(tmp_path / "b50", remap) == pytest.approx(50.0, rel=1e-6)
    assert imu_rate_hz(tmp_path / "b50", remap, max_samples=2) == pytest.approx(50.0, rel=1e-6)
    assert imu_rate_hz(tmp_path / "b50") is None  # no IMU under the name to play
    assert not is_bac_recording(tmp_path / "b50", remap) and is_bac_recording(tmp_path / "bac")
