"""The reduction steps of the simulation phase (paper sec. III-D), on any surrogate of J.

Pure numpy, no simulator and no optimizer here: the input is a function ``J_mu(X)``
(``(n, d)`` parameters in their own units -> ``(n,)`` J), the best point ``θ̄`` and the
parameters' bounds. The steps:

1. **Sensitivity** (paper eq. 4): ``s_i(v) = J_mu(θ̄ with θ^i = v)``, each parameter swept
   one at a time over its whole range on a grid (:func:`sensitivity_curves`).
2. **Significance**: keep the parameters whose worst loss
   ``(max s_i - J_mu(θ̄)) / J_mu(θ̄)`` exceeds ``T`` (:func:`significant`).
3. **Similarity**: group the kept parameters whose optima agree into meta-parameters
   (:func:`similarity_groups`), then check each group by sweeping its members *together*
   and split the groups that lose more than a tolerance when tied (:func:`check_ties`).

What "the optima agree" means here. A one-at-a-time curve often has a flat bottom (or a
bottom that is flat within the noise of J), so its argmin on a grid is a poor summary: two
parameters whose curves are both flat over [0, 0.4] of their range agree, even when the grid
argmins fall at 0.0 and 0.35. So the optimum of parameter i is its **near-optimal interval**:
the contiguous stretch of the grid around the argmin of ``s_i`` where
``s_i <= min s_i + flat_tol · J_mu(θ̄)``, in *relative* units (0 = lower bound, 1 = upper
bound, so parameters with different ranges compare). Two parameters agree within ``ε`` when
their intervals are at most ``ε`` apart; a group is a set of parameters with one common
relative value that lies within ``ε/2`` of every member's interval (pairwise within ``ε``).
With ``flat_tol = 0`` the interval is the argmin alone and this is the paper's
``|θ̂^a - θ̂^b| < ε``. The fewest such groups come from the classic greedy stabbing of
intervals (sort by right end, put a common value at the first uncovered right end): it is
optimal, and the groups do not depend on the order of the parameters.

The curves see each parameter alone; tying several moves them at once. :func:`check_ties`
sweeps each group's common value (all members at the same relative position, which is how
a :class:`~bac_common.paramspace.MetaParameter` drives them) and splits off the member that
disagrees most while the tied sweep's best is worse than ``J_mu(θ̄)`` by more than
``tie_tol``.

The spread of the M campaigns' optima is reported beside (the boxplot), not used: a wide
spread says "flat" *or* "several local minima" and cannot tell which.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition, MetaParameter

FloatArray = NDArray[np.float64]
Surrogate = Callable[[FloatArray], FloatArray]

DEFAULT_THRESHOLD = 0.05  # T: a parameter matters when mis-setting it can cost more than 5 % of J
DEFAULT_EPSILON = 0.05  # ε: optima within 5 % of the range agree
DEFAULT_FLAT_TOL = 0.005  # values within 0.5 % of J of a curve's minimum count as optimal (about the run noise)
DEFAULT_TIE_TOL = 0.005  # a group is kept when tying its members costs at most 0.5 % of J (= DEFAULT_FLAT_TOL)
DEFAULT_POINTS = 51  # grid points of a one-at-a-time sweep


class ReductionError(BacError, ValueError):
    """The reduction cannot be done as asked (bad bounds, thresholds, or an unusable surrogate)."""


@dataclass(frozen=True)
class SensitivityCurves:
    """One-at-a-time sweeps of a surrogate from ``θ̄`` (paper eq. 4)."""

    names: tuple[str, ...]
    bounds: FloatArray  # (d, 2) lower, upper
    theta_bar: FloatArray  # (d,) the point swept from
    j_bar: float  # J_mu(θ̄)
    values: FloatArray  # (d, m) swept values of each parameter (its own units)
    s: FloatArray  # (d, m) J_mu along each sweep

    @property
    def dim(self) -> int:
        return len(self.names)

    @property
    def loss(self) -> FloatArray:
        """Worst relative loss of each parameter: (max s_i - J_mu(θ̄)) / J_mu(θ̄)."""
        return np.asarray((self.s.max(axis=1) - self.j_bar) / self.j_bar)

    @property
    def gain(self) -> FloatArray:
        """Best relative improvement a parameter alone offers from θ̄: (J_mu(θ̄) - min s_i) / J_mu(θ̄)."""
        return np.asarray((self.j_bar - self.s.min(axis=1)) / self.j_bar)

    @property
    def best_value(self) -> FloatArray:
        """Grid argmin of each curve (own units)."""
        return np.asarray(self.values[np.arange(self.dim), np.argmin(self.s, axis=1)])

    def relative(self, values: FloatArray) -> FloatArray:
        """Own units -> relative position in the range (0 lower, 1 upper), per parameter (last axis)."""
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        return np.asarray((np.asarray(values, dtype=float) - lo) / (hi - lo))

    def optimal_intervals(self, flat_tol: float = DEFAULT_FLAT_TOL) -> FloatArray:
        """(d, 2) relative [a, b]: the contiguous near-optimal stretch of each curve around its argmin."""
        if not (math.isfinite(flat_tol) and flat_tol >= 0):
            raise ReductionError(f"flat_tol must be >= 0, got {flat_tol!r}")
        rel = (self.values - self.bounds[:, :1]) / (self.bounds[:, 1:] - self.bounds[:, :1])
        level = self.s.min(axis=1, keepdims=True) + flat_tol * abs(self.j_bar)
        ok = self.s <= level  # (d, m)
        m = self.s.shape[1]
        k = np.argmin(self.s, axis=1)
        idx = np.arange(m)[None, :]
        # a grid point is in the stretch when every point between it and the argmin is near-optimal
        bad = ~ok
        # last bad index left of k and first bad index right of k
        left_bad = np.where(bad & (idx < k[:, None]), idx, -1).max(axis=1)
        right_bad = np.where(bad & (idx > k[:, None]), idx, m).min(axis=1)
        rows = np.arange(self.dim)
        return np.stack([rel[rows, left_bad + 1], rel[rows, right_bad - 1]], axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "names": list(self.names),
            "bounds": self.bounds.tolist(),
            "theta_bar": self.theta_bar.tolist(),
            "j_bar": self.j_bar,
            "values": self.values.tolist(),
            "s": self.s.tolist(),
            "loss": self.loss.tolist(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SensitivityCurves:
        return cls(
            tuple(d["names"]),
            np.asarray(d["bounds"], dtype=float),
            np.asarray(d["theta_bar"], dtype=float),
            float(d["j_bar"]),
            np.asarray(d["values"], dtype=float),
            np.asarray(d["s"], dtype=float),
        )


def _check_bounds(bounds: FloatArray, d: int) -> FloatArray:
    b = np.asarray(bounds, dtype=float)
    if b.shape != (d, 2) or not np.all(np.isfinite(b)) or np.any(b[:, 0] >= b[:, 1]):
        raise ReductionError(f"bounds must be a finite ({d}, 2) array with lower < upper, got shape {b.shape}")
    return b


def sensitivity_curves(
    surrogate: Surrogate,
    theta_bar: FloatArray,
    bounds: FloatArray,
    names: Sequence[str],
    points: int = DEFAULT_POINTS,
) -> SensitivityCurves:
    """Sweep each parameter over ``points`` values of its range, the others at ``θ̄``; one surrogate call."""
    th = np.asarray(theta_bar, dtype=float).ravel()
    d = th.size
    if len(names) != d:
        raise ReductionError(f"{len(names)} names for a {d}-dimensional θ̄")
    b = _check_bounds(bounds, d)
    if points < 3:
        raise ReductionError(f"a sweep needs at least 3 points, got {points}")
    if np.any(th < b[:, 0]) or np.any(th > b[:, 1]):
        raise ReductionError("θ̄ lies outside the bounds")
    values = np.linspace(b[:, 0], b[:, 1], points).T  # (d, m)
    X = np.repeat(th[None, :], d * points + 1, axis=0)
    rows = 1 + np.arange(d * points)
    X[rows, np.repeat(np.arange(d), points)] = values.ravel()
    J = np.asarray(surrogate(X), dtype=float).ravel()
    if J.shape != (d * points + 1,) or not np.all(np.isfinite(J)):
        raise ReductionError("the surrogate returned a wrong shape or a non-finite J")
    if J[0] <= 0:
        raise ReductionError(f"J_mu(θ̄) = {J[0]:.4g} must be positive (a relative loss divides by it)")
    return SensitivityCurves(tuple(names), b, th, float(J[0]), values, J[1:].reshape(d, points))


def significant(curves: SensitivityCurves, threshold: float = DEFAULT_THRESHOLD) -> tuple[str, ...]:
    """Significance step: the parameters whose worst loss exceeds ``threshold`` (in the curves' order)."""
    if not (math.isfinite(threshold) and threshold >= 0):
        raise ReductionError(f"threshold T must be >= 0, got {threshold!r}")
    return tuple(n for n, s in zip(curves.names, curves.loss, strict=True) if s > threshold)


@dataclass(frozen=True)
class Group:
    """Kept parameters that share an optimum: one meta-parameter (or a single parameter)."""

    members: tuple[str, ...]
    value: float  # common relative position (0..1) of the members' optima
    intervals: tuple[tuple[float, float], ...]  # each member's near-optimal interval (relative)
    tie_loss: float = math.nan  # (min of the tied sweep - J_mu(θ̄)) / J_mu(θ̄), from check_ties
    epsilon: float = math.nan  # the ε the group was formed with

    @property
    def is_meta(self) -> bool:
        return len(self.members) > 1

    def to_dict(self) -> dict[str, Any]:
        return {
            "members": list(self.members),
            "value": self.value,
            "intervals": [list(iv) for iv in self.intervals],
            "tie_loss": self.tie_loss,
            "epsilon": self.epsilon,
        }


def _stab(intervals: Mapping[str, tuple[float, float]], epsilon: float) -> list[Group]:
    """Fewest groups such that each member's interval is within ε/2 of its group's common value."""
    half = epsilon / 2.0
    order = sorted(intervals, key=lambda n: (intervals[n][1], intervals[n][0], n))
    groups: list[list[str]] = []
    points: list[float] = []
    for n in order:
        a, b = intervals[n]
        if points and a - half <= points[-1]:  # sorted by right end: b + half >= points[-1] holds already
            groups[-1].append(n)
        else:
            points.append(b + half)  # the right end of the widened interval: covers most of what follows
            groups.append([n])
    out = []
    for members in groups:
        members.sort()
        ivs = [intervals[m] for m in members]
        lo = max(a for a, _ in ivs) - half  # the common values: within ε/2 of every member's interval
        hi = min(b for _, b in ivs) + half
        centre = float(np.median([(a + b) / 2 for a, b in ivs]))
        value = float(np.clip(centre, max(lo, 0.0), min(hi, 1.0))) if lo <= hi else float(np.clip(lo, 0, 1))
        out.append(Group(tuple(members), value, tuple(ivs), math.nan, epsilon))
    return out


def similarity_groups(
    curves: SensitivityCurves,
    kept: Sequence[str],
    epsilon: float = DEFAULT_EPSILON,
    flat_tol: float = DEFAULT_FLAT_TOL,
) -> list[Group]:
    """Similarity step: group the ``kept`` parameters whose near-optimal intervals agree within ``epsilon``.

    ``epsilon`` and the intervals are relative to each parameter's range (see the module doc).
    Groups come sorted by their first member's position in ``curves.names``.
    """
    if not (math.isfinite(epsilon) and 0 <= epsilon <= 1):
        raise ReductionError(f"epsilon must be in [0, 1] (a share of the range), got {epsilon!r}")
    unknown = [k for k in kept if k not in curves.names]
    if unknown:
        raise ReductionError(f"kept parameters not in the curves: {unknown}")
    iv = curves.optimal_intervals(flat_tol)
    pos = {n: i for i, n in enumerate(curves.names)}
    intervals = {k: (float(iv[pos[k], 0]), float(iv[pos[k], 1])) for k in kept}
    groups = _stab(intervals, epsilon)
    return sorted(groups, key=lambda g: min(pos[m] for m in g.members))


def tied_sweep(
    surrogate: Surrogate, curves: SensitivityCurves, members: Sequence[str], points: int | None = None
) -> tuple[FloatArray, FloatArray]:
    """J_mu with ``members`` all at the same relative position u (others at θ̄): (u grid, J)."""
    m = points or curves.values.shape[1]
    u = np.linspace(0.0, 1.0, m)
    idx = [curves.names.index(n) for n in members]
    X = np.repeat(curves.theta_bar[None, :], m, axis=0)
    lo, hi = curves.bounds[idx, 0], curves.bounds[idx, 1]
    X[:, idx] = lo[None, :] + u[:, None] * (hi - lo)[None, :]
    return u, np.asarray(surrogate(X), dtype=float).ravel()


def check_ties(
    surrogate: Surrogate,
    curves: SensitivityCurves,
    groups: Sequence[Group],
    tie_tol: float = DEFAULT_TIE_TOL,
) -> list[Group]:
    """Sweep each group tied; while tying costs more than ``tie_tol``, the member that suffers most at the
    tied optimum leaves the group.

    The members that left are grouped again among themselves (same intervals, same ε) and checked the
    same way once more; what still does not fit is tuned alone. Finally, groups whose tied optima lie
    within ε are joined when the union still ties within ``tie_tol``. Returns the groups with ``tie_loss``
    and ``value`` measured on the tied sweep (``value`` = the relative position of its minimum).
    """
    if not (math.isfinite(tie_tol) and tie_tol >= 0):
        raise ReductionError(f"tie_tol must be >= 0, got {tie_tol!r}")
    pos = {n: i for i, n in enumerate(curves.names)}
    out: list[Group] = []
    leavers: list[Group] = []
    for g in groups:
        kept, left = _tie(surrogate, curves, g, tie_tol, pos)
        out.append(kept)
        leavers.extend(left)
    if len(leavers) > 1:
        epsilon = _epsilon_of(groups)
        intervals = {lv.members[0]: lv.intervals[0] for lv in leavers}
        for g in _stab(intervals, epsilon):
            kept, left = _tie(surrogate, curves, g, tie_tol, pos)
            out.append(kept)
            out.extend(_single(curves, lv, pos) for lv in left)
    else:
        out.extend(_single(curves, lv, pos) for lv in leavers)
    out = _merge(surrogate, curves, out, tie_tol, _epsilon_of(groups), pos)
    return sorted(out, key=lambda g: min(pos[m] for m in g.members))


def _merge(
    surrogate: Surrogate,
    curves: SensitivityCurves,
    groups: list[Group],
    tie_tol: float,
    epsilon: float,
    pos: Mapping[str, int],
) -> list[Group]:
    """Join checked groups whose tied optima are within ε while the union still ties within ``tie_tol``
    (splitting and regrouping can leave two groups at the same value, e.g. both at the upper bound)."""
    groups = list(groups)
    m = curves.values.shape[1]
    while True:
        best: tuple[float, int, int, Group] | None = None
        for a in range(len(groups)):
            for b in range(a + 1, len(groups)):
                ga, gb = groups[a], groups[b]
                if abs(ga.value - gb.value) > epsilon + 1e-12:
                    continue
                members = tuple(sorted(ga.members + gb.members))
                u, j = tied_sweep(surrogate, curves, members, m)
                k = int(np.argmin(j))
                loss = float(j[k] / curves.j_bar - 1.0)
                if loss <= tie_tol and (best is None or loss < best[0]):
                    ivs = {
                        **dict(zip(ga.members, ga.intervals, strict=True)),
                        **dict(zip(gb.members, gb.intervals, strict=True)),
                    }
                    best = (loss, a, b, Group(members, float(u[k]), tuple(ivs[x] for x in members), loss, epsilon))
        if best is None:
            return groups
        _, a, b, joined = best
        groups = [g for i, g in enumerate(groups) if i not in (a, b)] + [joined]


def _epsilon_of(groups: Sequence[Group]) -> float:
    eps = [g.epsilon for g in groups if math.isfinite(g.epsilon)]
    return max(eps) if eps else DEFAULT_EPSILON


def _single(curves: SensitivityCurves, g: Group, pos: Mapping[str, int]) -> Group:
    i = pos[g.members[0]]
    k = int(np.argmin(curves.s[i]))
    rel = float(curves.relative(curves.values[:, k])[i])
    return Group(g.members, rel, g.intervals, float(curves.s[i, k] / curves.j_bar - 1.0), g.epsilon)


def _tie(
    surrogate: Surrogate, curves: SensitivityCurves, g: Group, tie_tol: float, pos: Mapping[str, int]
) -> tuple[Group, list[Group]]:
    """(the group with the members that can be tied, the members that left it, one group each)."""
    members = list(g.members)
    ivs = dict(zip(g.members, g.intervals, strict=True))
    left: list[Group] = []
    m = curves.values.shape[1]
    while len(members) > 1:
        u, j = tied_sweep(surrogate, curves, members, m)
        k = int(np.argmin(j))
        loss = float(j[k] / curves.j_bar - 1.0)
        if loss <= tie_tol:
            return Group(tuple(members), float(u[k]), tuple(ivs[x] for x in members), loss, g.epsilon), left
        # each member's own loss at the tied value u[k] (its one-at-a-time curve, on the same grid)
        own = [curves.s[pos[x], k] - curves.s[pos[x]].min() for x in members]
        far = members.pop(int(np.argmax(own)))
        left.append(Group((far,), float(u[k]), (ivs[far],), math.nan, g.epsilon))
    return _single(
        curves, Group(tuple(members), g.value, tuple(ivs[x] for x in members), math.nan, g.epsilon), pos
    ), left


def reduced_definition(
    base: CalibrationDefinition,
    groups: Sequence[Group],
    fixed_values: Mapping[str, float],
    name: str | None = None,
    description: str = "",
) -> CalibrationDefinition:
    """The meta-parameter file: tuned = one dimension per group, every other parameter fixed.

    A group of one tunes that raw parameter directly; a larger group becomes a meta-parameter
    ``m1, m2, ...`` whose range is the members' common range when they share one (Controller II:
    [0, 1000], the meta value is every member's value), else [0, 1] (the members' relative position).
    ``fixed_values`` gives the value of every parameter that no group tunes (e.g. θ̄'s, or the nominal
    values); they are quantized to the CAN resolution.
    """
    if base.meta or set(base.tuned) != set(base.parameter_names):
        raise ReductionError(
            f"the definition to reduce must tune every raw parameter directly; '{base.name}' has "
            f"meta-parameters or fixed values (reduce the full definition)"
        )
    seen: set[str] = set()
    for g in groups:
        for m in g.members:
            base.parameter(m)
            if m in seen:
                raise ReductionError(f"parameter '{m}' is in two groups")
            seen.add(m)
    if not groups:
        raise ReductionError("no parameter was kept: lower the threshold T (nothing would be left to calibrate)")
    tuned: list[str] = []
    meta: list[MetaParameter] = []
    k = 0
    for g in groups:
        if not g.is_meta:
            tuned.append(g.members[0])
            continue
        k += 1
        mname = f"m{k}"
        while mname in base.parameter_names:  # a raw parameter could be called m1
            mname = "meta_" + mname
        ranges = {(base.parameter(m).lower, base.parameter(m).upper) for m in g.members}
        lo, hi = next(iter(ranges)) if len(ranges) == 1 else (0.0, 1.0)
        meta.append(
            MetaParameter(
                mname,
                tuple(g.members),
                lo,
                hi,
                description=f"drives {', '.join(g.members)} together (shared optimum near {g.value:.2f} of the range)",
            )
        )
        tuned.append(mname)
    fixed: dict[str, float] = {}
    for p in base.parameters:
        if p.name in seen:
            continue
        if p.name not in fixed_values:
            raise ReductionError(f"no fixed value for the discarded parameter '{p.name}'")
        fixed[p.name] = float(p.quantize(float(fixed_values[p.name])))
    return CalibrationDefinition(
        name=name or f"{base.name}_reduced",
        parameters=base.parameters,
        tuned=tuple(tuned),
        meta=tuple(meta),
        fixed=fixed,
        baseline=dict(base.baseline),
        description=description or f"{base.name} reduced by the simulation phase (bac reduce)",
        xcp=dict(base.xcp),  # the ECU's XCP settings: the reduced definition runs over either protocol
    )
