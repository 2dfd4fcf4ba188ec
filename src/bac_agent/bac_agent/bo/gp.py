"""A Gaussian process with a Matérn-5/2 ARD kernel and learned observation noise.

Inputs live on the unit cube (the engine scales them), outputs are standardized
here (zero mean, unit variance), so the hyperparameter priors are the same for
every problem:

* lengthscales ℓ_k: log-normal, median ``exp(ls_loc + ls_dim_scale·log d)``, by default √2
  in any dimension (Hvarfner et al. 2024 scale it with √d; on our benchmarks that was worse
  in d = 6 and the same in d = 2);
* outputscale s²: log-normal around 1 (the standardized variance);
* noise σ²: log-normal around ``exp(noise_loc)``, bounded below by ``noise_floor``
  (a learned noise level: runs are noisy, and the GP must not interpolate them).

The prior mean is ``zero``, a learned ``constant`` (its GLS estimate), or a ``bowl``: a mixture,
over candidate centres c, of trends b0 + b1·√(|(x − c)/s|² + tip²), a cone with a rounded tip.
For each c, b0 and b1 are the GLS estimate and only b1 > 0 is kept; the weights are the tempered
marginal likelihoods; s is the anisotropy of a constant-mean fit. A comfort KPI over damping-like
parameters is bowl-shaped, and with few runs such a trend locates the optimum's basin where a
stationary GP alone cannot (see :class:`Bowl`).

The hyperparameters are the maximum a posteriori (the marginal likelihood times
these priors), found by L-BFGS-B with analytic gradients from several starts
(the prior mode, the previous fit, draws from the prior). Everything here is
vectorized numpy; no Python loop over samples.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.linalg import lapack
from scipy.optimize import minimize
from scipy.special import log_ndtr, logsumexp
from scipy.stats import qmc

from bac_agent.bo.blas import one_blas_thread
from bac_agent.bo.kernel import SQRT5, matern52_dr2_factor, matern52_from_r2, sq_dist
from bac_common.errors import BacError

FloatArray = NDArray[np.float64]

LOG_2PI = math.log(2.0 * math.pi)


MEANS = ("zero", "constant", "bowl")  # GPConfig.mean (the node's gp_mean)
# further means of GPConfig.mean and GPConfig.bowl_then (issue 23, options): "linear" a linear trend (GLS, profiled
# out of the likelihood); "select" the constant or the linear trend, whichever predicts the runs left out better
TREND_MEANS = ("linear", "select")


class GPError(BacError, ValueError):
    """The GP cannot be fitted or used (no data, NaN, a singular kernel)."""


@dataclass(frozen=True)
class GPConfig:
    """Priors and bounds of the hyperparameters (log space, on standardized outputs)."""

    # log-lengthscale prior mean: ls_loc + ls_dim_scale * log d; by default a median lengthscale of sqrt(2) on
    # the unit cube in any dimension (a d-scaled median, sqrt(d), was measured worse on Hartmann-6: bench/)
    ls_loc: float = 0.5 * math.log(2.0)
    ls_dim_scale: float = 0.0
    ls_scale: float = 1.0
    ls_bounds: tuple[float, float] = (0.01, 50.0)
    os_loc: float = 0.0  # log outputscale prior
    os_scale: float = 1.0
    os_bounds: tuple[float, float] = (0.02, 50.0)
    noise_loc: float = -4.0  # log noise-variance prior
    noise_scale: float = 1.5
    noise_floor: float = 1e-6  # smallest noise variance (standardized units)
    noise_ceiling: float = 2.0
    # prior mean of the standardized outputs: "bowl" (a mixture of cone-shaped trends, see Bowl), "constant"
    # (a learned constant, GLS) or "zero"
    mean: str = "bowl"
    bowl_centres: int = 512  # candidate centres of the bowl (scrambled Sobol over the unit cube)
    bowl_tip: float = 0.05  # radius of the bowl's rounded tip (unit cube, after the anisotropy scaling)
    bowl_temper: float = 0.5  # power of the likelihood in the weights of the centres (1: the plain posterior)
    # the centres are drawn over [-bowl_reach, 1 + bowl_reach] on every axis: a centre outside the box is a
    # trend that falls towards a face or a corner, where many a calibration's optimum lies (issue 23)
    bowl_reach: float = 0.0
    # > 0: the bowl is weighed against a constant mean by their marginal likelihoods (the bowl's slope b1 with a
    # half-normal prior of this sd, standardized units; its centre uniform over the centres), from a prior
    # probability of 0.5, and the prior mean is the two models' average (issue 23: an optimum at a corner of the
    # box is better found with a constant mean, one inside with the bowl); 0: always the bowl
    bowl_slope_sd: float = 0.0
    # prior probability that the bowl's centre lies on the box's boundary (centres on every face and at the
    # corners, besides the Sobol centres inside): a calibration's optimum often lies at a bound; 0: inside only
    bowl_faces: float = 0.0
    # the prior mean once the bowl's runs are over (the engine's bowl_runs): "constant"; "linear" (a linear trend,
    # its GLS estimate profiled out of the likelihood as the constant is); "select" (constant or linear, whichever
    # predicts the runs better left out one at a time)
    bowl_then: str = "constant"
    # the bowl is kept only while it predicts the runs, left out one at a time, better than a constant mean (the
    # bowl's mixture and the constant both re-estimated without the run left out); else the constant mean. The
    # default since 2026-11-24 (late; the tuning split, docs/agent.md); an engine state written before it (no key)
    # reads back without it
    bowl_loo: bool = True
    bowl_loo_margin: float = 0.0  # how much better (log predictive density, nats) the constant must predict
    # fewer runs than this: the bowl without the comparison; 0 = automatic, 2d + 1 and at least 5 (in 2-D the
    # engine's own design: the LOO of 3 or 4 runs cost road_c1 on the tuning split, and in 3-D that of 5 or 6 runs
    # cost Hartmann-3, docs/agent.md; the bowl lasts d + 2 runs beyond 4-D, so it is never dropped there)
    bowl_loo_runs: int = 0
    # a learned input warping (issue 23, opt-in): the kernel sees each input through a Kumaraswamy CDF
    # 1 − (1 − x^a)^b (BoTorch's `Warp`), its concentrations a, b per dimension learned with the other
    # hyperparameters under log-normal priors around 1 (the identity) of this sd (BoTorch's tutorial: √0.75) and
    # within warp_bounds; a, b < 1 stretch the region near the bound 0 or 1, so that a kink or an optimum at a face
    # or a corner can be resolved. The prior mean (the bowl) stays in the raw coordinates
    warp: bool = False
    warp_sd: float = math.sqrt(0.75)
    warp_bounds: tuple[float, float] = (0.1, 10.0)
    warp_runs: int = 0  # the warp is learned from this many runs on (the identity before)
    # > 0 (issue 23, opt-in): the kernel is fitted twice, under the lengthscale prior of sd ls_scale and under one of
    # this sd (tighter: lengthscales held near the median, which carry the runs' trend on), and the fit whose kernel
    # predicts the runs left out one at a time better (constant mean) is kept (in place of ls_average's model average)
    ls_select: float = 0.0
    # > 0: a Bayesian model average over two lengthscale priors: the kernel fitted under the prior of sd ls_scale
    # and under one of this sd (meant tighter: lengthscales held near the median, which carry the runs' trend on
    # to a face or a corner), each weighed by its evidence (the Laplace approximation of its marginal likelihood,
    # hyperparameters integrated out) raised to ls_average_temper (0: equal weights), from a prior probability of
    # 0.5 each; the engine averages the noisy EI and the posterior mean over the two (GP.alt). The default since
    # 2026-11-25: 0.5 with equal weights, chosen on the tuning split of the problem families (docs/agent.md);
    # 0: one fit, as before (an engine state saved before it reads back without it)
    ls_average: float = 0.5
    ls_average_temper: float = 0.0
    ls_average_median: float = 0.0  # > 0: the tighter prior's median lengthscale (0: the configured one's, √2)
    draws: int = 8  # draws from the prior, screened by their objective
    restarts: int = 1  # best draws optimized, besides the prior mode and the previous fit
    maxiter: int = 200

    def __post_init__(self) -> None:
        if self.mean not in MEANS + TREND_MEANS:
            raise GPError(f"GP mean must be one of {', '.join(MEANS + TREND_MEANS)}, got {self.mean!r}")
        if self.bowl_then not in MEANS + TREND_MEANS or self.bowl_then == "bowl":
            raise GPError(f"bowl_then must be one of zero, constant, linear, select, got {self.bowl_then!r}")
        if not (self.bowl_slope_sd >= 0.0 and 0.0 <= self.bowl_faces < 1.0):
            raise GPError(
                f"bowl_slope_sd must be >= 0 and bowl_faces in [0, 1), got {self.bowl_slope_sd}, {self.bowl_faces}"
            )
        lo, hi = self.warp_bounds
        if not (self.warp_sd > 0.0 and 0.0 < lo <= 1.0 <= hi < math.inf):
            raise GPError(f"warp_sd must be > 0 and warp_bounds contain 1, got {self.warp_sd}, {self.warp_bounds}")
        if self.warp_runs < 0:
            raise GPError(f"warp_runs must be >= 0 (0: the warp from the first fit), got {self.warp_runs}")
        if not (self.ls_select == 0.0 or 0.0 < self.ls_select < self.ls_scale):
            raise GPError(
                f"ls_select must be 0 (off) or a lengthscale prior sd tighter than ls_scale {self.ls_scale:g}, got "
                f"{self.ls_select}"
            )
        if not 0.0 <= self.ls_average < math.inf:
            raise GPError(
                f"ls_average must be 0 (off) or the second lengthscale prior's sd (> 0), got {self.ls_average}"
            )
        if not 0.0 <= self.ls_average_median < math.inf:
            raise GPError(
                f"ls_average_median must be >= 0 and finite (0: ls_loc's median), got {self.ls_average_median}"
            )
        if not 0.0 <= self.ls_average_temper < math.inf:
            raise GPError(f"ls_average_temper must be >= 0 and finite (0: equal weights), got {self.ls_average_temper}")
        if self.bowl_centres < 1 or not self.bowl_tip > 0.0 or not self.bowl_temper > 0.0:
            raise GPError(
                f"bowl_centres must be >= 1 and bowl_tip, bowl_temper > 0, got {self.bowl_centres}, "
                f"{self.bowl_tip}, {self.bowl_temper}"
            )


WARP_EPS = 1e-7  # the warp's inputs are mapped into [eps, 1 − eps] first (BoTorch's Warp: finite derivatives)


def kumaraswamy(X: FloatArray, a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The Kumaraswamy CDF u = 1 − (1 − x^a)^b per column of X (n, d) with concentrations a, b (d,), of
    x = eps + (1 − 2 eps)·clip(X, 0, 1); returns u and its derivatives du/dX, du/d log a, du/d log b (each (n, d))."""
    x = WARP_EPS + (1.0 - 2.0 * WARP_EPS) * np.clip(X, 0.0, 1.0)
    lx = np.log(x)
    p = np.exp(a * lx)  # x^a
    q = 1.0 - p
    lq = np.log(q)
    qb = np.exp(b * lq)  # (1 − x^a)^b
    common = b * (qb / q) * p  # b q^(b−1) x^a
    du_dx = (1.0 - 2.0 * WARP_EPS) * common * a / x
    du_dla = common * a * lx
    du_dlb = -b * qb * lq
    return 1.0 - qb, du_dx, du_dla, du_dlb


def boundary_centres(d: int, m: int, seed: int) -> FloatArray:
    """Candidate centres on the unit cube's boundary: ``m`` scrambled Sobol points projected onto each of the
    2d faces (the power of two nearest to m // (2d) each, at least 8) and, up to 8 dimensions, the 2^d corners."""
    k = max(3, round(math.log2(max(m // (2 * d), 1))))
    S = qmc.Sobol(d, scramble=True, seed=seed + 1).random_base2(k)
    faces = []
    for j in range(d):
        for side in (0.0, 1.0):
            F = S.copy()
            F[:, j] = side
            faces.append(F)
    if d <= 8:
        faces.append(np.array(list(itertools.product((0.0, 1.0), repeat=d)), dtype=float))
    return np.asarray(np.vstack(faces), dtype=float)


def cone_radius(X: FloatArray, centres: FloatArray, scale: FloatArray, tip: float) -> FloatArray:
    """(n, m) rounded distances √(|(x − c)/s|² + tip²) between the rows of X and the centres."""
    A = X / scale
    B = centres / scale
    r2 = np.sum(A * A, axis=1)[:, None] - 2.0 * A @ B.T + np.sum(B * B, axis=1)[None, :]
    return np.asarray(np.sqrt(np.maximum(r2, 0.0) + tip**2), dtype=float)


@dataclass(frozen=True)
class Bowl:
    """A bowl-shaped prior mean: a weighted mixture of rounded cones over candidate centres.

    ``value(x) = Σ_c w_c (b0_c + b1_c · r_c(x))`` with ``r_c(x) = √(|(x − c)/s|² + tip²)``. The
    weights are the (tempered) marginal likelihoods of the centres, so the trend stays broad while
    few runs cannot tell the centres apart, instead of betting on one centre (a single fitted
    centre locked campaigns onto a biased one: docs/agent.md).
    """

    centres: FloatArray  # (m, d) unit cube
    b0: FloatArray  # (m,) standardized units
    b1: FloatArray  # (m,) > 0
    weights: FloatArray  # (m,) sum 1 (with GPConfig.bowl_slope_sd: the bowl's probability against a constant)
    scale: FloatArray  # (d,) anisotropy, geometric mean 1
    tip: float

    def value(self, Xq: FloatArray) -> FloatArray:
        """The trend at the rows of ``Xq`` (m_q,), standardized units."""
        return np.asarray(
            (self.b0 + self.b1 * cone_radius(np.atleast_2d(Xq), self.centres, self.scale, self.tip)) @ self.weights,
            dtype=float,
        )

    def value_and_grad(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]:
        Xq = np.atleast_2d(Xq)
        r = cone_radius(Xq, self.centres, self.scale, self.tip)
        G = (self.weights * self.b1)[None, :] / r  # (m_q, m): d value / d r_c times 1 / r_c
        grad = (Xq * G.sum(axis=1)[:, None] - G @ self.centres) / self.scale**2
        return np.asarray((self.b0 + self.b1 * r) @ self.weights, dtype=float), np.asarray(grad, dtype=float)

    def to_dict(self) -> dict[str, Any]:
        return {
            "centres": self.centres.tolist(),
            "b0": self.b0.tolist(),
            "b1": self.b1.tolist(),
            "weights": self.weights.tolist(),
            "scale": self.scale.tolist(),
            "tip": self.tip,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Bowl:
        return cls(
            np.asarray(d["centres"], dtype=float).reshape(len(d["centres"]), -1),
            np.asarray(d["b0"], dtype=float),
            np.asarray(d["b1"], dtype=float),
            np.asarray(d["weights"], dtype=float),
            np.asarray(d["scale"], dtype=float),
            float(d["tip"]),
        )


class Trend(Protocol):
    """A prior-mean trend over the unit cube (standardized units): e.g. bo.prior.PriorTrend, a source's shape."""

    def value(self, Xq: FloatArray) -> FloatArray: ...
    def value_and_grad(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]: ...


@dataclass
class Hyper:
    """Fitted hyperparameters (lengthscales on the unit cube, standardized units)."""

    lengthscales: FloatArray
    outputscale: float
    noise: float
    mean: float = 0.0  # constant prior mean (standardized units; 0 with GPConfig.mean == "zero")
    bowl: Bowl | None = None  # the bowl trend, added to ``mean`` (GPConfig.mean == "bowl"; None: none fitted)
    # another trend added to the mean (a transfer prior's a + b s(x), bo/prior.py); set by the engine, not saved
    prior: Trend | None = None
    # a linear trend's slope over the unit cube (GPConfig.mean "linear" or "select"), added to ``mean``
    slope: FloatArray | None = None
    # the input warping's concentrations (2, d): rows a, b of the Kumaraswamy CDF the kernel sees each input
    # through (GPConfig.warp); None: the kernel sees the inputs themselves
    warp: FloatArray | None = None

    def kernel_inputs(self, X: FloatArray) -> FloatArray:
        """The inputs as the kernel sees them: X itself, or warped (``warp``)."""
        if self.warp is None:
            return X
        return kumaraswamy(np.atleast_2d(X), self.warp[0], self.warp[1])[0]

    def kernel_inputs_grad(self, X: FloatArray) -> tuple[FloatArray, FloatArray | None]:
        """The kernel's inputs and their derivative w.r.t. X, elementwise (None: the identity)."""
        if self.warp is None:
            return X, None
        u, du, _, _ = kumaraswamy(np.atleast_2d(X), self.warp[0], self.warp[1])
        return u, du

    def mean_at(self, Xq: FloatArray) -> FloatArray:
        """The prior mean at the rows of ``Xq`` (standardized units)."""
        Xq = np.atleast_2d(Xq)
        out = np.full(Xq.shape[0], self.mean)
        if self.slope is not None:
            out = out + Xq @ self.slope
        if self.bowl is not None:
            out = out + self.bowl.value(Xq)
        if self.prior is not None:
            out = out + self.prior.value(Xq)
        return out

    def mean_and_grad(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]:
        Xq = np.atleast_2d(Xq)
        v, g = np.full(Xq.shape[0], self.mean), np.zeros_like(Xq)
        if self.slope is not None:
            v, g = v + Xq @ self.slope, g + self.slope[None, :]
        if self.bowl is not None:
            vb, gb = self.bowl.value_and_grad(Xq)
            v, g = v + vb, g + gb
        if self.prior is not None:
            vp, gp = self.prior.value_and_grad(Xq)
            v, g = v + vp, g + gp
        return v, g

    def to_vector(self) -> FloatArray:
        v = np.concatenate([np.log(self.lengthscales), [math.log(self.outputscale), math.log(self.noise)]])
        return v if self.warp is None else np.concatenate([v, np.log(self.warp).ravel()])

    @classmethod
    def from_vector(cls, v: FloatArray, d: int | None = None) -> Hyper:
        """From log-hyperparameters; with ``d`` and 3d + 2 of them, the last 2d are the warp's (GPConfig.warp)."""
        v = np.asarray(v, dtype=float)
        if d is not None and v.size == 3 * d + 2:
            return cls(
                np.exp(v[:d]), float(math.exp(v[d])), float(math.exp(v[d + 1])), warp=np.exp(v[d + 2 :]).reshape(2, d)
            )
        return cls(np.exp(v[:-2]), float(math.exp(v[-2])), float(math.exp(v[-1])))

    def to_dict(self) -> dict[str, Any]:
        return {
            "lengthscales": self.lengthscales.tolist(),
            "outputscale": self.outputscale,
            "noise": self.noise,
            "mean": self.mean,
            "bowl": self.bowl.to_dict() if self.bowl is not None else None,
            **({"slope": self.slope.tolist()} if self.slope is not None else {}),
            **({"warp": self.warp.tolist()} if self.warp is not None else {}),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Hyper:
        """Read :meth:`to_dict`'s output back; a saved state whose shapes do not fit together (the lengthscales'
        dimension against the slope's and the warp's (2, d)) or whose scales are not positive raises GPError."""
        ls = np.asarray(d["lengthscales"], dtype=float)
        h = cls(
            ls,
            float(d["outputscale"]),
            float(d["noise"]),
            float(d.get("mean", 0.0)),
            Bowl.from_dict(d["bowl"]) if d.get("bowl") else None,
            slope=np.asarray(d["slope"], dtype=float) if d.get("slope") is not None else None,
            warp=np.asarray(d["warp"], dtype=float) if d.get("warp") is not None else None,
        )
        dim = ls.size
        problems = []
        if ls.ndim != 1 or dim == 0 or not np.all(np.isfinite(ls) & (ls > 0)):
            problems.append(f"lengthscales {ls.tolist()} (positive, one per dimension)")
        if not (h.outputscale > 0 and h.noise > 0 and math.isfinite(h.outputscale) and math.isfinite(h.noise)):
            problems.append(f"outputscale {h.outputscale}, noise {h.noise} (positive)")
        if h.slope is not None and h.slope.shape != (dim,):
            problems.append(f"slope of shape {h.slope.shape} (expected ({dim},))")
        if h.warp is not None and (h.warp.shape != (2, dim) or not np.all(np.isfinite(h.warp) & (h.warp > 0))):
            problems.append(f"warp of shape {h.warp.shape} (expected (2, {dim}), positive)")
        if problems:
            raise GPError("saved hyperparameters do not fit together: " + "; ".join(problems))
        return h


@dataclass
class GP:
    """GP regression on the unit cube. ``fit`` learns hyperparameters; ``condition`` only factorizes."""

    config: GPConfig = field(default_factory=GPConfig)
    hyper: Hyper | None = None
    X: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    y_mean: float = 0.0
    y_std: float = 1.0
    _L: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    _alpha: FloatArray = field(default_factory=lambda: np.zeros(0))
    _z: FloatArray = field(default_factory=lambda: np.zeros(0))
    _offset: FloatArray | float = 0.0  # a fixed trend subtracted from z while fitting (the bowl's)
    _bowl_loo: float = -math.inf  # the bowl's leave-one-out log predictive density (GPConfig.bowl_loo)
    _const_loo: float = -math.inf  # the constant mean's, the last time they were compared
    _lin: bool = False  # the fit profiles a linear trend out of the likelihood (GPConfig.mean "linear"/"select")
    # GPConfig.ls_average: the fit under the tighter lengthscale prior and its posterior probability (this fit's is
    # 1 - alt_weight); set by fit, None otherwise (condition() leaves them as they are)
    alt: GP | None = None
    alt_weight: float = 0.0

    # --- priors ------------------------------------------------------------------
    def _prior(self, d: int) -> tuple[FloatArray, FloatArray]:
        c = self.config
        loc = np.concatenate([np.full(d, c.ls_loc + c.ls_dim_scale * math.log(d)), [c.os_loc, c.noise_loc]])
        scale = np.concatenate([np.full(d, c.ls_scale), [c.os_scale, c.noise_scale]])
        if c.warp:  # the warp's log-concentrations a, b: around 0 (the identity)
            loc, scale = np.concatenate([loc, np.zeros(2 * d)]), np.concatenate([scale, np.full(2 * d, c.warp_sd)])
        return loc, scale

    def _prior_cached(self, d: int) -> tuple[FloatArray, FloatArray]:
        key = (d, self.config)
        if getattr(self, "_prior_key", None) != key:
            self._prior_key = key
            self._prior_val = self._prior(d)
        return self._prior_val

    def _bounds(self, d: int) -> list[tuple[float, float]]:
        c = self.config
        ls = (math.log(c.ls_bounds[0]), math.log(c.ls_bounds[1]))
        warp = [(math.log(c.warp_bounds[0]), math.log(c.warp_bounds[1]))] * (2 * d if c.warp else 0)
        return (
            [ls] * d
            + [
                (math.log(c.os_bounds[0]), math.log(c.os_bounds[1])),
                (math.log(c.noise_floor), math.log(c.noise_ceiling)),
            ]
            + warp
        )

    # --- data ------------------------------------------------------------------------
    def _set_data(self, X: FloatArray, y: FloatArray, scaling: tuple[float, float] | None = None) -> None:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        y = np.asarray(y, dtype=float).ravel()
        if X.shape[0] == 0 or X.shape[0] != y.shape[0]:
            raise GPError(f"need matching, non-empty X and y, got X {X.shape} and y {y.shape}")
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
            raise GPError("X and y must be finite (NaN or inf observations cannot be modelled)")
        self.X = X
        if scaling is not None:
            self.y_mean, self.y_std = float(scaling[0]), float(scaling[1])
        else:
            self.y_mean = float(np.mean(y))
            sd = float(np.std(y))
            self.y_std = sd if sd > 1e-12 * max(1.0, abs(self.y_mean)) else 1.0
        self._z = (y - self.y_mean) / self.y_std

    # --- the objective: negative log posterior and its gradient ------------------------------
    def neg_log_posterior(self, v: FloatArray, D2: FloatArray | None = None) -> tuple[float, FloatArray]:
        """-(log marginal likelihood + log prior) of log-hyperparameters ``v`` and its gradient.

        ``D2`` is the (n*n, d) matrix of squared coordinate differences of the inputs
        (computed once per fit).
        """
        X, z = self.X, self._z - self._offset
        n, d = X.shape
        if self.config.warp:  # the kernel's inputs warped by v's concentrations (v[d + 2:]): D2 of them
            U, _, dUa, dUb = kumaraswamy(X, np.exp(v[d + 2 : 2 * d + 2]), np.exp(v[2 * d + 2 :]))
            D2 = ((U[:, None, :] - U[None, :, :]) ** 2).reshape(-1, d)
        elif D2 is None:
            D2 = self._d2()
        ls2 = np.exp(2.0 * v[:d])
        s2 = math.exp(v[d])
        sn2 = math.exp(v[d + 1])
        r2 = (D2 @ (1.0 / ls2)).reshape(n, n)
        r = np.sqrt(r2)
        e = np.exp(-SQRT5 * r)
        poly = 1.0 + SQRT5 * r
        Kf = s2 * (poly + (5.0 / 3.0) * r2) * e
        K = Kf.copy()
        K.flat[:: n + 1] += sn2 + 1e-10 * s2
        L, info = lapack.dpotrf(K, lower=1, clean=1)
        if info != 0:
            return 1e10, np.zeros_like(v)
        Kinv, _ = lapack.dpotri(L, lower=1)
        Kinv = np.tril(Kinv) + np.tril(Kinv, -1).T
        if self._lin:
            z = z - self._trend_basis() @ self._gls_beta(Kinv, z)
        elif self.config.mean != "zero":
            # the constant mean profiled out (its GLS estimate); by the envelope theorem the gradient
            # below (at fixed c) is the gradient of the profiled likelihood
            z = z - self._gls_mean(Kinv, z)
        alpha = Kinv @ z
        mll = -0.5 * float(z @ alpha) - float(np.sum(np.log(np.diag(L)))) - 0.5 * n * LOG_2PI
        W = np.outer(alpha, alpha) - Kinv
        # F = -2 dk/d(r^2) = s2 (5/3)(1 + sqrt5 r) exp(-sqrt5 r); d mll/d log l_k = 0.5 sum_ij W F D2_k / l_k^2
        M = W * ((s2 * 5.0 / 3.0) * poly * e)
        g_ls = 0.5 * (M.ravel() @ D2) / ls2
        g_os = 0.5 * float(np.sum(W * Kf))
        g_sn = 0.5 * sn2 * float(np.trace(W))
        grad = np.concatenate([g_ls, [g_os, g_sn]])
        if self.config.warp:
            # d r²_ij/dθ_k = 2 (u_ik − u_jk)(∂u_ik − ∂u_jk)/ℓ_k² and dk/dr² = −F/2, so with M = W∘F (symmetric)
            # d mll/dθ_k = −½ Σ_ij M_ij (u_ik − u_jk)(∂u_ik − ∂u_jk)/ℓ_k² = −Σ_i u_ik (m_i ∂u_ik − (M ∂U)_ik)/ℓ_k²
            m = M.sum(axis=1)[:, None]
            g_a = -np.sum(U * (m * dUa - M @ dUa), axis=0) / ls2
            g_b = -np.sum(U * (m * dUb - M @ dUb), axis=0) / ls2
            grad = np.concatenate([grad, g_a, g_b])
        loc, scale = self._prior_cached(d)
        lp = -0.5 * float(np.sum(((v - loc) / scale) ** 2))
        glp = -(v - loc) / scale**2
        return -(mll + lp), -(grad + glp)

    @staticmethod
    def _gls_mean(Kinv: FloatArray, z: FloatArray) -> float:
        """The generalized-least-squares constant: argmax of the likelihood over a constant mean."""
        k1 = Kinv.sum(axis=0)
        return float(k1 @ z / max(float(k1.sum()), 1e-300))

    def _trend_basis(self) -> FloatArray:
        """(n, d + 1) basis of the linear trend at the runs: 1 and the inputs about the box's centre."""
        return np.hstack([np.ones((self.X.shape[0], 1)), self.X - 0.5])

    def _gls_beta(self, Kinv: FloatArray, z: FloatArray) -> FloatArray:
        """The generalized-least-squares coefficients of the linear trend (basis ``_trend_basis``)."""
        H = self._trend_basis()
        KH = Kinv @ H
        A = H.T @ KH
        A.flat[:: A.shape[0] + 1] += 1e-10 * max(float(np.trace(A)), 1e-300)
        return np.asarray(np.linalg.solve(A, KH.T @ z), dtype=float)

    def _linear_ok(self) -> bool:
        """Enough runs for a linear trend: at least d + 3 (its d + 1 coefficients and some left for the kernel)."""
        return bool(self.X.shape[0] >= self.X.shape[1] + 3)

    def loo_log_predictive(self, v: FloatArray, linear: bool) -> float:
        """Leave-one-out log predictive density of the standardized runs under log-hyperparameters ``v``, with a
        constant or a linear trend re-estimated (GLS, flat prior) without the run left out.

        Closed form (universal kriging, Dubrule 1983; R&W 2006 §5.4.2 with the trend's coefficients integrated
        out): with P = K⁻¹ − K⁻¹H(HᵀK⁻¹H)⁻¹HᵀK⁻¹, run i's left-out residual is (Pz)ᵢ/Pᵢᵢ and its variance 1/Pᵢᵢ.
        """
        h = Hyper.from_vector(v, self.X.shape[1])
        n = self.X.shape[0]
        U = h.kernel_inputs(self.X)
        K = matern52_from_r2(sq_dist(U, U, h.lengthscales), h.outputscale)
        K.flat[:: n + 1] += h.noise + 1e-10 * h.outputscale
        Kinv = sla.cho_solve((np.linalg.cholesky(K), True), np.eye(n), check_finite=False)
        H = self._trend_basis() if linear else np.ones((n, 1))
        KH = Kinv @ H
        P = Kinv - KH @ np.linalg.solve(H.T @ KH, KH.T)
        pii = np.maximum(np.diag(P), 1e-300)
        r = P @ self._z
        return float(np.sum(-0.5 * np.log(2.0 * math.pi / pii) - 0.5 * r * r / pii))

    def _d2(self) -> FloatArray:
        X = self.X
        return ((X[:, None, :] - X[None, :, :]) ** 2).reshape(-1, X.shape[1])

    def log_marginal_likelihood(self, hyper: Hyper) -> float:
        """Log marginal likelihood of the standardized data under ``hyper`` (no prior; the constant mean
        profiled out unless the mean is "zero", a bowl in ``hyper`` not counted)."""
        v = hyper.to_vector()
        nlp, _ = self.neg_log_posterior(v)
        loc, scale = self._prior(self.X.shape[1])
        return -nlp + 0.5 * float(np.sum(((v - loc) / scale) ** 2))

    # --- fitting -------------------------------------------------------------------------
    def fit(self, X: FloatArray, y: FloatArray, rng: np.random.Generator | None = None) -> GP:
        """Learn the hyperparameters (MAP, multi-start L-BFGS-B) and condition on (X, y).

        With the bowl mean: the kernel's hyperparameters with a constant mean, the bowl under that
        kernel, the hyperparameters again on what the bowl leaves, and the bowl again. BLAS runs on one thread
        meanwhile (:mod:`bac_agent.bo.blas`).
        """
        with one_blas_thread():
            return self._fit(X, y, rng)

    def _fit(self, X: FloatArray, y: FloatArray, rng: np.random.Generator | None = None) -> GP:
        if self.config.ls_select > 0.0:
            return self._fit_ls_select(X, y, rng)
        if self.config.ls_average > 0.0:
            return self._fit_ls_average(X, y, rng)
        if self.config.warp and np.atleast_2d(X).shape[0] < self.config.warp_runs:
            warped = self.config  # (GPConfig.warp_runs) too few runs to learn the warp: this fit without it
            self.config = replace(warped, warp=False)
            try:
                return self.fit(X, y, rng)
            finally:
                self.config = warped
        self._set_data(X, y)
        rng = rng if rng is not None else np.random.default_rng(0)
        self._offset = 0.0
        self._lin = False
        v = self._map_hyper(rng)
        if self.config.mean in TREND_MEANS and self._linear_ok():
            v = self._fit_linear(v, rng)
        bowl = None
        v_const = v
        if self.config.mean == "bowl" and self.X.shape[0] >= 3:
            h0 = Hyper.from_vector(v, self.X.shape[1])
            ls0 = h0.lengthscales
            scale = np.clip(ls0 / math.exp(float(np.mean(np.log(ls0)))), 1.0 / 3.0, 3.0)
            bowl = self._fit_bowl(h0, scale)
            if bowl is not None:
                self._offset = bowl.value(self.X)
                self.hyper = h0  # the next fit starts from it
                v = self._map_hyper(rng)
                self._offset = 0.0
                bowl = self._fit_bowl(Hyper.from_vector(v, self.X.shape[1]), scale)
            if bowl is not None and self._bowl_loo_due():
                try:
                    const_loo = self.loo_log_predictive(v_const, False)
                except np.linalg.LinAlgError:
                    const_loo = -math.inf
                self._const_loo = const_loo  # (shown by bench diagnostics)
                if const_loo > self._bowl_loo + self.config.bowl_loo_margin:
                    bowl, v = None, v_const
        self.hyper = Hyper.from_vector(v, self.X.shape[1])
        if bowl is not None and self.config.bowl_slope_sd > 0.0:
            # the bowl's weights carry its probability against a constant mean: the constant given that trend
            self.hyper = replace(self.hyper, bowl=bowl)
            self._factorize(refit_mean=False)
            ones = sla.cho_solve((self._L, True), np.ones(self.X.shape[0]), check_finite=False)
            c = float(ones @ (self._z - bowl.value(self.X)) / max(float(ones.sum()), 1e-300))
            self.hyper = replace(self.hyper, mean=c)
            self._factorize(refit_mean=False)
        elif bowl is not None:
            self.hyper = replace(self.hyper, bowl=bowl)  # its constants b0 carry the mean
            self._factorize(refit_mean=False)
        else:
            self._factorize(refit_mean=True)
        return self

    def _fit_ls_select(self, X: FloatArray, y: FloatArray, rng: np.random.Generator | None) -> GP:
        """GPConfig.ls_select: the fit under the configured and under the tighter lengthscale prior, whichever
        kernel has the better leave-one-out log predictive density of the runs (a constant mean re-estimated)."""
        c = self.config
        seed = int((rng if rng is not None else np.random.default_rng(0)).integers(2**63 - 1))
        best: tuple[float, GP] | None = None
        c = replace(c, ls_select=0.0, ls_average=0.0)  # (one fit each)
        for cfg in (c, replace(c, ls_scale=self.config.ls_select)):
            gp = GP(cfg, hyper=self.hyper).fit(X, y, np.random.default_rng(seed))
            assert gp.hyper is not None
            try:
                loo = gp.loo_log_predictive(gp.hyper.to_vector(), False)
            except np.linalg.LinAlgError:
                loo = -math.inf
            if best is None or loo > best[0]:
                best = (loo, gp)
        assert best is not None
        for k, v in vars(best[1]).items():
            if k != "config":
                setattr(self, k, v)
        return self

    def _fit_ls_average(self, X: FloatArray, y: FloatArray, rng: np.random.Generator | None) -> GP:
        """GPConfig.ls_average: this GP is the fit under the configured lengthscale prior, ``alt`` the fit under the
        tighter one, ``alt_weight`` the latter's posterior probability (their evidences, tempered). Both fits start
        from the last hyperparameters of this one (the only ones an engine's state keeps) and draw their starts
        from one seed taken from ``rng``."""
        c = self.config
        seed = int((rng if rng is not None else np.random.default_rng(0)).integers(2**63 - 1))
        base = GP(replace(c, ls_average=0.0), hyper=self.hyper).fit(X, y, np.random.default_rng(seed))
        alt_cfg = replace(c, ls_scale=c.ls_average, ls_average=0.0)
        if c.ls_average_median > 0.0:  # (the median in any dimension: ls_dim_scale's log d taken off)
            d = np.atleast_2d(X).shape[1]
            alt_cfg = replace(alt_cfg, ls_loc=math.log(c.ls_average_median) - c.ls_dim_scale * math.log(d))
        alt = GP(alt_cfg, hyper=self.hyper)
        alt.fit(X, y, np.random.default_rng(seed))
        # (temper 0: equal weights, the evidences not computed)
        log_odds = c.ls_average_temper * (alt.log_evidence() - base.log_evidence()) if c.ls_average_temper else 0.0
        if not math.isfinite(log_odds):  # (a Hessian that could not be evaluated: no preference)
            log_odds = 0.0
        for k, v in vars(base).items():
            if k != "config":
                setattr(self, k, v)
        self.alt = alt
        self.alt_weight = float(1.0 / (1.0 + math.exp(-log_odds))) if log_odds > -700.0 else 0.0
        return self

    def log_evidence(self) -> float:
        """The Laplace approximation of the log evidence of the standardized runs under this GP's hyperprior:
        log p(z | v̂) + log p(v̂) + (k/2) log 2π − ½ log det H at the fitted log-hyperparameters v̂ (k of them; H the
        Hessian of the negative log posterior, central differences of its analytic gradient, eigenvalues clipped at
        1e-6), with the prior's normalizing constants; the fitted bowl (if any) a fixed offset, the constant mean
        profiled out as in the fit. Two fits under different hyperpriors compare by it (GPConfig.ls_average)."""
        if not self.fitted:
            raise GPError("the GP has no data yet")
        assert self.hyper is not None
        v = self.hyper.to_vector()
        k = v.size
        cfg = self.config
        if cfg.warp and self.hyper.warp is None:  # fitted without the warp (GPConfig.warp_runs): judged as fitted
            self.config = replace(cfg, warp=False)
        D2 = None if self.config.warp else self._d2()
        self._offset = self.hyper.bowl.value(self.X) if self.hyper.bowl is not None else 0.0
        try:
            f0, _ = self.neg_log_posterior(v, D2)
            H = np.empty((k, k))
            step = 1e-4
            for i in range(k):
                e = np.zeros(k)
                e[i] = step
                H[i] = (self.neg_log_posterior(v + e, D2)[1] - self.neg_log_posterior(v - e, D2)[1]) / (2.0 * step)
            _, scale = self._prior(self.X.shape[1])
        finally:
            self._offset = 0.0
            self.config = cfg
        eig = np.linalg.eigvalsh(0.5 * (H + H.T))
        return float(-f0 - np.sum(np.log(scale)) - 0.5 * np.sum(np.log(np.maximum(eig, 1e-6))))

    def _bowl_loo_due(self) -> bool:
        """GPConfig.bowl_loo compares the bowl with a constant mean at this many runs (bowl_loo_runs; 0: 2d + 1 and
        at least 5)."""
        c = self.config
        return c.bowl_loo and self.X.shape[0] >= (c.bowl_loo_runs or max(5, 2 * self.X.shape[1] + 1))

    def _fit_linear(self, v_const: FloatArray, rng: np.random.Generator) -> FloatArray:
        """The hyperparameters with a linear trend profiled out (sets ``_lin``); with the mean "select", only when
        the linear trend predicts the runs left out one at a time better than the constant (``v_const``'s fit)."""
        self.hyper = Hyper.from_vector(v_const, self.X.shape[1])  # a start of the linear fit
        self._lin = True
        v_lin = self._map_hyper(rng)
        if self.config.mean == "select":
            try:
                better = self.loo_log_predictive(v_lin, True) > self.loo_log_predictive(v_const, False)
            except np.linalg.LinAlgError:
                better = False
            if not better:
                self._lin = False
                return v_const
        return v_lin

    def _fit_bowl(self, h: Hyper, scale: FloatArray) -> Bowl | None:
        """The bowl's mixture under kernel ``h``, or None when no centre gives an upward slope.

        For each candidate centre c the trend's b0, b1 are the GLS estimate with the basis
        [1, r_c(x)]; its weight is the marginal likelihood with a flat prior on (b0, b1),
        ``½ bᵀA⁻¹b − ½ log det A`` (A = HᵀK⁻¹H, b = HᵀK⁻¹z), raised to ``bowl_temper``.
        """
        c = self.config
        X, z = self.X, self._z
        n, d = X.shape
        U = h.kernel_inputs(X)
        K = matern52_from_r2(sq_dist(U, U, h.lengthscales), h.outputscale)
        K.flat[:: n + 1] += h.noise + 1e-10 * h.outputscale
        try:
            Kinv = sla.cho_solve((np.linalg.cholesky(K), True), np.eye(n), check_finite=False)
        except np.linalg.LinAlgError:
            return None
        C = qmc.Sobol(d, scramble=True, seed=n).random(c.bowl_centres) * (1.0 + 2.0 * c.bowl_reach) - c.bowl_reach
        log_prior = np.full(C.shape[0], -math.log(C.shape[0]))
        if c.bowl_faces > 0.0:
            F = boundary_centres(d, c.bowl_centres, n)
            C = np.vstack([C, F])
            log_prior = np.concatenate(
                [log_prior + math.log1p(-c.bowl_faces), np.full(F.shape[0], math.log(c.bowl_faces / F.shape[0]))]
            )
        R = cone_radius(X, C, scale, c.bowl_tip)  # (n, m)
        k1 = Kinv.sum(axis=0)
        a11 = float(k1.sum())
        b1 = float(k1 @ z)
        a12 = k1 @ R
        a22 = np.sum(R * (Kinv @ R), axis=0)
        b2 = (Kinv @ z) @ R
        det = a11 * a22 - a12**2
        ok = det > 1e-12 * a11 * a22
        safe = np.where(ok, det, 1.0)
        beta0 = (a22 * b1 - a12 * b2) / safe
        beta1 = (a11 * b2 - a12 * b1) / safe
        ok &= beta1 > 0.0
        if not np.any(ok):
            return None
        logw = np.where(ok, c.bowl_temper * (0.5 * (beta0 * b1 + beta1 * b2) - 0.5 * np.log(safe)), -np.inf)
        if c.bowl_faces > 0.0:
            logw = logw + log_prior  # (else uniform: the weights as before, to the bit)
        w = np.exp(logw - np.max(logw))
        keep = w > 1e-6
        if self._bowl_loo_due():
            self._bowl_loo = self._bowl_loo_lpd(Kinv, z, k1, R, a12, a22, safe, beta0, beta1, logw)
        p_bowl = 1.0
        if c.bowl_slope_sd > 0.0:
            p_bowl = self._bowl_probability(a11, b1, a12, a22, b2, log_prior)
        return Bowl(C[keep], beta0[keep], beta1[keep], p_bowl * w[keep] / w[keep].sum(), scale, c.bowl_tip)

    def _bowl_loo_lpd(
        self,
        Kinv: FloatArray,
        z: FloatArray,
        k1: FloatArray,
        R: FloatArray,
        a12: FloatArray,
        a22: FloatArray,
        det: FloatArray,
        beta0: FloatArray,
        beta1: FloatArray,
        logw: FloatArray,
    ) -> float:
        """Leave-one-out log predictive density of the runs under the bowl's mixture (GPConfig.bowl_loo).

        Per centre c, the basis H = [1, r_c(x)] with its coefficients integrated out (flat prior) gives run i's
        left-out prediction in closed form (as :meth:`loo_log_predictive`): with P = K⁻¹ − K⁻¹H A⁻¹HᵀK⁻¹,
        residual (Pz)ᵢ/Pᵢᵢ, variance 1/Pᵢᵢ. The centres' weights without run i are their (tempered) evidence
        over the other runs: the evidence of all runs divided by run i's left-out density, p(z) = p(z₋ᵢ) p(zᵢ|z₋ᵢ).
        """
        a11 = float(k1.sum())
        KR = Kinv @ R  # (n, m)
        r = (Kinv @ z)[:, None] - k1[:, None] * beta0[None, :] - KR * beta1[None, :]
        quad = a22[None, :] * (k1 * k1)[:, None] - 2.0 * a12[None, :] * k1[:, None] * KR + a11 * KR * KR
        pii = np.maximum(np.diag(Kinv)[:, None] - quad / det[None, :], 1e-300)
        logp = -0.5 * np.log(2.0 * math.pi / pii) - 0.5 * r * r / pii  # (n, m)
        ok = np.isfinite(logw)
        lw = np.where(ok[None, :], logw[None, :] - self.config.bowl_temper * logp, -np.inf)
        lw = lw - logsumexp(lw, axis=1, keepdims=True)
        return float(np.sum(logsumexp(np.where(ok[None, :], lw + logp, -np.inf), axis=1)))

    def _bowl_probability(
        self, a11: float, b1: float, a12: FloatArray, a22: FloatArray, b2: FloatArray, log_prior: FloatArray
    ) -> float:
        """Posterior probability of the bowl against a constant mean (prior 0.5 each), under the current kernel.

        Both models share the constant b0 (flat prior: it cancels); the bowl adds the slope b1 with a
        half-normal prior of sd τ = ``bowl_slope_sd`` and its centre c with the prior ``log_prior``. With
        A = HᵀK⁻¹H, b = HᵀK⁻¹z and P = diag(0, 1/τ²), the Bayes factor of centre c is
        ``2 Φ(m₁/√S₁₁) · √(a11 / det(A + P)) / τ · exp(½ bᵀ(A + P)⁻¹b − b₁²/(2 a11))`` (m, S: the posterior mean
        and covariance (A + P)⁻¹b, (A + P)⁻¹; the truncation to b1 > 0); the bowl's is their prior average."""
        tau2 = self.config.bowl_slope_sd**2
        p22 = a22 + 1.0 / tau2
        det = a11 * p22 - a12**2
        det = np.maximum(det, 1e-300)
        m1 = (a11 * b2 - a12 * b1) / det  # posterior mean of the slope
        s11 = a11 / det  # its posterior variance
        quad = (p22 * b1 * b1 - 2.0 * a12 * b1 * b2 + a11 * b2 * b2) / det
        log_bf = (
            math.log(2.0)
            + log_ndtr(m1 / np.sqrt(s11))
            + 0.5 * (math.log(a11) - np.log(det) - math.log(tau2))
            + 0.5 * (quad - b1 * b1 / a11)
        )
        lb = float(logsumexp(log_bf + log_prior))
        return float(1.0 / (1.0 + math.exp(-lb))) if lb > -700 else 0.0

    def _map_hyper(self, rng: np.random.Generator, warm_only: bool = False) -> FloatArray:
        """MAP log-hyperparameters of the data minus ``_offset`` (multi-start L-BFGS-B).

        ``warm_only``: one start, the current hyperparameters (a refinement after a small change of the offset,
        e.g. a transfer prior's trend rescaled; no draws are taken from ``rng``)."""
        d = self.X.shape[1]
        loc, scale = self._prior(d)
        bounds = self._bounds(d)
        lo = np.array([b[0] for b in bounds])
        hi = np.array([b[1] for b in bounds])
        warm = self.hyper is not None and self.hyper.lengthscales.shape[0] == d
        warm = warm and self.hyper is not None and self.hyper.to_vector().size == loc.size  # (GPConfig.warp)
        if warm_only and warm:
            assert self.hyper is not None
            starts = [np.clip(self.hyper.to_vector(), lo, hi)]
            return self._minimize_from(starts, bounds, self._d2())
        starts = [np.clip(loc, lo, hi)]
        if warm:
            assert self.hyper is not None
            starts.append(np.clip(self.hyper.to_vector(), lo, hi))
        draws = [np.clip(loc + scale * rng.standard_normal(loc.size) * 0.7, lo, hi) for _ in range(self.config.draws)]
        D2 = self._d2()
        if draws:
            # screen the prior draws by their objective; optimize only from the best ones
            vals = [self.neg_log_posterior(v, D2)[0] for v in draws]
            starts += [draws[i] for i in np.argsort(vals)[: self.config.restarts]]
        return self._minimize_from(starts, bounds, D2)

    def _minimize_from(self, starts: list[FloatArray], bounds: list[tuple[float, float]], D2: FloatArray) -> FloatArray:
        """The best of L-BFGS-B runs of the negative log posterior from each start."""
        best_v, best_f = starts[0], math.inf
        for v0 in starts:
            try:
                res = minimize(
                    self.neg_log_posterior,
                    v0,
                    args=(D2,),
                    jac=True,
                    method="L-BFGS-B",
                    bounds=bounds,
                    options={"maxiter": self.config.maxiter, "ftol": 1e-7, "gtol": 1e-4},
                )
            except (np.linalg.LinAlgError, ValueError, FloatingPointError):
                continue
            if np.isfinite(res.fun) and res.fun < best_f:
                best_f, best_v = float(res.fun), np.asarray(res.x)
        return np.asarray(best_v, dtype=float)

    def condition(
        self,
        X: FloatArray,
        y: FloatArray,
        hyper: Hyper | None = None,
        scaling: tuple[float, float] | None = None,
    ) -> GP:
        """Condition on (X, y) with given (or the current) hyperparameters, no fitting.

        ``scaling`` = (y_mean, y_std) keeps another GP's standardization (e.g. a model with
        fantasized points added, whose hyperparameters, constant mean included, are those of
        the GP fitted without them); by default y is standardized by its own mean and std.
        """
        self._set_data(X, y, scaling)
        if hyper is not None:
            self.hyper = hyper
        if self.hyper is None:
            loc, _ = self._prior(self.X.shape[1])
            self.hyper = Hyper.from_vector(loc, self.X.shape[1])
        self._factorize(refit_mean=False)
        return self

    def _factorize(self, refit_mean: bool) -> None:
        """Cholesky of the kernel matrix; ``refit_mean``: set the constant mean to its GLS estimate."""
        assert self.hyper is not None
        h = self.hyper
        n = self.X.shape[0]
        U = h.kernel_inputs(self.X)
        K = matern52_from_r2(sq_dist(U, U, h.lengthscales), h.outputscale)
        jitter = 1e-10 * h.outputscale
        for _ in range(6):
            try:
                self._L = np.asarray(np.linalg.cholesky(K + (h.noise + jitter) * np.eye(n)), dtype=float)
                break
            except np.linalg.LinAlgError:
                jitter *= 100.0
        else:
            raise GPError("kernel matrix is not positive definite even with jitter; duplicate points with no noise?")
        if self._lin and refit_mean:
            Kinv = sla.cho_solve((self._L, True), np.eye(n), check_finite=False)
            beta = self._gls_beta(Kinv, self._z)
            h = self.hyper = replace(h, mean=float(beta[0] - 0.5 * np.sum(beta[1:])), bowl=None, slope=beta[1:])
        elif self.config.mean != "zero" and refit_mean:
            ones = sla.cho_solve((self._L, True), np.ones(n), check_finite=False)
            h = self.hyper = replace(
                h, mean=float(ones @ self._z / max(float(ones.sum()), 1e-300)), bowl=None, slope=None
            )
        elif self.config.mean == "zero" and (h.mean != 0.0 or h.bowl is not None or h.slope is not None):
            h = self.hyper = replace(h, mean=0.0, bowl=None, slope=None)
        elif self.config.mean != "bowl" and h.bowl is not None:
            h = self.hyper = replace(h, bowl=None)
        resid = self._z - h.mean_at(self.X)
        self._alpha = np.asarray(sla.cho_solve((self._L, True), resid, check_finite=False), dtype=float)

    # --- prediction ------------------------------------------------------------------------
    @property
    def fitted(self) -> bool:
        return self.hyper is not None and self._alpha.size > 0

    def predict_std_units(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and variance of the latent function, standardized units."""
        if not self.fitted:
            raise GPError("the GP has no data yet")
        assert self.hyper is not None
        h = self.hyper
        Xq = np.atleast_2d(np.asarray(Xq, dtype=float))
        Ks = matern52_from_r2(sq_dist(h.kernel_inputs(Xq), h.kernel_inputs(self.X), h.lengthscales), h.outputscale)
        mu = h.mean_at(Xq) + Ks @ self._alpha
        return mu, latent_var(self._L, Ks, h.outputscale)

    def predict_mean_units(self, Xq: FloatArray) -> FloatArray:
        """Posterior mean of the latent function, standardized units (no variance: a transfer prior's surface is
        evaluated at every step of the acquisition's maximizer, where only its mean is wanted)."""
        if not self.fitted:
            raise GPError("the GP has no data yet")
        assert self.hyper is not None
        h = self.hyper
        Xq = np.atleast_2d(np.asarray(Xq, dtype=float))
        Ks = matern52_from_r2(sq_dist(h.kernel_inputs(Xq), h.kernel_inputs(self.X), h.lengthscales), h.outputscale)
        return np.asarray(h.mean_at(Xq) + Ks @ self._alpha, dtype=float)

    def _mean_with_grad(
        self, Xq: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """Standardized mean and its gradient, with what the std's gradient reuses: (Uq, mu, dmu, Ks, F, il2), Uq the
        query points as the kernel sees them (Hyper.kernel_inputs: Xq itself without a warp)."""
        if not self.fitted:
            raise GPError("the GP has no data yet")
        assert self.hyper is not None
        h = self.hyper
        Xq = np.atleast_2d(np.asarray(Xq, dtype=float))
        il2 = 1.0 / h.lengthscales**2
        Uq, Jq = h.kernel_inputs_grad(Xq)
        r2 = sq_dist(Uq, h.kernel_inputs(self.X), h.lengthscales)
        Ks = matern52_from_r2(r2, h.outputscale)
        F = matern52_dr2_factor(r2, h.outputscale)
        m0, dm0 = h.mean_and_grad(Xq)
        Fa = F * self._alpha[None, :]
        dk = (Uq * Fa.sum(axis=1)[:, None] - Fa @ h.kernel_inputs(self.X)) * il2
        dmu = dm0 - (dk if Jq is None else dk * Jq)
        return Uq, np.asarray(m0 + Ks @ self._alpha, dtype=float), np.asarray(dmu, dtype=float), Ks, F, il2

    def predict_mean_with_grad(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Standardized posterior mean and its gradient w.r.t. the query points: (m,), (m, d)."""
        _, mu, dmu, _, _, _ = self._mean_with_grad(Xq)
        return mu, dmu

    def predict(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and standard deviation of the latent function, in the units of y."""
        mu, var = self.predict_std_units(Xq)
        return self.y_mean + self.y_std * mu, self.y_std * np.sqrt(var)

    def predict_with_grad(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Standardized mean, std and their gradients w.r.t. the query points: (m,), (m,), (m, d), (m, d)."""
        Uq, mu, dmu, Ks, F, il2 = self._mean_with_grad(Xq)
        h = self.hyper
        assert h is not None
        sd, dsd = latent_sd_with_grad(Uq, h.kernel_inputs(self.X), self._L, Ks, F, il2, h.outputscale)
        Jq = h.kernel_inputs_grad(np.atleast_2d(Xq))[1] if h.warp is not None else None
        return mu, sd, dmu, (dsd if Jq is None else dsd * Jq)


def latent_var(L: FloatArray, Ks: FloatArray, outputscale: float) -> FloatArray:
    """Posterior variance at m query points: ``outputscale - diag(Ks K^-1 Ks^T)``, K = L L^T, Ks (m, n)."""
    V = sla.solve_triangular(L, Ks.T, lower=True, check_finite=False)
    return np.asarray(np.maximum(outputscale - np.sum(V * V, axis=0), 1e-12 * outputscale), dtype=float)


def latent_sd_with_grad(
    Xq: FloatArray, X: FloatArray, L: FloatArray, Ks: FloatArray, F: FloatArray, il2: FloatArray, outputscale: float
) -> tuple[FloatArray, FloatArray]:
    """Posterior standard deviation (m,) and its gradient w.r.t. the query points (m, d).

    ``F`` is the Matérn derivative factor at (Xq, X) (kernel.matern52_dr2_factor), ``il2`` = 1 / lengthscales².
    Shared by the GP and by noisy EI (whose draws condition on a noise-free factor L of the same kernel).
    """
    Vt = sla.cho_solve((L, True), Ks.T, check_finite=False).T  # (m, n) = Ks K^-1
    var_raw = outputscale - np.sum(Ks * Vt, axis=1)
    var = np.maximum(var_raw, 1e-12 * outputscale)
    FV = F * Vt
    dvar = 2.0 * (Xq * FV.sum(axis=1)[:, None] - FV @ X) * il2
    dvar[var_raw <= 1e-12 * outputscale] = 0.0
    sd = np.sqrt(var)
    return sd, dvar / (2.0 * sd[:, None])
