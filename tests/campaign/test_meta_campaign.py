"""The experimental phase through the graph: a campaign on a meta-parameter definition (paper sec. III-D).

``bac demo --definition`` runs the sim profile (each node in its own process, the car and the bridge sharing one)
on a definition whose one tuned dimension drives both raw parameters. The agent proposes the
meta-parameter; the bridge expands it and the ECU confirms both raw values; the run is scored and the
recommendation judged against that space's own optimum.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bac_common.paramspace import CalibrationDefinition

from conftest import ROOT

pytestmark = pytest.mark.integration
DEFINITION = ROOT / "tests" / "data" / "controller_i_one_meta.yaml"


def test_a_meta_parameter_campaign_runs_through_the_graph(ros_env: dict[str, str], tmp_path: Path) -> None:
    camp = tmp_path / "meta"
    proc = subprocess.run(
        [sys.executable, "-m", "bac_bringup.cli", "demo", "--definition", str(DEFINITION), "--budget", "4",
         "--campaign-dir", str(camp), "--timeout", "400"],
        env=ros_env, capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    last = proc.stdout.strip().splitlines()[-1]
    m = re.fullmatch(r"recommendation_gap_pct (-?\d+\.\d+)", last)
    assert m, last
    assert "controller_i_one_meta (1 tuned: damping)" in proc.stdout

    events = [json.loads(x) for x in (camp / "journal.jsonl").read_text().splitlines()]
    proposed = {e["trial_id"]: e["params"] for e in events if e["event"] == "trial_proposed"}
    applied = [e for e in events if e["event"] == "apply_result" and e["success"]]
    scored = [e for e in events if e["event"] == "trial_scored"]
    assert len(proposed) >= 4 and len(scored) >= 4
    assert all(set(p) == {"damping"} for p in proposed.values())
    for e in applied:
        # what the ECU confirmed: the meta value on both raw parameters (or the meta value itself, as asked)
        want = proposed[e["trial_id"]]["damping"]
        got = e["applied"]
        values = [got[k] for k in ("damping_front", "damping_rear", "damping") if k in got]
        assert values and all(abs(v - want) <= 1e-4 for v in values), (want, got)
    rec = json.loads((camp / "recommendation.json").read_text())
    assert set(rec["params"]) == {"damping"} and 0.0 <= rec["params"]["damping"] <= 1.0
    # judged in the one-dimensional space (its own J*, not Controller I's two-dimensional optimum)
    summary = json.loads((camp / "report" / "summary.json").read_text())["summary"]
    assert summary["recommendation"]["params"] == rec["params"]
    assert float(m.group(1)) == pytest.approx(100 * summary["gap"], abs=0.006)
    assert summary["true_j_of_recommendation"] >= summary["j_star"] - 1e-9
    assert "J* " in proc.stdout and "noise-free simulator" in proc.stdout


@pytest.mark.slow
@pytest.mark.timeout(900)  # road runs of Controller II: 3-5 min on a quiet machine, beyond 300 s under a CPU burner
def test_the_controller_ii_meta_parameter_file_runs_through_the_graph(ros_env: dict[str, str], tmp_path: Path) -> None:
    """The paper's experimental phase: Controller II on the test road through the shipped meta-parameter file
    (the bridge expands its meta-parameters into 20 raw parameters). The first trial is the file's best guess;
    no trial fails, the report is drawn and the recommendation is the reduced problem's optimum."""
    camp = tmp_path / "c2"
    definition = ROOT / "ros_ws" / "config" / "calibrations" / "controller_ii_reduced.yaml"
    proc = subprocess.run(
        [sys.executable, "-m", "bac_bringup.cli", "demo", "--scenario", "road", "--definition", str(definition),
         "--budget", "2", "--campaign-dir", str(camp), "--timeout", "750"],
        env=ros_env, capture_output=True, text=True, timeout=850, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "Traceback" not in proc.stdout + proc.stderr
    events = [json.loads(x) for x in (camp / "journal.jsonl").read_text().splitlines()]
    proposed = [e for e in events if e["event"] == "trial_proposed"]
    guess = CalibrationDefinition.load(definition).best_guess
    assert guess and proposed[0]["reason"] == "guess" and set(proposed[0]["params"]) == set(guess)
    assert all(proposed[0]["params"][k] == pytest.approx(v, abs=0.011) for k, v in guess.items())
    assert not [e for e in events if e["event"] in ("trial_failed", "run_rejected")]
    applied = [e for e in events if e["event"] == "apply_result" and e["success"]]
    assert applied and all(len(e["applied"]) == 20 for e in applied)  # every raw parameter confirmed
    summary = json.loads((camp / "report" / "summary.json").read_text())["summary"]
    assert summary["failed_trials"] == 0 and summary["gap"] <= 0.05
    assert (camp / "report" / "gp_contour.png").exists()
    assert "best guess: the simulation phase's optimum" in proc.stdout
