"""The ``ecu_bridge`` node: writes calibrations to the ECU over CAN and says when the ECU confirmed them.

Services (names in :mod:`bac_common.contracts`):

* ``ecu_bridge/apply_calibration`` (bac_msgs/srv/ApplyCalibration): the
  request names the definition's tuned dimensions (raw or meta-parameters; or
  every raw parameter); the bridge expands them to the full raw set, refuses
  anything malformed, unknown or outside the declared bounds before sending,
  writes, commits with a CRC over the whole set and answers success only when
  the ECU acknowledged exactly those values (and read them back). Bounded in
  time: ``step_timeout_s`` per step, ``step_retries`` re-sends,
  ``max_attempts`` transactions, the request's ``timeout_s`` (0 = ``default_timeout_s``).
* ``ecu_bridge/read_calibration`` (bac_msgs/srv/ReadCalibration): the active calibration, read back.
* ``ecu_bridge/restore_baseline`` (std_srvs/srv/Trigger): write the definition's safe baseline.

Topics: ``bac/calibration`` (bac_msgs/Calibration, latched) each time the ECU
confirms a calibration; ``/diagnostics`` (bus and ECU health, every
``diagnostics_period_s``).

The decisions live in :class:`bac_ecu_bridge.core.BridgeCore` (plain Python):
the ECU is read at start and a calibration other than the baseline is restored
or reported before anything else; a failed apply reports what the ECU holds
(read back when the outcome was uncertain) and restores the baseline when it
holds anything else (``restore_baseline_on_abort``); the baseline is restored
on shutdown (``restore_baseline_on_shutdown``), and a restore the ECU refuses
(busy: the vehicle moves) stays pending and is retried until it goes through
(``restore_pending_s``), with an ERROR on ``/diagnostics`` and in the log.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Mapping
from typing import Any

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from std_srvs.srv import Trigger

from bac_common.contracts import (
    SRV_APPLY_CALIBRATION,
    SRV_READ_CALIBRATION,
    SRV_RESTORE_BASELINE,
    TOPIC_CALIBRATION,
    TOPIC_DIAGNOSTICS,
)
from bac_common.errors import BacError, DefinitionError, OutOfBoundsError, UnknownParameterError
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition
from bac_common.rosnode import QOS_LATCHED, BacNode, run_node
from bac_ecu_bridge.backend import ApplyResult, CalibrationBackend, EcuStatus, ReadResult
from bac_ecu_bridge.canbus import BusSettings, TracedBus, open_bus
from bac_ecu_bridge.client import CalibrationClient, ClientConfig
from bac_ecu_bridge.core import BridgeCore
from bac_ecu_bridge.errors import BridgeError, BusError, ErrorCode, InvalidRequestError
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.protocol import DEFAULT_REQUEST_ID, DEFAULT_RESPONSE_ID, CalibrationCodec, CanIds, resolve_request
from bac_ecu_bridge.xcp.client import XcpCalibrationClient, XcpConfig, XcpSettings
from bac_msgs.msg import Calibration
from bac_msgs.srv import ApplyCalibration, ReadCalibration

MAX_CAN_ID = 0x1FFF_FFFF


class EcuBridgeNode(BacNode):
    """The ECU bridge (see the module docstring and docs/ecu_bridge.md)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("ecu_bridge", **kwargs)
        self.protocol = self.declare_str(
            "protocol",
            "bac",
            "the ECU's calibration protocol: bac (bac's own, docs/ecu_bridge.md section 1) or xcp (ASAM XCP on CAN, "
            "the definition's parameters carrying their A2L addresses)",
            choices=("bac", "xcp"),
            read_only=True,
        )
        definition_file = self.declare_str(
            "definition_file",
            "controller_i",
            "calibration definition (YAML path, or the name of a shipped definition)",
            read_only=True,
        )
        self.settings = BusSettings(
            interface=self.declare_str(
                "can.interface",
                "virtual",
                "python-can interface: virtual (one process), udp_multicast (between processes, private network "
                "namespace only), socketcan, pcan, kvaser, vector, ixxat, slcan, gs_usb, ...",
                read_only=True,
            ),
            channel=self.declare_str(
                "can.channel", "bac", "python-can channel (can0, PCAN_USBBUS1, 0, a multicast group)", read_only=True
            ),
            bitrate=self.declare_int(
                "can.bitrate",
                500_000,
                "bit rate, bit/s (classic CAN; socketcan: set with ip link)",
                10_000,
                1_000_000,
                read_only=True,
            ),
            receive_own_messages=self.declare_bool(
                "can.receive_own_messages",
                False,
                "python-can receive_own_messages (not on udp_multicast)",
                read_only=True,
            ),
            port=self.declare_int(
                "can.port", 0, "udp_multicast UDP port (0 = python-can's default)", 0, 65535, read_only=True
            ),
        )
        self.ids = CanIds(
            self.declare_int(
                "can.request_id",
                DEFAULT_REQUEST_ID,
                "CAN id of the requests (laptop -> ECU)",
                0,
                MAX_CAN_ID,
                read_only=True,
            ),
            self.declare_int(
                "can.response_id",
                DEFAULT_RESPONSE_ID,
                "CAN id of the ECU's responses",
                0,
                MAX_CAN_ID,
                read_only=True,
            ),
            self.declare_bool("can.extended_id", False, "29-bit CAN identifiers", read_only=True),
        )
        xcp_overrides = {
            "can_id_master": self.declare_int(
                "xcp.can_id_master",
                -1,
                "XCP: CAN id of the commands (bridge -> ECU, the A2L's CAN_ID_MASTER); -1 = the definition's, "
                "else 0x7E0",
                -1,
                MAX_CAN_ID,
                read_only=True,
            ),
            "can_id_slave": self.declare_int(
                "xcp.can_id_slave",
                -1,
                "XCP: CAN id of the ECU's responses (CAN_ID_SLAVE); -1 = the definition's, else 0x7E1",
                -1,
                MAX_CAN_ID,
                read_only=True,
            ),
            "pages": self.declare_str(
                "xcp.pages",
                "auto",
                "XCP: the calibration segment has a reference and a working page (true), one page (false), or as "
                "the definition says (auto; default true)",
                choices=("auto", "true", "false"),
                read_only=True,
            ),
            "key_algorithm": self.declare_str(
                "xcp.key_algorithm",
                "",
                "XCP seed & key: xor:<hex secret>, or module.path:function(resource, seed) -> key; '' = the "
                "definition's (none)",
                read_only=True,
            ),
        }
        self.declare_float(
            "xcp.step_timeout_s",
            0.01,
            "XCP's T1: wait for one response of the ECU, s (each lost frame costs one; raise it for an ECU whose XCP "
            "driver answers in a slow task)",
            0.001,
            5.0,
        )
        self.declare_float("xcp.t7_s", 0.02, "XCP t7: wait before repeating a command the ECU found busy, s", 0.0, 5.0)
        self.declare_float(
            "xcp.settle_s",
            0.02,
            "XCP: the bus's worst frame delay: after an anomaly (a timeout, a late or duplicated answer) the final "
            "checks wait this long for frames still on the way, s (longer than any frame stays in the adapter's "
            "or a gateway's queues)",
            0.0,
            5.0,
        )
        self.declare_bool("xcp.block_mode", True, "XCP: DOWNLOAD in master block mode when the ECU offers it")
        self.declare_bool(
            "xcp.verify_readback",
            False,
            "XCP: UPLOAD every written byte back besides BUILD_CHECKSUM (off: the ECU's CRC-32 of each written run "
            "confirms it; the bytes are read back anyway where the ECU builds no CRC-32 or its CRC-32 differs)",
        )
        self.trace_file = self.declare_str(
            "can.trace_file",
            "",
            "write every frame sent and received to this trace (.log candump, .asc, .blf, .trc, .csv); '' = none",
            read_only=True,
        )
        fault_spec = self.declare_str(
            "can.faults",
            "",
            "TESTS AND DEMOS ONLY: faults injected on the bridge's bus, e.g. drop=0.1,corrupt=0.1,seed=3",
            read_only=True,
        )
        self.declare_float(
            "step_timeout_s",
            0.025,
            "bac protocol: wait for one reply of the ECU, s (XCP: xcp.step_timeout_s, XCP's T1)",
            0.001,
            5.0,
        )
        self.declare_int("step_retries", 5, "re-sends of one request before the transaction fails", 0, 100)
        self.declare_int("max_attempts", 3, "transactions per apply (new sequence number each)", 1, 20)
        self.declare_float(
            "default_timeout_s", 3.0, "overall time limit of an apply when the request gives 0, s", 0.01, 600.0
        )
        self.declare_int("window", 16, "requests in flight at once", 1, 255)
        self.declare_bool(
            "verify_readback",
            True,
            "bac protocol: read every value back after the ECU's acknowledgment (XCP: xcp.verify_readback)",
        )
        self.restore_on_shutdown = self.declare_bool(
            "restore_baseline_on_shutdown", True, "write the safe baseline when the node stops"
        )
        self.declare_bool(
            "restore_baseline_on_abort", True, "write the safe baseline when an apply ends with the ECU's state unknown"
        )
        self.declare_float("restore_timeout_s", 2.0, "time limit of one try of a baseline restore, s", 0.01, 60.0)
        self.declare_float(
            "restore_pending_s",
            30.0,
            "a baseline restore the ECU refuses (busy: the vehicle moves) is tried again for this long at shutdown, s "
            "(while the node runs, it is tried again with each diagnostics tick until it goes through)",
            0.0,
            3600.0,
        )
        self.declare_float(
            "restore_retry_s", 0.5, "period of the tries of a pending restore at shutdown, s", 0.05, 60.0
        )
        restore_on_start = self.declare_bool(
            "restore_baseline_on_start",
            True,
            "read the ECU at start and restore the baseline if it holds anything else (false: report it)",
            read_only=True,
        )
        period = self.declare_float(
            "diagnostics_period_s", 1.0, "period of /diagnostics, s", 0.05, 60.0, read_only=True
        )
        self.declare_bool("poll_ecu", True, "ask the ECU for its status with each diagnostics message")

        try:
            self.definition = CalibrationDefinition.load(resolve_definition(definition_file))
            self.codec = CalibrationCodec(self.definition)
            self.faults = FaultConfig.parse(fault_spec)
            self.xcp_settings: XcpSettings | None = None
            if self.protocol == "xcp":
                from bac_ecu_bridge.xcp.layout import XcpLayout

                layout = XcpLayout(self.definition)  # every parameter has its XCP address, none overlap
                for q in layout.params:
                    why = q.off_grid(self.definition.parameter(q.name).resolution)
                    if why:
                        self.get_logger().warning(why)
                pages = xcp_overrides.pop("pages")
                given = {k: v for k, v in xcp_overrides.items() if v not in (-1, "")}
                if pages != "auto":
                    given["pages"] = pages == "true"
                self.xcp_settings = XcpSettings.of(self.definition, **given)
                s = self.xcp_settings
                self.ids = CanIds(s.can_id_master, s.can_id_slave, s.extended_id)  # the ids the bus filters on
        except (BacError, ValueError) as exc:
            raise DefinitionError(f"ecu_bridge cannot start: {exc}") from exc

        self._lock = threading.Lock()  # one CAN transaction at a time
        self._bus: can.BusABC | None = None
        self._ecu_status = "not polled yet"
        self._ecu_crc: int | None = None
        self._ecu_count: int | None = None
        self._poll_failures = 0
        self._closed = False
        self.core = BridgeCore(
            self.definition,
            self._open_backend,
            log=self._log,
            on_confirmed=self._publish_confirmed,
            restore_on_abort=lambda: bool(self.get_parameter("restore_baseline_on_abort").value),
        )
        self.core.configure_start_check(restore_on_start, float(self.get_parameter("restore_timeout_s").value))

        self._srv_group = MutuallyExclusiveCallbackGroup()
        self._timer_group = MutuallyExclusiveCallbackGroup()
        self.pub_calibration = self.create_publisher(Calibration, TOPIC_CALIBRATION, QOS_LATCHED)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        self.create_service(ApplyCalibration, SRV_APPLY_CALIBRATION, self._on_apply, callback_group=self._srv_group)
        self.create_service(ReadCalibration, SRV_READ_CALIBRATION, self._on_read, callback_group=self._srv_group)
        self.create_service(Trigger, SRV_RESTORE_BASELINE, self._on_restore, callback_group=self._srv_group)
        self.create_timer(period, self._on_diagnostics, callback_group=self._timer_group)

        with self._lock:
            try:
                self._ensure()  # opens the bus and checks what the ECU holds before anything else
            except BusError:
                pass  # reported below and on /diagnostics; every call tries again (and checks the ECU then)
        self.get_logger().info(
            f"ecu_bridge ({self.protocol}): definition '{self.definition.name}' ({len(self.codec.params)} raw "
            f"parameters, tuned: {', '.join(self.definition.tuned)}), CAN {self.settings.describe()}, "
            f"request 0x{self.ids.request_id:X} / response 0x{self.ids.response_id:X}"
            f"{' (29-bit)' if self.ids.extended else ''}"
            + (f", trace {self.trace_file}" if self.trace_file else "")
            + (f", INJECTED FAULTS {fault_spec}" if self.faults.any else "")
            + ("" if self._bus is not None else f"; CAN not open yet: {self.core.bus_error}")
            + (f"; {self.core.start_report}" if self.core.start_report else "")
        )

    # --- the bus ------------------------------------------------------------------------------------
    def _log(self, level: str, text: str) -> None:
        # rclpy refuses one call site logging at several severities: one call per level
        if level == "error":
            self.get_logger().error(text)
        elif level == "warn":
            self.get_logger().warning(text)
        else:
            self.get_logger().info(text)

    def _config(self) -> ClientConfig:
        p = self.get_parameter
        return ClientConfig(
            step_timeout_s=float(p("step_timeout_s").value),
            step_retries=int(p("step_retries").value),
            max_attempts=int(p("max_attempts").value),
            timeout_s=float(p("default_timeout_s").value),
            window=int(p("window").value),
            verify_readback=bool(p("verify_readback").value),
        )

    def _xcp_config(self) -> XcpConfig:
        p = self.get_parameter
        return XcpConfig(
            step_timeout_s=float(p("xcp.step_timeout_s").value),
            step_retries=int(p("step_retries").value),
            max_attempts=int(p("max_attempts").value),
            timeout_s=float(p("default_timeout_s").value),
            verify_readback=bool(p("xcp.verify_readback").value),
            t7_s=float(p("xcp.t7_s").value),
            settle_s=float(p("xcp.settle_s").value),
            block_mode=bool(p("xcp.block_mode").value),
        )

    def _open_backend(self) -> CalibrationBackend:
        """Open the bus and the protocol's client on it; raises :class:`BusError`. Called with the lock held."""
        bus: can.BusABC = open_bus(self.settings, self.ids)
        if self.faults.any:
            bus = FaultyBus(bus, self.faults)
        if self.trace_file:
            bus = TracedBus(bus, self.trace_file)
        self._bus = bus
        client: CalibrationBackend
        try:
            if self.xcp_settings is not None:
                client = XcpCalibrationClient(bus, self.definition, self.xcp_settings, self._xcp_config())
            else:
                client = CalibrationClient(bus, self.codec, self.ids, self._config(), logger=None)
        except BaseException:
            bus.shutdown()
            raise
        return _OwnedBus(client, bus)

    def _ensure(self) -> CalibrationBackend:
        backend = self.core.ensure()
        self._ensure_config()
        return backend

    # --- services -----------------------------------------------------------------------------------------
    def _calibration(self, result_values: dict[str, float], crc: int, trial_id: int) -> Calibration:
        msg = Calibration()
        msg.trial_id = int(trial_id)
        msg.names = list(result_values)
        msg.values = [float(v) for v in result_values.values()]
        msg.crc32 = int(crc)
        return msg

    def _publish_confirmed(self, values: dict[str, float], crc: int, trial_id: int) -> None:
        """The ECU holds ``values`` (an apply, a restore, the check at start): bac/calibration says so."""
        if not self.context.ok():  # shutting down: ROS is gone, the CAN work was still done
            return
        try:
            self.pub_calibration.publish(self._calibration(values, crc, trial_id))
        except Exception as exc:  # the context can end between the check and the publish
            self.get_logger().warning(f"could not publish the confirmed calibration: {exc}")

    def _on_apply(self, request: ApplyCalibration.Request, response: ApplyCalibration.Response) -> Any:
        t0 = time.monotonic()
        cal = request.calibration
        trial = int(cal.trial_id)
        code = ErrorCode.NONE
        try:
            raw = resolve_request(self.definition, list(cal.names), list(cal.values))
        except InvalidRequestError as exc:
            code, message = exc.code, str(exc)
        except DefinitionError as exc:
            code, message = ErrorCode.INVALID_REQUEST, str(exc)
        except UnknownParameterError as exc:
            code, message = ErrorCode.UNKNOWN_PARAMETER, str(exc)
        except OutOfBoundsError as exc:
            code, message = ErrorCode.OUT_OF_BOUNDS, str(exc)
        if code != ErrorCode.NONE:
            response.success = False
            response.error_code = int(code)
            response.message = f"refused before sending anything: {message}"
            response.latency_s = time.monotonic() - t0
            self.core.last_error = response.message
            self.get_logger().warning(f"trial {trial}: {response.message}")
            return response
        with self._lock:
            self._ensure_config()
            out = self.core.apply(
                raw, float(request.timeout_s), trial, float(self.get_parameter("restore_timeout_s").value)
            )
        response.latency_s = time.monotonic() - t0
        response.attempts = int(out.attempts)
        if not out.success or out.result is None:
            response.success = False
            response.error_code = int(out.code)
            response.message = out.message
            self.get_logger().error(
                f"trial {trial}: apply failed ({out.code.name}) after {out.attempts} transaction(s), "
                f"{response.latency_s * 1e3:.0f} ms: {out.message}"
            )
            return response
        result = out.result
        response.success = True
        response.error_code = int(ErrorCode.NONE)
        response.applied = self._calibration(result.values, result.crc, trial)
        response.message = out.message
        self.get_logger().info(
            f"trial {trial}: ECU confirmed {len(result.values)} parameters, CRC-32 0x{result.crc:08X}, "
            f"{result.attempts} transaction(s), {response.latency_s * 1e3:.1f} ms"
            + ("" if result.read_back else " (not read back)")
            + (f"; {result.note}" if result.note else "")
        )
        return response

    def _ensure_config(self) -> None:
        """Pass parameters changed at run time (ros2 param set) to an open backend."""
        backend = self.core.backend
        if isinstance(backend, _OwnedBus):
            if isinstance(backend.client, CalibrationClient):
                backend.client.config = self._config()
            elif isinstance(backend.client, XcpCalibrationClient):
                backend.client.config = self._xcp_config()

    def _on_read(self, request: ReadCalibration.Request, response: ReadCalibration.Response) -> Any:
        with self._lock:
            self._ensure_config()
            try:
                result = self.core.read(float(self.get_parameter("default_timeout_s").value))
            except BridgeError as exc:
                response.success = False
                response.message = f"{ErrorCode(exc.code).name}: {exc}"
                return response
        response.success = True
        response.message = result.note
        response.active = self._calibration(result.values, result.crc, 0)
        return response

    def _on_restore(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        with self._lock:
            self._ensure_config()
            ok, text = self.core.restore("service", float(self.get_parameter("restore_timeout_s").value))
        if not ok:
            self.get_logger().error(text)
        response.success = ok
        response.message = text
        return response

    # --- diagnostics -------------------------------------------------------------------------------------------
    def _on_diagnostics(self) -> None:
        if self._closed:
            return
        if self._lock.acquire(blocking=False):  # never wait behind an apply
            try:
                if self.core.pending is not None:
                    with contextlib.suppress(BusError):
                        self._ensure()
                    self.core.retry_pending(float(self.get_parameter("restore_timeout_s").value))
                self._poll_locked()
            finally:
                self._lock.release()
        self.pub_diag.publish(self._diagnostics())

    def _poll_locked(self) -> None:
        try:
            backend = self._ensure()
        except BusError:
            return
        if not self.get_parameter("poll_ecu").value:
            return
        try:
            st = backend.status(timeout_s=min(0.25, float(self.get_parameter("diagnostics_period_s").value) / 2))
        except BusError as exc:
            self.core.drop(str(exc))
            self._bus = None
            self._ecu_status = "bus failed"
            return
        except BridgeError as exc:
            self._poll_failures += 1
            self._ecu_status = f"not answering ({exc.code.name})"
            return
        self._poll_failures = 0
        self._ecu_status = "answering"
        self._ecu_crc, self._ecu_count = st.crc, st.count

    def _diagnostics(self) -> DiagnosticArray:
        status = DiagnosticStatus()
        status.name = "ecu_bridge: CAN calibration link"
        status.hardware_id = self.settings.describe()
        core = self.core
        level, message = DiagnosticStatus.OK, "CAN open, ECU answering"
        bus_state = "closed"
        bus = self._bus if core.backend is not None else None
        if bus is not None:
            try:
                bus_state = bus.state.name
            except Exception:  # not every interface reports it
                bus_state = "unknown"
        if core.pending is not None:
            level, message = DiagnosticStatus.ERROR, core.pending_text()
        elif core.backend is None:
            level, message = DiagnosticStatus.ERROR, f"CAN interface not open: {core.bus_error}"
        elif bus_state == "ERROR":
            level, message = DiagnosticStatus.ERROR, "CAN controller in error state (bus off?)"
        elif self._poll_failures >= 2:
            level, message = DiagnosticStatus.ERROR, f"ECU not answering ({self._ecu_status})"
        elif core.ecu_unexpected:
            level, message = DiagnosticStatus.WARN, core.ecu_unexpected[:300]
        elif bus_state == "PASSIVE":
            level, message = DiagnosticStatus.WARN, "CAN controller error-passive"
        elif (
            core.confirmed_values is not None
            and self._ecu_crc is not None
            and self._ecu_count == len(core.confirmed_values)
            and self._ecu_crc != core.confirmed_crc
        ):
            level, message = (
                DiagnosticStatus.WARN,
                "the ECU's active calibration differs from the last one confirmed (ECU reset or another tool?)",
            )
        elif core.last_apply_failed:
            level, message = DiagnosticStatus.WARN, f"last apply failed: {core.last_error}"[:300]
        status.level = level
        status.message = message

        def kv(k: str, v: object) -> KeyValue:
            return KeyValue(key=k, value=str(v))

        known = core.confirmed_values is not None
        values = [
            kv("protocol", self.protocol),
            kv("interface", self.settings.interface),
            kv("channel", self.settings.channel),
            kv("bitrate", self.settings.bitrate),
            kv("request_id", f"0x{self.ids.request_id:X}"),
            kv("response_id", f"0x{self.ids.response_id:X}"),
            kv("bus_state", bus_state),
            kv("ecu", self._ecu_status),
            kv("ecu_table_crc32", "" if self._ecu_crc is None else f"0x{self._ecu_crc:08X}"),
            kv("definition", self.definition.name),
            kv("ecu_holds", core.holds_text()),
            kv("last_confirmed_trial", core.confirmed_trial if known else ""),
            kv("last_confirmed_crc32", "" if core.confirmed_crc is None else f"0x{core.confirmed_crc:08X}"),
            kv("restore_pending", core.pending_text()),
            kv("start_check", core.start_report),
            kv("last_error", core.last_error),
        ]
        values += [kv(name, v) for name, v in core.counters().items()]
        status.values = values
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status]
        return arr

    # --- shutdown -----------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Restore the baseline (if configured; retried while the ECU refuses it) and close the bus; once."""
        if self._closed:
            return
        self._closed = True
        wait, timeout, pending = self._close_bounds()
        if not self._lock.acquire(timeout=wait):  # an apply in flight ends within its own bound
            self.get_logger().error("an apply did not end in time; closing without restoring the baseline")
            return
        try:
            if self.restore_on_shutdown:
                try:
                    self._ensure()
                except BusError as exc:
                    self.get_logger().error(
                        f"shutdown: cannot restore the baseline, CAN not open: {exc}; the ECU keeps "
                        f"{self.core.holds_text()}"
                    )
                else:
                    self.core.restore_until(
                        "shutdown",
                        timeout,
                        pending,
                        float(self.get_parameter("restore_retry_s").value),
                        on_pending=self._publish_pending,
                    )
        finally:
            try:
                self.core.drop("closed")
            finally:
                self._bus = None
                self._lock.release()

    def _publish_pending(self) -> None:
        """While a shutdown restore waits for the ECU, /diagnostics says so (if ROS is still up)."""
        if not self.context.ok():
            return
        try:
            self.pub_diag.publish(self._diagnostics())
        except Exception:  # the context can end between the check and the publish
            pass

    def _close_bounds(self) -> tuple[float, float, float]:
        """close()'s time limits, s: waiting out an apply in flight, one restore try, retrying a refused one."""
        wait = float(self.get_parameter("default_timeout_s").value) + 1.0  # an apply ends within its own bound
        return (
            wait,
            float(self.get_parameter("restore_timeout_s").value),
            float(self.get_parameter("restore_pending_s").value),
        )

    def cleanup_time_s(self) -> float:
        """close() within its bounds, plus a second for opening and closing the bus."""
        wait, timeout, pending = self._close_bounds()
        return wait + timeout + pending + 2.0

    def destroy_node(self) -> None:
        try:
            self.close()
        except Exception as exc:  # never keep a node from going down
            self.get_logger().error(f"shutdown: {exc}")
        super().destroy_node()


class _OwnedBus:
    """A backend together with the bus it runs on: closing it closes the bus."""

    def __init__(self, client: CalibrationBackend, bus: can.BusABC) -> None:
        self.client = client
        self.bus = bus

    @property
    def protocol(self) -> str:
        return self.client.protocol

    def apply(self, values: Mapping[str, float], timeout_s: float | None = None) -> ApplyResult:
        return self.client.apply(values, timeout_s)

    def read_active(self, timeout_s: float | None = None) -> ReadResult:
        return self.client.read_active(timeout_s)

    def status(self, timeout_s: float | None = None) -> EcuStatus:
        return self.client.status(timeout_s)

    def restore_baseline(self, timeout_s: float | None = None) -> ApplyResult:
        return self.client.restore_baseline(timeout_s)

    def quantize(self, values: Mapping[str, float]) -> dict[str, float]:
        return self.client.quantize(values)

    def counters(self) -> dict[str, int]:
        return self.client.counters()

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            self.bus.shutdown()


def main(args: list[str] | None = None) -> int:
    return run_node(EcuBridgeNode, args)


if __name__ == "__main__":
    sys.exit(main())
