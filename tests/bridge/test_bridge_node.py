"""The ecu_bridge node in a real process, the simulated ECU in another, CAN over udp_multicast.

pytest runs inside a private network namespace (scripts/pytest.sh, make test),
so the multicast frames never leave the machine.
"""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from bridge_rig import CALIBRATIONS, load

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.dbc import shipped_dbc
from bac_ecu_bridge.errors import ErrorCode
from bac_ecu_bridge.protocol import CalibrationCodec
from bac_ecu_bridge.trace import decode_trace, load_database

from conftest import Procs, RosHarness, wait_for

pytestmark = pytest.mark.integration

II = load("controller_ii")
CODEC = CalibrationCodec(II)
_PORTS = iter(range(43200, 43400))


@pytest.fixture(autouse=True)
def _netns(in_private_netns: bool) -> None:
    if not in_private_netns:
        pytest.skip("udp_multicast CAN only inside a private network namespace: run scripts/pytest.sh")


@pytest.fixture
def can_link() -> tuple[str, int]:
    """A multicast group and UDP port of this test alone."""
    port = next(_PORTS)
    return f"239.74.{port % 250}.{1 + port % 200}", port


def ramp(offset: float = 0.0) -> dict[str, float]:
    return {p.name: 10.0 + 47.123 * k + offset for k, p in enumerate(II.parameters)}


def start_ecu(
    procs: Procs, link: tuple[str, int], name: str = "ecu", definition: Path | None = None, *extra: str
) -> subprocess.Popen[bytes]:
    group, port = link
    p = procs.python(
        name,
        [
            "-m",
            "bac_sim.ecu",
            "--interface",
            "udp_multicast",
            "--channel",
            group,
            "--port",
            str(port),
            "--definition",
            str(definition or CALIBRATIONS / "controller_ii.yaml"),
            *extra,
        ],
    )
    wait_for(lambda: "ECU ready" in procs.log(name) or p.poll() is not None, 20, what=f"{name} to start")
    assert p.poll() is None, procs.log(name)
    return p


def stop(p: subprocess.Popen[bytes]) -> int:
    os.killpg(p.pid, signal.SIGINT)
    return p.wait(timeout=15)


def start_bridge(procs: Procs, link: tuple[str, int], name: str = "bridge", *params: str) -> subprocess.Popen[bytes]:
    group, port = link
    args = [
        "-m",
        "bac_ecu_bridge.bridge_node",
        "--ros-args",
        "-p",
        f"definition_file:={CALIBRATIONS / 'controller_ii.yaml'}",
        "-p",
        "can.interface:=udp_multicast",
        "-p",
        f"can.channel:={group}",
        "-p",
        f"can.port:={port}",
        "-p",
        "step_timeout_s:=0.02",
        "-p",
        "diagnostics_period_s:=0.5",
    ]
    for prm in params:
        args += ["-p", prm]
    return procs.python(name, args)


class BridgeCaller:
    """Service clients of the ecu_bridge node, in the test process."""

    def __init__(self, ros: RosHarness) -> None:
        from std_srvs.srv import Trigger

        from bac_msgs.srv import ApplyCalibration, ReadCalibration

        self.node = ros.node("bridge_test_client")
        self.apply_cli = self.node.create_client(ApplyCalibration, "ecu_bridge/apply_calibration")
        self.read_cli = self.node.create_client(ReadCalibration, "ecu_bridge/read_calibration")
        self.restore_cli = self.node.create_client(Trigger, "ecu_bridge/restore_baseline")
        self.ApplyCalibration = ApplyCalibration

    def wait_ready(self) -> None:
        for cli in (self.apply_cli, self.read_cli, self.restore_cli):
            wait_for(lambda c=cli: c.service_is_ready(), 30, what=f"service {cli.srv_name}")
        self.handshake()

    def handshake(self, timeout: float = 30.0) -> None:
        """Wait until an answer of ``apply_calibration`` reaches this client.

        ``service_is_ready`` says the bridge's request reader is matched, not that its response writer has matched
        this client's reader; Fast DDS drops a response sent before (rmw_fastrtps: "failed to send response
        (timeout): client will not receive response"), and under load that window can outlast the first apply.
        A request the bridge refuses before it touches the bus (an unknown name) is asked until one answer comes.
        """
        req = self.ApplyCalibration.Request()
        req.calibration.names = ["__handshake__"]
        req.calibration.values = [0.0]
        deadline = time.monotonic() + timeout
        futures = []  # every request stays awaited: a slow answer to an earlier one counts as well
        while True:
            futures.append(self.apply_cli.call_async(req))
            end = time.monotonic() + 2.0
            while not any(f.done() for f in futures) and time.monotonic() < end:
                time.sleep(0.02)
            done = [f for f in futures if f.done()]
            if done:
                resp = done[0].result()
                assert resp is not None and resp.error_code == ErrorCode.UNKNOWN_PARAMETER, resp
                return
            if time.monotonic() > deadline:
                pytest.fail(f"no answer of {self.apply_cli.srv_name} reached the test client in {timeout} s")

    def call(self, cli: Any, req: Any, timeout: float = 20.0) -> Any:
        fut = cli.call_async(req)
        wait_for(fut.done, timeout, what=f"an answer of {cli.srv_name}")
        return fut.result()

    def apply(self, values: dict[str, float], trial_id: int = 1, timeout_s: float = 0.0) -> Any:
        req = self.ApplyCalibration.Request()
        req.calibration.trial_id = trial_id
        req.calibration.names = list(values)
        req.calibration.values = [float(v) for v in values.values()]
        req.timeout_s = timeout_s
        return self.call(self.apply_cli, req)

    def apply_raw(self, names: list[str], values: list[float]) -> Any:
        req = self.ApplyCalibration.Request()
        req.calibration.names = names
        req.calibration.values = values
        return self.call(self.apply_cli, req)

    def read(self) -> Any:
        return self.call(self.read_cli, self.read_cli.srv_type.Request())

    def restore(self) -> Any:
        return self.call(self.restore_cli, self.restore_cli.srv_type.Request())


def ecu_commits(log: str) -> list[int]:
    return [int(m, 16) for m in re.findall(r"ECU committed seq=\d+ count=\d+ crc=0x([0-9A-F]{8})", log)]


def test_apply_read_restore_and_shutdown_through_the_node(
    procs: Procs, ros_context: RosHarness, can_link: tuple[str, int], tmp_path: Path
) -> None:
    from diagnostic_msgs.msg import DiagnosticArray

    from bac_common.rosnode import QOS_LATCHED
    from bac_msgs.msg import Calibration

    trace = tmp_path / "apply.log"
    start_ecu(procs, can_link)
    bridge = start_bridge(procs, can_link, "bridge", f"can.trace_file:={trace}")
    caller = BridgeCaller(ros_context)
    diags: list[Any] = []
    caller.node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    caller.wait_ready()

    want = ramp()
    resp = caller.apply(want, trial_id=7)
    assert resp.success, resp.message
    assert resp.error_code == ErrorCode.NONE and resp.attempts == 1
    assert dict(zip(resp.applied.names, resp.applied.values, strict=True)) == CODEC.quantize(want)
    assert resp.applied.trial_id == 7
    assert resp.applied.crc32 == CODEC.crc(want)
    assert 0 < resp.latency_s < 1.0
    assert ecu_commits(procs.log("ecu"))[-1] == CODEC.crc(want)

    # bac/calibration is latched: a late subscriber gets the confirmed calibration
    got: list[Any] = []
    caller.node.create_subscription(Calibration, "bac/calibration", got.append, QOS_LATCHED)
    wait_for(lambda: got, 20, what="bac/calibration")
    assert got[-1].trial_id == 7 and got[-1].crc32 == CODEC.crc(want)

    rd = caller.read()
    assert rd.success and rd.active.crc32 == CODEC.crc(want)
    assert list(rd.active.values) == pytest.approx(list(CODEC.quantize(want).values()))

    def ok_diag() -> Any:
        for arr in diags:
            for st in arr.status:
                if st.level == st.OK and {"key": "ecu", "value": "answering"} in [
                    {"key": kv.key, "value": kv.value} for kv in st.values
                ]:
                    return st
        return None

    st = wait_for(ok_diag, 20, what="an OK diagnostics status with the ECU answering")
    assert st.hardware_id == f"udp_multicast:{can_link[0]}"

    baseline_crc = CODEC.crc(II.baseline_values())
    rs = caller.restore()
    assert rs.success and f"0x{baseline_crc:08X}" in rs.message
    wait_for(
        lambda: got[-1].crc32 == baseline_crc and got[-1].trial_id == 0, 20, what="the baseline on bac/calibration"
    )

    assert caller.apply(ramp(1.0), trial_id=8).success
    # shutting the node down restores the safe baseline
    assert stop(bridge) == 0
    assert ecu_commits(procs.log("ecu"))[-1] == baseline_crc
    assert "shutdown: baseline restored" in procs.log("bridge")

    # the captured trace decodes with the shipped DBC, every frame
    rows = decode_trace(trace, load_database(shipped_dbc("controller_ii")))
    assert rows and all(r.crc_ok for r in rows)
    # 4 applies (2 trials, the restore, the baseline at shutdown), each frame once (or more after a re-send)
    writes = {(r.signals["Seq"], r.signals["Index"]) for r in rows if r.op == "WRITE"}
    assert len(writes) == 4 * 20
    assert len({r.signals["Seq"] for r in rows if r.op == "ACK"}) == 4
    assert any(r.op == "STATUS_OK" for r in rows)
    first_writes = [r for r in rows if r.op == "WRITE"][:20]
    for r in first_writes:
        name = CODEC.by_index[r.signals["Index"]].name
        assert r.signals[f"P_{name}"] == pytest.approx(want[name], abs=0.005 + 1e-9)
    commits = [r for r in rows if r.op == "COMMIT"]
    assert commits[0].signals["CommitCrc32"] == CODEC.crc(want) and commits[0].signals["CommitCount"] == 20


def write_definition(path: Path, definition: CalibrationDefinition, **changes: dict[str, Any]) -> Path:
    data = definition.to_dict()
    for p in data["parameters"]:
        p.update(changes.get(p["name"], {}))
    path.write_text(yaml.safe_dump(data))
    return path


def test_each_negative_reason_surfaces_as_a_service_error(
    procs: Procs, ros_context: RosHarness, can_link: tuple[str, int], tmp_path: Path
) -> None:
    group, port = can_link
    start_bridge(procs, can_link, "bridge", "step_retries:=2", "max_attempts:=2", "poll_ecu:=false")
    caller = BridgeCaller(ros_context)
    caller.wait_ready()
    # the bridge reads the ECU first (there is none yet): the bus is quiet once that is over
    wait_for(lambda: "start: could not read the ECU" in procs.log("bridge"), 30, what="the check at start")
    sniffer = can.Bus(interface="udp_multicast", channel=group, port=port, fd=False)
    try:
        # refused before anything is sent
        cases = [
            (["p01"], [1.0, 2.0], ErrorCode.INVALID_REQUEST, "1 names but 2 values"),
            ([p.name for p in II.parameters], [math.nan] + [1.0] * 19, ErrorCode.INVALID_REQUEST, "not a finite"),
            (["p01", "p01"], [1.0, 1.0], ErrorCode.INVALID_REQUEST, "given twice"),
            (["p99"], [1.0], ErrorCode.UNKNOWN_PARAMETER, "unknown parameter 'p99'"),
            ([p.name for p in II.parameters], [500.0] * 19 + [1000.5], ErrorCode.OUT_OF_BOUNDS, "p20"),
        ]
        for names, values, code, text in cases:
            resp = caller.apply_raw(names, values)
            assert not resp.success and resp.error_code == code, resp.message
            assert text in resp.message and "before sending anything" in resp.message
        sniffer.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"marker"))
        seen = []
        while (msg := sniffer.recv(timeout=5)) is not None and msg.arbitration_id != 0x7FF:
            seen.append(msg)
        assert seen == [], "a refused request put frames on the bus"
    finally:
        sniffer.shutdown()

    def ecu_case(name: str, code: ErrorCode, text: str, *ecu_args: str, definition: Path | None = None) -> Any:
        ecu = start_ecu(procs, can_link, name, definition, *ecu_args)
        resp = caller.apply(ramp())
        assert not resp.success and resp.error_code == code, (name, resp.error_code, resp.message)
        assert text in resp.message, resp.message
        return ecu, resp

    ecu, _ = ecu_case(
        "ecu_unknown",
        ErrorCode.UNKNOWN_PARAMETER,
        "does not know parameter p20 (CAN index 19)",
        definition=write_definition(tmp_path / "unknown.yaml", II, p20={"index": 40}),
    )
    stop(ecu)
    ecu, _ = ecu_case(
        "ecu_range",
        ErrorCode.ECU_OUT_OF_RANGE,
        "p12 = 528.35 (CAN index 11) as out of its range",
        definition=write_definition(tmp_path / "range.yaml", II, p12={"upper": 500.0, "nominal": 250.0}),
    )
    stop(ecu)
    ecu, _ = ecu_case("ecu_busy", ErrorCode.ECU_BUSY, "stop the vehicle", "--driving")
    os.killpg(ecu.pid, signal.SIGUSR2)  # the vehicle stops: the same request goes through
    wait_for(lambda: "driving=False" in procs.log("ecu_busy"), 10, what="the ECU to stand")
    assert caller.apply(ramp()).success
    stop(ecu)
    ecu, resp = ecu_case("ecu_crc", ErrorCode.CRC_MISMATCH, "does not match", "--refuse", "commit=crc_mismatch")
    assert resp.attempts == 2  # retried with a new transaction, then reported
    stop(ecu)
    ecu, _ = ecu_case("ecu_seq", ErrorCode.SEQUENCE, "sequence error", "--refuse", "commit=sequence")
    stop(ecu)
    assert ecu_commits(procs.log("ecu_crc")) == ecu_commits(procs.log("ecu_seq")) == []
    t0 = time.monotonic()
    ecu, resp = ecu_case("ecu_silent", ErrorCode.TIMEOUT, "no valid answer to BEGIN", "--fault", "silent")
    assert resp.latency_s < 2 * 3 * 0.02 + 1.0 and time.monotonic() - t0 < 15
    stop(ecu)

    # an adapter that is not there: the node runs, reports it, and answers every apply with ERROR_BUS
    start_bridge(
        procs,
        can_link,
        "bridge_nobus",
        "can.interface:=socketcan",
        "can.channel:=bacnope0",
        "restore_baseline_on_shutdown:=false",
    )
    wait_for(lambda: "CAN not open yet" in procs.log("bridge_nobus"), 30, what="the bridge without an adapter")
    ros_context.executor.remove_node(caller.node)
    caller.node.destroy_node()
    ros_context.nodes.remove(caller.node)
    stop(procs.items[0][1])  # the first bridge: the service name must answer from the second one now
    caller = BridgeCaller(ros_context)
    caller.wait_ready()
    resp = caller.apply(ramp())
    assert not resp.success and resp.error_code == ErrorCode.BUS
    assert "cannot open CAN interface socketcan:bacnope0" in resp.message
    rd = caller.read()  # what bo_agent asks before trial 1 (it waits, telling the driver this)
    assert not rd.success and "is the adapter plugged in and 'bacnope0' up" in rd.message


def test_faulty_bus_across_processes_never_acknowledges_falsely(
    procs: Procs, ros_context: RosHarness, can_link: tuple[str, int]
) -> None:
    """The ECU process loses or garbles 30 % of its frames (both ways); 30 applies through the node."""
    start_ecu(procs, can_link, "ecu", None, "--fault", "drop=0.15,corrupt=0.15,duplicate=0.05,reorder=0.05,seed=4")
    start_bridge(
        procs,
        can_link,
        "bridge",
        "step_timeout_s:=0.01",
        "step_retries:=8",
        "default_timeout_s:=2.0",
        "poll_ecu:=false",
        "restore_baseline_on_abort:=false",
    )
    caller = BridgeCaller(ros_context)
    caller.wait_ready()
    successes = false_acks = 0
    for k in range(30):
        want = ramp(1.7 * k)
        resp = caller.apply(want, trial_id=k + 1)
        if not resp.success:
            assert resp.error_code in (ErrorCode.TIMEOUT, ErrorCode.CRC_MISMATCH, ErrorCode.SEQUENCE)
            assert resp.latency_s < 2.0 + 0.5
            continue
        successes += 1
        applied = dict(zip(resp.applied.names, resp.applied.values, strict=True))
        in_ecu = ecu_commits(procs.log("ecu"))
        if applied != CODEC.quantize(want) or not in_ecu or in_ecu[-1] != CODEC.crc(want):
            false_acks += 1
    assert false_acks == 0
    assert successes >= 27


def test_a_shutdown_while_the_vehicle_moves_restores_the_baseline_once_it_stops(
    procs: Procs, ros_context: RosHarness, can_link: tuple[str, int]
) -> None:
    """The agent is killed mid-run: the bridge stops while the ECU refuses calibrations (vehicle moving)."""
    ecu = start_ecu(procs, can_link)
    bridge = start_bridge(procs, can_link, "bridge", "restore_pending_s:=30.0", "restore_retry_s:=0.1")
    caller = BridgeCaller(ros_context)
    caller.wait_ready()
    assert caller.apply(ramp(), trial_id=4).success
    os.killpg(ecu.pid, signal.SIGUSR1)  # the car drives the run
    wait_for(lambda: "driving=True" in procs.log("ecu"), 10, what="the ECU to drive")
    os.killpg(bridge.pid, signal.SIGINT)  # the graph stops mid-run
    wait_for(lambda: "BASELINE RESTORE PENDING" in procs.log("bridge"), 20, what="the pending restore")
    assert "trial 4's calibration" in procs.log("bridge") and "STOP THE VEHICLE" in procs.log("bridge")
    assert bridge.poll() is None  # still there, retrying
    os.killpg(ecu.pid, signal.SIGUSR2)  # the car stops
    assert bridge.wait(timeout=20) == 0
    assert "went through" in procs.log("bridge")
    assert ecu_commits(procs.log("ecu"))[-1] == CODEC.crc(II.baseline_values())
    stop(ecu)
