"""Errors of the simulated vehicle (all derive from :class:`bac_common.errors.BacError`)."""

from __future__ import annotations

from bac_common.errors import BacError


class SimError(BacError):
    """Base class of bac_sim errors."""


class ModelError(SimError, ValueError):
    """Vehicle parameters that make no physical sense (negative mass, unstable model, ...)."""


class RoadError(SimError, ValueError):
    """A road profile that cannot be used (file missing or malformed, too short, NaN heights)."""


class ScenarioError(SimError, ValueError):
    """An unknown scenario name or a scenario the road cannot hold (window outside the road)."""


class ControllerError(SimError, ValueError):
    """Controller parameters of the wrong shape, unknown names or values outside their bounds."""
