"""Two tiny nodes that check a graph can start, talk and end (the ``smoke`` profile).

``trial_announcer`` publishes one latched bac_msgs/Trial; ``trial_listener``
ends the graph (exit 0) when it has received it, or fails after a timeout.
"""

from __future__ import annotations

import math
import sys
from typing import Any

from bac_common.contracts import TOPIC_TRIAL
from bac_common.rosnode import QOS_LATCHED, BacNode, run_node
from bac_msgs.msg import Trial


class TrialAnnouncer(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("trial_announcer", **kwargs)
        self.campaign_id = self.declare_str("campaign_id", "smoke", "campaign id to announce")
        self.pub = self.create_publisher(Trial, TOPIC_TRIAL, QOS_LATCHED)
        msg = Trial(
            campaign_id=self.campaign_id,
            state=Trial.STATE_IDLE,
            last_j=math.nan,
            best_j=math.nan,
            predicted_j=math.nan,
            predicted_j_std=math.nan,
            instruction="smoke test: nothing to drive",
        )
        msg.stamp = self.get_clock().now().to_msg()
        self.pub.publish(msg)
        self.get_logger().info(f"announced trial state of campaign '{self.campaign_id}'")


class TrialListener(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("trial_listener", **kwargs)
        self.timeout_s = self.declare_float(
            "timeout_s", 30.0, "fail when nothing arrives within this time, s", 0.1, 600.0
        )
        self.sub = self.create_subscription(Trial, TOPIC_TRIAL, self._on_trial, QOS_LATCHED)
        self.timer = self.create_timer(self.timeout_s, self._on_timeout)

    def _on_trial(self, msg: Trial) -> None:
        self.get_logger().info(f"received trial state of campaign '{msg.campaign_id}': the graph works")
        self.finish(0)

    def _on_timeout(self) -> None:
        self.get_logger().error(f"no bac/trial within {self.timeout_s} s")
        self.finish(1)


def main(args: list[str] | None = None) -> int:
    """Run one of the two smoke nodes: ``python -m bac_bringup.smoke_node --ros-args -r __node:=trial_listener``
    (the listener when the node is named so, else the announcer)."""
    argv = list(sys.argv if args is None else args)
    cls = TrialListener if "__node:=trial_listener" in " ".join(argv) else TrialAnnouncer
    return run_node(cls, argv)


def announcer_main(args: list[str] | None = None) -> int:
    """``trial_announcer`` (console script)."""
    return run_node(TrialAnnouncer, list(sys.argv if args is None else args))


def listener_main(args: list[str] | None = None) -> int:
    """``trial_listener`` (console script)."""
    return run_node(TrialListener, list(sys.argv if args is None else args))


if __name__ == "__main__":
    sys.exit(main())
