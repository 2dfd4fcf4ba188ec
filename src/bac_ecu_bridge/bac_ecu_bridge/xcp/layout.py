"""Where and how an XCP ECU holds a calibration: addresses, data types, byte orders, conversions.

One codec serves both ends: the bridge's XCP client (what it writes and how it
reads the ECU's bytes back) and the simulated XCP ECU in ``bac_sim`` (its memory
image). A parameter's value p travels as the ECU's internal value x of its A2L
data type, p = factor * x + offset (the A2L COMPU_METHOD, see
:class:`bac_common.paramspace.EcuAddress`). Integer types are rounded to the
nearest x whose p lies within the declared bounds; float types hold the value
as the ECU's float (FLOAT32_IEEE rounds it). Parameters that follow each other
in memory form a *run*: written with one SET_MTA and checked with one
BUILD_CHECKSUM / UPLOAD.
"""

from __future__ import annotations

import itertools
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from bac_common.errors import OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition, EcuAddress, RawParameter
from bac_ecu_bridge.errors import ProtocolConfigError

# datatype -> (struct code, size, integer range or None for floats)
_TYPES: dict[str, tuple[str, int, tuple[int, int] | None]] = {
    "UBYTE": ("B", 1, (0, 0xFF)),
    "SBYTE": ("b", 1, (-0x80, 0x7F)),
    "UWORD": ("H", 2, (0, 0xFFFF)),
    "SWORD": ("h", 2, (-0x8000, 0x7FFF)),
    "ULONG": ("I", 4, (0, 0xFFFF_FFFF)),
    "SLONG": ("i", 4, (-0x8000_0000, 0x7FFF_FFFF)),
    "A_UINT64": ("Q", 8, (0, 2**64 - 1)),
    "A_INT64": ("q", 8, (-(2**63), 2**63 - 1)),
    "FLOAT32_IEEE": ("f", 4, None),
    "FLOAT64_IEEE": ("d", 8, None),
}
_EPS = 1e-9


def datatype_size(datatype: str) -> int:
    return _TYPES[datatype][1]


def integer_range(datatype: str) -> tuple[int, int]:
    """The internal values an integer A2L data type holds (floats: refused with KeyError)."""
    span = _TYPES[datatype][2]
    if span is None:
        raise KeyError(f"{datatype} is not an integer type")
    return span


@dataclass(frozen=True)
class XcpParam:
    """One raw parameter as an XCP ECU holds it."""

    name: str
    index: int
    lower: float
    upper: float
    where: EcuAddress
    factor: float
    offset: float
    size: int
    x_min: int  # integer types: the internal values whose physical value lies within [lower, upper]
    x_max: int

    @classmethod
    def of(cls, p: RawParameter) -> XcpParam:
        if p.xcp is None:
            raise ProtocolConfigError(
                f"parameter '{p.name}' has no XCP address: write the definition from the ECU's A2L "
                "(bac definition from-a2l ECU.a2l --characteristic ...) or add an 'xcp:' entry to it"
            )
        _code, size, span = _TYPES[p.xcp.datatype]
        factor, offset = p.xcp.linear
        x_min = x_max = 0
        if span is not None:
            a = (p.lower - offset) / factor
            b = (p.upper - offset) / factor
            lo, hi = min(a, b), max(a, b)
            x_min = math.ceil(lo - _EPS)
            x_max = math.floor(hi + _EPS)
            if x_min < span[0] or x_max > span[1]:  # it was clamped to the type without a word
                raise ProtocolConfigError(
                    f"parameter '{p.name}': its bounds [{p.lower:g}, {p.upper:g}] need internal values "
                    f"{x_min}..{x_max}, beyond what a {p.xcp.datatype} holds ({span[0]}..{span[1]})"
                )
            if x_min > x_max:
                raise ProtocolConfigError(
                    f"parameter '{p.name}': no {p.xcp.datatype} value of conversion p = {factor:g} x + {offset:g} "
                    f"lies within [{p.lower:g}, {p.upper:g}]"
                )
        return cls(p.name, p.index, p.lower, p.upper, p.xcp, factor, offset, size, x_min, x_max)

    def off_grid(self, resolution: float) -> str:
        """Why the agent's values (lower + k x ``resolution``, :meth:`RawParameter.quantize`) are not all values the
        ECU holds ("" when they are): the value told to the optimizer would then differ from the value held by up
        to half a step (bac definition from-a2l writes definitions on the ECU's grid)."""
        if self.where.is_float:
            return ""
        off = [f"{n} {v:g}" for n, v in (("lower", self.lower), ("upper", self.upper))
               if abs((v - self.offset) / self.factor - round((v - self.offset) / self.factor)) > 1e-6]  # fmt: skip
        steps = resolution / abs(self.factor)
        if not off and abs(steps - round(steps)) <= 1e-6 and round(steps) >= 1:
            return ""
        why = f"{', '.join(off)} not on it" if off else f"resolution {resolution:g} no multiple of {abs(self.factor):g}"
        return (
            f"parameter '{self.name}': the agent's grid is not the ECU's (p = {self.factor:g} x + {self.offset:g}; "
            f"{why}): a value told to the optimizer may differ from the value the ECU holds by up to half a step"
        )

    @property
    def address(self) -> int:
        return self.where.address

    @property
    def end(self) -> int:
        return self.where.address + self.size

    @property
    def _fmt(self) -> str:
        return ("<" if self.where.byte_order == "MSB_LAST" else ">") + _TYPES[self.where.datatype][0]

    def internal(self, value: float) -> int | float:
        """The ECU's internal value for ``value``; raises :class:`OutOfBoundsError` outside the bounds or NaN."""
        v = float(value)
        if not (math.isfinite(v) and self.lower <= v <= self.upper):
            raise OutOfBoundsError(self.name, v, self.lower, self.upper)
        x = (v - self.offset) / self.factor
        if self.where.is_float:
            return self._inside_float(x)
        return min(max(round(x), self.x_min), self.x_max)

    def _inside_float(self, x: float) -> float:
        """The float the ECU stores (FLOAT32 rounds), nudged back inside the bounds if rounding left them."""
        dtype = np.float32 if self.where.datatype == "FLOAT32_IEEE" else np.float64
        stored = dtype(x)
        for _ in range(4):
            p = self.factor * float(stored) + self.offset
            if p > self.upper:
                stored = np.nextafter(stored, dtype(-np.inf) if self.factor > 0 else dtype(np.inf))
            elif p < self.lower:
                stored = np.nextafter(stored, dtype(np.inf) if self.factor > 0 else dtype(-np.inf))
            else:
                break
        return float(stored)

    def encode(self, value: float) -> bytes:
        return struct.pack(self._fmt, self.internal(value))

    def physical(self, x: int | float) -> float:
        return float(self.factor * x + self.offset)

    def decode(self, data: bytes) -> float:
        """The physical value of the ECU's bytes (exactly what it holds; may lie outside the bounds)."""
        if len(data) != self.size:
            raise ValueError(f"parameter '{self.name}': {len(data)} bytes, its {self.where.datatype} takes {self.size}")
        x = struct.unpack(self._fmt, data)[0]
        p = self.physical(x)
        if self.where.is_float:
            return p
        # the integer grid: keep exactly what quantize gives (p of the same x), inside the bounds' float noise
        if self.x_min <= x <= self.x_max:
            return min(max(p, self.lower), self.upper)
        return p

    def quantize(self, value: float) -> float:
        return self.decode(self.encode(value))

    def holds_valid(self, data: bytes) -> bool:
        """True when the ECU's bytes are a value within the declared bounds."""
        try:
            p = self.decode(data)
        except ValueError:
            return False
        return math.isfinite(p) and self.lower <= p <= self.upper


@dataclass(frozen=True)
class Run:
    """Parameters that follow each other in memory (one address extension), in address order."""

    extension: int
    address: int
    params: tuple[XcpParam, ...]

    @property
    def size(self) -> int:
        return self.params[-1].end - self.address


class XcpLayout:
    """The XCP memory layout of a calibration definition's raw parameters."""

    def __init__(self, definition: CalibrationDefinition) -> None:
        params = sorted((XcpParam.of(p) for p in definition.parameters), key=lambda q: (q.where.extension, q.address))
        for a, b in itertools.pairwise(params):
            if a.where.extension == b.where.extension and b.address < a.end:
                raise ProtocolConfigError(
                    f"parameters '{a.name}' and '{b.name}' overlap in the ECU's memory (0x{a.address:X}+{a.size}, "
                    f"0x{b.address:X})"
                )
        self.definition = definition
        self.params: tuple[XcpParam, ...] = tuple(params)
        self.by_name: dict[str, XcpParam] = {p.name: p for p in params}
        runs: list[list[XcpParam]] = []
        for p in params:
            if runs and runs[-1][-1].where.extension == p.where.extension and runs[-1][-1].end == p.address:
                runs[-1].append(p)
            else:
                runs.append([p])
        self.runs: tuple[Run, ...] = tuple(Run(r[0].where.extension, r[0].address, tuple(r)) for r in runs)
        self.names = tuple(p.name for p in sorted(params, key=lambda q: q.index))  # the definition's index order

    def param(self, name: str) -> XcpParam:
        try:
            return self.by_name[name]
        except KeyError:
            raise UnknownParameterError(name, self.names) from None

    def check_complete(self, values: Mapping[str, float]) -> None:
        for n in values:
            self.param(n)
        missing = [n for n in self.names if n not in values]
        if missing:
            raise ProtocolConfigError(f"an XCP apply writes every parameter; missing {missing}")

    def image(self, values: Mapping[str, float]) -> dict[Run, bytes]:
        """The bytes of every run for a full calibration (refuses anything outside the bounds)."""
        self.check_complete(values)
        return {run: b"".join(p.encode(values[p.name]) for p in run.params) for run in self.runs}

    def decode_run(self, run: Run, data: bytes) -> dict[str, float]:
        if len(data) != run.size:
            raise ValueError(f"run at 0x{run.address:X}: {len(data)} bytes, expected {run.size}")
        out = {}
        for p in run.params:
            start = p.address - run.address
            out[p.name] = p.decode(data[start : start + p.size])
        return out

    def decode(self, data: Mapping[Run, bytes]) -> dict[str, float]:
        """Values by name, in the definition's index order."""
        got: dict[str, float] = {}
        for run in self.runs:
            got.update(self.decode_run(run, data[run]))
        return {n: got[n] for n in self.names}

    def quantize(self, values: Mapping[str, float]) -> dict[str, float]:
        """What the ECU holds after writing ``values`` (every parameter), in index order."""
        return {n: self.param(n).quantize(values[n]) for n in self.names if n in values}

    @property
    def span(self) -> tuple[int, int]:
        """(lowest address, highest address + 1) over every parameter (extension ignored)."""
        return min(p.address for p in self.params), max(p.end for p in self.params)
