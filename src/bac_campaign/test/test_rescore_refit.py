"""``bac rescore --refit`` models the outcome limits as the live agent did (issue 23, the outside review)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from bac_agent.bo import Engine, EngineConfig
from bac_agent.journal import Journal, journaled_engine_options
from bac_campaign.rescore import RunResult, refit
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition
from bac_measure.segmentation import RunId

LIMIT = "peak_accel_z<=6.0"


def _j(a: float, b: float) -> float:
    return (a - 0.9) ** 2 + (b - 0.4) ** 2  # the optimum breaks the limit: its peak is 8 * 0.9 = 7.2


def _peak(a: float) -> float:
    return 8.0 * a


def test_the_refit_tells_each_run_the_outcomes_the_agent_was_told(tmp_path: Path) -> None:
    """The live agent was told each run's outcomes (here the peak it limits); the rescore measures J again and,
    over them, the outcomes it can measure. A refit told J alone modelled no limit and recommended a calibration
    beyond it."""
    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    config = {"constraints": [LIMIT], "constraint_level": 0.05, "gp_mean": "bowl"}
    grid = [(a, b) for a in (0.1, 0.4, 0.6, 0.95) for b in (0.2, 0.6)]
    runs = []
    with Journal(tmp_path) as jr:
        jr.append(
            "campaign_started", campaign_id="c", definition=definition.to_dict(), strategy="bo", seed=0, config=config
        )
        for k, (a, b) in enumerate(grid, start=1):
            params = {"damping_front": a, "damping_rear": b}
            jr.append("trial_proposed", trial_id=k, kind=0, params=params, predicted_j=None, predicted_std=None)
            jr.append("trial_scored", trial_id=k, attempt=1, j=_j(a, b), outcomes={"peak_accel_z": _peak(a)})
            score = SimpleNamespace(valid=True, j=_j(a, b), outcomes={})  # an IMU rescore of these runs
            runs.append(RunResult(RunId("c", k, 1), params, _j(a, b), "", None, score))  # type: ignore[arg-type]
    rec = refit(tmp_path, runs)

    started = {"config": config}
    opts = {**journaled_engine_options(started), "budget": len(runs), "seed": 0}
    agent, blind = (Engine(definition, EngineConfig.from_dict(opts)) for _ in range(2))
    for a, b in grid:
        agent.tell({"damping_front": a, "damping_rear": b}, _j(a, b), {"peak_accel_z": _peak(a)})
        blind.tell({"damping_front": a, "damping_rear": b}, _j(a, b))
    want = agent.recommend().params
    assert _peak(want["damping_front"]) <= 6.0 < _peak(blind.recommend().params["damping_front"])  # the premise
    assert np.allclose([rec["params"][k] for k in want], list(want.values()))


def test_each_run_gets_its_own_outcomes_and_the_rescored_ones_win(tmp_path: Path, monkeypatch: Any) -> None:
    """Outcomes are matched by run (trial and attempt): an attempt rejected live (now valid) was never told any,
    and one measurement is not told twice; what the rescore measures again replaces what was told."""
    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    params = {"damping_front": 0.3, "damping_rear": 0.6}
    with Journal(tmp_path) as jr:
        jr.append(
            "campaign_started",
            campaign_id="c",
            definition=definition.to_dict(),
            strategy="bo",
            seed=0,
            config={"constraints": [LIMIT, "max_travel_mm<=60"]},
        )
        jr.append("trial_proposed", trial_id=1, kind=0, params=params, predicted_j=None, predicted_std=None)
        jr.append("run_rejected", trial_id=1, attempt=1, reason="too slow")
        jr.append("trial_scored", trial_id=1, attempt=2, j=1.0, outcomes={"peak_accel_z": 5.0, "max_travel_mm": 50.0})
    told: list[dict[str, float]] = []
    monkeypatch.setattr(Engine, "tell", lambda self, p, j, outcomes=None: told.append(dict(outcomes or {})))
    monkeypatch.setattr(Engine, "recommend", lambda self: SimpleNamespace(params=p, predicted_j=1.0, predicted_std=0.0))
    p = params
    runs = [
        RunResult(
            RunId("c", 1, a),
            params,
            1.0,
            "",
            None,  # type: ignore[arg-type]
            SimpleNamespace(valid=True, j=1.0, outcomes={"peak_accel_z": 5.5}),
        )
        for a in (1, 2)
    ]
    refit(tmp_path, runs)
    assert told == [{"peak_accel_z": 5.5}, {"peak_accel_z": 5.5, "max_travel_mm": 50.0}]
