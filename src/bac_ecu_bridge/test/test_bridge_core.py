"""The bridge's decisions without ROS or CAN: a fake backend that refuses, settles and reads as told."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from bac_common.paramspace import CalibrationDefinition, uniform_parameters
from bac_ecu_bridge.backend import ApplyResult, EcuState, EcuStatus, Holds, ReadResult
from bac_ecu_bridge.core import BridgeCore
from bac_ecu_bridge.errors import BridgeError, EcuRejectedError, EcuTimeoutError, ErrorCode

DEF = CalibrationDefinition("two", uniform_parameters("p", 2, 0.0, 10.0, 5.0, 0.5))
BASE = {"p01": 5.0, "p02": 5.0}


@dataclass
class FakeBackend:
    """Holds a calibration; ``busy`` refuses restores and applies (the vehicle moves)."""

    holds: dict[str, float] = field(default_factory=lambda: dict(BASE))
    busy: bool = False
    restores: int = 0
    fail_next: BridgeError | None = None
    protocol: str = "fake"

    def _result(self, values: Mapping[str, float]) -> ApplyResult:
        return ApplyResult(dict(values), {}, hash(tuple(values.items())) & 0xFFFF, 1, 0.0, 0, True)

    def apply(self, values: Mapping[str, float], timeout_s: float | None = None) -> ApplyResult:
        if self.fail_next is not None:
            err, self.fail_next = self.fail_next, None
            raise err
        if self.busy:
            raise EcuRejectedError("busy", ErrorCode.ECU_BUSY, 3)
        self.holds = dict(values)
        return self._result(values)

    def read_active(self, timeout_s: float | None = None) -> ReadResult:
        return ReadResult(dict(self.holds), {}, 1, 0.0)

    def status(self, timeout_s: float | None = None) -> EcuStatus:
        return EcuStatus(2, 1, 0.0)

    def restore_baseline(self, timeout_s: float | None = None) -> ApplyResult:
        self.restores += 1
        return self.apply(BASE, timeout_s)

    def quantize(self, values: Mapping[str, float]) -> dict[str, float]:
        return dict(values)

    def counters(self) -> dict[str, int]:
        return {"restores": self.restores}

    def close(self) -> None:
        pass


class Recorder:
    def __init__(self) -> None:
        self.logs: list[tuple[str, str]] = []
        self.published: list[tuple[dict[str, float], int, int]] = []

    def log(self, level: str, text: str) -> None:
        self.logs.append((level, text))

    def confirmed(self, values: dict[str, float], crc: int, trial: int) -> None:
        self.published.append((values, crc, trial))

    def errors(self) -> list[str]:
        return [t for lvl, t in self.logs if lvl == "error"]


def core_of(backend: FakeBackend, **kw: object) -> tuple[BridgeCore, Recorder]:
    rec = Recorder()
    core = BridgeCore(DEF, lambda: backend, log=rec.log, on_confirmed=rec.confirmed, **kw)  # type: ignore[arg-type]
    return core, rec


def test_a_restore_refused_while_driving_stays_pending_and_goes_through_when_the_vehicle_stops() -> None:
    ecu = FakeBackend()
    core, rec = core_of(ecu)
    assert core.apply({"p01": 1.0, "p02": 2.0}, 1.0, 7, 1.0).success
    ecu.busy = True
    tries = 0

    def stop_after_three() -> None:  # the driver stops after the third refusal
        nonlocal tries
        tries += 1
        if tries == 3:
            ecu.busy = False

    assert core.restore_until("shutdown", 0.1, 5.0, 0.001, on_pending=stop_after_three)
    assert ecu.holds == BASE and core.pending is None
    assert ecu.restores == 4
    pending_logs = [t for t in rec.errors() if "BASELINE RESTORE PENDING" in t]
    assert pending_logs and "trial 7's calibration" in pending_logs[0] and "STOP THE VEHICLE" in pending_logs[0]
    assert rec.published[-1][2] == 0  # the baseline, confirmed, is published with trial 0


def test_a_restore_that_stays_refused_gives_up_loudly_within_its_bound() -> None:
    ecu = FakeBackend()
    core, rec = core_of(ecu)
    core.apply({"p01": 1.0, "p02": 2.0}, 1.0, 9, 1.0)
    ecu.busy = True
    assert not core.restore_until("shutdown", 0.1, 0.05, 0.01)
    assert ecu.holds == {"p01": 1.0, "p02": 2.0} and ecu.restores >= 2
    assert "GAVE UP restoring the baseline after 0.05 s" in rec.errors()[-1]
    assert "trial 9's calibration" in rec.errors()[-1]


def test_a_restore_that_fails_otherwise_is_not_waited_for() -> None:
    ecu = FakeBackend()
    core, rec = core_of(ecu)
    core.apply({"p01": 1.0, "p02": 2.0}, 1.0, 9, 1.0)
    ecu.fail_next = EcuTimeoutError("no answer")
    assert not core.restore_until("shutdown", 0.1, 30.0, 0.01)  # returns at once: waiting would not help
    assert ecu.restores == 1 and "GAVE UP restoring the baseline:" in rec.errors()[-1]


def test_a_pending_restore_is_retried_by_the_tick_and_superseded_by_a_confirmed_apply() -> None:
    ecu = FakeBackend()
    core, _ = core_of(ecu)
    core.apply({"p01": 1.0, "p02": 2.0}, 1.0, 3, 1.0)
    ecu.busy = True
    ok, text = core.restore("service", 0.1)
    assert not ok and "ECU_BUSY" in text and core.pending is not None
    assert not core.retry_pending(0.1)
    ecu.busy = False
    assert core.retry_pending(0.1) and ecu.holds == BASE and core.pending is None
    ecu.busy = True
    core.restore("service", 0.1)
    ecu.busy = False
    assert core.apply({"p01": 3.0, "p02": 3.0}, 1.0, 4, 1.0).success
    assert core.pending is None


def test_at_start_a_calibration_other_than_the_baseline_is_restored_before_anything_else() -> None:
    ecu = FakeBackend(holds={"p01": 9.0, "p02": 9.0})  # a campaign was killed mid-run
    core, rec = core_of(ecu)
    core.ensure()
    assert ecu.holds == BASE and ecu.restores == 1
    assert "other than the baseline" in core.start_report and "baseline restored" in core.start_report
    assert rec.published[-1] == (BASE, rec.published[-1][1], 0)


def test_at_start_a_busy_ecu_leaves_the_restore_pending() -> None:
    ecu = FakeBackend(holds={"p01": 9.0, "p02": 9.0}, busy=True)
    core, _ = core_of(ecu)
    core.ensure()
    assert core.pending is not None and "restore pending" in core.start_report
    assert "other than the baseline" in core.pending_text()
    ecu.busy = False
    assert core.retry_pending(0.1) and ecu.holds == BASE


def test_at_start_the_calibration_is_only_reported_when_restoring_is_off() -> None:
    ecu = FakeBackend(holds={"p01": 9.0, "p02": 9.0})
    core, rec = core_of(ecu)
    core.configure_start_check(False, 1.0)
    core.ensure()
    assert ecu.restores == 0 and "left in place" in core.ecu_unexpected
    assert any("other than the baseline" in t for t in rec.errors())


def test_a_failed_apply_restores_only_when_the_ecu_holds_something_unknown() -> None:
    ecu = FakeBackend()
    core, _ = core_of(ecu)
    core.apply({"p01": 1.0, "p02": 2.0}, 1.0, 1, 1.0)
    for holds, restores in ((Holds.PREVIOUS, 0), (Holds.BASELINE, 0), (Holds.OTHER, 1), (Holds.UNKNOWN, 1)):
        ecu.restores = 0
        err = EcuTimeoutError("no ACK", uncertain=True)
        values = None if holds is Holds.UNKNOWN else {"p01": 1.0, "p02": 2.0}
        err.ecu_state = EcuState(holds, values, 1, True)
        ecu.fail_next = err
        out = core.apply({"p01": 4.0, "p02": 4.0}, 1.0, 2, 1.0)
        assert not out.success and out.code == ErrorCode.TIMEOUT
        assert ecu.restores == restores, holds
        assert ("safe baseline was restored" in out.message) == bool(restores)
