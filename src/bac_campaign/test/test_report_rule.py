"""The recommendation rule a report names for journals written before the rule was recorded (issue 23)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_agent.journal import Journal
from bac_campaign.report import load_campaign
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition


@pytest.mark.parametrize(("strategy", "rule"), [("bo", "mean"), ("grid", "best_run"), ("random", "best_run")])
@pytest.mark.parametrize("source", ["journal", "recommendation.json"])
def test_an_old_campaign_names_the_rule_it_ran_with(strategy: str, rule: str, source: str, tmp_path: Path) -> None:
    """Before the rule was recorded the engine recommended the argmin of its posterior mean and the baselines
    (grid, random) their best run: an old grid campaign must not read as 'mean'."""
    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    params = {"damping_front": 0.25, "damping_rear": 0.75}
    with Journal(tmp_path) as j:
        j.append("campaign_started", campaign_id="old", definition=definition.to_dict(), strategy=strategy, seed=0)
        j.append("trial_proposed", trial_id=1, kind=0, params=params, predicted_j=None, predicted_std=None)
        j.append("trial_scored", trial_id=1, attempt=1, j=1.0)
        if source == "journal":
            j.append("recommendation", params=params, predicted_j=1.0, predicted_std=0.0)  # no "rule": old
    if source == "recommendation.json":
        (tmp_path / "recommendation.json").write_text(
            '{"params": {"damping_front": 0.25, "damping_rear": 0.75}, "predicted_j": 1.0, "predicted_std": 0.0}'
        )
    rec = load_campaign(tmp_path).recommendation
    assert rec is not None and rec["rule"] == rule
