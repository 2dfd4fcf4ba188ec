"""Errors of the ECU bridge.

Each error carries the ``ApplyCalibration`` error code it surfaces as
(:class:`ErrorCode`, the same numbers as ``bac_msgs/srv/ApplyCalibration``),
so that the node only copies ``code`` and ``str(error)`` into its response.
"""

from __future__ import annotations

from enum import IntEnum
from typing import TYPE_CHECKING

from bac_common.errors import BacError

if TYPE_CHECKING:
    from bac_ecu_bridge.backend import EcuState


class ErrorCode(IntEnum):
    """The error codes of ``bac_msgs/srv/ApplyCalibration`` (same numbers)."""

    NONE = 0
    OUT_OF_BOUNDS = 1
    UNKNOWN_PARAMETER = 2
    ECU_OUT_OF_RANGE = 3
    ECU_BUSY = 4
    CRC_MISMATCH = 5
    SEQUENCE = 6
    TIMEOUT = 7
    BUS = 8
    INVALID_REQUEST = 9


class BridgeError(BacError):
    """Base class of the errors an apply / read can end with."""

    code: ErrorCode = ErrorCode.INVALID_REQUEST

    def __init__(self, message: str, *, attempts: int = 0, uncertain: bool = False) -> None:
        super().__init__(message)
        self.attempts = attempts
        # True when a COMMIT may have reached the ECU without a decisive answer:
        # the calibration active in the ECU is then unknown until it is read back.
        self.uncertain = uncertain
        # what the ECU holds after the failure (settled by reading it back when uncertain); set by the backend
        self.ecu_state: EcuState | None = None


class ProtocolConfigError(BridgeError, ValueError):
    """A calibration definition or CAN setting that the protocol cannot carry."""

    code = ErrorCode.INVALID_REQUEST


class InvalidRequestError(BridgeError, ValueError):
    """A malformed request (lengths differ, NaN, duplicate or missing names)."""

    code = ErrorCode.INVALID_REQUEST


class FrameError(BridgeError, ValueError):
    """A CAN frame that is not a valid protocol frame (wrong length, CRC-8, opcode).

    Internal: garbled frames are counted and ignored, never surfaced to a caller.
    """


class EcuRejectedError(BridgeError):
    """The ECU answered with a negative response (see :class:`bac_ecu_bridge.protocol.Reason`)."""

    def __init__(self, message: str, code: ErrorCode, reason: int, *, attempts: int = 0, uncertain: bool = False):
        super().__init__(message, attempts=attempts, uncertain=uncertain)
        self.code = code
        self.reason = reason


class EcuTimeoutError(BridgeError):
    """No valid answer within the bounded time and retries."""

    code = ErrorCode.TIMEOUT


class AcknowledgeMismatchError(BridgeError):
    """The ECU acknowledged or read back something else than what was written."""

    code = ErrorCode.CRC_MISMATCH


class BusError(BridgeError):
    """The CAN interface failed: it could not be opened, or sending / receiving failed."""

    code = ErrorCode.BUS
