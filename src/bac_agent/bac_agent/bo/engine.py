"""The ask/tell optimizer: paper algorithm 1's brain, without ROS.

>>> from bac_agent.bo import Engine
>>> eng = Engine({"damping_front": (0.0, 1.0), "damping_rear": (0.0, 1.0)}, budget=12, seed=1)
>>> while not eng.done:
...     p = eng.ask()
...     eng.tell(p, run_on_the_car(p))          # doctest: +SKIP
>>> eng.recommend()                             # doctest: +SKIP
Recommendation(params={...}, predicted_j=..., predicted_std=..., ...)

* the first ``n_initial`` asks are a space-filling design (a Latin hypercube);
* then a GP (Matérn-5/2 ARD, MAP hyperparameters, learned noise) is fitted to what
  was told (through a fitted Yeo-Johnson output warp, bo/warp.py), and the next
  point maximizes log Expected Improvement over the best *posterior mean* at an
  observed point (an incumbent that noise cannot fool);
  points asked but not yet told are "fantasized" at their posterior mean, so two
  asks in a row give two different points;
* the recommendation is the argmin of the posterior mean over the whole domain
  (the paper), with its predicted J and standard deviation;
* asks are quantized to the space's resolution and always within bounds, so the
  values told are the values the ECU holds.

The whole state (observations, failures, pending asks, the random generator, the
last hyperparameters) serializes to JSON; ``Engine.from_json(eng.to_json())``
continues exactly where ``eng`` was.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from bac_agent.bo.acquisition import NoisyEI, log_ei, log_ei_with_grad
from bac_agent.bo.blas import one_blas_thread
from bac_agent.bo.constraints import OutcomeLimit, OutcomeModels, parse_limits, violations
from bac_agent.bo.design import candidates, default_n_initial, initial_design
from bac_agent.bo.gp import GP, GPConfig, Hyper
from bac_agent.bo.prior import SourceSurface, TransferFit, TransferSettings, fit_with_source, without_source
from bac_agent.bo.space import SearchSpace
from bac_agent.bo.warp import WARPS, OutputWarp
from bac_common.errors import BacError

FloatArray = NDArray[np.float64]

STATE_VERSION = 1
VARIANT_RECOMMEND = ("best", "average")
VARIANT_MIN_SHARE = 1e-3  # prior_variants: models in the averaged acquisition down to this share of the most probable
PRIOR_N_INITIAL = 3  # initial design with a transfer prior: its argmin and two spread points (then the model)
KIND_INITIAL = "initial"
KIND_GUESS = "guess"  # a best guess given with the configuration (initial_points), asked first
KIND_PRIOR = "prior"  # the argmin of a transfer prior's source (the simulator's optimum), asked first
KIND_SAFE = "safe"  # a calibration known to keep the outcome limits (the ECU's baseline), asked first (safe_start)
KIND_OPTIMIZED = "optimized"
KIND_RANDOM = "random"
KIND_GRID = "grid"
ACQUISITIONS = ("ei", "nei")
RULES = ("mean", "observed", "best_run")  # Engine.recommend(rule)
# the GPConfig fields every saved whole GPConfig holds (EngineConfig.from_dict tells such a dump, which ran with the
# defaults of its day, from a partial override)
WHOLE_GP_KEYS = frozenset({"maxiter", "ls_loc", "ls_scale", "os_loc", "noise_loc", "noise_floor"})
TREND_MODEL = "the retreat's model with a linear trend"  # named in the least risky calibration's warning
# EngineConfig.limit_far_sd's default (see there; bo_agent's limit_far_sd)
LIMIT_FAR_SD = 2.0
# EngineConfig.limit_reach's default (see there)
LIMIT_REACH = 0.15
# a safe start's design grows from the runs that kept every limit by steps (SafeOpt's safe set, Sui et al. 2015: a
# calibration is safe when a safe run's margin to the limit exceeds the Lipschitz constant times the distance), not
# by the outcome model's extrapolation alone: fitted to a few runs close together it is confident far beyond them
# (a MAP lengthscale from 3 runs). The step from a run is at most SAFE_STEP (unit cube) and at most its margin to
# each limit over SAFE_LIPSCHITZ_FACTOR times the steepest slope seen between two runs (an estimate of the
# Lipschitz constant; pairs closer than SAFE_MIN_PAIR, where the scatter of a run dominates, left out)
SAFE_STEP = 0.25
SAFE_LIPSCHITZ_FACTOR = 1.5
SAFE_MIN_PAIR = 0.05
# the step from a run that kept the limits is at least SAFE_MIN_STEP (the scale below which a run's scatter hides
# the slope), and the outcome models must allow it: a run on the limit (margin 0, Lipschitz step 0) still grows the
# design by small steps where the models predict the limit kept (away from it), rather than repeating itself
SAFE_MIN_STEP = 0.05
# the steps towards the design point tried from each such run, as fractions of the reachable distance (0.9 at
# most: the edge of the step is where the estimated Lipschitz bound is used up; in 2-D, 100 seeds of the review's
# travel, the edge broke the limit in 13 of 500 runs, 0.9 in 9, Sobol points in the balls (before) in 8)
SAFE_LADDER = (0.9, 0.75, 0.5, 0.25)
# the exploration along the faces after a stall (EngineConfig.face_explore) acts up to this many dimensions: it was
# measured in 2-D and 3-D (issue 23); in many dimensions a face's most uncertain calibration is a jump across the box,
# and the recommendation it needs at every ask cost 10-70 % of an ask with 100 runs in 20-D
FACE_MAX_DIM = 4


class _VariantMean:
    """The posterior means of several sources' models averaged by their probabilities, in J, expressed in the
    standardized units of ``ref`` (the most probable source's model), with ``ref``'s standard deviation: what
    ``Engine._minimize_bound`` needs of a GP (``X``, ``predict_std_units``, ``predict_with_grad``)."""

    # one model as far as the lengthscale priors' model average goes (GPConfig.ls_average): the sources' models are
    # transfer models, fitted once
    alt: GP | None = None
    alt_weight: float = 0.0

    def __init__(self, ref: GP, members: list[tuple[float, GP]]) -> None:
        self.ref = ref
        self.X = ref.X
        total = sum(w for w, _ in members)
        # each member's standardized mean in ref's units: (y_mean_k + y_std_k m_k - y_mean_ref) / y_std_ref
        self.members = [(w / total, m, m.y_std / ref.y_std, (m.y_mean - ref.y_mean) / ref.y_std) for w, m in members]

    def predict_std_units(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        _, var = self.ref.predict_std_units(U)
        mu = sum(w * (c + k * m.predict_std_units(U)[0]) for w, m, k, c in self.members)
        return np.asarray(mu, dtype=float), var

    def predict_with_grad(self, U: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        _, sd, _, dsd = self.ref.predict_with_grad(U)
        mu = np.zeros(np.atleast_2d(U).shape[0])
        dmu = np.zeros(np.atleast_2d(U).shape)
        for w, m, k, c in self.members:
            mk, _, dmk, _ = m.predict_with_grad(U)
            mu += w * (c + k * mk)
            dmu += w * k * dmk
        return mu, sd, dmu, dsd


def _nei_mixture(
    neis: list[tuple[float, NoisyEI]],
) -> tuple[Callable[[FloatArray], FloatArray], Callable[[FloatArray], tuple[FloatArray, FloatArray]]]:
    """log of sum_i exp(log_w_i) NEI_i, the noisy EI averaged over several models with log weights, and its gradient
    (the model averages: with and without a transfer source, the lengthscale priors' fits, the prior variants)."""

    def values(U: FloatArray) -> FloatArray:
        return np.asarray(np.logaddexp.reduce([lw + nei(U) for lw, nei in neis], axis=0), dtype=float)

    def value_and_grad(U: FloatArray) -> tuple[FloatArray, FloatArray]:
        vg = [(lw + v, g) for lw, nei in neis for v, g in [nei.value_and_grad(U)]]
        v = np.logaddexp.reduce([a for a, _ in vg], axis=0)
        grad = sum(np.exp(a - v)[:, None] * g for a, g in vg)
        return np.asarray(v, dtype=float), np.asarray(grad, dtype=float)

    return values, value_and_grad


class EngineError(BacError, ValueError):
    """The optimizer was used wrongly (nothing told yet, a bad value, a bad saved state)."""


@dataclass(frozen=True)
class EngineConfig:
    """Configuration of a campaign's optimizer."""

    budget: int = 15  # trials of the campaign (told + failed)
    n_initial: int = 0  # initial design size; 0 = automatic (see design.default_n_initial)
    # the initial design spans [design_margin, 1 - design_margin] of every parameter's range: runs at the faces,
    # where J is steep, tell a few-run model little about where the minimum lies; 0.25 (2026-11-23, chosen on the
    # Controller I bump) kept it from optima at a face or a corner; 0.1 on the tuning split of the problem
    # families (issue 23, docs/agent.md)
    design_margin: float = 0.1
    seed: int = 0
    n_candidates: int = 1024  # space-filling candidates for the acquisition maximizer
    n_local: int = 256  # candidates around the best points
    acq_restarts: int = 4  # L-BFGS-B starts from the best candidates
    # L-BFGS-B iterations of the acquisition's maximizer (all starts at once): with outcome limits the log
    # probability of keeping them is a steep wall where the best points lie, and the last of 150-300 iterations
    # gained < 2 % of EI (issue 23's latency: 100 runs in 20-D, 2 limits); the result is never worse than the
    # best start
    acq_maxiter: int = 60
    recommend_beta: float = 0.0  # recommendation minimizes mean + beta * std (0: the paper's argmin of the mean)
    # how recommend() chooses (RULES): "mean" the argmin of the posterior mean over the domain (the paper; the
    # best rule on the tuning split of the problem families, issue 23), "observed" the driven calibration with the
    # best posterior mean, "best_run" the driven calibration with the best measured J
    recommend_rule: str = "mean"
    acquisition: str = "nei"  # "nei": noisy EI (sampled incumbents); "ei": log EI over the best posterior mean
    nei_samples: int = 64  # joint draws at the observed points for "nei"
    # with gp.mean == "bowl": the bowl is the prior mean while at most this many runs are told, then a constant
    # (a trend helps while runs are few; later it would only bias a model that the runs can carry); 0 = automatic:
    # the engine's own initial design + 1 (6 up to 4 dimensions; twice the design, 10, until 2026-11-24: the tuning
    # split of the problem families chose the shorter bowl, the optima at a corner of Controller II's box sooner)
    bowl_runs: int = 0
    # "yeo-johnson": the GP is fitted to the runs through a fitted power transform (bo/warp.py); "none": as told
    output_warp: str = "yeo-johnson"
    # best guesses (tuned values by name) asked first, in place of the first points of the initial design (the
    # paper's "best guess policy"): e.g. the simulation phase's optimum of a meta-parameter file
    initial_points: tuple[Mapping[str, float], ...] = ()
    gp: GPConfig = field(default_factory=GPConfig)
    # --- transfer (bo/prior.py): a model of J learned elsewhere (the simulator's surrogate, an earlier campaign),
    # SourceSurface.to_dict() over this space's unit cube; its argmin is the first run (unless initial_points are
    # given) and its shape the GP's prior mean while the car's runs support it
    prior: Mapping[str, Any] | None = None
    prior_weight: float = 0.5  # prior probability that the source describes this car
    prior_scale_sd: float = 0.5  # prior sd of the learned scale around 1
    prior_residual_os: float = 0.25  # prior median of the residual's variance (source-standardized units)
    prior_n_initial: int = 0  # initial design size with a prior (the source's argmin included); 0 = automatic
    # runs told up to which the source's trend may be the prior mean (while the runs support it); after them the
    # engine's own model of the car's runs alone; 0 = no limit (the default). Issue 23, tuning split of
    # bench/transfer.py: a source that is nearly right kept a weight of 0.94 and held the model near its own
    # optimum (road_c1 > 15 runs; 7 with 6, 6 with 4), but right after the switch the recommendation can jump
    # away from an optimum the source had right (test_prior.py): not the default (docs/agent.md)
    prior_runs: int = 0
    # while the runs support the source (weight >= 0.5), the acquisition is the expected improvement averaged over
    # the two models the weight weighs: with the source (weight w) and without it (1 - w), both on the source's
    # scale (Bayesian model averaging); False: the model with the source alone (before 2026-11-24, late). Issue 23,
    # tuning split of bench/transfer.py: a source right in shape but not at its optimum held the runs near its own
    # optimum (road_c1 > 15 runs with the simulator's prior; 4.5 averaged); docs/agent.md
    prior_average: bool = True
    # with prior_average and gp.ls_average > 0 (issue 23, 2026-11-25): the model without the source in that average
    # is itself the model average over the two lengthscale priors, as the engine's own model of the runs is (each
    # fit with half of its share 1 - w); False: one fit under gp.ls_scale's prior (before 2026-11-25; an engine
    # state or whole configuration saved before reads back False). Tuning split of bench/transfer.py, 5 designs:
    # the simulator's prior on road_c1 5 -> 4 runs, bump_c1 5 -> 4 (docs/agent.md)
    prior_average_ls: bool = True
    # further sources beside ``prior`` (each a SourceSurface.to_dict() over this space's unit cube): the simulation
    # phase run over the vehicle's uncertainty, e.g. K vehicles drawn within the car's tolerances besides the nominal
    # one. Each source is a model of the car (its own learned offset and scale, weighed as ``prior`` is); their
    # posterior probabilities share ``prior_weight`` equally a priori, the model is the most probable source's, the
    # acquisition the noisy EI averaged over every source's model and the model without a source (in J's units).
    # Run 1 stays ``prior``'s argmin. Empty (the default): ``prior`` alone. Issue 23; not the default: docs/agent.md
    prior_variants: tuple[Mapping[str, Any], ...] = ()
    # with prior_variants, the recommendation (rule "mean", no outcome limits): "best" the argmin of the most probable
    # source's model; "average" the argmin of the sources' posterior means averaged by their probabilities (in J)
    prior_variants_recommend: str = "best"
    # --- outcome constraints (bo/constraints.py): limits on measured outcomes besides J, e.g.
    # {"name": "max_travel_mm", "bound": 60.0, "upper": True}; a proposal's probability of breaking any is at
    # most constraint_level, and so is the recommendation's
    constraints: tuple[Any, ...] = ()  # OutcomeLimit, its dict, or text such as "max_travel_mm<=60"
    constraint_level: float = 0.05
    # what the simulator (or an earlier campaign) knows of a limited outcome: outcome name -> SourceSurface.to_dict()
    # of that outcome over this space's unit cube; its model's prior mean from the first run on (bo/constraints.py)
    outcome_priors: Mapping[str, Any] | None = None
    # a calibration known to keep the outcome limits (tuned values by name: the ECU's baseline, the calibration it
    # runs now). With limits of which one has no outcome prior (nothing known of it before run 1) it is run 1
    # (kind "safe"), in place of the nearest design point, and the initial design grows from it: each design point
    # is proposed once the outcome models allow it and it lies within a step of a run that kept the limits
    # (SAFE_STEP), else the nearest such calibration (safe exploration, as SafeOpt: Sui et al. 2015). Ignored
    # without limits or when every limited outcome has a prior. Not the default: docs/agent.md (issue 23)
    safe_start: Mapping[str, float] | None = None
    # with outcome limits, the retreat's model (the outcome's model plus a linear trend, slopes integrated out:
    # bo/constraints.py RETREAT_TREND_SD) judges more than the retreat (issue 23, 2026-11-25): during the initial
    # design a calibration is proposed only when it allows it too (a MAP fit to a few runs in one corner is confident
    # far beyond them: design points at the opposite face broke the limit by 8-15 mm with a predicted probability of
    # 2e-7), and whenever no calibration is within the level, also after a run kept the limits (a run that broke
    # a limit but measured inside it ended the retreat, and the constant-mean model's least risky calibrations then
    # hugged that run). Not with a safe start (its safe set bounds the proposals). Chosen on the tuning instances of
    # bench/outcome_limits.py (12 seeds: 12.2 % -> 11.2 % of the runs broke the limit, every final recommendation
    # kept it; docs/agent.md). False: as before 2026-11-25 (journals and engine states written before read back false)
    limit_trend: bool = True
    # > 0 (opt-in, off by default; issue 23, 2026-11-25): with limit_trend, after the initial design a calibration
    # farther than this (unit cube, Euclidean) from every run is proposed only when the retreat's model with a
    # linear trend allows it too. Far from the runs the outcome's constant-mean model reverts to the runs' mean: on
    # the tuning instances of bench/outcome_limits.py proposals more than 0.4 from every run broke the limit 13
    # times in 16 at a predicted probability <= 0.05 (jumps to the soft faces). 0.2 there: 492 -> 474 breaking runs
    # of 3600 (seeds 0-35), final keeps and gaps as before; a small gain, measured in 2-D only (in many dimensions
    # nearly every candidate is that far from every run): not the default (docs/agent.md)
    limit_trend_far: float = 0.0
    # > 0 (issue 23, 2026-11-25; the default since the same day's afternoon, 0 = off): with outcome limits and no
    # outcome prior nor safe start, after the initial design a proposal lies within this distance of a run that kept
    # every limit (as measured), once one has: the acquisition's jumps far from the runs that kept the limits are where
    # the outcome's model is least right (the tuning instances of bench/outcome_limits.py, 36 seeds: later proposals
    # within the level but 0.2 or more from every run broke the limit 19 times in 61). The distance is Euclidean in the
    # unit cube, given for 2 dimensions and scaled by sqrt(d / 2) in d (Engine.limit_reach_radius: the distances between
    # points of the unit cube grow as sqrt(d)). An ask where it leaves no candidate within the level goes without it (in
    # 20-D with 100 runs few candidates lie within its reach, and the least risky calibration anywhere was proposed
    # instead of the acquisition's); when none is within the level at all, the least risky calibration as before. 0.15
    # on the tuning instances: 427 -> 408 breaking runs of 3600, final keeps 171 of 180 as before, runs to the 2 mm
    # optimum 13 -> 12 (median), final gap 0.76 -> 0.78; held-out 10.8 % -> 10.0 %; the same cars with 2 and 4 weak
    # parameters more (d = 4, 6) no worse (docs/agent.md). An engine state or whole configuration saved before it reads
    # back 0
    limit_reach: float = LIMIT_REACH
    # >= 0 (issue 23, 2026-11-25): far from the runs a limited outcome's model (without an outcome prior) is widened:
    # its latent sd multiplied by 1 + limit_far_sd * rho, rho its posterior variance over the kernel's variance (0 at
    # a run, 1 far from every run), for the proposals and the recommendation. The constant-mean GP reverts to the
    # runs' mean away from them, and on the tuning instances of bench/outcome_limits.py (36 seeds) proposals 0.2 or
    # more from every run broke the limit 53 times in 152 at a summed predicted probability of 3.2 (calibration:
    # docs/agent.md). 2 there: 466 -> 425 breaking runs of 3600, final recommendations keeping the limit 166 -> 171
    # of 180, the runs to the constrained optimum (2 mm margin) as before, the final gap 0.63 -> 0.76; 3 broke
    # fewer (404) but cost those runs. Not with a safe start (its safe set bounds every proposal; as limit_trend).
    # 0: off (an engine state or a journal written before it reads back 0)
    limit_far_sd: float = LIMIT_FAR_SD
    # exploration along the faces after a stall (issue 23, 2026-11-25; the default since then, 0 = off, as before;
    # an engine state saved before it reads back with 0): when the recommendation (the argmin
    # of the posterior mean) lies on a face of the box (a parameter at a bound) and the last ``face_explore`` runs lie
    # within ``face_radius`` (unit cube, Euclidean) of it, the next run is the calibration with the largest posterior
    # standard deviation on the faces through the recommendation, among those farther than ``face_radius`` from
    # every run (and allowed by the outcome limits); when there is none, the acquisition's as usual. A calibration's
    # optimum often lies on a face (every Controller II meta-parameter instance: a narrow valley along the face
    # x0 = 0, J falling along it towards a corner while it rises inside the box): the GP, fitted mostly to runs
    # inside, carried the inside's trend on to the face and was confident there (gap 1.2 +- 0.2 predicted where the
    # optimum lay), so its EI refined a local minimum at the face's other end for up to 13 runs. Chosen on the tuning
    # split of the problem families (1 run, radius 0.2: Controller II bump -1.3 runs, road -0.4, no family worse by
    # more than 0.2 in the mean; docs/agent.md). Not with a safe start (its safe set bounds the proposals); only up to
    # FACE_MAX_DIM dimensions
    face_explore: int = 1
    face_radius: float = 0.2

    def __post_init__(self) -> None:
        if self.budget < 1:
            raise EngineError(f"budget must be >= 1, got {self.budget}")
        if self.bowl_runs < 0:
            raise EngineError(f"bowl_runs must be >= 0 (0 = automatic), got {self.bowl_runs}")
        if not 0.0 <= self.design_margin < 0.5:
            raise EngineError(f"design_margin must be in [0, 0.5), got {self.design_margin}")
        if self.acq_restarts < 1 or self.acq_maxiter < 1:
            raise EngineError(
                f"acq_restarts and acq_maxiter must be >= 1, got {self.acq_restarts} and {self.acq_maxiter}"
            )
        if self.n_initial < 0:
            raise EngineError(f"n_initial must be >= 0 (0 = automatic), got {self.n_initial}")
        if self.output_warp not in WARPS:
            raise EngineError(f"output_warp must be one of {', '.join(WARPS)}, got {self.output_warp!r}")
        if self.recommend_rule not in RULES:
            raise EngineError(f"recommend_rule must be one of {', '.join(RULES)}, got {self.recommend_rule!r}")
        if self.acquisition not in ACQUISITIONS:
            raise EngineError(f"acquisition must be one of {', '.join(ACQUISITIONS)}, got {self.acquisition!r}")
        if not 0.0 < self.prior_weight < 1.0:
            raise EngineError(f"prior_weight must be in (0, 1), got {self.prior_weight}")
        if not (self.prior_scale_sd > 0 and self.prior_residual_os > 0):
            raise EngineError("prior_scale_sd and prior_residual_os must be > 0")
        if self.prior_runs < 0:
            raise EngineError(f"prior_runs must be >= 0 (0 = no limit), got {self.prior_runs}")
        if self.prior_n_initial < 0:
            raise EngineError(f"prior_n_initial must be >= 0 (0 = automatic), got {self.prior_n_initial}")
        if self.prior_variants and self.prior is None:
            raise EngineError("prior_variants are further transfer sources beside prior: give prior too")
        if not all(isinstance(v, Mapping) for v in self.prior_variants):
            raise EngineError("prior_variants must be a list of source surfaces (SourceSurface.to_dict())")
        if self.prior_variants_recommend not in VARIANT_RECOMMEND:
            raise EngineError(
                f"prior_variants_recommend must be one of {', '.join(VARIANT_RECOMMEND)}, "
                f"got {self.prior_variants_recommend!r}"
            )
        if not 0.0 < self.constraint_level < 1.0:
            raise EngineError(f"constraint_level must be in (0, 1), got {self.constraint_level}")
        if self.face_explore < 0:
            raise EngineError(
                "face_explore must be >= 0 (0 = off; else the last runs that must lie near a face's "
                f"recommendation), got {self.face_explore}"
            )
        if not (math.isfinite(self.face_radius) and 0.0 < self.face_radius < 1.0):
            raise EngineError(f"face_radius must be in (0, 1) (unit cube, Euclidean), got {self.face_radius}")
        if not (math.isfinite(self.limit_trend_far) and self.limit_trend_far >= 0.0):
            raise EngineError(f"limit_trend_far must be >= 0 (0 = off), got {self.limit_trend_far}")
        if not (math.isfinite(self.limit_reach) and self.limit_reach >= 0.0):
            raise EngineError(f"limit_reach must be >= 0 (0 = off), got {self.limit_reach}")
        if not (math.isfinite(self.limit_far_sd) and self.limit_far_sd >= 0.0):
            raise EngineError(f"limit_far_sd must be >= 0 (0 = off), got {self.limit_far_sd}")
        limited = {lim.name for lim in parse_limits(self.constraints)}
        unknown = sorted(set(self.outcome_priors or {}) - limited)
        if unknown:
            raise EngineError(
                f"outcome priors for {', '.join(unknown)}, which no limit names (limits: {', '.join(sorted(limited))}"
                " or none): a prior is used by the model of a limited outcome only"
            )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["gp"] = asdict(self.gp)
        d["initial_points"] = [dict(p) for p in self.initial_points]
        d["constraints"] = [OutcomeLimit.from_spec(c).to_dict() for c in self.constraints]
        d["prior"] = dict(self.prior) if self.prior is not None else None
        if self.prior_variants:
            d["prior_variants"] = [dict(v) for v in self.prior_variants]
        else:  # the configuration of a campaign without them reads as before they existed
            d.pop("prior_variants")
            if self.prior_variants_recommend == "best":
                d.pop("prior_variants_recommend")
        d["outcome_priors"] = {k: dict(v) for k, v in self.outcome_priors.items()} if self.outcome_priors else None
        d["safe_start"] = dict(self.safe_start) if self.safe_start else None
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EngineConfig:
        data = dict(d)
        data["initial_points"] = tuple(
            {str(k): float(v) for k, v in p.items()} for p in data.get("initial_points") or ()
        )
        data["constraints"] = tuple(OutcomeLimit.from_spec(c).to_dict() for c in data.get("constraints") or ())
        if not isinstance(data.get("prior_variants") or (), list | tuple):
            raise EngineError("prior_variants must be a list of source surfaces (SourceSurface.to_dict())")
        data["prior_variants"] = tuple(data.get("prior_variants") or ())
        if data.get("safe_start"):
            data["safe_start"] = {str(k): float(v) for k, v in data["safe_start"].items()}
        if "n_candidates" in data and "limit_trend" not in data:  # a whole config saved before limit_trend existed
            data["limit_trend"] = False
        if "n_candidates" in data and "limit_far_sd" not in data:  # (the same for limit_far_sd)
            data["limit_far_sd"] = 0.0
        if "n_candidates" in data and "prior_average_ls" not in data:  # (the same for prior_average_ls)
            data["prior_average_ls"] = False
        if "n_candidates" in data and "face_explore" not in data:  # (the same: before the exploration along faces)
            data["face_explore"] = 0
        if "n_candidates" in data and "limit_reach" not in data:  # (the same: before limit_reach was the default)
            data["limit_reach"] = 0.0
        gp = dict(data.pop("gp", {}) or {})
        # a whole GPConfig saved (its oldest fields all there), not a partial override such as {"maxiter": 100},
        # which keeps today's defaults
        whole = gp.keys() >= WHOLE_GP_KEYS
        if whole and "bowl_loo" not in gp:  # a whole GPConfig saved before bowl_loo existed: it ran without
            gp["bowl_loo"] = False
        if whole and "ls_average" not in gp:  # a whole GPConfig saved before ls_average was the default
            gp["ls_average"] = 0.0
        for k in ("ls_bounds", "os_bounds", "warp_bounds"):
            if k in gp:
                gp[k] = tuple(gp[k])
        return cls(**data, gp=GPConfig(**gp))


@dataclass(frozen=True)
class Suggestion:
    """One ask: the parameters, why they were chosen and what the model expects."""

    params: dict[str, float]
    kind: str  # KIND_*
    predicted_j: float = math.nan
    predicted_std: float = math.nan
    # what the model knew when it chose: the transfer prior's weight, offset and scale; the outcomes' predicted
    # means and probabilities of breaking their limits; why a safer point was taken
    info: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Recommendation:
    """The campaign's answer: argmin of the posterior mean, with its prediction."""

    params: dict[str, float]
    predicted_j: float
    predicted_std: float
    n_observations: int
    best_observed_params: dict[str, float] | None = None
    best_observed_j: float = math.nan
    # with outcome limits: each limit's predicted mean, std and probability of being broken here
    predicted_outcomes: Mapping[str, Any] = field(default_factory=dict)
    # with a transfer prior: its weight, offset and scale when the recommendation was made
    transfer: Mapping[str, float] = field(default_factory=dict)
    rule: str = "mean"  # how it was chosen: mean (argmin over the domain), observed, best_run

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Observation:
    params: dict[str, float]
    value: float
    outcomes: Mapping[str, float] = field(default_factory=dict)  # measured besides J (peak_accel_z, ...)


@dataclass(frozen=True)
class Failure:
    params: dict[str, float]
    reason: str


class Engine:
    """Bayesian optimization by ask/tell over a :class:`SearchSpace` (see the module doc)."""

    def __init__(
        self,
        space: Any,
        config: EngineConfig | None = None,
        *,
        budget: int | None = None,
        n_initial: int | None = None,
        seed: int | None = None,
    ) -> None:
        self.space = SearchSpace.from_spec(space)
        cfg = config or EngineConfig()
        over: dict[str, Any] = {}
        if budget is not None:
            over["budget"] = int(budget)
        if n_initial is not None:
            over["n_initial"] = int(n_initial)
        if seed is not None:
            over["seed"] = int(seed)
        self.config = replace(cfg, **over) if over else cfg
        self.observations: list[Observation] = []
        self.failures: list[Failure] = []
        self.pending: list[dict[str, float]] = []
        self.rng = np.random.default_rng(self.config.seed)
        self._gp = GP(self.config.gp)
        self._gp_key: tuple[int, int] | None = None
        self._warp = OutputWarp()  # refitted with the GP; a pure function of the observations
        self._source = SourceSurface.from_dict(dict(self.config.prior)) if self.config.prior else None
        if self._source is not None and self._source.dim != self.space.dim:
            raise EngineError(
                f"the transfer prior has {self._source.dim} dimensions, this space {self.space.dim} ({self.names})"
            )
        self._variants = [SourceSurface.from_dict(dict(v)) for v in self.config.prior_variants]
        for i, src in enumerate(self._variants):
            if src.dim != self.space.dim:
                raise EngineError(
                    f"prior variant {i} has {src.dim} dimensions, this space {self.space.dim} ({self.names})"
                )
        # with prior_variants: the last weighing's models (source, its model, posterior probability), the most
        # probable source first; empty otherwise
        self._variant_models: list[tuple[SourceSurface, GP, float]] = []
        self._variant_best = 0  # the most probable source: 0 prior, i prior_variants[i - 1]
        self._variant_none = 0.0  # the posterior probability of the model without any source
        self._active_source = self._source
        self.transfer: TransferFit | None = None
        self._limits = parse_limits(self.config.constraints)
        outcome_sources = {
            str(k): SourceSurface.from_dict(dict(v)) for k, v in (self.config.outcome_priors or {}).items()
        }
        for k, src in outcome_sources.items():
            if src.dim != self.space.dim:
                raise EngineError(
                    f"the outcome prior of {k} has {src.dim} dimensions, this space {self.space.dim} ({self.names})"
                )
        self._outcomes = OutcomeModels(
            self._limits,
            self.config.constraint_level,
            outcome_sources,
            self.config.limit_far_sd,
        )
        self._outcome_key: tuple[int, int] | None = None
        self._design = initial_design(self.n_initial, self.space.dim, self.config.seed, self.config.design_margin)
        self._n_guess = 0
        self._guess_kind = KIND_GUESS
        guess_points: FloatArray | None = None
        if self.config.initial_points:
            guess_points = self.space.to_unit(np.array([self.space.to_array(p) for p in self.config.initial_points]))
        elif self._source is not None:
            u_src = self._source.argmin(self.config.seed)
            if self._outcomes.has_prior and not self._outcomes.allowed(u_src[None, :])[0]:
                u_src = self._source_argmin_allowed(u_src)
            guess_points = self.space.to_unit(self.space.from_unit(u_src)[None, :])
            self._guess_kind = KIND_PRIOR
        if guess_points is not None:
            guesses = guess_points
            n_g = min(guesses.shape[0], self._design.shape[0])
            # the guesses first; each takes the place of the design point nearest to it, the rest still spans
            remaining = list(range(self._design.shape[0]))
            for g in guesses[:n_g]:
                remaining.remove(min(remaining, key=lambda i: float(np.sum((self._design[i] - g) ** 2))))
            self._design = np.vstack([guesses[:n_g], self._design[remaining]])
            self._n_guess = n_g
        self._n_safe = 0
        self._reach_dropped = False  # limit_reach left out of one ask (see _maximize_acquisition)
        if self.safe_start_used:
            self._start_safe()
            for m in self._outcomes.models:  # the safe set bounds every proposal: the models are not widened
                m.far_sd = 0.0

    @property
    def safe_start_used(self) -> bool:
        """A safe start is given, limits are set and one limited outcome has no prior (see EngineConfig)."""
        return bool(self.config.safe_start) and any(m.source is None for m in self._outcomes.models)

    def _start_safe(self) -> None:
        """The safe calibration first, in place of the design point nearest to it (the guesses are kept)."""
        assert self.config.safe_start is not None
        u = self.space.to_unit(self.space.to_array(self.config.safe_start))
        rows = list(range(self._n_guess, self._design.shape[0])) or [self._design.shape[0] - 1]
        drop = min(rows, key=lambda i: float(np.sum((self._design[i] - u) ** 2)))
        self._design = np.vstack([u[None, :], np.delete(self._design, drop, axis=0)])
        self._n_safe = 1

    def _source_argmin_allowed(self, fallback: FloatArray) -> FloatArray:
        """The source's best calibration among those the outcome priors allow (Sobol candidates and the source's
        points; ``fallback``, its unconstrained argmin, when none is allowed)."""
        assert self._source is not None
        cand = np.vstack(
            [
                candidates(self.config.n_candidates, self.space.dim, np.random.default_rng(self.config.seed)),
                self._source.X,
            ]
        )
        ok = self._outcomes.allowed(cand)
        if not np.any(ok):
            return fallback
        s = np.where(ok, self._source.standardized(cand), np.inf)
        return np.asarray(cand[int(np.argmin(s))], dtype=float)

    # --- facts ------------------------------------------------------------------------
    @property
    def n_initial(self) -> int:
        if self.config.prior is not None and not self.config.n_initial:
            return self.config.prior_n_initial or max(2, min(PRIOR_N_INITIAL, self.config.budget // 2))
        return self.config.n_initial or default_n_initial(self.space.dim, self.config.budget)

    @property
    def limits(self) -> tuple[Any, ...]:
        """The outcome limits (bo.constraints.OutcomeLimit) of this campaign."""
        return self._limits

    @property
    def source(self) -> SourceSurface | None:
        """The transfer prior's source, if any."""
        return self._source

    @property
    def bowl_runs(self) -> int:
        """Runs told up to which a ``bowl`` prior mean is used (then a constant)."""
        if self.config.bowl_runs:
            return self.config.bowl_runs
        # the engine's own design (a transfer prior's shorter one is not counted: its bowl is kept as long)
        return (self.config.n_initial or default_n_initial(self.space.dim, self.config.budget)) + 1

    @property
    def prior_runs(self) -> int:
        """Runs told up to which a transfer prior's trend may be the prior mean (then the engine's own model)."""
        return self.config.prior_runs or self.config.budget  # 0: no limit (never more runs than the budget)

    def _transfer_dict(self) -> dict[str, float]:
        """The last weighing of the transfer prior, and whether the model uses its trend now (``prior_in_use``: 0
        once the runs reject it or after ``prior_runs`` runs, when the weight shown is that of the last weighing)."""
        assert self.transfer is not None
        in_use = self.transfer.used and len(self.observations) <= self.prior_runs
        out = {**self.transfer.to_dict(), "prior_in_use": 1.0 if in_use else 0.0}
        if self._variants and self._variant_models:  # which source the model is (0: prior, i: prior_variants[i-1])
            out["prior_source_index"] = float(self._variant_best)
            out["prior_source_weight"] = self._variant_models[0][2]
        return out

    def _gp_config(self) -> GPConfig:
        cfg = self.config.gp
        if cfg.mean == "bowl" and len(self.observations) > self.bowl_runs:
            return replace(cfg, mean=cfg.bowl_then)
        return cfg

    @property
    def n_trials(self) -> int:
        """Trials finished: told or failed."""
        return len(self.observations) + len(self.failures)

    @property
    def done(self) -> bool:
        return self.n_trials >= self.config.budget

    @property
    def names(self) -> tuple[str, ...]:
        return self.space.names

    def best_observed(self) -> Observation | None:
        return min(self.observations, key=lambda o: o.value) if self.observations else None

    # --- ask ----------------------------------------------------------------------------------
    def ask(self) -> dict[str, float]:
        """The next parameters to run, name -> value (fixed values included)."""
        return self.ask_with_info().params

    def ask_with_info(self) -> Suggestion:
        """The next parameters with the reason they were chosen and the model's prediction."""
        with one_blas_thread():
            return self._ask_with_info()

    def _ask_with_info(self) -> Suggestion:
        k = self.n_trials + len(self.pending)
        self._acq_info: dict[str, Any] = {}
        self._reach_dropped = False  # set for this ask when limit_reach leaves no candidate within the level
        s: Suggestion | None = None
        if self._n_safe and k == 1 and len(self.observations) == 1:
            self._say_safe_start_broke(self.observations[0])
        if k < self.n_initial and k < self._design.shape[0]:
            u = self._design[k]
            if self._n_safe and k >= self._n_safe and self._kept_runs().size:
                # from a safe start that kept the limits: the design point when it is allowed and within a step of
                # a run that kept them, else the nearest such calibration (the explored region grows outwards)
                v = self._grow_safe(u)
                if v is u:
                    s = self._suggest(u, self._guess_kind if k - self._n_safe < self._n_guess else KIND_INITIAL)
                else:
                    self._acq_info["design_point_skipped"] = "predicted to break an outcome limit, or not yet reached"
                    s = self._suggest(v, KIND_INITIAL)
            elif self._outcomes_known() and not self._design_allowed(u[None, :])[0]:
                # a design point the outcome models expect to break a limit: the model chooses instead (before it
                # can, the allowed calibration nearest to the design point); from a safe start always the nearest
                # allowed one: the explored region grows from the safe calibration towards the design's points
                self._acq_info["design_point_skipped"] = "predicted to break an outcome limit"
                if not self._can_model():
                    s = self._suggest(self._nearest_allowed(u), KIND_INITIAL)
            elif k < self._n_safe:
                s = self._suggest(u, KIND_SAFE)
            else:
                s = self._suggest(u, self._guess_kind if k - self._n_safe < self._n_guess else KIND_INITIAL)
        if s is None:
            if not self._can_model():
                safe = self._safe_set()
                u = self._random_allowed() if safe is None else self._grow_safe(self.rng.random(self.space.dim))
                s = self._suggest(u, KIND_RANDOM)
            else:
                s = self._suggest(self._maximize_acquisition(), KIND_OPTIMIZED)
        self.pending.append(dict(s.params))
        return s

    def _can_model(self) -> bool:
        """A model of J with a shape: two different runs, or a transfer prior the runs support (in use: it gives
        the shape). Else the posterior mean is flat and its argmin an arbitrary calibration."""
        if not self.observations:
            return False
        if len(self.observations) >= 2 and float(np.ptp([o.value for o in self.observations])) > 0.0:
            return True
        if self._source is None or len(self.observations) > self.prior_runs:
            return False
        self._model()  # the fit weighs the prior against the runs
        return self.transfer is not None and self.transfer.used

    def _outcomes_known(self) -> bool:
        """The outcome limits' models predict: runs were told, or a limit's outcome has a prior."""
        return bool(self._limits) and (bool(self.observations) or self._outcomes.has_prior)

    def _nearest_allowed(self, u: FloatArray) -> FloatArray:
        """The calibration nearest to ``u`` among Sobol candidates the outcome models allow (else the least likely
        to break a limit)."""
        cand = candidates(self.config.n_candidates, self.space.dim, self.rng)
        outc = self._outcome_models()
        p = outc.prob_violation(cand).max(axis=1)
        ok = (p <= outc.level) & self._design_allowed(cand)
        if not np.any(ok):
            # no run has kept every limit yet: the retreat (a linear trend gives it a direction); else the least risky
            # (with limit_trend judged by the retreat's model too)
            trend = self._trend_fallback()
            risk = outc.retreat_prob(cand) if trend else p
            i = int(np.argmin(risk))
            self._no_safe_candidate(float(risk[i]), TREND_MODEL if trend else "")
            return np.asarray(cand[i], dtype=float)
        d2 = np.where(ok, np.sum((cand - u) ** 2, axis=1), np.inf)
        return np.asarray(cand[int(np.argmin(d2))], dtype=float)

    @property
    def _limit_trend(self) -> bool:
        """``limit_trend`` in use: set, and no safe start (whose design and proposals SafeOpt's safe set bounds)."""
        return self.config.limit_trend and not self._n_safe

    def _design_allowed(self, U: FloatArray) -> NDArray[np.bool_]:
        """The outcome models allow the rows of ``U``; with ``limit_trend``, during the initial design (fewer runs told
        than ``n_initial``), the retreat's model with a linear trend must allow them too, and after it those farther
        than ``limit_trend_far`` from every run; with ``limit_reach``, after the design, only rows within
        ``limit_reach_radius`` (``limit_reach`` sqrt(d/2)) of a run that kept every limit (see EngineConfig)."""
        outc = self._outcome_models()
        ok = outc.allowed(U)
        n = len(self.observations)
        if self._limit_trend and 0 < n < self.n_initial:
            ok = ok & (outc.retreat_prob(U) <= outc.level)
        elif self._limit_trend and n and self.config.limit_trend_far > 0.0:
            # far from every run the constant-mean model reverts to the runs' mean: the trend judges there too
            X = self._obs_unit()
            d2 = np.min(np.sum((U[:, None, :] - X[None, :, :]) ** 2, axis=2), axis=1)
            chk = np.flatnonzero(ok & (d2 > self.config.limit_trend_far**2))
            if chk.size:
                ok = np.array(ok, dtype=bool)
                ok[chk] = outc.retreat_prob(U[chk]) <= outc.level
        near = self._within_reach(U, outc)
        if near is not None:
            ok = np.asarray(ok, dtype=bool) & near
        return np.asarray(ok)

    def _within_reach(self, U: FloatArray, outc: OutcomeModels) -> NDArray[np.bool_] | None:
        """With ``limit_reach`` in use (limits without an outcome prior nor a safe start, after the design, once a run
        kept every limit): the rows of ``U`` within its radius of such a run; else None."""
        kept = None if self._reach_dropped else self._reach_centres(outc)
        if kept is None:
            return None
        d2 = np.min(np.sum((U[:, None, :] - kept[None, :, :]) ** 2, axis=2), axis=1)
        return np.asarray(d2 <= self.limit_reach_radius**2)

    def _reach_centres(self, outc: OutcomeModels) -> FloatArray | None:
        """The runs (unit cube) that kept every limit, when ``limit_reach`` is in use (see :meth:`_within_reach`)."""
        if not (
            self.config.limit_reach > 0.0
            and len(self.observations) >= self.n_initial
            and not self._n_safe
            and not outc.has_prior
        ):
            return None
        kept = self._kept_runs()
        return kept if kept.shape[0] else None

    @property
    def limit_reach_radius(self) -> float:
        """``limit_reach``'s radius in this space (unit cube, Euclidean): the value given in 2-D, scaled by
        sqrt(d / 2) (a typical distance between points of the unit cube grows as sqrt(d)); 0 = off."""
        return self.config.limit_reach * math.sqrt(self.space.dim / 2.0)

    def _trend_fallback(self) -> bool:
        """The least risky calibration is judged by the retreat's model (a linear trend): while no run has kept every
        limit, and with ``limit_trend`` always."""
        return self._limit_trend or not self._kept_runs().size

    def _kept_runs(self) -> FloatArray:
        """The runs (unit cube) that kept every outcome limit as measured."""
        ok = self._outcomes.observed_ok([o.outcomes for o in self.observations])
        return self._obs_unit()[ok] if np.any(ok) else np.zeros((0, self.space.dim))

    def _safe_set(self) -> tuple[FloatArray, FloatArray] | None:
        """With a safe start, after its run kept the limits: the runs that kept every limit and their safe steps
        (the balls every proposal stays in); else None."""
        if not self._n_safe:
            return None
        kept, radii = self._safe_balls()
        return (kept, radii) if kept.size else None

    def _safe_balls(self) -> tuple[FloatArray, FloatArray]:
        """The runs that kept every limit and their safe steps (SAFE_MIN_STEP at least); none before such a run."""
        kept = self._kept_runs()
        return kept, (np.maximum(self._safe_radii(), SAFE_MIN_STEP) if kept.size else np.zeros(0))

    def _safe_radii(self) -> FloatArray:
        """How far (unit cube) the safe region reaches from each run that kept every limit (SAFE_STEP at most)."""
        ok = self._outcomes.observed_ok([o.outcomes for o in self.observations])
        U = self._obs_unit()
        r = np.full(int(np.sum(ok)), SAFE_STEP)
        d = np.sqrt(np.sum((U[:, None, :] - U[None, :, :]) ** 2, axis=2))
        far = d > SAFE_MIN_PAIR
        for lim in self._limits:
            v = np.array([float(o.outcomes.get(lim.name, math.nan)) for o in self.observations])
            dv = np.abs(v[:, None] - v[None, :])
            slopes = np.where(far & np.isfinite(dv), dv / np.where(far, d, 1.0), 0.0)
            slope = float(np.max(slopes)) if slopes.size else 0.0
            if slope <= 0.0:
                continue
            margin = (lim.bound - v[ok]) if lim.upper else (v[ok] - lim.bound)
            r = np.minimum(r, np.where(np.isfinite(margin), margin, 0.0) / (SAFE_LIPSCHITZ_FACTOR * slope))
        return r

    def _grow_safe(self, u: FloatArray) -> FloatArray:
        """``u`` itself when the outcome models allow it and it lies within the safe step of a run that kept every
        limit, else the allowed calibration nearest to ``u`` among candidates drawn inside those steps' balls (the
        point of each ball nearest to ``u``, points towards it at shorter steps, points uniform in each ball), else
        the least likely of those to break a limit: never a calibration outside the balls (2026-11-24: the
        candidates were Sobol points over the whole box, of which in 8-D about one in ten, in 20-D none fell in a
        ball, and then the least risky calibration anywhere was taken: jumps across the box)."""
        kept, radii = self._safe_balls()
        # every candidate as the ECU will hold it, rounded to the resolution: a point inside a ball may round out of
        # it (outside review D1: up to 0.06 of the box with a resolution of 0.1)
        cand = self._snap(np.vstack([u[None, :], self._safe_ball_candidates(u, kept, radii)]))
        outc = self._outcome_models()
        p = outc.prob_violation(cand).max(axis=1)
        near = _in_balls(cand, kept, radii)
        ok = (p <= outc.level) & near & ~self._near_failures(cand)
        if ok[0]:
            return np.asarray(cand[0], dtype=float)
        if not np.any(ok):
            if not np.any(near):  # no candidate rounds into a ball: the widest ball's own run, driven before
                j = int(np.argmax(radii))
                self._no_safe_candidate(float(outc.prob_violation(kept[j : j + 1]).max()))
                return np.asarray(kept[j], dtype=float)
            i = int(np.argmin(np.where(near, p, np.inf)))
            self._no_safe_candidate(float(p[i]))
            return np.asarray(cand[i], dtype=float)
        d2 = np.where(ok, np.sum((cand - u) ** 2, axis=1), np.inf)
        return np.asarray(cand[int(np.argmin(d2))], dtype=float)

    def _snap(self, U: FloatArray) -> FloatArray:
        """Unit-cube points as the ECU will hold them: clipped and rounded to each dimension's resolution."""
        return np.asarray(self.space.to_unit(self.space.from_unit(U)), dtype=float)

    def _safe_ball_candidates(
        self, u: FloatArray, kept: FloatArray, radii: FloatArray, rng: np.random.Generator | None = None
    ) -> FloatArray:
        """Candidates inside the balls (``radii``) around the runs that kept every limit, clipped to the box (the
        centres are in it, so a clipped point stays in its ball): for each ball the steps towards ``u`` of
        SAFE_LADDER times the reachable distance (the first is the ball's point nearest to ``u``), and points
        uniform in the ball (a random direction times r * U^(1/D)), n_candidates in all (16 per ball at least);
        drawn from ``rng`` (default: the engine's; the recommendation's own, which leaves the asks unchanged)."""
        n, dim = kept.shape
        diff = u[None, :] - kept
        dist = np.sqrt(np.sum(diff**2, axis=1))
        unit = diff / np.where(dist > 0.0, dist, 1.0)[:, None]
        reach = np.minimum(dist, radii)
        ladder = kept[:, None, :] + (np.asarray(SAFE_LADDER)[None, :, None] * reach[:, None, None]) * unit[:, None, :]
        m = max(16, self.config.n_candidates // max(n, 1))
        rng = self.rng if rng is None else rng
        g = rng.standard_normal((n, m, dim))
        g /= np.maximum(np.sqrt(np.sum(g**2, axis=2, keepdims=True)), 1e-12)
        rho = radii[:, None] * rng.random((n, m)) ** (1.0 / dim)
        ball = kept[:, None, :] + rho[:, :, None] * g
        return np.asarray(np.clip(np.vstack([ladder.reshape(-1, dim), ball.reshape(-1, dim)]), 0.0, 1.0), dtype=float)

    def _say_safe_start_broke(self, run: Observation) -> None:
        """The safe start's run broke a limit: said with the next proposal (the campaign logs it as a warning)."""
        broke = violations(self._limits, run.outcomes)
        if broke:
            self._acq_info["safe_start_broke"] = (
                f"the safe start broke {'; '.join(broke)}: it does not keep these limits; the next calibrations are "
                "those least likely to break them"
            )

    def _no_safe_candidate(self, p_violation: float, model: str = "") -> None:
        """Said with the proposal (the campaign logs it as a warning and journals it); ``model``: the model whose
        probability ``p_violation`` is, when not the outcome's own (the one that chose the calibration)."""
        self._acq_info["no_safe_candidate"] = (
            f"no calibration is predicted to keep every limit with probability >= "
            f"{1 - self.config.constraint_level:g}; the least risky one ({p_violation:.2f}"
            f"{' under ' + model if model else ''})"
        )

    def _least_risky(self, cand: FloatArray, risk: FloatArray, model: str) -> int:
        """The index of the candidate of least ``risk`` (a probability; inf = excluded) away from the failed runs,
        said with the proposal (:meth:`_no_safe_candidate`); when every candidate that is not excluded lies within
        0.01 of a failed run, the least risky of those, and the warning says so (before 2026-11-25 it said 'inf')."""
        near = self._near_failures(cand)
        masked = np.where(near, np.inf, risk)
        if np.any(np.isfinite(masked)):
            i = int(np.argmin(masked))
            self._no_safe_candidate(float(masked[i]), model)
            return i
        i = int(np.argmin(risk))
        self._no_safe_candidate(float(risk[i]), model)
        self._acq_info["no_safe_candidate"] += "; every candidate lies within 0.01 of a failed run"
        return i

    def _fallback_risk(self, cand: FloatArray, outc: OutcomeModels) -> FloatArray:
        """The risk by which the least risky calibration is chosen when none is within the level: with limit_trend the
        retreat's model's probability, else the outcome models'."""
        if self._limit_trend:
            return outc.retreat_prob(cand)
        return np.asarray(outc.prob_violation(cand).max(axis=1), dtype=float)

    def _random_allowed(self) -> FloatArray:
        """A random point, within the outcome limits' level when they are modelled."""
        if self._outcomes_known():
            cand = self.rng.random((256, self.space.dim))
            outc = self._outcome_models()
            p = outc.prob_violation(cand).max(axis=1)
            ok = p <= outc.level
            if np.any(ok):
                return np.asarray(cand[int(np.flatnonzero(ok)[0])], dtype=float)
            # the least risky; with limit_trend judged by the retreat's model (before: the constant-mean model's, the
            # calibration farthest from the runs after a run that broke a limit)
            risk = outc.retreat_prob(cand) if self._limit_trend else p
            i = int(np.argmin(risk))
            self._no_safe_candidate(float(risk[i]), TREND_MODEL if self._limit_trend else "")
            return np.asarray(cand[i], dtype=float)
        return self.rng.random(self.space.dim)

    def _suggest(self, u: FloatArray, kind: str) -> Suggestion:
        x = self.space.from_unit(u)
        params = self.space.to_params(x)
        mean, std = (math.nan, math.nan)
        info: dict[str, Any] = dict(getattr(self, "_acq_info", {}))
        U = self.space.to_unit(x)[None, :]
        if kind == KIND_OPTIMIZED and self._can_model():
            m, s = self._predict_j(U)
            mean, std = float(m[0]), float(s[0])
            if self.transfer is not None:
                info["transfer"] = self._transfer_dict()
        if self._outcomes_known():
            info["outcomes"] = self._outcome_models().describe(U)
            if "no_safe_candidate" in info:  # the user is told what the model expects there, with the numbers
                info["no_safe_candidate"] += "; each limit's own model (no trend) predicts there " + ", ".join(
                    f"{lim}: {v['mean']:.4g} +- {v['std']:.2g}" for lim, v in info["outcomes"].items()
                )
        return Suggestion(params, kind, mean, std, info)

    def _obs_unit(self) -> FloatArray:
        return self.space.to_unit(np.array([self.space.to_array(o.params) for o in self.observations]))

    def _model(self) -> GP:
        """The GP fitted to every observation (refitted only when they changed).

        With a transfer prior: the model with the source's trend when the runs support it (bo/prior.py),
        else the engine's own model (the bowl or a constant mean, the output warp)."""
        if not self.observations:
            raise EngineError("nothing has been told yet: tell() at least one result first")
        key = (len(self.observations), hash(tuple(o.value for o in self.observations)))
        if self._gp_key == key:
            return self._gp
        X = self._obs_unit()
        y = np.array([o.value for o in self.observations])
        if self._source is not None and len(self.observations) <= self.prior_runs:
            settings = TransferSettings(
                self.config.prior_weight,
                self.config.prior_scale_sd,
                self.config.prior_residual_os,
            )
            if self._variants:
                gp, fit = self._fit_with_variants(X, y, settings)
            else:
                gp, fit = fit_with_source(self.config.gp, X, y, self._source, settings, self.rng, self._gp.hyper)
            self.transfer = fit
            if fit.used:
                self._gp, self._warp, self._gp_key = gp, OutputWarp(), key
                return self._gp
        cfg = self._gp_config()
        if self._gp.config != cfg:
            self._gp = GP(cfg, hyper=self._gp.hyper)  # the last fit stays a start of the next one
        self._warp = OutputWarp.for_runs(self.config.output_warp, y)
        self._gp.fit(X, self._warp.forward(y), self.rng)
        self._gp_key = key
        return self._gp

    def _fit_with_variants(self, X: FloatArray, y: FloatArray, settings: TransferSettings) -> tuple[GP, TransferFit]:
        """``prior`` and ``prior_variants`` each weighed against the runs (``fit_with_source``); their posterior
        probabilities from ``prior_weight`` shared equally, against the model without a source (1 - prior_weight;
        the one ``prior`` is weighed against), all from their likelihoods of the runs in J's units. Returns the most
        probable source's model and a TransferFit
        whose weight is the probability that one of the sources describes the car (its offset and scale the most
        probable source's)."""
        assert self._source is not None
        sources = [self._source, *self._variants]
        fits = [fit_with_source(self.config.gp, X, y, s, settings, self.rng, self._gp.hyper) for s in sources]
        pw = self.config.prior_weight
        # each model's likelihood of the runs' contrasts in J's units (a source's restricted likelihood is on its own
        # standardized scale: minus (n - 1) log(scale)); the model without a source is the prior's (its Bayes factor's
        # other side); a Bayes factor of each source against its own model without it would compare the sources on
        # their scales' reference models instead of on the runs
        n1 = X.shape[0] - 1
        ll = np.array([f.log_lik - n1 * math.log(src.scale) for src, (_, f) in zip(sources, fits, strict=True)])
        f0 = fits[0][1]
        ll_none = f0.log_lik - f0.log_bayes_factor - n1 * math.log(sources[0].scale)
        logit = np.where(np.isnan(ll), -np.inf, ll) + math.log(pw / len(sources))
        log_none = ll_none + math.log1p(-pw) if math.isfinite(ll_none) else -np.inf
        if np.any(logit == np.inf):  # a source the runs make certain (round-off): it alone
            w = (logit == np.inf).astype(float) / float(np.sum(logit == np.inf))
            w_none = 0.0
        elif not np.any(np.isfinite(logit)):  # no source can describe the runs
            w, w_none = np.zeros(len(sources)), 1.0
        else:
            log_z = float(np.logaddexp.reduce(np.append(logit, log_none)))
            w, w_none = np.exp(logit - log_z), math.exp(log_none - log_z)
        # ties (to round-off: one run weighs no shape) keep prior first, then the order given
        order = np.argsort(-np.where(w >= w.max() * (1.0 - 1e-9), np.inf, w), kind="stable")
        best = int(order[0])
        gp, f = fits[best]
        total = float(min(1.0, np.sum(w)))
        # the sources' mixture against the model without a source
        lbf_mix = float(np.logaddexp.reduce(logit)) - math.log(pw) - ll_none if np.all(np.isfinite(ll)) else math.nan
        fit = replace(f, weight=total, log_bayes_factor=lbf_mix if math.isfinite(lbf_mix) else f.log_bayes_factor)
        self._variant_models = [(sources[i], fits[i][0], float(w[i])) for i in order]
        self._variant_none = float(w_none)
        self._active_source = sources[best]
        self._variant_best = best
        return gp, fit

    def _outcome_models(self) -> OutcomeModels:
        """The constrained outcomes' GPs, fitted to every observation (refitted when they changed)."""
        key = (len(self.observations), hash(tuple(tuple(sorted(o.outcomes.items())) for o in self.observations)))
        if self._outcome_key != key and self.observations:
            self._outcomes.fit(self._obs_unit(), [o.outcomes for o in self.observations], self.rng)
            self._outcome_key = key
        return self._outcomes

    def _predict_j(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and std at unit-cube points, in J (through the output warp's inverse)."""
        gp = self._model()
        if self._members(gp) is None:
            m, s = self._single(gp).predict(U)  # (GPConfig.ls_average: the fit whose weight is within 1e-6 of 1)
        else:
            mu, var = self._mean_var(gp, U)
            m, s = gp.y_mean + gp.y_std * mu, gp.y_std * np.sqrt(var)
        return self._warp.inverse_mean_std(m, s)

    def _members(self, gp: GP) -> tuple[float, GP] | None:
        """The model average over the two lengthscale priors (GPConfig.ls_average): (the tighter prior's weight,
        its fit), ``gp`` being the other; None when ``gp`` is a single model (the option off, a transfer prior's
        model, or a weight within 1e-6 of 0 or 1: then the model with the weight, to round-off)."""
        alt = gp.alt
        if alt is None or not 1e-6 < gp.alt_weight < 1.0 - 1e-6:
            return None
        return gp.alt_weight, alt

    def _single(self, gp: GP) -> GP:
        """The one model when the model average is a single model: ``gp``, or its tighter fit when its weight is
        within 1e-6 of 1 (GPConfig.ls_average)."""
        if gp.alt is not None and gp.alt_weight >= 1.0 - 1e-6:
            return gp.alt
        return gp

    def _mean_var(self, gp: GP, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and variance (standardized units) of the model average: the mixture's moments."""
        return _mixture_mean_var(self._single(gp), self._members(gp), U)

    def _mean_sd_grad(self, gp: GP, U: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The model average's posterior mean, std and their gradients (standardized units; the mixture's std)."""
        return _mixture_sd_grad(self._single(gp), self._members(gp), U)

    def _model_without_source(self, gp: GP) -> GP | None:
        """The other member of the transfer prior's model average (``prior_average``): the model the source was
        weighed against (a constant and a GP on the runs, on the source's scale), while the model with the source
        is in use (``gp``) and the model without it has a share of at least 1e-6 (below it the average is the
        model with the source to round-off: 100 runs of a right source give a weight of 1 - e^-127)."""
        tr = self.transfer
        if not self.config.prior_average or self._source is None or tr is None or tr.alt_hyper is None:
            return None
        if not tr.used or 1.0 - tr.weight < 1e-6 or gp.hyper is None or gp.hyper.prior is None:
            return None
        y = np.array([o.value for o in self.observations])
        assert self._active_source is not None
        return without_source(self.config.gp, gp.X, y, self._active_source, tr.alt_hyper)

    def _with_pending(self, gp: GP) -> GP:
        """``gp`` with the pending asks fantasized at its posterior mean (kriging believer); ``gp`` when none."""
        if not self.pending:
            return gp
        Xp = self.space.to_unit(np.array([self.space.to_array(p) for p in self.pending]))
        mp, _ = gp.predict(Xp)
        y_all = np.concatenate([gp.y_mean + gp.y_std * gp._z, mp])
        return GP(gp.config).condition(np.vstack([gp.X, Xp]), y_all, gp.hyper, scaling=(gp.y_mean, gp.y_std))

    def _averaged_nei(
        self, model: GP, alt: GP, incumbents: NDArray[np.bool_] | None
    ) -> tuple[Callable[[FloatArray], FloatArray], Callable[[FloatArray], tuple[FloatArray, FloatArray]]]:
        """log of the noisy EI averaged over the model with the source (``model``, weight w) and the model without
        it (``alt``, 1 - w): the expected improvement under the model average (both in the source's units, so
        their improvements add), and its gradient. Pending points are fantasized in ``alt`` as in ``model``."""
        assert self.transfer is not None
        self._acq_info["acquisition"] = (
            f"noisy EI averaged over the models with the transfer prior ({self.transfer.weight:.3f}) and without it"
        )
        w = self.transfer.weight
        tight = self._without_source_tight(model, alt)
        if tight is None:
            return self._nei_pair(model, alt, (math.log(w), math.log1p(-w)), incumbents)
        # prior_average_ls: the model without the source is the average of its fits under both lengthscale priors
        half = math.log1p(-w) + math.log(0.5)
        neis = [
            (math.log(w), NoisyEI(model, self.config.nei_samples, self.rng, incumbents)),
            (half, NoisyEI(self._with_pending(alt), self.config.nei_samples, self.rng, incumbents)),
            (half, NoisyEI(self._with_pending(tight), self.config.nei_samples, self.rng, incumbents)),
        ]

        return _nei_mixture(neis)

    def _without_source_tight(self, model: GP, alt: GP) -> GP | None:
        """``prior_average_ls``: the model without the source (``alt``'s data and scaling) fitted under the tighter
        lengthscale prior (sd ``gp.ls_average``, median ``gp.ls_average_median`` when set), its MAP fit from ``alt``'s
        hyperparameters (with fewer than 3 runs the prior's mode). None when the option is off, ``gp.ls_average`` is
        0 or with ``prior_variants`` (their own average)."""
        gcfg = self.config.gp
        if not self.config.prior_average_ls or gcfg.ls_average <= 0.0 or self._variants:
            return None
        assert self.transfer is not None and self.transfer.alt_hyper is not None and self._active_source is not None
        src = self._active_source
        y = np.array([o.value for o in self.observations])
        cfg = replace(gcfg, mean="constant", warp=False, ls_scale=gcfg.ls_average, ls_average=0.0)
        if gcfg.ls_average_median > 0.0:  # (as GP._fit_ls_average: the tighter prior's own median)
            cfg = replace(cfg, ls_loc=math.log(gcfg.ls_average_median) - gcfg.ls_dim_scale * math.log(alt.X.shape[1]))
        g = GP(cfg, hyper=self.transfer.alt_hyper)
        g._set_data(alt.X, y, (src.loc, src.scale))
        # (fewer than 3 runs: the prior's mode, as fit_with_source's models)
        v = g._map_hyper(self.rng) if y.size >= 3 else g._prior(alt.X.shape[1])[0]
        return without_source(cfg, alt.X, y, src, Hyper.from_vector(v))

    def _nei_pair(
        self, model: GP, alt: GP, log_w: tuple[float, float], incumbents: NDArray[np.bool_] | None
    ) -> tuple[Callable[[FloatArray], FloatArray], Callable[[FloatArray], tuple[FloatArray, FloatArray]]]:
        """log of the noisy EI averaged over two models, ``model`` (its pending asks already fantasized) and ``alt``
        (fantasized here as ``model``), with the log weights ``log_w`` (model's, alt's), and its gradient."""
        alt = self._with_pending(alt)
        nei1 = NoisyEI(model, self.config.nei_samples, self.rng, incumbents)
        nei0 = NoisyEI(alt, self.config.nei_samples, self.rng, incumbents)
        return _nei_mixture([(log_w[0], nei1), (log_w[1], nei0)])

    def _variants_nei(
        self, alt: GP | None, incumbents: NDArray[np.bool_] | None
    ) -> tuple[Callable[[FloatArray], FloatArray], Callable[[FloatArray], tuple[FloatArray, FloatArray]]]:
        """log of the noisy EI averaged over every source's model (``prior_variants``) and the model without a
        source (``alt``; None: negligible or ``prior_average`` off), by their posterior probabilities; each EI in
        J's units (its source's scale), so that they add. Members below VARIANT_MIN_SHARE of the most probable are
        left out (their share of the average is negligible; an NEI each costs an ask's time)."""
        assert self._active_source is not None
        members: list[tuple[float, GP]] = []
        top = max([w for _, _, w in self._variant_models] + [self._variant_none])
        for src, gp, w in self._variant_models:
            if w >= VARIANT_MIN_SHARE * top:
                members.append((math.log(w) + math.log(src.scale), self._with_pending(gp)))
        if alt is not None and self._variant_none >= VARIANT_MIN_SHARE * top:
            members.append(
                (math.log(self._variant_none) + math.log(self._active_source.scale), self._with_pending(alt))
            )
        neis = [(lw, NoisyEI(gp, self.config.nei_samples, self.rng, incumbents)) for lw, gp in members]
        self._acq_info["acquisition"] = (
            f"noisy EI averaged over {len(neis)} models (sources and none; the most probable source's share "
            f"{self._variant_models[0][2]:.3f})"
        )

        return _nei_mixture(neis)

    def _maximize_acquisition(self) -> FloatArray:
        gp = self._model()
        d = self.space.dim
        X_obs = gp.X
        mu_obs, _ = self._mean_var(gp, X_obs)
        best = float(np.min(mu_obs))
        model = self._with_pending(gp)
        if self.pending:
            best = float((np.min(model.predict(X_obs)[0]) - model.y_mean) / model.y_std)
        cand = candidates(self.config.n_candidates, d, self.rng)
        # local candidates around the best points by posterior mean
        assert gp.hyper is not None
        top = X_obs[np.argsort(mu_obs)[: min(5, X_obs.shape[0])]]
        scale = np.minimum(0.1 * gp.hyper.lengthscales, 0.1)
        idx = self.rng.integers(0, top.shape[0], self.config.n_local)
        local = np.clip(top[idx] + self.rng.standard_normal((self.config.n_local, d)) * scale, 0.0, 1.0)
        cand = np.vstack([cand, local])
        outc = self._outcome_models() if self._limits else None
        # a safe start: the proposals stay in the safe set after the design too (SafeOpt, Sui et al. 2015), each
        # within a safe step of a run that kept every limit; candidates drawn in those steps' balls besides
        safe = self._safe_set()
        if safe is not None:
            cand = np.vstack([cand, self._safe_ball_candidates(top[0], *safe)])
        incumbents = None
        if outc is not None:
            ok_obs = outc.observed_ok([o.outcomes for o in self.observations])
            incumbents = np.concatenate([ok_obs, np.zeros(len(self.pending), dtype=bool)])
            if ok_obs.any():
                best = float(np.min(model.predict_std_units(X_obs[ok_obs])[0]))
        acq_values: Callable[[FloatArray], FloatArray]
        acq_grad: Callable[[FloatArray], tuple[FloatArray, FloatArray]]
        if outc is not None and incumbents is not None and not incumbents.any():
            # no run has kept every limit yet: look for the calibration most likely to keep them
            if not np.any(outc.allowed(cand) & ~self._near_failures(cand)):
                # none is within the level: the retreat, in the direction the runs' values give (a linear trend)
                i = self._least_risky(cand, outc.retreat_prob(cand), TREND_MODEL)
                self._acq_info["acquisition"] = "retreat (no run has kept every limit yet)"
                return np.asarray(cand[i], dtype=float)

            def feasible_values(U: FloatArray) -> FloatArray:
                return outc.log_feasible_and_grad(U)[0]

            acq_values, acq_grad = feasible_values, outc.log_feasible_and_grad
            self._acq_info["acquisition"] = "feasibility (no run has kept every limit yet)"
        else:
            j_values: Callable[[FloatArray], FloatArray]
            j_grad: Callable[[FloatArray], tuple[FloatArray, FloatArray]]
            alt = self._model_without_source(gp)
            ls_mix = self._members(gp)
            if self.config.acquisition == "nei" and self._variants and self.transfer is not None and self.transfer.used:
                # every source's model (and the model without one while its share counts), also when the model
                # without a source is negligible or prior_average is off: the sources share the weight
                j_values, j_grad = self._variants_nei(alt, incumbents)
            elif self.config.acquisition == "nei" and alt is not None:
                j_values, j_grad = self._averaged_nei(model, alt, incumbents)
            elif self.config.acquisition == "nei" and ls_mix is not None:
                # the model average over the two lengthscale priors (GPConfig.ls_average)
                w_alt = ls_mix[0]
                j_values, j_grad = self._nei_pair(model, ls_mix[1], (math.log1p(-w_alt), math.log(w_alt)), incumbents)
                self._acq_info["acquisition"] = (
                    f"noisy EI averaged over the lengthscale priors' fits (the tighter one {ls_mix[0]:.3f})"
                )
            elif self.config.acquisition == "nei":
                if gp.alt is not None:  # (GPConfig.ls_average, one fit's weight within 1e-6 of 1: that fit)
                    model = self._with_pending(self._single(gp))
                nei = NoisyEI(model, self.config.nei_samples, self.rng, incumbents)
                j_values, j_grad = nei, nei.value_and_grad
            elif gp.alt is None:

                def j_values(U: FloatArray) -> FloatArray:
                    mu, var = model.predict_std_units(U)
                    return log_ei(mu, np.sqrt(var), best)

                def j_grad(U: FloatArray) -> tuple[FloatArray, FloatArray]:
                    return log_ei_with_grad(*model.predict_with_grad(U), best)

            else:  # "ei" with GPConfig.ls_average: the EI of the model average's moments (pending asks in both fits)
                mem = self._members(gp)
                base = model if self._single(gp) is gp else self._with_pending(self._single(gp))
                mix = None if mem is None else (mem[0], self._with_pending(mem[1]))
                X_inc = X_obs if incumbents is None or not incumbents.any() else X_obs[incumbents[: X_obs.shape[0]]]
                ei_best = float(np.min(_mixture_mean_var(base, mix, X_inc)[0]))

                def j_values(U: FloatArray) -> FloatArray:
                    mu, var = _mixture_mean_var(base, mix, U)
                    return log_ei(mu, np.sqrt(var), ei_best)

                def j_grad(U: FloatArray) -> tuple[FloatArray, FloatArray]:
                    return log_ei_with_grad(*_mixture_sd_grad(base, mix, U), ei_best)

            if outc is None:
                acq_values, acq_grad = j_values, j_grad
            else:  # weighted by the probability that every limit holds
                oc = outc

                def weighted_values(U: FloatArray) -> FloatArray:
                    return j_values(U) + oc.log_feasible_and_grad(U)[0]

                def weighted_grad(U: FloatArray) -> tuple[FloatArray, FloatArray]:
                    v, g = j_grad(U)
                    vf, gf = oc.log_feasible_and_grad(U)
                    return v + vf, g + gf

                acq_values, acq_grad = weighted_values, weighted_grad

        def allowed(U: FloatArray) -> NDArray[np.bool_]:
            ok = ~self._near_failures(U)
            if safe is not None:  # judged as the ECU will hold it: rounded to the resolution (outside review D1)
                ok &= _in_balls(self._snap(U), *safe)
            return ok & self._design_allowed(U) if outc is not None else ok

        face = self._face_candidates() if self.config.face_explore > 0 and safe is None and d <= FACE_MAX_DIM else None

        def face_proposal() -> FloatArray | None:
            """After a stall at a face of the box, the allowed calibration along it the model knows least of."""
            if face is None:
                return None
            face_ok = allowed(face)
            if not np.any(face_ok):
                return None
            sd = np.where(face_ok, self._mean_var(gp, face)[1], -np.inf)
            self._acq_info["acquisition"] = (
                "exploration along a face: the runs stalled at the recommendation on it (face_explore)"
            )
            return np.asarray(face[int(np.argmax(sd))], dtype=float)

        proposal = face_proposal()
        if proposal is not None:
            return proposal
        ok = allowed(cand)
        if not np.any(ok) and outc is not None and not self._reach_dropped and self._reach_centres(outc) is not None:
            # limit_reach leaves no candidate within the level (in many dimensions few lie within its reach): this ask
            # goes without it, as before it existed (the face exploration judged again too), rather than to the
            # least risky calibration anywhere; the proposal's record says so
            self._reach_dropped = True
            left_out = (
                f"no candidate within {self.limit_reach_radius:.3g} (limit_reach) of a run that kept every limit is "
                "within the level: this ask went without the reach"
            )
            proposal = face_proposal()
            if proposal is not None:
                self._acq_info["limit_reach_left_out"] = left_out
                return proposal
            ok = allowed(cand)
            if np.any(ok):  # (else nothing is within the level at all: the least risky calibration, which says so)
                self._acq_info["limit_reach_left_out"] = left_out
        if not np.any(ok):
            if outc is None:
                return self.rng.random(d)
            # nothing is within the level: the calibration least likely to break a limit
            worst = self._fallback_risk(cand, outc)
            if safe is not None:
                worst = np.where(_in_balls(self._snap(cand), *safe), worst, np.inf)
                if not np.any(np.isfinite(worst)):  # no candidate rounds into a ball: the widest ball's own run
                    self._no_safe_candidate(float(outc.prob_violation(safe[0]).max(axis=1).min()))
                    return np.asarray(safe[0][int(np.argmax(safe[1]))], dtype=float)
            i = self._least_risky(cand, worst, TREND_MODEL if self._limit_trend else "")
            return np.asarray(cand[i], dtype=float)
        acq = np.where(ok, acq_values(cand), -np.inf)
        order = np.argsort(-acq)
        starts = cand[order[: min(self.config.acq_restarts, int(np.sum(ok)))]]
        k = starts.shape[0]

        def f(flat: FloatArray) -> tuple[float, FloatArray]:
            lei, g = acq_grad(flat.reshape(k, d))
            return -float(np.sum(lei)), -g.ravel()

        res = minimize(
            f,
            starts.ravel(),
            jac=True,
            method="L-BFGS-B",
            bounds=[(0.0, 1.0)] * (k * d),
            options={"maxiter": self.config.acq_maxiter},
        )
        opt = np.clip(res.x.reshape(k, d), 0.0, 1.0)
        if safe is not None:  # the maximizer is bounded by the box only: back into the nearest ball
            opt = _into_balls(opt, *safe)
        both = np.vstack([opt, starts])
        acq2 = np.where(allowed(both), acq_values(both), -np.inf)
        acq2 = np.where(np.isfinite(acq2), acq2, -np.inf)
        i = int(np.argmax(acq2))
        if not np.isfinite(acq2[i]):
            return np.asarray(starts[0], dtype=float)
        return np.asarray(both[i], dtype=float)

    def _face_candidates(self) -> FloatArray | None:
        """After a stall at a face (EngineConfig.face_explore): candidates on the faces through the recommendation
        (each a parameter of it at its bound, 256 Sobol points each), farther than ``face_radius`` from every run and
        pending ask; None when the recommendation lies inside, the last runs do not all lie near it, or no
        candidate is that far."""
        n = self.config.face_explore
        if len(self.observations) < n:
            return None
        u_r = self._minimize_bound(self.config.recommend_beta, self._variant_mean())
        if u_r is None:
            return None
        lo, hi = u_r <= 1e-9, u_r >= 1.0 - 1e-9
        if not np.any(lo | hi):
            return None
        X = self._obs_unit()
        rho2 = self.config.face_radius**2
        if np.any(np.sum((X[-n:] - u_r) ** 2, axis=1) > rho2):
            return None
        # far from the pending asks and the failed runs too (outside review, 2026-11-25: a failed run at a face was
        # proposed again, 0.01 beside itself or exactly with a resolution, until max_consecutive_failures)
        others = [*self.pending, *(f.params for f in self.failures)]
        if others:
            X = np.vstack([X, self.space.to_unit(np.array([self.space.to_array(p) for p in others]))])
        d = self.space.dim
        rng = np.random.default_rng(self.config.seed + 104729 * len(self.observations))
        parts = []
        for i in np.flatnonzero(lo | hi):
            c = candidates(256, d, rng)
            c[:, i] = 0.0 if lo[i] else 1.0
            parts.append(c)
        C = np.vstack(parts)
        if any(dim.resolution > 0 for dim in self.space.dims):  # judged as the ECU will hold them
            C = self._snap(C)
        far = np.min(np.sum((C[:, None, :] - X[None, :, :]) ** 2, axis=2), axis=1) > rho2
        return C[far] if np.any(far) else None

    def _near_failures(self, U: FloatArray, radius: float = 0.01) -> NDArray[np.bool_]:
        if not self.failures:
            return np.zeros(U.shape[0], dtype=bool)
        F = self.space.to_unit(np.array([self.space.to_array(f.params) for f in self.failures]))
        d2 = np.sum((U[:, None, :] - F[None, :, :]) ** 2, axis=2)
        return np.asarray(np.any(d2 < radius**2, axis=1))

    # --- tell ---------------------------------------------------------------------------------
    def tell(self, params: Mapping[str, float], value: float, outcomes: Mapping[str, float] | None = None) -> None:
        """Record the (noisy) J measured with ``params``, and the run's other outcomes (for outcome limits)."""
        v = float(value)
        if not math.isfinite(v):
            raise EngineError(f"value must be finite, got {value!r}; use tell_failed() for a run without a result")
        x = self.space.to_array(params)
        p = self.space.to_params(x)
        out = {str(k): float(o) for k, o in (outcomes or {}).items() if o is not None}
        self._drop_pending(x)
        self.observations.append(Observation(p, v, out))

    def tell_failed(self, params: Mapping[str, float], reason: str) -> None:
        """Record that ``params`` could not be evaluated (never re-proposed exactly).

        The next ask fits the model again, as after a :meth:`tell` (the failure does not change the model's
        data, but a fit cached from before it would make the engine's state depend on more than what was
        told, the random generator and the last hyperparameters: see :meth:`ask_state`)."""
        x = self.space.to_array(params)
        self._drop_pending(x)
        self.failures.append(Failure(self.space.to_params(x), str(reason)))
        self._gp_key = None
        self._outcome_key = None  # the outcome limits' models too

    def _drop_pending(self, x: FloatArray) -> None:
        for i, p in enumerate(self.pending):
            if np.allclose(self.space.to_array(p), x, rtol=0.0, atol=1e-12):
                del self.pending[i]
                return

    def ask_state(self) -> dict[str, Any]:
        """What the next asks depend on besides the tells, as JSON: the random generator and the last fitted
        hyperparameters (the start of the next fit). A campaign journals it with each proposal; replaying the
        tells and :meth:`restore_ask` then asks what the uninterrupted engine would have (every fit after a
        tell or a failure starts again from these, so no other cached state matters)."""
        state: dict[str, Any] = {"rng": self.rng.bit_generator.state, "hyper": _hyper_state(self._gp.hyper)}
        if self._limits:
            # each outcome limit's model starts its next fit from its last hyperparameters too (issue 23)
            state["outcomes"] = [_hyper_state(m.gp.hyper) for m in self._outcomes.models]
        return state

    def restore_ask(self, params: Mapping[str, float], state: Mapping[str, Any] | None) -> None:
        """Replay an ask from a journal: ``params`` become pending as :meth:`ask` left them, and the random
        generator and the last hyperparameters are those :meth:`ask_state` gave right after it (``None``: a
        journal without them; the engine then goes on from its own state, and later asks differ from the
        uninterrupted run's)."""
        x = self.space.to_array(params)
        self.pending.append(self.space.to_params(x))
        if not state:
            return
        try:
            self.rng.bit_generator.state = dict(state["rng"])
            hyper = _hyper_of_state(state.get("hyper"))
            outcomes = [_hyper_of_state(h) for h in state.get("outcomes") or []]
        except (KeyError, TypeError, ValueError) as exc:
            raise EngineError(f"malformed journaled optimizer state: {exc}") from exc
        if outcomes and len(outcomes) != len(self._outcomes.models):
            raise EngineError(
                f"the journaled optimizer state holds {len(outcomes)} outcome models, this engine has "
                f"{len(self._outcomes.models)} outcome limits"
            )
        self._gp = GP(self._gp.config, hyper=hyper)
        self._gp_key = None
        for m, h in zip(self._outcomes.models, outcomes, strict=False):
            m.gp = GP(m.gp.config, hyper=h)
            m.n = 0
        self._outcome_key = None

    def forget_pending(self) -> None:
        """Drop every ask that was never told (e.g. abandoned trials)."""
        self.pending.clear()

    # --- the model's view ----------------------------------------------------------------------
    def predict(self, params: Mapping[str, float]) -> tuple[float, float]:
        """Posterior mean and standard deviation of J at ``params`` (with the output warp: the J at the
        warped posterior mean, i.e. the predictive median, and the std through the warp's slope)."""
        x = self.space.to_array(params)
        with one_blas_thread():
            m, s = self._predict_j(self.space.to_unit(x)[None, :])
        return float(m[0]), float(s[0])

    def predict_unit(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and std at unit-cube points (m, d), in J units (for plots)."""
        return self._predict_j(np.atleast_2d(U))

    @property
    def hyper(self) -> Hyper | None:
        return self._gp.hyper

    def _minimize_bound(self, beta: float, model: Any = None) -> FloatArray | None:
        """Unit-cube argmin of posterior mean + beta * std (multi-start L-BFGS-B), quantized; with outcome limits
        among the calibrations within the level (None when none is). ``model``: the GP's stand-in
        (``_VariantMean``)."""
        gp = self._model() if model is None else model
        d = self.space.dim
        rng = np.random.default_rng(self.config.seed + 7919 * len(self.observations))
        cand = np.vstack([candidates(self.config.n_candidates, d, rng), gp.X])
        # a safe start: the recommendation too lies in the safe set (SafeOpt), within a safe step of a kept run
        safe = self._safe_set()
        if safe is not None:
            kept_best = safe[0][int(np.argmin(self._mean_var(gp, safe[0])[0]))]
            cand = np.vstack([cand, self._safe_ball_candidates(kept_best, *safe, rng=rng)])
        mu, var = self._mean_var(gp, cand)
        score = mu + beta * np.sqrt(var)
        if safe is not None:
            score = np.where(_in_balls(cand, *safe), score, np.inf)
        outc = self._outcome_models() if self._limits else None
        log_ok = math.log(1.0 - self.config.constraint_level)
        if outc is not None:
            # the recommendation is judged on the calibration's true outcomes (latent variance): a run's
            # measurement noise is not the calibration's (proposals are judged on what a run measures)
            score = np.where(outc.allowed(cand, measured=False), score, np.inf)
            if not np.any(np.isfinite(score)):
                return None
        starts = cand[np.argsort(score)[: max(1, min(self.config.acq_restarts, int(np.sum(np.isfinite(score)))))]]
        k = starts.shape[0]

        def f(flat: FloatArray) -> tuple[float, FloatArray]:
            U = flat.reshape(k, d)
            m, s, dm, ds = self._mean_sd_grad(gp, U)
            val, grad = m + beta * s, dm + beta * ds
            if outc is not None:  # a penalty outside the level keeps the search where it may recommend
                lf, glf = outc.log_feasible_and_grad(U, measured=False)
                short = np.maximum(log_ok - lf, 0.0)
                val = val + 100.0 * short**2
                grad = grad - (200.0 * short)[:, None] * glf
            return float(np.sum(val)), grad.ravel()

        res = minimize(f, starts.ravel(), jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * (k * d))
        pts = np.vstack([np.clip(res.x.reshape(k, d), 0.0, 1.0), starts])
        if safe is not None:
            pts = _into_balls(pts, *safe)
        U = self._snap(pts)
        m, v = self._mean_var(gp, U)
        sc = m + beta * np.sqrt(v)
        if safe is not None:
            sc = np.where(_in_balls(U, *safe), sc, np.inf)
        if outc is not None:
            sc = np.where(outc.allowed(U, measured=False), sc, np.inf)
            if not np.any(np.isfinite(sc)):
                return None
        return np.asarray(U[int(np.argmin(sc))], dtype=float)

    def recommend(self, rule: str | None = None) -> Recommendation:
        """The campaign's answer, with its prediction. ``rule`` (None: the configuration's ``recommend_rule``):

        * ``mean`` (the paper, the default): argmin over the domain of the posterior mean (+ recommend_beta · std);
        * ``observed``: the driven calibration with the best posterior mean (what Ax recommends);
        * ``best_run``: the driven calibration with the best measured J.

        With outcome limits every rule keeps to calibrations within ``constraint_level`` (``observed`` and
        ``best_run``: to runs that kept every limit); when none is, the run that kept them with the best posterior
        mean, else the calibration least likely to break one.
        """
        rule = self.config.recommend_rule if rule is None else rule
        if rule not in RULES:
            raise EngineError(f"recommendation rule must be one of {', '.join(RULES)}, got {rule!r}")
        with one_blas_thread():
            return self._recommend(rule)

    def _recommend(self, rule: str = "mean") -> Recommendation:
        if not self.observations:
            raise EngineError("nothing has been told yet: tell() at least one result first")
        u: FloatArray | None = None
        if rule == "mean" and self._can_model():
            # (else: one run, or runs all equal, and no transfer prior in use: the posterior mean is flat, its
            # "argmin" would be an arbitrary calibration never driven; the driven one is the answer, issue 23)
            u = self._minimize_bound(self.config.recommend_beta, self._variant_mean())
        if u is None:
            u = self._best_observed_unit(by_model=rule != "best_run")
        x = self.space.from_unit(u)
        U = self.space.to_unit(x)[None, :]
        m, s = self._predict_j(U)
        mean, std = float(m[0]), float(s[0])
        best = self.best_observed()
        return Recommendation(
            params=self.space.to_params(x),
            predicted_j=mean,
            predicted_std=std,
            n_observations=len(self.observations),
            best_observed_params=dict(best.params) if best else None,
            best_observed_j=best.value if best else math.nan,
            predicted_outcomes=self._outcome_models().describe(U) if self._limits else {},
            transfer=self._transfer_dict() if self.transfer is not None and self._source is not None else {},
            rule=rule,
        )

    def _variant_mean(self) -> _VariantMean | None:
        """With prior_variants and ``prior_variants_recommend`` "average", while a source is in use and no outcome is
        limited: the sources' posterior means averaged by their probabilities (what the recommendation minimizes)."""
        if self.config.prior_variants_recommend != "average" or not self._variants or self._limits:
            return None
        gp = self._model()
        if self.transfer is None or not self.transfer.used or gp.hyper is None or gp.hyper.prior is None:
            return None
        return _VariantMean(gp, [(w, m) for _, m, w in self._variant_models])

    def _best_observed_unit(self, by_model: bool) -> FloatArray:
        """The driven calibration with the best posterior mean (``by_model``) or measured J, among the runs that
        kept every outcome limit (all runs when none did: then the least likely to break one)."""
        U = self._obs_unit()
        values = np.array([o.value for o in self.observations])
        if by_model:
            values = self._predict_j(U)[0]
        if self._limits:
            outc = self._outcome_models()
            ok = outc.observed_ok([o.outcomes for o in self.observations])
            if np.any(ok):
                values = np.where(ok, values, np.inf)
            else:
                return np.asarray(U[int(np.argmin(outc.prob_violation(U).max(axis=1)))], dtype=float)
        return np.asarray(U[int(np.argmin(values))], dtype=float)

    # --- state ------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "version": STATE_VERSION,
            "space": self.space.to_dict(),
            "config": self.config.to_dict(),
            "observations": [
                {"params": o.params, "value": o.value, **({"outcomes": dict(o.outcomes)} if o.outcomes else {})}
                for o in self.observations
            ],
            "failures": [{"params": f.params, "reason": f.reason} for f in self.failures],
            "pending": [dict(p) for p in self.pending],
            "rng": self.rng.bit_generator.state,
            "hyper": self._gp.hyper.to_dict() if self._gp.hyper is not None else None,
        }

    def to_json(self) -> str:
        return json.dumps(self.state_dict())

    @classmethod
    def from_state_dict(cls, data: Mapping[str, Any]) -> Engine:
        if data.get("version") != STATE_VERSION:
            raise EngineError(f"saved engine state has version {data.get('version')!r}, expected {STATE_VERSION}")
        try:
            eng = cls(SearchSpace.from_dict(data["space"]), EngineConfig.from_dict(data["config"]))
            eng.observations = [
                Observation(
                    dict(o["params"]),
                    float(o["value"]),
                    {str(k): float(v) for k, v in (o.get("outcomes") or {}).items() if v is not None},
                )
                for o in data["observations"]
            ]
            eng.failures = [Failure(dict(f["params"]), str(f["reason"])) for f in data["failures"]]
            eng.pending = [dict(p) for p in data["pending"]]
            eng.rng.bit_generator.state = data["rng"]
            if data.get("hyper"):
                eng._gp.hyper = Hyper.from_dict(data["hyper"])
        except (KeyError, TypeError, ValueError) as exc:  # (GPError is a ValueError)
            raise EngineError(f"malformed engine state: {exc}") from exc
        return eng

    @classmethod
    def from_json(cls, text: str) -> Engine:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise EngineError(f"engine state is not valid JSON: {exc}") from exc
        return cls.from_state_dict(data)


def _mixture_mean_var(gp: GP, mix: tuple[float, GP] | None, U: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean and variance (standardized units) of ``gp`` alone (``mix`` None) or of the mixture of ``gp`` (weight
    1 - w) and ``mix`` = (w, another GP on the same runs and scaling): the mixture's moments."""
    if mix is None:
        return gp.predict_std_units(U)
    w, alt = mix
    m0, v0 = gp.predict_std_units(U)
    m1, v1 = alt.predict_std_units(U)
    mu = (1.0 - w) * m0 + w * m1
    var = (1.0 - w) * (v0 + m0 * m0) + w * (v1 + m1 * m1) - mu * mu
    return mu, np.maximum(var, 1e-12 * min(v0.min(initial=1.0), v1.min(initial=1.0)))


def _mixture_sd_grad(
    gp: GP, mix: tuple[float, GP] | None, U: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Mean, std and their gradients of ``gp`` alone or of the mixture (as :func:`_mixture_mean_var`)."""
    if mix is None:
        return gp.predict_with_grad(U)
    w, alt = mix
    m0, s0, dm0, ds0 = gp.predict_with_grad(U)
    m1, s1, dm1, ds1 = alt.predict_with_grad(U)
    mu = (1.0 - w) * m0 + w * m1
    dmu = (1.0 - w) * dm0 + w * dm1
    var = (1.0 - w) * (s0 * s0 + m0 * m0) + w * (s1 * s1 + m1 * m1) - mu * mu
    dvar = (
        2.0 * (1.0 - w) * (s0[:, None] * ds0 + m0[:, None] * dm0)
        + 2.0 * w * (s1[:, None] * ds1 + m1[:, None] * dm1)
        - 2.0 * mu[:, None] * dmu
    )
    sd = np.sqrt(np.maximum(var, 1e-300))
    return mu, sd, dmu, dvar / (2.0 * sd[:, None])


def _in_balls(U: FloatArray, centres: FloatArray, radii: FloatArray) -> NDArray[np.bool_]:
    """Which rows of ``U`` lie within ``radii`` of one of ``centres`` (1e-9: rounding)."""
    d2 = np.sum((U[:, None, :] - centres[None, :, :]) ** 2, axis=2)
    return np.asarray(np.any(d2 <= radii[None, :] ** 2 + 1e-9, axis=1))


def _into_balls(U: FloatArray, centres: FloatArray, radii: FloatArray) -> FloatArray:
    """Each row of ``U`` outside every ball moved onto the nearest ball (towards its centre, 0.999 of its radius;
    the centres are in the box, so the point stays in it)."""
    diff = U[:, None, :] - centres[None, :, :]
    dist = np.sqrt(np.sum(diff**2, axis=2))
    j = np.argmin(dist - radii[None, :], axis=1)
    rows = np.arange(U.shape[0])
    dj, rj = dist[rows, j], radii[j]
    out = U.copy()
    far = dj > rj
    scale = (0.999 * rj[far] / dj[far])[:, None]
    out[far] = centres[j[far]] + scale * diff[rows[far], j[far]]
    return np.asarray(np.clip(out, 0.0, 1.0), dtype=float)


def _hyper_state(h: Hyper | None) -> dict[str, Any] | None:
    """The part of fitted hyperparameters the next fit starts from (Engine.ask_state), as JSON."""
    if h is None:
        return None
    state: dict[str, Any] = {
        "lengthscales": h.lengthscales.tolist(),
        "outputscale": h.outputscale,
        "noise": h.noise,
        "mean": h.mean,
    }
    if h.warp is not None:  # GPConfig.warp: the next fit starts from the learned warp too
        state["warp"] = h.warp.tolist()
    return state


def _hyper_of_state(h: Mapping[str, Any] | None) -> Hyper | None:
    if not h:
        return None
    return Hyper(
        np.asarray(h["lengthscales"], dtype=float),
        float(h["outputscale"]),
        float(h["noise"]),
        float(h.get("mean", 0.0)),
        warp=np.asarray(h["warp"], dtype=float) if h.get("warp") is not None else None,
    )
