"""The output warp: a Yeo-Johnson transform of the runs, fitted, inverted, and used by the engine."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import yeojohnson, yeojohnson_llf, yeojohnson_normmax

from bac_agent.bo import Engine, EngineConfig, EngineError
from bac_agent.bo.warp import LAMBDA_BOUNDS, OutputWarp, _lambda_mle, _log_likelihood


@pytest.mark.parametrize("lam", [0.0, 0.35, 1.0, 1.6, 2.0])
def test_warp_is_scipys_yeo_johnson_and_inverts(lam: float) -> None:
    y = np.linspace(-3.0, 9.0, 61)
    w = OutputWarp(loc=2.0, scale=1.5, lam=lam)
    t = w.forward(y)
    np.testing.assert_allclose(t, yeojohnson((y - 2.0) / 1.5, lam), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(w.inverse(t), y, rtol=1e-10, atol=1e-10)
    assert np.all(np.diff(t) > 0.0)  # strictly increasing: the argmin and the order of runs are kept


def test_std_is_carried_through_the_slope_of_the_inverse() -> None:
    w = OutputWarp(loc=1.0, scale=0.5, lam=0.3)
    mean_t, std_t = np.array([-1.2, 0.0, 0.8, 2.5]), np.array([0.1, 0.2, 0.05, 0.3])
    m, s = w.inverse_mean_std(mean_t, std_t)
    np.testing.assert_allclose(m, w.inverse(mean_t), rtol=1e-12)
    h = 1e-6
    slope = (w.inverse(mean_t + h) - w.inverse(mean_t - h)) / (2 * h)
    np.testing.assert_allclose(s, slope * std_t, rtol=1e-6)


def test_fit_makes_skewed_runs_gaussian_and_keeps_lambda_in_bounds() -> None:
    rng = np.random.default_rng(3)
    # many runs near the bottom of the basin and a long tail up a flank: lambda < 1 compresses the tail
    y = 0.9 + rng.gamma(1.5, 0.05, 60)
    w = OutputWarp.fit(y)
    assert LAMBDA_BOUNDS[0] <= w.lam < 0.8
    t = w.forward(y)
    skew = lambda v: float(np.mean((v - v.mean()) ** 3) / np.std(v) ** 3)
    assert skew(y) > 1.0 and abs(skew(t)) < 0.3
    # log-normal runs want lambda < 0: clipped to 0, where the warp still maps the real line onto itself
    w = OutputWarp.fit(np.exp(3.0 * rng.standard_normal(80)))
    assert w.lam == LAMBDA_BOUNDS[0]
    assert np.isfinite(w.inverse(np.array([-50.0, 50.0]))).all()


def test_lambda_is_scipys_maximum_likelihood_clipped_to_the_bounds() -> None:
    rng = np.random.default_rng(1)
    lams = np.array([0.0, 0.4, 1.0, 1.7, 2.0])
    for k in range(40):
        n = int(rng.integers(3, 100))
        y = [
            rng.gamma(1.5, 1.0, n),
            -rng.gamma(1.5, 1.0, n),
            rng.standard_normal(n),
            np.exp(2.0 * rng.standard_normal(n)),
        ][k % 4]
        z = (y - y.mean()) / y.std()
        np.testing.assert_allclose(_log_likelihood(z, lams), [yeojohnson_llf(v, z) for v in lams], rtol=1e-9, atol=1e-9)
        with np.errstate(all="ignore"):
            ref = float(np.clip(yeojohnson_normmax(z), *LAMBDA_BOUNDS))
        got = _lambda_mle(z)
        assert LAMBDA_BOUNDS[0] <= got <= LAMBDA_BOUNDS[1]
        # the same maximum (on a flat likelihood the two lambdas may differ a little, their likelihoods not)
        assert yeojohnson_llf(got, z) >= yeojohnson_llf(ref, z) - 1e-8


def test_fit_is_the_identity_when_nothing_can_be_estimated() -> None:
    assert OutputWarp.fit(np.array([1.0, 2.0])).is_identity  # two runs have no shape
    assert OutputWarp.fit(np.full(6, 0.7)).is_identity  # all equal
    np.testing.assert_allclose(OutputWarp().forward(np.array([-1.0, 0.5])), [-1.0, 0.5])


def _skewed(p: dict[str, float]) -> float:
    return float(np.exp(4.0 * ((p["a"] - 0.3) ** 2 + (p["b"] - 0.6) ** 2)))


def test_engine_predicts_in_j_units_through_the_warp() -> None:
    rng = np.random.default_rng(0)
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=30, seed=2))
    plain = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=30, seed=2, output_warp="none"))
    for _ in range(14):
        p = {"a": float(rng.random()), "b": float(rng.random())}
        v = _skewed(p)
        eng.tell(p, v)
        plain.tell(p, v)
    eng.recommend()
    assert not eng._warp.is_identity and eng._warp.lam < 1.0  # the runs' long upper tail is compressed
    assert plain._warp.is_identity
    # predictions are J, not the GP's warped units: both engines agree on the values they were told
    for o in eng.observations[:5]:
        m, s = eng.predict(o.params)
        assert m == pytest.approx(o.value, rel=0.05, abs=0.02) and s > 0.0
    r = eng.recommend()
    assert abs(r.params["a"] - 0.3) < 0.15 and abs(r.params["b"] - 0.6) < 0.15
    assert r.predicted_j == pytest.approx(_skewed(r.params), abs=0.15)
    assert eng.ask_with_info().predicted_j > 0.5  # a J, where the warped units would be standardized around 0


def test_engine_refuses_an_unknown_warp_and_round_trips_it() -> None:
    with pytest.raises(EngineError, match="output_warp"):
        EngineConfig(output_warp="box-cox")
    cfg = EngineConfig(budget=9, output_warp="none")
    assert EngineConfig.from_dict(cfg.to_dict()) == cfg
    eng = Engine({"a": (0.0, 1.0)}, cfg)
    assert Engine.from_json(eng.to_json()).config.output_warp == "none"
