"""bac_agent.agent_setup: what bo_agent builds from its parameters, without ROS."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_agent.agent_setup import BACKSTOP_RUN_TIMEOUT_S, AgentSettings, build_agent, make_verifier
from bac_agent.bo.baselines import GridStrategy
from bac_agent.bo.engine import Engine
from bac_agent.journal import Journal
from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition

LIMIT = "max_travel_mm<=60"


def _journal_started(cdir: Path, config: dict[str, object]) -> None:
    with Journal(cdir) as j:
        j.append("campaign_started", config=config)


def test_the_defaults_build_the_bo_engine_and_record_every_option(tmp_path: Path) -> None:
    setup = build_agent(AgentSettings(campaign_dir=str(tmp_path / "c1"), budget=9, seed=4))
    try:
        assert isinstance(setup.optimizer, Engine)
        eng = setup.optimizer
        assert eng.config.budget == 9 and eng.config.seed == 4 and eng.config.gp.bowl_loo
        assert not setup.definition.best_guess and eng.config.initial_points == ()  # controller_i: no best guess
        cfg = setup.config
        assert cfg.campaign_id == "c1" and cfg.strategy == "bo" and cfg.run_timeout_s == BACKSTOP_RUN_TIMEOUT_S
        assert cfg.extra["bowl_runs"] == eng.bowl_runs and cfg.extra["gp_bowl_loo"] is True
        assert cfg.extra["safe_start"] == {} and cfg.extra["outcome_priors"] == {} and cfg.extra["prior"] is None
        assert setup.log_lines() == [
            f"bo_agent: definition '{setup.definition.name}' ({', '.join(eng.names)}), strategy bo, budget 9, "
            f"campaign 'c1' in {tmp_path / 'c1'}"
        ]
    finally:
        setup.journal.close()


def test_a_grid_campaign_takes_the_grid_s_budget(tmp_path: Path) -> None:
    setup = build_agent(AgentSettings(campaign_dir=str(tmp_path), strategy="grid", grid_size=3, budget=99))
    setup.journal.close()
    assert isinstance(setup.optimizer, GridStrategy)
    assert setup.config.budget == setup.optimizer.budget == 3 ** len(setup.optimizer.names)
    assert setup.config.extra["bowl_runs"] == 0


def test_an_existing_journal_is_refused_without_resume_and_left_closed(tmp_path: Path) -> None:
    _journal_started(tmp_path, {})
    with pytest.raises(BacError, match="already holds a campaign journal and resume is false"):
        build_agent(AgentSettings(campaign_dir=str(tmp_path), resume=False))
    with pytest.raises(BacError, match="unknown strategy 'grid_search'"):
        build_agent(AgentSettings(campaign_dir=str(tmp_path), strategy="grid_search"))


def test_the_safe_start_is_the_baseline_but_not_for_a_journal_started_before_it(tmp_path: Path) -> None:
    defn = CalibrationDefinition.load(resolve_definition("controller_i"))
    fresh = build_agent(AgentSettings(campaign_dir=str(tmp_path / "new"), constraints=(LIMIT, " "), safe_start=True))
    fresh.journal.close()
    assert isinstance(fresh.optimizer, Engine)
    assert fresh.optimizer.config.safe_start == defn.baseline_tuned()
    assert fresh.config.extra["safe_start"] == defn.baseline_tuned()
    assert fresh.config.extra["constraints"] == [LIMIT] and fresh.config.outcome_limits == (LIMIT,)
    assert f"outcome limits: {LIMIT} (level 0.05)" in fresh.log_lines()
    # a journal whose campaign_started has no "safe_start" key ran without it: it resumes without it
    _journal_started(tmp_path / "old", {"constraints": [LIMIT]})
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old"), constraints=(LIMIT,), safe_start=True))
    old.journal.close()
    assert isinstance(old.optimizer, Engine) and old.optimizer.config.safe_start is None
    assert old.config.extra["safe_start"] == {}
    # without limits the safe start means nothing
    plain = build_agent(AgentSettings(campaign_dir=str(tmp_path / "plain"), safe_start=True))
    plain.journal.close()
    assert isinstance(plain.optimizer, Engine) and plain.optimizer.config.safe_start is None


def test_the_verifier_accepts_an_echo_within_one_lsb_and_names_what_differs() -> None:
    defn = CalibrationDefinition.load(resolve_definition("controller_i"))
    params = defn.baseline_tuned()
    expected = defn.expand(params)
    verify = make_verifier(defn)
    assert verify(params, {}) is None
    assert verify(params, expected) is None
    name = next(iter(expected))
    off = {**expected, name: expected[name] + 3 * defn.parameter(name).resolution}
    problem = verify(params, off)
    assert problem is not None and problem.startswith(f"{name}=")


def test_a_prior_source_that_cannot_be_read_closes_the_journal_it_opened(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    closed: list[Path] = []
    real_close = Journal.close

    def close(self: Journal) -> None:
        closed.append(self.dir)
        real_close(self)

    monkeypatch.setattr(Journal, "close", close)
    with pytest.raises(BacError, match="nowhere"):
        build_agent(AgentSettings(campaign_dir=str(tmp_path / "c"), prior_source=str(tmp_path / "nowhere")))
    assert closed == [tmp_path / "c"]
