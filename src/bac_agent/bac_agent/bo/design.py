"""Space-filling designs on the unit cube (scipy.stats.qmc) and the grid baseline."""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np
from numpy.typing import NDArray
from scipy.stats import qmc

FloatArray = NDArray[np.float64]


def default_n_initial(dim: int, budget: int) -> int:
    """Initial design size for ``dim`` dimensions and a ``budget`` of trials.

    Five runs up to d = 4 (enough for the GP to see the shape of a bowl before the
    acquisition takes over: measured on the simulated bump and Branin), d + 1 beyond;
    never more than half the budget (at least 2).
    """
    n = max(5, dim + 1)
    return int(max(2, min(n, budget // 2)))


def sobol(n: int, dim: int, seed: int) -> FloatArray:
    """``n`` scrambled Sobol points in [0, 1]^dim (a balanced power-of-two prefix is not required)."""
    if n <= 0:
        return np.zeros((0, dim))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "balance properties" warning for n != 2^m
        pts = qmc.Sobol(d=dim, scramble=True, seed=np.random.default_rng(seed)).random(n)
    return np.asarray(pts, dtype=float)


def lhs(n: int, dim: int, seed: int) -> FloatArray:
    """``n`` Latin-hypercube points, optimized for space filling ("random-cd")."""
    if n <= 0:
        return np.zeros((0, dim))
    return np.asarray(qmc.LatinHypercube(d=dim, optimization="random-cd", seed=np.random.default_rng(seed)).random(n))


def initial_design(n: int, dim: int, seed: int, margin: float = 0.02) -> FloatArray:
    """The initial design: a Latin hypercube (space filling for any n) stretched over [margin, 1 - margin] on
    every axis, its lowest and highest points on each axis at the two margins."""
    if not 0.0 <= margin < 0.5:
        raise ValueError(f"design margin must be in [0, 0.5), got {margin}")
    pts = lhs(n, dim, seed)
    if n >= 2:
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pts = (pts - lo) / np.where(hi > lo, hi - lo, 1.0)
    return np.asarray(margin + (1.0 - 2.0 * margin) * pts, dtype=float)


def grid(size: int, dim: int) -> FloatArray:
    """A full factorial grid with ``size`` levels per dimension, cell centres excluded: levels 0..1."""
    if size < 1:
        raise ValueError("grid size must be >= 1")
    if size**dim > 1_000_000:
        raise ValueError(f"a {size}^{dim} grid has {size**dim} points; too many for a campaign")
    levels = np.array([0.5]) if size == 1 else np.linspace(0.0, 1.0, size)
    return np.array(list(itertools.product(levels, repeat=dim)), dtype=float)


def candidates(n: int, dim: int, rng: np.random.Generator) -> FloatArray:
    """Space-filling candidate set for maximizing the acquisition (Sobol, a power of two)."""
    m = max(1, math.ceil(math.log2(max(n, 2))))
    # an integer seed drawn from rng: qmc given a Generator spawns from its SeedSequence, which is not part of
    # the generator's saved state (the engine's JSON state would then not continue identically)
    seed = int(rng.integers(0, 2**63 - 1))
    return np.asarray(qmc.Sobol(d=dim, scramble=True, seed=seed).random_base2(m), dtype=float)
