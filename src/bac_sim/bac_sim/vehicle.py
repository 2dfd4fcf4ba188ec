"""Full-car vertical model: 7 degrees of freedom, semi-active dampers, linear parts in matrix form.

Coordinates (ISO 8855 / REP 103: x forward, y left, z up), absolute, measured from the unloaded
geometry (springs and tyres at free length), so gravity is an explicit input and the static
equilibrium is a result, not an assumption:

* ``q = [z, theta, phi, zu_fl, zu_fr, zu_rl, zu_rr]``: heave of the sprung mass's centre of gravity
  (m, up), pitch (rad, positive nose **down**, a right-hand rotation about y-left), roll (rad, positive
  left side **up**, a right-hand rotation about x-forward), vertical positions of the four wheel centres.
* state ``x = [q, dq/dt]`` (14).
* corners in the order FL, FR, RL, RR at ``(x_i, y_i)`` = ``(a, +tf/2), (a, -tf/2), (-b, +tr/2),
  (-b, -tr/2)`` from the centre of gravity; the body's height at corner i is
  ``z - x_i theta + y_i phi`` (small angles).
* suspension extension ``Delta_i = z_body,i - zu_i`` (rebound = extension, velocity > 0).

The corner forces that are not linear (the semi-active dampers, the bump stops and the tyre leaving
the road) are inputs ``u`` of the linear model: ``M q'' = -K q + D^T f + T_r r + F_g``. The simulator
(:mod:`bac_sim.engine`) discretizes the linear part exactly (matrix exponential, zero-order hold on
the corner forces, first-order hold on the road) and evaluates the nonlinear forces once per step.

The figures of :class:`VehicleParams` are those of the paper where it gives them (sprung mass
1370 kg, unsprung mass 160 kg, spring 153 N/mm) and plausible values for a luxury sedan elsewhere;
``docs/sim.md`` lists them with their sources.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg

from bac_sim.errors import ModelError

G = 9.80665  # standard gravity, m/s^2
N_CORNERS = 4
N_DOF = 7
N_STATE = 2 * N_DOF
CORNERS = ("fl", "fr", "rl", "rr")
FloatArray = np.ndarray[Any, Any]


@dataclass(frozen=True)
class DamperCurve:
    """One force-velocity characteristic Phi(v) of a damper, at the wheel.

    Piecewise linear and digressive: slope ``rebound_low`` up to ``knee_rebound`` (m/s), then
    ``rebound_high``; in compression (v < 0) slope ``compression_low`` down to ``-knee_compression``,
    then ``compression_high``. Forces are the magnitude the damper resists with (N, positive for
    extension), the force on the body is ``-Phi(v)``.
    """

    rebound_low: float
    rebound_high: float
    compression_low: float
    compression_high: float

    def __post_init__(self) -> None:
        for name in ("rebound_low", "rebound_high", "compression_low", "compression_high"):
            if not getattr(self, name) > 0:
                raise ModelError(f"damper slope {name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class DamperMap:
    """The controllability region of the semi-active damper: ``Phi_min`` and ``Phi_max`` (paper eq. 2).

    Both curves share the knee velocities so that ``F = c Phi_max + (1 - c) Phi_min`` stays a
    piecewise-linear function with the same breakpoints for every command ``c`` in [0, 1].
    """

    soft: DamperCurve = DamperCurve(1100.0, 650.0, 550.0, 380.0)
    firm: DamperCurve = DamperCurve(6500.0, 1900.0, 3200.0, 1000.0)
    knee_rebound: float = 0.12  # m/s
    knee_compression: float = 0.10  # m/s

    def __post_init__(self) -> None:
        if not (self.knee_rebound > 0 and self.knee_compression > 0):
            raise ModelError("damper knee velocities must be > 0")
        for a, b in (
            (self.soft.rebound_low, self.firm.rebound_low),
            (self.soft.rebound_high, self.firm.rebound_high),
            (self.soft.compression_low, self.firm.compression_low),
            (self.soft.compression_high, self.firm.compression_high),
        ):
            if not b > a:
                raise ModelError("the firm damper curve must lie above the soft one everywhere")

    def basis_coefficients(self, curve: DamperCurve) -> FloatArray:
        """Coefficients of ``Phi`` on the basis ``[v, |v|, max(v - kr, 0), min(v + kc, 0)]``."""
        return np.array(
            [
                (curve.rebound_low + curve.compression_low) / 2,
                (curve.rebound_low - curve.compression_low) / 2,
                curve.rebound_high - curve.rebound_low,
                curve.compression_high - curve.compression_low,
            ]
        )

    def force(self, v: FloatArray | float, command: FloatArray | float) -> FloatArray:
        """``Phi(v) = c Phi_max(v) + (1 - c) Phi_min(v)`` (N, resisting; the body feels ``-Phi``)."""
        v = np.asarray(v, dtype=float)
        c = np.asarray(command, dtype=float)
        basis = np.stack(
            [v, np.abs(v), np.maximum(v - self.knee_rebound, 0.0), np.minimum(v + self.knee_compression, 0.0)]
        )
        lo = self.basis_coefficients(self.soft)
        hi = self.basis_coefficients(self.firm)
        coef = lo.reshape((4,) + (1,) * v.ndim) + (hi - lo).reshape((4,) + (1,) * v.ndim) * c
        return np.asarray(np.sum(coef * basis, axis=0))


@dataclass(frozen=True)
class VehicleParams:
    """Parameters of the full-car model (SI units). Defaults: a luxury sedan, see docs/sim.md."""

    sprung_mass: float = 1370.0  # kg (paper, sec. IV-A)
    unsprung_mass_total: float = 160.0  # kg, four corners together (paper, sec. IV-A)
    spring_rate: float = 153_000.0  # N/m at the spring (paper: 153 N/mm)
    motion_ratio_front: float = 0.40  # wheel travel -> spring travel; wheel rate = MR^2 * spring rate
    motion_ratio_rear: float = 0.42
    wheelbase: float = 2.94  # m
    cg_to_front_axle: float = 1.38  # m (a); front static load share b / L = 53 %
    track_front: float = 1.60  # m
    track_rear: float = 1.61  # m
    pitch_inertia: float = 2450.0  # kg m^2 (sprung, about y)
    roll_inertia: float = 540.0  # kg m^2 (sprung, about x)
    tyre_rate: float = 260_000.0  # N/m per tyre (vertical)
    antiroll_front: float = 18_000.0  # N/m at the wheel, per unit of left-right travel difference
    antiroll_rear: float = 8_000.0  # N/m
    bump_stop_rate: float = 400_000.0  # N/m at the wheel, beyond the free travel
    travel_compression: float = 0.075  # m of compression from static before the bump stop
    travel_rebound: float = 0.085  # m of rebound from static before the rebound stop
    dampers: DamperMap = field(default_factory=DamperMap)
    gravity: float = G

    def __post_init__(self) -> None:
        positive = (
            "sprung_mass",
            "unsprung_mass_total",
            "spring_rate",
            "motion_ratio_front",
            "motion_ratio_rear",
            "wheelbase",
            "cg_to_front_axle",
            "track_front",
            "track_rear",
            "pitch_inertia",
            "roll_inertia",
            "tyre_rate",
            "bump_stop_rate",
            "travel_compression",
            "travel_rebound",
        )
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ModelError(f"vehicle parameter {name} must be finite and > 0, got {value}")
        for name in ("antiroll_front", "antiroll_rear", "gravity"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ModelError(f"vehicle parameter {name} must be finite and >= 0")
        if not 0 < self.cg_to_front_axle < self.wheelbase:
            raise ModelError("the centre of gravity must lie between the axles (0 < a < wheelbase)")

    # --- derived figures -----------------------------------------------------------------
    @property
    def a(self) -> float:
        return self.cg_to_front_axle

    @property
    def b(self) -> float:
        return self.wheelbase - self.cg_to_front_axle

    @property
    def unsprung_mass(self) -> float:
        """Per corner, kg."""
        return self.unsprung_mass_total / N_CORNERS

    @property
    def wheel_rates(self) -> FloatArray:
        """Suspension spring rate at each wheel (N/m): motion ratio squared times the spring rate."""
        kf = self.motion_ratio_front**2 * self.spring_rate
        kr = self.motion_ratio_rear**2 * self.spring_rate
        return np.array([kf, kf, kr, kr])

    @property
    def corner_x(self) -> FloatArray:
        return np.array([self.a, self.a, -self.b, -self.b])

    @property
    def corner_y(self) -> FloatArray:
        return np.array([self.track_front / 2, -self.track_front / 2, self.track_rear / 2, -self.track_rear / 2])

    @property
    def corner_sprung_loads(self) -> FloatArray:
        """Static load of the sprung mass on each corner (N), left/right symmetric."""
        w = self.sprung_mass * self.gravity
        front = w * self.b / self.wheelbase / 2
        rear = w * self.a / self.wheelbase / 2
        return np.array([front, front, rear, rear])

    def with_(self, **changes: Any) -> VehicleParams:
        return replace(self, **changes)


@dataclass(frozen=True)
class LinearModel:
    """The linear part of the model in state-space form.

    ``dx/dt = A x + Bf f + Br r + bg`` with ``f`` = the corner forces acting between body and wheel
    (8 inputs: 4 suspension forces on the body, up; 4 extra tyre forces on the wheels, up) and ``r``
    the road heights under the four wheels.
    """

    params: VehicleParams
    M: FloatArray  # (7, 7) mass matrix
    K: FloatArray  # (7, 7) stiffness matrix (springs, anti-roll bars, tyres)
    D: FloatArray  # (4, 7) suspension extension Delta = D q
    L: FloatArray  # (4, 3) body height at the corners = L [z, theta, phi]
    A: FloatArray  # (14, 14)
    Bf: FloatArray  # (14, 8)
    Br: FloatArray  # (14, 4)
    bg: FloatArray  # (14,) gravity
    x_static: FloatArray  # (14,) static equilibrium on a flat road (r = 0, no force input)

    @property
    def static_deflection(self) -> FloatArray:
        """Suspension extension at static equilibrium (m, negative = compressed), per corner."""
        return np.asarray(self.D @ self.x_static[:N_DOF])

    @property
    def static_tyre_deflection(self) -> FloatArray:
        """Tyre compression at static equilibrium (m, positive), per corner."""
        return np.asarray(-self.x_static[3:N_DOF])

    def modes(self) -> tuple[FloatArray, FloatArray]:
        """Undamped natural frequencies (Hz, ascending) and mode shapes (columns, q coordinates)."""
        w2, vecs = scipy.linalg.eigh(self.K, self.M)
        return np.sqrt(np.maximum(w2, 0.0)) / (2 * np.pi), vecs

    def passive_frequency_response(
        self, freqs_hz: FloatArray, damping: FloatArray | float, seat: tuple[float, float] = (0.0, 0.0)
    ) -> dict[str, FloatArray]:
        """Frequency response of the passive car (linear dampers ``damping`` N s/m per corner).

        Input: the same road height under all four wheels (pure heave excitation, as a four-poster
        rig). Returns magnitudes of body heave acceleration at the seat point ``(x, y)``, of the
        pitch rate (both per metre of road), and of the front wheel's travel per metre of road.
        """
        c = np.broadcast_to(np.asarray(damping, dtype=float), (N_CORNERS,))
        C = self.D.T @ np.diag(c) @ self.D
        n = N_DOF
        Tr = np.zeros((n, N_CORNERS))
        Tr[3:, :] = np.diag(np.full(N_CORNERS, self.params.tyre_rate))
        r = np.ones(N_CORNERS)
        out_acc, out_q, out_w = [], [], []
        for f in np.asarray(freqs_hz, dtype=float):
            w = 2 * np.pi * f
            H = -(w**2) * self.M + 1j * w * C + self.K
            q = np.linalg.solve(H, Tr @ r)
            acc = -(w**2) * q
            out_acc.append(abs(acc[0] - seat[0] * acc[1] + seat[1] * acc[2]))
            out_q.append(abs(1j * w * q[1]))
            out_w.append(abs(q[3]))
        return {"accel_z": np.array(out_acc), "pitch_rate": np.array(out_q), "wheel_fl": np.array(out_w)}


def build_linear_model(p: VehicleParams) -> LinearModel:
    """Mass, stiffness and input matrices of the 7-DOF car, and its static equilibrium."""
    ms, mu = p.sprung_mass, p.unsprung_mass
    M = np.diag([ms, p.pitch_inertia, p.roll_inertia, mu, mu, mu, mu])
    L = np.column_stack([np.ones(N_CORNERS), -p.corner_x, p.corner_y])  # (4, 3)
    D = np.hstack([L, -np.eye(N_CORNERS)])  # (4, 7): Delta = D q
    k = p.wheel_rates
    K_s = D.T @ np.diag(k) @ D
    arb = np.zeros((N_CORNERS, N_CORNERS))
    for i, j, ka in ((0, 1, p.antiroll_front), (2, 3, p.antiroll_rear)):
        arb[np.ix_([i, j], [i, j])] = ka * np.array([[1.0, -1.0], [-1.0, 1.0]])
    K_arb = D.T @ arb @ D
    K_t = np.zeros((N_DOF, N_DOF))
    K_t[3:, 3:] = np.eye(N_CORNERS) * p.tyre_rate
    K = K_s + K_arb + K_t
    Minv = np.linalg.inv(M)
    # generalized forces of the 8 corner force inputs: suspension pair (body up / wheel down), tyre extra
    Fq = np.zeros((N_DOF, 2 * N_CORNERS))
    Fq[:, :N_CORNERS] = D.T
    Fq[3:, N_CORNERS:] = np.eye(N_CORNERS)
    Tr = np.zeros((N_DOF, N_CORNERS))
    Tr[3:, :] = np.eye(N_CORNERS) * p.tyre_rate
    Fg = np.array([-ms * p.gravity, 0.0, 0.0, -mu * p.gravity, -mu * p.gravity, -mu * p.gravity, -mu * p.gravity])
    A = np.zeros((N_STATE, N_STATE))
    A[:N_DOF, N_DOF:] = np.eye(N_DOF)
    A[N_DOF:, :N_DOF] = -Minv @ K
    Bf = np.vstack([np.zeros((N_DOF, 2 * N_CORNERS)), Minv @ Fq])
    Br = np.vstack([np.zeros((N_DOF, N_CORNERS)), Minv @ Tr])
    bg = np.concatenate([np.zeros(N_DOF), Minv @ Fg])
    q_static = np.linalg.solve(K, Fg)
    x_static = np.concatenate([q_static, np.zeros(N_DOF)])
    eig = np.linalg.eigvals(A)
    if np.any(eig.real > 1e-9):
        raise ModelError("the vehicle model is unstable with these parameters")
    return LinearModel(p, M, K, D, L, A, Bf, Br, bg, x_static)


@dataclass(frozen=True)
class Discretization:
    """Exact discretization of :class:`LinearModel` at step ``dt``.

    ``x[k+1] = Phi x[k] + Gf f[k] + Gr0 r[k] + Gr1 r[k+1] + gg`` with ``f`` held over the step (ZOH)
    and ``r`` linear over the step (FOH).
    """

    dt: float
    Phi: FloatArray
    Gf: FloatArray
    Gr0: FloatArray
    Gr1: FloatArray
    gg: FloatArray


def discretize(model: LinearModel, dt: float) -> Discretization:
    if not (np.isfinite(dt) and 0 < dt <= 0.02):
        raise ModelError(f"time step must be in (0, 0.02] s, got {dt}")
    n = N_STATE
    nf = model.Bf.shape[1]
    nr = model.Br.shape[1]
    # inputs: f (ZOH), g (constant 1), r (FOH: value and slope)
    m = nf + 1 + nr
    big = np.zeros((n + m + nr, n + m + nr))
    big[:n, :n] = model.A
    big[:n, n : n + nf] = model.Bf
    big[:n, n + nf] = model.bg
    big[:n, n + nf + 1 : n + m] = model.Br
    big[n + nf + 1 : n + m, n + m :] = np.eye(nr) / dt  # r(t) = r_k + (r_{k+1} - r_k) t / dt
    E = scipy.linalg.expm(big * dt)
    Phi = E[:n, :n]
    Gf = E[:n, n : n + nf]
    gg = E[:n, n + nf]
    Ga = E[:n, n + nf + 1 : n + m]  # effect of r_k held
    Gb = E[:n, n + m :]  # effect of the slope (r_{k+1} - r_k)
    return Discretization(dt, Phi, Gf, Ga - Gb, Gb, gg)
