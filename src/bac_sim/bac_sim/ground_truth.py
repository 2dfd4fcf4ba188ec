"""Ground truth of the batch problems: ``bac ground-truth`` regenerates ``bac_sim/data/ground_truth.json``.

* ``bump_c1``, ``road_c1`` (Controller I): J on a dense 51 x 51 grid of [0, 1]^2 (the paper's
  exhaustive search, finer), then two local grids of 11 x 11 around the best point (spacing 0.004,
  then 0.0008): ``j_star`` / ``theta_star`` are the best of those, the grid is stored for plots.
* ``road_c2``, ``road_c2b`` (Controller II and II-B, 20 parameters): the best value found by a heavy search
  on the noise-free simulator: 1024 Sobol points, then CMA-ES (the ``cma`` library) restarted 8 times (from
  the best Sobol point, the stored best and random points; at most 4000 runs each, population 24, four
  restarts in lock-step so that their populations are simulated as one batch), then sweeps of batched
  coordinate search; about 35 000 noise-free runs, stored as the best *known* value with every restart's
  result (how far apart the restarts end says how rugged the problem is), not a proven optimum.
* ``j_med``: median of J over uniformly random calibrations (Sobol, 1024 points).
* ``noise_rel``: std / mean of ``noisy_j`` over 64 runs at ``theta_star``.

Everything is seeded; the command takes about a quarter of an hour on two cores (most of it the CMA-ES).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.stats import qmc

from bac_common.console import say
from bac_sim.problems import GROUND_TRUTH_PATH, PROBLEM_NAMES, Problem, get_problem

FloatArray = np.ndarray[Any, Any]
SEED = 20240


def _grid(lo: FloatArray, hi: FloatArray, n: int) -> tuple[FloatArray, FloatArray]:
    a = np.linspace(lo[0], hi[0], n)
    b = np.linspace(lo[1], hi[1], n)
    A, Bm = np.meshgrid(a, b, indexing="ij")
    return np.column_stack([A.ravel(), Bm.ravel()]), np.vstack([a, b])


def controller_i_truth(p: Problem, n: int = 51, log: Any = print) -> dict[str, Any]:
    bounds = p.bounds
    pts, axes = _grid(bounds[:, 0], bounds[:, 1], n)
    t0 = time.perf_counter()
    j = p.true_j(pts)
    log(f"{p.name}: {n}x{n} grid in {time.perf_counter() - t0:.1f} s, best {j.min():.5f}")
    best = pts[int(np.argmin(j))]
    best_j = float(j.min())
    for half in (0.02, 0.004):
        lo = np.maximum(best - half, bounds[:, 0])
        hi = np.minimum(best + half, bounds[:, 1])
        local, _ = _grid(lo, hi, 11)
        jl = p.true_j(local)
        if jl.min() < best_j:
            best_j = float(jl.min())
            best = local[int(np.argmin(jl))]
        log(f"{p.name}: local grid +-{half}: best {best_j:.6f} at {np.round(best, 4).tolist()}")
    sob = qmc.Sobol(p.dim, seed=SEED).random(1024)
    rand = bounds[:, 0] + sob * (bounds[:, 1] - bounds[:, 0])
    j_med = float(np.median(p.true_j(rand)))
    return {
        "j_star": best_j,
        "theta_star": [float(x) for x in best],
        "j_med": j_med,
        "method": f"{n}x{n} grid of the bounds, then 11x11 local grids of half-width 0.02 and 0.004",
        "grid": {"axes": axes.tolist(), "j": j.reshape(n, n).round(6).tolist()},
    }


def controller_ii_truth(
    p: Problem,
    restarts: int = 8,
    evals_per_restart: int = 4000,
    popsize: int = 24,
    concurrent: int = 4,
    polish_sweeps: int = 12,
    start: Any = None,
    log: Any = print,
) -> dict[str, Any]:
    """Best known J of a 20-parameter problem: CMA-ES with restarts on the noise-free simulator, then a batched
    coordinate polish; ``start`` = a stored result to polish only (no Sobol points, no CMA-ES)."""
    rng = np.random.default_rng(SEED)
    runs: list[dict[str, Any]] = []
    if start is not None:
        best = np.asarray(start["theta_star"], dtype=float)
        best_j = float(p.true_j(best[None])[0])
        j_med = float(start["j_med"])
        evaluations = int(start.get("evaluations", 0))
        runs = list(start.get("restarts", []))
        log(f"{p.name}: polishing the stored result {best_j:.5f}")
        method_head = str(start.get("method", "")).split("; then")[0]
    else:
        best, best_j, j_med, evaluations, runs = _sobol_and_cma(
            p, rng, restarts, evals_per_restart, popsize, concurrent, log
        )
        method_head = (
            f"best known: 1024 Sobol points, then CMA-ES (the cma library, {restarts} restarts of at most "
            f"{evals_per_restart} noise-free runs, population {popsize}, {concurrent} at a time in one batch; "
            "starts: the best Sobol point, the stored best, random points)"
        )
    best, best_j, sweeps, evaluations = _polish(p, best, best_j, polish_sweeps, evaluations, log)
    finals = sorted(float(r["j_best"]) for r in runs)
    return {
        "j_star": best_j,
        "theta_star": [float(x) for x in best],
        "j_med": j_med,
        "evaluations": evaluations,
        "restarts": runs,
        "method": (
            f"{method_head}; then {sweeps} sweeps of batched coordinate search ({evaluations} noise-free runs in all); "
            f"the restarts ended at {', '.join(f'{j:.4f}' for j in finals)}; not a proven optimum"
        ),
    }


def _sobol_and_cma(
    p: Problem,
    rng: np.random.Generator,
    restarts: int,
    evals_per_restart: int,
    popsize: int,
    concurrent: int,
    log: Any,
) -> tuple[FloatArray, float, float, int, list[dict[str, Any]]]:
    """1024 Sobol points (J_med, a start), then CMA-ES restarts in the unit cube, ``concurrent`` of them in
    lock-step so that their populations are simulated as one batch (split over the cores)."""
    import cma

    lo, hi = p.bounds[:, 0], p.bounds[:, 1]
    width = hi - lo
    sob = qmc.Sobol(p.dim, seed=SEED).random(1024)
    t0 = time.perf_counter()
    j = p.true_j(lo + sob * width)
    log(
        f"{p.name}: 1024 Sobol points in {time.perf_counter() - t0:.1f} s, "
        f"best {j.min():.5f}, median {np.median(j):.5f}"
    )
    j_med = float(np.median(j))
    best_u, best_j = sob[int(np.argmin(j))].copy(), float(j.min())
    evaluations = 1024
    starts: list[tuple[str, FloatArray]] = [("best Sobol point", best_u.copy())]
    stored = p.truth.get("theta_star")
    if stored is not None and len(stored) == p.dim:
        starts.append(("stored best", (np.asarray(stored, dtype=float) - lo) / width))
    while len(starts) < restarts:
        starts.append(("random point", rng.random(p.dim)))
    starts = starts[:restarts]
    runs: list[dict[str, Any]] = []
    queue = list(enumerate(starts))
    active: list[tuple[int, str, Any, list[int]]] = []
    opts = {"bounds": [0.0, 1.0], "popsize": popsize, "verbose": -9, "maxfevals": evals_per_restart, "tolfun": 1e-7}
    while queue or active:
        while queue and len(active) < concurrent:
            k, (what, x0) = queue.pop(0)
            es = cma.CMAEvolutionStrategy(np.clip(x0, 0.0, 1.0), 0.3, {**opts, "seed": SEED + k})
            active.append((k, what, es, [0]))
        asks = [np.clip(np.asarray(es.ask()), 0.0, 1.0) for _, _, es, _ in active]
        jj = p.true_j(lo + np.vstack(asks) * width)
        evaluations += int(jj.size)
        pos = 0
        still = []
        for (k, what, es, count), X in zip(active, asks, strict=True):
            f = jj[pos : pos + len(X)]
            pos += len(X)
            es.tell(list(X), f.tolist())
            count[0] += len(X)
            if float(f.min()) < best_j:
                best_j, best_u = float(f.min()), X[int(np.argmin(f))].copy()
            if es.stop():
                jb = float(es.result.fbest)
                runs.append({"start": what, "evaluations": count[0], "j_best": jb, "stop": sorted(es.stop())})
                log(f"{p.name}: CMA-ES restart {k + 1}/{len(starts)} from the {what}: {jb:.5f} after {count[0]} runs")
            else:
                still.append((k, what, es, count))
        active = still
    return lo + best_u * width, best_j, j_med, evaluations, runs


def _polish(
    p: Problem, best: FloatArray, best_j: float, polish_sweeps: int, evaluations: int, log: Any
) -> tuple[FloatArray, float, int, int]:
    """Batched coordinate search: every parameter on 11 values around the incumbent at once."""
    lo, hi = p.bounds[:, 0], p.bounds[:, 1]
    width = hi - lo
    span = 0.25 * width
    sweeps = 0
    while sweeps < polish_sweeps and np.max(span / width) > 0.002:
        sweeps += 1
        rows = []
        for i in range(p.dim):
            for v in np.clip(best[i] + span[i] * np.linspace(-1, 1, 11), lo[i], hi[i]):
                r = best.copy()
                r[i] = v
                rows.append(r)
        cand = np.array(rows)
        jc = p.true_j(cand)
        evaluations += len(rows)
        per = jc.reshape(p.dim, 11)
        gains = best_j - per.min(axis=1)
        improved = False
        # take every improving coordinate move, best first, keeping each only if the combination still improves
        for i in np.argsort(-gains):
            if gains[i] <= 1e-9:
                break
            trial = best.copy()
            trial[i] = cand[i * 11 + int(np.argmin(per[i])), i]
            jt = float(p.true_j(trial[None])[0])
            evaluations += 1
            if jt < best_j - 1e-9:
                best, best_j, improved = trial, jt, True
        if not improved:
            span = span / 2
        log(f"{p.name}: polish sweep {sweeps}: best {best_j:.5f}, span {np.max(span / width):.3f}")
    best = np.round(best, 2)
    return best, float(p.true_j(best[None])[0]), sweeps, evaluations


def noise_figure(p: Problem, theta: FloatArray, runs: int = 64) -> float:
    j = p.noisy_j(np.repeat(np.atleast_2d(theta), runs, axis=0), np.random.default_rng(SEED + 1))
    return float(np.std(j) / np.mean(j))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bac ground-truth", description=__doc__.splitlines()[0])
    ap.add_argument("--problems", nargs="*", default=list(PROBLEM_NAMES), choices=PROBLEM_NAMES)
    ap.add_argument("--output", default=str(GROUND_TRUTH_PATH), help="JSON file to (re)write")
    ap.add_argument("--grid", type=int, default=51, help="grid points per axis for Controller I")
    ap.add_argument("--restarts", type=int, default=8, help="CMA-ES restarts for the 20-parameter problems")
    ap.add_argument("--evals", type=int, default=4000, help="noise-free runs per CMA-ES restart at most")
    ap.add_argument(
        "--polish-only",
        action="store_true",
        help="Controller II: resume from the stored result and only run the coordinate search",
    )
    args = ap.parse_args(argv)
    out_path = GROUND_TRUTH_PATH.__class__(args.output)
    data: dict[str, Any] = {"problems": {}}
    if out_path.is_file():
        data = json.loads(out_path.read_text())
        data.setdefault("problems", {})
    for name in args.problems:
        get_problem.cache_clear()
        p = get_problem(name)
        t0 = time.perf_counter()
        if p.dim == 2:
            truth = controller_i_truth(p, n=args.grid)
        else:
            start = data["problems"].get(name) if args.polish_only else None
            truth = controller_ii_truth(p, restarts=args.restarts, evals_per_restart=args.evals, start=start)
        truth["noise_rel"] = noise_figure(p, np.asarray(truth["theta_star"]))
        truth["scenario"] = p.scenario.name
        truth["dt"] = p.scenario.dt
        truth["seconds"] = round(time.perf_counter() - t0, 1)
        data["problems"][name] = truth
        say(
            f"{name}: j_star {truth['j_star']:.5f} at {np.round(truth['theta_star'], 3).tolist()}, "
            f"j_med {truth['j_med']:.5f}, noise {100 * truth['noise_rel']:.2f} %"
        )
        data["generated_by"] = "bac ground-truth (python -m bac_sim.ground_truth)"
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(data, indent=1) + "\n")
    get_problem.cache_clear()
    say(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
