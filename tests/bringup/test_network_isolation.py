"""Nothing leaves loopback: interface counters while bac's ROS and CAN traffic flows.

Each case runs in a throw-away network namespace that has, beside loopback, a
fake external interface `ext0` (one end of a veth pair, holding the default route): any
packet that would leave the machine is counted on its transmit counter.
The control cases show that the counter does see leaking traffic, so the
zero in the real cases means something.

The sim graph runs in the machine's own namespace (CAN stays in one process), so that a ROS tool started apart
from it (``ros2 topic echo /bac/trial``) sees it, with nothing leaving loopback all the same; with
``--process-per-node`` CAN crosses processes over udp_multicast and the launcher hides the graph in a private
namespace of its own.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from conftest import ROOT

pytestmark = pytest.mark.integration
PROBE = ROOT / "tests" / "helpers" / "net_probe.py"
VISIBILITY_PROBE = ROOT / "tests" / "helpers" / "visibility_probe.py"


def run_probe(ros_env: dict[str, str], discovery_range: str, lo_multicast_route: bool, launch: bool) -> dict:
    args = [sys.executable, str(PROBE), "--discovery-range", discovery_range] + (["--launch"] if launch else [])
    return run_in_namespace_with_an_external_interface(ros_env, args, lo_multicast_route)


def run_in_namespace_with_an_external_interface(
    ros_env: dict[str, str], args: list[str], lo_multicast_route: bool, timeout: float = 240
) -> dict:
    """Run ``args`` in a new network namespace with loopback and ``ext0`` (the default route); its last line of
    output is JSON."""
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
    env = {**ros_env, "PYTHONPATH": f"{ROOT / 'tests' / 'helpers'}:{ros_env.get('PYTHONPATH', '')}"}
    env["BAC_PRIVATE_NETNS"] = "1"
    # output to files, not pipes: a grandchild left running could otherwise keep a pipe open and hang the test
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.run(
            ["unshare", "--net", "--", "/bin/sh", "-c", script, "sh", *args],
            env=env,
            stdout=out,
            stderr=err,
            timeout=timeout,
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


def sim_graph_seen_from_outside(ros_env: dict[str, str], tmp_path: Path, *launch_args: str) -> dict:
    """``bac launch sim`` (2 trials) and, apart from it, a plain rclpy listener of bac/trial, in a namespace whose
    only way off the machine is ext0, with no multicast route on loopback (a machine's usual routes)."""
    args = [
        sys.executable, str(VISIBILITY_PROBE), str(tmp_path / "campaign"), "launch", "sim",
        "--timeout", "300", "--log-dir", str(tmp_path / "logs"),
        "-p", "bo_agent.budget:=2", "-p", "bo_agent.confirmation_run:=false", *launch_args,
    ]  # fmt: skip
    return run_in_namespace_with_an_external_interface(ros_env, args, lo_multicast_route=False, timeout=480)


@pytest.mark.slow
def test_a_ros_tool_apart_from_the_launcher_sees_the_sim_graph_and_nothing_leaves(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    r = sim_graph_seen_from_outside(ros_env, tmp_path)
    assert r["launch_rc"] == 0, r["launch_log"]
    assert "private network namespace" not in r["launch_log"]
    assert r["graph_in_this_namespace"], r["graph_namespaces"]
    states = {m["state"] for m in r["received"] if m["campaign_id"] == "campaign"}
    assert 7 in states, r["received"]  # the campaign's end (Trial.STATE_DONE), heard by the outside listener
    assert r["delta"]["lo"]["tx_packets"] > 100, r["delta"]  # the traffic really flowed, on loopback
    assert r["delta"]["ext0"]["tx_packets"] == 0, r["delta"]


@pytest.mark.slow
def test_control_with_can_between_processes_the_graph_hides_in_a_private_namespace(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    r = sim_graph_seen_from_outside(ros_env, tmp_path, "--process-per-node")
    assert r["launch_rc"] == 0, r["launch_log"]
    assert "entering a private network namespace" in r["launch_log"]
    assert not r["graph_in_this_namespace"] and r["graph_namespaces"], r["graph_namespaces"]
    assert r["received"] == []  # the whole campaign ran, and a tool outside its namespace heard nothing


@pytest.mark.slow
def test_the_demo_keeps_its_graph_in_a_private_namespace(ros_env: dict[str, str], tmp_path: Path) -> None:
    """bac demo is a measurement: no other graph on the machine may disturb it (bac demo --visible: it is seen)."""
    args = [sys.executable, str(VISIBILITY_PROBE), str(tmp_path / "campaign"), "demo", "--budget", "2"]
    r = run_in_namespace_with_an_external_interface(ros_env, args, lo_multicast_route=False, timeout=480)
    assert r["launch_rc"] == 0, r["launch_log"]
    assert "recommendation_gap_pct" in r["launch_log"]
    assert not r["graph_in_this_namespace"] and r["graph_namespaces"], r["graph_namespaces"]
    assert r["received"] == []
    assert r["delta"]["ext0"]["tx_packets"] == 0, r["delta"]


WORKER_PROBE = """
import json, os, socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
try:
    s.bind(("127.0.0.1", int(sys.argv[1])))
    bound = True
except OSError:
    bound = False
ifaces = sorted(line.split(":")[0].strip() for line in open("/proc/self/net/dev").readlines()[2:])
print(json.dumps({"pid": os.getpid(), "bound": bound, "ifaces": ifaces, "marker": os.environ.get("BAC_PRIVATE_NETNS")}))
"""


def test_a_test_worker_has_a_namespace_of_its_own(ros_env: dict[str, str]) -> None:
    """scripts/test-worker (make test's pytest-xdist workers) is the venv's Python in a fresh private namespace,
    made even inside one, in the same process (xdist talks to it over its standard streams and stops it by pid):
    a UDP port held here is free there, and it has loopback only."""
    if shutil.which("unshare") is None:
        pytest.skip("needs unshare")
    held = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    held.bind(("127.0.0.1", 0))
    port = held.getsockname()[1]
    try:
        proc = subprocess.Popen(
            [str(ROOT / "scripts" / "test-worker"), "-c", WORKER_PROBE, str(port)],
            env={**ros_env, "BAC_PRIVATE_NETNS": "1"},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    finally:
        held.close()
    assert proc.returncode == 0, err
    got = json.loads(out.strip().splitlines()[-1])
    assert got["bound"], "the worker shares this namespace's loopback"
    assert got["ifaces"] == ["lo"]
    assert got["pid"] == proc.pid, "the worker is not the process xdist started"
    assert got["marker"] == "1"


def test_workers_take_disjoint_shares_of_the_ros_domains(monkeypatch: pytest.MonkeyPatch, ros_domain: int) -> None:
    """Fast DDS's shared-memory transport is not namespaced: two workers must never use one domain. This test's
    own domain, and the next, come from its worker's share."""
    import conftest

    assert ros_domain in conftest._worker_domains() and conftest.fresh_domain() in conftest._worker_domains()
    for count in (1, 2, 3, 4):
        shares = []
        for k in range(count):
            monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", str(count))
            monkeypatch.setenv("PYTEST_XDIST_WORKER", f"gw{k}")
            shares.append(set(conftest._worker_domains()))
        assert sum(len(s) for s in shares) == 101 and set().union(*shares) == set(range(1, 102)), count
        assert all(len(s) >= 25 for s in shares)
    monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT")
    monkeypatch.delenv("PYTEST_XDIST_WORKER")
    assert set(conftest._worker_domains()) == set(range(1, 102))
