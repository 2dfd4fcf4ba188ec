"""What the simulator knows, carried to the car: runs until the optimum with and without a transfer prior (issue 23).

On the car families' instances of a split (``bench/problem_families.py``), bac's engine (its defaults, rule (a):
the argmin of the posterior mean) runs three ways on the same seeds and noise streams:

* ``none``: no prior (what bo_agent does without ``prior_source``);
* ``sim``: the simulator's surrogate as the prior: the **nominal** car on the same test (the simulation phase
  knows the test but not this car), 64 noise-free runs at Sobol points, fitted by ``SourceSurface.fit`` (what
  ``bac_agent.transfer`` builds from a ``bac reduce`` output or a campaign folder);
* ``misleading``: a deliberately wrong simulator: the same surrogate mirrored through the centre of the box, so
  that its optimum lies in the opposite corner of wherever the nominal car's lies;
* ``tol`` (not by default): the simulation phase **over the vehicle's uncertainty**: the nominal car's surrogate
  as ``sim``'s, and besides it (``EngineConfig.prior_variants``) the surrogates of ``--tolerance-k`` vehicles drawn
  from the family's spread around the nominal one (``bac_sim.families.draw_vehicle``, seeds of their own: not the
  benchmark's cars), each from 64 runs at the same Sobol points; ``tol_misleading``: the same, every surrogate
  mirrored as ``misleading``'s. The simulator is then no longer the nominal vehicle alone (issue 23's definition):
  a variant beside the goal's figures.

Printed per family and pooled over the car families: median runs until the recommendation's true gap ≤ 0.05
(budget + 1 when never), with a 90 % bootstrap interval, the share found after 1, 2 and 3 runs, and the gap of
the simulator's own optimum on each car; with the ``none`` and ``misleading`` arms, per family the misleading
prior's median minus no prior's with a 90 % interval that resamples the campaigns in pairs, and the cars' run-to-run
noise at their optimum in gap units (its sd over J_med - J*: the goal's 0.05 against what one run can tell).
``--seed-list`` runs a **variant** with other seeds than the split's (each seed is one initial design of the
engine: the split's two seeds are two designs per family, and a per-family median moves by runs with them);
``--noise-scale`` a **variant** with the cars' run-to-run noise scaled (0: noise-free runs; what the noise costs).
The results file records the run's arguments and conditions (``run``: split, seed list, budget, bac config, ...);
``--from-json`` takes the heading from what the files record ("unknown" for a file written before they were
recorded) and refuses files that record different values (summarize them apart).
LAST lines:
``transfer_sim_median_runs <x>`` (goal ≤ 2) and ``transfer_misleading_extra_runs <x>`` (the misleading prior's
median minus no prior's; goal ≤ 1).

    nice -n 10 .venv/bin/python bench/transfer.py --split held-out
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import problem_families as pf

from bac_common.progress import gap, runs_to_optimum

ARMS = ("none", "sim", "misleading")
ALL_ARMS = (*ARMS, "tol", "tol_misleading")
SOURCE_POINTS = 64
SOURCE_CACHE = Path(__file__).resolve().parent / "out" / "transfer_sources"


def _surface(family: str, index: int, vehicle: int, mirrored: bool) -> dict[str, Any]:
    """The surrogate (SourceSurface.to_dict()) of the nominal car (``vehicle`` -1) or of drawn vehicle ``vehicle``
    on instance ``index``'s test, mirrored or not; cached under bench/out (a pure function of its arguments)."""
    from bac_agent.bo.prior import SourceSurface
    from bac_sim.families import _seed, draw_vehicle, get_family

    path = SOURCE_CACHE / f"{family}_{index}_{vehicle}_{int(mirrored)}.json"
    if path.is_file():
        return dict(json.loads(path.read_text()))
    fam = get_family(family)
    inst = fam.instance(index)
    if vehicle < 0:
        sim = fam.nominal(inst)
    else:  # a vehicle within the tolerances, from seeds of its own (not the benchmark's instances)
        rng = np.random.default_rng(_seed("bench.transfer.tolerance", family, index, vehicle))
        sim = inst.with_vehicle(draw_vehicle(rng), f"drawn {vehicle}")
    b = sim.bounds

    def f(U: np.ndarray) -> np.ndarray:
        V = 1.0 - U if mirrored else U  # misleading: mirrored through the box centre
        return sim.evaluate(b[:, 0] + V * (b[:, 1] - b[:, 0]))["j"]

    what = "nominal car" if vehicle < 0 else f"drawn vehicle {vehicle}"
    label = f"{what} on {sim.scenario.name}" + (" (mirrored: misleading)" if mirrored else "")
    d = SourceSurface.from_function(f, b.shape[0], SOURCE_POINTS, label=label, seed=index).to_dict()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(d))
    return d


def variants_for(family: str, index: int, arm: str, k: int) -> list[dict[str, Any]]:
    """The ``tol`` arms' further sources: ``k`` drawn vehicles' surrogates (mirrored for ``tol_misleading``)."""
    if arm not in ("tol", "tol_misleading"):
        return []
    return [_surface(family, index, v, arm == "tol_misleading") for v in range(k)]


def source_for(family: str, index: int, arm: str) -> dict[str, Any] | None:
    """The transfer prior (SourceSurface.to_dict()) of an arm, or None."""
    if arm == "none":
        return None
    if arm in ("tol", "tol_misleading"):
        return _surface(family, index, -1, arm == "tol_misleading")
    from bac_agent.bo.prior import SourceSurface
    from bac_sim.families import get_family

    fam = get_family(family)
    nominal = fam.nominal(fam.instance(index))
    b = nominal.bounds

    def f(U: np.ndarray) -> np.ndarray:
        V = U if arm == "sim" else 1.0 - U  # misleading: mirrored through the box centre
        return nominal.evaluate(b[:, 0] + V * (b[:, 1] - b[:, 0]))["j"]

    label = f"nominal car on {nominal.scenario.name}" + (" (mirrored: misleading)" if arm == "misleading" else "")
    return SourceSurface.from_function(f, b.shape[0], SOURCE_POINTS, label=label, seed=index).to_dict()


def _with_noise_scale(inst: Any, factor: float) -> Any:
    """``inst`` with its run-to-run J noise multiplied by ``factor`` (``--noise-scale``, a variant)."""
    if factor == 1.0:
        return inst
    if dataclasses.is_dataclass(inst):  # the simulator's CarInstance (frozen)
        return dataclasses.replace(inst, noise_rel=inst.noise_rel * factor)
    inst.noise_rel = inst.noise_rel * factor  # the quick mode's GridInstance
    return inst


def _task(args: tuple[str, int, int, str, int, str, int, int, float]) -> dict[str, Any]:
    family, index, seed, arm, budget, config, grid, tol_k, noise_scale = args
    from threadpoolctl import threadpool_limits

    from bac_agent.bo import Engine, EngineConfig

    with threadpool_limits(1):
        inst = _with_noise_scale(pf.instance(family, index, grid), noise_scale)
        truth = pf.truth_of(family, index)
        b = inst.bounds
        names = [f"x{i}" for i in range(b.shape[0])]
        src = source_for(family, index, arm)
        extra = {"prior_variants": variants_for(family, index, arm, tol_k)} if arm.startswith("tol") else {}
        cfg = EngineConfig.from_dict(
            {**json.loads(config or "{}"), "budget": budget, "seed": seed, "prior": src, **extra}
        )
        eng = Engine([(n, lo, hi) for n, (lo, hi) in zip(names, b, strict=True)], cfg)
        noise_rng = np.random.default_rng([index, seed, 12345])
        recs, weights = [], []
        t0 = time.perf_counter()
        for _ in range(budget):
            q = eng.ask()
            x = np.array([[q[n] for n in names]])
            eng.tell(q, float(inst.noisy(x, noise_rng)["j"][0]))
            r = eng.recommend()
            recs.append([r.params[n] for n in names])
            weights.append(eng.transfer.weight if eng.transfer is not None else float("nan"))
        dt = time.perf_counter() - t0
        js = inst.true_j(np.array(recs))
        sim_gap = float("nan")
        if eng.source is not None:
            u = eng.source.argmin(seed)
            j_src = inst.true_j((b[:, 0] + u * (b[:, 1] - b[:, 0]))[None, :])
            sim_gap = float(gap(j_src, truth["j_star"], truth["j_med"])[0])
    return {
        "family": family,
        "instance": index,
        "seed": seed,
        "arm": arm,
        "gaps": [float(g) for g in gap(js, truth["j_star"], truth["j_med"])],
        "weights": weights,
        "source_optimum_gap": sim_gap,
        # the run-to-run noise's sd at the optimum in gap units (what one run can tell against the goal's 0.05)
        "noise_gap": float(inst.noise_rel * truth["j_star"] / (truth["j_med"] - truth["j_star"])),
        "noise_scale": noise_scale,  # 1: the split's own noise; else the --noise-scale variant
        "seconds": dt,
    }


# the arguments a results file records (its "run") that a --from-json summary must agree on and shows in its heading
# (besides them the file records the seed list, which files may differ in, the noise factor, which each result
# records too, and the run's conditions)
RUN_KEYS = ("split", "budget", "bac_config", "grid_truth")


class SummaryError(Exception):
    """Results that must not be summarized together (they record different runs' arguments)."""


def _canonical(key: str, value: Any) -> str:
    """A recorded value as compared between files: the bac config as the JSON it parses to (``{"a":1}`` and
    ``{"a": 1}`` are one config), the rest as recorded."""
    if key == "bac_config" and isinstance(value, str) and value.strip():
        try:
            value = json.loads(value)
        except json.JSONDecodeError:
            pass  # compared as written
    return json.dumps(value, sort_keys=True)


def pooled_run(runs: list[dict[str, Any] | None], results: list[dict[str, Any]]) -> dict[str, Any]:
    """What the results files' ``run`` records (None: a file written before it, or without the key) say of
    RUN_KEYS together: the one value all record, None when a file records none ("unknown"); files that record
    different values raise SummaryError. ``seed_list``: true when a file ran other seeds than the split's (a
    variant), else None when a file does not say, else false. ``budget`` is checked against the runs themselves (a
    campaign's gaps: one per run) and ``runs_per_campaign`` is that length (the budget the summary counts with,
    recorded or not)."""
    out: dict[str, Any] = {}
    seed_lists = [r.get("seed_list") if r is not None else None for r in runs]
    out["seed_list"] = True if any(seed_lists) else (None if None in seed_lists else False)
    for key in RUN_KEYS:
        vals = {_canonical(key, r[key]) for r in runs if r is not None and key in r}
        if len(vals) > 1:
            raise SummaryError(f"the files record different {key}: {', '.join(sorted(vals))}: summarize them apart")
        known = bool(vals) and all(r is not None and key in r for r in runs)
        out[key] = next(r[key] for r in runs if r is not None) if known else None  # (the first file's spelling)
    lengths = {len(r["gaps"]) for r in results}
    if len(lengths) > 1:
        raise SummaryError(f"the results hold campaigns of {sorted(lengths)} runs: summarize them apart")
    if not lengths:
        raise SummaryError("the files hold no campaigns: nothing to summarize")
    out["runs_per_campaign"] = lengths.pop()
    if out["budget"] is not None and out["runs_per_campaign"] != out["budget"]:
        raise SummaryError(f"the files record budget {out['budget']} but hold campaigns of {out['runs_per_campaign']}")
    return out


def heading(run: dict[str, Any], noise_label: str, instances: list[int], seeds: list[int], conditions: str) -> str:
    """The summary's first line, from what the run records (``pooled_run``'s None: unknown)."""

    def shown(v: Any, none: str = "unknown") -> str:
        return none if v is None else str(v)

    seed_tag = (
        " (seed list unknown)" if run["seed_list"] is None else (" (VARIANT: --seed-list)" if run["seed_list"] else "")
    )
    budget = shown(run["budget"], f"unknown (campaigns of {run['runs_per_campaign']} runs)")
    config = "unknown" if run["bac_config"] is None else (run["bac_config"] or "defaults")
    quick = (
        "; --grid-truth unknown"
        if run["grid_truth"] is None
        else (f"; quick mode --grid-truth {run['grid_truth']}" if run["grid_truth"] else "")
    )
    insts = f"{min(instances)}..{max(instances)}" if instances else "none"
    return (
        f"# transfer, split {shown(run['split'])}{seed_tag}{noise_label}: instances {insts}, seeds {seeds}, "
        f"budget {budget}, rule (a); bac config {config}{quick}; {conditions}"
    )


def _ci(runs: np.ndarray, draws: int = 4000) -> tuple[float, float]:
    rng = np.random.default_rng(0)
    m = np.median(runs[rng.integers(0, runs.size, (draws, runs.size))], axis=1)
    return float(np.quantile(m, 0.05)), float(np.quantile(m, 0.95))


def _paired_extra(
    rows: list[dict[str, Any]], budget: int, draws: int = 4000, arms: tuple[str, str] = ("misleading", "none")
) -> tuple[float, float, float]:
    """Arm ``arms[0]``'s median runs minus ``arms[1]``'s (by default the misleading prior's minus no prior's) over
    the same campaigns (family, instance, seed), with a 90 % bootstrap interval that resamples the campaigns in
    pairs (both arms share a campaign's car and noise)."""
    runs: dict[tuple[str, int, int], dict[str, int | float]] = {}
    for r in rows:
        runs.setdefault((r["family"], r["instance"], r["seed"]), {})[r["arm"]] = min(
            runs_to_optimum(r["gaps"]), budget + 1
        )
    x, y = arms
    pairs = np.array([[v[x], v[y]] for v in runs.values() if x in v and y in v])
    if pairs.size == 0:
        return math.nan, math.nan, math.nan
    rng = np.random.default_rng(0)
    idx = rng.integers(0, pairs.shape[0], (draws, pairs.shape[0]))
    diff = np.median(pairs[idx, 0], axis=1) - np.median(pairs[idx, 1], axis=1)
    point = float(np.median(pairs[:, 0]) - np.median(pairs[:, 1]))
    return point, float(np.quantile(diff, 0.05)), float(np.quantile(diff, 0.95))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", default="held-out", choices=sorted(pf.SPLITS))
    ap.add_argument("--families", default=",".join(pf.CAR_FAMILIES))
    ap.add_argument("--arms", default=",".join(ARMS), help=f"of {', '.join(ALL_ARMS)}")
    ap.add_argument(
        "--tolerance-k", type=int, default=8, help="arms tol*: vehicles drawn within the tolerances beside the nominal"
    )
    ap.add_argument("--instances", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=0)
    ap.add_argument(
        "--seed-list",
        default="",
        help="comma list of seeds in place of the split's (a variant, not the split: more designs per instance)",
    )
    ap.add_argument(
        "--noise-scale",
        type=float,
        default=1.0,
        help="the cars' run-to-run noise multiplied by this (a variant, not the split's conditions; 0: noise-free)",
    )
    ap.add_argument("--budget", type=int, default=15)
    ap.add_argument("--bac-config", default="")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--grid-truth", type=int, default=0, help="tuning split only: the cars' J interpolated (quick)")
    ap.add_argument("--out", default="")
    ap.add_argument("--from-json", default="", help="comma list of earlier --out files: summarize them together")
    a = ap.parse_args(argv)
    split = pf.SPLITS[a.split]
    insts = split["instances"][: a.instances or None]
    seeds = [int(x) for x in a.seed_list.split(",") if x] if a.seed_list else split["seeds"][: a.seeds or None]
    fams = [f for f in a.families.split(",") if f]
    arms = [x for x in a.arms.split(",") if x]
    if set(arms) - set(ALL_ARMS):
        ap.error(f"unknown arms {sorted(set(arms) - set(ALL_ARMS))}; known: {', '.join(ALL_ARMS)}")
    if not (math.isfinite(a.noise_scale) and a.noise_scale >= 0.0):
        ap.error(f"--noise-scale must be a finite number >= 0, got {a.noise_scale}")
    if a.grid_truth and a.split != "tuning":
        ap.error("--grid-truth is for exploring defaults on the tuning split only")
    tasks = [
        (f, i, s, arm, a.budget, a.bac_config, a.grid_truth, a.tolerance_k, a.noise_scale)
        for f in fams
        for i in insts
        for s in seeds
        for arm in arms
    ]
    t0 = time.perf_counter()
    if a.from_json:  # e.g. one run per family: summarized together (the pooled line over all of them)
        results: list[dict[str, Any]] = []
        recorded: list[dict[str, Any] | None] = []
        for f in (f for f in a.from_json.split(",") if f):
            data = json.loads(Path(f).read_text())
            results += data["results"]
            rec = data.get("run")  # (files written before 2026-11-25, late, record no arguments)
            recorded.append(rec)
            print(
                f"# summarized {f}: "
                + (
                    f"finished {rec.get('finished_utc', '?')}, wall {rec.get('wall_s', math.nan):.0f} s, "
                    f"{rec.get('workers', '?')} workers, load {rec.get('load', math.nan):.1f}"
                    if rec
                    else "its run's arguments and conditions not recorded"
                )
            )
        fams = list(dict.fromkeys(r["family"] for r in results))
        seeds = sorted({int(r["seed"]) for r in results})
        present = {r["arm"] for r in results}
        # the arms the files hold (--arms, when given, picks among them)
        arms = [x for x in (arms if a.arms != ap.get_default("arms") else ALL_ARMS) if x in present]
        try:
            pooled_args = pooled_run(recorded, results)
        except SummaryError as exc:
            sys.stderr.write(f"bench/transfer.py: {exc}\n")
            return 2
        conditions = f"summarized from {len(recorded)} file(s)"
    else:
        with ProcessPoolExecutor(max_workers=a.workers) as ex:
            results = list(ex.map(_task, tasks))
        wall = time.perf_counter() - t0
        run = {
            "split": a.split,
            "seed_list": a.seed_list,
            "budget": a.budget,
            "bac_config": a.bac_config,
            "grid_truth": a.grid_truth,
            "tolerance_k": a.tolerance_k,
            "noise_scale": a.noise_scale,
            "families": fams,
            "arms": arms,
            "instances": list(insts),
            "seeds": seeds,
            "workers": a.workers,
            "wall_s": wall,
            "load": os.getloadavg()[0],
            "finished_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
        }
        pooled_args = pooled_run([run], results)
        conditions = f"wall {wall:.0f} s, {a.workers} workers, load {run['load']:.1f}"
    budget = int(pooled_args["runs_per_campaign"])  # the runs per campaign (the recorded budget when there is one)
    # the noise variant is read from the results (a --from-json summary labels each file by what it holds; results
    # written before the factor was recorded have none: unknown, since --noise-scale existed for a while without it)
    scales = {r.get("noise_scale") for r in results}
    if len(scales) > 1:
        sys.stderr.write(
            f"bench/transfer.py: the results mix run-to-run noise factors {sorted(map(str, scales))} "
            "(None: not recorded): summarize them apart\n"
        )
        return 2
    noise_scale = scales.pop() if scales else a.noise_scale
    noise_label = (
        " (run-to-run noise factor not recorded)"
        if noise_scale is None
        else (f" (VARIANT: run-to-run noise x{noise_scale:g})" if noise_scale != 1.0 else "")
    )
    instances = sorted({int(r["instance"]) for r in results})
    print(heading(pooled_args, noise_label, instances, seeds, conditions))
    medians: dict[tuple[str, str], float] = {}
    for fam in [*fams, "all car families"]:
        rows = [r for r in results if fam == "all car families" or r["family"] == fam]
        ng = [r["noise_gap"] for r in rows if "noise_gap" in r]  # (results written before it have none)
        noise = f" (run-to-run noise at the optimum: {np.median(ng):.3f} gap units in median)" if ng else ""
        print(f"\n## {fam}{noise}")
        print(
            f"   {'prior':<11} {'runs':>5} {'90% CI':>9} {'by 1':>5} {'by 2':>5} {'by 3':>5} {'gap@end':>8} "
            f"{'weight@end':>10} {'source opt. gap':>15} {'n':>4}"
        )
        for arm in arms:
            rs = [r for r in rows if r["arm"] == arm]
            runs = np.array([min(runs_to_optimum(r["gaps"]), budget + 1) for r in rs])
            med = float(np.median(runs))
            medians[(fam, arm)] = med
            lo, hi = _ci(runs)
            by = [float(np.mean(runs <= k)) for k in (1, 2, 3)]
            gend = float(np.median([r["gaps"][-1] for r in rs]))
            w = np.array([r["weights"][-1] for r in rs])
            sg = np.array([r["source_optimum_gap"] for r in rs])
            wtxt = f"{np.nanmedian(w):.2f}" if np.any(np.isfinite(w)) else "-"
            stxt = f"{np.nanmedian(sg):.3f}" if np.any(np.isfinite(sg)) else "-"
            shown = f">{budget}" if med > budget else f"{med:g}"
            print(
                f"   {arm:<11} {shown:>5} {f'{lo:g}-{hi:g}':>9} {by[0]:>5.0%} {by[1]:>5.0%} {by[2]:>5.0%} "
                f"{gend:>8.3f} {wtxt:>10} {stxt:>15} {len(rs):>4}"
            )
        if "misleading" in arms and "none" in arms:
            d, lo, hi = _paired_extra(rows, budget)
            if math.isfinite(d):
                print(f"   misleading - none: {d:+g} runs (90% CI {lo:+g} to {hi:+g}, campaigns resampled in pairs)")
        for x, y in (("tol", "sim"), ("tol_misleading", "misleading"), ("tol_misleading", "none")):
            if x in arms and y in arms:
                d, lo, hi = _paired_extra(rows, budget, arms=(x, y))
                if math.isfinite(d):
                    print(f"   {x} - {y}: {d:+g} runs (90% CI {lo:+g} to {hi:+g}, paired)")
    if not a.from_json:
        # a run that is not the split's whole default run never writes over the split's own results
        whole = (
            not (a.seed_list or a.bac_config or a.grid_truth or a.instances or a.seeds)
            and a.noise_scale == 1.0
            and a.budget == ap.get_default("budget")
            and a.tolerance_k == ap.get_default("tolerance_k")
            and a.arms == ap.get_default("arms")
            and a.families == ap.get_default("families")
        )
        variant = "" if whole else (f"_noise{a.noise_scale:g}" if a.noise_scale != 1.0 else "") + "_variant"
        out = Path(a.out or f"bench/out/transfer_{a.split}{variant}.json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"run": run, "results": results}))
        print(f"\n# raw results {out}")
    pooled = "all car families"
    if (pooled, "sim") in medians:
        print(f"transfer_sim_median_runs {medians[(pooled, 'sim')]:g}")
    if (pooled, "misleading") in medians and (pooled, "none") in medians:
        print(f"transfer_misleading_extra_runs {medians[(pooled, 'misleading')] - medians[(pooled, 'none')]:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
