"""Opening a python-can bus from the settings users give (profile, node parameters, command line).

One place knows which python-can interface takes which options: ``virtual``
(one process), ``udp_multicast`` (between processes, only inside a private
network namespace), and the adapters of the car: ``socketcan`` (bitrate set
with ``ip link``), ``pcan``, ``kvaser``, ``vector``, ``ixxat``, ``slcan``,
``gs_usb``, ... (bitrate passed to the driver).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from bac_ecu_bridge.errors import BusError
from bac_ecu_bridge.protocol import CanIds

# interfaces whose bitrate is not set by python-can (virtual buses; socketcan uses `ip link set canX type can bitrate`)
_NO_BITRATE = frozenset({"virtual", "udp_multicast", "socketcan", "socketcand"})


@dataclass(frozen=True)
class BusSettings:
    interface: str = "virtual"
    channel: str = "bac"
    bitrate: int = 500_000
    receive_own_messages: bool = False
    port: int = 0  # udp_multicast: UDP port (0 = python-can's default 43113)
    options: dict[str, Any] = field(default_factory=dict)  # any further python-can constructor options

    def describe(self) -> str:
        return f"{self.interface}:{self.channel}" + ("" if self.interface in _NO_BITRATE else f"@{self.bitrate}")


def bus_kwargs(settings: BusSettings) -> dict[str, Any]:
    """The python-can constructor arguments for ``settings`` (classic CAN, FD off)."""
    kw: dict[str, Any] = {"interface": settings.interface, "channel": settings.channel}
    if settings.interface == "udp_multicast":
        kw["fd"] = False
        if settings.port:
            kw["port"] = settings.port
    elif settings.interface not in _NO_BITRATE:
        kw["bitrate"] = int(settings.bitrate)
        kw["fd"] = False
    elif settings.interface == "socketcan":
        kw["fd"] = False
    if settings.receive_own_messages:
        kw["receive_own_messages"] = True
    kw.update(settings.options)
    return kw


def open_bus(settings: BusSettings, ids: CanIds | None = None) -> can.BusABC:
    """Open the bus, filtered to the protocol's response id when ``ids`` is given (the bridge's view).

    Raises :class:`BusError` with what to check when the interface cannot be opened.
    """
    kw = bus_kwargs(settings)
    if ids is not None:
        mask = 0x1FFF_FFFF if ids.extended else 0x7FF
        kw["can_filters"] = [{"can_id": ids.response_id, "can_mask": mask, "extended": ids.extended}]
    try:
        return can.Bus(**kw)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        hint = {
            "socketcan": f"is the adapter plugged in and '{settings.channel}' up (ip link set {settings.channel} up "
            f"type can bitrate {settings.bitrate})?",
            "udp_multicast": "udp_multicast needs msgpack and a multicast route (run inside the private network "
            "namespace: python -m bac_bringup.netns -- ...)",
        }.get(settings.interface, "is the adapter plugged in, its driver installed and the channel name right?")
        raise BusError(f"cannot open CAN interface {settings.describe()}: {exc}; {hint}") from exc


class TracedBus(can.BusABC):
    """A bus that writes every frame it sends and receives to a trace file (python-can's ``can.Logger``).

    The format follows the extension: ``.asc`` (Vector, CANalyzer / CANape),
    ``.blf``, ``.log`` (candump -L, SavvyCAN / can-utils), ``.csv``, ``.trc``
    (PEAK), ``.mf4``. Decode it with the project's DBC (docs/ecu_bridge.md).
    """

    def __init__(self, inner: can.BusABC, path: str | Path, *, owns_inner: bool = True, **kwargs: Any) -> None:
        self.inner = inner
        self.owns_inner = owns_inner
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = can.Logger(str(self.path))
        self._lock = threading.Lock()
        self._ready = False
        self.channel_info = f"traced({inner.channel_info} -> {self.path})"
        super().__init__(channel=getattr(inner, "channel", None) or inner.channel_info, **kwargs)
        self._can_protocol = inner.protocol
        self._ready = True

    def _log(self, msg: can.Message, rx: bool) -> None:
        entry = can.Message(
            timestamp=msg.timestamp if rx and msg.timestamp else time.time(),
            arbitration_id=msg.arbitration_id,
            is_extended_id=msg.is_extended_id,
            is_remote_frame=msg.is_remote_frame,
            is_error_frame=msg.is_error_frame,
            dlc=msg.dlc,
            data=bytes(msg.data),
            is_rx=rx,
            channel=0,
        )
        with self._lock:
            self._writer.on_message_received(entry)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)
        self._log(msg, rx=False)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout=timeout)
        if msg is not None:
            self._log(msg, rx=True)
        return msg, True

    def _apply_filters(self, filters: Any) -> None:
        if getattr(self, "_ready", False):
            self.inner.set_filters(filters)

    @property  # type: ignore[misc]
    def state(self) -> can.BusState:
        return self.inner.state

    def flush(self) -> None:
        """Write what is buffered to the file (the trace stays open)."""
        with self._lock:
            fn = getattr(self._writer, "flush", None) or getattr(getattr(self._writer, "file", None), "flush", None)
            if fn is not None:
                fn()

    def shutdown(self) -> None:
        with self._lock:
            self._writer.stop()
        super().shutdown()
        if self.owns_inner:
            self.inner.shutdown()
