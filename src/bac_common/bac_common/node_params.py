"""Declare a configuration dataclass as ROS parameters (same names, the dataclass's defaults).

The measurement chain's nodes fill their pure cores' configurations
(:class:`~bac_imu.ingest.IngestConfig`, ``SegmentConfig``, ``KpiConfig``) from
parameters declared here, so the defaults live in one place and an offline
tool builds the same configuration from the same YAML
(``bac_measure.measure_config``). No rclpy import: ``node`` is a
``bac_common.rosnode.BacNode``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, fields
from typing import Any, NamedTuple, Protocol, TypeVar


class ParamSpec(NamedTuple):
    description: str
    lower: float | None = None
    upper: float | None = None
    choices: tuple[str, ...] = ()


class _Declares(Protocol):
    def declare_float(
        self,
        name: str,
        default: float,
        description: str,
        lower: float | None = ...,
        upper: float | None = ...,
        read_only: bool = ...,
    ) -> float: ...

    def declare_int(
        self,
        name: str,
        default: int,
        description: str,
        lower: int | None = ...,
        upper: int | None = ...,
        read_only: bool = ...,
    ) -> int: ...

    def declare_str(
        self, name: str, default: str, description: str, choices: Any = ..., read_only: bool = ...
    ) -> str: ...

    def declare_bool(self, name: str, default: bool, description: str, read_only: bool = ...) -> bool: ...


C = TypeVar("C")


def declare_config(node: _Declares, cls: type[C], specs: Mapping[str, ParamSpec], read_only: bool = True) -> C:
    """Declare every field of ``cls`` as a parameter and return ``cls`` built from their values.

    Every field must have a spec (a description): a new field cannot slip in undocumented.
    """
    values: dict[str, Any] = {}
    for f in fields(cls):  # type: ignore[arg-type]
        if f.name not in specs:
            raise KeyError(f"parameter {f.name} of {cls.__name__} has no description")
        spec = specs[f.name]
        default = f.default
        if default is MISSING:
            raise KeyError(f"{cls.__name__}.{f.name} has no default")
        if isinstance(default, bool):
            values[f.name] = node.declare_bool(f.name, default, spec.description, read_only=read_only)
        elif isinstance(default, int):
            lo = None if spec.lower is None else int(spec.lower)
            hi = None if spec.upper is None else int(spec.upper)
            values[f.name] = node.declare_int(f.name, default, spec.description, lo, hi, read_only=read_only)
        elif isinstance(default, float):
            values[f.name] = node.declare_float(
                f.name, default, spec.description, spec.lower, spec.upper, read_only=read_only
            )
        elif isinstance(default, str):
            values[f.name] = node.declare_str(
                f.name, default, spec.description, spec.choices or None, read_only=read_only
            )
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: unsupported parameter type {type(default).__name__}")
    return cls(**values)
