"""A small ``ros2 bag play`` for tests: publishers built from a bag's ``offered_qos_profiles``, the messages in bag
order, ``/clock`` before each of them.

As ``ros2 bag play --clock --wait-for-all-acked`` (ROS 2 Jazzy, rosbag2_transport): each topic is published with the
QoS rosbag2 derives from the recorded profiles (``bac_measure.recording.playback_qos``: the recorded reliability,
durability, deadline and liveliness, history keep last 10; rosbag2's default, reliable + volatile, for a topic
recorded without profiles), and the player waits for every reader to acknowledge before going on (rosbag2's
``--wait-for-all-acked``), so that a keep-last-10 writer loses nothing. One difference, as in bac's own
``bag_player``: a ``bac/trial`` message that ends the run being replayed waits (``hold``) until the chain has
scored it, as the live agent moved on only then (sim time stands still while the agent applies a calibration, so
the bag's times alone do not leave the chain time to answer).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosTime

from bac_campaign.bagplay import BagMessage, iter_bag_messages
from bac_measure.bagio import offered_qos
from bac_measure.recording import PLAYBACK_DEPTH, QOS_INFINITE, playback_qos

NS = 1_000_000_000


def rclpy_qos(q: Qos | None) -> QoSProfile:
    """The rclpy profile of a rosbag2 QoS (None: rosbag2's default offer, reliable + volatile, keep last 10)."""
    if q is None:
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=PLAYBACK_DEPTH,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )

    def duration(t: QosTime) -> Duration:
        if t == QOS_INFINITE:
            return Duration(nanoseconds=2**63 - 1)  # RMW_DURATION_INFINITE
        return Duration(seconds=t.sec, nanoseconds=t.nsec)

    return QoSProfile(
        history=HistoryPolicy(q.history.value),
        depth=q.depth,
        reliability=ReliabilityPolicy(q.reliability.value),
        durability=DurabilityPolicy(q.durability.value),
        deadline=duration(q.deadline),
        lifespan=duration(q.lifespan),
        liveliness=LivelinessPolicy(q.liveliness.value),
        liveliness_lease_duration=duration(q.liveliness_lease_duration),
        avoid_ros_namespace_conventions=q.avoid_ros_namespace_conventions,
    )


def _msg_class(msgtype: str) -> Any:
    import importlib

    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class Rosbag2Player:
    """Plays ``topics`` of ``bag`` from ``node`` (see the module doc)."""

    def __init__(self, node: Any, bag: Path, topics: Sequence[str], rate: float = 1.0) -> None:
        from rosgraph_msgs.msg import Clock

        self.node = node
        self.rate = rate
        self.messages: list[BagMessage] = list(iter_bag_messages(bag, topics))
        self.recorded_qos = offered_qos(bag)
        self.qos: dict[str, QoSProfile] = {}
        self.pubs: dict[str, Any] = {}
        for m in self.messages:
            if m.topic not in self.pubs:
                self.qos[m.topic] = rclpy_qos(playback_qos(self.recorded_qos.get("/" + m.topic, [])))
                self.pubs[m.topic] = node.create_publisher(_msg_class(m.msgtype), m.topic, self.qos[m.topic])
        self._clock_cls = Clock
        self.clock_pub = node.create_publisher(
            Clock,
            "/clock",
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE),
        )

    def clock(self, t_ns: int) -> None:
        m = self._clock_cls()
        m.clock.sec, m.clock.nanosec = divmod(int(t_ns), NS)
        self.clock_pub.publish(m)

    def play(self, hold: Callable[[BagMessage], bool] | None = None, hold_timeout_s: float = 60.0) -> int:
        """Publish every message at ``rate`` x the bag's pace; return how many were published."""
        if not self.messages:
            return 0
        t_bag0 = self.messages[0].time_ns
        wall0 = time.monotonic()
        sent = dict.fromkeys(self.pubs, 0)
        for m in self.messages:
            if hold is not None and hold(m):
                deadline = time.monotonic() + hold_timeout_s
                paused = time.monotonic()
                while hold(m) and time.monotonic() < deadline:
                    time.sleep(0.02)  # a wait for a condition (the chain's answer), polled
                wall0 += time.monotonic() - paused
            # pacing of the player, as ros2 bag play keeps the bag's pace (--rate)
            ahead = (m.time_ns - t_bag0) / NS / self.rate - (time.monotonic() - wall0)
            if ahead > 0:
                time.sleep(ahead)
            self.clock(m.time_ns)
            pub = self.pubs[m.topic]
            pub.publish(m.cdr)
            sent[m.topic] += 1
            if sent[m.topic] % (PLAYBACK_DEPTH // 2) == 0 or m.topic not in ("imu/data_raw", "vehicle/odom"):
                pub.wait_for_all_acked(Duration(seconds=10))  # --wait-for-all-acked, before the history is full
        self.clock(self.messages[-1].time_ns)
        return len(self.messages)
