"""What an earlier model knows of J, carried to a new campaign: the simulator's surrogate as a prior (issue 23).

A :class:`SourceSurface` is a smooth model of J over the campaign's unit cube learned elsewhere: the simulation
phase (``bac reduce``'s J_mu through the meta-parameter file), a campaign on another car, or any set of runs over
the same tuned parameters. It is a GP posterior mean fitted to points of that model (``fit``), stored with the
engine's state, and used in two ways:

* its argmin is the first run of the campaign (the paper's best guess, now from the model rather than a file);
* its shape is the GP's **prior mean** on the car: ``m(x) = a + b · s(x)``, where ``s`` is the source's J
  standardized by the source's own mean and spread, and the car's runs are put on the same scale. The offset
  ``a`` and scale ``b`` are learned: a flat prior on ``a``, ``b ~ N(1, scale_sd²)``; their
  posterior given the runs under the current kernel (Rasmussen & Williams 2006, sec. 2.7, "explicit basis
  functions"); a GP residual carries what the source does not explain.

Whether the source is used at all is decided by the car's runs, at every fit: the marginal likelihood of the runs
under ``a + b s(x) + residual`` is compared with a model without the source (``a + residual``, the same scale),
and the posterior probability of the source, from a prior probability ``weight``, is the **transfer weight**.
While it is at least 0.5 the source's trend is the prior mean, and the engine's acquisition averages the expected
improvement of that model (weight w) and of the model without the source (``without_source``, 1 - w); once the
runs disagree with the source, the weight falls and the engine returns to its own model (the bowl, the output
warp). A simulator that is right needs no
runs to be believed; one that is wrong costs the few runs that show it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.stats import qmc

from bac_agent.bo.gp import GP, GPConfig, GPError, Hyper
from bac_agent.bo.kernel import matern52_from_r2, sq_dist

FloatArray = NDArray[np.float64]

# the GP the source points are fitted with: a learned constant mean, a low noise (the points are a model's
# predictions or averaged runs), the engine's kernel and priors otherwise
SOURCE_GP = GPConfig(mean="constant", noise_loc=-7.0, noise_scale=1.0, ls_average=0.0)
NOISY_SOURCE_GP = GPConfig(mean="constant", ls_average=0.0)  # runs of an earlier campaign: the engine's noise prior
MAX_SOURCE_POINTS = 512


def spread_subset(X: FloatArray, m: int) -> NDArray[np.intp]:
    """Indices (sorted) of ``m`` rows of ``X`` spread over their region: greedy farthest-point selection (each next
    row the one farthest from those taken), from the row nearest to the rows' centroid; all rows when there are
    at most ``m``. Duplicates are taken last."""
    X = np.atleast_2d(np.asarray(X, dtype=float))
    n = X.shape[0]
    if n <= m:
        return np.arange(n)
    first = int(np.argmin(np.sum((X - X.mean(axis=0)) ** 2, axis=1)))
    taken = np.zeros(n, dtype=bool)
    order = np.empty(m, dtype=np.intp)
    d2 = np.full(n, np.inf)
    j = first
    for i in range(m):  # m steps of O(n d) each (a source is fitted once per campaign)
        order[i], taken[j] = j, True
        d2 = np.minimum(d2, np.sum((X - X[j]) ** 2, axis=1))
        j = int(np.argmax(np.where(taken, -1.0, d2)))
    return np.sort(order)


@dataclass(frozen=True)
class SourceSurface:
    """A model of J over the unit cube learned elsewhere (see the module doc)."""

    X: FloatArray  # (m, d) unit cube
    y: FloatArray  # (m,) J at X (the source's values)
    hyper: Hyper  # its GP's hyperparameters (standardized units of y)
    label: str = ""  # where it came from (journaled, shown in the report)
    noisy: bool = False  # the points are noisy runs (an earlier campaign), not a model's predictions

    def __post_init__(self) -> None:
        X = np.atleast_2d(np.asarray(self.X, dtype=float))
        y = np.asarray(self.y, dtype=float).ravel()
        if X.shape[0] != y.shape[0] or X.shape[0] < 2:
            raise GPError(f"a source surface needs at least 2 matching points, got X {X.shape} and y {y.shape}")
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
            raise GPError("a source surface's points and values must be finite")
        object.__setattr__(self, "X", X)
        object.__setattr__(self, "y", y)
        gp = GP(SOURCE_GP).condition(X, y, self.hyper)
        object.__setattr__(self, "_gp", gp)

    @property
    def dim(self) -> int:
        return int(self.X.shape[1])

    @property
    def loc(self) -> float:
        """The J the standardized source value 0 stands for (its points' mean)."""
        return float(self._gp.y_mean)  # type: ignore[attr-defined]

    @property
    def scale(self) -> float:
        """The J one standardized unit stands for (its points' standard deviation)."""
        return float(self._gp.y_std)  # type: ignore[attr-defined]

    @classmethod
    def fit(
        cls,
        X: FloatArray,
        y: FloatArray,
        label: str = "",
        rng: np.random.Generator | None = None,
        noisy: bool = False,
        outcome: bool = False,
    ) -> SourceSurface:
        """Fit the source GP (MAP hyperparameters) to points ``X`` (unit cube) and values ``y`` (J); ``noisy``:
        they are runs (the engine's noise prior), not a model's predictions (a low noise). Of more than
        MAX_SOURCE_POINTS points, J's source keeps the 64 lowest and a spread of the rest (where J is low matters
        most); an ``outcome``'s source (a limited outcome's values: a limit may lie anywhere in its range, and its
        lowest values, e.g. the smallest travels, are no better known than the others) keeps the points spread over
        the cube (``spread_subset``)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        y = np.asarray(y, dtype=float).ravel()
        if X.shape[0] > MAX_SOURCE_POINTS and outcome:
            keep = spread_subset(X, MAX_SOURCE_POINTS)
            X, y = X[keep], y[keep]
        elif X.shape[0] > MAX_SOURCE_POINTS:  # keep the best points and a spread of the rest
            order = np.argsort(y)
            keep = np.unique(
                np.concatenate([order[:64], np.linspace(0, y.size - 1, MAX_SOURCE_POINTS - 64).astype(int)])
            )
            X, y = X[keep], y[keep]
        gp = GP(NOISY_SOURCE_GP if noisy else SOURCE_GP).fit(X, y, rng if rng is not None else np.random.default_rng(0))
        assert gp.hyper is not None
        return cls(X, y, gp.hyper, label, noisy)

    @classmethod
    def from_function(cls, f: Any, dim: int, n: int = 128, label: str = "", seed: int = 0) -> SourceSurface:
        """Sample ``f`` (unit cube (n, d) -> (n,) J) at ``n`` Sobol points and fit the surface to them."""
        U = qmc.Sobol(dim, scramble=True, seed=seed).random(n)
        return cls.fit(U, np.asarray(f(U), dtype=float), label)

    # --- values ------------------------------------------------------------------------------------
    def standardized(self, U: FloatArray) -> FloatArray:
        """s(U): the source's J at unit-cube points, standardized by its own loc and scale."""
        mu: FloatArray = self._gp.predict_mean_units(np.atleast_2d(U))  # type: ignore[attr-defined]
        return mu

    def standardized_and_grad(self, U: FloatArray) -> tuple[FloatArray, FloatArray]:
        U = np.atleast_2d(U)
        # the last call's result is kept: an outcome model evaluates its source twice at the same points (its
        # trend in the GP's mean and the coefficients' variance), at every step of the acquisition's maximizer
        last = getattr(self, "_last", None)
        if last is not None and last[0].shape == U.shape and np.array_equal(last[0], U):
            return last[1], last[2]
        mu, dmu = self._gp.predict_mean_with_grad(U)  # type: ignore[attr-defined]
        out = (np.asarray(mu, dtype=float), np.asarray(dmu, dtype=float))
        object.__setattr__(self, "_last", (U.copy(), *out))
        return out

    def predict_j(self, U: FloatArray) -> FloatArray:
        """The source's J at unit-cube points."""
        return self.loc + self.scale * self.standardized(U)

    def argmin(self, seed: int = 0) -> FloatArray:
        """The unit-cube minimizer of the source's J (Sobol candidates, then L-BFGS-B from the best 4)."""
        d = self.dim
        cand = np.vstack([qmc.Sobol(d, scramble=True, seed=seed).random(1024), self.X])
        s = self.standardized(cand)
        starts = cand[np.argsort(s)[:4]]

        def f(u: FloatArray) -> tuple[float, FloatArray]:
            v, g = self.standardized_and_grad(u[None, :])
            return float(v[0]), g[0]

        best, best_v = starts[0], float(np.min(s))
        for u0 in starts:
            res = minimize(f, u0, jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * d)
            if res.success or np.isfinite(res.fun):
                u = np.clip(res.x, 0.0, 1.0)
                v = float(self.standardized(u[None, :])[0])
                if v < best_v:
                    best, best_v = u, v
        return np.asarray(best, dtype=float)

    # --- state --------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "X": self.X.tolist(),
            "y": self.y.tolist(),
            "hyper": self.hyper.to_dict(),
            "label": self.label,
            "noisy": self.noisy,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SourceSurface:
        try:
            return cls(
                np.asarray(d["X"], dtype=float),
                np.asarray(d["y"], dtype=float),
                Hyper.from_dict(d["hyper"]),
                str(d.get("label", "")),
                bool(d.get("noisy", False)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise GPError(f"malformed source surface: {exc}") from exc


@dataclass(frozen=True)
class PriorTrend:
    """The prior mean ``a + b · s(x)`` of the car's GP (standardized units of the car's runs)."""

    source: SourceSurface
    a: float
    b: float

    def value(self, Xq: FloatArray) -> FloatArray:
        return self.a + self.b * self.source.standardized(Xq)

    def value_and_grad(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]:
        s, g = self.source.standardized_and_grad(Xq)
        return self.a + self.b * s, self.b * g


@dataclass(frozen=True)
class TransferFit:
    """The outcome of weighing the source against the car's runs (journaled with every proposal)."""

    weight: float  # posterior probability of the model with the source
    a: float  # posterior mean of the offset
    b: float  # posterior mean of the scale
    b_sd: float  # its posterior standard deviation
    log_bayes_factor: float  # log p(runs | source) - log p(runs | no source)
    # the kernel of the model without the source (an offset and a residual, on the source's scale): the other
    # member of the model average (``without_source``); not journaled
    alt_hyper: Hyper | None = field(default=None, compare=False, repr=False)
    # log p(runs' contrasts | source), on the source's standardized scale (the restricted likelihood): sources of
    # different scales are compared on J's after subtracting (n - 1) log(scale) (Engine's prior_variants); not journaled
    log_lik: float = field(default=math.nan, compare=False, repr=False)

    @property
    def used(self) -> bool:
        return self.weight >= 0.5 - 1e-9  # a tie (one run says nothing about the shape) keeps the source

    def to_dict(self) -> dict[str, float]:
        return {
            "transfer_weight": self.weight,
            "prior_offset": self.a,
            "prior_scale": self.b,
            "prior_scale_sd": self.b_sd,
            "log_bayes_factor": self.log_bayes_factor,
        }


def _kernel(X: FloatArray, h: Hyper) -> FloatArray:
    n = X.shape[0]
    K = matern52_from_r2(sq_dist(X, X, h.lengthscales), h.outputscale)
    K.flat[:: n + 1] += h.noise + 1e-10 * h.outputscale
    return K


def _restricted_log_likelihood(r: FloatArray, C: FloatArray) -> float:
    """log p(r) for r ~ N(c·1, C) with the constant c under a flat prior (the likelihood of r's contrasts, up to a
    constant that is the same for every model of the same runs): the offset of the car's J against the source's
    is left out of the comparison, which is about shape only."""
    n = r.shape[0]
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return -math.inf
    a = sla.cho_solve((L, True), r, check_finite=False)
    o = sla.cho_solve((L, True), np.ones(n), check_finite=False)
    so = float(np.sum(o))
    quad = float(r @ a) - float(np.sum(a)) ** 2 / so
    log_det = float(np.sum(np.log(np.diag(L))))
    return float(-0.5 * quad - log_det - 0.5 * math.log(so) - 0.5 * (n - 1) * math.log(2.0 * math.pi))


def weigh_source(
    X: FloatArray,
    z: FloatArray,
    s: FloatArray,
    h1: Hyper,
    h0: Hyper,
    scale_sd: float,
    weight: float,
) -> TransferFit:
    """The posterior of (a, b) and of the source's relevance, given runs ``z`` at ``X`` on the source's scale.

    ``s`` is the standardized source at ``X``; ``h1`` the residual kernel of the model with the source, ``h0``
    the kernel of the model without it (an offset and a residual only). The offset has a flat prior in both
    models and the scale ``b ~ N(1, scale_sd²)`` is integrated out, so the two marginal likelihoods compare the
    shapes fairly at any number of runs (one run says nothing about a shape: the weight stays the prior's).
    """
    n = X.shape[0]
    K1 = _kernel(X, h1)
    lml1 = _restricted_log_likelihood(z - s, K1 + scale_sd**2 * np.outer(s, s))
    lml0 = _restricted_log_likelihood(z, _kernel(X, h0))
    # posterior of the coefficients under the source model: flat on a, N(1, scale_sd²) on b
    H = np.column_stack([np.ones(n), s])
    Kinv_H = np.linalg.solve(K1, H)
    prior_prec = np.diag([0.0, 1.0 / scale_sd**2])
    A = H.T @ Kinv_H + prior_prec
    rhs = Kinv_H.T @ z + prior_prec @ np.array([0.0, 1.0])
    cov = np.linalg.pinv(A)
    beta = cov @ rhs
    if math.isfinite(lml1) and math.isfinite(lml0):
        lbf = lml1 - lml0
    else:
        lbf = -math.inf if not math.isfinite(lml1) else math.inf
    prior_logit = math.log(weight / (1.0 - weight)) if 0.0 < weight < 1.0 else (math.inf if weight >= 1 else -math.inf)
    t = lbf + prior_logit
    w = 1.0 / (1.0 + math.exp(-t)) if t > -700 else 0.0
    return TransferFit(
        float(w),
        float(beta[0]),
        float(beta[1]),
        float(math.sqrt(max(cov[1, 1], 0.0))),
        float(lbf),
        alt_hyper=h0,
        log_lik=float(lml1),
    )


@dataclass(frozen=True)
class TransferSettings:
    """How a source is weighed against the car's runs (EngineConfig's prior_* fields)."""

    weight: float = 0.5  # prior probability that the source describes this car
    scale_sd: float = 0.5  # prior sd of the scale b around 1
    residual_os: float = 0.25  # prior median of the residual GP's variance (source-standardized units)


def fit_with_source(
    config: GPConfig,
    X: FloatArray,
    y: FloatArray,
    source: SourceSurface,
    settings: TransferSettings,
    rng: np.random.Generator,
    previous: Hyper | None = None,
) -> tuple[GP, TransferFit]:
    """The car's GP with the source's trend as its prior mean, and the weight of the source.

    The runs ``y`` (J) are put on the source's scale; with 3 runs or more the residual kernel and the kernel of
    the model without the source are MAP fits (the residual's around ``residual_os``), with fewer they are the
    priors' modes. The returned GP carries ``a + b s(x)`` (posterior means) in its hyperparameters' ``prior``.
    """
    n = X.shape[0]
    scaling = (source.loc, source.scale)
    cfg0 = replace(config, mean="constant", warp=False)  # (the input warping is not learned with a source)
    cfg1 = replace(cfg0, os_loc=math.log(settings.residual_os))
    gp0 = GP(cfg0, hyper=previous)
    gp1 = GP(cfg1, hyper=previous)
    gp0._set_data(X, y, scaling)
    gp1._set_data(X, y, scaling)
    z = gp1._z
    s = source.standardized(gp1.X)
    if n >= 3:
        h0 = Hyper.from_vector(gp0._map_hyper(rng))
        gp1._offset = s
        h1 = Hyper.from_vector(gp1._map_hyper(rng))
        fit = weigh_source(gp1.X, z, s, h1, h0, settings.scale_sd, settings.weight)
        gp1._offset = fit.b * s
        gp1.hyper = h1
        # the residual's kernel again on what the learned scale leaves: a refinement from h1 (the offset moved
        # from s to b·s), not a new search (one start: issue 23's latency)
        h1 = Hyper.from_vector(gp1._map_hyper(rng, warm_only=True))
        gp1._offset = 0.0
    else:
        loc0, _ = gp0._prior(X.shape[1])
        loc1, _ = gp1._prior(X.shape[1])
        h0, h1 = Hyper.from_vector(loc0), Hyper.from_vector(loc1)
    fit = weigh_source(gp1.X, z, s, h1, h0, settings.scale_sd, settings.weight)
    gp1.hyper = replace(h1, mean=0.0, bowl=None, prior=PriorTrend(source, fit.a, fit.b))
    gp1._factorize(refit_mean=False)
    return gp1, fit


def without_source(config: GPConfig, X: FloatArray, y: FloatArray, source: SourceSurface, hyper: Hyper) -> GP:
    """The model the source is weighed against (``weigh_source``'s ``h0``): a constant mean (its GLS value) and a
    GP on the runs ``y`` put on the source's scale, so that its predictions and expected improvements are in the
    same units as the model with the source (the two members of the model average)."""
    gp = GP(replace(config, mean="constant"))
    gp._set_data(X, y, (source.loc, source.scale))
    gp.hyper = replace(hyper, mean=0.0, bowl=None, prior=None)
    gp._factorize(refit_mean=True)
    return gp


__all__ = [
    "PriorTrend",
    "SourceSurface",
    "TransferFit",
    "TransferSettings",
    "fit_with_source",
    "spread_subset",
    "weigh_source",
    "without_source",
]
