"""Several nodes in one process on one multi-threaded executor, as a component container would.

The launcher starts ``python -m bac_bringup.container SPEC.json`` for each shared process of a profile
(``process:`` in the profile: the simulated vehicle with its ECU and the ECU bridge on python-can's
in-process ``virtual`` bus), and runs the same loop (:func:`run_nodes`) in its own process for
``bac launch --single-process``. ``SPEC.json`` is written by the launcher::

    {"process": "vehicle", "linger_s": 1.0,
     "nodes": [{"name": "vehicle_sim", "entry": "bac_sim.vehicle_sim_node:VehicleSimNode",
                "args": ["--ros-args", "-r", "__node:=vehicle_sim", "--params-file", "..."],
                "ends_graph": false, "stop_order": 1}, ...]}

Each node gets its own (node-local) ROS arguments, exactly those it would get in a process of its own.
The process ends when a node finishes: with code 0 when that node ``ends_graph`` (after ``linger_s`` of
spinning, so that the others take its last messages), else with the node's code (1 for a 0). On SIGINT
or SIGTERM it ends with 0 after a clean stop: the callbacks in flight finish, then the nodes are destroyed
in waves of increasing ``stop_order`` (the bridge restores the baseline on the simulated ECU before the
simulated vehicle goes) while the ROS context is still valid (the signals are handled here, not by rclpy,
which would shut the context down first and leave the nodes still running publishing into it), and only
then is the context shut down; a watchdog ends the process if that clean-up hangs, and a hard deadline
(:class:`bac_common.rosnode.StopSignals`) if anything hangs after a stop signal or in the interpreter's exit.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

LOG = logging.getLogger("bac.container")


@dataclass(frozen=True)
class ContainedNode:
    name: str
    entry: str  # module:Class
    args: tuple[str, ...]  # the node's own ROS arguments (--ros-args -r __node:=... --params-file ...)
    ends_graph: bool = False
    stop_order: int = 0

    def as_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "entry": self.entry,
            "args": list(self.args),
            "ends_graph": self.ends_graph,
            "stop_order": self.stop_order,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ContainedNode:
        return cls(
            name=str(data["name"]),
            entry=str(data["entry"]),
            args=tuple(str(a) for a in data.get("args", [])),
            ends_graph=bool(data.get("ends_graph", False)),
            stop_order=int(data.get("stop_order", 0)),
        )


def write_spec(path: Path, process: str, nodes: Sequence[ContainedNode], linger_s: float) -> Path:
    path.write_text(
        json.dumps({"process": process, "linger_s": linger_s, "nodes": [n.as_json() for n in nodes]}, indent=2)
    )
    return path


def read_spec(path: Path) -> tuple[str, list[ContainedNode], float]:
    data = json.loads(path.read_text())
    return str(data["process"]), [ContainedNode.from_json(n) for n in data["nodes"]], float(data.get("linger_s", 1.0))


def run_nodes(
    nodes: Sequence[ContainedNode],
    linger_s: float = 1.0,
    timeout_s: float | None = None,
    cleanup_timeout_s: float | None = None,
    restore_signals: bool = True,
) -> int:
    """Create the nodes in this process, spin them on one executor until one finishes or a signal arrives.

    ``cleanup_timeout_s``: when given (a process's main), the process is ended by a watchdog if stopping
    takes longer than this (plus the nodes' own :meth:`BacNode.cleanup_time_s`) once spinning has stopped.
    ``restore_signals``: give SIGINT and SIGTERM back to their previous handlers at the end (False for a
    process's main: the launcher repeats SIGINT until the process is gone, and it must stay a no-op).
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rclpy.utilities import ok, try_shutdown

    from bac_common.errors import BacError
    from bac_common.rosnode import (
        STOP_NOTICE_S,
        USER_PARAMETER_ERRORS,
        BacNode,
        StopSignals,
        UserParameterError,
        drain_executor,
        start_exit_watchdog,
        start_refusal,
    )

    stop = threading.Event()
    # a process's main: after a stop signal, and for the interpreter's exit, a hard deadline (run_node's)
    hard = None if cleanup_timeout_s is None else StopSignals(cleanup_timeout_s + STOP_NOTICE_S)

    def on_signal(signum: int, _frame: Any) -> None:
        if not stop.is_set():
            LOG.info("received %s: stopping", signal.Signals(signum).name)
        stop.set()
        if hard is not None:
            hard.notice(signum)  # never blocks (the main thread may be inside hard.arm())

    old_handlers = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    if hard is not None:  # after our handlers: the SIGTERM stack dump chains to them; the wakeup-fd watcher
        hard.install(handlers=False)
    rclpy.init(args=["bac_container"], signal_handler_options=SignalHandlerOptions.NO)
    created: list[tuple[ContainedNode, Any]] = []
    executor: MultiThreadedExecutor | None = None
    code = 0
    own_at_start = 0.0  # the nodes' clean-up time when the stop deadline was set (after their constructors)
    making = ""  # the node being made: a refusal names it (several nodes share a parameter's name)
    try:
        for spec in nodes:
            making = spec.name
            module, class_name = spec.entry.split(":", 1)
            cls = getattr(importlib.import_module(module), class_name)
            created.append((spec, cls(cli_args=list(spec.args))))
        if hard is not None:
            own_at_start = sum(n.cleanup_time_s() for _, n in created if isinstance(n, BacNode))
            hard.deadline_s += own_at_start
            if stop.is_set():  # armed with the shorter deadline while the nodes were made
                hard.arm(hard.deadline_s, later=True)
        executor = MultiThreadedExecutor(num_threads=max(4, len(created) + 2))
        for _, n in created:
            executor.add_node(n)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while ok() and not stop.is_set():
            executor.spin_once(timeout_sec=0.05)
            done = [(s, n) for s, n in created if getattr(n, "exit_code", None) is not None]
            if done:
                spec, node = done[0]
                if spec.ends_graph and node.exit_code == 0:
                    LOG.info("%s finished: shutting down the graph", spec.name)
                    linger_end = time.monotonic() + linger_s
                    while ok() and not stop.is_set() and time.monotonic() < linger_end:
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
    except UserParameterError as exc:  # a node's -p overrides: a message to act on, as a process of its own says it
        LOG.critical("not started: %s", exc)
        code = 2
    except (BacError, *USER_PARAMETER_ERRORS) as exc:
        if executor is None and ok():  # a constructor's refusal says what to do, as run_node says it
            LOG.critical("not started: %s%s", f"{making}: " if making else "", start_refusal(exc))
            code = 2
        elif ok():
            LOG.exception("a node crashed: shutting down the graph")
            code = 1
    except Exception:
        if ok():
            LOG.exception("a node crashed: shutting down the graph")
            code = 1
        else:  # SIGINT/SIGTERM shut the context down while the executor built its wait set (an RCLError)
            code = 0
    finally:
        own = sum(n.cleanup_time_s() for _, n in created if isinstance(n, BacNode))
        if cleanup_timeout_s is not None:
            start_exit_watchdog("+".join(s.name for s in nodes), cleanup_timeout_s + own, code)
        if hard is not None and cleanup_timeout_s is not None:  # the clean-up and the interpreter's exit (run_node's)
            grown = own > own_at_start  # a clean-up time raised at runtime (the bridge's timeouts) extends it
            if grown:
                hard.deadline_s += own - own_at_start
            hard.arm(cleanup_timeout_s + own + 0.5, later=grown)
        drain_s = 4.0 if cleanup_timeout_s is None else cleanup_timeout_s / 2
        if executor is not None and not drain_executor(executor, drain_s):
            LOG.warning("a callback was still running at shutdown")
        # lower stop_order first; among equals, the last created first
        for _, n in sorted(reversed(created), key=lambda sn: sn[0].stop_order):
            try:
                n.destroy_node()
            except Exception:
                LOG.exception("destroying a node failed")
        try_shutdown()
        if restore_signals:
            for s, h in old_handlers.items():
                signal.signal(s, h)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    from bac_common.rosnode import CLEANUP_TIMEOUT_S

    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    ap = argparse.ArgumentParser(prog="python -m bac_bringup.container", description=__doc__.split("\n\n")[0])
    ap.add_argument("spec", type=Path, help="the process's nodes (JSON, written by the launcher)")
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))
    process, nodes, linger_s = read_spec(args.spec)
    LOG.info("process %s: %s", process, ", ".join(n.name for n in nodes))
    code = run_nodes(nodes, linger_s=linger_s, cleanup_timeout_s=CLEANUP_TIMEOUT_S, restore_signals=False)
    # the interpreter's exit resets Python-handled signals to SIG_DFL: the launcher's repeated SIGINT would then
    # kill a process that stopped cleanly (-2); an ignored one is left as it is (run_node does the same)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


if __name__ == "__main__":
    sys.exit(main())
