"""What the two simulated ECUs share: a request/response server on a CAN bus, and their standalone process.

:class:`CanServer` receives requests on one CAN id on a background thread, hands each to the protocol (the bac
protocol's :class:`bac_ecu_bridge.engine.EcuEngine` in :class:`bac_sim.ecu.SimulatedEcu`, the XCP slave in
:class:`bac_sim.xcp_ecu.SimulatedXcpEcu`) under the ECU's lock, and answers on the other id. When the
calibration in force changed, the subclass's :meth:`CanServer._changed_values` reports it and ``on_commit``
gets the new values, outside the lock. :func:`add_common_args`, :func:`open_faulty_bus` and
:func:`serve_until_signalled` are the standalone processes' shared command line, bus and signal handling.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import Protocol

import can

from bac_ecu_bridge.canbus import BusSettings, open_bus
from bac_ecu_bridge.faults import FaultConfig, FaultyBus


class CanServer:
    """Serves a protocol on a CAN bus from a background thread (``start`` / ``stop``).

    Subclasses set the ids (:attr:`request_id`, :attr:`response_id`, :attr:`extended`) and implement
    :meth:`_handle` (under :attr:`_lock`) and :meth:`_changed_values`.
    """

    request_id: int
    response_id: int
    extended: bool

    def __init__(
        self,
        bus: can.BusABC,
        log: logging.Logger,
        label: str,
        reply_delay_s: float,
        on_commit: Callable[[dict[str, float]], None] | None,
        reply_word: str = "reply",
    ) -> None:
        self.bus = bus
        self._reply_word = reply_word  # the log's word for an answer: "reply" (bac protocol), "response" (XCP)
        self.reply_delay_s = reply_delay_s
        self.send_errors = 0
        self._log = log
        self._label = label  # "ECU", "XCP ECU": the log lines' prefix
        self._on_commit = on_commit
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Serve the protocol on a background thread."""
        if self._thread is not None:
            return
        self._stop.clear()
        name = "simulated-" + self._label.lower().replace(" ", "-")
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    # --- what a subclass provides ---------------------------------------------------------------------
    def _handle(self, data: bytes) -> tuple[list[bytes], dict[str, float] | None]:
        """One request (called under :attr:`_lock`): the replies, and the calibration in force if it changed."""
        raise NotImplementedError

    def _changed_values(self, values: dict[str, float]) -> None:
        """The calibration in force changed to ``values`` (called on the server thread, outside the lock,
        before ``on_commit``): log it, take the time a commit takes."""

    # --- serving --------------------------------------------------------------------------------------
    def _accepts(self, msg: can.Message | None) -> bool:
        return (
            msg is not None
            and msg.arbitration_id == self.request_id
            and bool(msg.is_extended_id) == self.extended
            and not msg.is_error_frame
            and not msg.is_remote_frame
        )

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.05)
            except (can.CanError, OSError) as exc:
                self._log.error("%s: receiving failed: %s", self._label, exc)
                self._stop.wait(0.1)
                continue
            if msg is None or not self._accepts(msg):
                continue
            with self._lock:
                replies, values = self._handle(bytes(msg.data))
            if values is not None:
                self._changed_values(values)
                if self._on_commit is not None:
                    try:
                        self._on_commit(values)
                    except Exception:
                        self._log.exception("%s: the on_commit callback failed", self._label)
            if self.reply_delay_s and replies:
                time.sleep(self.reply_delay_s)
            for data in replies:
                try:
                    reply = can.Message(
                        arbitration_id=self.response_id, is_extended_id=self.extended, data=data, is_fd=False
                    )
                    self.bus.send(reply)
                except (can.CanError, OSError) as exc:
                    self.send_errors += 1
                    self._log.warning("%s: sending a %s failed: %s", self._label, self._reply_word, exc)


# --- the standalone processes ----------------------------------------------------------------------------
def add_common_args(ap: argparse.ArgumentParser) -> None:
    """The options both simulated ECUs' processes take: the bus, the definition, faults, driving, delays."""
    ap.add_argument("--interface", default="udp_multicast", help="python-can interface (default udp_multicast)")
    ap.add_argument("--channel", default="239.74.163.2", help="python-can channel (default 239.74.163.2)")
    ap.add_argument("--bitrate", type=int, default=500_000)
    ap.add_argument("--port", type=int, default=0, help="udp_multicast UDP port (default python-can's)")
    ap.add_argument("--definition", required=True, type=Path, help="calibration definition YAML of this ECU")
    ap.add_argument("--fault", default="", help="faults on the ECU's frames, e.g. drop=0.1,corrupt=0.1,seed=3")
    ap.add_argument("--driving", action="store_true", help="start with the vehicle moving (changes refused)")
    ap.add_argument("--reply-delay", type=float, default=0.0, help="seconds before each answer")
    ap.add_argument("--log-level", default="INFO")


def open_faulty_bus(args: argparse.Namespace) -> can.BusABC:
    """The bus of :func:`add_common_args`' options, with the ``--fault`` injection when asked for (raises
    :class:`bac_common.errors.BacError` or ``ValueError`` with the reason)."""
    faults = FaultConfig.parse(args.fault)
    bus: can.BusABC = open_bus(BusSettings(args.interface, args.channel, args.bitrate, port=args.port))
    return FaultyBus(bus, faults) if faults.any else bus


class _Served(Protocol):
    @property
    def commits(self) -> int: ...

    @property
    def driving(self) -> bool: ...

    def set_driving(self, driving: bool) -> None: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...


def serve_until_signalled(
    ecu: _Served,
    bus: can.BusABC,
    log: logging.Logger,
    label: str,
    driving: bool,
    ready: Callable[[], None],
    counted: str = "commits",
) -> int:
    """Run ``ecu`` until SIGINT or SIGTERM (exit code 0); SIGUSR1 / SIGUSR2 set driving on / off. ``ready`` logs
    the start line once the ECU serves; the last line says how many ``counted`` (``ecu.commits``) it made."""
    ecu.set_driving(driving)
    stop = threading.Event()

    def on_stop(signum: int, _frame: FrameType | None) -> None:
        log.info("%s: %s, stopping", label, signal.Signals(signum).name)
        stop.set()

    def on_driving(signum: int, _frame: FrameType | None) -> None:
        ecu.set_driving(signum == signal.SIGUSR1)
        log.info("%s: driving=%s", label, ecu.driving)

    signal.signal(signal.SIGINT, on_stop)
    signal.signal(signal.SIGTERM, on_stop)
    signal.signal(signal.SIGUSR1, on_driving)
    signal.signal(signal.SIGUSR2, on_driving)
    ecu.start()
    ready()
    try:
        while not stop.wait(0.2):
            pass
    finally:
        ecu.stop()
        bus.shutdown()
        log.info("%s stopped after %d %s", label, ecu.commits, counted)
    return 0
