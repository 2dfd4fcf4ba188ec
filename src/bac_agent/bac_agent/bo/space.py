"""The search space of the optimizer: named, bounded dimensions, fixed values, a resolution.

The engine works on the unit cube; a :class:`SearchSpace` maps between the
user's units and it, quantizes to what the ECU can hold and checks bounds.

Built from

* a :class:`bac_common.paramspace.CalibrationDefinition` (its tuned dimensions,
  raw or meta-parameters; raw dimensions take the parameter's CAN resolution so
  that what is told equals what the ECU holds; a meta-parameter takes the finest
  step that moves each of its members by at most one of their LSBs), or
* a plain mapping ``{"x": (0.0, 1.0), "z": 0.3}`` (a scalar is a fixed value) or a
  list of ``(name, lower, upper)`` / ``(name, lower, upper, resolution)`` tuples.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bac_common.errors import BacError, OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition

FloatArray = NDArray[np.float64]


class SpaceError(BacError, ValueError):
    """A search-space description is malformed."""


@dataclass(frozen=True)
class Dim:
    """One optimized dimension."""

    name: str
    lower: float
    upper: float
    resolution: float = 0.0  # 0 = continuous

    def __post_init__(self) -> None:
        if not self.name:
            raise SpaceError("a dimension needs a name")
        if not (math.isfinite(self.lower) and math.isfinite(self.upper) and self.lower < self.upper):
            raise SpaceError(f"dimension '{self.name}': bounds [{self.lower}, {self.upper}] need lower < upper")
        if not (math.isfinite(self.resolution) and self.resolution >= 0):
            raise SpaceError(f"dimension '{self.name}': resolution must be >= 0, got {self.resolution}")


@dataclass(frozen=True)
class SearchSpace:
    """Named bounded dimensions (optimized) and fixed values (passed through)."""

    dims: tuple[Dim, ...]
    fixed: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.dims:
            raise SpaceError("the search space has no dimension to optimize")
        names = [d.name for d in self.dims] + list(self.fixed)
        if len(set(names)) != len(names):
            raise SpaceError(f"duplicate names in the search space: {names}")
        object.__setattr__(self, "fixed", {str(k): float(v) for k, v in self.fixed.items()})

    # --- construction ------------------------------------------------------------
    @classmethod
    def from_definition(cls, definition: CalibrationDefinition) -> SearchSpace:
        dims = []
        for d in definition.dimensions:
            if d.is_meta:
                m = definition.meta_parameter(d.name)
                steps = [
                    definition.parameter(p).resolution / (definition.parameter(p).upper - definition.parameter(p).lower)
                    for p in m.members
                ]
                res = min(steps) * (d.upper - d.lower)
            else:
                res = definition.parameter(d.name).resolution
            dims.append(Dim(d.name, d.lower, d.upper, res))
        return cls(tuple(dims))

    @classmethod
    def from_spec(cls, spec: Any) -> SearchSpace:
        """From a SearchSpace, a CalibrationDefinition, a mapping or a list of tuples."""
        if isinstance(spec, SearchSpace):
            return spec
        if isinstance(spec, CalibrationDefinition):
            return cls.from_definition(spec)
        dims: list[Dim] = []
        fixed: dict[str, float] = {}
        items: list[tuple[Any, ...]]
        if isinstance(spec, Mapping):
            items = []
            for k, v in spec.items():
                if isinstance(v, int | float):
                    fixed[str(k)] = float(v)
                elif isinstance(v, Sequence) and not isinstance(v, str):
                    items.append((k, *v))
                else:
                    raise SpaceError(f"'{k}': expected (lower, upper[, resolution]) or a fixed number, got {v!r}")
        elif isinstance(spec, Sequence) and not isinstance(spec, str):
            items = [tuple(x) for x in spec]
        else:
            raise SpaceError(f"cannot build a search space from {type(spec).__name__}")
        for it in items:
            if len(it) not in (3, 4):
                raise SpaceError(f"expected (name, lower, upper[, resolution]), got {it!r}")
            try:
                dims.append(Dim(str(it[0]), float(it[1]), float(it[2]), float(it[3]) if len(it) == 4 else 0.0))
            except (TypeError, ValueError) as exc:
                if isinstance(exc, SpaceError):
                    raise
                raise SpaceError(f"dimension {it!r}: bounds must be numbers") from exc
        return cls(tuple(dims), fixed)

    # --- look-ups -------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.dims)

    @property
    def dim(self) -> int:
        return len(self.dims)

    @property
    def lower(self) -> FloatArray:
        return np.array([d.lower for d in self.dims])

    @property
    def upper(self) -> FloatArray:
        return np.array([d.upper for d in self.dims])

    @property
    def bounds(self) -> FloatArray:
        """(d, 2) array of [lower, upper]."""
        return np.stack([self.lower, self.upper], axis=1)

    # --- conversions -------------------------------------------------------------------
    def to_unit(self, x: FloatArray) -> FloatArray:
        return (np.asarray(x, dtype=float) - self.lower) / (self.upper - self.lower)

    def from_unit(self, u: FloatArray) -> FloatArray:
        """Unit cube -> user units, clipped to the bounds and quantized to the resolution."""
        u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
        x = self.lower + u * (self.upper - self.lower)
        return self.quantize(x)

    def quantize(self, x: FloatArray) -> FloatArray:
        """Round each dimension with a resolution to its grid (from its lower bound), within bounds."""
        x = np.asarray(x, dtype=float).copy()
        res = np.array([d.resolution for d in self.dims])
        q = res > 0
        if np.any(q):
            lo, hi = self.lower[q], self.upper[q]
            steps = np.round((x[..., q] - lo) / res[q])
            # rounded to 12 decimals: 0.3465, not 0.34650000000000003, in logs and journals
            x[..., q] = np.minimum(np.round(lo + steps * res[q], 12), hi)
        return np.clip(x, self.lower, self.upper)

    def to_params(self, x: FloatArray) -> dict[str, float]:
        """One point (d,) in user units -> {name: value}, fixed values included."""
        out = {n: float(v) for n, v in zip(self.names, np.asarray(x, dtype=float).ravel(), strict=True)}
        out.update(self.fixed)
        return out

    def to_array(self, params: Mapping[str, float]) -> FloatArray:
        """{name: value} -> (d,) in user units; checks names, finiteness, bounds and fixed values."""
        known = set(self.names) | set(self.fixed)
        for n in params:
            if n not in known:
                raise UnknownParameterError(str(n), tuple(self.names) + tuple(self.fixed))
        missing = [n for n in self.names if n not in params]
        if missing:
            raise SpaceError(f"parameters lack dimensions {missing}")
        for n, v in self.fixed.items():
            if n in params and not math.isclose(float(params[n]), v, rel_tol=1e-12, abs_tol=1e-12):
                raise SpaceError(f"'{n}' is fixed at {v}, got {params[n]}")
        x = np.array([float(params[n]) for n in self.names])
        for d, v in zip(self.dims, x, strict=True):
            if not (math.isfinite(v) and d.lower <= v <= d.upper):
                raise OutOfBoundsError(
                    d.name,
                    float(v),
                    d.lower,
                    d.upper,
                    "the optimizer refuses it (a calibration outside the search space)",
                )
        return x

    # --- (de)serialization -------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "dims": [
                {"name": d.name, "lower": d.lower, "upper": d.upper, "resolution": d.resolution} for d in self.dims
            ],
            "fixed": dict(self.fixed),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SearchSpace:
        try:
            dims = tuple(
                Dim(str(d["name"]), float(d["lower"]), float(d["upper"]), float(d.get("resolution", 0.0)))
                for d in data["dims"]
            )
            return cls(dims, {str(k): float(v) for k, v in (data.get("fixed") or {}).items()})
        except (KeyError, TypeError) as exc:
            raise SpaceError(f"malformed search space: {exc}") from exc
