"""bac_agent.agent_setup: what bo_agent builds from its parameters, without ROS."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_agent.agent_setup import BACKSTOP_RUN_TIMEOUT_S, AgentSettings, AgentSetup, build_agent, make_verifier
from bac_agent.bo.baselines import GridStrategy
from bac_agent.bo.engine import Engine, EngineConfig
from bac_agent.journal import Journal, journaled_engine_options
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


def _record_closes(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    closed: list[Path] = []
    real_close = Journal.close

    def close(self: Journal) -> None:
        closed.append(self.dir)
        real_close(self)

    monkeypatch.setattr(Journal, "close", close)
    return closed


def test_an_existing_journal_is_refused_without_resume_and_left_closed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _journal_started(tmp_path, {})
    closed = _record_closes(monkeypatch)
    with pytest.raises(BacError, match="already holds a campaign journal and resume is false"):
        build_agent(AgentSettings(campaign_dir=str(tmp_path), resume=False))
    assert closed == [tmp_path]


@pytest.mark.parametrize(
    ("settings", "message"),
    [({"strategy": "grid_search"}, "unknown strategy 'grid_search'"), ({"start_from": "desing"}, "unknown start_from")],
)
def test_an_unknown_choice_is_refused_before_anything_is_opened(
    tmp_path: Path, settings: dict[str, str], message: str
) -> None:
    with pytest.raises(BacError, match=message):
        build_agent(AgentSettings(campaign_dir=str(tmp_path / "c"), **settings))  # type: ignore[arg-type]
    assert not (tmp_path / "c").exists()


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


def test_a_prior_source_that_cannot_be_read_closes_the_journal_it_opened_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    closed = _record_closes(monkeypatch)
    with pytest.raises(BacError, match="nowhere"):
        build_agent(AgentSettings(campaign_dir=str(tmp_path / "c"), prior_source=str(tmp_path / "nowhere")))
    assert closed == [tmp_path / "c"]
    assert not (tmp_path / "c").exists()  # the folder it created, with its empty journal, is gone
    # a folder that was there keeps its other files; only the empty journal this start made is removed
    kept = tmp_path / "k"
    kept.mkdir()
    (kept / "notes.txt").write_text("the driver's notes")
    with pytest.raises(BacError, match="nowhere"):
        build_agent(AgentSettings(campaign_dir=str(kept), prior_source=str(tmp_path / "nowhere")))
    assert sorted(p.name for p in kept.iterdir()) == ["notes.txt"]
    # and the settings, mended, start the campaign there
    build_agent(AgentSettings(campaign_dir=str(kept))).journal.close()


def test_a_refused_resume_leaves_the_journal_as_it_was(tmp_path: Path) -> None:
    _journal_started(tmp_path, {})
    before = (tmp_path / "journal.jsonl").read_bytes()
    with pytest.raises(BacError, match="nowhere"):
        build_agent(AgentSettings(campaign_dir=str(tmp_path), resume=True, prior_source=str(tmp_path / "nowhere")))
    assert (tmp_path / "journal.jsonl").read_bytes() == before


def _definition_with_guess(tmp_path: Path) -> Path:
    """controller_i with a best guess, as bac reduce writes one."""
    text = resolve_definition("controller_i").read_text()
    path = tmp_path / "guessed.yaml"
    path.write_text(text.rstrip("\n") + "\nbest_guess: {damping_front: 0.2, damping_rear: 0.3}\n")
    return path


def _earlier_campaign(path: Path) -> Path:
    """An earlier campaign's folder: 15 scored runs of J and of the travel."""
    with Journal(path) as j:
        j.append("campaign_started", campaign_id="earlier", names=["damping_front", "damping_rear"], stamp=0.0)
        k = 0
        for a in (0.1, 0.3, 0.5, 0.7, 0.9):
            for b in (0.2, 0.5, 0.8):
                k += 1
                j.append(
                    "trial_scored",
                    campaign_id="earlier",
                    trial_id=k,
                    params={"damping_front": a, "damping_rear": b},
                    j=1.0 + (a - 0.3) ** 2 + (b - 0.6) ** 2,
                    outcomes={"max_travel_mm": 80.0 - 40.0 * a},
                    stamp=float(k),
                )
    return path


@pytest.mark.slow
def test_the_best_guess_is_trial_1_unless_the_design_is_asked_for_or_a_prior_gives_trial_1(tmp_path: Path) -> None:
    defn = str(_definition_with_guess(tmp_path))
    guess = {"damping_front": 0.2, "damping_rear": 0.3}
    runs = {
        "guess": AgentSettings(definition_file=defn, campaign_dir=str(tmp_path / "a")),
        "design": AgentSettings(definition_file=defn, campaign_dir=str(tmp_path / "b"), start_from="design"),
        "prior": AgentSettings(
            definition_file=defn,
            campaign_dir=str(tmp_path / "c"),
            prior_source=str(_earlier_campaign(tmp_path / "earlier")),
        ),
    }
    built = {k: build_agent(v) for k, v in runs.items()}
    for setup in built.values():
        setup.journal.close()
    assert built["guess"].config.extra["initial_points"] == [guess]
    assert built["design"].config.extra["initial_points"] == []
    assert built["prior"].config.extra["initial_points"] == []  # the prior's optimum is trial 1
    assert built["prior"].prior_info and built["prior"].config.extra["prior"] is not None
    assert any(line.startswith("transfer prior: ") for line in built["prior"].log_lines())


@pytest.mark.slow
def test_outcome_priors_come_from_the_source_but_not_for_a_journal_started_before_them(tmp_path: Path) -> None:
    source = str(_earlier_campaign(tmp_path / "earlier"))
    limit = ("max_travel_mm<=60",)
    new = build_agent(AgentSettings(campaign_dir=str(tmp_path / "new"), prior_source=source, constraints=limit))
    new.journal.close()
    assert list(new.outcome_sources) == ["max_travel_mm"]
    assert list(new.config.extra["outcome_priors"]) == ["max_travel_mm"]
    assert any(line.startswith("outcome priors: ") and "none" not in line for line in new.log_lines())
    assert isinstance(new.optimizer, Engine) and new.optimizer.config.outcome_priors
    _journal_started(tmp_path / "old", {"constraints": list(limit)})  # no "outcome_priors" key: ran without
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old"), prior_source=source, constraints=limit))
    old.journal.close()
    assert old.outcome_sources == {} and old.config.extra["outcome_priors"] == {}
    assert "outcome priors: none (the prior source records no limited outcome)" in old.log_lines()
    # a prior on another strategy than bo is not loaded at all, nor is a safe start used
    rnd = build_agent(
        AgentSettings(
            campaign_dir=str(tmp_path / "rnd"),
            strategy="random",
            prior_source=source,
            constraints=limit,
            safe_start=True,
        )
    )
    rnd.journal.close()
    assert rnd.prior_info == {} and rnd.config.extra["prior"] is None and rnd.config.extra["safe_start"] == {}


def test_the_node_passes_every_setting_it_declares() -> None:
    """bo_agent builds AgentSettings(...) by hand: a field added later and forgotten there would silently keep its
    default whatever the user set. Every field must be passed, and each must be a parameter the node declares."""
    import ast
    import dataclasses
    import importlib.util

    spec = importlib.util.find_spec("bac_agent.agent_node")  # its source only: the node itself needs rclpy
    assert spec is not None and spec.origin is not None
    tree = ast.parse(Path(spec.origin).read_text())
    calls = [
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "AgentSettings" and n.keywords
    ]
    assert len(calls) == 1
    passed = {kw.arg for kw in calls[0].keywords}
    assert passed == {f.name for f in dataclasses.fields(AgentSettings)}
    declared = {
        n.args[0].value
        for n in ast.walk(tree)
        if isinstance(n, ast.Call)
        and isinstance(n.func, ast.Attribute)
        and n.func.attr.startswith("declare_")
        and n.args
        and isinstance(n.args[0], ast.Constant)
    }
    assert passed <= declared, passed - declared


def test_limit_trend_is_passed_journaled_and_off_for_a_journal_started_before_it(tmp_path: Path) -> None:
    limit = ("max_travel_mm<=60",)
    for flag in (True, False):
        setup = build_agent(AgentSettings(campaign_dir=str(tmp_path / str(flag)), constraints=limit, limit_trend=flag))
        setup.journal.close()
        assert isinstance(setup.optimizer, Engine)
        assert setup.optimizer.config.limit_trend is flag and setup.config.extra["limit_trend"] is flag
    # a journal whose campaign_started has no "limit_trend" key ran without it: it resumes without it (not refused)
    _journal_started(tmp_path / "old", {"constraints": list(limit)})
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old"), constraints=limit))
    old.journal.close()
    assert isinstance(old.optimizer, Engine) and old.optimizer.config.limit_trend is False
    assert old.config.extra["limit_trend"] is False


def test_limit_far_sd_is_passed_journaled_and_off_for_a_journal_started_before_it(tmp_path: Path) -> None:
    limit = ("max_travel_mm<=60",)
    for sd in (2.0, 0.0):
        setup = build_agent(AgentSettings(campaign_dir=str(tmp_path / str(sd)), constraints=limit, limit_far_sd=sd))
        setup.journal.close()
        assert isinstance(setup.optimizer, Engine)
        assert setup.optimizer.config.limit_far_sd == sd and setup.config.extra["limit_far_sd"] == sd
    # a journal whose campaign_started has no "limit_far_sd" key ran without it: it resumes without it (not refused)
    _journal_started(tmp_path / "old", {"constraints": list(limit)})
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old"), constraints=limit, limit_far_sd=2.0))
    old.journal.close()
    assert isinstance(old.optimizer, Engine) and old.optimizer.config.limit_far_sd == 0.0
    assert old.config.extra["limit_far_sd"] == 0.0
    # an offline refit models as the campaign did
    assert journaled_engine_options({"config": {"constraints": list(limit)}})["limit_far_sd"] == 0.0
    opts = journaled_engine_options({"config": {"constraints": list(limit), "limit_far_sd": 2.0}})
    assert opts["limit_far_sd"] == 2.0


@pytest.mark.parametrize("key", ["limit_trend_far", "limit_reach"])
def test_the_limit_distances_are_passed_journaled_and_off_for_a_journal_started_before_them(
    tmp_path: Path, key: str
) -> None:
    """limit_trend_far (opt-in, 0: off) and limit_reach (the engine's default 0.15), bo_agent parameters since
    2026-11-25; a journal from before them ran both off."""
    limit = ("max_travel_mm<=60",)
    assert (
        getattr(AgentSettings(), key)
        == getattr(EngineConfig(), key)
        == {"limit_trend_far": 0.0, "limit_reach": 0.15}[key]
    )

    def said(setup: AgentSetup) -> list[str]:  # what the node warns of this option (the older ones' aside)
        return [n for n in setup.resumed_as_journaled if n.startswith(key)]

    for r in (0.15, 0.0):
        setup = build_agent(AgentSettings(campaign_dir=str(tmp_path / str(r)), constraints=limit, **{key: r}))  # type: ignore[arg-type]
        setup.journal.close()
        assert isinstance(setup.optimizer, Engine)
        assert getattr(setup.optimizer.config, key) == r and setup.config.extra[key] == r
        assert setup.resumed_as_journaled == []
    # a journal whose campaign_started has no such key ran without it: it resumes without it (not refused) and the
    # node says that the parameter is not used
    _journal_started(tmp_path / "old", {"constraints": list(limit)})
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old"), constraints=limit, **{key: 0.15}))  # type: ignore[arg-type]
    old.journal.close()
    assert isinstance(old.optimizer, Engine) and getattr(old.optimizer.config, key) == 0.0
    assert old.config.extra[key] == 0.0
    (note,) = said(old)
    assert note.startswith(f"{key} 0.15 is not used") and f"resumes as it ran ({key} 0)" in note
    # a journal that has the key resumes with it; without limits the option acts on nothing: nothing to say
    _journal_started(tmp_path / "knew", {"constraints": list(limit), key: 0.15})
    knew = build_agent(AgentSettings(campaign_dir=str(tmp_path / "knew"), constraints=limit, **{key: 0.15}))  # type: ignore[arg-type]
    knew.journal.close()
    assert isinstance(knew.optimizer, Engine) and getattr(knew.optimizer.config, key) == 0.15
    assert said(knew) == []
    _journal_started(tmp_path / "free", {"budget": 15})
    free = build_agent(AgentSettings(campaign_dir=str(tmp_path / "free"), **{key: 0.15}))  # type: ignore[arg-type]
    free.journal.close()
    assert said(free) == [] and free.optimizer.config.limit_reach == free.optimizer.config.limit_trend_far == 0.0  # type: ignore[union-attr]
    # an offline refit models as the campaign did
    assert journaled_engine_options({"config": {"constraints": list(limit)}})[key] == 0.0
    assert journaled_engine_options({"config": {"constraints": list(limit), key: 0.15}})[key] == 0.15
    # a value out of range is refused with its name, before a journal is left behind
    with pytest.raises(BacError, match=f"{key} must be >= 0"):
        build_agent(AgentSettings(campaign_dir=str(tmp_path / "bad"), constraints=limit, **{key: -0.1}))  # type: ignore[arg-type]
    assert not (tmp_path / "bad").exists()


def test_gp_ls_average_is_passed_journaled_and_off_for_a_journal_started_before_it(tmp_path: Path) -> None:
    for sd in (0.5, 0.0):
        setup = build_agent(AgentSettings(campaign_dir=str(tmp_path / str(sd)), gp_ls_average=sd))
        setup.journal.close()
        assert isinstance(setup.optimizer, Engine)
        assert setup.optimizer.config.gp.ls_average == sd and setup.config.extra["gp_ls_average"] == sd
    assert AgentSettings().gp_ls_average == 0.5  # the default (issue 23, 2026-11-25)
    # a journal whose campaign_started has no "gp_ls_average" key ran one fit: it resumes so (not refused)
    _journal_started(tmp_path / "old", {"budget": 15})
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old")))
    old.journal.close()
    assert isinstance(old.optimizer, Engine) and old.optimizer.config.gp.ls_average == 0.0
    assert old.config.extra["gp_ls_average"] == 0.0
    # an offline refit of such a journal models as the campaign did
    assert journaled_engine_options({"config": {}})["gp"]["ls_average"] == 0.0
    assert journaled_engine_options({"config": {"gp_ls_average": 0.5}})["gp"]["ls_average"] == 0.5


@pytest.mark.slow
def test_a_resumed_journal_that_overrides_a_parameter_says_so(tmp_path: Path) -> None:
    """A journal started before an option existed resumes as it ran whatever the (read-only) parameter says: the
    node warns with these sentences instead of leaving a parameter that reads otherwise than the campaign runs."""
    source = str(_earlier_campaign(tmp_path / "earlier"))
    settings = {"constraints": (LIMIT,), "prior_source": source, "safe_start": True}
    fresh = build_agent(AgentSettings(campaign_dir=str(tmp_path / "new"), **settings))  # type: ignore[arg-type]
    fresh.journal.close()
    assert fresh.resumed_as_journaled == []
    _journal_started(tmp_path / "old", {"constraints": [LIMIT]})  # none of the eight options' keys
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old"), **settings))  # type: ignore[arg-type]
    old.journal.close()
    notes = old.resumed_as_journaled
    assert [n.split(" is not used")[0] for n in notes] == [
        "the outcome priors from prior_source",
        "safe_start true",
        "limit_trend true",
        "gp_ls_average 0.5",
        "limit_far_sd 2",
        "limit_reach 0.15",
        "face_explore 1",
    ]  # (prior_average_ls acts only with the lengthscale average, which this journal ran without)
    assert "resumes as it ran (gp_ls_average 0, one fit)" in notes[3]
    # a journal that knew the options resumes with them: nothing to say
    knew = {
        "constraints": [LIMIT],
        "outcome_priors": {},
        "safe_start": {},
        "limit_trend": True,
        "gp_ls_average": 0.5,
        "limit_far_sd": 2.0,
        "limit_reach": 0.15,
        "prior_average_ls": True,
        "face_explore": 1,
    }
    _journal_started(tmp_path / "knew", knew)
    again = build_agent(AgentSettings(campaign_dir=str(tmp_path / "knew"), **settings))  # type: ignore[arg-type]
    again.journal.close()
    assert again.resumed_as_journaled == []
    # a journal with the lengthscale average but from before prior_average_ls
    _journal_started(tmp_path / "old_ls", {"constraints": [LIMIT], "gp_ls_average": 0.5})
    old_ls = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old_ls"), **settings))  # type: ignore[arg-type]
    old_ls.journal.close()
    assert "prior_average_ls true is not used" in " ".join(old_ls.resumed_as_journaled)
    # a grid or random campaign has no engine whose options could be overridden: nothing to say
    for strategy in ("grid", "random"):
        _journal_started(tmp_path / strategy, {"constraints": [LIMIT]})
        other = build_agent(AgentSettings(campaign_dir=str(tmp_path / strategy), strategy=strategy, **settings))  # type: ignore[arg-type]
        other.journal.close()
        assert other.resumed_as_journaled == [], strategy
    # a parameter at the value the old campaign ran with is not overridden
    _journal_started(tmp_path / "old_off", {"budget": 15})
    off = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old_off"), gp_ls_average=0.0, face_explore=0))
    off.journal.close()
    assert off.resumed_as_journaled == []


def test_prior_average_ls_is_passed_journaled_and_off_for_a_journal_started_before_it(tmp_path: Path) -> None:
    for flag in (True, False):
        setup = build_agent(AgentSettings(campaign_dir=str(tmp_path / str(flag)), prior_average_ls=flag))
        setup.journal.close()
        assert isinstance(setup.optimizer, Engine)
        assert setup.optimizer.config.prior_average_ls is flag and setup.config.extra["prior_average_ls"] is flag
    assert AgentSettings().prior_average_ls is True  # the default (issue 23, 2026-11-25)
    # a journal whose campaign_started has no "prior_average_ls" key ran one fit there: it resumes so (not refused)
    _journal_started(tmp_path / "old", {"budget": 15})
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old")))
    old.journal.close()
    assert isinstance(old.optimizer, Engine) and old.optimizer.config.prior_average_ls is False
    assert old.config.extra["prior_average_ls"] is False


def test_face_explore_is_passed_journaled_and_off_for_a_journal_started_before_it(tmp_path: Path) -> None:
    for n in (1, 0, 2):
        setup = build_agent(AgentSettings(campaign_dir=str(tmp_path / str(n)), face_explore=n))
        setup.journal.close()
        assert isinstance(setup.optimizer, Engine)
        assert setup.optimizer.config.face_explore == n and setup.config.extra["face_explore"] == n
    assert AgentSettings().face_explore == 1  # the default (issue 23, 2026-11-25)
    # a journal whose campaign_started has no "face_explore" key ran without it: it resumes so (not refused)
    _journal_started(tmp_path / "old", {"budget": 15})
    old = build_agent(AgentSettings(campaign_dir=str(tmp_path / "old")))
    old.journal.close()
    assert isinstance(old.optimizer, Engine) and old.optimizer.config.face_explore == 0
    assert old.config.extra["face_explore"] == 0
