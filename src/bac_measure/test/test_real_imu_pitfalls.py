"""The pitfalls of real IMUs, on recordings the project makes itself (bac_measure.synthetic.imu_recording) shaped
like the public ones review tried (issue 21): a Phidgets IMU upside down at 250 Hz with single lost samples, an
IMU with its y axis up and no standstill, a clipped 2 g accelerometer, an AR.Drone-like 50 Hz stream with 1 s gaps.
Each gives the right mount, the right health figures, and either a correct J or a refusal that names the cause.
They go through the command line (``python -m bac_measure.imu_health``) from a real rosbag2 on disk."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from bac_imu.ingest import ImuIngestor, IngestConfig, IngestOutput, diagnose, find_clipping, ingest_all
from bac_measure.bagio import write_bag
from bac_measure.imu_health import analyse_report, main
from bac_measure.measure_config import ParamsFileError
from bac_measure.synthetic import imu_recording


def run_health(tmp_path: Path, raw: object, *args: str, capsys: pytest.CaptureFixture[str]) -> dict:
    bag = write_bag(tmp_path / "rec", raw)  # type: ignore[arg-type]
    assert main([str(bag), "--json", *args]) == 0
    out = capsys.readouterr().out
    return json.loads(out, parse_constant=_no_nan)  # strict JSON: NaN / Infinity are not JSON


def _no_nan(token: str) -> None:
    raise AssertionError(f"not JSON: {token}")


@pytest.mark.parametrize(
    ("mount", "standstill_s"),
    [((90.0, 0.0, 0.0), 3.0), ((90.0, 0.0, 0.0), 0.0), ((180.0, 0.0, 0.0), 3.0), ((180.0, 0.0, 0.0), 0.0)],
    ids=["y-up standstill", "y-up moving", "upside-down standstill", "upside-down moving"],
)
def test_a_rotated_imu_gives_its_mount_and_the_true_j(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], mount: tuple[float, float, float], standstill_s: float
) -> None:
    rec = imu_recording(duration_s=60.0, fs=250.0, mount_rpy_deg=mount, standstill_s=standstill_s, seed=1)
    rep = run_health(tmp_path, rec.raw, capsys=capsys)
    h, sc = rep["health"], rep["score"]
    roll, pitch, _ = h["mount_rpy_deg"]
    # the accelerometer's offsets (0.3 m/s^2 on z) tilt the estimate by up to 2 deg; yaw is never observable
    assert abs((roll - mount[0] + 180) % 360 - 180) < 2.5 and abs(pitch - mount[1]) < 2.5, h["mount_rpy_deg"]
    if standstill_s:
        assert h["mount_source"] == "standstill" and h["bias_source"] == "standstill"
    else:
        assert h["mount_source"] == "mean accelerometer over 60.0 s (no standstill found)"
        assert h["bias_source"] == "long-run mean over 60.0 s (no standstill found)"
    assert abs(h["mean_accel_mps2"][2]) < 0.05 and h["gravity_problem"] is None and h["level"] == "OK"
    assert sc["valid"] and sc["j"] == pytest.approx(rec.j_true, rel=0.01), (sc["j"], rec.j_true)


def test_a_rotated_imu_without_its_mount_is_refused_with_the_cause(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The review's first finding: gravity on y, no standstill, the mount from the (identity) config: no J."""
    rec = imu_recording(duration_s=60.0, fs=69.4, mount_rpy_deg=(90.0, 0.0, 0.0), seed=2)
    bag = write_bag(tmp_path / "razor", rec.raw)
    assert main([str(bag), "-p", "mount_source=config", "-p", "bias_source=none"]) == 0
    text = capsys.readouterr().out
    assert "health: ERROR" in text
    assert "no J: mean a_z -9." in text and "gravity is on the vehicle's +y axis" in text
    assert re.search(r"the mean acceleration says roll (8[89]|9[0-2]) pitch 0 deg", text) and "give the mount" in text
    # upside down: the same, naming it
    up = imu_recording(duration_s=20.0, fs=250.0, mount_rpy_deg=(180.0, 0.0, 0.0), seed=3)
    r = analyse_report(up.raw, [], {"mount_source": "config", "bias_source": "none"})
    assert not r.score.valid and "the IMU is upside down" in r.score.reason and math.isnan(r.score.j)
    assert diagnose(r.health).level == 2
    # a standstill with a wrong configured mount: the offsets would hide gravity, the tilt does not
    r = analyse_report(
        imu_recording(duration_s=20.0, fs=250.0, mount_rpy_deg=(90.0, 0.0, 0.0), standstill_s=3.0).raw,
        [],
        {"mount_source": "config", "bias_source": "standstill"},
    )
    assert not r.score.valid and re.match(r"gravity is (8[89]|9[0-2]) deg off the vehicle's z axis", r.score.reason)


def test_phidgets_like_upside_down_250hz_with_single_lost_samples(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """96 single lost samples are no gaps (one missing step is below 2.5 periods) but they are counted."""
    rec = imu_recording(
        duration_s=120.0, fs=250.0, mount_rpy_deg=(180.0, 0.0, 0.0), standstill_s=2.0, single_losses=96, seed=4
    )
    assert rec.lost == 96
    rep = run_health(tmp_path, rec.raw, capsys=capsys)
    h = rep["health"]
    assert h["lost_samples"] == 96 and h["gaps"] == 0
    assert h["samples_expected"] == 30_000 and h["samples_in"] == 30_000 - 96
    assert h["loss_pct"] == pytest.approx(0.32, abs=1e-9)
    assert h["level"] == "WARN" and "96 lost samples" in h["message"]
    assert rep["score"]["valid"] and rep["score"]["j"] == pytest.approx(rec.j_true, rel=0.01)


def test_clipped_2g_accelerometer_is_found_at_the_recordings_extreme_and_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    g2 = 2 * 9.80665
    rec = imu_recording(duration_s=60.0, fs=250.0, standstill_s=3.0, bumps_mps2=14.0, clip_mps2=g2, seed=5)
    n_clipped = int(np.count_nonzero(rec.raw.accel[:, 2] == g2))
    assert 10 < n_clipped < 100
    (clip,) = find_clipping(rec.raw.accel, rec.raw.gyro)
    assert clip.axis == "accel_z" and clip.level == pytest.approx(g2) and clip.samples == n_clipped
    # accel_range is configured at 16 g: the range check alone would let the clipped peaks through
    rep = run_health(tmp_path, rec.raw, "-p", "accel_range=156.9", capsys=capsys)
    h = rep["health"]
    assert h["saturated"] == n_clipped and rep["config"]["accel_range"] == pytest.approx(g2)
    assert any("accel_z clipped at +19.61 m/s^2 (2.00 g)" in n for n in rep["notes"])
    assert h["level"] == "ERROR" and not rep["score"]["valid"] and rep["score"]["j"] is None
    assert "IMU data missing or invalid" in rep["score"]["reason"]
    # without clipping nothing is found, and a quantized signal's peaks are no clipping either
    clean = imu_recording(duration_s=60.0, fs=250.0, standstill_s=3.0, bumps_mps2=14.0, seed=5)
    assert find_clipping(clean.raw.accel, clean.raw.gyro) == []
    assert find_clipping(np.round(clean.raw.accel / 0.05) * 0.05, np.round(clean.raw.gyro / 0.001) * 0.001) == []


def test_50hz_stream_with_one_second_gaps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """AR.Drone-like: 50 Hz, stamp jitter, three 1 s gaps. Health over the whole recording; no J at full
    coverage (the holes named), a J within 2 % of the truth with min_coverage 0.9."""
    gaps = ((20.0, 1.0), (40.0, 1.0), (60.0, 1.0))
    rec = imu_recording(duration_s=80.0, fs=50.0, standstill_s=3.0, gaps=gaps, jitter_s=0.0015, seed=6)
    rep = run_health(tmp_path, rec.raw, capsys=capsys)
    h = rep["health"]
    assert h["gaps"] == 3 and h["longest_gap_s"] == pytest.approx(1.02, abs=0.01) and h["lost_samples"] == 150
    assert h["samples_expected"] == 4000 and h["samples_in"] == 3850
    steps = np.diff(rec.raw.stamp_ns) / 1e6
    ok = steps[steps < 50.0]  # gaps excluded, as the report does
    assert h["jitter_ms"] == pytest.approx(float(np.std(ok)), rel=1e-9)  # every step, not the last 1000
    arrival = np.diff(rec.raw.recv_ns) / 1e6
    assert h["arrival_jitter_ms"] == pytest.approx(float(np.std(arrival)), rel=1e-9)
    assert not rep["score"]["valid"] and "for 3.0" in rep["score"]["reason"]
    assert "coverage 0.96" in rep["score"]["reason"] and "below min_coverage 1" in rep["score"]["reason"]
    rep = run_health(tmp_path / "b", rec.raw, "-p", "min_coverage=0.9", capsys=capsys)
    assert rep["score"]["valid"] and rep["score"]["j"] == pytest.approx(rec.j_true, rel=0.02)
    assert any("bridged by linear interpolation" in n for n in rep["notes"])


def test_p_values_are_yaml_and_unknown_names_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = imu_recording(duration_s=10.0, fs=100.0, standstill_s=2.0)
    plain = analyse_report(rec.raw, [], {"detrend": False})
    detrended = analyse_report(rec.raw, [], {"detrend": True})
    assert plain.score.j != detrended.score.j
    bag = write_bag(tmp_path / "r", rec.raw)
    assert main([str(bag), "--json", "-p", "detrend=false"]) == 0
    assert json.loads(capsys.readouterr().out)["score"]["j"] == pytest.approx(plain.score.j, rel=1e-12)
    assert main([str(bag), "-p", "bogus_param=3"]) == 2
    assert "unknown parameter 'bogus_param'" in capsys.readouterr().err
    assert main([str(bag), "-p", "min_coverag=0.9"]) == 2
    assert "did you mean min_coverage?" in capsys.readouterr().err
    assert main([str(bag), "-p", "detrend=maybe"]) == 2
    assert "detrend must be true or false, got 'maybe'" in capsys.readouterr().err
    with pytest.raises(ParamsFileError, match="unknown parameter"):
        analyse_report(rec.raw, [], {"window": 3})


def test_json_is_valid_with_missing_numbers_as_null(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = imu_recording(duration_s=10.0, fs=100.0, mount_rpy_deg=(180.0, 0.0, 0.0), gaps=((5.0, 0.5),))
    rep = run_health(tmp_path, rec.raw, "-p", "mount_source=config", "-p", "bias_source=none", capsys=capsys)
    assert rep["score"]["j"] is None and rep["score"]["rms_accel_z"] is None and not rep["score"]["valid"]
    assert rep["health"]["gravity_problem"].startswith("mean a_z -19.")
    assert rep["health"]["gravity_tilt_deg"] is None  # no standstill: not measured


def test_mean_fallback_is_the_same_pushed_in_chunks() -> None:
    rec = imu_recording(duration_s=40.0, fs=200.0, mount_rpy_deg=(90.0, 3.0, 0.0), seed=7)
    cfg = IngestConfig(output_rate_hz=200.0, mount_source="standstill", bias_source="standstill")
    r = rec.raw
    whole, h = ingest_all(r.stamp_ns, r.accel, r.gyro, cfg)
    ing = ImuIngestor(cfg)
    parts = [
        ing.push(r.stamp_ns[i : i + 777], r.accel[i : i + 777], r.gyro[i : i + 777]) for i in range(0, len(r), 777)
    ]
    chunked = IngestOutput.concatenate([p for p in [*parts, ing.flush()] if len(p)])
    assert np.array_equal(chunked.accel, whole.accel) and np.array_equal(chunked.gyro, whole.gyro)
    assert h.bias_source == "long-run mean over 30.0 s (no standstill found)"


def test_a_campaign_folder_is_named_with_the_bag_to_give(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # outside review 2026-11-29: a campaign folder was called a truncated or corrupt bag (ros2 bag reindex advice)
    camp = tmp_path / "camp"
    (camp / "bags" / "trial_0001").mkdir(parents=True)
    (camp / "journal.jsonl").write_text("")
    assert main([str(camp)]) == 2
    assert f"{camp} is a campaign folder: give one of its bags, e.g. {camp}/bags/trial_0001" in capsys.readouterr().err
