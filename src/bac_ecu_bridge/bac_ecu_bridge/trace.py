"""Reading CAN traces of the calibration protocol (candump .log, Vector .asc, .blf, .trc, .csv, ...).

:func:`decode_trace` decodes every protocol frame of a trace with the DBC
(cantools: engineering values by signal name) and checks each frame's CRC-8
with the protocol codec, which a DBC cannot express.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import cantools
from cantools.database import Database

from bac_ecu_bridge.errors import FrameError
from bac_ecu_bridge.protocol import CanIds, crc8


@dataclass(frozen=True)
class TraceRow:
    timestamp: float
    can_id: int
    direction: str  # "request" (laptop -> ECU) or "response"
    signals: dict[str, Any]  # cantools' decoding (choices as their names)
    crc_ok: bool
    raw: bytes

    @property
    def op(self) -> str:
        return str(self.signals.get("Op", "?"))

    def text(self) -> str:
        fields = " ".join(f"{k}={_fmt(v)}" for k, v in self.signals.items() if k not in ("Crc8", "Op"))
        arrow = "->" if self.direction == "request" else "<-"
        flag = "" if self.crc_ok else "  [CRC-8 MISMATCH: garbled frame]"
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
    yield from can.LogReader(str(p))


def decode_trace(path: str | Path, db: Database, ids: CanIds | None = None) -> list[TraceRow]:
    """Decode every protocol frame of a trace; other CAN ids are skipped.

    Raises :class:`FrameError` when the DBC cannot decode a protocol frame
    whose CRC-8 is right (the DBC and the protocol disagree).
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
        ok = len(data) == 8 and crc8(data[1:]) == data[0]
        signals: dict[str, Any] = {}
        try:
            decoded = db.decode_message(msg.arbitration_id, data, decode_choices=True)
        except Exception as exc:  # cantools raises several types for undecodable frames
            if ok:
                raise FrameError(f"the DBC cannot decode a valid frame {data.hex(' ')}: {exc}") from exc
        else:
            signals = {str(k): (v if isinstance(v, int | float) else str(v)) for k, v in dict(decoded).items()}
        rows.append(TraceRow(float(msg.timestamp), msg.arbitration_id, direction, signals, ok, data))
    return rows
