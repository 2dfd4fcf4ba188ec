"""The benchmark's problem families and its two splits, fixed before any default was tuned (issue 23).

A **family** is a calibration task; an **instance** is one member of it (a car drawn from the family's spread,
or a standard function shifted and rotated); a **campaign** is one optimizer run on one instance with one
seed. The splits:

* ``tuning``: instances 0-9 of every family, optimizer seeds 0 and 1 (20 campaigns per family). Defaults of
  the engine are chosen on this split only.
* ``held-out``: instances 100-109, seeds 1000 and 1001 (20 campaigns per family). Never used to choose
  anything; it is what the docs report as the engine's performance, beside the tuning figures.

Families (``FAMILIES``): the car families of :mod:`bac_sim.families` (``bump_c1``, ``road_c1``, ``bump_c2``,
``road_c2``: both controllers, Controller II through its meta-parameter file) and standard functions, each
instance shifted and rotated, with run-to-run noise of 1-3 % of (J_med − J*) drawn per instance:

* ``branin_sr``: Branin (three global minima), its domain rotated by up to ±30° about the box centre and
  shifted by up to ±15 % of the range, evaluated on the unit square;
* ``bowl_sr``: a smooth anisotropic bowl, ``√(1 + |A (u − m)|²)``, its minimum ``m`` anywhere in the box,
  near a face or a corner in half of the instances (the outside check of issue 23: a minimum at (0.92, 0.08));
* ``hartmann3_sr``: Hartmann-3 (d = 3), rotated by up to ±20° and shifted by up to ±10 %.

Each instance's reference values (``J*``, its location, ``J_med``, and for the car families the optimum
under the travel limit of :data:`TRAVEL_LIMIT_MM`) are computed once and cached in ``bench/data/
family_truth.json`` (``python bench/problem_families.py --truth``): a 41 × 41 grid of the unit square (21³
for d = 3) refined twice by 11 × 11 local grids (J*), and 1024 Sobol points (J_med); the car families by
batches of noise-free simulation.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import qmc

FloatArray = np.ndarray

SPLITS: dict[str, dict[str, list[int]]] = {
    "tuning": {"instances": list(range(10)), "seeds": [0, 1]},
    "held-out": {"instances": list(range(100, 110)), "seeds": [1000, 1001]},
}
CAR_FAMILIES = ("bump_c1", "road_c1", "bump_c2", "road_c2")
FUNCTION_FAMILIES = ("branin_sr", "bowl_sr", "hartmann3_sr")
FAMILIES = CAR_FAMILIES + FUNCTION_FAMILIES
BUDGETS = {"hartmann3_sr": 30}
DEFAULT_BUDGET = 20
TRUTH_PATH = Path(__file__).resolve().parent / "data" / "family_truth.json"
# the constraint of the constrained benchmark: the suspension travel from static stays below this (the bump stops
# sit at 75 mm in compression): on many bump instances the unconstrained optimum (soft dampers) goes past it
TRAVEL_LIMIT_MM = 60.0


def _seed(*parts: object) -> int:
    h = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(h[:8], "little")


# --- standard functions ---------------------------------------------------------------------------
def _branin(t: FloatArray) -> FloatArray:
    x1, x2 = t[:, 0], t[:, 1]
    b, c, r, s, tt = 5.1 / (4 * math.pi**2), 5 / math.pi, 6.0, 10.0, 1 / (8 * math.pi)
    return (x2 - b * x1**2 + c * x1 - r) ** 2 + s * (1 - tt) * np.cos(x1) + s


_H3_A = np.array([[3.0, 10, 30], [0.1, 10, 35], [3.0, 10, 30], [0.1, 10, 35]])
_H3_P = 1e-4 * np.array([[3689, 1170, 2673], [4699, 4387, 7470], [1091, 8732, 5547], [381, 5743, 8828]])
_H3_ALPHA = np.array([1.0, 1.2, 3.0, 3.2])


def _hartmann3(t: FloatArray) -> FloatArray:
    inner = np.sum(_H3_A[None] * (t[:, None, :] - _H3_P[None]) ** 2, axis=2)
    return -np.sum(_H3_ALPHA * np.exp(-inner), axis=1)


def _rotation(d: int, rng: np.random.Generator, max_deg: float) -> FloatArray:
    """A rotation by angles up to ``max_deg`` in each coordinate plane (composed Givens rotations)."""
    R = np.eye(d)
    for i in range(d):
        for j in range(i + 1, d):
            a = math.radians(float(rng.uniform(-max_deg, max_deg)))
            G = np.eye(d)
            G[i, i] = G[j, j] = math.cos(a)
            G[i, j], G[j, i] = -math.sin(a), math.sin(a)
            R = G @ R
    return R


@dataclass(frozen=True)
class FunctionInstance:
    """A standard function on the unit cube, shifted and rotated, with multiplicative-free additive noise."""

    family: str
    index: int
    f: Callable[[FloatArray], FloatArray]  # on the unit cube
    dim: int
    noise_share: float  # noise sd / (J_med - J*)
    describe: dict[str, Any] = field(default_factory=dict)
    truth: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.family}#{self.index}"

    @property
    def bounds(self) -> FloatArray:
        return np.array([[0.0, 1.0]] * self.dim)

    def true_j(self, thetas: FloatArray) -> FloatArray:
        return np.asarray(self.f(np.atleast_2d(np.asarray(thetas, dtype=float))), dtype=float)

    def noisy(self, thetas: FloatArray, rng: np.random.Generator) -> dict[str, FloatArray]:
        j = self.true_j(thetas)
        sd = self.noise_share * (self.truth["j_med"] - self.truth["j_star"]) if self.truth else 0.0
        return {"j": j + sd * rng.standard_normal(j.shape[0])}


def function_instance(family: str, index: int) -> FunctionInstance:
    rng = np.random.default_rng(_seed("bench.problem_families", family, index))
    noise = float(rng.uniform(0.01, 0.03))
    if family == "branin_sr":
        lo, hi = np.array([-5.0, 0.0]), np.array([10.0, 15.0])
        R = _rotation(2, rng, 30.0)
        shift = rng.uniform(-0.15, 0.15, 2)

        def f(u: FloatArray) -> FloatArray:
            v = 0.5 + (u - 0.5) @ R.T + shift
            return _branin(lo + v * (hi - lo))

        return FunctionInstance(family, index, f, 2, noise, {"shift": shift.round(3).tolist()})
    if family == "bowl_sr":
        near_edge = bool(rng.random() < 0.5)
        m = rng.uniform(0.0, 1.0, 2)
        if near_edge:  # one or both coordinates within 10 % of a face
            k = int(rng.integers(0, 3))  # 0: first coordinate, 1: second, 2: both
            for i in ([0], [1], [0, 1])[k]:
                m[i] = rng.uniform(0.0, 0.1) if rng.random() < 0.5 else rng.uniform(0.9, 1.0)
        R = _rotation(2, rng, 90.0)
        scales = np.array([float(rng.uniform(2.0, 6.0)), float(rng.uniform(2.0, 6.0))])
        A = np.diag(scales) @ R

        def f(u: FloatArray) -> FloatArray:
            z = (u - m) @ A.T
            return np.sqrt(1.0 + np.sum(z * z, axis=1))

        return FunctionInstance(family, index, f, 2, noise, {"minimum": m.round(3).tolist()})
    if family == "hartmann3_sr":
        R = _rotation(3, rng, 20.0)
        shift = rng.uniform(-0.1, 0.1, 3)

        def f(u: FloatArray) -> FloatArray:
            return _hartmann3(np.clip(0.5 + (u - 0.5) @ R.T + shift, -0.5, 1.5))

        return FunctionInstance(family, index, f, 3, noise, {"shift": shift.round(3).tolist()})
    raise ValueError(f"unknown function family {family!r}; known: {', '.join(FUNCTION_FAMILIES)}")


# --- instances of any family ---------------------------------------------------------------------------
def instance(family: str, index: int, grid: int = 0) -> Any:
    """A car instance (bac_sim.families.CarInstance; with ``grid``, its GridInstance stand-in) or a
    FunctionInstance, with its cached truth if any."""
    if family in CAR_FAMILIES:
        from bac_sim.families import get_family

        inst = get_family(family).instance(index)
        return GridInstance(inst, grid) if grid else inst
    inst = function_instance(family, index)
    truth = load_truth().get(f"{family}#{index}")
    return FunctionInstance(inst.family, inst.index, inst.f, inst.dim, inst.noise_share, inst.describe, truth or {})


def budget_of(family: str) -> int:
    return BUDGETS.get(family, DEFAULT_BUDGET)


def unit_fn(inst: Any, what: str = "j") -> Callable[[FloatArray], FloatArray]:
    """J (or an outcome) of an instance on the unit cube."""
    b = np.asarray(inst.bounds, dtype=float)
    if hasattr(inst, "evaluate"):
        return lambda U: inst.evaluate(b[:, 0] + np.asarray(U) * (b[:, 1] - b[:, 0]))[what]
    return lambda U: inst.true_j(np.asarray(U))


def _grid(n: int, d: int) -> FloatArray:
    g = np.linspace(0.0, 1.0, n)
    return np.array(np.meshgrid(*([g] * d), indexing="ij")).reshape(d, -1).T


def compute_truth(inst: Any, travel_limit: float | None = TRAVEL_LIMIT_MM) -> dict[str, Any]:
    """J*, its location (unit cube and user units), J_med; for cars the optimum under the travel limit."""
    d = int(inst.bounds.shape[0])
    n = 41 if d == 2 else 21
    U = _grid(n, d)
    b = np.asarray(inst.bounds, dtype=float)
    if hasattr(inst, "evaluate"):
        out = inst.evaluate(b[:, 0] + U * (b[:, 1] - b[:, 0]))
        j, travel = out["j"], out["max_travel_mm"]
    else:
        j, travel = inst.true_j(U), None
    best_u, best_j = U[int(np.argmin(j))], float(np.min(j))
    step = 1.0 / (n - 1)
    for half in (step, step / 5):
        L = np.clip(best_u + (_grid(11, d) - 0.5) * 2 * half, 0.0, 1.0)
        jl = inst.evaluate(b[:, 0] + L * (b[:, 1] - b[:, 0]))["j"] if hasattr(inst, "evaluate") else inst.true_j(L)
        if float(np.min(jl)) < best_j:
            best_j, best_u = float(np.min(jl)), L[int(np.argmin(jl))]
    S = qmc.Sobol(d, scramble=True, seed=20240).random(1024)
    js = inst.evaluate(b[:, 0] + S * (b[:, 1] - b[:, 0]))["j"] if hasattr(inst, "evaluate") else inst.true_j(S)
    truth: dict[str, Any] = {
        "j_star": best_j,
        "u_star": [float(v) for v in best_u],
        "theta_star": [float(v) for v in b[:, 0] + best_u * (b[:, 1] - b[:, 0])],
        "j_med": float(np.median(js)),
        "describe": dict(getattr(inst, "describe", {})),
    }
    if travel is not None and travel_limit is not None:
        ok = travel <= travel_limit
        truth["travel_at_star_mm"] = float(
            inst.evaluate(b[:, 0] + best_u[None, :] * (b[:, 1] - b[:, 0]))["max_travel_mm"][0]
        )
        truth["travel_limit_mm"] = travel_limit
        truth["feasible_share"] = float(np.mean(ok))
        if np.any(ok):
            k = int(np.argmin(np.where(ok, j, np.inf)))
            truth["j_star_constrained"] = float(j[k])
            truth["u_star_constrained"] = [float(v) for v in U[k]]
        else:
            truth["j_star_constrained"] = math.nan
    return truth


GRID_DIR = Path(__file__).resolve().parent / "out" / "grids"


class GridInstance:
    """A car instance's J and travel on a grid of its unit square, interpolated (bicubic): a quick stand-in for
    the simulator when defaults are explored on the tuning split (``bo_efficiency.py --grid-truth N``). The
    figures the docs report come from the simulator itself."""

    def __init__(self, inst: Any, n: int) -> None:
        from scipy.interpolate import RectBivariateSpline

        self.inst = inst
        self.bounds = np.asarray(inst.bounds, dtype=float)
        self.noise_rel = float(inst.noise_rel)
        self.describe = dict(inst.describe)
        path = GRID_DIR / f"{inst.family}_{inst.index}_{n}.npz"
        if path.is_file():
            data = np.load(path)
            J, T = data["j"], data["travel"]
        else:
            U = _grid(n, 2)
            out = inst.evaluate(self.bounds[:, 0] + U * (self.bounds[:, 1] - self.bounds[:, 0]))
            J, T = out["j"].reshape(n, n), out["max_travel_mm"].reshape(n, n)
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, j=J, travel=T)
        g = np.linspace(0.0, 1.0, n)
        self._j = RectBivariateSpline(g, g, J, kx=3, ky=3)
        self._t = RectBivariateSpline(g, g, T, kx=3, ky=3)

    def _unit(self, thetas: FloatArray) -> FloatArray:
        th = np.atleast_2d(np.asarray(thetas, dtype=float))
        return np.clip((th - self.bounds[:, 0]) / (self.bounds[:, 1] - self.bounds[:, 0]), 0.0, 1.0)

    def evaluate(self, thetas: FloatArray) -> dict[str, FloatArray]:
        U = self._unit(thetas)
        return {
            "j": np.asarray(self._j.ev(U[:, 0], U[:, 1]), dtype=float),
            "max_travel_mm": np.asarray(self._t.ev(U[:, 0], U[:, 1]), dtype=float),
        }

    def true_j(self, thetas: FloatArray) -> FloatArray:
        return self.evaluate(thetas)["j"]

    def noisy(self, thetas: FloatArray, rng: np.random.Generator) -> dict[str, FloatArray]:
        from bac_sim.families import with_run_noise

        return with_run_noise(self.evaluate(thetas), self.noise_rel, rng)


def load_truth(path: Path = TRUTH_PATH) -> dict[str, Any]:
    if not path.is_file():
        return {}
    return dict(json.loads(path.read_text()).get("instances", {}))


def truth_of(family: str, index: int) -> dict[str, Any]:
    t = load_truth().get(f"{family}#{index}")
    if t is None:
        raise SystemExit(
            f"no cached truth for {family}#{index} in {TRUTH_PATH}: run `python bench/problem_families.py --truth`"
        )
    return dict(t)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--truth", action="store_true", help="compute the missing reference values and cache them")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--splits", default="tuning,held-out")
    ap.add_argument("--redo", action="store_true", help="recompute cached instances too")
    a = ap.parse_args(argv)
    data = json.loads(TRUTH_PATH.read_text()) if TRUTH_PATH.is_file() else {"instances": {}}
    inst_truth = data.setdefault("instances", {})
    fams = [f for f in a.families.split(",") if f]
    for split in a.splits.split(","):
        for fam in fams:
            for i in SPLITS[split]["instances"]:
                key = f"{fam}#{i}"
                if key in inst_truth and not a.redo:
                    continue
                if not a.truth:
                    print(f"{key}: not cached")
                    continue
                t0 = time.perf_counter()
                inst = instance(fam, i)
                inst_truth[key] = compute_truth(inst)
                inst_truth[key]["seconds"] = round(time.perf_counter() - t0, 1)
                t = inst_truth[key]
                print(
                    f"{split:>8} {key:<16} J*={t['j_star']:.4g} at {np.round(t['u_star'], 3).tolist()} "
                    f"J_med={t['j_med']:.4g}"
                    + (
                        f" travel {t['travel_at_star_mm']:.0f} mm, feasible {100 * t['feasible_share']:.0f} %"
                        if "travel_at_star_mm" in t
                        else ""
                    )
                    + f" ({t['seconds']} s)",
                    flush=True,
                )
                TRUTH_PATH.parent.mkdir(parents=True, exist_ok=True)
                data["generated_by"] = "python bench/problem_families.py --truth"
                TRUTH_PATH.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
