"""The simulation phase's 20-dimensional tools: batch trust-region BO (turbo), the CMA-ES polish, SALib's global
sensitivity, on analytic problems whose answer is known (not on the problem the phase is judged on)."""

from __future__ import annotations

import numpy as np
import pytest

from bac_reduce.analysis import ReductionError
from bac_reduce.global_sensitivity import GlobalSensitivity, disagreements, global_sensitivity
from bac_reduce.objectives import SyntheticObjective, SyntheticTerm
from bac_reduce.turbo import PolishConfig, TrustRegion, TurboConfig, polish_many


def twenty() -> SyntheticObjective:
    """20 parameters, a 20-dimensional bowl with optima at the edges and inside (J* = 1), 0.5 % run noise."""
    rng = np.random.default_rng(7)
    opt = rng.choice([0.0, 1.0, 0.2, 0.6, 0.85], size=20)
    w = np.geomspace(0.4, 0.004, 20)
    return SyntheticObjective(
        tuple(SyntheticTerm(f"r{i + 1:02d}", float(o), float(x)) for i, (o, x) in enumerate(zip(opt, w, strict=True)))
    )


def run_campaign(obj: SyntheticObjective, budget: int, seed: int) -> tuple[np.ndarray, float]:
    tr = TrustRegion(obj.definition, TurboConfig(budget=budget, batch=16, seed=seed))
    rng = np.random.default_rng(seed + 100)
    while not tr.done:
        X = tr.ask()
        tr.tell(X, obj.evaluate(X, rng))
    x, mean, _ = tr.recommend()
    return x, mean


@pytest.mark.slow
def test_the_trust_region_reaches_a_20_dimensional_optimum_within_two_percent() -> None:
    """240 noisy runs (0.5 % noise) in 20 dimensions: within 2 % of J* (the noise-free polish does the rest)."""
    obj = twenty()
    j_star = float(obj.raw_j(obj.optimum[None, :])[0])
    assert j_star == pytest.approx(1.0)
    x, mean = run_campaign(obj, budget=240, seed=3)
    j = float(obj.true_j(x[None, :])[0])
    assert j <= 1.02 * j_star, j
    assert mean == pytest.approx(j, rel=0.02)  # the recommendation's posterior mean tells the truth
    # the same runs spent at random get nowhere near it: the test measures the optimizer
    rng = np.random.default_rng(3)
    X = rng.random((240, 20)) * 1000.0
    assert float(obj.true_j(X).min()) > 1.08 * j_star


@pytest.mark.slow
def test_the_trust_region_shrinks_around_the_optimum_and_is_reproducible() -> None:
    obj = twenty()
    tr = TrustRegion(obj.definition, TurboConfig(budget=160, batch=16, seed=1))
    rng = np.random.default_rng(1)
    while not tr.done:
        X = tr.ask()
        assert X.shape[1] == 20 and np.all((X >= 0.0) & (X <= 1000.0))  # never outside the box
        tr.tell(X, obj.evaluate(X, rng))
    assert tr.n_told == 160 and tr.history
    assert tr.length < TurboConfig().length_init  # it narrowed down on the basin
    a, _ = run_campaign(obj, budget=96, seed=5)
    b, _ = run_campaign(obj, budget=96, seed=5)
    assert np.array_equal(a, b)
    state = tr.engine_state(a)
    assert '"turbo"' in state and '"hyper"' in state  # J_mu can be rebuilt from it


def test_the_polish_finds_each_start_s_minimum_in_lock_step() -> None:
    obj = twenty()
    bounds = np.array([[0.0, 1000.0]] * 20)
    starts = np.clip(obj.optimum[None, :] + np.array([[60.0] * 20, [-60.0] * 20]), 0.0, 1000.0)
    calls: list[int] = []

    def true_j(X: np.ndarray) -> np.ndarray:
        calls.append(X.shape[0])
        return obj.raw_j(X)

    x, j, spent, runs = polish_many(true_j, starts, bounds, PolishConfig(evals=1500, sigma=0.1), seed=0)
    j0 = obj.raw_j(starts)
    assert np.all(j < j0) and np.all(j <= 1.0 + 1e-3), (j0, j)
    assert np.allclose(obj.raw_j(x), j) and np.all((x >= 0.0) & (x <= 1000.0))  # the points of those values
    assert np.all(spent <= 1500 + PolishConfig().popsize - 1) and [r[0].shape[0] for r in runs] == list(spent)
    assert max(calls[1:]) == 2 * PolishConfig().popsize  # both searches' populations in one batch
    # no polish: the starts come back
    x0, jj, spent0, _ = polish_many(true_j, starts, bounds, PolishConfig(evals=0))
    assert np.array_equal(x0, starts) and np.array_equal(spent0, [1, 1]) and np.allclose(jj, j0)


def test_morris_finds_the_parameters_that_matter_over_the_box() -> None:
    obj = SyntheticObjective()  # q1..q6 matter, q7 and q8 cost at most 0.5 % (default_terms)
    d = obj.definition
    bounds = np.array([[p.lower, p.upper] for p in d.parameters])
    g = global_sensitivity(obj.raw_j, d.parameter_names, bounds, "morris", runs=900, seed=0)
    assert g.runs == 900 // 9 * 9 and g.index.shape == (8,)
    assert g.significant(0.05, 1.0) == ("q1", "q2", "q3", "q4", "q5", "q6")
    kept = ["q1", "q2", "q3", "q7"]  # a one-at-a-time decision that kept q7 and dropped q4..q6
    assert disagreements(d.parameter_names, kept, g, 0.05, 1.0) == (["q7"], ["q4", "q5", "q6"])
    assert GlobalSensitivity.from_dict(g.to_dict()).significant(0.05, 1.0) == g.significant(0.05, 1.0)
    s = global_sensitivity(obj.raw_j, d.parameter_names, bounds, "sobol", runs=2048, seed=0)
    assert set(s.significant(0.05, 1.0)) == {"q1", "q2", "q3", "q4", "q5", "q6"}
    with pytest.raises(ReductionError, match="method"):
        global_sensitivity(obj.raw_j, d.parameter_names, bounds, "fast")


@pytest.mark.parametrize("gp", [{"warp": True}, {"ls_select": 0.5}, {"ls_average": 0.5}])
def test_turbo_refuses_the_engine_s_gp_options_it_cannot_use(gp: dict[str, object]) -> None:
    """The trust region's Thompson draws use the kernel on the raw inputs and one fit: an input warp or a second
    fit would silently be a different model (outside review)."""
    with pytest.raises(ValueError, match=r"neither gp\.warp nor gp\.ls_select nor gp\.ls_average"):
        TurboConfig(gp=gp)
