"""The suspension controllers under calibration, vectorized over a batch of calibrations.

* **Controller I** (paper sec. IV-C-1): constant damping command front and rear, two parameters in
  [0, 1] (``damping_front``, ``damping_rear``; 1 = ``Phi_max``).
* **Controller II** (paper sec. IV-C-2): a semi-active comfort logic with 20 parameters ``p01..p20``
  in [0, 1000] that the calibration treats as a black box. Inside, it is a production-style blend:
  modal skyhook (heave, pitch and roll body velocities estimated by leaky integration of body
  accelerometers), groundhook on the wheel velocities, an acceleration-driven-damper (ADD) term,
  a deadband, an inverse damper map from the demanded force to the command, per-axle floors, a cap,
  a vehicle-speed gain table, end-stop protection, cornering roll control, anti-dive, and a command
  filter. :data:`CONTROLLER_II_PARAMETERS` gives each parameter's meaning and physical range: the
  truth the black-box reduction should rediscover (some matter much, some hardly at all, the speed
  table entries away from the test speed and the cornering gain not at all on a straight road).

Each controller is evaluated once per simulation step on ``(4, B)`` arrays (corners FL, FR, RL, RR).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from bac_common.paramspace import CalibrationDefinition, RawParameter, uniform_parameters
from bac_common.paths import calibration_file
from bac_sim.errors import ControllerError
from bac_sim.vehicle import N_CORNERS, VehicleParams

FloatArray = np.ndarray[Any, Any]


# --- definitions ----------------------------------------------------------------------------
def controller_i_definition() -> CalibrationDefinition:
    """Controller I's definition (the shipped controller_i.yaml when installed)."""
    path = calibration_file("controller_i")
    if path is not None:
        return CalibrationDefinition.load(path)
    params = (
        RawParameter("damping_front", 0, 0.0, 1.0, 0.5, 0.0001, "1", "constant damping command of both front dampers"),
        RawParameter("damping_rear", 1, 0.0, 1.0, 0.5, 0.0001, "1", "constant damping command of both rear dampers"),
    )
    return CalibrationDefinition(
        "controller_i", params, baseline={"damping_front": 0.5, "damping_rear": 0.5}, description="Constant damping"
    )


def controller_ii_definition() -> CalibrationDefinition:
    """Controller II's definition (the shipped controller_ii.yaml when installed)."""
    path = calibration_file("controller_ii")
    if path is not None:
        return CalibrationDefinition.load(path)
    return CalibrationDefinition(
        "controller_ii", uniform_parameters("p", 20, 0.0, 1000.0, 500.0, 0.01), description="Semi-active logic"
    )


def controller_iib_definition() -> CalibrationDefinition:
    """Controller II-B's definition (q01..q20 in [0, 1000]; see :data:`CONTROLLER_IIB_PARAMETERS`)."""
    return CalibrationDefinition(
        "controller_ii_b",
        uniform_parameters("q", 20, 0.0, 1000.0, 500.0, 0.01),
        description="Semi-active logic, another release (parameters in another order and on other scales)",
    )


@dataclass(frozen=True)
class ParamSpec:
    """Meaning of one Controller II parameter: value = lower + u (upper - lower), u = raw / 1000 (``reverse``:
    u = 1 - raw / 1000); ``slot``: the input of the logic it sets (default: ``name``, Controller II's own)."""

    name: str
    meaning: str
    unit: str
    lower: float
    upper: float
    log: bool = False
    slot: str = ""
    reverse: bool = False

    @property
    def input(self) -> str:
        return self.slot or self.name

    def physical(self, raw: FloatArray) -> FloatArray:
        u = np.asarray(raw, dtype=float) / 1000.0
        if self.reverse:
            u = 1.0 - u
        if self.log:
            return np.asarray(self.lower * (self.upper / self.lower) ** u)
        return np.asarray(self.lower + u * (self.upper - self.lower))


CONTROLLER_II_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("p01", "body-velocity estimator high-pass corner (integrator leak)", "Hz", 0.05, 2.0, log=True),
    ParamSpec("p02", "suspension-velocity filter corner", "Hz", 4.0, 80.0, log=True),
    ParamSpec("p03", "command filter corner", "Hz", 1.0, 40.0, log=True),
    ParamSpec("p04", "skyhook deadband on body velocity", "m/s", 0.0, 0.06),
    ParamSpec("p05", "skyhook gain, front axle", "N s/m", 0.0, 10000.0),
    ParamSpec("p06", "skyhook gain, rear axle", "N s/m", 0.0, 10000.0),
    ParamSpec("p07", "pitch weight of the modal skyhook", "1", 0.0, 2.0),
    ParamSpec("p08", "groundhook gain (wheel velocity), both axles", "N s/m", 0.0, 5000.0),
    ParamSpec("p09", "minimum damping command (floor), front axle", "1", 0.0, 0.7),
    ParamSpec("p10", "roll weight of the modal skyhook", "1", 0.0, 2.0),
    ParamSpec("p11", "minimum damping command (floor), rear axle", "1", 0.0, 0.7),
    ParamSpec("p12", "acceleration-driven-damper (ADD) mass", "kg", 0.0, 600.0),
    ParamSpec("p13", "ADD acceleration low-pass corner", "Hz", 1.0, 30.0, log=True),
    ParamSpec("p14", "maximum damping command (cap)", "1", 0.3, 1.0),
    ParamSpec("p15", "skyhook gain factor at 30 km/h", "1", 0.3, 1.7),
    ParamSpec("p16", "skyhook gain factor at 60 km/h", "1", 0.3, 1.7),
    ParamSpec("p17", "skyhook gain factor at 90 km/h", "1", 0.3, 1.7),
    ParamSpec("p18", "skyhook gain factor at 120 km/h", "1", 0.3, 1.7),
    ParamSpec("p19", "cornering roll-control gain (per g of lateral acceleration)", "1/g", 0.0, 2.0),
    ParamSpec("p20", "end-stop protection threshold (travel from static)", "m", 0.015, 0.09),
)
# Controller II-B: the same logic in another software release (problem road_c2b, parameters q01..q20): another
# order, nine parameters on reversed scales (a softness in place of a gain, a rate of decay in place of a corner
# frequency, ...) and the skyhook gains over twice the range. Its optimal groups differ from Controller II's: the
# simulation phase is judged on it too, so that the method is not tuned to one problem (docs/reduce.md).
_IIB_LAYOUT: tuple[tuple[str, str, bool, float | None], ...] = (
    # (name, Controller II input, reversed, new upper bound or None)
    ("q01", "p14", True, None),
    ("q02", "p05", False, 20000.0),
    ("q03", "p11", True, None),
    ("q04", "p20", False, None),
    ("q05", "p03", True, None),
    ("q06", "p08", True, None),
    ("q07", "p16", False, None),
    ("q08", "p01", False, None),
    ("q09", "p06", True, 20000.0),
    ("q10", "p19", False, None),
    ("q11", "p09", False, None),
    ("q12", "p02", True, None),
    ("q13", "p12", True, None),
    ("q14", "p07", False, None),
    ("q15", "p17", True, None),
    ("q16", "p04", False, None),
    ("q17", "p13", False, None),
    ("q18", "p10", True, None),
    ("q19", "p15", False, None),
    ("q20", "p18", False, None),
)
_II_BY_NAME = {s.name: s for s in CONTROLLER_II_PARAMETERS}
CONTROLLER_IIB_PARAMETERS: tuple[ParamSpec, ...] = tuple(
    ParamSpec(
        name,
        ("reversed: " if rev else "") + _II_BY_NAME[slot].meaning,
        _II_BY_NAME[slot].unit,
        _II_BY_NAME[slot].lower,
        upper if upper is not None else _II_BY_NAME[slot].upper,
        _II_BY_NAME[slot].log,
        slot,
        rev,
    )
    for name, slot, rev, upper in _IIB_LAYOUT
)
SPEED_TABLE_KMH = np.array([30.0, 60.0, 90.0, 120.0])
ACTUATOR_BANDWIDTH_HZ = 15.0  # valve + current driver of the semi-active damper (first-order)


# --- batch controller protocol --------------------------------------------------------------
class BatchController(Protocol):
    """What the simulator needs from a controller (see :mod:`bac_sim.engine`)."""

    batch: int
    constant: FloatArray | None  # (4, B) command when it never changes, else None

    def reset(self, dt: float, speed: FloatArray, x0: FloatArray) -> None:
        """Start a run: step ``dt``, speed of each run (B,), initial state (14, B)."""

    def command(
        self, x: FloatArray, v: FloatArray, travel: FloatArray, acc: FloatArray, phi_min: FloatArray, dphi: FloatArray
    ) -> FloatArray:
        """Damping command (4, B) in [0, 1] for this step.

        ``x`` state (14, B); ``v`` suspension extension velocity (4, B); ``travel`` suspension
        extension from static (4, B); ``acc`` body vertical acceleration at the corners (4, B);
        ``phi_min``, ``dphi``: the damper's force on the body (N, up) at command 0, ``-Phi_min(v)``,
        and its change from command 0 to 1, ``-(Phi_max(v) - Phi_min(v))`` (4, B): the force at
        command c is ``phi_min + c dphi``.
        """
        ...


def _as_batch(values: FloatArray | Sequence[Sequence[float]], dim: int, what: str) -> FloatArray:
    arr = np.atleast_2d(np.asarray(values, dtype=float))
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ControllerError(f"{what}: expected an (n, {dim}) array of parameters, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ControllerError(f"{what}: parameters contain NaN or infinite values")
    return arr


def check_bounds(definition: CalibrationDefinition, raw: FloatArray) -> None:
    """Raise :class:`ControllerError` if any raw value is outside its declared bounds."""
    lo = np.array([p.lower for p in definition.parameters])
    hi = np.array([p.upper for p in definition.parameters])
    bad = (raw < lo) | (raw > hi)
    if np.any(bad):
        row, col = (int(i) for i in np.argwhere(bad)[0])
        p = definition.parameters[col]
        raise ControllerError(
            f"{definition.name}: parameter '{p.name}' = {raw[row, col]!r} (row {row}) is outside its bounds "
            f"[{p.lower:g}, {p.upper:g}]"
        )


def raw_matrix(definition: CalibrationDefinition, calibrations: Sequence[Mapping[str, float]]) -> FloatArray:
    """Raw calibrations (every parameter by name) -> (n, P) array in the definition's order."""
    names = definition.parameter_names
    rows = []
    for cal in calibrations:
        unknown = set(cal) - set(names)
        if unknown:
            raise ControllerError(f"{definition.name}: unknown parameters {sorted(unknown)}; known: {list(names)}")
        missing = [n for n in names if n not in cal]
        if missing:
            raise ControllerError(f"{definition.name}: calibration lacks {missing}")
        rows.append([float(cal[n]) for n in names])
    raw = _as_batch(rows, len(names), definition.name)
    check_bounds(definition, raw)
    return raw


class ControllerI:
    """Constant damping: ``damping_front`` on both front dampers, ``damping_rear`` on both rear ones."""

    def __init__(self, raw: FloatArray) -> None:
        raw = _as_batch(raw, 2, "Controller I")
        if np.any(raw < 0) or np.any(raw > 1):
            raise ControllerError("Controller I: damping commands must lie in [0, 1]")
        self.batch = raw.shape[0]
        self.constant: FloatArray | None = np.ascontiguousarray(raw[:, [0, 0, 1, 1]].T)

    def reset(self, dt: float, speed: FloatArray, x0: FloatArray) -> None:
        return None

    def command(
        self, x: FloatArray, v: FloatArray, travel: FloatArray, acc: FloatArray, phi_min: FloatArray, dphi: FloatArray
    ) -> FloatArray:
        assert self.constant is not None
        return self.constant


def _lowpass_alpha(corner_hz: FloatArray, dt: float) -> FloatArray:
    return np.asarray(1.0 - np.exp(-2 * np.pi * corner_hz * dt))


class ControllerII:
    """The 20-parameter semi-active logic (see the module doc and :data:`CONTROLLER_II_PARAMETERS`)."""

    def __init__(
        self,
        raw: FloatArray,
        vehicle: VehicleParams | None = None,
        specs: Sequence[ParamSpec] = CONTROLLER_II_PARAMETERS,
    ) -> None:
        raw = _as_batch(raw, len(specs), "Controller II")
        if np.any(raw < 0) or np.any(raw > 1000):
            raise ControllerError("Controller II: parameters must lie in [0, 1000]")
        self.batch = raw.shape[0]
        self.constant: FloatArray | None = None
        vp = vehicle or VehicleParams()
        P = {spec.input: spec.physical(raw[:, i]) for i, spec in enumerate(specs)}
        if set(P) != set(_II_BY_NAME):
            raise ControllerError(f"Controller II: the parameter specs must set every input {sorted(_II_BY_NAME)}")
        self.P = P
        self._cx = -vp.corner_x[:, None]  # body height at corner = z - x theta + y phi
        self._cy = vp.corner_y[:, None]
        self._sky = np.vstack([P["p05"], P["p05"], P["p06"], P["p06"]])  # (4, B)
        self._floor = np.vstack([P["p09"], P["p09"], P["p11"], P["p11"]])
        self._cap = np.maximum(P["p14"], self._floor.max(axis=0))[None, :]
        self._state: dict[str, FloatArray] = {}

    def reset(self, dt: float, speed: FloatArray, x0: FloatArray) -> None:
        P, b = self.P, self.batch
        kmh = np.broadcast_to(np.asarray(speed, dtype=float), (b,)) * 3.6
        table = np.vstack([P["p15"], P["p16"], P["p17"], P["p18"]])  # (4, B)
        factor = np.array([np.interp(kmh[i], SPEED_TABLE_KMH, table[:, i]) for i in range(b)])
        self._gain = self._sky * factor[None, :]  # (4, B) N s/m
        self._a_hp = np.exp(-2 * np.pi * P["p01"] * dt)[None, :]  # (1, B)
        self._a_v = _lowpass_alpha(P["p02"], dt)[None, :]
        self._a_cmd = _lowpass_alpha(P["p03"], dt)[None, :]
        self._a_add = _lowpass_alpha(P["p13"], dt)[None, :]
        self._a_act = float(1.0 - np.exp(-2 * np.pi * ACTUATOR_BANDWIDTH_HZ * dt))
        self._db = np.repeat(P["p04"][None, :], N_CORNERS, axis=0)
        self._neg_db = -self._db
        self._gh = P["p08"][None, :]
        self._add = P["p12"][None, :]
        self._endstop = P["p20"][None, :]
        self._lat = P["p19"]  # x lateral acceleration: 0 on a straight road
        # modal skyhook: corner velocity = [1, -x_i, y_i] . (weights * [heave, pitch, roll] velocities)
        self._modal = np.column_stack([np.ones(N_CORNERS), self._cx[:, 0], self._cy[:, 0]])  # (4, 3)
        self._weights = np.vstack([np.ones(b), P["p07"], P["p10"]])  # (3, B)
        w0 = np.asarray(x0[7:10], dtype=float)
        floor0 = np.repeat(self._floor.mean(axis=0, keepdims=True), N_CORNERS, axis=0)
        # the filter states in one array (the compiled step loop updates it in place, bac_sim.kernels), and views
        st = np.zeros((22, b))
        st[0:3] = w0
        st[14:18] = floor0
        st[18:22] = floor0
        self._st = st
        self._state = {
            "w_prev": st[0:3],
            "hp": st[3:6],
            "w3": np.zeros((3, b)),
            "zsky": np.zeros((N_CORNERS, b)),
            "tmp": np.zeros((N_CORNERS, b)),
            "tmp2": np.zeros((N_CORNERS, b)),
            "flag": np.zeros((N_CORNERS, b), dtype=bool),
            "v_f": st[6:10],
            "acc_f": st[10:14],
            "cmd": np.zeros((N_CORNERS, b)),
            "cmd_f": st[14:18],
            "c_act": st[18:22],
        }

    def kernel_arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(modal (4, 3), parameters (21, B), filter states (22, B)) for :func:`bac_sim.kernels.steps_controller_ii`;
        the states are the arrays :meth:`command` updates (call after :meth:`reset`)."""
        b = self.batch
        par = np.empty((21, b))
        par[0:4] = self._gain
        par[4:8] = self._floor
        par[8] = self._cap[0]
        par[9] = self._a_hp[0]
        par[10] = self._a_v[0]
        par[11] = self._a_cmd[0]
        par[12] = self._a_add[0]
        par[13] = self._db[0]
        par[14] = self._endstop[0]
        par[15] = self._a_act
        par[16:19] = self._weights
        par[19] = self._gh[0]
        par[20] = self._add[0]
        return np.ascontiguousarray(self._modal), par, self._st

    def command(
        self, x: FloatArray, v: FloatArray, travel: FloatArray, acc: FloatArray, phi_min: FloatArray, dphi: FloatArray
    ) -> FloatArray:
        st = self._state
        hp, tmp, tmp2, flag, cmd = st["hp"], st["tmp"], st["tmp2"], st["flag"], st["cmd"]
        w = x[7:10]  # heave velocity, pitch rate, roll rate
        # leaky integration of the accelerometers == first-order high-pass of the body velocities
        hp += w
        hp -= st["w_prev"]
        hp *= self._a_hp
        st["w_prev"][...] = w
        # modal skyhook velocity at each corner, then the deadband (soft threshold)
        np.multiply(self._weights, hp, out=st["w3"])
        zsky = st["zsky"]
        np.matmul(self._modal, st["w3"], out=zsky)
        np.clip(zsky, self._neg_db, self._db, out=tmp)
        zsky -= tmp
        # filtered suspension velocity and body acceleration (ECU signal conditioning)
        v_f = st["v_f"]
        np.subtract(v, v_f, out=tmp)
        tmp *= self._a_v
        v_f += tmp
        acc_f = st["acc_f"]
        np.subtract(acc, acc_f, out=tmp)
        tmp *= self._a_add
        acc_f += tmp
        # demanded force on the body (up): groundhook - skyhook - ADD, minus the soft damper's force
        np.multiply(self._gh, x[10:14], out=cmd)
        np.multiply(self._gain, zsky, out=tmp)
        cmd -= tmp
        np.multiply(self._add, acc_f, out=tmp)
        cmd -= tmp
        cmd -= phi_min
        # inverse damper map: the damper's force on the body is f_soft + c f_span
        cmd *= dphi
        np.multiply(dphi, dphi, out=tmp)
        tmp += 25.0  # regularized division (f_span ~ 0 at rest)
        cmd /= tmp
        # the ECU trusts the demand only when its filtered velocity agrees in sign with the damper's
        np.multiply(v_f, v, out=tmp)
        np.greater_equal(tmp, 0.0, out=flag)
        cmd *= flag
        np.maximum(cmd, self._floor, out=cmd)
        np.minimum(cmd, self._cap, out=cmd)
        # end-stop protection: firm when the travel from static exceeds the threshold
        np.abs(travel, out=tmp2)
        np.greater(tmp2, self._endstop, out=flag)
        np.maximum(cmd, flag, out=cmd)
        cmd_f = st["cmd_f"]
        np.subtract(cmd, cmd_f, out=tmp)
        tmp *= self._a_cmd
        cmd_f += tmp
        c_act = st["c_act"]
        np.subtract(cmd_f, c_act, out=tmp)
        tmp *= self._a_act
        c_act += tmp
        return c_act


def make_controller(
    definition: CalibrationDefinition, raw: FloatArray, vehicle: VehicleParams | None = None
) -> ControllerI | ControllerII:
    """The controller simulating ``definition`` for raw calibrations ``raw`` (n, P)."""
    raw = _as_batch(raw, len(definition.parameters), definition.name)
    check_bounds(definition, raw)
    names = definition.parameter_names
    if set(names) == {"damping_front", "damping_rear"}:
        order = [names.index("damping_front"), names.index("damping_rear")]
        return ControllerI(raw[:, order])
    for specs in (CONTROLLER_II_PARAMETERS, CONTROLLER_IIB_PARAMETERS):
        expected = tuple(spec.name for spec in specs)
        if set(names) == set(expected):
            order = [names.index(n) for n in expected]
            return ControllerII(raw[:, order], vehicle, specs)
    raise ControllerError(
        f"no simulated controller for definition '{definition.name}' (parameters {list(names)}); the simulator "
        "knows Controller I (damping_front, damping_rear), Controller II (p01..p20) and Controller II-B (q01..q20)"
    )
