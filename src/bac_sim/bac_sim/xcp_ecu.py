"""The simulated XCP ECU on CAN: serves :class:`bac_sim.xcp_slave.XcpSlave` on a python-can bus.

Same interface as :class:`bac_sim.ecu.SimulatedEcu` (the bac protocol's), so
``vehicle_sim`` drives either by configuration: ``active`` is the calibration
the ECU application uses (decoded from its page of the slave's memory),
``set_driving`` makes it refuse calibration changes, ``start`` / ``stop`` /
``reset``. The CAN ids are XCP's (the A2L's IF_DATA XCP_ON_CAN: CAN_ID_MASTER
receives commands, CAN_ID_SLAVE carries responses).

As a process, for tests and for trying the bridge without a car::

    python -m bac_sim.xcp_ecu --interface udp_multicast --channel 239.74.163.2 \\
        --definition ros_ws/config/calibrations/controller_ii.yaml [--fault drop=0.1,seed=3] [--driving] \\
        [--key xor:5a17c3] [--no-pages] [--refuse download=0x23]

It logs "XCP ECU ready ..." and one "ECU calibration: page P crc=0x..." line
per change of what the ECU application uses, exits 0 on SIGINT/SIGTERM, and
SIGUSR1 / SIGUSR2 set driving on / off.
"""

from __future__ import annotations

import argparse
import logging
import sys
import zlib
from collections.abc import Callable, Sequence
from typing import Any

import can

from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.xcp.seedkey import load_key_algorithm
from bac_sim.canserver import CanServer, add_common_args, open_faulty_bus, serve_until_signalled
from bac_sim.xcp_slave import Cmd, Err, XcpSlave

LOG = logging.getLogger("bac_sim.xcp_ecu")

DEFAULT_CAN_ID_MASTER = 0x7E0  # commands: master (bridge) -> slave (ECU)
DEFAULT_CAN_ID_SLAVE = 0x7E1  # responses: slave -> master


class SimulatedXcpEcu(CanServer):
    """An ECU with an XCP-on-CAN slave (see the module doc).

    ``options``: ``can_id_master`` / ``can_id_slave`` / ``extended_id``; ``reply_delay_s``; ``initial`` (values
    on the working page at start); ``pages`` (False: one RAM page); ``key_algorithm`` (a spec of
    :func:`bac_ecu_bridge.xcp.seedkey.load_key_algorithm`, or a function); ``byte_order``; ``max_bs``;
    ``busy_error``; ``refuse`` ({command code: error code}); ``on_commit`` (called with the new active values
    after each change of what the ECU application uses, on the ECU thread).
    """

    def __init__(self, bus: can.BusABC, definition: CalibrationDefinition, **options: Any) -> None:
        opts = dict(options)
        self.definition = definition
        self.can_id_master = int(opts.pop("can_id_master", definition.xcp.get("can_id_master", DEFAULT_CAN_ID_MASTER)))
        self.can_id_slave = int(opts.pop("can_id_slave", definition.xcp.get("can_id_slave", DEFAULT_CAN_ID_SLAVE)))
        self.request_id, self.response_id = self.can_id_master, self.can_id_slave
        self.extended = bool(opts.pop("extended_id", definition.xcp.get("extended_id", False)))
        reply_delay_s = float(opts.pop("reply_delay_s", 0.0))
        on_commit: Callable[[dict[str, float]], None] | None = opts.pop("on_commit", None)
        key = opts.pop("key_algorithm", None)
        if isinstance(key, str):
            key = load_key_algorithm(key)
        super().__init__(bus, LOG, "XCP ECU", reply_delay_s, on_commit, reply_word="response")
        self._changes = 0
        self._pending_change = False
        self._page = 0
        self.slave = XcpSlave(definition, key_algorithm=key, on_change=self._changed, **opts)

    # --- the interface vehicle_sim uses ---------------------------------------------------------------
    @property
    def active(self) -> dict[str, float]:
        """The calibration the ECU application uses (the values of its page), by name."""
        with self._lock:
            return self.slave.active_values()

    @property
    def active_crc(self) -> int:
        with self._lock:
            s = self.slave
            return zlib.crc32(bytes(s.pages[s.ecu_page])) & 0xFFFF_FFFF

    @property
    def commits(self) -> int:
        """Changes of what the ECU application uses (page switches, writes into its page)."""
        with self._lock:
            return self._changes

    @property
    def ecu_page(self) -> int:
        with self._lock:
            return self.slave.ecu_page

    @property
    def driving(self) -> bool:
        return self.slave.driving

    def set_driving(self, driving: bool) -> None:
        with self._lock:
            self.slave.driving = bool(driving)

    def reset(self) -> None:
        with self._lock:
            self.slave.reset()

    # --- serving ----------------------------------------------------------------------------------------
    def _changed(self) -> None:  # under self._lock, from the slave
        self._changes += 1
        self._pending_change = True

    def _handle(self, data: bytes) -> tuple[list[bytes], dict[str, float] | None]:
        replies = self.slave.handle(data)
        changed, self._pending_change = self._pending_change, False
        self._page = self.slave.ecu_page
        return replies, (self.slave.active_values() if changed else None)

    def _changed_values(self, values: dict[str, float]) -> None:
        LOG.info("ECU calibration: page %d crc=0x%08X", self._page, values_crc(values))


def values_crc(values: dict[str, float]) -> int:
    """The CRC the process logs for a calibration (tests compare it with what they asked for)."""
    return zlib.crc32(repr(sorted(values.items())).encode()) & 0xFFFF_FFFF


# --- the standalone process ------------------------------------------------------------------------------
def parse_refusals(items: Sequence[str]) -> dict[int, int]:
    """``["download=write_protected", "set_cal_page=0x26", ...]`` -> {command code: error code}."""
    out: dict[int, int] = {}
    for item in items:
        cmd, _, err = item.partition("=")
        try:
            code = int(Cmd[cmd.strip().upper()])
            e = err.strip()
            out[code] = int(e, 0) if e[:1].isdigit() else int(Err[e.upper().removeprefix("ERR_")])
        except (KeyError, ValueError):
            raise ValueError(
                f"--refuse {item!r}: expected COMMAND=ERROR with COMMAND in {[c.name.lower() for c in Cmd]} and "
                f"ERROR a code (0x23) or one of {[e.name.lower() for e in Err]}"
            ) from None
    return out


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m bac_sim.xcp_ecu",
        description="A simulated ECU with an XCP-on-CAN slave (for tests and bench work).",
    )
    add_common_args(ap)
    ap.add_argument("--can-id-master", type=lambda s: int(s, 0), default=None, help="default: definition, 0x7E0")
    ap.add_argument("--can-id-slave", type=lambda s: int(s, 0), default=None, help="default: definition, 0x7E1")
    ap.add_argument("--no-pages", action="store_true", help="one RAM page only (no reference page)")
    ap.add_argument("--key", default="", help="protect calibration with seed & key, e.g. xor:5a17c3")
    ap.add_argument("--refuse", action="append", default=[], metavar="COMMAND=ERROR")
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
    options: dict[str, Any] = {"reply_delay_s": args.reply_delay, "pages": not args.no_pages, "refuse": refuse}
    if args.can_id_master is not None:
        options["can_id_master"] = args.can_id_master
    if args.can_id_slave is not None:
        options["can_id_slave"] = args.can_id_slave
    if args.key:
        options["key_algorithm"] = args.key
    try:
        ecu = SimulatedXcpEcu(bus, definition, **options)
    except (BacError, ValueError) as exc:
        LOG.error("%s", exc)
        bus.shutdown()
        return 2

    def ready() -> None:
        LOG.info(
            "XCP ECU ready: definition %s (%d parameters), %s:%s, CAN_ID_MASTER 0x%X, CAN_ID_SLAVE 0x%X, pages=%s, "
            "seed&key=%s, driving=%s, faults=%s",
            definition.name,
            len(definition.parameters),
            args.interface,
            args.channel,
            ecu.can_id_master,
            ecu.can_id_slave,
            not args.no_pages,
            bool(args.key),
            args.driving,
            args.fault or "none",
        )

    return serve_until_signalled(ecu, bus, LOG, "XCP ECU", args.driving, ready, counted="changes")


if __name__ == "__main__":
    sys.exit(main())
