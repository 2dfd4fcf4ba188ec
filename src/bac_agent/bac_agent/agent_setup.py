"""What ``bo_agent`` builds from its parameters before it touches the graph: the optimizer, the campaign's
configuration, the journal; pure Python, no rclpy (the node declares the parameters and wires the callbacks).

:func:`build_agent` takes the node's structural parameters (:class:`AgentSettings`) and returns an
:class:`AgentSetup`: the calibration definition, the opened journal, the optimizer (the BO engine with its
transfer prior, outcome priors and safe start; or a grid or random strategy) and the :class:`CampaignConfig`
whose ``extra`` is what the journal's ``campaign_started`` records and a resume is compared against. Resume
compatibility lives here too: a journal started before a feature existed (its ``campaign_started.config`` lacks
that feature's key) resumes as it ran, without the feature.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, cast

from bac_agent.bo.baselines import GridStrategy, RandomStrategy
from bac_agent.bo.constraints import parse_limits
from bac_agent.bo.engine import LIMIT_FAR_SD, LIMIT_REACH, Engine, EngineConfig
from bac_agent.bo.gp import GPConfig
from bac_agent.bo.prior import SourceSurface
from bac_agent.bo.space import SearchSpace
from bac_agent.campaign import ADDED_LATER, CampaignConfig, Optimizer
from bac_agent.journal import Journal
from bac_agent.transfer import load_outcome_sources, load_source
from bac_agent.transfer import summary as source_summary
from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition

_T = TypeVar("_T")

STRATEGIES = ("bo", "grid", "random")
START_FROM = ("guess", "design")
BACKSTOP_RUN_TIMEOUT_S = 3600.0  # run_timeout_s 0: the segmenter's verdict decides; this only guards a dead chain


@dataclass(frozen=True)
class AgentSettings:
    """``bo_agent``'s parameters that shape the campaign (their meaning: the node's parameter descriptions)."""

    definition_file: str = "controller_i"
    campaign_dir: str = "campaigns/default"
    campaign_id: str = ""
    strategy: str = "bo"
    budget: int = 15
    n_initial: int = 0
    seed: int = 0
    acquisition: str = "nei"
    recommend_beta: float = 0.0
    recommend_rule: str = "mean"
    gp_mean: str = "bowl"
    bowl_runs: int = 0
    gp_bowl_loo: bool = True
    gp_ls_average: float = 0.5
    face_explore: int = 1
    output_warp: str = "yeo-johnson"
    design_margin: float = 0.1
    start_from: str = "guess"
    prior_source: str = ""
    prior_weight: float = 0.5
    prior_runs: int = 0
    prior_average: bool = True
    prior_average_ls: bool = True
    constraints: tuple[str, ...] = ()
    constraint_level: float = 0.05
    safe_start: bool = False
    limit_trend: bool = True
    limit_far_sd: float = LIMIT_FAR_SD
    limit_trend_far: float = 0.0
    limit_reach: float = LIMIT_REACH
    grid_size: int = 4
    max_attempts: int = 3
    apply_timeout_s: float = 10.0
    apply_retries: int = 2
    run_timeout_s: float = 0.0
    confirmation_run: bool = False
    max_consecutive_failures: int = 3
    busy_retry_s: float = 2.0
    busy_timeout_s: float = 120.0
    link_retry_s: float = 2.0
    link_timeout_s: float = 600.0
    resume: bool = True


@dataclass
class AgentSetup:
    """What the node runs: the definition, the journal (open), the optimizer and the campaign's configuration."""

    definition: CalibrationDefinition
    campaign_dir: Path
    journal: Journal
    optimizer: Optimizer
    config: CampaignConfig
    prior_info: dict[str, Any] = field(default_factory=dict)
    outcome_sources: dict[str, SourceSurface] = field(default_factory=dict)
    # settings the node was given that a resumed journal overrides (it was started before the feature existed and
    # resumes as it ran): one sentence each, which the node logs as a warning
    resumed_as_journaled: list[str] = field(default_factory=list)

    def log_lines(self) -> list[str]:
        """The lines the node logs at its start: what runs, the transfer prior, the limits and their priors."""
        cfg, extra = self.config, self.config.extra
        lines = [
            f"bo_agent: definition '{self.definition.name}' ({', '.join(self.optimizer.names)}), strategy "
            f"{cfg.strategy}, budget {cfg.budget}, campaign '{cfg.campaign_id}' in {self.campaign_dir}"
        ]
        if self.prior_info:
            lines.append(
                f"transfer prior: {self.prior_info['label']}; its optimum {self.prior_info['optimum']} "
                f"(J {self.prior_info['optimum_j']:.4g}) is trial 1"
            )
        constraints = extra["constraints"]
        if constraints:
            lines.append(f"outcome limits: {', '.join(constraints)} (level {extra['constraint_level']:g})")
        if self.outcome_sources:
            lines.append("outcome priors: " + "; ".join(src.label for src in self.outcome_sources.values()))
        elif self.prior_info and constraints:
            lines.append("outcome priors: none (the prior source records no limited outcome)")
        return lines


def make_verifier(defn: CalibrationDefinition) -> Callable[[Mapping[str, float], Mapping[str, float]], str | None]:
    """Check the raw values the ECU echoed against the expansion of what was asked (within one LSB)."""

    def verify(params: Mapping[str, float], applied: Mapping[str, float]) -> str | None:
        if not applied:
            return None  # the bridge's success already says the ECU acknowledged these values
        expected = defn.expand(params)
        bad = []
        for name, value in applied.items():
            if name in expected:
                tol = defn.parameter(name).resolution * 1.01
                if abs(float(value) - expected[name]) > tol:
                    bad.append(f"{name}={value:g} (asked {expected[name]:g})")
        return ", ".join(bad) or None

    return verify


def build_agent(s: AgentSettings) -> AgentSetup:
    """Load the definition and the prior sources, open the journal, build the optimizer and the configuration.

    Raises :class:`BacError` (the journal closed again) when the campaign folder holds a journal and ``resume``
    is false; a prior source that cannot be read raises its own error (``TransferError``), the journal closed
    and, if it was empty, removed with the campaign folder if this call created it (nothing is left to resume)."""
    if s.strategy not in STRATEGIES:
        raise BacError(f"unknown strategy {s.strategy!r}: one of {', '.join(STRATEGIES)}")
    if s.start_from not in START_FROM:
        raise BacError(f"unknown start_from {s.start_from!r}: one of {', '.join(START_FROM)}")
    definition = CalibrationDefinition.load(resolve_definition(s.definition_file))
    cdir = Path(s.campaign_dir).expanduser()
    cid = s.campaign_id or cdir.resolve().name
    # a refused build removes an empty journal and a folder this call created: a wrong prior_source leaves no
    # empty journal.jsonl behind (before 2026-11-25 it did)
    created_dir = not cdir.exists()
    journal = Journal(cdir)
    empty_at_open = len(journal) == 0 and journal.path.stat().st_size == 0
    if len(journal) and not s.resume:
        journal.close()
        raise BacError(f"{cdir} already holds a campaign journal and resume is false: choose a new campaign_dir")
    try:
        return _build(s, definition, cdir, cid, journal)
    except BaseException:
        journal.close()
        _remove_if_empty(journal.path if empty_at_open else None, cdir if created_dir else None)
        raise


def _remove_if_empty(path: Path | None, folder: Path | None) -> None:
    """Remove a journal file and a campaign folder a refused build created, if still empty (nothing else)."""
    if path is not None and path.exists() and path.stat().st_size == 0:
        path.unlink()
    if folder is not None and folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()


def _build(s: AgentSettings, definition: CalibrationDefinition, cdir: Path, cid: str, journal: Journal) -> AgentSetup:
    constraints = [c for c in s.constraints if c.strip()]
    source = load_source(s.prior_source, definition) if s.prior_source and s.strategy == "bo" else None
    prior_info = source_summary(source, SearchSpace.from_definition(definition)) if source else {}
    # what the same source knows of the limited outcomes (an earlier campaign's measured outcomes; a reduce
    # output's simulated runs' outcomes, result.json schema 2): each outcome's model starts from it
    started = journal.events[0] if len(journal) else {}
    started_config = started.get("config") if started.get("event") == "campaign_started" else None
    outcome_sources = (
        load_outcome_sources(s.prior_source, definition, [limit.name for limit in parse_limits(constraints)])
        if source is not None
        and constraints
        # a campaign started before outcome priors existed (its journal has no such key) resumes as it ran
        and not (isinstance(started_config, dict) and "outcome_priors" not in started_config)
        else {}
    )
    # with a transfer prior the first trial is the prior's optimum (the model's, not the file's best guess)
    initial_points = (
        (dict(definition.best_guess),) if s.start_from == "guess" and definition.best_guess and source is None else ()
    )
    # a campaign started before the safe start (its journal has no such key) resumes as it ran
    safe_calibration = (
        definition.baseline_tuned()
        if s.safe_start
        and constraints
        and s.strategy == "bo"
        and not (isinstance(started_config, dict) and "safe_start" not in started_config)
        else None
    )

    def as_ran(key: str, value: _T) -> _T:
        """``value``, or what the agent did before the option existed (campaign.ADDED_LATER) for a campaign whose
        journal has no such key: it resumes as it ran."""
        missing = isinstance(started_config, dict) and key not in started_config
        return cast(_T, ADDED_LATER[key]) if missing else value

    # without: limit_trend, the limits' models widened far from the runs (limit_far_sd), limit_trend_far and
    # limit_reach (bo_agent parameters since 2026-11-25), the model average over two lengthscale priors, the
    # exploration along the faces, the transfer average's model without the source over both lengthscale priors
    limit_trend = as_ran("limit_trend", s.limit_trend)
    limit_far_sd = as_ran("limit_far_sd", s.limit_far_sd)
    limit_trend_far = as_ran("limit_trend_far", s.limit_trend_far)
    limit_reach = as_ran("limit_reach", s.limit_reach)
    ls_average = as_ran("gp_ls_average", s.gp_ls_average)
    face_explore = as_ran("face_explore", s.face_explore)
    prior_average_ls = as_ran("prior_average_ls", s.prior_average_ls)
    # what the parameters ask and the resumed journal overrides: said, not silent (the parameters are read-only)
    overridden: list[tuple[str, str]] = []
    before = isinstance(started_config, dict) and "outcome_priors" not in started_config
    if source is not None and constraints and before:
        overridden.append(("the outcome priors from prior_source", "the limits' models start from nothing"))
    if s.safe_start and constraints and s.strategy == "bo" and safe_calibration is None:
        overridden.append(("safe_start true", "without a safe start"))
    if s.strategy == "bo" and s.limit_trend and constraints and not limit_trend:
        overridden.append(("limit_trend true", "limit_trend false"))
    if s.strategy == "bo" and ls_average != s.gp_ls_average:
        overridden.append((f"gp_ls_average {s.gp_ls_average:g}", f"gp_ls_average {ls_average:g}, one fit"))
    ran_limits = {"limit_far_sd": limit_far_sd, "limit_trend_far": limit_trend_far, "limit_reach": limit_reach}
    for key, ran in ran_limits.items():
        if s.strategy == "bo" and constraints and ran != getattr(s, key):
            overridden.append((f"{key} {getattr(s, key):g}", f"{key} {ran:g}"))
    # (prior_average_ls acts only in the transfer average with the lengthscale average on)
    if s.strategy == "bo" and source is not None and s.prior_average and ls_average > 0 and not prior_average_ls:
        overridden.append(("prior_average_ls true", "prior_average_ls false"))
    if s.strategy == "bo" and face_explore != s.face_explore:
        overridden.append((f"face_explore {s.face_explore}", f"face_explore {face_explore}"))
    resumed_as_journaled = [
        f"{asked} is not used: this campaign's journal was started before the option existed and the campaign "
        f"resumes as it ran ({ran}); a new campaign_dir starts with it"
        for asked, ran in overridden
    ]
    budget = s.budget
    optimizer: Optimizer
    if s.strategy == "grid":
        grid = GridStrategy(definition, s.grid_size, s.seed)
        budget = grid.budget
        optimizer = grid
    elif s.strategy == "random":
        optimizer = RandomStrategy(definition, budget, s.seed)
    else:
        optimizer = Engine(
            definition,
            EngineConfig(
                budget=budget,
                n_initial=s.n_initial,
                seed=s.seed,
                acquisition=s.acquisition,
                recommend_beta=s.recommend_beta,
                recommend_rule=s.recommend_rule,
                output_warp=s.output_warp,
                design_margin=s.design_margin,
                initial_points=initial_points,
                gp=GPConfig(mean=s.gp_mean, bowl_loo=s.gp_bowl_loo, ls_average=ls_average),
                bowl_runs=s.bowl_runs,
                prior=source.to_dict() if source is not None else None,
                prior_weight=s.prior_weight,
                prior_runs=s.prior_runs,
                prior_average=s.prior_average,
                prior_average_ls=prior_average_ls,
                constraints=tuple(constraints),
                constraint_level=s.constraint_level,
                outcome_priors={k: v.to_dict() for k, v in outcome_sources.items()} or None,
                safe_start=safe_calibration,
                limit_trend=limit_trend,
                face_explore=face_explore,
                limit_far_sd=limit_far_sd,
                limit_trend_far=limit_trend_far,
                limit_reach=limit_reach,
            ),
        )
    cfg = CampaignConfig(
        campaign_id=cid,
        budget=budget,
        strategy=s.strategy,
        seed=s.seed,
        max_attempts=s.max_attempts,
        apply_retries=s.apply_retries,
        apply_timeout_s=s.apply_timeout_s,
        run_timeout_s=s.run_timeout_s or BACKSTOP_RUN_TIMEOUT_S,
        confirmation_run=s.confirmation_run,
        max_consecutive_failures=s.max_consecutive_failures,
        busy_retry_s=s.busy_retry_s,
        busy_timeout_s=s.busy_timeout_s,
        link_retry_s=s.link_retry_s,
        link_timeout_s=s.link_timeout_s,
        extra={
            "n_initial": s.n_initial,
            "grid_size": s.grid_size,
            "definition_file": str(s.definition_file),
            "acquisition": s.acquisition,
            "recommend_beta": s.recommend_beta,
            "recommend_rule": s.recommend_rule,
            "gp_mean": s.gp_mean,
            "gp_bowl_loo": s.gp_bowl_loo,
            # the model average over the lengthscale priors of sd 1 and this (0: one fit; issue 23, 2026-11-25)
            "gp_ls_average": ls_average,
            # the exploration along the faces after a stall (0: off; issue 23, 2026-11-25)
            "face_explore": face_explore,
            "bowl_runs": optimizer.bowl_runs if isinstance(optimizer, Engine) else 0,
            "output_warp": s.output_warp,
            "design_margin": s.design_margin,
            "start_from": s.start_from,
            "initial_points": [dict(p) for p in initial_points],
            "prior_source": s.prior_source,
            "prior_summary": prior_info,
            "prior": source.to_dict() if source is not None else None,
            "prior_weight": s.prior_weight,
            "prior_runs": s.prior_runs,
            "prior_average": s.prior_average,
            # the model without the source in that average: both lengthscale priors' fits (issue 23, 2026-11-25)
            "prior_average_ls": prior_average_ls,
            "constraints": constraints,
            "constraint_level": s.constraint_level,
            # what the prior source knew of the limited outcomes: each surface (a refit models as the agent did)
            "outcome_priors": {k: v.to_dict() for k, v in outcome_sources.items()},
            # the calibration trial 1 drives and the design grows from (issue 23; {} = none)
            "safe_start": dict(safe_calibration or {}),
            # the retreat's trend judges the design and the least risky calibrations (issue 23, 2026-11-25)
            "limit_trend": limit_trend,
            # the limited outcomes' models widened far from the runs (issue 23, 2026-11-25; 0: off)
            "limit_far_sd": limit_far_sd,
            # after the design, calibrations this far from every run judged by the retreat's trend too (opt-in; 0: off)
            "limit_trend_far": limit_trend_far,
            # after the design, proposals within this (times sqrt(d/2)) of a run that kept the limits (0: off)
            "limit_reach": limit_reach,
        },
        outcome_limits=tuple(constraints),
    )
    return AgentSetup(
        definition, cdir, journal, optimizer, cfg, prior_info, dict(outcome_sources), resumed_as_journaled
    )
