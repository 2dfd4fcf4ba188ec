"""The whole simulation phase (paper sec. III-D): campaigns -> J_mu -> sensitivity -> reduction -> file -> checks.

:func:`run_reduction` is what ``bac reduce`` runs; every step is also usable alone
(:mod:`.campaigns`, :mod:`.analysis`). The result (:class:`ReductionResult`) holds
everything a report or a plot needs and serializes to JSON.

1. M independent BO campaigns of N trials on the full definition (noisy simulated runs).
2. ``J_i`` = each campaign's posterior mean at its recommendation ``θ_i``; ``θ̄`` = the
   ``θ_i`` of the smallest ``J_i``; ``J_mu`` = the average of the M posterior means.
3. One-at-a-time sensitivity curves of ``J_mu`` from ``θ̄``; significance (worst loss > T);
   similarity (near-optimal intervals within ε, checked by tied sweeps).
4. The meta-parameter file: a :class:`CalibrationDefinition` whose tuned dimensions are the
   groups (meta-parameters and kept single parameters) and whose other parameters are fixed
   (at ``θ̄``'s values by default: the best calibration the phase knows; or at their nominal
   values).
5. Checks that only a simulator allows: the same one-at-a-time sweep on the noise-free
   simulator (does the surrogate tell the truth?), and the validation table: BO on the reduced
   problem beside the full one (the true J of the recommendations, mean and standard deviation
   over repeats), the reduced problem's optimum (polished by a batched coordinate search on
   the noise-free simulator) and its median J (for the gap of the experimental phase).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bac_agent.bo import GP, EngineConfig, Hyper, SearchSpace
from bac_agent.bo.warp import OutputWarp
from bac_common.paramspace import CalibrationDefinition
from bac_reduce.analysis import (
    DEFAULT_EPSILON,
    DEFAULT_FLAT_TOL,
    DEFAULT_POINTS,
    DEFAULT_THRESHOLD,
    DEFAULT_TIE_TOL,
    Group,
    ReductionError,
    SensitivityCurves,
    check_ties,
    reduced_definition,
    sensitivity_curves,
    significant,
    similarity_groups,
)
from bac_reduce.campaigns import (
    CampaignResult,
    CampaignSettings,
    Progress,
    campaign_specs,
    run_campaigns,
)
from bac_reduce.objectives import BatchObjective, make_objective

FloatArray = NDArray[np.float64]

# The GP settings of the simulation phase's campaigns (20 dimensions, 100 noisy runs): the engine's model and
# acquisition with (a) the lengthscale prior scaled with the dimension, median sqrt(2 d) on the unit cube (Hvarfner
# et al. 2024, "vanilla BO in high dimensions"; the agent's default, sqrt(2) in any dimension, suits its 2-6
# dimensions on the car) and (b) a lighter hyperparameter search (from the prior mode and the previous fit only,
# at most 60 L-BFGS-B iterations; 512 + 256 acquisition candidates, 2 starts). Measured on road_c2, 5 campaigns
# of 100 trials, 4 asks per step: GP time 16 s CPU instead of 103 s with the agent's prior, true J of the
# recommendations 0.668 on average instead of 0.678 (docs/reduce.md). (c) the zero prior mean and plain log EI,
# with which the reduction's figures were measured (the agent's defaults are the bowl mean and noisy EI), and (d)
# no output warp: with the agent's Yeo-Johnson warp one run of `bac reduce` kept 8 of 20 parameters instead of 12
# and its reduced optimum was 0.6671 instead of 0.6495; the warp has not been measured here beyond that one run;
# (e) the initial design over the whole ranges (2 % off the faces), as measured; the agent's runs on the car start
# from 10 % inside every range (design_margin 0.1, issue 23), not measured here.
FAST_ENGINE: Mapping[str, Any] = {
    "gp": {
        "draws": 0,
        "restarts": 0,
        "maxiter": 60,
        "ls_loc": 0.5 * math.log(2.0),
        "ls_dim_scale": 0.5,
        "mean": "zero",
    },
    "acquisition": "ei",
    "n_candidates": 512,
    "n_local": 256,
    "acq_restarts": 2,
    "output_warp": "none",
    "design_margin": 0.02,
}


@dataclass(frozen=True)
class ReduceConfig:
    """Everything ``bac reduce`` can be told (see the CLI's --help for the meanings)."""

    problem: str = "road_c2"
    campaigns: int = 10  # M
    trials: int = 100  # N
    batch: int = 4  # asks per campaign per step (the validation campaigns too)
    n_initial: int = 0
    engine: Mapping[str, Any] = field(default_factory=lambda: dict(FAST_ENGINE))
    seed: int = 0
    threshold: float = DEFAULT_THRESHOLD  # T
    epsilon: float = DEFAULT_EPSILON  # ε, share of the range
    flat_tol: float = DEFAULT_FLAT_TOL
    tie_tol: float = DEFAULT_TIE_TOL
    points: int = DEFAULT_POINTS
    fixed_at: str = "optimum"  # discarded parameters at θ̄'s values ("optimum") or at "nominal"
    surrogate: str = "weighted"  # how J_mu averages the M posterior means: "weighted" (precision) or "mean"
    theta_bar: str = "simulator"  # θ̄ = the optimum with the least noise-free J ("simulator") or least J_i
    verify_points: int = 11  # noise-free simulator sweep from θ̄ (0 = skip)
    validate_repeats: int = 10  # BO campaigns on the reduced problem (0 = skip the validation)
    validate_trials: int = 30
    polish_iterations: int = 8  # batched coordinate-search steps for the reduced optimum
    workers: int | None = None
    scheduler: str | None = None
    group_size: int | None = None
    name: str = ""  # name of the reduced definition (default <base>_reduced)

    def __post_init__(self) -> None:
        if self.surrogate not in SURROGATES:
            raise ReductionError(f"surrogate must be one of {SURROGATES}, got {self.surrogate!r}")
        if self.theta_bar not in ("simulator", "posterior"):
            raise ReductionError(f"theta_bar must be 'simulator' or 'posterior', got {self.theta_bar!r}")
        if self.fixed_at not in ("optimum", "nominal"):
            raise ReductionError(f"fixed_at must be 'optimum' or 'nominal', got {self.fixed_at!r}")
        if self.campaigns < 1:
            raise ReductionError(f"need M >= 1 campaigns, got {self.campaigns}")
        if self.validate_repeats < 0 or (self.validate_repeats and self.validate_trials < 2):
            raise ReductionError("validation needs repeats >= 0 and at least 2 trials per repeat")

    def settings(self) -> CampaignSettings:
        return CampaignSettings(self.trials, self.n_initial, self.batch, dict(self.engine))

    def to_dict(self) -> dict[str, Any]:
        from dataclasses import asdict

        d = asdict(self)
        d["engine"] = dict(self.engine)
        return d


SURROGATES = ("weighted", "mean")


class PosteriorMean:
    """``J_mu(X)``: the average of the campaigns' GP posterior means (paper eq. 3), X in tuned units.

    Each campaign's GP is rebuilt from its observations and its last fitted hyperparameters (conditioning
    only: no refit, so each is exactly the posterior its campaign ended with). Two averages:

    * ``"mean"``: the plain average ``(1/M) Σ E[X_i]`` of eq. 3;
    * ``"weighted"`` (default): each posterior mean weighted by its precision ``1/Var[X_i]`` at the point,
      ``Σ E[X_i]/Var[X_i] / Σ 1/Var[X_i]``. Where every campaign has observations the two agree; where only
      some have (the campaigns explore different regions: that is why there are M of them), the plain
      average mixes in the others' prior means -- the mean of *their* runs, a constant -- and flattens
      every curve. On Controller II this flattening hid most of the sensitivity (docs/reduce.md).
    """

    def __init__(self, models: Sequence[tuple[SearchSpace, GP, OutputWarp]], mode: str = "weighted") -> None:
        if not models:
            raise ReductionError("J_mu needs at least one campaign")
        if mode not in SURROGATES:
            raise ReductionError(f"surrogate must be one of {SURROGATES}, got {mode!r}")
        self.models = list(models)
        self.mode = mode
        self.evaluations = 0

    @classmethod
    def from_campaigns(cls, campaigns: Sequence[CampaignResult], mode: str = "weighted") -> PosteriorMean:
        models = []
        for c in campaigns:
            state = json.loads(c.engine_state)
            space = SearchSpace.from_dict(state["space"])
            cfg = EngineConfig.from_dict(state["config"])
            if not state.get("hyper"):
                raise ReductionError(f"campaign {c.index} ended without a fitted GP")
            # the campaign's own output warp (a pure function of its runs), so that J_mu is in J
            warp = OutputWarp.for_runs(cfg.output_warp, c.y)
            gp = GP(cfg.gp).condition(space.to_unit(c.X), warp.forward(c.y), Hyper.from_dict(state["hyper"]))
            models.append((space, gp, warp))
        return cls(models, mode)

    def with_mode(self, mode: str) -> PosteriorMean:
        return PosteriorMean(self.models, mode)

    def predict_all(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Each campaign's posterior mean and standard deviation at X: two (M, n) arrays."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        means, stds = [], []
        for space, gp, warp in self.models:
            m, sd = warp.inverse_mean_std(*gp.predict(space.to_unit(X)))
            means.append(np.asarray(m, dtype=float))
            stds.append(np.asarray(sd, dtype=float))
        return np.array(means), np.array(stds)

    def __call__(self, X: FloatArray) -> FloatArray:
        means, stds = self.predict_all(X)
        self.evaluations += means.shape[1]
        if self.mode == "mean":
            return np.asarray(means.mean(axis=0))
        w = 1.0 / np.maximum(stds, 1e-12) ** 2
        return np.asarray(np.sum(w * means, axis=0) / np.sum(w, axis=0))


@dataclass
class Validation:
    """BO on the reduced problem beside the full one, and the reduced problem's references."""

    full_true_j: FloatArray  # (M,) true J of the full campaigns' recommendations
    reduced_true_j: FloatArray  # (R,) true J of the reduced campaigns' recommendations
    reduced_trials: int
    reduced_optimum: dict[str, float]  # tuned values of the best reduced calibration found
    j_star_reduced: float  # its true J (the reduced problem's J*, best known)
    j_med_reduced: float  # median true J over random reduced calibrations
    j_full_best: float  # the full problem's optimum as the phase found it: least true J of the M recommendations
    j_star_known: float  # the full problem's best known J* (the simulator's stored ground truth), NaN if none
    seconds: float
    sim_s: float
    gp_s: float

    @property
    def loss_pct(self) -> float:
        """How much worse the reduced problem's optimum is than the full problem's optimum found by the phase's
        BO campaigns, in % (negative: better). What the reduction costs against calibrating all parameters."""
        return 100.0 * (self.j_star_reduced - self.j_full_best) / self.j_full_best

    @property
    def loss_vs_known_pct(self) -> float:
        """The same against the best known J* of the full problem (NaN without a stored ground truth)."""
        return 100.0 * (self.j_star_reduced - self.j_star_known) / self.j_star_known

    @property
    def table_pct(self) -> float:
        """The paper's table: mean optimal J of BO on the reduced problem against BO on the full one, in %."""
        full = float(np.mean(self.full_true_j))
        return 100.0 * (float(np.mean(self.reduced_true_j)) - full) / full

    def table(self, dims_full: int, dims_reduced: int) -> str:
        def sd(x: FloatArray) -> float:
            return float(np.std(x, ddof=1)) if x.size > 1 else math.nan

        f, r = self.full_true_j, self.reduced_true_j
        return "\n".join(
            [
                "Parameters  Optimal J  Std     (true J of the recommendations; "
                "paper: 20 0.4917 0.0020, 3 0.4926 0.0004)",
                f"{dims_full:>10}  {np.mean(f):.4f}     {sd(f):.4f}  ({f.size} campaigns of the phase)",
                f"{dims_reduced:>10}  {np.mean(r):.4f}     {sd(r):.4f}  "
                f"({r.size} campaigns of {self.reduced_trials} trials on the reduced problem)",
            ]
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "full_true_j": self.full_true_j.tolist(),
            "reduced_true_j": self.reduced_true_j.tolist(),
            "reduced_trials": self.reduced_trials,
            "reduced_optimum": self.reduced_optimum,
            "j_star_reduced": self.j_star_reduced,
            "j_med_reduced": self.j_med_reduced,
            "j_full_best": self.j_full_best,
            "j_star_known": self.j_star_known,
            "loss_pct": self.loss_pct,
            "loss_vs_known_pct": self.loss_vs_known_pct,
            "table_pct": self.table_pct,
            "seconds": self.seconds,
            "sim_s": self.sim_s,
            "gp_s": self.gp_s,
        }


@dataclass
class ReductionResult:
    config: ReduceConfig
    base: CalibrationDefinition
    campaigns: list[CampaignResult]
    theta_bar_index: int
    curves: SensitivityCurves
    kept: tuple[str, ...]
    groups: list[Group]
    untied_groups: list[Group]  # the similarity step before the tie check
    definition: CalibrationDefinition
    timings: dict[str, float]
    backend: str
    true_curves: SensitivityCurves | None = None  # the same sweep on the noise-free simulator
    other_curves: SensitivityCurves | None = None  # the same sweep with the other average (for comparison)
    optima_true_j: FloatArray | None = None  # noise-free J of the M optima (when θ̄ is chosen by the simulator)
    validation: Validation | None = None

    @property
    def j_i(self) -> FloatArray:
        return np.array([c.j_pred for c in self.campaigns])

    @property
    def thetas(self) -> FloatArray:
        return np.array([c.theta for c in self.campaigns])

    @property
    def theta_bar(self) -> FloatArray:
        return self.campaigns[self.theta_bar_index].theta

    @property
    def dims_reduced(self) -> int:
        return len(self.definition.dimensions)

    def to_dict(self) -> dict[str, Any]:
        return {
            "config": self.config.to_dict(),
            "base": self.base.to_dict(),
            "campaigns": [c.to_dict() for c in self.campaigns],
            "theta_bar_index": self.theta_bar_index,
            "theta_bar": self.theta_bar.tolist(),
            "j_i": self.j_i.tolist(),
            "curves": self.curves.to_dict(),
            "kept": list(self.kept),
            "groups": [g.to_dict() for g in self.groups],
            "untied_groups": [g.to_dict() for g in self.untied_groups],
            "definition": self.definition.to_dict(),
            "timings": dict(self.timings),
            "backend": self.backend,
            "true_curves": self.true_curves.to_dict() if self.true_curves is not None else None,
            "other_curves": self.other_curves.to_dict() if self.other_curves is not None else None,
            "optima_true_j": self.optima_true_j.tolist() if self.optima_true_j is not None else None,
            "validation": self.validation.to_dict() if self.validation is not None else None,
        }


def _log_nothing(_: str) -> None:
    pass


def run_reduction(
    config: ReduceConfig,
    objective: BatchObjective | None = None,
    *,
    log: Callable[[str], None] = _log_nothing,
    on_progress: Callable[[Progress], None] | None = None,
    client: Any = None,
    campaigns: Sequence[CampaignResult] | None = None,
) -> ReductionResult:
    """Run the whole phase (see the module doc); with ``campaigns`` (e.g. from an earlier result.json)
    the campaigns are not run again and only the analysis, the file and the checks are made."""
    t_start = time.perf_counter()
    obj = objective if objective is not None else make_objective(config.problem)
    base = obj.definition
    if base.meta or set(base.tuned) != set(base.parameter_names):
        raise ReductionError(f"'{base.name}' is already reduced: the simulation phase starts from the full definition")
    names = tuple(d.name for d in base.dimensions)
    bounds = np.array([[d.lower, d.upper] for d in base.dimensions])
    if campaigns is None:
        log(
            f"simulation phase on {obj.label}: M = {config.campaigns} campaigns of N = {config.trials} trials, "
            f"{config.batch} ask(s) per step"
        )

    # 1. the campaigns (or those of an earlier run: only the analysis is done again)
    if campaigns is None:
        outcome = run_campaigns(
            obj,
            config.settings(),
            campaign_specs(config.campaigns, config.seed),
            noise_seed=config.seed,
            workers=config.workers,
            scheduler=config.scheduler,
            client=client,
            group_size=config.group_size,
            on_progress=on_progress,
        )
        campaigns = outcome.campaigns
        log(f"campaigns done in {outcome.wall_s:.1f} s on {outcome.backend}")
        backend = outcome.backend
        timings = {
            "campaigns_wall_s": outcome.wall_s,
            "campaigns_sim_s": outcome.sim_s,
            "campaigns_gp_s": outcome.gp_s,
        }
    else:
        campaigns = list(campaigns)
        if not campaigns or any(c.names != names for c in campaigns):
            raise ReductionError(f"the stored campaigns do not tune the dimensions of {base.name}: {names}")
        backend = "stored campaigns"
        timings = {"campaigns_wall_s": 0.0, "campaigns_sim_s": 0.0, "campaigns_gp_s": 0.0}
        log(f"re-analysing {len(campaigns)} stored campaigns")

    # 2. J_i, θ̄, J_mu
    t1 = time.perf_counter()
    j_i = np.array([c.j_pred for c in campaigns])
    optima_true_j: FloatArray | None = None
    if config.theta_bar == "simulator":
        ts = time.perf_counter()
        optima_true_j = np.asarray(obj.true_j(np.array([c.theta for c in campaigns])), dtype=float)
        timings["theta_bar_sim_s"] = time.perf_counter() - ts
        ibar = int(np.argmin(optima_true_j))
    else:
        ibar = int(np.argmin(j_i))
    theta_bar = campaigns[ibar].theta
    surrogate = PosteriorMean.from_campaigns(campaigns, config.surrogate)

    # 3. sensitivity, significance, similarity
    curves = sensitivity_curves(surrogate, theta_bar, bounds, names, config.points)
    other = "mean" if config.surrogate == "weighted" else "weighted"
    other_curves = sensitivity_curves(surrogate.with_mode(other), theta_bar, bounds, names, config.points)
    kept = significant(curves, config.threshold)
    untied = similarity_groups(curves, kept, config.epsilon, config.flat_tol) if kept else []
    groups = check_ties(surrogate, curves, untied, config.tie_tol) if untied else []
    if not groups:
        raise ReductionError(
            f"no parameter has a worst loss above T = {100 * config.threshold:g} % "
            f"(largest: {100 * float(np.max(curves.loss)):.2f} %): lower --threshold, or run longer campaigns"
        )

    # 4. the meta-parameter file
    if config.fixed_at == "optimum":
        fixed_values = {n: float(v) for n, v in zip(names, theta_bar, strict=True)}
    else:
        fixed_values = {p.name: p.nominal for p in base.parameters}
    summary = (
        f"{base.name} reduced by bac reduce: M={config.campaigns} N={config.trials} T={config.threshold:g} "
        f"eps={config.epsilon:g}; {len(kept)} of {len(names)} parameters kept, {len(groups)} tuned dimensions; "
        f"others fixed at the {'best calibration found' if config.fixed_at == 'optimum' else 'nominal values'}"
    )
    definition = reduced_definition(base, groups, fixed_values, config.name or None, summary)
    t_analysis = time.perf_counter() - t1
    log(f"J_mu and reduction in {t_analysis:.1f} s: kept {len(kept)}/{len(names)}, {len(groups)} tuned dimensions")

    timings["analysis_s"] = t_analysis
    result = ReductionResult(
        config,
        base,
        campaigns,
        ibar,
        curves,
        kept,
        groups,
        untied,
        definition,
        timings,
        backend,
        other_curves=other_curves,
        optima_true_j=optima_true_j,
    )

    # 5. checks on the noise-free simulator
    if config.verify_points:
        t2 = time.perf_counter()
        result.true_curves = sensitivity_curves(obj.true_j, theta_bar, bounds, names, config.verify_points)
        timings["verify_s"] = time.perf_counter() - t2
        log(f"noise-free one-at-a-time check in {timings['verify_s']:.1f} s")
    if config.validate_repeats:
        result.validation = validate(obj, result, log=log, on_progress=on_progress, client=client)
        timings["validate_s"] = result.validation.seconds
    timings["total_s"] = time.perf_counter() - t_start
    v = result.validation
    timings["sim_s"] = timings["campaigns_sim_s"] + timings.get("verify_s", 0.0) + (v.sim_s if v else 0.0)
    timings["gp_s"] = timings["campaigns_gp_s"] + t_analysis + (v.gp_s if v else 0.0)
    return result


# --- validation -------------------------------------------------------------------------------------------
def start_point(result: ReductionResult) -> dict[str, float]:
    """θ̄ seen through the reduced definition: single parameters at θ̄, meta-parameters at their tied optimum."""
    out: dict[str, float] = {}
    pos = {n: i for i, n in enumerate(result.curves.names)}
    metas = {tuple(m.members): m for m in result.definition.meta}
    for g in result.groups:
        if g.is_meta:
            m = metas[tuple(g.members)]
            out[m.name] = m.lower + g.value * (m.upper - m.lower)
        else:
            out[g.members[0]] = float(result.theta_bar[pos[g.members[0]]])
    return out


def polish(
    true_j: Callable[[FloatArray], FloatArray],
    start: FloatArray,
    bounds: FloatArray,
    iterations: int = 8,
    step: float = 0.125,
) -> tuple[FloatArray, float, int]:
    """Batched coordinate search on a noise-free J: each iteration evaluates ±step and ±step/2 along every
    dimension in ONE batch and moves to the best point; the step halves when nothing improves.
    Returns (best point, its J, evaluations)."""
    x = np.asarray(start, dtype=float).copy()
    lo, hi = bounds[:, 0], bounds[:, 1]
    d = x.size
    fx = float(true_j(x[None, :])[0])
    evals = 1
    h = step
    for _ in range(iterations):
        offsets = np.array([-h, -h / 2, h / 2, h]) * (hi - lo)[:, None]  # (d, 4)
        cand = np.repeat(x[None, :], 4 * d, axis=0)
        cand[np.arange(4 * d), np.repeat(np.arange(d), 4)] += offsets.ravel()
        cand = np.clip(cand, lo, hi)
        cand = np.unique(cand, axis=0)
        jc = np.asarray(true_j(cand), dtype=float)
        evals += cand.shape[0]
        k = int(np.argmin(jc))
        if jc[k] < fx:
            x, fx = cand[k], float(jc[k])
        else:
            h /= 2
    return x, fx, evals


def validate(
    obj: BatchObjective,
    result: ReductionResult,
    *,
    log: Callable[[str], None] = _log_nothing,
    on_progress: Callable[[Progress], None] | None = None,
    client: Any = None,
) -> Validation:
    """BO on the reduced problem beside the full one; the reduced problem's J* and J_med (see the module doc)."""
    cfg = result.config
    t0 = time.perf_counter()
    reduced = obj.with_definition(result.definition)
    dims = result.definition.dimensions
    rnames = [d.name for d in dims]
    rbounds = np.array([[d.lower, d.upper] for d in dims])
    sim_s = 0.0

    if result.optima_true_j is not None:
        full_true = result.optima_true_j
    else:
        ts = time.perf_counter()
        full_true = np.asarray(obj.true_j(result.thetas), dtype=float)
        sim_s += time.perf_counter() - ts

    settings = CampaignSettings(cfg.validate_trials, 0, cfg.batch, {})
    specs = [s for s in campaign_specs(cfg.validate_repeats, cfg.seed + 1)]
    log(f"validation: {cfg.validate_repeats} BO campaigns of {cfg.validate_trials} trials on the reduced problem")
    outcome = run_campaigns(
        reduced,
        settings,
        specs,
        noise_seed=cfg.seed + 1,
        workers=cfg.workers,
        scheduler=cfg.scheduler,
        client=client,
        on_progress=on_progress,
    )
    sim_s += outcome.sim_s
    gp_s = outcome.gp_s
    rthetas = np.array([c.theta for c in outcome.campaigns])

    # one batch: the recommendations, θ̄ seen through the reduced definition, random points for J_med
    sp = start_point(result)
    x0 = np.array([sp[n] for n in rnames])
    n_med = 128
    rng = np.random.default_rng(cfg.seed + 7)
    rand = rbounds[:, 0] + rng.random((n_med, len(rnames))) * (rbounds[:, 1] - rbounds[:, 0])
    ts = time.perf_counter()
    jj = np.asarray(reduced.true_j(np.vstack([rthetas, x0[None, :], rand])), dtype=float)
    sim_s += time.perf_counter() - ts
    red_true = jj[: len(rthetas)]
    j_med = float(np.median(jj[len(rthetas) + 1 :]))
    candidates = np.vstack([rthetas, x0[None, :]])
    jc = jj[: len(rthetas) + 1]
    best = int(np.argmin(jc))
    ts = time.perf_counter()
    x_opt, j_opt, _ = polish(reduced.true_j, candidates[best], rbounds, cfg.polish_iterations)
    sim_s += time.perf_counter() - ts

    ref = getattr(obj, "reference", lambda: None)()
    j_known = float(ref[0]) if ref is not None else math.nan
    v = Validation(
        full_true_j=full_true,
        reduced_true_j=red_true,
        reduced_trials=cfg.validate_trials,
        reduced_optimum={n: float(x) for n, x in zip(rnames, x_opt, strict=True)},
        j_star_reduced=float(j_opt),
        j_med_reduced=j_med,
        j_full_best=float(np.min(full_true)),
        j_star_known=j_known,
        seconds=time.perf_counter() - t0,
        sim_s=sim_s,
        gp_s=gp_s,
    )
    log(
        f"validation done in {v.seconds:.1f} s: reduced optimum {v.j_star_reduced:.4f} "
        f"({v.loss_pct:+.2f} % against the best full optimum found)"
    )
    return v
