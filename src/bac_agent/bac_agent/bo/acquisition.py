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
import warnings

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.special import erfcx, log_ndtr, logsumexp, ndtr, ndtri
from scipy.stats import qmc

from bac_agent.bo.gp import GP, latent_sd_with_grad, latent_var
from bac_agent.bo.kernel import matern52_dr2_factor, matern52_from_r2, sq_dist

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


def log_ei(mu: FloatArray, sd: FloatArray, best: float | FloatArray) -> FloatArray:
    """log EI for minimization, elementwise."""
    z = (best - mu) / sd
    return np.log(sd) + log_h(z)


def log_ei_with_grad(
    mu: FloatArray, sd: FloatArray, dmu: FloatArray, dsd: FloatArray, best: float | FloatArray
) -> tuple[FloatArray, FloatArray]:
    """log EI and its gradient w.r.t. the inputs, given μ, σ and their gradients (m, d).

    ``best`` is a scalar or one incumbent per point (m,).
    """
    z = (best - mu) / sd
    lh = log_h(z)
    lei = np.log(sd) + lh
    # d EI/dμ = −Φ(z), d EI/dσ = φ(z); divide by EI = σ·h in log space
    r_phi_cdf = np.exp(log_ndtr(z) - lh)  # Φ(z)/h(z)
    r_phi = np.exp(-0.5 * z * z - _LOG_SQRT_2PI - lh)  # φ(z)/h(z)
    grad = (-r_phi_cdf / sd)[:, None] * dmu + (r_phi / sd)[:, None] * dsd
    return lei, grad


class NoisyEI:
    """Noisy Expected Improvement (Letham et al. 2019, "Constrained Bayesian optimization with noisy
    experiments"), in log form, for a fitted :class:`~bac_agent.bo.gp.GP`.

    With noisy runs nobody knows the best value seen so far. Plain EI plugs in an estimate (the best
    posterior mean); NEI integrates over it: ``n_samples`` joint draws of the latent J at the observed
    points (quasi-random, fixed for one ask), and for each draw the GP conditioned *noise-free* on the
    drawn values gives an analytic EI over that draw's best. The acquisition is their mean:
    log NEI(x) = logsumexp_s log EI_s(x) − log S. Points near the incumbent score by how much better
    they may be than the incumbent *jointly*, which makes local refinement under noise much cheaper.
    """

    def __init__(
        self, gp: GP, n_samples: int, rng: np.random.Generator, incumbents: NDArray[np.bool_] | None = None
    ) -> None:
        """``incumbents``: which observed points may be the incumbent (e.g. the runs that kept every outcome
        limit); all of them by default."""
        h = gp.hyper
        if h is None or gp.X.shape[0] == 0:
            raise ValueError("NoisyEI needs a fitted GP")
        self.X = h.kernel_inputs(gp.X)  # as the kernel sees them (GPConfig.warp; gp.X itself without it)
        self.ls = h.lengthscales
        self.os = h.outputscale
        self.hyper = h
        n = self.X.shape[0]
        K = matern52_from_r2(sq_dist(self.X, self.X, self.ls), self.os)
        mu_b, _ = gp.predict_std_units(gp.X)
        # posterior covariance of f at X: K - K (K + s2 I)^-1 K, sampled through its eigendecomposition
        # (positive semidefinite up to round-off; negative eigenvalues clipped)
        V = sla.solve_triangular(gp._L, K, lower=True, check_finite=False)
        cov = K - V.T @ V
        w, Q = np.linalg.eigh(0.5 * (cov + cov.T))
        root = Q * np.sqrt(np.maximum(w, 0.0))
        S = max(1, int(n_samples))
        Z = _normal_qmc(n, S, rng)
        F = mu_b[:, None] + root @ Z  # (n, S)
        if incumbents is not None and np.any(incumbents):
            self.best = F[np.asarray(incumbents, dtype=bool)].min(axis=0)  # each draw's incumbent
        else:
            self.best = F.min(axis=0)
        jitter = 1e-8 * self.os
        for _ in range(8):
            try:
                self._L0 = np.asarray(np.linalg.cholesky(K + jitter * np.eye(n)), dtype=float)
                break
            except np.linalg.LinAlgError:
                jitter *= 10.0
        else:  # pragma: no cover - K + 1e-1*os*I is always positive definite
            raise ValueError("kernel matrix not positive definite")
        self.A = np.asarray(
            sla.cho_solve((self._L0, True), F - h.mean_at(gp.X)[:, None], check_finite=False), dtype=float
        )
        self.log_s = math.log(S)

    def __call__(self, Xq: FloatArray) -> FloatArray:
        """log NEI at the rows of ``Xq`` (m, d), standardized units."""
        Xq = np.atleast_2d(Xq)
        Ks = matern52_from_r2(sq_dist(self.hyper.kernel_inputs(Xq), self.X, self.ls), self.os)
        mu = self.hyper.mean_at(Xq)[:, None] + Ks @ self.A  # (m, S): each draw's noise-free conditional mean
        sd = np.sqrt(latent_var(self._L0, Ks, self.os))  # the same for every draw
        lei = log_ei(mu, sd[:, None], self.best[None, :])
        return np.asarray(logsumexp(lei, axis=1) - self.log_s, dtype=float)

    def value_and_grad(self, Xq: FloatArray) -> tuple[FloatArray, FloatArray]:
        """log NEI (m,) and its gradient w.r.t. the rows of ``Xq`` (m, d)."""
        Xq = np.atleast_2d(Xq)
        m, d = Xq.shape
        Uq, Jq = self.hyper.kernel_inputs_grad(Xq)  # (GPConfig.warp; Xq itself and None without it)
        r2 = sq_dist(Uq, self.X, self.ls)
        Ks = matern52_from_r2(r2, self.os)
        m0, dm0 = self.hyper.mean_and_grad(Xq)
        mu = m0[:, None] + Ks @ self.A  # (m, S)
        S = mu.shape[1]
        il2 = 1.0 / self.ls**2
        Fk = matern52_dr2_factor(r2, self.os)  # (m, n)
        FA = Fk @ self.A  # (m, S)
        # sum_n Fk[m, n] A[n, s] X[n, :] as one batched matrix product (m, S, n) @ (n, d)
        FAX = np.matmul((Fk[:, :, None] * self.A[None, :, :]).transpose(0, 2, 1), self.X)
        dk = (Uq[:, None, :] * FA[:, :, None] - FAX) * il2
        dmu = dm0[:, None, :] - (dk if Jq is None else dk * Jq[:, None, :])
        sd, dsd = latent_sd_with_grad(Uq, self.X, self._L0, Ks, Fk, il2, self.os)
        if Jq is not None:
            dsd = dsd * Jq
        lei, g = log_ei_with_grad(
            mu.ravel(),
            np.repeat(sd, S),
            dmu.reshape(m * S, d),
            np.repeat(dsd, S, axis=0),
            np.tile(self.best, m),
        )
        lei = lei.reshape(m, S)
        val = logsumexp(lei, axis=1)
        wts = np.exp(lei - val[:, None])  # softmax over the draws
        grad = np.matmul(wts[:, None, :], g.reshape(m, S, d))[:, 0, :]
        return np.asarray(val - self.log_s, dtype=float), np.asarray(grad, dtype=float)


def _normal_qmc(n: int, s: int, rng: np.random.Generator) -> FloatArray:
    """(n, s) standard normal draws, quasi-random over the s draws (scrambled Sobol, inverse CDF)."""
    seed = int(rng.integers(0, 2**63 - 1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # balance warning for s != 2^m
        u = qmc.Sobol(d=n, scramble=True, seed=seed).random(s) if n <= 21201 else rng.random((s, n))
    u = np.clip(u, 1e-10, 1.0 - 1e-10)
    return np.asarray(ndtri(u).T, dtype=float)
