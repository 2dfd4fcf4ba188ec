"""The integrator's inner step loop compiled by numba: one call per chunk of steps instead of ~40 numpy calls
per step.

:func:`bac_sim.engine.simulate` keeps its pure-numpy loop as the reference (``kernel="numpy"``); this
module runs the same arithmetic, in the same order, over a whole chunk of steps:

* the step product ``G @ [r_k; r_k+1; u_k; x_k; 1]`` is the same BLAS call (``np.dot`` into the next slot
  of the chunk buffer);
* the damper forces, the bump stops, the tyre leaving the road and Controller II's logic are fused
  into loops over the corners and the runs (no temporaries, no Python between the steps).

Both paths give the same J to about 1e-12 (relative); the small differences come from the order of
floating-point sums in the 2 x 4 damper-basis product and Controller II's 4 x 3 modal product
(``src/bac_sim/test/test_kernels.py`` checks the tolerance on every scenario and controller).
Where numba is missing, or ``BAC_SIM_KERNEL=numpy``, the engine uses the numpy loop.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

FloatArray = np.ndarray[Any, Any]

try:  # numba is a runtime dependency; the numpy loop stays the reference and the fallback
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is installed with bac_sim
    numba = None  # type: ignore[assignment]
    HAVE_NUMBA = False

KERNELS = ("auto", "numba", "numpy")


def kernel_choice(kernel: str = "auto") -> str:
    """``numba`` or ``numpy``: ``auto`` = numba when it is installed, unless ``BAC_SIM_KERNEL=numpy``."""
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if kernel == "auto":
        kernel = os.environ.get("BAC_SIM_KERNEL", "").strip().lower() or "numba"
        if kernel not in KERNELS[1:]:
            kernel = "numba"
    if kernel == "numba" and not HAVE_NUMBA:
        return "numpy"
    return kernel


def _jit(fn: Any) -> Any:
    if not HAVE_NUMBA:  # pragma: no cover
        return fn
    return numba.njit(cache=True, nogil=True, boundscheck=False)(fn)


# rows of the chunk buffer S[k] (see bac_sim.engine): road (8), u (8), then the product's 35 rows
_U0 = 8
_O0 = 16
_O_V = _O0 + 15
_O_T1 = _O0 + 19
_O_T2 = _O0 + 23
_O_TY = _O0 + 27
_O_A = _O0 + 31
_X_W = _O0 + 7  # body velocities (heave, pitch, roll) in the state
_X_WHEEL = _O0 + 10  # wheel velocities


@_jit
def _forces(nxt: FloatArray, c: int, b: int, cmd: float, W: FloatArray, kr: float, kc: float, kbs: float) -> None:
    """Corner c of run b (``nxt`` = the next slot of the chunk buffer): damper force at command ``cmd``, bump
    stops, tyre tension."""
    v = nxt[_O_V + c, b]
    b1 = abs(v)
    b2 = max(v - kr, 0.0)
    b3 = min(v + kc, 0.0)
    pmin = W[0, 0] * v + W[0, 1] * b1 + W[0, 2] * b2 + W[0, 3] * b3
    dphi = W[1, 0] * v + W[1, 1] * b1 + W[1, 2] * b2 + W[1, 3] * b3
    fs = cmd * dphi + pmin
    fs -= max(nxt[_O_T1 + c, b], 0.0) * kbs
    fs += max(nxt[_O_T2 + c, b], 0.0) * kbs
    nxt[_U0 + c, b] = fs
    nxt[_U0 + 4 + c, b] = max(nxt[_O_TY + c, b], 0.0)


@_jit
def steps_constant(
    S: FloatArray,
    Gs: FloatArray,
    shared: bool,
    n: int,
    W: FloatArray,
    kr: float,
    kc: float,
    kbs: float,
    command: FloatArray,
) -> None:
    """``n`` steps of a chunk with a constant command (4, B) (Controller I)."""
    B = S.shape[2]
    n_in = Gs.shape[2]
    lo = 31 - n_in  # the product reads [u; x; 1] (rows 8..30) or [r_k; r_k+1; u; x; 1] (rows 0..30)
    for i in range(n):
        g = Gs[i] if shared else Gs[0]
        np.dot(g, S[i, lo : lo + n_in], S[i + 1, _O0:])
        nxt = S[i + 1]
        for c in range(4):
            for b in range(B):
                _forces(nxt, c, b, command[c, b], W, kr, kc, kbs)


@_jit
def steps_controller_ii(
    S: FloatArray,
    Gs: FloatArray,
    shared: bool,
    n: int,
    W: FloatArray,
    kr: float,
    kc: float,
    kbs: float,
    tr: float,
    modal: FloatArray,
    par: FloatArray,
    st: FloatArray,
    cmd_out: FloatArray,
    record: bool,
) -> None:
    """``n`` steps of a chunk with Controller II (the arithmetic of ``ControllerII.command``).

    ``par`` (21, B): gain (4), floor (4), cap, a_hp, a_v, a_cmd, a_add, deadband, end-stop threshold,
    a_act, modal weights (3: heave, pitch, roll), groundhook gain, ADD mass; ``st`` (22, B): w_prev (3),
    hp (3), v_f (4), acc_f (4), cmd_f (4), c_act (4), updated in place (see
    :meth:`bac_sim.controllers.ControllerII.kernel_arrays`).
    """
    B = S.shape[2]
    n_in = Gs.shape[2]
    lo = 31 - n_in
    w3 = np.empty(3)
    for i in range(n):
        g = Gs[i] if shared else Gs[0]
        np.dot(g, S[i, lo : lo + n_in], S[i + 1, _O0:])
        nxt = S[i + 1]
        for b in range(B):
            a_hp = par[9, b]
            # leaky integration of the accelerometers == first-order high-pass of the body velocities
            for k in range(3):
                w = nxt[_X_W + k, b]
                h = st[3 + k, b] + w
                h -= st[k, b]
                h *= a_hp
                st[3 + k, b] = h
                st[k, b] = w
                w3[k] = par[16 + k, b] * h
            a_v = par[10, b]
            a_cmd = par[11, b]
            a_add = par[12, b]
            db = par[13, b]
            gh = par[19, b]
            add = par[20, b]
            endstop = par[14, b]
            a_act = par[15, b]
            cap = par[8, b]
            for c in range(4):
                zs = modal[c, 0] * w3[0] + modal[c, 1] * w3[1] + modal[c, 2] * w3[2]
                zs -= min(max(zs, -db), db)
                v = nxt[_O_V + c, b]
                vf = st[6 + c, b]
                vf += (v - vf) * a_v
                st[6 + c, b] = vf
                af = st[10 + c, b]
                af += (nxt[_O_A + c, b] - af) * a_add
                st[10 + c, b] = af
                b1 = abs(v)
                b2 = max(v - kr, 0.0)
                b3 = min(v + kc, 0.0)
                pmin = W[0, 0] * v + W[0, 1] * b1 + W[0, 2] * b2 + W[0, 3] * b3
                dphi = W[1, 0] * v + W[1, 1] * b1 + W[1, 2] * b2 + W[1, 3] * b3
                cmd = gh * nxt[_X_WHEEL + c, b]
                cmd -= par[c, b] * zs
                cmd -= add * af
                cmd -= pmin
                cmd *= dphi
                cmd /= dphi * dphi + 25.0
                if not vf * v >= 0.0:
                    cmd *= 0.0
                cmd = max(cmd, par[4 + c, b])
                cmd = min(cmd, cap)
                if abs(nxt[_O_T1 + c, b] + tr) > endstop:
                    cmd = max(cmd, 1.0)
                cf = st[14 + c, b]
                cf += (cmd - cf) * a_cmd
                st[14 + c, b] = cf
                ca = st[18 + c, b]
                ca += (cf - ca) * a_act
                st[18 + c, b] = ca
                if record:
                    cmd_out[i, c, b] = ca
                fs = ca * dphi + pmin
                fs -= max(nxt[_O_T1 + c, b], 0.0) * kbs
                fs += max(nxt[_O_T2 + c, b], 0.0) * kbs
                nxt[_U0 + c, b] = fs
                nxt[_U0 + 4 + c, b] = max(nxt[_O_TY + c, b], 0.0)


@_jit
def drive_and_road(
    t: FloatArray,
    knot_t: FloatArray,
    knot_v: FloatArray,
    knot_s: FloatArray,
    left: FloatArray,
    right: FloatArray,
    dleft: FloatArray,
    dright: FloatArray,
    s0: float,
    inv_ds: float,
    wheelbase: float,
    s_out: FloatArray,
    r_out: FloatArray,
) -> None:
    """Front-axle positions ``s_out`` (n, Bd) at times ``t`` (n,) of a drive (``Drive.position``) and the road
    heights ``r_out`` (n, 4, Bd) under FL, FR, RL, RR (``engine.road_under_wheels``), the same arithmetic."""
    n = t.size
    bd = knot_v.shape[1]
    last = knot_t.size - 2
    top = left.size - 2
    for k in range(n):
        tk = t[k]
        j = np.searchsorted(knot_t, tk, side="right") - 1
        j = min(max(j, 0), last)
        tau = tk - knot_t[j]
        h = knot_t[j + 1] - knot_t[j]
        for b in range(bd):
            v0 = knot_v[j, b]
            acc = (knot_v[j + 1, b] - v0) / h
            s = knot_s[j, b] + v0 * tau + 0.5 * acc * tau * tau
            s_out[k, b] = s
            for axle in range(2):
                u = (s - wheelbase * axle if axle else s) - s0
                u *= inv_ds
                i = min(int(u), top)
                u -= i
                r_out[k, 2 * axle, b] = left[i] + u * dleft[i]
                r_out[k, 2 * axle + 1, b] = right[i] + u * dright[i]


@_jit
def chunk_outputs(
    S: FloatArray,
    n: int,
    u_prev: FloatArray,
    seat_x: FloatArray,
    seat_u: FloatArray,
    seat_const: float,
    where: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    travel_rebound: float,
    travel_compression: float,
    sum_az2: FloatArray,
    sum_q2: FloatArray,
    count: FloatArray,
    max_travel: FloatArray,
    lift: FloatArray,
) -> None:
    """The KPI parts of a chunk (what ``engine.simulate`` computes with numpy after the steps): seat-rail vertical
    acceleration and pitch rate at t_k of the samples inside each run's window (``lo <= where < hi``, ``where``
    (n, 1 or B): times or front-axle positions), the largest travel and the steps with a wheel off the ground.
    ``u_prev`` (8, B): the forces of the step before the chunk, replaced by the chunk's last ones."""
    B = S.shape[2]
    shared = where.shape[1] == 1
    az = np.empty(B)
    for i in range(n):
        cur = S[i]
        prev = u_prev if i == 0 else S[i - 1, 8:16]
        nxt = S[i + 1]
        for b in range(B):
            az[b] = seat_const
        for r in range(14):
            g = seat_x[r]
            row = cur[16 + r]
            for b in range(B):
                az[b] += g * row[b]
        for r in range(8):
            g = 0.5 * seat_u[r]
            row = cur[8 + r]
            prow = prev[r]
            for b in range(B):
                az[b] += g * (prow[b] + row[b])
        q = cur[24]
        for b in range(B):
            w = where[i, 0] if shared else where[i, b]
            inside = 1.0 if (w >= lo[b] and w < hi[b]) else 0.0
            a = az[b]
            sum_az2[b] += inside * (a * a)
            sum_q2[b] += inside * (q[b] * q[b])
            count[b] += inside
            reach = max_travel[b]
            for c in range(4):
                reach = max(reach, nxt[35 + c, b] + travel_rebound)
                reach = max(reach, nxt[39 + c, b] + travel_compression)
            max_travel[b] = reach
            off = cur[12, b] > 0.0 or cur[13, b] > 0.0 or cur[14, b] > 0.0 or cur[15, b] > 0.0
            if off:
                lift[b] += 1.0
    for r in range(8):
        for b in range(B):
            u_prev[r, b] = S[n - 1, 8 + r, b]
