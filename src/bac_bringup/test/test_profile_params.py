"""The profiles' parameter YAML gives the measurement chain valid configurations (what the nodes get, an offline
tool gets), and the sim profile's chain fits the simulated IMU."""

from __future__ import annotations

from pathlib import Path

import pytest

from bac_measure.measure_config import ingest_config, kpi_config, segment_config

PARAMS = Path(__file__).resolve().parents[1] / "params"


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
