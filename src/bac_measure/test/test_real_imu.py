"""A real robot's IMU recording (ROS 1, 50 Hz, not made by bac) through ingestion and scoring."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bac_imu.ingest import ImuIngestor, IngestConfig, IngestOutput, diagnose
from bac_measure.bagio import read_imu
from bac_measure.imu_health import analyse, main, report_text

REAL_BAG = Path(__file__).resolve().parent / "data" / "robot_localization_test2.bag"


def test_real_recording_is_ingested_scored_and_its_health_reported() -> None:
    raw = read_imu(REAL_BAG)
    out, health, sc = analyse(raw, [], {"output_rate_hz": 50.0})
    # what the stream is: 50 Hz, stamps without jitter, no gaps, nothing broken
    assert health.rate_hz == pytest.approx(50.0, rel=1e-9)
    assert health.jitter_ms == pytest.approx(0.0, abs=1e-9)
    assert health.gaps == 0 and health.nonfinite == 0 and health.duplicates == 0 and health.clock_jumps == 0
    assert 0.1 < health.arrival_jitter_ms < 5.0  # the bag's receive times do jitter
    assert len(out) == len(raw) and np.all(np.isfinite(out.accel_z))
    # gravity removed, the robot's motion kept
    assert abs(float(np.mean(out.accel_z))) < 0.2
    assert sc.valid and math.isfinite(sc.j) and 0.05 < sc.rms_accel_z < 2.0 and 0.01 < sc.rms_pitch_rate < 0.5
    assert sc.j == pytest.approx(sc.rms_accel_z + sc.rms_pitch_rate, rel=1e-12)
    text = report_text(raw, health, sc)
    for phrase in ("rate 50.00 Hz", "jitter 0.000 ms", "no gaps", "no NaN/inf samples", "J (rms) ="):
        assert phrase in text, phrase
    assert diagnose(health).level == 0


def test_real_recording_chunked_equals_one_shot_and_upsampling_is_flagged() -> None:
    raw = read_imu(REAL_BAG)
    cfg = IngestConfig(output_rate_hz=200.0, mount_source="standstill", bias_source="standstill")
    ing = ImuIngestor(cfg)
    parts = [
        ing.push(raw.stamp_ns[i : i + 37], raw.accel[i : i + 37], raw.gyro[i : i + 37]) for i in range(0, len(raw), 37)
    ]
    parts.append(ing.flush())
    chunked = IngestOutput.concatenate([p for p in parts if len(p)])
    one = ImuIngestor(cfg)
    whole = IngestOutput.concatenate([one.push(raw.stamp_ns, raw.accel, raw.gyro), one.flush()])
    assert np.array_equal(chunked.accel, whole.accel) and np.array_equal(chunked.stamp_ns, whole.stamp_ns)
    h = ing.health()
    # the robot moves through its first 30 s: roll and pitch from the mean accelerometer over them
    assert h.mount_source == "mean accelerometer over 30.0 s (no standstill found)"
    assert abs(h.mount_rpy_deg[0]) < 5 and abs(h.mount_rpy_deg[1]) < 5 and h.gravity_problem() == ""
    assert h.upsampling and diagnose(h).level == 1 and "above the IMU's 50.0 Hz" in diagnose(h).message


def test_health_command_line_prints_the_report_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png = tmp_path / "health.png"
    assert main([str(REAL_BAG), "-p", "output_rate_hz=50", "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "IMU topic /imu/data" in text and "rate 50.00 Hz" in text and "no gaps" in text
    assert png.stat().st_size > 20_000
    assert main([str(tmp_path / "nothing.bag")]) == 2
    assert "no such bag" in capsys.readouterr().err
