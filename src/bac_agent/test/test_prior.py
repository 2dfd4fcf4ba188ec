"""The transfer prior (bo/prior.py): a source's surface, its weight against the car's runs, the engine with it."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from bac_agent.bo import Engine, EngineConfig
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


def test_a_wrong_source_fades_and_the_engine_finds_the_optimum() -> None:
    def wrong(U: np.ndarray) -> np.ndarray:
        return sim(1.0 - np.atleast_2d(U))  # its optimum at (0.3, 0.75)

    src = SourceSurface.from_function(wrong, 2, 64, label="wrong")
    eng, recs = _campaign(src, 12)
    assert eng.transfer is not None and eng.transfer.weight < 0.5
    assert np.linalg.norm(recs[-1] - OPT) < 0.1
    # without fading (the source forced in) the recommendation would sit near the wrong optimum: the test is real
    assert np.linalg.norm(src.argmin() - OPT) > 0.5


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
