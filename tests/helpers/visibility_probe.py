"""Is a running sim graph visible to a ROS tool started apart from it? Report JSON on stdout.

Run inside a throw-away network namespace that has a loopback and a fake external interface `ext0` (a veth end
holding the default route; see tests/bringup/test_network_isolation.py): any packet that would leave the machine
is counted on ext0's transmit counter.

    visibility_probe.py CAMPAIGN_DIR launch sim [ARGS ...]      (or: demo [ARGS ...])

starts ``bac launch sim --campaign-dir CAMPAIGN_DIR ARGS`` (or ``bac demo``), as a user would: not marked as
inside a private namespace, so the launcher enters one of its own if the profile needs it; and beside it,
apart from the launcher, a plain rclpy process that subscribes to bac/trial as ``ros2 topic echo /bac/trial``
would. It waits for the campaign to end, stops the
listener and prints what the listener received, the launcher's exit code and output, whether any process of
the graph ran in another network namespace than this one, and the interface counters' change.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

LISTENER = r"""
import json, sys
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from bac_msgs.msg import Trial

out = open(sys.argv[1], "a", buffering=1)
rclpy.init()
node = rclpy.create_node("trial_echo")
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
node.create_subscription(
    Trial, "bac/trial", lambda m: out.write(json.dumps({"campaign_id": m.campaign_id, "state": m.state}) + "\n"), qos
)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
"""


def counters() -> dict[str, dict[str, int]]:
    out = {}
    for line in Path("/proc/net/dev").read_text().splitlines()[2:]:
        name, data = line.split(":", 1)
        f = data.split()
        out[name.strip()] = {"rx_packets": int(f[1]), "tx_packets": int(f[9])}
    return out


def descendants(root: int) -> set[int]:
    """The processes below ``root`` (the launcher and the nodes it started, or re-ran itself to start)."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
                parent[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    found, todo = set(), [root]
    while todo:
        pid = todo.pop()
        kids = [c for c, p in parent.items() if p == pid and c not in found]
        found.update(kids)
        todo.extend(kids)
    return found


def graph_namespaces(launcher: int, marker: str) -> set[int]:
    """Network namespaces of the launcher's descendants whose command line mentions ``marker`` (a node)."""
    found = set()
    for pid in descendants(launcher):
        d = Path("/proc") / str(pid)
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            if marker in cmd:
                found.add(os.stat(d / "ns" / "net").st_ino)
        except OSError:
            continue
    return found


def main() -> int:
    camp = Path(sys.argv[1])
    command = [*sys.argv[2:], "--campaign-dir", str(camp)]
    camp.parent.mkdir(parents=True, exist_ok=True)
    env = {k: v for k, v in os.environ.items() if k != "BAC_PRIVATE_NETNS"}  # as a user's shell
    received = camp.parent / "received.jsonl"
    before = counters()
    here = os.stat("/proc/self/ns/net").st_ino
    with (camp.parent / "launch.log").open("wb") as log:
        launch = subprocess.Popen(
            [sys.executable, "-m", "bac_bringup.cli", *command],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    listener = subprocess.Popen([sys.executable, "-c", LISTENER, str(received)], env=env, start_new_session=True)
    namespaces: set[int] = set()
    try:
        deadline = time.monotonic() + 400
        while launch.poll() is None and time.monotonic() < deadline:
            namespaces |= graph_namespaces(launch.pid, "bac_agent.agent_node")
            time.sleep(0.2)
        if launch.poll() is None:
            os.killpg(launch.pid, signal.SIGINT)
        launch_rc = launch.wait(timeout=60)
    finally:
        for p in (launch, listener):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
    time.sleep(0.5)  # let in-flight packets reach the counters (measurement, not synchronisation)
    after = counters()
    messages = [json.loads(x) for x in received.read_text().splitlines()] if received.exists() else []
    result = {
        "received": messages,
        "launch_rc": launch_rc,
        "launch_log": (camp.parent / "launch.log").read_text(errors="replace")[-4000:],
        "graph_in_this_namespace": namespaces == {here},
        "graph_namespaces": sorted(namespaces),
        "delta": {k: {m: after[k][m] - before.get(k, {}).get(m, 0) for m in after[k]} for k in after},
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
