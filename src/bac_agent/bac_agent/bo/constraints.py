"""Outcome constraints: limits on what a run measures besides J, modelled so that none is knowingly broken.

A run carries outcomes besides J (``peak_accel_z`` from the IMU, ``max_travel_mm`` from a travel sensor, ...);
the user sets limits on them (:class:`OutcomeLimit`, e.g. ``max_travel_mm <= 60``). Each constrained outcome
gets its own GP (the engine's Matérn-5/2 kernel, a learned constant mean, learned noise; MAP hyperparameters
from 3 runs on, the priors' modes before), and the probability that a run of a calibration breaks a limit is
``1 − Φ((limit − μ(x)) / σ(x))`` with μ the outcome's posterior mean there and σ² its posterior variance plus the
learned noise variance: a run is judged on what it measures, so a calibration whose true outcome sits just
inside the limit but whose runs scatter across it counts as risky. The engine

* never proposes a calibration whose probability of breaking any limit is above ``constraint_level`` (if no
  calibration is that safe, it proposes the one least likely to break a limit, and says so);
* weighs the acquisition by the probability that every limit holds (Gardner et al. 2014; Gelbart et al.
  2014), with the incumbent of noisy EI taken over the runs that kept every limit (Letham et al. 2019);
* recommends the argmin of J's posterior mean among calibrations within the same level.

With fewer than 3 values of an outcome, its spread is unknown; the model then assumes a standard deviation as
large as the distance from the values to the limit (or their spread if larger), so that after the first runs
only calibrations near them count as safe, and calibrations far from them as uncertain.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import log_ndtr, ndtr

from bac_agent.bo.gp import GP, GPConfig, GPError, Hyper
from bac_common.errors import BacError

FloatArray = NDArray[np.float64]

# the outcome's GP: a learned constant mean; a shorter lengthscale prior than J's (median 0.5 of the range instead
# of √2): an outcome such as the suspension travel can change fast across the box, and a limit is safety, so
# until runs show otherwise a calibration far from the driven ones counts as uncertain
# and a noise prior around exp(-2) of the outcome's variance (J's: exp(-4)): a travel or a peak measured on one
# run scatters more, relative to its spread over the box, than a KPI averaged over a window
# Its MAP fit starts from the prior's mode and the last fit only (no screened prior draws: an outcome such as a
# peak or a travel is one smooth response whose fits from a draw landed where the others did, and each start costs
# as much as J's: issue 23's latency with two limits)
OUTCOME_GP = GPConfig(mean="constant", ls_loc=math.log(0.5), noise_loc=-2.0, noise_scale=1.0, draws=0, restarts=0)
_LIMIT_RE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_.]*)\s*(<=|>=)\s*([-+0-9.eE]+)\s*$")


class ConstraintError(BacError, ValueError):
    """A malformed outcome limit."""


@dataclass(frozen=True)
class OutcomeLimit:
    """``name <= bound`` (upper) or ``name >= bound`` (lower) on an outcome of every run."""

    name: str
    bound: float
    upper: bool = True  # True: the outcome must stay <= bound; False: >= bound

    def __post_init__(self) -> None:
        if not self.name or not math.isfinite(self.bound):
            raise ConstraintError(f"an outcome limit needs a name and a finite bound, got {self.name!r} {self.bound!r}")

    @classmethod
    def parse(cls, text: str) -> OutcomeLimit:
        """From ``"max_travel_mm <= 60"`` or ``"peak_accel_z>=-1"``."""
        m = _LIMIT_RE.match(str(text))
        if not m:
            raise ConstraintError(
                f"cannot read the outcome limit {text!r}: write it as NAME<=VALUE or NAME>=VALUE, "
                "e.g. max_travel_mm<=60 or peak_accel_z<=6.5"
            )
        try:
            bound = float(m.group(3))
        except ValueError as exc:
            raise ConstraintError(f"outcome limit {text!r}: {m.group(3)!r} is not a number") from exc
        return cls(m.group(1), bound, m.group(2) == "<=")

    @classmethod
    def from_spec(cls, spec: Any) -> OutcomeLimit:
        if isinstance(spec, OutcomeLimit):
            return spec
        if isinstance(spec, str):
            return cls.parse(spec)
        if isinstance(spec, Mapping):
            try:
                return cls(str(spec["name"]), float(spec["bound"]), bool(spec.get("upper", True)))
            except (KeyError, TypeError, ValueError) as exc:
                raise ConstraintError(f"malformed outcome limit {dict(spec)!r}: {exc}") from exc
        raise ConstraintError(f"cannot build an outcome limit from {spec!r}")

    def violated(self, value: float) -> bool:
        """True when a measured value breaks the limit (a missing, non-finite value breaks nothing)."""
        if not math.isfinite(value):
            return False
        return value > self.bound if self.upper else value < self.bound

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "bound": self.bound, "upper": self.upper}

    def __str__(self) -> str:
        return f"{self.name} {'<=' if self.upper else '>='} {self.bound:g}"


def parse_limits(specs: Sequence[Any]) -> tuple[OutcomeLimit, ...]:
    limits = tuple(OutcomeLimit.from_spec(s) for s in specs)
    seen = set()
    for lim in limits:
        key = (lim.name, lim.upper)
        if key in seen:
            raise ConstraintError(f"two limits of the same kind on {lim.name!r}: give one")
        seen.add(key)
    return limits


class OutcomeModel:
    """The GP of one constrained outcome (see the module doc)."""

    def __init__(self, limit: OutcomeLimit) -> None:
        self.limit = limit
        self.gp = GP(OUTCOME_GP)
        self.n = 0

    def fit(self, X: FloatArray, values: FloatArray, rng: np.random.Generator) -> None:
        ok = np.isfinite(values)
        X, v = X[ok], values[ok]
        self.n = int(v.size)
        if self.n == 0:
            return
        if self.n >= 3 and float(np.std(v)) > 1e-12 * max(1.0, abs(float(np.mean(v)))):
            self.gp.fit(X, v, rng)
            return
        mean = float(np.mean(v))
        spread = max(float(np.std(v)), abs(self.limit.bound - mean), 1e-6 * max(1.0, abs(mean)))
        loc, _ = self.gp._prior(X.shape[1])
        self.gp = GP(OUTCOME_GP).condition(X, v, Hyper.from_vector(loc), scaling=(mean, spread))

    @property
    def fitted(self) -> bool:
        return self.n > 0 and self.gp.fitted

    def _t(self, mu: FloatArray, sd: FloatArray) -> FloatArray:
        """Standardized margin to the limit: Φ(t) is the probability that the limit holds."""
        gp = self.gp
        b = (self.limit.bound - gp.y_mean) / gp.y_std
        return np.asarray((b - mu) / sd if self.limit.upper else (mu - b) / sd, dtype=float)

    def _noise(self) -> float:
        h = self.gp.hyper
        return float(h.noise) if h is not None else 0.0

    def prob_violation(self, U: FloatArray, measured: bool = True) -> FloatArray:
        """The probability that a run here *measures* the outcome beyond the limit (latent and noise variance);
        ``measured`` False: that the calibration's true outcome is beyond it (the latent variance alone)."""
        if not self.fitted:
            return np.zeros(np.atleast_2d(U).shape[0])
        mu, var = self.gp.predict_std_units(U)
        noise = self._noise() if measured else 0.0
        return np.asarray(1.0 - ndtr(self._t(mu, np.sqrt(np.maximum(var + noise, 1e-18)))), dtype=float)

    def log_feasible_and_grad(self, U: FloatArray, measured: bool = True) -> tuple[FloatArray, FloatArray]:
        U = np.atleast_2d(U)
        if not self.fitted:
            return np.zeros(U.shape[0]), np.zeros_like(U)
        mu, sd_f, dmu, dsd_f = self.gp.predict_with_grad(U)
        sd = np.sqrt(np.maximum(sd_f**2 + (self._noise() if measured else 0.0), 1e-18))
        dsd = dsd_f * (sd_f / sd)[:, None]
        t = self._t(mu, sd)
        sign = 1.0 if self.limit.upper else -1.0
        # t = sign (b - mu) / sd: dt = (-sign dmu - t dsd) / sd
        dt = (-sign * dmu - t[:, None] * dsd) / sd[:, None]
        lf = log_ndtr(t)
        ratio = np.exp(-0.5 * t * t - 0.5 * math.log(2.0 * math.pi) - lf)  # φ(t) / Φ(t)
        return np.asarray(lf, dtype=float), np.asarray(ratio[:, None] * dt, dtype=float)

    def predict(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and std of the outcome, in its units."""
        if not self.fitted:
            n = np.atleast_2d(U).shape[0]
            return np.full(n, math.nan), np.full(n, math.nan)
        return self.gp.predict(U)


class OutcomeModels:
    """Every constrained outcome's model, fitted together from the observations."""

    def __init__(self, limits: Sequence[OutcomeLimit], level: float) -> None:
        if not 0.0 < level < 1.0:
            raise ConstraintError(f"constraint_level must be in (0, 1), got {level}")
        self.limits = tuple(limits)
        self.level = float(level)
        self.models = [OutcomeModel(lim) for lim in self.limits]

    def __bool__(self) -> bool:
        return bool(self.limits)

    def fit(self, X: FloatArray, outcomes: Sequence[Mapping[str, float]], rng: np.random.Generator) -> None:
        for m in self.models:
            v = np.array([float(o.get(m.limit.name, math.nan)) for o in outcomes], dtype=float)
            try:
                m.fit(X, v, rng)
            except GPError:
                m.n = 0

    def prob_violation(self, U: FloatArray, measured: bool = True) -> FloatArray:
        """(m, c): the probability that each limit is broken at each point (by a run's measurement; ``measured``
        False: by the calibration's true outcome)."""
        U = np.atleast_2d(U)
        if not self.models:
            return np.zeros((U.shape[0], 0))
        return np.column_stack([m.prob_violation(U, measured) for m in self.models])

    def allowed(self, U: FloatArray, measured: bool = True) -> NDArray[np.bool_]:
        """Points whose probability of breaking any limit is at most the level."""
        p = self.prob_violation(U, measured)
        return np.asarray(np.all(p <= self.level, axis=1)) if p.size else np.ones(np.atleast_2d(U).shape[0], bool)

    def log_feasible_and_grad(self, U: FloatArray, measured: bool = True) -> tuple[FloatArray, FloatArray]:
        """log P(every limit holds) (independent outcomes) and its gradient."""
        U = np.atleast_2d(U)
        v, g = np.zeros(U.shape[0]), np.zeros_like(U)
        for m in self.models:
            vm, gm = m.log_feasible_and_grad(U, measured)
            v, g = v + vm, g + gm
        return v, g

    def observed_ok(self, outcomes: Sequence[Mapping[str, float]]) -> NDArray[np.bool_]:
        """Which observations kept every limit (as measured)."""
        return np.array(
            [not any(lim.violated(float(o.get(lim.name, math.nan))) for lim in self.limits) for o in outcomes],
            dtype=bool,
        )

    def describe(self, U: FloatArray) -> dict[str, dict[str, float]]:
        """Predicted mean, std and probability of breaking the limit at one point, per outcome."""
        U = np.atleast_2d(U)
        out = {}
        for m in self.models:
            mu, sd = m.predict(U)
            out[str(m.limit)] = {
                "mean": float(mu[0]),
                "std": float(sd[0]),
                "p_violation": float(m.prob_violation(U)[0]),  # a run here measures beyond the limit
                "p_violation_true": float(m.prob_violation(U, measured=False)[0]),  # its true outcome is beyond
            }
        return out


def violations(limits: Sequence[OutcomeLimit], outcomes: Mapping[str, float]) -> list[str]:
    """The limits a run's measured outcomes break, as text (``"max_travel_mm <= 60 (measured 64.2)"``)."""
    out = []
    for lim in limits:
        v = float(outcomes.get(lim.name, math.nan))
        if lim.violated(v):
            out.append(f"{lim} (measured {v:.4g})")
    return out


__all__ = ["ConstraintError", "OutcomeLimit", "OutcomeModel", "OutcomeModels", "parse_limits", "violations"]
