"""The optimizer of bac: a ROS-free ask/tell Bayesian-optimization engine (see docs/agent.md)."""

from bac_agent.bo.engine import (
    Engine,
    EngineConfig,
    EngineError,
    Failure,
    Observation,
    Recommendation,
    Suggestion,
)
from bac_agent.bo.gp import GP, GPConfig, GPError, Hyper
from bac_agent.bo.space import Dim, SearchSpace, SpaceError

__all__ = [
    "GP",
    "Dim",
    "Engine",
    "EngineConfig",
    "EngineError",
    "Failure",
    "GPConfig",
    "GPError",
    "Hyper",
    "Observation",
    "Recommendation",
    "SearchSpace",
    "SpaceError",
    "Suggestion",
]
