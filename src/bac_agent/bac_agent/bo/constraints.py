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

**Far from the runs** (``far_sd``, the engine's ``limit_far_sd``; since 2026-11-25): the constant-mean GP reverts to
the runs' mean away from them, and the runs cluster where J is good, inside the limit, so that a calibration far from
every run was predicted safe where the outcome had risen beyond the limit (issue 23's tuning instances: runs 0.2 or
more from every run broke the limit 53 times in 152 at a summed predicted probability of 3.2). Without a source the
latent sd is multiplied by ``1 + far_sd · ρ``, ρ = σ²(x) / σ_f² the posterior variance over the kernel's (0 at a run,
1 far from every run): the model near the runs is unchanged, its tails far from them heavier.

**The retreat** (no run has kept every limit yet and no calibration is within the level, e.g. after an unsafe
first run; since 2026-11-24): the calibration least likely to break a limit under the outcome's model plus a
linear trend with its slopes integrated out (``RETREAT_TREND_SD``), so that the runs' values give a direction;
under the constant-mean model alone the least risky calibration is simply the one farthest from the runs.

**What the simulator knows of an outcome** (``OutcomeModel(limit, source)``; issue 23): a
:class:`~bac_agent.bo.prior.SourceSurface` of the outcome over the same unit cube (the simulation phase's travel,
the nominal car's peaks, an earlier campaign's measurements) is the outcome GP's prior mean ``a + b · s(x)``, with
``s`` the source's outcome standardized by its own mean and spread and the car's values put on that scale. Unlike
J's transfer prior, the offset matters here (a limit is a level, not a shape): ``a ~ N(0, offset_sd²)``,
``b ~ N(1, scale_sd²)``, both posteriors given the car's values under the residual's kernel, a GP residual
(variance prior median ``residual_os``) for what the source does not explain. Before the first run the model is
the source itself with the coefficients' and the residual's prior variance: the first proposal already keeps away
from where the simulator says a limit breaks. The coefficients' posterior variance is added to the residual's
where the runs do not pin the outcome down (Rasmussen & Williams 2006, eq. 2.42). The source is itself a GP
posterior, uncertain where it had no points (an earlier campaign's runs cluster near its optimum): its posterior
covariance C_s, scaled by β² = E[b²], is part of the outcome's covariance, k(x, x') + σa² + σb² s(x) s(x') +
β² C_s(x, x') (exact for a + b s(x) + β (S(x) − s(x)) + residual, S the source's unknown true outcome; since
2026-11-24), so that a calibration where the source knew nothing is as uncertain as the source is there.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.special import log_ndtr, ndtr
from scipy.stats import qmc

from bac_agent.bo.gp import GP, GPConfig, GPError, Hyper
from bac_agent.bo.kernel import matern52_dr2_factor, matern52_from_r2, sq_dist
from bac_agent.bo.prior import PriorTrend, SourceSurface
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
OUTCOME_GP = GPConfig(
    mean="constant", ls_loc=math.log(0.5), noise_loc=-2.0, noise_scale=1.0, draws=0, restarts=0, ls_average=0.0
)

# an outcome's source (the simulator's travel, peaks): priors of the trend a + b·s(x) and of the residual, in the
# source's standardized units (its points' mean 0, spread 1); chosen on the tuning split of bench/outcome_limits.py
# (issue 23; the nominal car against the drawn bump_c1 cars: offsets up to 0.7 of the nominal travel's spread,
# scales 0.93-1.5, what a fitted a + b·s leaves 0.1-0.45 of it: docs/agent.md)
OUTCOME_PRIOR_OFFSET_SD = 0.5
OUTCOME_PRIOR_SCALE_SD = 0.3
OUTCOME_PRIOR_RESIDUAL_OS = 0.1
# the residual's GP under a source: the same kernel priors, its variance around OUTCOME_PRIOR_RESIDUAL_OS of the
# source's spread (the noise prior is relative to the source's spread too)
_SOURCE_OUTCOME_GP = replace(OUTCOME_GP, os_loc=math.log(OUTCOME_PRIOR_RESIDUAL_OS))
# a source's own posterior variance below this (its standardized units: a hundredth of its spread in sd) is taken
# as 0: a dense noise-free source's variance is round-off there (k(x, x) − k K⁻¹ k of two numbers ~ its outputscale,
# with K's condition number up to ~1e10), which would only add noise to the model and its gradient
SOURCE_VAR_FLOOR = 1e-4
# E[b²] under b's prior: before the first run, the factor of the source's own posterior covariance
_PRIOR_B2 = 1.0 + OUTCOME_PRIOR_SCALE_SD**2
# the retreat (no run has kept every limit yet and no calibration is within the level): the calibration least likely
# to break a limit under the outcome's model plus a linear trend whose slopes, N(0, RETREAT_TREND_SD²) per unit of
# the box in the outcome's few-run units (the spread as before 3 runs), are integrated out (a linear kernel): the
# runs' values give the retreat a direction. The constant-mean model's least risky calibration is the one farthest
# from the runs, a coin toss that kept breaking the limit run after run (issue 23, bench/outcome_limits.py's tuning
# instances with 12 seeds: 18.2 % of the runs broke the limit, 12.2 % with 2 or 4; docs/agent.md); 0: off
RETREAT_TREND_SD = 2.0
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


class _SourceCov:
    """The source surface's own posterior covariance C_s (its GP's latent covariance given its points, in its
    standardized units) and its gradients: what the source does not know, e.g. far from a clustered campaign's
    runs (issue 23: such a source was taken as if known everywhere)."""

    def __init__(self, source: SourceSurface) -> None:
        g = source._gp  # type: ignore[attr-defined]
        h = g.hyper
        self.Xs = np.asarray(g.X, dtype=float)
        self.ls = np.asarray(h.lengthscales, dtype=float)
        self.os = float(h.outputscale)
        self.il2 = 1.0 / self.ls**2
        self.L = np.asarray(g._L, dtype=float)
        self.Kinv = np.asarray(sla.cho_solve((self.L, True), np.eye(self.Xs.shape[0]), check_finite=False))
        self._runs: tuple[FloatArray, FloatArray] | None = None  # (X, k_s(X, Xs) K_s⁻¹) of the last runs
        # a source whose variance is below the floor everywhere (a dense noise-free one: round-off) has no C_s at
        # all: its round-off off the diagonal, with the floor taken off the diagonal only, would leave C_s
        # indefinite (min eigenvalue -1e-7: outside review, 2026-11-24). Probed at 1024 Sobol points, the corners
        # (d <= 10) and the source's own points
        d = self.Xs.shape[1]
        probe = [qmc.Sobol(d, scramble=True, seed=0).random(1024), self.Xs]
        if d <= 10:
            probe.append(np.array(np.meshgrid(*[[0.0, 1.0]] * d)).reshape(d, -1).T)
        Kp = self._k(np.vstack(probe), self.Xs)[0]
        self.zero = bool(np.max(self.os - np.sum((Kp @ self.Kinv) * Kp, axis=1)) <= SOURCE_VAR_FLOOR)

    def _k(self, A: FloatArray, B: FloatArray) -> tuple[FloatArray, FloatArray]:
        r2 = sq_dist(A, B, self.ls)
        return matern52_from_r2(r2, self.os), matern52_dr2_factor(r2, self.os)

    def _at_runs(self, X: FloatArray) -> FloatArray:
        if self._runs is None or self._runs[0].shape != X.shape or not np.array_equal(self._runs[0], X):
            kX = self._k(X, self.Xs)[0]
            self._runs = (X.copy(), np.asarray(sla.cho_solve((self.L, True), kX.T, check_finite=False).T, dtype=float))
        return self._runs[1]

    def cov_runs(self, X: FloatArray) -> FloatArray:
        """C_s(X, X) (its diagonal less the round-off floor, as ``var_with_grad``; 0 for a source whose variance is
        below the floor everywhere)."""
        if self.zero:
            return np.zeros((X.shape[0], X.shape[0]))
        A = self._at_runs(X)
        C = self._k(X, X)[0] - A @ self._k(self.Xs, X)[0]
        C = 0.5 * (C + C.T)
        np.fill_diagonal(C, np.maximum(np.diag(C) - SOURCE_VAR_FLOOR, 0.0))
        return np.asarray(C, dtype=float)

    def var_with_grad(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """C_s(x, x) − SOURCE_VAR_FLOOR, at least 0, at the rows of ``U`` and its gradient: (q,), (q, d)."""
        if self.zero:
            return np.zeros(U.shape[0]), np.zeros_like(U)
        Kq, F = self._k(U, self.Xs)
        V = Kq @ self.Kinv
        var = self.os - np.sum(V * Kq, axis=1) - SOURCE_VAR_FLOOR
        FV = F * V
        dvar = 2.0 * (U * FV.sum(axis=1)[:, None] - FV @ self.Xs) * self.il2
        dvar[var <= 0.0] = 0.0
        return np.asarray(np.maximum(var, 0.0), dtype=float), np.asarray(dvar, dtype=float)

    def cross(self, U: FloatArray, X: FloatArray) -> tuple[FloatArray, Any]:
        """C_s(U, X) (q, n), and a function that contracts its gradient in U with weights (q, n) or (n,):
        Σ_j w_j ∂C_s(x_q, X_j)/∂x_q, (q, d), without the (q, n, d) tensor (and its (q, n, m, d) sum)."""
        if self.zero:
            return np.zeros((U.shape[0], X.shape[0])), lambda W: np.zeros_like(U)
        A = self._at_runs(X)  # (n, m) = k_s(X, Xs) K_s⁻¹
        Kq, Fq = self._k(U, self.Xs)
        KX, FX = self._k(U, X)
        C = KX - Kq @ A.T

        def contract(W: FloatArray) -> FloatArray:
            # ∂C_s(x, X_j)/∂x = −F_X,j (x − X_j) il2 + Σ_i F_i A[j, i] (x − Xs_i) il2
            FW = FX * W
            B = Fq * (W @ A)  # (q, m): Σ_j w_j F_i A[j, i]
            out = -(U * FW.sum(axis=1)[:, None] - FW @ X) + (U * B.sum(axis=1)[:, None] - B @ self.Xs)
            return np.asarray(out * self.il2, dtype=float)

        return np.asarray(C, dtype=float), contract


class OutcomeModel:
    """The GP of one constrained outcome (see the module doc); ``source``: what the simulator knows of it."""

    def __init__(self, limit: OutcomeLimit, source: SourceSurface | None = None, far_sd: float = 0.0) -> None:
        self.limit = limit
        self.source = source
        self.far_sd = float(far_sd)  # far from the runs the latent sd times 1 + far_sd * rho (no source; module doc)
        self.gp = GP(OUTCOME_GP if source is None else _SOURCE_OUTCOME_GP)
        self.n = 0
        self._coef_cov: FloatArray | None = None  # posterior covariance of (a, b) with a source
        self._Kinv_H = np.zeros((0, 2))  # K⁻¹ H, H = (1, s) at the runs
        self._H = np.zeros((0, 2))
        self._Kinv = np.zeros((0, 0))  # K⁻¹ of the runs' covariance (residual + β² C_s + noise)
        self._alpha = np.zeros(0)  # K⁻¹ (z − H β̂)
        self._beta2 = _PRIOR_B2  # E[b²]: the factor of the source's own covariance
        self._src_cov: _SourceCov | None = None
        self._data: tuple[FloatArray, FloatArray] | None = None

    def _source_cov(self) -> _SourceCov:
        assert self.source is not None
        if self._src_cov is None:
            self._src_cov = _SourceCov(self.source)
        return self._src_cov

    def fit(self, X: FloatArray, values: FloatArray, rng: np.random.Generator) -> None:
        ok = np.isfinite(values)
        X, v = X[ok], values[ok]
        self.n = int(v.size)
        self._data = (X, v) if self.n else None
        if self.source is not None:
            self._fit_with_source(X, v, rng)
            return
        if self.n == 0:
            return
        if self.n >= 3 and float(np.std(v)) > 1e-12 * max(1.0, abs(float(np.mean(v)))):
            self.gp.fit(X, v, rng)
            return
        mean, spread = self._few_run_scale(v)
        loc, _ = self.gp._prior(X.shape[1])
        self.gp = GP(OUTCOME_GP).condition(X, v, Hyper.from_vector(loc), scaling=(mean, spread))

    def _few_run_scale(self, v: FloatArray) -> tuple[float, float]:
        """The values' mean and the spread assumed with few of them: their distance to the limit when larger than
        their scatter (so that calibrations far from the runs count as uncertain)."""
        mean = float(np.mean(v))
        return mean, max(float(np.std(v)), abs(self.limit.bound - mean), 1e-6 * max(1.0, abs(mean)))

    def retreat_prob(self, U: FloatArray) -> FloatArray:
        """The probability that a run at the rows of ``U`` breaks the limit under the model with a linear trend (see
        RETREAT_TREND_SD; the outcome's own model with a source, before a run, or with the trend off)."""
        U = np.atleast_2d(U)
        if self.source is not None or self._data is None or RETREAT_TREND_SD <= 0.0:
            return self.prob_violation(U)
        X, v = self._data
        mean, spread = self._few_run_scale(v)
        z = (v - mean) / spread
        loc, _ = GP(OUTCOME_GP)._prior(X.shape[1])
        h = Hyper.from_vector(loc)
        c = X.mean(axis=0)
        sw2 = RETREAT_TREND_SD**2
        n = X.shape[0]
        K = matern52_from_r2(sq_dist(X, X, h.lengthscales), h.outputscale) + sw2 * (X - c) @ (X - c).T
        K.flat[:: n + 1] += h.noise + 1e-10
        Kinv = sla.cho_solve(sla.cho_factor(K, lower=True), np.eye(n), check_finite=False)
        ks = matern52_from_r2(sq_dist(U, X, h.lengthscales), h.outputscale) + sw2 * (U - c) @ (X - c).T
        kss = h.outputscale + sw2 * np.sum((U - c) ** 2, axis=1)
        one = np.ones(n)
        a = float(one @ Kinv @ one)
        beta = float(one @ Kinv @ z) / a
        V = ks @ Kinv
        mu = beta + V @ (z - beta)
        R = 1.0 - V @ one
        var = kss - np.sum(V * ks, axis=1) + R * R / a
        sd = np.sqrt(np.maximum(var, 1e-12) + h.noise)
        b = (self.limit.bound - mean) / spread
        t = (b - mu) / sd if self.limit.upper else (mu - b) / sd
        return np.asarray(1.0 - ndtr(t), dtype=float)

    def _fit_with_source(self, X: FloatArray, v: FloatArray, rng: np.random.Generator) -> None:
        """The residual's kernel (MAP from 3 values, the prior's mode before) and the posterior of (a, b).

        The covariance of the car's values is the residual's kernel plus the source's own posterior covariance
        scaled by β² = E[b²] (``_SourceCov``): where the source had no runs (a clustered campaign) its value is
        uncertain, and so is the trend built on it."""
        src = self.source
        assert src is not None
        self._coef_cov = None
        if self.n == 0:
            return  # the source alone (see _moments)
        gp = GP(_SOURCE_OUTCOME_GP, hyper=self.gp.hyper)
        gp._set_data(X, v, (src.loc, src.scale))
        s = src.standardized(gp.X)
        if self.n >= 3:
            gp._offset = s  # the residual's kernel on what the source (a = 0 … profiled, b = 1) leaves
            h = Hyper.from_vector(gp._map_hyper(rng))
            gp._offset = 0.0
        else:
            loc, _ = gp._prior(X.shape[1])
            h = Hyper.from_vector(loc)
        n = gp.X.shape[0]
        H = np.column_stack([np.ones(n), s])
        gp.hyper = replace(h, mean=0.0, bowl=None, prior=None)
        gp._factorize(refit_mean=False)  # the residual kernel's Cholesky factor (the trend is set below)
        prior_prec = np.diag([1.0 / OUTCOME_PRIOR_OFFSET_SD**2, 1.0 / OUTCOME_PRIOR_SCALE_SD**2])
        b0 = prior_prec @ np.array([0.0, 1.0])
        # first the scale's posterior without the source's uncertainty: β² = E[b²] = b̄² + var(b), then the
        # coefficients' posterior under the residual kernel + β² C_s (the source's posterior covariance)
        Kinv_H = sla.cho_solve((gp._L, True), H, check_finite=False)
        cov = np.linalg.inv(H.T @ Kinv_H + prior_prec)
        beta = cov @ (Kinv_H.T @ gp._z + b0)
        self._beta2 = float(beta[1] ** 2 + cov[1, 1])
        K = matern52_from_r2(sq_dist(gp.X, gp.X, h.lengthscales), h.outputscale)
        K += self._beta2 * self._source_cov().cov_runs(gp.X)
        K.flat[:: n + 1] += h.noise + 1e-10 * h.outputscale
        try:
            L = np.linalg.cholesky(K)
        except np.linalg.LinAlgError as exc:
            raise GPError(f"the outcome model's covariance is not positive definite: {exc}") from exc
        Kinv = sla.cho_solve((L, True), np.eye(n), check_finite=False)
        Kinv_H = Kinv @ H
        cov = np.linalg.inv(H.T @ Kinv_H + prior_prec)
        beta = cov @ (Kinv_H.T @ gp._z + b0)
        gp.hyper = replace(h, mean=0.0, bowl=None, prior=PriorTrend(src, float(beta[0]), float(beta[1])))
        gp._factorize(refit_mean=False)
        self.gp = gp
        self._coef_cov = np.asarray(cov, dtype=float)
        self._Kinv_H = np.asarray(Kinv_H, dtype=float)
        self._H = H
        self._Kinv = np.asarray(Kinv, dtype=float)
        self._alpha = np.asarray(Kinv @ (gp._z - H @ beta), dtype=float)

    @property
    def fitted(self) -> bool:
        return self.source is not None or (self.n > 0 and self.gp.fitted)

    def _scaling(self) -> tuple[float, float]:
        if self.source is not None and self.n == 0:
            return self.source.loc, self.source.scale
        return self.gp.y_mean, self.gp.y_std

    def _t(self, mu: FloatArray, sd: FloatArray) -> FloatArray:
        """Standardized margin to the limit: Φ(t) is the probability that the limit holds."""
        loc, scale = self._scaling()
        b = (self.limit.bound - loc) / scale
        return np.asarray((b - mu) / sd if self.limit.upper else (mu - b) / sd, dtype=float)

    def _noise(self) -> float:
        if self.source is not None and self.n == 0:
            return float(math.exp(_SOURCE_OUTCOME_GP.noise_loc))  # the noise prior's mode
        h = self.gp.hyper
        return float(h.noise) if h is not None else 0.0

    def _moments(self, U: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Latent mean, standard deviation and their gradients (standardized units of ``_scaling``)."""
        U = np.atleast_2d(U)
        src = self.source
        if src is None or (self._coef_cov is None and self.n > 0):
            return self.gp.predict_with_grad(U)
        s, ds = src.standardized_and_grad(U)
        var_s, dvar_s = self._source_cov().var_with_grad(U)
        if self.n == 0:  # the source alone: a = 0, b = 1 with their prior spread, and the source's own variance
            var = (
                math.exp(_SOURCE_OUTCOME_GP.os_loc)
                + OUTCOME_PRIOR_OFFSET_SD**2
                + OUTCOME_PRIOR_SCALE_SD**2 * s * s
                + _PRIOR_B2 * var_s
            )
            sd = np.sqrt(var)
            dvar = 2.0 * OUTCOME_PRIOR_SCALE_SD**2 * s[:, None] * ds + _PRIOR_B2 * dvar_s
            return s, sd, ds, dvar / (2.0 * sd[:, None])
        # the GP of prior mean h(x)ᵀ b̄ and covariance k_res + β² C_s with the coefficients integrated out
        # (Rasmussen & Williams 2006, eq. 2.42): mean h(x)ᵀβ̂ + k(x, X) α; variance k(x, x) − k(x, X) K⁻¹ k(X, x)
        # + Rᵀ Σ R, R = h(x) − Hᵀ K⁻¹ k(X, x), h(x) = (1, s(x))
        h = self.gp.hyper
        assert h is not None and h.prior is not None
        X = self.gp.X
        r2 = sq_dist(U, X, h.lengthscales)
        il2 = 1.0 / h.lengthscales**2
        Fr = matern52_dr2_factor(r2, h.outputscale)
        Cq, contract_c = self._source_cov().cross(U, X)
        Kq = matern52_from_r2(r2, h.outputscale) + self._beta2 * Cq

        def contract(W: FloatArray) -> FloatArray:  # Σ_j w_j ∂k(x_q, X_j)/∂x_q, (q, d)
            FW = Fr * W
            out = -(U * FW.sum(axis=1)[:, None] - FW @ X) * il2 + self._beta2 * contract_c(W)
            return np.asarray(out, dtype=float)

        trend = cast(PriorTrend, h.prior)
        mu = trend.a + trend.b * s + Kq @ self._alpha
        dmu = trend.b * ds + contract(self._alpha)
        V = Kq @ self._Kinv  # k(x, X) K⁻¹
        R = np.column_stack([np.ones(U.shape[0]), s]) - V @ self._H
        assert self._coef_cov is not None
        RC = R @ self._coef_cov
        var = h.outputscale + self._beta2 * var_s - np.sum(V * Kq, axis=1) + np.sum(RC * R, axis=1)
        dR0 = -contract(self._Kinv_H[:, 0])
        dR1 = ds - contract(self._Kinv_H[:, 1])
        dvar = self._beta2 * dvar_s - 2.0 * contract(V) + 2.0 * (RC[:, 0:1] * dR0 + RC[:, 1:2] * dR1)
        floor = 1e-12 * h.outputscale
        dvar[var <= floor] = 0.0
        sd = np.sqrt(np.maximum(var, floor))
        return mu, sd, dmu, dvar / (2.0 * sd[:, None])

    def prob_violation(self, U: FloatArray, measured: bool = True) -> FloatArray:
        """The probability that a run here *measures* the outcome beyond the limit (latent and noise variance);
        ``measured`` False: that the calibration's true outcome is beyond it (the latent variance alone)."""
        if not self.fitted:
            return np.zeros(np.atleast_2d(U).shape[0])
        if self.source is None:
            mu, var = self.gp.predict_std_units(U)
            if self.far_sd > 0.0:
                var = var * self._widening(var) ** 2
        else:
            mu, sd_l, _, _ = self._moments(U)
            var = sd_l * sd_l
        noise = self._noise() if measured else 0.0
        return np.asarray(1.0 - ndtr(self._t(mu, np.sqrt(np.maximum(var + noise, 1e-18)))), dtype=float)

    def log_feasible_and_grad(self, U: FloatArray, measured: bool = True) -> tuple[FloatArray, FloatArray]:
        U = np.atleast_2d(U)
        if not self.fitted:
            return np.zeros(U.shape[0]), np.zeros_like(U)
        mu, sd_f, dmu, dsd_f = self._moments(U) if self.source is not None else self.gp.predict_with_grad(U)
        if self.source is None and self.far_sd > 0.0:
            # sd (1 + κ ρ), ρ = sd² / σ_f² (at most 1): d/dx = dsd (1 + κ ρ) + sd κ dρ = dsd (1 + 3 κ ρ) below 1
            w = self._widening(sd_f * sd_f)
            dw = np.where(w < 1.0 + self.far_sd, 2.0 * (w - 1.0), 0.0)
            dsd_f = dsd_f * (w + dw)[:, None]
            sd_f = sd_f * w
        sd = np.sqrt(np.maximum(sd_f**2 + (self._noise() if measured else 0.0), 1e-18))
        dsd = dsd_f * (sd_f / sd)[:, None]
        t = self._t(mu, sd)
        sign = 1.0 if self.limit.upper else -1.0
        # t = sign (b - mu) / sd: dt = (-sign dmu - t dsd) / sd
        dt = (-sign * dmu - t[:, None] * dsd) / sd[:, None]
        lf = log_ndtr(t)
        ratio = np.exp(-0.5 * t * t - 0.5 * math.log(2.0 * math.pi) - lf)  # φ(t) / Φ(t)
        return np.asarray(lf, dtype=float), np.asarray(ratio[:, None] * dt, dtype=float)

    def _widening(self, var: FloatArray) -> FloatArray:
        """1 + far_sd · ρ, ρ = the latent variance over the kernel's (clipped to [0, 1]): the factor of the latent sd
        far from the runs (module doc)."""
        h = self.gp.hyper
        assert h is not None
        return np.asarray(1.0 + self.far_sd * np.clip(var / float(h.outputscale), 0.0, 1.0), dtype=float)

    def predict(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and std of the outcome, in its units."""
        if not self.fitted:
            n = np.atleast_2d(U).shape[0]
            return np.full(n, math.nan), np.full(n, math.nan)
        if self.source is None:
            return self.gp.predict(U)
        mu, sd, _, _ = self._moments(U)
        loc, scale = self._scaling()
        return loc + scale * mu, scale * sd


class OutcomeModels:
    """Every constrained outcome's model, fitted together from the observations."""

    def __init__(
        self,
        limits: Sequence[OutcomeLimit],
        level: float,
        sources: Mapping[str, SourceSurface] | None = None,
        far_sd: float = 0.0,
    ) -> None:
        if not 0.0 < level < 1.0:
            raise ConstraintError(f"constraint_level must be in (0, 1), got {level}")
        self.limits = tuple(limits)
        self.level = float(level)
        sources = dict(sources or {})
        self.models = [OutcomeModel(lim, sources.get(lim.name), far_sd) for lim in self.limits]

    @property
    def has_prior(self) -> bool:
        """Some limited outcome has a source: the models predict before the first run."""
        return any(m.source is not None for m in self.models)

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

    def retreat_prob(self, U: FloatArray) -> FloatArray:
        """(m,): the largest probability that a run breaks a limit, under the retreat's models (RETREAT_TREND_SD)."""
        U = np.atleast_2d(U)
        if not self.models:
            return np.zeros(U.shape[0])
        return np.asarray(np.max(np.column_stack([m.retreat_prob(U) for m in self.models]), axis=1), dtype=float)

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
        """Predicted mean, std and probability of breaking the limit at one point, per outcome (with ``far_sd`` the
        std is the widened one the probabilities use, and ``std_model`` the model's own)."""
        U = np.atleast_2d(U)
        out = {}
        for m in self.models:
            mu, sd = m.predict(U)
            entry = {
                "mean": float(mu[0]),
                "std": float(sd[0]),
                "p_violation": float(m.prob_violation(U)[0]),  # a run here measures beyond the limit
                "p_violation_true": float(m.prob_violation(U, measured=False)[0]),  # its true outcome is beyond
            }
            if m.fitted and m.source is None and m.far_sd > 0.0:
                # far from the runs the probabilities use the widened sd: "std" is that one (the one they go with),
                # "std_model" the model's own (outside review, 2026-11-25: the two were shown side by side unsaid)
                w = float(m._widening(m.gp.predict_std_units(U)[1])[0])
                entry["std"], entry["std_model"] = float(sd[0]) * w, float(sd[0])
            out[str(m.limit)] = entry
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
