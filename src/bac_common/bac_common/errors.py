"""Exception types shared by the bac packages.

Every error a user can meet says what is wrong and what to do about it. Each
package derives its own specific errors from :class:`BacError`.
"""

from __future__ import annotations


class BacError(Exception):
    """Base class of all bac errors."""


class DefinitionError(BacError, ValueError):
    """A calibration definition (parameter space, meta-parameters) is malformed."""


class OutOfBoundsError(BacError, ValueError):
    """A parameter value lies outside its declared bounds.

    Raised before anything is sent to the ECU: nothing is ever written outside
    the declared bounds.
    """

    def __init__(
        self, name: str, value: float, lower: float, upper: float, consequence: str = "nothing was written"
    ) -> None:
        """``consequence``: what was not done, as the user reads it (the ECU path: nothing was written)."""
        self.name = name
        self.value = value
        self.lower = lower
        self.upper = upper
        super().__init__(
            f"parameter '{name}' = {value!r} is outside its declared bounds [{lower:g}, {upper:g}]; {consequence}"
        )


class UnknownParameterError(BacError, KeyError):
    """A parameter name that the calibration definition does not declare."""

    def __init__(self, name: str, known: tuple[str, ...]) -> None:
        self.name = name
        self.known = known
        shown = ", ".join(known[:12]) + (" ..." if len(known) > 12 else "")
        super().__init__(f"unknown parameter '{name}'; the definition declares: {shown}")

    def __str__(self) -> str:  # KeyError quotes its argument otherwise
        return str(self.args[0])
