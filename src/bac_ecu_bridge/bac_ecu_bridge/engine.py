"""The ECU side of the calibration protocol, as a pure engine: request bytes in, response bytes out.

:class:`EcuEngine` holds what an ECU holds: the active calibration table (raw
values by index), a staging area for one transaction, the recent transaction
sequence numbers and whether the vehicle is moving. ``bac_sim.ecu`` serves it
on a CAN bus; tests drive it directly. See :mod:`bac_ecu_bridge.protocol` and
docs/ecu_bridge.md for the frames.

Rules:

* BEGIN(seq, count) opens a transaction; refused with BUSY while driving, with
  SEQUENCE when ``seq`` was used by one of the last :data:`SEQ_HISTORY`
  transactions (a stale or duplicated BEGIN never reopens an old transaction;
  the NACK's detail is then a sequence number the ECU accepts),
  and answered again (idempotent) when it repeats the open transaction's BEGIN.
* WRITE(seq, index, raw) stages a value of the open transaction; SEQUENCE for
  another transaction, UNKNOWN_PARAMETER / OUT_OF_RANGE for a bad index / raw
  value, COUNT_MISMATCH for more distinct indices than announced. STAGED echoes
  what was staged.
* COMMIT(seq, count, crc) applies the staged set atomically when the count and
  the set CRC match (else COUNT_MISMATCH / CRC_MISMATCH, nothing applied) and
  the vehicle stands still (else BUSY); ACK carries the count and the CRC of
  the *active* values at the committed indices. A repeated COMMIT of the last
  committed transaction is answered with the ACK again (its ACK may have been
  lost); anything else is SEQUENCE.
* READ(seq, index) answers VALUE with the active raw value; STATUS answers the
  table size and the CRC of the whole active table.
* ABORT(seq) drops whatever is staged (any transaction) and answers ABORTED
  with the number of values dropped; a staged set is also dropped when no
  frame of its transaction came for ``staging_timeout_s``
  (:data:`~bac_ecu_bridge.protocol.STAGING_TIMEOUT_S`). A COMMIT of a dropped
  set is refused (SEQUENCE): a late COMMIT can never apply values the bridge
  has given up on.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.errors import FrameError
from bac_ecu_bridge.protocol import (
    DETAIL_NONE,
    SEQ_MODULO,
    STAGING_TIMEOUT_S,
    Abort,
    Aborted,
    Ack,
    Begin,
    BeginOk,
    CalibrationCodec,
    Commit,
    Nack,
    Op,
    Read,
    Reason,
    Request,
    Staged,
    StatusOk,
    StatusRequest,
    Value,
    Write,
    decode_request,
    encode,
    set_crc,
)

SEQ_HISTORY = 32  # BEGINs with a sequence number among the last 32 transactions are stale


@dataclass
class EngineStats:
    requests: int = 0
    invalid_frames: int = 0
    nacks: int = 0
    commits: int = 0
    aborts: int = 0  # ABORT requests that dropped a staged set
    staging_expired: int = 0  # staged sets dropped after staging_timeout_s without a frame of their transaction
    by_reason: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class CommitEvent:
    """A committed transaction."""

    seq: int
    raw: dict[int, int]  # the committed (index -> raw) set
    crc: int


class EcuEngine:
    """The protocol state machine of the ECU. Not thread-safe: callers serialize ``handle``."""

    def __init__(
        self,
        definition: CalibrationDefinition,
        *,
        initial: Mapping[str, float] | None = None,
        on_commit: Callable[[CommitEvent], None] | None = None,
        refuse: Mapping[int, int] | None = None,
        staging_timeout_s: float = STAGING_TIMEOUT_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``refuse`` maps request opcodes to a :class:`Reason`: the ECU refuses them with it, touching
        nothing (a refusing ECU, for tests). A staged set is dropped ``staging_timeout_s`` after the last
        frame of its transaction (``clock``)."""
        if not staging_timeout_s > 0:
            raise ValueError("staging_timeout_s must be > 0")
        self.staging_timeout_s = float(staging_timeout_s)
        self._clock = clock
        self._staging_touched = 0.0
        self.codec = CalibrationCodec(definition)
        start = dict(definition.baseline_values())
        if initial is not None:
            start.update(initial)
        self._baseline = self.codec.encode_set(start)
        self.active: dict[int, int] = dict(self._baseline)
        self.driving = False
        self.on_commit = on_commit
        self.refuse = {int(k): int(v) for k, v in (refuse or {}).items()}
        self.stats = EngineStats()
        self._staging_seq: int | None = None
        self._staging_count = 0
        self._staged: dict[int, int] = {}
        self._history: deque[int] = deque(maxlen=SEQ_HISTORY)
        self._last_commit: CommitEvent | None = None

    # --- state --------------------------------------------------------------------------------
    def active_values(self) -> dict[str, float]:
        return self.codec.decode_set(self.active)

    def active_crc(self) -> int:
        return set_crc(self.active)

    @property
    def last_commit(self) -> CommitEvent | None:
        return self._last_commit

    @property
    def staging_seq(self) -> int | None:
        """The open transaction's number (None when nothing is staged)."""
        self._expire()
        return self._staging_seq

    def _drop_staging(self) -> int:
        dropped = len(self._staged)
        self._staging_seq = None
        self._staging_count = 0
        self._staged = {}
        return dropped

    def _expire(self) -> None:
        if self._staging_seq is not None and self._clock() - self._staging_touched > self.staging_timeout_s:
            self._drop_staging()
            self.stats.staging_expired += 1

    def reset(self) -> None:
        """A power cycle: the baseline is active again, no transaction is remembered."""
        self.active = dict(self._baseline)
        self._drop_staging()
        self._history.clear()
        self._last_commit = None

    # --- frames ----------------------------------------------------------------------------------
    def handle(self, data: bytes | bytearray) -> list[bytes]:
        """Process one request frame's data bytes; return the response frames' data bytes."""
        try:
            req = decode_request(data)
        except FrameError:
            self.stats.invalid_frames += 1
            return []
        self.stats.requests += 1
        resp = self._handle(req)
        if isinstance(resp, Nack):
            self.stats.nacks += 1
            name = Reason(resp.reason).name
            self.stats.by_reason[name] = self.stats.by_reason.get(name, 0) + 1
        return [encode(resp)]

    def _nack(self, req: Request, reason: Reason, index: int = 0, detail: int = DETAIL_NONE) -> Nack:
        return Nack(req.seq, int(req.op), int(reason), index, detail)

    def _recent_seq(self) -> int:
        return self._history[-1] if self._history else DETAIL_NONE

    def _free_seq(self) -> int:
        """The first sequence number after the most recent one that no remembered transaction used."""
        start = self._history[-1] if self._history else 0
        for step in range(1, SEQ_MODULO + 1):
            seq = (start + step) % SEQ_MODULO
            if seq not in self._history:
                return seq
        return DETAIL_NONE  # unreachable: the history holds fewer than 256 numbers

    def _handle(self, req: Request) -> BeginOk | Staged | Ack | Value | StatusOk | Aborted | Nack:
        self._expire()
        if int(req.op) in self.refuse:
            return self._nack(req, Reason(self.refuse[int(req.op)]), getattr(req, "index", 0))
        if isinstance(req, Abort):
            dropped = self._drop_staging()
            self.stats.aborts += 1 if dropped else 0
            return Aborted(req.seq, dropped)
        if isinstance(req, Begin):
            return self._begin(req)
        if isinstance(req, Write):
            return self._write(req)
        if isinstance(req, Commit):
            return self._commit(req)
        if isinstance(req, Read):
            if req.index not in self.codec.by_index:
                return self._nack(req, Reason.UNKNOWN_PARAMETER, req.index)
            return Value(req.seq, req.index, self.active[req.index])
        assert isinstance(req, StatusRequest)
        return StatusOk(req.seq, len(self.active), set_crc(self.active))

    def _begin(self, req: Begin) -> BeginOk | Nack:
        if self.driving:
            return self._nack(req, Reason.BUSY)
        if req.seq == self._staging_seq:
            if req.count != self._staging_count:
                # never name the refused number itself: a bridge resynchronizing onto it would be refused again
                return self._nack(req, Reason.SEQUENCE, detail=self._free_seq())
            self._staging_touched = self._clock()
            return BeginOk(req.seq, req.count)
        if req.seq in self._history:
            # the detail names a sequence number this ECU accepts next, so a bridge can resynchronize
            return self._nack(req, Reason.SEQUENCE, detail=self._free_seq())
        if not 1 <= req.count <= len(self.codec.params):
            return self._nack(req, Reason.COUNT_MISMATCH, detail=len(self.codec.params))
        self._staging_seq = req.seq
        self._staging_count = req.count
        self._staged = {}
        self._staging_touched = self._clock()
        self._history.append(req.seq)
        return BeginOk(req.seq, req.count)

    def _write(self, req: Write) -> Staged | Nack:
        if req.seq != self._staging_seq:
            recent = self._staging_seq if self._staging_seq is not None else DETAIL_NONE
            return self._nack(req, Reason.SEQUENCE, req.index, recent)
        p = self.codec.by_index.get(req.index)
        if p is None:
            return self._nack(req, Reason.UNKNOWN_PARAMETER, req.index)
        if req.raw > p.max_raw:
            # the low 16 bits of the refused value let the bridge tell a real refusal from a garbled write
            return self._nack(req, Reason.OUT_OF_RANGE, req.index, req.raw & 0xFFFF)
        if req.index not in self._staged and len(self._staged) >= self._staging_count:
            return self._nack(req, Reason.COUNT_MISMATCH, req.index, len(self._staged))
        self._staged[req.index] = req.raw
        self._staging_touched = self._clock()
        return Staged(req.seq, req.index, req.raw)

    def _commit(self, req: Commit) -> Ack | Nack:
        last = self._last_commit
        if req.seq != self._staging_seq:
            if last is not None and last.seq == req.seq and last.crc == req.crc and len(last.raw) == req.count:
                # the ACK of the last commit was lost: answer again with the truth about the active values
                return Ack(req.seq, req.count, set_crc({i: self.active[i] for i in last.raw}))
            recent = self._staging_seq if self._staging_seq is not None else self._recent_seq()
            return self._nack(req, Reason.SEQUENCE, detail=recent)
        if self.driving:
            return self._nack(req, Reason.BUSY)
        if req.count != self._staging_count or len(self._staged) != req.count:
            return self._nack(req, Reason.COUNT_MISMATCH, detail=len(self._staged))
        staged_crc = set_crc(self._staged)
        if staged_crc != req.crc:
            return self._nack(req, Reason.CRC_MISMATCH, detail=staged_crc & 0xFFFF)
        committed = dict(self._staged)
        table = dict(self.active)
        table.update(committed)
        self.active = table  # atomic: one reference swap
        self._drop_staging()
        event = CommitEvent(req.seq, committed, set_crc({i: table[i] for i in committed}))
        self._last_commit = event
        self.stats.commits += 1
        if self.on_commit is not None:
            self.on_commit(event)
        return Ack(req.seq, req.count, event.crc)


__all__ = ["SEQ_HISTORY", "CommitEvent", "EcuEngine", "EngineStats", "Op"]
