"""Benchmark: the issue's fault campaign (issue 18): applies of random in-bounds 20-parameter calibrations
(Controller II) through buses that drop, corrupt, delay, duplicate and reorder frames, for ASAM XCP on CAN and
for the bac protocol, and the counts that matter for safety.

Several client/ECU pairs run side by side on python-can virtual buses (threads of one process), the faults on
the bridge's side of even pairs and on the ECU's side of odd ones (both directions of that side). The simulated
ECUs (bac_sim.xcp_ecu, bac_sim.ecu) report every change of the calibration their application uses, so a value
outside the declared bounds is seen even when it is in use for a moment only.

    .venv/bin/python bench/xcp_fault_campaign.py [--applies 2000] [--protocols xcp,bac] [--pairs 4]
        [--faults drop=0.15,corrupt=0.15,duplicate=0.05,delay=0.05,delay_s=0.01,reorder=0.05] [--seed 0]
        [--timeout 3.0]

Counts per protocol: successes; false successes (reported applied, but the ECU, or the result, holds other
values than the quantized request); failures, the worst failure time against its bound (``timeout_s``, plus
``settle_timeout_s`` when the outcome had to be settled); failures whose state the bridge reports UNKNOWN
(it could not read the ECU back within the bound: the node then keeps the baseline restore pending and the
agent scores no run); unreported states (the bridge names values the ECU does not hold); out-of-bounds ECU
states (the ECU application ran on a value outside the declared bounds at any moment, and at the end of an
apply). Between applies each client is asked its status() once, as the node does every diagnostics period.
The last line is one JSON object per protocol.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import random
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.backend import Holds
from bac_ecu_bridge.client import CalibrationClient, ClientConfig
from bac_ecu_bridge.errors import BridgeError
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.protocol import CalibrationCodec
from bac_ecu_bridge.xcp.client import XcpCalibrationClient, XcpConfig
from bac_sim.ecu import SimulatedEcu
from bac_sim.xcp_ecu import SimulatedXcpEcu

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FAULTS = "drop=0.15,corrupt=0.15,duplicate=0.05,delay=0.05,delay_s=0.01,reorder=0.05"
# the same budget for both protocols: 10 ms per step, 8 repeats, 3 attempts, 3 s per apply, 3 s to settle; XCP's
# settle_s is the fault bus's worst delay (a frame held back for reordering is released after 50 ms, plus
# the scheduling of a loaded machine's threads)
XCP_CONFIG = XcpConfig(
    step_timeout_s=0.01, step_retries=8, max_attempts=3, timeout_s=3.0, settle_timeout_s=3.0, settle_s=0.1
)
BAC_CONFIG = ClientConfig(step_timeout_s=0.01, step_retries=8, max_attempts=3, timeout_s=3.0, settle_timeout_s=3.0)
_CHANNELS = itertools.count()


@dataclass
class Tally:
    protocol: str
    applies: int = 0
    successes: int = 0
    false_successes: int = 0
    failures: int = 0
    failure_codes: dict[str, int] = field(default_factory=dict)
    uncertain: int = 0
    unknown: int = 0  # failures whose state the bridge reports as unknown
    unreported: int = 0  # failures whose reported state differs from what the ECU holds
    overtime: int = 0  # failures beyond their bound (+ scheduling slack)
    worst_failure_s: float = 0.0
    bound_s: float = 0.0
    out_of_bounds_in_use: int = 0  # changes of what the ECU application uses that put a value outside the bounds
    out_of_bounds_at_end: int = 0  # applies after which the ECU application holds a value outside the bounds
    restored_in_settlement: int = 0  # XCP: settlements that switched the ECU back to its reference page
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


def in_bounds(definition: CalibrationDefinition, values: dict[str, float]) -> bool:
    return all(definition.parameter(k).lower <= v <= definition.parameter(k).upper for k, v in values.items())


def pair(protocol: str, definition: CalibrationDefinition, faults: FaultConfig, bridge_side: bool, watch: Any) -> Any:
    channel = f"bench-faults-{next(_CHANNELS)}"
    ecu_bus: can.BusABC = can.Bus(interface="virtual", channel=channel)
    bridge_bus: can.BusABC = can.Bus(interface="virtual", channel=channel)
    if bridge_side:
        bridge_bus = FaultyBus(bridge_bus, faults)
    else:
        ecu_bus = FaultyBus(ecu_bus, faults)
    ecu: Any
    client: Any
    if protocol == "xcp":
        ecu = SimulatedXcpEcu(ecu_bus, definition, on_commit=watch)
        client = XcpCalibrationClient(bridge_bus, definition, config=XCP_CONFIG)
    else:
        ecu = SimulatedEcu(ecu_bus, definition, on_commit=watch)
        client = CalibrationClient(bridge_bus, CalibrationCodec(definition), config=BAC_CONFIG)
    ecu.start()

    def close() -> None:
        if isinstance(client, XcpCalibrationClient):
            client.close()
        ecu.stop()
        bridge_bus.shutdown()
        ecu_bus.shutdown()

    return client, ecu, close


def poll(client: Any) -> None:
    """What the node asks between applies, every diagnostics period: which set the ECU uses (its CRC-32)."""
    try:
        client.status(timeout_s=0.25)  # the node's bound: min(0.25 s, half the diagnostics period)
    except BridgeError:
        pass  # the node counts it as "not answering" and goes on


def campaign(
    protocol: str, client: Any, ecu: Any, definition: CalibrationDefinition, n: int, seed: int, tally: Tally, lock: Any
) -> None:
    rng = random.Random(seed)
    config = client.config
    for _ in range(20):  # the bridge reads the ECU first, as the node does when it starts
        try:
            client.read_active()
            break
        except BridgeError:
            continue
    for k in range(n):
        if k:
            poll(client)
        want = {p.name: rng.uniform(p.lower, p.upper) for p in definition.parameters}
        quantized = client.quantize(want) if protocol == "xcp" else CalibrationCodec(definition).quantize(want)
        t0 = time.monotonic()
        try:
            res = client.apply(want)
        except BridgeError as err:
            elapsed = time.monotonic() - t0
            active = ecu.active
            state = err.ecu_state
            bound = config.timeout_s + (config.settle_timeout_s if (err.uncertain or protocol == "xcp") else 0.0)
            with lock:
                tally.applies += 1
                tally.failures += 1
                tally.failure_codes[err.code.name] = tally.failure_codes.get(err.code.name, 0) + 1
                tally.uncertain += err.uncertain
                tally.worst_failure_s = max(tally.worst_failure_s, elapsed)
                tally.bound_s = max(tally.bound_s, bound)
                if elapsed > bound + 1.0:
                    tally.overtime += 1
                if state is not None and state.holds is Holds.UNKNOWN:
                    tally.unknown += 1
                elif state is None or state.values is None or state.values != active:
                    tally.unreported += 1
                    tally.notes.append(f"{protocol}: failed apply ({err}) left {active}, reported {state}")
                if not in_bounds(definition, active):
                    tally.out_of_bounds_at_end += 1
            continue
        active = ecu.active
        with lock:
            tally.applies += 1
            tally.successes += 1
            if not (res.values == quantized == active):
                tally.false_successes += 1
                tally.notes.append(f"{protocol}: false success: asked {quantized}, told {res.values}, ECU {active}")
            if not in_bounds(definition, active):
                tally.out_of_bounds_at_end += 1


def run(protocol: str, total: int, pairs: int, faults: FaultConfig, seed: int, progress: float) -> Tally:
    definition = CalibrationDefinition.load(ROOT / "ros_ws/config/calibrations/controller_ii.yaml")
    tally = Tally(protocol)
    lock = threading.Lock()

    def watch(values: dict[str, float]) -> None:
        if not in_bounds(definition, values):
            with lock:
                tally.out_of_bounds_in_use += 1
                tally.notes.append(f"{protocol}: the ECU application ran on {values}")

    rigs = [
        pair(
            protocol,
            definition,
            FaultConfig(**{**faults.__dict__, "seed": seed * 1000 + 100 + k}),
            k % 2 == 0,
            watch,
        )
        for k in range(pairs)
    ]
    t0 = time.monotonic()
    stop = threading.Event()

    def report() -> None:
        while not stop.wait(progress):
            with lock:
                print(
                    f"  {protocol}: {tally.applies}/{total} applies after {time.monotonic() - t0:.0f} s, "
                    f"{tally.successes} succeeded, false {tally.false_successes}, unknown {tally.unknown}, "
                    f"unreported {tally.unreported}, out of bounds {tally.out_of_bounds_in_use}",
                    flush=True,
                )

    reporter = threading.Thread(target=report, daemon=True)
    if progress > 0:
        reporter.start()
    try:
        threads = [
            threading.Thread(
                target=campaign,
                args=(protocol, client, ecu, definition, total // pairs, seed * 1000 + k, tally, lock),
            )
            for k, (client, ecu, _) in enumerate(rigs)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        stop.set()
        for client, _, close in rigs:
            if protocol == "xcp":
                tally.restored_in_settlement += client.stats.restored_in_settle
            close()
    tally.seconds = time.monotonic() - t0
    return tally


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--applies", type=int, default=2000, help="applies per protocol")
    ap.add_argument("--protocols", default="xcp,bac")
    ap.add_argument("--pairs", type=int, default=4, help="client/ECU pairs side by side")
    ap.add_argument("--faults", default=DEFAULT_FAULTS, help="FaultConfig spec (bac_ecu_bridge.faults)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=3.0, help="each apply's overall bound, s (both protocols)")
    ap.add_argument("--progress", type=float, default=60.0, help="print progress every this many seconds (0: no)")
    args = ap.parse_args()
    faults = FaultConfig.parse(args.faults)
    global XCP_CONFIG, BAC_CONFIG  # noqa: PLW0603 (the pairs read them; a bench script, set once here)
    XCP_CONFIG = dataclasses.replace(XCP_CONFIG, timeout_s=args.timeout)
    BAC_CONFIG = dataclasses.replace(BAC_CONFIG, timeout_s=args.timeout)
    print(f"faults on either side: {args.faults}; {args.applies} applies per protocol, {args.pairs} pairs", flush=True)
    results = []
    for protocol in args.protocols.split(","):
        t = run(protocol, args.applies, args.pairs, faults, args.seed, args.progress)
        xcp = protocol == "xcp"
        results.append(t)
        print(
            f"{protocol:3s}: {t.applies} applies in {t.seconds:.0f} s: {t.successes} succeeded, "
            f"false successes {t.false_successes}; {t.failures} failed {t.failure_codes} ({t.uncertain} uncertain), "
            f"worst failure {t.worst_failure_s:.2f} s vs bound {t.bound_s:.1f} s (over it: {t.overtime}); "
            f"state unknown {t.unknown}, unreported states {t.unreported}; out of bounds in use "
            f"{t.out_of_bounds_in_use}, at the end of an apply {t.out_of_bounds_at_end}"
            + (f"; switched back to the reference page while settling {t.restored_in_settlement}" if xcp else ""),
            flush=True,
        )
        for note in t.notes[:5]:
            print(f"    {note[:400]}")
    print(json.dumps([{k: v for k, v in asdict(t).items() if k != "notes"} for t in results]))


if __name__ == "__main__":
    main()
