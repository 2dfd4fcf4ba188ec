"""The GP view: the posterior mean over the two tuned parameters (or the two that matter most), the trials on it,
the recommendation; fitted as bac report fits it, then kept up to date run by run."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
from campaign_maker import make_campaign

from bac_campaign.report import load_campaign, refit_engine
from bac_cockpit.model import compute_model
from bac_common.paramspace import CalibrationDefinition


@pytest.mark.slow
def test_two_parameters_give_the_posterior_mean_the_trials_and_the_recommendation(tmp_path: Path) -> None:
    folder = tmp_path / "camp"
    make_campaign(folder, budget=6)
    m = compute_model(folder, grid=21)
    json.dumps(m, allow_nan=False)
    assert m["kind"] == "contour" and m["n_runs"] == 7 and m["status"] == "GP posterior mean after 7 runs"
    assert [d["name"] for d in m["dims"]] == ["damping_front", "damping_rear"] and m["fixed"] == {}
    assert len(m["x"]) == len(m["y"]) == 21 and np.array(m["mean"]).shape == (21, 21)
    assert [t["trial_id"] for t in m["trials"]] == list(range(1, 8))
    rec = json.loads((folder / "recommendation.json").read_text())
    assert m["recommendation"]["final"] is True and m["recommendation"]["params"] == rec["params"]
    # the same model as bac report's contour: the engine refitted on the journal
    eng = refit_engine(load_campaign(folder))
    mean, _ = eng.predict({"damping_front": m["x"][5], "damping_rear": m["y"][12]})
    assert m["mean"][12][5] == pytest.approx(mean, rel=1e-4)
    # the map is the runs' bowl: low near the true optimum (0.2, 0.35), high in the far corner
    mean = np.array(m["mean"], dtype=float)
    assert mean[7, 4] < mean[20, 20] - 0.2 and abs(m["x"][4] - 0.2) < 1e-9 and abs(m["y"][7] - 0.35) < 1e-9


def test_before_the_end_the_models_own_recommendation_and_each_run_updates_it(tmp_path: Path) -> None:
    folder = tmp_path / "camp"
    make_campaign(folder, budget=8, stop_after=3)
    m3 = compute_model(folder, grid=11)
    assert m3["n_runs"] == 3 and m3["recommendation"]["final"] is False
    make_campaign(folder, budget=8, stop_after=2)  # the same campaign, resumed: two more runs
    m5 = compute_model(folder, grid=11)
    assert m5["n_runs"] == 5 and m5["mean"] != m3["mean"]


def test_no_run_no_model(tmp_path: Path) -> None:
    assert compute_model(tmp_path / "nothing")["status"].startswith("no model")
    folder = tmp_path / "camp"
    make_campaign(folder, budget=4, stop_after=0)
    m = compute_model(folder)
    assert m["n_runs"] == 0 and "no scored run" in m["status"] and "kind" not in m


def test_with_three_parameters_the_two_that_matter_are_drawn(tmp_path: Path) -> None:
    defn = CalibrationDefinition.from_dict(
        {
            "name": "three",
            "parameters": [
                {"name": n, "index": i, "lower": 0.0, "upper": 1.0, "nominal": 0.5, "resolution": 0.0001}
                for i, n in enumerate(("a", "b", "c"))
            ],
        }
    )

    def j(p: Mapping[str, float]) -> float:  # b and c matter, a hardly
        return 1.0 + 0.01 * p["a"] + 2.0 * (p["b"] - 0.3) ** 2 + 2.0 * (p["c"] - 0.6) ** 2

    folder = tmp_path / "camp"
    make_campaign(folder, budget=12, j=j, definition=defn, confirmation=False)
    m = compute_model(folder, grid=11)
    assert [d["name"] for d in m["dims"]] == ["b", "c"]
    assert set(m["fixed"]) == {"a"} and math.isclose(m["fixed"]["a"], m["recommendation"]["params"]["a"])
    assert m["lengthscales"]["a"] > max(m["lengthscales"]["b"], m["lengthscales"]["c"])
