"""The bridge's decisions, without ROS: apply, settle, restore, a restore that must wait, the check at start.

:class:`BridgeCore` owns a calibration backend (the bac protocol's or XCP's
client on an open CAN bus, opened again after a bus failure) and decides what
the ``ecu_bridge`` node answers and publishes:

* **apply**: the backend's bounded, verified apply. When it fails, the
  backend reports what the ECU holds (:class:`~bac_ecu_bridge.backend.EcuState`,
  read back whenever the outcome was uncertain). The previous calibration or the
  baseline: reported as such. Anything else (or unknown): the safe baseline is
  restored (``restore_on_abort``) before the answer goes out.
* **restore**: writing the baseline (or switching to the ECU's reference
  page) can be refused while the vehicle moves. Then the restore stays
  **pending**: it is retried (:meth:`BridgeCore.retry_pending`, each
  diagnostics tick, and in a loop at shutdown within ``restore_pending_s``) until
  the ECU accepts it, and until then every diagnostics message is an ERROR and
  the log says loudly which calibration the ECU still holds.
* **start**: before anything else, the ECU is read; a calibration other than the
  baseline (a campaign killed mid-run, another tool) is restored
  (``restore_on_start``) or reported.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from bac_common.paramspace import CalibrationDefinition
from bac_ecu_bridge.backend import ApplyResult, CalibrationBackend, EcuState, Holds, ReadResult
from bac_ecu_bridge.errors import BridgeError, BusError, ErrorCode

Log = Callable[[str, str], None]  # (level: "info" | "warn" | "error", text)
Confirmed = Callable[[dict[str, float], int, int], None]  # (values, crc, trial_id): the ECU holds this


@dataclass(frozen=True)
class Outcome:
    """The answer to an apply."""

    success: bool
    code: ErrorCode
    message: str
    result: ApplyResult | None = None
    attempts: int = 0
    ecu_state: EcuState | None = None  # after a failure: what the ECU holds (reported in the message)


@dataclass
class PendingRestore:
    reason: str
    since: float  # monotonic
    holds: str  # what the ECU holds meanwhile, in words
    tries: int = 0
    last_error: str = ""
    last_warned: float = -1e9
    busy: bool = False  # the last try was refused as busy (the vehicle moves): worth waiting for


class BridgeCore:
    """See the module doc. Not thread-safe: the node serializes every call (one CAN transaction at a time)."""

    def __init__(
        self,
        definition: CalibrationDefinition,
        open_backend: Callable[[], CalibrationBackend],
        *,
        log: Log,
        on_confirmed: Confirmed,
        restore_on_abort: Callable[[], bool] = lambda: True,
        clock: Callable[[], float] = time.monotonic,
        warn_every_s: float = 5.0,
    ) -> None:
        self.definition = definition
        self._open_backend = open_backend
        self._log = log
        self._on_confirmed = on_confirmed
        self._restore_on_abort = restore_on_abort
        self._clock = clock
        self.warn_every_s = warn_every_s
        self.backend: CalibrationBackend | None = None
        self.bus_error = ""
        self.last_error = ""
        self.last_apply_failed = False
        self.confirmed_values: dict[str, float] | None = None  # what the ECU was last confirmed to hold
        self.confirmed_crc: int | None = None
        self.confirmed_trial = 0
        self.pending: PendingRestore | None = None
        self.start_checked = False
        self.start_report = ""  # what the check at start found
        self.ecu_unexpected = ""  # a non-baseline calibration found and left in place (restore_on_start off)
        self._restore_on_start = True
        self._start_timeout_s = 2.0

    # --- the backend ----------------------------------------------------------------------------
    def configure_start_check(self, restore_on_start: bool, timeout_s: float) -> None:
        self._restore_on_start = bool(restore_on_start)
        self._start_timeout_s = float(timeout_s)

    def ensure(self) -> CalibrationBackend:
        """The backend on an open bus (re-opened after a failure); raises :class:`BusError`.

        The first time the ECU can be reached, its calibration is checked before anything else is done.
        """
        if self.backend is None:
            try:
                self.backend = self._open_backend()
            except BusError as exc:
                self.bus_error = str(exc)
                raise
            self.bus_error = ""
        if not self.start_checked:
            self.start_checked = True  # once, even if the check fails (the ECU's state is then reported unknown)
            self._check_at_start(self.backend)
        return self.backend

    def drop(self, reason: str) -> None:
        """Close a failed backend; the next call opens it again."""
        self.bus_error = reason
        if self.backend is not None:
            try:
                self.backend.close()
            except Exception as exc:  # a broken adapter may fail to close too
                self._log("warn", f"closing the CAN bus failed: {exc}")
        self.backend = None

    def _bus_guard(self, exc: BridgeError) -> None:
        if isinstance(exc, BusError):
            self.drop(str(exc))

    def _confirm(self, values: Mapping[str, float], crc: int, trial_id: int) -> None:
        self.confirmed_values = dict(values)
        self.confirmed_crc = int(crc)
        self.confirmed_trial = int(trial_id)
        self._on_confirmed(dict(values), int(crc), int(trial_id))

    def _is_baseline(self, values: Mapping[str, float]) -> bool:
        backend = self.backend
        baseline = self.definition.baseline_values()
        want = backend.quantize(baseline) if backend is not None else baseline
        return dict(values) == want

    # --- the check at start -----------------------------------------------------------------------
    def _check_at_start(self, backend: CalibrationBackend) -> None:
        try:
            rd = backend.read_active(self._start_timeout_s)
        except BridgeError as exc:
            self._bus_guard(exc)
            self.start_report = f"could not read the ECU at start ({exc.code.name}): {exc}"
            self._log("warn", f"start: {self.start_report}")
            return
        if self._is_baseline(rd.values):
            self.start_report = f"the ECU holds the baseline (CRC-32 0x{rd.crc:08X})"
            self._confirm(rd.values, rd.crc, 0)
            self._log("info", f"start: {self.start_report}")
            return
        shown = ", ".join(f"{k}={v:g}" for k, v in list(rd.values.items())[:8])
        found = f"the ECU holds a calibration other than the baseline (CRC-32 0x{rd.crc:08X}: {shown})"
        self.confirmed_values, self.confirmed_crc, self.confirmed_trial = dict(rd.values), rd.crc, -1
        if not self._restore_on_start:
            self.start_report = found + "; left in place (restore_baseline_on_start is off)"
            self.ecu_unexpected = self.start_report
            self._log("error", f"start: {self.start_report}")
            return
        self._log("warn", f"start: {found}: restoring the baseline before anything else")
        ok, text = self.restore("start", self._start_timeout_s, holds=found)
        self.start_report = found + ("; baseline restored" if ok else f"; restore pending: {text}")

    # --- apply -------------------------------------------------------------------------------------
    def apply(self, raw: Mapping[str, float], timeout_s: float, trial_id: int, restore_timeout_s: float) -> Outcome:
        """Apply a full raw calibration (see the module doc)."""
        try:
            backend = self.ensure()
            result = backend.apply(raw, timeout_s)
        except BridgeError as exc:
            self._bus_guard(exc)
            state = exc.ecu_state
            message = str(exc)
            if state is not None and state.holds is not Holds.UNKNOWN and state.values is not None:
                message += f"; {state.text()}"
                if state.holds is Holds.BASELINE and state.crc is not None:
                    self._confirm(state.values, state.crc, 0)
                elif state.holds in (Holds.OTHER,) or (state.holds is Holds.PREVIOUS and state.read_back):
                    self.confirmed_values, self.confirmed_crc = dict(state.values), state.crc
            elif state is not None:
                message += f"; {state.text()}"
            needs_restore = (state is None and exc.uncertain) or (
                state is not None and state.holds in (Holds.OTHER, Holds.UNKNOWN)
            )
            if needs_restore and not isinstance(exc, BusError):
                if self._restore_on_abort():
                    ok, text = self.restore("abort", restore_timeout_s, holds=state.text() if state else "unknown")
                    message += (
                        f"; so the safe baseline was restored ({text})"
                        if ok
                        else f"; restoring the baseline failed, it stays pending: {text}"
                    )
                else:
                    message += "; restore_baseline_on_abort is off: read the ECU back and restore it"
            self.last_error = message
            self.last_apply_failed = True
            return Outcome(False, ErrorCode(exc.code), message, None, int(exc.attempts), state)
        self._confirm(result.values, result.crc, trial_id)
        self.last_apply_failed = False
        if self.pending is not None:  # a confirmed apply replaced whatever the pending restore was about
            self._log("info", f"the pending baseline restore ({self.pending.reason}) is superseded by trial {trial_id}")
            self.pending = None
        self.ecu_unexpected = ""
        return Outcome(True, ErrorCode.NONE, result.note, result, result.attempts)

    def read(self, timeout_s: float) -> ReadResult:
        try:
            return self.ensure().read_active(timeout_s)
        except BridgeError as exc:
            self._bus_guard(exc)
            raise

    # --- restore ---------------------------------------------------------------------------------------
    def restore(self, reason: str, timeout_s: float, holds: str = "") -> tuple[bool, str]:
        """Put the baseline in force now; when that fails (e.g. busy: the vehicle moves) it stays pending."""
        try:
            backend = self.ensure()
            result = backend.restore_baseline(timeout_s)
        except BridgeError as exc:
            self._bus_guard(exc)
            text = f"restoring the baseline failed ({ErrorCode(exc.code).name}): {exc}"
            self._pend(reason, holds, text, busy=exc.code == ErrorCode.ECU_BUSY)
            return False, text
        self._confirm(result.values, result.crc, 0)
        self.pending = None
        self.ecu_unexpected = ""
        text = f"baseline restored: CRC-32 0x{result.crc:08X}" + (f" ({result.note})" if result.note else "")
        self._log("info", f"{reason}: {text}")
        return True, text

    def _pend(self, reason: str, holds: str, error: str, busy: bool) -> None:
        now = self._clock()
        if self.pending is None:
            if not holds:
                holds = self.holds_text()
            self.pending = PendingRestore(reason, now, holds)
        p = self.pending
        p.tries += 1
        p.last_error = error
        p.busy = busy
        if now - p.last_warned >= self.warn_every_s:
            p.last_warned = now
            self._log("error", self.pending_text())
        self.last_error = error

    def holds_text(self) -> str:
        if self.confirmed_values is None:
            return "an unknown calibration"
        if self.confirmed_trial > 0:
            return f"trial {self.confirmed_trial}'s calibration (CRC-32 0x{self.confirmed_crc or 0:08X})"
        if self.confirmed_trial == 0:
            return "the baseline"
        return f"a calibration other than the baseline (CRC-32 0x{self.confirmed_crc or 0:08X})"

    def pending_text(self) -> str:
        p = self.pending
        if p is None:
            return ""
        age = self._clock() - p.since
        head = f"BASELINE RESTORE PENDING ({p.reason}, {age:.0f} s, {p.tries} tries): {p.holds}; "
        if p.busy:
            return head + (
                "the ECU refuses it while the vehicle moves: STOP THE VEHICLE, it is written as soon as the ECU "
                "accepts it"
            )
        return head + f"the last try failed ({p.last_error[:200]}); it is tried again with each diagnostics tick"

    def retry_pending(self, timeout_s: float) -> bool:
        """One more try of a pending restore; True when nothing is pending any more."""
        if self.pending is None:
            return True
        p = self.pending
        ok, _ = self.restore(p.reason, timeout_s, p.holds)
        if ok:
            self._log("warn", f"the pending baseline restore ({p.reason}) went through after {p.tries + 1} tries")
        return ok

    def restore_until(
        self,
        reason: str,
        timeout_s: float,
        bound_s: float,
        retry_every_s: float,
        alive: Callable[[], bool] = lambda: True,
        on_pending: Callable[[], None] = lambda: None,
    ) -> bool:
        """Restore now, and while the ECU refuses it as busy retry every ``retry_every_s`` for at most ``bound_s``.

        Other failures (no answer, the bus) end the tries at once: nothing suggests that waiting would help.
        """
        end = self._clock() + bound_s
        ok, _ = self.restore(reason, timeout_s, self.holds_text())
        while not ok and alive() and self.pending is not None and self.pending.busy:
            on_pending()
            left = end - self._clock()
            if left <= 0:
                break
            time.sleep(min(retry_every_s, left))
            ok = self.retry_pending(timeout_s)
        if not ok:
            waited = "" if self.pending is None or not self.pending.busy else f" after {bound_s:g} s"
            self._log(
                "error",
                f"GAVE UP restoring the baseline{waited}: {self.pending_text()}. The ECU keeps this calibration: "
                "restore it by hand (python -m bac_ecu_bridge restore ...) before driving on",
            )
        return ok

    # --- state for diagnostics ----------------------------------------------------------------------
    def counters(self) -> dict[str, Any]:
        return self.backend.counters() if self.backend is not None else {}
