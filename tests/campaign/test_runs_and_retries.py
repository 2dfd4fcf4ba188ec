"""Runs through the real graph (every node in its own process): slow runs, timeouts, retries, reports.

* A simulated run that takes longer to compute than the run timeout (at 10x real time) is still scored:
  no sim time passes while vehicle_sim computes a run.
* A retry after a timed-out run waits for a new drive: the rest of the drive in progress when the retry
  was announced is never scored as the new attempt.
* Three rejections in a row take three drives.
* A campaign with one valid run, and one with none, still get their report.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from bac_agent.journal import read_journal
from bac_measure.recording import bac_typestore

pytestmark = pytest.mark.integration


def launch(camp: Path, env: dict[str, str], *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "bac_bringup.cli", "launch", "sim", "--campaign-dir", str(camp),
           "--log-dir", str(camp / "logs"), "--timeout", str(timeout)]  # fmt: skip
    for o in overrides:
        cmd += ["-p", o]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout + 60, check=False)


def logs(camp: Path) -> str:
    return "\n".join(f"--- {f.name}\n{f.read_text()[-4000:]}" for f in sorted((camp / "logs").glob("*.log")))


def events(camp: Path, kind: str) -> list[dict[str, Any]]:
    return [e for e in read_journal(camp / "journal.jsonl").events if e["event"] == kind]


def bag_messages(camp: Path, topic: str) -> list[tuple[int, Any]]:
    """(receive stamp, message) of ``topic`` over every trial bag of the campaign."""
    out: list[tuple[int, Any]] = []
    store = bac_typestore()
    for bag in sorted((camp / "bags").iterdir()):
        with AnyReader([bag], default_typestore=store) as r:
            conns = [c for c in r.connections if c.topic.lstrip("/") == topic.lstrip("/")]
            if not conns:
                continue
            out += [(t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages(connections=conns)]
    return out


def drive_starts_ns(camp: Path) -> list[int]:
    """Sim-time stamps where vehicle_sim's odometry began a new drive (the car came back to the start between runs:
    the pose is back there after a silence)."""
    odom = sorted(
        ((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, t, m.pose.pose.position.x)
         for t, m in bag_messages(camp, "vehicle/odom")),
    )  # fmt: skip
    t = np.array([o[0] for o in odom])
    d = np.array([o[2] for o in odom])
    new = np.concatenate([[True], np.diff(d) < -1.0])
    return sorted(set(int(x) for x in t[new]))


BUMP_FAST = [
    "bo_agent.confirmation_run:=false",
    "bo_agent.seed:=5",
    "vehicle_sim.seed:=5",
]


def test_a_run_slower_to_compute_than_the_run_timeout_is_still_scored(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Each run takes 6 s of wall time more to compute (a slow machine): at 10x that is 60 s of sim time, far
    beyond the 20 s run timeout of the agent and the segmenter; the sim clock stands still meanwhile."""
    camp = tmp_path / "slow"
    proc = launch(
        camp, ros_env, *BUMP_FAST,
        "bo_agent.budget:=2", "vehicle_sim.compute_delay_s:=6.0",
        "bo_agent.run_timeout_s:=20.0", "run_segmenter.run_timeout_s:=20.0",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-2000:] + logs(camp)
    assert len(events(camp, "trial_scored")) == 2, logs(camp)
    assert events(camp, "run_rejected") == [], logs(camp)
    sim = (camp / "logs" / "vehicle_sim.log").read_text()
    computed = [float(x) for x in re.findall(r"computed in (\d+\.\d) s \(sim time stood still\)", sim)]
    assert len(computed) == 2 and min(computed) >= 6.0, sim[-3000:]
    assert "Traceback" not in sim


def test_a_retry_after_a_timed_out_run_scores_a_new_drive(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Trial 1's first drive starts 12.5 s late (the driver comes back round): the segmenter's 14 s timeout ends
    attempt 1 while the car is 1.5 s into its drive, before the bump. The rest of that drive, the bump with a
    clean approach included, comes after attempt 2 was announced; it must not be scored as attempt 2: the
    new drive is (the car comes back to the start, ~2.5 s at 60 km/h, and ends its window ~11 s after attempt 2's
    announcement)."""
    camp = tmp_path / "retry"
    proc = launch(
        camp, ros_env, *BUMP_FAST,
        "bo_agent.budget:=1", "run_segmenter.run_timeout_s:=14.0", "vehicle_sim.driver.start_delay_s:=[12.5, 0.0]",
        "vehicle_sim.run_out_s:=0.5",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-2000:] + logs(camp)
    rejected = events(camp, "run_rejected")
    assert [(e["trial_id"], e["attempt"]) for e in rejected] == [(1, 1)], logs(camp)
    assert "run timeout" in rejected[0]["reason"]
    (scored,) = events(camp, "trial_scored")
    assert (scored["trial_id"], scored["attempt"]) == (1, 2)
    # attempt 2's announcement came while the first drive was going on; the segment it was scored on lies in
    # the drive that began after it
    ready2 = next(e for e in events(camp, "run_ready") if e["trial_id"] == 1 and e["attempt"] == 2)
    t_ready2 = round(ready2["stamp"] * 1e9)
    starts = drive_starts_ns(camp)
    assert len(starts) == 2 and starts[0] < t_ready2 < starts[1], (starts, t_ready2)
    seg = next(m for _, m in bag_messages(camp, "bac/run_segment") if m.attempt == 2)
    window_start = seg.header.stamp.sec * 10**9 + seg.header.stamp.nanosec
    assert seg.valid and window_start > starts[1]
    sim = (camp / "logs" / "vehicle_sim.log").read_text()
    assert "driving trial 1 attempt 2" in sim


def test_three_rejections_take_three_drives_and_the_report_says_so(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Every run driven too slow: each rejection is followed by a new drive, three per trial, then the trial
    fails; the campaign ends with no valid run and still gets its report."""
    camp = tmp_path / "rejections"
    proc = launch(
        camp, ros_env, *BUMP_FAST,
        "bo_agent.budget:=1", "bo_agent.max_consecutive_failures:=1", "vehicle_sim.driver.bad_run_probability:=1.0",
    )  # fmt: skip
    assert proc.returncode != 0  # no recommendation: the campaign failed
    rejected = events(camp, "run_rejected")
    assert [e["attempt"] for e in rejected] == [1, 2, 3], logs(camp)
    assert all("too slow" in e["reason"] for e in rejected)
    starts = drive_starts_ns(camp)
    readies = [round(e["stamp"] * 1e9) for e in events(camp, "run_ready")]
    assert len(starts) == 3 and len(readies) == 3
    # each attempt was scored on its own drive, begun after it was announced
    segs = sorted((m.attempt, m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)
                  for _, m in bag_messages(camp, "bac/run_segment"))  # fmt: skip
    assert [a for a, _ in segs] == [1, 2, 3]
    for (_, w), ready, start in zip(segs, readies, starts, strict=True):
        assert ready <= start < w
    report = subprocess.run(
        [sys.executable, "-m", "bac_bringup.cli", "report", str(camp)],
        env=ros_env, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert report.returncode == 0 and "Traceback" not in report.stderr, report.stderr
    summary = json.loads((camp / "report" / "summary.json").read_text())["summary"]
    assert summary["scored_trials"] == 0 and summary["failed_trials"] == 1
    assert summary["status"].startswith("No valid run: all 1 trials failed")
    page = (camp / "report" / "report.html").read_text()
    assert "No valid run" in page and "too slow" in page


def test_a_campaign_with_one_valid_run_gets_its_report(ros_env: dict[str, str], tmp_path: Path) -> None:
    camp = tmp_path / "one"
    proc = launch(camp, ros_env, *BUMP_FAST, "bo_agent.budget:=1")
    assert proc.returncode == 0, proc.stdout[-2000:] + logs(camp)
    report = subprocess.run(
        [sys.executable, "-m", "bac_bringup.cli", "report", str(camp), "--truth", "bump_c1"],
        env=ros_env, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert report.returncode == 0 and "Traceback" not in report.stderr, report.stderr
    summary = json.loads((camp / "report" / "summary.json").read_text())["summary"]
    assert summary["scored_trials"] == 1 and "One valid run" in summary["status"]
    assert (camp / "report" / "gp_contour.png").stat().st_size > 10_000
    assert (camp / "report" / "j_per_trial.png").exists()
    assert len(summary["gap_after_each_run"]) == 1
