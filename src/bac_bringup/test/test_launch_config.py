"""The configuration a launch saves (config/, config.resumeN/) is kept only when the launch's agent started or
resumed the campaign: a refused launch's would be read by bac rescore and bac report as the campaign's."""

from __future__ import annotations

from pathlib import Path

from bac_agent.journal import Journal
from bac_bringup.launcher import drop_unused_config
from bac_campaign.launches import campaign_launches_begun


def _saved(camp: Path, name: str) -> Path:
    d = camp / name
    d.mkdir(parents=True)
    (d / "launch.json").write_text("{}")
    return d


def test_a_first_launch_that_never_started_the_campaign_leaves_no_config(tmp_path: Path) -> None:
    camp = tmp_path / "camp"
    camp.mkdir()
    before = campaign_launches_begun(camp)
    assert before == 0  # no journal yet
    saved = _saved(camp, "config")
    assert drop_unused_config(saved, camp, before) and not saved.exists()


def test_a_refused_resume_leaves_no_config_resume(tmp_path: Path) -> None:
    camp = tmp_path / "camp"
    camp.mkdir()
    with Journal(camp) as j:
        j.append("campaign_started", campaign_id="c")
    first = _saved(camp, "config")
    before = campaign_launches_begun(camp)
    assert before == 1
    refused = _saved(camp, "config.resume1")
    assert drop_unused_config(refused, camp, before) and not refused.exists() and first.exists()
    # a launch that did resume keeps its configuration
    resumed = _saved(camp, "config.resume1")
    with Journal(camp) as j:
        j.append("campaign_resumed", campaign_id="c")
    assert not drop_unused_config(resumed, camp, before) and resumed.exists()


def test_an_unreadable_journal_keeps_everything(tmp_path: Path) -> None:
    camp = tmp_path / "camp"
    camp.mkdir()
    (camp / "journal.jsonl").write_text('{"seq":0,"event":"campaign_started"}\n{not json at all\n{"seq":2}\n')
    before = campaign_launches_begun(camp)
    saved = _saved(camp, "config.resume1")
    assert not drop_unused_config(saved, camp, before) and saved.exists()
