"""The batch simulator: many runs of the full-car model at once, fixed step, pure numpy.

Integration scheme (one step ``k -> k+1`` of length ``dt``):

* the linear part (springs, anti-roll bars, tyres, gravity, masses) is discretized **exactly**
  (:func:`bac_sim.vehicle.discretize`): zero-order hold on the corner forces, first-order hold on
  the road heights, so it is unconditionally stable and exact for any ``dt``;
* the nonlinear corner forces (semi-active dampers, bump stops, a tyre leaving the road) are
  evaluated once per step from the state extrapolated to the middle of the step
  (``1.5 x[k+1] - 0.5 x[k]``, second order), and held over the step.

A step's inputs ``[u (8); x (14); 1]`` (force inputs, state, a constant), one column per run, sit in
a chunk buffer; one step is one matrix product ``(35, 23) @ (23, B)`` (``(35, 31)`` with per-run road
inputs) that writes the next state and every linear signal the forces and the controller need
straight into the next slot, plus about fifteen elementwise operations on ``(4, B)`` arrays. Road
inputs and the outputs are computed in chunks of steps with large vectorized operations. With a
step of 2.5 ms on the road (30 steps per wheel-hop period) and 1 ms at the bump, the KPI agrees
with fine references within 0.15 % (see ``tests/sim/test_engine.py``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from bac_sim.controllers import BatchController
from bac_sim.driver import Drive
from bac_sim.errors import ScenarioError
from bac_sim.kernels import chunk_outputs, drive_and_road, kernel_choice, steps_constant, steps_controller_ii
from bac_sim.roads import Road
from bac_sim.vehicle import (
    N_CORNERS,
    N_DOF,
    N_STATE,
    Discretization,
    LinearModel,
    VehicleParams,
    build_linear_model,
    discretize,
)

FloatArray = np.ndarray[Any, Any]

DT_DEFAULT = 0.002  # s
CHUNK_STEPS = 200
N_INPUTS = 2 * N_CORNERS  # suspension force on the body (4), tyre tension cancelled (4)
# rows of the stored step state S[k] = [r_k, r_k+1 (8); u_k (8); x_k (14); 1; signals (20)]
N_ROAD = 2 * N_CORNERS
U = slice(N_ROAD, N_ROAD + N_INPUTS)
U0 = N_ROAD
O0 = N_ROAD + N_INPUTS  # the step product writes rows O0.. of S[k+1]
XS = slice(O0, O0 + N_STATE)
N_IN = N_INPUTS + N_STATE + 1  # the product reads [u; x; 1], or [r_k; r_k+1; u; x; 1] with per-run roads
# rows of the step product (written to S[k+1][8:]), relative to its start
O_X = slice(0, 14)
O_ONE = 14
O_V = slice(15, 19)  # suspension extension velocity at mid-step
O_T1 = slice(19, 23)  # travel beyond the rebound stop (> 0: on the stop)
O_T2 = slice(23, 27)  # travel beyond the compression stop (> 0: on the stop)
O_STOPS = slice(19, 27)
O_TY = slice(27, 31)  # tyre tension (> 0: the wheel left the road)
O_A = slice(31, 35)  # body vertical acceleration at the corners
N_OUT = 35
N_S = O0 + N_OUT
SEAT_DEFAULT = (-0.25, -0.38, -0.30)  # m from the sprung centre of gravity: front passenger seat rail


@dataclass(frozen=True)
class SimModel:
    """A vehicle ready to simulate: linear model, discretization and the step matrices."""

    params: VehicleParams
    linear: LinearModel
    disc: Discretization
    G: FloatArray  # (35, 23) step matrix on [u; x; 1]
    R0: FloatArray  # (35, 4) road at k
    R1: FloatArray  # (35, 4) road at k+1
    acc_x: FloatArray  # (3, 14) body accelerations [z'', theta'', phi''] = acc_x x + acc_u u + acc_const
    acc_u: FloatArray  # (3, 8)
    acc_const: FloatArray  # (3,)
    W_damp: FloatArray  # (2, 4): -[Phi_min; Phi_max - Phi_min] on the damper basis
    static_travel: FloatArray  # (4,)

    @property
    def dt(self) -> float:
        return self.disc.dt

    def initial_state(self, r0: FloatArray) -> FloatArray:
        """Static equilibrium (14, B) on a road whose heights under the wheels are ``r0`` (4, B)."""
        lin = self.linear
        Tr = np.zeros((N_DOF, N_CORNERS))
        Tr[3:, :] = np.eye(N_CORNERS) * self.params.tyre_rate
        dq = np.linalg.solve(lin.K, Tr @ np.atleast_2d(r0.T).T)
        x0 = np.repeat(lin.x_static[:, None], dq.shape[1], axis=1)
        x0[:N_DOF] += dq
        return x0


@lru_cache(maxsize=16)
def make_model(params: VehicleParams | None = None, dt: float = DT_DEFAULT) -> SimModel:
    """Build (and cache) the step matrices of a vehicle at step ``dt``."""
    p = params or VehicleParams()
    lin = build_linear_model(p)
    d = discretize(lin, dt)
    n = N_STATE
    I4 = np.eye(N_CORNERS)
    Z4 = np.zeros((N_CORNERS, N_DOF))
    Cv = np.hstack([Z4, lin.D])  # extension velocity
    Ct = np.hstack([lin.D, Z4])  # extension
    Cu = np.zeros((N_CORNERS, n))
    Cu[:, 3:N_DOF] = I4  # wheel heights
    A_b = lin.A[N_DOF : N_DOF + 3]
    Bf_b = lin.Bf[N_DOF : N_DOF + 3]
    bg_b = lin.bg[N_DOF : N_DOF + 3]
    Lc = lin.L
    Tu = np.diag(np.concatenate([np.ones(N_CORNERS), np.full(N_CORNERS, p.tyre_rate)]))
    static_travel = lin.D @ lin.x_static[:N_DOF]
    G = np.zeros((N_OUT, N_IN))
    R0 = np.zeros((N_OUT, N_CORNERS))
    R1 = np.zeros((N_OUT, N_CORNERS))

    def rows(
        sl: slice,
        c_next: FloatArray,
        c_now: FloatArray | None = None,
        c_u: FloatArray | None = None,
        const: FloatArray | float = 0.0,
        r_now: FloatArray | None = None,
        r_next: FloatArray | None = None,
    ) -> None:
        """Rows = c_next x[k+1] + c_now x[k] + c_u f[k] + const + r_now r[k] + r_next r[k+1]."""
        G[sl, N_INPUTS : N_INPUTS + n] = c_next @ d.Phi + (0 if c_now is None else c_now)
        G[sl, :N_INPUTS] = (c_next @ d.Gf + (0 if c_u is None else c_u)) @ Tu
        G[sl, N_IN - 1] = c_next @ d.gg + const
        R0[sl] = c_next @ d.Gr0 + (0 if r_now is None else r_now)
        R1[sl] = c_next @ d.Gr1 + (0 if r_next is None else r_next)

    rows(O_X, np.eye(n))
    G[O_ONE, N_IN - 1] = 1.0
    rows(O_V, 1.5 * Cv, -0.5 * Cv)
    rows(O_T1, 1.5 * Ct, -0.5 * Ct, const=-static_travel - p.travel_rebound)
    rows(O_T2, -1.5 * Ct, 0.5 * Ct, const=static_travel - p.travel_compression)
    rows(O_TY, 1.5 * Cu, -0.5 * Cu, r_now=0.5 * I4, r_next=-1.5 * I4)
    rows(O_A, Lc @ A_b, c_u=Lc @ Bf_b, const=Lc @ bg_b)
    dm = p.dampers
    lo = dm.basis_coefficients(dm.soft)
    hi = dm.basis_coefficients(dm.firm)
    W_damp = -np.vstack([lo, hi - lo])
    return SimModel(p, lin, d, G, R0, R1, A_b.copy(), Bf_b @ Tu, bg_b.copy(), W_damp, static_travel)


@dataclass(frozen=True)
class KpiWindow:
    """The part of a run that is scored.

    ``distance``: the front axle between ``start_m`` and ``end_m`` along the road (a road section,
    cut by odometry). ``event``: ``length_s`` seconds from ``pre_s`` before the front axle reaches
    ``event_m`` (a single event such as the speed bump, cut around the detected impact).
    """

    mode: str
    start_m: float = 0.0
    end_m: float = 0.0
    event_m: float = 0.0
    pre_s: float = 0.0
    length_s: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in ("distance", "event"):
            raise ScenarioError(f"KPI window mode must be 'distance' or 'event', got {self.mode!r}")
        if self.mode == "distance" and not self.end_m > self.start_m:
            raise ScenarioError("KPI window: end_m must be > start_m")
        if self.mode == "event" and not (self.length_s > 0 and self.pre_s >= 0):
            raise ScenarioError("KPI window: length_s must be > 0 and pre_s >= 0")


@dataclass
class Recording:
    """Every step of a (small) batch: times, positions, states, forces and commands."""

    t: FloatArray  # (n,) s
    s: FloatArray  # (n, Bd) front-axle position, m
    v: FloatArray  # (n, Bd) speed, m/s
    X: FloatArray  # (n, 22, B) state x (14) and inputs u (8) at each step (u: mid value at t_k)
    command: FloatArray  # (n, 4, B) damping command in force
    road: FloatArray  # (n, 4, Bd) road heights under the wheels


@dataclass
class BatchResult:
    """KPI parts of each run of a batch (paper eq. 1 on the ground-truth seat-rail signals)."""

    sum_az2: FloatArray  # (B,) sum of squared vertical acceleration over the window
    sum_q2: FloatArray  # (B,) sum of squared pitch rate
    count: FloatArray  # (B,) samples in the window
    window_start: FloatArray  # (B,) s
    window_end: FloatArray  # (B,) s
    max_travel: FloatArray  # (B,) largest |travel from static| of any corner, m
    lift_off: FloatArray  # (B,) steps with a wheel off the ground
    recording: Recording | None = field(default=None)

    @property
    def rms_az(self) -> FloatArray:
        return np.asarray(np.sqrt(self.sum_az2 / np.maximum(self.count, 1)))

    @property
    def rms_q(self) -> FloatArray:
        return np.asarray(np.sqrt(self.sum_q2 / np.maximum(self.count, 1)))

    @property
    def j(self) -> FloatArray:
        """J = RMS(a_z) + RMS(pitch rate) (paper eq. 1)."""
        return self.rms_az + self.rms_q


def road_under_wheels(road: Road, s_front: FloatArray, wheelbase: float) -> FloatArray:
    """Road heights (n, 4, Bd) under FL, FR, RL, RR for front-axle positions ``s_front`` (n, Bd)."""
    pos = np.stack([s_front, s_front - wheelbase], axis=1)  # (n, 2 axles, Bd)
    z = road.heights_stacked(pos)  # (n, 2, Bd, 2 tracks)
    return np.ascontiguousarray(z.transpose(0, 1, 3, 2).reshape(s_front.shape[0], N_CORNERS, s_front.shape[1]))


def _blas_limiter() -> Any:
    """A context manager holding BLAS to one thread (threadpoolctl), or doing nothing without it.

    A step's product is small ((35, 31) @ (31, B)): a multi-threaded OpenBLAS spends more on waking and
    waiting for its threads than on the product, worst on a shared machine; batches are split over
    processes instead (bac_sim.parallel).
    """
    holder: dict[str, Any] = {}

    @contextmanager
    def limit() -> Iterator[None]:
        if "c" not in holder:
            try:
                from threadpoolctl import ThreadpoolController

                holder["c"] = ThreadpoolController()
            except Exception:  # pragma: no cover - threadpoolctl missing or unable to inspect the BLAS
                holder["c"] = None
        if holder["c"] is None:
            yield
            return
        with holder["c"].limit(limits=1, user_api="blas"):
            yield

    return limit


_one_blas_thread = _blas_limiter()


def simulate(
    model: SimModel,
    road: Road,
    controller: BatchController,
    drive: Drive,
    duration: float,
    window: KpiWindow | None = None,
    seat: tuple[float, float, float] = SEAT_DEFAULT,
    record: bool = False,
    window_shift: FloatArray | None = None,
    initial_offset: FloatArray | None = None,
    kernel: str = "auto",
) -> BatchResult:
    """Simulate ``controller.batch`` runs for ``duration`` seconds.

    ``drive`` gives each run's front-axle position and speed (its batch is B or 1, shared).
    ``window`` selects the samples scored (all of them when None); ``window_shift`` (B,) moves each
    run's window (m in distance mode, s in event mode): the residual error of cutting and aligning.
    ``initial_offset`` (14,) is added to the static equilibrium the runs start from.
    ``kernel``: the step loop compiled by numba (``"numba"``, :mod:`bac_sim.kernels`) or the numpy reference
    loop (``"numpy"``); ``"auto"`` = numba when installed, unless ``BAC_SIM_KERNEL=numpy``. BLAS runs on one
    thread meanwhile.
    """
    with _one_blas_thread():
        return _simulate(
            model, road, controller, drive, duration, window, seat, record, window_shift, initial_offset, kernel
        )


def _simulate(
    model: SimModel,
    road: Road,
    controller: BatchController,
    drive: Drive,
    duration: float,
    window: KpiWindow | None = None,
    seat: tuple[float, float, float] = SEAT_DEFAULT,
    record: bool = False,
    window_shift: FloatArray | None = None,
    initial_offset: FloatArray | None = None,
    kernel: str = "auto",
) -> BatchResult:
    """The body of :func:`simulate`."""
    B = controller.batch
    Bd = drive.batch
    if Bd not in (1, B):
        raise ScenarioError(f"drive batch {Bd} must be 1 or the controller batch {B}")
    dt = model.dt
    n_steps = round(duration / dt)
    if n_steps < 2:
        raise ScenarioError("duration must hold at least two steps")
    if duration > drive.duration + 1e-9:
        raise ScenarioError(f"the drive lasts {drive.duration:.2f} s, less than the run ({duration:.2f} s)")
    p = model.params
    s_first = drive.position(np.array([0.0]))[0]
    s_last = drive.position(np.array([n_steps * dt]))[0]
    road.check_covers(float(s_first.min() - p.wheelbase), float(s_last.max()), "this run")
    # KPI window per run, as times
    if window is None:
        w_start = np.zeros(B)
        w_end = np.full(B, np.inf)
        dist_window: tuple[FloatArray, FloatArray] | None = None
    elif window.mode == "event":
        t_event = drive.time_at(window.event_m)
        w_start = np.broadcast_to(t_event - window.pre_s, (B,)).copy()
        if window_shift is not None:
            w_start += window_shift
        w_end = w_start + window.length_s
        if np.any(w_start < 0) or np.any(w_end > n_steps * dt):
            raise ScenarioError("the KPI window does not fit in the run; lengthen the run-in or run-out")
        dist_window = None
    else:
        shift = np.zeros(Bd) if window_shift is None else np.asarray(window_shift, dtype=float)
        if window_shift is not None and shift.shape != (Bd,):
            raise ScenarioError("per-run window shifts need per-run drives")
        w_start = np.broadcast_to(drive.time_at(window.start_m + shift), (B,)).copy()
        w_end = np.broadcast_to(drive.time_at(window.end_m + shift), (B,)).copy()
        if np.any(w_end > n_steps * dt):
            raise ScenarioError("the KPI section does not fit in the run; lengthen the run")
        dist_window = (np.broadcast_to(window.start_m + shift, (B,)), np.broadcast_to(window.end_m + shift, (B,)))

    # initial state: static equilibrium on the road under the wheels
    r_first = road_under_wheels(road, s_first[None, :], p.wheelbase)[0]  # (4, Bd)
    x0 = model.initial_state(r_first)
    if initial_offset is not None:
        x0 = x0 + np.asarray(initial_offset, dtype=float).reshape(N_STATE, 1)
    S = np.zeros((CHUNK_STEPS + 1, N_S, B))
    S[0, XS] = x0 if Bd == B else np.repeat(x0, B, axis=1)
    S[0, O0 + O_ONE] = 1.0
    speed0 = np.broadcast_to(drive.speed(np.array([0.0]))[0], (B,))
    controller.reset(dt, np.asarray(speed0, dtype=float), S[0, XS])
    constant = controller.constant
    basis = np.empty((4, N_CORNERS, B))
    basis2 = basis.reshape(4, N_CORNERS * B)
    pm = np.empty((2, N_CORNERS * B))
    phi_min = pm[0].reshape(N_CORNERS, B)  # -Phi_min(v): force on the body of the soft damper
    dphi = pm[1].reshape(N_CORNERS, B)  # -(Phi_max - Phi_min)(v)
    travel = np.empty((N_CORNERS, B))
    stop = np.empty((N_CORNERS, B))
    kr = p.dampers.knee_rebound
    kc = p.dampers.knee_compression
    k_bs = p.bump_stop_rate
    tr = p.travel_rebound
    seat_w = np.array([1.0, -seat[0], seat[1]])
    seat_x = seat_w @ model.acc_x
    seat_u = seat_w @ model.acc_u
    seat_const = float(seat_w @ model.acc_const)
    G, W = model.G, model.W_damp
    G_road = np.hstack([model.R0, model.R1, G])  # per-run roads: [r_k; r_k+1] are inputs too
    matmul, add, multiply, maximum, minimum = np.matmul, np.add, np.multiply, np.maximum, np.minimum
    absolute, subtract = np.abs, np.subtract
    # views of each slot of the chunk buffer, made once
    s_in = [S[i, U0 : U0 + N_IN] for i in range(CHUNK_STEPS)]
    s_in_road = [S[i, : U0 + N_IN] for i in range(CHUNK_STEPS)]
    s_out = [S[i + 1, O0:] for i in range(CHUNK_STEPS)]
    views = []
    for i in range(CHUNK_STEPS):
        o = s_out[i]
        views.append(
            (
                o,
                o[O_V],
                o[O_STOPS],
                o[O_T1],
                o[O_T2],
                o[O_TY],
                S[i + 1, U0 : U0 + N_CORNERS],
                S[i + 1, U0 + N_CORNERS : O0],
            )
        )

    sum_az2 = np.zeros(B)
    sum_q2 = np.zeros(B)
    count = np.zeros(B)
    max_travel = np.zeros(B)
    lift = np.zeros(B)
    rec_X: list[FloatArray] = []
    rec_c: list[FloatArray] = []
    rec_s: list[FloatArray] = []
    rec_v: list[FloatArray] = []
    rec_r: list[FloatArray] = []
    cmd_chunk = np.empty((CHUNK_STEPS, N_CORNERS, B)) if record else None
    u_prev = np.zeros((N_INPUTS, B))
    shared_road = Bd == 1 and B > 1
    compiled = kernel_choice(kernel) == "numba" and (constant is not None or hasattr(controller, "kernel_arrays"))
    if compiled:
        W_c = np.ascontiguousarray(W)
        G_road_c = np.ascontiguousarray(G_road[None])
        if constant is None:
            modal_c, par_c, st_c = controller.kernel_arrays()  # type: ignore[attr-defined]
            rec_c_buf = cmd_chunk if cmd_chunk is not None else np.empty((1, N_CORNERS, B))
        else:
            const_c = np.ascontiguousarray(np.broadcast_to(constant, (N_CORNERS, B)), dtype=float)
        drive_arrays = tuple(np.ascontiguousarray(a, dtype=float) for a in (drive.t, drive.v, drive.s))
        road_tables = tuple(np.ascontiguousarray(a, dtype=float) for a in road._tables())
        s_buf = np.empty((CHUNK_STEPS + 1, Bd))
        r_buf = np.empty((CHUNK_STEPS + 1, N_CORNERS, Bd))
    k0 = 0
    while k0 < n_steps:
        n = min(CHUNK_STEPS, n_steps - k0)
        t = (k0 + np.arange(n + 1)) * dt
        if compiled:
            s_pos = s_buf[: n + 1]
            r = r_buf[: n + 1]
            drive_and_road(t, *drive_arrays, *road_tables, road.s0, 1.0 / road.ds, p.wheelbase, s_pos, r)
        else:
            s_pos = drive.position(t)  # (n+1, Bd)
            r = road_under_wheels(road, s_pos, p.wheelbase)  # (n+1, 4, Bd)
        if shared_road:
            # the road is the same for every run: fold it into the constant column of the step matrix
            pre1 = np.matmul(model.R0, r[:-1, :, 0].T) + np.matmul(model.R1, r[1:, :, 0].T)  # (35, n)
            Gs = np.repeat(G[None], n, axis=0)
            Gs[:, :, N_IN - 1] += pre1.T
        else:
            S[:n, :N_CORNERS] = r[:-1]
            S[:n, N_CORNERS:N_ROAD] = r[1:]
        if compiled:
            g_c = Gs if shared_road else G_road_c
            if constant is None:
                steps_controller_ii(
                    S, g_c, shared_road, n, W_c, kr, kc, k_bs, tr, modal_c, par_c, st_c, rec_c_buf, record
                )
            else:
                steps_constant(S, g_c, shared_road, n, W_c, kr, kc, k_bs, const_c)
                if cmd_chunk is not None:
                    cmd_chunk[:n] = const_c
        for i in range(0 if compiled else n):
            o, v, stops, t1, t2, ty, fs, ft = views[i]
            if shared_road:
                matmul(Gs[i], s_in[i], out=o)
            else:
                matmul(G_road, s_in_road[i], out=o)
            # damper basis [v, |v|, max(v - kr, 0), min(v + kc, 0)] -> -Phi_min, -dPhi
            basis[0] = v
            absolute(v, out=basis[1])
            subtract(v, kr, out=basis[2])
            maximum(basis[2], 0.0, out=basis[2])
            add(v, kc, out=basis[3])
            minimum(basis[3], 0.0, out=basis[3])
            matmul(W, basis2, out=pm)
            if constant is None:
                add(t1, tr, out=travel)
                c = controller.command(o[O_X], v, travel, o[O_A], phi_min, dphi)
            else:
                c = constant
            if cmd_chunk is not None:
                cmd_chunk[i] = c
            multiply(c, dphi, out=fs)
            add(fs, phi_min, out=fs)
            # bump stops (rare): a stiff spring beyond the free travel
            if stops.max() > 0.0:
                maximum(t1, 0.0, out=stop)
                subtract(fs, stop * k_bs, out=fs)
                maximum(t2, 0.0, out=stop)
                add(fs, stop * k_bs, out=fs)
            # a tyre cannot pull the wheel down: cancel its tension (input scaled by the tyre rate)
            maximum(ty, 0.0, out=ft)
        if compiled and not record:
            where = s_pos[:n] if dist_window is not None else t[:n, None]
            lo_w, hi_w = dist_window if dist_window is not None else (w_start, w_end)
            chunk_outputs(
                S, n, u_prev, seat_x, seat_u, seat_const, where, np.ascontiguousarray(lo_w),
                np.ascontiguousarray(hi_w), p.travel_rebound, p.travel_compression,
                sum_az2, sum_q2, count, max_travel, lift,
            )  # fmt: skip
            S[0] = S[n]
            k0 += n
            continue
        # outputs of the chunk: seat-rail vertical acceleration and pitch rate at t_k, k in chunk
        Xc = S[:n, XS]
        Uc = S[:n, U]
        # the forces held over [t_k, t_k+1] are mid-step values: at t_k use the mean of k-1 and k
        u_mid = np.empty((n, N_INPUTS, B))
        u_mid[0] = u_prev
        u_mid[1:] = Uc[:-1]
        u_mid += Uc
        u_mid *= 0.5
        u_prev = Uc[n - 1].copy()
        az = np.matmul(seat_x, Xc) + np.matmul(seat_u, u_mid) + seat_const  # (n, B)
        q = Xc[:, N_DOF + 1, :]
        tk = t[:n]
        if dist_window is not None:
            sk = s_pos[:n]
            mask = (sk >= dist_window[0][None, :Bd]) & (sk < dist_window[1][None, :Bd])
            if Bd != B:
                mask = np.broadcast_to(mask, (n, B))
        else:
            mask = (tk[:, None] >= w_start[None, :]) & (tk[:, None] < w_end[None, :])
        sum_az2 += np.einsum("nb,nb->b", az * mask, az)
        sum_q2 += np.einsum("nb,nb->b", q * mask, q)
        count += mask.sum(axis=0)
        stops = S[1 : n + 1, O0 + O_STOPS.start : O0 + O_STOPS.stop]  # travel beyond the stops, mid-step
        reach = np.maximum(
            stops[:, :N_CORNERS].max(axis=1) + p.travel_rebound, stops[:, N_CORNERS:].max(axis=1) + p.travel_compression
        )
        max_travel = np.maximum(max_travel, reach.max(axis=0))
        lift += (Uc[:, N_CORNERS:, :] > 0).any(axis=1).sum(axis=0)
        if record:
            assert cmd_chunk is not None
            rec_X.append(np.concatenate([Xc, u_mid], axis=1))
            rec_c.append(cmd_chunk[:n].copy())
            rec_s.append(s_pos[:n].copy())
            rec_v.append(drive.speed(tk))
            rec_r.append(r[:n].copy())
        S[0] = S[n]
        k0 += n

    recording = None
    if record:
        recording = Recording(
            t=np.arange(n_steps) * dt,
            s=np.concatenate(rec_s),
            v=np.concatenate(rec_v),
            X=np.concatenate(rec_X),
            command=np.concatenate(rec_c),
            road=np.concatenate(rec_r),
        )
    if dist_window is None and window is None:
        w_end = np.full(B, n_steps * dt)
    return BatchResult(sum_az2, sum_q2, count, w_start, w_end, max_travel, lift, recording)
