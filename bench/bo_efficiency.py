"""How many runs each optimizer needs to find the optimum, on problem families split before tuning (issue 23).

The problems are the families of ``bench/problem_families.py``: cars drawn from bac_sim's spread (both
controllers, bumps and roads) and standard functions shifted and rotated, each with 1-3 % run-to-run noise,
in two splits fixed before any default was tuned: ``tuning`` (defaults are chosen there) and ``held-out``
(never used to choose anything). In one run, with the same instances, seeds, noise streams and budgets:

* ``bac``: the engine with its defaults (``--bac-config`` overrides them);
* ``botorch``: SingleTaskGP + qLogNoisyExpectedImprovement with BoTorch's defaults, Ax's Sobol initialization
  of max(5, 2d) points, ``optimize_acqf`` with 10 restarts and 512 raw samples;
* ``optuna_gp``: Optuna's GPSampler (its defaults);
* ``random``: uniformly random calibrations.

Every optimizer is judged after every run under the same three **recommendation rules**, on the true,
noise-free J of the calibration each rule recommends:

* (a) ``mean``: the argmin over the domain of a posterior mean. bac: its own model
  (``Engine.recommend("mean")``); BoTorch: its own GP's posterior mean, maximized by ``optimize_acqf`` with the
  same restarts and raw samples as its acquisition; Optuna and random search have no model of their own that
  can be asked, so a *referee* GP judges their runs: BoTorch's SingleTaskGP with its defaults, fitted to them;
* (b) ``observed``: the observed point with the best posterior mean (what Ax recommends; the same models);
* (c) ``best_run``: the observed point with the best noisy J.

gap = (J − J*) / (J_med − J*) (bac_common.progress, J* and J_med of the instance from bench/data/
family_truth.json); found = gap ≤ 0.05. Printed per family and rule: each optimizer's median runs until the
recommendation is first found (a campaign that never finds it counts as budget + 1, shown ">B"), with a 90 %
bootstrap interval over the campaigns, the share found, the median gap after 5 and 10 runs and at the end;
per family the ratio of bac's median to BoTorch's under rule (a), with a paired bootstrap interval. LAST
line: ``worst_ratio_vs_botorch <x>``: the largest over the families of that ratio.

Needs the benchmark dependencies (``scripts/setup.sh --bench``) and the cached truth
(``python bench/problem_families.py --truth``).

    nice -n 10 .venv/bin/python bench/bo_efficiency.py --split held-out        # the issue's run (hours)
    .venv/bin/python bench/bo_efficiency.py --split tuning --optimizers bac --families bump_c1
    .venv/bin/python bench/bo_efficiency.py --from-json bench/out/a.json,bench/out/b.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import problem_families as pf

from bac_common.progress import FOUND_GAP, gap, runs_to_optimum

FloatArray = np.ndarray
RULES = ("mean", "observed", "best_run")
RULE_LABEL = {
    "mean": "(a) argmin of the posterior mean",
    "observed": "(b) best posterior mean at a run",
    "best_run": "(c) best noisy run",
}
OPTIMIZERS = ("bac", "botorch", "optuna_gp", "random")
BAC_CONFIG: dict[str, Any] = {}  # EngineConfig overrides (--bac-config)
Recs = dict[str, list[list[float]]]  # rule -> recommendation (user units) after every run


def _noisy_j(inst: Any, x: FloatArray, rng: np.random.Generator) -> float:
    return float(inst.noisy(np.atleast_2d(x), rng)["j"][0])


# --- optimizers ------------------------------------------------------------------------------------
def run_bac(inst: Any, seed: int, budget: int, noise_rng: np.random.Generator) -> Recs:
    from bac_agent.bo import Engine, EngineConfig

    names = [f"x{i}" for i in range(inst.bounds.shape[0])]
    cfg = EngineConfig.from_dict({**BAC_CONFIG, "budget": budget, "seed": seed})
    eng = Engine([(n, lo, hi) for n, (lo, hi) in zip(names, inst.bounds, strict=True)], cfg)
    out: Recs = {r: [] for r in RULES}
    for _ in range(budget):
        q = eng.ask()
        eng.tell(q, _noisy_j(inst, np.array([q[n] for n in names]), noise_rng))
        for r in RULES:
            rec = eng.recommend(r)
            out[r].append([rec.params[n] for n in names])
    return out


class _BotorchReferee:
    """BoTorch's SingleTaskGP (defaults) on the runs so far: rules (a) and (b), and its qLogNEI."""

    def __init__(self, bounds: FloatArray) -> None:
        import torch

        self.torch = torch
        self.lo = torch.tensor(bounds[:, 0], dtype=torch.double)
        self.hi = torch.tensor(bounds[:, 1], dtype=torch.double)
        self.d = bounds.shape[0]
        self.unit = torch.stack([torch.zeros(self.d), torch.ones(self.d)]).to(torch.double)

    def fit(self, X: FloatArray, y: FloatArray) -> Any:
        from botorch.fit import fit_gpytorch_mll
        from botorch.models import SingleTaskGP
        from botorch.models.transforms import Standardize
        from gpytorch.mlls import ExactMarginalLogLikelihood

        torch = self.torch
        U = (torch.tensor(X, dtype=torch.double) - self.lo) / (self.hi - self.lo)
        Y = -torch.tensor(y, dtype=torch.double).unsqueeze(-1)  # BoTorch maximizes
        model = SingleTaskGP(U, Y, outcome_transform=Standardize(1))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
        self.U = U
        return model

    def to_user(self, u: Any) -> list[float]:
        return [float(v) for v in (self.lo + u * (self.hi - self.lo)).tolist()]

    def rules(self, model: Any) -> tuple[list[float], list[float]]:
        """(a) the argmin of the posterior mean of J over the domain, (b) the run with the best one."""
        from botorch.acquisition import PosteriorMean
        from botorch.optim import optimize_acqf

        torch = self.torch
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cand, _ = optimize_acqf(PosteriorMean(model), bounds=self.unit, q=1, num_restarts=10, raw_samples=512)
        with torch.no_grad():
            i = int(torch.argmax(model.posterior(self.U).mean.squeeze(-1)))
        return self.to_user(cand.detach()[0]), self.to_user(self.U[i])

    def next_point(self, model: Any) -> FloatArray:
        from botorch.acquisition.logei import qLogNoisyExpectedImprovement
        from botorch.optim import optimize_acqf

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            acq = qLogNoisyExpectedImprovement(model, X_baseline=self.U)
            cand, _ = optimize_acqf(acq, bounds=self.unit, q=1, num_restarts=10, raw_samples=512)
        return np.asarray(self.to_user(cand.detach()[0]), dtype=float)


def _judge(ref: _BotorchReferee, X: list[FloatArray], y: list[float], out: Recs) -> Any:
    """Append the three rules' recommendations after these runs; the fitted referee model (None below 2 runs)."""
    i = int(np.argmin(y))
    out["best_run"].append([float(v) for v in X[i]])
    if len(y) < 2:
        out["mean"].append([float(v) for v in X[i]])
        out["observed"].append([float(v) for v in X[i]])
        return None
    model = ref.fit(np.array(X), np.array(y))
    a, b = ref.rules(model)
    out["mean"].append(a)
    out["observed"].append(b)
    return model


def run_botorch(inst: Any, seed: int, budget: int, noise_rng: np.random.Generator) -> Recs:
    import torch
    from torch.quasirandom import SobolEngine

    torch.manual_seed(seed)
    b = np.asarray(inst.bounds, dtype=float)
    d = b.shape[0]
    ref = _BotorchReferee(b)
    n_init = max(5, 2 * d)  # Ax's default Sobol initialization
    U0 = SobolEngine(d, scramble=True, seed=seed).draw(n_init).to(torch.double).numpy()
    X: list[FloatArray] = []
    y: list[float] = []
    out: Recs = {r: [] for r in RULES}
    model = None
    for k in range(budget):
        x = b[:, 0] + U0[k] * (b[:, 1] - b[:, 0]) if k < n_init or model is None else ref.next_point(model)
        X.append(np.clip(x, b[:, 0], b[:, 1]))
        y.append(_noisy_j(inst, X[-1], noise_rng))
        model = _judge(ref, X, y, out)
    return out


def run_optuna(inst: Any, seed: int, budget: int, noise_rng: np.random.Generator) -> Recs:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.ERROR)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sampler = optuna.samplers.GPSampler(seed=seed)
    study = optuna.create_study(direction="minimize", sampler=sampler)
    b = np.asarray(inst.bounds, dtype=float)
    dists = {f"x{i}": optuna.distributions.FloatDistribution(lo, hi) for i, (lo, hi) in enumerate(b)}
    ref = _BotorchReferee(b)
    X: list[FloatArray] = []
    y: list[float] = []
    out: Recs = {r: [] for r in RULES}
    for _ in range(budget):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trial = study.ask(dists)
        x = np.array([trial.params[f"x{i}"] for i in range(b.shape[0])])
        v = _noisy_j(inst, x, noise_rng)
        study.tell(trial, v)
        X.append(x)
        y.append(v)
        _judge(ref, X, y, out)
    return out


def run_random(inst: Any, seed: int, budget: int, noise_rng: np.random.Generator) -> Recs:
    rng = np.random.default_rng(seed)
    b = np.asarray(inst.bounds, dtype=float)
    ref = _BotorchReferee(b)
    X: list[FloatArray] = []
    y: list[float] = []
    out: Recs = {r: [] for r in RULES}
    for _ in range(budget):
        x = b[:, 0] + rng.random(b.shape[0]) * (b[:, 1] - b[:, 0])
        X.append(x)
        y.append(_noisy_j(inst, x, noise_rng))
        _judge(ref, X, y, out)
    return out


RUNNERS: dict[str, Callable[[Any, int, int, np.random.Generator], Recs]] = {
    "bac": run_bac,
    "botorch": run_botorch,
    "optuna_gp": run_optuna,
    "random": run_random,
}


def _task(args: tuple[str, int, int, str, str, int, int]) -> dict[str, Any]:
    family, index, seed, opt, bac_config, budget, grid = args
    BAC_CONFIG.clear()
    BAC_CONFIG.update(json.loads(bac_config or "{}"))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        inst = pf.instance(family, index, grid)
        truth = pf.truth_of(family, index)
        budget = budget or pf.budget_of(family)
        noise_rng = np.random.default_rng([index, seed, 12345])  # the same noise stream for every optimizer
        t0 = time.perf_counter()
        recs = RUNNERS[opt](inst, seed, budget, noise_rng)
        dt = time.perf_counter() - t0
        b = np.asarray(inst.bounds, dtype=float)
        all_pts = np.clip(np.array([p for r in RULES for p in recs[r]], dtype=float), b[:, 0], b[:, 1])
        uniq, inv = np.unique(all_pts, axis=0, return_inverse=True)
        js = np.asarray(inst.true_j(uniq), dtype=float)[inv.ravel()].reshape(len(RULES), budget)
    g = gap(js, truth["j_star"], truth["j_med"])
    return {
        "family": family,
        "instance": index,
        "seed": seed,
        "optimizer": opt,
        "gaps": {r: [float(v) for v in g[i]] for i, r in enumerate(RULES)},
        "seconds": dt,
    }


# --- statistics ------------------------------------------------------------------------------------------
BOOTSTRAP_DRAWS = 4000


def bootstrap_ci(
    statistic: Callable[..., FloatArray], *per_seed: FloatArray, level: float = 0.9, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic`` over campaigns (resampled together: paired)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, per_seed[0].size, (BOOTSTRAP_DRAWS, per_seed[0].size))
    values = statistic(*(a[idx] for a in per_seed))
    q = (1.0 - level) / 2.0
    return float(np.quantile(values, q)), float(np.quantile(values, 1.0 - q))


def _median(runs: FloatArray) -> FloatArray:
    return np.median(runs, axis=1)


def _median_ratio(ours: FloatArray, theirs: FloatArray) -> FloatArray:
    return np.median(ours, axis=1) / np.median(theirs, axis=1)


def runs_of(gaps: list[float], budget: int) -> float:
    return float(min(runs_to_optimum(gaps), budget + 1))


def summarize(results: list[dict[str, Any]], out_path: Path | None, header: str) -> float:
    """Print the tables; returns the worst ratio vs BoTorch under rule (a) (nan without both)."""
    print(header)
    families = [f for f in pf.FAMILIES if any(r["family"] == f for r in results)]
    families += sorted({r["family"] for r in results} - set(families))
    optimizers = [o for o in OPTIMIZERS if any(r["optimizer"] == o for r in results)]
    summary: dict[str, Any] = {}
    ratios: dict[str, float] = {}
    for fam in families:
        rows = [r for r in results if r["family"] == fam]
        budget = len(rows[0]["gaps"]["mean"])
        where = [pf.truth_of(fam, i)["u_star"] for i in sorted({r["instance"] for r in rows})]
        print(
            f"\n## {fam}  d={len(where[0])}  budget={budget}  {len({r['instance'] for r in rows})} instances x "
            f"{len({r['seed'] for r in rows})} seeds"
        )
        print("   optima (unit cube): " + " ".join("(" + ",".join(f"{v:.2f}" for v in u) + ")" for u in where))
        summary[fam] = {}
        runs_by: dict[tuple[str, str], dict[tuple[int, int], float]] = {}
        for rule in RULES:
            print(f"   {RULE_LABEL[rule]}")
            print(
                f"   {'optimizer':<10} {'runs':>5} {'90% CI':>10} {'found':>6} {'gap@5':>7} {'gap@10':>7} "
                f"{'gap@end':>7} {'s/run':>6} {'n':>4}"
            )
            for opt in optimizers:
                rs = sorted((r for r in rows if r["optimizer"] == opt), key=lambda r: (r["instance"], r["seed"]))
                if not rs:
                    continue
                G = np.array([r["gaps"][rule] for r in rs])
                runs = np.array([runs_of(list(g), budget) for g in G])
                runs_by[(opt, rule)] = {(r["instance"], r["seed"]): v for r, v in zip(rs, runs, strict=True)}
                med = float(np.median(runs))
                lo, hi = bootstrap_ci(_median, runs)
                found = float(np.mean(runs <= budget))
                g5, g10, ge = (float(np.median(G[:, min(k, budget) - 1])) for k in (5, 10, budget))
                spr = float(np.mean([r["seconds"] for r in rs])) / budget
                summary[fam].setdefault(opt, {})[rule] = {
                    "median_runs": med,
                    "ci90": [lo, hi],
                    "found": found,
                    "gap5": g5,
                    "gap10": g10,
                    "gap_end": ge,
                    "s_per_run": spr,
                    "n": len(rs),
                }
                shown = f">{budget}" if med > budget else f"{med:g}"
                print(
                    f"   {opt:<10} {shown:>5} {f'{lo:g}-{hi:g}':>10} {found:>6.0%} {g5:>7.3f} {g10:>7.3f} "
                    f"{ge:>7.3f} {spr:>6.2f} {len(rs):>4}"
                )
        if ("bac", "mean") in runs_by and ("botorch", "mean") in runs_by:
            a, b = runs_by[("bac", "mean")], runs_by[("botorch", "mean")]
            common = sorted(set(a) & set(b))
            ra = np.array([a[k] for k in common])
            rb = np.array([b[k] for k in common])
            r = float(np.median(ra) / np.median(rb))
            rlo, rhi = bootstrap_ci(_median_ratio, ra, rb)
            ratios[fam] = r
            summary[fam]["ratio_vs_botorch_rule_a"] = {"ratio": r, "ci90": [rlo, rhi], "paired": len(common)}
            print(
                f"   ratio bac/botorch, rule (a): {r:.3f} (90% paired bootstrap interval {rlo:.2f}-{rhi:.2f}, "
                f"{len(common)} campaigns)"
            )
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps({"summary": summary, "results": results}))
        print(f"\n# raw results {out_path}")
    worst = max(ratios.values()) if ratios else math.nan
    if ratios:
        print("# ratio under rule (a) per family: " + ", ".join(f"{f} {v:.2f}" for f, v in ratios.items()))
    return worst


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", default="held-out", choices=sorted(pf.SPLITS))
    ap.add_argument("--families", default=",".join(pf.FAMILIES))
    ap.add_argument("--optimizers", default=",".join(OPTIMIZERS))
    ap.add_argument("--instances", type=int, default=0, help="only the first N instances of the split (0: all)")
    ap.add_argument("--seeds", type=int, default=0, help="only the first N seeds of the split (0: all)")
    ap.add_argument("--budget", type=int, default=0, help="override every family's budget")
    ap.add_argument("--bac-config", default="", help='JSON overrides of EngineConfig, e.g. {"design_margin": 0.1}')
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument(
        "--grid-truth",
        type=int,
        default=0,
        help="quick mode for exploring defaults on the tuning split: the car families' J from a bicubic "
        "interpolation of an N x N grid of simulated runs (cached in bench/out/grids), not the simulator",
    )
    ap.add_argument("--out", default="", help="raw results (JSON); default bench/out/bo_efficiency_<split>.json")
    ap.add_argument("--from-json", default="", help="comma list of earlier --out files: summarize them together")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    if a.from_json:
        results: list[dict[str, Any]] = []
        seen = set()
        for f in [x for x in a.from_json.split(",") if x]:
            for r in json.loads(Path(f).read_text())["results"]:
                key = (r["family"], r["instance"], r["seed"], r["optimizer"])
                if key not in seen:
                    seen.add(key)
                    results.append(r)
        header = f"# summarized {a.from_json}"
        out = Path(a.out) if a.out else None
    else:
        split = pf.SPLITS[a.split]
        insts = split["instances"][: a.instances or None]
        seeds = split["seeds"][: a.seeds or None]
        fams = [f for f in a.families.split(",") if f]
        opts = [o for o in a.optimizers.split(",") if o]
        for o in opts:
            if o not in RUNNERS:
                ap.error(f"unknown optimizer {o!r}; known: {', '.join(RUNNERS)}")
        if a.grid_truth and a.split != "tuning":
            ap.error("--grid-truth is for exploring defaults on the tuning split only")
        tasks = [
            (f, i, s, o, a.bac_config, a.budget, a.grid_truth) for f in fams for i in insts for s in seeds for o in opts
        ]
        # the slow optimizers first, so that the pool ends together
        tasks.sort(key=lambda t: {"botorch": 0, "optuna_gp": 1, "random": 2, "bac": 3}.get(t[3], 4))
        results = []
        with ProcessPoolExecutor(max_workers=a.workers) as ex:
            for r in ex.map(_task, tasks):
                results.append(r)
        wall = time.perf_counter() - t0
        header = (
            f"# split {a.split}: instances {insts[0]}..{insts[-1]}, seeds {seeds}; noise 1-3 % per instance; "
            f"found = gap <= {FOUND_GAP}; bac config {a.bac_config or 'defaults'}; "
            + (f"QUICK: car J from a {a.grid_truth}x{a.grid_truth} grid, interpolated; " if a.grid_truth else "")
            + f"wall time {wall:.0f} s with "
            f"{a.workers} workers; load {os.getloadavg()[0]:.1f}"
        )
        out = Path(a.out or f"bench/out/bo_efficiency_{a.split}.json")
    worst = summarize(results, out, header)
    print(f"worst_ratio_vs_botorch {worst:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
