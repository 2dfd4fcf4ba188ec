"""The simulated ECU on CAN: serves the calibration protocol of bac_ecu_bridge on a python-can bus.

:class:`SimulatedEcu` runs :class:`bac_ecu_bridge.engine.EcuEngine` (the one
codec and state machine of the protocol) on a background thread: it receives
requests on the REQUEST id, answers on the RESPONSE id, and holds the
calibration in force (:attr:`SimulatedEcu.active`, starting at the
definition's baseline). The vehicle simulator reads ``active`` (or registers
``on_commit``) to drive its controller, and calls ``set_driving`` so that
commits are refused with "busy" while the vehicle moves.

As a process, for tests and for trying the bridge without a car::

    python -m bac_sim.ecu --interface udp_multicast --channel 239.74.163.2 \\
        --definition ros_ws/config/calibrations/controller_ii.yaml [--fault drop=0.1,seed=3] [--driving]

It logs to stderr ("ECU ready ...", one "committed ..." line per commit),
exits cleanly on SIGINT / SIGTERM, and toggles driving on SIGUSR1 (moving) /
SIGUSR2 (standing).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any

import can

from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.canbus import BusSettings, open_bus
from bac_ecu_bridge.engine import CommitEvent, EcuEngine
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.protocol import DEFAULT_REQUEST_ID, DEFAULT_RESPONSE_ID, CanIds, Op, Reason

LOG = logging.getLogger("bac_sim.ecu")


class SimulatedEcu:
    """An ECU that holds a calibration and serves the bac calibration protocol on a CAN bus.

    ``protocol_options``:

    * ``request_id`` / ``response_id`` / ``extended_id``: the CAN ids (defaults 0x6C0 / 0x6C1, 11-bit);
    * ``reply_delay_s``: processing time before each answer (a slow ECU);
    * ``commit_delay_s``: extra time a commit takes (writing the calibration);
    * ``initial``: raw values in force at start instead of the baseline;
    * ``refuse``: {request opcode: reason}: refuse those requests with that reason (a refusing ECU);
    * ``on_commit``: called with the new active values (by name) after each commit, on the ECU thread.
    """

    def __init__(self, bus: can.BusABC, definition: CalibrationDefinition, **protocol_options: Any) -> None:
        opts = dict(protocol_options)
        self.bus = bus
        self.definition = definition
        self.ids = CanIds(
            int(opts.pop("request_id", DEFAULT_REQUEST_ID)),
            int(opts.pop("response_id", DEFAULT_RESPONSE_ID)),
            bool(opts.pop("extended_id", False)),
        )
        self.reply_delay_s = float(opts.pop("reply_delay_s", 0.0))
        self.commit_delay_s = float(opts.pop("commit_delay_s", 0.0))
        self._on_commit: Callable[[dict[str, float]], None] | None = opts.pop("on_commit", None)
        initial = opts.pop("initial", None)
        refuse = opts.pop("refuse", None)
        if opts:
            raise TypeError(f"unknown SimulatedEcu options: {sorted(opts)}")
        self._lock = threading.Lock()
        self._engine = EcuEngine(definition, initial=initial, on_commit=self._committed, refuse=refuse)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._commit_event: CommitEvent | None = None
        self.send_errors = 0

    # --- the interface vehicle_sim uses ---------------------------------------------------------------
    def start(self) -> None:
        """Serve the protocol on a background thread."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="simulated-ecu", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    @property
    def active(self) -> dict[str, float]:
        """The calibration in force (raw parameters by name): the last one committed, or the baseline."""
        with self._lock:
            return self._engine.active_values()

    @property
    def active_crc(self) -> int:
        with self._lock:
            return self._engine.active_crc()

    @property
    def commits(self) -> int:
        with self._lock:
            return self._engine.stats.commits

    @property
    def driving(self) -> bool:
        return self._engine.driving

    def set_driving(self, driving: bool) -> None:
        """While driving, the ECU refuses to begin or commit a calibration ("busy")."""
        with self._lock:
            self._engine.driving = bool(driving)

    def reset(self) -> None:
        """A power cycle: the baseline is in force again."""
        with self._lock:
            self._engine.reset()

    @property
    def engine(self) -> EcuEngine:
        return self._engine

    # --- serving --------------------------------------------------------------------------------------
    def _committed(self, event: CommitEvent) -> None:
        self._commit_event = event  # called under self._lock by the engine

    def _serve(self) -> None:
        ids = self.ids
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.05)
            except (can.CanError, OSError) as exc:
                LOG.error("ECU: receiving failed: %s", exc)
                self._stop.wait(0.1)
                continue
            if (
                msg is None
                or msg.arbitration_id != ids.request_id
                or bool(msg.is_extended_id) != ids.extended
                or msg.is_error_frame
                or msg.is_remote_frame
            ):
                continue
            with self._lock:
                replies = self._engine.handle(msg.data)
                event, self._commit_event = self._commit_event, None
                values = self._engine.active_values() if event is not None else None
            if event is not None:
                if self.commit_delay_s:
                    time.sleep(self.commit_delay_s)
                LOG.info("ECU committed seq=%d count=%d crc=0x%08X", event.seq, len(event.raw), event.crc)
                if self._on_commit is not None and values is not None:
                    try:
                        self._on_commit(values)
                    except Exception:
                        LOG.exception("ECU: the on_commit callback failed")
            if self.reply_delay_s and replies:
                time.sleep(self.reply_delay_s)
            for data in replies:
                try:
                    self.bus.send(
                        can.Message(arbitration_id=ids.response_id, is_extended_id=ids.extended, data=data, is_fd=False)
                    )
                except (can.CanError, OSError) as exc:
                    self.send_errors += 1
                    LOG.warning("ECU: sending a reply failed: %s", exc)


# --- the standalone process ------------------------------------------------------------------------------
def parse_refusals(items: Sequence[str]) -> dict[int, int]:
    """``["commit=crc_mismatch", ...]`` -> {opcode: reason}."""
    out: dict[int, int] = {}
    for item in items:
        op, _, reason = item.partition("=")
        try:
            out[int(Op[op.strip().upper()])] = int(Reason[reason.strip().upper()])
        except KeyError:
            raise ValueError(
                f"--refuse {item!r}: expected OP=REASON with OP in {[o.name.lower() for o in Op if o < 0x40]} "
                f"and REASON in {[r.name.lower() for r in Reason]}"
            ) from None
    return out


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m bac_sim.ecu",
        description="A simulated ECU serving the bac calibration protocol on a CAN bus (for tests and bench work).",
    )
    ap.add_argument("--interface", default="udp_multicast", help="python-can interface (default udp_multicast)")
    ap.add_argument("--channel", default="239.74.163.2", help="python-can channel (default 239.74.163.2)")
    ap.add_argument("--bitrate", type=int, default=500_000)
    ap.add_argument("--port", type=int, default=0, help="udp_multicast UDP port (default python-can's)")
    ap.add_argument("--definition", required=True, type=Path, help="calibration definition YAML of this ECU")
    ap.add_argument("--fault", default="", help="faults on the ECU's frames, e.g. drop=0.1,corrupt=0.1,seed=3")
    ap.add_argument("--request-id", type=lambda s: int(s, 0), default=DEFAULT_REQUEST_ID)
    ap.add_argument("--response-id", type=lambda s: int(s, 0), default=DEFAULT_RESPONSE_ID)
    ap.add_argument("--extended-id", action="store_true", help="29-bit CAN identifiers")
    ap.add_argument("--driving", action="store_true", help="start with the vehicle moving (commits refused)")
    ap.add_argument(
        "--refuse",
        action="append",
        default=[],
        metavar="OP=REASON",
        help="refuse a request with a reason, e.g. commit=crc_mismatch, write=out_of_range, begin=busy (repeatable)",
    )
    ap.add_argument("--reply-delay", type=float, default=0.0, help="seconds before each answer")
    ap.add_argument("--log-level", default="INFO")
    return ap.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), stream=sys.stderr, format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    try:
        definition = CalibrationDefinition.load(args.definition)
        faults = FaultConfig.parse(args.fault)
        refuse = parse_refusals(args.refuse)
        bus: can.BusABC = open_bus(BusSettings(args.interface, args.channel, args.bitrate, port=args.port))
    except (BacError, ValueError) as exc:
        LOG.error("%s", exc)
        return 2
    if faults.any:
        bus = FaultyBus(bus, faults)
    ecu = SimulatedEcu(
        bus,
        definition,
        request_id=args.request_id,
        response_id=args.response_id,
        extended_id=args.extended_id,
        reply_delay_s=args.reply_delay,
        refuse=refuse,
    )
    ecu.set_driving(args.driving)
    stop = threading.Event()

    def on_stop(signum: int, _frame: FrameType | None) -> None:
        LOG.info("ECU: %s, stopping", signal.Signals(signum).name)
        stop.set()

    def on_driving(signum: int, _frame: FrameType | None) -> None:
        ecu.set_driving(signum == signal.SIGUSR1)
        LOG.info("ECU: driving=%s", ecu.driving)

    signal.signal(signal.SIGINT, on_stop)
    signal.signal(signal.SIGTERM, on_stop)
    signal.signal(signal.SIGUSR1, on_driving)
    signal.signal(signal.SIGUSR2, on_driving)
    ecu.start()
    LOG.info(
        "ECU ready: definition %s (%d parameters), %s:%s, request 0x%X, response 0x%X, driving=%s, faults=%s",
        definition.name,
        len(definition.parameters),
        args.interface,
        args.channel,
        args.request_id,
        args.response_id,
        args.driving,
        args.fault or "none",
    )
    try:
        while not stop.wait(0.2):
            pass
    finally:
        ecu.stop()
        bus.shutdown()
        LOG.info("ECU stopped after %d commits", ecu.commits)
    return 0


if __name__ == "__main__":
    sys.exit(main())
