"""The bridge's apply transaction against the simulated ECU on a python-can virtual bus."""

from __future__ import annotations

import threading
import time
from typing import Any

import can
import pytest
from bridge_rig import FAST, RigFactory, load, make_rig_fixture  # noqa: F401  (the make_rig fixture)

from bac_common.errors import OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition, RawParameter
from bac_ecu_bridge.backend import Holds
from bac_ecu_bridge.client import CalibrationClient, ClientConfig
from bac_ecu_bridge.errors import BridgeError, BusError, ErrorCode
from bac_ecu_bridge.faults import FaultConfig
from bac_ecu_bridge.protocol import (
    Ack,
    Begin,
    CalibrationCodec,
    Commit,
    Nack,
    Op,
    Reason,
    Value,
    decode_request,
    decode_response,
    encode,
)

II = load("controller_ii")


def ramp(offset: float = 0.0) -> dict[str, float]:
    """A controller II calibration with every parameter different (and not on the 0.01 grid)."""
    return {p.name: 10.0 + 47.123 * k + offset for k, p in enumerate(II.parameters)}


def test_happy_path_applies_exactly_the_quantized_values(make_rig: RigFactory) -> None:
    rig = make_rig("controller_ii")
    want = ramp()
    res = rig.client.apply(want)
    quantized = rig.codec.quantize(want)
    assert res.values == quantized
    assert res.values["p02"] == pytest.approx(57.12)  # 57.123 on the 0.01 grid
    assert rig.ecu.active == quantized
    assert res.crc == rig.codec.crc(want) == rig.ecu.active_crc
    assert res.attempts == 1 and res.read_back
    assert rig.ecu.commits == 1
    assert rig.client.stats.applies_ok == 1
    assert list(res.values) == [p.name for p in II.parameters]


def test_read_back_and_status(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i")
    assert rig.client.read_active().values == {"damping_front": 0.5, "damping_rear": 0.5}  # the baseline
    rig.client.apply({"damping_front": 0.12346, "damping_rear": 0.9})
    rd = rig.client.read_active()
    assert rd.values == {"damping_front": pytest.approx(0.1235), "damping_rear": pytest.approx(0.9)}
    st = rig.client.status()
    assert (st.count, st.crc) == (2, rd.crc)


def test_out_of_bounds_and_unknown_names_are_refused_before_anything_is_sent(make_rig: RigFactory) -> None:
    rig = make_rig("controller_ii")
    bad = ramp()
    bad["p07"] = 1000.01
    with pytest.raises(OutOfBoundsError, match="p07"):
        rig.client.apply(bad)
    with pytest.raises(UnknownParameterError, match="p99"):
        rig.client.apply({"p99": 1.0})
    assert rig.client.stats.frames_sent == 0
    rig.client.apply(ramp())  # frames sent before this apply would have reached the ECU first
    assert rig.ecu.engine.stats.requests == rig.client.stats.frames_sent >= 1 + 20 + 1 + 20


def test_busy_while_driving(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i")
    rig.ecu.set_driving(True)
    with pytest.raises(BridgeError, match="moving") as err:
        rig.client.apply({"damping_front": 0.1, "damping_rear": 0.1})
    assert err.value.code == ErrorCode.ECU_BUSY
    assert err.value.attempts == 1 and not err.value.uncertain
    assert rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}
    rig.ecu.set_driving(False)
    assert rig.client.apply({"damping_front": 0.1, "damping_rear": 0.1}).attempts == 1


def narrowed(definition: CalibrationDefinition, name: str, **changes: Any) -> CalibrationDefinition:
    params = []
    for p in definition.parameters:
        if p.name == name:
            fields = {**p.__dict__, **changes}
            params.append(RawParameter(**fields))
        else:
            params.append(p)
    return CalibrationDefinition(definition.name, tuple(params))


def test_ecu_out_of_range(make_rig: RigFactory) -> None:
    # the ECU's software holds p12 in [0, 500] at the same resolution; the definition says [0, 1000]
    rig = make_rig("controller_ii", ecu_definition=narrowed(II, "p12", upper=500.0, nominal=250.0))
    want = ramp()
    assert want["p12"] > 500
    with pytest.raises(BridgeError, match=r"p12 = 528.35 \(CAN index 11\) as out of its range") as err:
        rig.client.apply(want)
    assert err.value.code == ErrorCode.ECU_OUT_OF_RANGE and err.value.attempts == 1
    assert rig.ecu.commits == 0


def test_ecu_does_not_know_a_parameter(make_rig: RigFactory) -> None:
    rig = make_rig("controller_ii", ecu_definition=narrowed(II, "p20", index=40))
    with pytest.raises(BridgeError, match=r"does not know parameter p20 \(CAN index 19\)") as err:
        rig.client.apply(ramp())
    assert err.value.code == ErrorCode.UNKNOWN_PARAMETER
    smaller = CalibrationDefinition("c", II.parameters[:19])
    rig2 = make_rig("controller_ii", ecu_definition=smaller)
    with pytest.raises(BridgeError, match="it holds 19") as err:
        rig2.client.apply(ramp())
    assert err.value.code == ErrorCode.UNKNOWN_PARAMETER


@pytest.mark.parametrize(
    ("reason", "code", "match"),
    [
        (Reason.CRC_MISMATCH, ErrorCode.CRC_MISMATCH, "CRC over the staged set does not match"),
        (Reason.COUNT_MISMATCH, ErrorCode.SEQUENCE, "incomplete"),
    ],
)
def test_retryable_refusals_are_retried_then_reported(
    make_rig: RigFactory, reason: Reason, code: ErrorCode, match: str
) -> None:
    rig = make_rig("controller_i", ecu_faults=FaultConfig(nack=int(reason), direction="send"))
    with pytest.raises(BridgeError, match=match) as err:
        rig.client.apply({"damping_front": 0.3, "damping_rear": 0.3})
    assert err.value.code == code
    assert err.value.attempts == FAST.max_attempts
    assert "gave up after 3 transaction(s)" in str(err.value)


def test_a_commit_answered_with_a_sequence_error_is_settled_by_reading_the_ecu_back(make_rig: RigFactory) -> None:
    # every ACK is replaced on the wire by a SEQUENCE refusal: the commit may or may not have been applied
    rig = make_rig("controller_i", ecu_faults=FaultConfig(nack=int(Reason.SEQUENCE), direction="send"))
    want = {"damping_front": 0.3, "damping_rear": 0.3}
    res = rig.client.apply(want)
    assert res.read_back and "read back" in res.note
    assert res.values == rig.ecu.active == rig.codec.quantize(want)  # it was: the read-back says so
    assert rig.client.stats.settled == 1


def test_a_silent_ecu_times_out_within_the_bound(make_rig: RigFactory) -> None:
    config = ClientConfig(step_timeout_s=0.01, step_retries=2, max_attempts=3, timeout_s=5.0)
    rig = make_rig("controller_i", ecu_faults=FaultConfig(silent=True), config=config)
    t0 = time.monotonic()
    with pytest.raises(BridgeError, match="no valid answer to BEGIN") as err:
        rig.client.apply({"damping_front": 0.3, "damping_rear": 0.3})
    elapsed = time.monotonic() - t0
    assert err.value.code == ErrorCode.TIMEOUT and err.value.attempts == 3 and not err.value.uncertain
    assert 3 * 3 * 0.01 <= elapsed < 2.0  # 3 transactions x 3 sends x 10 ms, well before the 5 s limit
    # the overall limit cuts retries short
    slow = make_rig("controller_i", ecu_faults=FaultConfig(silent=True), config=ClientConfig(step_timeout_s=0.05))
    t0 = time.monotonic()
    with pytest.raises(BridgeError, match="overall timeout") as err:
        slow.client.apply({"damping_front": 0.3, "damping_rear": 0.3}, timeout_s=0.12)
    assert err.value.code == ErrorCode.TIMEOUT
    assert 0.12 <= time.monotonic() - t0 < 1.0  # the 0.12 s limit plus scheduling on a loaded machine


def test_lost_acknowledgments_are_settled_by_reading_the_ecu_back(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i", ecu_faults=FaultConfig(drop=1.0, ops=(int(Op.ACK),), direction="send"))
    want = {"damping_front": 0.3, "damping_rear": 0.7}
    res = rig.client.apply(want)  # the ECU did apply it, only its word is missing: the read-back says so
    assert res.values == rig.ecu.active == rig.codec.quantize(want)
    assert "read back" in res.note and rig.client.stats.settled == 1
    assert rig.ecu.engine.staging_seq is None


class LateCommits(can.BusABC):
    """The bridge's bus, on which every COMMIT reaches the ECU ``late_s`` late (held in an adapter's queue)."""

    def __init__(self, inner: can.BusABC, late_s: float) -> None:
        super().__init__(channel="late")
        self.inner, self.late_s, self.channel_info = inner, late_s, "late-commits"
        self.in_flight: list[threading.Timer] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if len(msg.data) == 8 and msg.data[1] == Op.COMMIT:
            timer = threading.Timer(self.late_s, self.inner.send, args=(msg,))
            self.in_flight.append(timer)
            timer.start()
        else:
            self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), False

    def landed(self) -> bool:
        return not any(t.is_alive() for t in self.in_flight)


def test_a_late_commit_never_changes_the_ecu_after_the_bridge_reported_its_state(make_rig: RigFactory) -> None:
    """The review's hole: commits arriving after the bridge gave up made staged values active afterwards."""
    rig = make_rig("controller_i")
    client = rig.client
    client.apply({"damping_front": 0.1, "damping_rear": 0.1})
    engine = rig.ecu.engine
    refused = engine.stats.by_reason.get("SEQUENCE", 0)
    late = LateCommits(rig.bridge_bus, late_s=0.15)
    client.bus = late
    client.config = ClientConfig(step_timeout_s=0.01, step_retries=1, max_attempts=1, timeout_s=0.05)
    with pytest.raises(BridgeError) as err:
        client.apply({"damping_front": 0.9, "damping_rear": 0.9})
    assert err.value.uncertain
    state = err.value.ecu_state
    assert state is not None and state.read_back and state.holds is Holds.PREVIOUS
    deadline = time.monotonic() + 5.0
    while not late.landed() and time.monotonic() < deadline:  # every late COMMIT reaches the ECU
        time.sleep(0.01)
    assert late.landed()
    while engine.stats.by_reason.get("SEQUENCE", 0) < refused + len(late.in_flight) and time.monotonic() < deadline:
        time.sleep(0.01)  # ... and is refused: its staged set was aborted
    assert engine.stats.by_reason.get("SEQUENCE", 0) >= refused + len(late.in_flight) >= 1
    assert rig.ecu.active == state.values == {"damping_front": 0.1, "damping_rear": 0.1}
    assert rig.ecu.commits == 1 and rig.ecu.engine.staging_seq is None
    late.shutdown()


def test_a_lost_acknowledgment_is_recovered_by_repeating_the_commit(make_rig: RigFactory) -> None:
    rig = make_rig("controller_ii", ecu_faults=FaultConfig(drop=0.5, ops=(int(Op.ACK),), direction="send", seed=3))
    for k in range(10):
        res = rig.client.apply(ramp(k))
        assert res.values == rig.ecu.active == rig.codec.quantize(ramp(k))
    assert rig.client.stats.retransmissions > 0
    assert rig.ecu.commits == 10  # a repeated COMMIT is acknowledged again, never applied twice


def test_stale_acknowledgments_of_an_earlier_transaction_are_never_taken(make_rig: RigFactory) -> None:
    """Replay every reply of a successful apply while the ECU is silent: the same values again must fail."""
    rig = make_rig("controller_i", ecu_faults=FaultConfig())
    sniffer = rig.sniffer()
    want = {"damping_front": 0.25, "damping_rear": 0.75}
    first = rig.client.apply(want)
    replies: list[can.Message] = []
    while (msg := sniffer.recv(timeout=0.5)) is not None:
        if msg.arbitration_id == rig.client.ids.response_id:
            replies.append(msg)
    assert [encode_op(m) for m in replies] == ["BEGIN_OK", "STAGED", "STAGED", "ACK", "VALUE", "VALUE"]
    rig.ecu_bus.set_silent(True)  # type: ignore[attr-defined]
    stop = threading.Event()

    def replay() -> None:  # answer every request with the whole earlier conversation (same CRC, old seq)
        while not stop.is_set():
            msg = sniffer.recv(timeout=0.05)
            if msg is not None and msg.arbitration_id == rig.client.ids.request_id:
                for r in replies:
                    sniffer.send(r)

    t = threading.Thread(target=replay, daemon=True)
    t.start()
    try:
        with pytest.raises(BridgeError) as err:
            rig.client.apply(want)
    finally:
        stop.set()
        t.join()
    assert err.value.code == ErrorCode.TIMEOUT
    assert rig.client.stats.stale_frames >= len(replies)
    assert rig.client.seq != first.seq


def encode_op(msg: can.Message) -> str:
    return Op(msg.data[1]).name


def test_duplicated_delayed_and_reordered_replies(make_rig: RigFactory) -> None:
    faults = FaultConfig(duplicate=0.5, delay=0.2, delay_s=0.005, reorder=0.2, seed=5)
    rig = make_rig("controller_ii", bridge_faults=faults)
    for k in range(5):
        res = rig.client.apply(ramp(k))
        assert res.values == rig.ecu.active == rig.codec.quantize(ramp(k))
    assert rig.client.stats.stale_frames + rig.client.stats.unexpected_frames > 0


def test_an_ecu_that_acknowledges_without_applying_is_caught_by_the_read_back(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i")
    engine = rig.ecu.engine
    honest = engine.handle

    def lying(data: bytes) -> list[bytes]:
        req = decode_request(data) if len(data) == 8 else None
        if isinstance(req, Commit):  # echo a perfect ACK, apply nothing
            return [encode(Ack(req.seq, req.count, req.crc))]
        return honest(data)

    engine.handle = lying  # type: ignore[method-assign]
    with pytest.raises(BridgeError, match="read-back of damping_front") as err:
        rig.client.apply({"damping_front": 0.2, "damping_rear": 0.5})
    assert err.value.code == ErrorCode.CRC_MISMATCH
    assert err.value.uncertain
    assert rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}


class EchoTrustingClient(CalibrationClient):
    """A client whose read-back takes any value the ECU reports (to see what the result is built from)."""

    def _match_read_expected(self, raw: dict[int, int]) -> Any:
        return lambda resp: (resp.index, resp.raw) if isinstance(resp, Value) and resp.index in raw else None

    def _check_read_back(self, got: Any, crc: int) -> None:
        pass


def test_the_result_reports_what_the_ecu_echoed_not_the_request(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i")
    engine = rig.ecu.engine
    honest = engine.handle

    def off_by_one(data: bytes) -> list[bytes]:  # the ECU reads damping_front back one LSB higher
        out = honest(data)
        resp = decode_response(out[0]) if out else None
        if isinstance(resp, Value) and resp.index == 0:
            return [encode(Value(resp.seq, 0, resp.raw + 1))]
        return out

    engine.handle = off_by_one  # type: ignore[method-assign]
    client = EchoTrustingClient(rig.bridge_bus, rig.codec, config=FAST)
    res = client.apply({"damping_front": 0.2, "damping_rear": 0.5})
    assert res.raw == {0: 2001, 1: 5000}  # the read-back, not the request's 2000
    assert res.values == {"damping_front": pytest.approx(0.2001), "damping_rear": 0.5}
    assert res.crc == rig.ecu.active_crc  # the CRC the ECU acknowledged
    assert rig.ecu.active == {"damping_front": 0.2, "damping_rear": 0.5}  # (what it really holds)


def test_sequence_numbers_resynchronize_with_the_ecu(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i", seq=9)
    rig.client.apply({"damping_front": 0.2, "damping_rear": 0.2})  # transaction 10
    late = CalibrationClient(rig.bridge_bus, rig.codec, config=FAST, seq=9)  # a restarted bridge reusing 10
    res = late.apply({"damping_front": 0.3, "damping_rear": 0.3})
    assert res.attempts == 2 and res.seq == 11
    assert late.stats.nack_reasons == {"SEQUENCE": 1}


def test_a_refused_begin_never_resynchronizes_onto_the_refused_number(make_rig: RigFactory) -> None:
    """Transaction 10 is open at the ECU for 1 parameter; a bridge whose next number is 10 asks for 2."""
    rig = make_rig("controller_i")
    assert rig.ecu.engine.handle(encode(Begin(10, 1)))  # an earlier bridge opened 10 and went away
    client = CalibrationClient(rig.bridge_bus, rig.codec, config=FAST, seq=9)
    res = client.apply({"damping_front": 0.3, "damping_rear": 0.3})
    assert res.attempts == 2 and res.seq != 10
    assert client.apply({"damping_front": 0.4, "damping_rear": 0.4}).attempts == 1  # and every apply after it
    assert rig.ecu.active == {"damping_front": 0.4, "damping_rear": 0.4}


def test_the_client_ignores_a_resynchronization_onto_a_number_refused_in_the_same_apply(
    make_rig: RigFactory,
) -> None:
    """An ECU that names the very number it refused (the first engine did) does not trap the bridge."""
    rig = make_rig("controller_i")
    engine = rig.ecu.engine
    honest = engine.handle

    def names_the_refused(data: bytes) -> list[bytes]:
        out = honest(data)
        req = decode_request(data) if len(data) == 8 else None
        resp = decode_response(out[0]) if out else None
        if isinstance(req, Begin) and isinstance(resp, Nack) and resp.reason == Reason.SEQUENCE:
            return [encode(Nack(resp.seq, resp.request_op, resp.reason, 0, req.seq))]
        return out

    engine.handle = names_the_refused  # type: ignore[method-assign]
    CalibrationClient(rig.bridge_bus, rig.codec, config=FAST, seq=9).apply({"damping_front": 0.2, "damping_rear": 0.2})
    late = CalibrationClient(rig.bridge_bus, rig.codec, config=FAST, seq=9)  # reuses 10: refused, "use 10"
    res = late.apply({"damping_front": 0.3, "damping_rear": 0.3})
    assert res.attempts == 2 and res.seq == 11
    assert late.apply({"damping_front": 0.4, "damping_rear": 0.4}).attempts == 1


class BrokenBus(can.BusABC):
    """An adapter that was unplugged: every send fails."""

    def __init__(self) -> None:
        super().__init__(channel="broken")
        self.channel_info = "broken"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("Network is down [Error Code 100]")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def test_bus_failures_surface_as_bus_errors() -> None:
    bus = BrokenBus()
    client = CalibrationClient(bus, CalibrationCodec(load("controller_i")), config=FAST)
    with pytest.raises(BusError, match="Network is down") as err:
        client.apply({"damping_front": 0.2, "damping_rear": 0.2})
    assert err.value.code == ErrorCode.BUS
    bus.shutdown()


def test_error_codes_match_the_service_definition() -> None:
    from bac_msgs.srv import ApplyCalibration

    for code in ErrorCode:
        assert getattr(ApplyCalibration.Response, f"ERROR_{code.name}") == int(code)


def test_frames_carry_the_current_sequence_number(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i", seq=41)
    sniffer = rig.sniffer()
    rig.client.apply({"damping_front": 0.2, "damping_rear": 0.2})
    seqs = set()
    while (msg := sniffer.recv(timeout=0.2)) is not None:
        seqs.add(msg.data[2])
    assert seqs == {42}
    assert decode_request(encode(Commit(42, 2, 0))).seq == 42


def test_resynchronization_lands_on_a_free_number_even_when_the_next_one_is_taken(make_rig: RigFactory) -> None:
    rig = make_rig("controller_i")
    for seq in (40, 41, 42, 39):  # transactions whose numbers the ECU remembers; the most recent is 39
        CalibrationClient(rig.bridge_bus, rig.codec, config=FAST, seq=seq - 1).apply(
            {"damping_front": 0.2, "damping_rear": seq / 100}
        )
    late = CalibrationClient(rig.bridge_bus, rig.codec, config=FAST, seq=40)  # would begin 41: taken
    res = late.apply({"damping_front": 0.3, "damping_rear": 0.3})
    assert res.attempts == 2 and res.seq == 43
