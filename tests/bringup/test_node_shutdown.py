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
