"""Calibration definitions: the ECU's raw parameters, what is tuned, meta-parameters.

A :class:`CalibrationDefinition` is the one description of a controller's
calibration that every part of bac shares:

* the ECU bridge encodes raw parameters on CAN (index, resolution, bounds) and
  refuses anything outside the bounds before sending;
* the agent optimizes over the *tuned* dimensions (raw parameters or
  meta-parameters) within their bounds;
* the simulation phase (``bac reduce``) writes a definition whose tuned
  dimensions are the meta-parameters it found and whose other parameters are
  fixed at nominal values.

A meta-parameter drives several raw parameters (paper sec. III-D, "similarity"):
its value u in [lower, upper] maps linearly to the same relative position in
each member's range (with equal ranges, every member takes the meta value).

The YAML form (see ``ros_ws/config/calibrations/``)::

    name: controller_i
    description: constant damping front and rear
    parameters:
      - {name: damping_front, index: 0, lower: 0.0, upper: 1.0, nominal: 0.5, resolution: 0.0001}
      - {name: damping_rear,  index: 1, lower: 0.0, upper: 1.0, nominal: 0.5, resolution: 0.0001}
    baseline: {damping_front: 0.5, damping_rear: 0.5}   # safe calibration, default: nominal
    tuned: [damping_front, damping_rear]                # default: every raw parameter
    meta:                                               # optional
      - {name: m1, members: [p05, p06, p07], lower: 0, upper: 1000}
    fixed: {p01: 500.0}                                 # raw values held fixed, default: nominal
    best_guess: {m1: 0.0}                               # optional: where the optimum is expected (bac reduce)

For an ECU calibrated over XCP, each parameter also says where the ECU holds it
(``xcp:``, an :class:`EcuAddress`, written by ``bac definition from-a2l`` from
the ECU's A2L file), and the definition may carry the XCP-on-CAN settings of
the A2L's IF_DATA (a top-level ``xcp:`` mapping, read by the ECU bridge)::

    parameters:
      - {name: p01, index: 0, lower: 0, upper: 1000, nominal: 500, resolution: 0.01,
         xcp: {address: 0x40000100, datatype: ULONG, conversion: LINEAR, coeffs: [0.01, 0.0]}}
    xcp: {can_id_master: 0x7E0, can_id_slave: 0x7E1, segment: 0, reference_page: 0, working_page: 1}
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bac_common.errors import DefinitionError, OutOfBoundsError, UnknownParameterError

MAX_PARAMETER_INDEX = 255


XCP_DATATYPES = (
    "UBYTE",
    "SBYTE",
    "UWORD",
    "SWORD",
    "ULONG",
    "SLONG",
    "A_UINT64",
    "A_INT64",
    "FLOAT32_IEEE",
    "FLOAT64_IEEE",
)
BYTE_ORDERS = ("MSB_LAST", "MSB_FIRST")  # A2L: MSB_LAST = little endian (Intel), MSB_FIRST = big endian (Motorola)
CONVERSIONS = {"IDENTICAL": 0, "LINEAR": 2, "RAT_FUNC": 6}  # A2L COMPU_METHOD kinds and their coefficient counts


@dataclass(frozen=True)
class EcuAddress:
    """Where an XCP ECU holds one raw parameter, and how (an A2L CHARACTERISTIC of type VALUE).

    ``conversion`` is the A2L COMPU_METHOD from the ECU's internal value x to the physical value p:
    IDENTICAL (p = x), LINEAR (``coeffs`` = (a, b): p = a x + b, COEFFS_LINEAR) or RAT_FUNC in its linear
    form (``coeffs`` = (a, b, c, d, e, f) with a = d = e = 0: x = (b p + c) / f, COEFFS).
    """

    address: int
    datatype: str
    byte_order: str = "MSB_LAST"
    extension: int = 0
    conversion: str = "IDENTICAL"
    coeffs: tuple[float, ...] = ()
    characteristic: str = ""  # the A2L CHARACTERISTIC's name, when it is not the parameter's

    def __post_init__(self) -> None:
        object.__setattr__(self, "coeffs", tuple(float(c) for c in self.coeffs))
        if not 0 <= self.address <= 0xFFFF_FFFF:
            raise DefinitionError(f"XCP address 0x{self.address:X} does not fit 32 bits")
        if not 0 <= self.extension <= 0xFF:
            raise DefinitionError(f"XCP address extension {self.extension} does not fit one byte")
        if self.datatype not in XCP_DATATYPES:
            raise DefinitionError(f"XCP datatype {self.datatype!r} is not one of {', '.join(XCP_DATATYPES)}")
        if self.byte_order not in BYTE_ORDERS:
            raise DefinitionError(f"byte order {self.byte_order!r} is not MSB_LAST (Intel) or MSB_FIRST (Motorola)")
        if self.conversion not in CONVERSIONS:
            raise DefinitionError(f"conversion {self.conversion!r} is not IDENTICAL, LINEAR or RAT_FUNC")
        if len(self.coeffs) != CONVERSIONS[self.conversion]:
            raise DefinitionError(
                f"a {self.conversion} conversion takes {CONVERSIONS[self.conversion]} coefficients, "
                f"got {len(self.coeffs)}"
            )
        if not all(math.isfinite(c) for c in self.coeffs):
            raise DefinitionError("conversion coefficients must be finite")
        if self.conversion == "LINEAR" and self.coeffs[0] == 0:
            raise DefinitionError("a LINEAR conversion needs a non-zero factor a (p = a x + b)")
        if self.conversion == "RAT_FUNC":
            a, b, _c, d, e, f = self.coeffs
            if a != 0 or d != 0 or e != 0 or b == 0 or f == 0:
                raise DefinitionError(
                    f"RAT_FUNC coefficients {list(self.coeffs)} are not linear (needs a = d = e = 0, b != 0, f != 0): "
                    "only x = (b p + c) / f is supported"
                )

    @property
    def linear(self) -> tuple[float, float]:
        """(factor, offset) with p = factor * x + offset."""
        if self.conversion == "LINEAR":
            return self.coeffs[0], self.coeffs[1]
        if self.conversion == "RAT_FUNC":
            _a, b, c, _d, _e, f = self.coeffs
            return f / b, -c / b
        return 1.0, 0.0

    @property
    def is_float(self) -> bool:
        return self.datatype.startswith("FLOAT")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"address": self.address, "datatype": self.datatype}
        if self.byte_order != "MSB_LAST":
            out["byte_order"] = self.byte_order
        if self.extension:
            out["extension"] = self.extension
        out["conversion"] = self.conversion
        if self.coeffs:
            out["coeffs"] = list(self.coeffs)
        if self.characteristic:
            out["characteristic"] = self.characteristic
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EcuAddress:
        known = {"address", "datatype", "byte_order", "extension", "conversion", "coeffs", "characteristic"}
        unknown = set(data) - known
        if unknown:
            raise DefinitionError(f"unknown xcp fields {sorted(unknown)} (known: {sorted(known)})")
        try:
            return cls(
                address=int(data["address"]),
                datatype=str(data["datatype"]),
                byte_order=str(data.get("byte_order", "MSB_LAST")),
                extension=int(data.get("extension", 0)),
                conversion=str(data.get("conversion", "IDENTICAL")),
                coeffs=tuple(float(c) for c in data.get("coeffs") or ()),
                characteristic=str(data.get("characteristic", "")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise DefinitionError(f"malformed xcp address {dict(data)}: {exc}") from exc


@dataclass(frozen=True)
class RawParameter:
    """One calibration parameter as the ECU knows it."""

    name: str
    index: int  # CAN parameter index, 0..255
    lower: float
    upper: float
    nominal: float  # value used when the parameter is not calibrated
    resolution: float  # CAN encoding step (one LSB), in the parameter's unit
    unit: str = ""
    description: str = ""
    xcp: EcuAddress | None = None  # where an XCP ECU holds it (None: the parameter is not reachable over XCP)

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("_", "").isalnum():
            raise DefinitionError(f"parameter name {self.name!r} must be a non-empty identifier")
        if not 0 <= self.index <= MAX_PARAMETER_INDEX:
            raise DefinitionError(f"parameter '{self.name}': index {self.index} outside 0..{MAX_PARAMETER_INDEX}")
        if not (math.isfinite(self.lower) and math.isfinite(self.upper) and self.lower < self.upper):
            raise DefinitionError(
                f"parameter '{self.name}': bounds [{self.lower}, {self.upper}] must be finite with lower < upper"
            )
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise DefinitionError(f"parameter '{self.name}': resolution must be > 0, got {self.resolution}")
        if not self.lower <= self.nominal <= self.upper:
            raise DefinitionError(
                f"parameter '{self.name}': nominal {self.nominal} outside [{self.lower}, {self.upper}]"
            )

    def contains(self, value: float) -> bool:
        return math.isfinite(value) and self.lower <= value <= self.upper

    def check(self, value: float) -> float:
        """Return ``value`` as float, or raise :class:`OutOfBoundsError`."""
        value = float(value)
        if not self.contains(value):
            raise OutOfBoundsError(self.name, value, self.lower, self.upper)
        return value

    def quantize(self, value: float) -> float:
        """The value the ECU will hold after encoding with this resolution."""
        steps = round((self.check(value) - self.lower) / self.resolution)
        return min(self.lower + steps * self.resolution, self.upper)


@dataclass(frozen=True)
class MetaParameter:
    """A tuned dimension that drives several raw parameters at once."""

    name: str
    members: tuple[str, ...]
    lower: float = 0.0
    upper: float = 1.0
    description: str = ""

    def __post_init__(self) -> None:
        if not self.members:
            raise DefinitionError(f"meta-parameter '{self.name}' has no members")
        if len(set(self.members)) != len(self.members):
            raise DefinitionError(f"meta-parameter '{self.name}' lists a member twice")
        if not (math.isfinite(self.lower) and math.isfinite(self.upper) and self.lower < self.upper):
            raise DefinitionError(f"meta-parameter '{self.name}': bounds must be finite with lower < upper")


@dataclass(frozen=True)
class Dimension:
    """One tuned dimension of the optimization (a raw or a meta-parameter)."""

    name: str
    lower: float
    upper: float
    is_meta: bool


@dataclass(frozen=True)
class CalibrationDefinition:
    """The calibration of one controller: raw parameters, tuned dimensions, fixed values."""

    name: str
    parameters: tuple[RawParameter, ...]
    tuned: tuple[str, ...] = ()
    meta: tuple[MetaParameter, ...] = ()
    fixed: Mapping[str, float] = field(default_factory=dict)
    baseline: Mapping[str, float] = field(default_factory=dict)
    description: str = ""
    # a best guess of the optimum over the tuned dimensions (e.g. the simulation phase's reduced optimum, written
    # by `bac reduce`): the agent may drive it first (the paper's "best guess policy" of the initialization)
    best_guess: Mapping[str, float] = field(default_factory=dict)
    # the XCP-on-CAN settings of the ECU holding this calibration (the A2L's IF_DATA; read by the ECU bridge)
    xcp: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [p.name for p in self.parameters]
        if not names:
            raise DefinitionError(f"definition '{self.name}' declares no parameters")
        if len(set(names)) != len(names):
            raise DefinitionError(f"definition '{self.name}': duplicate parameter names")
        indices = [p.index for p in self.parameters]
        if len(set(indices)) != len(indices):
            raise DefinitionError(f"definition '{self.name}': duplicate CAN parameter indices")
        by_name = {p.name: p for p in self.parameters}
        meta_names = [m.name for m in self.meta]
        if set(meta_names) & set(names) or len(set(meta_names)) != len(meta_names):
            raise DefinitionError(f"definition '{self.name}': meta-parameter names must be unique and new")
        driven: set[str] = set()
        for m in self.meta:
            for member in m.members:
                if member not in by_name:
                    raise DefinitionError(f"meta-parameter '{m.name}': unknown member '{member}'")
                if member in driven:
                    raise DefinitionError(f"raw parameter '{member}' belongs to two meta-parameters")
                driven.add(member)
        tuned = self.tuned or tuple(names)
        object.__setattr__(self, "tuned", tuple(tuned))
        if len(set(tuned)) != len(tuned):
            raise DefinitionError(f"definition '{self.name}': a tuned dimension is listed twice")
        meta_by_name = {m.name: m for m in self.meta}
        for t in tuned:
            if t not in by_name and t not in meta_by_name:
                raise DefinitionError(f"tuned dimension '{t}' is neither a parameter nor a meta-parameter")
            if t in driven:
                raise DefinitionError(f"'{t}' is tuned directly and also driven by a meta-parameter")
        unused_meta = set(meta_by_name) - set(tuned)
        if unused_meta:
            raise DefinitionError(f"meta-parameters not tuned: {sorted(unused_meta)}")
        for key, table in (("fixed", self.fixed), ("baseline", self.baseline)):
            for n, v in table.items():
                if n not in by_name:
                    raise UnknownParameterError(n, tuple(names))
                by_name[n].check(v)
            if key == "fixed":
                clash = set(table) & (set(tuned) | driven)
                if clash:
                    raise DefinitionError(f"parameters both fixed and tuned: {sorted(clash)}")
        object.__setattr__(self, "fixed", dict(self.fixed))
        object.__setattr__(self, "baseline", dict(self.baseline))
        guess = {str(k): float(v) for k, v in self.best_guess.items()}
        if guess:
            if set(guess) != set(tuned):
                raise DefinitionError(
                    f"definition '{self.name}': best_guess must give every tuned dimension ({', '.join(tuned)}), "
                    f"got {', '.join(sorted(guess))}"
                )
            for dim in self.dimensions:
                v = guess[dim.name]
                if not (dim.lower <= v <= dim.upper):
                    raise DefinitionError(
                        f"definition '{self.name}': best_guess {dim.name} = {v:g} is outside [{dim.lower:g}, "
                        f"{dim.upper:g}]"
                    )
        object.__setattr__(self, "best_guess", guess)
        object.__setattr__(self, "xcp", dict(self.xcp))

    # --- look-ups ------------------------------------------------------------------
    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    def parameter(self, name: str) -> RawParameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise UnknownParameterError(name, self.parameter_names)

    def meta_parameter(self, name: str) -> MetaParameter:
        for m in self.meta:
            if m.name == name:
                return m
        raise UnknownParameterError(name, tuple(m.name for m in self.meta))

    @property
    def dimensions(self) -> tuple[Dimension, ...]:
        """The tuned dimensions, in order, with their bounds."""
        meta_by_name = {m.name: m for m in self.meta}
        dims = []
        for t in self.tuned:
            if t in meta_by_name:
                m = meta_by_name[t]
                dims.append(Dimension(t, m.lower, m.upper, True))
            else:
                p = self.parameter(t)
                dims.append(Dimension(t, p.lower, p.upper, False))
        return tuple(dims)

    def baseline_values(self) -> dict[str, float]:
        """The safe calibration (raw, every parameter): baseline, else fixed, else nominal."""
        return {p.name: float(self.baseline.get(p.name, self.fixed.get(p.name, p.nominal))) for p in self.parameters}

    def baseline_tuned(self) -> dict[str, float]:
        """The safe calibration in the tuned dimensions (what an optimizer can start from): a raw dimension's
        baseline value; a meta-parameter at its members' mean relative position in their ranges (exact when the
        baseline moves them together), within its bounds."""
        base = self.baseline_values()
        out: dict[str, float] = {}
        for d in self.dimensions:
            if not d.is_meta:
                out[d.name] = min(max(base[d.name], d.lower), d.upper)
                continue
            m = self.meta_parameter(d.name)
            rel = [(base[n] - p.lower) / (p.upper - p.lower) for n in m.members for p in (self.parameter(n),)]
            u = min(max(sum(rel) / len(rel), 0.0), 1.0)
            out[d.name] = m.lower + u * (m.upper - m.lower)
        return out

    # --- tuned values -> raw values ------------------------------------------------------
    def expand(self, values: Mapping[str, float]) -> dict[str, float]:
        """Map tuned values (every tuned dimension, by name) to the full raw calibration.

        Raises :class:`UnknownParameterError` for a name that is not tuned,
        :class:`DefinitionError` for a missing dimension and
        :class:`OutOfBoundsError` for a value outside its bounds.
        """
        dims = {d.name: d for d in self.dimensions}
        for n in values:
            if n not in dims:
                raise UnknownParameterError(n, tuple(dims))
        missing = [n for n in dims if n not in values]
        if missing:
            raise DefinitionError(f"calibration lacks tuned dimensions: {missing}")
        raw: dict[str, float] = {p.name: float(self.fixed.get(p.name, p.nominal)) for p in self.parameters}
        for name, d in dims.items():
            v = float(values[name])
            if not (math.isfinite(v) and d.lower <= v <= d.upper):
                raise OutOfBoundsError(name, v, d.lower, d.upper)
            if d.is_meta:
                m = self.meta_parameter(name)
                u = (v - m.lower) / (m.upper - m.lower)
                for member in m.members:
                    p = self.parameter(member)
                    raw[member] = min(max(p.lower + u * (p.upper - p.lower), p.lower), p.upper)
            else:
                raw[name] = v
        self.check_raw(raw)
        return raw

    def check_raw(self, raw: Mapping[str, float]) -> None:
        """Raise unless every name is declared and every value within its bounds."""
        for n, v in raw.items():
            self.parameter(n).check(v)

    # --- (de)serialization -----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "description": self.description,
            "parameters": [
                {
                    "name": p.name,
                    "index": p.index,
                    "lower": p.lower,
                    "upper": p.upper,
                    "nominal": p.nominal,
                    "resolution": p.resolution,
                    "unit": p.unit,
                    "description": p.description,
                    **({"xcp": p.xcp.to_dict()} if p.xcp is not None else {}),
                }
                for p in self.parameters
            ],
            "tuned": list(self.tuned),
            "meta": [
                {
                    "name": m.name,
                    "members": list(m.members),
                    "lower": m.lower,
                    "upper": m.upper,
                    "description": m.description,
                }
                for m in self.meta
            ],
            "fixed": dict(self.fixed),
            "baseline": dict(self.baseline),
        }
        if self.best_guess:
            out["best_guess"] = dict(self.best_guess)
        if self.xcp:
            out["xcp"] = dict(self.xcp)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> CalibrationDefinition:
        try:
            params = tuple(
                RawParameter(
                    name=str(p["name"]),
                    index=int(p["index"]),
                    lower=float(p["lower"]),
                    upper=float(p["upper"]),
                    nominal=float(p.get("nominal", (float(p["lower"]) + float(p["upper"])) / 2)),
                    resolution=float(p["resolution"]),
                    unit=str(p.get("unit", "")),
                    description=str(p.get("description", "")),
                    xcp=EcuAddress.from_dict(p["xcp"]) if p.get("xcp") else None,
                )
                for p in data["parameters"]
            )
            meta = tuple(
                MetaParameter(
                    name=str(m["name"]),
                    members=tuple(str(x) for x in m["members"]),
                    lower=float(m.get("lower", 0.0)),
                    upper=float(m.get("upper", 1.0)),
                    description=str(m.get("description", "")),
                )
                for m in data.get("meta") or ()
            )
            return cls(
                name=str(data["name"]),
                description=str(data.get("description", "")),
                parameters=params,
                tuned=tuple(str(t) for t in data.get("tuned") or ()),
                meta=meta,
                fixed={str(k): float(v) for k, v in (data.get("fixed") or {}).items()},
                baseline={str(k): float(v) for k, v in (data.get("baseline") or {}).items()},
                best_guess={str(k): float(v) for k, v in (data.get("best_guess") or {}).items()},
                xcp=dict(data.get("xcp") or {}),
            )
        except (KeyError, TypeError) as exc:
            raise DefinitionError(f"malformed calibration definition: missing or wrong field {exc}") from exc

    @classmethod
    def load(cls, path: str | Path) -> CalibrationDefinition:
        import yaml

        p = Path(path)
        try:
            data = yaml.safe_load(p.read_text())
        except FileNotFoundError as exc:
            raise DefinitionError(f"calibration definition file not found: {p}") from exc
        except yaml.YAMLError as exc:
            raise DefinitionError(f"{p}: not valid YAML: {exc}") from exc
        if not isinstance(data, Mapping):
            raise DefinitionError(f"{p}: expected a mapping at the top level")
        return cls.from_dict(data)

    def save(self, path: str | Path) -> None:
        import yaml

        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


def uniform_parameters(
    prefix: str, count: int, lower: float, upper: float, nominal: float, resolution: float, start_index: int = 0
) -> tuple[RawParameter, ...]:
    """``count`` parameters named ``prefix01``..., with the same range (e.g. Controller II)."""
    width = max(2, len(str(count)))
    return tuple(
        RawParameter(
            name=f"{prefix}{i + 1:0{width}d}",
            index=start_index + i,
            lower=lower,
            upper=upper,
            nominal=nominal,
            resolution=resolution,
        )
        for i in range(count)
    )


def as_mapping(names: Sequence[str], values: Sequence[float]) -> dict[str, float]:
    """Pair names and values (e.g. from a Calibration message), refusing mismatches."""
    if len(names) != len(values):
        raise DefinitionError(f"{len(names)} names but {len(values)} values")
    if len(set(names)) != len(names):
        raise DefinitionError("a parameter name is given twice")
    return {str(n): float(v) for n, v in zip(names, values, strict=True)}
