"""The experimental phase in simulation: runs until BO on the meta-parameters finds the reduced optimum (issue 8).

Takes the meta-parameter file written by ``bac reduce`` (and its ``result.json`` for the reduced
problem's J* and J_med; without it they are computed here: the median over random reduced
calibrations, and a polished best point) and runs the agent's engine with its **default**
configuration (what ``bo_agent`` runs on the car: one run per trial, noisy runs of the simulated
car) for ``--seeds`` independent campaigns of ``--budget`` trials. After every run the
recommendation's true (noise-free) J gives its gap ``(J - J*_red) / (J_med,red - J*_red)``; a campaign
has found the optimum after the first run whose recommendation has gap <= 0.05
(``bac_common.progress``). The campaigns run in lock-step: each step simulates the runs of all seeds
as one batch; the recommendations' true J are simulated in one batch at the end.

Baseline measured in the same run: random search on the same reduced problem (best observed run).

    .venv/bin/python bench/reduce_experimental.py --definition ros_ws/config/calibrations/controller_ii_reduced.yaml \\
        [--result reduce_out/result.json] [--seeds 16] [--budget 15]

LAST line: ``runs_to_optimum_median <n>`` (the paper took 6 runs on its car with 3 meta-parameters).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from bac_agent.bo import Engine, EngineConfig
from bac_agent.bo.baselines import RandomStrategy
from bac_common.paramspace import CalibrationDefinition
from bac_common.progress import FOUND_GAP, gap, runs_to_optimum, runs_to_stay_found
from bac_reduce.objectives import SimulatedCar
from bac_reduce.truth import definition_truth


def run(
    car: SimulatedCar, strategy: str, seeds: int, budget: int, guess: bool = False
) -> tuple[np.ndarray, float, float]:
    """(S, budget) true J of the recommendation after each run; simulation and optimizer seconds.

    ``guess``: the engine starts from the definition's best_guess (what bo_agent does with start_from: guess)."""
    d = car.definition
    names = [x.name for x in d.dimensions]
    if strategy == "bo":
        cfg = EngineConfig(initial_points=(dict(d.best_guess),) if guess and d.best_guess else ())
        engines = [Engine(d, cfg, budget=budget, seed=s) for s in range(seeds)]
    else:
        engines = [RandomStrategy(d, budget, s) for s in range(seeds)]  # type: ignore[misc]
    rng = np.random.default_rng(12345)
    recs: list[list[np.ndarray]] = [[] for _ in range(seeds)]
    sim_s = opt_s = 0.0
    while not all(e.done for e in engines):
        t0 = time.perf_counter()
        # the initial design needs no model: all its runs in one step
        asks = []
        for k, e in enumerate(engines):
            n = 1
            if strategy == "bo":
                n = max(1, e.n_initial - e.n_trials - len(e.pending))
            for _ in range(n):
                if e.n_trials + len(e.pending) < budget:
                    asks.append((k, e.ask()))
        t1 = time.perf_counter()
        y = car.evaluate(np.array([[p[x] for x in names] for _, p in asks]), rng)
        t2 = time.perf_counter()
        for (k, p), v in zip(asks, y, strict=True):
            e = engines[k]
            e.tell(p, float(v))
            r = e.recommend()
            recs[k].append(np.array([r.params[x] for x in names]))
        opt_s += (t1 - t0) + (time.perf_counter() - t2)
        sim_s += t2 - t1
    t3 = time.perf_counter()
    flat = np.array([r for rs in recs for r in rs])
    jt = car.true_j(flat).reshape(seeds, budget)
    sim_s += time.perf_counter() - t3
    return jt, sim_s, opt_s


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--definition", type=Path, required=True, help="meta-parameter file written by bac reduce")
    ap.add_argument("--result", type=Path, default=None, help="its result.json (reduced J*, J_med)")
    ap.add_argument("--problem", default="road_c2")
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--budget", type=int, default=15)
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument(
        "--start-from",
        choices=("guess", "design"),
        default="guess",
        help="guess: start from the file's best_guess, as bo_agent does by default; design: the design alone",
    )
    args = ap.parse_args()
    d = CalibrationDefinition.load(args.definition)
    car = SimulatedCar(args.problem).with_definition(d)
    t0 = time.perf_counter()
    truth = definition_truth(d, args.problem, args.result)
    j_star, j_med, source = truth.j_star, truth.j_med, truth.source
    print(
        f"{d.name}: {len(d.dimensions)} tuned dimensions ({', '.join(d.tuned)}); J*_red {j_star:.5f}, "
        f"J_med,red {j_med:.5f} ({source})"
    )
    out = {}
    for strategy in ("bo",) + (() if args.no_baseline else ("random",)):
        jt, sim_s, opt_s = run(car, strategy, args.seeds, args.budget, args.start_from == "guess")
        g = gap(jt, j_star, j_med)
        rto = np.array([runs_to_optimum(row, FOUND_GAP) for row in g])
        good = np.array([runs_to_stay_found(row, FOUND_GAP) for row in g])
        med = float(np.median(rto))
        out[strategy] = med
        found10 = float(np.mean(rto <= 10))

        def g_at(n: int, g: np.ndarray = g) -> float:
            return float(np.median(g[:, min(n, args.budget) - 1]))

        print(
            f"{strategy:>6}: runs to gap <= {FOUND_GAP}: median {med:g}, per seed {rto.tolist()}; for good: median "
            f"{float(np.median(good)):g}, per seed {good.tolist()}; found within 10 "
            f"runs: {100 * found10:.0f} %; median gap after 5/10/{args.budget} runs: "
            f"{g_at(5):.3f}/{g_at(10):.3f}/{g_at(args.budget):.3f} "
            f"(simulation {sim_s:.0f} s, optimizer {opt_s:.0f} s)"
        )
    if "random" in out and math.isfinite(out["random"]) and math.isfinite(out["bo"]):
        print(f"ratio random/bo: {out['random'] / out['bo']:.2f}")
    print(f"bench time {time.perf_counter() - t0:.0f} s")
    print(f"runs_to_optimum_median {out['bo']:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
