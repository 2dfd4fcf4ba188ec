"""Output warping: the runs pass through a fitted Yeo-Johnson transform before the GP sees them.

A comfort KPI, and most objectives an optimizer meets, is not Gaussian over the domain: a few
runs far up a flank (a stiff corner of the damping map) and many near the bottom once the
campaign has found the basin. A stationary GP fitted to such values spends its variance on
the flank and calls the bottom flat. The power transform of Yeo and Johnson (2000),

    ψ(z; λ) = ((z + 1)^λ − 1) / λ                 z ≥ 0
              −((1 − z)^(2 − λ) − 1) / (2 − λ)    z < 0

applied to the standardized runs z, with λ the maximum-likelihood value that makes them most
Gaussian (the profile likelihood of scipy.stats.yeojohnson_llf, maximized over [0, 2]), makes
the model's job the ordinary one again (HEBO, Cowen-Rivers et al. 2022, does the same). λ = 1 is
the identity. ψ is strictly increasing, so the argmin of the posterior mean and the ordering of
the runs do not change; only the GP's view of the distances between values does.

λ is kept in [0, 2]: there ψ maps the real line onto itself (for λ < 0 the upper branch is
bounded, for λ > 2 the lower), so every posterior mean has a J it stands for. λ is refitted
from the runs at every fit (a pure function of them: nothing to store in the engine's state).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize_scalar

FloatArray = NDArray[np.float64]

LAMBDA_BOUNDS = (0.0, 2.0)
MIN_RUNS = 3  # fewer runs than this: the identity (no shape can be estimated from two values)
WARPS = ("none", "yeo-johnson")  # EngineConfig.output_warp


def _psi(z: FloatArray, lam: float | FloatArray) -> FloatArray:
    """ψ(z; λ), broadcasting z against λ (a scalar, or e.g. a column of λ against a row of runs)."""
    a = np.log1p(np.abs(z))
    lam = np.asarray(lam, dtype=float)
    q = 2.0 - lam
    with np.errstate(over="ignore", invalid="ignore"):  # the branch not taken may overflow; np.where drops it
        upper = np.where(np.abs(lam) < 1e-12, a, np.expm1(lam * a) / np.where(np.abs(lam) < 1e-12, 1.0, lam))
        lower = -np.where(np.abs(q) < 1e-12, a, np.expm1(q * a) / np.where(np.abs(q) < 1e-12, 1.0, q))
    return np.asarray(np.where(z >= 0.0, upper, lower), dtype=float)


def _psi_inv(t: FloatArray, lam: float) -> FloatArray:
    out = np.empty_like(t)
    pos = t >= 0.0
    tp, tn = t[pos], t[~pos]
    out[pos] = np.expm1(tp) if abs(lam) < 1e-12 else np.expm1(np.log1p(lam * tp) / lam)
    out[~pos] = -np.expm1(-tn) if abs(lam - 2.0) < 1e-12 else -np.expm1(np.log1p(-(2.0 - lam) * tn) / (2.0 - lam))
    return out


def _psi_grad(z: FloatArray, lam: float) -> FloatArray:
    """dψ/dz (> 0 everywhere for λ in [0, 2])."""
    return np.where(z >= 0.0, np.power(1.0 + np.abs(z), lam - 1.0), np.power(1.0 + np.abs(z), 1.0 - lam))


def _log_likelihood(z: FloatArray, lams: FloatArray) -> FloatArray:
    """The Yeo-Johnson profile log-likelihood of each λ in ``lams`` (the normal's mean and variance profiled
    out), as scipy.stats.yeojohnson_llf, for many λ at once: (len(lams),)."""
    with np.errstate(over="ignore", invalid="ignore"):
        var = np.var(_psi(z[None, :], lams[:, None]), axis=1)
    jac = np.sum(np.sign(z) * np.log1p(np.abs(z)))  # Σ sign(z) log(1 + |z|): times (λ − 1), the log-Jacobian
    return np.asarray(-0.5 * z.size * np.log(var) + (lams - 1.0) * jac, dtype=float)


def _lambda_mle(z: FloatArray) -> float:
    """argmax over λ in LAMBDA_BOUNDS of the profile log-likelihood: a grid of 41, then a bounded refinement
    around the best node (the clipped value of scipy.stats.yeojohnson_normmax, at a tenth of its cost)."""
    lo, hi = LAMBDA_BOUNDS
    grid = np.linspace(lo, hi, 41)
    llf = _log_likelihood(z, grid)
    if not np.any(np.isfinite(llf)):
        return 1.0
    i = int(np.nanargmax(np.where(np.isfinite(llf), llf, -np.inf)))
    step = grid[1] - grid[0]
    a, b = max(lo, grid[i] - step), min(hi, grid[i] + step)
    res = minimize_scalar(
        lambda v: -float(_log_likelihood(z, np.array([v]))[0]), bounds=(a, b), method="bounded", options={"xatol": 1e-5}
    )
    best = float(res.x) if res.success and -res.fun >= llf[i] else float(grid[i])
    return min(max(best, lo), hi)


@dataclass(frozen=True)
class OutputWarp:
    """t = ψ((y − loc) / scale; λ): what the GP is fitted to, and the way back to J."""

    loc: float = 0.0
    scale: float = 1.0
    lam: float = 1.0

    @classmethod
    def fit(cls, y: FloatArray) -> OutputWarp:
        """The Yeo-Johnson warp that makes the standardized ``y`` most Gaussian (λ clipped to [0, 2])."""
        y = np.asarray(y, dtype=float)
        if y.size < MIN_RUNS or not np.all(np.isfinite(y)):
            return cls()
        loc, scale = float(np.mean(y)), float(np.std(y))
        if not scale > 1e-12 * max(1.0, abs(loc)):  # all runs equal (up to rounding): no shape to fit
            return cls()
        return cls(loc, scale, _lambda_mle((y - loc) / scale))

    @classmethod
    def for_runs(cls, kind: str, y: FloatArray) -> OutputWarp:
        """The warp an ``EngineConfig.output_warp`` of ``kind`` gives these runs (``"none"``: the identity)."""
        return cls.fit(y) if kind == "yeo-johnson" else cls()

    @property
    def is_identity(self) -> bool:
        return self.lam == 1.0

    def forward(self, y: FloatArray) -> FloatArray:
        """J → the GP's units."""
        return _psi((np.asarray(y, dtype=float) - self.loc) / self.scale, self.lam)

    def inverse(self, t: FloatArray) -> FloatArray:
        """The GP's units → J."""
        return self.loc + self.scale * _psi_inv(np.asarray(t, dtype=float), self.lam)

    def inverse_mean_std(self, mean_t: FloatArray, std_t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A posterior (mean, std) in the GP's units as J: the J at the mean (the predictive median, ψ
        being monotone) and the std carried through ψ⁻¹'s slope there (delta method)."""
        mean_t = np.asarray(mean_t, dtype=float)
        z = _psi_inv(mean_t, self.lam)
        slope = self.scale / _psi_grad(z, self.lam)
        return self.loc + self.scale * z, np.abs(slope) * np.asarray(std_t, dtype=float)
