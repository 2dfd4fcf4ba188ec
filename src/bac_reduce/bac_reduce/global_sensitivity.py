"""Global sensitivity of J on the simulator (SALib), beside the paper's one-at-a-time sweep from θ̄.

The paper's significance test (eq. 4) looks at one point: how much worse J gets when one parameter alone is
moved across its range from the best calibration θ̄. A global method looks at the whole box: Morris' elementary
effects (the change of J when one parameter moves by a fixed step, from many random starting points; ``mu_star``
= the mean of their absolute values, ``sigma`` = their spread: interactions and curvature) or Sobol' indices
(the share of J's variance over the box a parameter explains, alone ``S1`` or with all its interactions ``ST``).
Both come from SALib (Herman & Usher 2017), on the noise-free simulator.

They answer different questions, and the report shows both: a parameter can matter much on average over the box
and not at all at the optimum (the optimum sits where it has no effect, e.g. an ADD gain whose term is off there),
or little on average and much at the optimum (it only matters once the others are good). Here a parameter is
*globally significant* when its ``mu_star`` exceeds T·J(θ̄) (Morris) or its ``ST`` exceeds T (Sobol'); the
report lists where that and the one-at-a-time decision disagree.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bac_reduce.analysis import ReductionError

FloatArray = NDArray[np.float64]
METHODS = ("morris", "sobol", "none")


@dataclass(frozen=True)
class GlobalSensitivity:
    """Indices of each parameter: Morris ``mu_star``/``sigma`` (J units) or Sobol' ``S1``/``ST`` (shares)."""

    method: str
    names: tuple[str, ...]
    index: FloatArray  # the index used for significance: mu_star (J units) or ST (share of the variance)
    spread: FloatArray  # sigma (Morris) or S1 (Sobol')
    runs: int
    seconds: float

    def relative(self, j_ref: float) -> FloatArray:
        """The index on the one-at-a-time scale: mu_star / J(θ̄) (Morris) or ST (Sobol')."""
        if self.method == "morris":
            return np.asarray(self.index / j_ref, dtype=float)
        return np.asarray(self.index, dtype=float)

    def significant(self, threshold: float, j_ref: float) -> tuple[str, ...]:
        rel = self.relative(j_ref)
        return tuple(n for n, r in zip(self.names, rel, strict=True) if r > threshold)

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "names": list(self.names),
            "index": self.index.tolist(),
            "spread": self.spread.tolist(),
            "runs": self.runs,
            "seconds": self.seconds,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> GlobalSensitivity:
        return cls(
            str(d["method"]),
            tuple(d["names"]),
            np.asarray(d["index"], dtype=float),
            np.asarray(d["spread"], dtype=float),
            int(d["runs"]),
            float(d["seconds"]),
        )


def global_sensitivity(
    true_j: Callable[[FloatArray], FloatArray],
    names: Sequence[str],
    bounds: FloatArray,
    method: str = "morris",
    runs: int = 1000,
    seed: int = 0,
) -> GlobalSensitivity:
    """Morris (``runs`` / (d + 1) trajectories on 4 levels) or Sobol' (Saltelli sampling, ``runs`` / (2 d + 2) base
    points, a power of two) indices of ``true_j`` over the box; every sample simulated in one batch."""
    from SALib.analyze import morris as morris_analyze
    from SALib.analyze import sobol as sobol_analyze
    from SALib.sample import morris as morris_sample
    from SALib.sample import sobol as sobol_sample

    if method not in METHODS[:2]:
        raise ReductionError(f"global sensitivity method must be one of {METHODS[:2]}, got {method!r}")
    d = len(names)
    problem = {"num_vars": d, "names": list(names), "bounds": np.asarray(bounds, dtype=float).tolist()}
    t0 = time.perf_counter()
    if method == "morris":
        r = max(2, runs // (d + 1))
        X = morris_sample.sample(problem, r, num_levels=4, seed=seed)
        Y = np.asarray(true_j(X), dtype=float)
        res = morris_analyze.analyze(problem, X, Y, num_levels=4, seed=seed)
        index, spread = np.asarray(res["mu_star"], dtype=float), np.asarray(res["sigma"], dtype=float)
    else:
        base = 2 ** max(1, int(math.log2(max(2, runs // (2 * d + 2)))))
        X = sobol_sample.sample(problem, base, calc_second_order=False, seed=seed)
        Y = np.asarray(true_j(X), dtype=float)
        res = sobol_analyze.analyze(problem, Y, calc_second_order=False, seed=seed)
        index, spread = np.asarray(res["ST"], dtype=float), np.asarray(res["S1"], dtype=float)
    return GlobalSensitivity(method, tuple(names), index, spread, int(X.shape[0]), time.perf_counter() - t0)


def disagreements(
    names: Sequence[str], kept: Sequence[str], glob: GlobalSensitivity, threshold: float, j_ref: float
) -> tuple[list[str], list[str]]:
    """(kept by the one-at-a-time test but not globally significant, globally significant but discarded)."""
    g = set(glob.significant(threshold, j_ref))
    k = set(kept)
    return [n for n in names if n in k and n not in g], [n for n in names if n in g and n not in k]
