"""``bac rescore`` and ``bac replay``: the campaign tools with what only the bringup knows (profiles and their
parameter files)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bac_bringup.cliargs import add_param_arguments, check_params_files, overrides_of
from bac_bringup.launcher import run_graph
from bac_bringup.profile import ProfileError, load_profile
from bac_campaign import rescore
from bac_campaign.bagplay import BagReadError, expand_bag_paths
from bac_common.console import in_range
from bac_common.errors import BacError


def profile_params(name: str) -> list[Path]:
    """The parameter files of a graph profile (``sim``, ``car``, ``replay``)."""
    return list(load_profile(name).params_files)


def rescore_main(argv: Sequence[str]) -> int:
    return rescore.main(argv, profile_params=profile_params)


def fit_foreign_rates(paths: Sequence[Path], args: argparse.Namespace, overrides: dict[str, dict[str, Any]]) -> str:
    """Recordings that are not a bac campaign's (a foreign bag, an MDF file): imu_ingest measures their IMU rate
    and keeps its output at or below it, the segmenter at the same rate, as ``bac rescore`` does (the replay
    profile is made for the simulator's 400 Hz IMU: a 50 Hz stream was all gaps). A ``-p`` wins. Returns a note
    for the user ("" for bac's own bags)."""
    from bac_campaign.bagplay import foreign_imu_rate_hz, parse_topic_map
    from bac_measure.mdfio import ChannelMap
    from bac_measure.measure_config import load_node_params

    channels = ChannelMap.load(str(args.channel_map) if args.channel_map else None, list(args.channel))
    rate = foreign_imu_rate_hz(paths, parse_topic_map(args.topic_map), channels)
    if rate is None:
        return ""
    ing, seg = overrides.setdefault("imu_ingest", {}), overrides.setdefault("run_segmenter", {})
    profile_out = float(load_node_params(profile_params("replay"), "imu_ingest").get("output_rate_hz", 200.0))
    out = float(ing.get("output_rate_hz", min(profile_out, round(rate, 6))))
    ing.setdefault("input_rate_hz", 0.0)
    ing.setdefault("output_rate_hz", out)
    seg.setdefault("imu_rate_hz", out)
    return (
        f"not a bac campaign (no bac/trial): the IMU is {rate:.1f} Hz; imu_ingest measures its input rate and "
        f"outputs {ing['output_rate_hz']:g} Hz. Mount and bias are the replay profile's (the simulator's IMU) "
        "unless -p imu_ingest.mount_* / bias_source say otherwise; bac rescore finds them from a standstill"
    )


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
    except (BagReadError, ProfileError) as exc:
        sys.stderr.write(f"bac replay: {exc}\n")
        return 2
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
    try:
        foreign = fit_foreign_rates(paths, args, overrides)
    except BacError as exc:
        sys.stderr.write(f"bac replay: {exc}\n")
        return 2
    if foreign:
        sys.stderr.write(f"bac replay: {foreign}\n")
    try:
        profile = load_profile("replay").with_overrides(params=overrides, extra_params_files=args.params_file)
    except ProfileError as exc:
        sys.stderr.write(f"bac replay: {exc}\n")
        return 2
    return run_graph(profile, single_process=args.single_process)
