"""The chain's configurations from the profiles' parameter YAML: what the nodes get, an offline tool gets."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_agent.measure_config import ParamsFileError, ingest_config, kpi_config, load_node_params, segment_config
from bac_imu.ingest import IngestConfig

ROOT = Path(__file__).resolve().parents[2]
PARAMS = ROOT / "ros_ws" / "params"


@pytest.mark.parametrize("profile", ["sim", "car", "replay"])
def test_every_profile_gives_valid_configurations(profile: str) -> None:
    files = [PARAMS / "common.yaml", PARAMS / f"{profile}.yaml"]
    ing, seg, kpi = ingest_config(files), segment_config(files), kpi_config(files)
    assert seg.imu_rate_hz == ing.output_rate_hz  # the segmenter's grid is the ingest's output
    assert kpi.kpi == "rms" and kpi.weight_accel_z == kpi.weight_pitch_rate == 1.0  # paper eq. 1
    assert seg.mode in ("event", "distance")


def test_sim_profile_matches_the_simulated_imu() -> None:
    from bac_sim.run import ImuSpec

    ing = ingest_config([PARAMS / "common.yaml", PARAMS / "sim.yaml"])
    spec = ImuSpec()
    assert (ing.mount_roll_deg, ing.mount_pitch_deg, ing.mount_yaw_deg) == spec.mount_rpy_deg
    assert ing.input_rate_hz == spec.rate_hz
    assert ing.accel_range <= spec.accel_range and ing.gyro_range <= spec.gyro_range  # full scale is saturation


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
