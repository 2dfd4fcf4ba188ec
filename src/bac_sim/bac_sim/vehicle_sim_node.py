"""The ``vehicle_sim`` node: the simulated car, its sensors on the graph's topics and its ECU on CAN.

* Owns a :class:`bac_sim.ecu.SimulatedEcu` on its CAN bus (``can.*`` parameters, read-only): the
  ECU bridge writes calibrations to it exactly as to the car's ECU.
* Subscribes ``bac/trial`` (latched). When a trial is ``STATE_READY_TO_DRIVE`` for a run
  ``(campaign_id, trial_id, attempt)`` not driven yet, it drives one run: it snapshots the ECU's
  active calibration (a calibration accepted later applies from the next run on), tells the ECU the
  car is moving (commits are refused as busy), simulates the run and publishes it paced in sim time:
  ``imu/data_raw`` (sensor_msgs/Imu, frame ``imu_link``, sensor-data QoS), ``vehicle/odom``
  (nav_msgs/Odometry as a standard odometry source publishes it, REP 105: the pose of the car in
  the ``odom`` frame, continuous from run to run, the road along +x from where the first run
  started; the forward speed in ``base_link``, :mod:`bac_sim.odometry`) and ``/clock``. Between
  two runs the car comes back to the start (not simulated: nothing is published) in the time that
  takes at ``way_back_speed_kmh``; the next run starts where the car then is. A run announced
  while another is being driven waits until that drive is over, then it is driven, if the trial
  still waits for it. Before a run's first message (the driver's start delay, the way back) sim
  time runs at ``approach_realtime_factor``: nothing is published then.
* Runs are computed in a worker process (``sim_process``), away from the publishing thread and the
  executor.
* Publishes ``/clock``, which follows the simulation as a simulator's clock does: between runs it
  advances at ``idle_realtime_factor`` (the agent's waits pass in sim time); **no sim time passes
  while a run is waited for or computed** (nothing is published then), nor while the agent proposes
  or applies a calibration (up to ``applying_pause_s``: a READY_TO_DRIVE delivered late finds the
  clock where the agent left it), so every sim-time deadline of
  the graph means what it means on the car however slow the machine; a run is published at most
  ``realtime_factor`` times faster than real time (1 = real time), in small slices so that a
  best-effort subscriber with a deep history loses nothing. The rate each run was published at is
  logged, with a warning and the reason when it falls short of ``realtime_factor`` by more than 20 %.
"""

from __future__ import annotations

import ctypes
import math
import multiprocessing
import queue
import signal
import sys
import threading
import time
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu

from bac_common.contracts import TOPIC_CLOCK, TOPIC_IMU_RAW, TOPIC_ODOM, TOPIC_TRIAL
from bac_common.paramspace import CalibrationDefinition
from bac_common.rosnode import QOS_LATCHED, QOS_STREAM, BacNode, run_node
from bac_msgs.msg import Trial
from bac_sim.driver import DriverModel
from bac_sim.odometry import OdomTrack
from bac_sim.run import ImuSpec, RunRecording, simulate_scenario_run
from bac_sim.scenarios import get_scenario

# the IMU stream: best effort like every IMU driver (sensor-data QoS), a deep writer history so that
# bursts faster than real time are not dropped on the publishing side
QOS_IMU_OUT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT)
QOS_CLOCK = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
PR_SET_PDEATHSIG = 1  # prctl option: a signal when the parent dies
RATE_WARN_FRACTION = 0.8  # a run published slower than this fraction of realtime_factor is reported with why


@dataclass
class _Job:
    key: tuple[str, int, int]
    calibration: dict[str, float]
    seed: int


@dataclass
class _Playback:
    job: _Job
    rec: RunRecording
    t0: float  # sim time of the run's first sample
    wall0: float
    x: np.ndarray  # pose.position.x of each odometry sample (odom frame), m
    i_imu: int = 0
    i_odom: int = 0
    wall_first: float = math.nan  # wall time of the first message and of the last
    wall_last: float = math.nan
    publish_s: float = 0.0  # wall seconds spent publishing
    loops: int = 0

    def __post_init__(self) -> None:
        self.t_imu = self.t0 + self.rec.t
        self.t_odom = self.t0 + self.rec.odom_t
        self.t_first = min(
            self.t_imu[0] if self.t_imu.size else math.inf, self.t_odom[0] if self.t_odom.size else math.inf
        )
        # the last message of the run, IMU or odometry: the next drive starts after it
        self.t_end = max(
            self.t_imu[-1] if self.t_imu.size else self.t0, self.t_odom[-1] if self.t_odom.size else self.t0
        )


def start_delay(delays: list[float], attempt: int) -> float:
    """The driver's delay before attempt ``attempt`` (1-based) starts moving: the list's entry, the last repeats."""
    if not delays:
        return 0.0
    return float(delays[min(max(attempt, 1), len(delays)) - 1])


def _stamp(msg_stamp: Any, t: float) -> None:
    sec = math.floor(t)
    msg_stamp.sec = int(sec)
    msg_stamp.nanosec = min(round((t - sec) * 1e9), 999_999_999)


class VehicleSimNode(BacNode):
    """The simulated vehicle (see the module doc)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("vehicle_sim", **kwargs)
        self.scenario_name = self.declare_str(
            "scenario",
            "road",
            "bump (speed bump, 30 km/h), road (1.5 km test road, 60 km/h) or a road file path",
            read_only=True,
        )
        definition_file = self.declare_str(
            "definition_file",
            "controller_i",
            "calibration definition of the ECU's controller (YAML path, or the name of a shipped definition)",
            read_only=True,
        )
        speed_kmh = self.declare_float(
            "speed_kmh", 0.0, "target speed, km/h; 0 = the scenario's", 0.0, 250.0, read_only=True
        )
        self.imu_rate = self.declare_float("imu_rate_hz", 400.0, "IMU output rate, Hz", 50.0, 2000.0, read_only=True)
        self.odom_rate = self.declare_float("odom_rate_hz", 100.0, "odometry rate, Hz", 50.0, 1000.0, read_only=True)
        self.seed = self.declare_int("seed", 0, "seed of the run-to-run noise (run i uses seed + i)", 0, 2**31 - 1)
        self.rtf = self.declare_float(
            "realtime_factor",
            2.0,
            "runs are published at most this much faster than real time (1 = real time)",
            0.05,
            200.0,
        )
        self.idle_rtf = self.declare_float(
            "idle_realtime_factor", 1.0, "speed of /clock between runs relative to the wall clock", 0.0, 200.0
        )
        self.clock_period = self.declare_float(
            "clock_period_s", 0.005, "wall period of the publishing loop, s", 0.001, 0.1
        )
        self.applying_pause_s = self.declare_float(
            "applying_pause_s",
            30.0,
            "while the agent proposes or applies a calibration (bac/trial PROPOSED / APPLYING), sim time stands still "
            "for up to this long (wall, s), so that the READY_TO_DRIVE that follows, however late it arrives, finds "
            "the clock where the agent left it; 0: the clock runs on at idle_realtime_factor",
            0.0,
            3600.0,
        )
        self.start_time = self.declare_float("start_time_s", 1.0, "sim time at start, s", 0.0, 1e9, read_only=True)
        self.run_in = self.declare_float("run_in_s", 6.0, "driving before the scored window, s", 1.0, 120.0)
        self.run_out = self.declare_float("run_out_s", 4.0, "driving after the scored window, s", 0.5, 120.0)
        self.frame_id = self.declare_str("frame_id", "imu_link", "frame of imu/data_raw", read_only=True)
        self.subscriber_wait_s = self.declare_float(
            "subscriber_wait_s",
            20.0,
            "before a run, wait this long (wall) for subscribers of the sensor topics, s",
            0.0,
            600.0,
        )
        self.expected_subscribers = self.declare_int(
            "expected_subscribers",
            1,
            "subscribers of imu/data_raw and of vehicle/odom to wait for before a run (the sim profile: the "
            "measurement chain and the recorder)",
            0,
            100,
        )
        self._listener_wait_since: float | None = None
        imu_reliability = self.declare_str(
            "imu_reliability",
            "best_effort",
            "QoS reliability of imu/data_raw: best_effort like an IMU driver (sensor-data QoS), or reliable "
            "(then a reliable imu_ingest never loses a sample however fast the simulation runs)",
            choices=("best_effort", "reliable"),
            read_only=True,
        )
        self.odom_frame = self.declare_str(
            "odom_frame_id", "odom", "frame of vehicle/odom's pose (REP 105: odom)", read_only=True
        )
        self.base_frame = self.declare_str(
            "base_frame_id", "base_link", "child frame of vehicle/odom: its twist (REP 105: base_link)", read_only=True
        )
        self.track = OdomTrack(
            self.declare_float(
                "way_back_speed_kmh",
                60.0,
                "between runs the car comes back to the start at this speed (not simulated: it sets when the next "
                "run can start, and so the sim time that passes), km/h",
                1.0,
                300.0,
                read_only=True,
            )
            / 3.6
        )
        self.approach_rtf = self.declare_float(
            "approach_realtime_factor",
            50.0,
            "before a run's first message (driver's start delay, the way back: nothing is published) sim time runs at "
            "up to this many times real time (at least realtime_factor)",
            0.05,
            1000.0,
        )
        self.sim_process = self.declare_bool(
            "sim_process",
            True,
            "compute each run in a worker process (true), away from the publishing thread and the executor, or "
            "in a thread of this process (false)",
            read_only=True,
        )
        self.compute_delay_s = self.declare_float(
            "compute_delay_s",
            0.0,
            "extra wall seconds added to the computation of every run: emulates a slower machine (tests); sim time "
            "does not pass meanwhile",
            0.0,
            3600.0,
        )
        self.start_delays = self.declare_float_list(
            "driver.start_delay_s",
            [0.0],
            "sim seconds the driver takes to reach the start of a run after READY_TO_DRIVE, per attempt of a trial "
            "(attempt 1, 2, ...; the last value repeats): a driver coming back round",
        )
        if not all(math.isfinite(v) and v >= 0 for v in self.start_delays):
            raise ValueError("node 'vehicle_sim': driver.start_delay_s must hold numbers >= 0")
        self.driver = DriverModel(
            speed_error_std=self.declare_float(
                "driver.speed_error_kmh", 0.3, "cruise set-point error, km/h (1 sigma)", 0.0, 20.0
            )
            / 3.6,
            speed_fluctuation_std=self.declare_float(
                "driver.speed_fluctuation_kmh", 0.15, "slow speed fluctuation, km/h (1 sigma)", 0.0, 20.0
            )
            / 3.6,
            start_offset_std=self.declare_float(
                "driver.start_offset_m", 5.0, "scatter of the start point, m", 0.0, 500.0
            ),
            bad_run_probability=self.declare_float(
                "driver.bad_run_probability",
                0.0,
                "chance that a run is driven too slow (the agent must repeat it)",
                0.0,
                1.0,
            ),
            bad_speed_factor=self.declare_float(
                "driver.bad_speed_factor", 0.85, "speed of a bad run / target", 0.1, 2.0
            ),
        )
        lever = self.declare_float_list(
            "imu.lever_arm_m", [-0.25, -0.38, -0.30], "IMU position from the centre of gravity, m", read_only=True
        )
        mount = self.declare_float_list(
            "imu.mount_rpy_deg", [0.8, -1.2, 0.5], "IMU mounting rotation (roll, pitch, yaw), deg", read_only=True
        )
        a_bias = self.declare_float_list(
            "imu.accel_bias", [0.03, -0.02, 0.05], "accelerometer bias, m/s^2", read_only=True
        )
        g_bias = self.declare_float_list("imu.gyro_bias", [0.002, -0.001, 0.0015], "gyro bias, rad/s", read_only=True)
        for name, vec in (
            ("imu.lever_arm_m", lever),
            ("imu.mount_rpy_deg", mount),
            ("imu.accel_bias", a_bias),
            ("imu.gyro_bias", g_bias),
        ):
            if len(vec) != 3 or not all(math.isfinite(v) for v in vec):
                raise ValueError(f"node 'vehicle_sim': parameter {name} must hold three finite numbers")
        self.imu = ImuSpec(
            rate_hz=self.imu_rate,
            lever_arm=(lever[0], lever[1], lever[2]),
            mount_rpy_deg=(mount[0], mount[1], mount[2]),
            accel_bias=(a_bias[0], a_bias[1], a_bias[2]),
            gyro_bias=(g_bias[0], g_bias[1], g_bias[2]),
            accel_noise_density=self.declare_float(
                "imu.accel_noise_density", 60e-6 * 9.80665, "m/s^2/sqrt(Hz)", 0.0, 1.0, read_only=True
            ),
            gyro_noise_density=self.declare_float(
                "imu.gyro_noise_density", math.radians(0.007), "rad/s/sqrt(Hz)", 0.0, 1.0, read_only=True
            ),
            accel_lsb=self.declare_float(
                "imu.accel_lsb", 16 * 9.80665 / 65536, "accelerometer resolution, m/s^2", 0.0, 1.0, read_only=True
            ),
            gyro_lsb=self.declare_float(
                "imu.gyro_lsb", math.radians(1000.0) / 65536, "gyro resolution, rad/s", 0.0, 1.0, read_only=True
            ),
        )
        from bac_common.paths import resolve_definition
        from bac_ecu_bridge.canbus import BusSettings, open_bus
        from bac_sim.ecu import SimulatedEcu

        self.definition = CalibrationDefinition.load(resolve_definition(definition_file))
        self.speed_kmh = speed_kmh or None
        self.scenario = get_scenario(self.scenario_name, self.speed_kmh)
        settings = BusSettings(
            interface=self.declare_str(
                "can.interface", "virtual", "python-can interface (virtual in one process)", read_only=True
            ),
            channel=self.declare_str("can.channel", "bac", "python-can channel", read_only=True),
            bitrate=self.declare_int("can.bitrate", 500_000, "bit rate, bit/s", 10_000, 1_000_000, read_only=True),
            port=self.declare_int("can.port", 0, "udp_multicast UDP port (0 = default)", 0, 65535, read_only=True),
        )
        self.bus = open_bus(settings)
        self.ecu = SimulatedEcu(self.bus, self.definition)
        self.ecu.start()

        self.add_post_set_parameters_callback(self._parameters_changed)
        qos_imu = QOS_IMU_OUT
        if imu_reliability == "reliable":
            # transient local too: a reader matched after a run was published (discovery) still gets it
            qos_imu = QoSProfile(
                history=HistoryPolicy.KEEP_LAST,
                depth=5000,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL,
            )
        self.pub_imu = self.create_publisher(Imu, TOPIC_IMU_RAW, qos_imu)
        self.pub_odom = self.create_publisher(Odometry, TOPIC_ODOM, QOS_STREAM)
        self.pub_clock = self.create_publisher(Clock, TOPIC_CLOCK, QOS_CLOCK)
        self.create_subscription(Trial, TOPIC_TRIAL, self._on_trial, QOS_LATCHED)
        self._driven: set[tuple[str, int, int]] = set()
        self._latest: tuple[tuple[str, int, int], int] | None = None  # last trial seen and its state
        self._state_since = time.monotonic()  # wall time the latest trial state was first seen
        self._jobs: queue.Queue[_Job] = queue.Queue()
        self._runs = 0
        self.runs_published = 0
        self._sim: Executor
        if self.sim_process:
            # spawn, not fork: a forked copy of a process with DDS threads is not safe
            self._sim = ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init
            )
        else:
            self._sim = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vehicle_sim_run")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="vehicle_sim_clock", daemon=True)
        self._thread.start()
        self.get_logger().info(
            f"vehicle_sim ready: scenario {self.scenario.name} at {self.scenario.speed * 3.6:.0f} km/h, controller "
            f"{self.definition.name}, IMU {self.imu_rate:g} Hz, ECU on {settings.describe()}, "
            f"runs at <= {self.rtf:g}x real time"
        )

    def _parameters_changed(self, params: list[Any]) -> None:
        """Pacing, seed, run margins and the driver can change between runs (the next run uses them)."""
        values = {p.name: p.value for p in params}
        self.rtf = float(values.get("realtime_factor", self.rtf))
        self.idle_rtf = float(values.get("idle_realtime_factor", self.idle_rtf))
        self.clock_period = float(values.get("clock_period_s", self.clock_period))
        self.applying_pause_s = float(values.get("applying_pause_s", self.applying_pause_s))
        self.approach_rtf = float(values.get("approach_realtime_factor", self.approach_rtf))
        self.seed = int(values.get("seed", self.seed))
        self.compute_delay_s = float(values.get("compute_delay_s", self.compute_delay_s))
        if "driver.start_delay_s" in values:
            self.start_delays = [float(v) for v in values["driver.start_delay_s"]]
        self.run_in = float(values.get("run_in_s", self.run_in))
        self.run_out = float(values.get("run_out_s", self.run_out))
        d = self.driver
        self.driver = DriverModel(
            speed_error_std=float(values.get("driver.speed_error_kmh", d.speed_error_std * 3.6)) / 3.6,
            speed_fluctuation_std=float(values.get("driver.speed_fluctuation_kmh", d.speed_fluctuation_std * 3.6))
            / 3.6,
            start_offset_std=float(values.get("driver.start_offset_m", d.start_offset_std)),
            bad_run_probability=float(values.get("driver.bad_run_probability", d.bad_run_probability)),
            bad_speed_factor=float(values.get("driver.bad_speed_factor", d.bad_speed_factor)),
        )

    # --- trials ---------------------------------------------------------------------------------
    def _on_trial(self, msg: Trial) -> None:
        key = (str(msg.campaign_id), int(msg.trial_id), int(msg.attempt))
        if self._latest is None or self._latest[1] != int(msg.state):
            self._state_since = time.monotonic()
        self._latest = (key, int(msg.state))
        if msg.state != Trial.STATE_READY_TO_DRIVE:
            return
        if key in self._driven:
            return
        self._driven.add(key)
        self._jobs.put(_Job(key, {}, self.seed + len(self._driven) - 1))
        self.get_logger().info(f"trial {key[1]} attempt {key[2]} of '{key[0]}' is ready to drive")

    def _submit(self, job: _Job) -> Future[RunRecording]:
        return self._sim.submit(
            _simulate_job,
            job.calibration,
            self.scenario_name,
            self.speed_kmh,
            self.compute_delay_s,
            seed=job.seed,
            definition=self.definition,
            imu=self.imu,
            driver=self.driver,
            run_in_s=self.run_in,
            run_out_s=self.run_out,
            odom_rate_hz=self.odom_rate,
        )

    def _listeners_ready(self, now: float) -> bool:
        """True when imu/data_raw and vehicle/odom have subscribers (or after subscriber_wait_s).

        Between processes, discovery takes a few seconds: a run published before the chain's readers are
        matched would be lost on a volatile topic (the run then times out and is driven again).
        """
        need = self.expected_subscribers
        if self.pub_imu.get_subscription_count() >= need and self.pub_odom.get_subscription_count() >= need:
            self._listener_wait_since = None
            return True
        if self._listener_wait_since is None:
            self._listener_wait_since = now
            self.get_logger().info(
                f"waiting for {need} subscriber(s) each of imu/data_raw and vehicle/odom before driving"
            )
        if now - self._listener_wait_since < self.subscriber_wait_s:
            return False
        self.get_logger().warning(
            f"fewer than {need} subscribers of imu/data_raw / vehicle/odom after {self.subscriber_wait_s:g} s "
            "(is the measurement chain running?): driving anyway"
        )
        self._listener_wait_since = None
        return True

    # --- the clock and the playback ----------------------------------------------------------------
    def _loop(self) -> None:
        sim_t = self.start_time
        last_wall = time.monotonic()
        pending: tuple[_Job, Future[RunRecording], float] | None = None
        play: _Playback | None = None
        clock = Clock()
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                if play is None and pending is None and not self._jobs.empty() and self._listeners_ready(now):
                    job = self._jobs.get_nowait()
                    if self._latest is not None and self._latest != (job.key, Trial.STATE_READY_TO_DRIVE):
                        # the agent moved on while another run was being driven: nobody waits for this one
                        self.get_logger().warning(
                            f"trial {job.key[1]} attempt {job.key[2]} is no longer ready to drive: not driven"
                        )
                        continue
                    job.calibration = self.ecu.active  # what is in force when the run starts
                    self.ecu.set_driving(True)
                    pending = (job, self._submit(job), now)
                if pending is not None and pending[1].done():
                    job, fut, wall_submitted = pending
                    pending = None
                    try:
                        rec = fut.result()
                    except Exception as exc:  # a run that cannot be simulated: log it, stop driving
                        self.ecu.set_driving(False)
                        self.get_logger().error(f"run {job.key} could not be simulated: {exc}")
                    else:
                        delay = start_delay(self.start_delays, job.key[2])
                        # the first message one odometry period after now at the earliest (a drive that follows
                        # another at once never shares a stamp with it), and once the car is back at the start
                        placed = self.track.place(rec, sim_t + delay + 1.0 / self.odom_rate)
                        play = _Playback(job, rec, placed.t0, now, placed.x)
                        cal = ", ".join(f"{k}={v:g}" for k, v in job.calibration.items())
                        self.get_logger().info(
                            f"driving trial {job.key[1]} attempt {job.key[2]}: {rec.duration:.1f} s, "
                            f"{rec.t.size} IMU samples, mean speed {3.6 * float(np.mean(rec.speed)):.1f} km/h"
                            f"{' (a bad run: too slow)' if rec.bad_run else ''}, true J {rec.j_true:.4f}; "
                            f"calibration {cal}; computed in {now - wall_submitted:.1f} s (sim time stood still)"
                            + (f"; the driver starts in {delay:g} s" if delay > 0 else "")
                            + (
                                f"; the car comes back {placed.way_back_m:.0f} m ({placed.way_back_s:.1f} s)"
                                if placed.way_back_m > 0
                                else ""
                            )
                        )
                if play is not None:
                    # advance by the wall time elapsed, but never by more than two loop periods: after a
                    # stall (a loaded machine) the run goes on at the same pace instead of in a burst
                    approaching = play.i_imu == 0 and play.i_odom == 0  # nothing published yet: the clock may hurry
                    rate = max(self.rtf, self.approach_rtf) if approaching else self.rtf
                    step = min(now - last_wall, 2 * self.clock_period) * rate
                    target = sim_t + step
                    if approaching and sim_t < play.t_first:
                        target = min(target, play.t_first)  # the run itself at realtime_factor
                    t_pub = time.monotonic()
                    done = self._publish_until(play, target)
                    play.publish_s += time.monotonic() - t_pub
                    play.loops += 1
                    sim_t = min(target, play.t_end)
                    if done:
                        if play.x.size:
                            self.track.driven(float(play.t_odom[-1]), float(play.x[-1]))
                        self.ecu.set_driving(False)
                        self.runs_published += 1
                        self._report_rate(play)
                        play = None
                elif pending is None and self._jobs.empty() and not self._agent_applying(now):
                    sim_t += (now - last_wall) * self.idle_rtf
                # else: a run is waited for or being computed, or the agent is applying a calibration: sim time
                # stands still (nothing is published)
                _stamp(clock.clock, sim_t)
                self.pub_clock.publish(clock)
            except Exception as exc:  # never let the clock thread die silently
                if self._stop.is_set():
                    break
                self.get_logger().error(f"vehicle_sim loop: {exc}")
            last_wall = now
            self._stop.wait(self.clock_period)

    def _agent_applying(self, now: float) -> bool:
        """The agent proposes or applies a calibration (a READY_TO_DRIVE is expected), for at most applying_pause_s."""
        latest = self._latest
        if latest is None or latest[1] not in (Trial.STATE_PROPOSED, Trial.STATE_APPLYING):
            return False
        return now - self._state_since < self.applying_pause_s

    def _report_rate(self, play: _Playback) -> None:
        """Log the rate the run was published at; warn, with the reason, when it fell short of realtime_factor."""
        key = play.job.key
        head = f"run of trial {key[1]} attempt {key[2]} published ({play.i_imu} IMU, {play.i_odom} odometry messages)"
        wall = play.wall_last - play.wall_first
        span = float(play.rec.t[-1] - play.rec.t[0]) if play.rec.t.size > 1 else 0.0
        if not (wall > 0 and span > 0):
            self.get_logger().info(head)
            return
        rate = span / wall
        text = f"{head}: {span:.1f} s of driving in {wall:.1f} s of wall time, {rate:.1f}x real time"
        if rate >= RATE_WARN_FRACTION * self.rtf:
            self.get_logger().info(f"{text} (requested {self.rtf:g}x)")
            return
        busy = play.publish_s / wall
        if busy > 0.8:
            why = (
                f"publishing took {100 * busy:.0f} % of the wall time: this process cannot publish "
                f"{(play.i_imu + play.i_odom) / span * self.rtf:.0f} messages/s; lower realtime_factor or imu_rate_hz"
            )
        else:
            why = (
                f"publishing took only {100 * busy:.0f} % of the wall time: the publishing thread was kept waiting "
                "(the CPU is shared with the other nodes: a loaded machine)"
            )
        self.get_logger().warning(f"{text}, below the requested {self.rtf:g}x: {why}")

    def _publish_until(self, play: _Playback, target: float) -> bool:
        rec = play.rec
        t_imu, t_odom = play.t_imu, play.t_odom
        while True:
            ni = t_imu[play.i_imu] if play.i_imu < t_imu.size else math.inf
            no = t_odom[play.i_odom] if play.i_odom < t_odom.size else math.inf
            nxt = min(ni, no)
            if nxt == math.inf:
                return True
            if nxt > target:
                return False
            play.wall_last = time.monotonic()
            if play.i_imu == 0 and play.i_odom == 0:
                play.wall_first = play.wall_last
            if ni <= no:
                i = play.i_imu
                m = Imu()
                _stamp(m.header.stamp, ni)
                m.header.frame_id = self.frame_id
                m.orientation_covariance[0] = -1.0  # no orientation estimate
                a, w = rec.accel[i], rec.gyro[i]
                m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = (
                    float(a[0]),
                    float(a[1]),
                    float(a[2]),
                )
                m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = float(w[0]), float(w[1]), float(w[2])
                self.pub_imu.publish(m)
                play.i_imu += 1
            else:
                i = play.i_odom
                o = Odometry()
                _stamp(o.header.stamp, no)
                o.header.frame_id = self.odom_frame
                o.child_frame_id = self.base_frame
                o.pose.pose.position.x = float(play.x[i])  # the road along +x: y = z = 0, heading 0
                o.pose.pose.orientation.w = 1.0
                o.twist.twist.linear.x = float(rec.speed[i])  # forward, in base_link
                self.pub_odom.publish(o)
                play.i_odom += 1

    def destroy_node(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        # a run being computed is not waited for: the worker process is ended (its result is of no use)
        workers = list((getattr(self._sim, "_processes", None) or {}).values())
        self._sim.shutdown(wait=False, cancel_futures=True)
        for w in workers:
            if w.is_alive():
                w.terminate()
        try:
            self.ecu.stop()
        finally:
            self.bus.shutdown()
        super().destroy_node()


def _worker_init() -> None:
    """The worker leaves Ctrl-C to its node (which ends it) and dies with it if the node is killed."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:  # not Linux: the worker ends when its pipe to the node closes
        pass


def _simulate_job(
    calibration: dict[str, float], scenario: str, speed_kmh: float | None, compute_delay_s: float, **kwargs: Any
) -> RunRecording:
    """One run, in the worker (a module-level function: what a process pool can call)."""
    rec = simulate_scenario_run(calibration, scenario, speed_kmh, **kwargs)
    if compute_delay_s > 0:
        time.sleep(compute_delay_s)  # an emulated slow machine (compute_delay_s), not a wait for a condition
    return rec


def main(args: list[str] | None = None) -> int:
    return run_node(VehicleSimNode, args)


if __name__ == "__main__":
    sys.exit(main())
