"""The simulation phase's campaign choices, measured on a problem (run by hand; default road_c2b, Controller II-B,
not the road_c2 the phase is judged on): ``.venv/bin/python bench/reduce_campaigns.py -M 4``.

For each choice, M campaigns (seeded as ``bac reduce`` seeds them) and the noise-free J of each recommendation
against the problem's best known J* (``bac ground-truth``):

* ``agent``: the agent's engine (one GP over the box, 4 fantasized asks per step), N = 100 noisy runs: the phase
  before issue 20;
* ``turbo``: batch trust-region BO (bac_reduce.turbo), N = 320 noisy runs, 16 per step, its recommendation as is;
* ``turbo+polish``: the same, then CMA-ES on the noise-free simulator from the recommendation (1500 runs): what
  ``bac reduce`` does (the two come from one run: the recommendation before and after the polish);
* ``polish``: the polish alone, from the best of the same 40-run initial design (no BO).

Prints a row per choice (median, worst and best gap to J* in %, campaigns within 1 %, wall and CPU seconds) and,
last, ``campaigns_within_1pct <k>/<M>`` of ``turbo+polish``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bac_reduce.campaigns import CampaignSettings, campaign_specs, run_campaigns
from bac_reduce.objectives import SimulatedCar
from bac_reduce.pipeline import FAST_ENGINE
from bac_reduce.turbo import PolishConfig, polish_many


def gaps(j: np.ndarray, j_star: float) -> str:
    g = 100 * (j - j_star) / j_star
    return (
        f"median {np.median(g):6.2f} %  worst {g.max():6.2f} %  best {g.min():6.2f} %  "
        f"within 1 %: {int(np.sum(g <= 1.0))}/{g.size}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default="road_c2b")
    ap.add_argument("-M", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--choices", default="agent,turbo+polish,polish")
    args = ap.parse_args()
    car = SimulatedCar(args.problem)
    j_star = float(car.reference()[0])  # type: ignore[index]
    specs = campaign_specs(args.M, args.seed)
    choices = args.choices.split(",")
    print(f"{args.problem}: best known J* {j_star:.5f}; M = {args.M}; load average {os.getloadavg()[0]:.1f}")
    last = ""
    if "agent" in choices:
        t0, c0 = time.perf_counter(), time.process_time()
        out = run_campaigns(car, CampaignSettings(100, 0, 4, dict(FAST_ENGINE)), specs, noise_seed=args.seed)
        j = car.true_j(np.array([c.theta for c in out.campaigns]))
        print(f"agent (N 100)          {gaps(j, j_star)}  wall {time.perf_counter() - t0:.0f} s")
        del c0
    if "turbo+polish" in choices or "turbo" in choices:
        t0 = time.perf_counter()
        settings = CampaignSettings(320, 0, 16, {}, optimizer="turbo", polish={"evals": 1500, "sigma": 0.05})
        out = run_campaigns(car, settings, specs, noise_seed=args.seed)
        before = np.array([c.j_true_bo for c in out.campaigns])
        after = np.array([c.j_true for c in out.campaigns])
        wall = time.perf_counter() - t0
        print(f"turbo (N 320)          {gaps(before, j_star)}")
        print(f"turbo+polish (+1500)   {gaps(after, j_star)}  wall {wall:.0f} s (CPU: sim {out.sim_cpu_s:.0f} s, "
              f"GP {out.gp_cpu_s:.0f} s)")  # fmt: skip
        last = f"campaigns_within_1pct {int(np.sum(100 * (after - j_star) / j_star <= 1.0))}/{after.size}"
    if "polish" in choices:
        t0 = time.perf_counter()
        from scipy.stats import qmc

        bounds = car.definition
        b = np.array([[d.lower, d.upper] for d in bounds.dimensions])
        starts = []
        for s in specs:  # the best of a 40-run design per campaign, by its noisy runs
            X = b[:, 0] + qmc.LatinHypercube(b.shape[0], seed=s.seed).random(40) * (b[:, 1] - b[:, 0])
            y = car.evaluate(X, np.random.default_rng([args.seed, s.index]))
            starts.append(X[int(np.argmin(y))])
        _, j, _, _ = polish_many(car.true_j, np.array(starts), b, PolishConfig(1500, 0.05), seed=args.seed)
        print(f"polish alone (40+1500) {gaps(j, j_star)}  wall {time.perf_counter() - t0:.0f} s")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")
    if last:
        print(last)


if __name__ == "__main__":
    main()
