"""The campaign journal: ``campaign_dir/journal.jsonl``, append-only, durable per event.

One JSON object per line, one line per event. Each append writes the whole line
with a single ``write`` on a file opened ``O_APPEND``, then ``fsync``: once
:meth:`Journal.append` returns, the event survives ``kill -9`` and a power cut.
A process killed in the middle of a write can leave a *torn* last line (no
newline, or not JSON): :class:`Journal` detects it when it opens the file,
reports it (``Journal.torn``), moves the torn bytes to ``journal.jsonl.torn``
and truncates the file after the last complete line, so the earlier events are
kept and new ones start on a clean line. A bad line *before* the last one is
not a torn write but corruption: :class:`JournalCorruptError`, nothing guessed; so is a line whose ``seq`` is not
its line number (lines inserted, removed, duplicated or moved) and one holding NaN or Infinity (never written).

Every event has ``seq`` (0-based line number), ``event`` (its type), ``wall_time``
(ISO 8601 UTC) and whatever fields its type defines; the schema is documented in
docs/agent.md and versioned by ``SCHEMA_VERSION`` (in the ``campaign_started``
event). Non-finite floats are written as ``null`` (strict JSON).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from bac_common.errors import BacError

SCHEMA_VERSION = 2  # 2 (2026-11-24): trial_proposed.optimizer_state, apply_result.outcome
JOURNAL_NAME = "journal.jsonl"


class JournalError(BacError):
    """The journal cannot be used (unreadable, from another campaign, ...)."""


class JournalCorruptError(JournalError):
    """A line other than the last one is not a JSON object: the file was damaged, not torn."""


@dataclass(frozen=True)
class JournalRead:
    """What :func:`read_journal` found."""

    events: list[dict[str, Any]]
    good_bytes: int  # length of the prefix made of complete, valid lines
    torn: bytes  # the torn tail (empty when the file ended cleanly)


def _clean(value: Any) -> Any:
    """Strict-JSON form: non-finite floats become None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    return value


def strict_json(value: Any) -> Any:
    """``value`` in the form the journal writes it: non-finite floats as None, mappings with str keys, tuples as
    lists (recursively)."""
    return _clean(value)


class _NonFiniteError(ValueError):
    pass


def _no_constant(name: str) -> Any:
    raise _NonFiniteError(name)


def _finite_float(text: str) -> float:
    v = float(text)
    if math.isinf(v):  # 1e999: another way to write Infinity
        raise _NonFiniteError(f"{text} (infinite)")
    return v


def read_journal(path: str | Path, check_seq: bool | None = None) -> JournalRead:
    """Read every complete event; a torn last line is returned apart, never guessed at.

    ``check_seq`` (default: for the campaign journal, whose one writer is the agent; not for other logs kept the
    same way, e.g. the recorder's index of bags, which two launches may append to): every event's ``seq`` must be
    its line number."""
    p = Path(path)
    if check_seq is None:
        check_seq = p.name == JOURNAL_NAME
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        return JournalRead([], 0, b"")
    except OSError as exc:
        raise JournalError(f"cannot read the journal {p}: {exc}") from exc
    events: list[dict[str, Any]] = []
    pos = 0
    lines = data.split(b"\n")
    for i, raw in enumerate(lines):
        last = i == len(lines) - 1
        if last:
            # after the final newline: empty when the file ended cleanly, else a torn write
            return JournalRead(events, pos, raw)
        try:
            obj = json.loads(raw, parse_constant=_no_constant, parse_float=_finite_float)
        except _NonFiniteError as exc:  # a whole line, parsed: not a torn write, an edit
            raise JournalCorruptError(
                f"{p}: line {i + 1} holds {exc}, which bac never writes (a non-finite value is written as null): "
                "the file was edited. Keep a copy, then correct the line by hand or start a new campaign_dir."
            ) from None
        except (json.JSONDecodeError, UnicodeDecodeError):
            obj = None
        if not isinstance(obj, dict) or "event" not in obj:
            if i == len(lines) - 2 and lines[-1] == b"":
                # the last complete-looking line is garbage: a torn write that happened to end in a newline
                return JournalRead(events, pos, raw + b"\n")
            raise JournalCorruptError(
                f"{p}: line {i + 1} is not a journal event ({raw[:80]!r}); the file is damaged before its end. "
                "Keep a copy, then remove the damaged lines by hand or start a new campaign_dir."
            )
        seq = obj.get("seq")
        if check_seq and (not isinstance(seq, int) or isinstance(seq, bool) or seq != i):
            # bac numbers the events 0, 1, 2, ... as it writes them (Journal.append): a line with another number was
            # inserted, removed, duplicated or moved (outside review 2026-11-29: a second trial_scored for a trial,
            # its seq copied, was read as the trial's J and became the best J of the report)
            raise JournalCorruptError(
                f"{p}: line {i + 1} has seq {seq!r}, not {i}: lines were inserted, removed, duplicated or reordered "
                "after bac wrote them. Keep a copy, then restore the file or start a new campaign_dir."
            )
        events.append(obj)
        pos += len(raw) + 1
    return JournalRead(events, pos, b"")  # pragma: no cover - split always yields a last element


class Journal:
    """An append-only, fsynced JSON-lines journal (see the module doc); ``name``: the file in ``campaign_dir``
    (another log kept the same way, e.g. the recorder's index of bags)."""

    def __init__(self, campaign_dir: str | Path, name: str = JOURNAL_NAME) -> None:
        self.dir = Path(campaign_dir)
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise JournalError(f"cannot create the campaign folder {self.dir}: {exc}") from exc
        self.path = self.dir / name
        read = read_journal(self.path)
        self.torn: bytes = read.torn
        if read.torn:
            torn_path = self.path.with_name(name + ".torn")
            with torn_path.open("ab") as f:
                f.write(read.torn + b"\n")
                f.flush()
                os.fsync(f.fileno())
            with self.path.open("r+b") as f:
                f.truncate(read.good_bytes)
                f.flush()
                os.fsync(f.fileno())
        self._events = read.events
        new = not self.path.exists()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        if new:
            self._fsync_dir()

    def _fsync_dir(self) -> None:
        try:
            dfd = os.open(self.dir, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)

    @property
    def events(self) -> list[dict[str, Any]]:
        return list(self._events)

    def __iter__(self) -> Iterator[dict[str, Any]]:
        return iter(list(self._events))

    def __len__(self) -> int:
        return len(self._events)

    def append(self, event: str, **fields: Any) -> dict[str, Any]:
        """Write one event durably (write + fsync) and return it as written."""
        if self._fd < 0:
            raise JournalError(f"journal {self.path} is closed")
        rec: dict[str, Any] = {
            "seq": len(self._events),
            "event": event,
            "wall_time": datetime.now(UTC).isoformat(timespec="milliseconds"),
        }
        rec.update(_clean(fields))
        line = (json.dumps(rec, allow_nan=False, separators=(",", ":")) + "\n").encode()
        n = os.write(self._fd, line)
        if n != len(line):  # a short write on a regular file: disk full
            raise JournalError(f"journal {self.path}: short write ({n} of {len(line)} bytes); is the disk full?")
        os.fsync(self._fd)
        self._events.append(rec)
        return rec

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def journaled_engine_options(started: Mapping[str, Any]) -> dict[str, Any]:
    """The EngineConfig fields an offline refit (``bac report``, ``bac rescore --refit``) needs to model and
    recommend the way the live campaign did, from its ``campaign_started`` record: ``recommend_beta``
    (0: the paper's argmin of the posterior mean), ``recommend_rule``, the GP's prior mean, ``bowl_runs``, the
    output warp, and a transfer prior and outcome limits (with their outcome priors) when the campaign had them.
    Journals written before these were configurable get what the agent used then: beta 0, the rule ``mean``, a
    constant mean, no warp."""
    cfg = started.get("config") or {}
    options: dict[str, Any] = {
        "recommend_beta": float(cfg.get("recommend_beta", 0.0) or 0.0),
        "recommend_rule": str(cfg.get("recommend_rule", "mean") or "mean"),
        "gp": {
            "mean": str(cfg.get("gp_mean", "constant") or "constant"),
            "bowl_loo": bool(cfg.get("gp_bowl_loo", False)),  # a journal from before it ran without it
            "ls_average": float(cfg.get("gp_ls_average", 0.0) or 0.0),  # (the same)
        },
        "bowl_runs": int(cfg.get("bowl_runs", 0) or 0),
        "output_warp": str(cfg.get("output_warp", "none") or "none"),
        "face_explore": int(cfg.get("face_explore", 0) or 0),  # a journal from before it ran without it
    }
    # issue 23: the transfer prior (its source surface, as the engine used it) and the outcome limits
    if cfg.get("prior"):
        options["prior"] = dict(cfg["prior"])
        options["prior_weight"] = float(cfg.get("prior_weight", 0.5) or 0.5)
        options["prior_runs"] = int(cfg.get("prior_runs", 0) or 0)
        options["prior_average"] = bool(cfg.get("prior_average", False))  # a journal from before it: without
        options["prior_average_ls"] = bool(cfg.get("prior_average_ls", False))  # (the same)
    if cfg.get("constraints"):
        options["constraints"] = [str(c) for c in cfg["constraints"]]
        options["constraint_level"] = float(cfg.get("constraint_level", 0.05) or 0.05)
        options["limit_trend"] = bool(cfg.get("limit_trend", False))  # a journal from before it: without
        options["limit_far_sd"] = float(cfg.get("limit_far_sd", 0.0) or 0.0)  # (the same)
        options["limit_trend_far"] = float(cfg.get("limit_trend_far", 0.0) or 0.0)  # (the same)
        options["limit_reach"] = float(cfg.get("limit_reach", 0.0) or 0.0)  # (the same)
        if cfg.get("outcome_priors"):  # what the prior source knew of the limited outcomes
            options["outcome_priors"] = {str(k): dict(v) for k, v in cfg["outcome_priors"].items()}
    return options


def write_json_atomic(path: str | Path, data: Mapping[str, Any]) -> None:
    """Write a JSON file so that a reader sees the old or the new content, never a mix."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    with tmp.open("w") as f:
        json.dump(_clean(data), f, indent=2, allow_nan=False)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, p)
