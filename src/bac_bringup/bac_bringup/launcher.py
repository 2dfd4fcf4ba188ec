"""The graph launcher (there is no ``ros2 launch`` here).

Two modes, the same profile:

* **processes** (default): each node in its own process, as ``ros2 run``
  would start it (``python -m module --ros-args -r __node:=name
  --params-file ...``), except the nodes a profile puts in one process
  (``process:``), which share one (``python -m bac_bringup.container``).
  CAN that stays in one process uses python-can's in-process ``virtual`` bus;
  CAN between processes goes over python-can's ``udp_multicast``, which is
  only allowed inside a private network namespace: the launcher re-runs
  itself in one when needed (the graph is then invisible to ROS tools
  outside it).
* **single process**: every node in this process on one multi-threaded
  executor, as a component container would; CAN over the ``virtual`` bus.

Either way every node gets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; SIGINT
and SIGTERM are forwarded and the graph shuts down cleanly; the launcher exits
with the code of the ``ends_graph`` node when it finishes, and non-zero when
any node dies.
"""

from __future__ import annotations

import ctypes
import functools
import json
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
from bac_bringup.container import ContainedNode, run_nodes, write_spec
from bac_bringup.profile import (
    CAN_INTERFACES_CROSS_PROCESS,
    CAN_INTERFACES_IN_PROCESS,
    CanSpec,
    NodeSpec,
    ProcessSpec,
    Profile,
    ProfileError,
)
from bac_common.contracts import ROS_ENV_DEFAULTS, USER_PARAMS

LOG = logging.getLogger("bac.launch")
STOP_GRACE_S = 8.0  # SIGINT, then this long before SIGTERM, then as long before SIGKILL
# SIGINT is sent again this often during its grace: a node process can lose one (Python swallows the
# KeyboardInterrupt of a SIGINT that lands in a finalizer, e.g. while the node still imports its modules;
# bac_common.rosnode.StopSignals), and a repeated SIGINT is harmless to a node that is already stopping
SIGINT_REPEAT_S = 1.0
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
    if spec.params:
        # the node's own overrides (-p, the profile's): the node checks at start that it has each and that the value
        # reached it (BacNode._check_user_params): rcl ignores a name a node does not declare, and keeps an earlier
        # file's value when a later one gives another type
        params[USER_PARAMS] = [f"{k}={json.dumps(v)}" for k, v in spec.params.items()]
    if params:
        args += ["--params-file", str(overrides_file(spec, params))]
    return args


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def contained(profile: Profile, spec: NodeSpec) -> ContainedNode:
    """A node as the container (or the single-process mode) creates it: with its own ROS arguments."""
    return ContainedNode(spec.name, spec.entry, tuple(ros_args_for(profile, spec)), spec.ends_graph, spec.stop_order)


@dataclass
class NodeProcess:
    """One process of the graph: a node of its own, or several nodes sharing it."""

    spec: ProcessSpec
    proc: subprocess.Popen[bytes]

    @property
    def name(self) -> str:
        return process_label(self.spec)


def process_label(process: ProcessSpec) -> str:
    """``imu_ingest``; ``vehicle (vehicle_sim, ecu_bridge)`` for a shared process."""
    if len(process.nodes) == 1 and process.nodes[0].name == process.name:
        return process.name
    return f"{process.name} ({', '.join(n.name for n in process.nodes)})"


def _link_node_logs(log_dir: Path, process: ProcessSpec) -> None:
    """``<node>.log`` of each node of a shared process: a link to ``<process>.log`` (one output stream)."""
    for n in process.nodes:
        link = log_dir / f"{n.name}.log"
        if link.name == f"{process.name}.log":
            continue
        if link.is_symlink():
            link.unlink()
        elif link.exists():  # a node log of an earlier launch in its own process (a resumed campaign): kept
            LOG.warning("%s exists: %s's output of this launch goes to %s.log", link, n.name, process.name)
            continue
        link.symlink_to(f"{process.name}.log")


class ProcessGraph:
    """Each node of a profile in its own process (``ros2 run`` style), or in the process it shares."""

    def __init__(self, profile: Profile, env: dict[str, str] | None = None, log_dir: Path | None = None) -> None:
        self.profile = profile
        self.env = ros_environment(env)
        self.log_dir = log_dir
        self.children: list[NodeProcess] = []
        self._stop_requested = False

    def command_for(self, process: ProcessSpec) -> list[str]:
        if len(process.nodes) == 1:
            spec = process.nodes[0]
            return [sys.executable, "-m", spec.module, *ros_args_for(self.profile, spec)]
        spec_file = write_spec(
            _override_dir() / f"{process.name}.process.json",
            process.name,
            [contained(self.profile, n) for n in process.nodes],
            self.profile.linger_s,
        )
        return [sys.executable, "-m", "bac_bringup.container", str(spec_file)]

    def start(self) -> None:
        for process in self.profile.processes():
            cmd = self.command_for(process)
            out: Any = None
            if self.log_dir is not None:
                self.log_dir.mkdir(parents=True, exist_ok=True)
                out = (self.log_dir / f"{process.name}.log").open("ab")
                if len(process.nodes) > 1:
                    _link_node_logs(self.log_dir, process)
            LOG.info("starting %s: %s", process_label(process), " ".join(cmd))
            proc = subprocess.Popen(
                cmd,
                env=self.env,
                stdout=out,
                stderr=subprocess.STDOUT if out is not None else None,
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )
            self.children.append(NodeProcess(process, proc))

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
        """Stop the nodes in waves of ``stop_order`` (SIGINT, repeated every :data:`SIGINT_REPEAT_S`, then SIGTERM,
        then SIGKILL per wave).

        Returns 0 if every node ended on SIGINT with code 0 (a node ended by its hard deadline, code 1 or
        SIGALRM, or failing in its clean-up is unclean: 1). Waves let a node that still needs another at its
        shutdown (the ECU bridge restoring the baseline calibration on the simulated vehicle's ECU) go first.
        """
        unclean = 0
        for order in sorted({c.spec.stop_order for c in self.children}):
            wave = [c for c in self.children if c.spec.stop_order == order]
            unclean += self._stop_wave(wave)
        return 1 if unclean else 0

    def _stop_wave(self, wave: list[NodeProcess]) -> int:
        live = stopping = [c for c in wave if c.proc.poll() is None]
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
            repeat_at = time.monotonic() + SIGINT_REPEAT_S
            while live and time.monotonic() < deadline:
                live = [c for c in live if c.proc.poll() is None]
                if sig == signal.SIGINT and live and time.monotonic() >= repeat_at:
                    repeat_at += SIGINT_REPEAT_S
                    for c in live:
                        try:
                            os.killpg(c.proc.pid, sig)
                        except ProcessLookupError:
                            pass
                time.sleep(0.02)
        for c in stopping:  # a node that ended by its hard deadline (1, or SIGALRM) stopped in time but not cleanly
            rc = c.proc.poll()
            if rc is not None and rc not in (0, -signal.SIGKILL, -signal.SIGTERM):
                # unclean: its clean-up was cut short (the bridge in the middle of its baseline restore) or failed
                LOG.warning("%s ended with code %s while stopping: see its log", c.name, rc)
                unclean += 1
        return unclean


class SingleProcessGraph:
    """Every node of a profile in this process on one multi-threaded executor."""

    def __init__(self, profile: Profile) -> None:
        self.profile = profile

    def run(self, timeout_s: float | None = None) -> int:
        for k, v in ros_environment().items():
            os.environ.setdefault(k, v)
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        nodes = [contained(self.profile, spec) for spec in self.profile.nodes]
        return run_nodes(nodes, linger_s=self.profile.linger_s, timeout_s=timeout_s)


def prepare(profile: Profile, single_process: bool) -> Profile:
    """Adapt the CAN settings to the processes: the virtual bus when CAN stays in one process.

    Raises :class:`ProfileError` for a ``virtual`` bus between processes (it would never carry a frame).
    """
    if not profile.needs_can or profile.can is None:
        return profile
    can_processes = profile.can_processes
    one_process = single_process or profile.can_in_one_process
    if one_process and profile.can.interface in CAN_INTERFACES_CROSS_PROCESS:
        return replace(profile, can=CanSpec("virtual", f"bac-{os.getpid()}", profile.can.bitrate, {}))
    if len(can_processes) > 1 and not single_process and profile.can.interface in CAN_INTERFACES_IN_PROCESS:
        raise ProfileError(
            f"profile '{profile.name}': CAN interface '{profile.can.interface}' reaches only the same process, but "
            f"its CAN nodes run in {len(can_processes)} processes ({', '.join(can_processes)}): give them one "
            "process (process: NAME), use --single-process, or a bus between processes (udp_multicast, socketcan)"
        )
    return profile


def needs_private_netns(profile: Profile, single_process: bool) -> bool:
    """True when CAN goes over udp_multicast (between processes, or to a peer outside the graph) and this process
    is not in a private namespace yet."""
    return (
        not single_process
        and profile.needs_can
        and profile.can is not None
        and profile.can.interface in CAN_INTERFACES_CROSS_PROCESS
        and not profile.can_in_one_process
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


def bags_opened(campaign_dir: Path) -> int:
    """Lines in the campaign's launch index (``launches.jsonl``, one per bag the recorder opened); 0 without it."""
    try:
        with open(campaign_dir / "launches.jsonl", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def drop_unused_config(saved: Path, campaign_dir: Path, begun_before: int | None) -> bool:
    """Remove the configuration saved for a launch whose agent neither started nor resumed the campaign (it
    refused: a resume with another configuration, a parameter out of range; or the launch was stopped first):
    nothing was driven with it, and a ``config/`` left by a refused first launch would be taken by ``bac rescore``
    and ``bac report`` for the configuration of the launch that did start the campaign. True when removed."""
    from bac_campaign.launches import campaign_launches_begun

    after = campaign_launches_begun(campaign_dir)
    if begun_before is None or after is None or after != begun_before or not saved.is_dir():
        return False
    import shutil

    shutil.rmtree(saved, ignore_errors=True)
    logging.getLogger("bac.launch").info(
        "%s removed: this launch did not start or resume the campaign, nothing was driven with it", saved.name
    )
    return True


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
