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
* :class:`StopSignals`: SIGINT and SIGTERM as a flag that cannot be lost (a
  ``KeyboardInterrupt`` can be: CPython swallows one raised in a finalizer or a
  weakref callback), with a hard deadline once a stop is asked for.
"""

from __future__ import annotations

import collections
import difflib
import faulthandler
import io
import json
import math
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, TypeVar

import rclpy
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterUninitializedException,
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

from bac_common.contracts import USER_PARAMS
from bac_common.errors import BacError

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


class UserParameterError(ValueError):
    """A parameter set with ``-p`` that the node does not have, or whose value did not reach it (its type)."""


class _CheckedAfterInit(type):
    """Runs :meth:`BacNode._check_user_params` once a node's constructor (the subclass's included) is done."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        node = super().__call__(*args, **kwargs)
        if isinstance(node, BacNode):
            try:
                node._check_user_params()
            except UserParameterError:
                node.destroy_node()
                raise
        return node


class BacNode(Node, metaclass=_CheckedAfterInit):
    """A Node with checked parameter declarations and a way to say "done"."""

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.exit_code: int | None = None
        self._param_checks: dict[str, Callable[[Any], str | None]] = {}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.declare_parameter(
            USER_PARAMS,
            [""],
            ParameterDescriptor(
                description="set by bac launch: the parameters given with -p (name=value), checked at start",
                type=ParameterType.PARAMETER_STRING_ARRAY,
                read_only=True,
            ),
        )

    def _check_user_params(self) -> None:
        """Every parameter the user set with ``-p`` is one of this node's and holds the value given: rcl keeps the
        value of an earlier parameter file when a later one gives another type (``budget:=abc`` left 15), and a
        name the node does not declare is ignored (``budgt:=3`` left 15): a campaign of 15 drives instead of 3
        (outside review 2026-11-29)."""
        given = [str(x) for x in (self.get_parameter(USER_PARAMS).value or []) if x]
        if not given:
            return
        declared = sorted(n for n in self._parameters if n != USER_PARAMS)
        problems = []
        for item in given:
            name, _, raw = item.partition("=")
            if not self.has_parameter(name):
                close = difflib.get_close_matches(name, declared, n=1, cutoff=0.6)
                hint = f"did you mean '{close[0]}'?" if close else f"its parameters: {', '.join(declared)}"
                problems.append(f"-p {self.get_name()}.{name}: {self.get_name()} has no parameter '{name}'; {hint}")
                continue
            want = json.loads(raw) if raw else ""  # (the launcher writes JSON: 1e-05 would be a string in YAML 1.1)
            try:
                have = self.get_parameter(name).value
            except ParameterUninitializedException:  # declared with no value (an empty list): nothing reached it
                have = None
            if have is None and want in ([], "", None):
                continue
            if not isinstance(have, str | bytes) and hasattr(have, "__iter__"):
                have = list(have)  # (an array parameter reads back as array.array)
            if have != want:  # (3 == 3.0: an integer given for a float parameter reaches it)
                kind = type(have).__name__ if have is not None else "unset"
                problems.append(
                    f"-p {self.get_name()}.{name}:={want}: the node has {have!r} ({kind}): a value of another type "
                    f"({type(want).__name__}) does not reach it"
                )
        if problems:
            raise UserParameterError("; ".join(problems))

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
        self._integer_override_as_float(name)
        value = self.declare_parameter(name, float(default), desc).value
        self._check_initial(name, value)
        return float(value)

    def _integer_override_as_float(self, name: str) -> None:
        """``-p x:=1`` (or ``x: 1`` in a file) for a float parameter: rclpy refuses an INTEGER for a DOUBLE and the
        node dies; the number is meant, so it is taken as 1.0."""
        given = self._parameter_overrides.get(name)
        if given is not None and given.type_ == Parameter.Type.INTEGER:
            self._parameter_overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(given.value))
        elif given is not None and given.type_ == Parameter.Type.INTEGER_ARRAY:
            values = [float(v) for v in given.value]
            self._parameter_overrides[name] = Parameter(name, Parameter.Type.DOUBLE_ARRAY, values)

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
        self._integer_override_as_float(name)
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


def spin_until_done(
    executor: MultiThreadedExecutor,
    nodes: Sequence[Node],
    poll_s: float = 0.1,
    stop: Callable[[], bool] | None = None,
) -> int:
    """Spin until a node sets ``exit_code``, the context shuts down or ``stop()`` is true; return the code."""
    while executor.context.ok() and not (stop is not None and stop()):
        executor.spin_once(timeout_sec=poll_s)
        for node in nodes:
            code = getattr(node, "exit_code", None)
            if code is not None:
                return int(code)
    for node in nodes:  # a worker thread may have set it just before the stop or the shutdown: not lost
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


STOP_NOTICE_S = 1.0  # a stop signal -> spinning stopped (the loop polls every 0.1 s): 6 s in all, 2 s inside the
# launcher's grace (8 s) on a loaded machine


class StopSignals:
    """SIGINT and SIGTERM of a node process as a flag that cannot be lost, and a hard deadline once one came.

    Python runs a signal's handler in the main thread between two bytecodes, wherever that is. A
    ``KeyboardInterrupt`` raised there is swallowed when the place is a finalizer (``__del__``) or a weakref
    callback ("Exception ignored in ...", e.g. importlib's module-lock callback while a node imports numpy),
    or C code that clears errors: the signal is lost. Found by hammering a node's start and stop (2026-11-24:
    2 of about 400 SIGINTs in the first second of a node's life, on a loaded 2-core machine); the node then
    spun until the launcher's SIGTERM. The handler here sets a flag, which nothing can swallow:
    :func:`run_node` checks it before creating the node, after its constructor and in every turn of the spin
    loop. While ``interrupt`` is true (the constructor runs) the handler also raises ``KeyboardInterrupt`` to
    cut a waiting constructor short, once (it clears ``interrupt``: a repeated SIGINT must not cut short the
    constructor's own clean-up); if that one is swallowed, the flag still stops the node.

    The first stop signal arms a hard deadline (:meth:`arm`): a process still alive ``deadline_s`` later
    writes every thread's stack to stderr (the node's log) and exits with code 1
    (``faulthandler.dump_traceback_later(exit=True)``: a C thread that needs neither the main thread nor the
    GIL), and up to a second later the kernel ends it with SIGALRM (``signal.alarm``: for a hang after the
    interpreter has finalized, where faulthandler is gone). A signal is noticed without the main thread too:
    its byte on the signal wakeup fd wakes a watcher thread, which arms the deadline when the main thread is
    stuck in C code. SIGTERM (the launcher's second step, when SIGINT was not enough) also writes the stacks
    at once (``faulthandler.register``; on a first, normal SIGTERM stop too: a conditional dump would need the
    main thread, which a hung node does not give). :func:`run_node` arms the same deadline for its clean-up and exit.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)
    # our wakeup fd's write end, and the instance its watcher serves
    _wakeup: ClassVar[tuple[int, StopSignals] | None] = None

    def __init__(self, deadline_s: float) -> None:
        self.deadline_s = deadline_s
        self.signum: int | None = None
        self.interrupt = False
        self._deadline_at: float | None = None  # time.monotonic() of the armed deadline
        self._arm_lock = threading.Lock()
        self._pending: collections.deque[tuple[float, bool]] = collections.deque()  # (monotonic time, later)

    def requested(self) -> bool:
        """True once SIGINT or SIGTERM came (a method: it changes under the caller's feet)."""
        return self.signum is not None

    def install(self, handlers: bool = True) -> StopSignals:
        """Take SIGINT and SIGTERM (call from the main thread, before ``rclpy.init``, whose handlers chain here).

        ``handlers``: False for a caller with handlers of its own (the container, which calls :meth:`notice`):
        only the SIGTERM stack dump and the wakeup-fd watcher are installed then (after the caller's handlers).
        A wakeup fd someone else installed (an asyncio loop) is left in place, without a watcher; one of ours
        (a second install in the process) is kept and its watcher serves this instance from now on.
        """
        if handlers:
            for s in self.SIGNALS:
                signal.signal(s, self._on_signal)
        try:
            faulthandler.register(signal.SIGTERM, file=sys.stderr, all_threads=True, chain=True)
        except (ValueError, OSError, AttributeError, io.UnsupportedOperation):  # no file descriptor (a test's capture)
            pass
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        old = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        if old == -1:
            StopSignals._wakeup = (write_fd, self)
            threading.Thread(target=self._watch, args=(read_fd,), name="bac-stop-signals", daemon=True).start()
            return self
        # not ours to take: give the old one back before our pipe is closed (a wakeup fd left pointing at a closed
        # descriptor sends the signal bytes into whatever file reuses its number)
        mine = StopSignals._wakeup is not None and StopSignals._wakeup[0] == old
        signal.set_wakeup_fd(old, warn_on_full_buffer=not mine)
        os.close(read_fd)
        os.close(write_fd)
        if mine:
            StopSignals._wakeup = (old, self)
        return self

    def notice(self, signum: int) -> None:
        """A stop signal came (from a handler): remember the first, arm the deadline (never blocks)."""
        if self.signum is None:
            self.signum = signum
        self._request(self.deadline_s, False, blocking=False)

    def _on_signal(self, signum: int, _frame: Any) -> None:
        self.notice(signum)
        if self.interrupt:
            # once: a repeated SIGINT (the launcher's, every second) must not cut short the constructor's own
            # except/finally clean-up that the first one started (a journal repair, a connection closed)
            self.interrupt = False
            raise KeyboardInterrupt

    @staticmethod
    def _watch(read_fd: int) -> None:
        while True:
            data = os.read(read_fd, 64)
            if not data:
                return
            wakeup = StopSignals._wakeup
            if wakeup is not None and any(b in StopSignals.SIGNALS for b in data):
                target = wakeup[1]
                target.arm(target.deadline_s)

    def arm(self, seconds: float, later: bool = False) -> None:
        """End the process ``seconds`` from now if it still lives (the earlier of this and an armed deadline;
        ``later``: this one even if later, e.g. once the node's own clean-up time is known). Waits for an
        arm in progress in another thread (the watcher's); never lost."""
        self._request(seconds, later, blocking=True)

    def _request(self, seconds: float, later: bool, blocking: bool) -> None:
        # Every request goes into a queue; whoever holds the lock applies all queued ones before it lets go and
        # looks again after. The signal handler does not block (it runs on the main thread, which may be inside
        # arm() holding the lock itself): if the lock is taken, its holder applies the handler's request.
        self._pending.append((time.monotonic() + seconds, later))
        while self._pending:
            if not self._arm_lock.acquire(blocking=blocking):
                return
            try:
                while self._pending:
                    self._apply(*self._pending.popleft())
            finally:
                self._arm_lock.release()

    def _apply(self, at: float, later: bool) -> None:
        if self._deadline_at is not None and at >= self._deadline_at and not later:
            return
        self._deadline_at = at
        seconds = max(at - time.monotonic(), 0.001)
        try:
            faulthandler.dump_traceback_later(seconds, exit=True, file=sys.stderr)
        except (ValueError, OSError, AttributeError, io.UnsupportedOperation):  # no file descriptor
            pass
        if signal.getsignal(signal.SIGALRM) in (signal.SIG_DFL, None):  # nobody else's alarm
            signal.alarm(math.ceil(seconds + 0.5))


# a parameter value the node's descriptor refuses (rclpy raises these from declare_parameter): the user's -p or
# parameter file, to be said as a reason, not shown as a traceback (2026-11-29: -p bo_agent.seed:=-5)
USER_PARAMETER_ERRORS = (InvalidParameterValueException, InvalidParameterTypeException)


def start_refusal(exc: BaseException | None) -> str:
    """Why a node's constructor refused to start, said to the user ("" for a crash, which keeps its traceback):
    bac's own errors, and a parameter value outside the node's declared range or type."""
    if isinstance(exc, BacError):
        return str(exc)
    if isinstance(exc, USER_PARAMETER_ERRORS):
        return f"{exc} (set by a -p or a parameter file: give a value the node's range or type allows)"
    return ""


def run_node(
    node_cls: Callable[..., N], args: Sequence[str] | None = None, cleanup_timeout_s: float = CLEANUP_TIMEOUT_S
) -> int:
    """A Jazzy-safe main() (a process's, not a library call): create, spin, clean up; returns the exit code.

    The returned code is final: once spinning stops, the process ends within ``cleanup_timeout_s`` (plus the
    node's own :meth:`BacNode.cleanup_time_s`) even if rclpy's clean-up, or the interpreter's exit that joins
    the executor's threads, hangs. SIGINT and SIGTERM are taken by :class:`StopSignals` (a flag, never lost;
    rclpy's own handlers still shut the context down); after the first one the process ends within
    ``cleanup_timeout_s`` + :data:`STOP_NOTICE_S` (plus the node's own clean-up time) whatever hangs.

    It must not be called in a process that goes on after it returns: it leaves the process-wide exit watchdog,
    the armed hard deadline (faulthandler's exit timer and ``SIGALRM``) and SIGINT ignored behind, which end the
    process a few seconds later by design (tests run it in a subprocess).
    """
    stop = StopSignals(cleanup_timeout_s + STOP_NOTICE_S).install()
    rclpy.init(args=list(args) if args is not None else sys.argv)
    node: N | None = None
    executor: MultiThreadedExecutor | None = None
    code = 0
    own_at_start = 0.0  # the node's clean-up time when the stop deadline was set (after its constructor)
    log_name = getattr(node_cls, "__name__", "bac")
    try:
        if not stop.requested():
            stop.interrupt = True
            try:
                node = node_cls()
            finally:
                stop.interrupt = False
            if isinstance(node, BacNode) and node.cleanup_time_s() > 0:
                own_at_start = node.cleanup_time_s()
                stop.deadline_s += own_at_start
                if stop.requested():  # armed with the shorter deadline while the constructor ran
                    stop.arm(stop.deadline_s, later=True)
        if node is None or stop.requested():
            rclpy.logging.get_logger(log_name).info("interrupted while starting")
        else:
            executor = MultiThreadedExecutor()
            executor.add_node(node)
            code = spin_until_done(executor, [node], stop=stop.requested)
    except (KeyboardInterrupt, ExternalShutdownException):
        if node is None or executor is None:
            rclpy.logging.get_logger(log_name).info("interrupted while starting")
        code = 0
    except UserParameterError as exc:  # the user's -p: a message to act on, not a traceback
        rclpy.logging.get_logger(log_name).fatal(f"not started: {exc}")
        code = 2
    except Exception:
        msg = traceback.format_exc()
        if (not rclpy_ok() or stop.requested()) and executor is None:
            # SIGINT (Ctrl-C, the launcher's stop) while the node was still starting: rclpy's handler shut the
            # context down under the constructor, whose next rcl call then fails. An interrupted start, not a crash.
            rclpy.logging.get_logger(log_name).info("interrupted while starting")
            code = 0
        elif node is not None and executor is not None and (not rclpy_ok() or stop.requested()):
            # a running node that failed after the stop was asked for (often the context shut down under a
            # callback): not an interrupted start; logged as what it is, the stop still clean unless it set a code
            err = sys.exc_info()[1]
            if "context is not valid" in str(err):  # rclpy shut its context down under a callback: the stop itself
                first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
                node.get_logger().info(f"the context was shut down under a callback while stopping ({first})")
            else:
                node.get_logger().error(f"an error after the stop was asked for:\n{msg}")
            exit_code = getattr(node, "exit_code", None)
            code = 0 if exit_code is None else int(exit_code)
        elif node is not None:
            node.get_logger().fatal(f"node crashed:\n{msg}")
            code = 1
        elif start_refusal(sys.exc_info()[1]):  # bac's own errors, a value out of range: say what to do
            rclpy.logging.get_logger(log_name).fatal(f"not started: {start_refusal(sys.exc_info()[1])}")
            code = 2
        else:
            rclpy.logging.get_logger(log_name).fatal(f"node failed to start:\n{msg}")
            code = 1
    finally:
        name = node.get_name() if node is not None else log_name
        own = node.cleanup_time_s() if isinstance(node, BacNode) else 0.0
        start_exit_watchdog(name, cleanup_timeout_s + own, code)  # and the interpreter's exit until it finalizes
        # the hard deadline 0.5 s after the watchdog's (whose exit code wins when it can run): for a clean-up
        # stuck in C code that holds the GIL (no Python thread runs then) and for the interpreter's exit once it
        # finalizes (the watchdog thread is gone then, and rclpy's SIGTERM handler, still installed, keeps SIGTERM
        # from ending the process: the CI hang of 54c04f0, neither SIGINT nor SIGTERM ended imu_ingest). The
        # node's clean-up time is read again: it may have grown at runtime (the bridge's timeouts are runtime
        # parameters), and then this extends the deadline a stop signal armed (later=True), repeated SIGINTs too.
        grown = own > own_at_start
        if grown:
            stop.deadline_s += own - own_at_start
        stop.arm(cleanup_timeout_s + own + 0.5, later=grown)
        if executor is not None and not drain_executor(executor, cleanup_timeout_s / 2):
            sys.stderr.write(f"[{name}] a callback was still running at shutdown\n")
        if node is not None:
            node.destroy_node()
        try_shutdown()
        # the interpreter's exit resets Python-handled signals to SIG_DFL: the launcher's repeated SIGINT would
        # then kill a process that stopped cleanly (-2); an ignored one is left as it is (the deadline stays)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code
