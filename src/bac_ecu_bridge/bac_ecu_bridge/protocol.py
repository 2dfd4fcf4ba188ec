"""The calibration protocol on classic CAN: frame layouts, encodings, checksums.

One codec serves both ends: the bridge (:mod:`bac_ecu_bridge.client`) and the
ECU side (:mod:`bac_ecu_bridge.engine`, used by ``bac_sim.ecu``). The DBC file
(:mod:`bac_ecu_bridge.dbc`) describes exactly these layouts; docs/ecu_bridge.md
is the human-readable specification.

Every frame is 8 bytes, little-endian (Intel) fields::

    byte 0    Crc8   CRC-8/AUTOSAR over bytes 1..7 (poly 0x2F, init 0xFF, xorout 0xFF)
    byte 1    Op     opcode (requests 0x01..0x05, positive responses = request + 0x40, 0x7F = negative)
    byte 2    Seq    transaction sequence number, echoed by every response
    byte 3..7 payload, by opcode:

    request  (laptop -> ECU, REQUEST id)          response (ECU -> laptop, RESPONSE id)
    0x01 BEGIN   [3] Count                        0x41 BEGIN_OK [3] Count
    0x02 WRITE   [3] Index [4..7] Raw u32         0x42 STAGED   [3] Index [4..7] Raw u32 (what was staged)
    0x03 COMMIT  [3] Count [4..7] SetCrc32        0x43 ACK      [3] Count [4..7] SetCrc32 (over the active values)
    0x04 READ    [3] Index                        0x44 VALUE    [3] Index [4..7] Raw u32 (active value)
    0x05 STATUS  -                                0x45 STATUS_OK [3] Count [4..7] TableCrc32 (whole table)
    0x06 ABORT   -                                0x46 ABORTED  [3] Count (staged values dropped)
                                                  0x7F NACK     [3] RequestOp [4] Reason [5] Index [6..7] Detail u16

A raw value is the count of resolution steps above the parameter's lower bound:
``value = lower + raw * resolution`` (the DBC's scale and offset). The set CRC
is the CRC-32 (IEEE 802.3, as zlib) over the (index u8, raw u32 LE) pairs of a
set, in ascending index order.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import IntEnum

from crccheck.crc import Crc8Autosar

from bac_common.errors import OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition, RawParameter
from bac_ecu_bridge.errors import FrameError, InvalidRequestError, ProtocolConfigError

FRAME_LENGTH = 8
SEQ_MODULO = 256
MAX_RAW = 0xFFFF_FFFF
MAX_SET_SIZE = 255  # the Count field is one byte
DETAIL_NONE = 0xFFFF

DEFAULT_REQUEST_ID = 0x6C0
DEFAULT_RESPONSE_ID = 0x6C1
MAX_STANDARD_ID = 0x7FF
MAX_EXTENDED_ID = 0x1FFF_FFFF

RESPONSE_OFFSET = 0x40


class Op(IntEnum):
    """Opcodes (byte 1). A positive response is the request's opcode + 0x40."""

    BEGIN = 0x01
    WRITE = 0x02
    COMMIT = 0x03
    READ = 0x04
    STATUS = 0x05
    ABORT = 0x06
    BEGIN_OK = 0x41
    STAGED = 0x42
    ACK = 0x43
    VALUE = 0x44
    STATUS_OK = 0x45
    ABORTED = 0x46
    NACK = 0x7F


REQUEST_OPS = frozenset({Op.BEGIN, Op.WRITE, Op.COMMIT, Op.READ, Op.STATUS, Op.ABORT})
RESPONSE_OPS = frozenset({Op.BEGIN_OK, Op.STAGED, Op.ACK, Op.VALUE, Op.STATUS_OK, Op.ABORTED, Op.NACK})

# The ECU drops a staged set when no frame of its transaction came for this long (and on ABORT), so that a
# COMMIT arriving late (delayed in an adapter, or a retransmission) can never apply it after the bridge gave
# up on the transaction and settled the ECU's state.
STAGING_TIMEOUT_S = 1.0


class Reason(IntEnum):
    """Reason codes of a negative response (NACK byte 4)."""

    OUT_OF_RANGE = 0x01  # a value outside the ECU's range for that index
    UNKNOWN_PARAMETER = 0x02  # an index the ECU does not know
    BUSY = 0x03  # the ECU refuses to change its calibration now (vehicle moving)
    CRC_MISMATCH = 0x04  # the CRC of the COMMIT does not match the staged set
    SEQUENCE = 0x05  # a frame of a transaction the ECU is not in (stale, or never begun)
    COUNT_MISMATCH = 0x06  # the staged set does not hold the announced number of parameters
    MALFORMED = 0x07  # a request the ECU cannot parse (wrong length, reserved bytes set)


REASON_TEXT = {
    Reason.OUT_OF_RANGE: "value out of the ECU's range",
    Reason.UNKNOWN_PARAMETER: "parameter index unknown to the ECU",
    Reason.BUSY: "ECU busy (vehicle moving)",
    Reason.CRC_MISMATCH: "CRC of the staged set does not match",
    Reason.SEQUENCE: "transaction sequence error",
    Reason.COUNT_MISMATCH: "staged set incomplete or too large",
    Reason.MALFORMED: "malformed request",
}


def reason_text(reason: int) -> str:
    try:
        return REASON_TEXT[Reason(reason)]
    except ValueError:
        return f"unknown reason 0x{reason:02X}"


# --- checksums ----------------------------------------------------------------------------------
# CRC-8/AUTOSAR (poly 0x2F): on these 8-byte frames it detects every error of up to three bits; the
# CRC-8/SAE-J1850 used before (poly 0x1D) missed 198 of the 41,664 three-bit errors (test_bridge_protocol).
CRC8_NAME = "CRC-8/AUTOSAR"


def crc8(data: bytes) -> int:
    """CRC-8/AUTOSAR (poly 0x2F, init 0xFF, xorout 0xFF, not reflected); crc8(b"123456789") == 0xDF."""
    return int(Crc8Autosar.calc(data))


_PAIR = struct.Struct("<BI")


def set_crc(raw_by_index: Mapping[int, int]) -> int:
    """CRC-32 over the (index u8, raw u32 LE) pairs of a set, in ascending index order."""
    payload = b"".join(_PAIR.pack(i, raw_by_index[i]) for i in sorted(raw_by_index))
    return zlib.crc32(payload) & 0xFFFF_FFFF


def seq_next(seq: int, step: int = 1) -> int:
    return (seq + step) % SEQ_MODULO


# --- protocol data units --------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Begin:
    seq: int
    count: int
    op = Op.BEGIN


@dataclass(frozen=True, slots=True)
class Write:
    seq: int
    index: int
    raw: int
    op = Op.WRITE


@dataclass(frozen=True, slots=True)
class Commit:
    seq: int
    count: int
    crc: int
    op = Op.COMMIT


@dataclass(frozen=True, slots=True)
class Read:
    seq: int
    index: int
    op = Op.READ


@dataclass(frozen=True, slots=True)
class StatusRequest:
    seq: int
    op = Op.STATUS


@dataclass(frozen=True, slots=True)
class Abort:
    seq: int
    op = Op.ABORT


@dataclass(frozen=True, slots=True)
class BeginOk:
    seq: int
    count: int
    op = Op.BEGIN_OK


@dataclass(frozen=True, slots=True)
class Staged:
    seq: int
    index: int
    raw: int
    op = Op.STAGED


@dataclass(frozen=True, slots=True)
class Ack:
    seq: int
    count: int
    crc: int
    op = Op.ACK


@dataclass(frozen=True, slots=True)
class Value:
    seq: int
    index: int
    raw: int
    op = Op.VALUE


@dataclass(frozen=True, slots=True)
class StatusOk:
    seq: int
    count: int
    crc: int
    op = Op.STATUS_OK


@dataclass(frozen=True, slots=True)
class Aborted:
    seq: int
    count: int  # staged values dropped (0: nothing was staged)
    op = Op.ABORTED


@dataclass(frozen=True, slots=True)
class Nack:
    seq: int
    request_op: int
    reason: int
    index: int = 0
    detail: int = DETAIL_NONE
    op = Op.NACK


Request = Begin | Write | Commit | Read | StatusRequest | Abort
Response = BeginOk | Staged | Ack | Value | StatusOk | Aborted | Nack
Pdu = Request | Response

_HEAD = struct.Struct("<BB")  # op, seq (byte 0, the CRC, is computed last)
_COUNT = struct.Struct("<B4x")
_INDEX_RAW = struct.Struct("<BI")
_COUNT_CRC = struct.Struct("<BI")
_INDEX = struct.Struct("<B4x")
_EMPTY = struct.Struct("<5x")
_NACK = struct.Struct("<BBBH")


def _check_u8(name: str, v: int) -> None:
    if not 0 <= v <= 0xFF:
        raise ValueError(f"{name} {v} does not fit one byte")


def _check_u32(name: str, v: int) -> None:
    if not 0 <= v <= MAX_RAW:
        raise ValueError(f"{name} {v} does not fit 32 bits")


def encode(pdu: Pdu) -> bytes:
    """The 8 data bytes of a frame, CRC-8 included."""
    _check_u8("seq", pdu.seq)
    payload: bytes
    if isinstance(pdu, Begin | BeginOk | Aborted):
        _check_u8("count", pdu.count)
        payload = _COUNT.pack(pdu.count)
    elif isinstance(pdu, Write | Staged | Value):
        _check_u8("index", pdu.index)
        _check_u32("raw", pdu.raw)
        payload = _INDEX_RAW.pack(pdu.index, pdu.raw)
    elif isinstance(pdu, Commit | Ack | StatusOk):
        _check_u8("count", pdu.count)
        _check_u32("crc", pdu.crc)
        payload = _COUNT_CRC.pack(pdu.count, pdu.crc)
    elif isinstance(pdu, Read):
        _check_u8("index", pdu.index)
        payload = _INDEX.pack(pdu.index)
    elif isinstance(pdu, StatusRequest | Abort):
        payload = _EMPTY.pack()
    else:
        _check_u8("request_op", pdu.request_op)
        _check_u8("reason", pdu.reason)
        _check_u8("index", pdu.index)
        if not 0 <= pdu.detail <= 0xFFFF:
            raise ValueError(f"detail {pdu.detail} does not fit 16 bits")
        payload = _NACK.pack(pdu.request_op, pdu.reason, pdu.index, pdu.detail)
    body = _HEAD.pack(int(pdu.op), pdu.seq) + payload
    return bytes((crc8(body),)) + body


def with_crc(body7: bytes) -> bytes:
    """Prefix bytes 1..7 with their CRC-8 (for tools that build frames by hand)."""
    if len(body7) != FRAME_LENGTH - 1:
        raise ValueError("a frame body is 7 bytes")
    return bytes((crc8(body7),)) + bytes(body7)


def decode(data: bytes | bytearray) -> Pdu:
    """Parse 8 data bytes; raise :class:`FrameError` for anything that is not a valid frame."""
    if len(data) != FRAME_LENGTH:
        raise FrameError(f"frame has {len(data)} data bytes, the protocol uses {FRAME_LENGTH}")
    data = bytes(data)
    if crc8(data[1:]) != data[0]:
        raise FrameError(f"CRC-8 mismatch in frame {data.hex(' ')}")
    op_code, seq = data[1], data[2]
    try:
        op = Op(op_code)
    except ValueError:
        raise FrameError(f"unknown opcode 0x{op_code:02X}") from None
    body = data[3:]
    if op in (Op.BEGIN, Op.BEGIN_OK, Op.ABORTED):
        if body[1:] != b"\x00\x00\x00\x00":
            raise FrameError(f"{op.name}: reserved bytes set")
        if op is Op.ABORTED:
            return Aborted(seq, body[0])
        return Begin(seq, body[0]) if op is Op.BEGIN else BeginOk(seq, body[0])
    if op in (Op.WRITE, Op.STAGED, Op.VALUE):
        index, raw = _INDEX_RAW.unpack(body)
        if op is Op.WRITE:
            return Write(seq, index, raw)
        return Staged(seq, index, raw) if op is Op.STAGED else Value(seq, index, raw)
    if op in (Op.COMMIT, Op.ACK, Op.STATUS_OK):
        count, crc = _COUNT_CRC.unpack(body)
        if op is Op.COMMIT:
            return Commit(seq, count, crc)
        return Ack(seq, count, crc) if op is Op.ACK else StatusOk(seq, count, crc)
    if op is Op.READ:
        if body[1:] != b"\x00\x00\x00\x00":
            raise FrameError("READ: reserved bytes set")
        return Read(seq, body[0])
    if op in (Op.STATUS, Op.ABORT):
        if body != b"\x00" * 5:
            raise FrameError(f"{op.name}: reserved bytes set")
        return StatusRequest(seq) if op is Op.STATUS else Abort(seq)
    request_op, reason, index, detail = _NACK.unpack(body)
    return Nack(seq, request_op, reason, index, detail)


def decode_request(data: bytes | bytearray) -> Request:
    pdu = decode(data)
    if pdu.op not in REQUEST_OPS:
        raise FrameError(f"{pdu.op.name} is a response, not a request")
    return pdu  # type: ignore[return-value]


def decode_response(data: bytes | bytearray) -> Response:
    pdu = decode(data)
    if pdu.op not in RESPONSE_OPS:
        raise FrameError(f"{pdu.op.name} is a request, not a response")
    return pdu  # type: ignore[return-value]


# --- CAN identifiers --------------------------------------------------------------------------------
@dataclass(frozen=True)
class CanIds:
    """The two CAN identifiers of the protocol."""

    request_id: int = DEFAULT_REQUEST_ID  # laptop -> ECU
    response_id: int = DEFAULT_RESPONSE_ID  # ECU -> laptop
    extended: bool = False  # 29-bit identifiers

    def __post_init__(self) -> None:
        limit = MAX_EXTENDED_ID if self.extended else MAX_STANDARD_ID
        kind = "29-bit" if self.extended else "11-bit"
        for name, v in (("request_id", self.request_id), ("response_id", self.response_id)):
            if not 0 <= v <= limit:
                raise ProtocolConfigError(f"CAN {name} 0x{v:X} is not a valid {kind} identifier (0..0x{limit:X})")
        if self.request_id == self.response_id:
            raise ProtocolConfigError("the request and response CAN ids must differ")


# --- parameter encodings ------------------------------------------------------------------------------
@dataclass(frozen=True)
class ParamCodec:
    """How one raw parameter travels on CAN: ``value = lower + raw * resolution``."""

    name: str
    index: int
    lower: float
    upper: float
    resolution: float
    max_raw: int
    unit: str = ""
    description: str = ""

    @classmethod
    def of(cls, p: RawParameter) -> ParamCodec:
        steps = (p.upper - p.lower) / p.resolution
        max_raw = math.floor(steps + 1e-9)
        if max_raw > MAX_RAW:
            raise ProtocolConfigError(
                f"parameter '{p.name}': [{p.lower:g}, {p.upper:g}] at resolution {p.resolution:g} needs "
                f"{max_raw + 1} steps, more than a 32-bit raw value holds; use a coarser resolution"
            )
        return cls(p.name, p.index, p.lower, p.upper, p.resolution, max_raw, p.unit, p.description)

    def encode(self, value: float) -> int:
        """The raw value of ``value``; raises :class:`OutOfBoundsError` outside [lower, upper] or NaN."""
        v = float(value)
        if not (math.isfinite(v) and self.lower <= v <= self.upper):
            raise OutOfBoundsError(self.name, v, self.lower, self.upper)
        return min(max(round((v - self.lower) / self.resolution), 0), self.max_raw)

    def decode(self, raw: int) -> float:
        if not 0 <= raw <= self.max_raw:
            raise FrameError(f"parameter '{self.name}': raw value {raw} outside 0..{self.max_raw}")
        return min(self.lower + raw * self.resolution, self.upper)

    def quantize(self, value: float) -> float:
        return self.decode(self.encode(value))


class CalibrationCodec:
    """The CAN encoding of a calibration definition's raw parameters."""

    def __init__(self, definition: CalibrationDefinition) -> None:
        params = sorted(definition.parameters, key=lambda p: p.index)
        if len(params) > MAX_SET_SIZE:
            raise ProtocolConfigError(
                f"definition '{definition.name}' has {len(params)} parameters; one transaction carries at most "
                f"{MAX_SET_SIZE}"
            )
        self.definition = definition
        self.params: tuple[ParamCodec, ...] = tuple(ParamCodec.of(p) for p in params)
        self.by_name: dict[str, ParamCodec] = {p.name: p for p in self.params}
        self.by_index: dict[int, ParamCodec] = {p.index: p for p in self.params}

    @property
    def names(self) -> tuple[str, ...]:
        """Raw parameter names in index order."""
        return tuple(p.name for p in self.params)

    def param(self, name: str) -> ParamCodec:
        try:
            return self.by_name[name]
        except KeyError:
            raise UnknownParameterError(name, self.names) from None

    def name_of(self, index: int) -> str:
        p = self.by_index.get(index)
        return p.name if p is not None else f"index {index}"

    def encode_set(self, values: Mapping[str, float]) -> dict[int, int]:
        """Raw values by index; refuses unknown names and anything outside the declared bounds."""
        out: dict[int, int] = {}
        for name, v in values.items():
            p = self.param(name)
            out[p.index] = p.encode(v)
        return out

    def decode_set(self, raw_by_index: Mapping[int, int]) -> dict[str, float]:
        """Values by name, in index order."""
        out: dict[str, float] = {}
        for i in sorted(raw_by_index):
            p = self.by_index.get(i)
            if p is None:
                raise FrameError(f"index {i} is not a parameter of '{self.definition.name}'")
            out[p.name] = p.decode(raw_by_index[i])
        return out

    def quantize(self, values: Mapping[str, float]) -> dict[str, float]:
        return self.decode_set(self.encode_set(values))

    def crc(self, values: Mapping[str, float]) -> int:
        """The set CRC of a calibration given by name (after quantization)."""
        return set_crc(self.encode_set(values))


def resolve_request(
    definition: CalibrationDefinition, names: Iterable[str], values: Iterable[float]
) -> dict[str, float]:
    """The full raw calibration a request asks for.

    ``names`` are the definition's tuned dimensions (raw or meta-parameters; the
    fixed parameters take their values) or, alternatively, every raw parameter.
    Raises :class:`InvalidRequestError` for a malformed request (lengths differ,
    duplicates, NaN/inf, a missing dimension), :class:`UnknownParameterError` for
    a name the definition does not know and :class:`OutOfBoundsError` for a value
    outside its declared bounds; nothing is sent in any of these cases.
    """
    names = [str(n) for n in names]
    vals = [float(v) for v in values]
    if len(names) != len(vals):
        raise InvalidRequestError(f"the request has {len(names)} names but {len(vals)} values")
    if not names:
        raise InvalidRequestError("the request names no parameter")
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise InvalidRequestError(f"parameter '{n}' is given twice")
        seen.add(n)
    for n, v in zip(names, vals, strict=True):
        if not math.isfinite(v):
            raise InvalidRequestError(f"parameter '{n}' = {v}: not a finite number")
    mapping = dict(zip(names, vals, strict=True))
    tuned = set(definition.tuned)
    raw_names = set(definition.parameter_names)
    if seen == raw_names and seen != tuned:
        definition.check_raw(mapping)
        return {n: mapping[n] for n in definition.parameter_names}
    known = tuned | raw_names | {m.name for m in definition.meta}
    for n in names:
        if n not in known:
            raise UnknownParameterError(n, tuple(definition.tuned))
    not_tuned = [n for n in names if n not in tuned]
    if not_tuned:
        raise InvalidRequestError(
            f"{not_tuned} are not tuned dimensions of '{definition.name}' (tuned: {list(definition.tuned)}); "
            "send the tuned dimensions, or every raw parameter"
        )
    missing = [n for n in definition.tuned if n not in seen]
    if missing:
        raise InvalidRequestError(f"the request lacks tuned dimensions {missing} of '{definition.name}'")
    return definition.expand(mapping)
