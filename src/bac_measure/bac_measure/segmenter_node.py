"""``run_segmenter``: buffers each run and emits exactly one ``bac/run_segment`` for it.

A run starts when ``bac/trial`` (latched) enters READY_TO_DRIVE for a new
(campaign_id, trial_id, attempt); from its stamp on, ``imu/vehicle`` and
``vehicle/odom`` (any nav_msgs/Odometry: the distance is the pose's path length,
the integral of the forward speed or pose.x, by ``distance_source``) are buffered
(plus what arrived in the last ``pre_buffer_s`` of wall time, for samples
stamped after the trial's stamp that arrived before it, and the last odometry
sample before that, so that a drive in progress is told from a new one); both are
taken in batches from their DDS readers
(:mod:`bac_common.topic_drain`), so a simulator running many times faster than
real time is followed. Every ``check_period_s`` the pure core
(:func:`bac_measure.segmentation.run_status`) says whether the window is
complete; then :func:`~bac_measure.segmentation.cut_run` cuts and aligns it and
one RunSegment is published, valid or invalid with its reason. A retry
(attempt > 1) is cut only from a drive that began after it was announced: the
segmenter waits for the vehicle to come back (``waiting_for`` on
``/diagnostics`` says so). A run also ends, invalid, when it takes longer than
``run_timeout_s`` (ROS time since the trial's stamp; 0 = derived from the
segment: ``approach_time_s`` plus the section or window at the target speed),
when no IMU sample arrives for ``no_data_timeout_s`` (ROS time, so a paused
simulation clock never fires it), when another run starts, or when the trial
leaves READY_TO_DRIVE first.

The reference is the first valid run of each campaign, kept in memory and in
``reference_file`` (``{campaign_id}`` is replaced) or, by default, in
``<campaign_dir>/reference.npz`` when the launcher gives a campaign folder, so
a restarted segmenter and the offline rescoring align against the same run;
``template_file`` names a stored reference used instead.
"""

from __future__ import annotations

import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu

from bac_common import cdr
from bac_common.contracts import TOPIC_DIAGNOSTICS, TOPIC_IMU_VEHICLE, TOPIC_ODOM, TOPIC_RUN_SEGMENT, TOPIC_TRIAL
from bac_common.errors import BacError
from bac_common.node_params import ParamSpec, declare_config
from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED, QOS_STREAM, QOS_STREAM_INPUT, BacNode, run_node
from bac_common.topic_drain import TopicDrain
from bac_measure.messages import segment_to_msg
from bac_measure.segmentation import (
    ImuSeries,
    OdomSeries,
    Reference,
    ReferenceStore,
    RunId,
    Segment,
    SegmentationError,
    SegmentConfig,
    cut_run,
    invalid_segment,
    run_status,
)
from bac_msgs.msg import RunSegment, Trial

SEGMENT_PARAMS = {
    "mode": ParamSpec(
        "event (speed bump: impact-triggered window) or distance (road section by odometry)",
        choices=("event", "distance"),
    ),
    "target_speed_mps": ParamSpec("speed the runs must be driven at, m/s", 0.1, 100.0),
    "speed_tolerance": ParamSpec("accepted relative deviation of the mean speed from the target", 1e-4, 0.99),
    "imu_rate_hz": ParamSpec("rate of imu/vehicle, Hz; 0 = measured from its stamps", 0.0, 10_000.0),
    "align_signal": ParamSpec(
        "signal(s) cross-correlated with the reference to refine the cut; none: the impact trigger (event) or the "
        "odometry (distance) alone",
        choices=("accel_z", "pitch_rate", "both", "none"),
    ),
    "min_alignment": ParamSpec("minimum normalized cross-correlation with the reference", -1.0, 1.0),
    "min_coverage": ParamSpec("minimum fraction of the window with valid IMU samples (1 = all)", 1e-3, 1.0),
    "max_mean_accel_z": ParamSpec(
        "|mean a_z| over the window beyond this makes the run invalid: gravity is in it (a wrong mount), m/s^2",
        1e-3,
        100.0,
    ),
    "pre_roll_s": ParamSpec(
        "a_z before the window handed to the scorer, so the ISO 2631-1 Wk filter does not start from rest, s",
        0.0,
        60.0,
    ),
    "trigger_threshold_mps2": ParamSpec("event mode: |a_z| that marks the impact, m/s^2", 1e-3, 1000.0),
    "trigger_after_m": ParamSpec("event mode: ignore impacts before this odometry distance, m", 0.0, 1e6),
    "pre_trigger_s": ParamSpec("event mode: the window starts this long before the impact, s", 0.0, 600.0),
    "window_s": ParamSpec("event mode: window length, s", 1e-3, 600.0),
    "max_lag_s": ParamSpec("event mode: alignment search range, +- s", 0.0, 10.0),
    "distance_start_m": ParamSpec("distance mode: section start, odometry m", 0.0, 1e6),
    "distance_end_m": ParamSpec("distance mode: section end, odometry m", 0.0, 1e6),
    "distance_step_m": ParamSpec("distance mode: grid step, m; 0 = target speed / IMU rate", 0.0, 100.0),
    "max_shift_m": ParamSpec("distance mode: alignment search range, +- m (covers the start offset)", 0.0, 1000.0),
    "distance_source": ParamSpec(
        "the distance along the road from vehicle/odom: path_length (length of the pose's path, any odometry after "
        "REP 105), speed_integral (integral of twist.linear.x), position_x (pose.position.x read as an odometer)",
        choices=("position_x", "path_length", "speed_integral"),
    ),
    "distance_origin": ParamSpec(
        "position_x only: odom: pose.x is the distance since the run started; run_start: subtract its value at the "
        "drive's start (path_length and speed_integral always count from the drive's start)",
        choices=("odom", "run_start"),
    ),
    "new_drive_speed_fraction": ParamSpec(
        "a new drive begins where the speed rises through this fraction of the target speed (after a stop or a "
        "turn; also at a reset of the distance and after silent odometry): a retry needs a new drive",
        0.01,
        0.99,
    ),
    "odom_gap_s": ParamSpec("odometry silent this long (stamps, s) starts a new drive", 1e-3, 3600.0),
}


class _Stream:
    """Samples of one topic (stamps and value columns): batches appended with their arrival (wall) time,
    consolidated into arrays on demand."""

    def __init__(self, columns: int = 2) -> None:
        self.parts: list[tuple[np.ndarray, ...]] = []
        self.arr: tuple[np.ndarray, ...] = (np.zeros(0, np.int64), *(np.zeros(0) for _ in range(columns)))
        self.arrival = np.zeros(0)  # wall time each sample was taken from the reader

    def add(self, t: np.ndarray, *columns: np.ndarray, wall: float) -> None:
        if t.size:
            self.parts.append((t, *columns))
            self.arrival = np.concatenate([self.arrival, np.full(t.size, wall)])

    def arrays(self) -> tuple[np.ndarray, ...]:
        if self.parts:
            self.arr = tuple(np.concatenate([self.arr[k], *(p[k] for p in self.parts)]) for k in range(len(self.arr)))
            self.parts = []
        return self.arr

    def drop_arrived_before(self, wall: float, keep_last: int = 0) -> None:
        """Forget the samples taken before ``wall`` (monotonic), except the ``keep_last`` newest of them by stamp."""
        arr = self.arrays()
        t = arr[0]
        keep = self.arrival >= wall
        if keep_last and not np.all(keep):
            old = np.flatnonzero(~keep)
            keep[old[np.argsort(t[old], kind="stable")[-keep_last:]]] = True
        if not np.all(keep):
            self.arr = tuple(a[keep] for a in arr)
            self.arrival = self.arrival[keep]


class RunSegmenterNode(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("run_segmenter", **kwargs)
        self.config: SegmentConfig = declare_config(self, SegmentConfig, SEGMENT_PARAMS)
        run_timeout = self.declare_float(
            "run_timeout_s",
            0.0,
            "a run not complete this long after READY_TO_DRIVE (ROS time) is invalid, s; 0 = derived from the "
            "segment: approach_time_s + the section (or the window) at the target speed, with margins",
            0.0,
            1e6,
        )
        self.approach_time_s = self.declare_float(
            "approach_time_s",
            60.0,
            "with run_timeout_s 0: time the driver has to reach the segment after READY_TO_DRIVE (ROS time), s",
            0.0,
            1e6,
        )
        self.run_timeout_s = run_timeout or derived_run_timeout(self.config, self.approach_time_s)
        self.no_data_timeout_s = self.declare_float(
            "no_data_timeout_s",
            30.0,
            "a run without any IMU sample for this long (ROS time: a paused simulation clock never fires it) is "
            "invalid, s",
            0.1,
            1e6,
        )
        self.pre_buffer_s = self.declare_float(
            "pre_buffer_s",
            10.0,
            "IMU/odometry that arrived this long (wall) before the trial message are kept for its run, s",
            0.0,
            600.0,
        )
        period = self.declare_float("check_period_s", 0.1, "how often a buffered run is checked, wall s", 0.005, 10.0)
        diag = self.declare_float("diagnostics_period_s", 1.0, "period of /diagnostics, wall s", 0.05, 60.0)
        campaign_dir = self.declare_str("campaign_dir", "", "campaign folder (given by the launcher)", read_only=True)
        ref_file = self.declare_str(
            "reference_file",
            "",
            "where the campaign's reference run is kept ({campaign_id} is replaced); "
            "default <campaign_dir>/reference.npz when campaign_dir is set, else memory only",
            read_only=True,
        )
        template = self.declare_str(
            "template_file",
            "",
            "a stored reference run used for every campaign instead of the first valid run",
            read_only=True,
        )
        odom_best_effort = self.declare_bool(
            "odom_best_effort", False, "subscribe vehicle/odom best effort (a car's odometry driver)", read_only=True
        )
        if not ref_file and campaign_dir:
            ref_file = str(Path(campaign_dir) / "reference.npz")
        tmpl = Reference.load(template) if template else None
        self.references = ReferenceStore(ref_file, tmpl)
        self.imu = _Stream(2)  # a_z, pitch rate
        self.odom = _Stream(4)  # pose x, speed, pose y, pose z
        self.run: RunId | None = None
        self.run_start_ns = 0
        self.run_wall_start = 0.0
        self.last_imu_ros_ns = 0
        self.emitted: set[tuple[str, int, int]] = set()
        self.waiting_for = ""
        self.last_result = ""
        self.pub = self.create_publisher(RunSegment, TOPIC_RUN_SEGMENT, QOS_EVENTS)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        odom_qos = (
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2000, reliability=ReliabilityPolicy.BEST_EFFORT)
            if odom_best_effort
            else QOS_STREAM_INPUT  # volatile: matches a car's odometry driver as well as vehicle_sim
        )
        # high-rate streams: drained in batches by the check timer (bac_common.topic_drain)
        self.imu_drain = TopicDrain(self, Imu, TOPIC_IMU_VEHICLE, QOS_STREAM)
        self.odom_drain = TopicDrain(self, Odometry, TOPIC_ODOM, odom_qos)
        self.create_subscription(Trial, TOPIC_TRIAL, self._on_trial, QOS_LATCHED)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self._check, clock=steady)
        self.create_timer(diag, self._diagnostics, clock=steady)
        where = self.references.path or "memory"
        self.get_logger().info(
            f"{self.config.mode} mode at {self.config.target_speed_mps * 3.6:.1f} km/h; run timeout "
            f"{self.run_timeout_s:.0f} s{' (derived)' if not run_timeout else ''}; reference runs kept in {where}"
            + (f"; template {template}" if template else "")
        )

    # --- inputs -------------------------------------------------------------------------------------
    def _drain(self) -> None:
        wall = time.monotonic()
        raws = self.imu_drain.take()
        if raws:
            d = cdr.imu(raws)
            if d is None:
                msgs = [deserialize_message(r, Imu) for r in raws]
                t = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs], np.int64)
                az = np.array([m.linear_acceleration.z for m in msgs])
                q = np.array([m.angular_velocity.y for m in msgs])
            else:
                t, az, q = d[0], d[1][:, 2].copy(), d[2][:, 1].copy()
            self.imu.add(t, az, q, wall=wall)
            self.last_imu_ros_ns = self.get_clock().now().nanoseconds
        raws = self.odom_drain.take()
        if raws:
            o = cdr.odometry(raws)
            if o is None:
                msgs = [deserialize_message(r, Odometry) for r in raws]
                o = (
                    np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs], np.int64),
                    np.array([[p.x, p.y, p.z] for p in (m.pose.pose.position for m in msgs)]).reshape(-1, 3),
                    np.array([m.twist.twist.linear.x for m in msgs]),
                )
            t, pos, v = o
            self.odom.add(t, pos[:, 0].copy(), v, pos[:, 1].copy(), pos[:, 2].copy(), wall=wall)

    def _on_trial(self, msg: Trial) -> None:
        key = (str(msg.campaign_id), int(msg.trial_id), int(msg.attempt))
        current = None if self.run is None else (self.run.campaign_id, self.run.trial_id, self.run.attempt)
        if msg.state == Trial.STATE_READY_TO_DRIVE:
            if key == current or key in self.emitted:
                return
            if self.run is not None:
                self._finish_invalid(f"superseded: trial {key[1]} attempt {key[2]} became ready before this run ended")
            self.run = RunId(*key)
            self.run_start_ns = msg.stamp.sec * 1_000_000_000 + msg.stamp.nanosec
            self.run_wall_start = time.monotonic()
            self.last_imu_ros_ns = max(self.last_imu_ros_ns, self.get_clock().now().nanoseconds)
            self.get_logger().info(
                f"run {self.run} started: buffering ({self.config.mode} mode"
                + (", a retry: waiting for a new drive" if self.run.attempt > 1 else "")
                + ")"
            )
            self._diagnostics()
        elif key == current:
            self._finish_invalid(f"cancelled: the trial entered state {msg.state} before the run was complete")

    # --- the run ------------------------------------------------------------------------------------
    def _series(self) -> tuple[ImuSeries, OdomSeries]:
        return ImuSeries(*self.imu.arrays()), OdomSeries(*self.odom.arrays())

    def _check(self) -> None:
        self._drain()
        now_ns = self.get_clock().now().nanoseconds
        if self.run is None:
            self._forget_old()
            return
        imu, odom = self._series()
        retry = self.run.attempt > 1
        try:
            ref = self.references.get(self.run.campaign_id)
            status = run_status(imu, odom, self.config, self.run_start_ns, ref, retry)
            self.waiting_for = status.waiting_for
            if status.complete:
                self._emit(cut_run(imu, odom, self.config, self.run_start_ns, ref, self.run, retry))
                return
        except BacError as exc:  # an unusable reference: every run would fail the same way
            self.get_logger().error(f"run {self.run}: {exc}")
            self._finish_invalid(f"cannot align: {exc}")
            return
        except Exception as exc:  # a bug must cost one run, not the campaign
            self.get_logger().error(f"run {self.run}: segmentation failed:\n{traceback.format_exc()}")
            self._finish_invalid(f"internal error in the segmentation ({type(exc).__name__}: {exc}); see the log")
            return
        elapsed = (now_ns - self.run_start_ns) / 1e9
        if elapsed > self.run_timeout_s:
            self._finish_invalid(f"run timeout after {elapsed:.1f} s: still waiting for {status.waiting_for}")
        elif (now_ns - max(self.last_imu_ros_ns, self.run_start_ns)) / 1e9 > self.no_data_timeout_s:
            self._finish_invalid(f"no IMU data (imu/vehicle) for {self.no_data_timeout_s:g} s during the run")

    def _forget_old(self) -> None:
        """While idle, keep what arrived in the last pre_buffer_s (wall) and the last odometry sample before it."""
        cutoff = time.monotonic() - self.pre_buffer_s
        self.imu.drop_arrived_before(cutoff)
        self.odom.drop_arrived_before(cutoff, keep_last=1)

    def _finish_invalid(self, reason: str) -> None:
        assert self.run is not None
        self._emit(invalid_segment(self.config, self.run, self.run_start_ns, reason))

    def _emit(self, seg: Segment) -> None:
        run = seg.run
        self.pub.publish(segment_to_msg(seg))
        self.emitted.add((run.campaign_id, run.trial_id, run.attempt))
        if seg.valid:
            self.get_logger().info(
                f"run {run}: segment valid, lag {seg.lag_s * 1e3:.1f} ms, alignment {seg.alignment_score:.3f}, "
                f"mean speed {seg.mean_speed_mps * 3.6:.1f} km/h"
            )
            try:
                ref = self.references.offer(seg, self.config)
            except (OSError, SegmentationError) as exc:
                self.get_logger().error(f"could not keep run {run} as the reference: {exc}")
                ref = None
            if ref is not None:
                where = self.references.file_for(run.campaign_id) or "memory"
                self.get_logger().info(f"run {run} is the reference of campaign '{run.campaign_id}' ({where})")
        else:
            self.get_logger().warning(f"run {run}: segment invalid: {seg.reason}")
        self.last_result = f"run {run}: " + ("valid" if seg.valid else f"invalid: {seg.reason}")
        self.run = None
        self.waiting_for = ""
        self._forget_old()
        self._diagnostics()

    def _diagnostics(self) -> None:
        """The segmenter's state: idle or buffering which run, what it waits for, what it holds."""
        t_imu = self.imu.arrays()[0]
        t_odom = self.odom.arrays()[0]
        st = DiagnosticStatus()
        st.name = f"{self.get_name()}: runs"
        st.hardware_id = ""
        if self.run is None:
            st.level = DiagnosticStatus.OK
            st.message = "idle: waiting for a trial ready to drive"
        else:
            waited = time.monotonic() - self.run_wall_start
            st.level = DiagnosticStatus.OK if t_imu.size else DiagnosticStatus.WARN
            st.message = f"buffering run {self.run} for {waited:.0f} s" + (
                f": waiting for {self.waiting_for}" if self.waiting_for else ""
            )
        values = {
            "state": "idle" if self.run is None else "buffering",
            "run": "" if self.run is None else str(self.run),
            "waiting_for": self.waiting_for,
            "imu_samples": str(t_imu.size),
            "imu_last_stamp_ns": str(int(t_imu[-1])) if t_imu.size else "",
            "odom_samples": str(t_odom.size),
            "odom_last_stamp_ns": str(int(t_odom[-1])) if t_odom.size else "",
            "runs_emitted": str(len(self.emitted)),
            "last_result": self.last_result,
            "mode": self.config.mode,
        }
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.pub_diag.publish(arr)

    def destroy_node(self) -> None:
        self.imu_drain.destroy()
        self.odom_drain.destroy()
        super().destroy_node()


def derived_run_timeout(config: SegmentConfig, approach_time_s: float) -> float:
    """The run timeout when none is set: the approach, then the segment driven at the slowest accepted speed."""
    slowest = config.target_speed_mps * (1.0 - config.speed_tolerance)
    if config.mode == "distance":
        drive = (config.distance_end_m + config.max_shift_m) / slowest
    else:
        drive = config.trigger_after_m / slowest + config.window_s + config.max_lag_s
    return approach_time_s + 1.25 * drive + 5.0


def main(args: list[str] | None = None) -> int:
    return run_node(RunSegmenterNode, args)


if __name__ == "__main__":
    sys.exit(main())
