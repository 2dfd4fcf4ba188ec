"""The bridge's XCP-on-CAN backend: pyxcp as the master, every apply verified end to end and bounded.

:class:`XcpCalibrationClient` gives the guarantees of the bac protocol's client
(:mod:`bac_ecu_bridge.client`) over ASAM MCD-1 XCP, with pyxcp's ``Master`` on
the caller's python-can bus (any bus: a real adapter, ``virtual``,
``udp_multicast``, the fault-injecting :class:`~bac_ecu_bridge.faults.FaultyBus`).
One apply, on an ECU with a reference and a working page (the A2L's two pages of
the calibration segment; ``xcp`` settings of the definition)::

    CONNECT, GET_COMM_MODE_INFO, GET_STATUS   once per session; GET_SEED/UNLOCK when CAL/PAG is protected;
                                              the reference page read once (read-only: answered from it after)
    SET_CAL_PAGE(ECU, reference)              the controller runs on the safe data set while the writes go on
                                              (only when GET_CAL_PAGE(ECU) says it is elsewhere)
    SET_CAL_PAGE(XCP, working)                only when XCP's access is elsewhere, confirmed by GET_CAL_PAGE(XCP);
                                              GET_CAL_PAGE(ECU) must show the reference page before a byte is written
    SET_MTA + DOWNLOAD [+ DOWNLOAD_NEXT...]   each run of contiguous parameters (master block mode if offered)
    SET_MTA + BUILD_CHECKSUM  vs the host's CRC-32 of the written bytes
    SET_MTA + UPLOAD (slave block mode, else UPLOADs of 7 bytes, never SHORT_UPLOAD): only where the ECU builds
                                              no CRC-32, where its CRC-32 differs (the pieces written again), or
                                              with ``verify_readback``; after an anomaly the CRC-32s asked again
    SET_CAL_PAGE(XCP, reference)              the park: XCP's access on the write-protected page, confirmed
    SET_CAL_PAGE(ECU, working)                the commit: one page switch, never a half-written set in use
    GET_CAL_PAGE(ECU) and (XCP)               the final word: the controller uses the checked page, XCP is parked;
                                              after an anomaly at or after the last check of the contents, XCP's
                                              access goes to the page in use, its CRC-32s are asked again, parked

Every SET_CAL_PAGE(XCP) is confirmed by GET_CAL_PAGE(XCP) (a garbled page byte is answered positively) before
that page is named or read, and goes only towards a page the bridge has checked or the application uses already.
Without pages the runs are written to the one page and verified the same way.
The result's values are what the ECU holds: confirmed by its CRC-32 of the written bytes, or read back.

**Errors and retries.** Every command follows XCP's error matrix (pyxcp's
``ERROR_MATRIX``): a timeout is answered with SYNCH and the command repeated
(SYNCH, SET_MTA and repeat for memory transfers), ERR_CMD_BUSY waits t7 and
repeats, ERR_CMD_SYNCH is skipped, ERR_ACCESS_LOCKED unlocks and repeats; an
answer of the wrong length counts as no answer. Repeats the matrix calls
"infinite" are bounded by ``step_retries``. A SYNCH that gets no answer means the
session is gone (a reset, a DISCONNECT): the session is connected again and the
attempt starts over. A failed attempt (a negative response, a checksum or
read-back mismatch) is retried up to ``max_attempts`` times, the whole apply
within its ``timeout_s``; a refusal as busy (the vehicle moves:
ERR_CMD_BUSY / ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE after the matrix's repeats)
ends it at once.

**Stale answers are fenced off.** XCP responses carry no sequence number: any
response still queued when a command is sent is dropped, an answer of the
wrong length is refused, and every write is judged by the ECU's CRC-32 of what
it holds (or the bytes read back), never by the positive responses alone. A
frame still on its way (held in an adapter, duplicated) could land after the
checks: after any anomaly of an apply (a timeout, a repeat, a stale or wrong
answer) the final checks wait until ``settle_s`` has passed since the last one,
and every call (apply, read, status, restore) starts only once ``settle_s`` has
passed since the last anomaly of the calls before it (a late CRC-32 of a status
poll must not confirm the next apply of the same set).

An ECU whose BUILD_CHECKSUM is not XCP_CRC_32 (e.g. XCP_ADD_44), or that has
none, is verified by read-back (asked again in each session). One whose CRC-32
disagrees, round after round, with the bytes UPLOAD reads is refused as
non-conforming (:class:`ProtocolConfigError`).

**Uncertain outcomes are settled.** When the commit (or the switch to the
reference page) went unanswered, the ECU is read back (which page the
controller uses, what that page holds) before the error is raised; the error's
``ecu_state`` says what the ECU holds.
"""

from __future__ import annotations

import logging
import math
import time
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar

import can

from bac_common.errors import BacError, OutOfBoundsError
from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.backend import ApplyResult, EcuState, EcuStatus, Holds, ReadResult, classify
from bac_ecu_bridge.errors import (
    AcknowledgeMismatchError,
    BridgeError,
    BusError,
    EcuRejectedError,
    EcuTimeoutError,
    ErrorCode,
    InvalidRequestError,
    ProtocolConfigError,
)
from bac_ecu_bridge.protocol import CalibrationCodec, set_crc
from bac_ecu_bridge.xcp import _pyxcp
from bac_ecu_bridge.xcp.layout import Run, XcpLayout
from bac_ecu_bridge.xcp.seedkey import RESOURCE_CAL_PAG, KeyAlgorithm, load_key_algorithm

T = TypeVar("T")

DEFAULT_CAN_ID_MASTER = 0x7E0
DEFAULT_CAN_ID_SLAVE = 0x7E1
MODE_ECU = 0x01
MODE_XCP = 0x02
MAX_UPLOAD = 255  # UPLOAD's length field is one byte
REPAIR_ROUNDS = 4  # checks of a written run, each followed by writing again what differs
CONFIRMATIONS = 2  # a final negative response counts once it came this many more times in a row
CHECKSUM_CRC_32 = "XCP_CRC_32"

# XCP negative responses -> the ApplyCalibration error code they surface as, and what to tell the user
_BUSY = {0x10, 0x11, 0x12, 0x33}  # ERR_CMD_BUSY, ERR_DAQ_ACTIVE, ERR_PGM_ACTIVE, ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE
_CODE_OF_ERROR: dict[int, ErrorCode] = {
    0x10: ErrorCode.ECU_BUSY,
    0x11: ErrorCode.ECU_BUSY,
    0x12: ErrorCode.ECU_BUSY,
    0x33: ErrorCode.ECU_BUSY,
    0x20: ErrorCode.INVALID_REQUEST,  # ERR_CMD_UNKNOWN: the ECU lacks a command the bridge needs
    0x21: ErrorCode.INVALID_REQUEST,  # ERR_CMD_SYNTAX
    0x22: ErrorCode.ECU_OUT_OF_RANGE,  # ERR_OUT_OF_RANGE
    0x23: ErrorCode.ECU_OUT_OF_RANGE,  # ERR_WRITE_PROTECTED
    0x24: ErrorCode.UNKNOWN_PARAMETER,  # ERR_ACCESS_DENIED: no such memory: the definition does not match the ECU
    0x25: ErrorCode.INVALID_REQUEST,  # ERR_ACCESS_LOCKED: seed & key
    0x26: ErrorCode.UNKNOWN_PARAMETER,  # ERR_PAGE_NOT_VALID
    0x27: ErrorCode.UNKNOWN_PARAMETER,  # ERR_MODE_NOT_VALID
    0x28: ErrorCode.UNKNOWN_PARAMETER,  # ERR_SEGMENT_NOT_VALID
    0x29: ErrorCode.SEQUENCE,  # ERR_SEQUENCE
    0x30: ErrorCode.ECU_OUT_OF_RANGE,  # ERR_MEMORY_OVERFLOW
    0x31: ErrorCode.SEQUENCE,  # ERR_GENERIC
    0x32: ErrorCode.CRC_MISMATCH,  # ERR_VERIFY
}
_HINTS: dict[int, str] = {
    0x10: "the ECU stays busy: stop the vehicle and apply again",
    0x33: "the ECU refuses to change its calibration now (vehicle moving?): stop the vehicle and apply again",
    0x20: "the ECU does not implement a command the bridge needs: check the A2L's OPTIONAL_CMD list",
    0x22: "a length, address or value the ECU does not accept: check the definition's addresses and data types",
    0x23: "the ECU refuses writes there: check the page settings (xcp.working_page) and the A2L's MEMORY_SEGMENT",
    0x24: "no such memory in the ECU: the definition's addresses do not match this ECU's software (A2L version?)",
    0x25: "the calibration is locked: set the seed & key algorithm (xcp.key_algorithm) the ECU's supplier gives",
    0x26: "no such page: check xcp.reference_page / xcp.working_page against the A2L's MEMORY_SEGMENT",
    0x27: "the ECU does not support this page mode: set xcp.pages to false if it has one page only",
    0x28: "no such segment: check xcp.segment against the A2L's MEMORY_SEGMENT",
}


@dataclass(frozen=True)
class XcpSettings:
    """How to reach the calibration of an XCP ECU (the definition's ``xcp`` mapping, node parameters win)."""

    can_id_master: int = DEFAULT_CAN_ID_MASTER  # commands, bridge -> ECU (the A2L's CAN_ID_MASTER)
    can_id_slave: int = DEFAULT_CAN_ID_SLAVE  # responses, ECU -> bridge (CAN_ID_SLAVE)
    extended_id: bool = False
    pages: bool = True  # the segment has a reference and a working page
    segment: int = 0
    reference_page: int = 0
    working_page: int = 1
    key_algorithm: str = ""  # seed & key (bac_ecu_bridge.xcp.seedkey), "" = none
    max_dlc_required: bool = False  # pad every command to 8 bytes (the A2L's MAX_DLC_REQUIRED)

    @classmethod
    def of(cls, definition: CalibrationDefinition, **overrides: Any) -> XcpSettings:
        known = {f for f in cls.__dataclass_fields__}
        data = {k: v for k, v in dict(definition.xcp).items() if k in known}
        unknown = set(definition.xcp) - known
        if unknown:
            raise ProtocolConfigError(f"definition '{definition.name}': unknown xcp settings {sorted(unknown)}")
        data.update({k: v for k, v in overrides.items() if v is not None})
        s = cls(**data)
        limit = 0x1FFF_FFFF if s.extended_id else 0x7FF
        for name in ("can_id_master", "can_id_slave"):
            v = int(getattr(s, name))
            if not 0 <= v <= limit:
                raise ProtocolConfigError(f"XCP {name} 0x{v:X} is not a valid {'29' if s.extended_id else '11'}-bit id")
        if s.can_id_master == s.can_id_slave:
            raise ProtocolConfigError("XCP CAN_ID_MASTER and CAN_ID_SLAVE must differ")
        if s.pages and s.reference_page == s.working_page:
            raise ProtocolConfigError("the reference and the working page must differ")
        return s


@dataclass(frozen=True)
class XcpConfig:
    # XCP's T1, the wait for one response: a CAN round trip of two frames takes well under 1 ms at 500 kbit/s and
    # an XCP driver answers within its task cycle; every lost frame costs one T1 (then SYNCH and the repeat), so
    # T1 is what a lossy bus's apply time is made of (at 10 % lost frames 25 ms gave a p99 of 827 ms, 10 ms 0.4 s)
    step_timeout_s: float = 0.01
    step_retries: int = 5  # bound of the error matrix's "repeat infinite times", and of a command's repeats
    max_attempts: int = 3  # attempts per apply (the runs written and checked again)
    timeout_s: float = 3.0  # default overall time limit of an apply / read
    # UPLOAD every written byte back besides BUILD_CHECKSUM. Off by default: the ECU's CRC-32 of each written run
    # equal to the host's is the confirmation (as INCA's and CANape's download verification); the bytes are read
    # back anyway where the ECU builds no CRC-32 and where its CRC-32 differs (to find the pieces to write again).
    # A full read-back is some 14 more answered commands per 80 bytes: at 10 % lost frames the p99 of an apply
    # went from 527 to 400 ms without it (bench/can_apply.py, 2026-11-24)
    verify_readback: bool = False
    t7_s: float = 0.02  # XCP's t7: wait before repeating a command the ECU found busy
    # the bus's worst frame delay: after an anomaly (a timeout, a late or duplicated answer) the final checks wait
    # this long for frames still on the way (a write landing after its check); raise it behind gateways
    settle_s: float = 0.02
    settle_timeout_s: float = 3.0  # reading the ECU back after an uncertain outcome
    block_mode: bool = True  # master block mode (DOWNLOAD_NEXT) when the ECU offers it

    def __post_init__(self) -> None:
        if not self.step_timeout_s > 0 or not self.timeout_s > 0:
            raise ValueError("step_timeout_s and timeout_s must be > 0")
        if self.step_retries < 0 or self.max_attempts < 1:
            raise ValueError("step_retries >= 0 and max_attempts >= 1 are required")


@dataclass
class XcpStats:
    commands: int = 0
    frames_sent: int = 0
    frames_received: int = 0
    stale_frames: int = 0  # responses still queued when a command was sent (dropped)
    unexpected_frames: int = 0  # answers of the wrong length or content
    step_timeouts: int = 0
    retransmissions: int = 0  # commands repeated (the error matrix)
    synchs: int = 0
    connects: int = 0
    unlocks: int = 0
    negative: int = 0  # negative responses
    attempts: int = 0
    applies_ok: int = 0
    applies_failed: int = 0
    reads_ok: int = 0
    reads_failed: int = 0
    settled: int = 0
    restored_in_settle: int = 0  # settlements that found a page they could not name in use and switched it back
    repairs: int = 0  # 6-byte pieces written again after a read-back found them wrong
    errors: dict[str, int] = field(default_factory=dict)


class XcpCommandError(BridgeError):
    """The ECU answered an XCP command with a negative response (after the error matrix's repeats)."""

    def __init__(self, command: str, error: int, error_name: str, text: str, code: ErrorCode) -> None:
        hint = _HINTS.get(error, "")
        super().__init__(
            f"XCP {command}: the ECU answered {error_name} (0x{error:02X}: {text})" + (f"; {hint}" if hint else "")
        )
        self.command = command
        self.error = error
        self.error_name = error_name
        self.code = code


class _RestartError(Exception):
    """The session was lost (a SYNCH unanswered): connect again and start the attempt over."""


class _MismatchError(BridgeError):
    code = ErrorCode.CRC_MISMATCH


class _OtherChecksumError(Exception):
    """The ECU answers BUILD_CHECKSUM, again and again, with another checksum type than XCP_CRC_32."""


class XcpCalibrationClient:
    """Apply, read and restore calibrations of an XCP ECU over one CAN bus. Not thread-safe: serialize the calls."""

    protocol = "xcp"

    def __init__(
        self,
        bus: can.BusABC,
        definition: CalibrationDefinition,
        settings: XcpSettings | None = None,
        config: XcpConfig | None = None,
        *,
        key_algorithm: KeyAlgorithm | None = None,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ) -> None:
        self.definition = definition
        self.layout = XcpLayout(definition)
        self.codec = CalibrationCodec(definition)
        self.settings = settings or XcpSettings.of(definition)
        self.config = config or XcpConfig()
        self.key_algorithm = key_algorithm or load_key_algorithm(self.settings.key_algorithm)
        self.stats = XcpStats()
        self.bus = bus
        self._clock = clock
        self._log = logger or logging.getLogger("bac_ecu_bridge.xcp")
        self._x = _pyxcp.load()
        self._types = self._x["types"]
        self._master: Any = None
        self._connected = False
        self._anomaly_at = -math.inf
        self._dirty = False
        self._degraded = False  # block transfers failed in this apply: one answered command per frame
        self._talked = False
        self._byte_order: str | None = None  # as the ECU announced it in the first session
        self._checksum_ok: bool | None = None  # the ECU implements BUILD_CHECKSUM (None: not asked yet)
        self._baseline = self.layout.quantize(definition.baseline_values())
        self.last_confirmed: dict[str, float] | None = None
        self._ecu_page: int | None = None  # what the bridge knows of the page the ECU application uses
        self._page_bytes: dict[int, dict[Run, bytes]] = {}  # what the bridge knows each page holds
        self._reference: dict[Run, bytes] | None = None  # the reference page (read-only: the flashed data set)

    # --- pyxcp ----------------------------------------------------------------------------------
    def _open(self) -> Any:
        if self._master is not None:
            return self._master
        x = self._x
        cfg = x["Config"]()
        cfg.Transport.layer = "CAN"
        cfg.Transport.timeout = float(self.config.step_timeout_s)
        cfg.Transport.Can.interface = "custom"
        ext = 0x8000_0000 if self.settings.extended_id else 0
        cfg.Transport.Can.can_id_master = int(self.settings.can_id_master) | ext
        cfg.Transport.Can.can_id_slave = int(self.settings.can_id_slave) | ext
        cfg.Transport.Can.max_dlc_required = bool(self.settings.max_dlc_required)
        cfg.General.disable_error_handling = True
        cfg.General.diagnostics_on_failure = False

        class _Conf:
            general = x["General"](config=cfg)
            transport = x["Transport"](config=cfg)

        try:
            master = x["Master"]("can", _Conf, transport_layer_interface=self.bus)
            master.transport.connect()
        except (can.CanError, OSError) as exc:
            raise BusError(f"XCP: the CAN bus ({self.bus.channel_info}) cannot be used: {exc}") from exc
        self._master = master
        return master

    def close(self) -> None:
        """Stop pyxcp's receiving thread (the bus stays the caller's). DISCONNECT is not sent: the ECU keeps
        its pages as they are."""
        m, self._master = self._master, None
        self._connected = False
        if m is not None:
            try:
                m.transport.close()
            except Exception as exc:  # closing must never raise
                self._log.warning("closing pyxcp's transport: %s", exc)

    def _set_timeout(self, seconds: float) -> None:
        m = self._open()
        m.transport.timeout = max(1, int(seconds * 1e9))

    def _flush(self) -> None:
        """Drop responses still queued (late, duplicated): none of them answers the next command."""
        t = self._master.transport
        with t.resQueue_condition:
            n = len(t.resQueue)
            if n:
                t.resQueue.clear()
        if n:
            self.stats.stale_frames += n
            self._anomaly()

    def _anomaly(self) -> None:
        self._anomaly_at = self._clock()
        self._dirty = True  # the next memory transfer sets its MTA first (a duplicate may have moved it)

    def counters(self) -> dict[str, int]:
        s = self.stats
        return {
            "applies_ok": s.applies_ok,
            "applies_failed": s.applies_failed,
            "frames_sent": s.frames_sent,
            "frames_received": s.frames_received,
            "stale_frames": s.stale_frames,
            "unexpected_frames": s.unexpected_frames,
            "retransmissions": s.retransmissions,
            "step_timeouts": s.step_timeouts,
            "nacks": s.negative,
            "synchs": s.synchs,
            "connects": s.connects,
            "settled": s.settled,
        }

    def quantize(self, values: Mapping[str, float]) -> dict[str, float]:
        return self.layout.quantize(values)

    # --- one command, by XCP's error matrix --------------------------------------------------------------
    def _cmd(self, command: str, call: Callable[[], T], deadline: float, check: Callable[[T], bool] | None = None) -> T:
        """Run one XCP command (or a memory transfer that starts with SET_MTA) until it is answered.

        By the error matrix row of ``command`` (pyxcp's ``ERROR_MATRIX``), bounded:

        * no answer, or one ``check`` refuses / pyxcp cannot parse (it answers something else): SYNCH and
          repeat, as the matrix says for a timeout, up to ``step_retries`` times (the matrix's count at least);
        * a negative response the matrix repeats (ERR_CMD_BUSY: wait t7; ERR_ACCESS_LOCKED: unlock; ...):
          repeated as often as it says ("infinite" = ``step_retries``);
        * a negative response the matrix does not repeat: confirmed once, after a SYNCH (XCP answers carry no
          sequence number: on a bus that delays or duplicates frames a late answer of an earlier command can
          stand in for this one's, and a garbled request is refused for what it became): asked again after a
          SYNCH until the same error came ``CONFIRMATIONS`` + 1 times in a row, then raised as
          :class:`XcpCommandError` naming the XCP error.
        """
        x = self._x
        types = self._types
        matrix = x["ERROR_MATRIX"].get(types.Command[command], {})
        Action, PreAction = x["Action"], x["PreAction"]
        limit = {Action.REPEAT: 1, Action.REPEAT_2_TIMES: 2, Action.REPEAT_INF_TIMES: self.config.step_retries}
        repeats = 0
        confirmed: int | None = None  # a final negative response seen again and again
        confirmations = 0
        while True:
            if self._clock() >= deadline:
                raise EcuTimeoutError(f"XCP {command}: no valid answer before the overall timeout")
            self._set_timeout(min(self.config.step_timeout_s, max(0.001, deadline - self._clock())))
            self._flush()
            self.stats.commands += 1
            try:
                got = call()
            except types.XcpTimeoutError:
                error: int = -1
                self.stats.step_timeouts += 1
            except types.XcpResponseError as exc:
                error = _error_code(exc)
                self.stats.negative += 1
                name = _error_name(error)
                self.stats.errors[name] = self.stats.errors.get(name, 0) + 1
            except (can.CanError, OSError) as exc:
                raise BusError(f"XCP {command}: the CAN bus ({self.bus.channel_info}) failed: {exc}") from exc
            except (ValueError, IndexError, KeyError, TypeError, AttributeError, x["ConstructError"]) as exc:
                # a garbled or stale answer pyxcp could not parse: it answers something else
                self._log.debug("XCP %s: unparsable answer: %s", command, exc)
                error = -2
                self.stats.unexpected_frames += 1
            else:
                if check is None or check(got):
                    self._dirty = False
                    return got
                error = -2
                self.stats.unexpected_frames += 1
            self._anomaly()
            if error == 0x00:  # ERR_CMD_SYNCH: the late answer to a SYNCH of ours: ask again
                pre, action, most = (PreAction.NONE,), Action.REPEAT, self.config.step_retries
            elif error < 0:
                pre, action = matrix.get("ERR_TIMEOUT", ((PreAction.SYNCH,), Action.REPEAT_2_TIMES))
                most = max(limit.get(action, 0), self.config.step_retries)
            else:
                handler = matrix.get(_error_name(error))
                if handler is not None and handler[1] in limit:
                    pre, action = handler
                    most = min(limit[action], self.config.step_retries)
                elif confirmed != error or confirmations < CONFIRMATIONS:
                    # final, unless it answered another command (late) or a garbled request: asked again
                    confirmations = confirmations + 1 if confirmed == error else 1
                    confirmed = error
                    pre, action, most = (PreAction.SYNCH,), Action.REPEAT, repeats + 1
                else:
                    raise self._refusal(command, error)
            if action == Action.SKIP:
                return None  # type: ignore[return-value]
            if repeats >= most:
                if error < 0:
                    raise EcuTimeoutError(
                        f"XCP {command}: no valid answer after {repeats + 1} tries of "
                        f"{self.config.step_timeout_s * 1e3:g} ms"
                    )
                raise self._refusal(command, error)
            repeats += 1
            self.stats.retransmissions += 1
            for p in pre if isinstance(pre, tuple | list) else (pre,):
                if p == PreAction.WAIT_T7:
                    time.sleep(self.config.t7_s)
                elif p == PreAction.SYNCH:
                    self._synch(deadline)
                elif p in (PreAction.UNLOCK_SLAVE, PreAction.GET_SEED_UNLOCK):
                    self._unlock(deadline, command)
                # SET_MTA: a memory transfer sets its MTA again when repeated (self._dirty)

    def _refusal(self, command: str, error: int) -> XcpCommandError:
        name = _error_name(error)
        text = self._x_error_text(error)
        return XcpCommandError(command, error, name, text, _CODE_OF_ERROR.get(error, ErrorCode.SEQUENCE))

    def _x_error_text(self, error: int) -> str:
        entry = self._x["ERROR_TABLE"].get(_error_name(error))
        return str(entry[0]).rstrip(".") if entry else "unknown error code"

    def _synch(self, deadline: float) -> None:
        """SYNCH, used as a fence: every answer before its ERR_CMD_SYNCH belongs to an earlier command and is
        dropped, so the command repeated next is answered by its own response. No answer at all means the
        session is gone (a reset, a DISCONNECT): :class:`_RestartError`."""
        t = self._master.transport
        types = self._types
        empty = self._x["EmptyFrameError"]
        self.stats.synchs += 1
        for _ in range(max(2, self.config.step_retries)):
            if self._clock() >= deadline:
                raise EcuTimeoutError("XCP SYNCH: no answer before the overall timeout")
            self._flush()
            try:
                t.block_request(types.Command.SYNCH)  # sent without waiting: the answers are read below
            except types.XcpResponseError:
                pass  # pyxcp found a queued negative answer first: a stale one
            except (can.CanError, OSError) as exc:
                raise BusError(f"XCP SYNCH: the CAN bus failed: {exc}") from exc
            end = min(deadline, self._clock() + self.config.step_timeout_s)
            while (left := end - self._clock()) > 0:
                t.timeout = max(1, int(left * 1e9))
                try:
                    pdu = bytes(t.get())
                except empty:
                    break
                if pdu[:2] == b"\xfe\x00":
                    return
                self.stats.stale_frames += 1  # an earlier command's answer, arriving late
            self.stats.step_timeouts += 1
        self._connected = False
        raise _RestartError()

    # --- the session ------------------------------------------------------------------------------------
    def _session(self, deadline: float) -> Any:
        m = self._open()
        if self._connected:
            self._talked = True
            return m
        types = self._types

        def connect() -> Any:
            r = m.connect(0x00)
            return r

        self._cmd("CONNECT", connect, deadline, check=self._plausible_connect)
        self._byte_order = str(m.slaveProperties.byteOrder)
        self.stats.connects += 1
        props = m.slaveProperties
        if props.optionalCommMode:
            try:
                self._cmd("GET_COMM_MODE_INFO", m.getCommModeInfo, deadline)
            except XcpCommandError:
                props.masterBlockMode = False
        else:
            props.masterBlockMode = False
            props.maxBs = 0
        self._talked = True
        status = self._cmd("GET_STATUS", m.getStatus, deadline)
        self._connected = True
        self._page_bytes = {}
        if self._checksum_ok is False:
            # asked again in each session: a refusal confirmed on a bus that garbles frames (or a checksum type
            # misread) must not turn the full read-back on for the client's whole life
            self._checksum_ok = None
        if status is not None and status.resourceProtectionStatus.calpag and self.key_algorithm is not None:
            self._unlock(deadline)  # without an algorithm, a protected command will be refused and say so
        del types
        if self.settings.pages and self._reference is None:
            # the reference page is read once, before the bridge writes anything (see _read_page); best effort:
            # what fails here is asked again where it is needed
            try:
                self._read_page(self.settings.reference_page, deadline)
            except (EcuTimeoutError, XcpCommandError, _MismatchError) as exc:
                self._log.debug("XCP: reading the reference page at the start failed: %s", exc)
        return m

    def _plausible_connect(self, r: Any) -> bool:
        """A CONNECT answer XCP on classic CAN can give (XCP on CAN has no frame CRC of its own: a garbled answer
        would set the session's frame sizes, address granularity or byte order, and a wrong UPLOAD size makes
        pyxcp wait for frames that never come): else it is taken as garbled and CONNECT is asked again."""
        if r is None:
            return False
        basic = r.commModeBasic
        ok = (
            int(r.maxCto) == 8
            and int(r.maxDto) == 8
            and int(r.protocolLayerVersion) == 1
            and int(r.transportLayerVersion) == 1
            and str(basic.addressGranularity) == "BYTE"
        )
        if ok and self._byte_order is not None and str(basic.byteOrder) != self._byte_order:
            ok = False  # the ECU announced the other byte order in an earlier session
        if not ok:
            self._anomaly()
        return ok

    def _unlock(self, deadline: float, command: str = "UNLOCK") -> None:
        m = self._master
        if self.key_algorithm is None:
            raise self._refusal(command, 0x25)  # the ECU's ERR_ACCESS_LOCKED: no algorithm to answer its seed
        seed = self._cmd("GET_SEED", lambda: m.getSeed(0x00, RESOURCE_CAL_PAG), deadline)
        data = bytes(seed.seed) if seed is not None else b""
        if not data:
            return  # not protected (any more)
        key = bytes(self.key_algorithm(RESOURCE_CAL_PAG, data))
        if len(key) > 6:
            raise ProtocolConfigError("keys longer than 6 bytes (several UNLOCK frames) are not supported")
        self.stats.unlocks += 1
        try:
            status = m.unlock(len(key), key)
        except self._types.XcpResponseError as exc:
            self._connected = False  # a wrong key ends the session
            raise self._refusal("UNLOCK", _error_code(exc)) from None
        except self._types.XcpTimeoutError:
            self._connected = False
            raise _RestartError() from None
        if status.calpag:
            raise XcpCommandError(
                "UNLOCK", 0x25, "ERR_ACCESS_LOCKED", "the key was not accepted", ErrorCode.INVALID_REQUEST
            )

    # --- memory ---------------------------------------------------------------------------------------------
    def _request(self, command: str, *data: int) -> bytes:
        types = self._types
        return bytes(self._master.transport.request(types.Command[command], *data))

    def _dword(self, v: int) -> bytes:
        return bytes(self._master.DWORD_pack(v))

    def _set_page(self, mode: int, page: int, deadline: float) -> None:
        seg = self.settings.segment
        self._cmd("SET_CAL_PAGE", lambda: self._request("SET_CAL_PAGE", mode, seg, page), deadline, _empty)

    def _get_page(self, mode: int, deadline: float) -> int:
        """The page of the application (MODE_ECU) or of XCP's access, asked until two answers in a row agree:
        every decision on pages rests on it, and XCP on CAN has no check of its own (one flipped bit of an
        answer names the other page)."""
        seg = self.settings.segment
        last: int | None = None
        for _ in range(2 + self.config.step_retries):
            got = self._cmd("GET_CAL_PAGE", lambda: self._request("GET_CAL_PAGE", mode, seg), deadline, _length(3))
            page = int(got[2])
            if page == last:
                return page
            if last is not None:
                self._anomaly()
            last = page
        raise EcuTimeoutError("XCP GET_CAL_PAGE: the answers disagree again and again")

    def _set_mta(self, address: int, ext: int) -> None:
        got = self._request("SET_MTA", 0, 0, ext, *self._dword(address))
        if got:
            raise ValueError("SET_MTA answered with data")

    def _block_mode(self) -> bool:
        props = self._master.slaveProperties
        return (
            self.config.block_mode
            and not self._degraded
            and bool(props.get("masterBlockMode"))
            and int(props.get("maxBs") or 0) > 1
        )

    def _write_run(self, run: Run, data: bytes, deadline: float) -> None:
        """Write one run: in master block mode when the ECU offers it (one answer per block), else (or once a
        block failed in this apply) DOWNLOAD by DOWNLOAD, each answered; after any anomaly the next DOWNLOAD
        sets the MTA again (the matrix's SYNCH, SET_MTA, repeat)."""
        step = 6  # classic CAN: DOWNLOAD carries at most MAX_CTO - 2 bytes
        if self._block_mode() and run.size > step:
            chunk = min(int(self._master.slaveProperties.maxBs) * step, 255)

            def blocks() -> bool:
                self._set_mta(run.address, run.extension)
                for k in range(0, len(data), chunk):
                    part = data[k : k + chunk]
                    got = (
                        self._request("DOWNLOAD", len(part), *part) if len(part) <= step else self._download_block(part)
                    )
                    if got:
                        raise ValueError("DOWNLOAD answered with data")
                return True

            try:
                self._cmd("DOWNLOAD", blocks, deadline)
                return
            except (EcuTimeoutError, XcpCommandError) as exc:
                if self._clock() >= deadline or (isinstance(exc, XcpCommandError) and exc.code == ErrorCode.ECU_BUSY):
                    raise
                self._degraded = True  # blocks do not get through: frame by frame for the rest of this apply
                self._log.debug("XCP: block download failed (%s); DOWNLOAD by DOWNLOAD", exc)
        self._dirty = True
        for k in range(0, len(data), step):
            part = data[k : k + step]
            address = run.address + k

            def one(part: bytes = part, address: int = address) -> bytes:
                if self._dirty:
                    self._set_mta(address, run.extension)
                return self._request("DOWNLOAD", len(part), *part)

            self._cmd("DOWNLOAD", one, deadline, _empty)

    def _download_block(self, part: bytes) -> bytes:
        """One master block: DOWNLOAD(n, 6 bytes), DOWNLOAD_NEXT(remaining, ...) unanswered, the last answered."""
        types = self._types
        t = self._master.transport
        n = len(part)
        t.block_request(types.Command.DOWNLOAD, n, *part[:6])
        for k in range(6, n, 6):
            piece = part[k : k + 6]
            if k + 6 >= n:
                return bytes(t.request(types.Command.DOWNLOAD_NEXT, n - k, *piece))
            t.block_request(types.Command.DOWNLOAD_NEXT, n - k, *piece)
        return b""

    def _read_run(self, run: Run, deadline: float) -> bytes:
        """The bytes of one run: UPLOAD in slave block mode when offered (until a block fails in this apply),
        else UPLOAD by UPLOAD of 7 bytes each, answered in one frame."""
        m = self._master
        if bool(m.slaveProperties.get("slaveBlockMode")) and not self._degraded and run.size > 7:

            def blocks() -> bytes:
                out = b""
                for pos in range(0, run.size, MAX_UPLOAD):
                    n = min(run.size - pos, MAX_UPLOAD)
                    self._set_mta(run.address + pos, run.extension)
                    got = bytes(m.upload(n)) if n > 7 else self._request("UPLOAD", n)
                    if len(got) != n:
                        raise ValueError(f"UPLOAD of {n} bytes answered {len(got)}")
                    out += got
                return out

            try:
                return self._cmd("UPLOAD", blocks, deadline)
            except EcuTimeoutError:
                if self._clock() >= deadline:
                    raise
                self._degraded = True
        # UPLOAD of at most 7 bytes, answered in one frame, from the MTA (set first, and again after any anomaly):
        # its command is 2 bytes long. Not SHORT_UPLOAD: its 8-byte command is one flipped bit (0xF4 -> 0xF0) away
        # from a DOWNLOAD of 7 bytes that writes its own address bytes at the MTA, and on a bus that garbles
        # frames above CAN's CRC (the fault campaign) that wrote garbage into the page the ECU application used
        # whenever that page was read; a garbled 2-byte UPLOAD is refused (ERR_CMD_SYNTAX) whatever it becomes.
        self._dirty = True
        out = b""
        for pos in range(0, run.size, 7):
            n = min(run.size - pos, 7)
            address = run.address + pos

            def one(n: int = n, address: int = address) -> bytes:
                if self._dirty:
                    self._set_mta(address, run.extension)
                return self._request("UPLOAD", n)

            out += self._cmd("UPLOAD", one, deadline, _length(n))
        return out

    def _crc_of(self, run: Run, deadline: float, strict: bool = True) -> int | None:
        """The ECU's CRC-32 over a run, or None when it does not implement BUILD_CHECKSUM (ERR_CMD_UNKNOWN):
        then the bridge verifies by read-back alone. ``strict=False`` (reading what the ECU holds): any other
        refusal of BUILD_CHECKSUM also falls back to the read-back, the refusal is left to the apply to report."""
        if self._checksum_ok is False:
            return None
        try:
            crc = self._checksum(run, deadline)
        except _OtherChecksumError as exc:
            self._checksum_ok = False  # asked again in the next session
            self._log.warning("XCP: %s: every write is verified by read-back", exc)
            return None
        except XcpCommandError as exc:
            if exc.error != 0x20:
                if strict:
                    raise
                self._log.warning("XCP: %s; verified by reading back instead", exc)
                return None
            self._checksum_ok = False
            self._log.warning("XCP: the ECU does not implement BUILD_CHECKSUM: every write is verified by read-back")
            return None
        self._checksum_ok = True
        return crc

    def _checksum(self, run: Run, deadline: float) -> int:
        m = self._master

        def build() -> Any:
            self._set_mta(run.address, run.extension)
            return m.buildChecksum(run.size)

        kinds: list[str] = []

        def crc32(r: Any) -> bool:  # another checksum type is a garbled answer, unless the ECU always says so
            kinds.append(str(getattr(r, "checksumType", "")))
            return r is not None and kinds[-1] == CHECKSUM_CRC_32

        try:
            got = self._cmd("BUILD_CHECKSUM", build, deadline, check=crc32)
        except EcuTimeoutError:
            if len(kinds) >= 3 and len(set(kinds)) == 1 and kinds[0]:
                # e.g. XCP_ADD_44, many XCP drivers' default: an additive checksum is too weak to confirm a write
                raise _OtherChecksumError(f"the ECU builds {kinds[0]} checksums, not XCP_CRC_32") from None
            raise
        return int(got.checksum)

    def _verify_run(self, run: Run, want: bytes, deadline: float, read_back: bool) -> bytes:
        """Make the ECU hold ``want`` in the run: its checksum must be the host's and, with read-back, every
        byte read back must match. What differs is written again (DOWNLOAD by DOWNLOAD), within bounds."""
        crc = zlib.crc32(want) & 0xFFFF_FFFF
        disagree = 0  # rounds in which the bytes read back were the written ones but the ECU's CRC-32 was not
        for _ in range(REPAIR_ROUNDS):
            ecu_crc = self._crc_of(run, deadline)
            matches = ecu_crc is None or ecu_crc == crc
            if matches and not read_back and ecu_crc is not None:
                return want
            got = self._read_run(run, deadline)
            if matches and got == want:
                return got
            bad = [k for k in range(0, run.size, 6) if got[k : k + 6] != want[k : k + 6]]
            if not bad:
                self._anomaly()  # the checksum and the bytes disagree: one of the answers was garbled or late
                disagree += 1
                continue
            self.stats.repairs += len(bad)
            self._dirty = True
            for k in bad:
                part = want[k : k + 6]

                def one(part: bytes = part, address: int = run.address + k) -> bytes:
                    if self._dirty:
                        self._set_mta(address, run.extension)
                    return self._request("DOWNLOAD", len(part), *part)

                self._cmd("DOWNLOAD", one, deadline, _empty)
                self._dirty = True  # each repaired piece sets its own MTA
        names = [p.name for p in run.params]
        if disagree == REPAIR_ROUNDS:
            raise _uncovered(run)
        raise _MismatchError(
            f"XCP: the ECU's memory of {', '.join(names[:4])}{'...' if len(names) > 4 else ''} does not take the "
            f"written bytes after {REPAIR_ROUNDS} rounds of checks and repairs"
        )

    def _read_page(self, page: int | None, deadline: float) -> dict[Run, bytes]:
        """Every run of ``page`` (None: the page XCP accesses already), each checked by the ECU's checksum (or,
        without BUILD_CHECKSUM, read twice alike).

        The reference page is read-only (the flashed data set): once read, later reads compare the ECU's
        checksums with the bytes known. After a page other than the reference one was read, XCP's access goes
        back to the reference page (:meth:`_park`)."""
        s = self.settings
        reference = s.pages and page == s.reference_page
        if reference and self._reference is not None:
            # the flashed data set, read (and checked by the ECU's CRC-32) once: reading it again would move XCP's
            # access off the working page, and moving it back is a SET_CAL_PAGE one flipped bit (mode 0x02 ->
            # 0x03) away from switching the application onto a working page that a failed apply left half written
            return dict(self._reference)
        if page is not None and s.pages and self._get_page(MODE_XCP, deadline) != page:
            self._move_xcp(page, deadline)  # confirmed: what is read below is this page, no other
        out = self._known_page(page, deadline) or self._read_runs(deadline)
        if reference:
            self._reference = dict(out)
        elif page is not None and s.pages:
            self._park(deadline, required=False)
        return out

    def _known_page(self, page: int | None, deadline: float) -> dict[Run, bytes] | None:
        """The page's bytes when the ECU's CRC-32 of every run equals that of a set the bridge knows (what it
        read of the page before, the last confirmed calibration, the definition's baseline): a checksum instead
        of some 15 answered UPLOADs per 80 bytes, each of which a bus that garbles frames can spoil (a CRC-32
        match by chance: 2^-32). None: none matches, or the ECU builds no checksums."""
        if self._checksum_ok is False:
            return None
        candidates: list[dict[Run, bytes]] = []
        if page is not None and page == self.settings.reference_page and self._reference is not None:
            candidates.append(self._reference)
        if page is not None and page in self._page_bytes:
            candidates.append(self._page_bytes[page])
        for values in (self.last_confirmed, self._baseline):
            if values is None:
                continue
            try:
                candidates.append(self.layout.image(values))
            except (BacError, ValueError):
                continue  # e.g. values read back outside the bounds
        seen: list[dict[Run, bytes]] = []
        for image in candidates:
            if image in seen:
                continue
            seen.append(image)
            if self._crcs_match(image, deadline):
                return dict(image)
        return None

    def _crcs_match(self, data: Mapping[Run, bytes], deadline: float, strict: bool = False) -> bool:
        """The ECU's CRC-32 of every run (of the page XCP accesses) equals the CRC-32 of ``data``; False also
        when the ECU does not build checksums. ``strict``: a refusal of BUILD_CHECKSUM is raised (asked again by
        the caller) instead of counting as a mismatch."""
        for run, want in data.items():
            crc = self._crc_of(run, deadline, strict=strict)
            if crc is None or crc != zlib.crc32(want) & 0xFFFF_FFFF:
                return False
        return True

    def _park(self, deadline: float, required: bool = True) -> None:
        """XCP's access goes back to the reference page, which refuses writes (ERR_WRITE_PROTECTED): a garbled
        or late command that turns into a DOWNLOAD can then change no page the ECU application may use. Asked
        back with GET_CAL_PAGE (a garbled SET_CAL_PAGE is answered positively). ``required=False`` (after a
        read): an ECU that refuses it is left as it is."""
        if not self.settings.pages:
            return
        try:
            self._move_xcp(self.settings.reference_page, deadline)
        except XcpCommandError as exc:
            if required or exc.code == ErrorCode.ECU_BUSY:
                raise
            self._log.warning("XCP: %s; XCP's access stays on the page read", exc)

    def _move_xcp(self, page: int, deadline: float) -> None:
        """XCP's access to ``page``: SET_CAL_PAGE(XCP, page), confirmed by GET_CAL_PAGE(XCP) (two agreeing
        answers), sent again when it did not go there. A SET_CAL_PAGE garbled in its page byte is answered
        positively and leaves XCP's access elsewhere: without the confirmation, a CRC-32 or read of "the page"
        would name the other one (the reference page matches the baseline; a working page in use would be
        reported as holding it). :class:`_MismatchError` when it does not go there."""
        for _ in range(3):
            self._set_page(MODE_XCP, page, deadline)
            if self._get_page(MODE_XCP, deadline) == page:
                return
            self._anomaly()  # acknowledged but not performed: a garbled command reached the ECU
        raise _MismatchError(f"XCP GET_CAL_PAGE: XCP's access does not go to page {page} after SET_CAL_PAGE")

    def _read_runs(self, deadline: float) -> dict[Run, bytes]:
        out: dict[Run, bytes] = {}
        for run in self.layout.runs:
            got = self._read_run(run, deadline)
            crc = self._crc_of(run, deadline, strict=False)
            if crc is None:
                if self._read_run(run, deadline) != got:
                    raise _MismatchError(f"XCP read of 0x{run.address:X}+{run.size}: two reads disagree")
            else:
                # a garbled answer of the right length spoils one piece: read again and take, piece by piece, the
                # bytes seen twice, until they match the ECU's CRC-32 (instead of reading everything again and
                # again, which on a bus that garbles many frames rarely comes out whole)
                reads = [got]
                while zlib.crc32(got) & 0xFFFF_FFFF != crc:
                    if len(reads) > REPAIR_ROUNDS:
                        if all(r == reads[0] for r in reads):
                            raise _uncovered(run)  # the same bytes every time: the checksum is over something else
                        raise _MismatchError(
                            f"XCP read of 0x{run.address:X}+{run.size}: the bytes do not match the ECU's CRC-32"
                        )
                    reads.append(self._read_run(run, deadline))
                    got = _agreed(reads)
            out[run] = got
        return out

    def _holds(self, run: Run, data: bytes, deadline: float) -> bool:
        """The ECU's run holds ``data`` (its CRC-32, or the bytes read back)."""
        crc = self._crc_of(run, deadline, strict=False)
        if crc is None:
            return self._read_run(run, deadline) == data
        return crc == zlib.crc32(data) & 0xFFFF_FFFF

    def _check_image(self, image: Mapping[Run, bytes], deadline: float) -> None:
        """The page XCP accesses holds ``image`` (the ECU's CRC-32 of each run, or the bytes read back)."""
        for run, data in image.items():
            if not self._holds(run, data, deadline):
                raise _MismatchError(f"XCP: the memory at 0x{run.address:X}+{run.size} changed after its check")

    def _wait_settled(self) -> None:
        """Frames still on the way after an anomaly land before the final checks."""
        wait = self._anomaly_at + self.config.settle_s - self._clock()
        if wait > 0:
            time.sleep(wait)

    def _fence(self) -> int:
        """Before a call's first command: frames still on the way after an anomaly of an earlier call (a late
        answer of the node's status poll, of a read, of the last apply) land and are dropped. Else one could
        stand in for an answer of this call: a late CRC-32 of the same set, when the same calibration is applied
        again, would confirm writes it never saw. Returns the number of frames dropped."""
        if self._master is None:
            return 0
        self._wait_settled()
        before = self.stats.stale_frames
        self._flush()
        return self.stats.stale_frames - before

    # --- public API ------------------------------------------------------------------------------------------
    def apply(self, values: Mapping[str, float], timeout_s: float | None = None) -> ApplyResult:
        """Write every raw parameter and return when the ECU holds exactly these values (see the module doc).

        Raises :class:`OutOfBoundsError` / :class:`UnknownParameterError` before sending anything, else a
        :class:`BridgeError` with its ``code`` and ``ecu_state``.
        """
        if not values:
            raise InvalidRequestError("nothing to apply: the calibration is empty")
        image = self.layout.image(values)  # refuses unknown names and anything outside the bounds
        want = self.layout.decode(image)
        t0 = self._clock()
        deadline = t0 + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        previous = self.last_confirmed
        attempts = 0
        last: BridgeError | None = None
        touched = False  # a command that changes what the ECU application uses was sent
        uncertain = False  # ... and its outcome is not known
        # block transfers come back only after an apply without any lost, late or garbled frame: on a lossy bus
        # a block of 14 frames rarely gets through whole, and each failed block costs a step timeout
        self._degraded = self._degraded and self._anomaly_at > -math.inf
        stale = self._fence()
        self._anomaly_at = -math.inf
        if stale:
            self._anomaly()  # frames of an earlier call arrived late: this apply checks again after settle_s
        self._talked = False  # a session with the ECU was up during this apply
        while attempts < self.config.max_attempts and self._clock() < deadline:
            attempts += 1
            self.stats.attempts += 1
            state = _Attempt()
            try:
                got = self._attempt(image, deadline, state)
            except _RestartError:
                touched |= state.touched
                uncertain |= state.touched
                last = EcuTimeoutError("XCP: the session was lost (SYNCH unanswered); connected again")
                continue
            except BusError as exc:
                touched |= state.touched
                exc.attempts = attempts
                self.stats.applies_failed += 1
                exc.uncertain = touched
                exc.ecu_state = EcuState(Holds.UNKNOWN, detail="the bus failed") if touched else self._kept(previous)
                raise
            except BridgeError as exc:
                touched |= state.touched
                uncertain |= state.in_doubt
                last = exc
                self._log.debug("XCP apply attempt %d failed: %s", attempts, exc)
                if exc.code == ErrorCode.ECU_BUSY or isinstance(exc, ProtocolConfigError):
                    break  # retrying cannot help: the vehicle moves, or the configuration is wrong
                continue
            self.stats.applies_ok += 1
            self.last_confirmed = dict(got)
            raw = self.codec.encode_set(got)
            return ApplyResult(
                got, dict(sorted(raw.items())), set_crc(raw), attempts, self._clock() - t0, attempts, True
            )
        if last is None:
            last = EcuTimeoutError("XCP: the overall timeout passed before an attempt could start")
        last.args = (f"{last} (gave up after {attempts} attempt(s) in {self._clock() - t0:.3f} s)",)
        last.attempts = attempts
        last.uncertain = uncertain
        self.stats.applies_failed += 1
        if not touched and (self._anomaly_at == -math.inf or not self._talked):
            # nothing that changes what the ECU uses was sent, and nothing odd happened in a session with it (a
            # garbled frame could become such a command; an ECU that never answered ignores them all)
            last.ecu_state = self._kept(previous)
            raise last
        state_after = self.settle(want, previous)
        last.ecu_state = state_after
        if state_after.holds is Holds.REQUESTED and state_after.values is not None:
            # the commit went through, only its answer was lost: the ECU's page was read and named (CRC-32)
            self.stats.applies_failed -= 1
            self.stats.applies_ok += 1
            self.last_confirmed = dict(state_after.values)
            raw = self.codec.encode_set(state_after.values)
            return ApplyResult(
                dict(state_after.values),
                dict(sorted(raw.items())),
                set_crc(raw),
                attempts,
                self._clock() - t0,
                attempts,
                True,
                note=f"the commit's answer was lost ({last}); the ECU was read back and holds the request",
            )
        raise last

    def _raw_crc(self, values: Mapping[str, float]) -> tuple[dict[int, int], int]:
        """The bac encoding and set CRC-32 of values read back; values outside their bounds (a garbled write
        the ECU holds) have no raw encoding: then the CRC-32 is over the values' text."""
        try:
            raw = self.codec.encode_set(values)
        except OutOfBoundsError:
            return {}, zlib.crc32(repr(sorted(values.items())).encode()) & 0xFFFF_FFFF
        return dict(sorted(raw.items())), set_crc(raw)

    def _crc(self, values: Mapping[str, float]) -> int | None:
        """The set CRC-32 of values read back (None when one lies outside its bounds: a garbled write)."""
        try:
            return self.codec.crc(values)
        except OutOfBoundsError:
            return None

    def _kept(self, previous: Mapping[str, float] | None) -> EcuState:
        return EcuState(
            Holds.PREVIOUS,
            None if previous is None else dict(previous),
            None if previous is None else self.codec.crc(previous),
            detail="nothing that changes what the ECU uses took effect",
        )

    def _attempt(self, image: dict[Run, bytes], deadline: float, state: _Attempt) -> dict[str, float]:
        s = self.settings
        self._session(deadline)
        if s.pages:
            if self._ecu_page is None:
                # asked first: a SET_CAL_PAGE(ECU, reference) garbled in its page byte switches the application
                # onto the working page, which a failed apply may have left half written
                self._ecu_page = self._get_page(MODE_ECU, deadline)
            if self._ecu_page != s.reference_page:
                # the controller runs on the reference page (the safe data set) while the working page is written
                state.touched = state.in_doubt = True
                self._ecu_page = None
                try:
                    self._set_page(MODE_ECU, s.reference_page, deadline)
                except XcpCommandError:
                    state.touched = state.in_doubt = False  # refused (and confirmed): nothing changed
                    raise
                self._ecu_page = s.reference_page
                state.in_doubt = False
            if self._reference is None:
                # known before a byte is written (reading it moves XCP's access there): afterwards the reference page
                # is answered from what was read, and no read moves XCP's access off a working page that a failed
                # apply left half written (moving it back would be the hazardous SET_CAL_PAGE(XCP, working))
                self._read_page(s.reference_page, deadline)
            if self._get_page(MODE_XCP, deadline) != s.working_page:
                # only after a confirmed apply (XCP's access parked on the reference page, the working page holds
                # that apply's checked set), so a garbled mode 0x02 -> 0x03 switches onto checked values at worst
                self._move_xcp(s.working_page, deadline)
            # asked every attempt, after XCP's page is set and before a byte is written: the page the application
            # uses must be the reference (a SET_CAL_PAGE garbled on the way, e.g. XCP's mode 0x02 into 0x03, is
            # answered positively and switches the application too)
            if self._get_page(MODE_ECU, deadline) != s.reference_page:
                self._ecu_page = None
                state.touched = state.in_doubt = True
                raise _MismatchError(
                    "XCP GET_CAL_PAGE: the ECU application does not use its reference page: the working page is "
                    "not written"
                )
        else:
            state.touched = state.in_doubt = True  # one page: the writes change what the ECU uses at once
        self._page_bytes.pop(s.working_page if s.pages else 0, None)
        for run, data in image.items():
            self._write_run(run, data, deadline)
        got: dict[Run, bytes] = {}
        checked_at = self._clock()  # the start of the last check of the page's contents
        for run, data in image.items():
            got[run] = self._verify_run(run, data, deadline, self.config.verify_readback)
        if self._anomaly_at > -math.inf:
            # a write still on its way (delayed, duplicated, held back; of this attempt or an earlier one) after an
            # anomaly could land after the check that passed: once the bus's worst delay has passed, the ECU's
            # checksums are asked again
            self._wait_settled()
            checked_at = self._clock()
            self._check_image(image, deadline)
        if s.pages:
            # nothing can write into the working page any more once XCP's access is on the (read-only) reference
            # page; then the application switches to the checked working page
            self._park(deadline)
            state.touched = state.in_doubt = True
            self._ecu_page = None
            self._set_page(MODE_ECU, s.working_page, deadline)  # the commit
            # the final word, once frames still on the way after an anomaly have landed
            for rechecked in (False, True):
                self._wait_settled()
                anomalous = self._anomaly_at >= checked_at
                if self._get_page(MODE_ECU, deadline) != s.working_page:
                    raise _MismatchError(
                        "XCP GET_CAL_PAGE: the ECU application does not use the working page after the switch"
                    )
                if self._get_page(MODE_XCP, deadline) != s.reference_page:
                    # the commit garbled into both modes (0x01 -> 0x03), or a late SET_CAL_PAGE(XCP): XCP's access
                    # is on the page in use
                    self._anomaly()
                    self._park(deadline)
                    if rechecked:
                        raise _MismatchError("XCP GET_CAL_PAGE: XCP's access went back to the page in use")
                    anomalous = True
                if rechecked or not anomalous:
                    break
                # an anomaly at or after the last check of the contents (during that check, the park or the commit:
                # a lost answer, a repeat, a garbled or late frame): a write on its way could have landed after it.
                # The application uses the working page now, so moving XCP's access there switches nothing: the
                # ECU's CRC-32s are asked again (frames on the way have landed: waited above; the move itself puts
                # no write on the way), then XCP's access is parked again. A mismatch fails the attempt with the
                # application on the working page: the next attempt switches it to the reference page first, a
                # settlement switches back a page it cannot name.
                self._move_xcp(s.working_page, deadline)
                checked_at = self._clock()
                self._check_image(image, deadline)
                self._park(deadline)
        elif self._anomaly_at > -math.inf and self._clock() - self._anomaly_at < self.config.settle_s:
            self._wait_settled()  # one page: an anomaly during the final checks: check once more after it settled
            for run, data in image.items():
                if not self._holds(run, data, deadline):
                    raise _MismatchError(f"XCP: the memory at 0x{run.address:X}+{run.size} changed after its check")
        self._ecu_page = s.working_page if s.pages else 0
        state.in_doubt = False
        self._page_bytes[self._ecu_page] = dict(got)
        return self.layout.decode(got)

    def settle(self, requested: Mapping[str, float] | None, previous: Mapping[str, float] | None = None) -> EcuState:
        """What the ECU application uses after an uncertain outcome: its page, and what that page holds.

        The reference page is the flashed data set (known once read, checked by the ECU's CRC-32). A working
        page in use is compared by the ECU's CRC-32 with the request and the previous calibration; when it holds
        neither, or values outside the declared bounds, the application is switched back to its reference page
        (one idempotent command, asked until GET_CAL_PAGE confirms it) and the state says so: the bridge never
        leaves the ECU running on a page it cannot name. Asked again until ``settle_timeout_s``."""
        self.stats.settled += 1
        t0 = self._clock()
        deadline = t0 + self.config.settle_timeout_s
        saved = self.config
        self.config = replace(saved, step_retries=max(saved.step_retries, 10))
        problem = "no time left"
        refused = ""  # the last negative response while reading back
        s = self.settings
        try:
            while self._clock() < deadline:
                self._wait_settled()
                try:
                    self._session(deadline)
                    page = self._get_page(MODE_ECU, deadline) if s.pages else 0
                    note = ""
                    data: dict[Run, bytes] | None = None
                    if s.pages and page != s.reference_page:
                        data, note = self._settle_working(page, requested, previous, deadline)
                        if data is None:
                            continue
                        page = self._ecu_page if self._ecu_page is not None else page
                    else:
                        data = self._read_page(page, deadline)
                except _RestartError:
                    problem = "the session was lost"
                    continue
                except BusError as exc:
                    problem = str(exc)
                    break
                except XcpCommandError as exc:
                    # asked again until the deadline: on a bus that garbles frames a refusal may be a garbled answer
                    problem = refused = str(exc)
                    continue
                except BridgeError as exc:
                    problem = str(exc)
                    continue
                values = self.layout.decode(data)
                self._ecu_page = page
                self._page_bytes[page] = data
                self.last_confirmed = dict(values)
                holds = classify(values, requested, previous, self._baseline)
                where = ""
                if s.pages:
                    kind = "reference" if page == s.reference_page else "working"
                    where = f"the ECU application uses its {kind} page {page}"
                return EcuState(holds, values, self._crc(values), True, "; ".join(filter(None, (where, note))))
        finally:
            self.config = saved
        self.last_confirmed = None
        self._ecu_page = None
        if refused and refused != problem:
            problem = f"{problem}; before, {refused}"
        return EcuState(Holds.UNKNOWN, detail=f"reading the ECU back failed: {problem}")

    def _settle_working(
        self,
        page: int,
        requested: Mapping[str, float] | None,
        previous: Mapping[str, float] | None,
        deadline: float,
    ) -> tuple[dict[Run, bytes] | None, str]:
        """The working page the application uses: the known set it holds (by the ECU's CRC-32), else the
        reference page switched to. (None, "") when the page in use changed meanwhile: asked again."""
        s = self.settings
        known: list[dict[Run, bytes]] = []
        for values in (requested, previous, self._baseline):
            if values is None:
                continue
            try:
                known.append(self.layout.image(values))
            except (BacError, ValueError):
                continue  # e.g. a previous read back outside the bounds: not a set to compare with
        data: dict[Run, bytes] | None = None
        why = "it holds neither the requested, the previous nor the baseline calibration"
        if self._checksum_ok is not False:
            if self._get_page(MODE_XCP, deadline) != page:
                self._move_xcp(page, deadline)  # confirmed: the CRC-32s below name this page, no other
            data = next((image for image in known if self._crcs_match(image, deadline, strict=True)), None)
            if data is not None:
                # parked only on a page the bridge can name: XCP's access stays on a page of unknown content while
                # the application is switched off it below, so that no SET_CAL_PAGE(XCP, working) has to follow
                # that one flipped bit makes a switch of the application onto it
                self._park(deadline, required=False)
        else:  # no BUILD_CHECKSUM: read it (XCP goes back to the reference page after)
            data = self._read_page(page, deadline)
            if self._crc(self.layout.decode(data)) is None:
                data, why = None, "it holds values outside the declared bounds"
        if self._get_page(MODE_ECU, deadline) != page:
            return None, ""  # a garbled SET_CAL_PAGE switched the application meanwhile: look again
        if data is not None:
            self._ecu_page = page
            return data, ""
        # the application runs on a page the bridge cannot name: back to the reference page
        self._ecu_page = None
        try:
            self._set_page(MODE_ECU, s.reference_page, deadline)
        except XcpCommandError as exc:
            # refused (the vehicle moves, a locked ECU): what the page holds is read and reported as it is
            data = self._read_page(page, deadline)
            if self._get_page(MODE_ECU, deadline) != page:
                return None, ""
            self._ecu_page = page
            return data, f"{why}; switching to the reference page was refused: {exc}"
        self._wait_settled()
        if self._get_page(MODE_ECU, deadline) != s.reference_page:
            return None, ""
        self._ecu_page = s.reference_page
        self.stats.restored_in_settle += 1
        return (
            self._read_page(s.reference_page, deadline),
            f"its working page {page} was in use and {why}: the bridge switched it to the reference page",
        )

    def read_active(self, timeout_s: float | None = None) -> ReadResult:
        """The calibration the ECU application uses: its page, read back and checked by the ECU's CRC-32."""
        self._fence()
        t0 = self._clock()
        deadline = t0 + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        for _ in range(self.config.max_attempts):
            try:
                self._session(deadline)
                page = self._get_page(MODE_ECU, deadline) if self.settings.pages else 0
                data = self._read_page(page, deadline)
                if (
                    self.settings.pages
                    and page != self.settings.reference_page
                    and self._get_page(MODE_ECU, deadline) != page
                ):
                    # XCP's access went back to the reference page with a SET_CAL_PAGE garbled into both modes
                    raise _MismatchError("XCP GET_CAL_PAGE: the page the ECU application uses changed while reading")
            except _RestartError:
                continue
            except _MismatchError:
                if self._clock() < deadline:
                    continue
                self.stats.reads_failed += 1
                raise
            except BridgeError:
                self.stats.reads_failed += 1
                raise
            values = self.layout.decode(data)
            self._ecu_page = page
            self._page_bytes[page] = data
            self.stats.reads_ok += 1
            self.last_confirmed = dict(values)
            raw, crc = self._raw_crc(values)
            note = ""
            if self.settings.pages:
                note = "reference page" if page == self.settings.reference_page else "working page"
            return ReadResult(values, raw, crc, self._clock() - t0, note)
        self.stats.reads_failed += 1
        raise EcuTimeoutError("XCP: the session was lost again and again while reading")

    def read_page(self, page: int | None = None, timeout_s: float | None = None) -> dict[str, float]:
        """The values one page holds (None: the reference page, or the only page): e.g. the flashed data set,
        the nominal and baseline of a definition written from the A2L."""
        self._fence()
        deadline = self._clock() + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        if page is None:
            page = self.settings.reference_page if self.settings.pages else 0
        for _ in range(self.config.max_attempts):
            try:
                self._session(deadline)
                data = self._read_page(page if self.settings.pages else None, deadline)
            except _RestartError:
                continue
            except _MismatchError:
                if self._clock() < deadline:
                    continue
                raise
            self._page_bytes[page] = data
            return self.layout.decode(data)
        raise EcuTimeoutError("XCP: the session was lost again and again while reading")

    def status(self, timeout_s: float | None = None) -> EcuStatus:
        """Which page the ECU application uses and the CRC-32 of its calibration (cheap when nothing changed)."""
        self._fence()
        t0 = self._clock()
        deadline = t0 + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        try:
            self._session(deadline)
            s = self.settings
            page = self._get_page(MODE_ECU, deadline) if s.pages else 0
            if s.pages and page == s.reference_page and self._reference is not None:
                # the flashed data set (read-only, read and checked once): XCP's access is not moved to it. Parking
                # it there after a failed apply would make the next apply send SET_CAL_PAGE(XCP, working) towards
                # the half-written working page, one flipped bit (mode 0x02 -> 0x03) from switching the
                # application onto it; the node asks this every diagnostics period
                values = self.layout.decode(self._reference)
                return EcuStatus(len(values), self._raw_crc(values)[1], self._clock() - t0)
            known = self._page_bytes.get(page)
            if known is not None:
                if s.pages:
                    # only to the page the application uses already (a working page the bridge has checked): a
                    # command garbled into a switch of the application changes nothing; confirmed, so that the
                    # CRC-32s below are this page's
                    self._move_xcp(page, deadline)
                same = all(self._holds(r, b, deadline) for r, b in known.items())
                if s.pages:
                    self._park(deadline, required=False)
                    same = same and self._get_page(MODE_ECU, deadline) == page
                if same:
                    values = self.layout.decode(known)
                    return EcuStatus(len(values), self._raw_crc(values)[1], self._clock() - t0)
        except _RestartError:
            raise EcuTimeoutError("XCP: the session was lost") from None
        rd = self.read_active(max(0.01, deadline - self._clock()))
        return EcuStatus(len(rd.values), rd.crc, self._clock() - t0)

    def restore_baseline(self, timeout_s: float | None = None) -> ApplyResult:
        """Put the safe baseline in force: a switch to the reference page (read back), else write the values."""
        if not self.settings.pages:
            return self.apply(self.definition.baseline_values(), timeout_s)
        s = self.settings
        self._fence()
        t0 = self._clock()
        deadline = t0 + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        last: BridgeError | None = None
        for attempt in range(1, self.config.max_attempts + 1):
            try:
                self._session(deadline)
                if self._get_page(MODE_ECU, deadline) != s.reference_page:
                    self._ecu_page = None
                    self._set_page(MODE_ECU, s.reference_page, deadline)
                self._wait_settled()
                if self._get_page(MODE_ECU, deadline) != s.reference_page:
                    raise _MismatchError("XCP GET_CAL_PAGE: the ECU does not use its reference page after the switch")
                data = self._read_page(s.reference_page, deadline)
            except _RestartError:
                continue
            except BridgeError as exc:
                last = exc
                if exc.code == ErrorCode.ECU_BUSY or isinstance(exc, BusError) or self._clock() >= deadline:
                    break
                continue
            self._ecu_page = s.reference_page
            self._page_bytes[s.reference_page] = data
            values = self.layout.decode(data)
            self.last_confirmed = dict(values)
            raw, crc = self._raw_crc(values)
            note = f"the ECU application switched to its reference page {s.reference_page}"
            if values != self._baseline:
                differ = [n for n in values if values[n] != self._baseline.get(n)]
                note += f"; it holds other values than the definition's baseline ({', '.join(differ[:6])})"
            return ApplyResult(values, raw, crc, attempt, self._clock() - t0, attempt, True, note)
        err = last or EcuTimeoutError("XCP: the session was lost while switching to the reference page")
        err.ecu_state = self.settle(None, self.last_confirmed)
        raise err


@dataclass
class _Attempt:
    touched: bool = False  # a command that changes what the ECU application uses was sent in this attempt
    in_doubt: bool = False  # ... and its outcome is not known yet


def _uncovered(run: Run) -> ProtocolConfigError:
    return ProtocolConfigError(
        f"XCP: the ECU's BUILD_CHECKSUM over 0x{run.address:X}+{run.size} differs, again and again, from the CRC-32 "
        "of the bytes UPLOAD reads there: its checksum does not cover that range of the page XCP accesses (a "
        "non-conforming XCP driver: its BUILD_CHECKSUM must use the MTA and block size it is given)"
    )


def _agreed(reads: list[bytes], piece: int = 7) -> bytes:
    """Piece by piece (an UPLOAD's 7 bytes), the bytes most reads agree on (the latest read on a tie)."""
    out = b""
    for k in range(0, len(reads[-1]), piece):
        seen = [r[k : k + piece] for r in reads]
        out += max(reversed(seen), key=seen.count)
    return out


def _span(data: bytes, run: Run, p: Any) -> bytes:
    return data[p.address - run.address : p.end - run.address]


def _empty(got: bytes) -> bool:
    return len(got) == 0


def _length(n: int) -> Callable[[bytes], bool]:
    return lambda got: len(got) == n


def _error_code(exc: BaseException) -> int:
    """The error code of pyxcp's XcpResponseError (a construct enum string, or a plain int when unknown)."""
    code = exc.args[0] if exc.args else -2
    return int(getattr(code, "intvalue", code))


def _error_name(error: int) -> str:
    """ERR_... for an XCP error code (the keys of pyxcp's error matrix)."""
    if error == -1:
        return "TIMEOUT"
    names: dict[int, str] = _pyxcp.load()["types"].XcpError.decmapping
    return str(names.get(error, f"0x{error:02X}"))


__all__ = [
    "AcknowledgeMismatchError",
    "EcuRejectedError",
    "XcpCalibrationClient",
    "XcpCommandError",
    "XcpConfig",
    "XcpSettings",
]
