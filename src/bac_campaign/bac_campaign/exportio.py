"""The layout of ``bac export``'s MDF4 file, and reading one back: ``bac rescore CAMPAIGN.mf4`` scores an exported
campaign as it scores the campaign folder.

An export holds, besides the channels a calibration engineer looks at (:mod:`bac_campaign.export`), what rescoring
needs, so the one file can travel (mailed to a colleague, archived beside the CANape measurements) and be rescored
without the folder it came from:

* per trial bag (``trial_0003``, ``trial_0003.r1`` for a resumed trial): ``<bag>.raw.*`` (the IMU as sent, with its
  receive times ``recv_ns``), ``<bag>.vehicle.*`` (what the live ingestion made of it), ``<bag>.odom.*`` (distance,
  speed, the pose's y and z) and ``<bag>.trial.*``: the agent's ``bac/trial`` announcements recorded in the bag
  (state, trial, attempt, campaign id, reason, receive time) at their stamps, which say where each run starts;
* the campaign's small files as embedded attachments (``journal.jsonl``, ``launches.jsonl``, ``config/*``,
  ``reference.npz``, ``recommendation.json``), each named in its comment (``bac campaign file: config/01_sim.yaml``).

Times are seconds from the file's start time (the campaign's first stamp, whole microseconds), stored as float64:
a stamp of a day-long campaign comes back to the nanosecond.

No rclpy; asammdf is imported only when a file is read or written.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import numpy as np

from bac_common.errors import BacError
from bac_measure.bagio import ImuArrays, OdomArrays, TrialEvent
from bac_measure.mdfio import asammdf, is_mdf, mdf_start_ns, open_mdf

ATTACHMENT_MARK = "bac campaign file: "  # an attachment's comment: the mark, then its path in the campaign folder
CAMPAIGN_FILES = ("journal.jsonl", "launches.jsonl", "recommendation.json", "reference.npz")  # and config/*
MANIFEST = "export.json"  # the export's own: its layout, whether it has the raw IMU, the bags it left out
MAX_ATTACHMENT_BYTES = 256 * 1024 * 1024  # a campaign's files are kB to MB: larger is not an export's
_CHANNEL = re.compile(r"(trial_\d+(?:\.r\d+)?)\.(raw|vehicle|odom|trial)\.(\w+)")
IMU_AXES = ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
TRIAL_CHANNELS = ("state", "trial_id", "attempt", "recv_ns", "campaign_id", "reason")


def is_campaign_file(name: str) -> bool:
    """A path an export may unpack to: one of :data:`CAMPAIGN_FILES`, the manifest, or ``config/<file name>``."""
    if name in CAMPAIGN_FILES or name == MANIFEST:
        return True
    if not name.startswith("config/"):
        return False
    base = name[len("config/") :]
    return bool(base) and base not in (".", "..") and not any(c in base for c in "/\\\0") and len(base) <= 255


class ExportReadError(BacError, ValueError):
    """A file that claims to be a bac export but cannot be read as one."""


@dataclass
class ExportedBag:
    """What one trial bag of the campaign held, as read back from the export."""

    name: str  # the bag's folder name: trial_0003, trial_0003.r1
    imu_vehicle: ImuArrays | None = None
    imu_raw: ImuArrays | None = None
    odom: OdomArrays | None = None
    trials: list[TrialEvent] = field(default_factory=list)


def campaign_files(campaign_dir: Path) -> list[tuple[str, bytes]]:
    """The campaign's small files an export carries: (path in the folder, content); every file of ``config/``."""
    out = [(name, (campaign_dir / name).read_bytes()) for name in CAMPAIGN_FILES if (campaign_dir / name).is_file()]
    config = campaign_dir / "config"
    if config.is_dir():
        out += [(f"config/{p.name}", p.read_bytes()) for p in sorted(config.iterdir()) if p.is_file()]
    bad = [name for name, _ in out if not is_campaign_file(name)]
    if bad:
        raise ExportReadError(f"{campaign_dir}: {bad[0]!r} cannot be carried by an export (a name with \\ or NUL)")
    return out


def attach_campaign_files(mdf: Any, campaign_dir: Path, manifest: dict[str, Any] | None = None) -> int:
    """Embed the campaign's files (and the export's manifest) in an MDF4 being written; the number of files.
    Every parameter file ``config/launch.json`` lists must be among them."""
    files = campaign_files(campaign_dir)
    names = {name for name, _ in files}
    launch = campaign_dir / "config" / "launch.json"
    if launch.is_file():
        listed = [f"config/{n}" for n in json.loads(launch.read_text()).get("params_files", [])]
        missing = [n for n in listed if n not in names]
        if missing:
            raise ExportReadError(f"{campaign_dir}: config/launch.json lists {missing[0]}, which is not in config/")
    for name, data in files:
        mdf.attach(data, file_name=name.replace("/", "__"), comment=ATTACHMENT_MARK + name)
    body = json.dumps({"layout": 2, **(manifest or {})}, indent=1).encode()
    mdf.attach(body, file_name=MANIFEST, comment=ATTACHMENT_MARK + MANIFEST)
    return len(files)


def _attachment_name(att: Any) -> str | None:
    comment = str(getattr(att, "comment", "") or "")
    return comment[len(ATTACHMENT_MARK) :].strip() if comment.startswith(ATTACHMENT_MARK) else None


def _bag_channels(mdf: Any) -> dict[str, dict[str, dict[str, tuple[int, int]]]]:
    """bag -> stream (raw, vehicle, odom, trial) -> channel -> (group, index) of the export's per-bag channels."""
    out: dict[str, dict[str, dict[str, tuple[int, int]]]] = {}
    for gi, grp in enumerate(mdf.groups):
        for ci, ch in enumerate(grp.channels):
            m = _CHANNEL.fullmatch(str(ch.name))
            if m:
                out.setdefault(m.group(1), {}).setdefault(m.group(2), {})[m.group(3)] = (gi, ci)
    return out


def is_bac_export(path: str | Path) -> bool:
    """True for an MDF4 file ``bac export`` wrote: it carries the campaign's files (attachments marked
    :data:`ATTACHMENT_MARK`). A file with only an export's channels (an export from before 2026-11-29, or one a tool
    filtered or cut, which drops attachments) is not one: it is read as any MDF file (see
    :func:`export_channels_hint`)."""
    p = Path(path)
    if not p.is_file() or not is_mdf(p):
        return False
    try:
        mdf = _open(p)
    except Exception:
        return False  # unreadable: the MDF reader says why
    try:
        if not str(getattr(mdf, "version", "")).startswith("4"):
            return False  # MDF 3 has no attachments (asammdf refuses to list them)
        return any(_attachment_name(a) for a in mdf.attachments)
    except Exception:
        return False
    finally:
        mdf.close()


def export_channels_hint(path: str | Path) -> str:
    """What to say of an MDF file whose channels are an export's but which carries no campaign files; "" else."""
    p = Path(path)
    try:
        mdf = _open(p)
    except Exception:
        return ""
    try:
        if not _bag_channels(mdf):
            return ""
    except Exception:
        return ""
    finally:
        mdf.close()
    return (
        "its channels are a bac export's (trial_NNNN.raw.*), but it carries no campaign files: an export written "
        "before 2026-11-29, or one a tool filtered or cut (asammdf drops the attachments); rescore the campaign "
        "folder or export it again, or give a channel map for one trial's channels"
    )


def _open(p: Path) -> Any:
    return open_mdf(p)  # a file asammdf refuses: MdfError with what to do


def _samples(mdf: Any, where: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    gi, ci = where
    sig = mdf.get(group=gi, index=ci, raw=False)
    return np.asarray(sig.samples), np.asarray(sig.timestamps, dtype=np.float64)


def read_export(path: str | Path, folder: str | Path, bags_too: bool = True) -> list[ExportedBag]:
    """Unpack a bac export: its campaign files into ``folder`` (a campaign folder without ``bags/``), its trial bags
    returned in memory, in the order of their names (none with ``bags_too`` false)."""
    p, dest = Path(path), Path(folder)
    mdf = _open(p)
    try:
        files = [(i, n) for i, n in ((i, _attachment_name(a)) for i, a in enumerate(mdf.attachments)) if n]
        bags = _bag_channels(mdf)
        for i, name in files:  # every name checked before anything is written
            if not is_campaign_file(name):
                raise ExportReadError(f"{p}: attachment {i} names {name!r}, not a campaign file: refused")
        seen = [n for _, n in files]
        twice = sorted({n for n in seen if seen.count(n) > 1})
        if twice:
            raise ExportReadError(f"{p}: {twice[0]} is attached {seen.count(twice[0])} times: which one is meant?")
        if "journal.jsonl" not in seen:
            raise ExportReadError(
                f"{p} carries campaign files but no journal: not an export bac can rescore; rescore the campaign "
                "folder it came from, or export it again"
            )
        for i, name in files:
            data = _attachment_bytes(p, mdf.attachments[i], name)
            target = dest / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        if not (dest / "journal.jsonl").read_bytes().strip():
            raise ExportReadError(f"{p}:journal.jsonl is empty: the export is damaged; export the campaign again")
        _check_launch_record(p, dest)
        start = mdf_start_ns(mdf)
        out: list[ExportedBag] = []
        for bag in sorted(bags, key=bag_order) if bags_too else []:
            streams = bags[bag]
            try:
                out.append(_read_bag(mdf, bag, streams, start))
            except (KeyError, ValueError) as exc:
                raise ExportReadError(f"{p}: the channels of {bag} are not an export's ({exc})") from exc
        return out
    finally:
        mdf.close()


def _attachment_bytes(p: Path, att: Any, name: str) -> bytes:
    """An embedded attachment's content, checked (asammdf returns b"" for what it cannot read, warns at most on a
    wrong MD5 and follows an external attachment's path on this machine)."""
    flags = int(getattr(att, "flags", 0))
    if not flags & 1:  # FLAG_AT_EMBEDDED
        raise ExportReadError(f"{p}:{name} is not embedded (it names a file elsewhere): refused")
    size = int(getattr(att, "original_size", 0) or 0)
    if size > MAX_ATTACHMENT_BYTES:
        raise ExportReadError(f"{p}:{name} would unpack to {size} bytes: not a campaign file; refused")
    try:
        data = bytes(att.extract())
    except Exception as exc:
        raise ExportReadError(f"{p}:{name} cannot be unpacked ({exc}): the export is damaged") from exc
    if flags & 4 and bytes(att.md5_sum) != hashlib.md5(data).digest():  # FLAG_AT_MD5_VALID
        raise ExportReadError(f"{p}:{name} does not match its MD5 sum: the export is damaged; export it again")
    if len(data) > MAX_ATTACHMENT_BYTES:
        raise ExportReadError(f"{p}:{name} unpacks to {len(data)} bytes: not a campaign file; refused")
    return data


def _check_launch_record(p: Path, dest: Path) -> None:
    """The unpacked config/launch.json may only name parameter files unpacked beside it."""
    launch = dest / "config" / "launch.json"
    if not launch.is_file():
        return
    try:
        listed = json.loads(launch.read_text()).get("params_files", [])
    except (ValueError, AttributeError) as exc:
        raise ExportReadError(f"{p}:config/launch.json is not a launch record ({exc})") from exc
    for n in listed:
        if not (isinstance(n, str) and is_campaign_file(f"config/{n}") and (launch.parent / n).is_file()):
            raise ExportReadError(f"{p}:config/launch.json names {n!r}, which the export does not carry: refused")


def read_manifest(folder: Path) -> dict[str, Any]:
    """The export's manifest unpacked in ``folder`` (an older export has none: {})."""
    f = folder / MANIFEST
    try:
        data = json.loads(f.read_text()) if f.is_file() else {}
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


def bag_order(name: str) -> tuple[int, int, str]:
    """trial_0003 < trial_0003.r1 < trial_0003.r2 < trial_0004: the order a campaign's recorders created its bags
    (by folder name; other names last, by name)."""
    m = re.fullmatch(r"trial_(\d+)(?:\.r(\d+))?", name)
    return (int(m.group(1)), int(m.group(2) or 0), "") if m else (1 << 62, 0, name)


def _stamps(start: int, t: np.ndarray) -> np.ndarray:
    return start + np.round(t * 1e9).astype(np.int64)


def _read_bag(mdf: Any, bag: str, streams: dict[str, dict[str, tuple[int, int]]], start: int) -> ExportedBag:
    out = ExportedBag(bag)
    if "raw" in streams:
        ch = streams["raw"]
        cols, t = zip(*(_samples(mdf, ch[a]) for a in IMU_AXES), strict=True)
        stamp = _stamps(start, t[0])
        recv = _samples(mdf, ch["recv_ns"])[0].astype(np.int64) if "recv_ns" in ch else stamp.copy()
        data = np.column_stack([np.asarray(c, dtype=np.float64) for c in cols])
        out.imu_raw = ImuArrays(
            "imu/data_raw", "", stamp, recv, data[:, :3].copy(), data[:, 3:].copy(), has_recv="recv_ns" in ch
        )
    if "vehicle" in streams:
        az, t = _samples(mdf, streams["vehicle"]["accel_z"])
        q, _ = _samples(mdf, streams["vehicle"]["pitch_rate"])
        accel = np.zeros((az.size, 3))
        gyro = np.zeros((az.size, 3))
        accel[:, 2] = az
        gyro[:, 1] = q
        stamp = _stamps(start, t)
        out.imu_vehicle = ImuArrays("imu/vehicle", "", stamp, stamp.copy(), accel, gyro, has_recv=False)
    if "odom" in streams:
        ch = streams["odom"]
        dist, t = _samples(mdf, ch["distance"])
        speed, _ = _samples(mdf, ch["speed"])
        y = _samples(mdf, ch["position_y"])[0] if "position_y" in ch else None
        z = _samples(mdf, ch["position_z"])[0] if "position_z" in ch else None
        stamp = _stamps(start, t)
        out.odom = OdomArrays(
            "vehicle/odom",
            "",
            stamp,
            stamp.copy(),
            np.asarray(dist, dtype=np.float64),
            np.asarray(speed, dtype=np.float64),
            None if y is None else np.asarray(y, dtype=np.float64),
            None if z is None else np.asarray(z, dtype=np.float64),
        )
    if "trial" in streams:
        ch = streams["trial"]
        state, t = _samples(mdf, ch["state"])
        cols = {k: _samples(mdf, ch[k])[0] for k in TRIAL_CHANNELS if k != "state"}
        stamp = _stamps(start, t)
        out.trials = [
            TrialEvent(
                recv_ns=int(cols["recv_ns"][i]),
                stamp_ns=int(stamp[i]),
                campaign_id=_text(cols["campaign_id"][i]),
                trial_id=int(cols["trial_id"][i]),
                attempt=int(cols["attempt"][i]),
                state=int(state[i]),
                reason=_text(cols["reason"][i]),
            )
            for i in range(stamp.size)
        ]
    return out


def _text(v: Any) -> str:
    return v.decode("utf-8", "replace").rstrip("\x00") if isinstance(v, bytes | bytearray) else str(v)


@contextmanager
def unpacked_export(path: str | Path, bags_too: bool = True) -> Iterator[tuple[Path, list[ExportedBag]]]:
    """A bac export unpacked into a temporary campaign folder (removed on exit), with its trial bags."""
    with TemporaryDirectory(prefix="bac-export-") as tmp:
        yield Path(tmp), read_export(path, tmp, bags_too)


@dataclass
class ExportedSegment:
    """A run's aligned window as the export holds it (``trial_NNNN.aN.*``): what ``bac report`` plots."""

    trial_id: int
    attempt: int
    valid: bool
    sample_rate_hz: float
    accel_z: np.ndarray
    pitch_rate: np.ndarray


def read_segments(path: str | Path) -> dict[int, ExportedSegment]:
    """Each trial's aligned window as the report takes it from the bags: its last attempt whose window was cut
    (``campaign.segment_valid``; an older export: ``campaign.valid``), at its recorded sample rate."""
    p = Path(path)
    mdf = _open(p)
    try:
        names = {str(ch.name): (gi, ci) for gi, g in enumerate(mdf.groups) for ci, ch in enumerate(g.channels)}
        if "campaign.trial_id" not in names:
            return {}

        def col(name: str) -> np.ndarray:
            return _samples(mdf, names[name])[0]

        trial = col("campaign.trial_id").astype(int)
        attempt = col("campaign.attempt").astype(int)
        valid = col("campaign.segment_valid" if "campaign.segment_valid" in names else "campaign.valid").astype(bool)
        rates = col("campaign.sample_rate_hz") if "campaign.sample_rate_hz" in names else np.full(trial.size, np.nan)
        out: dict[int, ExportedSegment] = {}
        for k in np.lexsort((attempt, trial)):  # the last attempt of a trial wins, as the last in its bags does
            tid, att = int(trial[k]), int(attempt[k])
            pre = f"trial_{tid:04d}.a{att}"
            if not valid[k] or f"{pre}.accel_z_aligned" not in names:
                continue
            az, t = _samples(mdf, names[f"{pre}.accel_z_aligned"])
            q, _ = _samples(mdf, names[f"{pre}.pitch_rate_aligned"])
            if t.size < 2 or not t[-1] > t[0]:
                continue
            rate = float(rates[k]) if math.isfinite(rates[k]) else (t.size - 1) / float(t[-1] - t[0])
            out[tid] = ExportedSegment(tid, att, True, rate, az.astype(float), q.astype(float))
        return out
    finally:
        mdf.close()


def trial_signals(bag: str, events: list[TrialEvent], t0: int) -> list[Any]:
    """The ``<bag>.trial.*`` channels of an export (asammdf Signals): the bag's bac/trial announcements."""
    Signal = asammdf().Signal
    t = (np.array([e.stamp_ns for e in events], dtype=np.int64) - t0) / 1e9

    def text(values: list[str]) -> np.ndarray:
        raw = [v.encode("utf-8") for v in values]
        return np.array(raw, dtype=f"S{max(1, *(len(r) for r in raw))}")

    return [
        Signal(
            np.array([e.state for e in events], dtype=np.uint8),
            t,
            name=f"{bag}.trial.state",
            comment="bac/trial state (3: READY_TO_DRIVE, the run's start)",
        ),
        Signal(np.array([e.trial_id for e in events], dtype=np.uint32), t, name=f"{bag}.trial.trial_id"),
        Signal(np.array([e.attempt for e in events], dtype=np.uint32), t, name=f"{bag}.trial.attempt"),
        Signal(
            np.array([e.recv_ns for e in events], dtype=np.int64),
            t,
            name=f"{bag}.trial.recv_ns",
            unit="ns",
            comment="bag (receive) time, ns since the epoch",
        ),
        Signal(text([e.campaign_id for e in events]), t, name=f"{bag}.trial.campaign_id", encoding="utf-8"),
        Signal(text([e.reason for e in events]), t, name=f"{bag}.trial.reason", encoding="utf-8"),
    ]


__all__ = [
    "ATTACHMENT_MARK",
    "ExportReadError",
    "ExportedBag",
    "ExportedSegment",
    "attach_campaign_files",
    "bag_order",
    "campaign_files",
    "export_channels_hint",
    "is_bac_export",
    "is_campaign_file",
    "read_export",
    "read_manifest",
    "read_segments",
    "trial_signals",
    "unpacked_export",
]
