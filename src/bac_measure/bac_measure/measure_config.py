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
from dataclasses import fields
from pathlib import Path
from typing import Any

from bac_common.errors import BacError
from bac_imu.ingest import IngestConfig
from bac_measure.kpi import KpiConfig
from bac_measure.segmentation import SegmentConfig

NODE_IMU_INGEST = "imu_ingest"
NODE_RUN_SEGMENTER = "run_segmenter"
NODE_KPI_SCORER = "kpi_scorer"


# parameters of the nodes that are not part of the pure cores' configurations: accepted offline, without effect
NODE_ONLY_PARAMS: dict[str, tuple[str, ...]] = {
    NODE_IMU_INGEST: (
        "frame_id",
        "qos_depth",
        "input_reliability",
        "process_period_s",
        "diagnostics_period_s",
        "stale_after_s",
        "expected_rate_hz",
        "use_receive_time",
        "use_sim_time",
    ),
    NODE_RUN_SEGMENTER: (
        "run_timeout_s",
        "approach_time_s",
        "no_data_timeout_s",
        "pre_buffer_s",
        "check_period_s",
        "diagnostics_period_s",
        "campaign_dir",
        "reference_file",
        "template_file",
        "odom_best_effort",
        "use_sim_time",
    ),
    NODE_KPI_SCORER: ("use_sim_time",),
}
CONFIG_OF_NODE = {NODE_IMU_INGEST: IngestConfig, NODE_RUN_SEGMENTER: SegmentConfig, NODE_KPI_SCORER: KpiConfig}


class ParamsFileError(BacError, ValueError):
    """A parameter YAML file is missing or malformed, or a parameter is unknown or of the wrong type."""


def config_params(node: str) -> tuple[str, ...]:
    """The parameters of ``node`` that its pure core's configuration has (what changes a result offline)."""
    return tuple(f.name for f in fields(CONFIG_OF_NODE[node]))


def known_params(node: str) -> tuple[str, ...]:
    return config_params(node) + NODE_ONLY_PARAMS.get(node, ())


def parse_value(text: str) -> Any:
    """A ``-p`` value as YAML (``false`` is a bool, ``0.9`` a float, ``[1, 2]`` a list), as ROS 2 parses it."""
    import yaml

    try:
        return yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError as exc:
        raise ParamsFileError(f"value {text!r} is not valid YAML: {exc}") from exc


def check_overrides(node: str, overrides: Mapping[str, Any]) -> list[str]:
    """Raise :class:`ParamsFileError` for a parameter ``node`` does not have (naming the close ones) or a value of
    the wrong type; return notes for those that are node-only (no effect offline)."""
    import difflib

    cls = CONFIG_OF_NODE[node]
    defaults = {f.name: f.default for f in fields(cls)}
    notes = []
    for k, v in overrides.items():
        if k in defaults:
            from bac_imu.ingest import typed_value

            try:
                typed_value(k, v, defaults[k])
            except ValueError as exc:
                raise ParamsFileError(f"{node}: {exc}") from exc
        elif k in NODE_ONLY_PARAMS.get(node, ()):
            notes.append(f"{node}.{k} is a parameter of the live node only: it changes nothing offline")
        else:
            close = difflib.get_close_matches(k, known_params(node), n=3)
            hint = f"; did you mean {' or '.join(close)}?" if close else ""
            raise ParamsFileError(
                f"{node} has no parameter {k!r}{hint} (its parameters: {', '.join(config_params(node))})"
            )
    return notes


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
