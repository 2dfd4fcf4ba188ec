"""How many runs each optimizer needs to find the optimum, under noise (issue 5).

In one run, with the same seeds, noise and budgets: bac's engine, BoTorch
(SingleTaskGP + qLogNoisyExpectedImprovement, its defaults), Optuna's GPSampler,
bayesian-optimization and random search, on Branin and Hartmann-6 (plus a noise
term) and, when bac_sim is installed, the simulated Controller I bump and road
problems. The optimizers only see noisy values; each is judged on the true,
noise-free J of its recommendation after every run:

* bac: argmin of the posterior mean over the domain (``Engine.recommend``);
* BoTorch: the observed point with the best posterior mean (what Ax recommends;
  BoTorch itself has no recommendation, and this beats its best noisy observation);
* Optuna, bayesian-optimization, random: their best observed point.

gap = (J - J*) / (J_med - J*) (bac_common.progress); found = gap <= 0.05.
Printed per problem and optimizer: the median number of runs until the optimum
is first found (a seed that never finds it counts as budget + 1, shown ">B") with
a 90 % bootstrap interval over the seeds, the share of seeds that found it, the
median gap after 10 and 20 runs, the time per run; per problem the ratio of bac's
median to BoTorch's with a 90 % bootstrap interval (seeds resampled in pairs: both
ran on the same seeds). LAST line: ``worst_ratio_vs_botorch <x>``, the largest
over problems of (bac's median runs to optimum) / (BoTorch's).

``--from-json a.json,b.json`` summarizes earlier outputs together: other problems,
or other seeds of the same problem (``--first-seed 20`` in b adds seeds 20..39).

Needs the benchmark dependencies: ``scripts/setup.sh --bench``.

    .venv/bin/python bench/bo_efficiency.py                       # everything, 20 seeds (about 1.5 h on 2 cores)
    .venv/bin/python bench/bo_efficiency.py --seeds 5 --problems branin --optimizers bac,botorch
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bac_common.progress import FOUND_GAP, gap, median_j, runs_to_optimum

FloatArray = np.ndarray


# --- problems -------------------------------------------------------------------------
@dataclass
class Problem:
    name: str
    bounds: FloatArray  # (d, 2)
    true_j: Callable[[FloatArray], FloatArray]
    noisy_j: Callable[[FloatArray, np.random.Generator], FloatArray]
    j_star: float
    j_med: float
    budget: int

    @property
    def dim(self) -> int:
        return int(self.bounds.shape[0])


def _branin(t: FloatArray) -> FloatArray:
    x1, x2 = t[:, 0], t[:, 1]
    b, c, r, s, tt = 5.1 / (4 * math.pi**2), 5 / math.pi, 6.0, 10.0, 1 / (8 * math.pi)
    return (x2 - b * x1**2 + c * x1 - r) ** 2 + s * (1 - tt) * np.cos(x1) + s


_H6_A = np.array(
    [[10, 3, 17, 3.5, 1.7, 8], [0.05, 10, 17, 0.1, 8, 14], [3, 3.5, 1.7, 10, 17, 8], [17, 8, 0.05, 10, 0.1, 14]]
)
_H6_P = 1e-4 * np.array(
    [
        [1312, 1696, 5569, 124, 8283, 5886],
        [2329, 4135, 8307, 3736, 1004, 9991],
        [2348, 1451, 3522, 2883, 3047, 6650],
        [4047, 8828, 8732, 5743, 1091, 381],
    ]
)
_H6_ALPHA = np.array([1.0, 1.2, 3.0, 3.2])


def _hartmann6(t: FloatArray) -> FloatArray:
    inner = np.sum(_H6_A[None] * (t[:, None, :] - _H6_P[None]) ** 2, axis=2)
    return -np.sum(_H6_ALPHA * np.exp(-inner), axis=1)


def _with_noise(
    f: Callable[[FloatArray], FloatArray], sd: float
) -> Callable[[FloatArray, np.random.Generator], FloatArray]:
    return lambda t, rng: f(t) + sd * rng.standard_normal(t.shape[0])


def make_problem(name: str, noise_share: float) -> Problem:
    """A problem with noise sd = noise_share * (J_med - J*) on the standard functions."""
    if name == "branin":
        bounds = np.array([[-5.0, 10.0], [0.0, 15.0]])
        j_star, j_med = 0.397887, median_j(_branin, bounds)
        return Problem(name, bounds, _branin, _with_noise(_branin, noise_share * (j_med - j_star)), j_star, j_med, 20)
    if name == "hartmann6":
        bounds = np.array([[0.0, 1.0]] * 6)
        j_star, j_med = -3.32237, median_j(_hartmann6, bounds)
        return Problem(
            name, bounds, _hartmann6, _with_noise(_hartmann6, noise_share * (j_med - j_star)), j_star, j_med, 80
        )
    from bac_sim.problems import get_problem  # the simulated vehicle (another package)

    p = get_problem(name)
    return Problem(
        name,
        np.asarray(p.bounds, dtype=float),
        p.true_j,
        p.noisy_j,
        float(p.j_star),
        float(p.j_med),
        20,
    )


def available_problems() -> list[str]:
    names = ["branin", "hartmann6"]
    try:
        from bac_sim.problems import get_problem

        for n in ("bump_c1", "road_c1"):
            get_problem(n)
            names.append(n)
    except Exception as exc:
        print(f"# bac_sim problems not available ({type(exc).__name__}: {exc}); standard functions only")
    return names


# --- optimizers: each returns the true J of its recommendation after every run -----------------
BAC_CONFIG: dict[
    str, object
] = {}  # EngineConfig overrides (--bac-config), e.g. {"n_initial": 8, "gp": {"ls_loc": 0.5}}


def run_bac(p: Problem, seed: int, noise_rng: np.random.Generator) -> list[list[float]]:
    from bac_agent.bo import Engine, EngineConfig

    names = [f"x{i}" for i in range(p.dim)]
    cfg = EngineConfig.from_dict({**BAC_CONFIG, "budget": p.budget, "seed": seed})  # "gp": partial GPConfig
    eng = Engine([(n, lo, hi) for n, (lo, hi) in zip(names, p.bounds, strict=True)], cfg)
    out = []
    for _ in range(p.budget):
        q = eng.ask()
        t = np.array([[q[n] for n in names]])
        eng.tell(q, float(p.noisy_j(t, noise_rng)[0]))
        r = eng.recommend()
        out.append([r.params[n] for n in names])
    return out


def run_random(p: Problem, seed: int, noise_rng: np.random.Generator) -> list[list[float]]:
    rng = np.random.default_rng(seed)
    T = p.bounds[:, 0] + rng.random((p.budget, p.dim)) * (p.bounds[:, 1] - p.bounds[:, 0])
    y = np.array([p.noisy_j(T[i : i + 1], noise_rng)[0] for i in range(p.budget)])
    idx = [int(np.argmin(y[: k + 1])) for k in range(p.budget)]
    return [T[i].tolist() for i in idx]


def run_botorch(p: Problem, seed: int, noise_rng: np.random.Generator) -> list[list[float]]:
    import torch
    from botorch.acquisition.logei import qLogNoisyExpectedImprovement
    from botorch.fit import fit_gpytorch_mll
    from botorch.models import SingleTaskGP
    from botorch.models.transforms import Normalize, Standardize
    from botorch.optim import optimize_acqf
    from gpytorch.mlls import ExactMarginalLogLikelihood
    from torch.quasirandom import SobolEngine

    torch.manual_seed(seed)
    d = p.dim
    lo = torch.tensor(p.bounds[:, 0], dtype=torch.double)
    hi = torch.tensor(p.bounds[:, 1], dtype=torch.double)
    n_init = max(5, 2 * d)  # Ax's default Sobol initialization
    U = SobolEngine(d, scramble=True, seed=seed).draw(n_init).to(torch.double)
    X = lo + U * (hi - lo)
    ys: list[float] = []
    xs_list: list[torch.Tensor] = []
    out: list[list[float]] = []
    unit = torch.stack([torch.zeros(d), torch.ones(d)]).to(torch.double)

    def recommend(Xs: torch.Tensor, Ys: torch.Tensor) -> list[float]:
        if Xs.shape[0] < 2:
            i = int(torch.argmin(Ys))
        else:
            model = SingleTaskGP(
                Xs, -Ys, input_transform=Normalize(d, bounds=torch.stack([lo, hi])), outcome_transform=Standardize(1)
            )
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
            with torch.no_grad():
                i = int(torch.argmax(model.posterior(Xs).mean.squeeze(-1)))
        return [float(v) for v in Xs[i].tolist()]

    for k in range(p.budget):
        if k < n_init:
            x = X[k : k + 1]
        else:
            Xs = torch.stack(xs_list)
            Ys = torch.tensor(ys, dtype=torch.double).unsqueeze(-1)
            model = SingleTaskGP((Xs - lo) / (hi - lo), -Ys, outcome_transform=Standardize(1))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
                acq = qLogNoisyExpectedImprovement(model, X_baseline=(Xs - lo) / (hi - lo))
                cand, _ = optimize_acqf(acq, bounds=unit, q=1, num_restarts=10, raw_samples=512)
            x = lo + cand.detach() * (hi - lo)
        xs_list.append(x[0])
        ys.append(float(p.noisy_j(x.numpy(), noise_rng)[0]))
        Xs = torch.stack(xs_list)
        Ys = torch.tensor(ys, dtype=torch.double).unsqueeze(-1)
        out.append(recommend(Xs, Ys))
    return out


def run_optuna(p: Problem, seed: int, noise_rng: np.random.Generator) -> list[list[float]]:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.ERROR)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sampler = optuna.samplers.GPSampler(seed=seed)
    study = optuna.create_study(direction="minimize", sampler=sampler)
    dists = {f"x{i}": optuna.distributions.FloatDistribution(lo, hi) for i, (lo, hi) in enumerate(p.bounds)}
    out = []
    for _ in range(p.budget):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trial = study.ask(dists)
        t = np.array([[trial.params[f"x{i}"] for i in range(p.dim)]])
        study.tell(trial, float(p.noisy_j(t, noise_rng)[0]))
        bp = study.best_trial.params
        out.append([bp[f"x{i}"] for i in range(p.dim)])
    return out


def run_bayes_opt(p: Problem, seed: int, noise_rng: np.random.Generator) -> list[list[float]]:
    from bayes_opt import BayesianOptimization

    pb = {f"x{i}": (float(lo), float(hi)) for i, (lo, hi) in enumerate(p.bounds)}
    opt = BayesianOptimization(f=None, pbounds=pb, random_state=seed, verbose=0, allow_duplicate_points=True)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(p.budget):
        if k < 5:  # its default: init_points=5 random points
            q = {n: float(lo + rng.random() * (hi - lo)) for n, (lo, hi) in pb.items()}
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                q = opt.suggest()
        t = np.array([[q[f"x{i}"] for i in range(p.dim)]])
        opt.register(params=q, target=-float(p.noisy_j(t, noise_rng)[0]))
        bp = opt.max["params"]
        out.append([bp[f"x{i}"] for i in range(p.dim)])
    return out


OPTIMIZERS: dict[str, Callable[[Problem, int, np.random.Generator], list[list[float]]]] = {
    "bac": run_bac,
    "botorch": run_botorch,
    "optuna_gp": run_optuna,
    "bayes_opt": run_bayes_opt,
    "random": run_random,
}


def _task(args: tuple[str, str, int, float, str, int]) -> tuple[str, str, int, list[float], float]:
    prob_name, opt_name, seed, noise_share, bac_config, budget = args
    BAC_CONFIG.update(json.loads(bac_config or "{}"))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # this pool already runs seeds in parallel; bac_sim's own process pool nested inside a worker hung
    os.environ.setdefault("BAC_SIM_WORKERS", "1")
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    p = make_problem(prob_name, noise_share)
    if budget:
        p.budget = budget
    noise_rng = np.random.default_rng([seed, 12345])  # the same noise stream for every optimizer
    t0 = time.perf_counter()
    recs = OPTIMIZERS[opt_name](p, seed, noise_rng)
    dt = time.perf_counter() - t0
    # the true J of every recommendation, in one batch (one simulation batch for the bac_sim problems)
    thetas = np.clip(np.array(recs, dtype=float), p.bounds[:, 0], p.bounds[:, 1])
    uniq, inv = np.unique(thetas, axis=0, return_inverse=True)
    js = p.true_j(uniq)[inv.ravel()]
    return prob_name, opt_name, seed, [float(j) for j in js], dt


BOOTSTRAP_DRAWS = 4000


def bootstrap_ci(
    statistic: Callable[..., FloatArray], *per_seed: FloatArray, level: float = 0.9, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic`` over seeds.

    ``per_seed`` are arrays with one value per seed, in the same seed order; a seed is resampled with all
    of its values (both optimizers ran on the same seeds, so a ratio is resampled in pairs).
    ``statistic`` maps the resampled arrays, each (draws, seeds), to (draws,). With 20 seeds a median
    of runs moves by several runs with the seeds alone; this interval says how far it can be trusted.
    """
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, per_seed[0].size, (BOOTSTRAP_DRAWS, per_seed[0].size))
    values = statistic(*(a[idx] for a in per_seed))
    q = (1.0 - level) / 2.0
    return float(np.quantile(values, q)), float(np.quantile(values, 1.0 - q))


def _median(runs: FloatArray) -> FloatArray:
    return np.median(runs, axis=1)


def _median_ratio(ours: FloatArray, theirs: FloatArray) -> FloatArray:
    return np.median(ours, axis=1) / np.median(theirs, axis=1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--problems", default="", help="comma list (default: every available problem)")
    ap.add_argument("--optimizers", default=",".join(OPTIMIZERS))
    ap.add_argument("--noise-share", type=float, default=0.05, help="noise sd / (J_med - J*) on standard functions")
    ap.add_argument("--bac-config", default="", help='JSON overrides of EngineConfig, e.g. {"gp": {"ls_loc": 0.5}}')
    ap.add_argument("--budget", type=int, default=0, help="override every problem's budget")
    ap.add_argument("--budgets", default="", help="per-problem budgets, e.g. hartmann6=60,branin=30")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--out", default="bench/out/bo_efficiency.json", help="raw results (JSON) and a PNG beside it")
    ap.add_argument(
        "--from-json",
        default="",
        help="comma list of earlier --out files: summarize them together (e.g. problems run separately), run nothing",
    )
    a = ap.parse_args(argv)
    results: dict[str, dict[str, list[tuple[int, list[float], float]]]] = {}
    t0 = time.perf_counter()
    if a.from_json:
        noise_shares = set()
        for f in a.from_json.split(","):
            data = json.loads(Path(f).read_text())
            noise_shares.add(data["noise_share"])
            for pn, d in data["curves"].items():
                for on, curves in d.items():
                    times = data.get("times", {}).get(pn, {}).get(on, [math.nan] * len(curves))
                    have = results.setdefault(pn, {}).setdefault(on, [])
                    # files of the same problem and optimizer add seeds (e.g. --first-seed 0 and 20)
                    first = int(data.get("first_seed", len(have)))
                    known = {s for s, _, _ in have}
                    for i, (c, t) in enumerate(zip(curves, times, strict=True)):
                        if first + i in known:
                            ap.error(f"{f}: seed {first + i} of {pn}/{on} is already in an earlier file")
                        have.append((first + i, c, t))
        if len(noise_shares) != 1:
            ap.error(f"the files mix noise shares {sorted(noise_shares)}; summarize one noise level at a time")
        a.noise_share = noise_shares.pop()
        a.seeds = max(len(v) for d in results.values() for v in d.values())
        problems = list(results)
        optimizers = [o for o in OPTIMIZERS if any(o in results[pn] for pn in problems)]
    else:
        problems = [s for s in a.problems.split(",") if s] or available_problems()
        optimizers = [s for s in a.optimizers.split(",") if s]
        for o in optimizers:
            if o not in OPTIMIZERS:
                ap.error(f"unknown optimizer {o!r}; known: {', '.join(OPTIMIZERS)}")
        per_problem = {k: int(v) for k, v in (kv.split("=") for kv in a.budgets.split(",") if kv)}
        tasks = [
            (pn, on, s, a.noise_share, a.bac_config, per_problem.get(pn, a.budget))
            for pn in problems
            for on in optimizers
            for s in range(a.first_seed, a.first_seed + a.seeds)
        ]
        with ProcessPoolExecutor(max_workers=a.workers) as ex:
            for pn, on, s, js, dt in ex.map(_task, tasks):
                results.setdefault(pn, {}).setdefault(on, []).append((s, js, dt))
    wall = time.perf_counter() - t0

    out_path = Path(a.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    summary: dict[str, dict[str, dict[str, Any]]] = {}
    ratio_info: dict[str, dict[str, Any]] = {}  # per problem: bac/BoTorch with its paired interval
    ratios = []
    print(
        f"# {a.seeds} seeds, noise sd = {a.noise_share} x (J_med - J*) on standard functions; "
        f"found = gap <= {FOUND_GAP}"
    )
    for pn in problems:
        p = make_problem(pn, a.noise_share)
        p.budget = len(next(iter(results[pn].values()))[0][1])
        print(f"\n## {pn}  d={p.dim}  budget={p.budget}  J*={p.j_star:.4g}  J_med={p.j_med:.4g}")
        print(
            f"{'optimizer':<11} {'runs_to_opt':>11} {'90% CI':>9} {'found':>6} {'gap@10':>8} {'gap@20':>8} "
            f"{'gap@' + str(p.budget) if p.budget > 20 else 'gap@end':>8} {'s/run':>7} {'seeds':>5}"
        )
        runs_by: dict[str, dict[int, float]] = {}
        summary[pn] = {}
        for on in [o for o in optimizers if o in results[pn]]:
            rows = sorted(results[pn][on])
            G = np.array([gap(js, p.j_star, p.j_med) for _, js, _ in rows])
            runs = np.array([min(runs_to_optimum(g), p.budget + 1) for g in G])
            runs_by[on] = {int(seed): float(r) for (seed, _, _), r in zip(rows, runs, strict=True)}
            med = float(np.median(runs))
            lo, hi = bootstrap_ci(_median, runs)
            found_share = float(np.mean(runs <= p.budget))
            g10 = float(np.median(G[:, min(9, p.budget - 1)]))
            g20 = float(np.median(G[:, min(19, p.budget - 1)]))
            g_end = float(np.median(G[:, -1]))
            spr = float(np.mean([dt for *_, dt in rows])) / p.budget
            summary[pn][on] = {
                "median_runs": med,
                "found": found_share,
                "gap10": g10,
                "gap20": g20,
                "gap_end": g_end,
                "s_per_run": spr,
                "median_runs_ci90": [lo, hi],
                "n_seeds": len(rows),
            }
            shown = f">{p.budget}" if med > p.budget else f"{med:g}"
            ci = f"{lo:g}-{hi:g}"
            print(
                f"{on:<11} {shown:>11} {ci:>9} {found_share:>6.0%} {g10:>8.3f} {g20:>8.3f} {g_end:>8.3f} "
                f"{spr:>7.3f} {len(rows):>5}"
            )
        if "bac" in summary[pn] and "botorch" in summary[pn]:
            r = summary[pn]["bac"]["median_runs"] / summary[pn]["botorch"]["median_runs"]
            ratios.append(r)
            common = sorted(set(runs_by["bac"]) & set(runs_by["botorch"]))
            rlo, rhi = bootstrap_ci(
                _median_ratio,
                np.array([runs_by["bac"][s] for s in common]),
                np.array([runs_by["botorch"][s] for s in common]),
            )
            ratio_info[pn] = {"ratio": r, "ci90": [rlo, rhi], "paired_seeds": len(common)}
            print(
                f"ratio bac/botorch (median runs to optimum): {r:.3f}  "
                f"(90% bootstrap interval over {len(common)} paired seeds: {rlo:.2f}-{rhi:.2f})"
            )
    out_path.write_text(
        json.dumps(
            {
                "seeds": a.seeds,
                "first_seed": a.first_seed,
                "noise_share": a.noise_share,
                "summary": summary,
                "ratio_vs_botorch": ratio_info,
                "curves": {
                    pn: {on: [js for _, js, _ in sorted(v)] for on, v in d.items()} for pn, d in results.items()
                },
                "times": {pn: {on: [t for *_, t in sorted(v)] for on, v in d.items()} for pn, d in results.items()},
            }
        )
    )
    _plot(results, problems, optimizers, a.noise_share, out_path.with_suffix(".png"))
    ran = f"summarized {a.from_json}" if a.from_json else f"wall time {wall:.0f} s with {a.workers} workers"
    print(f"\n# {ran}; raw results {out_path}, plot {out_path.with_suffix('.png')}")
    if ratios:
        print(f"worst_ratio_vs_botorch {max(ratios):.3f}")
    else:
        print("worst_ratio_vs_botorch nan")
    return 0


def _plot(results: dict, problems: list[str], optimizers: list[str], noise_share: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(problems), figsize=(4.5 * len(problems), 3.6), squeeze=False)
    for ax, pn in zip(axes[0], problems, strict=True):
        p = make_problem(pn, noise_share)
        ran = [o for o in optimizers if o in results[pn]]
        mixed = len({len(results[pn][o]) for o in ran}) > 1  # merged files: say which curve has how many seeds
        for on in ran:
            G = np.array([gap(js, p.j_star, p.j_med) for _, js, _ in results[pn][on]])
            n = np.arange(1, G.shape[1] + 1)
            label = f"{on} ({G.shape[0]} seeds)" if mixed else on
            ax.plot(n, np.maximum(np.median(G, axis=0), 1e-4), label=label, lw=2 if on == "bac" else 1)
        ax.axhline(FOUND_GAP, color="k", ls=":", lw=1)
        ax.set_yscale("log")
        ax.set_title(f"{pn} (d={p.dim})")
        ax.set_xlabel("runs")
        ax.set_ylabel("median gap of the recommendation")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
