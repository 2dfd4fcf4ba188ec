"""The graph launcher: both modes, parameters, signals, a dying node, network isolation."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from bac_bringup.profile import ProfileError, load_profile

from conftest import ROOT, wait_for

pytestmark = pytest.mark.integration
HELPERS = ROOT / "tests" / "helpers"


def make_profile(tmp_path: Path, nodes: list[dict[str, Any]], **extra: Any) -> Path:
    path = tmp_path / "test_profile.yaml"
    path.write_text(yaml.safe_dump({"description": "launcher test", "nodes": nodes, **extra}))
    return path


def reporter(name: str, out: Path, **params: Any) -> dict[str, Any]:
    return {
        "name": name,
        "entry": "graph_nodes:Reporter",
        "params": {"out_dir": str(out), **params},
        **({"ends_graph": True} if params.pop("_ends", False) else {}),
    }


def launch(env: dict[str, str], *args: str) -> subprocess.Popen[bytes]:
    env = {**env, "PYTHONPATH": f"{HELPERS}:{env.get('PYTHONPATH', '')}"}
    return subprocess.Popen(
        [sys.executable, "-m", "bac_bringup.cli", "launch", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def report(out: Path, name: str, kind: str = "start") -> dict[str, Any] | None:
    f = out / f"{name}.{kind}.json"
    return json.loads(f.read_text()) if f.exists() else None


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_smoke_profile_runs_and_exits_zero(ros_env: dict[str, str], mode: list[str]) -> None:
    p = launch(ros_env, "smoke", *mode)
    out, _ = p.communicate(timeout=90)
    text = out.decode(errors="replace")
    assert p.returncode == 0, text
    assert "received trial state of campaign 'smoke'" in text


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_parameters_environment_and_finish(ros_env: dict[str, str], tmp_path: Path, mode: list[str]) -> None:
    nodes = [
        reporter("alpha", tmp_path),
        {**reporter("omega", tmp_path, finish_after_s=2.0), "ends_graph": True},
    ]
    prof = make_profile(tmp_path, nodes, use_sim_time=False)
    p = launch(ros_env, str(prof), *mode, "-p", "alpha.tag:=hello world", "-p", "omega.tag:='42'")
    out, _ = p.communicate(timeout=90)
    assert p.returncode == 0, out.decode(errors="replace")
    a, o = report(tmp_path, "alpha"), report(tmp_path, "omega")
    assert a is not None and o is not None
    assert a["tag"] == "hello world" and o["tag"] == "42"
    assert a["discovery_range"] == "LOCALHOST" == o["discovery_range"]
    if mode:
        assert a["pid"] == o["pid"]  # one process
    else:
        assert a["pid"] != o["pid"] != os.getpid()
    # alpha was shut down cleanly when omega ended the graph
    assert report(tmp_path, "alpha", "clean") is not None


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_command_line_overrides_win_over_parameter_files(
    ros_env: dict[str, str], tmp_path: Path, mode: list[str]
) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(
        yaml.safe_dump({"alpha": {"ros__parameters": {"tag": "from file"}}, "omega": {"ros__parameters": {"tag": "x"}}})
    )
    nodes = [reporter("alpha", tmp_path), {**reporter("omega", tmp_path, finish_after_s=1.5), "ends_graph": True}]
    nodes[0]["params"].pop("tag", None)
    prof = make_profile(tmp_path, nodes, params_files=[str(params)])
    p = launch(ros_env, str(prof), *mode, "-p", "omega.tag:=from command line")
    out, _ = p.communicate(timeout=90)
    assert p.returncode == 0, out.decode(errors="replace")
    a, o = report(tmp_path, "alpha"), report(tmp_path, "omega")
    assert a is not None and o is not None
    assert a["tag"] == "from file"
    assert o["tag"] == "from command line"


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_a_mistyped_or_wrongly_typed_override_stops_the_launch_with_the_reason(
    ros_env: dict[str, str], tmp_path: Path, mode: list[str]
) -> None:
    # outside review 2026-11-29: -p bo_agent.budgt:=3 and -p bo_agent.budget:=abc both ran a campaign of 15 drives
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"omega": {"ros__parameters": {"finish_after_s": 30.0}}}))
    nodes = [reporter("alpha", tmp_path), {**reporter("omega", tmp_path), "ends_graph": True}]
    prof = make_profile(tmp_path, nodes, params_files=[str(params)], use_sim_time=False)
    for override, reason in (
        ("alpha.tagg:=x", "-p alpha.tagg: alpha has no parameter 'tagg'; did you mean 'tag'?"),
        (
            "omega.finish_after_s:=soon",
            "-p omega.finish_after_s:=soon: the node has 30.0 (float): a value of another type (str) does not",
        ),
    ):
        p = launch(ros_env, str(prof), *mode, "-p", override)
        out, _ = p.communicate(timeout=90)
        text = out.decode(errors="replace")
        assert p.returncode == 2 and f"not started: {reason}" in text and "Traceback" not in text, text
    # the same graph with the overrides right runs (an integer for a float parameter reaches it)
    p = launch(
        ros_env,
        str(prof),
        *mode,
        "-p",
        "alpha.tag:=x",
        "-p",
        "omega.finish_after_s:=1",
        "-p",
        "alpha.slow_destroy_s:=1e-05",
    )
    out, _ = p.communicate(timeout=90)
    assert p.returncode == 0, out.decode(errors="replace")
    a = report(tmp_path, "alpha")
    assert a is not None and a["tag"] == "x"


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_a_node_that_refuses_to_start_says_why_without_a_traceback(
    ros_env: dict[str, str], tmp_path: Path, mode: list[str]
) -> None:
    """bac's own errors (BacError) raised while a node starts are a message to act on: 'not started: ...', exit 2,
    the graph stopped (a foreign bag with nothing to play was a FATAL traceback, exit 1)."""
    nodes = [reporter("alpha", tmp_path, refuse_start="bag x has nothing to play"), reporter("omega", tmp_path)]
    p = launch(ros_env, str(make_profile(tmp_path, nodes, use_sim_time=False)), *mode)
    out, _ = p.communicate(timeout=90)
    text = out.decode(errors="replace")
    who = "alpha: " if mode else ""  # in a shared process the refusal names its node
    assert p.returncode == 2 and f"not started: {who}bag x has nothing to play" in text and "Traceback" not in text, (
        text
    )


def test_a_missing_or_broken_params_file_is_refused_before_anything_is_made(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    # outside review 2026-11-29: a FileNotFoundError traceback after the campaign folder's config/ was made; a file
    # that is not YAML started the graph and killed a node
    (tmp_path / "broken.yaml").write_text("x: [1\n")
    (tmp_path / "flat.yaml").write_text("budget: 3\n")
    # a namespaced file, as rcl reads it, is a parameter file (it gets past the check to the graph)
    (tmp_path / "ns.yaml").write_text(yaml.safe_dump({"ns": {"alpha": {"ros__parameters": {"tag": "x"}}}}))
    from bac_bringup.cliargs import ros_params_layout

    assert ros_params_layout(yaml.safe_load((tmp_path / "ns.yaml").read_text()))
    assert not ros_params_layout({"budget": 3}) and not ros_params_layout({"ns": {"alpha": {"tag": "x"}}})
    for name, reason in (
        ("nope.yaml", "no such file"),
        ("broken.yaml", "not YAML"),
        ("flat.yaml", "not a ROS parameter file"),
    ):
        camp = tmp_path / f"camp_{name}"
        p = launch(ros_env, "sim", "--params-file", str(tmp_path / name), "--campaign-dir", str(camp))
        out, _ = p.communicate(timeout=60)
        text = out.decode(errors="replace")
        assert p.returncode == 2 and f"--params-file {tmp_path / name}: {reason}" in text, text
        assert not camp.exists()


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_a_launch_whose_agent_refuses_to_start_leaves_no_configuration(
    ros_env: dict[str, str], tmp_path: Path, mode: list[str]
) -> None:
    """A first launch whose bo_agent refused (here a seed out of range: a traceback before 2026-11-29) left config/
    behind; the next launch that did start the campaign saved config.resume1/, and bac rescore / report took the
    refused launch's config/ for the campaign's."""
    camp = tmp_path / "camp"
    p = launch(ros_env, "sim", *mode, "--campaign-dir", str(camp), "-p", "bo_agent.seed:=-5")
    out, _ = p.communicate(timeout=120)
    text = out.decode(errors="replace")
    who = "bo_agent: " if mode else ""  # in a shared process the refusal names its node
    assert p.returncode == 2 and f"not started: {who}Invalid parameter value (-5)" in text, text
    assert "Parameter seed out of range" in text and "Traceback" not in text, text
    assert "config removed: this launch did not start or resume the campaign" in text, text
    assert not (camp / "config").exists() and not list(camp.glob("config.resume*"))
    # the agent told to journal elsewhere (its own -p wins over --campaign-dir): its start is not seen in this
    # folder, whose bags and config it may still fill; nothing is removed (an outside review: a campaign that ran
    # lost its config/ so)
    other = tmp_path / "other"
    p = launch(ros_env, "sim", *mode, "--campaign-dir", str(camp), "-p", f"bo_agent.campaign_dir:={other}",
               "-p", "bo_agent.seed:=-5")  # fmt: skip
    out, _ = p.communicate(timeout=120)
    text = out.decode(errors="replace")
    assert p.returncode == 2 and "config removed" not in text and (camp / "config" / "launch.json").is_file(), text


@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_a_dying_node_fails_the_graph(ros_env: dict[str, str], tmp_path: Path, mode: list[str]) -> None:
    nodes = [reporter("steady", tmp_path), reporter("crasher", tmp_path, crash_after_s=1.0)]
    p = launch(ros_env, str(make_profile(tmp_path, nodes)), *mode)
    out, _ = p.communicate(timeout=90)
    text = out.decode(errors="replace")
    assert p.returncode != 0, text
    assert "crash" in text
    assert report(tmp_path, "steady", "clean") is not None  # the survivor was stopped cleanly


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("mode", [[], ["--single-process"]], ids=["processes", "single-process"])
def test_signals_are_forwarded_and_nodes_shut_down_cleanly(
    ros_env: dict[str, str], tmp_path: Path, mode: list[str], sig: signal.Signals
) -> None:
    nodes = [reporter("one", tmp_path), reporter("two", tmp_path)]
    p = launch(ros_env, str(make_profile(tmp_path, nodes)), *mode)
    wait_for(lambda: report(tmp_path, "one") and report(tmp_path, "two"), 60, what="both nodes started")
    p.send_signal(sig)
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 0, out.decode(errors="replace")
    assert report(tmp_path, "one", "clean") is not None
    assert report(tmp_path, "two", "clean") is not None


def test_udp_multicast_can_between_processes_gets_a_private_netns(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Outside a private namespace, a udp_multicast profile re-runs itself inside a new one."""
    nodes = [
        {**reporter("can_a", tmp_path), "can": True},
        {**reporter("can_b", tmp_path, finish_after_s=1.5), "can": True, "ends_graph": True},
    ]
    prof = make_profile(tmp_path, nodes, can={"interface": "udp_multicast", "channel": "239.74.163.2"})
    env = {k: v for k, v in ros_env.items() if k != "BAC_PRIVATE_NETNS"}
    p = launch(env, str(prof))
    out, _ = p.communicate(timeout=90)
    assert p.returncode == 0, out.decode(errors="replace")
    a, b = report(tmp_path, "can_a"), report(tmp_path, "can_b")
    assert a is not None and b is not None
    assert a["can_interface"] == "udp_multicast"
    assert a["netns"] == b["netns"] != os.stat("/proc/self/ns/net").st_ino


def test_single_process_uses_the_virtual_bus(ros_env: dict[str, str], tmp_path: Path) -> None:
    nodes = [{**reporter("can_a", tmp_path, finish_after_s=1.0), "can": True, "ends_graph": True}]
    prof = make_profile(tmp_path, nodes, can={"interface": "udp_multicast", "channel": "239.74.163.2"})
    p = launch(ros_env, str(prof), "--single-process")
    out, _ = p.communicate(timeout=90)
    assert p.returncode == 0, out.decode(errors="replace")
    a = report(tmp_path, "can_a")
    assert a is not None and a["can_interface"] == "virtual"
    assert a["netns"] == os.stat("/proc/self/ns/net").st_ino


def test_a_node_with_a_stop_grace_may_take_longer_than_the_default_to_stop(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    """The ECU bridge may retry a refused baseline restore at shutdown: stop_grace_s keeps SIGTERM away."""
    slow = reporter("slow", tmp_path, slow_destroy_s=10.0)
    slow["stop_grace_s"] = 20.0
    p = launch(ros_env, str(make_profile(tmp_path, [slow])))
    wait_for(lambda: report(tmp_path, "slow"), 60, what="the node started")
    p.send_signal(signal.SIGINT)
    out, _ = p.communicate(timeout=60)
    text = out.decode(errors="replace")
    assert p.returncode == 0 and "sent SIGTERM" not in text, text
    assert report(tmp_path, "slow", "clean") is not None


def test_a_node_that_loses_the_sigint_while_it_imports_still_stops_cleanly(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    """CPython swallows the KeyboardInterrupt of a SIGINT that lands in a finalizer; a node still importing its
    modules then started and spun until the launcher's SIGTERM (2 of ~400 SIGINTs in a node's first second under
    load, 2026-11-24). The launcher sends SIGINT again every second of its grace, which is harmless to a node
    already stopping (run_node's SIGINT is a flag), so the node stops cleanly on the next one."""
    marker = tmp_path / "importing"
    nodes = [{"name": "lossy", "entry": "lossy_import_node:Reporter", "params": {"out_dir": str(tmp_path)}}]
    p = launch({**ros_env, "BAC_TEST_LOSSY_MARKER": str(marker)}, str(make_profile(tmp_path, nodes)))
    try:
        wait_for(marker.exists, 60, what="the node importing its modules")
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = out.decode(errors="replace")
    assert "Exception ignored" in text and "KeyboardInterrupt" in text, text  # the first SIGINT was lost
    assert p.returncode == 0 and "SIGTERM" not in text and "SIGKILL" not in text, text


def shared_process_profile(tmp_path: Path, can: dict[str, Any]) -> Path:
    """Two CAN nodes sharing the process "car" (the ECU's side stops last), a third node in its own process."""
    nodes = [
        {**reporter("ecu_side", tmp_path), "can": True, "process": "car", "stop_order": 1},
        {**reporter("bridge_side", tmp_path), "can": True, "process": "car"},
        {**reporter("solo", tmp_path, finish_after_s=2.0), "ends_graph": True},
    ]
    return make_profile(tmp_path, nodes, can=can)


def test_nodes_sharing_a_process_keep_can_in_it_without_a_namespace(ros_env: dict[str, str], tmp_path: Path) -> None:
    """CAN between nodes of one process: the in-process virtual bus, and no private namespace (ROS tools see the
    graph), even though the profile names udp_multicast for CAN between processes."""
    prof = shared_process_profile(tmp_path, {"interface": "udp_multicast", "channel": "239.74.163.2"})
    env = {k: v for k, v in ros_env.items() if k != "BAC_PRIVATE_NETNS"}
    p = launch(env, str(prof), "--log-dir", str(tmp_path / "logs"))
    out, _ = p.communicate(timeout=90)
    text = out.decode(errors="replace")
    assert p.returncode == 0, text
    ecu, bridge, solo = (report(tmp_path, n) for n in ("ecu_side", "bridge_side", "solo"))
    assert ecu is not None and bridge is not None and solo is not None
    assert ecu["pid"] == bridge["pid"] != solo["pid"]
    assert ecu["can_interface"] == bridge["can_interface"] == "virtual"
    here = os.stat("/proc/self/ns/net").st_ino
    assert ecu["netns"] == bridge["netns"] == solo["netns"] == here, text
    assert "private network namespace" not in text
    # both stopped cleanly, the bridge's side first (stop_order), then the ECU's
    clean = {n: tmp_path / f"{n}.clean.json" for n in ("ecu_side", "bridge_side")}
    assert all(f.exists() for f in clean.values()), text
    assert clean["bridge_side"].stat().st_mtime_ns <= clean["ecu_side"].stat().st_mtime_ns
    # one log for the shared process; each of its nodes' logs leads there
    logs = tmp_path / "logs"
    assert (logs / "car.log").is_file() and (logs / "solo.log").is_file()
    assert (logs / "ecu_side.log").resolve() == (logs / "car.log").resolve()
    assert "process car: ecu_side, bridge_side" in (logs / "bridge_side.log").read_text()


def test_process_per_node_takes_shared_can_between_processes_into_a_namespace(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    prof = shared_process_profile(tmp_path, {"interface": "udp_multicast", "channel": "239.74.163.2"})
    env = {k: v for k, v in ros_env.items() if k != "BAC_PRIVATE_NETNS"}
    p = launch(env, str(prof), "--process-per-node")
    out, _ = p.communicate(timeout=90)
    assert p.returncode == 0, out.decode(errors="replace")
    ecu, bridge = report(tmp_path, "ecu_side"), report(tmp_path, "bridge_side")
    assert ecu is not None and bridge is not None
    assert ecu["pid"] != bridge["pid"]
    assert ecu["can_interface"] == "udp_multicast"
    assert ecu["netns"] == bridge["netns"] != os.stat("/proc/self/ns/net").st_ino


def test_a_lone_can_node_keeps_the_profiles_bus(ros_env: dict[str, str], tmp_path: Path) -> None:
    """One CAN node talks to a peer outside the graph (python -m bac_sim.ecu): its bus stays udp_multicast."""
    nodes = [{**reporter("bridge_only", tmp_path, finish_after_s=1.0), "can": True, "ends_graph": True}]
    prof = make_profile(tmp_path, nodes, can={"interface": "udp_multicast", "channel": "239.74.163.2"})
    p = launch(ros_env, str(prof))
    out, _ = p.communicate(timeout=90)
    assert p.returncode == 0, out.decode(errors="replace")
    r = report(tmp_path, "bridge_only")
    assert r is not None and r["can_interface"] == "udp_multicast"


def test_a_virtual_bus_between_processes_is_refused(ros_env: dict[str, str], tmp_path: Path) -> None:
    prof = shared_process_profile(tmp_path, {"interface": "virtual", "channel": "x"})
    p = launch(ros_env, str(prof), "--process-per-node")
    out, _ = p.communicate(timeout=90)
    text = out.decode(errors="replace")
    assert p.returncode == 2, text
    assert "reaches only the same process" in text and "ecu_side, bridge_side" in text
    assert report(tmp_path, "ecu_side") is None  # nothing was started


def test_profiles_shipped_load() -> None:
    for name in ("sim", "car", "replay", "smoke"):
        prof = load_profile(name)
        assert prof.nodes
    sim = load_profile("sim")
    assert sim.use_sim_time and sim.can is not None and sim.can.interface == "udp_multicast"
    assert [n.name for n in sim.nodes if n.ends_graph] == ["bo_agent"]
    # the simulated car's ECU and the bridge share a process: CAN stays in it, the graph in this namespace
    assert sim.can_processes == ("vehicle",)
    assert {n.name for n in sim.nodes if n.process == "vehicle"} == {"vehicle_sim", "ecu_bridge"}
    assert len(sim.one_process_per_node().can_processes) == 2
    car = load_profile("car")
    assert not car.use_sim_time and "vehicle_sim" not in [n.name for n in car.nodes]
    bridge = next(n for n in car.nodes if n.name == "ecu_bridge")
    assert bridge.stop_grace_s > 60.0  # beyond the bridge's restore_pending_s (params/car.yaml)


def test_bad_profiles_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ProfileError, match="unknown profile"):
        load_profile("no_such_profile")
    bad = tmp_path / "bad.yaml"
    bad.write_text("nodes: [{name: x}]\n")
    with pytest.raises(ProfileError, match="entry"):
        load_profile(bad)
    bad.write_text("nodes: [{name: a, entry: 'm:A', process: b}, {name: b, entry: 'm:B', process: c}]\n")
    with pytest.raises(ProfileError, match="name the shared process differently"):
        load_profile(bad)


def test_a_node_ended_by_its_hard_deadline_makes_the_stop_unclean(ros_env: dict[str, str], tmp_path: Path) -> None:
    """A node that ends with a non-zero code while stopping (its hard deadline: 1, or SIGALRM; the bridge cut short
    in its baseline restore) ended in time but not cleanly: the launcher stopped by Ctrl-C says so with its exit
    code, not only in a warning (it exited 0)."""
    nodes = [reporter("cut", tmp_path, stop_exit_code=1), reporter("fine", tmp_path)]
    p = launch(ros_env, str(make_profile(tmp_path, nodes)))
    wait_for(lambda: report(tmp_path, "cut") and report(tmp_path, "fine"), 60, what="both nodes started")
    p.send_signal(signal.SIGINT)
    out, _ = p.communicate(timeout=60)
    text = out.decode(errors="replace")
    assert p.returncode == 1 and "cut ended with code 1 while stopping" in text, text
    assert "sent SIGTERM" not in text, text
    assert report(tmp_path, "fine", "clean") is not None
