"""The ask/tell optimizer: paper algorithm 1's brain, without ROS.

>>> from bac_agent.bo import Engine
>>> eng = Engine({"damping_front": (0.0, 1.0), "damping_rear": (0.0, 1.0)}, budget=12, seed=1)
>>> while not eng.done:
...     p = eng.ask()
...     eng.tell(p, run_on_the_car(p))          # doctest: +SKIP
>>> eng.recommend()                             # doctest: +SKIP
Recommendation(params={...}, predicted_j=..., predicted_std=..., ...)

* the first ``n_initial`` asks are a space-filling design (a Latin hypercube);
* then a GP (Matérn-5/2 ARD, MAP hyperparameters, learned noise) is fitted to what
  was told (through a fitted Yeo-Johnson output warp, bo/warp.py), and the next
  point maximizes log Expected Improvement over the best *posterior mean* at an
  observed point (an incumbent that noise cannot fool);
  points asked but not yet told are "fantasized" at their posterior mean, so two
  asks in a row give two different points;
* the recommendation is the argmin of the posterior mean over the whole domain
  (the paper), with its predicted J and standard deviation;
* asks are quantized to the space's resolution and always within bounds, so the
  values told are the values the ECU holds.

The whole state (observations, failures, pending asks, the random generator, the
last hyperparameters) serializes to JSON; ``Engine.from_json(eng.to_json())``
continues exactly where ``eng`` was.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from bac_agent.bo.acquisition import NoisyEI, log_ei, log_ei_with_grad
from bac_agent.bo.design import candidates, default_n_initial, initial_design
from bac_agent.bo.gp import GP, GPConfig, Hyper
from bac_agent.bo.space import SearchSpace
from bac_agent.bo.warp import WARPS, OutputWarp
from bac_common.errors import BacError

FloatArray = NDArray[np.float64]

STATE_VERSION = 1
KIND_INITIAL = "initial"
KIND_GUESS = "guess"  # a best guess given with the configuration (initial_points), asked first
KIND_OPTIMIZED = "optimized"
KIND_RANDOM = "random"
KIND_GRID = "grid"
ACQUISITIONS = ("ei", "nei")


def _make_blas_limiter() -> Callable[[], Any]:
    """A context manager that runs BLAS on one thread (threadpoolctl), or does nothing without it.

    The GP works on many small matrices: a multi-threaded OpenBLAS on a busy 2-core machine spins
    on descheduled threads and one ask took 7 s instead of 0.09 s (bench/agent_latency.py).
    """
    try:
        from threadpoolctl import ThreadpoolController

        controller = ThreadpoolController()
    except Exception:  # threadpoolctl missing or unable to inspect the BLAS: leave it alone
        controller = None

    @contextmanager
    def limit() -> Iterator[None]:
        if controller is None:
            yield
            return
        with controller.limit(limits=1, user_api="blas"):
            yield

    return limit


_one_blas_thread = _make_blas_limiter()


class EngineError(BacError, ValueError):
    """The optimizer was used wrongly (nothing told yet, a bad value, a bad saved state)."""


@dataclass(frozen=True)
class EngineConfig:
    """Configuration of a campaign's optimizer."""

    budget: int = 15  # trials of the campaign (told + failed)
    n_initial: int = 0  # initial design size; 0 = automatic (see design.default_n_initial)
    # the initial design spans [design_margin, 1 - design_margin] of every parameter's range: runs at the faces,
    # where J is steep, tell a few-run model little about where the minimum lies (measured: docs/agent.md)
    design_margin: float = 0.25
    seed: int = 0
    n_candidates: int = 1024  # space-filling candidates for the acquisition maximizer
    n_local: int = 256  # candidates around the best points
    acq_restarts: int = 4  # L-BFGS-B starts from the best candidates
    recommend_beta: float = 0.0  # recommendation minimizes mean + beta * std (0: the paper's argmin of the mean)
    acquisition: str = "nei"  # "nei": noisy EI (sampled incumbents); "ei": log EI over the best posterior mean
    nei_samples: int = 64  # joint draws at the observed points for "nei"
    # with gp.mean == "bowl": the bowl is the prior mean while at most this many runs are told, then a constant
    # (a trend helps while runs are few; later it would only bias a model that the runs can carry); 0 = automatic,
    # twice the initial design
    bowl_runs: int = 0
    # "yeo-johnson": the GP is fitted to the runs through a fitted power transform (bo/warp.py); "none": as told
    output_warp: str = "yeo-johnson"
    # best guesses (tuned values by name) asked first, in place of the first points of the initial design (the
    # paper's "best guess policy"): e.g. the simulation phase's optimum of a meta-parameter file
    initial_points: tuple[Mapping[str, float], ...] = ()
    gp: GPConfig = field(default_factory=GPConfig)

    def __post_init__(self) -> None:
        if self.budget < 1:
            raise EngineError(f"budget must be >= 1, got {self.budget}")
        if self.bowl_runs < 0:
            raise EngineError(f"bowl_runs must be >= 0 (0 = automatic), got {self.bowl_runs}")
        if not 0.0 <= self.design_margin < 0.5:
            raise EngineError(f"design_margin must be in [0, 0.5), got {self.design_margin}")
        if self.n_initial < 0:
            raise EngineError(f"n_initial must be >= 0 (0 = automatic), got {self.n_initial}")
        if self.output_warp not in WARPS:
            raise EngineError(f"output_warp must be one of {', '.join(WARPS)}, got {self.output_warp!r}")
        if self.acquisition not in ACQUISITIONS:
            raise EngineError(f"acquisition must be one of {', '.join(ACQUISITIONS)}, got {self.acquisition!r}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["gp"] = asdict(self.gp)
        d["initial_points"] = [dict(p) for p in self.initial_points]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EngineConfig:
        data = dict(d)
        data["initial_points"] = tuple(
            {str(k): float(v) for k, v in p.items()} for p in data.get("initial_points") or ()
        )
        gp = dict(data.pop("gp", {}) or {})
        for k in ("ls_bounds", "os_bounds"):
            if k in gp:
                gp[k] = tuple(gp[k])
        return cls(**data, gp=GPConfig(**gp))


@dataclass(frozen=True)
class Suggestion:
    """One ask: the parameters, why they were chosen and what the model expects."""

    params: dict[str, float]
    kind: str  # KIND_*
    predicted_j: float = math.nan
    predicted_std: float = math.nan


@dataclass(frozen=True)
class Recommendation:
    """The campaign's answer: argmin of the posterior mean, with its prediction."""

    params: dict[str, float]
    predicted_j: float
    predicted_std: float
    n_observations: int
    best_observed_params: dict[str, float] | None = None
    best_observed_j: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Observation:
    params: dict[str, float]
    value: float


@dataclass(frozen=True)
class Failure:
    params: dict[str, float]
    reason: str


class Engine:
    """Bayesian optimization by ask/tell over a :class:`SearchSpace` (see the module doc)."""

    def __init__(
        self,
        space: Any,
        config: EngineConfig | None = None,
        *,
        budget: int | None = None,
        n_initial: int | None = None,
        seed: int | None = None,
    ) -> None:
        self.space = SearchSpace.from_spec(space)
        cfg = config or EngineConfig()
        over: dict[str, Any] = {}
        if budget is not None:
            over["budget"] = int(budget)
        if n_initial is not None:
            over["n_initial"] = int(n_initial)
        if seed is not None:
            over["seed"] = int(seed)
        self.config = replace(cfg, **over) if over else cfg
        self.observations: list[Observation] = []
        self.failures: list[Failure] = []
        self.pending: list[dict[str, float]] = []
        self.rng = np.random.default_rng(self.config.seed)
        self._gp = GP(self.config.gp)
        self._gp_key: tuple[int, int] | None = None
        self._warp = OutputWarp()  # refitted with the GP; a pure function of the observations
        self._design = initial_design(self.n_initial, self.space.dim, self.config.seed, self.config.design_margin)
        self._n_guess = 0
        if self.config.initial_points:
            guesses = self.space.to_unit(np.array([self.space.to_array(p) for p in self.config.initial_points]))
            n_g = min(guesses.shape[0], self._design.shape[0])
            # the guesses first; each takes the place of the design point nearest to it, the rest still spans
            remaining = list(range(self._design.shape[0]))
            for g in guesses[:n_g]:
                remaining.remove(min(remaining, key=lambda i: float(np.sum((self._design[i] - g) ** 2))))
            self._design = np.vstack([guesses[:n_g], self._design[remaining]])
            self._n_guess = n_g

    # --- facts ------------------------------------------------------------------------
    @property
    def n_initial(self) -> int:
        return self.config.n_initial or default_n_initial(self.space.dim, self.config.budget)

    @property
    def bowl_runs(self) -> int:
        """Runs told up to which a ``bowl`` prior mean is used (then a constant)."""
        return self.config.bowl_runs or 2 * self.n_initial

    def _gp_config(self) -> GPConfig:
        cfg = self.config.gp
        if cfg.mean == "bowl" and len(self.observations) > self.bowl_runs:
            return replace(cfg, mean="constant")
        return cfg

    @property
    def n_trials(self) -> int:
        """Trials finished: told or failed."""
        return len(self.observations) + len(self.failures)

    @property
    def done(self) -> bool:
        return self.n_trials >= self.config.budget

    @property
    def names(self) -> tuple[str, ...]:
        return self.space.names

    def best_observed(self) -> Observation | None:
        return min(self.observations, key=lambda o: o.value) if self.observations else None

    # --- ask ----------------------------------------------------------------------------------
    def ask(self) -> dict[str, float]:
        """The next parameters to run, name -> value (fixed values included)."""
        return self.ask_with_info().params

    def ask_with_info(self) -> Suggestion:
        """The next parameters with the reason they were chosen and the model's prediction."""
        with _one_blas_thread():
            return self._ask_with_info()

    def _ask_with_info(self) -> Suggestion:
        k = self.n_trials + len(self.pending)
        if k < self.n_initial and k < self._design.shape[0]:
            u = self._design[k]
            s = self._suggest(u, KIND_GUESS if k < self._n_guess else KIND_INITIAL)
        elif len(self.observations) < 2 or float(np.ptp([o.value for o in self.observations])) == 0.0:
            s = self._suggest(self.rng.random(self.space.dim), KIND_RANDOM)
        else:
            s = self._suggest(self._maximize_acquisition(), KIND_OPTIMIZED)
        self.pending.append(dict(s.params))
        return s

    def _suggest(self, u: FloatArray, kind: str) -> Suggestion:
        x = self.space.from_unit(u)
        params = self.space.to_params(x)
        mean, std = (math.nan, math.nan)
        if len(self.observations) >= 1 and kind == KIND_OPTIMIZED:
            m, s = self._predict_j(self.space.to_unit(x)[None, :])
            mean, std = float(m[0]), float(s[0])
        return Suggestion(params, kind, mean, std)

    def _model(self) -> GP:
        """The GP fitted to every observation (refitted only when they changed)."""
        if not self.observations:
            raise EngineError("nothing has been told yet: tell() at least one result first")
        key = (len(self.observations), hash(tuple(o.value for o in self.observations)))
        cfg = self._gp_config()
        if self._gp.config != cfg:
            self._gp = GP(cfg, hyper=self._gp.hyper)  # the last fit stays a start of the next one
            self._gp_key = None
        if self._gp_key != key:
            X = self.space.to_unit(np.array([self.space.to_array(o.params) for o in self.observations]))
            y = np.array([o.value for o in self.observations])
            self._warp = OutputWarp.for_runs(self.config.output_warp, y)
            self._gp.fit(X, self._warp.forward(y), self.rng)
            self._gp_key = key
        return self._gp

    def _predict_j(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and std at unit-cube points, in J (through the output warp's inverse)."""
        m, s = self._model().predict(U)
        return self._warp.inverse_mean_std(m, s)

    def _maximize_acquisition(self) -> FloatArray:
        gp = self._model()
        d = self.space.dim
        X_obs = gp.X
        mu_obs, _ = gp.predict_std_units(X_obs)
        best = float(np.min(mu_obs))
        model = gp
        if self.pending:
            # kriging believer: pending points are fantasized at their posterior mean
            Xp = self.space.to_unit(np.array([self.space.to_array(p) for p in self.pending]))
            mp, _ = gp.predict(Xp)
            y_all = np.concatenate([gp.y_mean + gp.y_std * gp._z, mp])
            model = GP(gp.config).condition(np.vstack([X_obs, Xp]), y_all, gp.hyper, scaling=(gp.y_mean, gp.y_std))
            best = float((np.min(model.predict(X_obs)[0]) - model.y_mean) / model.y_std)
        cand = candidates(self.config.n_candidates, d, self.rng)
        # local candidates around the best points by posterior mean
        assert gp.hyper is not None
        top = X_obs[np.argsort(mu_obs)[: min(5, X_obs.shape[0])]]
        scale = np.minimum(0.1 * gp.hyper.lengthscales, 0.1)
        idx = self.rng.integers(0, top.shape[0], self.config.n_local)
        local = np.clip(top[idx] + self.rng.standard_normal((self.config.n_local, d)) * scale, 0.0, 1.0)
        cand = np.vstack([cand, local])
        if self.config.acquisition == "nei":
            nei = NoisyEI(model, self.config.nei_samples, self.rng)
            acq_values: Callable[[FloatArray], FloatArray] = nei
            acq_grad: Callable[[FloatArray], tuple[FloatArray, FloatArray]] = nei.value_and_grad
        else:

            def acq_values(U: FloatArray) -> FloatArray:
                mu, var = model.predict_std_units(U)
                return log_ei(mu, np.sqrt(var), best)

            def acq_grad(U: FloatArray) -> tuple[FloatArray, FloatArray]:
                return log_ei_with_grad(*model.predict_with_grad(U), best)

        acq = np.where(self._near_failures(cand), -np.inf, acq_values(cand))
        order = np.argsort(-acq)
        starts = cand[order[: self.config.acq_restarts]]
        k = starts.shape[0]

        def f(flat: FloatArray) -> tuple[float, FloatArray]:
            lei, g = acq_grad(flat.reshape(k, d))
            return -float(np.sum(lei)), -g.ravel()

        res = minimize(f, starts.ravel(), jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * (k * d))
        opt = np.clip(res.x.reshape(k, d), 0.0, 1.0)
        both = np.vstack([opt, starts])
        acq2 = np.where(self._near_failures(both), -np.inf, acq_values(both))
        acq2 = np.where(np.isfinite(acq2), acq2, -np.inf)
        i = int(np.argmax(acq2))
        if not np.isfinite(acq2[i]):
            return self.rng.random(d)
        return np.asarray(both[i], dtype=float)

    def _near_failures(self, U: FloatArray, radius: float = 0.01) -> NDArray[np.bool_]:
        if not self.failures:
            return np.zeros(U.shape[0], dtype=bool)
        F = self.space.to_unit(np.array([self.space.to_array(f.params) for f in self.failures]))
        d2 = np.sum((U[:, None, :] - F[None, :, :]) ** 2, axis=2)
        return np.asarray(np.any(d2 < radius**2, axis=1))

    # --- tell ---------------------------------------------------------------------------------
    def tell(self, params: Mapping[str, float], value: float) -> None:
        """Record the (noisy) J measured with ``params``."""
        v = float(value)
        if not math.isfinite(v):
            raise EngineError(f"value must be finite, got {value!r}; use tell_failed() for a run without a result")
        x = self.space.to_array(params)
        p = self.space.to_params(x)
        self._drop_pending(x)
        self.observations.append(Observation(p, v))

    def tell_failed(self, params: Mapping[str, float], reason: str) -> None:
        """Record that ``params`` could not be evaluated (never re-proposed exactly).

        The next ask fits the model again, as after a :meth:`tell` (the failure does not change the model's
        data, but a fit cached from before it would make the engine's state depend on more than what was
        told, the random generator and the last hyperparameters: see :meth:`ask_state`)."""
        x = self.space.to_array(params)
        self._drop_pending(x)
        self.failures.append(Failure(self.space.to_params(x), str(reason)))
        self._gp_key = None

    def _drop_pending(self, x: FloatArray) -> None:
        for i, p in enumerate(self.pending):
            if np.allclose(self.space.to_array(p), x, rtol=0.0, atol=1e-12):
                del self.pending[i]
                return

    def ask_state(self) -> dict[str, Any]:
        """What the next asks depend on besides the tells, as JSON: the random generator and the last fitted
        hyperparameters (the start of the next fit). A campaign journals it with each proposal; replaying the
        tells and :meth:`restore_ask` then asks what the uninterrupted engine would have (every fit after a
        tell or a failure starts again from these, so no other cached state matters)."""
        h = self._gp.hyper
        return {
            "rng": self.rng.bit_generator.state,
            "hyper": None
            if h is None
            else {
                "lengthscales": h.lengthscales.tolist(),
                "outputscale": h.outputscale,
                "noise": h.noise,
                "mean": h.mean,
            },
        }

    def restore_ask(self, params: Mapping[str, float], state: Mapping[str, Any] | None) -> None:
        """Replay an ask from a journal: ``params`` become pending as :meth:`ask` left them, and the random
        generator and the last hyperparameters are those :meth:`ask_state` gave right after it (``None``: a
        journal without them; the engine then goes on from its own state, and later asks differ from the
        uninterrupted run's)."""
        x = self.space.to_array(params)
        self.pending.append(self.space.to_params(x))
        if not state:
            return
        try:
            self.rng.bit_generator.state = dict(state["rng"])
            h = state.get("hyper")
            hyper = (
                None
                if not h
                else Hyper(
                    np.asarray(h["lengthscales"], dtype=float),
                    float(h["outputscale"]),
                    float(h["noise"]),
                    float(h.get("mean", 0.0)),
                )
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise EngineError(f"malformed journaled optimizer state: {exc}") from exc
        self._gp = GP(self._gp.config, hyper=hyper)
        self._gp_key = None

    def forget_pending(self) -> None:
        """Drop every ask that was never told (e.g. abandoned trials)."""
        self.pending.clear()

    # --- the model's view ----------------------------------------------------------------------
    def predict(self, params: Mapping[str, float]) -> tuple[float, float]:
        """Posterior mean and standard deviation of J at ``params`` (with the output warp: the J at the
        warped posterior mean, i.e. the predictive median, and the std through the warp's slope)."""
        x = self.space.to_array(params)
        with _one_blas_thread():
            m, s = self._predict_j(self.space.to_unit(x)[None, :])
        return float(m[0]), float(s[0])

    def predict_unit(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and std at unit-cube points (m, d), in J units (for plots)."""
        return self._predict_j(np.atleast_2d(U))

    @property
    def hyper(self) -> Hyper | None:
        return self._gp.hyper

    def _minimize_bound(self, beta: float) -> FloatArray:
        """Unit-cube argmin of posterior mean + beta * std (multi-start L-BFGS-B), quantized."""
        gp = self._model()
        d = self.space.dim
        rng = np.random.default_rng(self.config.seed + 7919 * len(self.observations))
        cand = np.vstack([candidates(self.config.n_candidates, d, rng), gp.X])
        mu, var = gp.predict_std_units(cand)
        score = mu + beta * np.sqrt(var)
        starts = cand[np.argsort(score)[: max(1, self.config.acq_restarts)]]
        k = starts.shape[0]

        def f(flat: FloatArray) -> tuple[float, FloatArray]:
            m, s, dm, ds = gp.predict_with_grad(flat.reshape(k, d))
            return float(np.sum(m + beta * s)), (dm + beta * ds).ravel()

        res = minimize(f, starts.ravel(), jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * (k * d))
        pts = np.vstack([np.clip(res.x.reshape(k, d), 0.0, 1.0), starts])
        U = self.space.to_unit(self.space.from_unit(pts))
        m, v = gp.predict_std_units(U)
        return np.asarray(U[int(np.argmin(m + beta * np.sqrt(v)))], dtype=float)

    def recommend(self) -> Recommendation:
        """argmin over the domain of the posterior mean (+ recommend_beta · std), with its prediction."""
        with _one_blas_thread():
            return self._recommend()

    def _recommend(self) -> Recommendation:
        u = self._minimize_bound(self.config.recommend_beta)
        x = self.space.from_unit(u)
        m, s = self._predict_j(self.space.to_unit(x)[None, :])
        best = self.best_observed()
        return Recommendation(
            params=self.space.to_params(x),
            predicted_j=float(m[0]),
            predicted_std=float(s[0]),
            n_observations=len(self.observations),
            best_observed_params=dict(best.params) if best else None,
            best_observed_j=best.value if best else math.nan,
        )

    # --- state ------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "version": STATE_VERSION,
            "space": self.space.to_dict(),
            "config": self.config.to_dict(),
            "observations": [{"params": o.params, "value": o.value} for o in self.observations],
            "failures": [{"params": f.params, "reason": f.reason} for f in self.failures],
            "pending": [dict(p) for p in self.pending],
            "rng": self.rng.bit_generator.state,
            "hyper": self._gp.hyper.to_dict() if self._gp.hyper is not None else None,
        }

    def to_json(self) -> str:
        return json.dumps(self.state_dict())

    @classmethod
    def from_state_dict(cls, data: Mapping[str, Any]) -> Engine:
        if data.get("version") != STATE_VERSION:
            raise EngineError(f"saved engine state has version {data.get('version')!r}, expected {STATE_VERSION}")
        try:
            eng = cls(SearchSpace.from_dict(data["space"]), EngineConfig.from_dict(data["config"]))
            eng.observations = [Observation(dict(o["params"]), float(o["value"])) for o in data["observations"]]
            eng.failures = [Failure(dict(f["params"]), str(f["reason"])) for f in data["failures"]]
            eng.pending = [dict(p) for p in data["pending"]]
            eng.rng.bit_generator.state = data["rng"]
            if data.get("hyper"):
                eng._gp.hyper = Hyper.from_dict(data["hyper"])
        except (KeyError, TypeError) as exc:
            raise EngineError(f"malformed engine state: {exc}") from exc
        return eng

    @classmethod
    def from_json(cls, text: str) -> Engine:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise EngineError(f"engine state is not valid JSON: {exc}") from exc
        return cls.from_state_dict(data)
