"""Nothing leaves loopback: interface counters while bac's ROS and CAN traffic flows.

Each case runs in a throw-away network namespace that has, beside loopback, a
fake external interface `ext0` (one end of a veth pair, holding the default route): any
packet that would leave the machine is counted on its transmit counter.
The control cases show that the counter does see leaking traffic, so the
zero in the real cases means something.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from conftest import ROOT

pytestmark = pytest.mark.integration
PROBE = ROOT / "tests" / "helpers" / "net_probe.py"


def run_probe(ros_env: dict[str, str], discovery_range: str, lo_multicast_route: bool, launch: bool) -> dict:
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("needs root and unshare to build a namespace with a fake external interface")
    setup = [
        "ip link set lo up multicast on",
        "ip link add ext0 type veth peer name ext1",
        "sysctl -q -w net.ipv6.conf.ext0.disable_ipv6=1 net.ipv6.conf.ext1.disable_ipv6=1",
        "ip addr add 10.213.0.2/24 dev ext0",
        "ip link set ext1 up",
        "ip link set ext0 up multicast on",
        "ip route add default via 10.213.0.1 dev ext0",
    ]
    if lo_multicast_route:
        setup.append("ip route add 224.0.0.0/4 dev lo")
    else:
        setup.append("ip route add 224.0.0.0/4 dev ext0")
    script = " && ".join(setup) + ' && exec "$@"'
    args = [sys.executable, str(PROBE), "--discovery-range", discovery_range] + (["--launch"] if launch else [])
    env = {**ros_env, "PYTHONPATH": f"{ROOT / 'tests' / 'helpers'}:{ros_env.get('PYTHONPATH', '')}"}
    env["BAC_PRIVATE_NETNS"] = "1"
    # output to files, not pipes: a grandchild left running could otherwise keep a pipe open and hang the test
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.run(
            ["unshare", "--net", "--", "/bin/sh", "-c", script, "sh", *args],
            env=env,
            stdout=out,
            stderr=err,
            timeout=240,
            check=False,
        )
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    assert proc.returncode == 0, stderr[-4000:]
    return json.loads(stdout.strip().splitlines()[-1])


def test_session_namespace_has_only_loopback(in_private_netns: bool) -> None:
    if not in_private_netns:
        pytest.skip("run through make test / scripts/pytest.sh (private network namespace)")
    names = [line.split(":", 1)[0].strip() for line in Path("/proc/net/dev").read_text().splitlines()[2:]]
    assert names == ["lo"]


def test_bac_traffic_stays_on_loopback(ros_env: dict[str, str]) -> None:
    r = run_probe(ros_env, "LOCALHOST", lo_multicast_route=True, launch=True)
    assert r["ros_ok"] and r["can_ok"] and r["launch_rc"] == 0, r
    assert r["delta"]["lo"]["tx_packets"] > 100, r  # the traffic really flowed, on loopback
    assert r["delta"]["ext0"]["tx_packets"] == 0, r


def test_control_a_wider_discovery_range_leaks_and_is_counted(ros_env: dict[str, str]) -> None:
    r = run_probe(ros_env, "SUBNET", lo_multicast_route=False, launch=False)
    assert r["delta"]["ext0"]["tx_packets"] > 0, r
