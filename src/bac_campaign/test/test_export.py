"""bac export CAMPAIGN --mf4: a campaign folder (journal + trial bags) as one MDF4 file that asammdf reopens with
every channel, its unit, comments, J and the calibration values."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from asammdf import MDF

from bac_agent.journal import Journal
from bac_campaign.export import ExportError, export_mf4, main
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition
from bac_measure.bagio import ImuArrays, imu_to_cdr, odom_to_cdr
from bac_measure.kpi import score
from bac_measure.recording import TrialBagWriter, bac_typestore
from bac_measure.segmentation import SegmentConfig, cut_run
from bac_measure.synthetic import bump_run

NS = 1_000_000_000
CAL = {1: {"damping_front": 0.25, "damping_rear": 0.75}, 2: {"damping_front": 0.6, "damping_rear": 0.3}}


def _msg(T: Any, name: str, **kw: Any) -> Any:
    return T[name](**kw)


def make_campaign(root: Path) -> Path:
    """Two trials of a bump campaign: journal, and per trial a bag with the raw IMU, imu/vehicle, odometry, the
    segment and the score, as campaign_recorder writes them."""
    camp = root / "camp"
    (camp / "bags").mkdir(parents=True)
    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    store = bac_typestore()
    T = store.types
    cfg = SegmentConfig(imu_rate_hz=200.0)
    with Journal(camp) as j:
        j.append("campaign_started", campaign_id="c1", definition=definition.to_dict(), strategy="bo", seed=0)
        for tid, params in CAL.items():
            j.append("trial_proposed", trial_id=tid, kind=0, params=params, predicted_j=None, predicted_std=None)
            j.append("run_ready", trial_id=tid, attempt=1)
            run = bump_run(seed=tid, t0_ns=(100 + 20 * tid) * NS, zeta=0.2 + 0.2 * tid)
            seg = cut_run(run.imu, run.odom, cfg, run.start_ns)
            sc = score(seg)
            assert seg.valid and sc.valid
            j.append("trial_scored", trial_id=tid, attempt=1, j=sc.j)
            t = run.imu.stamp_ns
            g = np.column_stack([np.zeros(t.size), np.zeros(t.size), run.imu.accel_z + 9.80665])
            raw = ImuArrays("imu/data_raw", "imu_link", t, t, g, np.column_stack([0 * t, run.imu.pitch_rate, 0 * t]))
            veh = ImuArrays("imu/vehicle", "base_link", t, t, g - [0, 0, 9.80665], raw.gyro)
            from bac_measure.bagio import OdomArrays

            o = run.odom
            odom = OdomArrays("vehicle/odom", "odom", o.stamp_ns, o.stamp_ns, o.distance_m, o.speed_mps)
            hdr = _msg(
                T,
                "std_msgs/msg/Header",
                stamp=_msg(
                    T, "builtin_interfaces/msg/Time", sec=seg.window_start_ns // NS, nanosec=seg.window_start_ns % NS
                ),
                frame_id="base_link",
            )
            segm = _msg(
                T,
                "bac_msgs/msg/RunSegment",
                header=hdr,
                campaign_id="c1",
                trial_id=tid,
                attempt=1,
                mode=0,
                window_start_s=seg.window_start_ns / 1e9,
                window_length_s=seg.window_length_s,
                distance_start_m=seg.distance_start_m,
                distance_step_m=0.0,
                sample_rate_hz=seg.sample_rate_hz,
                lag_s=seg.lag_s,
                alignment_score=seg.alignment_score,
                mean_speed_mps=seg.mean_speed_mps,
                target_speed_mps=seg.target_speed_mps,
                coverage=seg.coverage,
                accel_z=seg.accel_z,
                pitch_rate=seg.pitch_rate,
                accel_z_pre_roll=seg.pre_roll_accel_z,
                valid=True,
                reason="",
            )
            scm = _msg(
                T,
                "bac_msgs/msg/RunScore",
                header=hdr,
                campaign_id="c1",
                trial_id=tid,
                attempt=1,
                j=sc.j,
                rms_accel_z=sc.rms_accel_z,
                rms_pitch_rate=sc.rms_pitch_rate,
                weighted_rms_accel_z=sc.weighted_rms_accel_z,
                vdv_accel_z=sc.vdv_accel_z,
                kpi="rms",
                weight_accel_z=1.0,
                weight_pitch_rate=1.0,
                psd_frequency_hz=sc.psd_frequency_hz,
                psd_accel_z=sc.psd_accel_z,
                psd_pitch_rate=sc.psd_pitch_rate,
                valid=True,
                reason="",
                outcome_names=["peak_accel_z"],
                outcome_values=np.array([2.5]),
            )
            with TrialBagWriter(camp / "bags" / f"trial_{tid:04d}") as w:
                w.write_many(("imu/data_raw", ts, b) for ts, b in imu_to_cdr(raw))
                w.write_many(("imu/vehicle", ts, b) for ts, b in imu_to_cdr(veh))
                w.write_many(("vehicle/odom", ts, b) for ts, b in odom_to_cdr(odom))
                w.write(
                    "bac/run_segment", seg.window_start_ns, bytes(store.serialize_cdr(segm, "bac_msgs/msg/RunSegment"))
                )
                w.write("bac/run_score", seg.window_start_ns, bytes(store.serialize_cdr(scm, "bac_msgs/msg/RunScore")))
        j.append(
            "recommendation", params={"damping_front": 0.4, "damping_rear": 0.5}, predicted_j=0.9, predicted_std=0.01
        )
    return camp


def test_export_reopens_with_every_channel_unit_j_and_calibration(tmp_path: Path) -> None:
    camp = make_campaign(tmp_path)
    res = export_mf4(camp)
    assert res.path == camp / "export" / "camp.mf4" and res.runs == 2
    mdf = MDF(res.path)
    try:
        names = {c.name: (gi, c.unit) for gi, g in enumerate(mdf.groups) for c in g.channels if c.name != "time"}
        for tid in (1, 2):
            p = f"trial_{tid:04d}"
            for a in "xyz":
                assert names[f"{p}.raw.accel_{a}"][1] == "m/s^2" and names[f"{p}.raw.gyro_{a}"][1] == "rad/s"
            assert names[f"{p}.vehicle.accel_z"][1] == "m/s^2" and names[f"{p}.vehicle.pitch_rate"][1] == "rad/s"
            assert names[f"{p}.odom.distance"][1] == "m" and names[f"{p}.odom.speed_kmh"][1] == "km/h"
            assert names[f"{p}.a1.accel_z_aligned"][1] == "m/s^2"
        units = {c.name: c.unit for c in CalibrationDefinition.load(resolve_definition("controller_i")).parameters}
        for n in ("damping_front", "damping_rear"):
            s = mdf.get(f"campaign.{n}")
            assert s.unit == units[n] and list(s.samples) == [CAL[1][n], CAL[2][n]]
        jv = mdf.get("campaign.J")
        assert "RMS(a_z)" in jv.comment and np.all(np.isfinite(jv.samples)) and jv.samples.size == 2
        # the aligned window is the segment the KPI scored: its RMS gives the exported parts
        az = mdf.get("trial_0001.a1.accel_z_aligned")
        rms = float(np.sqrt(np.mean(az.samples**2)))
        assert rms == pytest.approx(float(mdf.get("campaign.rms_accel_z").samples[0]), rel=1e-12)
        assert az.timestamps.size == 500 and np.allclose(np.diff(az.timestamps), 1 / 200.0)
        # absolute time: the file starts at the campaign's first stamp, the raw IMU at 0
        assert mdf.header.start_time.timestamp() == pytest.approx(100 + 20 - 0.5, abs=1e-6)
        assert mdf.get("trial_0001.raw.accel_z").timestamps[0] == pytest.approx(0.0, abs=1e-9)
        assert "recommendation: damping_front=0.4, damping_rear=0.5" in mdf.header.comment
        assert "controller_i" in mdf.header.comment
        grp_comments = [g.channel_group.comment for g in mdf.groups]
        assert any("trial 1 attempt 1: aligned window" in c and "J 0." in c for c in grp_comments)
    finally:
        mdf.close()


def test_export_of_no_campaign_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ExportError, match="not a campaign folder"):
        export_mf4(tmp_path)
    assert main([str(tmp_path), "--mf4"]) == 2
    assert "not a campaign folder" in capsys.readouterr().err
    camp = make_campaign(tmp_path / "x")
    out = tmp_path / "out" / "c.mf4"
    assert main([str(camp), "--mf4", "--out", str(out), "--no-raw"]) == 0
    m = MDF(out)
    try:
        assert not any(c.name.endswith("raw.accel_x") for g in m.groups for c in g.channels)
        assert math.isfinite(float(m.get("campaign.J").samples[0]))
    finally:
        m.close()


def test_an_out_file_not_named_as_mdf_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--out x.csv wrote an MDF4 file named .csv (outside review 2026-11-29): refused, nothing written."""
    camp = make_campaign(tmp_path / "x")
    for name in ("c.csv", "c.mat", "c", "c.mdf", "c.MF4"):  # asammdf would write c.mf4 for the last two
        assert main([str(camp), "--out", str(tmp_path / name)]) == 2
        assert f"--out {tmp_path / name}: bac export writes ASAM MDF 4 only" in capsys.readouterr().err
        assert not (tmp_path / name).exists()
    assert main([str(camp), "--out", str(tmp_path / "c.mf4"), "--no-raw"]) == 0 and (tmp_path / "c.mf4").is_file()
