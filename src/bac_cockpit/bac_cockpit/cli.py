"""``bac cockpit CAMPAIGN``: the cockpit's page for a campaign folder, with no graph running.

    bac cockpit CAMPAIGN [--port 8765] [--host 127.0.0.1] [--token TOKEN|auto] [--no-follow]

It reads the journal (the trials and the recommendation, as ``bac report`` reads them), the configuration
(the target speed) and the bags (each run's aligned signals and spectra, the calibration the ECU confirmed),
fits the GP view, and serves the same page as the live ``cockpit`` node, so that the desk and the car look the
same. While the folder grows (a campaign being driven, a folder being synced) the page follows it.

Safe by default: 127.0.0.1 only. ``--host`` with another address is refused without ``--token`` (or the
``BAC_COCKPIT_TOKEN`` environment variable); every request must then carry it (``?token=``).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bac_cockpit.feed import CampaignFeed
from bac_cockpit.folder import read_folder, why_no_campaign
from bac_cockpit.model import GRID
from bac_cockpit.server import DEFAULT_HOST, DEFAULT_PORT, CockpitError, CockpitServer
from bac_cockpit.state import CockpitState
from bac_common.console import say


def cockpit_main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="bac cockpit", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("campaign", type=Path, help="campaign folder (journal.jsonl, bags/, config/)")
    ap.add_argument("--host", default=DEFAULT_HOST, help="address to listen on (default 127.0.0.1: this machine only)")
    ap.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (0: any free one)")
    ap.add_argument(
        "--token",
        default=os.environ.get("BAC_COCKPIT_TOKEN", ""),
        help="access token every request must carry (required with --host; auto = a random one, printed)",
    )
    ap.add_argument("--no-follow", action="store_true", help="read the folder once (do not follow it as it grows)")
    ap.add_argument("--model-grid", type=int, default=GRID, help="points per axis of the GP view")
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))
    camp = args.campaign.expanduser().resolve()
    if not camp.is_dir():
        say(f"bac cockpit: no such folder: {camp}", err=True)
        return 2
    if read_folder(camp) is None:
        say(f"bac cockpit: {why_no_campaign(camp)}", err=True)
        return 2
    try:
        server = CockpitServer(CockpitState("offline"), host=args.host, port=args.port, token=args.token)
        feed = CampaignFeed(
            server, camp, model_grid=args.model_grid, follow_bags=True, poll_s=1.0, follow=not args.no_follow
        )
        bound = server.start()
    except CockpitError as exc:
        say(f"bac cockpit: {exc}", err=True)
        return 2
    feed.start()
    if bound.fallback_from:
        say(f"bac cockpit: port {bound.fallback_from} is taken: using {bound.port}", err=True)
    say(f"cockpit: {server.url}")
    say(f"  campaign folder {camp} (read-only{'' if args.no_follow else ', followed as it grows'}); Ctrl-C stops")
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not stop.wait(0.5):
            pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        feed.close()
        server.stop()
    return 0


def watch_main(argv: Sequence[str] | None = None) -> int:
    from bac_cockpit.watch import main

    return main(argv)


if __name__ == "__main__":
    sys.exit(cockpit_main())
