"""``campaign_recorder``: one rosbag2 (mcap) per trial inside the campaign folder.

Subscribes every topic of a run (raw and ingested IMU, odometry, trial,
segment, score, confirmed calibration) without deserializing them and writes
the bytes as they arrived into ``<campaign_dir>/bags/trial_NNNN/``, with the
metadata ``ros2 bag record`` (Jazzy) writes: each topic offered reliable +
transient local, so ``ros2 bag play`` feeds every reader of the graph
(:mod:`bac_measure.recording`).

Topics are not ordered with respect to each other (a lagging IMU subscription
can deliver a run's last samples after the next trial was announced), so a
message goes to a trial by its *stamp*: trial k owns the stamps from its first
``bac/trial`` message up to the next trial's. The previous trial's bag stays
open for ``close_grace_s`` after the next trial starts, to take late arrivals;
Trial, RunSegment, RunScore and Calibration messages go by their trial id (and
wait for their trial's announcement when they overtake it). Stamped streams and
``bac/trial`` are written at their own stamps (a Trial's: when the agent entered
that state), the other messages at their arrival on this node's clock.

Each bag opened is first written down in ``<campaign_dir>/launches.jsonl``
with this process's launch id (:mod:`bac_campaign.launches`): a resumed campaign
holds bags of several launches whose sim times overlap, and offline tools cut each
run from the launch that drove it.
"""

from __future__ import annotations

import functools
import sys
import threading
import time
from pathlib import Path
from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

from bac_campaign.launches import LaunchIndex
from bac_common.contracts import TOPIC_CALIBRATION, TOPIC_RUN_SCORE, TOPIC_RUN_SEGMENT, TOPIC_TRIAL
from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED_READER, BacNode, run_node
from bac_common.topic_drain import TopicDrain
from bac_measure.recording import RECORDED_TOPICS, TrialBagWriter, cdr_stamp_ns, trial_bag_dir
from bac_msgs.msg import Calibration, RunScore, RunSegment, Trial

# the high-rate streams are read in batches (bac_common.topic_drain) from deep reader histories: an executor
# callback per message cannot keep up with a simulation running 10x faster than real time
SENSOR_DEEP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50000, reliability=ReliabilityPolicy.BEST_EFFORT)
STREAM_DEEP = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=50000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,  # gets what was published before it matched
)
STREAM_INPUT_DEEP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50000, reliability=ReliabilityPolicy.RELIABLE)
DRAINED_TOPICS = ("imu/data_raw", "imu/vehicle", "vehicle/odom")
STOP_QUIET_S = 0.3  # at a stop: the readers empty this long (wall) = nothing more on its way
# bac/trial is taken by the same timer, right after the streams: a stream sample taken in a batch was published
# after its trial's announcement, so the announcement is in its reader by then and the trial's bag opens before
# the sample is routed (an executor callback for bac/trial could run later than the timer that drains the
# trial's samples: on a loaded machine a whole run's raw IMU then went to the previous trial's bag)


def _msg_class(msgtype: str) -> Any:
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu

    return {
        "sensor_msgs/msg/Imu": Imu,
        "nav_msgs/msg/Odometry": Odometry,
        "bac_msgs/msg/Trial": Trial,
        "bac_msgs/msg/RunSegment": RunSegment,
        "bac_msgs/msg/RunScore": RunScore,
        "bac_msgs/msg/Calibration": Calibration,
    }[msgtype]


QOS_BY_TOPIC = {
    "imu/data_raw": SENSOR_DEEP,
    "imu/vehicle": STREAM_DEEP,
    "vehicle/odom": STREAM_INPUT_DEEP,  # may come from a car's odometry driver (volatile)
    "bac/trial": QOS_LATCHED_READER,
    "bac/run_segment": QOS_EVENTS,
    "bac/run_score": QOS_EVENTS,
    "bac/calibration": QOS_LATCHED_READER,
}


class CampaignRecorderNode(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("campaign_recorder", **kwargs)
        self.campaign_dir = self.declare_str(
            "campaign_dir", "", "campaign folder; bags go to <campaign_dir>/bags/trial_NNNN", read_only=True
        )
        self.storage = self.declare_str(
            "storage", "mcap", "rosbag2 storage", choices=("mcap", "sqlite3"), read_only=True
        )
        topics = self.declare_str_list(
            "topics", list(RECORDED_TOPICS), "topics to record (each must be a known bac topic)", read_only=True
        )
        unknown = [t for t in topics if t not in RECORDED_TOPICS]
        if unknown:
            raise ValueError(
                f"campaign_recorder: cannot record unknown topics {unknown}; known: {list(RECORDED_TOPICS)}"
            )
        if not self.campaign_dir:
            raise ValueError("campaign_recorder: parameter campaign_dir is required")
        self.close_grace_s = self.declare_float(
            "close_grace_s", 3.0, "keep the previous trial's bag open this long (wall) for late messages, s", 0.0, 60.0
        )
        self._lock = threading.RLock()
        # open bags: trial id -> (writer, first stamp of the trial in ns)
        self._open_bags: dict[int, tuple[TrialBagWriter, int]] = {}
        self._current = 0
        self._pending: dict[int, list[tuple[str, int, bytes]]] = {}  # messages of trials not announced yet
        self.dropped = 0  # messages that belong to no open trial
        self.bags: list[Path] = []
        self._launches: LaunchIndex | None = None  # opened with the first bag
        group = MutuallyExclusiveCallbackGroup()
        self._subs = [
            (
                t,
                self.create_subscription(
                    _msg_class(RECORDED_TOPICS[t]),
                    t,
                    functools.partial(self._on_message, t),
                    QOS_BY_TOPIC[t],
                    raw=True,
                    callback_group=group,
                ),
            )
            for t in topics
            if t not in DRAINED_TOPICS and t != TOPIC_TRIAL
        ]
        self._trial_drain = (
            TopicDrain(self, Trial, TOPIC_TRIAL, QOS_BY_TOPIC[TOPIC_TRIAL]) if TOPIC_TRIAL in topics else None
        )
        raw_reliability = self.declare_str(
            "imu_raw_reliability",
            "best_effort",
            "QoS reliability of the imu/data_raw recording: best_effort (IMU drivers publish so) or reliable "
            "(a simulator publishing reliably: the bag then holds every sample, even on a loaded machine)",
            choices=("best_effort", "reliable"),
            read_only=True,
        )
        qos = dict(QOS_BY_TOPIC)
        if raw_reliability == "reliable":
            qos["imu/data_raw"] = STREAM_INPUT_DEEP
        self._drains = [
            (t, TopicDrain(self, _msg_class(RECORDED_TOPICS[t]), t, qos[t])) for t in topics if t in DRAINED_TOPICS
        ]
        self.drain_period_s = self.declare_float(
            "drain_period_s", 0.02, "how often the high-rate streams are taken from their readers, s", 0.001, 1.0
        )
        self.stop_drain_s = self.declare_float(
            "stop_drain_s",
            2.0,
            "at a stop, keep taking what is still on its way (a recorder lagging on a loaded machine) until nothing "
            f"came for {STOP_QUIET_S} s, at most this long (wall), s",
            0.0,
            30.0,
        )
        self._wall = Clock(clock_type=ClockType.STEADY_TIME)
        self._close_timers: list[Any] = []
        self._stopping = False
        self._drain_timer = self.create_timer(self.drain_period_s, self._drain, callback_group=group, clock=self._wall)
        self.get_logger().info(f"recording {len(topics)} topics into {Path(self.campaign_dir) / 'bags'}")

    # --- routing -----------------------------------------------------------------------
    def _drain(self) -> int:
        """Route what waits in the drained readers; the number of messages taken."""
        batches = [(topic, drain.take()) for topic, drain in self._drains]
        taken = sum(len(b) for _, b in batches)
        if self._trial_drain is not None:  # after the streams (the note at DRAINED_TOPICS)
            for data in self._trial_drain.take():
                self._on_message(TOPIC_TRIAL, data)
                taken += 1
        for topic, batch in batches:
            for data in batch:
                self._on_message(topic, data)
        return taken

    def _take_callback_topics(self) -> int:
        """At a stop the executor no longer runs the callbacks: take what waits in those readers too."""
        taken = 0
        for topic, sub in self._subs:
            with sub.handle:
                while (got := sub.handle.take_message(sub.msg_type, True)) is not None:
                    self._on_message(topic, got[0])
                    taken += 1
        return taken

    def _drain_until_quiet(self) -> None:
        """Take everything until the readers stay empty for STOP_QUIET_S, at most ``stop_drain_s``: the end of a run
        the agent just scored can still be on its way here when the graph stops (the DDS threads of a process
        starved by a loaded machine deliver it late; seen in CI, a run's last 0.7 s missing from its bag)."""
        start = time.monotonic()
        quiet_since = start
        while True:
            if self._drain() + self._take_callback_topics():
                quiet_since = time.monotonic()
            now = time.monotonic()
            if now - quiet_since >= STOP_QUIET_S or now - start >= self.stop_drain_s:
                return
            time.sleep(0.02)

    def cleanup_time_s(self) -> float:
        return self.stop_drain_s + 1.0  # the drain at a stop, then the bags' closing

    def _on_message(self, topic: str, data: bytes) -> None:
        now_ns = self.get_clock().now().nanoseconds
        with self._lock:
            if topic == TOPIC_TRIAL:
                trial = deserialize_message(data, Trial)
                if trial.trial_id == 0:
                    return
                at = cdr_stamp_ns(data) or now_ns
                if trial.trial_id not in self._open_bags and trial.trial_id > self._current:
                    self._start_trial(trial.trial_id, at)
                # at its stamp (when the agent entered the state), like the streams at theirs: this process's clock
                # lags the simulation on a loaded machine, and a SCORED message written at its arrival came before
                # the run's last samples (a player that holds it until the run is scored then stalled)
                self._write(trial.trial_id, topic, at, data)
                if trial.state == Trial.STATE_DONE:
                    self._close_later(trial.trial_id)
                return
            if topic in (TOPIC_RUN_SEGMENT, TOPIC_RUN_SCORE, TOPIC_CALIBRATION):
                cls = {TOPIC_RUN_SEGMENT: RunSegment, TOPIC_RUN_SCORE: RunScore, TOPIC_CALIBRATION: Calibration}[topic]
                tid = int(deserialize_message(data, cls).trial_id)
                if tid > self._current and tid not in self._open_bags:
                    # its trial's announcement has not arrived yet (topics are not ordered): hold it
                    self._pending.setdefault(tid, []).append((topic, now_ns, data))
                    return
                self._write(tid if tid else self._current, topic, now_ns, data)
                return
            stamp = cdr_stamp_ns(data)
            # a batch taken from a drain arrives at once: its messages' own stamps keep their timing
            self._write(self._owner(stamp), topic, stamp or now_ns, data)

    def _owner(self, stamp_ns: int | None) -> int:
        """The open trial a stamped message belongs to (the current one when unstamped)."""
        if stamp_ns is None or stamp_ns == 0:
            return self._current
        owner = 0
        for trial_id, (_, start) in sorted(self._open_bags.items(), key=lambda kv: kv[1][1]):
            if stamp_ns >= start:
                owner = trial_id
        return owner or (min(self._open_bags) if self._open_bags else 0)

    def _write(self, trial_id: int, topic: str, now_ns: int, data: bytes) -> None:
        entry = self._open_bags.get(trial_id)
        if entry is None:
            self.dropped += 1
            if self.dropped in (1, 10, 100, 1000) or self.dropped % 10000 == 0:
                self.get_logger().warning(f"{self.dropped} messages belonged to no open trial bag (last on {topic})")
            return
        entry[0].write(topic, now_ns, data)

    # --- bags --------------------------------------------------------------------------------
    def _start_trial(self, trial_id: int, start_ns: int) -> None:
        for old in list(self._open_bags):
            self._close_later(old)
        path = trial_bag_dir(self.campaign_dir, trial_id)
        n = 1
        while path.exists():  # a resumed campaign re-drives a trial: never overwrite
            path = path.with_name(f"{trial_bag_dir(self.campaign_dir, trial_id).name}.r{n}")
            n += 1
        if self._launches is None:
            self._launches = LaunchIndex(self.campaign_dir)
        self._launches.bag_opened(path, trial_id, start_ns)  # durably, before the bag holds anything
        self._open_bags[trial_id] = (TrialBagWriter(path, storage=self.storage), start_ns)
        self._current = trial_id
        for topic, t_ns, data in self._pending.pop(trial_id, []):
            self._write(trial_id, topic, t_ns, data)
        self.bags.append(path)
        self.get_logger().info(f"trial {trial_id}: recording into {path}")

    def _close_later(self, trial_id: int) -> None:
        if self._stopping:  # every bag is closed at the end of the stop (and no timer can be made once SIGINT shut
            return  # the context down: the error would lose the batch being routed)

        def close() -> None:
            with self._lock:
                self._close(trial_id)
            timer.cancel()

        timer = self.create_timer(max(self.close_grace_s, 1e-3), close, clock=self._wall)
        self._close_timers.append(timer)

    def _close(self, trial_id: int) -> None:
        entry = self._open_bags.pop(trial_id, None)
        if entry is not None:
            entry[0].close()
            self.get_logger().info(f"closed {entry[0].path} ({entry[0].count} messages)")

    def destroy_node(self) -> None:
        self._stopping = True
        with self._lock:
            try:
                self._drain_until_quiet()  # what arrived since the last drain, and what is still on its way
            except Exception as exc:
                self.get_logger().warning(f"last drain failed: {exc}")
            for trial_id in list(self._open_bags):
                self._close(trial_id)
            if self._launches is not None:
                self._launches.close()
        for _, drain in self._drains:
            drain.destroy()
        if self._trial_drain is not None:
            self._trial_drain.destroy()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(CampaignRecorderNode, args)


if __name__ == "__main__":
    sys.exit(main())
