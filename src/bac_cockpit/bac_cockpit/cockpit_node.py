"""``cockpit``: the calibration cockpit, a live page for the engineer and the driver.

Listens to ``bac/trial``, ``bac/run_score``, ``bac/run_segment``, ``bac/calibration`` and ``/diagnostics``,
reads the campaign journal in ``campaign_dir``, and serves one page over HTTP with live updates (server-sent
events): :mod:`bac_cockpit.server`. Its callbacks only convert a message and hand it to the web server's
thread; the journal and the GP view are worked on there and in a worker process (:mod:`bac_cockpit.feed`), so
the page never slows the graph.

It listens on 127.0.0.1 by default; another ``host`` needs ``token`` (refused at start otherwise). The address
is logged at start and written to ``<campaign_dir>/cockpit.json`` (mode 0600: it may hold the token), which
``bac demo`` and ``bac watch`` read. When the launcher runs the graph in a private network namespace, it
publishes the page from outside through a Unix socket (``unix_socket``, ``public_url``:
:mod:`bac_cockpit.relay`).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from bac_cockpit.feed import CampaignFeed
from bac_cockpit.server import DEFAULT_HOST, DEFAULT_PORT, CockpitServer
from bac_cockpit.state import (
    CockpitState,
    calibration_from_msg,
    diagnostics_from_msg,
    score_from_msg,
    segment_from_msg,
    trial_from_msg,
)
from bac_common.contracts import (
    TOPIC_CALIBRATION,
    TOPIC_DIAGNOSTICS,
    TOPIC_RUN_SCORE,
    TOPIC_RUN_SEGMENT,
    TOPIC_TRIAL,
)
from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED_READER, BacNode, run_node
from bac_msgs.msg import Calibration, RunScore, RunSegment, Trial

ADDRESS_FILE = "cockpit.json"
QOS_DIAGNOSTICS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)


def write_address_file(campaign_dir: Path, record: dict[str, Any]) -> Path:
    """``<campaign_dir>/cockpit.json``: where the page is (readable by the user only: it may carry the token)."""
    path = campaign_dir / ADDRESS_FILE
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(record, f, indent=2)
        f.write("\n")
    os.replace(tmp, path)
    return path


class CockpitNode(BacNode):
    """The cockpit (see the module doc and docs/cockpit.md)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("cockpit", **kwargs)
        campaign_dir = self.declare_str(
            "campaign_dir",
            "",
            "campaign folder whose journal the page shows (the launcher sets it); '' = topics only",
            read_only=True,
        )
        host = self.declare_str(
            "host",
            DEFAULT_HOST,
            "address to listen on: 127.0.0.1 (this machine only); any other needs token",
            read_only=True,
        )
        port = self.declare_int(
            "port", DEFAULT_PORT, "TCP port (0: any free one; a taken port falls back to one)", 0, 65535, read_only=True
        )
        token = self.declare_str(
            "token",
            "",
            "access token every request must carry (?token=...); auto = a random one, printed with the "
            "address; required when host is not a loopback address",
            read_only=True,
        )
        unix_socket = self.declare_str(
            "unix_socket",
            "",
            "also serve on this Unix socket (the launcher relays the page out of a private "
            "network namespace through it)",
            read_only=True,
        )
        self.public_url = self.declare_str(
            "public_url", "", "the page's address when the launcher relays it (else host:port)", read_only=True
        )
        model_grid = self.declare_int(
            "model_grid", 41, "points per axis of the GP posterior mean shown", 5, 201, read_only=True
        )
        max_points = self.declare_int(
            "max_signal_points", 2000, "at most this many samples per signal drawn", 100, 100000, read_only=True
        )
        poll_s = self.declare_float(
            "journal_poll_s",
            0.1,
            "how often the journal's size is looked at (it is read when it changed): the agent's J and "
            "recommendation reach the page as soon as they are journaled, s",
            0.1,
            60.0,
            read_only=True,
        )

        self._t0 = time.monotonic()
        self.campaign_dir = Path(campaign_dir).expanduser() if campaign_dir else None
        state = CockpitState("live", max_signal_points=max_points)
        relayed = bool(unix_socket and self.public_url)
        # token check first (CockpitError: host without a token is refused before anything listens)
        self.server = CockpitServer(
            state, host=host, port=port, token=token, unix_socket=unix_socket, serve_tcp=not relayed
        )
        self.feed = CampaignFeed(self.server, self.campaign_dir, model_grid=model_grid, poll_s=poll_s)
        bound = self.server.start()
        self.url = (
            self.public_url + (f"?token={self.server.token}" if self.server.token else "")
            if relayed
            else (self.server.url)
        )
        if bound.fallback_from:
            self.get_logger().warning(f"port {bound.fallback_from} is taken: the cockpit uses {bound.port}")
        self.feed.start()

        group = MutuallyExclusiveCallbackGroup()  # one callback at a time: they only hand messages over
        self._subs = [
            self.create_subscription(Trial, TOPIC_TRIAL, self._on_trial, QOS_LATCHED_READER, callback_group=group),
            self.create_subscription(RunSegment, TOPIC_RUN_SEGMENT, self._on_segment, QOS_EVENTS, callback_group=group),
            self.create_subscription(RunScore, TOPIC_RUN_SCORE, self._on_score, QOS_EVENTS, callback_group=group),
            self.create_subscription(
                Calibration, TOPIC_CALIBRATION, self._on_calibration, QOS_LATCHED_READER, callback_group=group
            ),
            self.create_subscription(
                DiagnosticArray, TOPIC_DIAGNOSTICS, self._on_diagnostics, QOS_DIAGNOSTICS, callback_group=group
            ),
        ]
        where = f"campaign {self.campaign_dir}" if self.campaign_dir else "topics only (no campaign_dir)"
        self.get_logger().info(f"cockpit: {self.url}  ({where}; read-only)")
        if self.campaign_dir is not None:
            with contextlib.suppress(OSError):
                self.campaign_dir.mkdir(parents=True, exist_ok=True)
                write_address_file(
                    self.campaign_dir,
                    {
                        "url": self.url,
                        "pid": os.getpid(),
                        "host": host,
                        "port": bound.port or port,
                        "token": bool(self.server.token),
                    },
                )

    # --- callbacks: convert and hand over, nothing else --------------------------------------------------
    def _on_trial(self, msg: Trial) -> None:
        self.feed.trial(trial_from_msg(msg))

    def _on_segment(self, msg: RunSegment) -> None:
        self.feed.segment(segment_from_msg(msg))

    def _on_score(self, msg: RunScore) -> None:
        self.feed.score(score_from_msg(msg))

    def _on_calibration(self, msg: Calibration) -> None:
        self.feed.calibration(calibration_from_msg(msg))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        self.feed.diagnostics(diagnostics_from_msg(msg))

    # --- end ----------------------------------------------------------------------------------------------------
    def cleanup_time_s(self) -> float:
        return 3.0

    def destroy_node(self) -> None:
        # what the page cost: this process's CPU and the model worker's fits (the graph's nodes are the others)
        self.get_logger().info(
            f"cockpit: {time.process_time():.1f} s of CPU in this process over {time.monotonic() - self._t0:.0f} s; "
            f"{self.feed.model_fits} GP fits in the worker, {self.feed.model_seconds_total:.1f} s of wall time in all"
        )
        self.feed.close()
        self.server.stop()
        if self.campaign_dir is not None:
            path = self.campaign_dir / ADDRESS_FILE
            with contextlib.suppress(OSError, ValueError):
                if json.loads(path.read_text()).get("pid") == os.getpid():
                    path.unlink()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(CockpitNode, args)


if __name__ == "__main__":
    sys.exit(main())
