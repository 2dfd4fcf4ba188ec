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

The baseline is restored on shutdown (``restore_baseline_on_shutdown``) and
when an apply aborts with the ECU's state unknown (a COMMIT sent without a
decisive answer; ``restore_baseline_on_abort``).
"""

from __future__ import annotations

import sys
import threading
import time
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
from bac_ecu_bridge.canbus import BusSettings, TracedBus, open_bus
from bac_ecu_bridge.client import ApplyResult, CalibrationClient, ClientConfig
from bac_ecu_bridge.errors import BridgeError, BusError, ErrorCode, InvalidRequestError
from bac_ecu_bridge.faults import FaultConfig, FaultyBus
from bac_ecu_bridge.protocol import DEFAULT_REQUEST_ID, DEFAULT_RESPONSE_ID, CalibrationCodec, CanIds, resolve_request
from bac_msgs.msg import Calibration
from bac_msgs.srv import ApplyCalibration, ReadCalibration

MAX_CAN_ID = 0x1FFF_FFFF


class EcuBridgeNode(BacNode):
    """The ECU bridge (see the module docstring and docs/ecu_bridge.md)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("ecu_bridge", **kwargs)
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
        self.declare_float("step_timeout_s", 0.025, "wait for one reply of the ECU, s", 0.001, 5.0)
        self.declare_int("step_retries", 5, "re-sends of one request before the transaction fails", 0, 100)
        self.declare_int("max_attempts", 3, "transactions per apply (new sequence number each)", 1, 20)
        self.declare_float(
            "default_timeout_s", 3.0, "overall time limit of an apply when the request gives 0, s", 0.01, 600.0
        )
        self.declare_int("window", 16, "requests in flight at once", 1, 255)
        self.declare_bool("verify_readback", True, "read every value back after the ECU's acknowledgment")
        self.restore_on_shutdown = self.declare_bool(
            "restore_baseline_on_shutdown", True, "write the safe baseline when the node stops"
        )
        self.declare_bool(
            "restore_baseline_on_abort", True, "write the safe baseline when an apply ends with the ECU's state unknown"
        )
        self.declare_float("restore_timeout_s", 2.0, "time limit of a baseline restore, s", 0.01, 60.0)
        period = self.declare_float(
            "diagnostics_period_s", 1.0, "period of /diagnostics, s", 0.05, 60.0, read_only=True
        )
        self.declare_bool("poll_ecu", True, "ask the ECU for its status with each diagnostics message")

        try:
            self.definition = CalibrationDefinition.load(resolve_definition(definition_file))
            self.codec = CalibrationCodec(self.definition)
            self.faults = FaultConfig.parse(fault_spec)
        except (BacError, ValueError) as exc:
            raise DefinitionError(f"ecu_bridge cannot start: {exc}") from exc

        self._lock = threading.Lock()  # one CAN transaction at a time
        self._bus: can.BusABC | None = None
        self._client: CalibrationClient | None = None
        self._bus_error = ""
        self._last_error = ""
        self._last_apply_failed = False
        self._last_confirmed: ApplyResult | None = None
        self._last_confirmed_trial = 0
        self._ecu_status = "not polled yet"
        self._ecu_crc: int | None = None
        self._ecu_count: int | None = None
        self._poll_failures = 0
        self._closed = False

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
                self._ensure_bus()
            except BusError:
                pass  # reported below and on /diagnostics; every call tries again
        self.get_logger().info(
            f"ecu_bridge: definition '{self.definition.name}' ({len(self.codec.params)} raw parameters, tuned: "
            f"{', '.join(self.definition.tuned)}), CAN {self.settings.describe()}, request 0x{self.ids.request_id:X} "
            f"/ response 0x{self.ids.response_id:X}{' (29-bit)' if self.ids.extended else ''}"
            + (f", trace {self.trace_file}" if self.trace_file else "")
            + (f", INJECTED FAULTS {fault_spec}" if self.faults.any else "")
            + ("" if self._bus is not None else f"; CAN not open yet: {self._bus_error}")
        )

    # --- the bus ------------------------------------------------------------------------------------
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

    def _ensure_bus(self) -> CalibrationClient:
        """The client on an open bus (re-opened after a failure); raises :class:`BusError`. Hold the lock."""
        if self._client is None:
            try:
                bus: can.BusABC = open_bus(self.settings, self.ids)
            except BusError as exc:
                self._bus_error = str(exc)
                raise
            if self.faults.any:
                bus = FaultyBus(bus, self.faults)
            if self.trace_file:
                bus = TracedBus(bus, self.trace_file)
            self._bus = bus
            self._bus_error = ""
            self._client = CalibrationClient(bus, self.codec, self.ids, self._config(), logger=None)
        self._client.config = self._config()
        return self._client

    def _drop_bus(self, reason: str) -> None:
        """Close a failed bus; the next call opens it again. Hold the lock."""
        self._bus_error = reason
        if self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception as exc:  # a broken adapter may fail to close too
                self.get_logger().warning(f"closing the CAN bus failed: {exc}")
        self._bus = None
        self._client = None

    # --- services -----------------------------------------------------------------------------------------
    def _calibration(self, result_values: dict[str, float], crc: int, trial_id: int) -> Calibration:
        msg = Calibration()
        msg.trial_id = int(trial_id)
        msg.names = list(result_values)
        msg.values = [float(v) for v in result_values.values()]
        msg.crc32 = int(crc)
        return msg

    def _apply_locked(self, raw: dict[str, float], timeout_s: float) -> ApplyResult:
        client = self._ensure_bus()
        try:
            return client.apply(raw, timeout_s)
        except BusError as exc:
            self._drop_bus(str(exc))
            raise

    def _confirmed(self, result: ApplyResult, trial_id: int) -> None:
        self._last_confirmed = result
        self._last_confirmed_trial = trial_id
        if not self.context.ok():  # shutting down: ROS is gone, the CAN work was still done
            return
        try:
            self.pub_calibration.publish(self._calibration(result.values, result.crc, trial_id))
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
            self._last_error = response.message
            self.get_logger().warning(f"trial {trial}: {response.message}")
            return response
        with self._lock:
            try:
                result = self._apply_locked(raw, float(request.timeout_s))
            except BridgeError as exc:
                response.success = False
                response.error_code = int(exc.code)
                response.attempts = int(exc.attempts)
                response.message = str(exc)
                if exc.uncertain:
                    response.message += "; " + self._abort_locked()
                response.latency_s = time.monotonic() - t0
                self._last_error = response.message
                self._last_apply_failed = True
                self.get_logger().error(
                    f"trial {trial}: apply failed ({ErrorCode(exc.code).name}) after {exc.attempts} transaction(s), "
                    f"{response.latency_s * 1e3:.0f} ms: {response.message}"
                )
                return response
            self._confirmed(result, trial)
            self._last_apply_failed = False
        response.success = True
        response.error_code = int(ErrorCode.NONE)
        response.applied = self._calibration(result.values, result.crc, trial)
        response.attempts = int(result.attempts)
        response.latency_s = time.monotonic() - t0
        response.message = ""
        self.get_logger().info(
            f"trial {trial}: ECU confirmed {len(result.values)} parameters, CRC-32 0x{result.crc:08X}, "
            f"{result.attempts} transaction(s), {response.latency_s * 1e3:.1f} ms"
            + ("" if result.read_back else " (not read back)")
        )
        return response

    def _abort_locked(self) -> str:
        """After an apply that left the ECU's state unknown: restore the baseline if configured."""
        if not self.get_parameter("restore_baseline_on_abort").value:
            return "the ECU's active calibration is UNKNOWN (restore_baseline_on_abort is off): read it back"
        try:
            result = self._apply_locked(
                self.definition.baseline_values(), float(self.get_parameter("restore_timeout_s").value)
            )
        except BridgeError as exc:
            return f"the ECU's active calibration is UNKNOWN and restoring the baseline failed too: {exc}"
        self._confirmed(result, 0)
        self.get_logger().warning(f"ECU state was unknown: baseline restored (CRC-32 0x{result.crc:08X})")
        return f"the ECU's state was unknown, so the safe baseline was restored (CRC-32 0x{result.crc:08X})"

    def _on_read(self, request: ReadCalibration.Request, response: ReadCalibration.Response) -> Any:
        with self._lock:
            try:
                client = self._ensure_bus()
                result = client.read_active(float(self.get_parameter("default_timeout_s").value))
            except BridgeError as exc:
                if isinstance(exc, BusError):
                    self._drop_bus(str(exc))
                response.success = False
                response.message = f"{ErrorCode(exc.code).name}: {exc}"
                return response
        response.success = True
        response.message = ""
        response.active = self._calibration(result.values, result.crc, 0)
        return response

    def _on_restore(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        with self._lock:
            ok, text = self._restore_locked(float(self.get_parameter("restore_timeout_s").value))
        response.success = ok
        response.message = text
        return response

    def _restore_locked(self, timeout_s: float) -> tuple[bool, str]:
        try:
            result = self._apply_locked(self.definition.baseline_values(), timeout_s)
        except BridgeError as exc:
            text = f"restoring the baseline failed ({ErrorCode(exc.code).name}): {exc}"
            self.get_logger().error(text)
            self._last_error = text
            return False, text
        self._confirmed(result, 0)
        text = f"baseline restored: CRC-32 0x{result.crc:08X}, " + ", ".join(
            f"{k}={v:g}" for k, v in result.values.items()
        )
        self.get_logger().info(text)
        return True, text

    # --- diagnostics -------------------------------------------------------------------------------------------
    def _on_diagnostics(self) -> None:
        if self._closed:
            return
        if self._lock.acquire(blocking=False):  # never wait behind an apply
            try:
                self._poll_locked()
            finally:
                self._lock.release()
        self.pub_diag.publish(self._diagnostics())

    def _poll_locked(self) -> None:
        try:
            client = self._ensure_bus()
        except BusError:
            return
        if not self.get_parameter("poll_ecu").value:
            return
        try:
            st = client.status(timeout_s=min(0.25, float(self.get_parameter("diagnostics_period_s").value) / 2))
        except BusError as exc:
            self._drop_bus(str(exc))
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
        client = self._client
        stats = client.stats if client is not None else None
        level, message = DiagnosticStatus.OK, "CAN open, ECU answering"
        bus_state = "closed"
        if self._bus is not None:
            try:
                bus_state = self._bus.state.name
            except Exception:  # not every interface reports it
                bus_state = "unknown"
        last = self._last_confirmed
        if self._bus is None:
            level, message = DiagnosticStatus.ERROR, f"CAN interface not open: {self._bus_error}"
        elif bus_state == "ERROR":
            level, message = DiagnosticStatus.ERROR, "CAN controller in error state (bus off?)"
        elif self._poll_failures >= 2:
            level, message = DiagnosticStatus.ERROR, f"ECU not answering ({self._ecu_status})"
        elif bus_state == "PASSIVE":
            level, message = DiagnosticStatus.WARN, "CAN controller error-passive"
        elif (
            last is not None
            and self._ecu_crc is not None
            and self._ecu_count == len(last.raw)
            and self._ecu_crc != last.crc
        ):
            level, message = (
                DiagnosticStatus.WARN,
                "the ECU's active calibration differs from the last one confirmed (ECU reset or another tool?)",
            )
        elif self._last_apply_failed:
            level, message = DiagnosticStatus.WARN, f"last apply failed: {self._last_error}"[:300]
        status.level = level
        status.message = message

        def kv(k: str, v: object) -> KeyValue:
            return KeyValue(key=k, value=str(v))

        values = [
            kv("interface", self.settings.interface),
            kv("channel", self.settings.channel),
            kv("bitrate", self.settings.bitrate),
            kv("request_id", f"0x{self.ids.request_id:X}"),
            kv("response_id", f"0x{self.ids.response_id:X}"),
            kv("bus_state", bus_state),
            kv("ecu", self._ecu_status),
            kv("ecu_table_crc32", "" if self._ecu_crc is None else f"0x{self._ecu_crc:08X}"),
            kv("definition", self.definition.name),
            kv("last_confirmed_trial", self._last_confirmed_trial if last is not None else ""),
            kv("last_confirmed_crc32", "" if last is None else f"0x{last.crc:08X}"),
            kv("last_error", self._last_error),
        ]
        if stats is not None:
            values += [
                kv(name, getattr(stats, name))
                for name in (
                    "applies_ok",
                    "applies_failed",
                    "frames_sent",
                    "frames_received",
                    "invalid_frames",
                    "stale_frames",
                    "retransmissions",
                    "step_timeouts",
                    "nacks",
                )
            ]
        status.values = values
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status]
        return arr

    # --- shutdown -----------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Restore the baseline (if configured) and close the bus; called once, on shutdown."""
        if self._closed:
            return
        self._closed = True
        wait, timeout = self._close_bounds()
        if not self._lock.acquire(timeout=wait):  # an apply in flight ends within its own bound
            self.get_logger().error("an apply did not end in time; closing without restoring the baseline")
            return
        try:
            if self.restore_on_shutdown:
                try:
                    self._ensure_bus()
                except BusError as exc:
                    self.get_logger().error(f"shutdown: cannot restore the baseline, CAN not open: {exc}")
                else:
                    ok, text = self._restore_locked(timeout)
                    if ok:
                        self.get_logger().info(f"shutdown: {text}")
        finally:
            try:
                if self._bus is not None:
                    self._bus.shutdown()
            finally:
                self._bus = None
                self._client = None
                self._lock.release()

    def _close_bounds(self) -> tuple[float, float]:
        """close()'s time limits, s: waiting out an apply in flight, then restoring the baseline."""
        wait = float(self.get_parameter("default_timeout_s").value) + 1.0  # an apply ends within its own bound
        return wait, float(self.get_parameter("restore_timeout_s").value)

    def cleanup_time_s(self) -> float:
        """close() within its bounds, plus a second for opening and closing the bus."""
        return sum(self._close_bounds()) + 1.0

    def destroy_node(self) -> None:
        try:
            self.close()
        except Exception as exc:  # never keep a node from going down
            self.get_logger().error(f"shutdown: {exc}")
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(EcuBridgeNode, args)


if __name__ == "__main__":
    sys.exit(main())
