"""Bags in, arrays out: rosbag2 (mcap, sqlite3), ROS 1, bac_msgs, and clear errors for broken bags."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from bac_measure.bagio import (
    BagError,
    ImuArrays,
    OdomArrays,
    _fast_cdr,
    bag_topics,
    read_imu,
    read_messages,
    read_odom,
    read_trials,
    run_starts,
    write_bag,
)
from bac_measure.recording import bac_typestore

REAL_BAG = Path(__file__).resolve().parent / "data" / "robot_localization_test2.bag"
T0 = 1_700_000_000 * 1_000_000_000


def arrays(n: int = 300, seed: int = 0) -> tuple[ImuArrays, OdomArrays]:
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(n, dtype=np.int64) * 2_000_000 + rng.integers(0, 1000, n)
    imu = ImuArrays(
        "imu/data_raw", "imu_link", t, t + 150_000, rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    )
    to = T0 + np.arange(n // 10, dtype=np.int64) * 20_000_000
    odom = OdomArrays(
        "vehicle/odom",
        "odom",
        to,
        to + 1,
        np.cumsum(rng.uniform(0, 0.3, to.size)),
        rng.uniform(8, 9, to.size),
        -40.0 + 0.01 * rng.standard_normal(to.size),  # a pose's y and z (REP 105 odom frame)
        3.0 + np.cumsum(rng.uniform(0, 0.01, to.size)),
    )
    return imu, odom


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rosbag2_round_trip_is_exact(tmp_path: Path, storage: str) -> None:
    imu, odom = arrays()
    bag = write_bag(tmp_path / "run", imu, odom, storage=storage)
    got = read_imu(bag)
    assert got.topic == "/imu/data_raw" and got.frame_id == "imu_link"
    assert np.array_equal(got.stamp_ns, imu.stamp_ns) and np.array_equal(got.recv_ns, imu.recv_ns)
    assert np.array_equal(got.accel, imu.accel) and np.array_equal(got.gyro, imu.gyro)
    o = read_odom(bag)
    assert np.array_equal(o.stamp_ns, odom.stamp_ns)
    assert np.array_equal(o.distance_m, odom.distance_m) and np.array_equal(o.speed_mps, odom.speed_mps)
    assert np.array_equal(o.position_y_m, odom.position_y_m) and np.array_equal(o.position_z_m, odom.position_z_m)
    # the odometry reaches the segmentation whole: each distance source sees the same pose and speed
    np.testing.assert_array_equal(o.series().position, odom.series().position)
    topics = bag_topics(bag)
    assert topics["/imu/data_raw"] == ("sensor_msgs/msg/Imu", 300) and topics["/vehicle/odom"][1] == 30


def test_bare_mcap_file_is_read(tmp_path: Path) -> None:
    imu, _ = arrays(50)
    bag = write_bag(tmp_path / "run", imu)
    mcap = next(bag.glob("*.mcap"))
    assert np.array_equal(read_imu(mcap).accel, imu.accel)


def test_vectorized_cdr_matches_rosbags_with_mixed_frame_ids() -> None:
    """Messages of one topic with different string lengths (different layouts) decode like rosbags does."""
    ts = bac_typestore()
    T = ts.types
    rng = np.random.default_rng(3)
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    raws, want = [], []
    for i, frame in enumerate(["imu", "imu_link", "a", "", "a_much_longer_frame_name"] * 4):
        v = rng.standard_normal(6)
        m = T["sensor_msgs/msg/Imu"](
            header=T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=100 + i, nanosec=7 * i), frame_id=frame
            ),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9),
            angular_velocity=V3(x=v[0], y=v[1], z=v[2]),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V3(x=v[3], y=v[4], z=v[5]),
            linear_acceleration_covariance=np.arange(9.0),
        )
        raws.append(bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu")))
        want.append((100 + i) * 1_000_000_000 + 7 * i)
        want.append(v)
    fast = _fast_cdr(raws, 37, 1)
    assert fast is not None
    stamps, d = fast
    assert stamps.tolist() == want[0::2]
    np.testing.assert_array_equal(d[:, 13:16], np.array(want[1::2])[:, :3])
    np.testing.assert_array_equal(d[:, 25:28], np.array(want[1::2])[:, 3:])
    np.testing.assert_array_equal(d[0, 28:37], np.arange(9.0))
    # odometry: two strings (frame_id, child_frame_id) of varying lengths
    raws = []
    for i, (f, c) in enumerate([("odom", "base_link"), ("o", "bl"), ("odometry_frame", "")] * 3):
        m = T["nav_msgs/msg/Odometry"](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=i, nanosec=0), frame_id=f),
            child_frame_id=c,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=10.0 * i, y=1.0 - i, z=2.0 + 0.25 * i),
                    orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                ),
                covariance=np.zeros(36),
            ),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=V3(x=0.5 * i, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36),
            ),
        )
        raws.append(bytes(ts.serialize_cdr(m, "nav_msgs/msg/Odometry")))
    fast = _fast_cdr(raws, 85, 2)
    assert fast is not None
    assert fast[1][:, 0].tolist() == [10.0 * i for i in range(9)]
    assert fast[1][:, 43].tolist() == [0.5 * i for i in range(9)]
    # the nodes' decoder (bac_common.cdr.odometry): the pose's position x, y, z and the forward speed
    from bac_common import cdr

    odo = cdr.odometry(raws)
    assert odo is not None
    t, pos, vx = odo
    assert t.tolist() == [i * 1_000_000_000 for i in range(9)]
    np.testing.assert_array_equal(pos, [[10.0 * i, 1.0 - i, 2.0 + 0.25 * i] for i in range(9)])
    assert vx.tolist() == [0.5 * i for i in range(9)]


def test_ros1_real_recording_is_read() -> None:
    imu = read_imu(REAL_BAG)
    assert imu.topic == "/imu/data" and len(imu) == 3061 and imu.frame_id == "base_link"
    assert 9.0 < float(np.mean(imu.accel[:, 2])) < 10.5  # gravity on z
    assert np.all(np.diff(imu.stamp_ns) == 20_000_000)
    odom = read_odom(REAL_BAG)
    assert odom.topic == "/jackal_velocity_controller/odom" and len(odom) == 3060


def test_bac_messages_are_read(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = bac_typestore()
    Trial, Time = ts.types["bac_msgs/msg/Trial"], ts.types["builtin_interfaces/msg/Time"]
    cal = ts.types["bac_msgs/msg/Calibration"](trial_id=1, names=[], values=np.zeros(0), crc32=0)

    def trial(state: int, attempt: int, sec: int) -> bytes:
        m = Trial(
            stamp=Time(sec=sec, nanosec=5),
            campaign_id="camp",
            trial_id=2,
            attempt=attempt,
            state=state,
            kind=0,
            calibration=cal,
            budget=10,
            trials_done=1,
            last_j=float("nan"),
            best_j=float("nan"),
            best_trial_id=0,
            predicted_j=float("nan"),
            predicted_j_std=float("nan"),
            instruction="drive",
            reason="",
        )
        return bytes(ts.serialize_cdr(m, "bac_msgs/msg/Trial"))

    with Writer(tmp_path / "b", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/bac/trial", "bac_msgs/msg/Trial", typestore=ts)
        for i, (state, attempt) in enumerate([(2, 1), (3, 1), (3, 1), (5, 1), (3, 2)]):
            w.write(c, (10 + i) * 1_000_000_000, trial(state, attempt, 10 + i))
    events = read_trials(tmp_path / "b")
    assert [e.state for e in events] == [2, 3, 3, 5, 3]
    starts = run_starts(events)
    assert [(e.attempt, e.stamp_ns) for e in starts] == [(1, 11_000_000_005), (2, 14_000_000_005)]
    assert read_messages(tmp_path / "b", "bac/trial")[0][1].instruction == "drive"


def test_broken_bags_give_clear_errors(tmp_path: Path) -> None:
    imu, _ = arrays(2000)
    bag = write_bag(tmp_path / "run", imu)
    mcap = next(bag.glob("*.mcap"))
    os.truncate(mcap, mcap.stat().st_size // 2)
    with pytest.raises(BagError, match="truncated or corrupt"):
        read_imu(bag)
    ros1 = tmp_path / "cut.bag"
    shutil.copy(REAL_BAG, ros1)
    os.truncate(ros1, ros1.stat().st_size // 3)
    with pytest.raises(BagError, match="truncated or corrupt"):
        read_imu(ros1)
    junk = tmp_path / "junk.bag"
    junk.write_bytes(np.random.default_rng(0).bytes(4000))
    with pytest.raises(BagError, match=r"junk\.bag is not a bag: it is binary data of an unknown kind"):
        read_imu(junk)
    sq = write_bag(tmp_path / "sq", imu, storage="sqlite3")
    db = next(sq.glob("*.db3"))
    os.truncate(db, db.stat().st_size // 2)
    with pytest.raises(BagError, match="truncated or corrupt"):
        read_imu(sq)
    with pytest.raises(BagError, match="no such bag"):
        read_imu(tmp_path / "missing")


def test_topic_choice_errors_name_what_is_there(tmp_path: Path) -> None:
    imu, odom = arrays(20)
    bag = write_bag(tmp_path / "run", imu, odom)
    with pytest.raises(BagError, match="no topic /imu/other; it has: /imu/data_raw, /vehicle/odom"):
        read_imu(bag, "imu/other")
    with pytest.raises(BagError, match="carries nav_msgs/msg/Odometry"):
        read_imu(bag, "vehicle/odom")
    only_odom = write_bag(tmp_path / "o", None, odom)
    with pytest.raises(BagError, match="holds no sensor_msgs/msg/Imu"):
        read_imu(only_odom)


def test_each_kind_of_bad_input_gets_its_own_message(tmp_path: Path) -> None:
    """Not a bag (a folder, an image, a text file), empty, a bag without an IMU topic: what was found, what to do."""
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "a.jpg").write_bytes(b"\xff\xd8\xff\xe0" + bytes(100))
    with pytest.raises(BagError, match=r"a folder but not a rosbag2 \(no metadata.yaml.*it holds a\.jpg\)"):
        read_imu(folder)
    with pytest.raises(BagError, match="is not a bag: it is a JPEG image"):
        read_imu(folder / "a.jpg")
    png = tmp_path / "plot.bag"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(BagError, match="is not a bag: it is a PNG image"):
        read_imu(png)
    text = tmp_path / "notes.bag"
    text.write_text("imu recorded at 400 Hz\n")
    with pytest.raises(BagError, match="is not a bag: it is a text file \\(it begins 'imu recorded at 400 Hz'\\)"):
        read_imu(text)
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    with pytest.raises(BagError, match=r"is empty \(0 bytes\): the recording was never written"):
        read_imu(empty)
    _, odom = arrays(20)
    no_imu = write_bag(tmp_path / "odom_only", None, odom)
    with pytest.raises(
        BagError,
        match=r"holds no sensor_msgs/msg/Imu messages; its topics: /vehicle/odom \(nav_msgs/msg/Odometry, 2\); "
        "record the IMU driver's sensor_msgs/Imu topic",
    ):
        read_imu(no_imu)


def test_a_topic_the_bag_lacks_reads_nothing(tmp_path: Path) -> None:
    """rosbags reads every message when given no connection: asked for a topic it does not have, a bag gave all of
    its messages (2026-11-29)."""
    from bac_measure.bagio import _Bag, _collect

    imu, _ = arrays(40)
    bag = write_bag(tmp_path / "run", imu)
    with _Bag(bag) as b:
        assert list(b.raw("/vehicle/odom")) == [] and len(list(b.raw("/imu/data_raw"))) == 40
        assert _collect(b, ["/vehicle/odom"]) == {"/vehicle/odom": ([], [], [])}
