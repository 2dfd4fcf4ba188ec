"""``python -m bac_ecu_bridge`` and ``python -m bac_sim.ecu`` from a shell."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import can
import pytest
from bridge_rig import CALIBRATIONS, load

from bac_ecu_bridge.canbus import TracedBus
from bac_ecu_bridge.cli import main
from bac_ecu_bridge.client import CalibrationClient
from bac_ecu_bridge.dbc import shipped_dbc
from bac_ecu_bridge.protocol import CalibrationCodec
from bac_sim.ecu import SimulatedEcu

from conftest import Procs, wait_for


def test_dbc_command_writes_the_shipped_file(tmp_path: Path) -> None:
    out = tmp_path / "c2.dbc"
    assert main(["dbc", "--definition", "controller_ii", "-o", str(out)]) == 0
    assert out.read_text() == shipped_dbc("controller_ii").read_text()
    assert main(["dbc", "--definition", str(CALIBRATIONS / "controller_i.yaml"), "--request-id", "0x100"]) == 0


def test_decode_command_prints_the_frames_of_a_trace(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = load("controller_i")
    ecu_bus = can.Bus(interface="virtual", channel="cli-decode")
    ecu = SimulatedEcu(ecu_bus, d)
    ecu.start()
    trace = tmp_path / "t.asc"
    bus = TracedBus(can.Bus(interface="virtual", channel="cli-decode"), trace)
    try:
        CalibrationClient(bus, CalibrationCodec(d)).apply({"damping_front": 0.25, "damping_rear": 0.75})
    finally:
        bus.shutdown()
        ecu.stop()
        ecu_bus.shutdown()
    capsys.readouterr()
    assert main(["decode", str(trace), "--dbc", str(shipped_dbc("controller_i"))]) == 0
    out = capsys.readouterr()
    lines = out.out.splitlines()
    assert len(lines) >= 12
    assert any("-> WRITE" in ln and "P_damping_rear=0.75" in ln for ln in lines)
    assert any("<- ACK" in ln for ln in lines)
    assert "0 with a CRC-8 mismatch" in out.err
    assert main(["decode", str(tmp_path / "missing.log"), "--definition", "controller_i"]) == 9


def test_refusals_before_sending_have_their_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    common = ["--definition", "controller_i", "--interface", "virtual", "--channel", "cli-refuse"]
    assert main(["apply", *common, "damping_front=1.5", "damping_rear=0.5"]) == 1
    assert "OUT_OF_BOUNDS" in capsys.readouterr().err
    assert main(["apply", *common, "damping_side=0.5"]) == 2
    assert main(["apply", *common, "damping_front"]) == 9


@pytest.mark.integration
def test_apply_read_status_restore_against_an_ecu_process(
    procs: Procs, in_private_netns: bool, ros_env: dict[str, str]
) -> None:
    if not in_private_netns:
        pytest.skip("udp_multicast only inside a private network namespace: run scripts/pytest.sh")
    group, port = "239.74.99.7", "43555"
    ecu = procs.python(
        "ecu",
        ["-m", "bac_sim.ecu", "--interface", "udp_multicast", "--channel", group, "--port", port, "--definition",
         str(CALIBRATIONS / "controller_i.yaml")],
    )  # fmt: skip
    wait_for(lambda: "ECU ready" in procs.log("ecu"), 20, what="the ECU")
    bus = ["--definition", "controller_i", "--interface", "udp_multicast", "--channel", group, "--port", port]

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "bac_ecu_bridge", *args],
            check=False,
            capture_output=True,
            text=True,
            timeout=60,
            env=ros_env,
        )

    r = cli("apply", *bus, "damping_front=0.3", "damping_rear=0.61234")
    assert r.returncode == 0, r.stderr
    assert "damping_rear = 0.6123" in r.stdout and "read back: True" in r.stderr
    r = cli("read", *bus)
    assert r.returncode == 0 and "damping_front = 0.3" in r.stdout
    r = cli("status", *bus)
    assert r.returncode == 0 and "2 parameters" in r.stdout
    os.killpg(ecu.pid, signal.SIGUSR1)  # the vehicle moves
    wait_for(lambda: "driving=True" in procs.log("ecu"), 10, what="the ECU to drive")
    r = cli("restore", *bus)
    assert r.returncode == 4 and "ECU_BUSY" in r.stderr
    os.killpg(ecu.pid, signal.SIGUSR2)
    wait_for(lambda: "driving=False" in procs.log("ecu"), 10, what="the ECU to stand")
    r = cli("restore", *bus)
    assert r.returncode == 0 and "damping_front = 0.5" in r.stdout
    os.killpg(ecu.pid, signal.SIGTERM)
    assert ecu.wait(timeout=10) == 0
    assert "ECU stopped after 2 commits" in procs.log("ecu")
    r = cli("status", *bus, "--timeout", "0.3")
    assert r.returncode == 7 and "TIMEOUT" in r.stderr


def test_simulated_ecu_process_refuses_a_bad_definition(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nparameters: []\n")
    r = subprocess.run(
        [sys.executable, "-m", "bac_sim.ecu", "--interface", "virtual", "--channel", "x", "--definition", str(bad)],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "declares no parameters" in r.stderr
