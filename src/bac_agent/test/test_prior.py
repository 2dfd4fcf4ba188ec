"""The transfer prior (bo/prior.py): a source's surface, its weight against the car's runs, the engine with it."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from bac_agent.bo import Engine, EngineConfig
from bac_agent.bo.acquisition import NoisyEI
from bac_agent.bo.engine import KIND_OPTIMIZED, KIND_PRIOR, EngineError
from bac_agent.bo.gp import GPError
from bac_agent.bo.prior import SourceSurface

OPT = np.array([0.7, 0.25])


def sim(U: np.ndarray) -> np.ndarray:
    """The 'simulator': a bowl with its optimum at OPT."""
    return np.sqrt(0.02 + np.sum((np.atleast_2d(U) - OPT) ** 2 * [1.0, 2.0], axis=1))


def car(U: np.ndarray) -> np.ndarray:
    """The 'car': the simulator's shape at another level and scale."""
    return 3.0 + 1.7 * sim(np.atleast_2d(U))


def test_source_surface_fits_and_round_trips() -> None:
    src = SourceSurface.from_function(sim, 2, 64, label="test")
    assert np.allclose(src.argmin(), OPT, atol=0.03)
    U = np.random.default_rng(0).random((20, 2))
    assert np.max(np.abs(src.predict_j(U) - sim(U))) < 0.02
    again = SourceSurface.from_dict(src.to_dict())
    assert np.allclose(again.predict_j(U), src.predict_j(U))
    assert again.label == "test"
    with pytest.raises(GPError):
        SourceSurface.from_dict({"X": [[0.1, 0.2]], "y": [1.0]})


def _campaign(source: SourceSurface | None, budget: int, seed: int = 0) -> tuple[Engine, list[np.ndarray]]:
    cfg = EngineConfig(budget=budget, seed=seed, prior=source.to_dict() if source else None)
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    rng = np.random.default_rng(seed)
    recs = []
    while not eng.done:
        p = eng.ask()
        u = np.array([p["a"], p["b"]])
        eng.tell(p, float(car(u)[0] * (1 + 0.01 * rng.standard_normal())))
        r = eng.recommend()
        recs.append(np.array([r.params["a"], r.params["b"]]))
    return eng, recs


@pytest.mark.slow
def test_a_right_source_is_believed_from_the_first_run() -> None:
    src = SourceSurface.from_function(sim, 2, 64, label="right")
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=6, prior=src.to_dict()))
    s = eng.ask_with_info()
    assert s.kind == KIND_PRIOR  # the first run is the source's optimum
    assert np.allclose([s.params["a"], s.params["b"]], OPT, atol=0.03)
    eng.tell(s.params, float(car(np.array([s.params["a"], s.params["b"]]))[0]))
    rec = eng.recommend()
    assert np.allclose([rec.params["a"], rec.params["b"]], OPT, atol=0.05)
    assert rec.transfer["transfer_weight"] == pytest.approx(0.5)  # one run says nothing about the shape
    eng2, recs = _campaign(src, 6)
    assert eng2.transfer is not None and eng2.transfer.used
    assert 1.0 < eng2.transfer.b < 2.5  # the car's scale (1.7 in source units) is learned
    assert all(np.linalg.norm(r - OPT) < 0.08 for r in recs)


@pytest.mark.slow
def test_a_wrong_source_fades_and_the_engine_finds_the_optimum() -> None:
    def wrong(U: np.ndarray) -> np.ndarray:
        return sim(1.0 - np.atleast_2d(U))  # its optimum at (0.3, 0.75)

    src = SourceSurface.from_function(wrong, 2, 64, label="wrong")
    eng, recs = _campaign(src, 12)
    assert eng.transfer is not None and eng.transfer.weight < 0.5
    assert np.linalg.norm(recs[-1] - OPT) < 0.1
    # without fading (the source forced in) the recommendation would sit near the wrong optimum: the test is real
    assert np.linalg.norm(src.argmin() - OPT) > 0.5


@pytest.mark.slow
def test_state_with_a_prior_continues_identically() -> None:
    src = SourceSurface.from_function(sim, 2, 32)
    eng, _ = _campaign(src, 4)
    eng.config = EngineConfig.from_dict({**eng.config.to_dict(), "budget": 8})
    pending = eng.ask()
    again = Engine.from_json(eng.to_json())
    assert again.config.prior == eng.config.prior and again.pending == [pending]
    v = float(car(np.array([pending["a"], pending["b"]]))[0])
    eng.tell(pending, v)
    again.tell(pending, v)
    a, b = eng.ask_with_info(), again.ask_with_info()
    assert a.kind == b.kind == KIND_OPTIMIZED
    assert all(a.params[k] == pytest.approx(b.params[k], abs=1e-6) for k in a.params)
    assert a.info["transfer"]["transfer_weight"] == pytest.approx(b.info["transfer"]["transfer_weight"], abs=1e-6)


def test_a_source_of_other_dimensions_is_refused() -> None:
    src = SourceSurface.from_function(lambda U: np.sum(U, axis=1), 3, 16)
    with pytest.raises(ValueError, match="3 dimensions"):
        Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(prior=src.to_dict()))


def test_the_source_is_evaluated_without_its_variance(monkeypatch: pytest.MonkeyPatch) -> None:
    """The source's mean and gradient (evaluated at every step of the acquisition's maximizer) skip the posterior
    variance (issue 23's latency) and equal the full prediction's."""
    from bac_agent.bo.gp import latent_sd_with_grad, latent_var

    src = SourceSurface.from_function(sim, 2, 64)
    U = np.random.default_rng(3).random((5, 2))
    mu, _, dmu, _ = src._gp.predict_with_grad(U)  # type: ignore[attr-defined]
    calls: list[int] = []

    def counting_sd(*args: Any, **kw: Any) -> Any:
        calls.append(1)
        return latent_sd_with_grad(*args, **kw)

    def counting_var(*args: Any, **kw: Any) -> Any:
        calls.append(1)
        return latent_var(*args, **kw)

    monkeypatch.setattr("bac_agent.bo.gp.latent_sd_with_grad", counting_sd)
    monkeypatch.setattr("bac_agent.bo.gp.latent_var", counting_var)
    s, g = src.standardized_and_grad(U)
    assert np.allclose(s, mu) and np.allclose(g, dmu)
    assert np.allclose(src.standardized(U), mu)
    assert not calls


@pytest.mark.slow
def test_fitting_with_a_source_refines_the_residual_from_one_start(monkeypatch: pytest.MonkeyPatch) -> None:
    """The model with the source: MAP fits of the kernel without the source and of the residual (each from the
    prior's mode and the best prior draw), then the residual once more from the first fit alone (issue 23's
    latency; it searched again from 3 starts)."""
    from scipy.optimize import minimize as real

    from bac_agent.bo.prior import TransferSettings, fit_with_source

    src = SourceSurface.from_function(sim, 2, 64)
    U = np.random.default_rng(4).random((8, 2))
    starts: list[int] = []

    def counting(*args: Any, **kw: Any) -> Any:
        starts.append(1)
        return real(*args, **kw)

    monkeypatch.setattr("bac_agent.bo.gp.minimize", counting)
    gp, fit = fit_with_source(
        EngineConfig().gp, U, car(U), src, TransferSettings(), np.random.default_rng(0), previous=None
    )
    assert len(starts) == 2 + 2 + 1
    assert fit.weight > 0.9
    assert np.allclose(gp.predict(U)[0], car(U), atol=0.05)


@pytest.mark.slow
def test_the_source_is_the_prior_mean_for_prior_runs_runs_then_the_engines_own_model() -> None:
    """issue 23: a source that is nearly right kept its weight and held the model near its own optimum; with
    ``prior_runs`` (0, the default: no limit) the car's runs alone are modelled after that many runs."""

    def f(U: np.ndarray) -> np.ndarray:
        return np.asarray(np.sum((np.atleast_2d(U) - 0.4) ** 2, axis=1))

    src = SourceSurface.from_function(f, 2, 64, seed=0).to_dict()
    assert Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=15, prior=src)).prior_runs == 15
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=12, seed=1, prior=src, prior_runs=4))
    assert eng.prior_runs == 4
    seen = []
    for k in range(6):
        s = eng.ask_with_info()
        u = np.array([s.params["a"], s.params["b"]])
        eng.tell(s.params, float(f(u)[0]) + 0.3)
        eng.recommend()
        trend = eng.hyper.prior if eng.hyper is not None else None
        seen.append((k + 1, trend is not None, eng.recommend().transfer["prior_in_use"]))
    assert seen[:4] == [(n, True, 1.0) for n in range(1, 5)]  # a right source is used for 4 runs
    assert seen[4:] == [(5, False, 0.0), (6, False, 0.0)]  # then the engine's own model, and the journal says so
    with pytest.raises(EngineError, match="prior_runs"):
        EngineConfig(prior_runs=-1)


def _told_near_the_source_optimum(average: bool, seed: int, ls: bool = True) -> tuple[Engine, np.ndarray]:
    """An engine with a source whose optimum is at (0.3, 0.3), told six runs that agree with it, all within 0.1 of
    that optimum: the source's shape is supported (weight > 0.9) and nothing was run elsewhere."""
    c = np.array([0.3, 0.3])

    def bowl(U: np.ndarray) -> np.ndarray:
        return np.sqrt(0.02 + np.sum((np.atleast_2d(U) - c) ** 2 * [1.0, 2.0], axis=1))

    src = SourceSurface.from_function(bowl, 2, 64, seed=0)
    cfg = EngineConfig(budget=20, seed=seed, prior=src.to_dict(), prior_average=average, prior_average_ls=ls)
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    runs = np.array([[0.3, 0.3], [0.4, 0.3], [0.3, 0.4], [0.2, 0.25], [0.35, 0.2], [0.25, 0.35]])
    rng = np.random.default_rng(seed)
    for u in runs:
        eng.tell({"a": float(u[0]), "b": float(u[1])}, float(1.0 + bowl(u)[0] + 0.01 * rng.standard_normal()))
    return eng, runs


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2])
def test_the_acquisition_averages_the_models_with_and_without_the_source(seed: int) -> None:
    """issue 23 (prior_average, the default): while the runs support the source, the expected improvement is
    averaged over the model with the source (weight w) and the model without it (1 - w). A source right where
    the runs are, but never tested elsewhere, no longer holds the proposals at its optimum: the model without the
    source is uncertain far from the runs, and its share of the average sends the next run there (on the tuning
    split of bench/transfer.py a nearly right simulator held road_c1's campaigns for > 15 runs)."""
    held, runs = _told_near_the_source_optimum(False, seed)
    s = held.ask_with_info()
    assert s.kind == KIND_OPTIMIZED and held.transfer is not None and 0.9 < held.transfer.weight < 1.0
    u = np.array([s.params["a"], s.params["b"]])
    assert np.min(np.linalg.norm(runs - u, axis=1)) < 0.1  # the model with the source alone: at its optimum
    averaged, _ = _told_near_the_source_optimum(True, seed)
    s = averaged.ask_with_info()
    assert s.kind == KIND_OPTIMIZED and s.info["transfer"]["prior_in_use"] == 1.0
    assert s.info["acquisition"].startswith("noisy EI averaged over the models with the transfer prior (0.9")
    assert "acquisition" not in held.ask_with_info().info  # journaled (trial_proposed's model) only when averaged
    u = np.array([s.params["a"], s.params["b"]])
    assert np.min(np.linalg.norm(runs - u, axis=1)) > 0.4  # far from every run


def _assert_acquisition(values: Any, value_and_grad: Any, U: np.ndarray, want: np.ndarray) -> None:
    """An averaged acquisition's values and its value_and_grad equal ``want`` at U; its gradient the central
    differences'."""
    assert np.allclose(values(U), want, rtol=1e-9, atol=1e-9)
    v, g = value_and_grad(U)
    assert np.allclose(v, want, rtol=1e-9, atol=1e-9)
    h = 1e-6
    for j in range(U.shape[1]):
        dU = np.zeros_like(U)
        dU[:, j] = h
        fd = (values(U + dU) - values(U - dU)) / (2 * h)
        assert np.allclose(g[:, j], fd, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_the_averaged_acquisition_is_the_weighted_mean_of_the_two_expected_improvements() -> None:
    eng, _ = _told_near_the_source_optimum(True, 0, ls=False)  # (prior_average_ls: below)
    gp = eng._model()
    alt = eng._model_without_source(gp)
    assert alt is not None and eng.transfer is not None
    assert alt.y_mean == gp.y_mean and alt.y_std == gp.y_std  # both on the source's scale: improvements add
    state = eng.rng.bit_generator.state
    eng._acq_info = {}  # what an ask journals with the proposal (set by ask_with_info)
    values, value_and_grad = eng._averaged_nei(gp, alt, None)
    eng.rng.bit_generator.state = state
    nei1 = NoisyEI(gp, eng.config.nei_samples, eng.rng, None)
    nei0 = NoisyEI(alt, eng.config.nei_samples, eng.rng, None)
    U = np.random.default_rng(5).random((7, 2))
    w = eng.transfer.weight
    want = np.log(w * np.exp(nei1(U)) + (1.0 - w) * np.exp(nei0(U)))
    _assert_acquisition(values, value_and_grad, U, want)
    # a right source's weight of 1 to round-off: the model with the source alone (no second model's cost)
    eng.transfer = replace(eng.transfer, weight=1.0 - 1e-9)
    assert eng._model_without_source(gp) is None
    eng.transfer = replace(eng.transfer, weight=0.4)  # the source rejected: the engine's own model, no average
    assert eng._model_without_source(gp) is None


@pytest.mark.slow
def test_an_outcome_source_keeps_points_spread_over_the_cube() -> None:
    """More than MAX_SOURCE_POINTS points: J's source keeps its 64 lowest and a spread of the rest; an outcome's
    source (a limit may lie anywhere in its range) keeps points spread over the cube, here every one of 40 runs
    spread over the box beside 700 clustered in a corner (a campaign that stayed near its optimum)."""
    from bac_agent.bo.prior import MAX_SOURCE_POINTS, spread_subset

    rng = np.random.default_rng(0)
    cluster = 0.15 * rng.random((700, 2))
    wide = 0.2 + 0.8 * np.random.default_rng(1).random((40, 2))
    X = np.vstack([cluster[:350], wide, cluster[350:]])
    y = 40.0 + 30.0 * X[:, 0] + rng.standard_normal(X.shape[0])  # e.g. a travel in mm

    def kept_wide(src: SourceSurface) -> int:
        return int(sum(np.any(np.all(np.isclose(src.X, p), axis=1)) for p in wide))

    out = SourceSurface.fit(X, y, noisy=True, outcome=True)
    assert out.X.shape[0] == MAX_SOURCE_POINTS and kept_wide(out) == 40
    j = SourceSurface.fit(X, y, noisy=True)  # J's rule: the lowest values first
    assert j.X.shape[0] <= MAX_SOURCE_POINTS and kept_wide(j) < 40
    # the subset itself: every row when there are few, the farthest ones first
    assert np.array_equal(spread_subset(X[:10], 20), np.arange(10))
    pick = spread_subset(np.array([[0.5, 0.5], [0.51, 0.5], [0.0, 0.0], [1.0, 1.0], [0.5, 0.49]]), 3)
    assert set(pick.tolist()) == {0, 2, 3}


@pytest.mark.slow
def test_prior_average_ls_averages_the_model_without_the_source_over_both_lengthscale_priors() -> None:
    """issue 23 (prior_average_ls, the default since 2026-11-25): the model without the source in the transfer
    prior's model average is itself the average of its fits under the two lengthscale priors (gp.ls_average), as the
    engine's own model of the runs is: the EI is w · EI(with) + (1 - w)/2 · (EI(without, sd ls_scale) + EI(without,
    sd ls_average))."""
    eng, _ = _told_near_the_source_optimum(True, 0)
    assert eng.config.prior_average_ls
    gp = eng._model()
    alt = eng._model_without_source(gp)
    assert alt is not None and eng.transfer is not None and 0.5 < eng.transfer.weight < 1.0 - 1e-6
    state = eng.rng.bit_generator.state
    eng._acq_info = {}
    values, value_and_grad = eng._averaged_nei(gp, alt, None)
    eng.rng.bit_generator.state = state
    tight = eng._without_source_tight(gp, alt)
    assert tight is not None and tight.y_mean == alt.y_mean and tight.y_std == alt.y_std  # the source's scale
    assert tight.config.ls_scale == eng.config.gp.ls_average and tight.config.mean == "constant"
    assert tight.hyper is not None and alt.hyper is not None
    assert not np.allclose(tight.hyper.lengthscales, alt.hyper.lengthscales)  # its own fit under the tighter prior
    neis = [NoisyEI(m, eng.config.nei_samples, eng.rng, None) for m in (gp, alt, tight)]
    U = np.random.default_rng(5).random((7, 2))
    w = eng.transfer.weight
    e = [np.exp(n(U)) for n in neis]
    want = np.log(w * e[0] + 0.5 * (1.0 - w) * (e[1] + e[2]))
    _assert_acquisition(values, value_and_grad, U, want)
    # off, or with one lengthscale prior (gp.ls_average 0): the model without the source is one fit
    off, _ = _told_near_the_source_optimum(True, 0, ls=False)
    assert off._without_source_tight(off._model(), alt) is None
    one = Engine(eng.space, replace(eng.config, gp=replace(eng.config.gp, ls_average=0.0)))
    assert one._without_source_tight(gp, alt) is None
    # an engine state saved before the option (a whole configuration without the key) reads back without it
    old = eng.config.to_dict()
    del old["prior_average_ls"]
    assert not EngineConfig.from_dict(old).prior_average_ls
    assert EngineConfig.from_dict({"budget": 5}).prior_average_ls  # a partial override keeps today's default
