"""Make ROS and CAN traffic the way bac does, and report interface counters (JSON on stdout).

Run inside a throw-away network namespace that has a loopback *and* a fake
external interface `ext0` (a veth end) with the default route, so that any packet that
would leave the machine is counted on ext0's transmit counter.

    net_probe.py --discovery-range LOCALHOST [--launch]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def counters() -> dict[str, dict[str, int]]:
    out = {}
    for line in Path("/proc/net/dev").read_text().splitlines()[2:]:
        name, data = line.split(":", 1)
        f = data.split()
        out[name.strip()] = {"rx_packets": int(f[1]), "tx_packets": int(f[9])}
    return out


def ros_traffic(discovery_range: str) -> bool:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    import bac_msgs.msg as M

    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": discovery_range}
    echo = subprocess.Popen([sys.executable, str(HERE / "echo_node.py")], env=env)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = discovery_range
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("net_probe", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    got: list[object] = []
    pub = node.create_publisher(M.Calibration, "rt/in/Calibration", 10)
    node.create_subscription(M.Calibration, "rt/out/Calibration", got.append, 10)
    try:
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline and not got:
            if pub.get_subscription_count() > 0:
                pub.publish(M.Calibration(trial_id=7, names=["a"], values=[1.0]))
            ex.spin_once(timeout_sec=0.1)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        stop(echo)
    return bool(got)


def stop(proc: subprocess.Popen) -> None:
    """Ctrl-C the child, then kill it: an echo node left behind would hold the caller's output pipe open."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


def can_traffic() -> bool:
    import can

    a = can.Bus(interface="udp_multicast", channel="239.74.163.2")
    b = can.Bus(interface="udp_multicast", channel="239.74.163.2")
    try:
        for i in range(20):
            a.send(can.Message(arbitration_id=0x600 + i, data=bytes([i] * 8), is_extended_id=False))
        seen = 0
        deadline = time.monotonic() + 10
        while seen < 20 and time.monotonic() < deadline:
            if b.recv(timeout=0.5) is not None:
                seen += 1
        return seen == 20
    finally:
        a.shutdown()
        b.shutdown()


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--discovery-range", default="LOCALHOST")
    ap.add_argument("--launch", action="store_true", help="also run the smoke graph with the launcher")
    args = ap.parse_args()
    before = counters()
    result = {"ros_ok": ros_traffic(args.discovery_range), "can_ok": can_traffic()}
    if args.launch:
        rc = subprocess.call(
            [sys.executable, "-m", "bac_bringup.cli", "launch", "smoke"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        result["launch_rc"] = rc
    time.sleep(0.5)  # let in-flight packets reach the counters (measurement, not synchronisation)
    after = counters()
    result["delta"] = {k: {m: after[k][m] - before.get(k, {}).get(m, 0) for m in after[k]} for k in after}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
