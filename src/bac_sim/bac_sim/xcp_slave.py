"""A simulated XCP slave (ASAM MCD-1 XCP 1.x on CAN): command frames in, response frames out.

:class:`XcpSlave` holds what an ECU with an XCP driver holds for calibration: a
calibration memory segment (segment 0) with two pages, the **reference page** 0
(the flashed data set, read-only) and the **working page** 1 (RAM, initialized
from the reference page), the page the ECU application uses and the page XCP
accesses, the memory transfer address (MTA), the session and the resource
protection. It is written independently of the master (pyxcp), from the
standard: the bridge's tests prove pyxcp talks to it unchanged.

Commands (packet identifier = command code, classic CAN: at most 8 bytes):
CONNECT, DISCONNECT, GET_STATUS, SYNCH, GET_COMM_MODE_INFO, GET_SEED, UNLOCK,
SET_MTA, UPLOAD (slave block mode beyond 7 bytes), SHORT_UPLOAD,
BUILD_CHECKSUM (XCP_CRC_32), DOWNLOAD, DOWNLOAD_NEXT (master block mode),
SET_CAL_PAGE, GET_CAL_PAGE. Anything else: ERR_CMD_UNKNOWN. Before CONNECT
every command is ignored (no response), as the standard requires.

Negative responses (0xFE + error code): ERR_CMD_SYNCH to SYNCH; ERR_CMD_SYNTAX
for a malformed command; ERR_OUT_OF_RANGE for a length or address extension
it does not serve; ERR_ACCESS_DENIED outside the calibration segment;
ERR_WRITE_PROTECTED for a write to the reference page; ERR_ACCESS_LOCKED
while CAL/PAG is protected (seed & key) and not unlocked;
ERR_PAGE_NOT_VALID / ERR_SEGMENT_NOT_VALID / ERR_MODE_NOT_VALID for
SET/GET_CAL_PAGE; ERR_SEQUENCE for a block transfer or an UNLOCK out of
sequence; and, while the vehicle moves (:attr:`XcpSlave.driving`),
ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE (or the configured ``busy_error``) for any
change of the calibration the ECU uses: a page switch of the ECU application,
a DOWNLOAD into the page it runs on.
"""

from __future__ import annotations

import random
import struct
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from typing import ClassVar

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.xcp.layout import XcpLayout
from bac_ecu_bridge.xcp.seedkey import RESOURCE_CAL_PAG, KeyAlgorithm


class Cmd(IntEnum):
    CONNECT = 0xFF
    DISCONNECT = 0xFE
    GET_STATUS = 0xFD
    SYNCH = 0xFC
    GET_COMM_MODE_INFO = 0xFB
    GET_ID = 0xFA
    GET_SEED = 0xF8
    UNLOCK = 0xF7
    SET_MTA = 0xF6
    UPLOAD = 0xF5
    SHORT_UPLOAD = 0xF4
    BUILD_CHECKSUM = 0xF3
    DOWNLOAD = 0xF0
    DOWNLOAD_NEXT = 0xEF
    SET_CAL_PAGE = 0xEB
    GET_CAL_PAGE = 0xEA


class Err(IntEnum):
    CMD_SYNCH = 0x00
    CMD_BUSY = 0x10
    CMD_UNKNOWN = 0x20
    CMD_SYNTAX = 0x21
    OUT_OF_RANGE = 0x22
    WRITE_PROTECTED = 0x23
    ACCESS_DENIED = 0x24
    ACCESS_LOCKED = 0x25
    PAGE_NOT_VALID = 0x26
    MODE_NOT_VALID = 0x27
    SEGMENT_NOT_VALID = 0x28
    SEQUENCE = 0x29
    GENERIC = 0x31
    RESOURCE_TEMPORARY_NOT_ACCESSIBLE = 0x33


POSITIVE = 0xFF
NEGATIVE = 0xFE
MAX_CTO = 8
MAX_DTO = 8
CHECKSUM_XCP_CRC_32 = 0x09
MODE_ECU = 0x01
MODE_XCP = 0x02
MODE_ALL_SEGMENTS = 0x80
REFERENCE_PAGE = 0
WORKING_PAGE = 1
SEED_LENGTH = 4


@dataclass
class SlaveStats:
    commands: int = 0
    ignored: int = 0  # frames before CONNECT, empty frames
    negative: int = 0
    by_error: dict[str, int] = field(default_factory=dict)
    downloads: int = 0
    page_switches: int = 0  # SET_CAL_PAGE of the ECU application's page


@dataclass
class _Block:
    remaining: int  # bytes of the master block transfer still to come


class XcpSlave:
    """The XCP protocol state machine of the simulated ECU. Not thread-safe: the caller serializes ``handle``.

    ``pages`` false: one RAM page only (an ECU without page switching; SET_CAL_PAGE then knows page 0 only).
    ``key_algorithm``: protect CAL/PAG with seed & key. ``byte_order``: "MSB_LAST" (Intel) or "MSB_FIRST".
    ``max_bs``: master block mode (DOWNLOAD_NEXT) with blocks of up to this many frames; 0 = off.
    ``on_change``: called after every change of what the ECU application uses (a page switch, a write into
    its page), with no argument.
    """

    def __init__(
        self,
        definition: CalibrationDefinition,
        *,
        initial: Mapping[str, float] | None = None,
        pages: bool = True,
        key_algorithm: KeyAlgorithm | None = None,
        byte_order: str = "MSB_LAST",
        max_bs: int = 32,
        busy_error: int = Err.RESOURCE_TEMPORARY_NOT_ACCESSIBLE,
        refuse: Mapping[int, int] | None = None,
        on_change: Callable[[], None] | None = None,
        seed: int | None = None,
    ) -> None:
        self.layout = XcpLayout(definition)
        lo, hi = self.layout.span
        self.base = lo
        self.size = hi - lo
        if any(p.where.extension != 0 for p in self.layout.params):
            raise ValueError("the simulated XCP ECU serves address extension 0 only")
        start = dict(definition.baseline_values())
        reference = bytearray(self.size)
        for run, data in self.layout.image(start).items():
            reference[run.address - lo : run.address - lo + len(data)] = data
        self.has_pages = pages
        self.pages: list[bytearray] = [reference, bytearray(reference)] if pages else [reference]
        self.ecu_page = WORKING_PAGE if pages else 0
        self.xcp_page = self.ecu_page
        if initial is not None:  # the working page holds these (e.g. a trial left behind by a killed campaign)
            values = {**start, **dict(initial)}
            for run, data in self.layout.image(values).items():
                self.pages[self.ecu_page][run.address - lo : run.address - lo + len(data)] = data
        self.key_algorithm = key_algorithm
        self.intel = byte_order == "MSB_LAST"
        self.max_bs = max_bs
        self.busy_error = int(busy_error)
        self.refuse = {int(k): int(v) for k, v in (refuse or {}).items()}
        self.on_change = on_change
        self.driving = False
        self.stats = SlaveStats()
        self.connected = False
        self.mta = 0
        self.mta_ext = 0
        self.protected = RESOURCE_CAL_PAG if key_algorithm is not None else 0
        self._seed: bytes | None = None
        self._seed_resource = 0
        self._block: _Block | None = None
        self._rng = random.Random(seed)

    # --- what the vehicle model reads -----------------------------------------------------------------
    def ecu_bytes(self, address: int, size: int) -> bytes:
        start = address - self.base
        return bytes(self.pages[self.ecu_page][start : start + size])

    def active_values(self) -> dict[str, float]:
        """The calibration the ECU application uses (its page), by name."""
        page = self.pages[self.ecu_page]
        return self.layout.decode(
            {run: bytes(page[run.address - self.base : run.address - self.base + run.size]) for run in self.layout.runs}
        )

    def page_values(self, page: int) -> dict[str, float]:
        data = self.pages[page]
        return self.layout.decode(
            {run: bytes(data[run.address - self.base : run.address - self.base + run.size]) for run in self.layout.runs}
        )

    def reset(self) -> None:
        """A power cycle: the working page is loaded from the reference page again, no session."""
        if self.has_pages:
            self.pages[WORKING_PAGE][:] = self.pages[REFERENCE_PAGE]
            self.ecu_page = self.xcp_page = WORKING_PAGE
        self.connected = False
        self.protected = RESOURCE_CAL_PAG if self.key_algorithm is not None else 0
        self._block = None
        self._changed()

    # --- packing ------------------------------------------------------------------------------------------
    def _word(self, v: int) -> bytes:
        return struct.pack("<H" if self.intel else ">H", v)

    def _dword(self, v: int) -> bytes:
        return struct.pack("<I" if self.intel else ">I", v)

    def _undword(self, b: bytes) -> int:
        return int(struct.unpack("<I" if self.intel else ">I", b)[0])

    def _err(self, code: int, *extra: int) -> list[bytes]:
        self.stats.negative += 1
        try:
            name = Err(code).name
        except ValueError:
            name = f"0x{code:02X}"
        self.stats.by_error[name] = self.stats.by_error.get(name, 0) + 1
        return [bytes((NEGATIVE, code, *extra))]

    def _ok(self, payload: bytes = b"") -> list[bytes]:
        return [bytes((POSITIVE,)) + payload]

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change()

    # --- memory --------------------------------------------------------------------------------------------
    def _access(self, address: int, ext: int, size: int) -> int | None:
        """The offset in the segment, or None when [address, address + size) is not all in it."""
        if ext != 0:
            return None
        start = address - self.base
        if start < 0 or start + size > self.size:
            return None
        return start

    def _write(self, data: bytes) -> list[bytes] | None:
        """Write at the MTA (post-increment); a negative response, or None when written."""
        start = self._access(self.mta, self.mta_ext, len(data))
        if start is None:
            return self._err(Err.ACCESS_DENIED)
        if self.has_pages and self.xcp_page == REFERENCE_PAGE:
            return self._err(Err.WRITE_PROTECTED)
        touches_ecu = self.xcp_page == self.ecu_page
        if touches_ecu and self.driving:
            return self._err(self.busy_error)
        page = self.pages[self.xcp_page]
        if bytes(page[start : start + len(data)]) != data:
            page[start : start + len(data)] = data
            if touches_ecu:
                self._changed()
        self.mta += len(data)
        self.stats.downloads += 1
        return None

    def _read(self, address: int, ext: int, size: int) -> bytes | None:
        start = self._access(address, ext, size)
        if start is None:
            return None
        return bytes(self.pages[self.xcp_page][start : start + size])

    # --- frames ------------------------------------------------------------------------------------------------
    def handle(self, frame: bytes | bytearray) -> list[bytes]:
        """One command frame (CAN data bytes, padding allowed) -> the response frames (none before CONNECT)."""
        data = bytes(frame)
        if not data:
            self.stats.ignored += 1
            return []
        pid = data[0]
        if not self.connected and pid != Cmd.CONNECT:
            self.stats.ignored += 1
            return []
        self.stats.commands += 1
        if pid in self.refuse:
            return self._err(self.refuse[pid])
        if self._block is not None and pid not in (Cmd.DOWNLOAD_NEXT, Cmd.SYNCH):
            self._block = None  # another command ends an unfinished block transfer
        handler = self._HANDLERS.get(pid)
        if handler is None:
            return self._err(Err.CMD_UNKNOWN)
        try:
            return handler(self, data)
        except (IndexError, struct.error):
            return self._err(Err.CMD_SYNTAX)

    def _connect(self, d: bytes) -> list[bytes]:
        if d[1] not in (0x00, 0x01):
            return self._err(Err.OUT_OF_RANGE)
        if not self.connected:
            self.connected = True
            self.protected = RESOURCE_CAL_PAG if self.key_algorithm is not None else 0
            self._seed = None
            self._block = None
        resource = RESOURCE_CAL_PAG  # CAL/PAG only: no DAQ, STIM or PGM
        comm_mode_basic = (0x00 if self.intel else 0x01) | 0x40 | 0x80  # byte granularity, slave block, optional
        return self._ok(bytes((resource, comm_mode_basic, MAX_CTO)) + self._word(MAX_DTO) + bytes((0x01, 0x01)))

    def _disconnect(self, d: bytes) -> list[bytes]:
        self.connected = False
        self.protected = RESOURCE_CAL_PAG if self.key_algorithm is not None else 0
        self._seed = None
        self._block = None
        return self._ok()

    def _get_status(self, d: bytes) -> list[bytes]:
        session_status = 0x00
        return self._ok(bytes((session_status, self.protected, 0x00)) + self._word(0))

    def _synch(self, d: bytes) -> list[bytes]:
        self._block = None
        return self._err(Err.CMD_SYNCH)

    def _get_comm_mode_info(self, d: bytes) -> list[bytes]:
        optional = 0x01 if self.max_bs > 0 else 0x00  # MASTER_BLOCK_MODE
        return self._ok(bytes((0x00, optional, 0x00, self.max_bs, 0x00, 0x00, 0x10)))

    def _get_seed(self, d: bytes) -> list[bytes]:
        mode, resource = d[1], d[2]
        if mode != 0x00:
            return self._err(Err.OUT_OF_RANGE)  # the seed always fits one frame here
        if resource not in (0x01, 0x04, 0x08, 0x10):
            return self._err(Err.OUT_OF_RANGE)
        if not self.protected & resource:
            self._seed = None
            return self._ok(bytes((0x00,)))  # not protected: seed length 0
        self._seed = bytes(self._rng.randrange(256) for _ in range(SEED_LENGTH))
        self._seed_resource = resource
        return self._ok(bytes((len(self._seed),)) + self._seed)

    def _unlock(self, d: bytes) -> list[bytes]:
        length = d[1]
        if self._seed is None or self.key_algorithm is None:
            return self._err(Err.SEQUENCE)
        if length > MAX_CTO - 2:
            return self._err(Err.OUT_OF_RANGE)
        key = d[2 : 2 + length]
        expected = self.key_algorithm(self._seed_resource, self._seed)
        self._seed = None
        if key != expected:
            self.connected = False  # a wrong key ends the session (the standard)
            return self._err(Err.ACCESS_LOCKED)
        self.protected &= ~self._seed_resource
        return self._ok(bytes((self.protected,)))

    def _set_mta(self, d: bytes) -> list[bytes]:
        if len(d) < 8:
            return self._err(Err.CMD_SYNTAX)
        self.mta_ext = d[3]
        self.mta = self._undword(d[4:8])
        self._block = None
        return self._ok()

    def _upload(self, d: bytes) -> list[bytes]:
        n = d[1]
        if n == 0:
            return self._err(Err.OUT_OF_RANGE)
        got = self._read(self.mta, self.mta_ext, n)
        if got is None:
            return self._err(Err.ACCESS_DENIED)
        self.mta += n
        if n <= MAX_CTO - 1:
            return self._ok(got)
        # slave block mode: the first frame carries 7 bytes after the PID, then further frames of 7
        return [bytes((POSITIVE,)) + got[k : k + MAX_CTO - 1] for k in range(0, n, MAX_CTO - 1)]

    def _short_upload(self, d: bytes) -> list[bytes]:
        if len(d) < 8:
            return self._err(Err.CMD_SYNTAX)
        n, ext, address = d[1], d[3], self._undword(d[4:8])
        if not 1 <= n <= MAX_CTO - 1:
            return self._err(Err.OUT_OF_RANGE)
        got = self._read(address, ext, n)
        if got is None:
            return self._err(Err.ACCESS_DENIED)
        self.mta, self.mta_ext = address + n, ext
        return self._ok(got)

    def _build_checksum(self, d: bytes) -> list[bytes]:
        if len(d) < 8:
            return self._err(Err.CMD_SYNTAX)
        size = self._undword(d[4:8])
        got = self._read(self.mta, self.mta_ext, size) if size else None
        if got is None:
            return self._err(Err.ACCESS_DENIED)
        self.mta += size
        crc = zlib.crc32(got) & 0xFFFF_FFFF
        return self._ok(bytes((CHECKSUM_XCP_CRC_32, 0x00, 0x00)) + self._dword(crc))

    def _locked(self) -> list[bytes] | None:
        return self._err(Err.ACCESS_LOCKED) if self.protected & RESOURCE_CAL_PAG else None

    def _download(self, d: bytes) -> list[bytes]:
        locked = self._locked()
        if locked:
            return locked
        n = d[1]
        if n == 0:
            return self._err(Err.OUT_OF_RANGE)
        first = min(n, MAX_CTO - 2)
        if len(d) < 2 + first:
            return self._err(Err.CMD_SYNTAX)
        if n > MAX_CTO - 2:
            if self.max_bs == 0 or n > self.max_bs * (MAX_CTO - 2):
                return self._err(Err.OUT_OF_RANGE)
            refused = self._write(d[2 : 2 + first])
            if refused:
                return refused
            self._block = _Block(n - first)
            return []  # block mode: the response comes after the last DOWNLOAD_NEXT
        refused = self._write(d[2 : 2 + n])
        return refused or self._ok()

    def _download_next(self, d: bytes) -> list[bytes]:
        locked = self._locked()
        if locked:
            return locked
        block = self._block
        n = d[1]
        if block is None or n != block.remaining:
            expected = block.remaining if block is not None else 0
            self._block = None
            return self._err(Err.SEQUENCE, min(expected, 0xFF))
        part = min(n, MAX_CTO - 2)
        if len(d) < 2 + part:
            self._block = None
            return self._err(Err.CMD_SYNTAX)
        refused = self._write(d[2 : 2 + part])
        if refused:
            self._block = None
            return refused
        block.remaining -= part
        if block.remaining > 0:
            return []
        self._block = None
        return self._ok()

    def _set_cal_page(self, d: bytes) -> list[bytes]:
        locked = self._locked()
        if locked:
            return locked
        mode, segment, page = d[1], d[2], d[3]
        if mode & ~(MODE_ECU | MODE_XCP | MODE_ALL_SEGMENTS) or not mode & (MODE_ECU | MODE_XCP):
            return self._err(Err.MODE_NOT_VALID)
        if not mode & MODE_ALL_SEGMENTS and segment != 0:
            return self._err(Err.SEGMENT_NOT_VALID)
        if page >= len(self.pages):
            return self._err(Err.PAGE_NOT_VALID)
        if mode & MODE_ECU and page != self.ecu_page:
            if self.driving:
                return self._err(self.busy_error)
            self.ecu_page = page
            self.stats.page_switches += 1
            self._changed()
        if mode & MODE_XCP:
            self.xcp_page = page
        return self._ok()

    def _get_cal_page(self, d: bytes) -> list[bytes]:
        mode, segment = d[1], d[2]
        if mode not in (MODE_ECU, MODE_XCP):
            return self._err(Err.MODE_NOT_VALID)
        if segment != 0:
            return self._err(Err.SEGMENT_NOT_VALID)
        page = self.ecu_page if mode == MODE_ECU else self.xcp_page
        return self._ok(bytes((0x00, 0x00, page)))

    _HANDLERS: ClassVar[dict[int, Callable[[XcpSlave, bytes], list[bytes]]]] = {
        Cmd.CONNECT: _connect,
        Cmd.DISCONNECT: _disconnect,
        Cmd.GET_STATUS: _get_status,
        Cmd.SYNCH: _synch,
        Cmd.GET_COMM_MODE_INFO: _get_comm_mode_info,
        Cmd.GET_SEED: _get_seed,
        Cmd.UNLOCK: _unlock,
        Cmd.SET_MTA: _set_mta,
        Cmd.UPLOAD: _upload,
        Cmd.SHORT_UPLOAD: _short_upload,
        Cmd.BUILD_CHECKSUM: _build_checksum,
        Cmd.DOWNLOAD: _download,
        Cmd.DOWNLOAD_NEXT: _download_next,
        Cmd.SET_CAL_PAGE: _set_cal_page,
        Cmd.GET_CAL_PAGE: _get_cal_page,
    }
