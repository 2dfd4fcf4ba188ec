"""Batch trust-region Bayesian optimization for the simulation phase's 20-dimensional campaigns (TuRBO-1).

The agent's engine (bac_agent.bo) is made for the car: a few runs, 2-6 dimensions, one run at a time. The
simulation phase calibrates all 20 parameters of Controller II on a batch simulator that runs a few hundred
runs as fast as one, and a GP over the whole 20-dimensional box, refitted after every run, can neither be
fitted fast enough nor trusted far from its data. This is Eriksson et al. 2019 ("Scalable global optimization
via local Bayesian optimization", TuRBO-1), with what noisy runs need:

* a **trust region**: a box around the incumbent, its side ``length`` (unit cube) stretched per dimension by
  the GP's lengthscales (longer along the parameters J hardly depends on); the box doubles after
  ``success_tol`` steps in a row that improved the incumbent, halves after ``failure_tol`` steps that did not,
  and stays at ``length_min`` (no restart: the campaign's remaining runs stay in its basin; the other campaigns
  explore other basins);
* a **local GP** (bac_agent.bo.GP: Matérn-5/2 ARD, MAP hyperparameters, learned noise) fitted to at most
  ``max_fit_points`` runs nearest the incumbent;
* **batches**: each step asks ``batch`` points at once, by Thompson sampling: ``batch`` joint draws of the
  posterior over ``n_candidates`` points of the box, the argmin of each (the simulator runs them as one batch);
* the **incumbent** is the observed point with the least posterior mean (a lucky noisy run cannot fool it),
  and an improvement must exceed ``improve_tol`` of J;
* the **recommendation** is the incumbent (the run with the least posterior mean).

The state a J_mu needs (the simulation phase averages the campaigns' posteriors, paper eq. 3) is exported as
the agent engine's JSON (space, GP configuration, hyperparameters), see :meth:`TrustRegion.engine_state`:
there the hyperparameters are refitted once over the whole campaign (its nearest runs to the recommendation
and a spread of the others), so that J_mu follows each campaign's runs everywhere, not only in its last box.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import qmc

from bac_agent.bo import GP, EngineConfig, GPConfig, Hyper, SearchSpace
from bac_agent.bo.blas import one_blas_thread
from bac_common.paramspace import CalibrationDefinition

FloatArray = NDArray[np.float64]


# the local GP: a constant mean, the lengthscale prior scaled with the dimension (median sqrt(2 d) on the unit
# cube, Hvarfner et al. 2024), one L-BFGS-B start from the prior mode and one from the previous fit
TURBO_GP: Mapping[str, Any] = {
    "mean": "constant",
    "draws": 0,
    "restarts": 0,
    "maxiter": 40,
    "ls_loc": 0.5 * math.log(2.0),
    "ls_dim_scale": 0.5,
}


@dataclass(frozen=True)
class TurboConfig:
    """A campaign of the simulation phase: ``budget`` noisy runs, ``batch`` per step (see the module doc)."""

    budget: int = 400
    n_initial: int = 0  # 0 = 2 d (a Latin hypercube over the whole box)
    batch: int = 16
    length_init: float = 0.8
    length_min: float = 0.5**6
    length_max: float = 1.6
    success_tol: int = 3
    failure_tol: int = 0  # 0 = ceil(max(4, d) / batch), as TuRBO
    n_candidates: int = 512
    max_fit_points: int = 192
    improve_tol: float = 2e-3  # relative improvement of the incumbent's posterior mean that counts as a success
    seed: int = 0
    gp: Mapping[str, Any] = field(default_factory=lambda: dict(TURBO_GP))

    def __post_init__(self) -> None:
        if self.budget < 2 or self.batch < 1 or self.n_initial < 0:
            raise ValueError(f"need budget >= 2, batch >= 1, n_initial >= 0; got {self.budget}, {self.batch}")
        if not 0 < self.length_min <= self.length_init <= self.length_max:
            raise ValueError("need 0 < length_min <= length_init <= length_max")
        gp = self.gp_config()  # checked here, not in a worker
        if gp.warp or gp.ls_select or gp.ls_average:  # the trust region's Thompson draws: raw inputs, one fit
            raise ValueError(
                "the simulation phase's TuRBO takes neither gp.warp nor gp.ls_select nor gp.ls_average (engine options)"
            )

    def gp_config(self) -> GPConfig:
        # one fit (the engine's model average over two lengthscale priors only when asked for: then refused)
        return GPConfig(**{"ls_average": 0.0, **dict(self.gp)})

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["gp"] = dict(self.gp)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> TurboConfig:
        data = dict(d)
        data["gp"] = {**TURBO_GP, **dict(data.get("gp") or {})}
        return cls(**data)


class TrustRegion:
    """One campaign: ask a batch, tell its values, recommend (see the module doc)."""

    def __init__(self, definition: CalibrationDefinition, config: TurboConfig) -> None:
        self.space = SearchSpace.from_definition(definition)
        self.config = config
        d = self.space.dim
        self.d = d
        self.rng = np.random.default_rng(config.seed)
        self.n_initial = config.n_initial or min(config.budget, 2 * d)
        self.failure_tol = config.failure_tol or math.ceil(max(4, d) / config.batch)
        self.length = config.length_init
        self.successes = 0
        self.failures = 0
        self.U = np.zeros((0, d))  # observed points, unit cube
        self.y = np.zeros(0)
        self.hyper: Hyper | None = None
        self.incumbent: FloatArray | None = None
        self.incumbent_mean = math.inf
        self.history: list[tuple[int, float]] = []  # (runs told, trust-region length) at each step
        self._cache: tuple[tuple[int, bytes], GP] | None = None  # the last fit, reused while nothing new is told
        design = qmc.LatinHypercube(d, seed=int(self.rng.integers(2**31))).random(self.n_initial)
        self._design = list(design)

    # --- the loop ----------------------------------------------------------------------------------------
    @property
    def n_told(self) -> int:
        return int(self.y.size)

    @property
    def done(self) -> bool:
        return self.n_told >= self.config.budget

    def ask(self) -> FloatArray:
        """The next batch (k, d) in tuned units: the rest of the design, else ``batch`` Thompson samples."""
        left = self.config.budget - self.n_told
        if left <= 0:
            return np.zeros((0, self.d))
        if self._design:
            U = np.array(self._design[:left])
            self._design = []
        else:
            U = self._thompson(min(self.config.batch, left))
        return np.asarray(self.space.from_unit(U), dtype=float)

    def tell(self, X: FloatArray, y: FloatArray, update: bool = True) -> None:
        """Runs and their J; ``update=False``: only add them to the data (no trust-region step), e.g. the runs
        of the campaign's polish."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        y = np.asarray(y, dtype=float).ravel()
        ok = np.isfinite(y)
        self.U = np.vstack([self.U, self.space.to_unit(X[ok])])
        self.y = np.concatenate([self.y, y[ok]])
        if update and self.n_told >= self.n_initial and not self._design:
            self._update_region(int(ok.sum()))

    # --- the model ---------------------------------------------------------------------------------------
    def _fit_points(self, centre: FloatArray | None, limit: int) -> NDArray[np.intp]:
        n = self.n_told
        if n <= limit or centre is None:
            return np.arange(max(0, n - limit), n)
        ls = self.hyper.lengthscales if self.hyper is not None else np.ones(self.d)
        dist = np.sum(((self.U - centre) / ls) ** 2, axis=1)
        return np.sort(np.argsort(dist)[:limit])

    def _fit(self, centre: FloatArray | None) -> tuple[GP, NDArray[np.intp]]:
        idx = self._fit_points(centre, self.config.max_fit_points)
        key = (self.n_told, idx.tobytes())
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], idx
        gp = GP(self.config.gp_config(), hyper=self.hyper)
        with one_blas_thread():
            gp.fit(self.U[idx], self.y[idx], self.rng)
        self.hyper = gp.hyper
        self._cache = (key, gp)
        return gp, idx

    def _update_region(self, told: int) -> None:
        gp, idx = self._fit(self.incumbent)
        mu, _ = gp.predict(self.U[idx])
        k = int(np.argmin(mu))
        new_point, new_mean = self.U[idx[k]], float(mu[k])
        if self.incumbent is None:
            self.incumbent, self.incumbent_mean = new_point, new_mean
            self.history.append((self.n_told, self.length))
            return
        old_now = float(gp.predict(self.incumbent[None, :])[0][0])  # the old incumbent under the new model
        from_batch = idx[k] >= self.n_told - told  # the new incumbent is one of the runs just told
        improved = bool(from_batch) and new_mean < old_now - self.config.improve_tol * abs(old_now)
        if improved:
            self.successes += 1
            self.failures = 0
        else:
            self.failures += 1
            self.successes = 0
        if self.successes >= self.config.success_tol:
            self.length = min(2.0 * self.length, self.config.length_max)
            self.successes = 0
        elif self.failures >= self.failure_tol:
            self.length = max(self.length / 2.0, self.config.length_min)
            self.failures = 0
        self.incumbent, self.incumbent_mean = new_point, new_mean
        self.history.append((self.n_told, self.length))

    def _box(self) -> tuple[FloatArray, FloatArray]:
        assert self.incumbent is not None
        ls = self.hyper.lengthscales if self.hyper is not None else np.ones(self.d)
        w = ls / math.exp(float(np.mean(np.log(ls))))
        w = np.clip(w, 0.1, 10.0)
        w = w / math.exp(float(np.mean(np.log(w))))
        lo = np.clip(self.incumbent - w * self.length / 2.0, 0.0, 1.0)
        hi = np.clip(self.incumbent + w * self.length / 2.0, 0.0, 1.0)
        return lo, hi

    def _thompson(self, q: int) -> FloatArray:
        if self.incumbent is None:  # a design that ended with failed runs only
            return np.asarray(self.rng.random((q, self.d)), dtype=float)
        gp, idx = self._fit(self.incumbent)
        lo, hi = self._box()
        m = self.config.n_candidates
        sob = qmc.LatinHypercube(self.d, seed=int(self.rng.integers(2**31))).random(m)
        # perturb a random subset of the dimensions around the incumbent (all of them when d <= 20)
        prob = min(1.0, 20.0 / self.d)
        mask = self.rng.random((m, self.d)) <= prob
        none = ~mask.any(axis=1)
        mask[none, self.rng.integers(0, self.d, size=int(none.sum()))] = True
        C = np.where(mask, lo + sob * (hi - lo), self.incumbent)
        with one_blas_thread():
            mu, cov = _joint_posterior(gp, self.y[idx], C)
            L = _psd_cholesky(cov)
        draws = mu[None, :] + (L @ self.rng.standard_normal((m, q))).T  # (q, m)
        chosen: list[int] = []
        for row in draws:
            order = np.argsort(row)
            k = next(int(i) for i in order if int(i) not in chosen)
            chosen.append(k)
        return np.asarray(C[chosen], dtype=float)

    # --- results -----------------------------------------------------------------------------------------
    def recommend(self) -> tuple[FloatArray, float, float]:
        """(tuned values, posterior mean, posterior std) of the run with the least posterior mean (near the
        incumbent). Not the minimum of the mean over the box: in 20 dimensions a few hundred runs leave most of a
        trust region unseen, and a minimum of the mean there was measured 40 % worse on the simulator than
        predicted (road_c2b)."""
        if self.n_told == 0:
            raise ValueError("nothing told: nothing to recommend")
        gp, idx = self._fit(self.incumbent)
        mu, sd = gp.predict(self.U[idx])
        k = int(np.argmin(mu))
        self.incumbent = self.U[idx[k]]
        return np.asarray(self.space.from_unit(self.incumbent[None, :])[0], dtype=float), float(mu[k]), float(sd[k])

    def engine_state(self, theta: FloatArray, limit: int = 256) -> str:
        """The agent engine's JSON state of this campaign's whole posterior (for J_mu): hyperparameters refitted
        over the runs nearest ``theta`` and a spread of the others, the GP configuration, the space."""
        n = self.n_told
        if n <= limit:
            idx = np.arange(n)
        else:
            u = self.space.to_unit(np.atleast_2d(theta))[0]
            near = np.argsort(np.sum((self.U - u) ** 2, axis=1))[: limit // 2]
            rest = np.setdiff1d(np.arange(n), near)
            spread = rest[np.linspace(0, rest.size - 1, limit - near.size).round().astype(int)]
            idx = np.sort(np.concatenate([near, spread]))
        gp = GP(self.config.gp_config(), hyper=self.hyper)
        gp.fit(self.U[idx], self.y[idx], np.random.default_rng(self.config.seed))
        assert gp.hyper is not None
        cfg = EngineConfig(budget=self.config.budget, seed=self.config.seed, output_warp="none")
        cfg = replace(cfg, gp=self.config.gp_config())
        return json.dumps(
            {
                "space": self.space.to_dict(),
                "config": cfg.to_dict(),
                "hyper": gp.hyper.to_dict(),
                "turbo": {**self.config.to_dict(), "history": self.history, "length": self.length},
            }
        )


def _joint_posterior(gp: GP, y: FloatArray, C: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Posterior mean (m,) and covariance (m, m) of the latent J at the rows of C (standardized units) of a GP
    fitted to (gp.X, y)."""
    from bac_agent.bo.kernel import matern52_from_r2, sq_dist

    h = gp.hyper
    assert h is not None
    X = gp.X
    z = (np.asarray(y, dtype=float) - gp.y_mean) / gp.y_std - h.mean_at(X)
    K = matern52_from_r2(sq_dist(X, X, h.lengthscales), h.outputscale)
    K[np.diag_indices_from(K)] += h.noise + 1e-10 * h.outputscale
    L = _psd_cholesky(K)
    Ks = matern52_from_r2(sq_dist(C, X, h.lengthscales), h.outputscale)  # (m, n)
    V = np.linalg.solve(L, Ks.T)  # (n, m)
    mu = h.mean_at(C) + V.T @ np.linalg.solve(L, z)
    Kcc = matern52_from_r2(sq_dist(C, C, h.lengthscales), h.outputscale)
    return np.asarray(mu, dtype=float), np.asarray(Kcc - V.T @ V, dtype=float)


def _psd_cholesky(cov: FloatArray) -> FloatArray:
    jitter = 1e-6 * max(float(np.mean(np.diag(cov))), 1e-12)
    for _ in range(8):
        try:
            return np.asarray(np.linalg.cholesky(cov + jitter * np.eye(cov.shape[0])), dtype=float)
        except np.linalg.LinAlgError:
            jitter *= 10.0
    w, Q = np.linalg.eigh(cov)
    return np.asarray(Q * np.sqrt(np.maximum(w, 0.0)), dtype=float)


@dataclass(frozen=True)
class PolishConfig:
    """The local polish of each campaign's recommendation on the noise-free simulator (CMA-ES, ``cma``)."""

    evals: int = 0  # noise-free runs per campaign (0 = no polish)
    sigma: float = 0.05  # initial step, share of each range
    popsize: int = 16
    keep: int = 256  # polish runs added to the campaign's runs (its posterior, J_mu): the best half and a spread

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def polish_many(
    true_j: Any,
    starts: FloatArray,
    bounds: FloatArray,
    config: PolishConfig,
    seed: int = 0,
) -> tuple[FloatArray, FloatArray, NDArray[np.int_], list[tuple[FloatArray, FloatArray]]]:
    """CMA-ES from each row of ``starts`` (k, d) on the noise-free ``true_j``, the k searches in lock-step (their
    populations simulated as one batch), about ``config.evals`` runs each (a search stops after the generation
    that reaches them: at most ``config.evals + config.popsize - 1``). Returns the best points (k, d), their
    J (k,), the runs each spent and each search's runs (points in the units of ``bounds``, J); a start is kept when
    nothing beats it."""
    import cma

    starts = np.atleast_2d(np.asarray(starts, dtype=float))
    lo, hi = bounds[:, 0], bounds[:, 1]
    width = hi - lo
    k = starts.shape[0]
    j0 = np.asarray(true_j(starts), dtype=float)
    best_u = (starts - lo) / width
    best_j = j0.copy()
    spent = np.ones(k, dtype=int)
    seen: list[tuple[list[FloatArray], list[FloatArray]]] = [([starts[i : i + 1]], [j0[i : i + 1]]) for i in range(k)]
    if config.evals <= 1:
        return starts, best_j, spent, [(starts[i : i + 1], j0[i : i + 1]) for i in range(k)]
    opts = {"bounds": [0.0, 1.0], "popsize": config.popsize, "verbose": -9, "maxfevals": config.evals - 1}
    es = [
        cma.CMAEvolutionStrategy(np.clip(best_u[i], 0.0, 1.0), config.sigma, {**opts, "seed": seed * 1000 + i + 1})
        for i in range(k)
    ]
    active = list(range(k))
    while active:
        asks = {i: np.clip(np.asarray(es[i].ask()), 0.0, 1.0) for i in active}
        jj = np.asarray(true_j(lo + np.vstack([asks[i] for i in active]) * width), dtype=float)
        pos = 0
        still = []
        for i in active:
            X = asks[i]
            f = jj[pos : pos + len(X)]
            pos += len(X)
            es[i].tell(list(X), f.tolist())
            spent[i] += len(X)
            seen[i][0].append(lo + X * width)
            seen[i][1].append(f.copy())
            b = int(np.argmin(f))
            if f[b] < best_j[i]:
                best_j[i], best_u[i] = float(f[b]), X[b].copy()
            if not es[i].stop() and spent[i] < config.evals:
                still.append(i)
        active = still
    runs = [(np.vstack(xs), np.concatenate(fs)) for xs, fs in seen]
    return lo + best_u * width, best_j, spent, runs
