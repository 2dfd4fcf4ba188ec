"""One simulated test run, as the car's sensors would record it.

:func:`simulate_run` drives one run of a scenario with a raw calibration and returns a
:class:`RunRecording`:

* ``t``, ``accel``, ``gyro``: the IMU's raw output at ``imu.rate_hz`` in the **IMU frame**: specific
  force (m/s^2, gravity included: an IMU at rest reads +g on its z axis) and angular rate (rad/s),
  with the IMU's lever arm from the centre of gravity, its small mounting rotation, constant biases,
  white noise, saturation and quantization (:class:`ImuSpec`);
* ``odom_t``, ``distance``, ``speed``: odometry at ``odom_rate_hz``: distance travelled since the run
  started (m) and speed (m/s); ``start_m``: where on the road the run started (m);
* ``truth``: the ground truth at the IMU rate: seat-rail vertical acceleration with gravity removed
  in the vehicle frame (``accel_z``), ``pitch_rate``, ``roll_rate``, heave/pitch/roll, the position
  of the front axle on the road, the damping commands;
* ``j_true``: the paper's J of the ground-truth signals over the scenario's KPI window, and the
  window itself (``window_start_s``, ``window_end_s``, in run time).

A run has a run-in before and a run-out after the KPI window so that a segmenter has margins; the
driver (:class:`~bac_sim.driver.DriverModel`) sets its speed profile and start point from the seed.
Seeded runs are deterministic.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bac_common.paramspace import CalibrationDefinition
from bac_sim.controllers import (
    controller_i_definition,
    controller_ii_definition,
    make_controller,
    raw_matrix,
)
from bac_sim.driver import DriverModel
from bac_sim.engine import SEAT_DEFAULT, make_model, simulate
from bac_sim.errors import ControllerError, ScenarioError
from bac_sim.scenarios import Scenario, get_scenario
from bac_sim.vehicle import N_DOF, N_STATE, G

FloatArray = np.ndarray[Any, Any]
IMU_SUBSTEPS_MIN = 1  # simulation steps per IMU sample (at least)


def _rotation(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Body-to-world rotation for roll (x), pitch (y), yaw (z), applied yaw-pitch-roll (ZYX)."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return np.asarray(rz @ ry @ rx)


@dataclass(frozen=True)
class ImuSpec:
    """The IMU on the seat rail (defaults: an automotive-grade MEMS unit, e.g. 60 ug/sqrt(Hz))."""

    rate_hz: float = 400.0
    lever_arm: tuple[float, float, float] = SEAT_DEFAULT  # m from the sprung centre of gravity
    mount_rpy_deg: tuple[float, float, float] = (0.8, -1.2, 0.5)  # IMU frame relative to the vehicle
    accel_bias: tuple[float, float, float] = (0.03, -0.02, 0.05)  # m/s^2
    gyro_bias: tuple[float, float, float] = (0.002, -0.001, 0.0015)  # rad/s
    accel_noise_density: float = 60e-6 * G  # m/s^2/sqrt(Hz)
    gyro_noise_density: float = math.radians(0.007)  # rad/s/sqrt(Hz)
    accel_range: float = 8 * G  # m/s^2, saturation
    gyro_range: float = math.radians(500.0)  # rad/s
    accel_lsb: float = 16 * G / 65536  # m/s^2, 16 bit over +-8 g
    gyro_lsb: float = math.radians(1000.0) / 65536  # rad/s, 16 bit over +-500 deg/s

    def __post_init__(self) -> None:
        if not 50.0 <= self.rate_hz <= 2000.0:
            raise ScenarioError(f"IMU rate must be in [50, 2000] Hz, got {self.rate_hz}")
        for name in ("accel_noise_density", "gyro_noise_density", "accel_lsb", "gyro_lsb"):
            if not getattr(self, name) >= 0:
                raise ScenarioError(f"IMU {name} must be >= 0")

    @property
    def mount_rotation(self) -> FloatArray:
        """IMU-to-vehicle rotation."""
        r, p, y = (math.radians(a) for a in self.mount_rpy_deg)
        return _rotation(r, p, y)


@dataclass
class RunRecording:
    """One run as the sensors recorded it (see the module doc)."""

    scenario: str
    calibration: dict[str, float]
    seed: int
    t: FloatArray  # (n,) s since the run started, IMU samples
    accel: FloatArray  # (n, 3) raw specific force, IMU frame, m/s^2
    gyro: FloatArray  # (n, 3) raw angular rate, IMU frame, rad/s
    odom_t: FloatArray  # (m,) s
    distance: FloatArray  # (m,) m since the run started
    speed: FloatArray  # (m,) m/s
    truth: dict[str, FloatArray] = field(default_factory=dict)
    j_true: float = math.nan
    rms_accel_z: float = math.nan
    rms_pitch_rate: float = math.nan
    window_start_s: float = math.nan
    window_end_s: float = math.nan
    target_speed: float = math.nan
    bad_run: bool = False
    imu: ImuSpec = field(default_factory=ImuSpec)
    start_m: float = 0.0  # road position of the front axle at the run's start, m (where the odometry's distance is 0)

    @property
    def duration(self) -> float:
        return float(self.t[-1]) if self.t.size else 0.0


def definition_for(calibration: Mapping[str, float]) -> CalibrationDefinition:
    """The simulated controller's definition that ``calibration``'s names belong to."""
    for d in (controller_i_definition(), controller_ii_definition()):
        if set(calibration) == set(d.parameter_names):
            return d
    raise ControllerError(
        f"calibration names {sorted(calibration)[:6]}... match neither Controller I (damping_front, damping_rear) "
        "nor Controller II (p01..p20); pass the definition"
    )


def simulate_run(
    raw_calibration: Mapping[str, float],
    scenario: str | Scenario = "road",
    seed: int = 0,
    definition: CalibrationDefinition | None = None,
    imu: ImuSpec | None = None,
    driver: DriverModel | None = None,
    run_in_s: float = 6.0,
    run_out_s: float = 4.0,
    odom_rate_hz: float = 100.0,
) -> RunRecording:
    """Drive one run of ``scenario`` with ``raw_calibration`` (every raw parameter by name).

    Raises :class:`~bac_sim.errors.ControllerError` for unknown names or values outside the
    definition's bounds.
    """
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    imu = imu or ImuSpec()
    driver = driver or DriverModel()
    definition = definition or definition_for(raw_calibration)
    if not 10.0 <= odom_rate_hz <= 1000.0:
        raise ScenarioError(f"odometry rate must be in [10, 1000] Hz, got {odom_rate_hz}")
    if run_in_s < 1.0 or run_out_s < 0.5:
        raise ScenarioError("run-in must be >= 1 s and run-out >= 0.5 s")
    raw = raw_matrix(definition, [raw_calibration])
    rng = np.random.default_rng(seed)
    # the scenario's step (the batch problems' step, whose KPI agrees with fine references within 0.15 %) or
    # finer, so that every IMU sample is the mean of whole steps
    n_sub = max(IMU_SUBSTEPS_MIN, math.ceil(1.0 / imu.rate_hz / sc.dt - 1e-9))
    dt = 1.0 / (imu.rate_hz * n_sub)
    model = make_model(dt=dt)
    start_nominal = sc.window_start_m - run_in_s * sc.speed
    window_m = sc.window_length_s * sc.speed
    run_m = run_in_s * sc.speed + window_m + run_out_s * sc.speed
    drive_s = run_m / (sc.speed * 0.75) + 1.0  # enough for a slow (bad) run
    drive, bad = driver.draw(sc.speed, start_nominal, drive_s, 1, rng)
    # a start scattered before the beginning of the road starts where the road does (a shorter run-in)
    earliest = sc.road.s0 + model.params.wheelbase + 0.1
    if drive.s[0, 0] < earliest:
        drive.s[:] += earliest - drive.s[0, 0]
    s_end = start_nominal + run_m
    duration = float(drive.time_at(s_end)[0])
    sc.road.check_covers(float(drive.s[0, 0]) - model.params.wheelbase, s_end, f"a run of scenario '{sc.name}'")
    res = simulate(
        model, sc.road, make_controller(definition, raw), drive, duration, sc.window, seat=imu.lever_arm, record=True
    )
    rec = res.recording
    assert rec is not None
    # IMU samples: mean of the sub-steps of each sample period (the IMU's own anti-alias filter)
    n = rec.t.size // n_sub
    X = rec.X[: n * n_sub, :, 0].reshape(n, n_sub, -1).mean(axis=1)  # (n, 22): x and mid-step inputs
    t = rec.t[: n * n_sub : n_sub] + (n_sub - 1) * dt / 2
    acc = X[:, :N_STATE] @ model.acc_x.T + X[:, N_STATE:] @ model.acc_u.T + model.acc_const  # (n, 3)
    z_dd, th_dd, ph_dd = acc[:, 0], acc[:, 1], acc[:, 2]
    theta, phi = X[:, 1], X[:, 2]
    q, p = X[:, N_DOF + 1], X[:, N_DOF + 2]
    lx, ly, lz = imu.lever_arm
    v = drive.speed(t)[:, 0]
    a_long = np.gradient(v, t) if t.size > 1 else np.zeros_like(t)
    # acceleration of the IMU point in the world (small angles for the rigid-body terms)
    a_point = np.column_stack([a_long + th_dd * lz, -ph_dd * lz, z_dd - lx * th_dd + ly * ph_dd])
    f_world = a_point + np.array([0.0, 0.0, G])
    # world -> vehicle (exact rotation of roll and pitch), vehicle -> IMU (mounting)
    cr, sr, cp, sp = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta)
    # body-to-world R = Ry(theta) Rx(phi); f_body = R^T f_world
    fx, fy, fz = f_world[:, 0], f_world[:, 1], f_world[:, 2]
    f_body = np.column_stack(
        [cp * fx - sp * fz, sr * sp * fx + cr * fy + sr * cp * fz, cr * sp * fx - sr * fy + cr * cp * fz]
    )
    w_body = np.column_stack([p, q, np.zeros_like(q)])
    Rm = imu.mount_rotation
    f_imu = f_body @ Rm  # (R_m^T f)^T = f^T R_m
    w_imu = w_body @ Rm
    bw = imu.rate_hz / 2
    f_imu = (
        f_imu + np.asarray(imu.accel_bias) + imu.accel_noise_density * math.sqrt(bw) * rng.standard_normal(f_imu.shape)
    )
    w_imu = (
        w_imu + np.asarray(imu.gyro_bias) + imu.gyro_noise_density * math.sqrt(bw) * rng.standard_normal(w_imu.shape)
    )
    f_imu = np.clip(f_imu, -imu.accel_range, imu.accel_range)
    w_imu = np.clip(w_imu, -imu.gyro_range, imu.gyro_range)
    if imu.accel_lsb > 0:
        f_imu = np.round(f_imu / imu.accel_lsb) * imu.accel_lsb
    if imu.gyro_lsb > 0:
        w_imu = np.round(w_imu / imu.gyro_lsb) * imu.gyro_lsb
    odom_t = np.arange(0.0, duration, 1.0 / odom_rate_hz)
    s_odom = drive.position(odom_t)[:, 0]
    truth = {
        "accel_z": z_dd - lx * th_dd + ly * ph_dd,
        "pitch_rate": q,
        "roll_rate": p,
        "heave": X[:, 0] - model.linear.x_static[0],
        "pitch": theta,
        "roll": phi,
        "front_axle_m": drive.position(t)[:, 0],
        "command": rec.command[: n * n_sub : n_sub, :, 0],
    }
    return RunRecording(
        scenario=sc.name,
        calibration={k: float(v) for k, v in raw_calibration.items()},
        seed=seed,
        t=t,
        accel=f_imu,
        gyro=w_imu,
        odom_t=odom_t,
        distance=s_odom - s_odom[0],
        speed=drive.speed(odom_t)[:, 0],
        truth=truth,
        j_true=float(res.j[0]),
        rms_accel_z=float(res.rms_az[0]),
        rms_pitch_rate=float(res.rms_q[0]),
        window_start_s=float(res.window_start[0]),
        window_end_s=float(res.window_end[0]),
        target_speed=sc.speed,
        bad_run=bool(bad[0]),
        imu=imu,
        start_m=float(s_odom[0]),
    )


def simulate_scenario_run(
    raw_calibration: Mapping[str, float], scenario: str, speed_kmh: float | None = None, **kwargs: Any
) -> RunRecording:
    """:func:`simulate_run` with the scenario given by name (and speed): what a worker process is sent, so
    that the road is built (and cached) in the worker instead of being pickled with every run."""
    return simulate_run(raw_calibration, get_scenario(scenario, speed_kmh), **kwargs)
