"""``python -m bac_ecu_bridge``: the calibration protocol from a shell, without ROS.

Subcommands::

    dbc      write the DBC of a definition (the files shipped in bac_ecu_bridge/dbc/ come from it)
    decode   decode a CAN trace (candump .log, .asc, .blf, .trc, .csv) with the DBC, checking each CRC-8
    status   ask the ECU for the size and CRC of its active table
    read     read the ECU's active calibration
    apply    write a calibration (name=value ...) and wait for the acknowledgment
    restore  write the definition's safe baseline

The exit status of ``apply`` / ``restore`` / ``read`` / ``status`` is 0 on
success, else the ``ApplyCalibration`` error code (1 out of bounds, 2 unknown
parameter, 3 ECU out of range, 4 busy, 5 CRC mismatch, 6 sequence, 7 timeout,
8 bus, 9 invalid request).

Examples::

    python -m bac_ecu_bridge dbc --definition controller_ii -o controller_ii.dbc
    python -m bac_ecu_bridge decode trace.log --definition controller_ii
    python -m bac_ecu_bridge read --definition controller_i --interface socketcan --channel can0
    python -m bac_ecu_bridge apply --definition controller_i --interface pcan --channel PCAN_USBBUS1 \\
        damping_front=0.4 damping_rear=0.6
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from bac_common.console import say
from bac_common.errors import BacError, OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition
from bac_ecu_bridge.canbus import BusSettings, TracedBus, open_bus
from bac_ecu_bridge.client import CalibrationClient, ClientConfig
from bac_ecu_bridge.errors import BridgeError, ErrorCode
from bac_ecu_bridge.protocol import (
    DEFAULT_REQUEST_ID,
    DEFAULT_RESPONSE_ID,
    FRAME_LENGTH,
    CalibrationCodec,
    CanIds,
    resolve_request,
)


def _hex(s: str) -> int:
    return int(s, 0)


def _add_ids(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--request-id", type=_hex, default=DEFAULT_REQUEST_ID, help="default 0x6C0")
    ap.add_argument("--response-id", type=_hex, default=DEFAULT_RESPONSE_ID, help="default 0x6C1")
    ap.add_argument("--extended-id", action="store_true", help="29-bit identifiers")


def _add_bus(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--interface", default="socketcan", help="python-can interface (default socketcan)")
    ap.add_argument("--channel", default="can0")
    ap.add_argument("--bitrate", type=int, default=500_000)
    ap.add_argument("--port", type=int, default=0, help="udp_multicast UDP port")
    ap.add_argument("--trace", type=Path, help="write every frame to this trace file (.log, .asc, .blf, ...)")
    ap.add_argument("--timeout", type=float, default=3.0, help="overall time limit, s")
    ap.add_argument("--step-timeout", type=float, default=0.025, help="wait for one reply, s")
    ap.add_argument("--retries", type=int, default=5, help="re-sends of one request")
    ap.add_argument("--attempts", type=int, default=3, help="transactions per apply")
    ap.add_argument("--no-readback", action="store_true", help="skip reading the values back after the ACK")


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m bac_ecu_bridge", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("dbc", help="write the DBC of a calibration definition")
    p.add_argument(
        "--definition", required=True, help="definition YAML, or a shipped definition's name (controller_i, ...)"
    )
    p.add_argument("-o", "--output", type=Path, help="file to write (default: stdout)")
    _add_ids(p)
    p = sub.add_parser("decode", help="decode a CAN trace with the DBC")
    p.add_argument("trace", type=Path)
    group = p.add_mutually_exclusive_group(required=True)
    group.add_argument("--definition", help="build the DBC from this definition")
    group.add_argument("--dbc", type=Path, help="use this DBC file")
    _add_ids(p)
    for name, text in (
        ("status", "the size and CRC of the ECU's active table"),
        ("read", "read the ECU's active calibration"),
        ("apply", "write a calibration: name=value ..."),
        ("restore", "write the definition's safe baseline"),
    ):
        p = sub.add_parser(name, help=text)
        p.add_argument("--definition", required=True)
        _add_bus(p)
        _add_ids(p)
        if name == "apply":
            p.add_argument("values", nargs="+", metavar="name=value")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except BridgeError as exc:
        say(f"error {exc.code.name}: {exc}", err=True)
        return int(exc.code)
    except OutOfBoundsError as exc:
        say(f"error OUT_OF_BOUNDS: {exc}", err=True)
        return int(ErrorCode.OUT_OF_BOUNDS)
    except UnknownParameterError as exc:
        say(f"error UNKNOWN_PARAMETER: {exc}", err=True)
        return int(ErrorCode.UNKNOWN_PARAMETER)
    except (BacError, FileNotFoundError, ValueError) as exc:
        say(f"error: {exc}", err=True)
        return int(ErrorCode.INVALID_REQUEST)


def _run(args: argparse.Namespace) -> int:
    ids = CanIds(args.request_id, args.response_id, args.extended_id)
    if args.cmd == "dbc":
        from bac_ecu_bridge.dbc import dbc_text  # cantools only where a DBC is needed

        text = dbc_text(CalibrationDefinition.load(resolve_definition(args.definition)), ids)
        if args.output:
            args.output.write_text(text)
        else:
            sys.stdout.write(text)
        return 0
    if args.cmd == "decode":
        from bac_ecu_bridge.trace import decode_trace, load_database

        trace_codec: CalibrationCodec | None = None
        if args.dbc:
            db = load_database(args.dbc)
        else:
            from bac_ecu_bridge.dbc import build_database

            definition = CalibrationDefinition.load(resolve_definition(args.definition))
            db = build_database(definition, ids)
            trace_codec = CalibrationCodec(definition)  # the indexes and bounds checked too
        rows = decode_trace(args.trace, db, ids, trace_codec)
        for row in rows:
            say(row.text())
        bad = sum(len(r.raw) == FRAME_LENGTH and not r.crc_ok for r in rows)
        invalid = sum(bool(r.problem) for r in rows)
        say(f"# {len(rows)} protocol frames, {bad} with a CRC-8 mismatch, {invalid} invalid in all", err=True)
        return 1 if any(r.problem.endswith("the DBC and the protocol disagree") for r in rows) else 0
    definition = CalibrationDefinition.load(resolve_definition(args.definition))
    codec = CalibrationCodec(definition)
    bus = open_bus(BusSettings(args.interface, args.channel, args.bitrate, port=args.port), ids)
    if args.trace:
        bus = TracedBus(bus, args.trace)
    config = ClientConfig(
        step_timeout_s=args.step_timeout,
        step_retries=args.retries,
        max_attempts=args.attempts,
        timeout_s=args.timeout,
        verify_readback=not args.no_readback,
    )
    client = CalibrationClient(bus, codec, ids, config)
    try:
        if args.cmd == "status":
            st = client.status()
            say(f"ECU table: {st.count} parameters, CRC-32 0x{st.crc:08X} ({st.latency_s * 1e3:.1f} ms)")
            return 0
        if args.cmd == "read":
            rd = client.read_active()
            for name, v in rd.values.items():
                say(f"{name} = {v:.10g}")
            say(f"# CRC-32 0x{rd.crc:08X}, {rd.latency_s * 1e3:.1f} ms", err=True)
            return 0
        if args.cmd == "restore":
            values = definition.baseline_values()
        else:
            pairs = [v.split("=", 1) for v in args.values]
            if any(len(p) != 2 for p in pairs):
                raise ValueError("values are given as name=value")
            values = resolve_request(definition, [p[0] for p in pairs], [float(p[1]) for p in pairs])
        try:
            res = client.apply(values)
        except BridgeError as exc:
            state = f" After it, {exc.ecu_state.text()}." if exc.ecu_state is not None else ""
            say(f"error {exc.code.name} ({int(exc.code)}): {exc}.{state}", err=True)
            return int(exc.code)
        for name, v in res.values.items():
            say(f"{name} = {v:.10g}")
        if res.note:
            say(f"# {res.note}", err=True)
        say(
            f"# applied: CRC-32 0x{res.crc:08X}, {res.attempts} transaction(s), {res.latency_s * 1e3:.1f} ms, "
            f"read back: {res.read_back}",
            err=True,
        )
        return 0
    finally:
        bus.shutdown()


if __name__ == "__main__":
    sys.exit(main())
