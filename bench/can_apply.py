"""Benchmark: a 20-parameter apply (controller II) on python-can's virtual bus, clean and at 10 % frame loss,
for both protocols of the bridge side by side: bac's own and ASAM XCP on CAN.

The bridge's clients with their default settings (bac: 25 ms step timeout, 5 re-sends, 3 transactions,
read-back on; XCP: pyxcp as the master, 10 ms step timeout (XCP's T1), 20 ms settle_s, the reference page
while writing, BUILD_CHECKSUM and read-back, a page switch as the commit) against the simulated ECUs
(bac_sim.ecu, bac_sim.xcp_ecu) on their own threads. The loss is applied to every frame, both directions, on
the bridge's side. The baseline, measured in the same run, is one request/response round trip over the same
bus (a bac STATUS request), so the ratios say how many round trips an apply costs.

    .venv/bin/python bench/can_apply.py [--applies 500] [--seed 1]

Last line: ``apply_ms median <clean median> p99_at_10pct_loss <p99 at 10 % loss>`` of XCP (goal: <= 50 and
<= 500).
"""

from __future__ import annotations

import argparse
import random
import statistics
import time
from pathlib import Path

import can
import numpy as np

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.client import CalibrationClient, ClientConfig
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.protocol import CalibrationCodec
from bac_ecu_bridge.xcp.client import XcpCalibrationClient
from bac_sim.ecu import SimulatedEcu
from bac_sim.xcp_ecu import SimulatedXcpEcu

ROOT = Path(__file__).resolve().parents[1]


def run(protocol: str, n: int, loss: float, seed: int, channel: str) -> tuple[np.ndarray, int, int]:
    definition = CalibrationDefinition.load(ROOT / "ros_ws/config/calibrations/controller_ii.yaml")
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    ecu: SimulatedEcu | SimulatedXcpEcu = (
        SimulatedXcpEcu(ecu_bus, definition) if protocol == "xcp" else SimulatedEcu(ecu_bus, definition)
    )
    ecu.start()
    bus: can.BusABC = can.Bus(interface="virtual", channel=channel)
    if loss:
        bus = FaultyBus(bus, FaultConfig(drop=loss, seed=seed))
    codec = CalibrationCodec(definition)
    client: CalibrationClient | XcpCalibrationClient = (
        XcpCalibrationClient(bus, definition)
        if protocol == "xcp"
        else CalibrationClient(bus, codec, config=ClientConfig())
    )
    rng = random.Random(seed)
    latencies = []
    failures = wrong = 0
    try:
        for _ in range(n):
            want = {p.name: rng.uniform(p.lower, p.upper) for p in codec.params}
            t0 = time.perf_counter()
            try:
                res = client.apply(want)
            except Exception:
                failures += 1
                latencies.append(time.perf_counter() - t0)
                continue
            latencies.append(time.perf_counter() - t0)
            if res.values != codec.quantize(want) or ecu.active != res.values:
                wrong += 1
    finally:
        if isinstance(client, XcpCalibrationClient):
            client.close()
        ecu.stop()
        bus.shutdown()
        ecu_bus.shutdown()
    return np.asarray(latencies) * 1e3, failures, wrong


def round_trip_ms(n: int, channel: str) -> float:
    definition = CalibrationDefinition.load(ROOT / "ros_ws/config/calibrations/controller_ii.yaml")
    ecu_bus = can.Bus(interface="virtual", channel=channel)
    ecu = SimulatedEcu(ecu_bus, definition)
    ecu.start()
    bus = can.Bus(interface="virtual", channel=channel)
    client = CalibrationClient(bus, CalibrationCodec(definition))
    try:
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            client.status()
            times.append(time.perf_counter() - t0)
    finally:
        ecu.stop()
        bus.shutdown()
        ecu_bus.shutdown()
    return statistics.median(times) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--applies", type=int, default=500, help="applies per condition")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    rt = round_trip_ms(200, "bench-rt")
    print(f"baseline: one request/response round trip on the virtual bus, median {rt:.3f} ms")
    figures = {}
    for protocol in ("bac", "xcp"):
        clean, clean_fail, clean_wrong = run(protocol, args.applies, 0.0, args.seed, f"bench-clean-{protocol}")
        lossy, lossy_fail, lossy_wrong = run(protocol, args.applies, 0.10, args.seed, f"bench-loss-{protocol}")
        med = float(np.median(clean))
        p99 = float(np.percentile(lossy, 99))
        figures[protocol] = (med, p99)
        print(
            f"{protocol:3s} clean:     {args.applies} applies, median {med:.2f} ms ({med / rt:.1f} round trips), "
            f"p99 {np.percentile(clean, 99):.2f} ms, failures {clean_fail}, false acknowledgments {clean_wrong}"
        )
        print(
            f"{protocol:3s} 10 % loss: {args.applies} applies, median {np.median(lossy):.2f} ms "
            f"({np.median(lossy) / rt:.1f} round trips), p99 {p99:.2f} ms ({p99 / rt:.1f} round trips), "
            f"max {lossy.max():.2f} ms, failures {lossy_fail}, false acknowledgments {lossy_wrong}"
        )
    med, p99 = figures["xcp"]
    verdict = ("met" if med <= 50 else "MISSED", "met" if p99 <= 500 else "MISSED")
    print(f"goal (xcp): median <= 50 ms ({verdict[0]}), p99 <= 500 ms ({verdict[1]})")
    print(f"apply_ms median {med:.2f} p99_at_10pct_loss {p99:.2f}")


if __name__ == "__main__":
    main()
