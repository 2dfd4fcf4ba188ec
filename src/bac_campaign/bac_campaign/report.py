"""The campaign report: PNG figures and one HTML page (``bac report``).

From a campaign folder (journal, bags, config) it draws:

* ``gp_contour.png``: the GP posterior mean of J over the first two tuned
  dimensions (the others at the recommendation), the trials in order and the
  recommendation; beside it the true J of the simulated vehicle when known
  (``--truth bump_c1``) with its optimum;
* ``j_per_trial.png``: J of every run, the best so far, rejected runs, the
  confirmation run (and J* when known);
* ``signals.png`` and ``spectra.png``: the aligned vertical acceleration and
  pitch rate of the best and the worst trial and of the passive extremes
  (minimum and maximum damping) with their Welch spectra. The extremes come
  from the campaign when it drove them; for a simulated campaign they are
  otherwise driven offline on the simulator and put through the same
  measurement chain (ingestion, cut & align with the campaign's reference,
  KPI), and labelled so;
* a grid-search baseline (``--baseline GRID_CAMPAIGN``, a campaign run with
  ``strategy: grid``) beside the BO campaign: runs used, best J, recommended
  calibration and, when the truth is known, its true J and gap;
* ``prior_posterior.png`` (a campaign with a transfer prior, issue 23): the prior (the simulator's or an earlier
  campaign's J over the first two tuned dimensions) beside the posterior after the campaign's runs, with the
  runs and the prior's and the recommendation's optima; the transfer weight, scale and offset at the end;
* outcome limits: each run's measured outcomes, and the runs that broke a limit marked in the table and in
  ``j_per_trial.png`` (never hidden);
* ``report.html``: all of it with the table of trials.

    bac report CAMPAIGN_DIR [--truth bump_c1|road_c1] [--baseline GRID_CAMPAIGN_DIR] [--out DIR]
"""

from __future__ import annotations

import argparse
import html
import json
import math
import sys
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bac_agent.journal import JOURNAL_NAME, journaled_engine_options, read_journal
from bac_campaign.exportio import is_bac_export, read_segments, unpacked_export
from bac_common.console import say
from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition

KIND_NAMES = {0: "initial", 1: "optimized", 2: "confirmation", 3: "grid", 4: "manual"}
# bo_agent's recommend_rule (bac_agent.bo.engine.RULES), as the report says it
RULE_TEXT = {
    "mean": "the argmin of the posterior mean over the box",
    "observed": "the driven calibration with the best posterior mean",
    "best_run": "the driven calibration with the best measured J",
}


class ReportError(BacError, ValueError):
    """The campaign folder cannot be reported on."""


@dataclass
class TrialRow:
    trial_id: int
    kind: int
    params: dict[str, float]
    j: float = math.nan
    predicted_j: float = math.nan
    attempts: int = 0
    status: str = "proposed"  # scored / failed / proposed
    reason: str = ""
    rejected: list[tuple[int, str]] = field(default_factory=list)
    outcomes: dict[str, float] = field(default_factory=dict)  # measured besides J (RunScore outcomes)
    violations: list[str] = field(default_factory=list)  # outcome limits the run broke


@dataclass
class Campaign:
    path: Path
    campaign_id: str
    strategy: str
    definition: CalibrationDefinition
    trials: list[TrialRow]
    recommendation: dict[str, Any] | None
    seed: int
    # the live campaign's optimizer settings that a refit needs (journal.journaled_engine_options)
    engine_options: dict[str, Any] = field(default_factory=lambda: journaled_engine_options({}))
    # the campaign stopped resumable because the ECU link stayed down (campaign_paused, no resume since): why
    paused: str = ""
    # read from a bac export (its files unpacked into ``path``): the file, and its runs' aligned windows
    export: Path | None = None
    segments: dict[int, Any] | None = None

    @property
    def shown(self) -> Path:
        """Where the campaign is, as the user gave it (the export, not the folder it was unpacked into)."""
        return self.export if self.export is not None else self.path

    @property
    def names(self) -> tuple[str, ...]:
        return self.definition.tuned

    @property
    def recommend_beta(self) -> float:
        return float(self.engine_options["recommend_beta"])

    @property
    def gp_mean(self) -> str:
        return str(self.engine_options["gp"]["mean"])

    def scored(self, include_confirmation: bool = False) -> list[TrialRow]:
        return [
            t
            for t in self.trials
            if t.status == "scored" and math.isfinite(t.j) and (include_confirmation or t.kind != 2)
        ]


def load_campaign(path: str | Path) -> Campaign:
    p = Path(path)
    jr = read_journal(p / JOURNAL_NAME)
    if not jr.events or jr.events[0].get("event") != "campaign_started":
        raise ReportError(f"{p} has no campaign journal ({JOURNAL_NAME} starting with campaign_started)")
    start = jr.events[0]
    if not start.get("definition"):
        raise ReportError(f"{p}: the journal does not give the calibration definition")
    definition = CalibrationDefinition.from_dict(start["definition"])
    # a journal from before the rule was recorded: the engine recommended by its posterior mean, the baselines
    # (grid, random) their best run
    default_rule = "mean" if str(start.get("strategy", "bo")) == "bo" else "best_run"
    rows: dict[int, TrialRow] = {}
    rec = None
    paused = ""
    for e in jr.events:
        kind = e.get("event")
        tid = int(e.get("trial_id", 0) or 0)
        if kind == "campaign_paused":
            paused = str(e.get("message") or "the ECU link was down")
        elif kind == "campaign_resumed":
            paused = ""
        if kind == "trial_proposed":
            rows[tid] = TrialRow(
                tid,
                int(e.get("kind", 1)),
                {k: float(v) for k, v in e["params"].items()},
                predicted_j=_num(e.get("predicted_j")),
            )
        elif kind == "run_ready" and tid in rows:
            rows[tid].attempts = max(rows[tid].attempts, int(e.get("attempt", 1)))
        elif kind == "trial_scored" and tid in rows:
            rows[tid].j = _num(e.get("j"))
            rows[tid].status = "scored"
            rows[tid].outcomes = {str(k): _num(v) for k, v in (e.get("outcomes") or {}).items()}
            rows[tid].violations = [str(v) for v in e.get("violations") or []]
        elif kind == "run_rejected" and tid in rows:
            rows[tid].rejected.append((int(e.get("attempt", 0)), str(e.get("reason", ""))))
        elif kind == "trial_failed" and tid in rows:
            rows[tid].status = "failed"
            rows[tid].reason = str(e.get("reason", ""))
        elif kind == "recommendation":
            rec = {
                "params": {k: float(v) for k, v in (e.get("params") or {}).items()},
                "predicted_j": _num(e.get("predicted_j")),
                "predicted_std": _num(e.get("predicted_std")),
                "predicted_outcomes": dict(e.get("predicted_outcomes") or {}),
                "transfer": dict(e.get("transfer") or {}),
                "rule": str(e.get("rule") or default_rule),
            }
    if rec is None and (p / "recommendation.json").exists():
        data = json.loads((p / "recommendation.json").read_text())
        rec = {
            "params": data["params"],
            "predicted_j": _num(data.get("predicted_j")),
            "predicted_std": _num(data.get("predicted_std")),
            "rule": str(data.get("rule") or default_rule),
        }
    return Campaign(
        path=p,
        campaign_id=str(start.get("campaign_id", p.name)),
        strategy=str(start.get("strategy", "bo")),
        definition=definition,
        trials=[rows[k] for k in sorted(rows)],
        recommendation=rec,
        seed=int(start.get("seed", 0) or 0),
        engine_options=journaled_engine_options(start),
        paused=paused,
    )


def _num(v: Any) -> float:
    try:
        return float(v) if v is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


# --- recorded signals ------------------------------------------------------------------------------------


@dataclass
class Signals:
    label: str
    j: float
    rate_hz: float
    accel_z: np.ndarray
    pitch_rate: np.ndarray
    source: str  # "recorded" or "simulated offline"


def recorded_segments(campaign: Campaign, notes: list[str] | None = None) -> dict[int, Any]:
    """The valid RunSegment of each trial, from its bag (the last valid attempt); ``notes`` gets what could not be
    read (no bags/, an unreadable bag)."""
    from bac_measure.bagio import BagError, read_messages

    if campaign.segments is not None:  # a bac export: its aligned windows
        return dict(campaign.segments)
    out: dict[int, Any] = {}
    bags = campaign.path / "bags"
    if not bags.is_dir():
        if notes is not None:
            notes.append(f"no bags/ folder in {campaign.path}: no recorded signals to show")
        return out
    for bag in sorted(d for d in bags.iterdir() if d.is_dir()):
        try:
            msgs = read_messages(bag, "bac/run_segment")
        except BagError as exc:
            if notes is not None:
                notes.append(f"bags/{bag.name} is unreadable, its runs' signals are not shown: {exc}")
            continue
        for _, m in msgs:
            if m.valid and len(m.accel_z):
                out[int(m.trial_id)] = m
    return out


def _simulated_extreme(campaign: Campaign, values: Mapping[str, float], label: str) -> Signals | None:
    """Drive ``values`` on the simulator and put the run through the campaign's measurement chain."""
    try:
        from bac_campaign.rescore import default_params_files
        from bac_imu.ingest import ingest_all
        from bac_measure.kpi import score
        from bac_measure.measure_config import ingest_config, kpi_config, load_node_params, segment_config
        from bac_measure.segmentation import ImuSeries, OdomSeries, ReferenceStore, RunId, cut_run
        from bac_sim.run import simulate_run
    except ImportError:
        return None
    files = default_params_files(campaign.path)
    sim = load_node_params(files, "vehicle_sim")
    scenario = str(sim.get("scenario", "bump"))
    raw = campaign.definition.expand(values)
    rec = simulate_run(
        raw,
        scenario,
        seed=12345,
        run_in_s=float(sim.get("run_in_s", 6.0)),
        run_out_s=float(sim.get("run_out_s", 4.0)),
    )
    t0 = 10 * 1_000_000_000
    stamps = t0 + np.round(rec.t * 1e9).astype(np.int64)
    out, _ = ingest_all(stamps, rec.accel, rec.gyro, ingest_config(files))
    imu = ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate)
    odom = OdomSeries(t0 + np.round(rec.odom_t * 1e9).astype(np.int64), rec.distance, rec.speed)
    seg_cfg = segment_config(files)
    ref = ReferenceStore(str(campaign.path / "reference.npz")).get(campaign.campaign_id)
    seg = cut_run(imu, odom, seg_cfg, t0, ref, RunId("report", 0, 0))
    if not seg.valid:
        return None
    sc = score(seg, kpi_config(files))
    return Signals(label, sc.j, seg.sample_rate_hz, seg.accel_z, seg.pitch_rate, "simulated offline")


def comparison_signals(campaign: Campaign, notes: list[str] | None = None) -> list[Signals]:
    """The best and worst runs' aligned signals (recorded) and the damping extremes (recorded, else simulated
    offline); ``notes`` gets every run that should be shown and is not, and why."""
    notes = [] if notes is None else notes
    segs = recorded_segments(campaign, notes)
    scored = campaign.scored()
    out: list[Signals] = []
    if scored:
        best = min(scored, key=lambda t: t.j)
        worst = max(scored, key=lambda t: t.j)
        for t, label in ((best, "best"), (worst, "worst")):
            m = segs.get(t.trial_id)
            if m is None:
                notes.append(
                    f"the {label} run (trial {t.trial_id}) has no recorded segment in the "
                    f"{'export' if campaign.export is not None else 'bags'}: its signals are "
                    "not in signals.png"
                )
            if m is not None:
                out.append(
                    Signals(
                        f"{label}: trial {t.trial_id} ({_fmt_params(t.params)})",
                        t.j,
                        float(m.sample_rate_hz),
                        np.asarray(m.accel_z),
                        np.asarray(m.pitch_rate),
                        "recorded",
                    )
                )
    dims = campaign.definition.dimensions
    for label, pick in (("minimum damping", 0), ("maximum damping", 1)):
        values = {d.name: (d.lower, d.upper)[pick] for d in dims}
        near = [
            t for t in scored if all(abs(t.params[d.name] - values[d.name]) <= 0.02 * (d.upper - d.lower) for d in dims)
        ]
        if near and near[0].trial_id in segs:
            m = segs[near[0].trial_id]
            out.append(
                Signals(
                    f"{label} (trial {near[0].trial_id})",
                    near[0].j,
                    float(m.sample_rate_hz),
                    np.asarray(m.accel_z),
                    np.asarray(m.pitch_rate),
                    "recorded",
                )
            )
            continue
        try:
            sig = _simulated_extreme(campaign, values, f"{label} (simulated offline)")
        except BacError:
            sig = None
        if sig is not None:
            out.append(sig)
    return out


# --- model ---------------------------------------------------------------------------------------------------


def refit_engine(campaign: Campaign) -> Any:
    from bac_agent.bo import Engine, EngineConfig

    eng = Engine(
        campaign.definition,
        EngineConfig.from_dict(
            {**campaign.engine_options, "budget": max(1, len(campaign.trials)), "seed": campaign.seed}
        ),
    )
    for t in campaign.scored(include_confirmation=True):
        eng.tell(t.params, t.j, t.outcomes)
    return eng


def _fmt_params(params: Mapping[str, float], limit: int = 4) -> str:
    items = list(params.items())
    text = ", ".join(f"{k}={v:.3g}" for k, v in items[:limit])
    return text + (f" (+{len(items) - limit})" if len(items) > limit else "")


# --- figures -------------------------------------------------------------------------------------------------


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_contour(campaign: Campaign, out: Path, truth: Any | None, baseline: Campaign | None) -> Path | None:
    dims = campaign.definition.dimensions
    if len(dims) < 2 or not campaign.scored():
        return None
    plt = _plt()
    eng = refit_engine(campaign)
    d0, d1 = dims[0], dims[1]
    n = 60
    g0 = np.linspace(d0.lower, d0.upper, n)
    g1 = np.linspace(d1.lower, d1.upper, n)
    base = dict(campaign.recommendation["params"]) if campaign.recommendation else {}
    mean = np.empty((n, n))
    for i, a in enumerate(g1):
        for k, b in enumerate(g0):
            p = {**base, d0.name: float(b), d1.name: float(a)}
            for d in dims[2:]:
                p.setdefault(d.name, (d.lower + d.upper) / 2)
            mean[i, k] = eng.predict(p)[0]
    panels = 2 if truth is not None and len(dims) == 2 else 1
    fig, axes = plt.subplots(1, panels, figsize=(6.2 * panels, 5.2), squeeze=False)
    ax = axes[0, 0]
    lo, hi = float(np.nanmin(mean)), float(np.nanmax(mean))
    if np.isfinite(lo) and np.isfinite(hi) and hi - lo > 1e-12 * max(1.0, abs(hi)):
        cs = ax.contourf(g0, g1, mean, levels=np.linspace(lo, hi, 21), cmap="viridis")
        fig.colorbar(cs, ax=ax, label="posterior mean of J")
    else:  # one run (or runs that agree exactly): the model is flat, there is nothing to shade
        ax.set_facecolor("#eeeeee")
        ax.text(
            0.5,
            0.5,
            f"posterior mean flat (J = {lo:.4g}):\nthe model needs runs at two or more calibrations",
            transform=ax.transAxes,
            ha="center",
            va="center",
            fontsize=9,
        )
        ax.set_xlim(d0.lower, d0.upper)
        ax.set_ylim(d1.lower, d1.upper)
    _draw_trials(ax, campaign, d0.name, d1.name)
    if baseline is not None:
        bx = [t.params[d0.name] for t in baseline.scored()]
        by = [t.params[d1.name] for t in baseline.scored()]
        ax.scatter(
            bx,
            by,
            marker="s",
            s=14,
            facecolors="none",
            edgecolors="white",
            linewidths=0.8,
            label=f"grid baseline ({len(bx)} runs)",
        )
    ax.set_title(f"GP posterior mean after {len(campaign.scored(True))} runs")
    ax.set_xlabel(d0.name)
    ax.set_ylabel(d1.name)
    ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    if truth is not None and panels == 2:
        ax2 = axes[0, 1]
        tg0 = np.linspace(d0.lower, d0.upper, 41)
        tg1 = np.linspace(d1.lower, d1.upper, 41)
        A, B = np.meshgrid(tg0, tg1)
        tj = truth.true_j(np.column_stack([A.ravel(), B.ravel()])).reshape(A.shape)
        cs2 = ax2.contourf(tg0, tg1, tj, levels=21, cmap="viridis")
        fig.colorbar(cs2, ax=ax2, label="true J (simulator, noise-free)")
        ts = np.array(truth.theta_star, dtype=np.float64)
        ax2.plot(
            ts[0],
            ts[1],
            marker="*",
            ms=16,
            color="red",
            mec="white",
            label=f"true optimum J*={truth.j_star:.4f}",
        )
        _draw_trials(ax2, campaign, d0.name, d1.name)
        ax2.set_title("true J of the simulated vehicle")
        ax2.set_xlabel(d0.name)
        ax2.set_ylabel(d1.name)
        ax2.legend(loc="upper right", fontsize=7, framealpha=0.8)
    fig.tight_layout()
    path = out / "gp_contour.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _draw_trials(ax: Any, campaign: Campaign, n0: str, n1: str) -> None:
    scored = campaign.scored()
    if scored:
        xs = [t.params[n0] for t in scored]
        ys = [t.params[n1] for t in scored]
        order = np.arange(1, len(xs) + 1)
        ax.scatter(
            xs,
            ys,
            c=order,
            cmap="autumn",
            s=36,
            edgecolors="black",
            linewidths=0.6,
            zorder=3,
            label="trials (colour = order)",
        )
        for t in scored:
            ax.annotate(
                str(t.trial_id),
                (t.params[n0], t.params[n1]),
                fontsize=6,
                xytext=(3, 3),
                textcoords="offset points",
                color="white",
            )
    failed = [t for t in campaign.trials if t.status == "failed"]
    if failed:
        ax.scatter(
            [t.params[n0] for t in failed],
            [t.params[n1] for t in failed],
            marker="x",
            color="red",
            zorder=3,
            label="failed trials",
        )
    if campaign.recommendation:
        r = campaign.recommendation["params"]
        ax.plot(r[n0], r[n1], marker="P", ms=14, color="lime", mec="black", zorder=4, label="recommendation")


def plot_j_per_trial(campaign: Campaign, out: Path, truth: Any | None) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.2))
    scored = campaign.scored()
    ids = [t.trial_id for t in scored]
    js = [t.j for t in scored]
    ax.plot(ids, js, "o", color="tab:blue", label="J of the trial's run")
    if js:
        best = np.minimum.accumulate(js)
        ax.step(ids, best, where="post", color="tab:green", label="best so far")
    for t in campaign.trials:
        if t.rejected:
            ax.axvline(t.trial_id, color="orange", alpha=0.3, lw=3)
        if t.status == "failed":
            ax.axvline(t.trial_id, color="red", alpha=0.4, lw=3)
    broke = [t for t in scored if t.violations]
    if broke:
        ax.plot(
            [t.trial_id for t in broke],
            [t.j for t in broke],
            "x",
            ms=11,
            mew=2.5,
            color="red",
            label="broke an outcome limit",
        )
    conf = [t for t in campaign.trials if t.kind == 2 and t.status == "scored"]
    if conf:
        ax.plot([conf[0].trial_id], [conf[0].j], "P", ms=12, color="lime", mec="black", label="confirmation run")
    if truth is not None:
        ax.axhline(truth.j_star, color="red", ls="--", lw=1, label=f"true optimum J* = {truth.j_star:.4f}")
    ax.set_xlabel("trial")
    ax.set_ylabel("J (RMS a_z + RMS pitch rate)")
    ax.set_title(f"campaign {campaign.campaign_id}: J per trial ({campaign.strategy})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "j_per_trial.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_signals(signals: Sequence[Signals], out: Path) -> tuple[Path | None, Path | None]:
    if not signals:
        return None, None
    from bac_measure.kpi import welch_psd

    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for s in signals:
        t = np.arange(len(s.accel_z)) / s.rate_hz
        style = "--" if s.source != "recorded" else "-"
        axes[0].plot(t, s.accel_z, style, lw=1, label=f"{s.label}: J={s.j:.4f}")
        axes[1].plot(t, s.pitch_rate, style, lw=1)
    axes[0].set_ylabel("vertical acceleration a_z, m/s^2")
    axes[1].set_ylabel("pitch rate, rad/s")
    axes[1].set_xlabel("time in the aligned window, s")
    axes[0].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle("aligned signals (dashed: simulated offline through the same chain)")
    fig.tight_layout()
    p1 = out / "signals.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for s in signals:
        seg_s = min(2.0, len(s.accel_z) / s.rate_hz)
        f, pa = welch_psd(np.asarray(s.accel_z, float), s.rate_hz, seg_s, 30.0)
        _, pq = welch_psd(np.asarray(s.pitch_rate, float), s.rate_hz, seg_s, 30.0)
        style = "--" if s.source != "recorded" else "-"
        axes[0].semilogy(f, pa, style, lw=1, label=s.label)
        axes[1].semilogy(f, pq, style, lw=1)
    axes[0].set_ylabel("PSD a_z, (m/s^2)^2/Hz")
    axes[1].set_ylabel("PSD pitch rate, (rad/s)^2/Hz")
    axes[1].set_xlabel("frequency, Hz")
    axes[0].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
    fig.suptitle("Welch spectra of the aligned signals")
    fig.tight_layout()
    p2 = out / "spectra.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return p1, p2


# --- summary, HTML --------------------------------------------------------------------------------------------


def plot_prior_posterior(campaign: Campaign, out: Path) -> Path | None:
    """The transfer prior's J beside the posterior after the runs (first two tuned dimensions, others at the
    recommendation), with the runs, the prior's optimum and the recommendation (issue 23)."""
    prior = campaign.engine_options.get("prior")
    names = list(campaign.names)
    if not prior or len(names) < 2 or not campaign.scored(include_confirmation=True):
        return None
    from bac_agent.bo.prior import SourceSurface

    source = SourceSurface.from_dict(dict(prior))
    eng = refit_engine(campaign)
    rec = eng.recommend()
    space = eng.space
    u_rec = space.to_unit(space.to_array(rec.params))
    n = 61
    g = np.linspace(0.0, 1.0, n)
    A, B = np.meshgrid(g, g, indexing="ij")
    U = np.repeat(u_rec[None, :], n * n, axis=0)
    U[:, 0], U[:, 1] = A.ravel(), B.ravel()
    prior_j = source.predict_j(U).reshape(n, n)
    post_j = eng.predict_unit(U)[0].reshape(n, n)
    lo, hi = space.lower, space.upper
    xa, xb = lo[0] + g * (hi[0] - lo[0]), lo[1] + g * (hi[1] - lo[1])
    u_src = source.argmin()
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    runs = campaign.scored(include_confirmation=True)
    for ax, Z, title in (
        (axes[0], prior_j, f"prior: {source.label[:60]}"),
        (axes[1], post_j, f"posterior after {len(runs)} runs"),
    ):
        cs = ax.contourf(xa, xb, Z.T, levels=20, cmap="viridis")
        fig.colorbar(cs, ax=ax, label="J")
        ax.plot([t.params[names[0]] for t in runs], [t.params[names[1]] for t in runs], "w.", ms=8, label="runs")
        broke = [t for t in runs if t.violations]
        if broke:
            ax.plot(
                [t.params[names[0]] for t in broke],
                [t.params[names[1]] for t in broke],
                "rx",
                ms=9,
                mew=2,
                label="broke a limit",
            )
        ax.plot(
            lo[0] + u_src[0] * (hi[0] - lo[0]),
            lo[1] + u_src[1] * (hi[1] - lo[1]),
            "m^",
            ms=11,
            mec="k",
            label="prior's optimum",
        )
        ax.plot(rec.params[names[0]], rec.params[names[1]], "r*", ms=15, mec="k", label="recommendation")
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_title(title, fontsize=9)
    axes[1].legend(fontsize=7, loc="best")
    tr = eng.transfer
    if tr is not None:
        fig.suptitle(
            f"transfer weight {tr.weight:.2f} (the prior is {'used' if tr.used else 'set aside'}), "
            f"scale {tr.b:.2f} ± {tr.b_sd:.2f}, offset {tr.a:.3g} (source units)",
            fontsize=10,
        )
    fig.tight_layout()
    path = out / "prior_posterior.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def campaign_status(campaign: Campaign) -> str:
    """One sentence on how the campaign ended, for the top of the page."""
    scored = campaign.scored()
    trials = [t for t in campaign.trials if t.kind != 2]
    failed = [t for t in trials if t.status == "failed"]
    open_ = [t for t in campaign.trials if t.status == "proposed"]
    if not scored:
        if failed:
            last = failed[-1].reason or "no reason given"
            return f"No valid run: all {len(failed)} trials failed (the last: {last}). Nothing to model."
        return "No valid run yet: nothing to model."
    text = f"{len(scored)} of {len(trials)} trials scored"
    if failed:
        text += f", {len(failed)} failed"
    broke = [t for t in scored if t.violations]
    if broke:
        text += f", {len(broke)} broke an outcome limit (trials {', '.join(str(t.trial_id) for t in broke)})"
    if len(scored) == 1:
        text += ". One valid run: the model is flat, no optimum can be located from it"
    if campaign.recommendation is None:
        if campaign.paused:
            text += (
                f"; paused: the ECU link stayed down ({campaign.paused[:200]}); launch again with this campaign "
                "folder to resume it"
            )
        else:
            text += "; no recommendation yet" + (" (a trial is in progress)" if open_ else "")
    return text + "."


def progress_by_run(campaign: Campaign, truth: Any) -> list[float]:
    """The true gap of the recommendation the engine makes after each scored run (in trial order)."""
    from bac_agent.bo import Engine, EngineConfig

    scored = campaign.scored()
    if campaign.strategy != "bo" or not scored:
        return []
    names = list(truth.names)
    eng = Engine(
        campaign.definition,
        EngineConfig.from_dict(
            {**campaign.engine_options, "budget": max(1, len(campaign.trials)), "seed": campaign.seed}
        ),
    )
    recs = []
    for t in scored:
        eng.tell(t.params, t.j, t.outcomes)
        recs.append([eng.recommend().params[n] for n in names])
    return [float(g) for g in truth.gap(truth.true_j(np.array(recs, dtype=float)))]


def summary(campaign: Campaign, truth: Any | None) -> dict[str, Any]:
    scored = campaign.scored()
    s: dict[str, Any] = {
        "campaign_id": campaign.campaign_id,
        "strategy": campaign.strategy,
        "status": campaign_status(campaign),
        "trials": len([t for t in campaign.trials if t.kind != 2]),
        "scored_trials": len(scored),
        "runs_driven": sum(max(t.attempts, 1 if t.status == "scored" else 0) for t in campaign.trials),
        "failed_trials": sum(t.status == "failed" for t in campaign.trials),
        "limit_breaking_trials": [t.trial_id for t in scored if t.violations],
        "best_observed_j": min((t.j for t in scored), default=math.nan),
        "recommendation": campaign.recommendation,
    }
    if truth is not None and campaign.recommendation:
        names = list(truth.names)
        rec = campaign.recommendation["params"]
        jt = float(truth.true_j(np.array([[rec[n] for n in names]]))[0])
        s["true_j_of_recommendation"] = jt
        s["gap"] = float(truth.gap(jt))
        s["j_star"] = float(truth.j_star)
        if scored:
            best = min(scored, key=lambda t: t.j)
            jb = float(truth.true_j(np.array([[best.params[n] for n in names]]))[0])
            s["true_j_of_best_observed"] = jb
            s["gap_of_best_observed"] = float(truth.gap(jb))
    if truth is not None and scored:
        from bac_common.progress import runs_to_optimum, runs_to_stay_found

        gaps = progress_by_run(campaign, truth)
        if gaps:
            s["gap_after_each_run"] = gaps
            s["runs_to_optimum"] = runs_to_optimum(gaps)
            s["runs_to_stay_found"] = runs_to_stay_found(gaps)
    return s


def _table(rows: list[list[str]], header: list[str]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def write_html(
    campaign: Campaign,
    out: Path,
    figures: Sequence[Path],
    summ: dict[str, Any],
    base_summ: dict[str, Any] | None,
    notes: Sequence[str] = (),
) -> Path:
    names = list(campaign.names)
    outcome_names = sorted({k for t in campaign.trials for k in t.outcomes})
    rows = []
    for t in campaign.trials:
        rej = "; ".join(f"run {a}: {html.escape(r)}" for a, r in t.rejected)
        broke = "; ".join(html.escape(v) for v in t.violations)
        rows.append(
            [
                str(t.trial_id),
                KIND_NAMES.get(t.kind, str(t.kind)),
                *[f"{t.params.get(n, math.nan):.4g}" for n in names],
                f"{t.j:.5f}" if math.isfinite(t.j) else "-",
                f"{t.predicted_j:.5f}" if math.isfinite(t.predicted_j) else "-",
                *[f"{t.outcomes[k]:.4g}" if k in t.outcomes else "-" for k in outcome_names],
                str(t.attempts),
                html.escape(t.status + (f": {t.reason}" if t.reason else ""))
                + (f"<br><b style='color:#c00'>broke {broke}</b>" if broke else "")
                + (f"<br><small>{rej}</small>" if rej else ""),
            ]
        )
    trials_table = _table(rows, ["trial", "kind", *names, "J", "predicted J", *outcome_names, "runs", "status"])

    def summary_rows(s: dict[str, Any]) -> list[list[str]]:
        rec = s.get("recommendation") or {}
        out_rows = [
            ["strategy", html.escape(str(s["strategy"]))],
            ["trials", str(s["trials"])],
            ["runs driven", str(s["runs_driven"])],
            ["failed trials", str(s["failed_trials"])],
            ["best observed J", f"{s['best_observed_j']:.5f}" if math.isfinite(s["best_observed_j"]) else "none"],
        ]
        if rec:
            out_rows.append(["recommendation", html.escape(_fmt_params(rec.get("params", {}), 8))])
            rule = str(rec.get("rule") or "mean")
            out_rows.append(["recommendation rule", html.escape(f"{rule}: {RULE_TEXT.get(rule, rule)}")])
            out_rows.append(
                [
                    "predicted J",
                    f"{rec.get('predicted_j', math.nan):.5f} ± {rec.get('predicted_std', math.nan):.5f}",
                ]
            )
        limits = campaign.engine_options.get("constraints") or []
        if limits:
            broke = s.get("limit_breaking_trials") or []
            out_rows.append(
                [
                    "outcome limits",
                    html.escape(", ".join(limits))
                    + f" (level {campaign.engine_options.get('constraint_level', 0.05):g}); "
                    + (f"broken by trials {', '.join(map(str, broke))}" if broke else "no run broke one"),
                ]
            )
        for lim, p in (rec.get("predicted_outcomes") or {}).items():
            out_rows.append(
                [
                    f"recommendation: {html.escape(lim)}",
                    f"predicted {p.get('mean', math.nan):.4g} ± {p.get('std', math.nan):.2g}, "
                    f"P(broken) {p.get('p_violation_true', p.get('p_violation', math.nan)):.3f}"
                    + (f" (a run there measures beyond it: {p['p_violation']:.3f})" if "p_violation_true" in p else ""),
                ]
            )
        tr = rec.get("transfer") or {}
        if tr:
            out_rows.append(
                [
                    "transfer prior at the end",
                    f"weight {tr.get('transfer_weight', math.nan):.2f}, scale {tr.get('prior_scale', math.nan):.2f}"
                    f" ± {tr.get('prior_scale_sd', math.nan):.2f}, offset {tr.get('prior_offset', math.nan):.3g}",
                ]
            )
        if "true_j_of_recommendation" in s:
            out_rows.append(
                [
                    "true J of the recommendation",
                    f"{s['true_j_of_recommendation']:.5f} (J* = {s['j_star']:.5f})",
                ]
            )
            out_rows.append(["gap of the recommendation", f"{100 * s['gap']:.2f} %"])
        if "true_j_of_best_observed" in s:
            out_rows.append(["gap of the best observed trial", f"{100 * s['gap_of_best_observed']:.2f} %"])
        if "runs_to_optimum" in s:
            r, r2 = s["runs_to_optimum"], s["runs_to_stay_found"]
            out_rows.append(
                [
                    "optimum found (recommendation's gap <= 5 %)",
                    (f"first after {r:.0f} runs" if math.isfinite(r) else "not within these runs")
                    + (f", for good after {r2:.0f}" if math.isfinite(r2) else ""),
                ]
            )
        return out_rows

    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>bac campaign {html.escape(campaign.campaign_id)}</title>",
        "<style>body{font-family:sans-serif;max-width:1300px;margin:auto;padding:1em}"
        "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:3px 8px;font-size:13px}"
        "th{background:#eee}img{max-width:100%;border:1px solid #ddd;margin:0.5em 0}"
        ".status{font-size:1.1em;font-weight:bold}</style></head><body>",
        f"<h1>Calibration campaign {html.escape(campaign.campaign_id)}</h1>",
        f"<p>{html.escape(campaign.definition.description or campaign.definition.name)}; folder "
        f"<code>{html.escape(str(campaign.shown))}</code></p>",
    ]
    if base_summ is not None:
        bo, gr = summary_rows(summ), summary_rows(base_summ)
        keys = [r[0] for r in bo]
        gmap = {r[0]: r[1] for r in gr}
        parts.append("<h2>Summary: Bayesian optimization vs grid search</h2>")
        parts.append(_table([[k, v, gmap.get(k, "-")] for k, v in bo], ["", "BO (this campaign)", "grid baseline"]))
        _ = keys
    else:
        parts.append("<h2>Summary</h2>")
        parts.append(f"<p class='status'>{html.escape(summ.get('status', ''))}</p>")
        parts.append(_table(summary_rows(summ), ["", ""]))
    if notes:
        parts.append("<h2>Not shown</h2><ul class='notes'>")
        parts += [f"<li>{html.escape(n)}</li>" for n in notes]
        parts.append("</ul>")
    for f in figures:
        parts.append(f"<h3>{html.escape(f.stem.replace('_', ' '))}</h3><img src='{html.escape(f.name)}'>")
    parts.append("<h2>Trials</h2>")
    parts.append(trials_table)
    parts.append("</body></html>")
    path = out / "report.html"
    path.write_text("\n".join(parts))
    return path


def make_report(
    campaign_dir: str | Path,
    out: str | Path | None = None,
    truth_name: str | None = None,
    baseline_dir: str | Path | None = None,
    truth: Any | None = None,
) -> dict[str, Any]:
    """Write the campaign's report; the truth (true J, J*, J_med) is a simulated problem by name, or an object
    with the same interface (``names``, ``true_j``, ``theta_star``, ``j_star``, ``j_med``, ``gap``), e.g. a
    reduced definition's (:func:`bac_reduce.truth.definition_truth`). ``campaign_dir`` (and ``baseline_dir``) may
    be a bac export (``bac export``'s MDF4): its report goes to ``<file>.report/`` beside it unless ``out`` says."""
    with ExitStack() as stack:
        campaign = _open_campaign(Path(campaign_dir), stack)
        baseline = _open_campaign(Path(baseline_dir), stack) if baseline_dir else None
        if out:
            out_dir = Path(out)
        elif campaign.export is not None:
            out_dir = campaign.export.parent / f"{campaign.export.stem}.report"
        else:
            out_dir = campaign.path / "report"
        return _make_report(campaign, out_dir, truth_name, baseline, truth)


def _open_campaign(p: Path, stack: ExitStack) -> Campaign:
    """A campaign folder, or a bac export unpacked for as long as ``stack`` is open."""
    if p.is_file() and is_bac_export(p):
        folder, _ = stack.enter_context(unpacked_export(p, bags_too=False))
        try:
            campaign = load_campaign(folder)
        except BacError as exc:  # name the export, not the temporary folder it was unpacked into
            raise ReportError(str(exc).replace(f"{folder}/", f"{p}:").replace(str(folder), str(p))) from exc
        campaign.export = p
        campaign.segments = read_segments(p)
        return campaign
    return load_campaign(p)


def _make_report(
    campaign: Campaign, out_dir: Path, truth_name: str | None, baseline: Campaign | None, truth: Any | None
) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    if truth is None and truth_name:
        from bac_sim.problems import get_problem

        truth = get_problem(truth_name)
        _check_truth(campaign, truth_name, truth)
    if baseline is not None and set(baseline.names) != set(campaign.names):
        raise ReportError(
            f"--baseline {baseline.shown} tunes {', '.join(baseline.names)}; this campaign tunes "
            f"{', '.join(campaign.names)}: a baseline must search the same parameters"
        )
    figures: list[Path] = []
    c = plot_contour(campaign, out_dir, truth, baseline)
    if c is not None:
        figures.append(c)
    figures.append(plot_j_per_trial(campaign, out_dir, truth))
    pp = plot_prior_posterior(campaign, out_dir)
    if pp is not None:
        figures.append(pp)
    notes: list[str] = []
    sig, spec = plot_signals(comparison_signals(campaign, notes), out_dir)
    figures += [p for p in (sig, spec) if p is not None]
    summ = summary(campaign, truth)
    base_summ = summary(baseline, truth) if baseline is not None else None
    page = write_html(campaign, out_dir, figures, summ, base_summ, notes)
    result = {
        "html": str(page),
        "figures": [str(f) for f in figures],
        "summary": summ,
        "baseline": base_summ,
        "notes": notes,
    }
    (out_dir / "summary.json").write_text(json.dumps(result, indent=2, default=_json_default))
    return result


def _check_truth(campaign: Campaign, name: str, truth: Any) -> None:
    """``--truth NAME`` must be the campaign's own problem: the same parameters and, for a simulated campaign, the
    same scenario (outside review 2026-11-29: another definition's truth crashed with a KeyError, another scenario's
    gave a gap of 182 %)."""
    if set(truth.names) != set(campaign.names):
        meta = {p.name for p in campaign.definition.parameters} == set(truth.names)
        raise ReportError(
            f"--truth {name} is a problem over {', '.join(truth.names)}; this campaign tunes "
            f"{', '.join(campaign.names)}"
            + (
                ": meta-parameters of that problem's, judged by the reduced definition's truth (bac demo "
                "--definition prints its gap)"
                if meta
                else ""
            )
        )
    from bac_campaign.rescore import default_params_files
    from bac_measure.measure_config import load_node_params

    files = default_params_files(campaign.path)
    drove = str(load_node_params(files, "vehicle_sim").get("scenario", "")) if files else ""
    scenario = str(getattr(getattr(truth, "scenario", None), "name", ""))
    if drove and scenario and drove != scenario:
        raise ReportError(
            f"--truth {name} is the {scenario} scenario; this campaign drove the {drove} (vehicle_sim.scenario in "
            "its config/): its true J would be another problem's"
        )


def _json_default(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, np.floating | np.integer):
        return v.item()
    return str(v)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="bac report", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("campaign", type=Path, help="campaign folder, or its bac export (CAMPAIGN.mf4)")
    ap.add_argument("--truth", help="simulated problem for the true J (bump_c1, road_c1, road_c2)")
    ap.add_argument("--baseline", type=Path, help="a grid-search campaign folder (or its export) to compare with")
    ap.add_argument("--out", type=Path, help="output folder (default: CAMPAIGN/report, CAMPAIGN.report/ for an export)")
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        result = make_report(args.campaign, args.out, args.truth, args.baseline)
    except BacError as exc:
        sys.stderr.write(f"bac report: {exc}\n")
        return 2
    s = result["summary"]
    for note in result["notes"]:
        say(f"note: {note}")
    say(f"report: {result['html']}")
    if "gap" in s:
        say(f"recommendation true J {s['true_j_of_recommendation']:.5f}, gap {100 * s['gap']:.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
