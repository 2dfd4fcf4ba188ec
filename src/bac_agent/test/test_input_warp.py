"""The learned input warping (GPConfig.warp, issue 23): a Kumaraswamy CDF per input, learned with the GP."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from bac_agent.bo import Engine, EngineConfig
from bac_agent.bo.acquisition import NoisyEI, log_ei
from bac_agent.bo.gp import GP, GPConfig, GPError, Hyper, kumaraswamy


def _kink(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Runs of a function with a kink near the bound x0 = 0 (a square-root valley at x0 = 0.03)."""
    rng = np.random.default_rng(seed)
    X = rng.random((n, 2))
    return X, np.sqrt(np.abs(X[:, 0] - 0.03)) + 0.2 * X[:, 1] + 0.005 * rng.standard_normal(n)


def test_kumaraswamy_and_its_derivatives() -> None:
    rng = np.random.default_rng(0)
    X = rng.random((7, 3))
    a, b = np.array([0.3, 1.0, 2.5]), np.array([1.7, 1.0, 0.4])
    u, du, dla, dlb = kumaraswamy(X, a, b)
    assert np.all((u > 0.0) & (u < 1.0))
    h = 1e-6
    np.testing.assert_allclose(du, (kumaraswamy(X + h, a, b)[0] - kumaraswamy(X - h, a, b)[0]) / (2 * h), rtol=1e-6)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fa = (kumaraswamy(X, a * np.exp(e), b)[0] - kumaraswamy(X, a * np.exp(-e), b)[0]) / (2 * h)
        fb = (kumaraswamy(X, a, b * np.exp(e))[0] - kumaraswamy(X, a, b * np.exp(-e))[0]) / (2 * h)
        np.testing.assert_allclose(dla[:, k], fa[:, k], rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(dlb[:, k], fb[:, k], rtol=1e-5, atol=1e-9)
    # a = b = 1 is the identity (up to the map into [eps, 1 - eps]); a < 1 stretches the region near 0
    np.testing.assert_allclose(u[:, 1], X[:, 1], atol=1e-6)
    assert kumaraswamy(np.array([[0.02]]), np.array([0.3]), np.array([1.0]))[0][0, 0] > 0.25


@pytest.mark.parametrize("mean", ["constant", "zero"])
def test_warped_likelihood_gradient_matches_finite_differences(mean: str) -> None:
    X, y = _kink(9, seed=1)
    gp = GP(GPConfig(mean=mean, warp=True))
    gp._set_data(X, y)
    gp._offset = 0.1 * X[:, 1]  # (a fixed trend, e.g. the bowl's, subtracted while fitting)
    v = np.concatenate([np.log([0.4, 0.7]), [0.1, -3.0], np.log([0.5, 1.5, 2.0, 0.6])])
    _, g = gp.neg_log_posterior(v)
    fd = approx_fprime(v, lambda w: gp.neg_log_posterior(w)[0], 1e-7)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-4)
    assert g.shape == (8,) and np.all(np.abs(g[4:]) > 1e-3)  # the warp's part is not zero


def test_warped_predictions_and_noisy_ei_have_exact_gradients() -> None:
    X, y = _kink(12, seed=2)
    gp = GP(GPConfig(warp=True)).fit(X, y, np.random.default_rng(0))
    assert gp.hyper is not None and gp.hyper.warp is not None
    Q = np.random.default_rng(3).random((5, 2))
    mu, sd, dmu, dsd = gp.predict_with_grad(Q)
    m2, v2 = gp.predict_std_units(Q)
    np.testing.assert_allclose(mu, m2, rtol=1e-12)
    np.testing.assert_allclose(sd, np.sqrt(v2), rtol=1e-10)
    np.testing.assert_allclose(gp.predict_mean_units(Q), mu, rtol=1e-12)
    for i, x in enumerate(Q):
        np.testing.assert_allclose(
            dmu[i], approx_fprime(x, lambda q: gp.predict_std_units(q[None])[0][0], 1e-7), rtol=1e-4, atol=1e-6
        )
        np.testing.assert_allclose(
            dsd[i], approx_fprime(x, lambda q: np.sqrt(gp.predict_std_units(q[None])[1][0]), 1e-7), rtol=1e-4, atol=1e-6
        )
    nei = NoisyEI(gp, 32, np.random.default_rng(1))
    val, g = nei.value_and_grad(Q)
    np.testing.assert_allclose(val, nei(Q), rtol=1e-9)
    eps = 1e-6
    fd = np.stack([(nei(Q + eps * e) - nei(Q - eps * e)) / (2 * eps) for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6)


def test_noisy_ei_without_noise_is_ei_over_the_best_mean_through_the_warp() -> None:
    # as in test_engine: with (almost) no noise every draw at the runs is the posterior mean there; the draws'
    # kernel must see the runs warped as the GP does
    X, y = _kink(10, seed=5)
    h = Hyper(np.array([0.3, 0.6]), 1.0, 1e-9, warp=np.array([[0.3, 1.0], [1.0, 2.0]]))
    gp = GP(GPConfig(mean="constant", warp=True)).condition(X, y, h)
    nei = NoisyEI(gp, 16, np.random.default_rng(1))
    Q = np.random.default_rng(3).random((20, 2))
    mu, var = gp.predict_std_units(Q)
    best = float(np.min(gp.predict_std_units(gp.X)[0]))
    np.testing.assert_allclose(nei(Q), log_ei(mu, np.sqrt(var), best), rtol=1e-3, atol=1e-3)


def test_without_the_warp_the_model_is_the_plain_one() -> None:
    X, y = _kink(10, seed=3)
    gp = GP(GPConfig()).fit(X, y, np.random.default_rng(0))
    assert gp.hyper is not None and gp.hyper.warp is None and gp.hyper.to_vector().size == 4
    Q = np.random.default_rng(4).random((6, 2))
    assert gp.hyper.kernel_inputs(Q) is Q
    # unfitted, the warp's prior mode is the identity
    mode = GP(GPConfig(warp=True)).condition(X, y)
    assert mode.hyper is not None and mode.hyper.warp is not None
    np.testing.assert_allclose(mode.hyper.kernel_inputs(Q), Q, atol=1e-6)
    # the identity warp (a = b = 1, pinned by its bounds) gives the plain GP's fit, up to the map into [eps, 1 - eps]
    plain = GP(GPConfig(mean="constant")).fit(X, y, np.random.default_rng(0))
    pinned = GP(GPConfig(mean="constant", warp=True, warp_bounds=(1.0, 1.0))).fit(X, y, np.random.default_rng(0))
    assert plain.hyper is not None and pinned.hyper is not None and pinned.hyper.warp is not None
    np.testing.assert_allclose(pinned.hyper.warp, 1.0)
    np.testing.assert_allclose(pinned.hyper.lengthscales, plain.hyper.lengthscales, rtol=1e-4)
    np.testing.assert_allclose(pinned.predict(Q)[0], plain.predict(Q)[0], rtol=1e-5, atol=1e-6)
    # the learned warp survives the saved state (to_dict, JSON, from_dict)
    back = Hyper.from_dict(json.loads(json.dumps(pinned.hyper.to_dict())))
    np.testing.assert_array_equal(back.warp, pinned.hyper.warp)
    with pytest.raises(GPError, match="warp"):
        GPConfig(warp=True, warp_bounds=(1.5, 10.0))


def test_the_warp_is_learned_where_the_data_have_a_kink_near_a_bound() -> None:
    for seed in range(4):
        X, y = _kink(20, seed)
        gp = GP(GPConfig(warp=True)).fit(X, y, np.random.default_rng(0))
        assert gp.hyper is not None and gp.hyper.warp is not None
        a, b = gp.hyper.warp
        assert a[0] < 0.6  # the region near x0 = 0 stretched
        assert 0.6 < a[1] < 1.6 and 0.6 < b[1] < 1.6  # the smooth input stays near the identity
        plain = GP(GPConfig()).fit(X, y, np.random.default_rng(0))
        assert plain.hyper is not None
        # the warped model explains the runs better (log marginal likelihood of its own fit)
        assert gp.log_marginal_likelihood(gp.hyper) > plain.log_marginal_likelihood(plain.hyper)


def test_an_engine_with_the_warp_runs_and_saves_it() -> None:
    cfg = EngineConfig(budget=9, seed=1, gp=GPConfig(warp=True))
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    rng = np.random.default_rng(1)
    while not eng.done:
        p = eng.ask()
        eng.tell(p, np.sqrt(np.hypot(p["a"], 1.0 - p["b"])) + 0.01 * rng.standard_normal())
    r = eng.recommend()
    assert eng.hyper is not None and eng.hyper.warp is not None
    again = Engine.from_json(eng.to_json())
    assert again.config.gp.warp and again.config.gp.warp_bounds == (0.1, 10.0)
    assert again.recommend().params == pytest.approx(r.params, abs=1e-9)


def test_the_warp_waits_for_warp_runs() -> None:
    X, y = _kink(12, seed=6)
    late = GPConfig(warp=True, warp_runs=10)
    early = GP(late).fit(X[:9], y[:9], np.random.default_rng(0))
    plain = GP(GPConfig()).fit(X[:9], y[:9], np.random.default_rng(0))
    assert early.hyper is not None and plain.hyper is not None
    assert early.hyper.warp is None and early.config.warp  # the fit without it, the configuration kept
    np.testing.assert_array_equal(early.hyper.lengthscales, plain.hyper.lengthscales)
    full = GP(late).fit(X, y, np.random.default_rng(0))
    assert full.hyper is not None and full.hyper.warp is not None


def test_ls_select_keeps_the_kernel_that_predicts_the_runs_left_out_better() -> None:
    """GPConfig.ls_select (issue 23, opt-in): the fit under the configured and under a tighter lengthscale prior,
    the one with the better leave-one-out density kept, as it would be fitted alone."""
    from dataclasses import replace

    rng = np.random.default_rng(3)
    X = rng.random((7, 2))
    chosen = set()
    for y in (np.sin(9.0 * X[:, 0]) + 0.3 * X[:, 1], 0.8 * X[:, 0] - X[:, 1] + 0.05 * rng.standard_normal(7)):
        cfg = GPConfig(mean="constant", ls_select=0.3, ls_average=0.0)
        sel = GP(cfg).fit(X, y, np.random.default_rng(0))
        assert sel.hyper is not None and sel.config.ls_select == 0.3
        seed = int(np.random.default_rng(0).integers(2**63 - 1))
        fits = [
            GP(replace(cfg, ls_select=0.0, **kw)).fit(X, y, np.random.default_rng(seed))  # type: ignore[arg-type]
            for kw in ({}, {"ls_scale": 0.3})
        ]
        loos = [f.loo_log_predictive(f.hyper.to_vector(), False) for f in fits if f.hyper is not None]
        kept = fits[int(np.argmax(loos))]
        assert kept.hyper is not None
        np.testing.assert_array_equal(sel.hyper.lengthscales, kept.hyper.lengthscales)
        np.testing.assert_array_equal(sel.predict(X)[0], kept.predict(X)[0])
        chosen.add(int(np.argmax(loos)))
    assert chosen == {0, 1}  # the wiggly runs keep the wide prior's short lengthscale, the tilt the tight prior's


def _replayed_asks_that_differ(gp: GPConfig) -> int:
    """An engine fed the same tells and each ask's state (Engine.restore_ask, as a resumed campaign is) asks
    what the uninterrupted one asked: the count of asks that differ."""

    def f(p: dict[str, float]) -> float:
        return float(np.sqrt(np.hypot(p["a"], 1.0 - p["b"])))

    cfg = EngineConfig(budget=14, seed=3, gp=gp)
    space = {"a": (0.0, 1.0), "b": (0.0, 1.0)}
    live = Engine(space, cfg)
    log = []
    while not live.done:
        p = live.ask()
        log.append((p, live.ask_state()))
        live.tell(p, f(p))
    fresh = Engine(space, cfg)
    diffs = 0
    for k, (p, state) in enumerate(log):
        q = fresh.ask()
        fresh.pending.clear()
        diffs += int(k >= 1 and any(abs(q[n] - p[n]) > 1e-9 for n in p))
        fresh.restore_ask(p, state)
        fresh.tell(p, f(p))
    return diffs


@pytest.mark.slow
def test_a_replayed_campaign_with_the_warp_asks_what_it_asked() -> None:
    """The ask state carries the learned warp (the next fit's warm start; the outside review found one ask of 14
    differing without it)."""
    assert _replayed_asks_that_differ(GPConfig(warp=True)) == 0


def test_bad_warp_and_ls_select_settings_are_refused() -> None:
    with pytest.raises(GPError, match="warp_runs must be >= 0"):
        GPConfig(warp=True, warp_runs=-1)
    with pytest.raises(GPError, match="ls_select must be 0"):
        GPConfig(ls_select=1.5)  # not tighter than ls_scale 1.0
    with pytest.raises(GPError, match="ls_select must be 0"):
        GPConfig(ls_select=float("nan"))
    with pytest.raises(GPError, match="warp_sd must be > 0"):
        GPConfig(warp=True, warp_sd=0.0)
