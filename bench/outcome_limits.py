"""A safety limit the agent must respect: runs to the constrained optimum and how often a run breaks it (issue 23).

The family: the bump cars of ``bench/problem_families.py`` (``bump_c1``, Controller I), each with a limit on the
suspension travel at least 4 mm below the travel of its unconstrained optimum, so that the unconstrained optimum
breaks it on every instance (soft dampers let the wheel travel towards the bump stop), and no higher than the
median travel over the box (rounded down to a mm). An instance where fewer than 15 % of the box keep such a
limit (a car that reaches its bump stops over this bump whatever the dampers do) is left out and listed. Each
run measures J and the travel (noisy: 1.5 mm + 2 %). bac runs with ``constraints: max_travel_mm <= limit`` (its defaults
otherwise, rule (a)), and without the limit for comparison, on the same seeds and noise streams. Arms:

* ``limit``: the limit, nothing known before the first run;
* ``limit_sim``: the limit with what the simulation phase knows, as bac's method runs it (the simulation phase
  precedes the car): the **nominal** car on the same bump (``bench/transfer.py``'s "simulator"), 64 noise-free runs
  at Sobol points, its J as the transfer prior (``prior``) and its travel as the travel model's prior
  (``outcome_priors``);
* ``limit_simout``: the limit with the simulator's travel only (no prior on J);
* ``limit_safe_start`` (added 2026-11-24): the limit, nothing known before the first run, but a safe start
  (``EngineConfig.safe_start``): run 1 is the calibration a user starts from, the shipped definition's baseline
  (``controller_i.yaml``, the same for every instance, as on a real car: the ECU's reference calibration), and the
  initial design grows from it within what the travel model allows. Whether that seed itself keeps each
  instance's limit is printed (``# the safe start's true travel``): where it does not, the engine must learn
  from that run and retreat;
* ``limit_campaign`` (added 2026-11-24, the outside review's case): the source is an earlier **15-run bac
  campaign** of the nominal car on the same bump (its defaults, no limit, noisy runs; its runs cluster near its
  optimum), written as a campaign journal and read by the node's own code path (``bac_agent.transfer.load_source``
  and ``load_outcome_sources``, what ``bo_agent``'s ``prior_source: <campaign folder>`` does): its J the transfer
  prior, its measured travel the travel model's prior;
* ``limit_reduce`` (added 2026-11-24): the simulation phase's campaigns (``bac_reduce.campaigns``, the agent's
  engine, 4 campaigns of 16 noisy runs of the nominal car, each run's travel recorded) written as a ``bac reduce``
  result.json (schema 2) and read by the node's code path (J_mu and the travel surrogate through the definition);
* ``limit_simfolder`` (added 2026-11-24): ``limit_sim``'s 64 Sobol calibrations of the nominal car, as **noisy
  runs** of a campaign (what a user gets by running the simulated car first: the ``sim`` profile with
  ``strategy: random``), journaled and read by the same node code path as ``limit_campaign``;
* ``none``: no limit.

Printed per arm: the share of campaigns whose final recommendation keeps the limit (true travel), the share of
all proposed runs whose true travel breaks it (goal < 10 %) and whose measured travel does, the median runs
until the recommendation is within gap 0.05 of the **constrained** optimum while keeping the limit (budget + 1
when never), with a 90 % bootstrap interval, the median final gap to it and the median final distance of the
recommendation's true travel to the limit; and (a variant, added 2026-11-24) the median runs until the
recommendation keeps the limit and is within gap 0.05 of the best calibration that keeps it by 2 mm
(``SAFE_MARGIN_MM``; over the instances where one does). The constrained optimum is the best point of a 41 × 41 grid of
simulated runs that keeps the limit. LAST lines: ``limit_violating_runs_pct_sim <x>`` (the ``limit_sim`` arm)
and ``limit_violating_runs_pct <x>`` (the ``limit`` arm), each with the goal < 10.

    nice -n 10 .venv/bin/python bench/outcome_limits.py --split held-out
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import qmc

sys.path.insert(0, str(Path(__file__).resolve().parent))
import problem_families as pf

from bac_common.progress import runs_to_optimum

FAMILY = "bump_c1"
MARGIN_MM = 4.0
MIN_FEASIBLE = 0.15
SOURCE_POINTS = 64  # the simulator's runs a prior is fitted to (as bench/transfer.py)
# the added variant (2026-11-24): the best calibration whose true travel keeps this margin to the limit. A run's
# travel scatters by 1.5 mm + 2 % (about 2.4 mm at 45 mm): a recommendation that keeps the limit with 95 %
# confidence cannot sit on it, and on most instances 1 mm of margin already costs more than gap 0.05 of the
# constrained optimum (docs/agent.md)
SAFE_MARGIN_MM = 2.0


@functools.cache  # the main process's, inherited by the forked workers: 1681 runs each
def constrained_truth(index: int) -> dict[str, Any]:
    inst = pf.instance(FAMILY, index)
    truth = pf.truth_of(FAMILY, index)
    b = inst.bounds
    g = np.linspace(0.0, 1.0, 41)
    U = np.array(np.meshgrid(g, g, indexing="ij")).reshape(2, -1).T
    out = inst.evaluate(b[:, 0] + U * (b[:, 1] - b[:, 0]))
    # below the unconstrained optimum's travel, and kept by at least half of the box's calibrations
    limit = min(float(truth["travel_at_star_mm"]) - MARGIN_MM, float(np.median(out["max_travel_mm"])))
    limit = float(np.floor(limit))
    ok = out["max_travel_mm"] <= limit
    k = int(np.argmin(np.where(ok, out["j"], np.inf)))
    ok_m = out["max_travel_mm"] <= limit - SAFE_MARGIN_MM
    return {
        "j_star_c_margin": float(np.min(out["j"][ok_m])) if ok_m.any() else float("nan"),
        "limit": limit,
        "j_star_c": float(out["j"][k]) if ok.any() else float("nan"),
        "u_star_c": U[k].tolist(),
        "feasible_share": float(np.mean(ok)),
        "j_med": truth["j_med"],
    }


def travel_source(index: int) -> dict[str, Any]:
    """The nominal car's travel on the instance's bump (SourceSurface.to_dict()): what the simulator knows of it."""
    from bac_agent.bo.prior import SourceSurface
    from bac_sim.families import get_family

    fam = get_family(FAMILY)
    nominal = fam.nominal(fam.instance(index))
    b = nominal.bounds

    def f(U: np.ndarray) -> np.ndarray:
        return nominal.evaluate(b[:, 0] + U * (b[:, 1] - b[:, 0]))["max_travel_mm"]

    label = f"nominal car's travel on {nominal.scenario.name}"
    return SourceSurface.from_function(f, b.shape[0], SOURCE_POINTS, label=label, seed=index).to_dict()


def safe_seed() -> dict[str, float]:
    """The calibration a user starts from: the shipped Controller I definition's baseline (tuned names)."""
    from bac_common.paramspace import CalibrationDefinition

    root = Path(__file__).resolve().parent.parent
    d = CalibrationDefinition.load(root / "ros_ws" / "config" / "calibrations" / "controller_i.yaml")
    base = d.baseline_values()
    return {n: base[n] for n in d.tuned}


def seed_travel(index: int) -> float:
    """The safe start's true (noise-free) travel on an instance."""
    inst = pf.instance(FAMILY, index)
    seed = safe_seed()
    b = inst.bounds
    x = np.array([[seed["damping_front"], seed["damping_rear"]]])
    assert np.all((x >= b[:, 0]) & (x <= b[:, 1]))
    return float(inst.evaluate(x)["max_travel_mm"][0])


CAMPAIGN_RUNS = 15  # the limit_campaign arm's source campaign


@functools.cache  # both seeds of an instance share their source (a worker computes it once)
def campaign_source(index: int, sobol: bool = False) -> dict[str, Any]:
    """The ``limit_campaign`` arm's priors: a 15-run bac campaign of the nominal car (no limit, noisy runs, seed =
    the instance), journaled in a temporary campaign folder and read back as ``bo_agent`` reads ``prior_source``;
    ``sobol``: the ``limit_simfolder`` arm's 64 noisy runs at ``limit_sim``'s Sobol points instead."""
    import tempfile

    from bac_agent.bo import Engine, EngineConfig
    from bac_agent.journal import Journal
    from bac_agent.transfer import load_outcome_sources, load_source
    from bac_sim.families import get_family

    fam = get_family(FAMILY)
    nominal = fam.nominal(fam.instance(index))
    definition = nominal.definition
    eng = Engine(definition, EngineConfig(budget=CAMPAIGN_RUNS, seed=index))
    names = list(eng.names)
    rng = np.random.default_rng([index, 777])
    b = nominal.bounds
    U = qmc.Sobol(b.shape[0], scramble=True, seed=index).random(SOURCE_POINTS)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / f"nominal_{index}"
        j = Journal(folder)
        j.append("campaign_started", campaign_id=folder.name, names=names, stamp=0.0)
        for k in range(SOURCE_POINTS if sobol else CAMPAIGN_RUNS):
            q = dict(zip(names, b[:, 0] + U[k] * (b[:, 1] - b[:, 0]), strict=True)) if sobol else eng.ask()
            out = nominal.noisy(np.array([[q[n] for n in names]]), rng)
            travel = float(out["max_travel_mm"][0])
            if not sobol:
                eng.tell(q, float(out["j"][0]), {"max_travel_mm": travel})
            j.append(
                "trial_scored",
                campaign_id=folder.name,
                trial_id=k + 1,
                params=q,
                j=float(out["j"][0]),
                outcomes={"max_travel_mm": travel},
                stamp=float(k + 1),
            )
        j.close()
        prior = load_source(folder, definition)
        outcome = load_outcome_sources(folder, definition, ["max_travel_mm"])
    return {"prior": prior.to_dict(), "outcome_priors": {k: v.to_dict() for k, v in outcome.items()}}


REDUCE_CAMPAIGNS, REDUCE_TRIALS = 4, 16  # the limit_reduce arm's simulation phase (64 runs, as the other sources)


@functools.cache
def reduce_source(index: int) -> dict[str, Any]:
    """The ``limit_reduce`` arm's priors: the simulation phase's campaigns on the nominal car, as ``bac reduce``
    runs them, stored as its result.json and read back as ``bo_agent``'s ``prior_source: reduce_out`` reads it."""
    import tempfile

    from bac_agent.transfer import load_outcome_sources, load_source
    from bac_reduce.campaigns import CampaignSettings, campaign_specs, run_campaigns
    from bac_reduce.pipeline import RESULT_SCHEMA_VERSION
    from bac_sim.families import get_family

    fam = get_family(FAMILY)
    nominal = fam.nominal(fam.instance(index))

    class NominalCar:  # a bac_reduce BatchObjective with the outcomes each run reports
        definition = nominal.definition
        label = f"nominal car on {nominal.scenario.name}"

        def evaluate_runs(self, thetas: np.ndarray, rng: Any) -> tuple[np.ndarray, dict[str, np.ndarray]]:
            rows = [nominal.noisy(th[None, :], g) for th, g in zip(np.atleast_2d(thetas), rng, strict=True)]
            return np.array([r["j"][0] for r in rows]), {
                "max_travel_mm": np.array([r["max_travel_mm"][0] for r in rows])
            }

        def evaluate(self, thetas: np.ndarray, rng: Any) -> np.ndarray:
            return self.evaluate_runs(thetas, rng)[0]

        def true_j(self, thetas: np.ndarray) -> np.ndarray:
            return np.asarray(nominal.evaluate(np.atleast_2d(thetas))["j"])

        def with_definition(self, definition: Any) -> NominalCar:
            return self

    out = run_campaigns(
        NominalCar(),  # type: ignore[arg-type]
        CampaignSettings(trials=REDUCE_TRIALS),
        campaign_specs(REDUCE_CAMPAIGNS, seed=index),
        workers=1,
        noise_seed=index,
    )
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "reduce_out"
        folder.mkdir()
        data = {"schema_version": RESULT_SCHEMA_VERSION, "campaigns": [c.to_dict() for c in out.campaigns]}
        (folder / "result.json").write_text(json.dumps(data))
        prior = load_source(folder, nominal.definition)
        outcome = load_outcome_sources(folder, nominal.definition, ["max_travel_mm"])
    return {"prior": prior.to_dict(), "outcome_priors": {k: v.to_dict() for k, v in outcome.items()}}


def _task(args: tuple[int, int, str, int, str]) -> dict[str, Any]:
    index, seed, arm, budget, config = args
    from threadpoolctl import threadpool_limits

    from bac_agent.bo import Engine, EngineConfig

    with threadpool_limits(1):
        inst = pf.instance(FAMILY, index)
        ct = constrained_truth(index)
        b = inst.bounds
        names = ["damping_front", "damping_rear"]
        cons = [f"max_travel_mm<={ct['limit']:.3f}"] if arm.startswith("limit") else []
        extra: dict[str, Any] = {}
        if arm in ("limit_sim", "limit_simout"):
            extra["outcome_priors"] = {"max_travel_mm": travel_source(index)}
        if arm == "limit_sim":
            from transfer import source_for

            extra["prior"] = source_for(FAMILY, index, "sim")
        if arm == "limit_safe_start":
            extra["safe_start"] = safe_seed()
        if arm == "limit_reduce":
            extra.update(reduce_source(index))
        if arm in ("limit_campaign", "limit_simfolder"):
            extra.update(campaign_source(index, sobol=arm == "limit_simfolder"))
        cfg = EngineConfig.from_dict(
            {**json.loads(config or "{}"), "budget": budget, "seed": seed, "constraints": cons, **extra}
        )
        eng = Engine([(n, lo, hi) for n, (lo, hi) in zip(names, b, strict=True)], cfg)
        noise_rng = np.random.default_rng([index, seed, 54321])
        asked, measured, recs = [], [], []
        t0 = time.perf_counter()
        for _ in range(budget):
            q = eng.ask()
            x = np.array([[q[n] for n in names]])
            out = inst.noisy(x, noise_rng)
            asked.append(x[0])
            measured.append(float(out["max_travel_mm"][0]))
            eng.tell(q, float(out["j"][0]), {"max_travel_mm": measured[-1]})
            r = eng.recommend()
            recs.append([r.params[n] for n in names])
        dt = time.perf_counter() - t0
        ev_runs = inst.evaluate(np.array(asked))
        ev_recs = inst.evaluate(np.array(recs))
    keeps = ev_recs["max_travel_mm"] <= ct["limit"]
    gap_c = (ev_recs["j"] - ct["j_star_c"]) / (ct["j_med"] - ct["j_star_c"])
    gap_c = np.where(keeps, gap_c, np.inf)
    jm = ct["j_star_c_margin"]
    gap_cm = np.where(keeps, (ev_recs["j"] - jm) / (ct["j_med"] - jm), np.inf) if np.isfinite(jm) else None
    return {
        "instance": index,
        "seed": seed,
        "arm": arm,
        "limit": ct["limit"],
        "feasible_share": ct["feasible_share"],
        "runs_broke_true": [bool(t > ct["limit"]) for t in ev_runs["max_travel_mm"]],
        "runs_broke_measured": [bool(t > ct["limit"]) for t in measured],
        "final_keeps": bool(keeps[-1]),
        "final_travel_minus_limit": float(ev_recs["max_travel_mm"][-1] - ct["limit"]),
        "gaps_c": [float(v) for v in gap_c],
        "gaps_c_margin": [float(v) for v in gap_cm] if gap_cm is not None else None,
        "seconds": dt,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", default="held-out", choices=sorted(pf.SPLITS))
    arms = "limit,limit_sim,limit_simout,limit_campaign,limit_simfolder,limit_reduce,limit_safe_start,none"
    ap.add_argument("--arms", default=arms)
    ap.add_argument("--budget", type=int, default=20)
    ap.add_argument("--instances", type=int, default=0, help="only the first N instances of the split (0: all)")
    ap.add_argument("--seeds", type=int, default=0, help="only the first N seeds of the split (0: all)")
    ap.add_argument("--bac-config", default="")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--out", default="")
    a = ap.parse_args(argv)
    split = pf.SPLITS[a.split]
    arms = [x for x in a.arms.split(",") if x]
    insts = split["instances"][: a.instances or None]
    seeds = split["seeds"][: a.seeds or None]
    shares = {i: constrained_truth(i)["feasible_share"] for i in insts}
    left_out = [i for i in insts if shares[i] < MIN_FEASIBLE]
    insts = [i for i in insts if shares[i] >= MIN_FEASIBLE]
    tasks = [(i, s, arm, a.budget, a.bac_config) for i in insts for s in seeds for arm in arms]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=a.workers) as ex:
        results = list(ex.map(_task, tasks))
    wall = time.perf_counter() - t0
    print(
        f"# left out (fewer than {MIN_FEASIBLE:.0%} of the box keep the limit): "
        + (", ".join(f"{i} ({100 * shares[i]:.0f} %)" for i in left_out) or "none")
    )
    print(
        f"# outcome limits on {FAMILY}, split {a.split}: travel limit min(the unconstrained optimum's travel - "
        f"{MARGIN_MM:g} mm, the median travel over the box); budget {a.budget}; rule (a); "
        f"bac config {a.bac_config or 'defaults'}; wall {wall:.0f} s, "
        f"{a.workers} workers, load {os.getloadavg()[0]:.1f}"
    )
    limits = sorted({(r["instance"], round(r["limit"], 1), round(100 * r["feasible_share"])) for r in results})
    print("# limits (instance, mm, feasible % of the box): " + ", ".join(f"{i}: {m} ({f} %)" for i, m, f in limits))
    if "limit_safe_start" in arms:
        seeds_t = {i: seed_travel(i) for i, _, _ in limits}
        broke = [i for i, m, _ in limits if seeds_t[i] > m]
        print(
            f"# the safe start {safe_seed()}'s true travel (instance: mm): "
            + ", ".join(f"{i}: {seeds_t[i]:.1f}" for i, _, _ in limits)
            + f"; it breaks the limit on {len(broke)} of {len(limits)} instances"
            + (f" ({', '.join(map(str, broke))})" if broke else "")
        )
    print(
        f"\n{'arm':<12} {'final keeps':>11} {'runs broke (true)':>17} {'(measured)':>10} {'runs to c-opt':>13} "
        f"{'90% CI':>9} {'n':>4} {'final gap_c':>11} {'final margin mm':>15} "
        f"{f'runs to c-opt -{SAFE_MARGIN_MM:g} mm':>20} {'n':>3}"
    )
    pct: dict[str, float] = {}
    for arm in arms:
        rs = [r for r in results if r["arm"] == arm]
        keeps = float(np.mean([r["final_keeps"] for r in rs]))
        broke_t = float(np.mean([b for r in rs for b in r["runs_broke_true"]]))
        broke_m = float(np.mean([b for r in rs for b in r["runs_broke_measured"]]))
        runs = np.array([min(runs_to_optimum(r["gaps_c"]), a.budget + 1) for r in rs])
        rng = np.random.default_rng(0)
        meds = np.median(runs[rng.integers(0, runs.size, (4000, runs.size))], axis=1)
        lo, hi = np.quantile(meds, [0.05, 0.95])
        med = float(np.median(runs))
        shown = f">{a.budget}" if med > a.budget else f"{med:g}"
        final_gap = float(np.median([r["gaps_c"][-1] for r in rs]))
        final_margin = float(np.median([-r["final_travel_minus_limit"] for r in rs]))
        rm = [r for r in rs if r.get("gaps_c_margin") is not None]
        med_m = float(np.median([min(runs_to_optimum(r["gaps_c_margin"]), a.budget + 1) for r in rm])) if rm else 0
        shown_m = f">{a.budget}" if med_m > a.budget else f"{med_m:g}"
        print(
            f"{arm:<12} {keeps:>11.0%} {broke_t:>17.1%} {broke_m:>10.1%} {shown:>13} {f'{lo:g}-{hi:g}':>9} "
            f"{len(rs):>4} {final_gap:>11.3f} {final_margin:>15.2f} {shown_m:>20} {len(rm):>3}"
        )
        pct[arm] = 100 * broke_t
    out = Path(a.out or f"bench/out/outcome_limits_{a.split}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"results": results}))
    print(f"\n# raw results {out}")
    if "limit_safe_start" in pct:
        print(f"limit_violating_runs_pct_safe_start {pct['limit_safe_start']:.1f}")
    if "limit_sim" in pct:
        print(f"limit_violating_runs_pct_sim {pct['limit_sim']:.1f}")
    for arm in ("limit_campaign", "limit_simfolder", "limit_reduce"):
        if arm in pct:
            print(f"limit_violating_runs_pct_{arm.removeprefix('limit_')} {pct[arm]:.1f}")
    print(f"limit_violating_runs_pct {pct.get('limit', float('nan')):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
