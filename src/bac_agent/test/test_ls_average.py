"""The model average over two lengthscale priors (GPConfig.ls_average, issue 23, opt-in): both fits weighed by their
Laplace evidences, the engine's noisy EI and posterior mean averaged over them."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.special import logsumexp

from bac_agent.bo import Engine, EngineConfig
from bac_agent.bo.acquisition import log_ei
from bac_agent.bo.gp import GP, GPConfig, GPError


def _runs(seed: int, n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.random((n, 2))
    return X, np.sin(5.0 * X[:, 0]) + 0.4 * X[:, 1] + 0.02 * rng.standard_normal(n)


@pytest.mark.slow
def test_laplace_evidence_matches_importance_sampling() -> None:
    """GP.log_evidence against an importance-sampling estimate of the same integral (the hyperparameters' prior
    times the likelihood; the proposal a widened Gaussian at the MAP), under both lengthscale priors."""
    rng = np.random.default_rng(1)
    X = rng.random((8, 1))
    y = np.sin(6.0 * X[:, 0]) + 0.05 * rng.standard_normal(8)
    estimates = []
    for sd in (1.0, 0.5):
        gp = GP(GPConfig(mean="constant", ls_scale=sd)).fit(X, y, np.random.default_rng(0))
        assert gp.hyper is not None
        v = gp.hyper.to_vector()
        k, h = v.size, 1e-4
        H = np.array(
            [(gp.neg_log_posterior(v + e)[1] - gp.neg_log_posterior(v - e)[1]) / (2 * h) for e in h * np.eye(k)]
        )
        cov = 2.0 * np.linalg.inv(0.5 * (H + H.T))  # widened twice: heavier tails than the posterior
        draws = np.random.default_rng(2).multivariate_normal(v, cov, 1500)
        _, scale = gp._prior(1)
        log_joint = np.array([-gp.neg_log_posterior(w)[0] for w in draws]) - np.sum(np.log(scale))
        log_joint -= 0.5 * k * math.log(2.0 * math.pi)
        diff = draws - v
        log_q = -0.5 * np.sum(diff @ np.linalg.inv(cov) * diff, axis=1) - 0.5 * np.linalg.slogdet(2 * math.pi * cov)[1]
        is_est = float(logsumexp(log_joint - log_q) - math.log(draws.shape[0]))
        lap = gp.log_evidence()
        assert abs(lap - is_est) < 0.15, (sd, lap, is_est)
        estimates.append((lap, is_est))
    # the wiggly runs favour the wide prior (short lengthscales) by about 2 nats, by both estimates
    assert estimates[0][0] - estimates[1][0] > 1.0 and estimates[0][1] - estimates[1][1] > 1.0


def test_the_fit_is_both_fits_weighed_by_their_evidence() -> None:
    """GP.fit with ls_average: this GP the fit under ls_scale, ``alt`` the fit under the tighter prior (each as it
    is fitted alone from one seed of the generator), ``alt_weight`` the tempered posterior probability of the
    latter."""
    X, y = _runs(0)
    for temper in (1.0, 0.5, 0.0):
        cfg = GPConfig(ls_average=0.5, ls_average_temper=temper)
        gp = GP(cfg).fit(X, y, np.random.default_rng(4))
        seed = int(np.random.default_rng(4).integers(2**63 - 1))
        base = GP(replace(cfg, ls_average=0.0)).fit(X, y, np.random.default_rng(seed))
        tight = GP(replace(cfg, ls_average=0.0, ls_scale=0.5)).fit(X, y, np.random.default_rng(seed))
        assert gp.hyper is not None and base.hyper is not None and gp.alt is not None and gp.alt.hyper is not None
        assert tight.hyper is not None
        np.testing.assert_array_equal(gp.hyper.lengthscales, base.hyper.lengthscales)
        np.testing.assert_array_equal(gp.alt.hyper.lengthscales, tight.hyper.lengthscales)
        np.testing.assert_array_equal(gp.predict(X)[0], base.predict(X)[0])
        odds = temper * (tight.log_evidence() - base.log_evidence())
        # (the fit's evidences are computed on one BLAS thread, these on the process's: round-off apart)
        assert gp.alt_weight == pytest.approx(1.0 / (1.0 + math.exp(-odds)), rel=1e-9)
        if temper == 0.0:
            assert gp.alt_weight == 0.5
        else:
            assert abs(gp.alt_weight - 0.5) > 0.01  # the evidences differ
    # the tighter prior holds the lengthscales nearer to its median √2
    far = np.abs(np.log(np.asarray([base.hyper.lengthscales, tight.hyper.lengthscales]) / math.sqrt(2.0)))
    assert np.all(far[1] < far[0] - 0.05)


def _engine(gp: GPConfig, n: int = 9, **kw: object) -> Engine:
    def f(p: dict[str, float]) -> float:
        return float(np.hypot(p["a"] - 0.1, p["b"] - 0.9) + 0.3 * np.sin(6.0 * p["a"]))

    # the campaign these tests were written on: without the exploration along the faces (its 10th ask is the noisy
    # EI's, not a face's most uncertain calibration)
    kw = {"face_explore": 0, **kw}
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=20, seed=5, gp=gp, **kw))  # type: ignore[arg-type]
    for _ in range(n):
        p = eng.ask()
        eng.tell(p, f(p))
    return eng


def test_the_engine_predicts_and_recommends_by_the_averaged_posterior_mean() -> None:
    eng = _engine(GPConfig(ls_average=0.5, ls_average_temper=0.0))  # equal weights: both fits count
    gp = eng._model()
    assert gp.alt is not None and gp.alt_weight == 0.5
    U = np.random.default_rng(0).random((400, 2))
    m0, v0 = gp.predict_std_units(U)
    m1, v1 = gp.alt.predict_std_units(U)
    mu = 0.5 * (m0 + m1)
    mean, var = eng._mean_var(gp, U)
    np.testing.assert_allclose(mean, mu, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(var, 0.5 * (v0 + m0**2) + 0.5 * (v1 + m1**2) - mu**2, rtol=1e-10, atol=1e-12)
    assert np.max(np.abs(m1 - m0)) > 0.05  # the two fits differ: the average is neither
    # Engine.predict is the average through the output warp; the recommendation minimizes the averaged mean
    j = eng._warp.inverse_mean_std(gp.y_mean + gp.y_std * mu, gp.y_std * np.sqrt(var))[0]
    p = eng.predict({"a": U[0, 0], "b": U[0, 1]})
    assert p[0] == pytest.approx(j[0], rel=1e-9)
    rec = eng.recommend()
    u = np.array([rec.params["a"], rec.params["b"]])
    rec_mu = eng._mean_var(gp, u[None, :])[0][0]
    g = np.linspace(0.0, 1.0, 41)
    G = np.array(np.meshgrid(g, g, indexing="ij")).reshape(2, -1).T
    gm = eng._mean_var(gp, G)[0]
    assert rec_mu <= np.min(gm) + 1e-6
    # the argmin of either fit's mean alone is worse under the average than the recommendation
    for member in (gp, gp.alt):
        own = G[int(np.argmin(member.predict_std_units(G)[0]))]
        assert eng._mean_var(gp, own[None, :])[0][0] > rec_mu + 1e-3


def test_the_averaged_std_has_its_gradient() -> None:
    eng = _engine(GPConfig(ls_average=0.5, ls_average_temper=0.0))
    gp = eng._model()
    U = np.random.default_rng(1).random((5, 2)) * 0.8 + 0.1
    m, s, dm, ds = eng._mean_sd_grad(gp, U)
    mv, vv = eng._mean_var(gp, U)
    np.testing.assert_allclose(m, mv, rtol=1e-10)
    np.testing.assert_allclose(s, np.sqrt(vv), rtol=1e-8)
    h = 1e-6
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        fm = (eng._mean_var(gp, U + e)[0] - eng._mean_var(gp, U - e)[0]) / (2 * h)
        fs = (np.sqrt(eng._mean_var(gp, U + e)[1]) - np.sqrt(eng._mean_var(gp, U - e)[1])) / (2 * h)
        np.testing.assert_allclose(dm[:, k], fm, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(ds[:, k], fs, rtol=1e-5, atol=1e-6)


def test_the_acquisition_is_the_noisy_ei_averaged_over_both_fits() -> None:
    eng = _engine(GPConfig(ls_average=0.5, ls_average_temper=0.0))
    s = eng.ask_with_info()
    assert "averaged over the lengthscale priors' fits" in s.info["acquisition"]
    assert s.kind == "optimized"
    # a pending ask is fantasized in both fits: the next ask is another calibration
    s2 = eng.ask_with_info()
    assert any(abs(s2.params[n] - s.params[n]) > 1e-6 for n in s.params)


def test_off_the_engine_is_as_before_and_one_weight_near_one_is_that_fit_alone() -> None:
    plain = _engine(GPConfig(ls_average=0.0))
    assert plain._model().alt is None and plain._members(plain._model()) is None
    eng = _engine(GPConfig(ls_average=0.5))
    gp = eng._model()
    assert gp.alt is not None
    gp.alt_weight = 1.0 - 1e-9  # (as a fit whose evidence is overwhelming)
    assert eng._members(gp) is None
    U = np.random.default_rng(2).random((6, 2))
    np.testing.assert_array_equal(eng._mean_var(gp, U)[0], gp.alt.predict_std_units(U)[0])


def test_a_replayed_campaign_with_the_model_average_asks_what_it_asked() -> None:
    """Both fits start from the last hyperparameters of the fit under ls_scale, which the ask state carries: a
    resumed campaign (Engine.restore_ask) asks what the uninterrupted one asked."""

    def f(p: dict[str, float]) -> float:
        return float(np.sqrt(np.hypot(p["a"], 1.0 - p["b"])))

    cfg = EngineConfig(budget=12, seed=3, gp=GPConfig(ls_average=0.5))
    space = {"a": (0.0, 1.0), "b": (0.0, 1.0)}
    live = Engine(space, cfg)
    log = []
    while not live.done:
        p = live.ask()
        log.append((p, live.ask_state()))
        live.tell(p, f(p))
    fresh = Engine(space, cfg)
    for k, (p, state) in enumerate(log):
        q = fresh.ask()
        fresh.pending.clear()
        if k >= 1:
            assert all(abs(q[n] - p[n]) <= 1e-9 for n in p), k
        fresh.restore_ask(p, state)
        fresh.tell(p, f(p))
    restored = Engine.from_json(live.to_json())
    assert restored.recommend().params == live.recommend().params


def test_bad_ls_average_settings_are_refused() -> None:
    with pytest.raises(GPError, match="ls_average must be 0"):
        GPConfig(ls_average=-0.5)
    with pytest.raises(GPError, match="ls_average must be 0"):
        GPConfig(ls_average=float("nan"))
    with pytest.raises(GPError, match="ls_average_temper must be >= 0"):
        GPConfig(ls_average=0.5, ls_average_temper=-1.0)


def test_the_tighter_prior_may_have_its_own_median() -> None:
    """ls_average_median: the second fit's lengthscale prior is centred on this median (in any dimension)."""
    X, y = _runs(1)
    gp = GP(GPConfig(ls_average=0.3, ls_average_median=4.0, ls_dim_scale=0.5)).fit(X, y, np.random.default_rng(0))
    assert gp.alt is not None and gp.alt.hyper is not None and gp.hyper is not None
    loc, scale = gp.alt._prior(2)
    np.testing.assert_allclose(np.exp(loc[:2]), 4.0, rtol=1e-12)
    np.testing.assert_allclose(scale[:2], 0.3)
    assert np.all(gp.alt.hyper.lengthscales > gp.hyper.lengthscales)
    with pytest.raises(GPError, match="ls_average_median must be >= 0"):
        GPConfig(ls_average=0.5, ls_average_median=-1.0)


def test_plain_ei_with_the_model_average_is_the_ei_of_its_moments() -> None:
    """acquisition "ei": log EI of the mixture's mean and std, against the best averaged mean at a run."""
    eng = _engine(GPConfig(ls_average=0.5, ls_average_temper=0.0), acquisition="ei")
    gp = eng._model()
    s = eng.ask_with_info()
    u = np.array([[s.params["a"], s.params["b"]]])
    mu_obs = eng._mean_var(gp, gp.X)[0]
    mu, var = eng._mean_var(gp, u)
    here = log_ei(mu, np.sqrt(var), float(np.min(mu_obs)))[0]
    G = np.random.default_rng(3).random((500, 2))
    m, v = eng._mean_var(gp, G)
    assert here >= np.max(log_ei(m, np.sqrt(v), float(np.min(mu_obs)))) - 1e-6  # the maximizer beats the candidates


def test_the_default_is_the_average_with_equal_weights_and_an_old_saved_config_reads_back_without_it() -> None:
    """The default since 2026-11-25 (the tuning split, docs/agent.md); an engine state saved before it (a whole
    GPConfig without the key) ran one fit, and reads back so."""
    cfg = EngineConfig()
    assert cfg.gp.ls_average == 0.5 and cfg.gp.ls_average_temper == 0.0
    assert EngineConfig.from_dict({"budget": 9}).gp.ls_average == 0.5
    saved = cfg.to_dict()
    assert EngineConfig.from_dict(saved).gp.ls_average == 0.5
    del saved["gp"]["ls_average"]
    assert EngineConfig.from_dict(saved).gp.ls_average == 0.0
    # a campaign with the default fits both: the model average is in use
    eng = _engine(GPConfig())
    assert eng._members(eng._model()) == (0.5, eng._model().alt)


def test_predictions_follow_the_fit_whose_weight_is_within_1e_6_of_1() -> None:
    """(outside review, 2026-11-25) with one fit's weight within 1e-6 of 1 the recommendation and the acquisition use
    that fit: Engine.predict must say what they use, not the other fit's prediction."""
    eng = _engine(GPConfig(ls_average=0.5))
    gp = eng._model()
    assert gp.alt is not None
    gp.alt_weight = 1.0 - 1e-9
    U = np.array([[0.9, 0.1], [0.3, 0.6]])
    tight = eng._warp.inverse_mean_std(*gp.alt.predict(U))[0]
    wide = eng._warp.inverse_mean_std(*gp.predict(U))[0]
    assert np.max(np.abs(tight - wide)) > 1e-3  # the two fits differ here
    np.testing.assert_allclose(eng.predict_unit(U)[0], tight, rtol=1e-12)


def test_the_evidence_of_a_fit_made_before_the_warp_is_learned_is_computed() -> None:
    """(outside review) ls_average_temper > 0 with gp.warp and fewer runs than warp_runs: the fits ran without the
    warp, and their evidences must be judged so (a shape error before)."""
    rng = np.random.default_rng(3)
    X = rng.random((6, 2))
    y = np.sum((X - 0.4) ** 2, axis=1) + 0.01 * rng.standard_normal(6)
    gp = GP(GPConfig(warp=True, warp_runs=10, ls_average=0.5, ls_average_temper=1.0)).fit(X, y, rng)
    assert gp.hyper is not None and gp.hyper.warp is None
    assert gp.alt is not None and 0.0 < gp.alt_weight < 1.0
    assert np.isfinite(gp.log_evidence())


def test_a_partial_gp_override_keeps_today_s_defaults_but_a_whole_old_dump_reads_as_it_ran() -> None:
    """(outside review) {"gp": {"maxiter": 100}} is an override, not a dump saved before ls_average and bowl_loo."""
    cfg = EngineConfig.from_dict({"gp": {"maxiter": 100}})
    assert cfg.gp.maxiter == 100 and cfg.gp.ls_average == 0.5 and cfg.gp.bowl_loo is True
    old = {k: v for k, v in dataclasses.asdict(GPConfig()).items() if k not in ("ls_average", "bowl_loo")}
    cfg = EngineConfig.from_dict({"gp": old})
    assert cfg.gp.ls_average == 0.0 and cfg.gp.bowl_loo is False
