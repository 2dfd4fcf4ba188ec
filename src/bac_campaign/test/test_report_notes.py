"""A report whose runs' signals cannot be read says which and why (page, console, summary.json), never just leaves
them out (outside review 2026-11-29: with the best run's bag cut in half, or no bags/, signals.png silently lost
the best run's trace)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bac_agent.journal import Journal
from bac_campaign.report import main as report_main
from bac_campaign.report import make_report
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition


def campaign(path: Path) -> Path:
    definition = CalibrationDefinition.load(resolve_definition("controller_i"))
    with Journal(path) as j:
        j.append("campaign_started", campaign_id="c", definition=definition.to_dict(), strategy="bo", seed=0)
        for tid, (f, r, jv) in enumerate([(0.2, 0.3, 0.95), (0.6, 0.4, 0.91), (0.8, 0.9, 1.02)], start=1):
            params = {"damping_front": f, "damping_rear": r}
            j.append("trial_proposed", trial_id=tid, kind=1, params=params, predicted_j=None, predicted_std=None)
            j.append("trial_scored", trial_id=tid, attempt=1, j=jv)
    return path


def test_missing_or_unreadable_bags_are_named_on_the_page_and_the_console(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    camp = campaign(tmp_path / "c")
    result = make_report(camp)
    assert f"no bags/ folder in {camp}: no recorded signals to show" in result["notes"]
    assert any("the best run (trial 2) has no recorded segment" in n for n in result["notes"])
    assert any("the worst run (trial 3) has no recorded segment" in n for n in result["notes"])
    page = Path(result["html"]).read_text()
    assert "<h2>Not shown</h2>" in page and "the best run (trial 2) has no recorded segment" in page
    assert json.loads((camp / "report" / "summary.json").read_text())["notes"] == result["notes"]
    (camp / "bags" / "trial_0002").mkdir(parents=True)
    (camp / "bags" / "trial_0002" / "metadata.yaml").write_text("rosbag2_bagfile_information: [cut")
    assert report_main([str(camp)]) == 0
    out = capsys.readouterr().out
    assert "note: bags/trial_0002 is unreadable, its runs' signals are not shown" in out
    assert "note: the best run (trial 2) has no recorded segment" in out


def test_rescore_of_a_campaign_without_bags_says_so(tmp_path: Path) -> None:
    from bac_campaign.rescore import RescoreError, rescore

    camp = campaign(tmp_path / "c")
    with pytest.raises(RescoreError, match=r"is a campaign folder without bags/: nothing was recorded to rescore"):
        rescore([camp])
    # outside review 2026-11-29: --window whole on a campaign scored its first launch as one run "trial 1"
    (camp / "bags" / "trial_0001").mkdir(parents=True)
    with pytest.raises(RescoreError, match=r"--window whole scores one recording as one run; .* is a campaign"):
        rescore([camp], window="whole")


def test_a_truth_or_baseline_of_another_problem_is_refused_with_the_reason(tmp_path: Path) -> None:
    # outside review 2026-11-29: --truth road_c2 on a Controller I campaign, a baseline of another definition: a
    # traceback; --truth road_c1 on a bump campaign: a gap of 182 %
    from bac_campaign.report import ReportError

    camp = campaign(tmp_path / "c")
    with pytest.raises(ReportError, match=r"--truth road_c2 is a problem over p01, .*; this campaign tunes damping_"):
        make_report(camp, truth_name="road_c2")
    (camp / "config").mkdir()
    (camp / "config" / "sim.yaml").write_text("vehicle_sim:\n  ros__parameters:\n    scenario: bump\n")
    (camp / "config" / "launch.json").write_text(json.dumps({"params_files": ["sim.yaml"]}))
    with pytest.raises(ReportError, match="--truth road_c1 is the road scenario; this campaign drove the bump"):
        make_report(camp, truth_name="road_c1")
    assert Path(make_report(camp, truth_name="bump_c1")["html"]).is_file()  # its own problem: no objection
    other = tmp_path / "other"
    definition = CalibrationDefinition.load(resolve_definition("controller_ii"))
    with Journal(other) as j:
        j.append("campaign_started", campaign_id="o", definition=definition.to_dict(), strategy="grid", seed=0)
    with pytest.raises(ReportError, match="a baseline must search the same parameters"):
        make_report(camp, baseline_dir=other)
