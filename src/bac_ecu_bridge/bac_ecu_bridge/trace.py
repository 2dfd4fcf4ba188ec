"""Reading CAN traces of the calibration protocol (candump .log, Vector .asc, .blf, .trc, .csv, ...).

:func:`decode_trace` decodes every protocol frame of a trace with the DBC
(cantools: engineering values by signal name) and checks each frame with the
protocol codec, which a DBC cannot express: the CRC-8, the length, the opcode,
the reserved bytes, the NACK reason and, given the calibration codec, the
parameter index and the raw value against the declared bounds. A frame the
bridge or the ECU would refuse is shown with the reason (``TraceRow.problem``),
never as a plain value, and the decoding goes on to the next frame.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import cantools
from cantools.database import Database

from bac_ecu_bridge.errors import FrameError
from bac_ecu_bridge.protocol import (
    FRAME_LENGTH,
    CalibrationCodec,
    CanIds,
    Nack,
    Reason,
    Staged,
    Value,
    Write,
    crc8,
    decode_request,
    decode_response,
)


@dataclass(frozen=True)
class TraceRow:
    timestamp: float
    can_id: int
    direction: str  # "request" (laptop -> ECU) or "response"
    signals: dict[str, Any]  # cantools' decoding (choices as their names)
    crc_ok: bool
    raw: bytes
    problem: str = ""  # why the bridge or the ECU would refuse the frame ("" when it is a valid frame)

    @property
    def op(self) -> str:
        return str(self.signals.get("Op", "?"))

    def text(self) -> str:
        fields = " ".join(f"{k}={_fmt(v)}" for k, v in self.signals.items() if k not in ("Crc8", "Op"))
        arrow = "->" if self.direction == "request" else "<-"
        if len(self.raw) == FRAME_LENGTH and not self.crc_ok:
            flag = "  [CRC-8 MISMATCH: garbled frame]"
        elif self.problem:
            flag = f"  [INVALID: {self.problem}]"
        else:
            flag = ""
        return f"{self.timestamp:17.6f} {self.can_id:03X} {arrow} {self.op:<9} {fields}{flag}"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, int) and v > 0xFFFF:
        return f"0x{v:08X}"
    return str(v)


def load_database(dbc: str | Path) -> Database:
    db = cantools.database.load_file(str(dbc))
    if not isinstance(db, Database):
        raise FrameError(f"{dbc}: not a CAN database")
    return db


def iter_trace(path: str | Path) -> Iterator[can.Message]:
    """The frames of a trace file, any format python-can reads (by extension)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"trace file not found: {p}")
    try:
        yield from can.LogReader(str(p))
    except (ValueError, UnicodeDecodeError, IndexError, struct.error) as exc:
        # python-can's readers raise these on a line or block they cannot parse ("could not convert string to
        # float: 'arbag'"), without the file
        raise FrameError(f"{p}: not a readable {p.suffix or 'CAN'} trace: {exc}") from None


def frame_problem(data: bytes, direction: str, codec: CalibrationCodec | None = None) -> str:
    """Why the receiving side would refuse this frame ("" for a valid one): its length, CRC-8, opcode, reserved bytes,
    a NACK's reason, and with ``codec`` a parameter index or raw value outside the definition's bounds."""
    try:
        pdu = decode_request(data) if direction == "request" else decode_response(data)
    except FrameError as exc:
        return str(exc)
    if isinstance(pdu, Nack):
        try:
            Reason(pdu.reason)
        except ValueError:
            return f"NACK with an unknown reason 0x{pdu.reason:02X}"
    if codec is not None and isinstance(pdu, Write | Staged | Value):
        p = codec.by_index.get(pdu.index)
        if p is None:
            return f"index {pdu.index} is not a parameter of '{codec.definition.name}'"
        if pdu.raw > p.max_raw:
            value = p.lower + pdu.raw * p.resolution
            return (
                f"'{p.name}' raw value {pdu.raw} outside 0..{p.max_raw}: {value:.6g} outside the declared "
                f"[{p.lower:g}, {p.upper:g}]"
            )
    return ""


def decode_trace(
    path: str | Path, db: Database, ids: CanIds | None = None, codec: CalibrationCodec | None = None
) -> list[TraceRow]:
    """Decode every protocol frame of a trace; other CAN ids are skipped.

    Every frame the protocol would refuse carries the reason (:func:`frame_problem`; with ``codec`` the definition's
    indexes and bounds are checked too); so does a valid frame the DBC cannot decode (the DBC and the protocol
    disagree: ``problem`` says so). Nothing stops the decoding; :class:`FrameError` only for an unreadable file.
    """
    ids = ids or CanIds()
    rows: list[TraceRow] = []
    for msg in iter_trace(path):
        if msg.is_error_frame or msg.is_remote_frame or bool(msg.is_extended_id) != ids.extended:
            continue
        if msg.arbitration_id == ids.request_id:
            direction = "request"
        elif msg.arbitration_id == ids.response_id:
            direction = "response"
        else:
            continue
        data = bytes(msg.data)
        ok = len(data) == FRAME_LENGTH and crc8(data[1:]) == data[0]
        problem = frame_problem(data, direction, codec)
        signals: dict[str, Any] = {}
        try:
            decoded = db.decode_message(msg.arbitration_id, data, decode_choices=True)
        except Exception as exc:  # cantools raises several types for undecodable frames
            if not problem:
                problem = f"the DBC cannot decode this valid frame ({exc}): the DBC and the protocol disagree"
        else:
            signals = {str(k): (v if isinstance(v, int | float) else str(v)) for k, v in dict(decoded).items()}
        rows.append(TraceRow(float(msg.timestamp), msg.arbitration_id, direction, signals, ok, data, problem))
    return rows
