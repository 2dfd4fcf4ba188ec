"""Replay: play recorded bags into the live graph on ``/clock`` (node ``bag_player``, ``bac replay``).

The ``replay`` profile runs ``bag_player`` beside the online measurement chain
(imu_ingest, run_segmenter, kpi_scorer): the recorded ``imu/data_raw``,
``vehicle/odom`` and ``bac/trial`` go out again as they were, on a sim clock
paced at ``rate`` times real time, and the chain cuts and scores every run
anew. A bag without ``bac/trial`` messages (any IMU recording) gets one
synthesized READY_TO_DRIVE trial per bag. When every replayed run has its
score (or ``score_timeout_s`` passed), the player logs a table of recorded vs
replayed J, writes it as JSON when ``output`` is set, and ends the graph.

    bac replay CAMPAIGN_DIR_OR_BAGS... [--rate 10] [--output scores.json] [-p node.param:=v]
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

from bac_campaign.bagplay import (
    PLAY_TOPICS,
    BagMessage,
    BagReadError,
    expand_bag_paths,
    iter_bag_messages,
    nothing_to_play,
    parse_topic_map,
    play_timeline,
)
from bac_common.contracts import TOPIC_CLOCK, TOPIC_RUN_SCORE, TOPIC_TRIAL
from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED, BacNode, run_node
from bac_measure.recording import OLD_MESSAGE_PAD
from bac_msgs.msg import RunScore, Trial

# while the player holds the current run's own end state (SCORED, REJECTED, ...) for the replayed score, it plays the
# sensor streams recorded after it up to this far (sim time) and never past another trial message: the live agent's
# clock can lag /clock, so the state may be stamped before the last samples the run needs (CI 2026-11-29: a run
# cancelled, "the trial entered state 4 before the run was complete", after the hold timed out)
LOOK_AHEAD_NS = 5_000_000_000
RunKey = tuple[str, int, int]


# played faster than real time: a deep reliable writer history, so that a reliable imu_ingest loses nothing
# (a best-effort reader, like the car profile's, still matches a reliable writer)
QOS_PLAY = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50000, reliability=ReliabilityPolicy.RELIABLE)


def _types() -> dict[str, Any]:
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu

    return {
        "imu/data_raw": (Imu, QOS_PLAY),
        "vehicle/odom": (Odometry, QOS_PLAY),
        "bac/trial": (Trial, QOS_LATCHED),
    }


def _run_score(cdr: bytes) -> RunScore:
    """A recorded RunScore; one recorded before outcome_names / outcome_values (2026-11-24) with them empty."""
    try:
        return deserialize_message(cdr, RunScore)
    except Exception:  # rclpy raises a bare RuntimeError-like error for a message that ends early
        return deserialize_message(cdr + OLD_MESSAGE_PAD, RunScore)


class BagPlayerNode(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("bag_player", **kwargs)
        bags = self.declare_str_list("bags", [], "campaign folders or bags to play, in order", read_only=True)
        topic_map = self.declare_str_list(
            "topic_map",
            [],
            "remappings FROM:=TO applied to the bags' topics, e.g. /imu/data:=imu/data_raw",
            read_only=True,
        )
        self.rate = self.declare_float("rate", 10.0, "playback speed, multiple of real time", 0.01, 1000.0)
        self.synthesize_trials = self.declare_bool(
            "synthesize_trials", True, "publish a READY_TO_DRIVE trial per bag that has none", read_only=True
        )
        self.campaign_id = self.declare_str(
            "campaign_id", "replay", "campaign id of synthesized trials", read_only=True
        )
        self.score_timeout_s = self.declare_float(
            "score_timeout_s", 60.0, "after the last message, wait this long (wall) for the scores, s", 0.0, 3600.0
        )
        self.wait_subscribers_s = self.declare_float(
            "wait_subscribers_s",
            30.0,
            "wait this long (wall) for subscribers of the played topics before playing, s",
            0.0,
            600.0,
        )
        self.settle_s = self.declare_float(
            "settle_s",
            2.0,
            "once every played topic and bac/run_score are connected, wait this long (wall) more before playing: "
            "discovery is not symmetric, and the chain's own links (imu/vehicle, bac/run_segment) match on their own",
            0.0,
            60.0,
        )
        self.output = self.declare_str("output", "", "write recorded vs replayed J as JSON to this file")
        channel_map = self.declare_str(
            "channel_map",
            "",
            "MDF files: YAML mapping roles (accel_x ... gyro_z, speed, distance) to channels",
            read_only=True,
        )
        channels = self.declare_str_list(
            "channels", [], "MDF files: ROLE=CHANNEL pairs (win over channel_map)", read_only=True
        )
        self.hold_s = self.declare_float(
            "hold_for_score_s",
            30.0,
            "before a new run starts, wait this long (wall) for the previous run's score, as the live agent did; "
            "0 = never wait",
            0.0,
            600.0,
        )
        if not bags:
            raise ValueError("bag_player: parameter 'bags' is empty: give campaign folders or bag paths")
        self.paths = expand_bag_paths(bags)
        self.topic_map = parse_topic_map(topic_map)
        from bac_measure.mdfio import ChannelMap

        self.channels = ChannelMap.load(channel_map or None, channels)
        self.queue, self.recorded = self._load()
        self.get_logger().info(
            f"{len(self.queue)} messages from {len(self.paths)} bags; {len(self.expected)} runs to rescore"
        )
        types = _types()
        self.pubs = {t: self.create_publisher(cls, t, qos) for t, (cls, qos) in types.items()}
        from rosgraph_msgs.msg import Clock as ClockMsg

        self.clock_pub = self.create_publisher(ClockMsg, TOPIC_CLOCK, 10)
        self._clock_cls = ClockMsg
        self.scores: dict[RunKey, RunScore | None] = {}  # None: given up waiting
        self.score_sub = self.create_subscription(RunScore, TOPIC_RUN_SCORE, self._on_score, QOS_EVENTS)
        self._wall = Clock(clock_type=ClockType.STEADY_TIME)
        self._t_start_wall: float | None = None
        self._t_wait0 = time.monotonic()
        self._t_ready: float | None = None
        self._i = 0
        self._last_tick = time.monotonic()
        self._current_run: RunKey | None = None
        self._hold_since: float | None = None
        self._end_wall: float | None = None
        self._played_ahead: set[int] = set()  # queue indices played ahead of a held end state
        self._ahead_next = 0  # the next index the look-ahead may play
        self._clock_hw = 0  # the latest /clock published: it never goes back
        self._bag_t0 = self.queue[0].time_ns if self.queue else 0
        self.timer = self.create_timer(0.002, self._tick, clock=self._wall)

    # --- loading ------------------------------------------------------------------------
    def _load(self) -> tuple[list[BagMessage], dict[RunKey, float]]:
        recorded: dict[RunKey, float] = {}
        self.expected: set[RunKey] = set()
        plays: list[list[BagMessage]] = []
        silent: list[str] = []  # bags with nothing to play, and why
        for k, path in enumerate(self.paths, start=1):
            msgs = list(iter_bag_messages(path, [*PLAY_TOPICS, TOPIC_RUN_SCORE], self.topic_map, self.channels))
            play = [m for m in msgs if m.topic in PLAY_TOPICS]
            for m in msgs:
                if m.topic == TOPIC_RUN_SCORE:
                    s = _run_score(m.cdr)
                    recorded[(s.campaign_id, s.trial_id, s.attempt)] = s.j if s.valid else math.nan
            trials = [deserialize_message(m.cdr, Trial) for m in play if m.topic == TOPIC_TRIAL]
            for t in trials:
                if t.state == Trial.STATE_READY_TO_DRIVE:
                    self.expected.add((t.campaign_id, t.trial_id, t.attempt))
            if not trials and self.synthesize_trials and play:
                t0 = min(m.time_ns for m in play) - 1
                trial = Trial(
                    campaign_id=self.campaign_id,
                    trial_id=k,
                    attempt=1,
                    state=Trial.STATE_READY_TO_DRIVE,
                    instruction="replayed recording",
                    last_j=math.nan,
                    best_j=math.nan,
                    predicted_j=math.nan,
                    predicted_j_std=math.nan,
                )
                trial.stamp.sec, trial.stamp.nanosec = divmod(t0, 1_000_000_000)
                from rclpy.serialization import serialize_message

                play.insert(0, BagMessage(TOPIC_TRIAL, "bac_msgs/msg/Trial", t0, serialize_message(trial)))
                self.expected.add((self.campaign_id, k, 1))
            if not play:
                silent.append(nothing_to_play(path, PLAY_TOPICS))
            plays.append(play)
        if silent and len(silent) == len(self.paths):
            raise BagReadError("nothing to play: " + "; ".join(silent))
        for why in silent:
            self.get_logger().warning(why)
        notes: list[str] = []
        queue = play_timeline(self.paths, plays, notes)  # a launch's bags as one timeline, in event order
        for note in notes:
            self.get_logger().warning(note)
        return queue, recorded

    # --- playing --------------------------------------------------------------------------
    def _publish_clock(self, t_ns: int) -> None:
        self._clock_hw = max(self._clock_hw, int(t_ns))
        msg = self._clock_cls()
        msg.clock.sec, msg.clock.nanosec = divmod(self._clock_hw, 1_000_000_000)
        self.clock_pub.publish(msg)

    def _tick(self) -> None:
        if self.exit_code is not None:  # finished: the executor may still run a tick or two before it stops
            return
        if self._t_start_wall is None:
            # discovery between processes takes seconds: play once the chain listens to every played topic
            counts = {t: p.get_subscription_count() for t, p in self.pubs.items()}
            ready = all(n > 0 for t, n in counts.items() if any(m.topic == t for m in self.queue[:1000]))
            ready = ready and self.score_sub.get_publisher_count() > 0  # the scorer is there to answer
            now = time.monotonic()
            if ready and self._t_ready is None:
                self._t_ready = now
            if ready and now - (self._t_ready or now) < self.settle_s:
                return
            if not ready and now - self._t_wait0 < self.wait_subscribers_s:
                return
            self._t_start_wall = time.monotonic()
            self._last_tick = self._t_start_wall
            self.get_logger().info(f"playing at {self.rate:g}x real time (subscribers: {counts})")
        wall = time.monotonic()
        now_bag = self._bag_t0 + int((wall - self._t_start_wall) * self.rate * 1e9)
        while self._i < len(self.queue) and self.queue[self._i].time_ns <= now_bag:
            if self._i in self._played_ahead:
                self._played_ahead.discard(self._i)
                self._i += 1
                continue
            m = self.queue[self._i]
            if m.topic == TOPIC_TRIAL and self._holds(m, wall):
                # the live agent started this run only after the previous one was scored: so does the replay
                # (the sim clock stands still meanwhile)
                self._t_start_wall += wall - self._last_tick
                now_bag = m.time_ns
                if self._current_run is not None and self._trial_key(m) == self._current_run:
                    self._play_ahead(m.time_ns + LOOK_AHEAD_NS)
                break
            self._publish_clock(m.time_ns)
            self.pubs[m.topic].publish(m.cdr)
            self._i += 1
        self._last_tick = wall
        self._publish_clock(now_bag)
        if self._i < len(self.queue):
            return
        if self._end_wall is None:
            self._end_wall = time.monotonic()
            self.get_logger().info("all messages played; waiting for the scores")
        missing = self.expected - {k for k, v in self.scores.items() if v is not None}
        if not missing or time.monotonic() - self._end_wall > self.score_timeout_s:
            self._report(missing)
            self.finish(0)

    @staticmethod
    def _trial_key(m: BagMessage) -> RunKey:
        t = deserialize_message(m.cdr, Trial)
        return (t.campaign_id, t.trial_id, t.attempt)

    def _play_ahead(self, limit_ns: int) -> None:
        """Play the sensor messages after the held one up to ``limit_ns``, never past another trial message (see
        LOOK_AHEAD_NS); the queue skips them when it gets there."""
        j = max(self._ahead_next, self._i + 1)
        while j < len(self.queue) and self.queue[j].time_ns <= limit_ns and self.queue[j].topic != TOPIC_TRIAL:
            q = self.queue[j]
            self._publish_clock(q.time_ns)
            self.pubs[q.topic].publish(q.cdr)
            self._played_ahead.add(j)
            j += 1
        self._ahead_next = j

    def _holds(self, m: BagMessage, wall: float) -> bool:
        """True while a trial message must wait for the current run's score.

        The live graph moved on (the next state of the trial, the next run) only once the run was scored;
        the replay does the same, so that the chain gets each run whole (the sim clock stands still meanwhile).
        """
        t = deserialize_message(m.cdr, Trial)
        key = (t.campaign_id, t.trial_id, t.attempt)
        current = self._current_run
        starts_run = t.state == Trial.STATE_READY_TO_DRIVE and key != current
        if current is not None and current not in self.scores and self.hold_s > 0 and (starts_run or key == current):
            if t.state == Trial.STATE_READY_TO_DRIVE and key == current:
                return False  # the same state again (a latched repeat)
            if self._hold_since is None:
                self._hold_since = wall
            if wall - self._hold_since < self.hold_s:
                return True
            self.get_logger().warning(f"no score for run {current} within {self.hold_s:g} s: playing on")
            self.scores.setdefault(current, None)
        self._hold_since = None
        if starts_run:
            self._current_run = key
        return False

    def _on_score(self, msg: RunScore) -> None:
        self.scores[(msg.campaign_id, msg.trial_id, msg.attempt)] = msg

    def _report(self, missing: set[RunKey]) -> None:
        rows: list[dict[str, Any]] = []
        for key in sorted(self.expected):
            s = self.scores.get(key)
            rows.append(
                {
                    "campaign_id": key[0],
                    "trial_id": key[1],
                    "attempt": key[2],
                    "recorded_j": self.recorded.get(key),
                    "replayed_j": (s.j if s.valid else None) if s is not None else None,
                    "valid": bool(s.valid) if s is not None else False,
                    "reason": (s.reason if s is not None else "no score within the timeout"),
                }
            )
        lines = ["trial attempt  recorded_J   replayed_J   valid  reason"]
        for r in rows:
            rec = r["recorded_j"]
            rep = r["replayed_j"]
            lines.append(
                f"{r['trial_id']:5d} {r['attempt']:7d}  "
                f"{rec if rec is not None and not math.isnan(rec) else float('nan'):10.6f}   "
                f"{rep if rep is not None else float('nan'):10.6f}   {r['valid']!s:5s}  {r['reason']}"
            )
        self.get_logger().info("replayed runs:\n" + "\n".join(lines))
        if missing:
            self.get_logger().warning(f"{len(missing)} runs got no score: {sorted(missing)}")
        if self.output:
            Path(self.output).write_text(json.dumps({"runs": rows}, indent=2, allow_nan=False, default=str))


def main(args: list[str] | None = None) -> int:
    return run_node(BagPlayerNode, args)


if __name__ == "__main__":
    sys.exit(main())
