"""run_node's shutdown: a callback in flight ends before the node is destroyed, and a hung clean-up cannot
keep the process alive (the launcher would otherwise need SIGTERM and SIGKILL, and report a failure)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT, wait_for

pytestmark = pytest.mark.integration
HELPERS = ROOT / "tests" / "helpers"


def start_reporter(env: dict[str, str], out: Path, **params: object) -> subprocess.Popen[bytes]:
    args = [f"out_dir:={out}"] + [f"{k}:={json.dumps(v)}" for k, v in params.items()]
    ros_args = [a for kv in args for a in ("-p", kv)]
    return subprocess.Popen(
        [sys.executable, "-m", "graph_nodes", "--ros-args", "-r", "__node:=reporter", *ros_args],
        env={**env, "PYTHONPATH": f"{HELPERS}:{env.get('PYTHONPATH', '')}"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def test_a_callback_in_flight_finishes_before_the_node_is_destroyed(ros_env: dict[str, str], tmp_path: Path) -> None:
    p = start_reporter(ros_env, tmp_path, busy_callback_s=1.5)
    try:
        wait_for(lambda: (tmp_path / "reporter.busy.json").exists(), 60, what="the long callback started")
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = out.decode(errors="replace")
    assert p.returncode == 0, text
    assert json.loads((tmp_path / "reporter.clean.json").read_text()) == {"callback_done": True}, text
    assert "never retrieved" not in text


def test_a_hung_clean_up_ends_the_process_with_its_code(ros_env: dict[str, str], tmp_path: Path) -> None:
    p = start_reporter(ros_env, tmp_path, hang_on_destroy=True)
    try:
        wait_for(lambda: (tmp_path / "reporter.start.json").exists(), 60, what="the node started")
        p.send_signal(signal.SIGINT)
        wait_for(lambda: (tmp_path / "reporter.clean.json").exists(), 30, what="clean-up began")
        t0 = time.monotonic()
        out, _ = p.communicate(timeout=30)
        waited = time.monotonic() - t0
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = out.decode(errors="replace")
    assert p.returncode == 0, text
    assert "clean-up did not finish within 5 s" in text
    assert waited < 8.0, f"the process took {waited:.1f} s to end after its clean-up hung (launcher grace 8 s)"


def test_a_repeated_sigint_does_not_cut_the_clean_up_short(ros_env: dict[str, str], tmp_path: Path) -> None:
    """The launcher repeats SIGINT during its grace (a node may lose one): a node already cleaning up (the bridge
    restoring the baseline) must take it as a no-op. It raised KeyboardInterrupt in the clean-up before."""
    p = start_reporter(ros_env, tmp_path, slow_destroy_s=2.0)
    try:
        wait_for(lambda: (tmp_path / "reporter.start.json").exists(), 60, what="the node started")
        p.send_signal(signal.SIGINT)
        wait_for(lambda: (tmp_path / "reporter.destroying.json").exists(), 30, what="clean-up began")
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = out.decode(errors="replace")
    assert p.returncode == 0 and "Traceback" not in text, text
    assert (tmp_path / "reporter.clean.json").exists(), text


def test_a_node_runs_on_without_a_stop_signal(ros_env: dict[str, str], tmp_path: Path) -> None:
    """The hard deadline is for a stop that was asked for only: a node with a clean-up time of its own (armed
    after its constructor by mistake once, the deadline ended the cockpit 10 s into a campaign) runs until it
    finishes, past the 6 s a stop would allow it."""
    p = start_reporter(ros_env, tmp_path, finish_after_s=9.0, slow_destroy_s=0.2)
    try:
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = out.decode(errors="replace")
    assert p.returncode == 0 and "most recent call first" not in text, text
    assert (tmp_path / "reporter.clean.json").exists(), text


EXIT_HANG = """
import ctypes
import sys
import time
from pathlib import Path
from bac_common.rosnode import BacNode, run_node

class HangsInAFinalizer:
    def __del__(self):  # runs while the interpreter finalizes (module teardown)
        while True:
            time.sleep(0.05)

class Up(BacNode):
    def __init__(self, **kwargs):
        super().__init__("up", **kwargs)
        self._up = self.create_timer(0.05, self.up)  # up once spinning: a SIGINT in the constructor is an
        # interrupted start

    def up(self):
        self._up.cancel()
        Path(sys.argv[1]).write_text("up")

    def destroy_node(self):
        if sys.argv[2] == "gil_held":  # C code that blocks with the GIL held (an rcl/DDS fini that hangs)
            ctypes.PyDLL("libc.so.6").sleep(60)
        super().destroy_node()

if sys.argv[2] == "finalizer":
    _hangs = HangsInAFinalizer()
elif sys.argv[2] == "after_finalize":  # a C function run by exit() after the interpreter has finalized
    libc = ctypes.CDLL("libc.so.6")
    libc.__cxa_atexit(ctypes.cast(libc.getchar, ctypes.c_void_p), None, None)  # stdin stays open: blocks
sys.exit(run_node(Up, sys.argv[:1]))
"""


@pytest.mark.parametrize("where", ["gil_held", "finalizer", "after_finalize"])
def test_a_hang_in_the_clean_up_or_the_exit_ends_within_the_grace(
    ros_env: dict[str, str], tmp_path: Path, where: str
) -> None:
    """The CI hang of 54c04f0 (imu_ingest ignored SIGINT and then SIGTERM, its log ending with its start line)
    has this shape: run_node returned after a clean stop and the process hung in the interpreter's exit, where
    the watchdog thread can no longer run (daemon threads stop once the interpreter finalizes) and rclpy's
    SIGTERM handler, still installed, keeps SIGTERM from ending it. The same when the clean-up blocks in C code
    that holds the GIL (no Python thread runs). The clean-up and the exit now have a hard deadline: faulthandler
    writes the stacks and exits with 1; after the interpreter has finalized, SIGALRM."""
    marker = tmp_path / "up"
    p = subprocess.Popen(
        [sys.executable, "-c", EXIT_HANG, str(marker), where],
        env=ros_env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        wait_for(marker.exists, 60, what="the node started")
        t0 = time.monotonic()
        p.send_signal(signal.SIGINT)
        wait_for(lambda: p.poll() is not None, 20, what="the process ending without SIGTERM")
        waited = time.monotonic() - t0
        out = p.stdout.read() if p.stdout else b""
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    text = out.decode(errors="replace")
    assert waited < 8.0, f"the process took {waited:.1f} s to end (launcher grace 8 s)\n{text}"
    if where == "finalizer":
        assert p.returncode == 1 and "most recent call first" in text and "__del__" in text, text
    elif where == "gil_held":
        assert p.returncode == 1 and "most recent call first" in text and "destroy_node" in text, text
    else:
        assert p.returncode == -signal.SIGALRM, (p.returncode, text)


STUCK = """
import sys
import time
from pathlib import Path
from bac_common.rosnode import BacNode, run_node

class Stuck(BacNode):
    def __init__(self, **kwargs):
        super().__init__("stuck", **kwargs)
        Path(sys.argv[1]).write_text("constructing")
        while True:  # a constructor that never returns (a C call that hangs; the interrupt swallowed)
            try:
                time.sleep(0.05)
            except KeyboardInterrupt:
                pass

sys.exit(run_node(Stuck, sys.argv[:1]))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_stop_signal_ends_a_node_whatever_hangs(ros_env: dict[str, str], tmp_path: Path, sig: int) -> None:
    """After SIGINT or SIGTERM the process ends within the clean-up time + 1 s (6 s, the launcher's grace is 8 s)
    even if its main thread never comes back (here: a constructor that never returns), with every thread's
    stack in its output, instead of lingering until the launcher's SIGKILL."""
    marker = tmp_path / "constructing"
    p = subprocess.Popen(
        [sys.executable, "-c", STUCK, str(marker)],
        env=ros_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        wait_for(marker.exists, 60, what="the constructor running")
        t0 = time.monotonic()
        p.send_signal(sig)
        out, _ = p.communicate(timeout=30)
        waited = time.monotonic() - t0
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = out.decode(errors="replace")
    assert p.returncode == 1, text
    assert waited < 8.0, f"the process took {waited:.1f} s to end (launcher grace 8 s)\n{text}"
    assert "most recent call first" in text and "__init__" in text, text  # where it hung, for the log


STARTING = """
import sys
import rclpy
from rcl_interfaces.msg import Log
from bac_common.rosnode import BacNode, run_node

class Starting(BacNode):
    def __init__(self, **kwargs):
        super().__init__("starting", **kwargs)
        if sys.argv[1] == "interrupted":
            rclpy.shutdown()  # what rclpy's SIGINT handler does to the context while the constructor runs
        else:
            raise ValueError("a real fault while starting")
        self.create_publisher(Log, "late", 1)

sys.exit(run_node(Starting, sys.argv[:1]))
"""


@pytest.mark.parametrize("case", ["interrupted", "crashed"])
def test_a_stop_while_a_node_is_starting_is_not_a_crash(ros_env: dict[str, str], case: str) -> None:
    """Ctrl-C (or the launcher's stop) while the constructor still runs: rclpy's handler shuts the context down
    under it and its next rcl call fails (an RCLError). That is an interrupted start, exit 0 without a FATAL
    traceback; it was 'node failed to start' and exit 1, seen in CI under load when SIGINT reached a node that
    was still making its publishers. A real fault while starting stays a FATAL exit 1."""
    p = subprocess.run(
        [sys.executable, "-c", STARTING, case], env=ros_env, capture_output=True, text=True, timeout=60, check=False
    )
    text = p.stdout + p.stderr
    if case == "interrupted":
        assert p.returncode == 0, text
        assert "interrupted while starting" in text and "FATAL" not in text, text
    else:
        assert p.returncode == 1, text
        assert "node failed to start" in text and "a real fault while starting" in text, text


WAKEUP_OWNER = """
import os, signal, sys, time
from bac_common.rosnode import StopSignals
r0, w0 = os.pipe()
os.set_blocking(w0, False)
os.set_blocking(r0, False)
signal.set_wakeup_fd(w0)  # someone else's wakeup fd (an asyncio loop)
StopSignals(100).install()
installed = signal.set_wakeup_fd(w0)
f = open(sys.argv[1], "wb")  # takes the lowest free descriptor: the one StopSignals closed
os.kill(os.getpid(), signal.SIGINT)
time.sleep(0.2)
f.close()
print("installed", installed == w0, "owner got", os.read(r0, 10).hex())
"""


def test_install_gives_a_wakeup_fd_back_to_its_owner(ros_env: dict[str, str], tmp_path: Path) -> None:
    """A wakeup fd someone else installed stays theirs: install() set its own write end back after closing it
    (it dropped the old one), so a later signal wrote its byte into whatever file reused that number (a
    journal opened after start-up got b'\\x02', the review's wakeup2.py)."""
    journal = tmp_path / "journal.bin"
    p = subprocess.run(
        [sys.executable, "-c", WAKEUP_OWNER, str(journal)],
        env=ros_env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    assert journal.read_bytes() == b"", p.stdout
    assert "installed True owner got 02" in p.stdout, p.stdout + p.stderr


CONSTRUCTOR_CLEAN_UP = """
import sys
import time
from pathlib import Path
from bac_common.rosnode import BacNode, run_node

class Opening(BacNode):
    def __init__(self, **kwargs):
        super().__init__("opening", **kwargs)
        try:
            Path(sys.argv[1]).write_text("waiting")
            time.sleep(60)  # waiting for the ECU
        finally:  # its own clean-up when interrupted (a journal repaired, a connection closed): 2 s
            Path(sys.argv[1] + ".cleaning").write_text("")
            for _ in range(20):
                time.sleep(0.1)
            Path(sys.argv[1] + ".cleaned").write_text("")

sys.exit(run_node(Opening, sys.argv[:1]))
"""


def test_a_repeated_sigint_does_not_cut_a_constructors_clean_up_short(ros_env: dict[str, str], tmp_path: Path) -> None:
    """While the constructor runs, the first SIGINT raises KeyboardInterrupt to cut its wait short; the launcher's
    repeated SIGINT (every second) raised it again in the constructor's own except/finally clean-up (the review's
    twice.py). Only the first raises now."""
    marker = tmp_path / "opening"
    p = subprocess.Popen(
        [sys.executable, "-c", CONSTRUCTOR_CLEAN_UP, str(marker)],
        env=ros_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        wait_for(marker.exists, 60, what="the constructor waiting")
        p.send_signal(signal.SIGINT)
        wait_for(Path(f"{marker}.cleaning").exists, 30, what="the constructor's clean-up began")
        while p.poll() is None:  # the launcher's repeats
            p.send_signal(signal.SIGINT)
            time.sleep(0.3)
        out = p.stdout.read() if p.stdout else b""
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    text = out.decode(errors="replace")
    assert Path(f"{marker}.cleaned").exists(), text
    assert p.returncode == 0 and "interrupted while starting" in text, text


ARM_CONTENDED = """
import faulthandler, os, signal, sys, threading, time
import bac_common.rosnode as rosnode
from bac_common.rosnode import StopSignals

stop = StopSignals(50.0)
signal.signal(signal.SIGINT, stop._on_signal)
real = faulthandler.dump_traceback_later
holding = threading.Event()

def slow(*args, **kwargs):  # the watcher thread inside arm(), holding its lock for a moment
    if threading.current_thread().name == "watcher":
        holding.set()
        time.sleep(0.5)
    real(*args, **kwargs)

rosnode.faulthandler.dump_traceback_later = slow
t = threading.Thread(target=stop.arm, args=(100.0,), name="watcher")
t.start()
holding.wait(10)
t0 = time.monotonic()
if sys.argv[1] == "later":
    stop.arm(200.0, later=True)  # the main thread: must wait for the watcher, not be dropped
    want = 200.0
else:
    os.kill(os.getpid(), signal.SIGINT)  # the handler: must not block, and must not be dropped either
    time.sleep(0.05)
    want = 50.0
blocked = time.monotonic() - t0
t.join()
left = stop._deadline_at - time.monotonic()
faulthandler.cancel_dump_traceback_later()
signal.alarm(0)
print(f"left {left:.1f} blocked {blocked:.2f}")
assert abs(left - want) < 5.0, (left, want)
if sys.argv[1] == "signal":
    assert blocked < 0.3, blocked
"""


@pytest.mark.parametrize("caller", ["later", "signal"])
def test_an_arm_is_never_dropped_while_another_holds_the_lock(ros_env: dict[str, str], caller: str) -> None:
    """arm() took its lock without blocking from every caller: a later=True arm from the main thread (or the
    signal handler's arm) was dropped silently when the watcher thread held it (the repeated SIGINT wakes the
    watcher every second). Now a thread waits for it; the handler, which must not block (the main thread may
    hold the lock itself), queues its request and the holder applies it."""
    p = subprocess.run(
        [sys.executable, "-c", ARM_CONTENDED, caller],
        env=ros_env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert p.returncode == 0, p.stdout + p.stderr


GROWN_CLEAN_UP = """
import sys
import time
from pathlib import Path
from bac_common.rosnode import BacNode, run_node

class Restoring(BacNode):
    def __init__(self, **kwargs):
        super().__init__("restoring", **kwargs)
        self.restore_s = 0.0
        self.create_timer(0.1, self.up)

    def up(self):  # a runtime parameter raised (the bridge's restore_timeout_s): a longer clean-up
        self.restore_s = 3.0
        Path(sys.argv[1]).write_text("up")

    def cleanup_time_s(self):
        return self.restore_s

    def destroy_node(self):
        time.sleep(2.5)  # the baseline restore: longer than the stop deadline armed before (1 + 1 s)
        Path(sys.argv[1] + ".restored").write_text("")
        super().destroy_node()

sys.exit(run_node(Restoring, sys.argv[:1], cleanup_timeout_s=1.0))
"""


def test_a_clean_up_time_raised_at_runtime_extends_the_stop_deadline(ros_env: dict[str, str], tmp_path: Path) -> None:
    """A node's cleanup_time_s was read once after its constructor: the bridge's comes from runtime parameters,
    and raising one let the hard deadline end the bridge in the middle of the baseline restore (exit 1). The
    clean-up reads it again and extends the deadline when it grew."""
    marker = tmp_path / "up"
    p = subprocess.Popen(
        [sys.executable, "-c", GROWN_CLEAN_UP, str(marker)],
        env=ros_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        wait_for(marker.exists, 60, what="the node up")
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    text = out.decode(errors="replace")
    assert p.returncode == 0 and "most recent call first" not in text, text
    assert Path(f"{marker}.restored").exists(), text


STUCK_IN_C = """
import ctypes
import sys
from pathlib import Path
from bac_common.rosnode import BacNode

class StuckInC(BacNode):
    def __init__(self, **kwargs):
        super().__init__("stuck_in_c", **kwargs)
        libc = ctypes.CDLL("libc.so.6")  # releases the GIL; a futex wait that signals do not interrupt
        mutex = ctypes.create_string_buffer(64)
        libc.pthread_mutex_lock(mutex)
        Path(MARKER).write_text(hex(ctypes.addressof(mutex)))  # the futex the main thread will wait on
        libc.pthread_mutex_lock(mutex)  # a C call that never returns to Python (an rcl/DDS wait)
"""


def _waits_on_futex(pid: int, address: int) -> bool:
    """The process's main thread is in a futex wait on ``address`` (Linux: /proc's syscall line, x86-64's 202)."""
    try:
        fields = Path(f"/proc/{pid}/task/{pid}/syscall").read_text().split()
    except OSError:
        return False
    return len(fields) > 1 and fields[0] == "202" and int(fields[1], 16) == address


@pytest.mark.parametrize("host", ["run_node", "container"])
def test_a_stop_signal_ends_a_process_whose_main_thread_is_stuck_in_c(
    ros_env: dict[str, str], tmp_path: Path, host: str
) -> None:
    """The main thread in C code that never returns to Python never runs a signal's Python handler: the watcher
    thread on the signal wakeup fd arms the hard deadline. The container's process had no watcher (and no SIGTERM
    stack dump): it lived on after SIGINT."""
    marker = tmp_path / "constructing"
    (tmp_path / "stuck_node.py").write_text(f"MARKER = {str(marker)!r}\n" + STUCK_IN_C)
    env = {**ros_env, "PYTHONPATH": f"{tmp_path}:{ros_env.get('PYTHONPATH', '')}"}
    if host == "run_node":
        cmd = [
            sys.executable,
            "-c",
            "import sys, stuck_node, bac_common.rosnode as r; sys.exit(r.run_node(stuck_node.StuckInC, sys.argv[:1]))",
        ]
    else:
        from bac_bringup.container import ContainedNode, write_spec

        node = ContainedNode("stuck_in_c", "stuck_node:StuckInC", ("--ros-args", "-r", "__node:=stuck_in_c"))
        spec = write_spec(tmp_path / "spec.json", "stuck", [node], 1.0)
        cmd = [sys.executable, "-m", "bac_bringup.container", str(spec)]
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(marker.exists, 60, what="the constructor running")
        wait_for(lambda: _waits_on_futex(p.pid, int(marker.read_text(), 16)), 30, what="the main thread in the C call")
        t0 = time.monotonic()
        p.send_signal(signal.SIGINT)
        try:
            out, _ = p.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            out = b""
        waited = time.monotonic() - t0
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    text = out.decode(errors="replace")
    assert p.returncode == 1, (p.returncode, text)
    assert waited < 8.0, f"the process took {waited:.1f} s to end (launcher grace 8 s)\n{text}"
    assert "most recent call first" in text and "__init__" in text, text


def test_spin_until_done_keeps_a_code_set_just_before_the_stop() -> None:
    """A worker thread sets exit_code, then the stop becomes true before the loop looks at the node again: the
    code was lost (0)."""
    from bac_common.rosnode import spin_until_done

    class Node:
        exit_code: int | None = None

    node = Node()
    stopped = []

    class Context:
        def ok(self) -> bool:
            return True

    class Executor:
        context = Context()

        def spin_once(self, timeout_sec: float) -> None:
            # the node's code and the stop land together; the first look at the node comes after the stop check
            stopped.append(True)

    def stop() -> bool:
        if stopped:
            node.exit_code = 3
            return True
        return False

    assert spin_until_done(Executor(), [node], stop=stop) == 3  # type: ignore[arg-type]


FAILS_AFTER_STOP = """
import os
import signal
import sys
import time
import bac_common.rosnode as r
from bac_common.rosnode import BacNode, run_node

class Up(BacNode):
    def __init__(self, **kwargs):
        super().__init__("up", **kwargs)
        if sys.argv[1] != "none":
            self.exit_code = int(sys.argv[1])

def spin_then_fail(executor, nodes, poll_s=0.1, stop=None):
    # a spin turn that fails once the stop was asked for (the context shut down under it): Ctrl-C, then the error
    os.kill(os.getpid(), signal.SIGINT)
    deadline = time.monotonic() + 20
    while not stop() and time.monotonic() < deadline:
        time.sleep(0.01)
    if sys.argv[2:] == ["rcl"]:  # what rclpy raises when the context is shut down under a callback
        from rclpy._rclpy_pybind11 import RCLError
        raise RCLError("failed to create guard condition: the given context is not valid, either because it was "
                       "never initialized or it was already shutdown, at ./src/rcl/guard_condition.c:67")
    raise RuntimeError("the context went away under the spin" if stop() else "no stop seen")

r.spin_until_done = spin_then_fail
sys.exit(run_node(Up, sys.argv[:1]))
"""


@pytest.mark.parametrize("exit_code", ["none", "3"])
def test_an_error_after_the_stop_was_asked_for_is_logged_not_a_crash(ros_env: dict[str, str], exit_code: str) -> None:
    """A running node whose spin fails after Ctrl-C (rclpy's handler shut the context down under it) stopped as
    asked: the error is logged as such, and the exit code is the node's own (0 when it set none), not a crash's 1
    (which the launcher would report as a failed stop)."""
    p = subprocess.Popen(
        [sys.executable, "-c", FAILS_AFTER_STOP, exit_code],
        env=ros_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    text = out.decode(errors="replace")
    assert p.returncode == (0 if exit_code == "none" else 3), (p.returncode, text)
    assert "an error after the stop was asked for" in text and "the context went away under the spin" in text, text
    assert "node crashed" not in text, text


def test_the_context_shut_down_under_a_callback_while_stopping_is_no_error(ros_env: dict[str, str]) -> None:
    """rclpy's 'context is not valid' after the stop was asked for is the stop itself, not a fault: one INFO line,
    no ERROR and no traceback (clean stops logged an RCLError traceback now and then, 2026-11-28)."""
    p = subprocess.run([sys.executable, "-c", FAILS_AFTER_STOP, "none", "rcl"], env=ros_env, capture_output=True,
                       text=True, timeout=60, check=False, start_new_session=True)  # fmt: skip
    text = p.stdout + p.stderr
    assert p.returncode == 0, text
    assert "the context was shut down under a callback while stopping" in text, text
    assert "ERROR" not in text and "Traceback" not in text, text
