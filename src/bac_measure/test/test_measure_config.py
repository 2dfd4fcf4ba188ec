"""The chain's configurations from parameter YAML: merged like ROS merges them."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_imu.ingest import IngestConfig
from bac_measure.measure_config import ParamsFileError, load_node_params


def test_parameters_merge_like_ros(tmp_path: Path) -> None:
    a = tmp_path / "a.yaml"
    a.write_text(
        "/**:\n  ros__parameters: {output_rate_hz: 100.0, gravity: 9.8}\n"
        "imu_ingest:\n  ros__parameters:\n    output_rate_hz: 250.0\n"
    )
    b = tmp_path / "b.yaml"
    b.write_text("/imu_ingest:\n  ros__parameters:\n    gravity: 9.81\n    nested: {x: 1}\n")
    params = load_node_params([a, b], "imu_ingest", {"mount_source": "standstill"})
    assert params == {"output_rate_hz": 250.0, "gravity": 9.81, "nested.x": 1, "mount_source": "standstill"}
    cfg = IngestConfig.from_params(params)
    assert cfg.output_rate_hz == 250.0 and cfg.gravity == 9.81 and cfg.mount_source == "standstill"
    with pytest.raises(ParamsFileError, match="not found"):
        load_node_params([tmp_path / "missing.yaml"], "imu_ingest")
    bad = tmp_path / "bad.yaml"
    bad.write_text("imu_ingest: [1, 2]\n")
    with pytest.raises(ParamsFileError, match="ros__parameters"):
        load_node_params([bad], "imu_ingest")
