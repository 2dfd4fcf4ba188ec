"""M independent BO campaigns of N trials on a batch objective, in lock-step, on local cores or a Dask cluster.

A simulated road run costs about the same whether one calibration is simulated or twenty
(the integrator is vectorized over the batch and dominated by per-step overhead), so the
campaigns of a *group* run in lock-step: at each step every campaign of the group asks its
next point(s) (the GP part) and the group's asks are simulated as **one** batch (the
simulation part). Groups are independent: locally they run in parallel worker processes (one
per core by default), on a Dask cluster as one task each. A campaign's result does not depend
on which group it ran in: each campaign draws its runs' noise from its own generator.

Each step a campaign asks: its whole remaining initial design at once (space filling, needs
no model), then ``batch`` points (1 = the paper's sequential BO; 2 = two points per step, the
second chosen with the first one fantasized at its posterior mean, which halves the steps and
the GP fits at a small cost in trials).

Everything a worker needs travels as plain values: the objective (a small picklable value),
the settings, the campaign specs; a group returns its campaigns' observations, their
recommendation and each engine's JSON state (from which the posterior means are rebuilt).
"""

from __future__ import annotations

import itertools
import math
import os
import queue
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from bac_agent.bo import Engine, EngineConfig
from bac_reduce.analysis import ReductionError
from bac_reduce.objectives import BatchObjective
from bac_reduce.turbo import PolishConfig, TrustRegion, TurboConfig, polish_many

FloatArray = NDArray[np.float64]
OPTIMIZERS = ("agent", "turbo")


@dataclass(frozen=True)
class CampaignSettings:
    """How each campaign runs: trials N, initial design, asks per step, the engine's configuration."""

    trials: int = 100
    n_initial: int = 0  # 0 = the engine's automatic size (d + 1 beyond 4 dimensions; turbo: 2 d)
    batch: int = 1  # asks per campaign per step after the initial design
    engine: Mapping[str, Any] = field(default_factory=dict)  # EngineConfig fields ({"gp": {...}} too)
    # "agent": the agent's engine (bac_agent.bo, one GP over the box, fantasized asks); "turbo": batch trust-region
    # BO (bac_reduce.turbo), configured by ``turbo`` (TurboConfig fields)
    optimizer: str = "agent"
    turbo: Mapping[str, Any] = field(default_factory=dict)
    # the recommendation polished on the noise-free simulator (PolishConfig fields; evals 0 = no polish)
    polish: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ReductionError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.trials < 2:
            raise ReductionError(f"a campaign needs at least 2 trials, got {self.trials}")
        if self.n_initial < 0 or self.n_initial > self.trials:
            raise ReductionError(f"n_initial must be in [0, trials], got {self.n_initial}")
        if self.batch < 1:
            raise ReductionError(f"batch (asks per step) must be >= 1, got {self.batch}")
        try:
            self.turbo_config(0)
            PolishConfig(**dict(self.polish))
        except (TypeError, ValueError) as exc:
            raise ReductionError(f"bad turbo or polish configuration: {exc}") from exc
        try:
            self.engine_config(0)
        except (TypeError, ValueError) as exc:
            raise ReductionError(f"bad engine configuration {dict(self.engine)!r}: {exc}") from exc

    def engine_config(self, seed: int) -> EngineConfig:
        base = EngineConfig().to_dict()
        over = dict(self.engine)
        # one GP fit (not the engine's model average over two lengthscale priors): J_mu, the transfer prior and the
        # reports rebuild each campaign's posterior from its saved hyperparameters, which are one fit's
        gp = {**base.pop("gp"), "ls_average": 0.0, **dict(over.pop("gp", {}) or {})}
        if gp["ls_average"]:
            raise ValueError(
                "the simulation phase's campaigns take no gp.ls_average: J_mu is rebuilt from each campaign's one fit"
            )
        base.update(over)
        base.update({"budget": self.trials, "n_initial": self.n_initial, "seed": int(seed), "gp": gp})
        return EngineConfig.from_dict(base)

    def turbo_config(self, seed: int) -> TurboConfig:
        over = {k: v for k, v in dict(self.turbo).items() if k not in ("budget", "n_initial", "batch", "seed")}
        return TurboConfig.from_dict(
            {**over, "budget": self.trials, "n_initial": self.n_initial, "batch": self.batch, "seed": int(seed)}
        )

    def polish_config(self) -> PolishConfig:
        return PolishConfig(**dict(self.polish))

    def to_dict(self) -> dict[str, Any]:
        return {
            "trials": self.trials,
            "n_initial": self.n_initial,
            "batch": self.batch,
            "engine": dict(self.engine),
            "optimizer": self.optimizer,
            "turbo": dict(self.turbo),
            "polish": dict(self.polish),
        }


@dataclass(frozen=True)
class CampaignSpec:
    index: int  # 0..M-1
    seed: int  # the engine's seed


@dataclass
class CampaignResult:
    """One finished campaign."""

    index: int
    seed: int
    names: tuple[str, ...]
    X: FloatArray  # (N, d) observed calibrations, tuned units, in trial order
    y: FloatArray  # (N,) noisy J
    theta: FloatArray  # (d,) recommendation
    j_pred: float  # posterior mean at the recommendation (the campaign's J_i)
    j_std: float
    engine_state: str  # Engine.to_json() at the end (turbo: the same JSON for the posterior)
    theta_bo: FloatArray | None = None  # the optimizer's recommendation before the polish (None: no polish)
    j_true: float = math.nan  # noise-free J of theta (when the campaign measured it: the polish)
    j_true_bo: float = math.nan  # noise-free J of theta_bo
    polish_runs: int = 0  # noise-free runs of the polish
    # what each run of X reported besides J (outcome name -> (N,), NaN where a run did not report it; issue 23):
    # the simulator's max_travel_mm, lift_off_ms; empty for an objective without outcomes or a result.json
    # written before them (schema 1)
    outcomes: dict[str, FloatArray] = field(default_factory=dict)

    @property
    def best_so_far(self) -> FloatArray:
        return np.asarray(np.minimum.accumulate(self.y))

    def engine(self) -> Engine:
        return Engine.from_json(self.engine_state)

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "seed": self.seed,
            "names": list(self.names),
            "X": self.X.tolist(),
            "y": self.y.tolist(),
            "theta": self.theta.tolist(),
            "j_pred": self.j_pred,
            "j_std": self.j_std,
            "engine_state": self.engine_state,
            "theta_bo": None if self.theta_bo is None else self.theta_bo.tolist(),
            "j_true": self.j_true,
            "j_true_bo": self.j_true_bo,
            "polish_runs": self.polish_runs,
            "outcomes": {k: [None if not math.isfinite(x) else float(x) for x in v] for k, v in self.outcomes.items()},
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CampaignResult:
        try:
            return cls(
                index=int(d["index"]),
                seed=int(d["seed"]),
                names=tuple(d["names"]),
                X=np.asarray(d["X"], dtype=float),
                y=np.asarray(d["y"], dtype=float),
                theta=np.asarray(d["theta"], dtype=float),
                j_pred=float(d["j_pred"]),
                j_std=float(d["j_std"]),
                engine_state=str(d["engine_state"]),
                theta_bo=None if d.get("theta_bo") is None else np.asarray(d["theta_bo"], dtype=float),
                j_true=_float_or_nan(d.get("j_true")),
                j_true_bo=_float_or_nan(d.get("j_true_bo")),
                polish_runs=int(d.get("polish_runs") or 0),
                outcomes={
                    str(k): np.array([math.nan if x is None else float(x) for x in v], dtype=float)
                    for k, v in (d.get("outcomes") or {}).items()
                },
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ReductionError(f"a stored campaign is incomplete ({exc}); re-run the campaigns") from exc


def _observed_outcomes(eng: Engine) -> dict[str, FloatArray]:
    """Outcome name -> its value at each of the engine's observations (NaN where a run did not report it)."""
    names = sorted({k for o in eng.observations for k in (o.outcomes or {})})
    return {
        n: np.array([float((o.outcomes or {}).get(n, math.nan)) for o in eng.observations], dtype=float) for n in names
    }


def _float_or_nan(x: Any) -> float:
    return math.nan if x is None else float(x)


@dataclass
class GroupResult:
    campaigns: list[CampaignResult]
    sim_s: float  # wall time in the objective (simulation)
    gp_s: float  # wall time in ask/tell/recommend (GP fits, acquisition)
    wall_s: float
    sim_cpu_s: float  # CPU time of this process in the objective (independent of other load on the machine)
    gp_cpu_s: float
    steps: int
    worker: str  # host:pid that ran it
    started: float = 0.0  # time.time() at the start and the end of the group
    finished: float = 0.0

    @classmethod
    def ended(
        cls,
        campaigns: list[CampaignResult],
        sim_s: float,
        gp_s: float,
        t_start: float,
        sim_cpu_s: float,
        gp_cpu_s: float,
        steps: int,
        started: float,
    ) -> GroupResult:
        """The group as it ends now in this process (``t_start``: its ``time.perf_counter()`` at the start)."""
        worker = f"{socket.gethostname()}:{os.getpid()}"
        wall = time.perf_counter() - t_start
        return cls(campaigns, sim_s, gp_s, wall, sim_cpu_s, gp_cpu_s, steps, worker, started, time.time())


@dataclass
class CampaignsOutcome:
    campaigns: list[CampaignResult]  # by index
    groups: list[GroupResult]
    wall_s: float
    backend: str  # "serial", "processes x2", "dask tcp://..."

    @property
    def sim_s(self) -> float:
        return float(sum(g.sim_s for g in self.groups))

    @property
    def gp_s(self) -> float:
        return float(sum(g.gp_s for g in self.groups))

    @property
    def sim_cpu_s(self) -> float:
        return float(sum(g.sim_cpu_s for g in self.groups))

    @property
    def gp_cpu_s(self) -> float:
        return float(sum(g.gp_cpu_s for g in self.groups))


@dataclass(frozen=True)
class Progress:
    """One lock-step of one group: the slowest campaign's trials and the best J seen in the group."""

    group: int
    trials_done: int
    trials: int
    best_j: float
    sim_s: float
    gp_s: float


class Sink(Protocol):
    def put(self, item: Any) -> None: ...


def _n_asks(eng: Engine, batch: int) -> int:
    left = eng.config.budget - eng.n_trials - len(eng.pending)
    in_design = eng.n_initial - eng.n_trials - len(eng.pending)
    return max(0, min(left, in_design if in_design > 0 else batch))


def run_group(
    objective: BatchObjective,
    settings: CampaignSettings,
    specs: Sequence[CampaignSpec],
    noise_seed: int,
    group: int = 0,
    sink: Sink | None = None,
) -> GroupResult:
    """Run the campaigns ``specs`` in lock-step on ``objective`` (in this process)."""
    if settings.optimizer == "turbo":
        return _run_turbo_group(objective, settings, specs, noise_seed, group, sink)
    t_start = time.perf_counter()
    c_start = time.process_time()
    started = time.time()
    definition = objective.definition
    engines = [Engine(definition, settings.engine_config(s.seed)) for s in specs]  # (their initial designs)
    names = engines[0].names
    # each campaign's runs draw their noise from the campaign's own generator: a campaign's runs do not depend on
    # which group (process, Dask task) it ran in
    rngs = [np.random.default_rng([int(noise_seed), int(s.index)]) for s in specs]
    sim_s, sim_cpu = 0.0, 0.0
    gp_s, gp_cpu = time.perf_counter() - t_start, time.process_time() - c_start
    steps = 0
    while True:
        c0 = time.process_time()
        t0 = time.perf_counter()
        asks: list[tuple[int, dict[str, float]]] = []
        for k, eng in enumerate(engines):
            for _ in range(_n_asks(eng, settings.batch)):
                asks.append((k, eng.ask()))
        gp_s += time.perf_counter() - t0
        c1 = time.process_time()
        gp_cpu += c1 - c0
        if not asks:
            break
        t1 = time.perf_counter()
        thetas = np.array([[p[n] for n in names] for _, p in asks])
        run_rngs = [rngs[k] for k, _ in asks]
        evaluate_runs = getattr(objective, "evaluate_runs", None)
        if evaluate_runs is not None:  # the runs' outcomes too (the simulator's travel; issue 23)
            values, outs = evaluate_runs(thetas, run_rngs)
            values = np.asarray(values, dtype=float).ravel()
        else:
            values, outs = np.asarray(objective.evaluate(thetas, run_rngs), dtype=float).ravel(), {}
        sim_s += time.perf_counter() - t1
        c2 = time.process_time()
        sim_cpu += c2 - c1
        if values.shape != (len(asks),):
            raise ReductionError(f"the objective returned {values.shape} values for {len(asks)} calibrations")
        t2 = time.perf_counter()
        for i, ((k, p), v) in enumerate(zip(asks, values, strict=True)):
            if math.isfinite(v):
                run_out = {name: float(o[i]) for name, o in outs.items() if math.isfinite(float(o[i]))}
                engines[k].tell(p, float(v), run_out or None)
            else:
                engines[k].tell_failed(p, "the simulation returned a non-finite J")
        gp_s += time.perf_counter() - t2
        gp_cpu += time.process_time() - c2
        steps += 1
        if sink is not None:
            best = min((o.value for e in engines for o in e.observations), default=math.nan)
            sink.put(Progress(group, min(e.n_trials for e in engines), settings.trials, best, sim_s, gp_s))
    t3 = time.perf_counter()
    c3 = time.process_time()
    results = []
    for s, eng in zip(specs, engines, strict=True):
        if not eng.observations:
            raise ReductionError(f"campaign {s.index}: every run failed; nothing to recommend")
        rec = eng.recommend()
        results.append(
            CampaignResult(
                index=s.index,
                seed=s.seed,
                names=tuple(names),
                X=np.array([[o.params[n] for n in names] for o in eng.observations]),
                y=np.array([o.value for o in eng.observations]),
                theta=np.array([rec.params[n] for n in names]),
                j_pred=float(rec.predicted_j),
                j_std=float(rec.predicted_std),
                engine_state=eng.to_json(),
                outcomes=_observed_outcomes(eng),
            )
        )
    gp_s += time.perf_counter() - t3
    gp_cpu += time.process_time() - c3
    return GroupResult.ended(results, sim_s, gp_s, t_start, sim_cpu, gp_cpu, steps, started)


def _run_turbo_group(
    objective: BatchObjective,
    settings: CampaignSettings,
    specs: Sequence[CampaignSpec],
    noise_seed: int,
    group: int,
    sink: Sink | None,
) -> GroupResult:
    """The campaigns of a group with batch trust-region BO in lock-step (each step all their batches simulated as
    one), then each recommendation polished on the noise-free simulator (the polishes in lock-step too)."""
    t_start = time.perf_counter()
    c_start = time.process_time()
    started = time.time()
    definition = objective.definition
    trs = [TrustRegion(definition, settings.turbo_config(s.seed)) for s in specs]
    names = tuple(d.name for d in definition.dimensions)
    rngs = [np.random.default_rng([int(noise_seed), int(s.index)]) for s in specs]
    sim_s = sim_cpu = 0.0
    gp_s, gp_cpu = time.perf_counter() - t_start, time.process_time() - c_start
    steps = 0
    while True:
        c0, t0 = time.process_time(), time.perf_counter()
        asks = [tr.ask() for tr in trs]
        gp_s += time.perf_counter() - t0
        gp_cpu += time.process_time() - c0
        sizes = [a.shape[0] for a in asks]
        if sum(sizes) == 0:
            break
        c1, t1 = time.process_time(), time.perf_counter()
        row_rngs = [rngs[k] for k, n in enumerate(sizes) for _ in range(n)]
        values = np.asarray(objective.evaluate(np.vstack(asks), row_rngs), dtype=float).ravel()
        sim_s += time.perf_counter() - t1
        sim_cpu += time.process_time() - c1
        if values.shape != (sum(sizes),):
            raise ReductionError(f"the objective returned {values.shape} values for {sum(sizes)} calibrations")
        c2, t2 = time.process_time(), time.perf_counter()
        pos = 0
        for tr, X in zip(trs, asks, strict=True):
            if X.shape[0]:
                tr.tell(X, values[pos : pos + X.shape[0]])
            pos += X.shape[0]
        gp_s += time.perf_counter() - t2
        gp_cpu += time.process_time() - c2
        steps += 1
        if sink is not None:
            best = min((float(tr.y.min()) for tr in trs if tr.n_told), default=math.nan)
            sink.put(Progress(group, min(tr.n_told for tr in trs), settings.trials, best, sim_s, gp_s))
    c3, t3 = time.process_time(), time.perf_counter()
    recs = []
    for s, tr in zip(specs, trs, strict=True):
        if tr.n_told == 0:
            raise ReductionError(f"campaign {s.index}: every run failed; nothing to recommend")
        recs.append(tr.recommend())
    gp_s += time.perf_counter() - t3
    gp_cpu += time.process_time() - c3
    thetas = np.array([r[0] for r in recs])
    pol = settings.polish_config()
    c4, t4 = time.process_time(), time.perf_counter()
    bounds = np.array([[d.lower, d.upper] for d in definition.dimensions], dtype=float)
    if pol.evals > 0:
        polished, j_pol, spent, pruns = polish_many(objective.true_j, thetas, bounds, pol, seed=int(specs[0].seed))
        j_bo = np.array([float(f[0]) for _, f in pruns])  # the first run of each polish is its start
        for tr, (Xp, fp) in zip(trs, pruns, strict=True):
            keep = _keep_runs(fp, pol.keep)
            tr.tell(Xp[keep], fp[keep], update=False)  # the polish's runs join the campaign's (for its posterior)
    else:
        j_bo = np.full(len(specs), math.nan)
        polished, j_pol, spent = thetas, j_bo, np.zeros(len(specs), dtype=int)
    sim_s += time.perf_counter() - t4
    sim_cpu += time.process_time() - c4
    c5, t5 = time.process_time(), time.perf_counter()
    results = []
    for k, (s, tr) in enumerate(zip(specs, trs, strict=True)):
        theta = np.asarray(polished[k], dtype=float)
        state = tr.engine_state(theta)
        results.append(
            CampaignResult(
                index=s.index,
                seed=s.seed,
                names=names,
                X=np.asarray(tr.space.from_unit(tr.U), dtype=float),
                y=tr.y.copy(),
                theta=theta,
                j_pred=math.nan,
                j_std=math.nan,
                engine_state=state,
                theta_bo=thetas[k] if pol.evals > 0 else None,
                j_true=float(j_pol[k]),
                j_true_bo=float(j_bo[k]),
                polish_runs=int(spent[k]),
            )
        )
    # J_i: each campaign's posterior (as J_mu rebuilds it) at its recommendation
    for r in results:
        mean, std = _posterior_at(r, r.theta)
        r.j_pred, r.j_std = mean, std
    gp_s += time.perf_counter() - t5
    gp_cpu += time.process_time() - c5
    return GroupResult.ended(results, sim_s, gp_s, t_start, sim_cpu, gp_cpu, steps, started)


def _keep_runs(f: FloatArray, keep: int) -> NDArray[np.intp]:
    """Which of a polish's runs join the campaign's: the best half of ``keep`` and the rest spread over the polish."""
    n = f.size
    if n <= keep:
        return np.arange(n)
    best = np.argsort(f)[: keep // 2]
    rest = np.setdiff1d(np.arange(n), best)
    spread = rest[np.linspace(0, rest.size - 1, keep - best.size).round().astype(int)]
    return np.sort(np.concatenate([best, spread]))


def _posterior_at(c: CampaignResult, theta: FloatArray) -> tuple[float, float]:
    """The posterior mean and std of a campaign (rebuilt from its state and runs, as J_mu does) at ``theta``."""
    import json

    from bac_agent.bo import GP, Hyper, SearchSpace

    state = json.loads(c.engine_state)
    space = SearchSpace.from_dict(state["space"])
    cfg = EngineConfig.from_dict(state["config"])
    gp = GP(cfg.gp).condition(space.to_unit(c.X), c.y, Hyper.from_dict(state["hyper"]))
    m, sd = gp.predict(space.to_unit(np.atleast_2d(theta)))
    return float(m[0]), float(sd[0])


# --- spreading groups ------------------------------------------------------------------------------
def split_groups(specs: Sequence[CampaignSpec], n_groups: int) -> list[list[CampaignSpec]]:
    """``n_groups`` contiguous groups of near-equal size (none empty)."""
    n = max(1, min(int(n_groups), len(specs)))
    edges = np.linspace(0, len(specs), n + 1).round().astype(int)
    return [list(specs[a:b]) for a, b in itertools.pairwise(edges) if b > a]


def local_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


class _Worker:
    """What a local worker process got from its initializer."""

    queue: Any = None
    barrier: Any = None


def _init_process(progress_queue: Any, barrier: Any) -> None:
    _Worker.queue = progress_queue
    _Worker.barrier = barrier
    # one BLAS thread and no nested simulator pool: this process is one of the cores' workers
    os.environ["BAC_SIM_WORKERS"] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover
        pass


def _process_task(
    objective: BatchObjective, settings: CampaignSettings, specs: Sequence[CampaignSpec], noise_seed: int, group: int
) -> GroupResult:
    if _Worker.barrier is not None:
        # one group per process: every group waits here until all have a process (a fast process must not
        # take a second group while another process is still starting)
        try:
            _Worker.barrier.wait(120.0)
        except threading.BrokenBarrierError:
            pass
    return run_group(objective, settings, specs, noise_seed, group, _Worker.queue)


class _CallbackSink:
    def __init__(self, fn: Callable[[Progress], None] | None) -> None:
        self.fn = fn

    def put(self, item: Any) -> None:
        if self.fn is not None:
            self.fn(item)


class _DaskSink:
    """Progress from a Dask task: an event on the worker, delivered to the client's topic handler."""

    def __init__(self, topic: str) -> None:
        self.topic = topic

    def put(self, item: Any) -> None:
        try:
            from distributed import get_worker

            p: Progress = item
            get_worker().log_event(
                self.topic,
                {
                    "group": p.group,
                    "trials_done": p.trials_done,
                    "trials": p.trials,
                    "best_j": p.best_j,
                    "sim_s": p.sim_s,
                    "gp_s": p.gp_s,
                },
            )
        except Exception:  # progress is best effort; never fail a campaign for it
            pass


def _iter_specs(m: int, seed: int) -> Iterator[CampaignSpec]:
    for i in range(m):
        yield CampaignSpec(i, int(seed) * 1000 + i)


def campaign_specs(m: int, seed: int = 0) -> list[CampaignSpec]:
    """M campaigns with distinct, reproducible engine seeds."""
    if m < 1:
        raise ReductionError(f"need at least one campaign, got M = {m}")
    return list(_iter_specs(m, seed))


def run_campaigns(
    objective: BatchObjective,
    settings: CampaignSettings,
    specs: Sequence[CampaignSpec],
    *,
    noise_seed: int = 0,
    workers: int | None = None,
    scheduler: str | None = None,
    client: Any = None,
    group_size: int | None = None,
    on_progress: Callable[[Progress], None] | None = None,
    connect_timeout_s: float = 20.0,
) -> CampaignsOutcome:
    """Run the campaigns and return them by index.

    * ``scheduler`` (a Dask scheduler address, e.g. ``tcp://10.0.0.5:8786``) or ``client`` (a
      ``distributed.Client``): one task per group on the cluster; groups of ``group_size``
      campaigns (default: spread over the cluster's worker threads);
    * else ``workers`` local processes (default: one per core; 1 = in this process), one group each.
    """
    if not specs:
        raise ReductionError("no campaign to run")
    t0 = time.perf_counter()
    if scheduler is not None or client is not None:
        groups, backend = _run_dask(
            objective, settings, specs, noise_seed, scheduler, client, group_size, on_progress, connect_timeout_s
        )
    else:
        n = local_workers() if workers is None else int(workers)
        if n < 1:
            raise ReductionError(f"workers must be >= 1, got {n}")
        n_groups = n if group_size is None else math.ceil(len(specs) / max(1, group_size))
        parts = split_groups(specs, n_groups)
        if n == 1 or len(parts) == 1:
            sink = _CallbackSink(on_progress)
            groups = [run_group(objective, settings, g, noise_seed, i, sink) for i, g in enumerate(parts)]
            backend = "serial (this process)"
        else:
            groups = _run_processes(objective, settings, parts, noise_seed, min(n, len(parts)), on_progress)
            backend = f"{min(n, len(parts))} local processes"
    campaigns = sorted((c for g in groups for c in g.campaigns), key=lambda c: c.index)
    return CampaignsOutcome(campaigns, groups, time.perf_counter() - t0, backend)


def _run_processes(
    objective: BatchObjective,
    settings: CampaignSettings,
    parts: list[list[CampaignSpec]],
    noise_seed: int,
    n: int,
    on_progress: Callable[[Progress], None] | None,
) -> list[GroupResult]:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = multiprocessing.get_context("spawn")
    q = ctx.Queue()
    barrier = ctx.Barrier(len(parts)) if len(parts) <= n else None
    results: dict[int, GroupResult] = {}
    with ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_init_process, initargs=(q, barrier)) as pool:
        futures = {pool.submit(_process_task, objective, settings, g, noise_seed, i): i for i, g in enumerate(parts)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            _drain(q, on_progress)
            for f in done:
                results[futures[f]] = f.result()  # re-raises a worker's exception here
        _drain(q, on_progress)
    return [results[i] for i in range(len(parts))]


def _drain(q: Any, on_progress: Callable[[Progress], None] | None) -> None:
    while True:
        try:
            item = q.get_nowait()
        except (queue.Empty, OSError, EOFError):
            return
        if on_progress is not None:
            on_progress(item)


def _dask_task(
    objective: BatchObjective,
    settings: CampaignSettings,
    specs: Sequence[CampaignSpec],
    noise_seed: int,
    group: int,
    sink: Sink,
) -> GroupResult:
    """A group on a Dask worker: its batches simulated in the worker's process (a worker process is daemonic
    and may not start the simulator's process pool; each worker thread is one core's share of the cluster)."""
    from bac_sim.parallel import in_this_process

    with in_this_process():
        return run_group(objective, settings, specs, noise_seed, group, sink)


def _call(fn: Any, *args: Any, **kwargs: Any) -> Any:
    """Call an untyped function of an optional dependency (dask.distributed)."""
    return fn(*args, **kwargs)


def _run_dask(
    objective: BatchObjective,
    settings: CampaignSettings,
    specs: Sequence[CampaignSpec],
    noise_seed: int,
    scheduler: str | None,
    client: Any,
    group_size: int | None,
    on_progress: Callable[[Progress], None] | None,
    connect_timeout_s: float,
) -> tuple[list[GroupResult], str]:
    try:
        import distributed
    except ImportError as exc:  # pragma: no cover - distributed is a runtime dependency
        raise ReductionError("a Dask scheduler was given but dask.distributed is not installed") from exc
    own = client is None
    if own:
        try:
            client = _call(distributed.Client, scheduler, timeout=f"{connect_timeout_s:g}s")
        except (OSError, TimeoutError) as exc:
            raise ReductionError(
                f"cannot reach the Dask scheduler at {scheduler!r}: {exc}; "
                "start one with `dask scheduler` and workers with `dask worker ADDRESS`"
            ) from exc
    try:
        threads = int(sum(client.nthreads().values()))
        if threads < 1:
            raise ReductionError(f"the Dask cluster at {client.scheduler.address} has no workers")
        n_groups = threads if group_size is None else math.ceil(len(specs) / max(1, group_size))
        parts = split_groups(specs, n_groups)
        topic = f"bac-reduce-{uuid.uuid4().hex[:8]}"
        lock = threading.Lock()

        finished: set[int] = set()

        def handler(event: Any) -> None:
            _, msg = event
            p = Progress(**{k: msg[k] for k in Progress.__dataclass_fields__})
            with lock:
                if p.trials_done >= p.trials:
                    finished.add(p.group)
                if on_progress is not None:
                    on_progress(p)

        client.subscribe_topic(topic, handler)
        futures = [
            client.submit(_dask_task, objective, settings, g, noise_seed, i, _DaskSink(topic), pure=False)
            for i, g in enumerate(parts)
        ]
        results: dict[int, GroupResult] = {}
        for fut in _call(distributed.as_completed, futures):
            res: GroupResult = fut.result()
            results[res.campaigns[0].index] = res
        # the workers' last progress events travel separately from the results: give them a moment
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and on_progress is not None and len(finished) < len(parts):
            time.sleep(0.02)
        client.unsubscribe_topic(topic)
        ordered = [results[k] for k in sorted(results)]
        return ordered, f"dask {client.scheduler.address} ({threads} threads, {len(parts)} tasks)"
    finally:
        if own:
            client.close()
