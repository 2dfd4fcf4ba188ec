"""The ask/tell engine: bounds, quantization, design, JSON state, recommendation, acquisition."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.stats import norm

from bac_agent.bo import Engine, EngineConfig, EngineError, SearchSpace, SpaceError
from bac_agent.bo.acquisition import NoisyEI, log_ei, log_ei_with_grad, log_h
from bac_agent.bo.gp import GP, GPConfig, Hyper
from bac_common.errors import OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition, MetaParameter, RawParameter, uniform_parameters


def quad(p: dict[str, float]) -> float:
    return (p["a"] - 0.3) ** 2 + 2.0 * (p["b"] - 0.7) ** 2


def test_log_h_matches_direct_formula_and_stays_finite() -> None:
    z = np.array([-0.5, 0.0, 1.0, 3.0, -2.0, -5.0])
    direct = np.log(norm.pdf(z) + z * norm.cdf(z))
    np.testing.assert_allclose(log_h(z), direct, rtol=1e-9)
    far = log_h(np.array([-40.0, -1e3, -1e9]))
    assert np.all(np.isfinite(far))
    assert far[0] > far[1] > far[2]
    # asymptotic: h(z) ~ phi(z)/z^2 for z -> -inf
    assert far[1] == pytest.approx(norm.logpdf(-1e3) - 2 * math.log(1e3), rel=1e-6)


def test_log_ei_gradient_matches_finite_difference() -> None:
    mu, sd, best = np.array([0.3]), np.array([0.2]), 0.1
    dmu, dsd = np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]])
    _, g = log_ei_with_grad(mu, sd, dmu, dsd, best)
    eps = 1e-7
    fd_mu = (log_ei(mu + eps, sd, best) - log_ei(mu - eps, sd, best)) / (2 * eps)
    fd_sd = (log_ei(mu, sd + eps, best) - log_ei(mu, sd - eps, best)) / (2 * eps)
    np.testing.assert_allclose(g[0], [fd_mu[0], fd_sd[0]], rtol=1e-5)


def _nei_gp(noise: float) -> GP:
    rng = np.random.default_rng(5)
    X = rng.random((14, 3))
    y = np.sin(3.0 * X[:, 0]) + X[:, 1] ** 2 + 0.1 * rng.standard_normal(14)
    return GP().condition(X, y, Hyper(np.array([0.4, 0.7, 1.5]), 1.3, noise))


def _nei_gp_bowl() -> GP:
    rng = np.random.default_rng(5)
    X = rng.random((14, 3))
    y = np.sqrt(np.sum((X - 0.4) ** 2, axis=1) + 0.01) + 0.02 * rng.standard_normal(14)
    gp = GP(GPConfig(mean="bowl")).fit(X, y, rng)
    assert gp.hyper is not None and gp.hyper.bowl is not None
    return gp


@pytest.mark.parametrize("mean", ["constant", "bowl"])
def test_noisy_ei_gradient_matches_finite_difference(mean: str) -> None:
    gp = _nei_gp(0.05) if mean == "constant" else _nei_gp_bowl()
    nei = NoisyEI(gp, 32, np.random.default_rng(1))
    Q = np.random.default_rng(2).random((6, 3))
    val, g = nei.value_and_grad(Q)
    np.testing.assert_allclose(val, nei(Q), rtol=1e-12)
    eps = 1e-6
    fd = np.stack([(nei(Q + eps * e) - nei(Q - eps * e)) / (2 * eps) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6)


def test_noisy_ei_without_noise_is_ei_over_the_best_mean() -> None:
    # with (almost) no observation noise every draw at the observed points is the posterior mean there, so
    # NEI is plain EI over the best observed mean
    gp = _nei_gp(1e-9)
    nei = NoisyEI(gp, 16, np.random.default_rng(1))
    Q = np.random.default_rng(3).random((20, 3))
    mu, var = gp.predict_std_units(Q)
    best = float(np.min(gp.predict_std_units(gp.X)[0]))
    np.testing.assert_allclose(nei(Q), log_ei(mu, np.sqrt(var), best), rtol=1e-3, atol=1e-3)


def test_noisy_ei_sees_no_gain_in_the_incumbent_itself() -> None:
    # plain EI over the best posterior mean gives the incumbent's own point EI = 0.4 sigma (z = 0) and so keeps
    # value in re-running it; in every joint draw the incumbent's value is what it is, so NEI there is ~0
    gp = _nei_gp(0.3)
    nei = NoisyEI(gp, 64, np.random.default_rng(4))
    mu_obs, _ = gp.predict_std_units(gp.X)
    i = int(np.argmin(mu_obs))
    mu, var = gp.predict_std_units(gp.X[i : i + 1])
    plain = float(log_ei(mu, np.sqrt(var), float(mu_obs[i]))[0])
    assert plain == pytest.approx(math.log(0.3989422804 * math.sqrt(var[0])), rel=1e-6)
    assert float(nei(gp.X[i : i + 1])[0]) < plain - 5.0
    # away from the data both see about the same prior uncertainty
    far = np.array([[0.99, 0.01, 0.99]])
    mu_f, var_f = gp.predict_std_units(far)
    assert abs(float(nei(far)[0]) - float(log_ei(mu_f, np.sqrt(var_f), float(mu_obs[i]))[0])) < 1.0


def test_unknown_acquisition_is_refused() -> None:
    with pytest.raises(EngineError, match="acquisition must be one of"):
        EngineConfig(acquisition="ucb")


@pytest.mark.parametrize("acquisition", ["ei", "nei"])
def test_both_acquisitions_find_quadratic_minimum_under_noise(acquisition: str) -> None:
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=15, seed=3, acquisition=acquisition))
    rng = np.random.default_rng(3)
    while not eng.done:
        p = eng.ask()
        assert eng.pending and 0.0 <= p["a"] <= 1.0 and 0.0 <= p["b"] <= 1.0
        eng.tell(p, quad(p) + 0.02 * rng.standard_normal())
    # near the minimum: noisy EI (the default) within the noise's standard deviation (seed 3: 0.006); log EI within
    # 1.25 of it (seed 3: 0.022 since the bowl is kept for the design + 1 runs, 0.011 with twice the design; over
    # seeds 0-9 log EI's median 0.0025 against 0.0011 before, noisy EI's 0.0010 against 0.0018)
    assert quad(eng.recommend().params) < (0.02 if acquisition == "nei" else 0.025)


def test_asks_never_leave_bounds_and_follow_resolution() -> None:
    space = [("a", -2.0, 3.0, 0.25), ("b", 10.0, 10.5)]
    eng = Engine(space, budget=14, seed=4)
    rng = np.random.default_rng(0)
    for _ in range(14):
        p = eng.ask()
        assert -2.0 <= p["a"] <= 3.0 and 10.0 <= p["b"] <= 10.5
        assert (p["a"] + 2.0) / 0.25 == pytest.approx(round((p["a"] + 2.0) / 0.25), abs=1e-9)
        # an objective whose optimum lies on the boundary pushes asks to the edges
        eng.tell(p, -p["a"] - 5 * p["b"] + 0.1 * rng.standard_normal())
    r = eng.recommend()
    assert -2.0 <= r.params["a"] <= 3.0 and 10.0 <= r.params["b"] <= 10.5
    assert r.params["a"] == pytest.approx(3.0) and r.params["b"] > 10.4


def test_asks_from_definition_are_what_the_ecu_holds() -> None:
    defn = CalibrationDefinition(
        name="t",
        parameters=(
            RawParameter("damping_front", 0, 0.0, 1.0, 0.5, 0.01),
            *uniform_parameters("p", 3, 0.0, 1000.0, 500.0, 0.5, start_index=1),
        ),
        tuned=("damping_front", "m1"),
        meta=(MetaParameter("m1", ("p01", "p02", "p03"), 0.0, 1000.0),),
    )
    eng = Engine(defn, budget=8, seed=0)
    assert eng.names == ("damping_front", "m1")
    for i in range(8):
        p = eng.ask()
        raw = defn.expand(p)  # never raises: inside the declared bounds
        for name in ("p01", "p02", "p03"):
            q = defn.parameter(name).quantize(raw[name])
            assert q == pytest.approx(raw[name], abs=1e-9)  # nothing lost in the CAN encoding
        assert defn.parameter("damping_front").quantize(p["damping_front"]) == pytest.approx(p["damping_front"])
        eng.tell(p, float(i))


def test_initial_design_is_space_filling_and_seeded() -> None:
    a = Engine({"x": (0, 1), "y": (0, 1), "z": (0, 1)}, budget=30, n_initial=8, seed=3)
    b = Engine({"x": (0, 1), "y": (0, 1), "z": (0, 1)}, budget=30, n_initial=8, seed=3)
    pa = [a.ask() for _ in range(8)]
    pb = [b.ask() for _ in range(8)]
    assert pa == pb
    X = np.array([[p["x"], p["y"], p["z"]] for p in pa])
    for k in range(3):
        # a Latin hypercube stretched over [0.1, 0.9] (the default margin): 8 levels per axis, extremes at the margins
        assert X[:, k].min() == pytest.approx(0.1) and X[:, k].max() == pytest.approx(0.9)
        assert np.min(np.diff(np.sort(X[:, k]))) > 0.0
    c = Engine({"x": (0, 1), "y": (0, 1), "z": (0, 1)}, budget=30, n_initial=8, seed=4)
    assert [c.ask() for _ in range(8)] != pa
    # the margin is a setting: 0 spreads the design over the whole range, on another parameter range too
    d = Engine({"x": (10, 20), "y": (-1, 1)}, EngineConfig(budget=30, n_initial=6, seed=3, design_margin=0.0))
    Y = np.array([[p["x"], p["y"]] for p in (d.ask() for _ in range(6))])
    assert Y.min(axis=0) == pytest.approx([10, -1]) and Y.max(axis=0) == pytest.approx([20, 1])
    with pytest.raises(EngineError, match="design_margin"):
        EngineConfig(design_margin=0.5)


def test_engine_finds_quadratic_minimum_under_noise() -> None:
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, budget=15, seed=2)
    rng = np.random.default_rng(2)
    while not eng.done:
        p = eng.ask()
        eng.tell(p, quad(p) + 0.02 * rng.standard_normal())
    r = eng.recommend()
    assert quad(r.params) < 0.01  # true J of the recommendation: near the minimum 0
    assert abs(r.predicted_j - quad(r.params)) < 0.05
    assert 0 < r.predicted_std < 0.1
    assert r.n_observations == 15
    assert r.best_observed_j == min(o.value for o in eng.observations)


def test_bowl_mean_only_for_the_first_runs() -> None:
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, budget=14, seed=3)
    # automatic: the initial design + 1 (twice the design until issue 23's tuning split chose the shorter bowl);
    # with a transfer prior the engine's own design counts, not the prior's shorter one
    assert eng.n_initial == 5 and eng.bowl_runs == 6
    assert Engine({"a": (0.0, 1.0)}, EngineConfig(n_initial=3)).bowl_runs == 4
    src = {"X": [[0.1], [0.5], [0.9]], "y": [1.0, 0.5, 1.0], "hyper": Hyper(np.array([0.5]), 1.0, 1e-4).to_dict()}
    with_prior = Engine({"a": (0.0, 1.0)}, EngineConfig(prior=src))
    assert with_prior.n_initial == 3 and with_prior.bowl_runs == 6
    rng = np.random.default_rng(3)
    means = []
    while not eng.done:
        p = eng.ask()
        eng.tell(p, math.sqrt(quad(p) + 0.01) + 0.01 * rng.standard_normal())
        eng.recommend()
        assert eng.hyper is not None
        means.append((eng._gp.config.mean, eng.hyper.bowl is not None))
    assert means[2:6] == [("bowl", True)] * 4  # from 3 runs on, a bowl-shaped J gets its bowl
    assert means[6:] == [("constant", False)] * 8  # then the constant mean
    r = eng.recommend()
    assert quad(r.params) < 0.01
    fixed = Engine({"a": (0.0, 1.0)}, EngineConfig(bowl_runs=3, gp=GPConfig(mean="constant")))
    assert fixed.bowl_runs == 3 and fixed._gp_config().mean == "constant"
    with pytest.raises(EngineError, match="bowl_runs"):
        EngineConfig(bowl_runs=-1)


def test_the_mean_after_the_bowl_is_configurable() -> None:
    """GPConfig.bowl_then (issue 23): after the bowl's runs a linear trend instead of the constant, through the
    engine and its JSON state; J falling towards the corner (0, 1) is carried there by the trend."""
    cfg = EngineConfig(budget=10, seed=2, gp=GPConfig(bowl_then="linear"))
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    rng = np.random.default_rng(2)
    slopes = []
    while not eng.done:
        p = eng.ask()
        eng.tell(p, 2.0 + 1.5 * p["a"] - p["b"] + 0.01 * rng.standard_normal())
        eng.recommend()
        assert eng.hyper is not None
        slopes.append(eng.hyper.slope is not None)
    assert slopes[:6] == [False] * 6 and slopes[6:] == [True] * 4  # the bowl's 6 runs, then the trend
    r = eng.recommend()
    assert r.params["a"] < 0.02 and r.params["b"] > 0.98
    eng2 = Engine.from_json(eng.to_json())
    assert eng2.config.gp.bowl_then == "linear"
    assert eng2.recommend().params == pytest.approx(r.params, abs=1e-9)


def test_best_guesses_are_asked_first_and_the_design_still_spans_the_space() -> None:
    space = {"a": (0.0, 1.0), "b": (0.0, 1.0)}
    plain = Engine(space, EngineConfig(n_initial=5, seed=4))
    guessed = Engine(space, EngineConfig(n_initial=5, seed=4, initial_points=({"a": 0.0, "b": 1.0},)))
    plain_pts = [plain.ask_with_info() for _ in range(5)]
    asks = [guessed.ask_with_info() for _ in range(5)]
    assert asks[0].params == {"a": 0.0, "b": 1.0} and asks[0].kind == "guess"
    assert all(s.kind == "initial" for s in asks[1:])
    # the guess took the place of the design point nearest to it; the other four are the plain design's
    rest = [tuple(s.params.values()) for s in asks[1:]]
    kept = [tuple(s.params.values()) for s in plain_pts]
    assert len(set(rest) & set(kept)) == 4
    nearest = min(kept, key=lambda p: (p[0] - 0.0) ** 2 + (p[1] - 1.0) ** 2)
    assert nearest not in rest
    # the configuration carries the guesses through JSON
    again = Engine.from_json(guessed.to_json())
    assert again.config.initial_points == ({"a": 0.0, "b": 1.0},)


@pytest.mark.slow
def test_two_asks_without_tell_differ_and_tell_clears_pending() -> None:
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, budget=10, n_initial=3, seed=0)
    for _ in range(3):
        p = eng.ask()
        eng.tell(p, quad(p))
    p1, p2 = eng.ask(), eng.ask()
    assert p1 != p2
    assert len(eng.pending) == 2
    eng.tell(p2, quad(p2))
    assert eng.pending == [p1]
    eng.tell_failed(p1, "ECU busy")
    assert eng.pending == [] and eng.n_trials == 5
    assert eng.failures[0].reason == "ECU busy"


def test_failed_point_is_not_proposed_again() -> None:
    eng = Engine({"a": (0.0, 1.0)}, budget=10, n_initial=2, seed=0)
    for p in ({"a": 0.1}, {"a": 0.9}):
        eng.tell(p, (p["a"] - 0.5) ** 2)
    nxt = eng.ask()
    eng.tell_failed(nxt, "apply failed")
    again = eng.ask()
    assert abs(again["a"] - nxt["a"]) > 0.005


def test_json_round_trip_continues_identically() -> None:
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0), "c": 0.25}, budget=12, seed=7)
    for i in range(6):
        p = eng.ask()
        assert p["c"] == 0.25  # fixed values pass through
        if i == 4:
            eng.tell_failed(p, "invalid")
        else:
            eng.tell(p, quad(p))
    pending = eng.ask()
    clone = Engine.from_json(eng.to_json())
    assert clone.pending == [pending]
    assert clone.config == eng.config
    eng.tell(pending, quad(pending))
    clone.tell(pending, quad(pending))
    # the same point (up to BLAS rounding, which may depend on memory alignment)
    for _ in range(3):
        a, b = clone.ask(), eng.ask()
        assert a.keys() == b.keys() and all(a[k] == pytest.approx(b[k], abs=1e-6) for k in a)
        clone.tell(a, quad(a))
        eng.tell(b, quad(b))
    ra, rb = clone.recommend(), eng.recommend()
    assert all(ra.params[k] == pytest.approx(rb.params[k], abs=1e-6) for k in ra.params)
    assert ra.predicted_j == pytest.approx(rb.predicted_j, rel=1e-6)
    with pytest.raises(EngineError, match="version"):
        Engine.from_json('{"version": 99}')
    with pytest.raises(EngineError, match="JSON"):
        Engine.from_json("{torn")


def test_a_state_written_before_bowl_loo_reads_back_without_it() -> None:
    """``gp.bowl_loo`` became the default on 2026-11-24: an engine state without the key (written before) goes on
    as it ran, with the bowl unchecked; a state with it keeps its value."""
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, budget=8, seed=1)
    assert eng.config.gp.bowl_loo
    data = json.loads(eng.to_json())
    assert Engine.from_json(json.dumps(data)).config.gp.bowl_loo
    del data["config"]["gp"]["bowl_loo"]
    assert not Engine.from_json(json.dumps(data)).config.gp.bowl_loo
    # a dict of overrides (the benches' --bac-config) is not a saved state: the defaults apply (outside review D4)
    assert EngineConfig.from_dict({"budget": 10}).gp.bowl_loo
    assert EngineConfig.from_dict({"budget": 10, "gp": {"mean": "bowl"}}).gp.bowl_loo


def test_bad_input_is_refused_clearly() -> None:
    eng = Engine({"a": (0.0, 1.0), "c": 0.25}, budget=5)
    with pytest.raises(OutOfBoundsError, match="outside its declared bounds") as err:
        eng.tell({"a": 1.5}, 1.0)
    # the optimizer's words, not the ECU path's "nothing was written" (outside review 2026-11-29)
    assert "the optimizer refuses it" in str(err.value) and "written" not in str(err.value)
    with pytest.raises(UnknownParameterError, match="unknown parameter 'zz'"):
        eng.tell({"a": 0.5, "zz": 1.0}, 1.0)
    with pytest.raises(SpaceError, match=r"fixed at 0\.25"):
        eng.tell({"a": 0.5, "c": 0.3}, 1.0)
    with pytest.raises(EngineError, match="finite"):
        eng.tell({"a": 0.5}, float("nan"))
    with pytest.raises(EngineError, match="nothing has been told"):
        eng.recommend()
    with pytest.raises(SpaceError, match="lower < upper"):
        Engine({"a": (1.0, 0.0)})
    with pytest.raises(EngineError, match="budget"):
        EngineConfig(budget=0)


def test_search_space_from_spec_forms() -> None:
    s1 = SearchSpace.from_spec({"x": (0, 2), "y": (1, 3, 0.5), "k": 4})
    s2 = SearchSpace.from_spec([("x", 0, 2), ("y", 1, 3, 0.5)])
    assert s1.names == s2.names == ("x", "y")
    assert s1.fixed == {"k": 4.0}
    np.testing.assert_allclose(s1.from_unit(np.array([0.5, 0.3])), [1.0, 1.5])
    assert SearchSpace.from_dict(s1.to_dict()) == s1


@pytest.mark.parametrize("rule", ["mean", "observed", "best_run"])
def test_the_configured_recommendation_rule_is_what_recommend_gives(rule: str) -> None:
    """EngineConfig.recommend_rule (bo_agent's recommend_rule, issue 23) decides recommend() without an argument;
    it is checked, kept in the state, and read back from a journal for an offline refit."""
    from bac_agent.journal import journaled_engine_options

    cfg = EngineConfig(budget=12, n_initial=5, seed=2, recommend_rule=rule)
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    rng = np.random.default_rng(0)
    for _ in range(8):
        p = eng.ask()
        eng.tell(p, (p["a"] - 0.37) ** 2 + (p["b"] - 0.61) ** 2 + 0.01 * rng.standard_normal())
    rec = eng.recommend()
    assert rec.rule == rule
    assert rec == eng.recommend(rule)
    driven = [o.params for o in eng.observations]
    if rule == "mean":
        assert not any(rec.params == pytest.approx(p) for p in driven)  # between the runs
    elif rule == "best_run":
        assert rec.params == min(eng.observations, key=lambda o: o.value).params
    else:
        assert any(rec.params == pytest.approx(p) for p in driven)
    assert Engine.from_json(eng.to_json()).recommend().rule == rule
    opts = journaled_engine_options({"config": {"recommend_rule": rule}})
    assert EngineConfig.from_dict(opts).recommend_rule == rule
    assert EngineConfig.from_dict(journaled_engine_options({})).recommend_rule == "mean"


def test_an_unknown_recommendation_rule_is_refused() -> None:
    with pytest.raises(EngineError, match="recommend_rule must be one of mean, observed, best_run"):
        EngineConfig(recommend_rule="median")


def test_one_run_is_recommended_as_driven_not_an_arbitrary_point() -> None:
    """With one run (or runs all equal) and no transfer prior the posterior mean is flat: its "argmin" was an
    arbitrary calibration that was never driven (on the benchmark it happened to land near the corner optimum
    of the Controller II families for one seed: found after 1 run by chance). The driven run is the answer."""
    for seed in range(4):
        eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=10, seed=seed))
        p = eng.ask()
        eng.tell(p, 1.0)
        rec = eng.recommend()
        assert rec.params == pytest.approx(p)
        assert rec.predicted_j == pytest.approx(1.0)
        q = eng.ask()
        eng.tell(q, 1.0)  # equal: still nothing to model
        assert eng.recommend().params in (pytest.approx(p), pytest.approx(q))
        r = eng.ask()
        eng.tell(r, 0.5)  # now the model decides, and may go between the runs
        assert eng.recommend().n_observations == 3


@pytest.mark.slow
def test_one_run_with_a_transfer_prior_the_runs_do_not_support_is_recommended_as_driven() -> None:
    """A transfer prior gives the model its shape only while it is in use: with a low prior_weight one run does
    not take it up (prior_in_use 0), the engine's own model of one run is flat, and its "argmin" would again be
    an arbitrary calibration never driven (found by the outside review: (0.015, 0.931) for a run at (0.3, 0.6))."""
    from bac_agent.bo.prior import SourceSurface

    src = SourceSurface.from_function(lambda U: np.sum((U - [0.3, 0.6]) ** 2, axis=1), 2, 64, "bowl")
    space = [("u0", 0.0, 1.0, 0.001), ("u1", 0.0, 1.0, 0.001)]
    for weight in (0.3, 0.1):
        eng = Engine(space, EngineConfig(budget=10, seed=0, prior=src.to_dict(), prior_weight=weight))
        p = eng.ask()
        eng.tell(p, 1.0)
        rec = eng.recommend()
        assert rec.transfer["prior_in_use"] == 0.0
        assert rec.params == pytest.approx(p)
    eng = Engine(space, EngineConfig(budget=10, seed=0, prior=src.to_dict(), prior_runs=1))
    for _ in range(2):
        eng.tell(eng.ask(), 1.0)  # two equal runs after the prior's last run: nothing to model
    assert eng.recommend().params in [pytest.approx(o.params) for o in eng.observations]


@pytest.mark.parametrize(
    ("hyper", "message"),
    [
        ({"outputscale": "x"}, "could not convert"),
        ({"lengthscales": [[0.3], [0.2, 0.1]]}, "inhomogeneous|sequence"),
        ({"warp": [[1.0, 1.0]]}, "do not fit together"),
    ],
)
def test_a_saved_state_with_malformed_hyperparameters_is_a_malformed_engine_state(
    hyper: dict[str, object], message: str
) -> None:
    eng = Engine({"x": (0.0, 1.0), "y": (0.0, 1.0)}, EngineConfig(budget=8, seed=1))
    for _ in range(4):
        p = eng.ask()
        eng.tell(p, (p["x"] - 0.3) ** 2 + (p["y"] - 0.6) ** 2)
    eng.ask()
    state = eng.state_dict()
    assert state.get("hyper")
    state["hyper"] = {**state["hyper"], **hyper}
    with pytest.raises(EngineError, match=f"malformed engine state.*({message})"):
        Engine.from_state_dict(json.loads(json.dumps(state)))
