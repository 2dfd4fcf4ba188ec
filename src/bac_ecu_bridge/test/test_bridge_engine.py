"""The ECU-side protocol engine: frames in, frames out, the state an ECU holds."""

from __future__ import annotations

import pytest

from bac_common.paramspace import CalibrationDefinition, uniform_parameters
from bac_ecu_bridge.engine import SEQ_HISTORY, CommitEvent, EcuEngine
from bac_ecu_bridge.protocol import (
    DETAIL_NONE,
    Abort,
    Aborted,
    Ack,
    Begin,
    BeginOk,
    Commit,
    Nack,
    Op,
    Read,
    Reason,
    Response,
    Staged,
    StatusOk,
    StatusRequest,
    Value,
    Write,
    decode_response,
    encode,
    set_crc,
)

DEF = CalibrationDefinition("three", uniform_parameters("p", 3, 0.0, 100.0, 50.0, 0.5))  # raw 0..200, nominal 100


def ask(engine: EcuEngine, req: object) -> Response:
    out = engine.handle(encode(req))  # type: ignore[arg-type]
    assert len(out) == 1
    return decode_response(out[0])


def transaction(engine: EcuEngine, seq: int, raw: dict[int, int]) -> Response:
    assert ask(engine, Begin(seq, len(raw))) == BeginOk(seq, len(raw))
    for i, r in raw.items():
        assert ask(engine, Write(seq, i, r)) == Staged(seq, i, r)
    return ask(engine, Commit(seq, len(raw), set_crc(raw)))


def test_starts_at_the_baseline_and_commits_atomically() -> None:
    events: list[CommitEvent] = []
    e = EcuEngine(DEF, on_commit=events.append)
    assert e.active_values() == {"p01": 50.0, "p02": 50.0, "p03": 50.0}
    raw = {0: 10, 1: 20, 2: 200}
    assert ask(e, Begin(5, 3)) == BeginOk(5, 3)
    assert ask(e, Write(5, 0, 10)) == Staged(5, 0, 10)
    assert ask(e, Write(5, 1, 20)) == Staged(5, 1, 20)
    assert e.active_values()["p01"] == 50.0  # staged, not active
    assert ask(e, Write(5, 2, 200)) == Staged(5, 2, 200)
    assert ask(e, Commit(5, 3, set_crc(raw))) == Ack(5, 3, set_crc(raw))
    assert e.active_values() == {"p01": 5.0, "p02": 10.0, "p03": 100.0}
    assert events == [CommitEvent(5, raw, set_crc(raw))]
    assert ask(e, Read(6, 2)) == Value(6, 2, 200)
    assert ask(e, StatusRequest(7)) == StatusOk(7, 3, set_crc(raw))


def test_crc_mismatch_applies_nothing() -> None:
    e = EcuEngine(DEF)
    assert ask(e, Begin(1, 2)) == BeginOk(1, 2)
    ask(e, Write(1, 0, 10))
    ask(e, Write(1, 1, 20))
    resp = ask(e, Commit(1, 2, set_crc({0: 10, 1: 21})))
    assert isinstance(resp, Nack) and resp.reason == Reason.CRC_MISMATCH and resp.request_op == Op.COMMIT
    assert e.active_values() == {"p01": 50.0, "p02": 50.0, "p03": 50.0}
    assert e.stats.commits == 0


def test_count_mismatch_when_the_staged_set_is_incomplete_or_too_large() -> None:
    e = EcuEngine(DEF)
    ask(e, Begin(1, 2))
    ask(e, Write(1, 0, 10))
    resp = ask(e, Commit(1, 2, set_crc({0: 10})))
    assert isinstance(resp, Nack) and resp.reason == Reason.COUNT_MISMATCH and resp.detail == 1
    ask(e, Write(1, 1, 10))
    resp = ask(e, Write(1, 2, 10))  # a third index in a transaction of two
    assert isinstance(resp, Nack) and resp.reason == Reason.COUNT_MISMATCH and resp.index == 2
    resp = ask(e, Begin(2, 4))  # more than the ECU holds
    assert isinstance(resp, Nack) and resp.reason == Reason.COUNT_MISMATCH and resp.detail == 3


def test_out_of_range_and_unknown_index_are_refused_with_the_index() -> None:
    e = EcuEngine(DEF)
    ask(e, Begin(1, 3))
    resp = ask(e, Write(1, 1, 201))
    assert resp == Nack(1, int(Op.WRITE), int(Reason.OUT_OF_RANGE), 1, 201)
    resp = ask(e, Write(1, 9, 1))
    assert resp == Nack(1, int(Op.WRITE), int(Reason.UNKNOWN_PARAMETER), 9, DETAIL_NONE)
    resp = ask(e, Read(2, 9))
    assert isinstance(resp, Nack) and resp.reason == Reason.UNKNOWN_PARAMETER


def test_busy_while_driving_then_accepted_when_standing() -> None:
    e = EcuEngine(DEF)
    e.driving = True
    resp = ask(e, Begin(1, 3))
    assert isinstance(resp, Nack) and resp.reason == Reason.BUSY and resp.request_op == Op.BEGIN
    e.driving = False
    assert ask(e, Begin(2, 1)) == BeginOk(2, 1)
    ask(e, Write(2, 0, 1))
    e.driving = True  # the vehicle starts moving between the writes and the commit
    resp = ask(e, Commit(2, 1, set_crc({0: 1})))
    assert isinstance(resp, Nack) and resp.reason == Reason.BUSY
    assert e.active_values()["p01"] == 50.0
    e.driving = False
    assert ask(e, Commit(2, 1, set_crc({0: 1}))) == Ack(2, 1, set_crc({0: 1}))


def test_stale_or_duplicated_frames_never_reopen_or_disturb_a_transaction() -> None:
    e = EcuEngine(DEF)
    assert isinstance(transaction(e, 10, {0: 1, 1: 2, 2: 3}), Ack)
    # a stale BEGIN of the committed transaction is refused and does not open anything
    resp = ask(e, Begin(10, 3))
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE and resp.detail == 11  # 11 is free
    # new transaction 11; a duplicated BEGIN 11 is answered again without losing the staged values
    assert ask(e, Begin(11, 3)) == BeginOk(11, 3)
    ask(e, Write(11, 0, 7))
    assert ask(e, Begin(11, 3)) == BeginOk(11, 3)
    # a stale WRITE of transaction 10 is refused and does not touch the staging of 11
    resp = ask(e, Write(10, 0, 99))
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE and resp.detail == 11
    ask(e, Write(11, 1, 8))
    ask(e, Write(11, 2, 9))
    raw = {0: 7, 1: 8, 2: 9}
    # a late duplicate of COMMIT 10 (the last committed) is acknowledged again, with the truth; nothing changes
    resp = ask(e, Commit(10, 3, set_crc({0: 1, 1: 2, 2: 3})))
    assert resp == Ack(10, 3, set_crc({0: 1, 1: 2, 2: 3}))
    assert e.active == {0: 1, 1: 2, 2: 3}
    # a stale COMMIT of an older transaction is refused
    resp = ask(e, Commit(9, 3, set_crc({0: 1, 1: 2, 2: 3})))
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE
    assert ask(e, Commit(11, 3, set_crc(raw))) == Ack(11, 3, set_crc(raw))
    # our ACK got lost: the repeated COMMIT is acknowledged again, nothing changes
    assert ask(e, Commit(11, 3, set_crc(raw))) == Ack(11, 3, set_crc(raw))
    assert e.stats.commits == 2
    # a commit of a transaction never begun
    resp = ask(e, Commit(12, 3, set_crc(raw)))
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE


def test_recent_sequence_numbers_are_remembered_until_they_leave_the_history() -> None:
    e = EcuEngine(DEF)
    for seq in range(SEQ_HISTORY):
        assert isinstance(transaction(e, seq, {0: seq}), Ack)
    assert isinstance(ask(e, Begin(0, 1)), Nack)  # still in the history
    assert isinstance(transaction(e, SEQ_HISTORY, {0: 1}), Ack)  # pushes 0 out
    assert ask(e, Begin(0, 1)) == BeginOk(0, 1)


def test_garbled_frames_are_ignored_and_counted() -> None:
    e = EcuEngine(DEF)
    frame = bytearray(encode(Begin(1, 1)))
    frame[3] ^= 0x01
    assert e.handle(bytes(frame)) == []
    assert e.handle(b"\x01\x02") == []
    assert e.handle(encode(Ack(1, 1, 1))) == []  # a response on the request id
    assert e.stats.invalid_frames == 3


def test_reset_is_a_power_cycle() -> None:
    e = EcuEngine(DEF, initial={"p02": 0.0})
    assert e.active_values()["p02"] == 0.0
    transaction(e, 3, {1: 150})
    e.reset()
    assert e.active_values()["p02"] == 0.0
    assert ask(e, Begin(3, 1)) == BeginOk(3, 1)  # history forgotten


@pytest.mark.parametrize("seq", [0, 255])
def test_sequence_numbers_wrap(seq: int) -> None:
    e = EcuEngine(DEF)
    assert isinstance(transaction(e, seq, {2: 4}), Ack)


def test_a_refused_begin_names_a_free_sequence_number() -> None:
    e = EcuEngine(DEF)
    for seq in (5, 6, 7, 4):  # the most recent is 4, but 5, 6 and 7 are taken
        assert isinstance(transaction(e, seq, {0: seq}), Ack)
    resp = ask(e, Begin(6, 1))
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE and resp.detail == 8
    assert ask(e, Begin(8, 1)) == BeginOk(8, 1)


def test_a_begin_repeating_the_open_number_with_another_count_names_another_free_number() -> None:
    e = EcuEngine(DEF)
    assert ask(e, Begin(10, 1)) == BeginOk(10, 1)  # transaction 10 open for one parameter
    resp = ask(e, Begin(10, 3))  # the same number, another count: refused
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE
    assert resp.detail != 10 and resp.detail == 11  # never the refused number itself
    assert ask(e, Begin(resp.detail, 3)) == BeginOk(11, 3)


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_a_staged_set_is_dropped_after_the_staging_timeout_and_a_late_commit_applies_nothing() -> None:
    clock = FakeClock()
    e = EcuEngine(DEF, staging_timeout_s=1.0, clock=clock)
    raw = {0: 7, 1: 8}
    assert ask(e, Begin(20, 2)) == BeginOk(20, 2)
    clock.t += 0.6
    ask(e, Write(20, 0, 7))
    clock.t += 0.6  # 1.2 s after BEGIN, but each frame of the transaction restarts the timeout
    ask(e, Write(20, 1, 8))
    assert e.staging_seq == 20
    clock.t += 1.01  # then nothing for longer than the timeout: the staged set is gone
    assert e.staging_seq is None
    resp = ask(e, Commit(20, 2, set_crc(raw)))  # a COMMIT that arrives late
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE
    assert e.active_values()["p01"] == 50.0 and e.stats.commits == 0
    assert e.stats.staging_expired == 1


def test_abort_drops_the_staged_set_so_that_no_later_commit_applies_it() -> None:
    e = EcuEngine(DEF)
    raw = {0: 7, 1: 8}
    ask(e, Begin(30, 2))
    ask(e, Write(30, 0, 7))
    ask(e, Write(30, 1, 8))
    assert ask(e, Abort(31)) == Aborted(31, 2)  # any staged transaction, whatever the ABORT's number
    resp = ask(e, Commit(30, 2, set_crc(raw)))
    assert isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE
    assert e.stats.commits == 0 and e.stats.aborts == 1
    assert ask(e, Abort(32)) == Aborted(32, 0)  # nothing staged: answered all the same
    e.driving = True
    assert ask(e, Abort(33)) == Aborted(33, 0)  # dropping is allowed while driving
