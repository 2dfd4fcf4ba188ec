"""What a campaign folder tells the cockpit: the journal (trials, recommendation, last apply), the configuration
the campaign was launched with (the target speed) and, for a finished campaign, its bags (the runs' signals,
scores, the calibration the ECU confirmed, the last ``bac/trial``).

The trials and the recommendation are read by :func:`bac_campaign.report.load_campaign`, the same reading as
``bac report``, so the cockpit and the report show the same campaign.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bac_agent.journal import JOURNAL_NAME, JournalError, read_journal
from bac_campaign.report import ReportError, campaign_status, load_campaign
from bac_cockpit.state import (
    CalibrationView,
    ScoreView,
    SegmentView,
    TrialRow,
    TrialView,
    calibration_from_msg,
    finite_or_none,
    score_from_msg,
    segment_from_msg,
    trial_from_msg,
)
from bac_common.errors import BacError

NODE_SEGMENTER = "run_segmenter"


@dataclass
class FolderFacts:
    """The journal's view of a campaign."""

    info: dict[str, Any]
    rows: list[TrialRow]
    recommendation: dict[str, Any] | None
    last_apply: dict[str, Any] | None
    n_events: int
    ended: str = ""  # "done", "failed", "paused" (the ECU link stayed down; resumable) or "" (running)


def journal_path(campaign_dir: str | Path) -> Path:
    return Path(campaign_dir) / JOURNAL_NAME


def why_no_campaign(campaign_dir: str | Path) -> str:
    """Why :func:`read_folder` found no campaign in the folder: no journal yet, or the reading's own error (a
    damaged line named by its number, as ``bac report`` names it)."""
    try:
        load_campaign(Path(campaign_dir))
    except (ReportError, JournalError) as exc:
        return str(exc)
    return f"{campaign_dir} has no campaign journal ({JOURNAL_NAME} starting with campaign_started)"


def read_folder(campaign_dir: str | Path) -> FolderFacts | None:
    """The campaign as its journal has it; None while there is no journal (the agent has not started)."""
    path = Path(campaign_dir)
    try:
        camp = load_campaign(path)
        events = read_journal(path / JOURNAL_NAME).events
    except (ReportError, JournalError):
        return None
    std: dict[int, float] = {}
    last_apply: dict[str, Any] | None = None
    ended = ""
    budget = 0
    for e in events:
        kind = e.get("event")
        if kind == "campaign_started":
            budget = int(e.get("budget") or 0)
        elif kind == "trial_proposed":
            std[int(e.get("trial_id") or 0)] = _num(e.get("predicted_std"))
        elif kind == "apply_result":
            last_apply = {
                "trial_id": int(e.get("trial_id") or 0),
                "apply_try": int(e.get("apply_try") or 0),
                "success": bool(e.get("success")),
                "error_code": int(e.get("error_code") or 0),
                "message": str(e.get("message") or ""),
                "latency_s": finite_or_none(e.get("latency_s")),
                "attempts": int(e["attempts"]) if e.get("attempts") is not None else None,
                "wall_time": str(e.get("wall_time") or ""),
            }
        elif kind == "campaign_done":
            ended = "done"
        elif kind == "campaign_failed":
            ended = "failed"
        elif kind == "campaign_paused":  # the ECU link stayed down: stopped, resumable
            ended = "paused"
        elif kind == "campaign_resumed" and ended == "paused":
            ended = ""
    rows = [
        TrialRow(
            trial_id=t.trial_id,
            kind=t.kind,
            params=dict(t.params),
            j=t.j,
            predicted_j=t.predicted_j,
            predicted_std=std.get(t.trial_id, math.nan),
            attempts=t.attempts,
            status=t.status,
            reason=t.reason,
            rejected=list(t.rejected),
        )
        for t in camp.trials
    ]
    info = {
        "campaign_id": camp.campaign_id,
        "path": str(path.resolve()),
        "strategy": camp.strategy,
        "budget": budget,
        "definition": camp.definition.name,
        "description": camp.definition.description or camp.definition.name,
        "dimensions": [{"name": d.name, "lower": d.lower, "upper": d.upper} for d in camp.definition.dimensions],
        "status": campaign_status(camp),
        "ended": ended,
    }
    rec = None
    if camp.recommendation is not None:
        rec = {
            "params": {k: float(v) for k, v in camp.recommendation["params"].items()},
            "predicted_j": finite_or_none(camp.recommendation.get("predicted_j")),
            "predicted_std": finite_or_none(camp.recommendation.get("predicted_std")),
            "final": True,
        }
    return FolderFacts(info, rows, rec, last_apply, len(events), ended)


def _num(v: Any) -> float:
    try:
        return float(v) if v is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


def speed_config(campaign_dir: str | Path) -> tuple[float, str, tuple[float, float] | None] | None:
    """The segmenter's target speed (m/s), mode and, in distance mode, the section (m) the campaign was launched
    with (its ``config/``); None without one."""
    from bac_campaign.rescore import default_params_files
    from bac_measure.measure_config import load_node_params

    files = default_params_files(Path(campaign_dir))
    if not files:
        return None
    try:
        p = load_node_params(files, NODE_SEGMENTER)
    except BacError:
        return None
    target = float(p.get("target_speed_mps", math.nan))
    mode = str(p.get("mode", "event"))
    section = None
    if mode == "distance":
        section = (float(p.get("distance_start_m", math.nan)), float(p.get("distance_end_m", math.nan)))
    return target, mode, section


# --- bags (offline) ------------------------------------------------------------------------------------------


@dataclass
class Recorded:
    """What a finished campaign's bags hold for the cockpit, in the order it was recorded."""

    segments: list[SegmentView] = field(default_factory=list)
    scores: list[ScoreView] = field(default_factory=list)
    calibrations: list[CalibrationView] = field(default_factory=list)
    last_trial: TrialView | None = None
    bags: list[str] = field(default_factory=list)


def bag_dirs(campaign_dir: str | Path) -> list[Path]:
    bags = Path(campaign_dir) / "bags"
    if not bags.is_dir():
        return []
    return sorted(d for d in bags.iterdir() if d.is_dir())


CAMPAIGN_TOPICS = ("/bac/run_segment", "/bac/run_score", "/bac/calibration", "/bac/trial")


def _messages(bag: Path) -> Iterator[tuple[str, Any]]:
    """(topic, message) of the cockpit's topics in one pass over the bag, in recording order; a bag that cannot
    be read gives nothing (the journal still has the trials)."""
    from rosbags.highlevel import AnyReader

    from bac_measure.recording import bac_typestore

    try:
        with AnyReader([bag], default_typestore=bac_typestore()) as reader:
            conns = [c for c in reader.connections if c.topic in CAMPAIGN_TOPICS]
            if not conns:  # rosbags reads every message when given no connections
                return
            for c, _, raw in reader.messages(connections=conns):
                yield c.topic, reader.deserialize(raw, c.msgtype)
    except Exception:  # rosbags raises many kinds on a damaged bag: the bag is passed over
        return


def read_bags(campaign_dir: str | Path, skip: set[str] | None = None) -> Recorded:
    """The segments, scores, confirmed calibrations and the last trial state of every bag not in ``skip``."""
    out = Recorded()
    for bag in bag_dirs(campaign_dir):
        if skip and bag.name in skip:
            continue
        out.bags.append(bag.name)
        for topic, m in _messages(bag):
            if topic == "/bac/run_segment":
                out.segments.append(segment_from_msg(m))
            elif topic == "/bac/run_score":
                out.scores.append(score_from_msg(m))
            elif topic == "/bac/calibration":
                out.calibrations.append(calibration_from_msg(m))
            else:
                out.last_trial = trial_from_msg(m)
    return out
