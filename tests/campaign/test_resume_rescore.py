"""A sim campaign whose agent is killed (SIGKILL) three times, each time relaunched on the same campaign folder
(a resume), then rescored offline: every run comes from the launch in which it was driven.

Sim time starts again at 0 with each launch, so the bags of different launches overlap in time; a run must be
found by its (campaign, trial, attempt), never by time alone. Every scored run's rescored J equals its live J
(same configuration) and none is missing, swapped or marked invalid.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from bac_campaign.launches import launch_of_bags
from bac_campaign.rescore import rescore

from conftest import wait_for

pytestmark = pytest.mark.integration

AGENT_MODULE = "bac_agent.agent_node"


def journal(camp: Path) -> list[dict[str, Any]]:
    """The complete lines of the journal (the agent may be writing the next one)."""
    path = camp / "journal.jsonl"
    if not path.exists():
        return []
    return [json.loads(x) for x in path.read_text().split("\n")[:-1] if x.strip()]


def descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        for c in children.get(p, []):
            out.append(c)
            todo.append(c)
    return out


def agent_pid(launcher: subprocess.Popen[str]) -> int | None:
    for pid in descendants(launcher.pid):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if AGENT_MODULE.encode() in cmd:
            return pid
    return None


def launch(camp: Path, env: dict[str, str]) -> subprocess.Popen[str]:
    cmd = [sys.executable, "-m", "bac_bringup.cli", "launch", "sim", "--campaign-dir", str(camp),
           "--log-dir", str(camp / "logs"), "--timeout", "400",
           "-p", "bo_agent.budget:=4", "-p", "bo_agent.seed:=5", "-p", "vehicle_sim.seed:=5",
           "-p", "bo_agent.confirmation_run:=true"]  # fmt: skip
    out = (camp.parent / f"{camp.name}-launcher.log").open("a")
    return subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, text=True)


def logs(camp: Path) -> str:
    files = [*sorted((camp / "logs").glob("*.log")), camp.parent / f"{camp.name}-launcher.log"]
    return "\n".join(f"--- {f.name}\n{f.read_text()[-3000:]}" for f in files if f.exists())


def kill_agent_when(
    camp: Path, env: dict[str, str], condition: Callable[[list[dict[str, Any]]], bool], what: str
) -> None:
    """Launch (or resume) the campaign, SIGKILL bo_agent as soon as the journal meets ``condition``, and wait for
    the launcher to end the graph."""
    launcher = launch(camp, env)
    try:
        n0 = len(journal(camp))
        wait_for(lambda: condition(journal(camp)[n0:]), 300, interval=0.005, what=what)
        pid = wait_for(lambda: agent_pid(launcher), 10, what="the bo_agent process")
        os.kill(pid, signal.SIGKILL)
        launcher.wait(timeout=120)
    finally:
        if launcher.poll() is None:
            launcher.kill()
    assert launcher.returncode != 0, logs(camp)  # a node died: the graph ended with an error


def count(ev: list[dict[str, Any]], kind: str) -> int:
    return sum(e["event"] == kind for e in ev)


def driving(camp: Path, ev: list[dict[str, Any]]) -> bool:
    """vehicle_sim has begun the drive of the last run announced in ``ev`` (its log says so)."""
    ready = [e for e in ev if e["event"] == "run_ready"]
    if not ready:
        return False
    log = camp / "logs" / "vehicle_sim.log"
    line = f"driving trial {ready[-1]['trial_id']} attempt {ready[-1]['attempt']}:"
    return log.exists() and line in log.read_text(errors="replace")


def test_rescoring_a_campaign_resumed_after_kills_gives_every_live_j(ros_env: dict[str, str], tmp_path: Path) -> None:
    camp = tmp_path / "killed"
    camp.mkdir()
    t0 = time.monotonic()
    # 1: in the middle of trial 1's drive
    kill_agent_when(camp, ros_env, lambda ev: driving(camp, ev), "trial 1 being driven")
    # 2: right after the resumed launch's first score: the next trial is being chosen or applied
    kill_agent_when(camp, ros_env, lambda ev: count(ev, "trial_scored") >= 1, "a score after the first resume")
    # 3: during the drive of the next trial after one scored in this launch
    kill_agent_when(
        camp,
        ros_env,
        lambda ev: count(ev, "trial_scored") >= 1 and count(ev, "run_ready") >= 2 and driving(camp, ev),
        "the second drive after the second resume",
    )
    final = launch(camp, ros_env)
    assert final.wait(timeout=400) == 0, logs(camp)
    elapsed = time.monotonic() - t0

    ev = journal(camp)
    assert sum(e["event"] == "campaign_resumed" for e in ev) == 3
    assert ev[-1]["event"] == "campaign_done"
    scored = {(e["trial_id"], e["attempt"]): e["j"] for e in ev if e["event"] == "trial_scored"}
    assert len({t for t, _ in scored}) == 5  # 4 trials and the confirmation run, each scored once
    bags = sorted(p.name for p in (camp / "bags").iterdir() if p.is_dir())
    assert any(".r" in b for b in bags), bags  # interrupted trials were driven again into new bags

    # the recorder wrote down which launch recorded each bag
    index = launch_of_bags(camp)
    assert set(index) == set(bags) and len({launch for _, launch in index.values()}) == 4, index
    result = rescore([camp])
    assert not any("not in launches.jsonl" in n for n in result.notes), result.notes
    runs: dict[tuple[int, int], Any] = {}
    for r in result.runs:
        key = (r.run.trial_id, r.run.attempt)
        assert key not in runs, f"run {key} rescored twice"
        runs[key] = r
    for key, live_j in sorted(scored.items()):
        assert key in runs, f"scored run {key} missing from the rescore: {sorted(runs)}"
        r = runs[key]
        assert r.score.valid, f"run {key} valid live (J={live_j}) is rescored invalid: {r.score.reason}"
        assert r.live_j == pytest.approx(live_j, abs=1e-12), (key, r.live_j, live_j)
        assert math.isclose(r.j, live_j, rel_tol=0.0, abs_tol=1e-9), f"run {key}: rescored {r.j}, live {live_j}"
    # the runs rescored are runs the agent announced (the interrupted ones too, when their announcement was
    # published before the kill)
    ready = {(e["trial_id"], e["attempt"]) for e in ev if e["event"] == "run_ready"}
    assert set(runs) <= ready, (sorted(runs), sorted(ready))
    print(f"4 launches, {len(bags)} bags, {len(runs)} runs rescored; {elapsed:.0f} s of launches")
