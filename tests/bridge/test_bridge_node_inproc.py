"""The ecu_bridge node in-process (rclpy, real topics and services) with the simulated ECU on a virtual bus."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from bridge_rig import CALIBRATIONS, ROOT, load

from bac_common.paramspace import CalibrationDefinition, MetaParameter, uniform_parameters
from bac_ecu_bridge.errors import ErrorCode
from bac_ecu_bridge.protocol import CalibrationCodec, Commit, decode_request
from bac_sim.ecu import SimulatedEcu

from conftest import RosHarness, wait_for

pytestmark = pytest.mark.integration

_CHANNELS = itertools.count()


def params_of(profile: str) -> dict[str, Any]:
    """The profile's ecu_bridge parameters as ROS reads the file: nested mappings are dotted names."""
    data = yaml.safe_load((ROOT / "ros_ws" / "params" / f"{profile}.yaml").read_text())

    def flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    return flat(data["ecu_bridge"]["ros__parameters"])


class InProc:
    def __init__(self, ros: RosHarness, definition: Path, **params: Any) -> None:
        from rclpy.parameter import Parameter

        from bac_ecu_bridge.bridge_node import EcuBridgeNode

        self.channel = f"node-inproc-{next(_CHANNELS)}"
        self.ecu_bus = can.Bus(interface="virtual", channel=self.channel)
        self.ecu = SimulatedEcu(self.ecu_bus, CalibrationDefinition.load(definition))
        self.ecu.start()
        overrides = {
            "definition_file": str(definition),
            "can.interface": "virtual",
            "can.channel": self.channel,
            "diagnostics_period_s": 0.1,
            **params,
        }
        self.node = EcuBridgeNode(
            context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()]
        )
        ros.add(self.node)
        self.ros = ros
        self.client_node = ros.node("inproc_client")

    def call(self, srv_type: Any, name: str, request: Any) -> Any:
        cli = self.client_node.create_client(srv_type, name)
        wait_for(cli.service_is_ready, 20, what=name)
        fut = cli.call_async(request)
        wait_for(fut.done, 20, what=f"answer of {name}")
        return fut.result()

    def apply(self, values: dict[str, float], trial_id: int = 1) -> Any:
        from bac_msgs.srv import ApplyCalibration

        req = ApplyCalibration.Request()
        req.calibration.trial_id = trial_id
        req.calibration.names = list(values)
        req.calibration.values = [float(v) for v in values.values()]
        return self.call(ApplyCalibration, "ecu_bridge/apply_calibration", req)

    def close(self) -> None:
        self.ecu.stop()
        self.ecu_bus.shutdown()


@pytest.fixture
def inproc(ros_context: RosHarness) -> Any:
    made: list[InProc] = []

    def make(definition: Path = CALIBRATIONS / "controller_i.yaml", **params: Any) -> InProc:
        rig = InProc(ros_context, definition, **params)
        made.append(rig)
        return rig

    yield make
    for rig in made:
        rig.node.close()
        rig.close()


@pytest.mark.parametrize("profile", ["sim", "car"])
def test_the_profiles_parameters_are_accepted(inproc: Any, profile: str) -> None:
    rig = inproc(**params_of(profile))
    for k, v in params_of(profile).items():
        assert rig.node.get_parameter(k).value == v
    assert rig.apply({"damping_front": 0.1, "damping_rear": 0.2}).success


def test_meta_parameters_are_expanded_to_the_raw_set(inproc: Any, tmp_path: Path) -> None:
    definition = CalibrationDefinition(
        "reduced",
        uniform_parameters("p", 4, 0.0, 1000.0, 500.0, 0.01),
        tuned=("m1", "p04"),
        meta=(MetaParameter("m1", ("p01", "p02"), 0.0, 1.0),),
        fixed={"p03": 123.0},
    )
    path = tmp_path / "reduced.yaml"
    definition.save(path)
    rig = inproc(path)
    resp = rig.apply({"m1": 0.25, "p04": 42.0}, trial_id=3)
    assert resp.success, resp.message
    applied = dict(zip(resp.applied.names, resp.applied.values, strict=True))
    assert applied == {"p01": 250.0, "p02": 250.0, "p03": 123.0, "p04": 42.0}
    assert rig.ecu.active == applied
    assert resp.applied.crc32 == CalibrationCodec(definition).crc(applied)


def test_an_apply_that_leaves_the_ecu_on_another_calibration_restores_the_baseline(inproc: Any) -> None:
    from bac_common.rosnode import QOS_LATCHED
    from bac_msgs.msg import Calibration

    rig = inproc(step_timeout_s=0.02, step_retries=1, max_attempts=1)
    want = {"damping_front": 0.1, "damping_rear": 0.9}
    codec = CalibrationCodec(load("controller_i"))
    target = codec.crc(want)
    engine = rig.ecu.engine
    honest = engine.handle

    def garbled_and_silent(data: bytes) -> list[bytes]:  # applies something else than asked, never acknowledges
        out = honest(data)
        req = decode_request(data)
        if isinstance(req, Commit) and req.crc == target:
            engine.active = {**engine.active, 0: engine.active[0] + 7}
            return []
        return out

    engine.handle = garbled_and_silent  # type: ignore[method-assign]
    got: list[Any] = []
    rig.client_node.create_subscription(Calibration, "bac/calibration", got.append, QOS_LATCHED)
    resp = rig.apply(want, trial_id=5)
    assert not resp.success and resp.error_code == ErrorCode.TIMEOUT
    assert "neither the requested, the previous nor the baseline" in resp.message  # settled by reading back
    assert "safe baseline was restored" in resp.message
    assert rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}
    wait_for(lambda: got and got[-1].trial_id == 0, 10, what="the restored baseline on bac/calibration")
    assert got[-1].crc32 == codec.crc(load("controller_i").baseline_values())


def diag_status(rig: InProc, seen: list[Any], level: int, text: str) -> Any:
    def find() -> Any:
        for arr in reversed(seen):
            for st in arr.status:
                if st.level == level and text in st.message:
                    return st
        return None

    return wait_for(find, 20, what=f"a diagnostics status of level {level} saying '{text}'")


def test_diagnostics_report_a_silent_ecu_and_a_calibration_changed_behind_our_back(inproc: Any) -> None:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    rig = inproc()
    seen: list[Any] = []
    rig.client_node.create_subscription(DiagnosticArray, "/diagnostics", seen.append, 10)
    diag_status(rig, seen, DiagnosticStatus.OK, "ECU answering")
    assert rig.apply({"damping_front": 0.3, "damping_rear": 0.3}).success
    rig.ecu.reset()  # a power cycle: the ECU is on its baseline again, the bridge confirmed something else
    st = diag_status(rig, seen, DiagnosticStatus.WARN, "differs from the last one confirmed")
    values = {kv.key: kv.value for kv in st.values}
    assert values["applies_ok"] == "1" and values["interface"] == "virtual"
    rig.ecu.stop()  # the ECU goes quiet
    diag_status(rig, seen, DiagnosticStatus.ERROR, "ECU not answering")


def test_read_and_restore_services(inproc: Any) -> None:
    from std_srvs.srv import Trigger

    from bac_msgs.srv import ReadCalibration

    rig = inproc()
    assert rig.apply({"damping_front": 0.7, "damping_rear": 0.2}).success
    rd = rig.call(ReadCalibration, "ecu_bridge/read_calibration", ReadCalibration.Request())
    assert rd.success and list(rd.active.names) == ["damping_front", "damping_rear"]
    assert list(rd.active.values) == pytest.approx([0.7, 0.2])
    rig.ecu.set_driving(True)
    rs = rig.call(Trigger, "ecu_bridge/restore_baseline", Trigger.Request())
    assert not rs.success and "ECU_BUSY" in rs.message
    rig.ecu.set_driving(False)
    rs = rig.call(Trigger, "ecu_bridge/restore_baseline", Trigger.Request())
    assert rs.success and rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}


def test_at_start_the_bridge_restores_a_calibration_left_on_the_ecu(ros_context: RosHarness) -> None:
    from bac_common.rosnode import QOS_LATCHED
    from bac_msgs.msg import Calibration

    rig = InProc.__new__(InProc)
    # the ECU still holds a trial's calibration (the last campaign was killed mid-run)
    left = {"damping_front": 0.9, "damping_rear": 0.1}
    made = _start_with_ecu(ros_context, rig, initial=left)
    try:
        assert rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}  # restored before anything else
        got: list[Any] = []
        rig.client_node.create_subscription(Calibration, "bac/calibration", got.append, QOS_LATCHED)
        wait_for(lambda: got and got[-1].trial_id == 0, 10, what="the restored baseline on bac/calibration")
        assert "other than the baseline" in rig.node.core.start_report
    finally:
        made()


def test_at_start_a_busy_ecu_keeps_the_restore_pending_on_diagnostics_until_it_goes_through(
    ros_context: RosHarness,
) -> None:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    rig = InProc.__new__(InProc)
    made = _start_with_ecu(ros_context, rig, initial={"damping_front": 0.9, "damping_rear": 0.1}, driving=True)
    try:
        seen: list[Any] = []
        rig.client_node.create_subscription(DiagnosticArray, "/diagnostics", seen.append, 10)
        st = diag_status(rig, seen, DiagnosticStatus.ERROR, "BASELINE RESTORE PENDING")
        assert "STOP THE VEHICLE" in st.message
        assert rig.ecu.active == {"damping_front": 0.9, "damping_rear": 0.1}
        rig.ecu.set_driving(False)
        wait_for(lambda: rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}, 10, what="the restore")
        diag_status(rig, seen, DiagnosticStatus.OK, "ECU answering")
    finally:
        made()


def test_a_shutdown_restore_refused_while_driving_waits_for_the_vehicle_to_stop(inproc: Any) -> None:
    import threading

    rig = inproc(restore_pending_s=20.0, restore_retry_s=0.05)
    assert rig.apply({"damping_front": 0.2, "damping_rear": 0.8}, trial_id=6).success
    rig.ecu.set_driving(True)
    closing = threading.Thread(target=rig.node.close)
    closing.start()
    wait_for(lambda: rig.node.core.pending is not None and rig.node.core.pending.tries >= 2, 10, what="retries")
    assert rig.ecu.active == {"damping_front": 0.2, "damping_rear": 0.8}
    rig.ecu.set_driving(False)
    closing.join(timeout=10)
    assert not closing.is_alive()
    assert rig.ecu.active == {"damping_front": 0.5, "damping_rear": 0.5}


def _start_with_ecu(ros: RosHarness, rig: InProc, initial: dict[str, float], driving: bool = False) -> Any:
    """Like InProc, but the ECU starts on ``initial`` (and moving when ``driving``) before the node exists."""
    from rclpy.parameter import Parameter

    from bac_ecu_bridge.bridge_node import EcuBridgeNode

    definition = CALIBRATIONS / "controller_i.yaml"
    rig.channel = f"node-inproc-{next(_CHANNELS)}"
    rig.ecu_bus = can.Bus(interface="virtual", channel=rig.channel)
    rig.ecu = SimulatedEcu(rig.ecu_bus, CalibrationDefinition.load(definition), initial=initial)
    rig.ecu.set_driving(driving)
    rig.ecu.start()
    overrides = {
        "definition_file": str(definition),
        "can.interface": "virtual",
        "can.channel": rig.channel,
        "diagnostics_period_s": 0.1,
        "restore_pending_s": 0.5,
    }
    rig.node = EcuBridgeNode(
        context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()]
    )
    ros.add(rig.node)
    rig.ros = ros
    rig.client_node = ros.node(f"inproc_client_{rig.channel.replace('-', '_')}")

    def close() -> None:
        rig.ecu.set_driving(False)
        rig.node.close()
        rig.close()

    return close


def test_xcp_reads_back_by_its_own_parameter_not_the_bac_protocols(inproc: Any) -> None:
    """The bac protocol's verify_readback (on in the profiles) does not turn on XCP's full read-back, which the
    ECU's CRC-32 makes redundant and which costs some 14 answered commands per 80 bytes on a lossy bus."""
    assert inproc(verify_readback=True).node._xcp_config().verify_readback is False
    assert inproc(**{"xcp.verify_readback": True}).node._xcp_config().verify_readback is True
