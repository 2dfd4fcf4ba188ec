"""The main job end to end: a short campaign through the real graph, each node in its own process.

Then, on what it left in its folder: every trial's bag opens; rescoring reproduces every live J to 1e-9;
replaying the bags into the live chain gives the same J again; the report is made; and the
recommendation beats the best trial of the initial design on the simulator's true J.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from bac_agent.journal import read_journal
from bac_campaign.rescore import rescore
from bac_measure.recording import bac_typestore

from conftest import ROOT, fresh_domain

pytestmark = [pytest.mark.integration, pytest.mark.slow]
REAL_BAG = ROOT / "src" / "bac_measure" / "test" / "data" / "robot_localization_test2.bag"
BUDGET = 8


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import os

    camp = tmp_path_factory.mktemp("campaign") / "c"
    env = {**os.environ, "ROS_DOMAIN_ID": str(fresh_domain()), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    cmd = [
        sys.executable, "-m", "bac_bringup.cli", "launch", "sim", "--campaign-dir", str(camp),
        "--log-dir", str(camp / "logs"), "--timeout", "400",
        "-p", f"bo_agent.budget:={BUDGET}", "-p", "bo_agent.seed:=3", "-p", "vehicle_sim.seed:=3",
        "-p", "bo_agent.confirmation_run:=false",
    ]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=False)
    if proc.returncode != 0:
        logs = "\n".join(f"--- {f.name}\n{f.read_text()[-3000:]}" for f in sorted((camp / "logs").glob("*.log")))
        pytest.fail(f"campaign failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{logs}")
    return camp


def live_scores(camp: Path) -> dict[int, float]:
    return {int(e["trial_id"]): float(e["j"]) for e in read_journal(camp / "journal.jsonl").events
            if e["event"] == "trial_scored"}  # fmt: skip


def test_every_trial_has_a_bag_that_opens(campaign: Path) -> None:
    bags = sorted((campaign / "bags").iterdir())
    assert [b.name for b in bags] == [f"trial_{i:04d}" for i in range(1, BUDGET + 1)]
    for bag in bags:
        assert list(bag.glob("*.mcap")) and (bag / "metadata.yaml").exists()
        with AnyReader([bag], default_typestore=bac_typestore()) as reader:
            topics = {c.topic for c in reader.connections}
            assert {"/imu/data_raw", "/imu/vehicle", "/vehicle/odom", "/bac/trial", "/bac/run_segment",
                    "/bac/run_score", "/bac/calibration"} <= topics, (bag, topics)  # fmt: skip
            scores = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                      if c.topic == "/bac/run_score"]  # fmt: skip
            assert scores and all(s.trial_id == int(bag.name[-4:]) for s in scores)
    # the launch configuration is kept with the campaign
    rec = json.loads((campaign / "config" / "launch.json").read_text())
    assert rec["profile"] == "sim" and rec["params_files"][-1].endswith("overrides.yaml")


def test_rescoring_reproduces_every_live_j(campaign: Path) -> None:
    result = rescore([campaign])
    live = live_scores(campaign)
    # every run the live graph scored (a run lost in transport live may be driven again: it has no live J)
    valid = [r for r in result.runs if r.live_j is not None and not math.isnan(r.live_j)]
    assert len(valid) == len(live) == BUDGET
    for r in valid:
        assert r.score.valid, r.score.reason
        assert abs(r.j - r.live_j) <= 1e-9, r.run
        assert abs(r.j - live[r.run.trial_id]) <= 1e-9, r.run
    # a changed KPI changes J: the rescoring really recomputes
    changed = {r.key: r for r in rescore([campaign], overrides={"kpi_scorer": {"weight_pitch_rate": 0.0}}).runs}
    for a in valid:
        b = changed[a.key]
        assert b.j == pytest.approx(a.score.rms_accel_z, rel=1e-12) and b.j < a.j


def replays_to_the_recorded_j(camp: Path, ros_env: dict[str, str], out: Path, *extra: str) -> str:
    """``bac replay`` of ``camp`` at 10x: every run valid with its recorded J to 1e-9. Returns the replay's output."""
    cmd = [sys.executable, "-m", "bac_bringup.cli", "replay", str(camp), "--rate", "10", "--output", str(out), *extra]
    proc = subprocess.run(cmd, env=ros_env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    runs = [r for r in json.loads(out.read_text())["runs"] if r["recorded_j"] is not None]
    assert len(runs) == BUDGET
    for r in runs:
        assert r["valid"], f"{r['reason']!r} in {r}\n{proc.stderr[-6000:]}"
        assert abs(r["replayed_j"] - r["recorded_j"]) <= 1e-9, r
    return proc.stdout + proc.stderr


def test_replay_into_the_live_chain_gives_the_same_j(campaign: Path, ros_env: dict[str, str], tmp_path: Path) -> None:
    replays_to_the_recorded_j(campaign, ros_env, tmp_path / "replay.json")


def _stamp_scored_mid_run(bag: Path) -> float:
    """Rewrite ``bag`` with its run's SCORED trial message stamped (and logged) in the middle of the run's cut
    window, before the last samples the run needs: what a live agent whose clock lags the simulation records.
    Returns how far (s) the message moved back."""
    import shutil

    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    store = bac_typestore()
    with Reader(bag) as reader:
        msgs = [(c, t, raw) for c, t, raw in reader.messages()]
        conns = list(reader.connections)
    seg = next(store.deserialize_cdr(raw, c.msgtype) for c, _, raw in msgs if c.topic == "/bac/run_segment")
    mid_ns = int((seg.window_start_s + seg.window_length_s / 2) * 1e9)
    out = bag.with_name(bag.name + ".raced")
    moved = 0.0
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        new = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store) for c in conns}
        for c, t, raw in msgs:
            m = store.deserialize_cdr(raw, c.msgtype) if c.topic == "/bac/trial" else None
            if m is not None and m.state == 4:  # SCORED
                moved = t / 1e9 - mid_ns / 1e9
                m.stamp.sec, m.stamp.nanosec = divmod(mid_ns, 1_000_000_000)
                writer.write(new[c.id], mid_ns, bytes(store.serialize_cdr(m, c.msgtype)))
            else:
                writer.write(new[c.id], t, raw)
    shutil.rmtree(bag)
    out.rename(bag)
    return moved


def test_replay_plays_on_past_a_score_stamped_before_the_runs_last_samples(
    campaign: Path, ros_env: dict[str, str], tmp_path: Path
) -> None:
    """A loaded machine records a run's SCORED before the run's last samples (CI 2026-11-29): the player holds that
    state until the replayed run is scored, and plays the samples recorded after it meanwhile, so every run is
    scored whole and gives its J again (before the fix: the hold timed out and the run was cancelled)."""
    import shutil

    camp = tmp_path / "c"
    shutil.copytree(campaign, camp, ignore=shutil.ignore_patterns("logs", "export", "report*"))
    moved = [_stamp_scored_mid_run(b) for b in sorted((camp / "bags").iterdir())]
    assert all(m > 1.0 for m in moved), moved  # each SCORED now sits seconds before its run's last samples
    text = replays_to_the_recorded_j(camp, ros_env, tmp_path / "replay.json", "-p", "bag_player.hold_for_score_s:=15")
    assert "playing on" not in text  # no hold timed out


def test_the_recommendation_is_the_optimum_and_no_worse_than_the_best_initial_trial(campaign: Path) -> None:
    """Found (true gap <= 0.05) after 8 runs, and not worse than the best run of the initial design by more than
    1 % of the J range (when that run is itself next to the optimum, the two differ by less than the noise)."""
    from bac_sim.problems import get_problem

    events = read_journal(campaign / "journal.jsonl").events
    initial = [e for e in events if e["event"] == "trial_scored" and e["kind"] == 0]
    assert len(initial) >= 3
    best_initial = min(initial, key=lambda e: e["j"])
    rec = json.loads((campaign / "recommendation.json").read_text())["params"]
    p = get_problem("bump_c1")
    names = list(p.names)
    j_rec, j_init = p.true_j(np.array([[rec[n] for n in names], [best_initial["params"][n] for n in names]]))
    g_rec, g_init = float(p.gap(j_rec)), float(p.gap(j_init))
    assert g_rec <= 0.05 and g_rec <= g_init + 0.01, (rec, best_initial["params"], g_rec, g_init)


def test_the_campaign_exports_to_mdf4(campaign: Path, tmp_path: Path) -> None:
    """bac export --mf4 of the campaign: asammdf reopens every trial's raw, ingested and aligned signals with their
    units, and J and the calibration of every run as they are in the journal."""
    from asammdf import MDF

    from bac_campaign.export import main as export_main

    out = campaign / "export" / "c.mf4"
    assert export_main([str(campaign), "--mf4", "--out", str(out)]) == 0
    events = read_journal(campaign / "journal.jsonl").events
    proposed = {e["trial_id"]: e["params"] for e in events if e["event"] == "trial_proposed"}
    scored = {e["trial_id"]: e["j"] for e in events if e["event"] == "trial_scored"}
    mdf = MDF(out)
    try:
        units = {c.name: c.unit for g in mdf.groups for c in g.channels}
        for tid in proposed:
            p = f"trial_{tid:04d}"
            assert units[f"{p}.raw.accel_z"] == "m/s^2" and units[f"{p}.raw.gyro_y"] == "rad/s"
            assert units[f"{p}.vehicle.accel_z"] == "m/s^2" and units[f"{p}.odom.speed"] == "m/s"
        trial = mdf.get("campaign.trial_id").samples.astype(int)
        valid = mdf.get("campaign.valid").samples.astype(bool)
        j = mdf.get("campaign.J").samples
        for name in ("damping_front", "damping_rear"):
            values = mdf.get(f"campaign.{name}").samples
            assert all(values[i] == proposed[int(t)][name] for i, t in enumerate(trial))
        for tid, jv in scored.items():  # the J the agent was told is the J of the trial's last valid run
            assert jv == pytest.approx(float(j[(trial == tid) & valid][-1]), abs=1e-12)
            aligned = [n for n in units if n.startswith(f"trial_{tid:04d}.a") and n.endswith(".accel_z_aligned")]
            assert aligned and all(units[n] == "m/s^2" for n in aligned)
    finally:
        mdf.close()
    # the one file rescores as the folder: every live J from the recorded imu/vehicle, and re-ingested from the raw
    # IMU the same J as the folder's re-ingestion (the launch's data, its runs' starts, the campaign's config)
    folder = {r.key: r for r in rescore([campaign], reingest=True).runs}
    exported = {r.key: r for r in rescore([out], reingest=True).runs}
    assert set(exported) == set(folder) and len(folder) >= BUDGET
    assert all(exported[k].j == folder[k].j and exported[k].live_j == folder[k].live_j for k in folder)
    alone = tmp_path / "c.mf4"  # mailed on, without its folder
    shutil.copy(out, alone)
    valid = [r for r in rescore([alone]).runs if r.live_j is not None and not math.isnan(r.live_j)]
    assert len(valid) == BUDGET and all(abs(r.j - r.live_j) <= 1e-9 for r in valid)
    # and its report is the folder's: the same summary, the same recorded signals of the best and worst runs
    from bac_campaign.report import make_report

    mine = make_report(alone, truth_name="bump_c1")
    theirs = make_report(campaign, out=tmp_path / "folder_report", truth_name="bump_c1")
    assert Path(mine["html"]).parent == tmp_path / "c.report" and mine["notes"] == [] == theirs["notes"]
    assert mine["summary"] == theirs["summary"]
    for fig in ("signals.png", "spectra.png"):  # the windows' samples and their sample rate, exactly
        assert (tmp_path / "c.report" / fig).read_bytes() == (tmp_path / "folder_report" / fig).read_bytes(), fig
    assert str(alone) in Path(mine["html"]).read_text()
    # every stream of every bag, to the nanosecond: the raw IMU with its receive times, the announcements
    from bac_campaign.exportio import read_export
    from bac_campaign.rescore import read_bag

    unpacked = tmp_path / "unpacked"
    unpacked.mkdir()
    for b in read_export(alone, unpacked):
        bag = read_bag(campaign / "bags" / b.name, None, None)
        assert b.imu_raw is not None and bag.imu_raw is not None and b.trials == bag.trials, b.name
        assert np.array_equal(b.imu_raw.recv_ns, bag.imu_raw.recv_ns) and b.imu_raw.has_recv
        assert np.array_equal(b.imu_raw.gyro, bag.imu_raw.gyro) and np.array_equal(b.imu_raw.accel, bag.imu_raw.accel)
        assert b.odom is not None and bag.odom is not None
        assert all(
            np.array_equal(getattr(b.odom, f), getattr(bag.odom, f))
            for f in ("stamp_ns", "distance_m", "speed_mps", "position_y_m", "position_z_m")
        )


def test_the_report_is_made(campaign: Path) -> None:
    from bac_campaign.report import make_report

    result = make_report(campaign, truth_name="bump_c1")
    names = {Path(f).name for f in result["figures"]}
    assert {"gp_contour.png", "j_per_trial.png", "signals.png", "spectra.png"} <= names
    html = Path(result["html"]).read_text()
    assert html.count("<tr>") >= BUDGET + 1  # a row per trial
    assert math.isfinite(result["summary"]["gap"]) and result["summary"]["trials"] == BUDGET
    assert result["notes"] == [] and "Not shown" not in html  # every run's bag read


def test_rescoring_a_ros1_bag_of_a_real_robot() -> None:
    """The real recording ships with the project (src/bac_measure/test/data): this test never skips."""
    whole = rescore([REAL_BAG], window="whole")
    (run,) = whole.runs
    # the health report's figure: mount and bias from the robot's standstill at 59.4 s (the whole recording is
    # searched offline; 0.402421 with the configured level mount and nominal gravity)
    assert run.score.valid and run.score.j == pytest.approx(0.411594, abs=1e-5)
    assert any("50.0 Hz" in n for n in whole.notes)
    assert any("mount roll -3.2 pitch 1.8 deg from standstill, bias from standstill" in n for n in whole.notes)
    cut: Any = rescore([REAL_BAG])
    (run,) = cut.runs
    assert not run.score.valid and "too slow" in run.score.reason  # a robot at 3 km/h is no 30 km/h bump run
