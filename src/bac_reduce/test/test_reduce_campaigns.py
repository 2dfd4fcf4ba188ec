"""Campaigns in lock-step: batching, reproducibility, local processes, a Dask LocalCluster, J_mu."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np
import pytest

from bac_agent.bo import Engine, GPConfig
from bac_reduce.analysis import ReductionError
from bac_reduce.campaigns import (
    CampaignResult,
    CampaignSettings,
    Progress,
    campaign_specs,
    run_campaigns,
    split_groups,
)
from bac_reduce.objectives import SyntheticObjective
from bac_reduce.pipeline import PosteriorMean, polish

QUICK = {
    "gp": {"draws": 0, "restarts": 0, "maxiter": 30, "mean": "constant"},
    "n_candidates": 128,
    "n_local": 64,
    "acq_restarts": 1,
    "design_margin": 0.02,  # the whole-range initial design these tests were written for (as the phase's own engine)
}


@dataclass(frozen=True)
class Counting:
    """A synthetic objective that records the size of every batch it evaluates."""

    inner: SyntheticObjective = field(default_factory=SyntheticObjective)
    batches: list[int] = field(default_factory=list)

    @property
    def definition(self):  # type: ignore[no-untyped-def]
        return self.inner.definition

    @property
    def label(self) -> str:
        return "counting"

    def evaluate(self, thetas: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        self.batches.append(int(np.atleast_2d(thetas).shape[0]))
        return self.inner.evaluate(thetas, rng)

    def true_j(self, thetas: np.ndarray) -> np.ndarray:
        return self.inner.true_j(thetas)

    def with_definition(self, definition):  # type: ignore[no-untyped-def]
        return Counting(self.inner.with_definition(definition))


def test_lockstep_simulates_each_step_of_all_campaigns_as_one_batch() -> None:
    obj = Counting()
    settings = CampaignSettings(trials=13, n_initial=5, batch=3, engine=QUICK)
    out = run_campaigns(obj, settings, campaign_specs(3), workers=1)
    # step 1: the three initial designs (3 x 5); then 3 asks per campaign: 3 x 3, 3 x 3, then the last 2 each
    assert obj.batches == [15, 9, 9, 6]
    assert [c.index for c in out.campaigns] == [0, 1, 2]
    for c in out.campaigns:
        assert c.X.shape == (13, 8) and c.y.shape == (13,)
        assert np.all((c.X >= 0) & (c.X <= 1000))
        assert c.theta.shape == (8,) and math.isfinite(c.j_pred) and c.j_std > 0
    g = out.groups[0]
    assert g.steps == 4 and g.sim_s > 0 and g.gp_s > 0 and g.worker.endswith(f":{os.getpid()}")


def test_campaigns_are_reproducible_and_independent() -> None:
    settings = CampaignSettings(trials=8, n_initial=4, batch=2, engine=QUICK)
    a = run_campaigns(SyntheticObjective(), settings, campaign_specs(2, seed=4), workers=1, noise_seed=1)
    b = run_campaigns(SyntheticObjective(), settings, campaign_specs(2, seed=4), workers=1, noise_seed=1)
    for ca, cb in zip(a.campaigns, b.campaigns, strict=True):
        np.testing.assert_array_equal(ca.X, cb.X)
        np.testing.assert_array_equal(ca.y, cb.y)
    # two campaigns start from different designs (different engine seeds)
    assert not np.allclose(a.campaigns[0].X[:3], a.campaigns[1].X[:3])


def test_settings_are_checked() -> None:
    with pytest.raises(ReductionError, match="at least 2 trials"):
        CampaignSettings(trials=1)
    with pytest.raises(ReductionError, match="batch"):
        CampaignSettings(batch=0)
    with pytest.raises(ReductionError, match="engine configuration"):
        CampaignSettings(engine={"no_such_field": 1})
    cfg = CampaignSettings(trials=20, engine={"gp": {"maxiter": 7}, "acq_restarts": 3}).engine_config(5)
    assert (cfg.budget, cfg.seed, cfg.gp.maxiter, cfg.acq_restarts, cfg.gp.draws) == (20, 5, 7, 3, GPConfig().draws)
    # one GP fit per campaign (J_mu is rebuilt from it), not the engine's default model average
    assert cfg.gp.ls_average == 0.0 and GPConfig().ls_average > 0.0
    with pytest.raises(ReductionError, match=r"take no gp\.ls_average"):
        CampaignSettings(engine={"gp": {"ls_average": 0.5}})


def test_split_groups_spreads_evenly() -> None:
    specs = campaign_specs(10)
    assert [len(g) for g in split_groups(specs, 3)] == [3, 4, 3]
    assert [len(g) for g in split_groups(specs, 20)] == [1] * 10
    assert [s.index for g in split_groups(specs, 4) for s in g] == list(range(10))


@pytest.mark.slow
def test_groups_run_in_parallel_worker_processes() -> None:
    seen: list[Progress] = []
    out = run_campaigns(
        SyntheticObjective(),
        CampaignSettings(trials=8, n_initial=4, batch=2, engine=QUICK),
        campaign_specs(4),
        workers=2,
        on_progress=seen.append,
    )
    assert out.backend == "2 local processes"
    workers = {g.worker for g in out.groups}
    assert len(workers) == 2 and all(not w.endswith(f":{os.getpid()}") for w in workers)
    assert [c.index for c in out.campaigns] == [0, 1, 2, 3]
    assert [len(g.campaigns) for g in out.groups] == [2, 2]
    a, b = out.groups
    assert a.started < b.finished and b.started < a.finished  # at the same time
    assert {p.group for p in seen} == {0, 1} and max(p.trials_done for p in seen) == 8


@pytest.mark.slow
def test_groups_run_on_a_dask_cluster() -> None:
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        seen: list[Progress] = []
        settings = CampaignSettings(trials=8, n_initial=4, batch=2, engine=QUICK)
        out = run_campaigns(SyntheticObjective(), settings, campaign_specs(4), client=client, on_progress=seen.append)
        assert out.backend.startswith("dask tcp://127.0.0.1:") and "2 tasks" in out.backend
        assert len({g.worker for g in out.groups}) == 2  # one task on each worker process
        assert [c.index for c in out.campaigns] == [0, 1, 2, 3]
        assert {p.group for p in seen if p.trials_done == 8} == {0, 1}
        # by address, one campaign per task; the same seeds give the same initial designs as a local run
        by_address = run_campaigns(
            SyntheticObjective(), settings, campaign_specs(4), scheduler=cluster.scheduler_address, group_size=1
        )
        assert "4 tasks" in by_address.backend
        local = run_campaigns(SyntheticObjective(), settings, campaign_specs(4), workers=1)
        for a, b in zip(by_address.campaigns, local.campaigns, strict=True):
            np.testing.assert_array_equal(a.X[:4], b.X[:4])  # the initial design


def test_an_unreachable_scheduler_is_a_clear_error() -> None:
    pytest.importorskip("distributed")
    with pytest.raises(ReductionError, match="cannot reach the Dask scheduler"):
        run_campaigns(
            SyntheticObjective(),
            CampaignSettings(trials=4, engine=QUICK),
            campaign_specs(1),
            scheduler="tcp://127.0.0.1:9",
            connect_timeout_s=1.0,
        )


def _campaign(obj: SyntheticObjective, seed: int, trials: int) -> tuple[Engine, CampaignResult]:
    eng = Engine(obj.definition, CampaignSettings(trials, 5, 1, QUICK).engine_config(seed))
    rng = np.random.default_rng(seed)
    names = eng.names
    while not eng.done:
        p = eng.ask()
        eng.tell(p, float(obj.evaluate(np.array([[p[n] for n in names]]), rng)[0]))
    rec = eng.recommend()
    X = np.array([[o.params[n] for n in names] for o in eng.observations])
    y = np.array([o.value for o in eng.observations])
    res = CampaignResult(0, seed, names, X, y, np.array([rec.params[n] for n in names]), 0.0, 0.0, eng.to_json())
    return eng, res


def test_j_mu_is_exactly_the_campaigns_posterior() -> None:
    obj = SyntheticObjective()
    eng_a, a = _campaign(obj, 1, 10)
    eng_b, b = _campaign(obj, 2, 10)
    rng = np.random.default_rng(0)
    X = rng.random((40, 8)) * 1000
    ma, sa = eng_a.predict_unit(X / 1000)
    mb, sb = eng_b.predict_unit(X / 1000)
    # one campaign: both averages are its posterior mean (rebuilt without a refit)
    for mode in ("mean", "weighted"):
        np.testing.assert_allclose(PosteriorMean.from_campaigns([a], mode)(X), ma, rtol=1e-10)
    np.testing.assert_allclose(PosteriorMean.from_campaigns([a, b], "mean")(X), (ma + mb) / 2, rtol=1e-10)
    w = PosteriorMean.from_campaigns([a, b], "weighted")(X)
    np.testing.assert_allclose(w, (ma / sa**2 + mb / sb**2) / (1 / sa**2 + 1 / sb**2), rtol=1e-10)
    # at a's own observations a is sure and b is not: the weighted average follows a
    at_a = PosteriorMean.from_campaigns([a, b], "weighted")(a.X)
    own_a, _ = eng_a.predict_unit(a.X / 1000)
    plain = PosteriorMean.from_campaigns([a, b], "mean")(a.X)
    assert np.mean(np.abs(at_a - own_a)) < np.mean(np.abs(plain - own_a))


def test_polish_finds_a_quadratic_minimum_with_batched_coordinate_steps() -> None:
    calls: list[int] = []

    def f(X: np.ndarray) -> np.ndarray:
        calls.append(X.shape[0])
        return 1.0 + np.sum(((X - np.array([310.0, 720.0, 55.0])) / 1000.0) ** 2, axis=1)

    x, fx, evals = polish(f, np.array([0.0, 0.0, 1000.0]), np.array([[0.0, 1000.0]] * 3), iterations=30)
    np.testing.assert_allclose(x, [310.0, 720.0, 55.0], atol=10.0)
    assert fx == pytest.approx(1.0, abs=1e-4)
    assert evals == sum(calls) and len(calls) == 31  # one batch per iteration (+ the start)


@pytest.mark.slow
def test_the_simulated_car_runs_on_a_cluster_of_worker_processes_as_locally() -> None:
    """A Dask worker process is daemonic: the simulator may not open its own process pool there (it did, and
    `bac reduce --scheduler` died with "daemonic processes are not allowed to have children"). Each group's first
    batch (2 campaigns x 8 runs of the 1.5 km road) is big enough for the simulator to split it over processes."""
    distributed = pytest.importorskip("distributed")
    from bac_reduce.objectives import SimulatedCar

    settings = CampaignSettings(trials=10, n_initial=8, batch=2, engine=QUICK)
    specs = campaign_specs(4, seed=3)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = run_campaigns(SimulatedCar("road_c2"), settings, specs, client=client, group_size=2, noise_seed=5)
    assert "2 tasks" in remote.backend
    local = run_campaigns(SimulatedCar("road_c2"), settings, specs, workers=1, noise_seed=5)
    for a, b in zip(remote.campaigns, local.campaigns, strict=True):
        assert a.index == b.index and a.X.shape == (10, 20)
        np.testing.assert_allclose(a.X, b.X, rtol=1e-9)
        np.testing.assert_allclose(a.y, b.y, rtol=1e-9)
