"""Text report and files of a simulation phase (what ``bac reduce`` prints and writes)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from bac_reduce.pipeline import ReductionResult, start_point


def format_report(result: ReductionResult) -> str:
    cfg = result.config
    c = result.curves
    lines: list[str] = []
    add = lines.append
    v = result.validation

    how_bo = (
        f"batch trust-region BO, {cfg.batch} runs per step" if cfg.optimizer == "turbo" else "the agent's BO engine"
    )
    polished = any(c.polish_runs for c in result.campaigns)
    add(
        f"== {len(result.campaigns)} BO campaigns of {cfg.trials} noisy runs ({how_bo}"
        + (
            f"; each optimum polished by CMA-ES on the noise-free simulator, {cfg.polish_evals} runs"
            if polished
            else ""
        )
        + f"; {result.backend}) =="
    )
    true_j = result.optima_true_j if result.optima_true_j is not None else (v.full_true_j if v is not None else None)
    ref = result.reference_j
    ref_name = "the best known J*" if v is None or math.isfinite(v.j_star_known) else "the phase's best"
    add(
        "campaign  seed   J_i (posterior mean)  true J   vs J* %"
        + ("  true J before the polish" if polished else "")
        + "  best observed"
    )
    for k, cr in enumerate(result.campaigns):
        tj = f"{true_j[k]:.4f}" if true_j is not None else "   -  "
        gap = f"{100 * (true_j[k] - ref) / ref:+7.2f}" if true_j is not None and math.isfinite(ref) else "    -  "
        before = f"   {cr.j_true_bo:.4f}              " if polished else ""
        mark = "  <- θ̄" if k == result.theta_bar_index else ""
        add(
            f"{cr.index:>8}  {cr.seed:>4}   {cr.j_pred:.4f} ± {cr.j_std:.4f}      {tj}  {gap}{before}   "
            f"{cr.y.min():.4f}{mark}"
        )
    if true_j is not None and math.isfinite(ref):
        worst = 100 * (float(np.max(true_j)) - ref) / ref
        add(
            f"reference: {ref_name} {ref:.5f}; the M optima are {100 * (float(np.min(true_j)) - ref) / ref:+.2f} % "
            f"... {worst:+.2f} % from it (std {float(np.std(true_j, ddof=1)) if len(true_j) > 1 else 0.0:.4f})"
        )

    how = "least noise-free J" if cfg.theta_bar == "simulator" else "least J_i"
    add(f"θ̄ = the optimum of campaign {result.campaigns[result.theta_bar_index].index} ({how})")
    add("")
    add(f"== sensitivity from θ̄ (J_mu(θ̄) = {c.j_bar:.4f}; T = {100 * cfg.threshold:g} %, ε = {cfg.epsilon:g}) ==")
    iv = c.optimal_intervals(cfg.flat_tol)
    group_of = {}
    meta_of = {tuple(m.members): m.name for m in result.definition.meta}
    for g in result.groups:
        for m in g.members:
            group_of[m] = meta_of.get(tuple(g.members), m)
    sim = result.true_curves
    oth = result.other_curves
    glob = result.global_sensitivity
    g_rel = glob.relative(c.j_bar) if glob is not None else None
    g_sig = set(glob.significant(cfg.threshold, c.j_bar)) if glob is not None else set()
    head = f"{'param':<8}{'θ̄':>9}{'best':>9}  {'optimal interval':<16}{'loss %':>8}"
    if oth is not None:
        head += f"{(cfg.surrogate == 'weighted' and 'mean %') or 'wtd %':>8}"
    if sim is not None:
        head += f"{'sim %':>8}"
    if glob is not None:
        head += (
            f"{'mu* %' if glob.method == 'morris' else 'ST %':>8}{'sigma %' if glob.method == 'morris' else 'S1 %':>9}"
        )
    head += "  kept  tuned as"
    add(head)
    spread = np.percentile(c.relative(result.thetas), [25, 75], axis=0)
    for i in np.argsort(-c.loss):
        n = c.names[i]
        row = (
            f"{n:<8}{c.theta_bar[i]:>9.1f}{c.best_value[i]:>9.1f}  [{iv[i, 0]:.2f}, {iv[i, 1]:.2f}]     "
            f"{100 * c.loss[i]:>8.2f}"
        )
        if oth is not None:
            row += f"{100 * oth.loss[i]:>8.2f}"
        if sim is not None:
            row += f"{100 * sim.loss[i]:>8.2f}"
        if glob is not None and g_rel is not None:
            spread_rel = glob.spread[i] / c.j_bar if glob.method == "morris" else glob.spread[i]
            row += f"{100 * g_rel[i]:>8.2f}{100 * spread_rel:>9.2f}"
        row += f"  {'yes ' if n in result.kept else 'no  '}  {group_of.get(n, 'fixed')}"
        if glob is not None and (n in g_sig) != (n in result.kept):
            row += "   (global: " + ("significant" if n in g_sig else "not significant") + ")"
        lines.append(row)
    add(
        f"(loss %: J_mu = the {'precision-weighted' if cfg.surrogate == 'weighted' else 'plain'} average of the M "
        f"posterior means, the decision; {'mean' if cfg.surrogate == 'weighted' else 'wtd'} %: the "
        f"{'plain' if cfg.surrogate == 'weighted' else 'precision-weighted'} average, for comparison"
        + ("; sim %: the noise-free simulator, the truth the surrogate estimates" if sim is not None else "")
        + ";"
    )
    add(
        f" optimal interval: where s_i is within {100 * cfg.flat_tol:g} % of J_mu(θ̄) of its minimum, "
        "share of the range;"
    )
    add(
        " IQR of the M optima per parameter: "
        + ", ".join(f"{n} {spread[1, i] - spread[0, i]:.2f}" for i, n in enumerate(c.names))
        + ")"
    )
    if sim is not None:
        sim_kept = {n for n, s in zip(sim.names, sim.loss, strict=True) if s > cfg.threshold}
        agree = set(result.kept) == sim_kept
        add(
            f"the noise-free one-at-a-time sweep {'agrees' if agree else 'disagrees'} on the kept set at T"
            + (
                ""
                if agree
                else f" (kept by J_mu only: {', '.join(sorted(set(result.kept) - sim_kept)) or '-'}; "
                f"by the simulator only: {', '.join(sorted(sim_kept - set(result.kept))) or '-'})"
            )
        )
    if glob is not None:
        only_oat = [n for n in c.names if n in result.kept and n not in g_sig]
        only_glob = [n for n in c.names if n in g_sig and n not in result.kept]
        what = "mu*/J_mu(θ̄)" if glob.method == "morris" else "total Sobol' index ST"
        verdict = "agrees with the one-at-a-time decision"
        if only_oat or only_glob:
            verdict = "disagrees: "
            if only_oat:
                verdict += f"kept from θ̄ but globally minor: {', '.join(only_oat)} (they matter at the optimum)"
                verdict += "; " if only_glob else ""
            if only_glob:
                verdict += (
                    f"globally significant but discarded: {', '.join(only_glob)} (they matter over the box, "
                    "little once the others are at θ̄)"
                )
        add(
            f"global sensitivity ({glob.method}, SALib, {glob.runs} noise-free runs over the whole box; significant "
            f"when {what} > T): {verdict}"
        )
    add("")
    add(f"== similarity: {len(result.kept)} kept parameters -> {len(result.groups)} tuned dimensions ==")
    for g in result.groups:
        name = meta_of.get(tuple(g.members), g.members[0])
        kind = "meta-parameter" if g.is_meta else "single"
        add(
            f"{name:<6} {kind:<15} {', '.join(g.members):<40} at {g.value:.2f} of the range, "
            f"tied-sweep best {100 * g.tie_loss:+.2f} % vs J_mu(θ̄)"
        )
    if [tuple(g.members) for g in result.untied_groups] != [tuple(g.members) for g in result.groups]:
        add("(the tie check split: " + "; ".join(", ".join(g.members) for g in result.untied_groups) + ")")
    fixed = result.definition.fixed
    add(f"fixed ({len(fixed)}): " + ", ".join(f"{k}={val:g}" for k, val in fixed.items()))

    if result.checks:
        add("")
        add(
            f"== the reduction checked on the noise-free simulator (tolerance {100 * cfg.loss_tol:g} % against "
            f"{ref_name} {result.reference_j:.5f}) =="
        )
        for ck in result.checks:
            gtxt = "; ".join("{" + ", ".join(g.members) + "}" if g.is_meta else g.members[0] for g in ck.groups)
            add(
                f"{'passes' if ck.passed else 'LOSES '} {ck.loss_pct:+.3f} %  {ck.dims} tuned  optimum {ck.j_opt:.5f}  "
                f"({ck.label}: {gtxt}; {ck.runs} runs)"
            )
        if result.repaired:
            add(
                f"the reduction of J_mu loses {result.checks[0].loss_pct:.2f} % (more than the tolerance): the file "
                f"holds the next best reduction, {result.checks[-1].label}"
                if any(ck.passed for ck in result.checks)
                else "no reduction within the tolerance was found; the file holds the one that loses least"
            )
    if v is not None:
        add("")
        add("== validation: BO on the reduced problem beside the full one ==")
        add(v.table(c.dim, result.dims_reduced))
        add(
            f"reduced problem: J* = {v.j_star_reduced:.4f} (best recommendation polished on the noise-free simulator), "
            f"J_med = {v.j_med_reduced:.4f}"
        )
        add(
            f"the paper's comparison: BO on the reduced problem finds {v.table_pct:+.2f} % against BO on the full one "
            "(mean optimal J)"
        )
        if math.isfinite(v.j_star_known):
            add(
                f"the reduced problem's optimum {v.j_star_reduced:.4f} is {v.loss_vs_known_pct:+.3f} % from the full "
                f"problem's best known J* {v.j_star_known:.5f} (the simulator's ground truth, bac ground-truth)"
            )
        add(
            f"and {v.loss_vs_phase_pct:+.3f} % from the full problem's optimum found by the phase "
            f"({v.j_full_best:.5f}, the best of the M campaigns)"
        )
        add("reduced optimum: " + ", ".join(f"{k}={x:.1f}" for k, x in v.reduced_optimum.items()))

    t = result.timings
    add("")
    add("== time ==")
    add(
        f"campaigns: {t['campaigns_wall_s']:.1f} s wall; summed over the workers: "
        f"simulation {t['campaigns_sim_s']:.1f} s, GP {t['campaigns_gp_s']:.1f} s"
    )
    add(f"J_mu, sensitivity, grouping: {t['analysis_s']:.1f} s (GP)")
    if "verify_s" in t:
        add(f"noise-free one-at-a-time sweep: {t['verify_s']:.1f} s (simulation)")
    if "global_s" in t:
        add(f"global sensitivity: {t['global_s']:.1f} s (simulation)")
    if "check_s" in t:
        add(f"the reduction checked (and repaired) on the simulator: {t['check_s']:.1f} s (simulation)")
    if "validate_s" in t and v is not None:
        add(f"validation: {t['validate_s']:.1f} s (simulation {v.sim_s:.1f} s, GP {v.gp_s:.1f} s)")
    add(f"total: {t['total_s'] / 60:.2f} min; simulation {t['sim_s']:.1f} s, GP {t['gp_s']:.1f} s (worker-seconds)")
    if "load_start" in t:
        add(
            f"machine: {t.get('cores', math.nan):.0f} cores, load average {t['load_start']:.1f} at the start, "
            f"{t['load_end']:.1f} at the end (the wall times above move with it)"
        )
    return "\n".join(lines)


def last_line(result: ReductionResult) -> str:
    """``reduce_minutes <t> params_kept <tuned dimensions> loss_pct <l> loss_vs_phase_pct <l2>``: l = the reduced
    optimum against the full problem's best known J* (the phase's own optimum when none is stored), l2 = against
    the phase's own full optimum, in %."""
    v = result.validation
    loss = v.loss_pct if v is not None else math.nan
    phase = v.loss_vs_phase_pct if v is not None else math.nan
    return (
        f"reduce_minutes {result.timings['total_s'] / 60:.2f} params_kept {result.dims_reduced} "
        f"loss_pct {loss:.3f} loss_vs_phase_pct {phase:.3f}"
    )


def definition_text(result: ReductionResult) -> str:
    """The meta-parameter file: a calibration definition with a provenance header."""
    import yaml

    cfg = result.config
    c = result.curves
    v = result.validation
    head = [
        f"# Meta-parameter file written by `bac reduce` on {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"# from {result.base.name}: M = {cfg.campaigns} BO campaigns of N = {cfg.trials} trials on {cfg.problem}, "
        f"seed {cfg.seed}",
        f"# significance T = {cfg.threshold:g}, similarity eps = {cfg.epsilon:g} (flat_tol {cfg.flat_tol:g}, "
        f"tie_tol {cfg.tie_tol:g})",
        "# worst loss from the best calibration (J_mu, %): "
        + ", ".join(f"{n} {100 * s:.1f}" for n, s in sorted(zip(c.names, c.loss, strict=True), key=lambda x: -x[1])),
    ]
    if v is not None:
        head.append(
            f"# reduced problem: J* = {v.j_star_reduced:.5f}, J_med = {v.j_med_reduced:.5f} "
            f"({v.loss_pct:+.2f} % against the full problem's best known J*, {v.loss_vs_phase_pct:+.2f} % against the "
            f"phase's best full optimum {v.j_full_best:.5f})"
        )
    head.append("# Load it with definition_file: <this path> (ecu_bridge, bo_agent, vehicle_sim).")
    head.append(
        "# best_guess: the simulation phase's optimum of the reduced problem; bo_agent drives it first "
        "(start_from: guess)"
    )
    return "\n".join(head) + "\n" + yaml.safe_dump(with_best_guess(result).to_dict(), sort_keys=False)


def with_best_guess(result: ReductionResult) -> Any:
    """The reduced definition carrying the phase's optimum as its best guess (validation's, else θ̄ through it)."""
    v = result.validation
    guess = dict(v.reduced_optimum) if v is not None and v.reduced_optimum else start_point(result)
    dims = {d.name: d for d in result.definition.dimensions}
    if set(guess) != set(dims):
        return result.definition
    # within the bounds, on the raw parameters' resolution (0.01 for Controller II: the value the ECU would hold)
    guess = {n: round(min(max(float(x), dims[n].lower), dims[n].upper), 2) for n, x in guess.items()}
    return replace(result.definition, best_guess=guess)


def _finite(x: Any) -> Any:
    """NaN and infinities as null: result.json is strict JSON."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    return x


def write_outputs(
    result: ReductionResult, out_dir: Path, definition_path: Path | None = None, plots: bool = True
) -> dict[str, Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    dpath = definition_path or out_dir / f"{result.definition.name}.yaml"
    dpath.parent.mkdir(parents=True, exist_ok=True)
    dpath.write_text(definition_text(result))
    files["definition"] = dpath
    from bac_ecu_bridge.dbc import write_dbc  # the CAN trace description of the file, for CANape / SavvyCAN

    files["dbc"] = write_dbc(result.definition, dpath.with_suffix(".dbc"))
    rpath = out_dir / "result.json"
    data = result.to_dict()
    data["definition_file"] = str(dpath)
    rpath.write_text(json.dumps(_finite(data), indent=1, allow_nan=False))
    files["result"] = rpath
    (out_dir / "report.txt").write_text(format_report(result) + "\n" + last_line(result) + "\n")
    files["report"] = out_dir / "report.txt"
    if plots:
        from bac_reduce.plots import write_plots

        for p in write_plots(result, out_dir):
            files[p.stem] = p
    return files
