"""A real campaign journal, made without ROS: the agent's state machine (bac_agent.campaign) driven with a known J,
plus bags holding run segments and scores (bac_measure.bagio.write_bag), for the cockpit's unit tests."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from bac_agent.bo import Engine
from bac_agent.campaign import Apply, AwaitRun, Campaign, CampaignConfig, Finish, Publish, TrialStatus
from bac_agent.journal import Journal
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition


def bowl(p: Mapping[str, float]) -> float:
    return 0.9 + (p["damping_front"] - 0.2) ** 2 + 0.5 * (p["damping_rear"] - 0.35) ** 2


def make_campaign(
    folder: Path,
    budget: int = 6,
    j: Callable[[Mapping[str, float]], float] = bowl,
    reject: Mapping[int, str] | None = None,
    confirmation: bool = True,
    stop_after: int | None = None,
    definition: CalibrationDefinition | None = None,
) -> list[TrialStatus]:
    """Run a campaign to its end (or until ``stop_after`` trials were scored); ``reject`` = {trial: reason}: its
    first run is invalid. Returns every Trial status the agent published."""
    defn = definition or CalibrationDefinition.load(resolve_definition("controller_i"))
    eng = Engine(defn, budget=budget, seed=2)
    cfg = CampaignConfig(campaign_id=folder.name, budget=budget, confirmation_run=confirmation)
    camp = Campaign(eng, Journal(folder), cfg, clock=lambda: 1.0, definition=defn.to_dict())
    published: list[TrialStatus] = []
    rejected: set[int] = set()
    queue: list[Any] = list(camp.start())
    scored = 0
    while queue:
        a = queue.pop(0)
        if isinstance(a, Publish):
            published.append(a.status)
        elif isinstance(a, Apply):
            queue += camp.on_apply_result(a.trial_id, a.apply_try, True, 0, "", dict(a.params), 0.012, attempts=2)
        elif isinstance(a, AwaitRun):
            if stop_after is not None and scored >= stop_after:
                break
            params = camp.current.params if camp.current else {}
            if reject and a.trial_id in reject and a.trial_id not in rejected:
                rejected.add(a.trial_id)
                queue += camp.on_score(cfg.campaign_id, a.trial_id, a.attempt, False, math.nan, reject[a.trial_id])
            else:
                scored += 1
                queue += camp.on_score(cfg.campaign_id, a.trial_id, a.attempt, True, j(params))
        elif isinstance(a, Finish):
            break
    camp.journal.close()
    return published


def segment_signals(n: int = 500, scale: float = 1.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0
    az = scale * np.sin(2 * np.pi * 1.3 * t) * np.exp(-t) + 0.01 * rng.standard_normal(n)
    q = 0.1 * scale * np.cos(2 * np.pi * 1.1 * t) * np.exp(-t)
    return az, q
