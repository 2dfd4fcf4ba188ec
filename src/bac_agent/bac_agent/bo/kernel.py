"""The Matérn-5/2 ARD kernel, vectorized, with the derivatives the GP needs.

k(x, x') = s² (1 + √5 r + 5/3 r²) exp(−√5 r),  r² = Σ_k (x_k − x'_k)² / ℓ_k²

(same as scikit-learn's ``ConstantKernel(s²) * Matern(length_scale=ℓ, nu=2.5)``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

SQRT5 = float(np.sqrt(5.0))


def sq_dist(A: FloatArray, B: FloatArray, lengthscales: FloatArray) -> FloatArray:
    """Scaled squared distances r² between rows of A (m, d) and B (n, d): (m, n)."""
    a = A / lengthscales
    b = B / lengthscales
    r2 = np.sum(a * a, axis=1)[:, None] + np.sum(b * b, axis=1)[None, :] - 2.0 * (a @ b.T)
    return np.asarray(np.maximum(r2, 0.0), dtype=float)


def matern52_from_r2(r2: FloatArray, outputscale: float) -> FloatArray:
    r = np.sqrt(r2)
    return outputscale * (1.0 + SQRT5 * r + (5.0 / 3.0) * r2) * np.exp(-SQRT5 * r)


def matern52(A: FloatArray, B: FloatArray, lengthscales: FloatArray, outputscale: float) -> FloatArray:
    """Kernel matrix (m, n)."""
    return matern52_from_r2(sq_dist(A, B, lengthscales), outputscale)


def matern52_dr2_factor(r2: FloatArray, outputscale: float) -> FloatArray:
    """-dk/d(r²)·2 = s²·(5/3)(1 + √5 r) exp(−√5 r): the factor shared by every derivative.

    dk/dx_k      = −factor · (x_k − x'_k) / ℓ_k²
    dk/d log ℓ_k =  factor · (x_k − x'_k)² / ℓ_k²
    """
    r = np.sqrt(r2)
    return outputscale * (5.0 / 3.0) * (1.0 + SQRT5 * r) * np.exp(-SQRT5 * r)
