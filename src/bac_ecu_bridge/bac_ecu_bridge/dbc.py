"""The DBC description of the calibration protocol, generated from a calibration definition.

Two messages: ``BAC_CalRequest`` (laptop -> ECU) and ``BAC_CalResponse``
(ECU -> laptop). ``Op`` multiplexes each frame; in WRITE / STAGED / VALUE frames
``Index`` (itself multiplexed by ``Op``, DBC extended multiplexing,
``SG_MUL_VAL_``) selects the parameter signal ``P_<name>`` whose scale
(= resolution), offset (= lower bound), range and unit are the definition's, so
CANape, SavvyCAN, cantools (``candump can0 | python -m cantools decode x.dbc``)
show engineering values.

The DBC files of the shipped definitions live in ``bac_ecu_bridge/dbc/``
(:func:`shipped_dbc`); regenerate them with ``python -m bac_ecu_bridge dbc``.
"""

from __future__ import annotations

from collections import OrderedDict
from importlib import resources
from pathlib import Path
from typing import Any

from cantools.database import Database
from cantools.database.can import Message, Node, Signal
from cantools.database.conversion import BaseConversion
from cantools.database.namedsignalvalue import NamedSignalValue

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.protocol import CalibrationCodec, CanIds, Op, Reason

REQUEST_MESSAGE = "BAC_CalRequest"
RESPONSE_MESSAGE = "BAC_CalResponse"
BRIDGE_NODE = "BAC_Bridge"
ECU_NODE = "ECU"
PARAM_PREFIX = "P_"

_REQUEST_OP_NAMES = {op: op.name for op in (Op.BEGIN, Op.WRITE, Op.COMMIT, Op.READ, Op.STATUS)}
_RESPONSE_OP_NAMES = {op: op.name for op in (Op.BEGIN_OK, Op.STAGED, Op.ACK, Op.VALUE, Op.STATUS_OK, Op.NACK)}


def _choices(table: dict[Any, str]) -> OrderedDict[int, str | NamedSignalValue]:
    return OrderedDict((int(k), v) for k, v in sorted(table.items(), key=lambda kv: int(kv[0])))


def _sig(
    name: str,
    start: int,
    length: int,
    comment: str,
    *,
    mux: list[int] | None = None,
    mux_signal: str | None = None,
    multiplexer: bool = False,
    choices: dict[Any, str] | None = None,
    scale: float = 1.0,
    offset: float = 0.0,
    minimum: float | None = None,
    maximum: float | None = None,
    unit: str | None = None,
    receiver: str = ECU_NODE,
) -> Signal:
    return Signal(
        name,
        start,
        length,
        byte_order="little_endian",
        is_signed=False,
        conversion=BaseConversion.factory(
            scale=scale, offset=offset, choices=_choices(choices) if choices else None, is_float=False
        ),
        minimum=minimum,
        maximum=maximum,
        unit=unit,
        comment=comment,
        receivers=[receiver],
        is_multiplexer=multiplexer,
        multiplexer_ids=mux,
        multiplexer_signal=mux_signal,
    )


def _param_signals(codec: CalibrationCodec, receiver: str) -> list[Signal]:
    out = []
    for p in codec.params:
        desc = f"{p.description}. " if p.description else ""
        out.append(
            _sig(
                f"{PARAM_PREFIX}{p.name}",
                32,
                32,
                f"{desc}Parameter '{p.name}' (CAN index {p.index}): value = {p.lower:g} + raw * {p.resolution:g}, "
                f"declared bounds [{p.lower:g}, {p.upper:g}]",
                mux=[p.index],
                mux_signal="Index",
                scale=p.resolution,
                offset=p.lower,
                minimum=p.lower,
                maximum=p.upper,
                unit=p.unit or None,
                receiver=receiver,
            )
        )
    return out


def _common(receiver: str, ops: dict[Op, str]) -> list[Signal]:
    return [
        _sig(
            "Crc8",
            0,
            8,
            "CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF) over data bytes 1..7",
            receiver=receiver,
        ),
        _sig("Op", 8, 8, "Opcode: multiplexes the frame", multiplexer=True, choices=ops, receiver=receiver),
        _sig(
            "Seq",
            16,
            8,
            "Transaction sequence number; every response echoes the request's",
            receiver=receiver,
        ),
    ]


def build_database(definition: CalibrationDefinition, ids: CanIds | None = None) -> Database:
    """The cantools database of the protocol for ``definition``."""
    codec = CalibrationCodec(definition)
    ids = ids or CanIds()
    req_signals = [
        *_common(ECU_NODE, _REQUEST_OP_NAMES),
        _sig("BeginCount", 24, 8, "Number of parameters the transaction will write", mux=[Op.BEGIN], mux_signal="Op"),
        _sig(
            "Index",
            24,
            8,
            "CAN index of the parameter written; multiplexes the P_ signals",
            mux=[Op.WRITE],
            mux_signal="Op",
            multiplexer=True,
        ),
        *_param_signals(codec, ECU_NODE),
        _sig("CommitCount", 24, 8, "Number of parameters staged", mux=[Op.COMMIT], mux_signal="Op"),
        _sig(
            "CommitCrc32",
            32,
            32,
            "CRC-32 over the (index u8, raw u32 LE) pairs of the staged set, ascending index",
            mux=[Op.COMMIT],
            mux_signal="Op",
        ),
        _sig("ReadIndex", 24, 8, "CAN index of the parameter to read back", mux=[Op.READ], mux_signal="Op"),
    ]
    rsp_signals = [
        *_common(BRIDGE_NODE, _RESPONSE_OP_NAMES),
        _sig(
            "BeginCount",
            24,
            8,
            "Number of parameters the transaction will write",
            mux=[Op.BEGIN_OK],
            mux_signal="Op",
            receiver=BRIDGE_NODE,
        ),
        _sig(
            "Index",
            24,
            8,
            "CAN index of the parameter staged (STAGED) or active (VALUE); multiplexes the P_ signals",
            mux=[Op.STAGED, Op.VALUE],
            mux_signal="Op",
            multiplexer=True,
            receiver=BRIDGE_NODE,
        ),
        *_param_signals(codec, BRIDGE_NODE),
        _sig("AckCount", 24, 8, "Number of parameters committed", mux=[Op.ACK], mux_signal="Op", receiver=BRIDGE_NODE),
        _sig(
            "AckCrc32",
            32,
            32,
            "CRC-32 over the committed indices' active values (equals CommitCrc32 when applied as written)",
            mux=[Op.ACK],
            mux_signal="Op",
            receiver=BRIDGE_NODE,
        ),
        _sig(
            "TableCount",
            24,
            8,
            "Number of parameters in the ECU's table",
            mux=[Op.STATUS_OK],
            mux_signal="Op",
            receiver=BRIDGE_NODE,
        ),
        _sig(
            "TableCrc32",
            32,
            32,
            "CRC-32 over the ECU's whole active table",
            mux=[Op.STATUS_OK],
            mux_signal="Op",
            receiver=BRIDGE_NODE,
        ),
        _sig(
            "NackRequestOp",
            24,
            8,
            "Opcode of the refused request",
            mux=[Op.NACK],
            mux_signal="Op",
            choices=_REQUEST_OP_NAMES,
            receiver=BRIDGE_NODE,
        ),
        _sig(
            "NackReason",
            32,
            8,
            "Why the ECU refused",
            mux=[Op.NACK],
            mux_signal="Op",
            choices={r: r.name for r in Reason},
            receiver=BRIDGE_NODE,
        ),
        _sig(
            "NackIndex",
            40,
            8,
            "CAN index of the refused parameter (WRITE / READ)",
            mux=[Op.NACK],
            mux_signal="Op",
            receiver=BRIDGE_NODE,
        ),
        _sig(
            "NackDetail",
            48,
            16,
            "OUT_OF_RANGE: low 16 bits of the refused raw value; SEQUENCE: to a BEGIN, a sequence number "
            "the ECU accepts, else its open transaction's; COUNT_MISMATCH: parameters staged or held; "
            "0xFFFF: none",
            mux=[Op.NACK],
            mux_signal="Op",
            receiver=BRIDGE_NODE,
        ),
    ]
    req = Message(
        ids.request_id,
        REQUEST_MESSAGE,
        8,
        req_signals,
        senders=[BRIDGE_NODE],
        is_extended_frame=ids.extended,
        comment=f"bac calibration protocol, laptop -> ECU, definition '{definition.name}' "
        f"({len(codec.params)} parameters). See docs/ecu_bridge.md",
        strict=True,
    )
    rsp = Message(
        ids.response_id,
        RESPONSE_MESSAGE,
        8,
        rsp_signals,
        senders=[ECU_NODE],
        is_extended_frame=ids.extended,
        comment=f"bac calibration protocol, ECU -> laptop, definition '{definition.name}'. See docs/ecu_bridge.md",
        strict=True,
    )
    return Database(
        messages=[req, rsp],
        nodes=[Node(BRIDGE_NODE, "the bac ECU bridge (laptop)"), Node(ECU_NODE, "the controller's ECU")],
        version=f"bac {definition.name}",
    )


def dbc_text(definition: CalibrationDefinition, ids: CanIds | None = None) -> str:
    """The DBC file text; ``Index`` is written as Vector's ``m<op>M`` (multiplexed multiplexer)."""
    db = build_database(definition, ids)
    text = str(db.as_dbc_string()).replace("\r\n", "\n")
    for name, op in ((REQUEST_MESSAGE, Op.WRITE), (RESPONSE_MESSAGE, Op.STAGED)):
        frame_id = db.get_message_by_name(name).frame_id | (0x8000_0000 if ids is not None and ids.extended else 0)
        start = text.index(f"BO_ {frame_id} {name}:")
        blank = text.find("\n\n", start)  # the message block ends at a blank line
        end = len(text) if blank < 0 else blank
        block = text[start:end].replace(" SG_ Index M :", f" SG_ Index m{int(op)}M :")
        text = text[:start] + block + text[end:]
    return text


def write_dbc(definition: CalibrationDefinition, path: str | Path, ids: CanIds | None = None) -> Path:
    p = Path(path)
    p.write_text(dbc_text(definition, ids))
    return p


def shipped_dbc(name: str) -> Path:
    """The DBC file shipped for a definition of ``ros_ws/config/calibrations`` (e.g. ``controller_ii``):
    ``share/bac_ecu_bridge/dbc/`` of the install space (ament index), else the package's own copy."""
    from bac_common.paths import package_share

    share = package_share("bac_ecu_bridge")
    path = share / "dbc" / f"{name}.dbc" if share is not None else Path()
    if share is None or not path.is_file():
        path = Path(str(resources.files("bac_ecu_bridge") / "dbc" / f"{name}.dbc"))
    if not path.is_file():
        raise FileNotFoundError(f"no shipped DBC for '{name}'; generate one: python -m bac_ecu_bridge dbc --help")
    return path
