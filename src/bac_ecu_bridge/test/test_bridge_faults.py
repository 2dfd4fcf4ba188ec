"""The fault-injecting bus: each fault does what it says, on either direction, reproducibly."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import can
import pytest

from bac_ecu_bridge.faults import FaultConfig, FaultSpecError, FaultyBus
from bac_ecu_bridge.protocol import Ack, Nack, Op, Reason, decode, encode

_CHANNELS = itertools.count()
A, MARK = 0x100, 0x7FF


_WRAPPERS: list[FaultyBus] = []


def wrap(inner: can.BusABC, config: FaultConfig) -> FaultyBus:
    bus = FaultyBus(inner, config, owns_inner=False)
    _WRAPPERS.append(bus)
    return bus


@pytest.fixture
def pair() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    ch = f"faults-{next(_CHANNELS)}"
    tx = can.Bus(interface="virtual", channel=ch)
    rx = can.Bus(interface="virtual", channel=ch)
    try:
        yield tx, rx
    finally:
        while _WRAPPERS:
            _WRAPPERS.pop().shutdown()
        tx.shutdown()
        rx.shutdown()


def frame(i: int, can_id: int = A) -> can.Message:
    return can.Message(arbitration_id=can_id, is_extended_id=False, data=i.to_bytes(8, "little"))


def until_marker(bus: can.BusABC, timeout: float = 5.0) -> list[can.Message]:
    """Every frame up to the marker frame (sent last, never faulted): no fixed sleep needed."""
    out = []
    while True:
        msg = bus.recv(timeout=timeout)
        assert msg is not None, "the marker frame never arrived"
        if msg.arbitration_id == MARK:
            return out
        out.append(msg)


def values(msgs: list[can.Message]) -> list[int]:
    return [int.from_bytes(m.data, "little") for m in msgs]


def test_spec_parsing() -> None:
    cfg = FaultConfig.parse("drop=0.1, corrupt=0.2,delay=0.3,delay_s=0.01,duplicate=0.05,reorder=0.5,seed=7")
    assert (cfg.drop, cfg.corrupt, cfg.delay, cfg.delay_s, cfg.duplicate, cfg.reorder, cfg.seed) == (
        0.1,
        0.2,
        0.3,
        0.01,
        0.05,
        0.5,
        7,
    )
    assert FaultConfig.parse("silent").silent
    nack = FaultConfig.parse("nack=busy,nack_ops=ack+begin_ok,direction=send,ids=0x6C1,ops=ack")
    assert nack.nack == Reason.BUSY and nack.nack_ops == (Op.ACK, Op.BEGIN_OK) and nack.nack_p == 1.0
    assert nack.direction == "send" and nack.ids == (0x6C1,) and nack.ops == (Op.ACK,)
    assert not FaultConfig.parse("").any
    with pytest.raises(FaultSpecError, match="unknown fault 'dorp'"):
        FaultConfig.parse("dorp=0.1")
    with pytest.raises(FaultSpecError, match=r"\[0, 1\]"):
        FaultConfig.parse("drop=1.5")
    with pytest.raises(FaultSpecError, match="bad value"):
        FaultConfig.parse("nack=sometimes")


def test_drop_on_send_loses_about_the_given_share(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(drop=0.3, seed=1, ids=(A,)))
    n = 2000
    for i in range(n):
        faulty.send(frame(i))
    faulty.send(frame(0, MARK))
    got = values(until_marker(rx))
    assert faulty.counts.dropped == n - len(got)
    assert 520 < faulty.counts.dropped < 680  # 600 +- 4 sigma
    assert got == sorted(got)  # nothing else happened to the order


def test_corrupt_changes_data_but_keeps_the_id(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(corrupt=1.0, seed=2, ids=(A,)))
    for i in range(200):
        faulty.send(frame(i))
    faulty.send(frame(0, MARK))
    got = until_marker(rx)
    assert len(got) == 200
    assert all(m.arbitration_id == A and len(m.data) == 8 for m in got)
    assert all(v != i for i, v in enumerate(values(got)))


def test_duplicate_delivers_twice(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(duplicate=1.0, seed=3))
    for i in range(5):
        faulty.send(frame(i))
    tx.send(frame(0, MARK))
    assert values(until_marker(rx)) == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]


def test_delay_lets_later_frames_overtake(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    # seed 4 draws a delay of 0.198 s: far longer than a stall of the machine between the two sends
    faulty = wrap(tx, FaultConfig(delay=1.0, delay_s=0.5, seed=4, ids=(A,)))
    faulty.send(frame(1))
    faulty.send(frame(2, 0x200))  # not faulted: goes at once
    first = rx.recv(timeout=5)
    second = rx.recv(timeout=5)
    assert first is not None and second is not None
    assert (first.arbitration_id, second.arbitration_id) == (0x200, A)


def test_reorder_releases_a_frame_after_the_next(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(reorder=1.0, reorder_hold_s=5.0, seed=5, ids=(A,)))
    faulty.send(frame(1))
    faulty.send(frame(2, 0x200))
    faulty.send(frame(0, MARK))
    got = until_marker(rx)
    assert [m.arbitration_id for m in got] == [0x200, A]


def test_reordered_frame_is_released_even_without_a_next_one(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(reorder=1.0, reorder_hold_s=0.02, seed=6))
    faulty.send(frame(9))
    msg = rx.recv(timeout=5)
    assert msg is not None and values([msg]) == [9]


def test_faults_on_the_receiving_side(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(rx, FaultConfig(duplicate=1.0, direction="recv", seed=7, ids=(A,)))
    for i in range(3):
        tx.send(frame(i))
    tx.send(frame(0, MARK))
    assert values(until_marker(faulty)) == [0, 0, 1, 1, 2, 2]
    assert faulty.counts.by_direction == {"recv": 3}


def test_receive_side_drop_and_reorder(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(rx, FaultConfig(reorder=1.0, direction="recv", seed=8, ids=(A,)))
    tx.send(frame(1))
    tx.send(frame(2, 0x200))
    tx.send(frame(0, MARK))
    assert [m.arbitration_id for m in until_marker(faulty)] == [0x200, A]
    silent = wrap(rx, FaultConfig(silent=True, direction="recv"))
    tx.send(frame(3))
    assert silent.recv(timeout=0.05) is None
    assert silent.counts.dropped == 1


def test_silent_passes_nothing_and_direction_is_respected(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(silent=True, direction="send"))
    faulty.send(frame(1))
    tx.send(frame(0, MARK))
    assert until_marker(rx) == []
    faulty.with_config(FaultConfig(silent=True, direction="recv"))
    faulty.send(frame(2))  # the send side is clean now
    tx.send(frame(0, MARK))
    assert values(until_marker(rx)) == [2]


def test_nack_injection_replaces_positive_responses(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(nack=int(Reason.CRC_MISMATCH)))
    faulty.send(can.Message(arbitration_id=0x6C1, is_extended_id=False, data=encode(Ack(9, 20, 1234))))
    faulty.send(frame(5))  # not a protocol frame: passes untouched
    tx.send(frame(0, MARK))
    got = until_marker(rx)
    assert decode(got[0].data) == Nack(9, int(Op.COMMIT), int(Reason.CRC_MISMATCH), 0)
    assert values(got[1:]) == [5]
    assert faulty.counts.nacked == 1


def test_only_the_selected_opcodes_are_faulted(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    faulty = wrap(tx, FaultConfig(drop=1.0, ops=(int(Op.ACK),)))
    faulty.send(can.Message(arbitration_id=0x6C1, is_extended_id=False, data=encode(Ack(1, 1, 1))))
    faulty.send(can.Message(arbitration_id=0x6C1, is_extended_id=False, data=encode(Nack(1, 3, 4))))
    tx.send(frame(0, MARK))
    got = until_marker(rx)
    assert [decode(m.data).op for m in got] == [Op.NACK]


def test_same_seed_same_fates(pair: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = pair
    runs = []
    for _ in range(2):
        faulty = wrap(tx, FaultConfig(drop=0.3, corrupt=0.2, seed=11, ids=(A,)))
        for i in range(100):
            faulty.send(frame(i))
        tx.send(frame(0, MARK))
        runs.append(values(until_marker(rx)))
    assert runs[0] == runs[1]
    assert len(runs[0]) < 100
