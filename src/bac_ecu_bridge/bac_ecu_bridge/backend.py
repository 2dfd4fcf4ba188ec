"""What every calibration backend of the bridge gives (the bac protocol's client, the XCP client).

The node and the tests talk to a :class:`CalibrationBackend`: ``apply`` writes
a full raw calibration and returns only when the ECU holds exactly those
values (:class:`ApplyResult`, built from what the ECU echoed or read back), or
raises a :class:`~bac_ecu_bridge.errors.BridgeError` whose ``ecu_state`` says
what the ECU holds after the failure (:class:`EcuState`: settled by reading the
ECU back whenever the outcome was uncertain). ``read_active`` reads the
calibration the ECU uses; ``restore_baseline`` puts the safe baseline in force
(a write of the baseline values, or a switch to the ECU's reference page).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Protocol


@dataclass(frozen=True)
class ApplyResult:
    """A calibration the ECU confirmed."""

    values: dict[str, float]  # what the ECU said it holds (read back, else echoed), by name in index order
    raw: dict[int, int]  # the same as raw values by index (the bac protocol's encoding)
    crc: int  # set CRC-32 of the values (the bac protocol: the one the ECU acknowledged)
    attempts: int  # transactions tried
    latency_s: float
    seq: int
    read_back: bool  # True when every value was confirmed from the ECU's memory (read back and compared; over XCP
    # also the ECU's CRC-32 of the written bytes equal to the host's)
    note: str = ""  # e.g. "settled by reading back after an unanswered commit"


@dataclass(frozen=True)
class ReadResult:
    values: dict[str, float]
    raw: dict[int, int]
    crc: int
    latency_s: float
    note: str = ""  # e.g. "reference page" (XCP)


@dataclass(frozen=True)
class EcuStatus:
    count: int  # parameters in the ECU's table
    crc: int  # CRC-32 of the ECU's whole active table
    latency_s: float


class Holds(Enum):
    """What an ECU holds after a failed apply, compared with the sets the bridge knows."""

    REQUESTED = "requested"  # the apply went through after all (its answer was lost)
    PREVIOUS = "previous"  # the calibration confirmed before the apply
    BASELINE = "baseline"  # the definition's safe baseline (e.g. an ECU left on its reference page)
    OTHER = "other"  # something else: must be restored
    UNKNOWN = "unknown"  # the ECU could not be read


@dataclass(frozen=True)
class EcuState:
    """The ECU's calibration after a failed apply, as the bridge reports it."""

    holds: Holds
    values: dict[str, float] | None = None  # None when unknown
    crc: int | None = None
    read_back: bool = False  # True: read from the ECU after the failure; False: known without reading
    detail: str = ""

    @property
    def known(self) -> bool:
        return self.values is not None

    def text(self) -> str:
        how = "read back" if self.read_back else "known without reading"
        crc = "" if self.crc is None else f", CRC-32 0x{self.crc:08X}"
        what = {
            Holds.REQUESTED: "the requested calibration",
            Holds.PREVIOUS: "the previous calibration",
            Holds.BASELINE: "the safe baseline",
            Holds.OTHER: "a calibration that is neither the requested, the previous nor the baseline one",
            Holds.UNKNOWN: "an UNKNOWN calibration (it could not be read)",
        }[self.holds]
        return f"the ECU holds {what} ({how}{crc})" + (f": {self.detail}" if self.detail else "")


def classify(
    values: Mapping[str, float],
    requested: Mapping[str, float] | None,
    previous: Mapping[str, float] | None,
    baseline: Mapping[str, float] | None,
) -> Holds:
    """Which known set ``values`` (read back) equals, in the order requested, previous, baseline."""
    got = dict(values)
    for holds, known in ((Holds.REQUESTED, requested), (Holds.PREVIOUS, previous), (Holds.BASELINE, baseline)):
        if known is not None and dict(known) == got:
            return holds
    return Holds.OTHER


class CalibrationBackend(Protocol):
    """One CAN calibration protocol (bac, XCP) behind the bridge's services."""

    @property
    def protocol(self) -> str: ...

    def apply(self, values: Mapping[str, float], timeout_s: float | None = None) -> ApplyResult: ...

    def read_active(self, timeout_s: float | None = None) -> ReadResult: ...

    def status(self, timeout_s: float | None = None) -> EcuStatus: ...

    def restore_baseline(self, timeout_s: float | None = None) -> ApplyResult: ...

    def quantize(self, values: Mapping[str, float]) -> dict[str, float]: ...

    def counters(self) -> dict[str, int]: ...

    def close(self) -> None: ...
