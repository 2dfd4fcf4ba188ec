"""Expected Improvement for minimization, in a numerically stable log form (LogEI).

EI(x) = σ·h(z), z = (best − μ)/σ, h(z) = φ(z) + z·Φ(z). For very negative z, h
underflows in floating point although its logarithm is perfectly finite; log h is
computed as in Ament et al. 2023 ("Unexpected improvements to expected
improvement"): directly for z > −1, else as log φ(z) + log(1 − |z|·m(|z|)) with
the Mills ratio m written through ``erfcx`` and an asymptotic branch beyond
1/√eps. Gradients are analytic, so the maximizer (L-BFGS-B) works in any dimension.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.special import erfcx, log_ndtr, ndtr

FloatArray = NDArray[np.float64]

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_LOG_SQRT_PI_2 = 0.5 * math.log(math.pi / 2.0)
_INV_SQRT_EPS = 1.0 / math.sqrt(np.finfo(float).eps)


def _log1mexp(x: FloatArray) -> FloatArray:
    """log(1 − exp(x)) for x < 0, accurate everywhere."""
    return np.where(x > -math.log(2.0), np.log(-np.expm1(x)), np.log1p(-np.exp(x)))


def log_h(z: FloatArray) -> FloatArray:
    """log(φ(z) + z·Φ(z)), stable for all z."""
    z = np.asarray(z, dtype=float)
    out = np.empty_like(z)
    big = z > -1.0
    zb = z[big]
    out[big] = np.log(np.exp(-0.5 * zb * zb - _LOG_SQRT_2PI) + zb * ndtr(zb))
    small = ~big
    zs = z[small]
    logphi = -0.5 * zs * zs - _LOG_SQRT_2PI
    mid = zs > -_INV_SQRT_EPS
    res = np.empty_like(zs)
    a = np.abs(zs[mid])
    # 1 - |z| m(|z|), m(t) = Φ(-t)/φ(t) = sqrt(pi/2) erfcx(t/sqrt2)
    log_zm = np.log(a) + _LOG_SQRT_PI_2 + np.log(erfcx(a / math.sqrt(2.0)))
    res[mid] = logphi[mid] + _log1mexp(log_zm)
    res[~mid] = logphi[~mid] - 2.0 * np.log(np.abs(zs[~mid]))
    out[small] = res
    return out


def log_ei(mu: FloatArray, sd: FloatArray, best: float) -> FloatArray:
    """log EI for minimization, elementwise."""
    z = (best - mu) / sd
    return np.log(sd) + log_h(z)


def log_ei_with_grad(
    mu: FloatArray, sd: FloatArray, dmu: FloatArray, dsd: FloatArray, best: float
) -> tuple[FloatArray, FloatArray]:
    """log EI and its gradient w.r.t. the inputs, given μ, σ and their gradients (m, d)."""
    z = (best - mu) / sd
    lh = log_h(z)
    lei = np.log(sd) + lh
    # d EI/dμ = −Φ(z), d EI/dσ = φ(z); divide by EI = σ·h in log space
    r_phi_cdf = np.exp(log_ndtr(z) - lh)  # Φ(z)/h(z)
    r_phi = np.exp(-0.5 * z * z - _LOG_SQRT_2PI - lh)  # φ(z)/h(z)
    grad = (-r_phi_cdf / sd)[:, None] * dmu + (r_phi / sd)[:, None] * dsd
    return lei, grad
