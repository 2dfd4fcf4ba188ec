"""Graph profiles: which nodes run, with which parameters (``share/bac_bringup/profiles/*.yaml``; ros_ws/profiles).

A profile is the bac equivalent of a launch file::

    description: simulated vehicle, whole calibration graph
    use_sim_time: true
    params_files: [../params/sim.yaml]        # relative to this file, keyed by node name
    can: {interface: udp_multicast, channel: 239.74.163.2, bitrate: 500000}
    nodes:
      - {name: vehicle_sim, entry: bac_sim.vehicle_sim_node:VehicleSimNode, can: true}
      - {name: bo_agent, entry: bac_agent.agent_node:BoAgentNode, ends_graph: true}

``entry`` is ``module:Class``: the process mode runs ``python -m module`` (the
module's ``main()``), the single-process mode instantiates ``Class``.
``linger_s`` (default 1 s): after the ``ends_graph`` node finished, the
other nodes keep running this long, so that its last messages reach them
(the recorder). ``campaign: true`` makes the launcher give every node a ``campaign_dir``
parameter (one new folder per launch unless ``--campaign-dir`` names one).
``can: true`` gives the node the profile's CAN settings as ``can.*``
parameters. ``ends_graph: true`` marks the node whose normal exit (code 0)
ends the whole graph; any other node exiting is a failure. ``stop_order`` (default 0): at shutdown
the nodes stop in waves of increasing ``stop_order`` (the simulated vehicle, whose ECU the bridge
still talks to while it stops, goes last).

``process: NAME`` puts nodes in one process (``bac_bringup.container``, as a component container would):
the nodes with the same process name share a process and its executor, the others keep one process each
(a node's process name is its own name unless it has ``process:``). CAN
stays in one process when the ``can: true`` nodes (two or more) share one: the launcher then uses python-can's
in-process ``virtual`` bus whatever the profile's ``can.interface`` says for the cross-process case
(``udp_multicast``), and the graph needs no private network namespace, so ROS tools on this machine see
it. A ``virtual`` bus between processes is refused (it cannot carry a frame from one process to another).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from bac_common.errors import BacError

CAN_INTERFACES_CROSS_PROCESS = ("udp_multicast",)  # needs a private network namespace between processes
CAN_INTERFACES_IN_PROCESS = ("virtual",)  # reaches only the buses opened in the same process


class ProfileError(BacError, ValueError):
    """A graph profile is missing or malformed."""


@dataclass(frozen=True)
class NodeSpec:
    name: str
    entry: str  # module:Class
    can: bool = False
    ends_graph: bool = False
    params: Mapping[str, Any] = field(default_factory=dict)  # per-node overrides
    stop_order: int = 0  # nodes stop in waves of increasing stop_order
    process: str = ""  # nodes with the same process name share one process; "" = a process of its own

    @property
    def process_name(self) -> str:
        """The name of the process this node runs in (its own name when it has a process of its own)."""
        return self.process or self.name

    @property
    def module(self) -> str:
        return self.entry.split(":", 1)[0]

    @property
    def class_name(self) -> str:
        return self.entry.split(":", 1)[1]


@dataclass(frozen=True)
class ProcessSpec:
    """One process of a graph: a node of its own, or several nodes sharing it (``process:`` in the profile)."""

    name: str
    nodes: tuple[NodeSpec, ...]

    @property
    def ends_graph(self) -> bool:
        return any(n.ends_graph for n in self.nodes)

    @property
    def stop_order(self) -> int:
        """A shared process stops with its last node's wave (inside, the nodes stop in their own order)."""
        return max(n.stop_order for n in self.nodes)

    @property
    def can(self) -> bool:
        return any(n.can for n in self.nodes)


@dataclass(frozen=True)
class CanSpec:
    interface: str = "virtual"
    channel: str = "bac"
    bitrate: int = 500000
    extra: Mapping[str, Any] = field(default_factory=dict)  # any further can.* parameters

    def as_params(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "can.interface": self.interface,
            "can.channel": self.channel,
            "can.bitrate": int(self.bitrate),
        }
        out.update({f"can.{k}": v for k, v in self.extra.items()})
        return out


@dataclass(frozen=True)
class Profile:
    name: str
    path: Path | None
    nodes: tuple[NodeSpec, ...]
    params_files: tuple[Path, ...] = ()
    use_sim_time: bool = False
    can: CanSpec | None = None
    description: str = ""
    global_params: Mapping[str, Any] = field(default_factory=dict)  # given to every node
    campaign: bool = False  # nodes take a campaign_dir (the launcher makes one per run)
    linger_s: float = 1.0  # after the ends_graph node finished, the others run this long (its last messages land)

    @property
    def needs_can(self) -> bool:
        return self.can is not None and any(n.can for n in self.nodes)

    def processes(self) -> tuple[ProcessSpec, ...]:
        """The processes of the process mode, in the order of their first node."""
        groups: dict[str, list[NodeSpec]] = {}
        for n in self.nodes:
            groups.setdefault(n.process_name, []).append(n)
        return tuple(ProcessSpec(name, tuple(nodes)) for name, nodes in groups.items())

    @property
    def can_processes(self) -> tuple[str, ...]:
        """The processes that open the CAN bus (process mode)."""
        return tuple(p.name for p in self.processes() if p.can) if self.needs_can else ()

    @property
    def can_in_one_process(self) -> bool:
        """True when CAN connects nodes of one process only (process mode): several CAN nodes, one process.

        A lone CAN node talks to something outside the graph (a real ECU, ``python -m bac_sim.ecu``), so its
        bus is the profile's."""
        return sum(n.can for n in self.nodes) >= 2 and len(self.can_processes) == 1

    def one_process_per_node(self) -> Profile:
        """A copy without the ``process:`` groups: every node in a process of its own."""
        return replace(self, nodes=tuple(replace(n, process="") for n in self.nodes))

    def node(self, name: str) -> NodeSpec:
        for n in self.nodes:
            if n.name == name:
                return n
        raise ProfileError(f"profile '{self.name}' has no node '{name}' (nodes: {[n.name for n in self.nodes]})")

    def params_for(self, spec: NodeSpec) -> dict[str, Any]:
        """The -p overrides of one node: use_sim_time, CAN, global, then the node's own."""
        out: dict[str, Any] = {"use_sim_time": self.use_sim_time}
        out.update(self.global_params)
        if spec.can and self.can is not None:
            out.update(self.can.as_params())
        out.update(spec.params)
        return out

    def with_overrides(
        self,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        global_params: Mapping[str, Any] | None = None,
        extra_params_files: Sequence[str | Path] = (),
        can: CanSpec | None = None,
        only: Sequence[str] | None = None,
        exclude: Sequence[str] = (),
        use_sim_time: bool | None = None,
    ) -> Profile:
        """A copy with parameter overrides (``{node: {key: value}}``) and node selection."""
        nodes = []
        for n in self.nodes:
            if only is not None and n.name not in only:
                continue
            if n.name in exclude:
                continue
            extra = dict((params or {}).get(n.name, {}))
            nodes.append(replace(n, params={**n.params, **extra}) if extra else n)
        unknown = set(params or {}) - {n.name for n in self.nodes}
        if unknown:
            raise ProfileError(f"overrides for unknown nodes {sorted(unknown)} in profile '{self.name}'")
        return replace(
            self,
            nodes=tuple(nodes),
            params_files=self.params_files + tuple(Path(p).resolve() for p in extra_params_files),
            global_params={**self.global_params, **(global_params or {})},
            can=can if can is not None else self.can,
            use_sim_time=self.use_sim_time if use_sim_time is None else use_sim_time,
        )


def workspace_dir() -> Path:
    """The folder holding ``profiles/`` and ``params/``: $BAC_WS when it has them, else bac_bringup's share
    (found through the ament index: an install space or the development install), else this package's source."""
    from bac_common.paths import package_share

    env = os.environ.get("BAC_WS", "").strip()
    candidates = [Path(env).expanduser()] if env else []
    share = package_share("bac_bringup")
    if share is not None:
        candidates.append(share)
    candidates.append(Path(__file__).resolve().parents[1])
    for c in candidates:
        if (c / "profiles").is_dir():
            return c.resolve()
    raise ProfileError(
        "cannot find the graph profiles: bac_bringup's share/ has no profiles/ (is the install space sourced?); "
        "set BAC_WS to a folder with profiles/ and params/"
    )


def resolve_profile_path(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") and p.exists():
        return p.resolve()
    candidate = workspace_dir() / "profiles" / f"{name_or_path}.yaml"
    if candidate.exists():
        return candidate
    known = sorted(x.stem for x in (workspace_dir() / "profiles").glob("*.yaml"))
    raise ProfileError(f"unknown profile '{name_or_path}' (known: {', '.join(known)}; or give a .yaml path)")


def load_profile(name_or_path: str | Path) -> Profile:
    import yaml

    path = resolve_profile_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ProfileError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("nodes"), list) or not data["nodes"]:
        raise ProfileError(f"{path}: a profile needs a non-empty 'nodes' list")
    nodes = []
    for i, n in enumerate(data["nodes"]):
        if not isinstance(n, dict) or "name" not in n or "entry" not in n or ":" not in str(n["entry"]):
            raise ProfileError(f"{path}: node #{i + 1} needs 'name' and 'entry: module:Class'")
        nodes.append(
            NodeSpec(
                name=str(n["name"]),
                entry=str(n["entry"]),
                can=bool(n.get("can", False)),
                ends_graph=bool(n.get("ends_graph", False)),
                stop_order=int(n.get("stop_order", 0)),
                params=dict(n.get("params") or {}),
                process=str(n.get("process") or ""),
            )
        )
    names = [n.name for n in nodes]
    if len(set(names)) != len(names):
        raise ProfileError(f"{path}: node names must be unique")
    for n in nodes:
        other = nodes[names.index(n.process)] if n.process in names else None
        if other is not None and other.process_name != n.process:
            raise ProfileError(
                f"{path}: node '{n.name}' asks for process '{n.process}', but node '{n.process}' runs in process "
                f"'{other.process_name}'; name the shared process differently"
            )
    files = []
    for f in data.get("params_files") or []:
        fp = (path.parent / str(f)).resolve()
        if not fp.exists():
            raise ProfileError(f"{path}: parameter file {fp} does not exist")
        files.append(fp)
    can = None
    if data.get("can"):
        c = dict(data["can"])
        can = CanSpec(
            interface=str(c.pop("interface", "virtual")),
            channel=str(c.pop("channel", "bac")),
            bitrate=int(c.pop("bitrate", 500000)),
            extra=c,
        )
    return Profile(
        name=path.stem,
        path=path,
        nodes=tuple(nodes),
        params_files=tuple(files),
        use_sim_time=bool(data.get("use_sim_time", False)),
        can=can,
        description=str(data.get("description", "")),
        global_params=dict(data.get("global_params") or {}),
        campaign=bool(data.get("campaign", False)),
        linger_s=float(data.get("linger_s", 1.0)),
    )
