"""The bridge side of the calibration protocol: a bounded, verified apply transaction over a python-can bus.

:class:`CalibrationClient` writes a calibration set to the ECU and returns only
when the ECU acknowledged exactly those values (after quantization) for this
transaction, or raises a :class:`~bac_ecu_bridge.errors.BridgeError` whose
``code`` says why. One apply is::

    BEGIN(seq, n) -> BEGIN_OK                      the ECU opens transaction seq (refuses while driving)
    WRITE(seq, i, raw) -> STAGED(seq, i, raw)      each parameter, pipelined (selective repeat, a window)
    COMMIT(seq, n, crc32) -> ACK(seq, n, crc32)    atomic; the ECU checks count and CRC of what it staged
    READ(seq, i) -> VALUE(seq, i, raw)             read-back of the active values (``verify_readback``)

* A reply counts only with the current sequence number, the expected opcode,
  index, raw value, count and CRC; anything else (a stale or duplicated reply
  of an earlier transaction, a garbled frame) is counted and ignored.
* Each request waits ``step_timeout_s`` for its reply and is sent again at most
  ``step_retries`` times; a failed transaction is retried with a new sequence
  number up to ``max_attempts`` times; the whole apply never takes longer than
  its ``timeout_s``.
* Negative responses that retrying cannot fix (out of range, unknown
  parameter, busy) end the apply at once.
* Values outside the declared bounds are refused before anything is sent.
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar

import can

from bac_ecu_bridge.backend import ApplyResult, EcuState, EcuStatus, Holds, ReadResult, classify
from bac_ecu_bridge.errors import (
    AcknowledgeMismatchError,
    BridgeError,
    BusError,
    EcuRejectedError,
    EcuTimeoutError,
    ErrorCode,
    FrameError,
    InvalidRequestError,
)
from bac_ecu_bridge.protocol import (
    STAGING_TIMEOUT_S,
    Abort,
    Aborted,
    Ack,
    Begin,
    BeginOk,
    CalibrationCodec,
    CanIds,
    Commit,
    Nack,
    Op,
    Read,
    Reason,
    Request,
    Response,
    Staged,
    StatusOk,
    StatusRequest,
    Value,
    Write,
    decode_response,
    encode,
    reason_text,
    seq_next,
    set_crc,
)

K = TypeVar("K")

_DRAIN_LIMIT = 10_000
SETTLE_STEP_RETRIES = 10  # re-sends of one request while settling the ECU's state after an uncertain apply


@dataclass(frozen=True)
class ClientConfig:
    step_timeout_s: float = 0.025  # wait for one reply (XCP's T1 is 25 ms)
    step_retries: int = 5  # re-sends of one request before the transaction fails
    max_attempts: int = 3  # transactions (new sequence number each) per apply
    timeout_s: float = 3.0  # default overall time limit of an apply / read
    window: int = 16  # requests in flight at once
    verify_readback: bool = True  # read the active values back after the ACK
    staging_timeout_s: float = STAGING_TIMEOUT_S  # the ECU drops a staged set this long after its last frame
    settle_timeout_s: float = 3.0  # after an uncertain apply: ABORT, then read the ECU back within this

    def __post_init__(self) -> None:
        if not self.step_timeout_s > 0:
            raise ValueError("step_timeout_s must be > 0")
        if self.step_retries < 0 or self.max_attempts < 1 or self.window < 1:
            raise ValueError("step_retries >= 0, max_attempts >= 1 and window >= 1 are required")
        if not self.timeout_s > 0:
            raise ValueError("timeout_s must be > 0")


@dataclass
class ClientStats:
    frames_sent: int = 0
    frames_received: int = 0
    foreign_frames: int = 0  # other CAN ids (when the interface cannot filter)
    invalid_frames: int = 0  # garbled: wrong length, CRC-8, opcode
    stale_frames: int = 0  # another sequence number: an earlier transaction's replies
    unexpected_frames: int = 0  # right sequence number, wrong content (counted, ignored)
    retransmissions: int = 0
    step_timeouts: int = 0
    nacks: int = 0
    transactions: int = 0
    applies_ok: int = 0
    applies_failed: int = 0
    reads_ok: int = 0
    reads_failed: int = 0
    settled: int = 0  # uncertain applies settled by reading the ECU back
    nack_reasons: dict[str, int] = field(default_factory=dict)


class _RetryableError(BridgeError):
    """A transaction failed in a way a new transaction may fix."""

    def __init__(self, error: BridgeError, resync_seq: int | None = None) -> None:
        super().__init__(str(error))
        self.error = error
        self.resync_seq = resync_seq


class _Resend:
    """Returned by a matcher: the reply was for this key but wrong; send the request again."""

    def __init__(self, problem: BridgeError) -> None:
        self.problem = problem


class CalibrationClient:
    """Apply, read and check calibrations over one CAN bus. Not thread-safe: serialize the calls."""

    def __init__(
        self,
        bus: can.BusABC,
        codec: CalibrationCodec,
        ids: CanIds | None = None,
        config: ClientConfig | None = None,
        *,
        seq: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ) -> None:
        self.bus = bus
        self.codec = codec
        self.ids = ids or CanIds()
        self.config = config or ClientConfig()
        self.stats = ClientStats()
        self._seq = random.randrange(256) if seq is None else seq % 256
        self._clock = clock
        self._log = logger or logging.getLogger("bac_ecu_bridge.client")
        self._refused: set[int] = set()  # sequence numbers whose BEGIN the ECU refused during this apply
        self._last_staging_frame = -1e9  # when a BEGIN or WRITE was last sent (restarts the ECU's staging timeout)
        # the last calibration the ECU confirmed (an apply, a read-back), by name: "previous" after a failure
        self.last_confirmed: dict[str, float] | None = None
        self._baseline = self.codec.quantize(self.codec.definition.baseline_values())

    protocol = "bac"

    def quantize(self, values: Mapping[str, float]) -> dict[str, float]:
        return self.codec.quantize(values)

    def counters(self) -> dict[str, int]:
        s = self.stats
        return {
            "applies_ok": s.applies_ok,
            "applies_failed": s.applies_failed,
            "frames_sent": s.frames_sent,
            "frames_received": s.frames_received,
            "invalid_frames": s.invalid_frames,
            "stale_frames": s.stale_frames,
            "retransmissions": s.retransmissions,
            "step_timeouts": s.step_timeouts,
            "nacks": s.nacks,
            "settled": s.settled,
        }

    def close(self) -> None:
        """Nothing to release: the bus belongs to the caller."""

    def restore_baseline(self, timeout_s: float | None = None) -> ApplyResult:
        """Write the definition's safe baseline values."""
        return self.apply(self.codec.definition.baseline_values(), timeout_s)

    # --- public API -----------------------------------------------------------------------------
    @property
    def seq(self) -> int:
        """The sequence number of the last transaction."""
        return self._seq

    def apply(self, values: Mapping[str, float], timeout_s: float | None = None) -> ApplyResult:
        """Write ``values`` (raw parameters by name) and wait for the ECU's confirmation.

        Raises :class:`OutOfBoundsError` / :class:`UnknownParameterError` before
        sending anything, else a :class:`BridgeError` with its ``code``.
        """
        if not values:
            raise InvalidRequestError("nothing to apply: the calibration is empty")
        raw = self.codec.encode_set(values)  # refuses unknown names and values outside the bounds
        t0 = self._clock()
        deadline = t0 + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        self._refused = set()
        previous = self.last_confirmed
        try:
            result = self._apply(raw, deadline, t0)
        except BridgeError as err:
            if not err.uncertain:
                # no commit of this apply is undecided: refused, or never sent; the ECU kept what it held
                err.ecu_state = EcuState(
                    Holds.PREVIOUS,
                    previous,
                    None if previous is None else self.codec.crc(previous),
                    detail="no commit of this apply took effect",
                )
                raise
            state = self.settle(self.codec.decode_set(raw), previous)
            err.ecu_state = state
            if state.holds is not Holds.REQUESTED or state.values is None:
                raise
            # the commit went through and only its answer was lost: the read-back confirmed every value
            self.stats.applies_failed -= 1
            self.stats.applies_ok += 1
            self.last_confirmed = dict(state.values)
            echoed = self.codec.encode_set(state.values)
            return ApplyResult(
                dict(state.values),
                dict(sorted(echoed.items())),
                set_crc(echoed),
                err.attempts,
                self._clock() - t0,
                self._seq,
                True,
                note=f"the commit's answer was lost ({err}); the ECU was read back and holds the request",
            )
        self.last_confirmed = dict(result.values)
        return result

    def settle(self, requested: Mapping[str, float] | None, previous: Mapping[str, float] | None = None) -> EcuState:
        """After an apply whose commit went unanswered: make sure nothing staged can still be committed, then
        read the ECU back and say which set it holds.

        An ABORT drops whatever the ECU has staged, so that no COMMIT arriving late (delayed on the way, or a
        retransmission) can apply it afterwards; if the ABORT is not confirmed, the ECU's own staging timeout
        is waited out. Bounded by ``settle_timeout_s``.
        """
        t0 = self._clock()
        deadline = t0 + self.config.settle_timeout_s
        self.stats.settled += 1
        aborted = False
        normal = self.config
        # settling is the way back to a known state: it may retry more than an apply, within its own bound
        self.config = replace(normal, step_retries=max(normal.step_retries, SETTLE_STEP_RETRIES))
        try:
            while not aborted and self._clock() < t0 + self.config.settle_timeout_s / 2:
                seq = self._new_seq()
                self._drain()
                try:
                    got = self._exchange(
                        "ABORT",
                        seq,
                        {0: Abort(seq)},
                        lambda resp: (0, resp) if isinstance(resp, Aborted) else None,
                        t0 + self.config.settle_timeout_s / 2,
                    )
                    aborted = 0 in got
                except BusError as exc:
                    self.last_confirmed = None
                    return EcuState(Holds.UNKNOWN, detail=f"the bus failed while settling: {exc}")
                except (_RetryableError, BridgeError):
                    continue
            if not aborted:
                # the ECU drops a staged set staging_timeout_s after the last frame of its transaction arrived; a
                # frame delayed on the way may arrive up to as late again
                until = self._last_staging_frame + 2 * self.config.staging_timeout_s
                wait = min(until, deadline) - self._clock()
                if wait > 0:
                    time.sleep(wait)
            problem = "no time left"
            while self._clock() < deadline:
                try:
                    rd = self.read_active(max(0.01, deadline - self._clock()))
                except BusError as exc:
                    problem = str(exc)
                    break
                except BridgeError as exc:
                    problem = str(exc)
                    continue
                holds = classify(rd.values, requested, previous, self._baseline)
                how = "staged set aborted" if aborted else "ABORT unanswered: the ECU's staging timeout waited out"
                return EcuState(holds, rd.values, rd.crc, True, how)
            self.last_confirmed = None
            return EcuState(Holds.UNKNOWN, detail=f"reading the ECU back failed: {problem}")
        finally:
            self.config = normal

    def _apply(self, raw: dict[int, int], deadline: float, t0: float) -> ApplyResult:
        attempts = 0
        uncertain = False
        last: BridgeError | None = None
        try:
            while attempts < self.config.max_attempts and self._clock() < deadline:
                attempts += 1
                seq = self._new_seq()
                state = _TxState()
                try:
                    result = self._transaction(seq, raw, deadline, state, attempts, t0)
                except EcuTimeoutError as e:  # the overall deadline
                    uncertain |= state.commit_undecided
                    last = e
                    break
                except _RetryableError as r:
                    uncertain |= state.commit_undecided
                    last = r.error
                    if r.resync_seq is not None:
                        self._seq = r.resync_seq
                    self._log.debug("apply attempt %d (seq %d) failed: %s", attempts, seq, r.error)
                    continue
                except BridgeError as e:
                    uncertain |= state.commit_undecided
                    e.attempts = attempts
                    e.uncertain = e.uncertain or uncertain
                    raise
                self.stats.applies_ok += 1
                return result
            if last is None:
                last = EcuTimeoutError("the overall timeout passed before a transaction could start")
            elapsed = self._clock() - t0
            last.args = (f"{last} (gave up after {attempts} transaction(s) in {elapsed:.3f} s)",)
            last.attempts = attempts
            last.uncertain = last.uncertain or uncertain
            raise last
        except BridgeError:
            self.stats.applies_failed += 1
            raise

    def read_active(self, timeout_s: float | None = None) -> ReadResult:
        """Read every parameter of the definition back from the ECU."""
        t0 = self._clock()
        deadline = t0 + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        seq = self._new_seq()
        self._drain()
        indices = [p.index for p in self.codec.params]
        try:
            raw = self._exchange("READ", seq, {i: Read(seq, i) for i in indices}, self._match_read_any(), deadline)
            values = self.codec.decode_set(raw)
        except FrameError as e:
            self.stats.reads_failed += 1
            raise AcknowledgeMismatchError(f"the ECU reported an impossible value: {e}") from None
        except _RetryableError as r:
            self.stats.reads_failed += 1
            raise r.error from None
        except BridgeError:
            self.stats.reads_failed += 1
            raise
        self.stats.reads_ok += 1
        self.last_confirmed = dict(values)
        return ReadResult(values, dict(sorted(raw.items())), set_crc(raw), self._clock() - t0)

    def status(self, timeout_s: float | None = None) -> EcuStatus:
        """The size and CRC of the ECU's active table (one request)."""
        t0 = self._clock()
        deadline = t0 + (self.config.timeout_s if not timeout_s or timeout_s <= 0 else timeout_s)
        seq = self._new_seq()
        self._drain()

        def match(resp: Response) -> tuple[int, StatusOk] | None:
            return (0, resp) if isinstance(resp, StatusOk) else None

        try:
            out = self._exchange("STATUS", seq, {0: StatusRequest(seq)}, match, deadline)
        except _RetryableError as r:
            raise r.error from None
        st = out[0]
        return EcuStatus(st.count, st.crc, self._clock() - t0)

    # --- one transaction ----------------------------------------------------------------------------
    def _new_seq(self) -> int:
        self._seq = seq_next(self._seq)
        self.stats.transactions += 1
        return self._seq

    def _transaction(
        self, seq: int, raw: dict[int, int], deadline: float, state: _TxState, attempts: int, t0: float
    ) -> ApplyResult:
        n = len(raw)
        crc = set_crc(raw)
        self._drain()
        self._exchange("BEGIN", seq, {0: Begin(seq, n)}, self._match_begin(n), deadline)
        staged: dict[int, int] = self._exchange(
            "WRITE", seq, {i: Write(seq, i, r) for i, r in sorted(raw.items())}, self._match_write(raw), deadline
        )
        state.commit_undecided = True
        try:
            acked = self._exchange("COMMIT", seq, {0: Commit(seq, n, crc)}, self._match_commit(n, crc, state), deadline)
        except _RetryableError as r:
            if state.commit_decided:
                state.commit_undecided = False
            raise r from None
        except BridgeError:
            if state.commit_decided:
                state.commit_undecided = False
            raise
        read_back = False
        # what the result reports is what the ECU said, never the request: the values it read back, else the
        # values it echoed when staging them (whose CRC it acknowledged for its active set)
        echoed = staged
        if self.config.verify_readback:
            # the ECU acknowledged the CRC of its active values; reading each one back confirms them
            got: dict[int, int] = self._exchange(
                "READ", seq, {i: Read(seq, i) for i in sorted(raw)}, self._match_read_expected(raw), deadline
            )
            self._check_read_back(got, crc)
            echoed = got
            read_back = True
        state.commit_undecided = False
        echoed = dict(sorted(echoed.items()))
        values = self.codec.decode_set(echoed)
        latency = self._clock() - t0
        ack_crc = int(acked[0].crc)
        self._log.debug("seq %d: %d parameters applied, crc 0x%08X, %.1f ms", seq, n, ack_crc, latency * 1e3)
        return ApplyResult(values, echoed, ack_crc, attempts, latency, seq, read_back)

    def _check_read_back(self, got: Mapping[int, int], crc: int) -> None:
        if set_crc(got) != crc:  # cannot differ when every value matched; kept as the last word
            raise _RetryableError(AcknowledgeMismatchError("the read-back set's CRC differs from the written one"))

    # --- matchers: a reply of the current sequence number -> (key, result) | _Resend | None -----------
    def _nack_error(self, nack: Nack, message: str, code: ErrorCode) -> EcuRejectedError:
        return EcuRejectedError(message, code, nack.reason)

    def _match_begin(self, n: int) -> Callable[[Response], tuple[int, bool] | None]:
        def match(resp: Response) -> tuple[int, bool] | None:
            if isinstance(resp, BeginOk):
                return (0, True) if resp.count == n else None
            if isinstance(resp, Nack) and resp.request_op == Op.BEGIN:
                self._refused.add(resp.seq)
                if resp.reason == Reason.BUSY:
                    raise self._nack_error(
                        resp,
                        "the ECU refuses to change its calibration while the vehicle is moving (busy): "
                        "stop the vehicle and apply again",
                        ErrorCode.ECU_BUSY,
                    )
                if resp.reason == Reason.COUNT_MISMATCH:
                    raise self._nack_error(
                        resp,
                        f"the ECU refuses a set of {n} parameters (it holds {resp.detail}): the calibration "
                        f"definition '{self.codec.definition.name}' does not match this ECU",
                        ErrorCode.UNKNOWN_PARAMETER,
                    )
                # a refused BEGIN names a sequence number the ECU accepts: the next transaction uses it, unless
                # it is a number the ECU refused in this apply (never resynchronize onto a refused number)
                resync = None
                if resp.reason == Reason.SEQUENCE and resp.detail <= 0xFF and resp.detail not in self._refused:
                    resync = (resp.detail - 1) % 256
                raise _RetryableError(
                    self._nack_error(
                        resp, f"the ECU refused to begin a transaction: {reason_text(resp.reason)}", _code(resp)
                    ),
                    resync_seq=resync,
                )
            return None

        return match

    def _match_write(self, raw: dict[int, int]) -> Callable[[Response], tuple[int, int] | tuple[int, _Resend] | None]:
        def match(resp: Response) -> tuple[int, int] | tuple[int, _Resend] | None:
            if isinstance(resp, Staged) and resp.index in raw:
                if resp.raw == raw[resp.index]:
                    return (resp.index, resp.raw)
                return (
                    resp.index,
                    _Resend(
                        AcknowledgeMismatchError(
                            f"the ECU staged {self.codec.name_of(resp.index)} raw {resp.raw}, written {raw[resp.index]}"
                        )
                    ),
                )
            if isinstance(resp, Nack) and resp.request_op == Op.WRITE and resp.index in raw:
                name = self.codec.name_of(resp.index)
                p = self.codec.by_index[resp.index]
                if resp.reason == Reason.OUT_OF_RANGE:
                    if resp.detail != raw[resp.index] & 0xFFFF:
                        # the ECU refused a value we did not send: our WRITE was garbled on the way
                        return (
                            resp.index,
                            _Resend(
                                EcuRejectedError(
                                    f"the ECU refused a garbled write of {name}",
                                    ErrorCode.ECU_OUT_OF_RANGE,
                                    resp.reason,
                                )
                            ),
                        )
                    value = p.decode(raw[resp.index])
                    raise self._nack_error(
                        resp,
                        f"the ECU rejected {name} = {value:g} (CAN index {resp.index}) as out of its range, "
                        f"although the definition allows [{p.lower:g}, {p.upper:g}]: check that the calibration "
                        "definition matches the ECU software",
                        ErrorCode.ECU_OUT_OF_RANGE,
                    )
                if resp.reason == Reason.UNKNOWN_PARAMETER:
                    raise self._nack_error(
                        resp,
                        f"the ECU does not know parameter {name} (CAN index {resp.index}): the calibration "
                        "definition does not match the ECU software",
                        ErrorCode.UNKNOWN_PARAMETER,
                    )
                raise _RetryableError(
                    self._nack_error(resp, f"the ECU refused writing {name}: {reason_text(resp.reason)}", _code(resp))
                )
            return None

        return match

    def _match_commit(
        self, n: int, crc: int, state: _TxState
    ) -> Callable[[Response], tuple[int, Ack] | tuple[int, _Resend] | None]:
        def match(resp: Response) -> tuple[int, Ack] | tuple[int, _Resend] | None:
            if isinstance(resp, Ack):
                if resp.count == n and resp.crc == crc:
                    state.commit_decided = True
                    return (0, resp)
                return (
                    0,
                    _Resend(
                        AcknowledgeMismatchError(
                            f"the ECU acknowledged {resp.count} parameters with CRC 0x{resp.crc:08X}, "
                            f"written {n} with CRC 0x{crc:08X}"
                        )
                    ),
                )
            if isinstance(resp, Nack) and resp.request_op == Op.COMMIT:
                if resp.reason in (Reason.BUSY, Reason.CRC_MISMATCH, Reason.COUNT_MISMATCH):
                    state.commit_decided = True  # refused before applying: the staging is still open
                if resp.reason == Reason.BUSY:
                    raise self._nack_error(
                        resp,
                        "the ECU refused to commit the calibration while the vehicle is moving (busy): "
                        "stop the vehicle and apply again; the previous calibration stays active",
                        ErrorCode.ECU_BUSY,
                    )
                if resp.reason == Reason.CRC_MISMATCH:
                    raise _RetryableError(
                        self._nack_error(
                            resp,
                            "the ECU's CRC over the staged set does not match the CRC sent with the commit "
                            "(a value was garbled on the way); nothing was applied",
                            ErrorCode.CRC_MISMATCH,
                        )
                    )
                raise _RetryableError(
                    self._nack_error(resp, f"the ECU refused the commit: {reason_text(resp.reason)}", _code(resp))
                )
            return None

        return match

    def _match_read_expected(
        self, raw: dict[int, int]
    ) -> Callable[[Response], tuple[int, int] | tuple[int, _Resend] | None]:
        def match(resp: Response) -> tuple[int, int] | tuple[int, _Resend] | None:
            if isinstance(resp, Value) and resp.index in raw:
                if resp.raw == raw[resp.index]:
                    return (resp.index, resp.raw)
                return (
                    resp.index,
                    _Resend(
                        AcknowledgeMismatchError(
                            f"read-back of {self.codec.name_of(resp.index)}: the ECU holds raw {resp.raw}, "
                            f"written {raw[resp.index]}"
                        )
                    ),
                )
            if isinstance(resp, Nack) and resp.request_op == Op.READ and resp.index in raw:
                self._raise_read_nack(resp)
            return None

        return match

    def _match_read_any(self) -> Callable[[Response], tuple[int, int] | None]:
        def match(resp: Response) -> tuple[int, int] | None:
            if isinstance(resp, Value) and resp.index in self.codec.by_index:
                if resp.raw > self.codec.by_index[resp.index].max_raw:
                    return None
                return (resp.index, resp.raw)
            if isinstance(resp, Nack) and resp.request_op == Op.READ and resp.index in self.codec.by_index:
                self._raise_read_nack(resp)
            return None

        return match

    def _raise_read_nack(self, resp: Nack) -> None:
        name = self.codec.name_of(resp.index)
        if resp.reason == Reason.UNKNOWN_PARAMETER:
            raise self._nack_error(
                resp,
                f"the ECU does not know parameter {name} (CAN index {resp.index}): the calibration definition "
                "does not match the ECU software",
                ErrorCode.UNKNOWN_PARAMETER,
            )
        raise _RetryableError(
            self._nack_error(resp, f"the ECU refused reading {name}: {reason_text(resp.reason)}", _code(resp))
        )

    # --- the selective-repeat exchange ------------------------------------------------------------------
    def _exchange(
        self,
        phase: str,
        seq: int,
        requests: dict[K, Request],
        match: Callable[[Response], tuple[Any, Any] | None],
        deadline: float,
    ) -> dict[K, Any]:
        """Send ``requests``, each until its reply matches; a window of them in flight at once.

        A request is sent again when its reply is ``step_timeout_s`` late or
        wrong, at most ``step_retries`` times (so a step is bounded in time);
        and at once, without waiting for the timeout, when a reply to a request
        sent after it arrives first: the ECU answers in order, so its request
        or its reply was probably lost ("fast retransmit", at most
        ``step_retries`` times per request too, never counted as a timeout).
        """
        cfg = self.config
        results: dict[K, Any] = {}
        queue = list(requests)
        outstanding: dict[K, _Pending] = {}
        problem: BridgeError | None = None
        order = 0

        def send(k: K, pending: _Pending | None, fast: bool = False) -> None:
            nonlocal order
            retries = fasts = 0
            if pending is not None:
                retries, fasts = pending.retries, pending.fasts
                if fast:
                    fasts += 1
                else:
                    if retries >= cfg.step_retries:
                        raise _RetryableError(
                            problem
                            or EcuTimeoutError(
                                f"no valid answer to {phase} of {self._key_text(phase, k)} (seq {seq}) after "
                                f"{1 + retries + fasts} sends, {retries + 1} waits of {cfg.step_timeout_s * 1e3:g} ms"
                            )
                        )
                    retries += 1
                self.stats.retransmissions += 1
            self._send(requests[k])
            order += 1
            outstanding[k] = _Pending(self._clock(), retries, fasts, order)

        while True:
            while queue and len(outstanding) < cfg.window:
                send(queue.pop(0), None)
            if not outstanding:
                return results
            now = self._clock()
            for k, late in list(outstanding.items()):
                if now - late.sent_at >= cfg.step_timeout_s:
                    self.stats.step_timeouts += 1
                    send(k, late)
            now = self._clock()
            if now >= deadline:
                raise EcuTimeoutError(
                    f"no valid answer to {phase} (seq {seq}) before the overall timeout"
                    + (f"; last problem: {problem}" if problem is not None else "")
                )
            next_expiry = min(p.sent_at for p in outstanding.values()) + cfg.step_timeout_s
            resp = self._recv(min(next_expiry, deadline) - now, seq)
            if resp is None:
                continue
            try:
                got = match(resp)
            except (EcuRejectedError, _RetryableError):
                self._count_nack(resp)
                raise
            if got is None:
                self.stats.unexpected_frames += 1
                continue
            key, value = got
            pending = outstanding.get(key)
            if pending is None:
                continue  # a duplicate of a reply already taken
            if isinstance(value, _Resend):
                problem = value.problem
                self.stats.unexpected_frames += 1
                send(key, pending)
                continue
            del outstanding[key]
            results[key] = value
            for k, other in list(outstanding.items()):
                if other.order < pending.order and other.fasts < cfg.step_retries:
                    send(k, other, fast=True)  # overtaken: its request or its reply was probably lost

    def _key_text(self, phase: str, k: object) -> str:
        if phase in ("WRITE", "READ") and isinstance(k, int):
            return self.codec.name_of(k)
        return "the request"

    def _count_nack(self, resp: Response) -> None:
        self.stats.nacks += 1
        if isinstance(resp, Nack):
            try:
                name = Reason(resp.reason).name
            except ValueError:
                name = f"0x{resp.reason:02X}"
            self.stats.nack_reasons[name] = self.stats.nack_reasons.get(name, 0) + 1

    # --- the bus ----------------------------------------------------------------------------------------
    def _send(self, pdu: Request) -> None:
        if isinstance(pdu, Begin | Write):
            self._last_staging_frame = self._clock()
        msg = can.Message(
            arbitration_id=self.ids.request_id,
            is_extended_id=self.ids.extended,
            data=encode(pdu),
            is_fd=False,
        )
        try:
            self.bus.send(msg, timeout=self.config.step_timeout_s)
        except (can.CanError, OSError) as exc:
            raise BusError(f"sending on the CAN bus ({self.bus.channel_info}) failed: {exc}") from exc
        self.stats.frames_sent += 1

    def _recv(self, timeout: float, seq: int) -> Response | None:
        """One response of transaction ``seq``, or None (timeout, or a frame to ignore)."""
        try:
            msg = self.bus.recv(timeout=max(0.0, timeout))
        except (can.CanError, OSError) as exc:
            raise BusError(f"receiving on the CAN bus ({self.bus.channel_info}) failed: {exc}") from exc
        if msg is None:
            return None
        self.stats.frames_received += 1
        if (
            msg.arbitration_id != self.ids.response_id
            or bool(msg.is_extended_id) != self.ids.extended
            or msg.is_error_frame
            or msg.is_remote_frame
            or msg.is_fd
        ):
            self.stats.foreign_frames += 1
            return None
        try:
            resp = decode_response(msg.data)
        except FrameError:
            self.stats.invalid_frames += 1
            return None
        if resp.seq != seq:
            self.stats.stale_frames += 1
            return None
        return resp

    def _drain(self) -> None:
        """Discard what arrived between transactions (late replies of earlier ones)."""
        for _ in range(_DRAIN_LIMIT):
            try:
                msg = self.bus.recv(timeout=0.0)
            except (can.CanError, OSError) as exc:
                raise BusError(f"receiving on the CAN bus ({self.bus.channel_info}) failed: {exc}") from exc
            if msg is None:
                return
            self.stats.frames_received += 1
            if msg.arbitration_id == self.ids.response_id:
                self.stats.stale_frames += 1
            else:
                self.stats.foreign_frames += 1


@dataclass
class _Pending:
    sent_at: float
    retries: int  # re-sends after a timeout or a wrong answer
    fasts: int  # fast retransmits
    order: int  # send order within the exchange


@dataclass
class _TxState:
    commit_undecided: bool = False  # a COMMIT was sent and no decisive answer came yet
    commit_decided: bool = False


def _code(nack: Nack) -> ErrorCode:
    codes: dict[int, ErrorCode] = {
        Reason.OUT_OF_RANGE: ErrorCode.ECU_OUT_OF_RANGE,
        Reason.UNKNOWN_PARAMETER: ErrorCode.UNKNOWN_PARAMETER,
        Reason.BUSY: ErrorCode.ECU_BUSY,
        Reason.CRC_MISMATCH: ErrorCode.CRC_MISMATCH,
        Reason.SEQUENCE: ErrorCode.SEQUENCE,
        Reason.COUNT_MISMATCH: ErrorCode.SEQUENCE,
    }
    return codes.get(nack.reason, ErrorCode.SEQUENCE)
