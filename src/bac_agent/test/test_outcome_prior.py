"""What the simulator knows of a limited outcome, carried to the car (bo/constraints.py, outcome_priors)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bac_agent.bo import Engine, EngineConfig
from bac_agent.bo.constraints import OutcomeLimit, OutcomeModel
from bac_agent.bo.engine import EngineError
from bac_agent.bo.prior import SourceSurface
from bac_agent.bo.space import SearchSpace

OPT = np.array([0.2, 0.3])  # J's unconstrained optimum: the nominal travel there is 70, the limit 60
LIMIT = 60.0


def j_of(U: np.ndarray) -> np.ndarray:
    U = np.atleast_2d(U)
    return np.asarray(np.sqrt(0.01 + np.sum((U - OPT) ** 2, axis=1)))


def nominal_travel(U: np.ndarray) -> np.ndarray:
    """The simulator's travel: soft (small u0) lets the suspension travel far: 80 at u0 = 0, 40 at u0 = 1."""
    U = np.atleast_2d(U)
    return np.asarray(80.0 - 40.0 * U[:, 0] + 5.0 * U[:, 1])


def car_travel(U: np.ndarray) -> np.ndarray:
    """The car travels more than the simulator says: an offset, a scale and a little shape the model lacks."""
    U = np.atleast_2d(U)
    return np.asarray(3.0 + 1.1 * nominal_travel(U) + 1.5 * np.sin(4.0 * U[:, 1]))


def _source(f: object, seed: int = 0) -> SourceSurface:
    return SourceSurface.from_function(f, 2, 64, label="nominal", seed=seed)


def test_an_outcome_prior_predicts_before_the_first_run() -> None:
    U = np.array([[0.1, 0.5], [0.9, 0.5]])  # nominal travel 78.5 and 46.5
    lim = OutcomeLimit("max_travel_mm", LIMIT)
    with_src = OutcomeModel(lim, _source(nominal_travel))
    with_src.fit(np.zeros((0, 2)), np.zeros(0), np.random.default_rng(0))
    p = with_src.prob_violation(U)
    assert p[0] > 0.95 and p[1] < 0.1
    mean, sd = with_src.predict(U)
    np.testing.assert_allclose(mean, nominal_travel(U), atol=0.5)  # the source itself, a = 0, b = 1
    assert np.all(sd > 0.5 * 0.5 * np.std(nominal_travel(np.random.default_rng(1).random((256, 2)))))
    # without a source nothing is known before the first run
    plain = OutcomeModel(lim)
    plain.fit(np.zeros((0, 2)), np.zeros(0), np.random.default_rng(0))
    np.testing.assert_array_equal(plain.prob_violation(U), [0.0, 0.0])


def test_an_outcome_prior_learns_the_cars_offset_and_scale() -> None:
    """Runs in one quarter of the box teach the model the car's offset and scale everywhere (a residual GP alone
    would know them only near the runs)."""
    rng = np.random.default_rng(3)
    X = 0.5 + 0.5 * rng.random((8, 2))  # the upper-right quarter
    v = car_travel(X) + 0.5 * rng.standard_normal(8)
    m = OutcomeModel(OutcomeLimit("max_travel_mm", LIMIT), _source(nominal_travel))
    m.fit(X, v, np.random.default_rng(0))
    Q = 0.5 * np.random.default_rng(4).random((64, 2))  # the lower-left quarter
    mean, _ = m.predict(Q)
    assert np.median(np.abs(mean - car_travel(Q))) < 2.0  # with the offset and scale fixed at 0 and 1: 5.1
    assert np.median(np.abs(nominal_travel(Q) - car_travel(Q))) > 9.0  # what the source alone is off by


def _clustered_source(seed: int = 2) -> SourceSurface:
    """Six noisy runs of the nominal travel, all at u0 >= 0.7 (an earlier campaign near its optimum)."""
    rng = np.random.default_rng(seed)
    Xs = np.column_stack([0.7 + 0.3 * rng.random(6), rng.random(6)])
    return SourceSurface.fit(Xs, nominal_travel(Xs), "six runs near the optimum", noisy=True)


@pytest.mark.parametrize("n", [0, 2, 7])
@pytest.mark.parametrize("measured", [True, False])
@pytest.mark.parametrize("clustered", [False, True])
def test_the_outcome_priors_gradient_matches_finite_differences(n: int, measured: bool, clustered: bool) -> None:
    """Dense: the source's variance is round-off; clustered: its variance and covariance with the runs matter."""
    rng = np.random.default_rng(n)
    X = rng.random((n, 2))
    v = car_travel(X) + 0.5 * rng.standard_normal(n)
    src = _clustered_source() if clustered else _source(nominal_travel)
    m = OutcomeModel(OutcomeLimit("max_travel_mm", LIMIT), src)
    m.fit(X, v, np.random.default_rng(0))
    assert (m._coef_cov is not None) == (n > 0)
    U = np.array([[0.45, 0.3], [0.55, 0.8], [0.35, 0.1]])  # near the limit: log P(keep) moves
    lf, g = m.log_feasible_and_grad(U, measured)
    eps = 1e-6
    for k in range(2):
        dU = np.zeros_like(U)
        dU[:, k] = eps
        fd = (m.log_feasible_and_grad(U + dU, measured)[0] - m.log_feasible_and_grad(U - dU, measured)[0]) / (2 * eps)
        np.testing.assert_allclose(g[:, k], fd, rtol=1e-4, atol=1e-7)
    # and the value agrees with prob_violation
    np.testing.assert_allclose(np.exp(lf), 1.0 - m.prob_violation(U, measured), rtol=1e-9, atol=1e-12)


def _campaign(priors: bool, seed: int, budget: int = 12, **over: object) -> tuple[Engine, list[np.ndarray], list[str]]:
    extra: dict[str, object] = dict(over)
    if priors:
        extra |= {
            "prior": _source(j_of, seed).to_dict(),
            "outcome_priors": {"max_travel_mm": _source(nominal_travel, seed).to_dict()},
        }
    cfg = EngineConfig(budget=budget, seed=seed, constraints=(f"max_travel_mm<={LIMIT}",), **extra)  # type: ignore[arg-type]
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    rng = np.random.default_rng(100 + seed)
    asked, kinds = [], []
    while not eng.done:
        s = eng.ask_with_info()
        u = np.array([s.params["a"], s.params["b"]])
        asked.append(u)
        kinds.append(s.kind)
        travel = float(car_travel(u)[0]) + 0.5 * rng.standard_normal()
        eng.tell(s.params, float(j_of(u)[0]) + 0.005 * rng.standard_normal(), {"max_travel_mm": travel})
    return eng, asked, kinds


@pytest.mark.slow
def test_with_the_simulators_outcome_the_first_runs_keep_the_limit() -> None:
    """The simulator's J optimum breaks the limit on the car; with its travel as the travel model's prior the first
    run is the simulator's best calibration that keeps the limit, and no run of the campaign breaks it."""
    assert car_travel(OPT)[0] > LIMIT + 10.0
    broke_with, broke_without = 0, 0
    for seed in range(3):
        eng, asked, kinds = _campaign(True, seed)
        assert kinds[0] == "prior"
        t = car_travel(np.array(asked))
        broke_with += int(np.sum(t > LIMIT))
        assert asked[0][0] > OPT[0] + 0.2  # not the unconstrained optimum: where its travel keeps the limit
        rec = eng.recommend()
        assert car_travel(np.array([rec.params["a"], rec.params["b"]]))[0] <= LIMIT
        _, asked0, _ = _campaign(False, seed)
        broke_without += int(np.sum(car_travel(np.array(asked0)) > LIMIT))
    assert broke_with == 0
    assert broke_without >= 3  # without the prior the first runs break it: the test is real


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_with_outcome_priors_limit_reach_is_not_used(seed: int) -> None:
    # limit_reach (the default 0.15: after the design, proposals within it of a run that kept the limits) is for
    # limits with nothing known; with the simulator's outcome a campaign asks the same with the default and off;
    # without, it differs
    on = _campaign(True, seed, budget=14)[1]
    off = _campaign(True, seed, budget=14, limit_reach=0.0)[1]
    assert all(np.array_equal(a, b) for a, b in zip(on, off, strict=True))
    on = _campaign(False, seed, budget=14)[1]
    off = _campaign(False, seed, budget=14, limit_reach=0.0)[1]
    assert not all(np.array_equal(a, b) for a, b in zip(on, off, strict=True))


def test_a_design_point_the_outcome_prior_rejects_is_replaced_by_the_nearest_allowed() -> None:
    src = _source(nominal_travel)
    cfg = EngineConfig(
        budget=10, seed=2, constraints=(f"max_travel_mm<={LIMIT}",), outcome_priors={"max_travel_mm": src.to_dict()}
    )
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    d = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, EngineConfig(budget=10, seed=2)).ask()  # the same design
    u_d = np.array([d["a"], d["b"]])
    prior_only = OutcomeModel(OutcomeLimit("max_travel_mm", LIMIT), src)
    assert prior_only.prob_violation(u_d[None, :])[0] > 0.05  # the prior rejects the first design point
    s = eng.ask_with_info()
    u = np.array([s.params["a"], s.params["b"]])
    assert s.kind == "initial" and "design_point_skipped" in s.info
    assert prior_only.prob_violation(u[None, :])[0] <= 0.05  # what is asked instead is allowed
    g = np.linspace(0.0, 1.0, 201)
    G = np.array(np.meshgrid(g, g, indexing="ij")).reshape(2, -1).T
    ok = prior_only.prob_violation(G) <= 0.05
    nearest = float(np.min(np.linalg.norm(G[ok] - u_d, axis=1)))
    assert np.linalg.norm(u - u_d) <= nearest + 0.03  # and it is the allowed calibration nearest to the design point


def test_outcome_priors_are_checked_and_kept_in_the_state() -> None:
    src = _source(nominal_travel).to_dict()
    with pytest.raises(EngineError, match="no limit names"):
        EngineConfig(constraints=("max_travel_mm<=60",), outcome_priors={"peak_accel_z": src})
    three = SourceSurface.from_function(lambda U: U[:, 0], 3, 16).to_dict()
    with pytest.raises(EngineError, match="3 dimensions"):
        Engine(
            {"a": (0.0, 1.0), "b": (0.0, 1.0)},
            EngineConfig(constraints=("max_travel_mm<=60",), outcome_priors={"max_travel_mm": three}),
        )
    cfg = EngineConfig(budget=8, seed=1, constraints=("max_travel_mm<=60",), outcome_priors={"max_travel_mm": src})
    eng = Engine({"a": (0.0, 1.0), "b": (0.0, 1.0)}, cfg)
    for _ in range(4):
        p = eng.ask()
        u = np.array([p["a"], p["b"]])
        eng.tell(p, float(j_of(u)[0]), {"max_travel_mm": float(car_travel(u)[0])})
    again = Engine.from_json(eng.to_json())
    assert again.config.outcome_priors is not None and set(again.config.outcome_priors) == {"max_travel_mm"}
    assert again.ask() == eng.ask()


def test_an_earlier_campaigns_measured_outcomes_are_the_outcome_priors(tmp_path: Path) -> None:
    """bo_agent's prior_source names an earlier campaign: its runs' measured outcomes become the priors of the
    outcomes this campaign limits (a reduce output, which scores J only, gives none); journaled for a refit."""
    from bac_agent.journal import Journal, journaled_engine_options
    from bac_agent.transfer import load_outcome_sources
    from bac_common.paramspace import CalibrationDefinition
    from bac_common.paths import resolve_definition

    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    space = SearchSpace.from_definition(definition)
    j = Journal(tmp_path / "earlier")
    j.append("campaign_started", campaign_id="earlier", names=list(space.names), stamp=0.0)
    rng = np.random.default_rng(0)
    U = rng.random((12, 2))
    for k, u in enumerate(U):
        outcomes = {"max_travel_mm": float(nominal_travel(u)[0])}
        if k < 2:
            outcomes["peak_accel_z"] = 5.0  # measured on 2 runs only: too few for a prior
        j.append(
            "trial_scored",
            campaign_id="earlier",
            trial_id=k + 1,
            params=space.to_params(space.from_unit(u)),
            j=float(j_of(u)[0]),
            outcomes=outcomes,
            stamp=float(k + 1),
        )
    j.close()
    got = load_outcome_sources(tmp_path / "earlier", definition, ["max_travel_mm", "peak_accel_z"])
    assert set(got) == {"max_travel_mm"}
    assert got["max_travel_mm"].label.startswith("max_travel_mm: campaign earlier (12 runs")
    Q = np.random.default_rng(1).random((32, 2))
    np.testing.assert_allclose(got["max_travel_mm"].predict_j(Q), nominal_travel(Q), atol=2.0)
    assert load_outcome_sources(tmp_path / "earlier", definition, []) == {}
    assert load_outcome_sources(tmp_path, definition, ["max_travel_mm"]) == {}  # not a campaign folder
    started = {
        "config": {
            "constraints": ["max_travel_mm<=60"],
            "outcome_priors": {k: v.to_dict() for k, v in got.items()},
        }
    }
    options = journaled_engine_options(started)
    assert set(options["outcome_priors"]) == {"max_travel_mm"}
    EngineConfig.from_dict({**options, "budget": 5})  # what a refit builds from the journal


def _brute_force(m: OutcomeModel, X: np.ndarray, v: np.ndarray, Q: np.ndarray, beta2: float) -> tuple[np.ndarray, ...]:
    """The model's latent mean and variance at Q as one joint Gaussian: prior mean s(x), covariance
    k_res(x, x') + σa² + σb² s(x) s(x') + β² C_s(x, x') (C_s: the source GP's own posterior covariance, computed
    here from its points by plain linear algebra), conditioned on the runs."""
    from bac_agent.bo import constraints as c
    from bac_agent.bo.kernel import matern52_from_r2, sq_dist

    src = m.source
    assert src is not None
    h = m.gp.hyper
    assert h is not None
    g = src._gp  # type: ignore[attr-defined]
    hs = g.hyper
    Ks_s = matern52_from_r2(sq_dist(g.X, g.X, hs.lengthscales), hs.outputscale)
    Ks_s += (hs.noise + 1e-10 * hs.outputscale) * np.eye(g.X.shape[0])

    def cs(A: np.ndarray, B: np.ndarray) -> np.ndarray:
        kAB = matern52_from_r2(sq_dist(A, B, hs.lengthscales), hs.outputscale)
        kA = matern52_from_r2(sq_dist(A, g.X, hs.lengthscales), hs.outputscale)
        kB = matern52_from_r2(sq_dist(B, g.X, hs.lengthscales), hs.outputscale)
        return np.asarray(kAB - kA @ np.linalg.solve(Ks_s, kB.T))

    def k(A: np.ndarray, B: np.ndarray, diag: bool) -> np.ndarray:
        sa, sb = src.standardized(A), src.standardized(B)
        base = matern52_from_r2(sq_dist(A, B, h.lengthscales), h.outputscale)
        C = cs(A, B) * (0.0 if c._SourceCov(src).zero else 1.0)  # below the floor everywhere: no C_s
        if diag:  # a variance below the round-off floor is 0 (c.SOURCE_VAR_FLOOR)
            np.fill_diagonal(C, np.maximum(np.diag(C) - c.SOURCE_VAR_FLOOR, 0.0))
        return np.asarray(
            base + c.OUTCOME_PRIOR_OFFSET_SD**2 + c.OUTCOME_PRIOR_SCALE_SD**2 * np.outer(sa, sb) + beta2 * C
        )

    z = (v - src.loc) / src.scale
    sX, sQ = src.standardized(X), src.standardized(Q)
    K = k(X, X, True) + (h.noise + 1e-10 * h.outputscale) * np.eye(X.shape[0])
    Ks = k(Q, X, False)
    mean = sQ + Ks @ np.linalg.solve(K, z - sX)
    var = np.diag(k(Q, Q, True)) - np.sum(Ks * np.linalg.solve(K, Ks.T).T, axis=1)
    return mean, var


def test_the_outcome_priors_posterior_is_that_of_a_gp_with_the_coefficients_integrated_out() -> None:
    """a ~ N(0, σa²), b ~ N(1, σb²), the source's own uncertainty (scaled by β² = E[b²]) and the residual GP are
    one GP of prior mean s(x) and covariance k(x, x') + σa² + σb² s(x) s(x') + β² C_s(x, x'): the model's mean and
    latent variance are that GP's (R&W 2006, eq. 2.42), with a dense source and with a clustered one."""
    rng = np.random.default_rng(5)
    X = rng.random((9, 2))
    v = car_travel(X) + 0.5 * rng.standard_normal(9)
    Q = np.vstack([X[:2] + 0.01, rng.random((6, 2))])  # near runs and far from them
    clustered = SourceSurface.fit(
        np.column_stack([0.7 + 0.3 * rng.random(6), rng.random(6)]), nominal_travel(X[:6]), "six runs", noisy=True
    )
    for src in (_source(nominal_travel), clustered):
        m = OutcomeModel(OutcomeLimit("max_travel_mm", LIMIT), src)
        m.fit(X, v, np.random.default_rng(0))
        assert m._coef_cov is not None
        beta2 = m._beta2
        # β² = E[b²]: the scale's posterior second moment under the residual kernel alone
        assert 0.5 < beta2 < 3.0
        mean, var = _brute_force(m, X, v, Q, beta2)
        mu, sd, _, _ = m._moments(Q)
        np.testing.assert_allclose(mu, mean, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(sd**2, var, rtol=1e-5, atol=1e-9)
    # before the first run: the source with its prior spread and its own variance, β² = E[b²] = 1 + σb²
    from bac_agent.bo import constraints as c

    m0 = OutcomeModel(OutcomeLimit("max_travel_mm", LIMIT), clustered)
    m0.fit(np.zeros((0, 2)), np.zeros(0), np.random.default_rng(0))
    mu0, sd0, _, _ = m0._moments(Q)
    s = clustered.standardized(Q)
    var_s = np.array([clustered._gp.predict_std_units(q[None, :])[1][0] for q in Q])  # type: ignore[attr-defined]
    want = (
        np.exp(c._SOURCE_OUTCOME_GP.os_loc)
        + c.OUTCOME_PRIOR_OFFSET_SD**2
        + c.OUTCOME_PRIOR_SCALE_SD**2 * s**2
        + (1.0 + c.OUTCOME_PRIOR_SCALE_SD**2) * np.maximum(var_s - c.SOURCE_VAR_FLOOR, 0.0)
    )
    np.testing.assert_allclose(mu0, s)
    np.testing.assert_allclose(sd0**2, want, rtol=1e-6)


def test_a_clustered_source_is_uncertain_where_it_had_no_runs() -> None:
    """The outside review's case (issue 23): a source whose runs all sit at u0 ≥ 0.7 (an earlier campaign near its
    optimum) knows nothing of the soft end, where the car breaks the limit by 20 mm; taken as known everywhere,
    the prior allowed runs there (p_violation 0.004-0.045). With the source's own variance it does not; where the
    source is dense and noise-free nothing changes much (its variance is round-off)."""
    rng = np.random.default_rng(2)
    clustered = _clustered_source()
    rng.random((6, 2))  # (the source's draws)
    soft = np.array([[0.02, 0.1], [0.05, 0.5], [0.1, 0.9]])
    assert np.all(car_travel(soft) > LIMIT + 15.0)
    lim = OutcomeLimit("max_travel_mm", LIMIT)
    m = OutcomeModel(lim, clustered)
    m.fit(np.zeros((0, 2)), np.zeros(0), np.random.default_rng(0))
    assert np.all(m.prob_violation(soft) > 0.05)  # before: 0.0003-0.002 (the source's mean reverts to 51 mm there)
    # after a few runs near the source's runs, still: the runs say nothing of the soft end either
    X = np.column_stack([0.75 + 0.2 * rng.random(4), rng.random(4)])
    m.fit(X, car_travel(X) + 0.5 * rng.standard_normal(4), np.random.default_rng(0))
    assert np.all(m.prob_violation(soft) > 0.05)
    # the dense noise-free source (64 Sobol runs): the same as without the source's variance, to 1e-3
    dense = OutcomeModel(lim, _source(nominal_travel))
    X = rng.random((7, 2))
    v = car_travel(X) + 0.5 * rng.standard_normal(7)
    dense.fit(X, v, np.random.default_rng(0))
    Q = rng.random((32, 2))
    mean0, var0 = _brute_force(dense, X, v, Q, 0.0)
    mu, sd, _, _ = dense._moments(Q)
    np.testing.assert_allclose(mu, mean0, atol=1e-3)
    np.testing.assert_allclose(sd, np.sqrt(var0), rtol=1e-3)


def test_a_source_evaluated_twice_at_the_same_points_computes_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """An outcome model evaluates its source twice per step of the acquisition's maximizer (its trend and the
    coefficients' variance); the second is the first's result (issue 23's latency with outcome priors)."""
    from bac_agent.bo import gp as gp_module

    src = _source(nominal_travel)
    calls: list[int] = []
    real = gp_module.GP.predict_mean_with_grad

    def counting(self: gp_module.GP, Xq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        calls.append(1)
        return real(self, Xq)

    monkeypatch.setattr(gp_module.GP, "predict_mean_with_grad", counting)
    U = np.array([[0.2, 0.3], [0.7, 0.9]])
    s1, g1 = src.standardized_and_grad(U)
    s2, g2 = src.standardized_and_grad(U.copy())
    assert len(calls) == 1
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(g1, g2)
    s3, _ = src.standardized_and_grad(U + 0.01)  # other points: computed
    assert len(calls) == 2 and not np.allclose(s3, s1)
    np.testing.assert_allclose(src.standardized_and_grad(U)[0], src.standardized(U))


def _reduce_output(tmp_path: Path, U_runs: list[np.ndarray], travel: object) -> Path:
    """A bac reduce result.json (schema 2) of campaigns over controller_i's dampers whose runs are ``U_runs``
    (unit cube) with their travel as each run reported it."""
    import json

    from bac_common.paramspace import CalibrationDefinition
    from bac_common.paths import resolve_definition

    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    space = SearchSpace.from_definition(definition)
    state = Engine(definition, EngineConfig(budget=5)).to_json()
    campaigns = [
        {
            "X": space.from_unit(U).tolist(),
            "y": j_of(U).tolist(),
            "engine_state": state,
            "outcomes": {"max_travel_mm": travel(U).tolist()},  # type: ignore[operator]
        }
        for U in U_runs
    ]
    out = tmp_path / "reduce_out"
    out.mkdir(exist_ok=True)
    (out / "result.json").write_text(json.dumps({"schema_version": 2, "campaigns": campaigns}))
    return out


def test_a_reduce_output_whose_runs_cluster_is_uncertain_where_the_phase_never_ran(tmp_path: Path) -> None:
    """The outside review's D2 (issue 23): a simulation phase whose BO campaigns all ran at u0 ≥ 0.7 (near their
    optimum) knows nothing of the soft end, where the car breaks the limit by 20 mm. The travel prior built from
    its result.json must be as uncertain there as one built from the same runs as a campaign folder (before: a
    noise-free fit to the surrogate's means at Sobol points, certain everywhere: p_violation 0.0003-0.0013 at the
    soft end; now 0.14-0.19); near the runs it agrees with the simulator's travel."""
    from bac_agent.transfer import load_outcome_sources
    from bac_common.paramspace import CalibrationDefinition
    from bac_common.paths import resolve_definition

    rng = np.random.default_rng(4)
    runs = [np.column_stack([0.7 + 0.3 * rng.random(8), rng.random(8)]) for _ in range(2)]
    noise = iter(0.5 * rng.standard_normal(16))
    out = _reduce_output(tmp_path, runs, lambda U: nominal_travel(U) + np.array([next(noise) for _ in U]))
    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    src = load_outcome_sources(out, definition, ["max_travel_mm"])["max_travel_mm"]
    assert "16 runs of 2 campaigns" in src.label and src.noisy
    lim = OutcomeLimit("max_travel_mm", LIMIT)
    m = OutcomeModel(lim, src)
    m.fit(np.zeros((0, 2)), np.zeros(0), np.random.default_rng(0))
    soft = np.array([[0.02, 0.1], [0.05, 0.5], [0.1, 0.9]])
    assert np.all(car_travel(soft) > LIMIT + 15.0)
    assert np.all(m.prob_violation(soft) > 0.05)
    # near the runs: the simulator's travel, and a calibration it keeps well inside the limit is allowed
    near = np.array([[0.8, 0.3], [0.9, 0.7]])
    np.testing.assert_allclose(src.predict_j(near), nominal_travel(near), atol=2.0)
    assert np.all(m.prob_violation(near) < 0.05)
    # the source's own sd: at least 5 times larger at the soft end than near the runs
    from bac_agent.bo.constraints import _SourceCov

    v_soft = _SourceCov(src).var_with_grad(soft)[0]
    v_near = _SourceCov(src).var_with_grad(near)[0]
    assert np.all(np.sqrt(v_soft) > 5.0 * np.sqrt(np.max(v_near) + 1e-12))


def test_a_damaged_reduce_output_is_a_transfer_error(tmp_path: Path) -> None:
    """result.json's fields a user may have damaged are TransferErrors that say what is wrong: a schema_version
    that is not a whole number, a campaign without its engine_state, an outcome list whose length is not the
    campaign's number of runs (before: ValueError, KeyError, and a campaign skipped silently)."""
    import json

    from bac_agent.transfer import TransferError, load_outcome_sources, load_source
    from bac_common.paramspace import CalibrationDefinition
    from bac_common.paths import resolve_definition

    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    rng = np.random.default_rng(0)
    out = _reduce_output(tmp_path, [rng.random((6, 2))], nominal_travel)
    good = json.loads((out / "result.json").read_text())
    assert set(load_outcome_sources(out, definition, ["max_travel_mm"])) == {"max_travel_mm"}

    def broken(edit: object) -> Path:
        data = json.loads(json.dumps(good))
        edit(data)  # type: ignore[operator]
        (out / "result.json").write_text(json.dumps(data))
        return out

    for version in ("2a", None, 2.5, [2]):
        with pytest.raises(TransferError, match=r"schema_version .* not a whole number"):
            load_outcome_sources(broken(lambda d, v=version: d.update(schema_version=v)), definition, ["max_travel_mm"])
    with pytest.raises(TransferError, match=r"campaign 1 of .* has no engine_state"):
        load_outcome_sources(broken(lambda d: d["campaigns"][0].pop("engine_state")), definition, ["max_travel_mm"])
    with pytest.raises(TransferError, match=r"campaign 1 of .* has no engine_state"):
        load_source(broken(lambda d: d["campaigns"][0].pop("engine_state")), definition, points=32)
    with pytest.raises(TransferError, match=r"campaign 1 of .* has 6 runs but 5 values of max_travel_mm"):
        load_outcome_sources(
            broken(lambda d: d["campaigns"][0]["outcomes"]["max_travel_mm"].pop()), definition, ["max_travel_mm"]
        )


@pytest.mark.parametrize(("dim", "points"), [(2, 64), (4, 256)])
def test_a_dense_noise_free_sources_covariance_is_dropped_not_indefinite(dim: int, points: int) -> None:
    """The outside review's nit: a dense noise-free source's variance is round-off (max 1e-7 for 2-D/64 points,
    5e-8 for 4-D/256), below SOURCE_VAR_FLOOR; taking the floor off C_s's diagonal only left it indefinite
    (min eigenvalue -1e-7). Such a source has no C_s at all; a clustered one keeps its own (positive
    semi-definite up to round-off)."""
    from bac_agent.bo.constraints import _SourceCov

    src = SourceSurface.from_function(
        lambda U: 80 - 40 * np.atleast_2d(U)[:, 0] + 5 * np.atleast_2d(U)[:, 1], dim, points, label="dense"
    )
    sc = _SourceCov(src)
    rng = np.random.default_rng(0)
    for spread in (0.3, 0.05, 0.01):
        X = 0.5 + spread * (rng.random((20, dim)) - 0.5)
        assert np.linalg.eigvalsh(sc.cov_runs(X)).min() >= 0.0
        np.testing.assert_array_equal(sc.cross(X[:3], X)[0], 0.0)
        np.testing.assert_array_equal(sc.var_with_grad(X)[0], 0.0)
    clustered = _SourceCov(_clustered_source())
    assert not clustered.zero
    far = np.array([[0.02, 0.1], [0.05, 0.5]])
    assert np.all(clustered.var_with_grad(far)[0] > 0.1)
