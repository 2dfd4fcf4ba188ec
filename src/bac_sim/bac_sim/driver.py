"""The driver: speed profiles of a batch of runs (cruise control with its error) and start points.

A :class:`Drive` holds, for each run of a batch, the speed of the car (m/s) at shared knot times
(piecewise linear in between) and the position of its front axle along the road (m), exactly
integrated (piecewise quadratic). The driver model draws them: each run the cruise control holds the
target speed with a constant set-point error and a slow fluctuation (an Ornstein-Uhlenbeck process),
and the run starts at a slightly different point, so that runs must be cut and aligned.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bac_sim.errors import ScenarioError

FloatArray = np.ndarray[Any, Any]
KNOT_DT = 0.1  # s, resolution of the speed profiles


@dataclass(frozen=True)
class Drive:
    """Speed and position profiles of ``batch`` runs on shared knot times ``t`` (K,)."""

    t: FloatArray  # (K,) s, from 0
    v: FloatArray  # (K, B) m/s
    s: FloatArray  # (K, B) m, front-axle position along the road

    @property
    def batch(self) -> int:
        return int(self.v.shape[1])

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def _locate(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        j = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 2)
        return j, t - self.t[j]

    def position(self, t: FloatArray) -> FloatArray:
        """Front-axle position (n, B) at times ``t`` (n,)."""
        j, tau = self._locate(np.asarray(t, dtype=float))
        h = (self.t[j + 1] - self.t[j])[:, None]
        v0 = self.v[j]
        acc = (self.v[j + 1] - v0) / h
        tau = tau[:, None]
        return np.asarray(self.s[j] + v0 * tau + 0.5 * acc * tau * tau)

    def speed(self, t: FloatArray) -> FloatArray:
        j, tau = self._locate(np.asarray(t, dtype=float))
        h = (self.t[j + 1] - self.t[j])[:, None]
        return np.asarray(self.v[j] + (self.v[j + 1] - self.v[j]) * (tau[:, None] / h))

    def time_at(self, s_target: float | FloatArray) -> FloatArray:
        """Time (B,) at which each run's front axle reaches ``s_target`` (exact on the quadratic)."""
        target = np.broadcast_to(np.asarray(s_target, dtype=float), (self.batch,))
        if np.any(target < self.s[0]) or np.any(target > self.s[-1]):
            raise ScenarioError("a run does not reach the requested distance within its duration")
        out = np.empty(self.batch)
        for b in range(self.batch):  # B root finds on a monotone profile, not a per-sample loop
            j = int(np.clip(np.searchsorted(self.s[:, b], target[b], side="right") - 1, 0, self.t.size - 2))
            h = self.t[j + 1] - self.t[j]
            v0 = self.v[j, b]
            acc = (self.v[j + 1, b] - v0) / h
            d = target[b] - self.s[j, b]
            tau = d / v0 if abs(acc) < 1e-12 else (-v0 + np.sqrt(max(v0 * v0 + 2 * acc * d, 0.0))) / acc
            out[b] = self.t[j] + tau
        return out


def constant_drive(speed: float | FloatArray, start: float | FloatArray, duration: float) -> Drive:
    """Runs at constant ``speed`` (scalar or (B,)) from ``start`` (scalar or (B,)) for ``duration`` s."""
    v = np.atleast_1d(np.asarray(speed, dtype=float))
    s0 = np.atleast_1d(np.asarray(start, dtype=float))
    v, s0 = np.broadcast_arrays(v, s0)
    if np.any(v <= 0):
        raise ScenarioError("speeds must be > 0")
    t = np.array([0.0, float(duration)])
    return Drive(t, np.vstack([v, v]).astype(float), np.vstack([s0, s0 + v * duration]).astype(float))


@dataclass(frozen=True)
class DriverModel:
    """Run-to-run variability of a human driver with cruise control.

    Defaults: the set-point error of a cruise control read off a speedometer (0.3 km/h, 1 sigma),
    slow speed fluctuation of 0.15 km/h with a 4 s correlation time (gradients, wind), start points
    scattered by 5 m. ``bad_run_probability``: chance that a run is driven ``bad_speed_factor`` too
    slow (a run the segmenter must reject).
    """

    speed_error_std: float = 0.3 / 3.6  # m/s
    speed_fluctuation_std: float = 0.15 / 3.6  # m/s
    speed_fluctuation_tau: float = 4.0  # s
    start_offset_std: float = 5.0  # m
    bad_run_probability: float = 0.0
    bad_speed_factor: float = 0.85

    def __post_init__(self) -> None:
        for name in ("speed_error_std", "speed_fluctuation_std", "start_offset_std"):
            if not getattr(self, name) >= 0:
                raise ScenarioError(f"driver {name} must be >= 0")
        if not self.speed_fluctuation_tau > 0:
            raise ScenarioError("driver speed_fluctuation_tau must be > 0")
        if not 0 <= self.bad_run_probability <= 1:
            raise ScenarioError("bad_run_probability must be in [0, 1]")
        if not 0 < self.bad_speed_factor <= 2:
            raise ScenarioError("bad_speed_factor must be in (0, 2]")

    def draw(
        self, target_speed: float, nominal_start: float, duration: float, batch: int, rng: np.random.Generator
    ) -> tuple[Drive, FloatArray]:
        """Speed profiles of ``batch`` runs; also returns which runs are bad (B,) bool."""
        k = int(np.ceil(duration / KNOT_DT)) + 1
        t = np.arange(k) * KNOT_DT
        set_point = target_speed + self.speed_error_std * rng.standard_normal(batch)
        bad = rng.random(batch) < self.bad_run_probability
        set_point = np.where(bad, target_speed * self.bad_speed_factor, set_point)
        # Ornstein-Uhlenbeck fluctuation, exact discretization on the knots
        phi = np.exp(-KNOT_DT / self.speed_fluctuation_tau)
        noise = rng.standard_normal((k, batch)) * self.speed_fluctuation_std * np.sqrt(1 - phi * phi)
        fluct = np.empty((k, batch))
        fluct[0] = self.speed_fluctuation_std * rng.standard_normal(batch)
        for i in range(1, k):  # K ~ duration / 0.1 s knots, vectorized over the batch
            fluct[i] = phi * fluct[i - 1] + noise[i]
        v = np.maximum(set_point[None, :] + fluct, 0.2 * target_speed)
        start = nominal_start + self.start_offset_std * rng.standard_normal(batch)
        # exact integral of the piecewise-linear speed
        s = np.vstack([np.zeros(batch), np.cumsum(0.5 * (v[1:] + v[:-1]) * KNOT_DT, axis=0)]) + start
        return Drive(t, v, s), bad
