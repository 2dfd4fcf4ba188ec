"""Reading bags for replay: every message of chosen topics, in time order, as CDR bytes for ROS 2.

Pure Python (``rosbags``, no ROS runtime). Accepts a campaign folder (its
``bags/trial_*``), rosbag2 folders or files (mcap, sqlite3), ROS 1 bags and MDF
files (MDF4 / MDF 3: their IMU and speed channels become ``imu/data_raw`` and
``vehicle/odom``, :mod:`bac_measure.mdfio`);
ROS 1 messages are converted to their ROS 2 Jazzy form (a Header loses its
``seq``) and serialized as CDR, so a live ROS 2 graph can take them.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Generator, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys.store import Typestore

from bac_agent.journal import JournalError
from bac_campaign.exportio import is_bac_export
from bac_campaign.launches import LAUNCH_INDEX_NAME, launch_of_bags
from bac_common.contracts import TOPIC_TRIAL
from bac_common.errors import BacError
from bac_measure import bagio
from bac_measure.bagio import BagError
from bac_measure.mdfio import ChannelMap, is_mdf
from bac_measure.recording import bac_typestore, cdr_stamp_ns

PLAY_TOPICS = ("imu/data_raw", "vehicle/odom", "bac/trial")  # what bac replay plays (after a topic map)


class BagReadError(BacError, OSError):
    """A bag is missing, truncated or not a bag."""


@dataclass(frozen=True)
class BagMessage:
    topic: str  # topic to publish on (after remapping)
    msgtype: str  # ROS 2 type, e.g. sensor_msgs/msg/Imu
    time_ns: int  # bag (receive) time
    cdr: bytes  # ROS 2 CDR serialization


def expand_bag_paths(paths: Sequence[str | Path]) -> list[Path]:
    """Campaign folders become their trial bags (sorted); anything else is taken as a bag."""
    out: list[Path] = []
    for raw in paths:
        p = Path(raw)
        if not p.exists():
            raise BagReadError(f"no such bag or campaign folder: {p}")
        if p.is_dir() and (p / "bags").is_dir():
            trials = sorted(d for d in (p / "bags").iterdir() if d.is_dir())
            if not trials:
                raise BagReadError(f"campaign folder {p} holds no trial bags")
            out.extend(trials)
        elif is_bac_export(p):
            raise BagReadError(
                f"{p} is a bac export (bac export's MDF4 of a whole campaign): bac replay plays recordings, not "
                f"exports; `bac rescore {p}` scores it as its campaign folder, and the folder's bags replay"
            )
        else:
            out.append(p)
    return out


@dataclass(frozen=True)
class LaunchGroup:
    """Consecutive bags (their positions in the list given) that one launch of the graph recorded, or one bag."""

    positions: list[int]
    indexed: bool  # named by a campaign's launches.jsonl: campaign_recorder wrote it (streams at their stamps)


def launch_groups(paths: Sequence[Path], notes: list[str] | None = None) -> list[LaunchGroup]:
    """``paths`` cut into runs of consecutive bags that one launch of the graph recorded (a campaign folder's
    ``launches.jsonl``): their stamps share one clock, so a player can merge them into one timeline. A bag that no
    index names (a foreign bag, an MDF file, a bag from before the index, a bag given a second time in the same
    run) is a group of its own; an unreadable index is named in ``notes`` and its bags are taken as not indexed."""
    indexes: dict[Path, dict[str, tuple[int, str]]] = {}
    groups: list[LaunchGroup] = []
    last: tuple[Path, str] | None = None
    for k, p in enumerate(paths):
        camp = p.parent.parent
        key: tuple[Path, str] | None = None
        if p.parent.name == "bags" and (camp / LAUNCH_INDEX_NAME).is_file():
            if camp not in indexes:
                try:
                    indexes[camp] = launch_of_bags(camp)
                except JournalError as exc:
                    indexes[camp] = {}
                    if notes is not None:
                        notes.append(f"{camp / LAUNCH_INDEX_NAME} is unreadable ({exc}): its bags play as recorded")
            launch = indexes[camp].get(p.name)
            key = (camp, launch[1]) if launch is not None else None
        same = key is not None and key == last and all(paths[i] != p for i in groups[-1].positions)
        if same:
            groups[-1].positions.append(k)
        else:
            groups.append(LaunchGroup([k], key is not None))
        last = key
    return groups


def play_timeline(
    paths: Sequence[Path], plays: Sequence[Sequence[BagMessage]], notes: list[str] | None = None
) -> list[BagMessage]:
    """The messages to play, ``plays[k]`` being bag ``paths[k]``'s in recorded order: the bags of one launch
    (:func:`launch_groups`) as one timeline in event order (:func:`in_event_order`), one group after another; any
    other bag as it was recorded (its bag times may be arrival times, on another clock than the stamps). Where a
    group starts before the previous one ends (the clock will jump back), ``notes`` says so."""
    queue: list[BagMessage] = []
    for group in launch_groups(paths, notes):
        msgs = [m for k in group.positions for m in plays[k]]
        play = in_event_order(msgs) if group.indexed else msgs
        if queue and play and play[0].time_ns < queue[-1].time_ns and notes is not None:
            notes.append(f"{paths[group.positions[0]]} starts before the previous bag ends: the clock will jump back")
        queue.extend(play)
    return queue


def parse_topic_map(items: Sequence[str]) -> dict[str, str]:
    """``["/imu/data:=imu/data_raw", ...]`` -> {"/imu/data": "imu/data_raw"}."""
    out = {}
    for item in items:
        if ":=" not in item:
            raise BagReadError(f"topic map entry {item!r} must read FROM:=TO")
        src, dst = item.split(":=", 1)
        out[src.strip()] = dst.strip()
    return out


def _norm(topic: str) -> str:
    return topic.lstrip("/")


def to_store(msg: Any, store: Typestore) -> Any:
    """Rebuild a deserialized message as the same-named type of ``store`` (drops unknown fields)."""
    if not dataclasses.is_dataclass(msg) or isinstance(msg, type):
        if isinstance(msg, list):
            return [to_store(m, store) for m in msg]
        return msg
    cls = store.types[msg.__msgtype__]  # type: ignore[attr-defined]
    kwargs = {}
    for f in dataclasses.fields(cast(Any, cls)):
        if hasattr(msg, f.name):
            kwargs[f.name] = to_store(getattr(msg, f.name), store)
        else:  # a field ROS 1 did not have: its zero value
            kwargs[f.name] = _zero(f.type)
    return cls(**kwargs)


def _zero(typ: Any) -> Any:
    return {"str": "", "bool": False, "float": 0.0, "int": 0}.get(str(typ), 0)


def mdf_messages(path: Path, topics: Sequence[str], channels: ChannelMap | None = None) -> Iterator[BagMessage]:
    """An MDF recording as the messages a driver would have sent: ``imu/data_raw`` (sensor_msgs/Imu) and, when a
    speed or distance channel is mapped or found, ``vehicle/odom`` (nav_msgs/Odometry), at their stamps."""
    from bac_measure.bagio import IMU_TYPE, ODOM_TYPE, imu_to_cdr, odom_to_cdr
    from bac_measure.mdfio import read_mdf

    rec = read_mdf(path, channels)
    wanted = {_norm(t) for t in topics}
    items: list[BagMessage] = []
    if "imu/data_raw" in wanted:
        items += [BagMessage("imu/data_raw", IMU_TYPE, t, b) for t, b in imu_to_cdr(rec.imu)]
    if rec.odom is not None and "vehicle/odom" in wanted:
        items += [BagMessage("vehicle/odom", ODOM_TYPE, t, b) for t, b in odom_to_cdr(rec.odom)]
    items.sort(key=lambda m: m.time_ns)
    yield from items


def in_event_order(messages: Sequence[BagMessage]) -> list[BagMessage]:
    """Messages of bags campaign_recorder wrote in the order their events happened: each ``bac/trial`` message at
    its own stamp (when the agent entered that state), every other message at its bag time (the recorder writes a
    stream sample at its header stamp); stable, so messages at the same time keep their recorded order.

    The recorder wrote a trial message at its own clock when the message arrived (until 2026-11-28). On a loaded
    machine that clock lags the simulation by up to seconds: a run's SCORED message, or the next run's
    READY_TO_DRIVE, landed before the last IMU samples of the run's window, and a player that holds it until the
    replayed run is scored (as bac's does) never played those samples. At its stamp the message comes after every
    sample stamped before it; the agent waits idle for a run's score, so its clock, and the SCORED stamp, are
    current when the score comes. A trial message without a stamp (0) keeps its bag time. Given all the bags of
    one launch (:func:`play_timeline`), a run's late samples that the recorder wrote into the next trial's bag
    also come back before that trial starts.
    """

    def when(m: BagMessage) -> int:
        if m.topic == TOPIC_TRIAL:
            return cdr_stamp_ns(m.cdr) or m.time_ns
        return m.time_ns

    return [
        m if t == m.time_ns else dataclasses.replace(m, time_ns=t)
        for t, m in sorted(((when(m), m) for m in messages), key=lambda tm: tm[0])
    ]


def bag_topics(bag: str | Path) -> list[tuple[str, str]]:
    """(topic, type) of every connection of a bag (empty for an MDF file or a bag that does not open)."""
    path = Path(bag)
    if is_mdf(path):
        return []
    try:
        return sorted((topic, typ) for topic, (typ, _) in bagio.bag_topics(path).items())
    except BagError:  # iter_bag_messages names it
        return []


# what a foreign bag's topics of these types most likely are, for a --topic-map hint
PLAY_TYPES = {"sensor_msgs/msg/Imu": "imu/data_raw", "nav_msgs/msg/Odometry": "vehicle/odom"}


def nothing_to_play(bag: str | Path, topics: Sequence[str]) -> str:
    """Why ``bag`` gives none of ``topics``, with the remappings that would make it play."""
    found = bag_topics(bag)
    shown = ", ".join(f"{t} ({m})" for t, m in found) or "none"
    hint = " ".join(f"--topic-map {t}:={PLAY_TYPES[m]}" for t, m in found if m in PLAY_TYPES and _norm(t) not in topics)
    return f"{bag} has none of the topics to play ({', '.join(topics)}); its topics: {shown}" + (
        f"; map them, e.g. {hint}" if hint else ""
    )


def holds_topics(bag: str | Path, topics: Sequence[str], topic_map: Mapping[str, str] | None = None) -> bool:
    """Whether a bag has a connection on one of ``topics`` (names after ``topic_map``); an MDF file: True (its
    channels become imu/data_raw and vehicle/odom, or its reader says which are missing)."""
    if is_mdf(Path(bag)):
        return True
    mapping = {_norm(k): _norm(v) for k, v in (topic_map or {}).items()}
    wanted = {_norm(t) for t in topics}
    return any(mapping.get(_norm(t), _norm(t)) in wanted for t, _ in bag_topics(bag))


def is_bac_recording(bag: str | Path, topic_map: Mapping[str, str] | None = None) -> bool:
    """A bag bac recorded (it has ``bac/trial``): its IMU is what the profiles are made for. MDF files: False."""
    return not is_mdf(Path(bag)) and holds_topics(bag, [TOPIC_TRIAL], topic_map)


def imu_rate_hz(
    bag: str | Path,
    topic_map: Mapping[str, str] | None = None,
    channels: ChannelMap | None = None,
    max_samples: int = 5000,
) -> float | None:
    """1 / median step of the header stamps of the first ``max_samples`` ``imu/data_raw`` messages (after
    ``topic_map``); None without two distinct stamps (what imu_ingest measures its input rate from)."""
    msgs = iter_bag_messages(bag, ["imu/data_raw"], topic_map, channels)
    try:
        stamps = [cdr_stamp_ns(m.cdr) or 0 for m in itertools.islice(msgs, max_samples)]
    finally:
        msgs.close()
    steps = np.diff(np.sort(np.asarray(stamps, dtype=np.int64)))
    steps = steps[steps > 0]
    return 1e9 / float(np.median(steps)) if steps.size else None


def _as_list(value: Any) -> list[str]:
    return [str(value)] if isinstance(value, (str, Path)) else [str(v) for v in (value or [])]


def fit_replay_rates(
    overrides: dict[str, dict[str, Any]], profile_files: Sequence[str | Path], user_files: Sequence[str | Path]
) -> str:
    """``bac replay``'s node overrides for what it plays (``overrides["bag_player"]``: bags, topic_map, channels).

    Recordings that are not a bac campaign's (a foreign bag, an MDF file): imu_ingest measures their IMU's rate
    and keeps its output at or below it, the segmenter at the same rate, as ``bac rescore`` does (the replay
    profile is made for the simulator's 400 Hz IMU: a 50 Hz stream was all gaps). What the user set (``-p``,
    ``--params-file``) is kept. Refuses (:class:`BagReadError`) bags with nothing to play, bac's bags mixed with
    other recordings, and recordings of different IMU rates. Returns a note for the user ("" for bac's bags)."""
    from bac_measure.measure_config import load_node_params

    player = overrides["bag_player"]  # the options and any -p bag_player.*
    paths = expand_bag_paths(_as_list(player.get("bags")))
    topic_map = parse_topic_map(_as_list(player.get("topic_map")))
    silent = [p for p in paths if not holds_topics(p, PLAY_TOPICS, topic_map)]
    if len(silent) == len(paths):
        raise BagReadError("nothing to play: " + "; ".join(nothing_to_play(p, PLAY_TOPICS) for p in silent))
    paths = [p for p in paths if p not in silent]  # bag_player names the others when it starts
    bac = [is_bac_recording(p, topic_map) for p in paths]
    if all(bac):
        return ""
    if any(bac):
        ours = next(p for p, b in zip(paths, bac, strict=True) if b)
        other = next(p for p, b in zip(paths, bac, strict=True) if not b)
        raise BagReadError(
            f"bac's campaign bags ({ours}) and other recordings ({other}) in one replay: their IMUs differ (the "
            "profile's ingestion is made for bac's), so replay them separately"
        )
    channels = ChannelMap.load(str(player.get("channel_map") or "") or None, _as_list(player.get("channels")))
    rates = {p: r for p in paths if (r := imu_rate_hz(p, topic_map, channels)) is not None}
    if not rates:
        return "not a bac campaign (no bac/trial), and its IMU stamps give no rate: imu_ingest gets the profile's"
    if max(rates.values()) > 1.05 * min(rates.values()):
        shown = ", ".join(f"{p.name} {r:.1f} Hz" for p, r in rates.items())
        raise BagReadError(f"recordings of different IMU rates ({shown}): replay them one rate at a time")
    rate = float(np.median(list(rates.values())))
    ing, seg = overrides.setdefault("imu_ingest", {}), overrides.setdefault("run_segmenter", {})
    user_ing = set(load_node_params(user_files, "imu_ingest")) | set(ing)
    user_seg = set(load_node_params(user_files, "run_segmenter")) | set(seg)
    merged = load_node_params([*profile_files, *user_files], "imu_ingest", ing)
    out = merged.get("output_rate_hz", 200.0)
    if "output_rate_hz" not in user_ing and float(out) > 1.01 * rate:
        ing["output_rate_hz"] = out = round(rate, 6)
    if "input_rate_hz" not in user_ing:
        ing["input_rate_hz"] = 0.0
    if "imu_rate_hz" not in user_seg:
        seg["imu_rate_hz"] = out
    return (
        f"not a bac campaign (no bac/trial): the IMU is {rate:.1f} Hz; imu_ingest measures its input rate and "
        f"outputs {out} Hz; mount from {merged.get('mount_source')}, bias from {merged.get('bias_source')} "
        "(set them with -p imu_ingest.* or a --params-file; bac rescore finds them from a standstill)"
    )


def iter_bag_messages(
    bag: str | Path,
    topics: Sequence[str],
    topic_map: Mapping[str, str] | None = None,
    channels: ChannelMap | None = None,
) -> Generator[BagMessage, None, None]:
    """Messages of ``topics`` (names after remapping, without leading '/') in time order. An MDF file gives its
    IMU and odometry channels (``channels``: the channel map; None: found by units and names)."""
    path = Path(bag)
    if is_mdf(path):
        yield from mdf_messages(path, topics, channels)
        return
    store = bac_typestore()
    mapping = {_norm(k): _norm(v) for k, v in (topic_map or {}).items()}
    wanted = {_norm(t) for t in topics}
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except Exception as exc:  # rosbags raises several types for a bad bag
        raise BagReadError(f"cannot open bag {path}: {exc}") from exc
    try:
        conns = [c for c in reader.connections if mapping.get(_norm(c.topic), _norm(c.topic)) in wanted]
        if not conns:  # rosbags reads every message when given no connections
            return
        ros1 = reader.is2 is False
        for conn, t_ns, raw in reader.messages(connections=conns):
            topic = mapping.get(_norm(conn.topic), _norm(conn.topic))
            if ros1 or conn.msgtype not in store.types:
                msg = to_store(reader.deserialize(raw, conn.msgtype), store)
                cdr = bytes(store.serialize_cdr(msg, conn.msgtype))
            else:
                cdr = bytes(raw)
            yield BagMessage(topic, conn.msgtype, int(t_ns), cdr)
    except BagReadError:
        raise
    except Exception as exc:
        raise BagReadError(f"bag {path} is truncated or damaged: {exc}") from exc
    finally:
        reader.close()
