"""``bac``: the command-line entry point of the project.

    bac launch PROFILE [--single-process] [-p node.param:=value ...]   run a node graph
    bac demo [...]                                                      the main job (make demo)
    bac netns -- COMMAND ...                                            run in a private network namespace

Further sub-commands (rescore, replay, reduce, report, ...) are provided by the
other packages and listed by ``bac --help``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from bac_bringup import launcher, netns
from bac_bringup.cliargs import add_param_arguments, check_params_files, overrides_of
from bac_bringup.profile import ProfileError, load_profile
from bac_common.errors import BacError

# sub-command -> (module, function, one-line help); the function takes argv and returns an exit code
SUBCOMMANDS: dict[str, tuple[str, str, str]] = {
    "launch": ("bac_bringup.cli", "launch_main", "run a node graph profile (sim, car, replay)"),
    "demo": ("bac_bringup.demo", "main", "the main job: a whole calibration campaign on the simulated vehicle"),
    "netns": ("bac_bringup.netns", "main", "run a command inside a private network namespace"),
    "rescore": ("bac_bringup.tools", "rescore_main", "re-cut and re-score a campaign's bags (or any IMU bag) offline"),
    "replay": ("bac_bringup.tools", "replay_main", "play bags into the live graph on /clock (the replay profile)"),
    "report": ("bac_campaign.report", "main", "make a campaign's report (PNG + HTML)"),
    "cockpit": ("bac_cockpit.cli", "cockpit_main", "serve the cockpit's page for a campaign folder (no graph needed)"),
    "watch": ("bac_cockpit.cli", "watch_main", "the cockpit in a terminal (a running cockpit or a campaign folder)"),
    "export": ("bac_campaign.export", "main", "write a campaign as ASAM MDF4 (--mf4) for asammdf, CANape, INCA"),
    "reduce": ("bac_reduce.cli", "main", "simulation phase: find the parameters that matter (paper sec. III-D)"),
    "ground-truth": ("bac_sim.ground_truth", "main", "recompute the simulator's true optima by dense grids"),
    "definition": ("bac_ecu_bridge.definition_cli", "main", "calibration definitions from an ECU's A2L file"),
}


def launch_main(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog="bac launch", description="Run a node graph profile from ros_ws/profiles.")
    ap.add_argument("profile", help="profile name (sim, car, replay, ...) or path to a profile YAML")
    ap.add_argument(
        "--single-process",
        action="store_true",
        help="all nodes in one process on a multi-threaded executor (CAN on the virtual bus)",
    )
    add_param_arguments(ap)
    ap.add_argument(
        "--process-per-node",
        action="store_true",
        help="every node in a process of its own, also those the profile puts in one (process:); CAN between "
        "processes then goes over udp_multicast inside a private network namespace",
    )
    ap.add_argument("--only", help="comma-separated node names to start (default: all)")
    ap.add_argument("--exclude", default="", help="comma-separated node names not to start")
    ap.add_argument("--log-dir", type=Path, help="write each node's output to LOG_DIR/<node>.log")
    ap.add_argument("--timeout", type=float, help="stop the graph after this many seconds (exit 124)")
    ap.add_argument(
        "--campaign-dir",
        type=Path,
        help="campaign folder (journal, bags, report) for profiles that run a campaign; "
        "default: a new folder campaigns/<profile>-<date>-<time> here; an existing folder is resumed",
    )
    args = ap.parse_args(list(argv))
    try:
        check_params_files(args.params_file)  # before anything is made (a campaign folder's config/, the nodes)
        profile = load_profile(args.profile)
        overrides = overrides_of(args.param)
        profile = profile.with_overrides(
            params=overrides,
            extra_params_files=args.params_file,
            only=args.only.split(",") if args.only else None,
            exclude=[x for x in args.exclude.split(",") if x],
        )
        if args.process_per_node:
            profile = profile.one_process_per_node()
        if profile.campaign:
            camp = args.campaign_dir or default_campaign_dir(profile.name)
            camp = camp.resolve()
            camp.mkdir(parents=True, exist_ok=True)
            profile = profile.with_overrides(global_params={"campaign_dir": str(camp)})
            argv = [*argv, "--campaign-dir", str(camp)] if args.campaign_dir is None else argv
            logging.getLogger("bac.launch").info("campaign folder: %s", camp)
        launcher.prepare(profile, args.single_process)  # refuses a CAN bus that cannot reach its nodes
    except ProfileError as exc:
        logging.getLogger("bac.launch").error("%s", exc)
        return 2
    if launcher.needs_private_netns(profile, args.single_process):
        try:
            extra, published = _publish_cockpit(profile, overrides)
        except BacError as exc:
            logging.getLogger("bac.launch").error("%s", exc)
            return 2
        try:
            return launcher.relaunch_in_netns(["launch", *argv, *extra])
        except netns.NetnsError as exc:
            logging.getLogger("bac.launch").error("%s", exc)
            return 3
        finally:
            if published is not None:
                published.close()
    saved: Path | None = None
    if profile.campaign:
        camp = Path(profile.global_params["campaign_dir"])
        from bac_campaign.launches import campaign_launches_begun

        begun = campaign_launches_begun(camp)
        bags_before = launcher.bags_opened(camp)
        saved = launcher.save_launch_config(profile, camp, argv, args.single_process)
        if "cockpit" in [n.name for n in profile.nodes]:
            announce_cockpit(camp)
    rc = launcher.run_graph(profile, single_process=args.single_process, log_dir=args.log_dir, timeout_s=args.timeout)
    agent = next((n for n in profile.nodes if n.name == "bo_agent"), None)
    # only when the agent journals into this folder (a -p bo_agent.campaign_dir elsewhere: its start is not seen
    # here) and the recorder opened no bag in it during the launch
    if (
        saved is not None
        and agent is not None
        and Path(str(profile.params_for(agent).get("campaign_dir", camp))).resolve() == camp.resolve()
        and launcher.bags_opened(camp) == bags_before
    ):
        launcher.drop_unused_config(saved, camp, begun)
    return rc


def _publish_cockpit(profile: Any, overrides: dict[str, dict[str, Any]]) -> tuple[list[str], Any]:
    """A cockpit in a graph that goes into a private network namespace is published from here, outside, through
    a Unix socket (bac_cockpit.relay): its address is then reachable from this machine's browser."""
    if "cockpit" not in [n.name for n in profile.nodes]:
        return [], None
    from bac_cockpit.relay import publish_cockpit

    extra, published = publish_cockpit(profile.params_files, overrides.get("cockpit"))
    logging.getLogger("bac.launch").info("cockpit published at %s (relayed into the graph's network namespace)",
                                         published.url)  # fmt: skip
    return extra, published


def announce_cockpit(campaign_dir: Path, timeout_s: float = 300.0) -> threading.Thread:
    """Print the cockpit's address (``cockpit: URL``, from the node's ``<campaign>/cockpit.json``) as soon as the
    node has started, whether its output goes to the terminal or to a log file (``--log-dir``)."""
    path = campaign_dir / "cockpit.json"
    started = time.time()

    def watch() -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                if path.stat().st_mtime >= started:  # this launch's node, not a file left by an earlier one
                    url = json.loads(path.read_text())["url"]
                    logging.getLogger("bac.launch").info("cockpit: %s", url)
                    return
            except (OSError, ValueError, KeyError):
                pass  # not there yet, or being written
            time.sleep(0.2)

    thread = threading.Thread(target=watch, name="bac-cockpit-address", daemon=True)
    thread.start()
    return thread


def default_campaign_dir(profile_name: str) -> Path:
    return Path("campaigns") / f"{profile_name}-{time.strftime('%Y%m%d-%H%M%S')}"


def _resolve(name: str) -> Callable[[Sequence[str]], int] | None:
    module, func, _ = SUBCOMMANDS[name]
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and module.startswith(exc.name):
            return None
        raise
    fn = getattr(mod, func, None)
    return fn


def main(argv: Sequence[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        lines = ["usage: bac COMMAND [ARGS ...]", "", "commands:"]
        for name, (_, _, text) in SUBCOMMANDS.items():
            lines.append(f"  {name:<13} {text}")
        sys.stdout.write("\n".join(lines) + "\n")
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in SUBCOMMANDS:
        sys.stderr.write(f"bac: unknown command '{name}' (bac --help lists them)\n")
        return 2
    fn = _resolve(name)
    if fn is None:
        sys.stderr.write(f"bac {name}: not available in this build yet\n")
        return 2
    return int(fn(rest))


if __name__ == "__main__":
    sys.exit(main())
