"""Several transfer sources (EngineConfig.prior_variants): the simulation phase over the vehicle's uncertainty."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bac_agent.bo import Engine, EngineConfig
from bac_agent.bo.engine import KIND_OPTIMIZED, KIND_PRIOR, EngineError
from bac_agent.bo.prior import SourceSurface

SPACE = {"a": (0.0, 1.0), "b": (0.0, 1.0)}
CAR_OPT = np.array([0.7, 0.25])


def bowl(c: np.ndarray, U: np.ndarray) -> np.ndarray:
    return np.sqrt(0.02 + np.sum((np.atleast_2d(U) - c) ** 2 * [1.0, 2.0], axis=1))


def car(U: np.ndarray) -> np.ndarray:
    """The car: a bowl at CAR_OPT, at another level and scale than the simulated vehicles'."""
    return 3.0 + 1.7 * bowl(CAR_OPT, U)


# the nominal vehicle's optimum is off the car's; of the vehicles drawn around it, the second (variant index 2) is
# the car's shape
NOMINAL = np.array([0.45, 0.5])
DRAWN = [np.array([0.2, 0.8]), CAR_OPT, np.array([0.3, 0.2]), np.array([0.8, 0.8])]


def _sources() -> tuple[SourceSurface, list[SourceSurface]]:
    nominal = SourceSurface.from_function(lambda U: bowl(NOMINAL, U), 2, 64, label="nominal")
    drawn = [
        SourceSurface.from_function(lambda U, c=c: bowl(c, U), 2, 64, label=f"drawn {i}") for i, c in enumerate(DRAWN)
    ]
    return nominal, drawn


def _engine(variants: bool, budget: int = 10, seed: int = 0) -> Engine:
    nominal, drawn = _sources()
    cfg = EngineConfig(
        budget=budget,
        seed=seed,
        prior=nominal.to_dict(),
        prior_variants=tuple(s.to_dict() for s in drawn) if variants else (),
    )
    return Engine(SPACE, cfg)


def _run(eng: Engine, n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    recs = []
    for _ in range(n):
        p = eng.ask()
        eng.tell(p, float(car(np.array([p["a"], p["b"]]))[0] * (1 + 0.01 * rng.standard_normal())))
        r = eng.recommend()
        recs.append(np.array([r.params["a"], r.params["b"]]))
    return recs


def test_prior_variants_are_validated() -> None:
    nominal, drawn = _sources()
    with pytest.raises(EngineError, match="give prior too"):
        EngineConfig(prior_variants=(drawn[0].to_dict(),))
    with pytest.raises(EngineError, match="list of source surfaces"):
        EngineConfig(prior=nominal.to_dict(), prior_variants=([1.0, 2.0],))  # type: ignore[arg-type]
    with pytest.raises(EngineError, match="list of source surfaces"):
        EngineConfig.from_dict({"prior": nominal.to_dict(), "prior_variants": drawn[0].to_dict()})
    three = SourceSurface.from_function(lambda U: np.sum(U, axis=1), 3, 16)
    cfg = EngineConfig(prior=nominal.to_dict(), prior_variants=(three.to_dict(),))
    with pytest.raises(EngineError, match="prior variant 0 has 3 dimensions"):
        Engine(SPACE, cfg)


def test_without_variants_the_configuration_reads_as_before() -> None:
    nominal, drawn = _sources()
    d = EngineConfig(prior=nominal.to_dict()).to_dict()
    assert "prior_variants" not in d  # a journal's engine configuration is unchanged when they are not used
    assert EngineConfig.from_dict(d).prior_variants == ()
    with_them = EngineConfig(prior=nominal.to_dict(), prior_variants=tuple(s.to_dict() for s in drawn))
    again = EngineConfig.from_dict(with_them.to_dict())
    assert len(again.prior_variants) == len(DRAWN) and again.prior_variants[1]["label"] == "drawn 1"


@pytest.mark.slow
def test_the_runs_pick_the_drawn_vehicle_that_is_the_car() -> None:
    """Run 1 is the nominal vehicle's optimum (as with the prior alone); the runs weigh every source, and the model
    becomes the drawn vehicle whose shape the car has: the recommendation moves to the car's optimum, which the
    nominal vehicle's model alone does not reach in as many runs."""
    eng = _engine(True)
    s = eng.ask_with_info()
    assert s.kind == KIND_PRIOR and np.allclose([s.params["a"], s.params["b"]], NOMINAL, atol=0.03)
    recs = _run(eng, 4)
    rec = eng.recommend()
    assert rec.transfer["prior_source_index"] == 2.0  # prior_variants[1]: the car's shape
    assert rec.transfer["prior_source_weight"] > 0.5
    assert rec.transfer["transfer_weight"] > 0.9  # some source describes the car
    assert np.linalg.norm(recs[-1] - CAR_OPT) < 0.05
    alone = _engine(False)
    recs_alone = _run(alone, 4)
    assert "prior_source_index" not in alone.recommend().transfer
    assert np.linalg.norm(recs_alone[-1] - CAR_OPT) > 0.05  # the test is real: the nominal alone is not there yet


@pytest.mark.slow
def test_one_run_keeps_the_nominal_source() -> None:
    eng = _engine(True)
    _run(eng, 1)
    t = eng.recommend().transfer
    assert t["prior_source_index"] == 0.0 and t["transfer_weight"] == pytest.approx(0.5)
    assert t["prior_source_weight"] == pytest.approx(0.5 / (1 + len(DRAWN)))


@pytest.mark.slow
def test_the_acquisition_averages_every_source_in_js_units() -> None:
    from bac_agent.bo.acquisition import NoisyEI

    eng = _engine(True, budget=12)
    _run(eng, 4)
    gp = eng._model()
    alt = eng._model_without_source(gp)
    assert alt is not None
    state = eng.rng.bit_generator.state
    eng._acq_info = {}
    values, value_and_grad = eng._variants_nei(alt, None)
    eng.rng.bit_generator.state = state
    top = max([w for _, _, w in eng._variant_models] + [eng._variant_none])
    want = np.zeros(6)
    U = np.random.default_rng(5).random((6, 2))
    for src, m, w in eng._variant_models:
        if w >= 1e-3 * top:
            want += w * src.scale * np.exp(NoisyEI(m, eng.config.nei_samples, eng.rng, None)(U))
    if eng._variant_none >= 1e-3 * top:
        want += (
            eng._variant_none
            * eng._active_source.scale
            * np.exp(  # type: ignore[union-attr]
                NoisyEI(alt, eng.config.nei_samples, eng.rng, None)(U)
            )
        )
    assert np.allclose(values(U), np.log(want), rtol=1e-9, atol=1e-9)
    v, g = value_and_grad(U)
    assert np.allclose(v, np.log(want), rtol=1e-9, atol=1e-9)
    h = 1e-6
    for j in range(2):
        dU = np.zeros_like(U)
        dU[:, j] = h
        assert np.allclose(g[:, j], (values(U + dU) - values(U - dU)) / (2 * h), rtol=1e-4, atol=1e-6)
    assert math.isclose(sum(w for _, _, w in eng._variant_models) + eng._variant_none, 1.0, rel_tol=1e-9)


@pytest.mark.slow
def test_state_with_variants_continues_identically() -> None:
    eng = _engine(True, budget=8)
    _run(eng, 4)
    pending = eng.ask()
    again = Engine.from_json(eng.to_json())
    assert len(again.config.prior_variants) == len(DRAWN) and again.pending == [pending]
    v = float(car(np.array([pending["a"], pending["b"]]))[0])
    eng.tell(pending, v)
    again.tell(pending, v)
    a, b = eng.ask_with_info(), again.ask_with_info()
    assert a.kind == b.kind == KIND_OPTIMIZED
    assert all(a.params[k] == pytest.approx(b.params[k], abs=1e-6) for k in a.params)
    assert a.info["transfer"]["prior_source_index"] == b.info["transfer"]["prior_source_index"]


@pytest.mark.slow
def test_the_average_recommendation_minimizes_the_sources_mean_averaged_by_their_probabilities() -> None:
    """prior_variants_recommend "average": after one run (every source as probable as a priori) the recommendation
    is the argmin of the sources' means averaged, which lies among the drawn vehicles' optima, not at the nominal's."""
    centres = [np.array([0.3, 0.7]), np.array([0.7, 0.3]), np.array([0.75, 0.25]), np.array([0.65, 0.35])]
    srcs = [SourceSurface.from_function(lambda U, c=c: bowl(c, U), 2, 64) for c in centres]

    def engine(rule: str) -> np.ndarray:
        cfg = EngineConfig(
            budget=6,
            prior=srcs[0].to_dict(),
            prior_variants=tuple(s.to_dict() for s in srcs[1:]),
            prior_variants_recommend=rule,
        )
        eng = Engine(SPACE, cfg)
        _run(eng, 1)
        r = eng.recommend()
        return np.array([r.params["a"], r.params["b"]])

    g = np.linspace(0, 1, 201)
    G = np.array(np.meshgrid(g, g, indexing="ij")).reshape(2, -1).T
    want = G[int(np.argmin(sum(bowl(c, G) for c in centres)))]  # one offset and scale for all: the same argmin
    got = engine("average")
    assert np.linalg.norm(got - want) < 0.05
    assert np.linalg.norm(got - centres[0]) > 0.3
    assert np.linalg.norm(engine("best") - centres[0]) < 0.05  # "best": the nominal's model after one run
    with pytest.raises(EngineError, match="prior_variants_recommend must be one of"):
        EngineConfig(prior=srcs[0].to_dict(), prior_variants_recommend="mode")


@pytest.mark.slow
def test_sources_are_weighed_on_js_scale_not_each_on_its_own() -> None:
    """Two runs: a drawn vehicle whose J varies five times less than the car's across them must not take the weight
    (each source's likelihood is compared in J's units; a Bayes factor against each source's own model without it
    favoured the flattest source, whose reference model explains a large contrast worst: bench/transfer.py,
    2026-11-25)."""
    nominal = SourceSurface.from_function(lambda U: bowl(NOMINAL, U), 2, 64)
    flat = SourceSurface.from_function(lambda U: 0.2 * bowl(CAR_OPT + np.array([0.05, 0.05]), U), 2, 64)
    right = SourceSurface.from_function(lambda U: bowl(CAR_OPT, U), 2, 64)
    cfg = EngineConfig(budget=6, prior=nominal.to_dict(), prior_variants=(flat.to_dict(), right.to_dict()))
    eng = Engine(SPACE, cfg)
    for u in ([0.45, 0.5], [0.1, 0.9]):
        eng.tell({"a": u[0], "b": u[1]}, float(3.0 + bowl(CAR_OPT, np.array(u))[0]))
    eng.recommend()
    w = {round(src.scale, 6): wk for src, _, wk in eng._variant_models}
    assert w[round(right.scale, 6)] > 5 * w[round(flat.scale, 6)]


@pytest.mark.slow
@pytest.mark.parametrize("prior_average", [True, False])
def test_the_sources_stay_averaged_when_the_model_without_a_source_drops_out(prior_average: bool) -> None:
    """The outside review's case (2026-11-25): with prior_average off, or once the model without a source has a
    negligible share (here a prior weight of 1 - 1e-8), the acquisition must still average the sources that share
    the weight (it fell back to the most probable source's NEI alone)."""
    nominal, drawn = _sources()
    cfg = EngineConfig(
        budget=14,
        seed=0,
        prior=nominal.to_dict(),
        prior_weight=1 - 1e-8,
        prior_average=prior_average,
        prior_variants=tuple(s.to_dict() for s in drawn),
    )
    eng = Engine(SPACE, cfg)
    rng = np.random.default_rng(0)
    for _ in range(4):
        p = eng.ask()
        eng.tell(p, float(car(np.array([p["a"], p["b"]]))[0] * (1 + 0.01 * rng.standard_normal())))
    s = eng.ask_with_info()
    assert eng.transfer is not None and eng.transfer.used
    weights = sorted(w for _, _, w in eng._variant_models)
    assert weights[-2] >= 0.005, weights  # a second source still counts (VARIANT_MIN_SHARE: 1e-3 of the top)
    assert eng._variant_none < 1e-6
    assert "noisy EI averaged over" in str(s.info.get("acquisition")), s.info.get("acquisition")
