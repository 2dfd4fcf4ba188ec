"""``bac rescore`` and ``bac replay``: the campaign tools with what only the bringup knows (profiles and their
parameter files)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from bac_bringup.cliargs import add_param_arguments, check_params_files, overrides_of
from bac_bringup.launcher import run_graph
from bac_bringup.profile import load_profile
from bac_campaign import rescore
from bac_campaign.bagplay import expand_bag_paths, fit_replay_rates
from bac_common.console import in_range
from bac_common.errors import BacError


def profile_params(name: str) -> list[Path]:
    """The parameter files of a graph profile (``sim``, ``car``, ``replay``)."""
    return list(load_profile(name).params_files)


def rescore_main(argv: Sequence[str]) -> int:
    return rescore.main(argv, profile_params=profile_params)


def replay_main(argv: Sequence[str]) -> int:
    """``bac replay``: the replay profile with the given bags."""
    ap = argparse.ArgumentParser(prog="bac replay", description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "bags", nargs="+", help="campaign folders and/or bags (rosbag2 folder/mcap/db3, ROS 1 .bag) or MDF files"
    )
    ap.add_argument(
        "--rate", type=in_range(float, 0.01, 1000.0), default=10.0, help="playback speed, multiple of real time"
    )
    ap.add_argument(
        "--topic-map",
        action="append",
        default=[],
        metavar="FROM:=TO",
        help="remap a bag topic, e.g. /imu/data:=imu/data_raw (repeatable)",
    )
    ap.add_argument("--output", type=Path, help="write recorded vs replayed J as JSON")
    ap.add_argument("--channel-map", type=Path, help="MDF files: YAML mapping roles to channels")
    ap.add_argument(
        "--channel", action="append", default=[], metavar="ROLE=NAME", help="MDF files: map one role (repeatable)"
    )
    ap.add_argument("--single-process", action="store_true", help="run the replay graph in one process")
    add_param_arguments(ap)
    args = ap.parse_args(list(argv))
    try:
        paths = expand_bag_paths(args.bags)
        check_params_files(args.params_file)
        player = {
            "bags": [str(p.resolve()) for p in paths],
            "rate": args.rate,
            "topic_map": args.topic_map,
            "output": str(args.output.resolve()) if args.output else "",
        }
        if args.channel_map:
            player["channel_map"] = str(args.channel_map.resolve())
        if args.channel:
            player["channels"] = list(args.channel)
        overrides = overrides_of(args.param)
        overrides["bag_player"] = {**player, **overrides.get("bag_player", {})}  # a -p wins over the options
        load_profile("replay").with_overrides(params=overrides)  # a -p for a node the profile lacks: refused now
        note = fit_replay_rates(overrides, profile_params("replay"), args.params_file)
        profile = load_profile("replay").with_overrides(params=overrides, extra_params_files=args.params_file)
    except BacError as exc:
        sys.stderr.write(f"bac replay: {exc}\n")
        return 2
    if note:
        sys.stderr.write(f"bac replay: {note}\n")
    return run_graph(profile, single_process=args.single_process)
