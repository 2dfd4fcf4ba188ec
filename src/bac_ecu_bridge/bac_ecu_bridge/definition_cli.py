"""``bac definition``: calibration definitions from an ECU's A2L file, and the A2L of a definition.

    bac definition from-a2l ECU.a2l --characteristic NAME [NAME ...] [--out FILE] [--name NAME]
                            [--set NAME=VALUE ...] [--midpoint]
                            [--from-ecu --interface socketcan --channel can0 [--bitrate 500000] [--key ALG]]
    bac definition to-a2l DEFINITION [--out FILE] [--module NAME]

``from-a2l`` writes the YAML calibration definition of the named CHARACTERISTICs
(their order is the parameters' index order; ``--all`` takes every VALUE
characteristic): addresses, data types, byte orders, bounds (LOWER_LIMIT /
UPPER_LIMIT), the COMPU_METHOD (IDENTICAL, LINEAR, RAT_FUNC in linear form), the
resolution, units, and the XCP-on-CAN settings of the A2L's IF_DATA. Nominal and
baseline values come from the ECU's reference page (``--from-ecu``: it connects
over XCP with the A2L's CAN ids), or are given (``--set``), or, on a bench ECU
only, the middle of each range (``--midpoint``). The definition works for both
protocols of the bridge (``ecu_bridge`` ``protocol: xcp`` or ``bac``).

``to-a2l`` writes the A2L of a definition whose parameters carry XCP addresses
(the shipped ``bac_ecu_bridge/a2l/controller_*.a2l`` describe the simulated ECU).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from bac_common.console import say
from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="bac definition", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("from-a2l", help="write a calibration definition from an ECU's A2L file")
    p.add_argument("a2l", type=Path, help="the ECU's A2L file")
    p.add_argument("-c", "--characteristic", nargs="+", default=[], help="A2L CHARACTERISTIC names, in index order")
    p.add_argument("--all", action="store_true", help="every VALUE characteristic of the A2L (sorted by name)")
    p.add_argument("-o", "--out", type=Path, help="definition YAML to write (default: stdout)")
    p.add_argument("--name", help="the definition's name (default: the A2L module's)")
    p.add_argument("--description", default="")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="nominal and baseline value")
    p.add_argument("--midpoint", action="store_true", help="the middle of each range where no value is known (bench)")
    p.add_argument("--from-ecu", action="store_true", help="read nominal and baseline from the ECU's reference page")
    p.add_argument("--interface", default="socketcan", help="python-can interface (with --from-ecu)")
    p.add_argument("--channel", default="can0")
    p.add_argument("--bitrate", type=int, default=500_000)
    p.add_argument("--port", type=int, default=0, help="udp_multicast UDP port")
    p.add_argument("--key", default="", help="seed & key algorithm (xor:<hex>, module:function)")
    p.add_argument("--timeout", type=float, default=5.0, help="reading the ECU, s")
    p = sub.add_parser("to-a2l", help="write the A2L of a definition with XCP addresses")
    p.add_argument("definition", help="definition YAML, or a shipped definition's name")
    p.add_argument("-o", "--out", type=Path, help="A2L file to write (default: stdout)")
    p.add_argument("--module", help="the A2L MODULE's name (default: the definition's, upper case)")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        if args.cmd == "to-a2l":
            from bac_ecu_bridge.xcp.a2l import a2l_text

            text = a2l_text(CalibrationDefinition.load(resolve_definition(args.definition)), args.module)
            _write(text, args.out)
            return 0
        return _from_a2l(args)
    except (BacError, OSError, ValueError) as exc:
        say(f"bac definition: {exc}", err=True)
        return 2


def _write(text: str, out: Path | None) -> None:
    if out is None:
        sys.stdout.write(text)
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
        say(f"wrote {out}", err=True)


def _from_a2l(args: argparse.Namespace) -> int:
    from bac_ecu_bridge.xcp.a2l import definition_from_a2l, read_a2l

    if not args.characteristic and not args.all:
        module = read_a2l(args.a2l)
        say("name the characteristics to calibrate (--characteristic ...) or --all; VALUE characteristics:", err=True)
        for n in sorted(module.characteristics):
            say(f"  {n}", err=True)
        if module.problems:
            say("not writable by bac:", err=True)
            for n, why in sorted(module.problems.items()):
                say(f"  {n}: {why}", err=True)
        return 2
    chars = args.characteristic or None
    given: dict[str, float] = {}
    for item in args.set:
        name, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"--set {item!r}: expected NAME=VALUE")
        given[name.strip()] = float(value)
    notes: list[str] = []
    definition = definition_from_a2l(
        args.a2l,
        chars,
        name=args.name,
        values=given,
        midpoint=args.midpoint or args.from_ecu,
        description=args.description,
        notes=notes,
    )
    for note in notes:
        say(f"note: {note}", err=True)
    if args.from_ecu:
        definition = _read_from_ecu(definition, args)
    import yaml

    header = (
        f"# written by `bac definition from-a2l {args.a2l.name}`: the parameters' xcp addresses, data types and\n"
        "# conversions are the A2L's; nominal and baseline are "
        + ("the ECU's reference page" if args.from_ecu else "as given")
        + ". Check the bounds before a campaign.\n"
    )
    _write(header + yaml.safe_dump(definition.to_dict(), sort_keys=False), args.out)
    return 0


def _read_from_ecu(definition: CalibrationDefinition, args: argparse.Namespace) -> CalibrationDefinition:
    """Nominal and baseline values from the ECU's reference page (the flashed data set)."""
    from dataclasses import replace

    from bac_ecu_bridge.canbus import BusSettings, open_bus
    from bac_ecu_bridge.protocol import CanIds
    from bac_ecu_bridge.xcp.client import XcpCalibrationClient, XcpConfig, XcpSettings

    settings = XcpSettings.of(definition, key_algorithm=args.key or None)
    bus = open_bus(
        BusSettings(args.interface, args.channel, args.bitrate, port=args.port),
        CanIds(settings.can_id_master, settings.can_id_slave, settings.extended_id),
    )
    client = XcpCalibrationClient(bus, definition, settings, XcpConfig(timeout_s=args.timeout))
    try:
        values = client.read_page(None, args.timeout)
    finally:
        client.close()
        bus.shutdown()
    params = []
    for p in definition.parameters:
        v = values[p.name]
        if not p.lower <= v <= p.upper:
            raise ValueError(
                f"the ECU's reference page holds {p.name} = {v:g}, outside the A2L's limits [{p.lower:g}, {p.upper:g}]"
            )
        params.append(replace(p, nominal=v))
    say(f"read {len(values)} values from the ECU's reference page", err=True)
    return replace(definition, parameters=tuple(params), baseline=dict(values))


if __name__ == "__main__":
    sys.exit(main())
