"""Helpers of the ECU bridge tests: a client and a simulated ECU on a python-can virtual bus (``make_rig``)."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import pytest

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.client import CalibrationClient, ClientConfig
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.protocol import CalibrationCodec
from bac_sim.ecu import SimulatedEcu

ROOT = Path(__file__).resolve().parents[2]
CALIBRATIONS = ROOT / "ros_ws" / "config" / "calibrations"
_CHANNELS = itertools.count()

# settings for in-process tests: the virtual bus answers in well under a millisecond, 50 ms leaves room for a
# loaded machine
FAST = ClientConfig(step_timeout_s=0.05, step_retries=5, max_attempts=3, timeout_s=5.0)


def load(name: str) -> CalibrationDefinition:
    return CalibrationDefinition.load(CALIBRATIONS / f"{name}.yaml")


@dataclass
class Rig:
    client: CalibrationClient
    ecu: SimulatedEcu
    codec: CalibrationCodec
    channel: str
    bridge_bus: can.BusABC
    ecu_bus: can.BusABC
    closers: list[Callable[[], None]] = field(default_factory=list)

    def sniffer(self) -> can.BusABC:
        bus = can.Bus(interface="virtual", channel=self.channel)
        self.closers.append(bus.shutdown)
        return bus


RigFactory = Callable[..., Rig]


def rig_factory() -> tuple[RigFactory, Callable[[], None]]:
    """A factory of rigs and the function that closes every rig it made."""
    rigs: list[Rig] = []

    def make(
        definition: CalibrationDefinition | str = "controller_ii",
        *,
        ecu_definition: CalibrationDefinition | None = None,
        ecu_faults: FaultConfig | None = None,
        bridge_faults: FaultConfig | None = None,
        config: ClientConfig = FAST,
        seq: int | None = None,
        **ecu_options: object,
    ) -> Rig:
        d = load(definition) if isinstance(definition, str) else definition
        channel = f"bridge-test-{next(_CHANNELS)}"
        ecu_bus: can.BusABC = can.Bus(interface="virtual", channel=channel)
        if ecu_faults is not None:
            ecu_bus = FaultyBus(ecu_bus, ecu_faults)
        bridge_bus: can.BusABC = can.Bus(interface="virtual", channel=channel)
        if bridge_faults is not None:
            bridge_bus = FaultyBus(bridge_bus, bridge_faults)
        ecu = SimulatedEcu(ecu_bus, ecu_definition or d, **ecu_options)
        ecu.start()
        codec = CalibrationCodec(d)
        client = CalibrationClient(bridge_bus, codec, config=config, seq=seq)
        rig = Rig(client, ecu, codec, channel, bridge_bus, ecu_bus)
        rigs.append(rig)
        return rig

    def close() -> None:
        for rig in rigs:
            rig.ecu.stop()
            rig.ecu_bus.shutdown()
            rig.bridge_bus.shutdown()
            for closer in rig.closers:
                closer()

    return make, close


@pytest.fixture(name="make_rig")
def make_rig_fixture() -> Iterator[RigFactory]:
    """Rigs made in a test, closed at its end (import this fixture into the test module)."""
    make, close = rig_factory()
    try:
        yield make
    finally:
        close()
