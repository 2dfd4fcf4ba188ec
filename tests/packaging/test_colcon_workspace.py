"""bac as a ROS user gets it: a workspace with a copy of src/ only, built and tested by colcon, used from its
install space.

The venv is the ROS 2 Jazzy underlay (ROS from the PyPI wheels; on a laptop it is /opt/ros/jazzy). In the copy:
``colcon build`` and ``colcon test`` pass and ``colcon test-result`` counts every quick unit test pytest collects
in src/*/test (``-m "not slow"``: the unit tests marked slow, a few seconds or more each, run once, in make test's
own pytest; the check asks that some exist, so a filter that matched nothing would not pass unseen); after
``source install/setup.bash`` the packages, the profiles, parameter files, calibration definitions and DBC files
come from install/ (ament index), ``bac`` is on PATH, every node starts as ``install/<pkg>/lib/<pkg>/<node>`` and
stops cleanly on SIGINT, and ``bac launch sim`` run in a folder outside the repository (BAC_WS unset) runs a
campaign to its end.

Figures (2026-11-25 09:33-09:39 UTC, 2-core machine at load 4.5-5, three benchmarks beside): colcon build with
2 workers 1:16, colcon test 3:10 (bac_agent's quick unit tests 1:47 of it, on the path of the packages above it;
3:51 with every unit test, same load), the whole module 5:45.
"""

from __future__ import annotations

import ast
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from conftest import ROOT, fresh_domain, wait_for

# the workspace fixture (colcon build + colcon test) takes 1 to 4 minutes depending on the machine's load
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(1200)]

VENV = Path(sys.prefix)
PACKAGES = [p.name for p in sorted((ROOT / "src").iterdir()) if (p / "package.xml").is_file()]
PY_PACKAGES = [p for p in PACKAGES if (ROOT / "src" / p / "setup.py").is_file()]
BUDGET = 3  # trials of the campaign run from the install space

# every node of bac: package, executable, the arguments it needs to come up (filled in per test below)
NODES: dict[str, str] = {
    "imu_ingest": "bac_imu",
    "run_segmenter": "bac_measure",
    "kpi_scorer": "bac_measure",
    "bo_agent": "bac_agent",
    "ecu_bridge": "bac_ecu_bridge",
    "vehicle_sim": "bac_sim",
    "campaign_recorder": "bac_campaign",
    "cockpit": "bac_cockpit",
    "bag_player": "bac_campaign",
    "trial_announcer": "bac_bringup",
    "trial_listener": "bac_bringup",
}
TOOLS = {"bac"}  # console scripts that are not nodes
# colcon test runs the quick unit tests (bac_common's pytest plugin declares the marker, so a workspace without the
# repository's pyproject.toml knows it; with --strict-markers an undeclared one would be an error)
SLOW_FILTER = ["-m", "not slow"]
COLCON_PYTEST_ARGS = [*SLOW_FILTER, "--strict-markers"]


def run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float, log: Path) -> subprocess.CompletedProcess[str]:
    """Run a command with its output in ``log`` (files, not pipes: colcon's children could hold a pipe open)."""
    with log.open("w") as out:
        proc = subprocess.run(
            cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, timeout=timeout, check=False, text=True
        )
    return subprocess.CompletedProcess(proc.args, proc.returncode, log.read_text(errors="replace"), "")


def underlay_env() -> dict[str, str]:
    """A shell with the venv as the ROS underlay and nothing of the repository: what a user has before sourcing
    the workspace (BAC_WS unset, no PYTHONPATH into the sources)."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("BAC_WS", "PYTHONPATH", "COLCON_PREFIX_PATH", "BAC_PRIVATE_NETNS") and not k.startswith("PYTEST")
    }
    env["VIRTUAL_ENV"] = str(VENV)
    env["PATH"] = f"{VENV / 'bin'}:{env.get('PATH', '/usr/bin:/bin')}"
    env["AMENT_PREFIX_PATH"] = str(VENV)
    env["CMAKE_PREFIX_PATH"] = str(VENV)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    return env


class Workspace:
    def __init__(self, root: Path, build: subprocess.CompletedProcess[str], test: subprocess.CompletedProcess[str]):
        self.root = root
        self.install = root / "install"
        self.build = build
        self.test = test
        env = underlay_env()
        out = subprocess.run(
            ["bash", "-c", "source install/setup.bash && env -0"],
            cwd=root,
            env=env,
            capture_output=True,
            check=True,
            timeout=60,
        ).stdout
        self.env = dict(item.split("=", 1) for item in out.decode().split("\0") if "=" in item)

    def exe(self, node: str) -> Path:
        pkg = NODES[node]
        return self.install / pkg / "lib" / pkg / node

    def python(self, code: str, cwd: Path) -> str:
        proc = subprocess.run(
            [sys.executable, "-c", code],
            cwd=cwd,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert proc.returncode == 0, proc.stderr
        return proc.stdout


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    if shutil.which("colcon", path=str(VENV / "bin")) is None:
        pytest.fail("colcon is not installed in the venv (requirements/test.txt; run scripts/setup.sh)")
    ws = tmp_path_factory.mktemp("colcon_ws")
    shutil.copytree(
        ROOT / "src",
        ws / "src",
        ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", ".pytest_cache", "*.pyc"),
        symlinks=True,
    )
    env = underlay_env()
    colcon = str(VENV / "bin" / "colcon")
    # two workers: the machine has two cores (bac_msgs' rosidl build takes most of the time)
    build = run([colcon, "build", "--parallel-workers", "2"], ws, env, 900, ws / "colcon_build.log")
    if build.returncode != 0:
        pytest.fail(f"colcon build failed ({build.returncode}):\n{build.stdout[-6000:]}")
    test = run(
        [colcon, "test", "--parallel-workers", "2", "--pytest-args", *COLCON_PYTEST_ARGS],
        ws,
        env,
        900,
        ws / "colcon_test.log",
    )
    return Workspace(ws, build, test)


def collected_unit_tests(*filter_args: str) -> dict[str, int]:
    """What pytest collects in each src/<pkg>/test of the repository (the reference count)."""
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "--collect-only",
            "-q",
            *filter_args,
            *(f"src/{p}/test" for p in PY_PACKAGES),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    counts = dict.fromkeys(PY_PACKAGES, 0)
    for line in proc.stdout.splitlines():
        m = re.match(r"src/(\w+)/test/\S+::", line)
        if m:
            counts[m.group(1)] += 1
    return counts


def test_colcon_build_and_test_pass_and_every_unit_test_is_counted(workspace: Workspace) -> None:
    assert f"Summary: {len(PACKAGES)} packages finished" in workspace.build.stdout, workspace.build.stdout[-3000:]
    assert workspace.test.returncode == 0, workspace.test.stdout[-6000:]
    # the marker's plugin comes with the install space itself (here the venv's editable bac_common declares it too;
    # on a laptop with apt ROS only install/ does)
    entry_points = list(
        (workspace.install / "bac_common").glob("lib/python3*/site-packages/bac_common*/entry_points.txt")
    )
    assert len(entry_points) == 1, entry_points
    assert "bac_markers = bac_common.pytest_markers" in entry_points[0].read_text()
    proc = subprocess.run(
        [str(VENV / "bin" / "colcon"), "test-result", "--all"],
        cwd=workspace.root,
        env=underlay_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-6000:]  # non-zero on a failed or erroneous test
    per_package = {
        m.group(1): int(m.group(2))
        for m in re.finditer(r"build/(\w+)/pytest\.xml: (\d+) tests, 0 errors, 0 failures", proc.stdout)
    }
    expected = collected_unit_tests(*SLOW_FILTER)
    assert all(n > 0 for n in expected.values()), expected  # every package has quick unit tests
    every = collected_unit_tests()
    assert sum(every.values()) > sum(expected.values()), every  # the filter deselects some: there are slow ones
    assert per_package == expected, proc.stdout
    total = re.search(r"Summary: (\d+) tests, (\d+) errors, (\d+) failures, (\d+) skipped", proc.stdout)
    assert total is not None, proc.stdout
    assert int(total.group(1)) == sum(expected.values()) and total.group(2) == total.group(3) == "0"


def test_the_install_space_holds_the_code_the_data_and_bac_on_path(workspace: Workspace, tmp_path: Path) -> None:
    install = str(workspace.install)
    assert shutil.which("bac", path=workspace.env["PATH"]) == f"{install}/bac_bringup/bin/bac"
    proc = subprocess.run(
        ["bac", "--help"], cwd=tmp_path, env=workspace.env, capture_output=True, text=True, timeout=60, check=False
    )
    assert proc.returncode == 0 and "launch" in proc.stdout, proc.stdout + proc.stderr
    # the packages' code, and their data found through the ament index, all from install/ (not the repository,
    # whose editable installs are still in the underlay)
    code = (
        "import importlib, json\n"
        "from bac_bringup.profile import load_profile, workspace_dir\n"
        "from bac_common.paths import calibration_file, package_share\n"
        "from bac_ecu_bridge.dbc import shipped_dbc\n"
        f"mods = {{p: importlib.import_module(p).__file__ for p in {PY_PACKAGES!r}}}\n"
        "import bac_msgs.msg\n"
        "mods['bac_msgs'] = bac_msgs.msg.__file__\n"
        "sim = load_profile('sim')\n"
        "names = ('controller_i', 'controller_ii', 'controller_ii_reduced')\n"
        "print(json.dumps({'modules': mods, 'workspace': str(workspace_dir()),\n"
        "  'profile': str(sim.path), 'params': [str(p) for p in sim.params_files],\n"
        "  'calibrations': [str(calibration_file(n)) for n in names],\n"
        "  'dbc': str(shipped_dbc('controller_i')), 'share': str(package_share('bac_bringup'))}))\n"
    )
    found = json.loads(workspace.python(code, tmp_path).strip().splitlines()[-1])
    for pkg, path in found["modules"].items():
        assert path.startswith(f"{install}/{pkg}/"), (pkg, path)
    assert found["workspace"] == found["share"] == f"{install}/bac_bringup/share/bac_bringup"
    assert found["profile"] == f"{install}/bac_bringup/share/bac_bringup/profiles/sim.yaml"
    assert [Path(p).name for p in found["params"]] == ["common.yaml", "sim.yaml"]
    for path in found["params"]:
        assert path.startswith(f"{install}/bac_bringup/share/bac_bringup/params/"), path
    for path in found["calibrations"]:
        assert path.startswith(f"{install}/bac_common/share/bac_common/calibrations/"), path
    assert found["dbc"] == f"{install}/bac_ecu_bridge/share/bac_ecu_bridge/dbc/controller_i.dbc"
    # the executables: every node, and bac, in lib/<pkg>/ (ros2 run's place); nothing else
    exes = {p.name for p in workspace.install.glob("*/lib/*/*") if p.is_file() and os.access(p, os.X_OK)}
    assert exes == set(NODES) | TOOLS
    assert not node_classes_without_console_script()


def node_classes_without_console_script() -> list[str]:
    """Modules defining a BacNode subclass that no setup.py names as a console script's module."""
    scripts: set[str] = set()
    for setup in (ROOT / "src").glob("*/setup.py"):
        for entry in re.findall(r'"\s*\w+\s*=\s*([\w.]+):\w+"', setup.read_text()):
            scripts.add(entry)
    missing = []
    for path in (ROOT / "src").glob("bac_*/bac_*/*.py"):
        tree = ast.parse(path.read_text())
        for cls in (n for n in tree.body if isinstance(n, ast.ClassDef)):
            if any(isinstance(b, ast.Name) and b.id == "BacNode" for b in cls.bases):
                module = f"{path.parent.name}.{path.stem}"
                if module not in scripts:
                    missing.append(f"{module}:{cls.name}")
    return missing


@pytest.mark.parametrize("node", sorted(NODES))
def test_every_node_starts_from_the_install_space_and_stops_on_sigint(
    workspace: Workspace, node: str, ros_domain: int, ros_context: Any, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    share = workspace.install / "bac_bringup" / "share" / "bac_bringup" / "params"
    profile = "replay" if node == "bag_player" else "sim"
    args = ["--ros-args", "--params-file", str(share / "common.yaml"), "--params-file", str(share / f"{profile}.yaml")]
    if node in ("bo_agent", "campaign_recorder", "run_segmenter"):
        args += ["-p", f"campaign_dir:={tmp_path / 'campaign'}"]
    if node == "bag_player":  # plays the bags of the campaign run from the install space
        args += ["-p", f"bags:=['{request.getfixturevalue('campaign')}']"]
    env = {**workspace.env, "ROS_DOMAIN_ID": str(ros_domain)}
    log = tmp_path / f"{node}.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [str(workspace.exe(node)), *args],
            cwd=tmp_path,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        probe = ros_context.node("install_space_probe")
        wait_for(
            lambda: node in probe.get_node_names() or proc.poll() is not None,
            90,
            what=f"{node} in the ROS graph",
        )
        assert proc.poll() is None, f"{node} exited with {proc.returncode}:\n{log.read_text()[-3000:]}"
        os.killpg(proc.pid, signal.SIGINT)
        rc = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert rc == 0, f"{node} ended with {rc} on SIGINT:\n{log.read_text()[-3000:]}"


@pytest.fixture(scope="module")
def campaign(workspace: Workspace, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``bac launch sim`` from the install space, in a folder outside the repository, to the campaign's end."""
    here = tmp_path_factory.mktemp("outside")
    assert ROOT not in here.parents
    env = {**workspace.env, "ROS_DOMAIN_ID": str(fresh_domain())}
    cmd = [
        "bac", "launch", "sim", "--log-dir", "logs", "--timeout", "400",
        "-p", f"bo_agent.budget:={BUDGET}", "-p", "bo_agent.confirmation_run:=false",
    ]  # fmt: skip
    out = run(cmd, here, env, 600, here / "launch.log")
    camps = sorted((here / "campaigns").glob("sim-*")) if (here / "campaigns").is_dir() else []
    if out.returncode != 0 or len(camps) != 1:
        logs = "\n".join(f"--- {f.name}\n{f.read_text()[-3000:]}" for f in sorted((here / "logs").glob("*.log")))
        pytest.fail(f"bac launch sim failed ({out.returncode}):\n{out.stdout[-3000:]}\n{logs}")
    assert "private network namespace" not in out.stdout  # CAN stays in one process: nothing to hide
    return camps[0]


def test_bac_launch_sim_from_the_install_space_runs_the_campaign_to_the_end(
    workspace: Workspace, campaign: Path
) -> None:
    events = [json.loads(line) for line in (campaign / "journal.jsonl").read_text().splitlines()]
    scored = [e for e in events if e["event"] == "trial_scored"]
    assert [e["trial_id"] for e in scored] == list(range(1, BUDGET + 1))
    assert events[-1]["event"] == "campaign_done"
    rec = json.loads((campaign / "recommendation.json").read_text())
    assert rec["params"] and set(rec["params"]) == {"damping_front", "damping_rear"}
    # the configuration it ran with came from the install space's share/
    launch = json.loads((campaign / "config" / "launch.json").read_text())
    assert launch["params_files"][:2] == ["00_common.yaml", "01_sim.yaml"]
    shipped = workspace.install / "bac_bringup" / "share" / "bac_bringup"
    assert (campaign / "config" / "01_sim.yaml").read_text() == (shipped / "params" / "sim.yaml").read_text()
    assert sorted(p.name for p in (campaign / "bags").iterdir()) == [f"trial_{i:04d}" for i in range(1, BUDGET + 1)]
