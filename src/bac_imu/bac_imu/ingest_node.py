"""``imu_ingest``: the IMU driver's stream in, the vehicle-frame stream and its health out.

Subscribes ``imu/data_raw`` (sensor_msgs/Imu, best effort with a deep history:
``qos_depth``; ``input_reliability: reliable`` for a simulator that publishes
reliably, so that nothing is lost even on a saturated CPU), takes what arrived
every ``process_period_s`` of wall time as one batch (raw bytes drained from the DDS reader and decoded vectorized,
:mod:`bac_common.topic_drain`: thousands of messages per second, far beyond what
one executor callback per message allows), feeds it to
:class:`bac_imu.ingest.ImuIngestor`, and publishes

* ``imu/vehicle`` (sensor_msgs/Imu, QOS_STREAM): fixed rate ``output_rate_hz``,
  frame ``frame_id`` (base_link), ``linear_acceleration`` = vehicle-frame
  acceleration with gravity removed from z, ``angular_velocity`` (y = pitch
  rate); a sample without data (gap, NaN/inf, saturation) carries NaN;
  ``orientation_covariance[0] = -1`` (no orientation);
* ``/diagnostics`` (diagnostic_msgs/DiagnosticArray) every
  ``diagnostics_period_s`` and at once when a new fault appears: rate,
  jitter, gaps, NaN/inf, duplicated / out-of-order stamps, saturation, clock
  jumps, the mount, STALE when nothing arrives.

Every ingestion parameter is read-only: the stream's state depends on it.
"""

from __future__ import annotations

import sys
import time
import traceback
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu

from bac_common import cdr
from bac_common.contracts import TOPIC_DIAGNOSTICS, TOPIC_IMU_RAW, TOPIC_IMU_VEHICLE
from bac_common.node_params import ParamSpec, declare_config
from bac_common.rosnode import QOS_STREAM, BacNode, run_node
from bac_common.topic_drain import TopicDrain
from bac_imu.ingest import ImuIngestor, IngestConfig, IngestOutput, StreamHealth, diagnose

INGEST_PARAMS = {
    "output_rate_hz": ParamSpec("rate of imu/vehicle, Hz", 1.0, 10_000.0),
    "input_rate_hz": ParamSpec("nominal rate of imu/data_raw, Hz; 0 = measured from the first samples", 0.0, 100_000.0),
    "rate_probe_samples": ParamSpec("samples used to measure the input rate when input_rate_hz is 0", 5, 100_000),
    "mount_source": ParamSpec(
        "where the mounting rotation comes from: config (mount_*_deg) or standstill (roll and pitch from gravity)",
        choices=("config", "standstill"),
    ),
    "standstill_fallback": ParamSpec(
        "without a standstill (mount_source standstill): mean (roll and pitch from the mean accelerometer over "
        "standstill_timeout_s) or config (mount_*_deg)",
        choices=("mean", "config"),
    ),
    "mount_roll_deg": ParamSpec("IMU mount roll relative to the vehicle frame, deg", -180.0, 180.0),
    "mount_pitch_deg": ParamSpec("IMU mount pitch relative to the vehicle frame, deg", -180.0, 180.0),
    "mount_yaw_deg": ParamSpec("IMU mount yaw relative to the vehicle frame, deg (never estimated)", -180.0, 180.0),
    "bias_source": ParamSpec(
        "none: nominal gravity, no gyro bias; standstill: gravity and gyro bias measured at standstill",
        choices=("none", "standstill"),
    ),
    "standstill_s": ParamSpec("length of the standstill window, s", 0.05, 600.0),
    "standstill_timeout_s": ParamSpec("look for a standstill over this much data, then fall back, s", 0.05, 3600.0),
    "standstill_accel_std": ParamSpec("max std of each accelerometer axis at standstill, m/s^2", 1e-6, 10.0),
    "standstill_gyro_std": ParamSpec("max std of each gyro axis at standstill, rad/s", 1e-6, 10.0),
    "gravity": ParamSpec("nominal gravity removed from z without a standstill, m/s^2", 5.0, 15.0),
    "accel_range": ParamSpec("accelerometer full scale (saturation), m/s^2; 0 = no check", 0.0, 1e5),
    "gyro_range": ParamSpec("gyro full scale (saturation), rad/s; 0 = no check", 0.0, 1e4),
    "gap_threshold_s": ParamSpec("a stamp step above this is a gap, s; 0 = 2.5 input periods", 0.0, 60.0),
    "clock_jump_s": ParamSpec("a stamp jump beyond this is a clock jump or restart, s", 1e-3, 1e6),
    "antialias_ratio": ParamSpec("anti-alias cutoff as a fraction of the output Nyquist frequency", 0.05, 0.95),
    "antialias_order": ParamSpec("Butterworth order of the anti-alias filter", 1, 10),
    "highpass_hz": ParamSpec("optional high-pass on every axis against drift, Hz; 0 = off", 0.0, 1000.0),
    "health_window": ParamSpec("recent stamp steps used for rate and jitter", 10, 1_000_000),
    "max_mean_accel_z": ParamSpec(
        "|mean a_z| after gravity removal beyond this is an ERROR naming the cause (a wrong mount), m/s^2",
        1e-3,
        100.0,
    ),
}


class ImuIngestNode(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("imu_ingest", **kwargs)
        self.config: IngestConfig = declare_config(self, IngestConfig, INGEST_PARAMS)
        self.frame_id = self.declare_str("frame_id", "base_link", "frame of imu/vehicle", read_only=True)
        depth = self.declare_int(
            "qos_depth",
            20_000,
            "history depth of the imu/data_raw subscription (a simulator faster than real time loses nothing)",
            1,
            10_000_000,
            read_only=True,
        )
        reliability = self.declare_str(
            "input_reliability",
            "best_effort",
            "QoS reliability of the imu/data_raw subscription: best_effort (what IMU drivers publish; a reliable "
            "subscription would never connect to them) or reliable (a simulator publishing reliably: nothing is "
            "lost even when the CPU is saturated)",
            choices=("best_effort", "reliable"),
            read_only=True,
        )
        period = self.declare_float("process_period_s", 0.02, "batch period of the ingestion, wall s", 1e-3, 1.0)
        diag = self.declare_float("diagnostics_period_s", 1.0, "period of /diagnostics, wall s", 0.05, 60.0)
        self.stale_after_s = self.declare_float(
            "stale_after_s", 1.0, "no sample for this long (wall): the stream is STALE", 0.01, 600.0
        )
        self.expected_rate_hz = self.declare_float(
            "expected_rate_hz", 0.0, "rate the IMU should have, Hz; 0 = the nominal rate found at start", 0.0, 1e5
        )
        self.use_receive_time = self.declare_bool(
            "use_receive_time", True, "use the receive time to tell a clock jump from a gap", read_only=True
        )
        self.ingestor = ImuIngestor(self.config)
        self._hw_id = ""
        self._last_rx = 0.0  # steady time of the last sample
        self._last_faults = 0
        self._last_diag = 0.0
        self._prev_health: StreamHealth | None = None
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        qos_in = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=depth,
            reliability=ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        )
        self.pub = self.create_publisher(Imu, TOPIC_IMU_VEHICLE, QOS_STREAM)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        self.drain = TopicDrain(self, Imu, TOPIC_IMU_RAW, qos_in)
        self.create_timer(period, self._process, clock=steady)
        self.create_timer(diag, self._diagnostics, clock=steady)
        self.get_logger().info(
            f"ingesting {TOPIC_IMU_RAW} -> {TOPIC_IMU_VEHICLE} at {self.config.output_rate_hz:g} Hz, "
            f"mount from {self.config.mount_source}, bias from {self.config.bias_source}"
        )

    # --- in -------------------------------------------------------------------------------------
    def _process(self) -> None:
        raws = self.drain.take()
        if not raws:
            return
        self._last_rx = time.monotonic()
        if not self._hw_id:
            self._hw_id = cdr.frame_id(raws[0])
        decoded = cdr.imu(raws)
        if decoded is None:  # not little-endian CDR: one by one
            msgs = [deserialize_message(r, Imu) for r in raws]
            stamps = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs], np.int64)
            acc = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in msgs])
            gyr = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in msgs])
        else:
            stamps, acc, gyr = decoded
        # one receive time per batch (ROS time: sim time under use_sim_time); enough to tell a clock
        # jump (data kept flowing) from a gap (the batches before and after it are apart)
        recv = np.full(stamps.shape, self.get_clock().now().nanoseconds, np.int64) if self.use_receive_time else None
        try:
            out = self.ingestor.push(stamps, acc, gyr, recv)
        except Exception:  # a bug must not end the stream: start over, say so
            self.get_logger().error(f"ingestion failed, the stream starts over:\n{traceback.format_exc()}")
            self.ingestor = ImuIngestor(self.config)
            self._prev_health = None
            return
        self._publish(out)
        faults = self.ingestor.health().faults
        if faults != self._last_faults and time.monotonic() - self._last_diag > 0.1:
            self._diagnostics()  # a new fault: say it now

    # --- out ------------------------------------------------------------------------------------
    def _publish(self, out: IngestOutput) -> None:
        for i in range(len(out)):
            m = Imu()
            ns = int(out.stamp_ns[i])
            m.header.stamp.sec = ns // 1_000_000_000
            m.header.stamp.nanosec = ns % 1_000_000_000
            m.header.frame_id = self.frame_id
            m.orientation_covariance[0] = -1.0
            acc, gyr = out.accel[i], out.gyro[i]
            m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = (
                float(acc[0]),
                float(acc[1]),
                float(acc[2]),
            )
            m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = (
                float(gyr[0]),
                float(gyr[1]),
                float(gyr[2]),
            )
            self.pub.publish(m)

    def _diagnostics(self) -> None:
        now_h = self.ingestor.health()
        silent = time.monotonic() - self._last_rx if self._last_rx else 0.0
        d = diagnose(now_h, self._prev_health, self.expected_rate_hz, silent, self.stale_after_s)
        self._prev_health = now_h
        self._last_faults = now_h.faults
        self._last_diag = time.monotonic()
        st = DiagnosticStatus()
        st.level = bytes([d.level])
        st.name = f"{self.get_name()}: {TOPIC_IMU_RAW}"
        st.message = d.message
        st.hardware_id = self._hw_id
        st.values = [KeyValue(key=k, value=v) for k, v in d.values]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.pub_diag.publish(arr)
        if d.level == 2:
            self.get_logger().warning(f"IMU stream: {d.message}")

    def destroy_node(self) -> None:
        self.drain.destroy()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(ImuIngestNode, args)


if __name__ == "__main__":
    sys.exit(main())
