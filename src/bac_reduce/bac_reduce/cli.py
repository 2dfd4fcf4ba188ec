"""``bac reduce``: the simulation phase (paper sec. III-D) -- find the few parameters that matter.

Runs M independent Bayesian-optimization campaigns of N trials on the simulated car
(Controller II on the test road by default) straight on the batch simulator, averages their
GP posterior means into J_mu, sweeps each parameter one at a time from the best optimum θ̄,
keeps the parameters whose worst loss exceeds T, groups those whose optima agree within ε into
meta-parameters, and writes the meta-parameter file that the ECU bridge, the agent and the
simulated car load for the experimental phase. Then it checks the reduction on the noise-free
simulator and validates it (BO on the reduced problem beside the full one).

    bac reduce                                    # M = 10, N = 320 on road_c2, on the local cores
    bac reduce -M 40 --scheduler tcp://head:8786  # on a Dask cluster
    bac reduce --problem synthetic -M 4 -N 30     # a cheap analytic problem with known answer

Writes into --out (default ``reduce_out/``): the meta-parameter file (``<name>.yaml``, or
--definition-out), ``result.json`` (everything), ``report.txt`` and the plots (PNG). The last
line printed is ``reduce_minutes <t> params_kept <k> loss_pct <l> loss_vs_phase_pct <l2>`` (k = tuned
dimensions of the reduced problem, l = how much worse its optimum is than the full problem's best known
J* on the simulator, l2 = than the full optimum the phase found, in %).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from bac_common.console import say
from bac_common.errors import BacError
from bac_reduce.analysis import (
    DEFAULT_EPSILON,
    DEFAULT_FLAT_TOL,
    DEFAULT_POINTS,
    DEFAULT_THRESHOLD,
    DEFAULT_TIE_TOL,
)
from bac_reduce.campaigns import CampaignResult, Progress
from bac_reduce.objectives import objective_names
from bac_reduce.pipeline import FAST_ENGINE, ReduceConfig, run_reduction
from bac_reduce.report import format_report, last_line, write_outputs


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="bac reduce",
        description="Simulation phase (paper sec. III-D): find the parameters that matter and write a "
        "meta-parameter file for the experimental phase.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ap.add_argument("--problem", default="road_c2", choices=list(objective_names()), help="what the campaigns run on")
    g = ap.add_argument_group("campaigns")
    g.add_argument("-M", "--campaigns", type=int, default=10, help="independent BO campaigns")
    g.add_argument("-N", "--trials", type=int, default=320, help="noisy runs per campaign")
    g.add_argument(
        "--batch",
        type=int,
        default=16,
        help="runs per campaign per lock-step after the initial design (1 = purely sequential BO)",
    )
    g.add_argument(
        "--n-initial", type=int, default=0, help="initial design size (0 = automatic: 2 d for turbo, d + 1 for agent)"
    )
    g.add_argument(
        "--optimizer",
        choices=("turbo", "agent"),
        default="turbo",
        help="the campaigns' BO: batch trust-region BO (bac_reduce.turbo) or the agent's engine (bac_agent.bo)",
    )
    g.add_argument("--turbo-config", type=json.loads, default=None, help="TurboConfig fields as JSON")
    g.add_argument(
        "--polish-evals",
        type=int,
        default=1500,
        help="noise-free simulator runs of the CMA-ES polish of each campaign's optimum (0 = no polish)",
    )
    g.add_argument("--polish-sigma", type=float, default=0.05, help="the polish's initial step, share of each range")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument(
        "--engine-config",
        type=json.loads,
        default=None,
        help=f"EngineConfig fields as JSON (default: {json.dumps(dict(FAST_ENGINE))}; '{{}}' = the agent's defaults)",
    )
    g = ap.add_argument_group("where they run")
    g.add_argument("--workers", type=int, default=None, help="local worker processes (default: one per core)")
    g.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786): run on that cluster")
    g.add_argument(
        "--group-size", type=int, default=None, help="campaigns per worker task (default: spread over the workers)"
    )
    g = ap.add_argument_group("reduction")
    g.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD, help="significance T (worst relative loss)")
    g.add_argument("--epsilon", type=float, default=DEFAULT_EPSILON, help="similarity ε (share of the range)")
    g.add_argument(
        "--flat-tol",
        type=float,
        default=DEFAULT_FLAT_TOL,
        help="a curve's values within this share of J of its minimum are optimal (0 = the argmin only)",
    )
    g.add_argument(
        "--tie-tol", type=float, default=DEFAULT_TIE_TOL, help="largest loss of tying a group's members together"
    )
    g.add_argument("--points", type=int, default=DEFAULT_POINTS, help="grid points of each sensitivity sweep")
    g.add_argument(
        "--fixed-at",
        choices=("optimum", "nominal"),
        default="optimum",
        help="value of the discarded parameters: θ̄'s (the best calibration found) or their nominal values",
    )
    g.add_argument(
        "--surrogate",
        choices=("weighted", "mean"),
        default="weighted",
        help="J_mu: the M posterior means averaged with precision weights, or plainly (paper eq. 3)",
    )
    g.add_argument(
        "--theta-bar",
        choices=("simulator", "posterior"),
        default="simulator",
        help="θ̄ = the campaign optimum with the least noise-free simulated J, or with the least posterior mean J_i",
    )
    g.add_argument("--name", default="", help="name of the reduced definition (default: <base>_reduced)")
    g = ap.add_argument_group("checks")
    g.add_argument("--verify-points", type=int, default=11, help="noise-free simulator sweep from θ̄, points (0 = skip)")
    g.add_argument(
        "--global-method",
        choices=("morris", "sobol", "none"),
        default="morris",
        help="global sensitivity on the noise-free simulator (SALib), shown beside the one-at-a-time sweep",
    )
    g.add_argument("--global-runs", type=int, default=1000, help="noise-free runs of the global sensitivity")
    g.add_argument(
        "--loss-tol",
        type=float,
        default=0.005,
        help="a reduction whose optimum loses more than this (share of J) against the best known J* on the "
        "simulator is reported and the next best reduction is searched",
    )
    g.add_argument(
        "--validate-repeats", type=int, default=10, help="BO campaigns on the reduced problem (0 = no validation)"
    )
    g.add_argument("--validate-trials", type=int, default=30, help="trials of each validation campaign")
    g.add_argument(
        "--from-result",
        type=Path,
        default=None,
        help="re-analyse the campaigns stored in an earlier result.json (other T, ε, ...) instead of running them",
    )
    g = ap.add_argument_group("output")
    g.add_argument("--out", type=Path, default=Path("reduce_out"), help="folder for result.json, report, plots")
    g.add_argument("--definition-out", type=Path, default=None, help="where to write the meta-parameter file")
    g.add_argument("--no-plots", action="store_true")
    g.add_argument("--quiet", action="store_true", help="no progress lines")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(list(argv) if argv is not None else None)
    try:
        stored = None
        if args.from_result is not None:
            data = json.loads(args.from_result.read_text())
            stored = [CampaignResult.from_dict(c) for c in data["campaigns"]]
            old = data["config"]
            args.problem, args.campaigns, args.trials = old["problem"], len(stored), old["trials"]
            args.batch, args.n_initial, args.seed = old["batch"], old["n_initial"], old["seed"]
            args.engine_config = old["engine"]
            args.optimizer = old.get("optimizer", "agent")
            args.turbo_config = old.get("turbo") or {}
            args.polish_evals = int(old.get("polish_evals", 0))
            args.polish_sigma = float(old.get("polish_sigma", args.polish_sigma))
        config = ReduceConfig(
            problem=args.problem,
            campaigns=args.campaigns,
            trials=args.trials,
            batch=args.batch,
            n_initial=args.n_initial,
            engine=dict(FAST_ENGINE) if args.engine_config is None else dict(args.engine_config),
            optimizer=args.optimizer,
            turbo=dict(args.turbo_config or {}),
            polish_evals=args.polish_evals,
            polish_sigma=args.polish_sigma,
            seed=args.seed,
            threshold=args.threshold,
            epsilon=args.epsilon,
            flat_tol=args.flat_tol,
            tie_tol=args.tie_tol,
            points=args.points,
            fixed_at=args.fixed_at,
            surrogate=args.surrogate,
            theta_bar=args.theta_bar,
            verify_points=args.verify_points,
            global_method=args.global_method,
            global_runs=args.global_runs,
            loss_tol=args.loss_tol,
            validate_repeats=args.validate_repeats,
            validate_trials=args.validate_trials,
            workers=args.workers,
            scheduler=args.scheduler,
            group_size=args.group_size,
            name=args.name,
        )
        t0 = time.perf_counter()
        last_print = [0.0]

        def log(msg: str) -> None:
            if not args.quiet:
                say(f"[{time.perf_counter() - t0:7.1f} s] {msg}", flush=True)

        def progress(p: Progress) -> None:
            now = time.perf_counter()
            if args.quiet or (now - last_print[0] < 10.0 and p.trials_done < p.trials):
                return
            last_print[0] = now
            say(
                f"[{now - t0:7.1f} s]   group {p.group}: {p.trials_done}/{p.trials} trials, best J {p.best_j:.4f} "
                f"(simulation {p.sim_s:.0f} s, GP {p.gp_s:.0f} s)",
                flush=True,
            )

        result = run_reduction(config, log=log, on_progress=progress, campaigns=stored)
        files = write_outputs(result, args.out, args.definition_out, plots=not args.no_plots)
    except (KeyError, TypeError, json.JSONDecodeError) as exc:
        say(f"bac reduce: {args.from_result} is not a result.json of bac reduce: {exc}", err=True)
        return 2
    except (BacError, OSError) as exc:
        say(f"bac reduce: {exc}", err=True)
        return 2
    say(format_report(result))
    say("")
    for kind, path in files.items():
        say(f"wrote {kind}: {path}")
    say(last_line(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
