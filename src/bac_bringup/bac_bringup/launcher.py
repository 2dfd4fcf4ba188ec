"""The graph launcher (there is no ``ros2 launch`` here).

Two modes, the same profile:

* **processes** (default): each node in its own process, as ``ros2 run``
  would start it (``python -m module --ros-args -r __node:=name
  --params-file ... -p k:=v``). CAN between processes goes over python-can's
  ``udp_multicast``, which is only allowed inside a private network
  namespace: the launcher re-runs itself in one when needed.
* **single process**: every node in this process on one multi-threaded
  executor, as a component container would; CAN over python-can's in-process
  ``virtual`` bus.

Either way every node gets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; SIGINT
and SIGTERM are forwarded and the graph shuts down cleanly; the launcher exits
with the code of the ``ends_graph`` node when it finishes, and non-zero when
any node dies.
"""

from __future__ import annotations

import ctypes
import functools
import importlib
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from bac_bringup import netns
from bac_bringup.profile import (
    CAN_INTERFACES_CROSS_PROCESS,
    CanSpec,
    NodeSpec,
    Profile,
)
from bac_common.contracts import ROS_ENV_DEFAULTS

LOG = logging.getLogger("bac.launch")
STOP_GRACE_S = 8.0  # SIGINT, then this long before SIGTERM, then as long before SIGKILL
PR_SET_PDEATHSIG = 1


def ros_environment(base: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of every ROS process bac starts (network rule, ament prefix)."""
    env = dict(os.environ if base is None else base)
    for k, v in ROS_ENV_DEFAULTS.items():
        env.setdefault(k, v)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # never widened by the launcher
    env.setdefault("AMENT_PREFIX_PATH", sys.prefix)
    env.setdefault("PYTHONUNBUFFERED", "1")
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    return env


def nest_params(flat: dict[str, Any]) -> dict[str, Any]:
    """``{"can.interface": x}`` -> ``{"can": {"interface": x}}`` (the parameter-file form)."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        d = out
        parts = key.split(".")
        for part in parts[:-1]:
            d = d.setdefault(part, {})
        d[parts[-1]] = value
    return out


@functools.lru_cache(maxsize=1)
def _override_dir() -> Path:
    import atexit
    import shutil

    path = Path(tempfile.mkdtemp(prefix="bac-launch-"))
    atexit.register(shutil.rmtree, path, True)
    return path


def overrides_file(spec: NodeSpec, params: dict[str, Any]) -> Path:
    """A parameter file with one node's overrides, keyed by its name.

    ``-p name:=value`` on the command line applies to every node (``/**``), and
    rcl lets a node-specific entry of a parameter file win over it; a file
    keyed by the node's name, given last, wins over the profile's files.
    """
    import yaml

    path = _override_dir() / f"{spec.name}.overrides.yaml"
    path.write_text(yaml.safe_dump({spec.name: {"ros__parameters": nest_params(params)}}))
    return path


def ros_args_for(profile: Profile, spec: NodeSpec) -> list[str]:
    args = ["--ros-args", "-r", f"__node:={spec.name}"]
    for f in profile.params_files:
        args += ["--params-file", str(f)]
    params = profile.params_for(spec)
    if params:
        args += ["--params-file", str(overrides_file(spec, params))]
    return args


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class NodeProcess:
    spec: NodeSpec
    proc: subprocess.Popen[bytes]

    @property
    def name(self) -> str:
        return self.spec.name


class ProcessGraph:
    """Each node of a profile in its own process (``ros2 run`` style)."""

    def __init__(self, profile: Profile, env: dict[str, str] | None = None, log_dir: Path | None = None) -> None:
        self.profile = profile
        self.env = ros_environment(env)
        self.log_dir = log_dir
        self.children: list[NodeProcess] = []
        self._stop_requested = False

    def command_for(self, spec: NodeSpec) -> list[str]:
        return [sys.executable, "-m", spec.module, *ros_args_for(self.profile, spec)]

    def start(self) -> None:
        for spec in self.profile.nodes:
            cmd = self.command_for(spec)
            out: Any = None
            if self.log_dir is not None:
                self.log_dir.mkdir(parents=True, exist_ok=True)
                out = (self.log_dir / f"{spec.name}.log").open("ab")
            LOG.info("starting %s: %s", spec.name, " ".join(cmd))
            proc = subprocess.Popen(
                cmd,
                env=self.env,
                stdout=out,
                stderr=subprocess.STDOUT if out is not None else None,
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )
            self.children.append(NodeProcess(spec, proc))

    def request_stop(self) -> None:
        self._stop_requested = True

    def poll(self) -> int | None:
        """None while the graph runs; else the exit code the graph should end with."""
        for child in self.children:
            rc = child.proc.poll()
            if rc is None:
                continue
            if child.spec.ends_graph and rc == 0:
                LOG.info("%s finished: shutting down the graph", child.name)
                self._linger()
                return 0
            LOG.error("node %s exited with code %s: shutting down the graph", child.name, rc)
            return rc if rc > 0 else 1
        return None

    def _linger(self) -> None:
        """Let the other nodes take the finished node's last messages (a grace period, not a synchronisation)."""
        deadline = time.monotonic() + self.profile.linger_s
        while time.monotonic() < deadline and not self._stop_requested:
            time.sleep(0.02)

    def wait(self, timeout_s: float | None = None) -> int:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        code: int | None = None
        while code is None and not self._stop_requested:
            code = self.poll()
            if code is None:
                if deadline is not None and time.monotonic() > deadline:
                    LOG.error("graph still running after %.0f s: stopping it", timeout_s)
                    code = 124
                    break
                time.sleep(0.05)
        stop_rc = self.stop()
        return code if code is not None else stop_rc

    def stop(self) -> int:
        """Stop the nodes in waves of ``stop_order`` (SIGINT, then SIGTERM, then SIGKILL per wave).

        Returns 0 if every node ended cleanly on SIGINT. Waves let a node that still needs another at its
        shutdown (the ECU bridge restoring the baseline calibration on the simulated vehicle's ECU) go first.
        """
        unclean = 0
        for order in sorted({c.spec.stop_order for c in self.children}):
            wave = [c for c in self.children if c.spec.stop_order == order]
            unclean += self._stop_wave(wave)
        return 1 if unclean else 0

    def _stop_wave(self, wave: list[NodeProcess]) -> int:
        live = [c for c in wave if c.proc.poll() is None]
        unclean = 0
        first = max([STOP_GRACE_S, *(c.spec.stop_grace_s for c in live)])  # a node may need longer (stop_grace_s)
        for sig, grace in ((signal.SIGINT, first), (signal.SIGTERM, STOP_GRACE_S), (signal.SIGKILL, 5.0)):
            if not live:
                break
            for c in live:
                try:
                    os.killpg(c.proc.pid, sig)
                except ProcessLookupError:
                    pass
            if sig != signal.SIGINT:
                unclean += len(live)
                LOG.warning("sent %s to %s", sig.name, ", ".join(c.name for c in live))
            deadline = time.monotonic() + grace
            while live and time.monotonic() < deadline:
                live = [c for c in live if c.proc.poll() is None]
                time.sleep(0.02)
        return unclean


class SingleProcessGraph:
    """Every node of a profile in this process on one multi-threaded executor."""

    def __init__(self, profile: Profile) -> None:
        self.profile = profile

    def run(self, timeout_s: float | None = None) -> int:
        import rclpy
        from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
        from rclpy.utilities import ok, try_shutdown

        for k, v in ros_environment().items():
            os.environ.setdefault(k, v)
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        rclpy.init(args=["bac_launch"])
        from bac_common.rosnode import drain_executor

        nodes: list[Any] = []
        executor: MultiThreadedExecutor | None = None
        code = 0
        try:
            for spec in self.profile.nodes:
                cls = getattr(importlib.import_module(spec.module), spec.class_name)
                # node-local arguments: the same remapping and parameters as in its own process
                nodes.append((spec, cls(cli_args=ros_args_for(self.profile, spec))))
            executor = MultiThreadedExecutor(num_threads=max(4, len(nodes) + 2))
            for _, n in nodes:
                executor.add_node(n)
            deadline = None if timeout_s is None else time.monotonic() + timeout_s
            while ok():
                executor.spin_once(timeout_sec=0.05)
                done = [(s, n) for s, n in nodes if getattr(n, "exit_code", None) is not None]
                if done:
                    spec, node = done[0]
                    if spec.ends_graph and node.exit_code == 0:
                        LOG.info("%s finished: shutting down the graph", spec.name)
                        linger_end = time.monotonic() + self.profile.linger_s
                        while ok() and time.monotonic() < linger_end:
                            executor.spin_once(timeout_sec=0.02)
                        code = 0
                    else:
                        LOG.error("node %s ended with code %s", spec.name, node.exit_code)
                        code = int(node.exit_code) or 1
                    break
                if deadline is not None and time.monotonic() > deadline:
                    LOG.error("graph still running after %.0f s: stopping it", timeout_s)
                    code = 124
                    break
        except (KeyboardInterrupt, ExternalShutdownException):
            code = 0
        except Exception:
            if ok():
                LOG.exception("a node crashed: shutting down the graph")
                code = 1
            else:  # SIGINT/SIGTERM shut the context down while the executor built its wait set (an RCLError)
                code = 0
        finally:
            if executor is not None and not drain_executor(executor, STOP_GRACE_S / 2):
                LOG.warning("a callback was still running at shutdown")
            for _, n in sorted(reversed(nodes), key=lambda sn: sn[0].stop_order):
                try:
                    n.destroy_node()
                except Exception:
                    LOG.exception("destroying a node failed")
            try_shutdown()
        return code


def prepare(profile: Profile, single_process: bool) -> Profile:
    """Adapt the CAN settings to the mode: the virtual bus in one process."""
    if (
        single_process
        and profile.needs_can
        and profile.can is not None
        and profile.can.interface in CAN_INTERFACES_CROSS_PROCESS
    ):
        return replace(profile, can=CanSpec("virtual", f"bac-{os.getpid()}", profile.can.bitrate, {}))
    return profile


def needs_private_netns(profile: Profile, single_process: bool) -> bool:
    return (
        not single_process
        and profile.needs_can
        and profile.can is not None
        and profile.can.interface in CAN_INTERFACES_CROSS_PROCESS
        and not netns.in_private_netns()
    )


LAUNCH_RECORD = "launch.json"


def save_launch_config(profile: Profile, campaign_dir: Path, argv: Sequence[str], single_process: bool) -> Path:
    """Keep the configuration a campaign ran with: ``<campaign_dir>/config/`` (``config.resumeN/`` later).

    The profile, each parameter file in order and the launch's overrides (node-keyed, last), with
    ``launch.json`` listing the files in the order the nodes read them, so that offline tools
    (rescoring, reports) rebuild exactly the nodes' configuration.
    """
    import json
    import shutil

    import yaml

    out = campaign_dir / "config"
    n = 1
    while out.exists():
        out = campaign_dir / f"config.resume{n}"
        n += 1
    out.mkdir(parents=True)
    files: list[str] = []
    for i, f in enumerate(profile.params_files):
        name = f"{i:02d}_{f.name}"
        shutil.copyfile(f, out / name)
        files.append(name)
    overrides = {spec.name: {"ros__parameters": nest_params(profile.params_for(spec))} for spec in profile.nodes}
    name = f"{len(files):02d}_overrides.yaml"
    (out / name).write_text(yaml.safe_dump(overrides, sort_keys=False))
    files.append(name)
    if profile.path is not None:
        shutil.copyfile(profile.path, out / "profile.yaml")
    record = {
        "profile": profile.name,
        "argv": list(argv),
        "single_process": single_process,
        "params_files": files,
        "nodes": [spec.name for spec in profile.nodes],
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    (out / LAUNCH_RECORD).write_text(json.dumps(record, indent=2))
    return out


def campaign_params_files(campaign_dir: str | Path) -> list[Path]:
    """The parameter files a campaign was launched with (its first launch), in reading order."""
    import json

    rec = Path(campaign_dir) / "config" / LAUNCH_RECORD
    data = json.loads(rec.read_text())
    return [rec.parent / name for name in data["params_files"]]


def run_graph(
    profile: Profile,
    single_process: bool = False,
    log_dir: Path | None = None,
    timeout_s: float | None = None,
) -> int:
    """Run a profile until its ends_graph node finishes, a node dies or a signal arrives."""
    profile = prepare(profile, single_process)
    if single_process:
        return SingleProcessGraph(profile).run(timeout_s=timeout_s)
    graph = ProcessGraph(profile, log_dir=log_dir)

    def on_signal(signum: int, _frame: Any) -> None:
        LOG.info("received %s: stopping the graph", signal.Signals(signum).name)
        graph.request_stop()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        graph.start()
        return graph.wait(timeout_s=timeout_s)
    finally:
        graph.stop()
        for s, h in old.items():
            signal.signal(s, h)


def relaunch_in_netns(argv: Sequence[str]) -> int:
    """Run ``python -m bac_bringup.cli <argv>`` again inside a private network namespace."""
    cmd = [sys.executable, "-m", "bac_bringup.cli", *argv]
    LOG.info("CAN over udp_multicast between processes: entering a private network namespace")
    proc = subprocess.Popen(netns.wrap_command(cmd), env=netns.private_env(ros_environment()))

    def forward(signum: int, _frame: Any) -> None:
        proc.send_signal(signum)

    old = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return proc.wait()
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def write_params_file(params: dict[str, dict[str, Any]], directory: Path | None = None) -> Path:
    """Write ``{node: {param: value}}`` as a ROS 2 parameter YAML file."""
    import yaml

    data = {node: {"ros__parameters": p} for node, p in params.items()}
    fd, name = tempfile.mkstemp(prefix="bac-params-", suffix=".yaml", dir=directory)
    with os.fdopen(fd, "w") as f:
        yaml.safe_dump(data, f)
    return Path(name)
