"""1,000 applies through a bus that loses or garbles 30 % of the frames: never a false acknowledgment.

Each apply either succeeds with exactly the requested values (after
quantization) in force in the ECU, or fails within its bounded time; and a
failed apply leaves the ECU on a calibration it was allowed to hold (the
previous one; or the requested one when the client reported the state as
uncertain). Four client/ECU pairs run side by side on python-can virtual buses,
with a fast step timeout, to keep the test short.

A negative control runs the same campaign with a client that skips the
sequence, CRC and read-back checks: the harness must catch it.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest
from bridge_rig import Rig, rig_factory

from bac_common.paramspace import CalibrationDefinition, RawParameter
from bac_ecu_bridge.client import CalibrationClient, ClientConfig
from bac_ecu_bridge.errors import BridgeError, ErrorCode, FrameError
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.protocol import Ack, Op, Response, decode_response

DEFINITION = CalibrationDefinition(
    "campaign",
    (
        RawParameter("gain", 0, -50.0, 50.0, 0.0, 0.01),
        RawParameter("cutoff", 1, 0.5, 20.0, 5.0, 0.5),
        RawParameter("damping", 2, 0.0, 1.0, 0.5, 0.0001),
        RawParameter("offset", 3, 0.0, 1000.0, 500.0, 0.01),
    ),
)
# 30 % of the frames lost (15 %) or garbled (15 %), both directions, plus duplicates, delays and reordering
FAULTS = FaultConfig(drop=0.15, corrupt=0.15, duplicate=0.05, delay=0.05, delay_s=0.01, reorder=0.05)
CONFIG = ClientConfig(step_timeout_s=0.003, step_retries=8, max_attempts=3, timeout_s=1.0)
# a tight budget makes applies fail often, to check that failures are bounded in time and leave a sane state
TIGHT = ClientConfig(step_timeout_s=0.003, step_retries=2, max_attempts=1, timeout_s=0.05)
SLACK_S = 0.5  # scheduling slack on a loaded machine, on top of the bounded time


@dataclass
class Tally:
    applies: int = 0
    successes: int = 0
    false_acks: int = 0
    failures: dict[str, int] = field(default_factory=dict)
    uncertain: int = 0
    by_config: dict[str, list[int]] = field(default_factory=dict)  # config name -> [successes, applies]
    overtime: int = 0
    wrong_state: int = 0
    worst_failure_s: float = 0.0
    notes: list[str] = field(default_factory=list)


def campaign(rig: Rig, n: int, seed: int, tally: Tally, lock: threading.Lock, name: str = "") -> None:
    rng = random.Random(seed)
    budget = rig.client.config.timeout_s
    with lock:
        tally.by_config.setdefault(name, [0, 0])
    codec = rig.codec
    for _ in range(20):  # the bridge reads the ECU first, as the node does when it starts
        try:
            rig.client.read_active()
            break
        except BridgeError:
            continue
    for _ in range(n):
        want = {p.name: rng.uniform(p.lower, p.upper) for p in codec.params}
        quantized = codec.quantize(want)
        t0 = time.monotonic()
        try:
            res = rig.client.apply(want)
        except BridgeError as err:
            elapsed = time.monotonic() - t0
            active = rig.ecu.active
            state = err.ecu_state  # what the bridge reports the ECU holds after the failure
            with lock:
                tally.applies += 1
                tally.by_config[name][1] += 1
                tally.failures[err.code.name] = tally.failures.get(err.code.name, 0) + 1
                tally.uncertain += err.uncertain
                tally.worst_failure_s = max(tally.worst_failure_s, elapsed)
                bound = budget + (rig.client.config.settle_timeout_s if err.uncertain else 0.0)
                if elapsed > bound + SLACK_S:
                    tally.overtime += 1
                if state is None or state.values is None or active != state.values:
                    tally.wrong_state += 1
                    tally.notes.append(f"failed apply ({err}) left {active}, reported {state}")
            continue
        active = rig.ecu.active
        ok = res.values == quantized and active == quantized and res.crc == codec.crc(want)
        with lock:
            tally.applies += 1
            tally.successes += 1
            tally.by_config[name][0] += 1
            tally.by_config[name][1] += 1
            if not ok:
                tally.false_acks += 1
                tally.notes.append(f"false ack: asked {quantized}, told {res.values}, ECU holds {active}")


def run_campaign(
    total: int,
    client_factory: Callable[[Rig], CalibrationClient] | None = None,
    pairs: int = 4,
    faults: FaultConfig = FAULTS,
    configs: dict[str, ClientConfig] | None = None,
) -> tuple[Tally, list[Rig]]:
    """``total`` applies over ``pairs`` client/ECU pairs (threads); pair k uses the k-th of ``configs``."""
    configs = configs or {"generous": CONFIG}
    names = [list(configs)[k % len(configs)] for k in range(pairs)]
    make, close = rig_factory()
    tally = Tally()
    lock = threading.Lock()
    rigs = [
        make(
            DEFINITION,
            bridge_faults=FaultConfig(**{**faults.__dict__, "seed": 100 + k}),
            config=configs[names[k]],
            seq=k * 64,
        )
        for k in range(pairs)
    ]
    if client_factory is not None:
        for rig in rigs:
            rig.client = client_factory(rig)
    try:
        threads = [
            threading.Thread(target=campaign, args=(rig, total // pairs, k, tally, lock, names[k]))
            for k, rig in enumerate(rigs)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        close()
    return tally, rigs


def test_1000_applies_at_30_percent_faults_never_acknowledge_falsely() -> None:
    tally, rigs = run_campaign(1000, configs={"generous": CONFIG, "tight": TIGHT})
    print(
        f"\n{tally.applies} applies: {tally.successes} succeeded ({tally.by_config}), failures {tally.failures}, "
        f"{tally.uncertain} uncertain, worst failure {tally.worst_failure_s:.3f} s, false acks {tally.false_acks}"
    )
    assert tally.applies == 1000
    assert tally.false_acks == 0, tally.notes[:5]
    assert tally.wrong_state == 0, tally.notes[:5]
    assert tally.overtime == 0
    assert set(tally.failures) <= {ErrorCode.TIMEOUT.name, ErrorCode.CRC_MISMATCH.name, ErrorCode.SEQUENCE.name}
    # the faults were real; with a generous budget the protocol still got almost everything through,
    # with the tight one many applies failed, each within its time and leaving an allowed state
    ok, n = tally.by_config["generous"]
    assert n == 500 and ok >= 490
    ok, n = tally.by_config["tight"]
    assert n == 500 and n - ok >= 20
    assert tally.uncertain > 0
    for rig in rigs:
        counts = rig.bridge_bus.counts  # type: ignore[attr-defined]
        assert 0.12 < counts.dropped / counts.frames < 0.18
        assert 0.12 < counts.corrupted / counts.frames < 0.18
        assert counts.duplicated > 0 and counts.delayed > 0 and counts.reordered > 0
        stats = rig.client.stats
        assert stats.invalid_frames > 0 and stats.stale_frames > 0 and stats.retransmissions > 0


class LaxClient(CalibrationClient):
    """A naive bridge: takes replies of any transaction and any ACK, keeps old replies, reads nothing back."""

    def _recv(self, timeout: float, seq: int) -> Response | None:
        msg = self.bus.recv(timeout=max(0.0, timeout))
        if msg is None or msg.arbitration_id != self.ids.response_id:
            return None
        try:
            return decode_response(msg.data)
        except FrameError:
            return None

    def _drain(self) -> None:
        pass

    def _match_commit(self, n: int, crc: int, state: object) -> Callable[[Response], tuple[int, Ack] | None]:  # type: ignore[override]
        return lambda resp: (0, resp) if isinstance(resp, Ack) else None


def lax(rig: Rig) -> CalibrationClient:
    config = ClientConfig(**{**CONFIG.__dict__, "verify_readback": False})
    return LaxClient(rig.bridge_bus, rig.codec, config=config, seq=rig.client.seq)


def test_the_harness_catches_a_client_without_the_checks() -> None:
    # commits get lost and acknowledgments arrive late and twice: a naive client takes an earlier
    # transaction's ACK for its own lost commit
    faults = FaultConfig(
        drop=0.3, duplicate=0.5, delay=0.5, delay_s=0.03, ops=(int(Op.COMMIT), int(Op.ACK)), direction="both"
    )
    tally, _ = run_campaign(200, client_factory=lax, pairs=2, faults=faults)
    assert tally.false_acks > 0
    # and the real client under the same faults stays clean
    tally, _ = run_campaign(200, pairs=2, faults=faults)
    assert tally.false_acks == 0 and tally.wrong_state == 0


def test_a_faulty_ecu_side_too() -> None:
    """Faults on the ECU's own bus (its receive and send), the bridge's bus clean."""
    make, close = rig_factory()
    try:
        rig = make(DEFINITION, ecu_faults=FaultConfig(drop=0.15, corrupt=0.15, seed=9), config=CONFIG)
        tally = Tally()
        campaign(rig, 100, 9, tally, threading.Lock())
    finally:
        close()
    assert tally.false_acks == 0 and tally.wrong_state == 0
    assert tally.successes >= 95
    assert isinstance(rig.ecu_bus, FaultyBus) and rig.ecu_bus.counts.corrupted > 0


@pytest.mark.parametrize("pairs", [1])
def test_campaign_helper_counts_every_apply(pairs: int) -> None:
    tally, _ = run_campaign(8, pairs=pairs)
    assert tally.applies == 8
