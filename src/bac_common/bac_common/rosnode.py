"""Thin ROS helpers shared by the bac nodes (the only rclpy module of bac_common).

* :class:`BacNode`: a Node with typed parameter declarations that carry a
  descriptor (range, description, read-only for structural ones), and an
  ``exit_code`` a node sets when its job is done (the launcher and
  :func:`run_node` stop spinning then).
* QoS profiles of the graph's contracts.
* :func:`run_node`: a Jazzy-safe ``main()`` (ros2/demos style): spin on a
  multi-threaded executor, handle Ctrl-C / SIGTERM / external shutdown, let
  the callbacks in flight finish (:func:`drain_executor`), destroy the node,
  ``try_shutdown``; a watchdog ends the process if that clean-up hangs.
"""

from __future__ import annotations

import os
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.utilities import ok as rclpy_ok
from rclpy.utilities import try_shutdown

# sensor streams: best effort, keep last 5 (what IMU drivers publish with)
QOS_SENSOR = qos_profile_sensor_data
# high-rate streams published inside the graph that must not drop samples (imu/vehicle; vehicle_sim's odom):
# reliable, and transient local so that a reader matched late (discovery between processes takes seconds)
# still gets the last samples (a run published just after start-up); readers ignore samples before their run
QOS_STREAM = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=5000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# readers of streams that may come from outside bac (vehicle/odom from a car's odometry driver): volatile, so
# that any reliable writer matches (a transient-local reader would not match a volatile writer)
QOS_STREAM_INPUT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.RELIABLE)
# one message per run (segments, scores): reliable, a generous queue, and transient local so that a reader
# matched late (discovery between processes takes seconds, more on a loaded machine) still gets the runs
# published before; readers key them by (campaign_id, trial_id, attempt) and ignore what is not theirs
QOS_EVENTS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=50,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# latched state (the trial, the active calibration): a late joiner gets the last one
QOS_LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# a reader of a latched topic that must see every state, not only the newest one left when it comes round (the
# writer keeps one message for late joiners; a deep reader still matches it)
QOS_LATCHED_READER = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


class BacNode(Node):
    """A Node with checked parameter declarations and a way to say "done"."""

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.exit_code: int | None = None
        self._param_checks: dict[str, Callable[[Any], str | None]] = {}
        self.add_on_set_parameters_callback(self._on_set_parameters)

    # --- declarations ---------------------------------------------------------------
    def _one_sided_bound(self, name: str, lo: float | None, hi: float | None) -> None:
        """A bound on one side only (a descriptor range needs both): checked on every set instead."""
        if (lo is None) == (hi is None):
            return
        self._param_checks[name] = lambda v: (
            f"{name} must be >= {lo}"
            if lo is not None and v < lo
            else f"{name} must be <= {hi}"
            if hi is not None and v > hi
            else None
        )

    def declare_float(
        self,
        name: str,
        default: float,
        description: str,
        lower: float | None = None,
        upper: float | None = None,
        read_only: bool = False,
    ) -> float:
        rng = []
        if lower is not None and upper is not None:
            rng = [FloatingPointRange(from_value=float(lower), to_value=float(upper), step=0.0)]
        desc = ParameterDescriptor(
            description=description,
            type=ParameterType.PARAMETER_DOUBLE,
            read_only=read_only,
            floating_point_range=rng,
        )
        self._one_sided_bound(name, lower, upper)
        value = self.declare_parameter(name, float(default), desc).value
        self._check_initial(name, value)
        return float(value)

    def declare_int(
        self,
        name: str,
        default: int,
        description: str,
        lower: int | None = None,
        upper: int | None = None,
        read_only: bool = False,
    ) -> int:
        rng = []
        if lower is not None and upper is not None:
            rng = [IntegerRange(from_value=int(lower), to_value=int(upper), step=1)]
        desc = ParameterDescriptor(
            description=description,
            type=ParameterType.PARAMETER_INTEGER,
            read_only=read_only,
            integer_range=rng,
        )
        self._one_sided_bound(name, lower, upper)
        value = self.declare_parameter(name, int(default), desc).value
        self._check_initial(name, value)
        return int(value)

    def declare_str(
        self,
        name: str,
        default: str,
        description: str,
        choices: Sequence[str] | None = None,
        read_only: bool = False,
    ) -> str:
        text = description
        if choices:
            text += f" (one of: {', '.join(choices)})"
            allowed = tuple(choices)
            self._param_checks[name] = lambda v: None if v in allowed else f"{name} must be one of {allowed}, got {v!r}"
        desc = ParameterDescriptor(description=text, type=ParameterType.PARAMETER_STRING, read_only=read_only)
        value = self.declare_parameter(name, str(default), desc).value
        self._check_initial(name, value)
        return str(value)

    def declare_bool(self, name: str, default: bool, description: str, read_only: bool = False) -> bool:
        desc = ParameterDescriptor(description=description, type=ParameterType.PARAMETER_BOOL, read_only=read_only)
        return bool(self.declare_parameter(name, bool(default), desc).value)

    def declare_float_list(
        self, name: str, default: Sequence[float], description: str, read_only: bool = False
    ) -> list[float]:
        desc = ParameterDescriptor(
            description=description, type=ParameterType.PARAMETER_DOUBLE_ARRAY, read_only=read_only
        )
        value = self.declare_parameter(name, [float(x) for x in default], desc).value
        return [float(x) for x in (value or [])]

    def declare_str_list(
        self, name: str, default: Sequence[str], description: str, read_only: bool = False
    ) -> list[str]:
        desc = ParameterDescriptor(
            description=description, type=ParameterType.PARAMETER_STRING_ARRAY, read_only=read_only
        )
        value = self.declare_parameter(name, list(default) or [""], desc).value
        # an empty list in a parameter file has no type: rclpy hands it over as None
        return [str(x) for x in (value or []) if str(x)]

    def add_parameter_check(self, name: str, check: Callable[[Any], str | None]) -> None:
        """Register an extra check for ``name``: returns None when fine, else the reason."""
        self._param_checks[name] = check
        self._check_initial(name, self.get_parameter(name).value)

    def _check_initial(self, name: str, value: Any) -> None:
        check = self._param_checks.get(name)
        reason = check(value) if check else None
        if reason:
            raise ValueError(f"node '{self.get_name()}': parameter {reason}")

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for p in params:
            check = self._param_checks.get(p.name)
            if check is not None:
                reason = check(p.value)
                if reason:
                    return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    # --- ending ---------------------------------------------------------------------------
    def cleanup_time_s(self) -> float:
        """The longest this node's own clean-up in ``destroy_node`` may take, s (run_node's watchdog allows it)."""
        return 0.0

    def finish(self, code: int = 0) -> None:
        """Ask whoever spins this node to stop (0 = job done, else failure)."""
        if self.exit_code is None:
            self.exit_code = code


N = TypeVar("N", bound=Node)


def spin_until_done(executor: MultiThreadedExecutor, nodes: Sequence[Node], poll_s: float = 0.1) -> int:
    """Spin until a node sets ``exit_code`` or the context shuts down; return the code."""
    while executor.context.ok():
        executor.spin_once(timeout_sec=poll_s)
        for node in nodes:
            code = getattr(node, "exit_code", None)
            if code is not None:
                return int(code)
    return 0


CLEANUP_TIMEOUT_S = 5.0  # after spinning: drain + destroy + shutdown must end by then (the launcher waits 8 s)


def drain_executor(executor: MultiThreadedExecutor, timeout_s: float) -> bool:
    """Stop handing out callbacks and wait up to ``timeout_s`` for those in flight; True if all ended.

    rclpy's MultiThreadedExecutor never stops its thread pool: a callback still running on a worker
    (a score being published as SIGINT arrives) would otherwise race the node's destruction.
    """
    executor.shutdown(timeout_sec=0)
    pool = getattr(executor, "_executor", None)  # rclpy: the ThreadPoolExecutor running the callbacks
    if pool is not None:
        # no new work; callbacks already handed to the pool still run (cancelling a queued one would leave
        # its rclpy task pending forever, and it may carry an event the node must not lose)
        pool.shutdown(wait=False)
    deadline = time.monotonic() + timeout_s
    for task in list(getattr(executor, "_futures", [])):
        while not task.done():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        task.exception()  # fetched: a publish cut short by the shutdown is expected, not "never retrieved"
    return True


def start_exit_watchdog(name: str, timeout_s: float, code: int) -> None:
    """Start a daemon thread that ends the process with ``code`` if it is still alive after ``timeout_s``.

    Clean-up after the job is done (the journal and bags are flushed as they go) must not keep a node
    alive: an rclpy shutdown that hangs would otherwise cost the launcher SIGTERM and SIGKILL. A process
    that exits in time takes the daemon thread with it.
    """

    def watch() -> None:
        time.sleep(timeout_s)
        sys.stderr.write(
            f"[{name}] clean-up did not finish within {timeout_s:g} s after spinning stopped "
            f"(an rclpy shutdown hang); exiting with code {code}\n"
        )
        sys.stderr.flush()
        os._exit(code)

    threading.Thread(target=watch, name="bac-exit-watchdog", daemon=True).start()


def run_node(
    node_cls: Callable[..., N], args: Sequence[str] | None = None, cleanup_timeout_s: float = CLEANUP_TIMEOUT_S
) -> int:
    """A Jazzy-safe main() (a process's, not a library call): create, spin, clean up; returns the exit code.

    The returned code is final: once spinning stops, the process ends within ``cleanup_timeout_s`` (plus the
    node's own :meth:`BacNode.cleanup_time_s`) even if rclpy's clean-up, or the interpreter's exit that joins
    the executor's threads, hangs.
    """
    rclpy.init(args=list(args) if args is not None else sys.argv)
    node: N | None = None
    executor: MultiThreadedExecutor | None = None
    code = 0
    try:
        node = node_cls()
        executor = MultiThreadedExecutor()
        executor.add_node(node)
        code = spin_until_done(executor, [node])
    except (KeyboardInterrupt, ExternalShutdownException):
        if node is None or executor is None:
            rclpy.logging.get_logger(getattr(node_cls, "__name__", "bac")).info("interrupted while starting")
        code = 0
    except Exception:
        msg = traceback.format_exc()
        if not rclpy_ok():
            # SIGINT (Ctrl-C, the launcher's stop) while the node was still starting: rclpy's handler shut the
            # context down under the constructor, whose next rcl call then fails. An interrupted start, not a crash.
            rclpy.logging.get_logger(getattr(node_cls, "__name__", "bac")).info("interrupted while starting")
            code = 0
        elif node is not None:
            node.get_logger().fatal(f"node crashed:\n{msg}")
            code = 1
        else:
            rclpy.logging.get_logger(getattr(node_cls, "__name__", "bac")).fatal(f"node failed to start:\n{msg}")
            code = 1
    finally:
        name = node.get_name() if node is not None else getattr(node_cls, "__name__", "bac")
        own = node.cleanup_time_s() if isinstance(node, BacNode) else 0.0
        start_exit_watchdog(name, cleanup_timeout_s + own, code)  # also covers the interpreter's exit
        if executor is not None and not drain_executor(executor, cleanup_timeout_s / 2):
            sys.stderr.write(f"[{name}] a callback was still running at shutdown\n")
        if node is not None:
            node.destroy_node()
        try_shutdown()
    return code
