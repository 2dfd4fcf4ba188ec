"""The measurement chain's configurations from the same parameter YAML the nodes read.

An offline tool (rescoring, replay, the IMU health report) builds exactly the
configuration the live nodes had::

    files = ["ros_ws/params/common.yaml", "ros_ws/params/sim.yaml"]
    ingest = ingest_config(files)      # imu_ingest's parameters -> IngestConfig
    segment = segment_config(files)    # run_segmenter's -> SegmentConfig
    kpi = kpi_config(files)            # kpi_scorer's -> KpiConfig

Parameters are merged like ROS 2 does: files in order, in each the ``/**``
section then the node's own section (``name`` or ``/name``), later wins;
``overrides`` come last.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from bac_common.errors import BacError
from bac_imu.ingest import IngestConfig
from bac_measure.kpi import KpiConfig
from bac_measure.segmentation import SegmentConfig

NODE_IMU_INGEST = "imu_ingest"
NODE_RUN_SEGMENTER = "run_segmenter"
NODE_KPI_SCORER = "kpi_scorer"


class ParamsFileError(BacError, ValueError):
    """A parameter YAML file is missing or malformed."""


def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    if isinstance(value, Mapping):
        for k, v in value.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    else:
        out[prefix] = value


def load_node_params(
    files: Sequence[str | Path], node: str, overrides: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` after merging ``files`` (nested keys become dotted names)."""
    import yaml

    out: dict[str, Any] = {}
    for f in files:
        p = Path(f)
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except FileNotFoundError as exc:
            raise ParamsFileError(f"parameter file not found: {p}") from exc
        except yaml.YAMLError as exc:
            raise ParamsFileError(f"{p}: not valid YAML: {exc}") from exc
        if not isinstance(data, Mapping):
            raise ParamsFileError(f"{p}: expected a mapping of node names at the top level")
        for key in ("/**", node, "/" + node):
            section = data.get(key)
            if section is None:
                continue
            params = section.get("ros__parameters") if isinstance(section, Mapping) else None
            if not isinstance(params, Mapping):
                raise ParamsFileError(f"{p}: section {key!r} lacks a ros__parameters mapping")
            _flatten("", params, out)
    out.update(overrides or {})
    return out


def ingest_config(files: Sequence[str | Path], overrides: Mapping[str, Any] | None = None) -> IngestConfig:
    return IngestConfig.from_params(load_node_params(files, NODE_IMU_INGEST, overrides))


def segment_config(files: Sequence[str | Path], overrides: Mapping[str, Any] | None = None) -> SegmentConfig:
    return SegmentConfig.from_params(load_node_params(files, NODE_RUN_SEGMENTER, overrides))


def kpi_config(files: Sequence[str | Path], overrides: Mapping[str, Any] | None = None) -> KpiConfig:
    return KpiConfig.from_params(load_node_params(files, NODE_KPI_SCORER, overrides))
