"""Plots of the simulation phase (matplotlib, PNG): what the paper shows in its figs. 15-17, and more.

* ``optima_boxplot.png``: the M campaigns' optima per parameter (relative to the range), θ̄ marked;
* ``worst_loss.png``: each parameter's worst loss from θ̄ (surrogate J_mu; the noise-free simulator
  beside it when checked) and its global index over the whole box (Morris or Sobol', SALib), the threshold T,
  kept parameters coloured by group;
* ``sensitivity_kept.png``: the one-at-a-time curves s_i of the kept parameters, one panel per
  group (members overlaid, as the paper's fig. 17 shows them), the near-optimal intervals shaded;
* ``campaigns.png``: the best observed J of each campaign against trials;
* ``validation.png``: the true J of the full and reduced problems' recommendations.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from bac_reduce.pipeline import ReductionResult


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    """Lay out, write (PNG, 120 dpi) and close a figure."""
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    _plt().close(fig)
    return path


def _group_colors(result: ReductionResult) -> dict[str, str]:
    cmap = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive"]
    out = {}
    for k, g in enumerate(result.groups):
        for m in g.members:
            out[m] = cmap[k % len(cmap)]
    return out


def optima_boxplot(result: ReductionResult, path: Path) -> Path:
    plt = _plt()
    c = result.curves
    rel = c.relative(result.thetas)  # (M, d)
    bar = c.relative(result.theta_bar)
    fig, ax = plt.subplots(figsize=(max(8.0, 0.45 * c.dim + 2), 4.2))
    ax.boxplot([rel[:, i] for i in range(c.dim)], tick_labels=list(c.names), widths=0.6)
    xs = np.arange(1, c.dim + 1)
    jitter = np.linspace(-0.15, 0.15, rel.shape[0]) if rel.shape[0] > 1 else np.zeros(1)
    for k in range(rel.shape[0]):
        ax.plot(xs + jitter[k], rel[k], ".", color="0.55", ms=4, zorder=1)
    ax.plot(xs, bar, "D", color="tab:red", ms=6, label="θ̄ (best of the M optima)", zorder=3)
    ax.set_ylabel("optimum (share of the range)")
    ax.set_ylim(-0.05, 1.05)
    ax.set_title(f"Optima of the {rel.shape[0]} campaigns (N = {result.config.trials} trials each)")
    ax.tick_params(axis="x", rotation=60 if c.dim > 12 else 0)
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def worst_loss_bars(result: ReductionResult, path: Path) -> Path:
    plt = _plt()
    c = result.curves
    colors = _group_colors(result)
    T = result.config.threshold
    fig, ax = plt.subplots(figsize=(max(9.0, 0.55 * c.dim + 2), 4.4))
    xs = np.arange(c.dim)
    series: list[tuple[str, Any, str | None]] = [("J_mu from θ̄ (the decision)", 100 * c.loss, None)]
    if result.true_curves is not None:
        series.append(("simulator from θ̄ (check)", 100 * result.true_curves.loss, "//"))
    glob = result.global_sensitivity
    if glob is not None:
        what = "Morris mu*/J(θ̄), whole box" if glob.method == "morris" else "Sobol' ST, whole box"
        series.append((f"{what} (global)", 100 * glob.relative(c.j_bar), ".."))
    w = 0.8 / len(series)
    for k, (label, vals, hatch) in enumerate(series):
        ax.bar(
            xs + (k - (len(series) - 1) / 2) * w,
            vals,
            w,
            color=[colors.get(n, "0.7") for n in c.names] if hatch is None else "white",
            edgecolor="k",
            hatch=hatch,
            linewidth=0.5,
            label=label,
        )
    ax.axhline(100 * T, color="tab:red", ls="--", lw=1.2, label=f"T = {100 * T:g} %")
    ax.set_xticks(xs, list(c.names), rotation=60 if c.dim > 12 else 0)
    ax.set_ylabel("% of J(θ̄)")
    ax.set_title(
        "Significance: worst loss (max s_i − J_mu(θ̄)) / J_mu(θ̄) one at a time from θ̄, beside the global index;\n"
        "kept parameters coloured by group",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def sensitivity_kept(result: ReductionResult, path: Path) -> Path:
    plt = _plt()
    c = result.curves
    groups = result.groups
    n = max(1, len(groups))
    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.4 * rows), squeeze=False)
    meta_of = {tuple(m.members): m.name for m in result.definition.meta}
    iv = c.optimal_intervals(result.config.flat_tol)
    pos = {name: i for i, name in enumerate(c.names)}
    for k, g in enumerate(groups):
        ax = axes[k // cols][k % cols]
        for m in g.members:
            i = pos[m]
            rel = c.relative(c.values[i][:, None].repeat(c.dim, axis=1))[:, i]
            (line,) = ax.plot(rel, c.s[i], lw=1.5, label=m)
            ax.axvspan(iv[i, 0], iv[i, 1], color=line.get_color(), alpha=0.12)
            if result.true_curves is not None:
                tc = result.true_curves
                trel = tc.relative(tc.values[i][:, None].repeat(tc.dim, axis=1))[:, i]
                ax.plot(trel, tc.s[i], ":", color=line.get_color(), lw=1.0)
        ax.axhline(c.j_bar, color="k", lw=0.8, alpha=0.6)
        ax.axhline(c.j_bar * (1 + result.config.threshold), color="tab:red", lw=0.8, ls="--", alpha=0.7)
        ax.axvline(g.value, color="k", ls="--", lw=0.8, alpha=0.6)
        title = meta_of.get(tuple(g.members), g.members[0])
        ax.set_title(f"{title}: {', '.join(g.members)}" if g.is_meta else f"{title} (single)", fontsize=9)
        ax.set_xlabel("value (share of the range)")
        ax.set_ylabel("s_i = J_mu")
        ax.legend(fontsize=7, ncol=2)
        ax.grid(alpha=0.3)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    extra = "; dotted: noise-free simulator" if result.true_curves is not None else ""
    fig.suptitle(
        "One-at-a-time sensitivity of the kept parameters from θ̄\n(shaded: near-optimal intervals; "
        f"dashed: group value, J_mu(θ̄)·(1+T){extra})",
        fontsize=9,
    )
    return _save(fig, path)


def campaigns_plot(result: ReductionResult, path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4))
    for c in result.campaigns:
        ax.plot(np.arange(1, c.y.size + 1), c.best_so_far, lw=1, alpha=0.8)
    v = result.validation
    if v is not None:
        ax.axhline(v.j_full_best, color="k", ls="--", lw=1, label=f"best full optimum found {v.j_full_best:.4f}")
        ax.legend(fontsize=8)
    ax.set_xlabel("trial")
    ax.set_ylabel("best observed (noisy) J")
    ax.set_title(f"The {len(result.campaigns)} campaigns of the simulation phase")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def validation_plot(result: ReductionResult, path: Path) -> Path | None:
    v = result.validation
    if v is None:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    data = [v.full_true_j, v.reduced_true_j]
    ax.boxplot(data, tick_labels=[f"{result.curves.dim} parameters", f"{result.dims_reduced} tuned (reduced)"])
    for k, d in enumerate(data):
        ax.plot(np.full(d.size, k + 1) + np.linspace(-0.08, 0.08, d.size), d, ".", color="0.4")
    ax.axhline(v.j_full_best, color="k", ls="--", lw=1, label=f"best full optimum found {v.j_full_best:.4f}")
    if np.isfinite(v.j_star_known):
        ax.axhline(v.j_star_known, color="0.5", ls="-.", lw=1, label=f"full J* best known {v.j_star_known:.4f}")
    ax.axhline(v.j_star_reduced, color="tab:green", ls=":", lw=1.2, label=f"reduced J* {v.j_star_reduced:.4f}")
    ax.set_ylabel("true J of the recommendation")
    ax.set_title("BO on the full and the reduced problem")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def write_plots(result: ReductionResult, out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    made = [
        optima_boxplot(result, out_dir / "optima_boxplot.png"),
        worst_loss_bars(result, out_dir / "worst_loss.png"),
        sensitivity_kept(result, out_dir / "sensitivity_kept.png"),
        campaigns_plot(result, out_dir / "campaigns.png"),
    ]
    v = validation_plot(result, out_dir / "validation.png")
    if v is not None:
        made.append(v)
    return made
