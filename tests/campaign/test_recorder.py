"""campaign_recorder: one mcap bag per trial, readable by rosbags and rclpy alike."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader

from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED, QOS_STREAM
from bac_measure.bagio import read_trials
from bac_measure.recording import bac_typestore
from bac_msgs.msg import RunScore, Trial

from conftest import wait_for

pytestmark = pytest.mark.integration


def trial(trial_id: int, state: int, stamp_s: float) -> Trial:
    t = Trial(
        campaign_id="c1",
        trial_id=trial_id,
        attempt=1,
        state=state,
        last_j=math.nan,
        best_j=math.nan,
        predicted_j=math.nan,
        predicted_j_std=math.nan,
    )
    t.stamp.sec, t.stamp.nanosec = int(stamp_s), int((stamp_s % 1) * 1e9)
    return t


def imu(stamp_s: float, az: float) -> Any:
    from sensor_msgs.msg import Imu

    m = Imu()
    m.header.stamp.sec, m.header.stamp.nanosec = int(stamp_s), round((stamp_s % 1) * 1e9)
    m.linear_acceleration.z = az
    return m


def read_bag(path: Path) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    with AnyReader([path], default_typestore=bac_typestore()) as reader:
        for conn, _t, raw in reader.messages():
            assert conn.topic.startswith("/")  # fully qualified, as ros2 bag record writes them
            out.setdefault(conn.topic.lstrip("/"), []).append(reader.deserialize(raw, conn.msgtype))
    return out


def test_one_bag_per_trial(procs: Any, ros_context: Any, tmp_path: Path) -> None:
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu

    camp = tmp_path / "campaign"
    procs.python(
        "recorder",
        ["-m", "bac_campaign.recorder_node", "--ros-args", "-p", f"campaign_dir:={camp}", "-p", "close_grace_s:=5.0"],
    )
    node = ros_context.node("feeder")
    p_trial = node.create_publisher(Trial, "bac/trial", QOS_LATCHED)
    p_imu = node.create_publisher(Imu, "imu/vehicle", QOS_STREAM)
    p_odom = node.create_publisher(Odometry, "vehicle/odom", QOS_STREAM)
    p_score = node.create_publisher(RunScore, "bac/run_score", QOS_EVENTS)
    for p in (p_trial, p_imu, p_odom, p_score):
        wait_for(lambda p=p: p.get_subscription_count() > 0, 60, what=f"recorder on {p.topic_name}")

    # trial 2 is announced before trial 1's samples arrive: they still go to trial 1 by their stamps
    p_trial.publish(trial(1, Trial.STATE_READY_TO_DRIVE, 10.0))
    wait_for(lambda: (camp / "bags" / "trial_0001").exists(), 20, what="bag of trial 1 opened")
    p_trial.publish(trial(2, Trial.STATE_READY_TO_DRIVE, 20.0))
    wait_for(lambda: (camp / "bags" / "trial_0002").exists(), 20, what="bag of trial 2 opened")
    for i in range(50):
        p_imu.publish(imu(10.0 + 0.1 * i, 0.1 * i))
    o = Odometry()
    o.header.stamp.sec = 15
    o.twist.twist.linear.x = 8.33
    p_odom.publish(o)
    p_score.publish(RunScore(campaign_id="c1", trial_id=1, attempt=1, j=1.2345, valid=True))
    for i in range(10):
        p_imu.publish(imu(20.0 + 0.1 * i, -1.0))
    p_trial.publish(trial(2, Trial.STATE_DONE, 22.0))
    for n in (1, 2):
        wait_for(lambda n=n: (camp / "bags" / f"trial_000{n}" / "metadata.yaml").exists(), 30, what=f"bag {n} closed")

    b1 = read_bag(camp / "bags" / "trial_0001")
    assert len(b1["imu/vehicle"]) == 50
    assert [round(m.linear_acceleration.z, 6) for m in b1["imu/vehicle"]][:3] == [0.0, 0.1, 0.2]
    assert b1["bac/run_score"][0].j == 1.2345 and b1["vehicle/odom"][0].twist.twist.linear.x == 8.33
    assert [t.trial_id for t in b1["bac/trial"]] == [1]
    b2 = read_bag(camp / "bags" / "trial_0002")
    assert [m.linear_acceleration.z for m in b2["imu/vehicle"]] == [-1.0] * 10
    assert [t.state for t in b2["bac/trial"]] == [Trial.STATE_READY_TO_DRIVE, Trial.STATE_DONE]
    assert list((camp / "bags" / "trial_0001").glob("*.mcap"))
    # a trial message is written at its own stamp, as the streams are at theirs (not at the recorder's clock, here
    # wall time 1.7e18 ns): a bag played in time order then gives a run's samples before its SCORED or the next
    # run's READY_TO_DRIVE (docs/campaign.md, section 5)
    events = read_trials(camp / "bags" / "trial_0001") + read_trials(camp / "bags" / "trial_0002")
    assert [(e.trial_id, e.recv_ns) for e in events] == [(1, 10 * 10**9), (2, 20 * 10**9), (2, 22 * 10**9)]
    assert all(e.recv_ns == e.stamp_ns for e in events)


def test_bag_bytes_deserialize_with_rclpy(tmp_path: Path) -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    from bac_measure.recording import TrialBagWriter

    msg = RunScore(campaign_id="x", trial_id=3, attempt=2, j=0.75, psd_accel_z=[1.0, 2.0], valid=True)
    with TrialBagWriter(tmp_path / "b", storage="mcap") as w:
        w.write("bac/run_score", 1_000, serialize_message(msg))
    with AnyReader([tmp_path / "b"], default_typestore=bac_typestore()) as reader:
        ((conn, t, raw),) = list(reader.messages())
    assert t == 1_000 and conn.msgtype == "bac_msgs/msg/RunScore"
    back = deserialize_message(raw, RunScore)
    assert back == msg
    with pytest.raises(OSError, match="never overwritten"):
        TrialBagWriter(tmp_path / "b")


def test_a_trial_announced_with_its_samples_in_one_batch_gets_them(ros_context: Any, tmp_path: Path) -> None:
    """The announcement and the run's samples both wait in their readers when the drain comes round (a loaded
    machine): the trial's bag opens first and takes its samples, not the previous trial's bag (seen in a CI run)."""
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Imu

    from bac_campaign.recorder_node import CampaignRecorderNode

    camp = tmp_path / "campaign"
    # never spun: nothing but the explicit drains below reads its topics
    rec = CampaignRecorderNode(
        context=ros_context.context,
        parameter_overrides=[Parameter("campaign_dir", value=str(camp)), Parameter("close_grace_s", value=30.0)],
    )
    try:
        node = ros_context.node("feeder")
        p_trial = node.create_publisher(Trial, "bac/trial", QOS_LATCHED)
        p_raw = node.create_publisher(Imu, "imu/data_raw", QOS_STREAM)
        for p in (p_trial, p_raw):
            wait_for(lambda p=p: p.get_subscription_count() > 0, 60, what=f"recorder on {p.topic_name}")
        p_trial.publish(trial(1, Trial.STATE_READY_TO_DRIVE, 10.0))
        for i in range(30):
            p_raw.publish(imu(10.0 + 0.1 * i, 1.0))
        p_trial.publish(trial(2, Trial.STATE_READY_TO_DRIVE, 20.0))
        for i in range(20):
            p_raw.publish(imu(20.0 + 0.1 * i, 2.0))

        def written() -> int:
            rec._drain()
            return sum(w.count for w, _ in rec._open_bags.values())

        wait_for(lambda: written() == 52, 30, what="2 announcements and 50 samples routed")
        assert rec.dropped == 0
    finally:
        rec.destroy_node()
    b1 = read_bag(camp / "bags" / "trial_0001")
    b2 = read_bag(camp / "bags" / "trial_0002")
    assert [m.linear_acceleration.z for m in b1["imu/data_raw"]] == [1.0] * 30
    assert [m.linear_acceleration.z for m in b2["imu/data_raw"]] == [2.0] * 20


def stopping_recorder(ros_context: Any, camp: Path, stop_drain_s: float) -> tuple[Any, Any, dict[str, Any]]:
    """A recorder on a context of its own (shut down before its destruction, as SIGINT does), never spun, trial 1's
    bag open; and a feeder's publishers."""
    import rclpy
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Imu

    from bac_campaign.recorder_node import CampaignRecorderNode

    own = rclpy.Context()
    rclpy.init(context=own, domain_id=ros_context.context.get_domain_id())
    rec = CampaignRecorderNode(
        context=own,
        parameter_overrides=[
            Parameter("campaign_dir", value=str(camp)),
            Parameter("close_grace_s", value=30.0),
            Parameter("stop_drain_s", value=stop_drain_s),
        ],
    )
    node = ros_context.node("feeder")
    pubs = {
        "trial": node.create_publisher(Trial, "bac/trial", QOS_LATCHED),
        "raw": node.create_publisher(Imu, "imu/data_raw", QOS_STREAM),
        "score": node.create_publisher(RunScore, "bac/run_score", QOS_EVENTS),
    }
    for pub in pubs.values():
        wait_for(lambda pub=pub: pub.get_subscription_count() > 0, 60, what=f"recorder on {pub.topic_name}")
    pubs["trial"].publish(trial(1, Trial.STATE_READY_TO_DRIVE, 10.0))
    wait_for(lambda: rec._drain() and (camp / "bags" / "trial_0001").exists(), 20, what="bag of trial 1 opened")
    return rec, own, pubs


def test_at_a_stop_the_recorder_takes_what_is_still_on_its_way(
    ros_context: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A CI run lost the last 0.7 s of a scored run and its RunScore from the run's bag: the agent was killed right
    after the score, and the recorder, lagging on a loaded machine, was stopped before its readers had them. At a
    stop it now keeps taking until its readers stay empty for a while: here, after its context was shut down (as
    SIGINT does), samples published for 0.4 s more, a RunScore no executor callback ever ran for, and what a
    lagging recorder gets late after a score: the next trial's announcement and its samples, the campaign's end."""
    import threading

    import rclpy

    from bac_campaign import recorder_node

    monkeypatch.setattr(recorder_node, "STOP_QUIET_S", 1.0)  # a feeder thread starved on a loaded machine
    camp = tmp_path / "campaign"
    rec, own, pubs = stopping_recorder(ros_context, camp, stop_drain_s=10.0)
    pubs["score"].publish(RunScore(campaign_id="c1", trial_id=1, attempt=1, j=0.5, valid=True))
    n = 40

    def feed() -> None:
        for i in range(n):
            pubs["raw"].publish(imu(10.0 + 0.01 * i, 3.0))
            time.sleep(0.01)  # a stream still arriving while the recorder stops, not a wait for a condition
        pubs["trial"].publish(trial(2, Trial.STATE_READY_TO_DRIVE, 20.0))
        for i in range(10):
            pubs["raw"].publish(imu(20.0 + 0.01 * i, 4.0))
        pubs["trial"].publish(trial(2, Trial.STATE_DONE, 21.0))

    feeder = threading.Thread(target=feed)
    rclpy.try_shutdown(context=own)  # what SIGINT does before the node is destroyed
    feeder.start()
    rec.destroy_node()
    feeder.join()
    b1 = read_bag(camp / "bags" / "trial_0001")
    assert [m.linear_acceleration.z for m in b1["imu/data_raw"]] == [3.0] * n
    assert [m.j for m in b1["bac/run_score"]] == [0.5]
    b2 = read_bag(camp / "bags" / "trial_0002")
    assert [m.linear_acceleration.z for m in b2["imu/data_raw"]] == [4.0] * 10
    assert [t.state for t in b2["bac/trial"]] == [Trial.STATE_READY_TO_DRIVE, Trial.STATE_DONE]
    assert rec.dropped == 0


def test_a_stream_that_never_goes_quiet_holds_the_stop_at_most_stop_drain_s(ros_context: Any, tmp_path: Path) -> None:
    """On the car the IMU driver is outside the graph and goes on publishing: the stop's drain ends at its cap."""
    import threading

    import rclpy

    rec, own, pubs = stopping_recorder(ros_context, tmp_path / "campaign", stop_drain_s=0.5)
    done = threading.Event()

    def feed() -> None:
        i = 0
        while not done.is_set():
            pubs["raw"].publish(imu(10.0 + 0.01 * i, 3.0))
            i += 1
            time.sleep(0.01)  # pacing a stream, not a wait for a condition

    feeder = threading.Thread(target=feed)
    feeder.start()
    try:
        rclpy.try_shutdown(context=own)
        t0 = time.monotonic()
        rec.destroy_node()
        took = time.monotonic() - t0
    finally:
        done.set()
        feeder.join()
    assert 0.5 <= took < 3.0, f"the stop took {took:.2f} s with stop_drain_s 0.5"
    assert (tmp_path / "campaign" / "bags" / "trial_0001" / "metadata.yaml").exists()
