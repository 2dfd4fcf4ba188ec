"""The journal: durable appends, torn last lines, corruption, strict JSON."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

from bac_agent.bo import EngineConfig
from bac_agent.journal import (
    JOURNAL_NAME,
    Journal,
    JournalCorruptError,
    journaled_engine_options,
    read_journal,
    write_json_atomic,
)


def test_append_and_reopen(tmp_path: Path) -> None:
    with Journal(tmp_path / "c1") as j:
        j.append("campaign_started", names=["a"])
        rec = j.append("trial_scored", trial_id=1, j=1.5, predicted_j=math.nan)
    assert rec["seq"] == 1 and rec["predicted_j"] is None  # NaN written as null: strict JSON
    lines = (tmp_path / "c1" / JOURNAL_NAME).read_text().splitlines()
    assert [json.loads(x)["event"] for x in lines] == ["campaign_started", "trial_scored"]
    j2 = Journal(tmp_path / "c1")
    assert len(j2) == 2 and j2.torn == b""
    assert j2.append("x")["seq"] == 2
    j2.close()


def test_torn_last_line_is_reported_moved_and_earlier_lines_kept(tmp_path: Path) -> None:
    with Journal(tmp_path) as j:
        j.append("campaign_started")
        j.append("trial_proposed", trial_id=1)
    path = tmp_path / JOURNAL_NAME
    with path.open("ab") as f:
        f.write(b'{"seq":2,"event":"trial_sco')  # kill -9 in the middle of a write
    read = read_journal(path)
    assert [e["event"] for e in read.events] == ["campaign_started", "trial_proposed"]
    assert read.torn == b'{"seq":2,"event":"trial_sco'
    j = Journal(tmp_path)
    assert j.torn == b'{"seq":2,"event":"trial_sco'
    assert len(j) == 2
    assert (tmp_path / (JOURNAL_NAME + ".torn")).read_bytes().startswith(b'{"seq":2')
    j.append("trial_scored", trial_id=1, j=2.0)
    j.close()
    events = [json.loads(x) for x in path.read_text().splitlines()]
    assert [e["event"] for e in events] == ["campaign_started", "trial_proposed", "trial_scored"]
    assert Journal(tmp_path).torn == b""  # repaired for good


def test_garbage_last_line_with_newline_counts_as_torn(tmp_path: Path) -> None:
    path = tmp_path / JOURNAL_NAME
    path.write_bytes(b'{"seq":0,"event":"campaign_started"}\n\x00\x00\x00\n')
    j = Journal(tmp_path)
    assert len(j) == 1 and j.torn
    j.close()


def test_damage_before_the_end_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / JOURNAL_NAME
    path.write_bytes(b'{"seq":0,"event":"campaign_started"}\nnot json\n{"seq":2,"event":"x"}\n')
    with pytest.raises(JournalCorruptError, match="line 2"):
        Journal(tmp_path)


def test_a_line_inserted_duplicated_or_removed_is_an_error_not_a_result(tmp_path: Path) -> None:
    # outside review 2026-11-29: a second trial_scored for trial 4 (its seq copied, a better J) was read as the
    # trial's J by rescore, report and the cockpit
    with Journal(tmp_path) as j:
        j.append("campaign_started")
        j.append("trial_scored", trial_id=1, attempt=1, j=0.95)
        j.append("trial_scored", trial_id=2, attempt=1, j=0.90)
    path = tmp_path / JOURNAL_NAME
    good = path.read_bytes()
    lines = good.splitlines(keepends=True)
    forged = lines[1].replace(b'"j":0.95', b'"j":0.55')
    for damaged, line in (
        (lines[0] + lines[1] + forged + lines[2], 3),  # duplicated, seq copied
        (lines[0] + forged + lines[1] + lines[2], 3),  # inserted before its original
        (lines[0] + lines[2], 2),  # removed
        (lines[0] + lines[2] + lines[1], 2),  # reordered
    ):
        path.write_bytes(damaged)
        with pytest.raises(JournalCorruptError, match=f"line {line} has seq .*inserted, removed"):
            read_journal(path)
        with pytest.raises(JournalCorruptError):
            Journal(tmp_path)
        assert path.read_bytes() == damaged  # nothing repaired, nothing truncated
    # a pasted line without its seq, and an infinity written as a number, are caught too (second outside review)
    for damaged, match in (
        (lines[0] + lines[1] + forged.replace(b'"seq":1,', b"") + lines[2], "line 3 has seq None"),
        (lines[0] + lines[1].replace(b'"j":0.95', b'"j":1e999') + lines[2], r"line 2 holds 1e999 \(infinite\)"),
    ):
        path.write_bytes(damaged)
        with pytest.raises(JournalCorruptError, match=match):
            read_journal(path)
    path.write_bytes(good)
    assert [e.get("j") for e in read_journal(path).events] == [None, 0.95, 0.90]


@pytest.mark.parametrize("constant", ["NaN", "Infinity", "-Infinity"])
def test_nan_or_infinity_in_a_line_is_an_error_even_in_the_last_line(tmp_path: Path, constant: str) -> None:
    path = tmp_path / JOURNAL_NAME
    for body in (
        f'{{"seq":0,"event":"campaign_started"}}\n{{"seq":1,"event":"trial_scored","j":{constant}}}\n',
        f'{{"seq":0,"event":"trial_scored","j":{constant}}}\n{{"seq":1,"event":"x"}}\n',
    ):
        path.write_text(body)
        with pytest.raises(JournalCorruptError, match=f"holds {constant}, which bac never writes"):
            read_journal(path)
        with pytest.raises(JournalCorruptError):
            Journal(tmp_path)  # not taken for a torn write: nothing moved away
        assert path.read_text() == body


def test_each_event_is_visible_to_other_readers_when_append_returns(tmp_path: Path) -> None:
    j = Journal(tmp_path)
    j.append("a", v=1)
    # another reader (another process) sees it at once, without close() (durability: the next test)
    assert read_journal(tmp_path / JOURNAL_NAME).events[0]["v"] == 1
    j.close()


def test_append_fsyncs_the_line_before_it_returns(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The event is on the disk (write, then fsync of the same file) when append returns, for every event."""
    j = Journal(tmp_path)
    calls: list[tuple[str, int, bytes]] = []
    real_write, real_fsync = os.write, os.fsync

    def write(fd: int, data: bytes) -> int:
        calls.append(("write", fd, bytes(data)))
        return real_write(fd, data)

    def fsync(fd: int) -> None:
        calls.append(("fsync", fd, b""))
        real_fsync(fd)

    monkeypatch.setattr(os, "write", write)
    monkeypatch.setattr(os, "fsync", fsync)
    for i in range(3):
        n = len(calls)
        rec = j.append("trial_scored", trial_id=i, j=1.0 + i)
        mine = calls[n:]  # what this append did, in order, before it returned
        writes = [k for k, c in enumerate(mine) if c[0] == "write"]
        assert len(writes) == 1, mine
        (w,) = writes
        fd, line = mine[w][1], mine[w][2]
        assert json.loads(line) == rec and line.endswith(b"\n")
        assert os.path.samefile(f"/proc/self/fd/{fd}", tmp_path / JOURNAL_NAME)
        assert ("fsync", fd, b"") in mine[w + 1 :], f"append {i} returned without an fsync after its write: {mine}"
    monkeypatch.undo()
    j.close()


def test_write_json_atomic(tmp_path: Path) -> None:
    write_json_atomic(tmp_path / "r.json", {"j": float("nan"), "p": {"a": 1.0}})
    assert json.loads((tmp_path / "r.json").read_text()) == {"j": None, "p": {"a": 1.0}}
    assert not (tmp_path / "r.json.tmp").exists()


def test_journaled_engine_options_rebuild_the_live_model_and_old_journals_their_own() -> None:
    live = {"config": {"recommend_beta": 0.5, "gp_mean": "bowl", "bowl_runs": 10, "output_warp": "yeo-johnson"}}
    cfg = EngineConfig.from_dict({**journaled_engine_options(live), "budget": 12})
    assert (cfg.recommend_beta, cfg.gp.mean, cfg.bowl_runs, cfg.output_warp) == (0.5, "bowl", 10, "yeo-johnson")
    # a journal from before these settings existed: what the agent used then
    old = EngineConfig.from_dict({**journaled_engine_options({"config": {}}), "budget": 12})
    assert (old.recommend_beta, old.gp.mean, old.bowl_runs, old.output_warp) == (0.0, "constant", 0, "none")


def test_journaled_engine_options_carry_the_face_exploration_and_the_transfer_average_over_lengthscales() -> None:
    """A refit models a campaign with a prior as it ran: with or without the model without the source over both
    lengthscale priors (a journal from before the key ran without it), and with its face exploration."""
    prior = {"kind": "test"}
    for started, ls, face in (
        ({"prior": prior, "prior_average": True, "prior_average_ls": True, "face_explore": 1}, True, 1),
        ({"prior": prior, "prior_average": True, "prior_average_ls": False, "face_explore": 0}, False, 0),
        ({"prior": prior, "prior_average": True}, False, 0),  # journals from before both keys
    ):
        opts = journaled_engine_options({"config": started})
        assert (opts["prior_average_ls"], opts["face_explore"]) == (ls, face), started
