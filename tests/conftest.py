"""Test fixtures shared by the whole suite.

* Each test gets its own ROS domain (``ROS_DOMAIN_ID``), so that nodes left by
  one test can never be heard by the next; ``make test`` also runs the whole
  suite inside a private network namespace, so tests of concurrent sessions
  cannot hear each other on the network. ``make test`` runs two pytest-xdist
  workers, each in a network namespace of its own (``scripts/test-worker``)
  and with its own share of the domains: Fast DDS's shared-memory transport
  is not namespaced, so one domain on two workers could still meet in
  /dev/shm (``--max-worker-restart=0``: a restarted worker, gw2, would take
  gw0's share). Two *sessions* at once (make test and a scripts/pytest.sh
  beside it) draw from the same 101 domains and can meet there: run one at a
  time. :func:`fresh_domain` gives a module-scoped fixture a domain of the
  worker's share.
* Whole files go to a worker (``--dist loadfile``: a module's campaign runs
  once), the slow ones first, so that the longest do not end the run alone;
  a file marked ``alone`` runs while no other does (``_MachineShare``).
* ``ros_context``: an rclpy context for in-process nodes, with a background
  executor, shut down after the test.
* ``procs``: starts real processes (nodes, the simulated ECU, ...) and kills
  whatever is left at the end of the test.
* ``wait_for``: poll a condition with a timeout (never a fixed sleep).
"""

from __future__ import annotations

import itertools
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def _worker_domains() -> list[int]:
    """ROS domain ids usable on Linux without port clashes, 1..101 (0 is everyone's default); under pytest-xdist
    worker k of n takes the ids d with d % n == k."""
    n = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    k = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0) % max(n, 1)
    ids = [d for d in range(1, 102) if d % max(n, 1) == k]
    return random.Random(os.getpid() ^ int(time.time())).sample(ids, len(ids))


_DOMAINS = itertools.cycle(_worker_domains())


def fresh_domain() -> int:
    """A ROS domain of this worker's share, not the one the previous test used."""
    return next(_DOMAINS)


os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
os.environ.setdefault("PYTHONUNBUFFERED", "1")


def wait_for(condition: Callable[[], Any], timeout: float = 20.0, interval: float = 0.02, what: str = "") -> Any:
    """Return the first truthy value of ``condition()``; fail the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what or condition}")
        time.sleep(interval)


@pytest.fixture(autouse=True)
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> int:
    domain = fresh_domain()
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    return domain


@pytest.fixture
def ros_env(ros_domain: int) -> dict[str, str]:
    """The environment for ROS processes started by a test (its own domain, localhost only)."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(ros_domain)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return env


class RosHarness:
    """An rclpy context with a background executor (single-threaded: rclpy's multi-threaded executor takes
    a few hundred messages a second at most, too few for a 400 Hz IMU replayed faster than real time)."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes: list[Any] = []
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except (ExternalShutdownException, Exception):
            pass

    def node(self, name: str, **kwargs: Any) -> Any:
        from rclpy.node import Node

        n = Node(name, context=self.context, **kwargs)
        self.add(n)
        return n

    def add(self, node: Any) -> Any:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def shutdown(self) -> None:
        import rclpy

        for n in self.nodes:
            self.executor.remove_node(n)
            n.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=5)


@pytest.fixture
def ros_context(ros_domain: int) -> Iterator[RosHarness]:
    h = RosHarness(ros_domain)
    try:
        yield h
    finally:
        h.shutdown()


class Procs:
    """Processes started by a test; all are stopped (SIGINT, then SIGKILL) at the end."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env = env
        self.log_dir = log_dir
        self.items: list[tuple[str, subprocess.Popen[bytes], Path]] = []

    def start(
        self, name: str, argv: Sequence[str], env: dict[str, str] | None = None, cwd: Path | None = None
    ) -> subprocess.Popen[bytes]:
        log = self.log_dir / f"{name}.log"
        f = log.open("wb")
        p = subprocess.Popen(
            list(argv),
            env={**self.env, **(env or {})},
            stdout=f,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=cwd,
        )
        self.items.append((name, p, log))
        return p

    def python(self, name: str, args: Sequence[str], **kw: Any) -> subprocess.Popen[bytes]:
        return self.start(name, [sys.executable, *args], **kw)

    def log(self, name: str) -> str:
        for n, _, path in self.items:
            if n == name:
                return path.read_text(errors="replace")
        raise KeyError(name)

    def ending(self, name: str, rc: int | None, lines: int = 40) -> str:
        """How a launcher's process ended, for an assertion's message (CI shows a message's beginning, and a whole
        log there hides its end): its exit code, the launcher's own warnings (a node's exit code, a SIGTERM), then
        the log's last lines."""
        log = self.log(name).splitlines()
        said = [ln for ln in log if ln.startswith("[bac.launch]") and ("code" in ln or "sent SIG" in ln)]
        return "\n".join([f"{name} ended with {rc}", *said[-10:], f"--- the last {lines} lines:", *log[-lines:]])

    def logs(self) -> str:
        return "\n".join(f"----- {n} -----\n{path.read_text(errors='replace')}" for n, _, path in self.items)

    def stop_all(self) -> None:
        for _, p, _ in self.items:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + 10
        for _, p, _ in self.items:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


@pytest.fixture
def procs(ros_env: dict[str, str], tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Procs]:
    ps = Procs(ros_env, tmp_path)
    try:
        yield ps
    finally:
        ps.stop_all()
        rep = getattr(request.node, "rep_call", None)
        if rep is not None and rep.failed:
            sys.stderr.write(ps.logs()[-20000:])


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    rep = yield
    setattr(item, f"rep_{rep.when}", rep)
    return rep


def _file_rank(items: list[pytest.Item]) -> tuple[int, float]:
    """Slow integration files first, then the other integration files, then slow unit tests, then the rest; within
    a rank the file with the longest declared timeout first (the test's own bound on how long it may take). Files
    marked ``alone`` last: while one runs the other worker waits (:class:`_MachineShare`), at the end it has
    little left to wait with."""
    marks = {m.name for item in items for m in item.iter_markers()}
    integration, slow = "integration" in marks, "slow" in marks
    rank = 4 if "alone" in marks else 0 if integration and slow else 1 if integration else 2 if slow else 3
    timeouts = [float(m.args[0]) for item in items for m in item.iter_markers("timeout") if m.args]
    return rank, -max(timeouts, default=0.0)


def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list[pytest.Item]) -> None:
    """Files in the order of :func:`_file_rank` (each file's tests in their order): with two workers the long files
    start early and the many short ones fill the end. The order is a function of the collection alone, the same
    on every worker (xdist checks that)."""
    files: dict[str, list[pytest.Item]] = {}
    for item in items:
        files.setdefault(item.nodeid.split("::", 1)[0], []).append(item)
    ranked = sorted(files.values(), key=_file_rank)  # stable: collection order within a rank
    items[:] = [item for group in ranked for item in group]
    share = config.pluginmanager.get_plugin("bac-machine-share")
    if isinstance(share, _MachineShare):
        share.alone_files = {f for f, group in files.items() if any(i.get_closest_marker("alone") for i in group)}


class _MachineShare:
    """Under make test's workers every test file, under src/ too, holds a shared lock on the run's lock file while
    its tests run, and a file marked ``alone`` (a timing bound that needs the machine to itself: the cockpit's
    update lag) holds it exclusively: it starts once the other worker's file has ended, and the other worker's next
    file waits for it. A global plugin (registered by pytest_configure: a conftest's own runtest hooks only see the
    tests below it), outermost around each test's protocol, so that pytest-timeout does not count the wait."""

    def __init__(self, config: pytest.Config, run: str) -> None:
        self.config, self.run = config, run
        self.path: Path | None = None
        self.alone_files: set[str] = set()
        self._file: Any = None
        self._held: str | None = None

    def _acquire(self, test_file: str) -> None:
        import fcntl

        if self.path is None:  # in the run's folder (the workers' basetemps are beneath it): pytest removes old ones
            factory = getattr(self.config, "_tmp_path_factory", None)
            folder = factory.getbasetemp().parent if factory is not None else Path(tempfile.gettempdir())
            self.path = folder / f"bac-machine-share-{self.run}.lock"
        # a POSIX record lock (lockf), not flock: a process forked by a test (a multiprocessing pool left running)
        # would inherit a flock and hold it after this process let it go; a record lock stays with this process
        mode = fcntl.LOCK_EX if test_file in self.alone_files else fcntl.LOCK_SH
        self._file = self.path.open("a+")
        try:
            fcntl.lockf(self._file, mode | fcntl.LOCK_NB)
        except OSError:
            what = "the machine to itself" if mode == fcntl.LOCK_EX else "a file marked alone to end"
            sys.stderr.write(f"\n{test_file} waits for {what}\n")
            fcntl.lockf(self._file, mode)
        self._held = test_file

    def _release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing drops this process's record locks on the file
        self._file, self._held = None, None

    @pytest.hookimpl(hookwrapper=True, tryfirst=True)
    def pytest_runtest_protocol(self, item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
        test_file = item.nodeid.split("::", 1)[0]
        if self._held != test_file:
            self._release()
            self._acquire(test_file)
        try:
            yield
        finally:
            if nextitem is None or nextitem.nodeid.split("::", 1)[0] != test_file:
                self._release()


def pytest_configure(config: pytest.Config) -> None:
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run and not config.pluginmanager.has_plugin("bac-machine-share"):
        config.pluginmanager.register(_MachineShare(config, run), "bac-machine-share")


@pytest.fixture
def in_private_netns() -> bool:
    return os.environ.get("BAC_PRIVATE_NETNS") == "1"
