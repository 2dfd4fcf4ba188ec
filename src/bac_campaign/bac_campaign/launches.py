"""Which launch recorded which trial bag: ``<campaign_dir>/launches.jsonl``.

A campaign that was resumed (the graph relaunched on the same campaign folder)
has bags from several launches. Sim time starts again with each launch, so the
stamps of different launches overlap: offline tools (``bac rescore``) must cut
each run from the data of the launch in which it was driven, never by time
alone. The ``campaign_recorder`` therefore appends one line per bag it opens,
durably (the journal's format: one JSON object a line, fsynced), before it
writes anything into the bag::

    {"seq": 3, "event": "bag_opened", "wall_time": "...", "launch": "5f0c...", "bag": "trial_0003.r1",
     "trial_id": 3, "start_stamp_ns": 54130941680, "pid": 4242}

``launch`` is one id per recorder process (one per launch of the graph). Bags
recorded before this index existed are not in it: :func:`launch_of_bags`
then says so and the caller falls back on the journal.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

from bac_agent.journal import JOURNAL_NAME, Journal, JournalError, read_journal

LAUNCH_INDEX_NAME = "launches.jsonl"


class LaunchIndex:
    """The recorder's side: one launch id for this process, one durable line per bag opened."""

    def __init__(self, campaign_dir: str | Path) -> None:
        self.launch = uuid.uuid4().hex
        self._journal = Journal(campaign_dir, LAUNCH_INDEX_NAME)

    def bag_opened(self, bag: Path, trial_id: int, start_stamp_ns: int) -> None:
        self._journal.append(
            "bag_opened",
            launch=self.launch,
            bag=bag.name,
            trial_id=int(trial_id),
            start_stamp_ns=int(start_stamp_ns),
            pid=os.getpid(),
        )

    def close(self) -> None:
        self._journal.close()


def launch_of_bags(campaign_dir: str | Path) -> dict[str, tuple[int, str]]:
    """Bag folder name (in ``bags/``) -> (launch number from 0 in recording order, launch id), for the bags in the
    index."""
    events = read_journal(Path(campaign_dir) / LAUNCH_INDEX_NAME).events
    order: dict[str, int] = {}
    out: dict[str, tuple[int, str]] = {}
    for e in events:
        if e.get("event") != "bag_opened" or not e.get("bag") or not e.get("launch"):
            continue
        launch = str(e["launch"])
        n = order.setdefault(launch, len(order))
        out[str(e["bag"])] = (n, launch)
    return out


def campaign_launches_begun(campaign_dir: Path) -> int | None:
    """How many times the campaign's agent started or resumed it (its journal's campaign_started and
    campaign_resumed events); 0 without a journal, None when the journal cannot be read."""
    path = campaign_dir / JOURNAL_NAME
    if not path.exists():
        return 0
    try:
        events = read_journal(path).events
    except (JournalError, OSError):
        return None
    return sum(1 for e in events if e.get("event") in ("campaign_started", "campaign_resumed"))


__all__ = ["LAUNCH_INDEX_NAME", "LaunchIndex", "campaign_launches_begun", "launch_of_bags"]
