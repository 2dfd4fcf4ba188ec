"""Helpers of the XCP tests: pyxcp (the bridge's XcpCalibrationClient) and the simulated XCP ECU on a virtual bus."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import can
import pytest
from bridge_rig import load

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.xcp.client import XcpCalibrationClient, XcpConfig, XcpSettings
from bac_sim.xcp_ecu import SimulatedXcpEcu

_CHANNELS = itertools.count()

# in-process virtual bus: a round trip takes a fraction of a millisecond; 50 ms leaves room for a loaded machine
XFAST = XcpConfig(step_timeout_s=0.05, step_retries=5, max_attempts=3, timeout_s=5.0, settle_timeout_s=3.0)


@dataclass
class XcpRig:
    client: XcpCalibrationClient
    ecu: SimulatedXcpEcu
    definition: CalibrationDefinition
    channel: str
    bridge_bus: can.BusABC
    ecu_bus: can.BusABC
    closers: list[Callable[[], None]] = field(default_factory=list)

    def sniffer(self) -> can.BusABC:
        bus = can.Bus(interface="virtual", channel=self.channel)
        self.closers.append(bus.shutdown)
        return bus

    def client_with(self, **kw: Any) -> XcpCalibrationClient:
        """Another client on the bridge's bus (the first one is closed)."""
        self.client.close()
        self.client = XcpCalibrationClient(self.bridge_bus, self.definition, **kw)
        return self.client


XcpRigFactory = Callable[..., XcpRig]


def xcp_rig_factory() -> tuple[XcpRigFactory, Callable[[], None]]:
    rigs: list[XcpRig] = []

    def make(  # ecu_options go to SimulatedXcpEcu (key_algorithm: the ECU's seed & key), client_key to the client
        definition: CalibrationDefinition | str = "controller_ii",
        *,
        ecu_faults: FaultConfig | None = None,
        bridge_faults: FaultConfig | None = None,
        config: XcpConfig = XFAST,
        settings: XcpSettings | None = None,
        client_key: Any = None,
        **ecu_options: Any,
    ) -> XcpRig:
        d = load(definition) if isinstance(definition, str) else definition
        channel = f"xcp-test-{next(_CHANNELS)}"
        ecu_bus: can.BusABC = can.Bus(interface="virtual", channel=channel)
        if ecu_faults is not None:
            ecu_bus = FaultyBus(ecu_bus, ecu_faults)
        bridge_bus: can.BusABC = can.Bus(interface="virtual", channel=channel)
        if bridge_faults is not None:
            bridge_bus = FaultyBus(bridge_bus, bridge_faults)
        ecu = SimulatedXcpEcu(ecu_bus, d, **ecu_options)
        ecu.start()
        client = XcpCalibrationClient(bridge_bus, d, settings, config, key_algorithm=client_key)
        rig = XcpRig(client, ecu, d, channel, bridge_bus, ecu_bus)
        rigs.append(rig)
        return rig

    def close() -> None:
        for rig in rigs:
            rig.client.close()
            rig.ecu.stop()
            rig.ecu_bus.shutdown()
            rig.bridge_bus.shutdown()
            for closer in rig.closers:
                closer()

    return make, close


@pytest.fixture(name="make_xcp_rig")
def make_xcp_rig_fixture() -> Iterator[XcpRigFactory]:
    make, close = xcp_rig_factory()
    try:
        yield make
    finally:
        close()
