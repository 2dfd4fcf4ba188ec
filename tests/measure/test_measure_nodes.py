"""imu_ingest -> run_segmenter -> kpi_scorer as real processes over real topics, on sim time.

The test plays a raw IMU stream (sensor frame, gravity in, 500 Hz) on
``imu/data_raw``, odometry on ``vehicle/odom``, ``/clock`` and ``bac/trial``
like vehicle_sim and bo_agent would, and checks what comes out: the same J as
the pure cores on the same samples (to 1e-9), exactly one segment and one
score per run, a timed-out run, and NaN + a 0.5 s gap reported in
/diagnostics with the run invalid.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bac_imu.ingest import GRAVITY, IngestConfig, ingest_all
from bac_measure.kpi import KpiConfig, score
from bac_measure.segmentation import ImuSeries, OdomSeries, SegmentConfig, cut_run
from bac_measure.synthetic import NS, bump_run, road_run

from conftest import wait_for

pytestmark = pytest.mark.integration

T0 = 1_000 * NS  # sim time of the first sample
RAW_HZ = 500.0


@dataclass
class Stream:
    """A raw IMU stream and odometry on one sim-time line, and the trial events to play with them."""

    t: list[np.ndarray] = field(default_factory=list)
    acc: list[np.ndarray] = field(default_factory=list)
    gyr: list[np.ndarray] = field(default_factory=list)
    odom: list[OdomSeries] = field(default_factory=list)

    def add(self, imu: ImuSeries, odom: OdomSeries | None, seed: int) -> None:
        rng = np.random.default_rng(seed)
        n = len(imu)
        acc = 0.01 * rng.standard_normal((n, 3))
        acc[:, 2] += GRAVITY + imu.accel_z
        gyr = 0.001 * rng.standard_normal((n, 3))
        gyr[:, 1] += imu.pitch_rate
        self.t.append(imu.stamp_ns)
        self.acc.append(acc)
        self.gyr.append(gyr)
        if odom is not None:
            self.odom.append(odom)

    def end_ns(self) -> int:
        return int(self.t[-1][-1]) if self.t else T0

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, OdomSeries]:
        o = self.odom
        odom = OdomSeries(
            np.concatenate([x.stamp_ns for x in o]),
            np.concatenate([x.distance_m for x in o]),
            np.concatenate([x.speed_mps for x in o]),
        )
        return np.concatenate(self.t), np.concatenate(self.acc), np.concatenate(self.gyr), odom


def flat(t_from: int, seconds: float, seed: int) -> ImuSeries:
    n = round(seconds * RAW_HZ)
    t = t_from + np.round(np.arange(1, n + 1) * NS / RAW_HZ).astype(np.int64)
    rng = np.random.default_rng(seed)
    return ImuSeries(t, 0.02 * rng.standard_normal(n), 0.001 * rng.standard_normal(n))


def run_after(stream_end: int, maker: Any, **kw: Any) -> Any:
    """A synthetic run whose first IMU sample follows ``stream_end`` by one raw period (continuous stream)."""
    lead = 0.5
    t0 = stream_end + round(NS / RAW_HZ) + round(lead * NS)
    return maker(fs=RAW_HZ, lead_s=lead, t0_ns=t0, **kw)


class Harness:
    """The test's side of the graph: publishers of the inputs, subscribers of the outputs."""

    def __init__(self, ros_context: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import Imu

        from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED, QOS_STREAM
        from bac_msgs.msg import RunScore, RunSegment, Trial

        self.Imu, self.Odometry, self.Trial, self.Clock = Imu, Odometry, Trial, Clock
        node = ros_context.node("measure_test")
        self.node = node
        # reliable with a deep history, like a simulator (the ingest takes it with input_reliability:=reliable):
        # best effort loses samples in the DDS transport when the CPU is saturated, which is not under test here
        deep = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50_000, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_imu = node.create_publisher(Imu, "imu/data_raw", deep)
        self.pub_odom = node.create_publisher(Odometry, "vehicle/odom", QOS_STREAM)
        self.pub_trial = node.create_publisher(Trial, "bac/trial", QOS_LATCHED)
        self.pub_clock = node.create_publisher(Clock, "/clock", 10)
        self.lock = threading.Lock()
        self.segments: list[Any] = []
        self.scores: list[Any] = []
        self.diagnostics: list[Any] = []

        def keep(store: list[Any]) -> Any:
            def cb(msg: Any) -> None:
                with self.lock:
                    store.append(msg)

            return cb

        node.create_subscription(RunSegment, "bac/run_segment", keep(self.segments), QOS_EVENTS)
        node.create_subscription(RunScore, "bac/run_score", keep(self.scores), QOS_EVENTS)
        node.create_subscription(DiagnosticArray, "/diagnostics", keep(self.diagnostics), 100)

    def wait_for_graph(self) -> None:
        n = self.node
        wait_for(lambda: self.pub_imu.get_subscription_count() >= 1, 30, what="imu_ingest on imu/data_raw")
        wait_for(lambda: self.pub_odom.get_subscription_count() >= 1, 30, what="run_segmenter on vehicle/odom")
        wait_for(lambda: self.pub_trial.get_subscription_count() >= 1, 30, what="run_segmenter on bac/trial")
        wait_for(lambda: self.pub_clock.get_subscription_count() >= 3, 30, what="three nodes on /clock")
        wait_for(lambda: n.count_publishers("bac/run_score") >= 1, 30, what="kpi_scorer publishing bac/run_score")
        wait_for(lambda: n.count_subscribers("bac/run_segment") >= 2, 30, what="kpi_scorer on bac/run_segment")
        wait_for(lambda: n.count_subscribers("imu/vehicle") >= 1, 30, what="run_segmenter on imu/vehicle")

    def trial(self, campaign: str, trial_id: int, attempt: int, stamp_ns: int, state: int = 3) -> None:
        m = self.Trial()
        m.stamp.sec, m.stamp.nanosec = stamp_ns // NS, stamp_ns % NS
        m.campaign_id, m.trial_id, m.attempt, m.state = campaign, trial_id, attempt, state
        m.last_j = m.best_j = m.predicted_j = m.predicted_j_std = float("nan")
        self.pub_trial.publish(m)

    def clock(self, ns: int) -> None:
        m = self.Clock()
        m.clock.sec, m.clock.nanosec = ns // NS, ns % NS
        self.pub_clock.publish(m)

    def play(
        self, t: np.ndarray, acc: np.ndarray, gyr: np.ndarray, odom: OdomSeries, upto_ns: int, speed: float = 5.0
    ) -> None:
        """Publish the samples with stamps up to ``upto_ns`` not yet sent, odometry interleaved, the clock
        following, at about ``speed`` x real time."""
        start = getattr(self, "_sent_imu", 0)
        ostart = getattr(self, "_sent_odom", 0)
        stop = int(np.searchsorted(t, upto_ns, side="right"))
        ostop = int(np.searchsorted(odom.stamp_ns, upto_ns, side="right"))
        oi = ostart
        wall0 = time.monotonic()
        for i in range(start, stop):
            ti = int(t[i])
            while oi < ostop and odom.stamp_ns[oi] <= ti:
                o = self.Odometry()
                os_ = int(odom.stamp_ns[oi])
                o.header.stamp.sec, o.header.stamp.nanosec = os_ // NS, os_ % NS
                o.header.frame_id = "odom"
                o.pose.pose.position.x = float(odom.distance_m[oi])
                o.twist.twist.linear.x = float(odom.speed_mps[oi])
                self.pub_odom.publish(o)
                oi += 1
            m = self.Imu()
            m.header.stamp.sec, m.header.stamp.nanosec = ti // NS, ti % NS
            m.header.frame_id = "imu_link"
            m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = (float(v) for v in acc[i])
            m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = (float(v) for v in gyr[i])
            self.pub_imu.publish(m)
            if i % 50 == 49:
                self.clock(ti)
                # pacing of the player, not a wait for a condition
                ahead = (i - start) / (speed * RAW_HZ) - (time.monotonic() - wall0)
                if ahead > 0:
                    time.sleep(ahead)
        self.clock(upto_ns)
        self._sent_imu, self._sent_odom = stop, oi

    def diag(self, prefix: str) -> dict[str, str]:
        """The key values of the latest /diagnostics status whose name starts with ``prefix``."""
        with self.lock:
            mine = [st for a in self.diagnostics for st in a.status if st.name.startswith(prefix)]
        return {kv.key: kv.value for kv in mine[-1].values} if mine else {}

    def warm_up(self, t: np.ndarray, acc: np.ndarray, gyr: np.ndarray, odom: OdomSeries, upto_ns: int) -> int:
        """Play the pre-roll until data demonstrably flows through ingest and segmenter (DDS discovery
        may match a reader seconds after its writer); return the first stamp the ingest received."""
        pos = [int(t[0])]

        def flowing() -> bool:
            if pos[0] < upto_ns:
                pos[0] = min(pos[0] + NS // 10, upto_ns)
                self.play(t, acc, gyr, odom, pos[0], speed=20.0)
            seen = self.diag("run_segmenter").get("imu_last_stamp_ns", "")
            return bool(seen) and int(seen) >= pos[0] - NS // 2 and bool(self.diag("imu_ingest").get("first_stamp_ns"))

        wait_for(flowing, 30, interval=0.05, what="data flowing through imu_ingest and run_segmenter")
        self.play(t, acc, gyr, odom, upto_ns, speed=20.0)
        return int(self.diag("imu_ingest")["first_stamp_ns"])

    def by_run(self, store: list[Any], trial_id: int) -> list[Any]:
        with self.lock:
            return [m for m in store if m.trial_id == trial_id]


def start_chain(procs: Any, segmenter: dict[str, Any], ingest: dict[str, Any], kpi: dict[str, Any]) -> None:
    def args(params: dict[str, Any]) -> list[str]:
        out = ["--ros-args", "-p", "use_sim_time:=true", "-p", "diagnostics_period_s:=0.25"]
        for k, v in params.items():
            out += ["-p", f"{k}:={str(v).lower() if isinstance(v, bool) else v}"]
        return out

    procs.python("imu_ingest", ["-m", "bac_imu.ingest_node", *args({"input_reliability": "reliable", **ingest})])
    procs.python("run_segmenter", ["-m", "bac_measure.segmenter_node", *args(segmenter)])
    procs.python("kpi_scorer", ["-m", "bac_measure.scorer_node", *args(kpi)])


def test_event_runs_through_the_node_chain(procs: Any, ros_context: Any, tmp_path: Path) -> None:
    ingest_cfg = IngestConfig(output_rate_hz=200.0)
    seg_cfg = SegmentConfig(mode="event", trigger_threshold_mps2=1.0, imu_rate_hz=200.0)
    kpi_cfg = KpiConfig()
    start_chain(
        procs,
        segmenter={
            "mode": "event",
            "trigger_threshold_mps2": 1.0,
            "imu_rate_hz": 200.0,
            "run_timeout_s": 8.0,
            "campaign_dir": str(tmp_path),
        },
        ingest={"output_rate_hz": 200.0},
        kpi={},
    )
    h = Harness(ros_context)
    # the timeline (sim time): pre-roll, run 1 (bump), 9 s without an impact (run 2 times out after 8 s),
    # run 3 (bump) with a NaN sample and a 0.5 s gap inside its window
    s = Stream()
    s.add(flat(T0 - round(NS / RAW_HZ), 6.0, seed=1), None, seed=1)  # pre-roll
    r1 = run_after(s.end_ns(), bump_run, seed=11, noise=0.05)
    s.add(r1.imu, r1.odom, seed=2)
    t2 = s.end_ns() + round(NS / RAW_HZ)
    s.add(flat(s.end_ns(), 9.0, seed=3), None, seed=3)
    r3 = run_after(s.end_ns(), bump_run, seed=13, noise=0.05, offset_m=1.5)
    s.add(r3.imu, r3.odom, seed=4)
    t, acc, gyr, odom = s.arrays()
    acc[np.searchsorted(t, r3.event_ns + round(0.6 * NS)), 0] = np.nan  # one NaN sample
    gap = (t >= r3.event_ns + NS) & (t < r3.event_ns + round(1.5 * NS))  # 0.5 s without data
    t, acc, gyr = t[~gap], acc[~gap], gyr[~gap]

    h.wait_for_graph()
    h.clock(T0)
    first = h.warm_up(t, acc, gyr, odom, r1.start_ns - NS)
    h.trial("itest", 1, 1, r1.start_ns)
    h.play(t, acc, gyr, odom, r1.start_ns + 7 * NS)
    wait_for(lambda: h.by_run(h.scores, 1), 30, what="the score of run 1")
    h.trial("itest", 2, 1, t2)
    h.play(t, acc, gyr, odom, r3.start_ns - round(0.6 * NS))
    wait_for(lambda: h.by_run(h.segments, 2), 30, what="the segment of run 2 (timeout)")
    h.trial("itest", 3, 1, r3.start_ns)
    h.play(t, acc, gyr, odom, int(t[-1]))
    wait_for(lambda: h.by_run(h.scores, 3), 30, what="the score of run 3")
    wait_for(lambda: h.by_run(h.scores, 2), 30, what="the score of run 2")

    # run 1: the same J as the pure cores on the same samples (from the first one the ingest received)
    got = t >= first
    out, health = ingest_all(t[got], acc[got], gyr[got], ingest_cfg)
    imu = ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate)
    seg1 = cut_run(imu, odom, seg_cfg, r1.start_ns)
    expected = score(seg1, kpi_cfg)
    assert seg1.valid and expected.valid, seg1.reason
    (score1,) = h.by_run(h.scores, 1)
    (segment1,) = h.by_run(h.segments, 1)
    assert score1.valid and segment1.valid, (segment1.reason, score1.reason)
    assert abs(score1.j - expected.j) <= 1e-9, (score1.j, expected.j)
    assert abs(score1.rms_pitch_rate - expected.rms_pitch_rate) <= 1e-9
    assert segment1.alignment_score == 1.0 and len(segment1.accel_z) == 500
    assert (score1.campaign_id, score1.trial_id, score1.attempt) == ("itest", 1, 1)
    assert (tmp_path / "reference.npz").exists()  # the first valid run is the campaign's reference

    # run 2: no impact within run_timeout_s -> one invalid segment, one invalid score
    (segment2,) = h.by_run(h.segments, 2)
    (score2,) = h.by_run(h.scores, 2)
    assert not segment2.valid and segment2.reason.startswith("run timeout after 8.")
    assert "waiting for the impact" in segment2.reason
    assert not score2.valid and np.isnan(score2.j) and score2.reason.startswith("segment invalid: run timeout")

    # run 3: the NaN and the gap are in /diagnostics, and the run is invalid for them
    (segment3,) = h.by_run(h.segments, 3)
    (score3,) = h.by_run(h.scores, 3)
    assert not segment3.valid and "IMU data missing or invalid" in segment3.reason, segment3.reason
    assert segment3.coverage < 0.85 and not score3.valid
    assert health.nonfinite == 1 and health.gaps == 1, health.events

    def last_values() -> dict[str, str]:
        return h.diag("imu_ingest")

    wait_for(lambda: (v := last_values()) and v["nonfinite"] == "1" and v["gaps"] == "1", 10, what="diagnostics")
    with h.lock:
        statuses = [s for a in h.diagnostics for s in a.status if s.name.startswith("imu_ingest")]
    errors = [s for s in statuses if s.level == b"\x02"]
    assert errors, "no ERROR diagnostics for the NaN and the gap"
    said = " ".join(s.message for s in errors)
    assert "gap" in said and "NaN/inf" in said, said
    assert float(last_values()["longest_gap_s"]) == pytest.approx(0.502, abs=1e-3)
    # exactly one segment and one score per run, nothing else
    with h.lock:
        assert sorted(m.trial_id for m in h.segments) == [1, 2, 3]
        assert sorted(m.trial_id for m in h.scores) == [1, 2, 3]


def test_distance_run_through_the_node_chain(procs: Any, ros_context: Any, tmp_path: Path) -> None:
    seg_params = {
        "mode": "distance",
        "target_speed_mps": 60 / 3.6,
        "distance_start_m": 20.0,
        "distance_end_m": 200.0,
        "imu_rate_hz": 200.0,
        "campaign_dir": str(tmp_path),
    }
    kpi_params = {"kpi": "iso_wk_rms", "weight_pitch_rate": 2.0}
    start_chain(procs, segmenter=seg_params, ingest={"output_rate_hz": 200.0}, kpi=kpi_params)
    h = Harness(ros_context)
    s = Stream()
    s.add(flat(T0 - round(NS / RAW_HZ), 6.0, seed=1), None, seed=1)
    r1 = run_after(s.end_ns(), road_run, seed=21, noise=0.05)
    s.add(r1.imu, r1.odom, seed=2)
    t, acc, gyr, odom = s.arrays()
    h.wait_for_graph()
    h.clock(T0)
    first = h.warm_up(t, acc, gyr, odom, r1.start_ns - NS)
    h.trial("road", 4, 2, r1.start_ns)
    h.play(t, acc, gyr, odom, int(t[-1]))
    wait_for(lambda: h.by_run(h.scores, 4), 30, what="the score of the road run")
    got = t >= first
    out, _ = ingest_all(t[got], acc[got], gyr[got], IngestConfig(output_rate_hz=200.0))
    seg = cut_run(
        ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate), odom, SegmentConfig.from_params(seg_params), r1.start_ns
    )
    expected = score(seg, KpiConfig.from_params(kpi_params))
    (got,) = h.by_run(h.scores, 4)
    (segment,) = h.by_run(h.segments, 4)
    assert got.valid and segment.valid and expected.valid, (segment.reason, got.reason)
    assert abs(got.j - expected.j) <= 1e-9, (got.j, expected.j)
    assert got.kpi == "iso_wk_rms" and got.j == pytest.approx(got.weighted_rms_accel_z + 2 * got.rms_pitch_rate)
    assert segment.mode == 1 and len(segment.accel_z) == 2160 and segment.mean_speed_mps == pytest.approx(60 / 3.6)
    assert got.attempt == 2 and len(got.psd_frequency_hz) > 10
