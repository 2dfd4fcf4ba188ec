"""Calibration definitions from an ECU's A2L file (ASAM MCD-2 MC), and the A2L of a definition.

:func:`definition_from_a2l` reads an A2L with pya2ldb (the ``pya2l`` module of
the PyPI package ``pya2ldb``, by pyxcp's author) and writes the calibration
definition of the named CHARACTERISTICs (type VALUE):

* the address, address extension, data type (RECORD_LAYOUT's FNC_VALUES) and
  byte order (the characteristic's BYTE_ORDER, else MOD_COMMON's);
* LOWER_LIMIT / UPPER_LIMIT as the bounds, moved inward onto the values the data type holds through the
  conversion (so the agent's grid is the ECU's); limits beyond the data type are refused;
* the COMPU_METHOD: IDENTICAL, LINEAR (COEFFS_LINEAR) or RAT_FUNC in its linear
  form (COEFFS with a = d = e = 0); other forms are refused with a reason;
* the resolution: one step of the internal value (|factor| of the conversion)
  for integer types; for floats the STEP_SIZE, else the FORMAT's decimals;
* the unit (PHYS_UNIT, else the COMPU_METHOD's) and the long identifier;
* the XCP-on-CAN ids of the module's IF_DATA XCP (CAN_ID_MASTER, CAN_ID_SLAVE,
  MAX_DLC_REQUIRED; two different pairs are refused) and the calibration pages
  of the MEMORY_SEGMENT holding the characteristics (its IF_DATA XCP SEGMENT:
  two pages are a reference page 0 and a working page 1).

A characteristic bac cannot write as one value at its address (BIT_MASK,
pointer or offset record layouts, READ_ONLY, no CALIBRATION_ACCESS, virtual,
defined twice, an ambiguous byte order, not a VALUE) is refused with the
reason (:func:`_cannot_write`); the file and every file it ``/include``s must
be whole (:func:`check_a2l_files`).

Nominal and baseline values are not in an A2L: they are read from the ECU's
reference page (the flashed data set) or given.

:func:`a2l_text` writes the A2L of a definition whose parameters carry XCP
addresses (the shipped ``bac_ecu_bridge/a2l/*.a2l`` describe the simulated
ECU; the test suite reads them back with pya2ldb to the same definition).

pya2ldb is GPL-2.0-or-later: bac (Apache-2.0) imports it only here, only when
an A2L is read; the bridge, the node and the simulator never do.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import sys
import tempfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from bac_common.errors import DefinitionError
from bac_common.paramspace import CalibrationDefinition, EcuAddress, RawParameter
from bac_ecu_bridge.xcp.layout import datatype_size, integer_range

FLOAT_DEFAULT_DECIMALS = 6


class A2lError(DefinitionError):
    """An A2L file that cannot be read, or a characteristic that cannot become a calibration parameter."""


@dataclass(frozen=True)
class A2lCharacteristic:
    """One CHARACTERISTIC of type VALUE, as read from an A2L."""

    name: str
    description: str
    address: int
    extension: int
    datatype: str
    byte_order: str
    conversion: str
    coeffs: tuple[float, ...]
    lower: float
    upper: float
    unit: str
    decimals: int | None  # from the FORMAT (characteristic's, else the COMPU_METHOD's)
    step_size: float | None = None  # the characteristic's STEP_SIZE (a calibration tool's increment)


@dataclass(frozen=True)
class MemorySegment:
    """A MEMORY_SEGMENT and the XCP paging of its IF_DATA XCP SEGMENT (None: the A2L gives none)."""

    name: str
    address: int
    size: int
    segment: int | None  # XCP segment number
    pages: int | None  # number of calibration pages

    def holds(self, address: int, size: int) -> bool:
        return self.address <= address and address + size <= self.address + self.size


@dataclass(frozen=True)
class A2lModule:
    name: str
    characteristics: dict[str, A2lCharacteristic]
    xcp: dict[str, Any]  # XCP-on-CAN settings found in IF_DATA
    problems: dict[str, str] = field(default_factory=dict)  # characteristics bac cannot write, and why
    segments: tuple[MemorySegment, ...] = ()
    notes: tuple[str, ...] = ()  # what the user should know about the settings read
    all_characteristics: frozenset[str] = frozenset()  # every CHARACTERISTIC's name, also those not read


def _load_pya2l() -> Any:
    """pya2ldb without its side effects: it installs rich's traceback handler (locals shown) on import."""
    hooks = (sys.excepthook, sys.displayhook)
    try:
        import pya2l  # GPL-2.0-or-later: imported here only (see the module doc)
        import pya2l.model as model  # noqa: PLR0402  (mypy: pya2l does not export model)
    except ImportError as exc:
        raise A2lError(
            f"reading A2L files needs pya2ldb (pip install pya2ldb; it is in requirements/runtime.txt): {exc}"
        ) from None
    finally:
        sys.excepthook, sys.displayhook = hooks
    # pya2ldb's parser sets its logger to INFO each time and prints progress: only its warnings pass
    lg = logging.getLogger("pya2l.A2LDB")
    if not any(isinstance(f, _QuietInfo) for f in lg.filters):
        lg.addFilter(_QuietInfo())
    return pya2l, model


class _QuietInfo(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING


def _decimals(fmt: str | None) -> int | None:
    m = re.match(r"\s*%\s*\d*\.(\d+)", fmt or "")
    return int(m.group(1)) if m else None


# comments and strings, so that a /begin or /end in them is not taken for a block (newlines kept: line numbers)
_A2L_NOISE = re.compile(r'/\*.*?\*/|//[^\n]*|"(?:\\.|[^"\\])*"', re.DOTALL)
_A2L_BLOCK = re.compile(r"/(begin|end)\s+(\w+)")


def check_a2l_structure(text: str, path: str | Path = "A2L", whole: bool = True) -> None:
    """Refuse a truncated or broken A2L before it is parsed: every ``/begin X`` needs its ``/end X``.

    pya2ldb reports a premature end of file on its log and goes on: a file cut within a CHARACTERISTIC's limits
    read as an upper limit of 0.9 where the whole file says 0.95 (outside review, 2026-11-29)."""
    if "\0" in text:
        raise A2lError(f"{path}: holds NUL bytes: not an A2L text file")
    body = _A2L_NOISE.sub(lambda m: "\n" * m.group().count("\n") + " ", text)
    for opener in ("/*", '"'):
        i = body.find(opener)
        if i >= 0:
            what = "a comment" if opener == "/*" else "a string"
            raise A2lError(
                f"{path}: line {body.count(chr(10), 0, i) + 1}: {what} that never ends: the file is truncated or broken"
            )
    stack: list[tuple[str, int]] = []
    line, last, seen = 1, 0, False
    for m in _A2L_BLOCK.finditer(body):
        line += body.count("\n", last, m.start())  # (a running count: A2Ls of 100 MB have 1e5-1e6 blocks)
        last, seen = m.start(), True
        kind, name = m.group(1), m.group(2)
        if kind == "begin":
            stack.append((name, line))
            continue
        if not stack:
            raise A2lError(f"{path}: line {line}: /end {name} without a /begin")
        top, top_line = stack.pop()
        if top != name:
            raise A2lError(f"{path}: line {line}: /end {name} closes /begin {top} of line {top_line}")
    if stack:
        name, line = stack[-1]
        raise A2lError(
            f"{path}: the file ends inside /begin {name} (line {line}) and {len(stack) - 1} enclosing block(s): "
            "it is truncated (copy it again from the ECU supplier's release)"
        )
    if not seen and whole:  # (an included file may hold no block)
        raise A2lError(f"{path}: no /begin ... /end block: not an A2L file")


# an /include and its file name, or a comment or string to pass over (an /include in them is none)
_A2L_INCLUDE = re.compile(r'/\*.*?\*/|//[^\n]*|/include\s+(?:"([^"]+)"|([^\s"]+))|"(?:\\.|[^"\\])*"', re.DOTALL)


def a2l_encoding(data: bytes) -> str:
    """UTF-8 when the bytes are UTF-8 (a BOM is skipped), else Latin-1 (every byte a character, ASAM's default)."""
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        return "latin-1"
    return "utf-8-sig" if data.startswith(b"\xef\xbb\xbf") else "utf-8"


def check_a2l_files(path: Path, encoding: str, seen: set[Path] | None = None) -> None:
    """:func:`check_a2l_structure` of an A2L and of every file it ``/include``s (a truncated included file was
    read to a wrong limit, as the main file was before the check: outside review 2026-11-29)."""
    seen = set() if seen is None else seen
    real = path.resolve()
    if real in seen:
        raise A2lError(f"{path}: included again (an /include cycle)")
    seen.add(real)
    text = path.read_bytes().decode(encoding if encoding != "utf-8-sig" else "utf-8-sig", errors="replace")
    check_a2l_structure(text, path, whole=not seen - {real})
    for m in _A2L_INCLUDE.finditer(text):
        if not (m.group(1) or m.group(2)):
            continue  # a comment or a string
        name = Path(m.group(1) or m.group(2))
        # where pya2ldb looks (its preprocessor's locate_file): as given (the working folder), then beside the file
        places = [name] if name.is_absolute() else [name, path.parent / name]
        inc = next((c for c in places if c.is_file()), None)
        if inc is None:
            raise A2lError(f"{path}: /include {name}: no such file ({' or '.join(str(c) for c in places)})")
        check_a2l_files(inc, a2l_encoding(inc.read_bytes()), seen)


# blocks bac never reads (in a supplier's A2L of 50-100 MB most of the text): left out before pya2ldb parses it
SLIM_DROP = frozenset({"MEASUREMENT", "FUNCTION", "GROUP", "FRAME", "USER_RIGHTS", "BLOB", "TRANSFORMER"})
_A2L_TOKEN = re.compile(r"/(begin|end)\s+(\w+)|/include\b")  # on the masked text: not in a comment or string
_A2L_INCLUDE_NAME = re.compile(r'/include\s+(?:"([^"]+)"|([^\s"]+))')  # on the text itself: the name may be a string
_A2L_NAME = re.compile(r"\s*([^\s/]+)")


def _mask(text: str) -> str:
    """``text`` with its comments and strings blanked, offsets and newlines kept."""
    return _A2L_NOISE.sub(lambda m: re.sub(r"[^\n]", " ", m.group()), text)


def _include_target(path: Path, name: str) -> Path:
    # where pya2ldb looks (its preprocessor's locate_file): as given (the working folder), then beside the file
    n = Path(name)
    places = [n] if n.is_absolute() else [n, path.parent / n]
    found = next((c for c in places if c.is_file()), None)
    if found is None:
        raise A2lError(f"{path}: /include {n}: no such file ({' or '.join(str(c) for c in places)})")
    return found


def slim_a2l(
    path: Path,
    out_dir: Path,
    keep: frozenset[str] | None = None,
    names: set[str] | None = None,
    inside_if_data: bool = False,
) -> Path:
    """A copy of the A2L in ``out_dir`` without the blocks bac never reads (:data:`SLIM_DROP`) and, when ``keep``
    is given, without the CHARACTERISTICs it does not name; each ``/include``d file slimmed the same way and
    included by its new path. A block left out becomes as many empty lines as it had, so that pya2ldb's line
    numbers stay the file's. ``names`` gets the name of every CHARACTERISTIC met (kept or not). Nothing inside an
    IF_DATA or A2ML block is left out (a supplier's A2ML may define its own GROUP or FRAME blocks). The files must
    have passed :func:`check_a2l_files`."""
    encoding = a2l_encoding(path.read_bytes())
    text = path.read_bytes().decode(encoding)
    body = _mask(text)
    pieces: list[str] = []
    at = 0
    depth = 0
    drop_depth = -1  # the depth of the block being left out, -1: none
    drop_from = 0
    vendor: list[int] = [0] if inside_if_data else []  # depths of the open IF_DATA / A2ML blocks
    for m in _A2L_TOKEN.finditer(body):
        kind, block = m.group(1), m.group(2)
        if kind is None:  # an /include
            inc = _A2L_INCLUDE_NAME.match(text, m.start())
            if inc is not None and drop_depth < 0:
                target = slim_a2l(
                    _include_target(path, inc.group(1) or inc.group(2)), out_dir, keep, names, bool(vendor)
                )
                pieces.append(text[at : m.start()])
                pieces.append(f'/include "{target}"')
                at = inc.end()
            continue
        if kind == "begin":
            depth += 1
            if drop_depth >= 0:
                continue
            if block in ("IF_DATA", "A2ML"):
                vendor.append(depth)
            leave = block in SLIM_DROP and not vendor
            if block == "CHARACTERISTIC":
                nm = _A2L_NAME.match(body, m.end())
                name = nm.group(1) if nm else ""
                if names is not None:
                    names.add(name)
                leave = keep is not None and name not in keep
            if leave:
                drop_depth, drop_from = depth, m.start()
        else:
            if drop_depth == depth:
                pieces.append(text[at:drop_from])
                pieces.append("\n" * text.count("\n", drop_from, m.end()))
                at = m.end()
                drop_depth = -1
            elif drop_depth < 0 and vendor and vendor[-1] == depth:
                vendor.pop()
            depth -= 1
    pieces.append(text[at:])
    out = out_dir / f"{len(list(out_dir.iterdir())):04d}_{path.name}"
    out.write_bytes("".join(pieces).encode(encoding))
    return out


def _short_reason(exc: Exception) -> str:
    """pya2ldb's error in a line: its database's errors carry the whole SQL statement and its parameters."""
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    m = re.search(r"NOT NULL constraint failed: (\w+)\.(\w+)", first)
    if m:
        return (
            f"a {m.group(1).upper()} has no valid {m.group(2)} (missing, or not a number such as NaN; the parser's "
            "log above names the line)"
        )
    return re.sub(r"^\(\w+(\.\w+)*\)\s*", "", first)


def read_a2l(path: str | Path, only: Iterable[str] | None = None) -> A2lModule:
    """Every VALUE characteristic of the A2L's (first) module (``only``: those named; the module's
    ``all_characteristics`` still names every one), and its XCP-on-CAN settings.

    pya2ldb parses the file after :func:`slim_a2l` has left out what bac never reads (measurements, functions,
    groups, and the characteristics not named): a supplier's A2L of 5 MB took 23 s and 0.7 GB whole."""
    p = Path(path)
    if not p.is_file():
        raise A2lError(f"A2L file not found: {p}")
    encoding = a2l_encoding(p.read_bytes())
    check_a2l_files(p, encoding)
    pya2l, model = _load_pya2l()
    with tempfile.TemporaryDirectory(prefix="bac-a2l-") as tmp:
        names: set[str] = set()
        slim_dir = Path(tmp) / "slim"
        slim_dir.mkdir()
        slim = slim_a2l(p, slim_dir, frozenset(only) if only is not None else None, names)
        try:
            # in memory: pya2ldb writes no .a2ldb file (output_dir: in case a version ignores in_memory)
            session = pya2l.import_a2l(
                str(slim), in_memory=True, progress_bar=False, loglevel="ERROR", output_dir=tmp, encoding=encoding
            )
        except Exception as exc:  # pya2ldb raises many kinds on a malformed file
            raise A2lError(f"{p}: not a readable A2L file: {_short_reason(exc)}") from exc
        try:
            return dataclasses.replace(_module(session, model, p), all_characteristics=frozenset(names))
        finally:
            try:
                session.close()
            except Exception:  # closing an in-memory database must not hide the result
                pass


def _module(session: Any, model: Any, path: Path) -> A2lModule:
    module = session.query(model.Module).first()
    if module is None:
        raise A2lError(f"{path}: no MODULE")
    mod_common = session.query(model.ModCommon).first()
    default_order = "MSB_LAST"
    if mod_common is not None and mod_common.byte_order is not None:
        default_order = str(mod_common.byte_order.byteOrder)
    layouts = {rl.name: rl for rl in session.query(model.RecordLayout).all()}
    methods = {cm.name: cm for cm in session.query(model.CompuMethod).all()}
    chars: dict[str, A2lCharacteristic] = {}
    problems: dict[str, str] = {}
    addresses: dict[str, list[int]] = {}
    for c in session.query(model.Characteristic).all():
        addresses.setdefault(str(c.name), []).append(int(c.address))
        why = _cannot_write(c, layouts.get(c.deposit))
        if why:
            problems[str(c.name)] = why
            continue
        rl = layouts[c.deposit]
        cm = methods.get(c.conversion)
        kind, unit, cm_format = "IDENTICAL", "", None
        coeffs: tuple[float, ...] = ()
        if cm is not None:
            kind = str(cm.conversionType)
            unit = str(cm.unit or "")
            cm_format = cm.format
            if kind == "LINEAR" and cm.coeffs_linear is not None:
                coeffs = (float(cm.coeffs_linear.a), float(cm.coeffs_linear.b))
            elif kind == "RAT_FUNC" and cm.coeffs is not None:
                k = cm.coeffs
                coeffs = tuple(float(v) for v in (k.a, k.b, k.c, k.d, k.e, k.f))
        elif c.conversion != "NO_COMPU_METHOD":
            raise A2lError(f"{path}: CHARACTERISTIC {c.name}: COMPU_METHOD {c.conversion} not found")
        order = str(c.byte_order.byteOrder) if c.byte_order is not None else default_order
        if order in _AMBIGUOUS_ORDERS:
            problems[str(c.name)] = (
                f"BYTE_ORDER {order} (deprecated; ASAP2 1.x read it as the opposite of its name, and tools still "
                "differ): the A2L must say MSB_FIRST or MSB_LAST"
            )
            continue
        fmt = c.format.formatString if c.format is not None else cm_format
        chars[c.name] = A2lCharacteristic(
            name=str(c.name),
            description=str(c.longIdentifier or ""),
            address=int(c.address),
            extension=int(c.ecu_address_extension.extension) if c.ecu_address_extension is not None else 0,
            datatype=str(rl.fnc_values.datatype),
            byte_order=order,
            conversion=kind,
            coeffs=coeffs,
            lower=float(c.lowerLimit),
            upper=float(c.upperLimit),
            unit=str(c.phys_unit.unit) if c.phys_unit is not None else unit,  # PHYS_UNIT wins (ASAP2 1.6)
            decimals=_decimals(fmt),
            step_size=float(c.step_size.stepSize) if c.step_size is not None else None,
        )
    for name, where in addresses.items():
        if len(where) > 1:
            chars.pop(name, None)
            problems[name] = f"defined {len(where)} times (at {', '.join(hex(a) for a in where)}): which one is meant?"
    xcp, segments, notes = _xcp_settings(session, model, module)
    return A2lModule(str(module.name), chars, xcp, problems, segments, notes)


_AMBIGUOUS_ORDERS = ("BIG_ENDIAN", "LITTLE_ENDIAN", "_BIG_ENDIAN", "_LITTLE_ENDIAN")
_WRITABLE_ACCESS = ("CALIBRATION",)  # OFFLINE_CALIBRATION: only in the data set, not in the running ECU


def _cannot_write(c: Any, rl: Any) -> str:
    """Why bac cannot write CHARACTERISTIC ``c`` as one value at its address ("" when it can)."""
    if c.type != "VALUE":
        return f"a {c.type}: bac tunes VALUE characteristics (one number each), not curves, maps or blocks"
    if c.virtual_characteristic is not None:
        return "a VIRTUAL_CHARACTERISTIC: computed from others, not held in memory"
    if c.read_only:
        return "READ_ONLY"
    access = c.calibration_access.type if c.calibration_access is not None else "CALIBRATION"
    if str(access) not in _WRITABLE_ACCESS:
        return f"CALIBRATION_ACCESS {access}: the ECU supplier does not allow it to be calibrated"
    if rl is None:
        return f"its RECORD_LAYOUT {c.deposit} is not in the A2L"
    fnc = rl.fnc_values
    if fnc is None:
        return f"RECORD_LAYOUT {c.deposit} has no FNC_VALUES"
    if str(fnc.addresstype) != "DIRECT":
        return (
            f"RECORD_LAYOUT {c.deposit} reaches the value through a pointer (FNC_VALUES ... {fnc.addresstype}): bac "
            "writes a value at the characteristic's address only"
        )
    before = [r for r in _as_list(rl.reserved) + _as_list(rl.identification) if int(r.position) < int(fnc.position)]
    if before:
        return (
            f"RECORD_LAYOUT {c.deposit} puts {len(before)} element(s) (RESERVED, IDENTIFICATION) before FNC_VALUES: "
            "bac writes the value at the characteristic's address itself"
        )
    if c.bit_mask is not None:
        full = (1 << 8 * datatype_size(str(fnc.datatype))) - 1 if str(fnc.datatype) in _INTEGER_TYPES else None
        if full is None or int(c.bit_mask.mask) & full != full:
            return (
                f"BIT_MASK {int(c.bit_mask.mask):#x}: the value is some bits of a {fnc.datatype}, and bac writes whole "
                "values (the other bits would be overwritten)"
            )
    return ""


_INTEGER_TYPES = ("UBYTE", "SBYTE", "UWORD", "SWORD", "ULONG", "SLONG", "A_UINT64", "A_INT64")


def _as_list(v: Any) -> list[Any]:
    return [] if v is None else list(v) if isinstance(v, list | tuple) else [v]


def _walk(node: Any) -> Iterable[tuple[str, Any]]:
    """(key, value) of every dict met in pya2ldb's parsed IF_DATA (nested lists and dicts)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield str(k), v
            yield from _walk(v)
    elif isinstance(node, list | tuple):
        for v in node:
            yield from _walk(v)


def _xcp_settings(
    session: Any, model: Any, module: Any
) -> tuple[dict[str, Any], tuple[MemorySegment, ...], tuple[str, ...]]:
    """The module's XCP-on-CAN settings, its memory segments with their XCP paging, and notes for the user."""
    out: dict[str, Any] = {}
    notes: list[str] = []
    try:
        parsed = session.parse_ifdata(module.if_data)
    except Exception as exc:  # an A2ML pya2ldb cannot use: the settings are then given by hand
        parsed = []
        notes.append(f"the module's IF_DATA could not be read ({_short_reason(exc)})")
    masters: set[int] = set()
    slaves: set[int] = set()
    for key, value in _walk(parsed):
        if key == "CAN_ID_MASTER":
            masters.add(int(value))
        elif key == "CAN_ID_SLAVE":
            slaves.add(int(value))
        elif key == "MAX_DLC_REQUIRED":
            out["max_dlc_required"] = True
        elif key == "BAUDRATE":
            out["baudrate"] = int(value)
    if len(masters) > 1 or len(slaves) > 1:
        raise A2lError(
            f"module {module.name}: its IF_DATA XCP gives several CAN id pairs (CAN_ID_MASTER "
            f"{', '.join(hex(v) for v in sorted(masters))}; CAN_ID_SLAVE {', '.join(hex(v) for v in sorted(slaves))}): "
            "keep the one the ECU answers on, or write the definition's xcp.can_id_master / can_id_slave by hand"
        )
    if masters and slaves:
        (master,), (slave,) = masters, slaves
        out["can_id_master"] = master & 0x1FFF_FFFF
        out["extended_id"] = bool(master & 0x8000_0000) or (master & 0x1FFF_FFFF) > 0x7FF
        out["can_id_slave"] = slave & 0x1FFF_FFFF
    else:
        notes.append(
            "no CAN_ID_MASTER / CAN_ID_SLAVE pair in the A2L's IF_DATA XCP_ON_CAN: set xcp.can_id_master and "
            "xcp.can_id_slave in the definition before it meets an ECU"
        )
    segments: list[MemorySegment] = []
    for seg in session.query(model.MemorySegment).all():
        number = pages = None
        try:
            seg_parsed = session.parse_ifdata(seg.if_data)
        except Exception:
            seg_parsed = []
        for key, value in _walk(seg_parsed):
            if key == "SEGMENT" and isinstance(value, list) and len(value) >= 2:
                number, pages = int(value[0]), int(value[1])  # segment number, number of pages
        segments.append(MemorySegment(str(seg.name), int(seg.address), int(seg.size), number, pages))
    return out, tuple(segments), tuple(notes)


def paging_of(segments: Sequence[MemorySegment], chars: Sequence[A2lCharacteristic]) -> dict[str, Any]:
    """The XCP paging settings for ``chars``: those of the MEMORY_SEGMENT that holds them (bac switches the pages
    of one segment). Refuses characteristics outside every segment, or spread over segments paged differently."""
    if not segments or not chars:
        return {}
    held: dict[str, MemorySegment] = {}
    for ch in chars:
        size = datatype_size(ch.datatype)
        holders = [s for s in segments if s.holds(ch.address, size)]
        if not holders:
            crossed = [s.name for s in segments if s.address <= ch.address < s.address + s.size]
            raise A2lError(
                f"CHARACTERISTIC {ch.name} at {ch.address:#x} ({size} bytes) "
                + (f"crosses the end of MEMORY_SEGMENT {crossed[0]}" if crossed else "lies in no MEMORY_SEGMENT")
                + f" of the A2L ({', '.join(f'{s.name} {s.address:#x}+{s.size:#x}' for s in segments)})"
            )
        # segments may nest (a flash segment around its calibration segment): the ones that say their XCP paging
        paged_holders = [s for s in holders if s.segment is not None] or holders
        if len({(s.segment, s.pages) for s in paged_holders}) > 1:
            raise A2lError(
                f"CHARACTERISTIC {ch.name} lies in overlapping memory segments paged differently "
                f"({', '.join(s.name for s in paged_holders)}): which one's pages hold it?"
            )
        held[ch.name] = paged_holders[0]
    paged = {(s.segment, s.pages) for s in held.values()}
    if len(paged) > 1:
        shown = "; ".join(f"{n} in {s.name}" for n, s in held.items())
        raise A2lError(f"the characteristics lie in memory segments paged differently ({shown}): choose one segment's")
    ((number, pages),) = paged
    if number is None or pages is None:
        return {}
    out: dict[str, Any] = {"segment": number, "pages": pages >= 2}
    if pages >= 2:
        out["reference_page"] = 0
        out["working_page"] = 1
    return out


def identifier(a2l_name: str) -> str:
    """A calibration parameter name for an A2L name (``Ctrl.Gain[2]`` -> ``Ctrl_Gain_2``)."""
    name = re.sub(r"[^0-9A-Za-z_]+", "_", a2l_name).strip("_")
    if not name or name[0].isdigit():
        name = f"c_{name}"
    return name


def resolution_of(ch: A2lCharacteristic) -> float:
    """One step of the internal value in physical units (floats: the STEP_SIZE, else the FORMAT's decimals)."""
    where = EcuAddress(ch.address, ch.datatype, ch.byte_order, ch.extension, ch.conversion, ch.coeffs)
    if not where.is_float:
        return abs(where.linear[0])
    if ch.step_size is not None and math.isfinite(ch.step_size) and ch.step_size > 0:
        return ch.step_size
    decimals = ch.decimals if ch.decimals is not None else FLOAT_DEFAULT_DECIMALS
    return 10.0**-decimals


def on_ecu_grid(
    name: str, where: EcuAddress, lower: float, upper: float
) -> tuple[float, float, Callable[[float], float]]:
    """LOWER_LIMIT / UPPER_LIMIT moved inward onto the values an integer type can hold (p = factor x + offset), so
    that the agent's grid (lower + k resolution) is the ECU's; refused when they exceed the type's range (a UBYTE
    with limits 0..300 was clamped to 255 without a word). Also the function that puts a value on that grid."""
    if where.is_float:
        return lower, upper, lambda v: v
    factor, offset = where.linear
    lo_x, hi_x = sorted(((lower - offset) / factor, (upper - offset) / factor))
    x_lo, x_hi = math.ceil(lo_x - 1e-9), math.floor(hi_x + 1e-9)
    t_lo, t_hi = integer_range(where.datatype)
    # a 64-bit type's own range as limits (2**64 - 1 is the float 2**64): within the float's rounding, clamped
    x_lo = t_lo if t_lo - math.ulp(float(t_lo)) <= x_lo < t_lo else x_lo
    x_hi = t_hi if t_hi < x_hi <= t_hi + math.ulp(float(t_hi)) else x_hi
    if x_lo < t_lo or x_hi > t_hi:
        raise A2lError(
            f"CHARACTERISTIC {name}: its limits [{lower:g}, {upper:g}] need internal values {x_lo}..{x_hi}, beyond "
            f"what a {where.datatype} holds ({t_lo}..{t_hi}, i.e. [{_phys(where, t_lo):g}, {_phys(where, t_hi):g}] "
            "through its COMPU_METHOD): the A2L's limits or type are wrong"
        )
    if x_lo > x_hi:
        raise A2lError(f"CHARACTERISTIC {name}: no {where.datatype} value lies within [{lower:g}, {upper:g}]")
    a, b = sorted((_phys(where, x_lo), _phys(where, x_hi)))
    a = lower if math.isclose(a, lower, rel_tol=1e-9, abs_tol=1e-12) else a  # on the grid already: the A2L's digits
    b = upper if math.isclose(b, upper, rel_tol=1e-9, abs_tol=1e-12) else b

    def grid(v: float) -> float:
        return min(max(_phys(where, min(max(round((v - offset) / factor), x_lo), x_hi)), a), b)

    return a, b, grid


def _phys(where: EcuAddress, x: int) -> float:
    factor, offset = where.linear
    return float(factor * x + offset)


def definition_from_a2l(
    path: str | Path,
    characteristics: Sequence[str] | None = None,
    *,
    name: str | None = None,
    values: Mapping[str, float] | None = None,
    midpoint: bool = False,
    description: str = "",
    notes: list[str] | None = None,
) -> CalibrationDefinition:
    """The calibration definition of ``characteristics`` (A2L names, in index order; None = every VALUE).

    ``values`` (by A2L or parameter name) are the nominal and baseline values (read from the ECU's reference
    page, or given); ``midpoint`` fills the others with the middle of their range (a bench ECU only). Without
    either, a missing value is refused: the baseline is the calibration a car is left on.
    """
    module = read_a2l(path, list(characteristics) if characteristics else None)
    if notes is not None:
        notes.extend(module.notes)
        if not characteristics:
            notes.extend(f"left out {n}: {why}" for n, why in sorted(module.problems.items()))
    wanted = list(characteristics) if characteristics else sorted(module.characteristics)
    if not wanted:
        why = "; ".join(f"{n}: {w}" for n, w in sorted(module.problems.items())) or "it has none"
        raise A2lError(f"{path}: no characteristic bac can write ({why})")
    refused = [f"{c}: {module.problems[c]}" for c in wanted if c in module.problems]
    if refused:
        raise A2lError(f"{path}: bac cannot write " + "; ".join(refused))
    missing = [c for c in wanted if c not in module.characteristics]
    if missing:
        known = ", ".join(sorted(module.all_characteristics - set(missing))[:20])
        raise A2lError(f"{path}: no VALUE characteristic {missing} (known: {known})")
    given = dict(values or {})
    params: list[RawParameter] = []
    no_value = []
    included: list[str] = []
    for a2l_name in wanted:
        ch = module.characteristics[a2l_name]
        pname = identifier(a2l_name)
        try:
            where = EcuAddress(
                ch.address,
                ch.datatype,
                ch.byte_order,
                ch.extension,
                ch.conversion,
                ch.coeffs,
                characteristic=a2l_name if pname != a2l_name else "",
            )
        except DefinitionError as exc:
            raise A2lError(f"CHARACTERISTIC {a2l_name}: {exc}") from None
        if ch.lower >= ch.upper:
            raise A2lError(f"CHARACTERISTIC {a2l_name}: LOWER_LIMIT {ch.lower:g} >= UPPER_LIMIT {ch.upper:g}")
        try:
            lower, upper, grid = on_ecu_grid(a2l_name, where, ch.lower, ch.upper)
        except A2lError as exc:
            if characteristics:  # named: refused
                raise
            if notes is not None:  # --all: left out, and said, as the characteristics bac cannot write
                notes.append(f"left out {a2l_name}: {str(exc).removeprefix(f'CHARACTERISTIC {a2l_name}: ')}")
            continue
        v = given.get(a2l_name, given.get(pname))
        if v is None:
            if not midpoint:
                no_value.append(a2l_name)
                continue
            v = grid((lower + upper) / 2)
        elif abs(grid(float(v)) - float(v)) > 1e-9 * max(1.0, abs(float(v))):
            raise A2lError(
                f"CHARACTERISTIC {a2l_name}: the value {float(v):g} is not one the ECU can hold (the nearest is "
                f"{grid(float(v)):g}; its steps are {resolution_of(ch):g} from {lower:g})"
            )
        params.append(
            RawParameter(
                name=pname,
                index=len(params),
                lower=lower,
                upper=upper,
                nominal=float(v),
                resolution=resolution_of(ch),
                unit=ch.unit,
                description=ch.description,
                xcp=where,
            )
        )
        included.append(a2l_name)
    if no_value:
        raise A2lError(
            f"no nominal / baseline value for {no_value}: read them from the ECU's reference page (--from-ecu), "
            "give them (--set NAME=VALUE), or take the middle of each range on a bench ECU (--midpoint)"
        )
    xcp = dict(module.xcp)
    xcp.pop("baudrate", None)  # the bus's bit rate is the adapter's setting (can.bitrate)
    if not params and not no_value:
        raise A2lError(f"{path}: no characteristic bac can write (" + "; ".join(notes or []) + ")")
    xcp.update(paging_of(module.segments, [module.characteristics[c] for c in included]))
    return CalibrationDefinition(
        name=name or identifier(module.name).lower(),
        parameters=tuple(params),
        baseline={p.name: p.nominal for p in params},
        description=description or f"from {Path(path).name}, module {module.name}",
        xcp=xcp,
    )


# --- writing ------------------------------------------------------------------------------------------------
_AML = """    /begin A2ML
      struct Protocol_Layer {
        uint; uint; uint; uint; uint; uint; uint; uint;
        uchar; uint;
        enum { "BYTE_ORDER_MSB_LAST" = 0, "BYTE_ORDER_MSB_FIRST" = 1 };
        enum { "ADDRESS_GRANULARITY_BYTE" = 1, "ADDRESS_GRANULARITY_WORD" = 2, "ADDRESS_GRANULARITY_DWORD" = 4 };
        taggedstruct {
          ("OPTIONAL_CMD" enum {
            "GET_COMM_MODE_INFO" = 0xFB, "GET_SEED" = 0xF8, "UNLOCK" = 0xF7, "SHORT_UPLOAD" = 0xF4,
            "BUILD_CHECKSUM" = 0xF3, "DOWNLOAD_NEXT" = 0xEF, "SET_CAL_PAGE" = 0xEB, "GET_CAL_PAGE" = 0xEA
          })*;
          "COMMUNICATION_MODE_SUPPORTED" taggedunion {
            "BLOCK" taggedstruct { "SLAVE" ; "MASTER" struct { uchar; uchar; }; };
          };
        };
      };
      struct Page {
        uchar;
        enum { "ECU_ACCESS_NOT_ALLOWED" = 0, "ECU_ACCESS_WITHOUT_XCP_ONLY" = 1,
               "ECU_ACCESS_WITH_XCP_ONLY" = 2, "ECU_ACCESS_DONT_CARE" = 3 };
        enum { "XCP_READ_ACCESS_NOT_ALLOWED" = 0, "XCP_READ_ACCESS_WITHOUT_ECU_ONLY" = 1,
               "XCP_READ_ACCESS_WITH_ECU_ONLY" = 2, "XCP_READ_ACCESS_DONT_CARE" = 3 };
        enum { "XCP_WRITE_ACCESS_NOT_ALLOWED" = 0, "XCP_WRITE_ACCESS_WITHOUT_ECU_ONLY" = 1,
               "XCP_WRITE_ACCESS_WITH_ECU_ONLY" = 2, "XCP_WRITE_ACCESS_DONT_CARE" = 3 };
      };
      struct Segment {
        uchar; uchar; uchar; uchar; uchar;
        taggedstruct {
          block "CHECKSUM" struct { enum { "XCP_CRC_32" = 9 }; };
          (block "PAGE" struct Page)*;
        };
      };
      struct CAN_Parameters {
        uint;
        taggedstruct {
          "CAN_ID_BROADCAST" ulong;
          "CAN_ID_MASTER" ulong;
          "CAN_ID_SLAVE" ulong;
          "BAUDRATE" ulong;
          "MAX_DLC_REQUIRED";
        };
      };
      block "IF_DATA" taggedunion if_data {
        "XCP" struct {
          taggedstruct {
            block "PROTOCOL_LAYER" struct Protocol_Layer;
            block "SEGMENT" struct Segment;
            block "XCP_ON_CAN" struct CAN_Parameters;
          };
        };
      };
    /end A2ML
"""


def _num(v: float) -> str:
    return repr(float(v)) if not float(v).is_integer() else f"{float(v):.1f}"


def _format(resolution: float, lower: float, upper: float) -> str:
    decimals = max(0, -math.floor(math.log10(resolution) + 1e-9)) if resolution < 1 else 0
    width = max(len(f"{lower:.{decimals}f}"), len(f"{upper:.{decimals}f}")) + 1
    return f"%{width}.{decimals}"


def a2l_text(definition: CalibrationDefinition, module_name: str | None = None, bitrate: int = 500_000) -> str:
    """The A2L (ASAP2 1.71) of ``definition``'s parameters, which must carry XCP addresses."""
    params = [p for p in definition.parameters if p.xcp is not None]
    if len(params) != len(definition.parameters):
        raise A2lError(f"definition '{definition.name}': every parameter needs an XCP address for an A2L")
    xcp = dict(definition.xcp)
    master = int(xcp.get("can_id_master", 0x7E0))
    slave = int(xcp.get("can_id_slave", 0x7E1))
    ext = 0x8000_0000 if xcp.get("extended_id") else 0
    pages = bool(xcp.get("pages", True))
    segment = int(xcp.get("segment", 0))
    mod = module_name or definition.name.upper()
    lo = min(p.xcp.address for p in params if p.xcp is not None)
    hi = max(p.xcp.address + datatype_size(p.xcp.datatype) for p in params if p.xcp is not None)
    lines = [
        "ASAP2_VERSION 1 71",
        f'/begin PROJECT {mod}_PRJ "bac: {definition.description or definition.name}"',
        '  /begin HEADER "written by bac (bac_ecu_bridge.xcp.a2l.a2l_text)"',
        '    VERSION "1"',
        "  /end HEADER",
        f'  /begin MODULE {mod} "the calibration of {definition.name}"',
        _AML.rstrip("\n"),
        '    /begin MOD_COMMON ""',
        "      BYTE_ORDER MSB_LAST",
        "      ALIGNMENT_BYTE 1",
        "    /end MOD_COMMON",
        '    /begin MOD_PAR ""',
        f'      /begin MEMORY_SEGMENT CalData "calibration data" DATA FLASH INTERN 0x{lo:08X} 0x{hi - lo:X} '
        "-1 -1 -1 -1 -1",
        "        /begin IF_DATA XCP",
        f"          /begin SEGMENT {segment} {2 if pages else 1} 0 0 0",
        "            /begin CHECKSUM XCP_CRC_32 /end CHECKSUM",
        "            /begin PAGE 0 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE "
        + ("XCP_WRITE_ACCESS_NOT_ALLOWED" if pages else "XCP_WRITE_ACCESS_DONT_CARE")
        + " /end PAGE",
    ]
    if pages:
        lines.append(
            "            /begin PAGE 1 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE "
            "XCP_WRITE_ACCESS_DONT_CARE /end PAGE"
        )
    lines += [
        "          /end SEGMENT",
        "        /end IF_DATA",
        "      /end MEMORY_SEGMENT",
        "    /end MOD_PAR",
        "    /begin IF_DATA XCP",
        "      /begin PROTOCOL_LAYER",
        "        0x0101 25 25 25 25 25 25 25 8 8 BYTE_ORDER_MSB_LAST ADDRESS_GRANULARITY_BYTE",
        "        OPTIONAL_CMD GET_COMM_MODE_INFO OPTIONAL_CMD GET_SEED OPTIONAL_CMD UNLOCK",
        "        OPTIONAL_CMD SHORT_UPLOAD OPTIONAL_CMD BUILD_CHECKSUM OPTIONAL_CMD DOWNLOAD_NEXT",
        "        OPTIONAL_CMD SET_CAL_PAGE OPTIONAL_CMD GET_CAL_PAGE",
        "        COMMUNICATION_MODE_SUPPORTED BLOCK SLAVE MASTER 32 0",
        "      /end PROTOCOL_LAYER",
        "      /begin XCP_ON_CAN",
        "        0x0100",
        f"        CAN_ID_MASTER 0x{master | ext:X}",
        f"        CAN_ID_SLAVE 0x{slave | ext:X}",
        f"        BAUDRATE {int(bitrate)}",
        "      /end XCP_ON_CAN",
        "    /end IF_DATA",
    ]
    methods: dict[tuple[Any, ...], str] = {}
    layouts: set[str] = set()
    chars: list[str] = []
    for p in params:
        assert p.xcp is not None
        x = p.xcp
        fmt = _format(p.resolution, p.lower, p.upper)
        key = (x.conversion, x.coeffs, p.unit, fmt)
        if key not in methods:
            methods[key] = f"CM_{definition.name}_{len(methods) + 1}"
        layouts.add(x.datatype)
        desc = (p.description or p.name).replace('"', "'")
        extra = []
        if x.byte_order != "MSB_LAST":
            extra.append(f"      BYTE_ORDER {x.byte_order}")
        if x.extension:
            extra.append(f"      ECU_ADDRESS_EXTENSION {x.extension}")
        extra.append(f'      FORMAT "{fmt}"')
        chars += [
            f'    /begin CHARACTERISTIC {x.characteristic or p.name} "{desc}" VALUE 0x{x.address:08X} '
            f"RL_{x.datatype} 0 {methods[key]} {_num(p.lower)} {_num(p.upper)}",
            *extra,
            "    /end CHARACTERISTIC",
        ]
    for (conversion, coeffs, unit, fmt), cm in methods.items():
        body = ""
        if conversion == "LINEAR":
            body = f" COEFFS_LINEAR {' '.join(_num(c) for c in coeffs)}"
        elif conversion == "RAT_FUNC":
            body = f" COEFFS {' '.join(_num(c) for c in coeffs)}"
        lines.append(f'    /begin COMPU_METHOD {cm} "" {conversion} "{fmt}" "{unit}"{body} /end COMPU_METHOD')
    for dt in sorted(layouts):
        lines.append(f"    /begin RECORD_LAYOUT RL_{dt} FNC_VALUES 1 {dt} ROW_DIR DIRECT /end RECORD_LAYOUT")
    lines += chars
    lines += ["  /end MODULE", "/end PROJECT", ""]
    return "\n".join(lines)


def shipped_a2l(name: str) -> Path:
    """The A2L shipped for a definition of ``ros_ws/config/calibrations`` (it describes the simulated ECU)."""
    path = Path(str(resources.files("bac_ecu_bridge") / "a2l" / f"{name}.a2l"))
    if not path.is_file():
        raise FileNotFoundError(f"no shipped A2L for '{name}'; write one: python -m bac_ecu_bridge a2l --help")
    return path
