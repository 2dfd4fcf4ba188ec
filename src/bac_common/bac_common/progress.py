"""How progress is judged, the same everywhere in bac: the *gap* of a calibration.

``gap(J) = (J - J*) / (J_med - J*)`` where ``J*`` is the true optimum of the
problem and ``J_med`` the median J over uniformly random parameters: the share
of the distance between a typical calibration and the best one that is still
left. 0 = the optimum, 1 = a typical random calibration, negative is impossible
for a true J (only a noisy observation can undershoot J*).

"Found the optimum" means ``gap <= FOUND_GAP`` (5 %) for the **true, noise-free**
J of a recommendation, while the optimizer only ever saw noisy runs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bac_common.errors import BacError

FOUND_GAP = 0.05  # gap at or below which the optimum counts as found


class ProgressError(BacError, ValueError):
    """The reference values of a gap are unusable (e.g. J_med <= J*)."""


def gap(j: ArrayLike, j_star: float, j_med: float) -> NDArray[np.float64]:
    """(J - J*) / (J_med - J*), elementwise; NaN stays NaN."""
    if not (np.isfinite(j_star) and np.isfinite(j_med) and j_med > j_star):
        raise ProgressError(f"gap needs finite J* < J_med, got J*={j_star!r}, J_med={j_med!r}")
    return (np.asarray(j, dtype=float) - j_star) / (j_med - j_star)


def found(gap_value: ArrayLike, threshold: float = FOUND_GAP) -> NDArray[np.bool_]:
    """True where the gap says the optimum is found (NaN: not found)."""
    g = np.asarray(gap_value, dtype=float)
    return np.asarray(np.nan_to_num(g, nan=np.inf) <= threshold)


def runs_to_optimum(gaps: Sequence[float] | NDArray[np.float64], threshold: float = FOUND_GAP) -> float:
    """Number of runs after which the recommendation first had gap <= threshold.

    ``gaps[k]`` is the gap of the recommendation made after ``k + 1`` runs.
    Returns ``inf`` when the optimum was never found within these runs.
    """
    hit = np.flatnonzero(found(np.asarray(gaps, dtype=float), threshold))
    return float(hit[0] + 1) if hit.size else float("inf")


def runs_to_stay_found(gaps: Sequence[float] | NDArray[np.float64], threshold: float = FOUND_GAP) -> float:
    """Number of runs after which every later recommendation had gap <= threshold (found for good).

    A recommendation after one or two runs can land near the optimum by chance (a flat model's argmin);
    this one cannot. Returns ``inf`` when the last recommendation is not within the threshold.
    """
    ok = found(np.asarray(gaps, dtype=float), threshold)
    if ok.size == 0 or not ok[-1]:
        return float("inf")
    bad = np.flatnonzero(~ok)
    return float(bad[-1] + 2) if bad.size else 1.0


def median_j(
    true_j: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    bounds: ArrayLike,
    n: int = 200_000,
    seed: int = 0,
) -> float:
    """J_med of a problem: the median true J over ``n`` uniformly random parameter vectors.

    ``true_j`` maps an (n, d) array of parameters to (n,) noise-free J; ``bounds`` is (d, 2).
    """
    b = np.asarray(bounds, dtype=float)
    if b.ndim != 2 or b.shape[1] != 2 or np.any(b[:, 0] >= b[:, 1]):
        raise ProgressError(f"bounds must be (d, 2) with lower < upper, got shape {b.shape}")
    rng = np.random.default_rng(seed)
    thetas = b[:, 0] + rng.random((n, b.shape[0])) * (b[:, 1] - b[:, 0])
    return float(np.median(true_j(thetas)))
