"""Baselines with the engine's interface: a full grid (the paper's exhaustive search) and random search.

Their recommendation is the best *observed* point (what an exhaustive search
reports); ``predicted_j`` is its observed J and ``predicted_std`` is NaN.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from bac_agent.bo.design import grid
from bac_agent.bo.engine import (
    KIND_GRID,
    KIND_RANDOM,
    EngineError,
    Failure,
    Observation,
    Recommendation,
    Suggestion,
)
from bac_agent.bo.space import SearchSpace


class _Baseline:
    kind = KIND_RANDOM

    def __init__(self, space: Any, budget: int, seed: int = 0) -> None:
        self.space = SearchSpace.from_spec(space)
        self.budget = int(budget)
        self.seed = int(seed)
        self.observations: list[Observation] = []
        self.failures: list[Failure] = []
        self.pending: list[dict[str, float]] = []

    @property
    def names(self) -> tuple[str, ...]:
        return self.space.names

    @property
    def n_trials(self) -> int:
        return len(self.observations) + len(self.failures)

    @property
    def done(self) -> bool:
        return self.n_trials >= self.budget

    def _point(self, k: int) -> np.ndarray:
        raise NotImplementedError

    def ask(self) -> dict[str, float]:
        return self.ask_with_info().params

    def ask_with_info(self) -> Suggestion:
        k = self.n_trials + len(self.pending)
        params = self.space.to_params(self.space.from_unit(self._point(k)))
        self.pending.append(dict(params))
        return Suggestion(params, self.kind)

    def _drop_pending(self, params: Mapping[str, float]) -> None:
        x = self.space.to_array(params)
        for i, p in enumerate(self.pending):
            if np.allclose(self.space.to_array(p), x, rtol=0.0, atol=1e-12):
                del self.pending[i]
                return

    def tell(self, params: Mapping[str, float], value: float, outcomes: Mapping[str, float] | None = None) -> None:
        if not math.isfinite(float(value)):
            raise EngineError(f"value must be finite, got {value!r}")
        self._drop_pending(params)
        out = {str(k): float(v) for k, v in (outcomes or {}).items()}
        self.observations.append(Observation(self.space.to_params(self.space.to_array(params)), float(value), out))

    def tell_failed(self, params: Mapping[str, float], reason: str) -> None:
        self._drop_pending(params)
        self.failures.append(Failure(self.space.to_params(self.space.to_array(params)), str(reason)))

    def ask_state(self) -> dict[str, Any]:
        """Nothing: point k depends only on the seed and k."""
        return {}

    def restore_ask(self, params: Mapping[str, float], state: Mapping[str, Any] | None) -> None:
        """Replay an ask from a journal: ``params`` become pending as :meth:`ask` left them."""
        self.pending.append(self.space.to_params(self.space.to_array(params)))

    def best_observed(self) -> Observation | None:
        return min(self.observations, key=lambda o: o.value) if self.observations else None

    def predict(self, params: Mapping[str, float]) -> tuple[float, float]:
        return math.nan, math.nan

    def recommend(self) -> Recommendation:
        best = self.best_observed()
        if best is None:
            raise EngineError("nothing has been told yet: tell() at least one result first")
        return Recommendation(
            dict(best.params),
            best.value,
            math.nan,
            len(self.observations),
            dict(best.params),
            best.value,
            rule="best_run",  # no model: the run with the best measured J
        )


class GridStrategy(_Baseline):
    """``size`` levels per dimension (0 and 1 included), visited in order: budget = size^d."""

    kind = KIND_GRID

    def __init__(self, space: Any, size: int, seed: int = 0) -> None:
        sp = SearchSpace.from_spec(space)
        self._grid = grid(size, sp.dim)
        super().__init__(sp, self._grid.shape[0], seed)

    def _point(self, k: int) -> np.ndarray:
        if k >= self._grid.shape[0]:
            raise EngineError(f"the grid has {self._grid.shape[0]} points; all were asked")
        return np.asarray(self._grid[k])


class RandomStrategy(_Baseline):
    """Uniformly random points (reproducible: point k depends only on the seed and k)."""

    def _point(self, k: int) -> np.ndarray:
        return np.random.default_rng([self.seed, k]).random(self.space.dim)
