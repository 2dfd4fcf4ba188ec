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
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import can

from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.engine import CommitEvent, EcuEngine
from bac_ecu_bridge.protocol import DEFAULT_REQUEST_ID, DEFAULT_RESPONSE_ID, CanIds, Op, Reason
from bac_sim.canserver import CanServer, add_common_args, open_faulty_bus, serve_until_signalled

LOG = logging.getLogger("bac_sim.ecu")


class SimulatedEcu(CanServer):
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
        self.definition = definition
        self.ids = CanIds(
            int(opts.pop("request_id", DEFAULT_REQUEST_ID)),
            int(opts.pop("response_id", DEFAULT_RESPONSE_ID)),
            bool(opts.pop("extended_id", False)),
        )
        self.request_id, self.response_id, self.extended = self.ids.request_id, self.ids.response_id, self.ids.extended
        reply_delay_s = float(opts.pop("reply_delay_s", 0.0))
        self.commit_delay_s = float(opts.pop("commit_delay_s", 0.0))
        on_commit: Callable[[dict[str, float]], None] | None = opts.pop("on_commit", None)
        initial = opts.pop("initial", None)
        refuse = opts.pop("refuse", None)
        if opts:
            raise TypeError(f"unknown SimulatedEcu options: {sorted(opts)}")
        super().__init__(bus, LOG, "ECU", reply_delay_s, on_commit)
        self._engine = EcuEngine(definition, initial=initial, on_commit=self._committed, refuse=refuse)
        self._commit_event: CommitEvent | None = None
        self._last_event: CommitEvent | None = None

    # --- the interface vehicle_sim uses ---------------------------------------------------------------
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

    def _handle(self, data: bytes) -> tuple[list[bytes], dict[str, float] | None]:
        replies = self._engine.handle(data)
        self._last_event, self._commit_event = self._commit_event, None
        return replies, (self._engine.active_values() if self._last_event is not None else None)

    def _changed_values(self, values: dict[str, float]) -> None:
        event = self._last_event
        if self.commit_delay_s:
            time.sleep(self.commit_delay_s)
        if event is not None:
            LOG.info("ECU committed seq=%d count=%d crc=0x%08X", event.seq, len(event.raw), event.crc)


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
    add_common_args(ap)
    ap.add_argument("--request-id", type=lambda s: int(s, 0), default=DEFAULT_REQUEST_ID)
    ap.add_argument("--response-id", type=lambda s: int(s, 0), default=DEFAULT_RESPONSE_ID)
    ap.add_argument("--extended-id", action="store_true", help="29-bit CAN identifiers")
    ap.add_argument(
        "--refuse",
        action="append",
        default=[],
        metavar="OP=REASON",
        help="refuse a request with a reason, e.g. commit=crc_mismatch, write=out_of_range, begin=busy (repeatable)",
    )
    return ap.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), stream=sys.stderr, format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    try:
        definition = CalibrationDefinition.load(args.definition)
        refuse = parse_refusals(args.refuse)
        bus = open_faulty_bus(args)
    except (BacError, ValueError) as exc:
        LOG.error("%s", exc)
        return 2
    ecu = SimulatedEcu(
        bus,
        definition,
        request_id=args.request_id,
        response_id=args.response_id,
        extended_id=args.extended_id,
        reply_delay_s=args.reply_delay,
        refuse=refuse,
    )

    def ready() -> None:
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

    return serve_until_signalled(ecu, bus, LOG, "ECU", args.driving, ready, counted="commits")


if __name__ == "__main__":
    sys.exit(main())
