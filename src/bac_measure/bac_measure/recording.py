"""Writing a campaign's recordings: one rosbag2 (mcap) per trial, with ``rosbags``.

Pure Python (no rclpy): the recorder node hands over serialized CDR bytes as
they arrived on the wire, so the bags hold exactly what the graph saw and
``ros2 bag``, Foxglove and rclpy read them back like any other bag.

Each topic's ``offered_qos_profiles`` are written into ``metadata.yaml`` (and the mcap
channel's metadata) as ``ros2 bag record`` of ROS 2 Jazzy writes them (rosbag2 format
version 9: a YAML list of profiles with the policies as names, the durations as
``sec``/``nsec``), and ``ros_distro: jazzy``: ``ros2 bag play`` then publishes every
topic reliable and transient local (:data:`OFFERED_QOS`), which every reader of the
graph matches, the transient-local ones (kpi_scorer on ``bac/run_segment``,
run_segmenter on ``imu/vehicle`` and ``bac/trial``, vehicle_sim on ``bac/trial``)
included. Bags without profiles (recorded before 2026-11-24) read as before.

Layout inside a campaign folder::

    <campaign_dir>/bags/trial_0001/       a rosbag2 folder (metadata.yaml + trial_0001_0.mcap)
    <campaign_dir>/bags/trial_0002/
    ...
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import yaml
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from bac_common.errors import BacError

# topic -> message type of everything a campaign records
RECORDED_TOPICS: dict[str, str] = {
    "imu/data_raw": "sensor_msgs/msg/Imu",
    "imu/vehicle": "sensor_msgs/msg/Imu",
    "vehicle/odom": "nav_msgs/msg/Odometry",
    "bac/trial": "bac_msgs/msg/Trial",
    "bac/run_segment": "bac_msgs/msg/RunSegment",
    "bac/run_score": "bac_msgs/msg/RunScore",
    "bac/calibration": "bac_msgs/msg/Calibration",
}
BAC_MSG_NAMES = ("Calibration", "Trial", "RunSegment", "RunScore")
# appended to a bac_msgs message recorded before fields were added at its end (RunScore.outcome_names and
# outcome_values, 2026-11-24): zero bytes read as the empty sequences (and the alignment before them), so an
# older message decodes as the current one with those fields empty
OLD_MESSAGE_PAD = bytes(16)
ROS_DISTRO = "jazzy"

# RMW_DURATION_INFINITE as rosbag2 writes a duration a publisher left at its default (sec, nsec)
QOS_INFINITE = QosTime(9223372036, 854775807)
# what the recorded topics are offered as, as ``ros2 bag record`` records a publisher's offer from discovery
# (history and depth are not discovered: unknown, 0). Reliable + transient local: a player re-publishing with it
# matches every reader of the graph (reliable and best-effort readers, volatile and transient-local ones): the
# latched bac/trial and bac/calibration, the transient-local streams (imu/vehicle, bac/run_segment,
# bac/run_score) and the volatile inputs (imu/data_raw, vehicle/odom) alike
OFFERED_QOS = Qos(
    history=QosHistory.UNKNOWN,
    depth=0,
    reliability=QosReliability.RELIABLE,
    durability=QosDurability.TRANSIENT_LOCAL,
    deadline=QOS_INFINITE,
    lifespan=QOS_INFINITE,
    liveliness=QosLiveliness.AUTOMATIC,
    liveliness_lease_duration=QOS_INFINITE,
    avoid_ros_namespace_conventions=False,
)
OFFERED_QOS_BY_TOPIC: dict[str, tuple[Qos, ...]] = {t: (OFFERED_QOS,) for t in RECORDED_TOPICS}
# ros2 bag play's history for every topic (rosbag2_storage::Rosbag2QoS::default_history: rmw's default depth)
PLAYBACK_DEPTH = 10


class RecordingError(BacError, OSError):
    """A bag could not be written."""


def bac_msgs_dir() -> Path:
    """The folder with bac_msgs' .msg files (installed share/ or the source tree)."""
    candidates = []
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        candidates.append(Path(prefix) / "share" / "bac_msgs" / "msg")
    here = Path(__file__).resolve()
    for d in here.parents:
        candidates.append(d / "bac_msgs" / "msg")
        candidates.append(d / "src" / "bac_msgs" / "msg")
    for c in candidates:
        if (c / "Trial.msg").exists():
            return c
    raise RecordingError("cannot find bac_msgs/msg/*.msg: set AMENT_PREFIX_PATH to the bac install prefix")


@lru_cache(maxsize=1)
def bac_typestore() -> Typestore:
    """The ROS 2 Jazzy type store plus the bac_msgs types (from their .msg definitions)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    folder = bac_msgs_dir()
    types = {}
    for name in BAC_MSG_NAMES:
        types.update(get_types_from_msg((folder / f"{name}.msg").read_text(), f"bac_msgs/msg/{name}"))
    store.register(types)
    return store


def cdr_stamp_ns(data: bytes) -> int | None:
    """The leading ``builtin_interfaces/Time`` of a CDR message (a Header's stamp, Trial.stamp), in ns.

    Every recorded type but Calibration starts with one; None when the bytes are too short.
    """
    if len(data) < 12:
        return None
    little = data[1] == 1  # encapsulation: 0x0001 CDR_LE, 0x0000 CDR_BE
    sec = int.from_bytes(data[4:8], "little" if little else "big", signed=True)
    nsec = int.from_bytes(data[8:12], "little" if little else "big", signed=False)
    return sec * 1_000_000_000 + nsec


# --- rosbag2 metadata as ros2 bag record (Jazzy) writes it ---------------------------------------------------

# the order in which rosbag2 (yaml-cpp) writes the fields of metadata.yaml (rosbag2_storage/yaml.hpp, qos.cpp)
_BAG_KEYS = (
    "version",
    "storage_identifier",
    "duration",
    "starting_time",
    "message_count",
    "topics_with_message_count",
    "compression_format",
    "compression_mode",
    "relative_file_paths",
    "files",
    "custom_data",
    "ros_distro",
)
_TOPIC_KEYS = ("name", "type", "serialization_format", "offered_qos_profiles", "type_description_hash")
_QOS_KEYS = (
    "history",
    "depth",
    "reliability",
    "durability",
    "deadline",
    "lifespan",
    "liveliness",
    "liveliness_lease_duration",
    "avoid_ros_namespace_conventions",
)
_FILE_KEYS = ("path", "starting_time", "duration", "message_count")


def _ordered(d: dict[str, Any], keys: Sequence[str]) -> dict[str, Any]:
    return {k: d[k] for k in (*keys, *(k for k in d if k not in keys)) if k in d}


def ordered_qos(profiles: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """QoS profiles (as rosbags dumps them for version 9) in rosbag2's field order."""
    out = []
    for profile in profiles:
        q = {k: (_ordered(v, ("sec", "nsec")) if isinstance(v, dict) else v) for k, v in profile.items()}
        out.append(_ordered(q, _QOS_KEYS))
    return out


def jazzy_metadata(info: dict[str, Any]) -> dict[str, Any]:
    """``rosbag2_bagfile_information`` in rosbag2's field order, with ``ros_distro: jazzy``."""
    out = dict(info)
    out["ros_distro"] = ROS_DISTRO
    topics = []
    for entry in out.get("topics_with_message_count") or []:
        meta = dict(entry["topic_metadata"])
        qos = meta.get("offered_qos_profiles")
        if isinstance(qos, list):
            meta["offered_qos_profiles"] = ordered_qos(qos)
        topics.append({"topic_metadata": _ordered(meta, _TOPIC_KEYS), "message_count": entry["message_count"]})
    out["topics_with_message_count"] = topics
    out["files"] = [_ordered(f, _FILE_KEYS) for f in out.get("files") or []]
    return _ordered(out, _BAG_KEYS)


class _IndentedDumper(yaml.SafeDumper):
    """Block YAML with sequences indented under their key, as yaml-cpp writes them."""

    def increase_indent(self, flow: bool = False, indentless: bool = False) -> None:
        super().increase_indent(flow, False)


def dump_metadata(info: dict[str, Any] | list[dict[str, Any]]) -> str:
    return yaml.dump(info, Dumper=_IndentedDumper, sort_keys=False, default_flow_style=False, width=1 << 16)


class JazzyWriter(Writer):
    """``rosbags``' rosbag2 writer, with the bag's metadata (metadata.yaml and the copy inside the storage file)
    written as ros2 bag record of ROS 2 Jazzy writes it: rosbag2's field order and ``ros_distro: jazzy``
    (rosbags writes ``ros_distro: rosbags``)."""

    def add_connection(self, *args: Any, **kwargs: Any) -> Any:
        storage = self.storage
        if storage is None:
            return super().add_connection(*args, **kwargs)
        add_to_storage = storage.add_connection

        def add_ordered(connection: Any, offered_qos_profiles: str) -> None:
            # the channel's copy, as rosbag2_storage_mcap writes it (serialize_rclcpp_qos_vector, version 9)
            profiles = yaml.safe_load(offered_qos_profiles) if offered_qos_profiles else []
            text = dump_metadata(ordered_qos(profiles)).strip() if profiles else ""
            add_to_storage(connection, text)

        storage.add_connection = add_ordered  # type: ignore[method-assign]
        try:
            return super().add_connection(*args, **kwargs)
        finally:
            storage.add_connection = add_to_storage  # type: ignore[method-assign]

    def close(self) -> None:
        storage = self.storage
        if storage is not None:
            close_storage = storage.close

            def close_with_distro(version: int, metadata: str) -> None:
                close_storage(version, dump_metadata(jazzy_metadata(yaml.safe_load(metadata))).strip())

            storage.close = close_with_distro  # type: ignore[method-assign]
        super().close()
        doc = yaml.safe_load(self.metapath.read_text())
        doc["rosbag2_bagfile_information"] = jazzy_metadata(doc["rosbag2_bagfile_information"])
        tmp = self.metapath.with_suffix(".yaml.tmp")
        tmp.write_text(dump_metadata(doc))
        tmp.replace(self.metapath)


def playback_qos(profiles: Sequence[Qos]) -> Qos | None:
    """The QoS ``ros2 bag play`` (Jazzy) offers a topic recorded with ``profiles``; None: rosbag2's default
    (reliable, volatile, keep last 10: what a bag without profiles is played with).

    As rosbag2_storage's ``Rosbag2QoS::adapt_offer_to_recorded_offers``: the recorded profile when all agree on
    the policies that decide compatibility (reliability, durability, deadline, liveliness and its lease), with
    history keep last :data:`PLAYBACK_DEPTH`; rosbag2's default otherwise.
    """
    if not profiles:
        return None
    first = profiles[0]
    key = (first.reliability, first.durability, first.deadline, first.liveliness, first.liveliness_lease_duration)
    if any(
        (p.reliability, p.durability, p.deadline, p.liveliness, p.liveliness_lease_duration) != key for p in profiles
    ):
        return None
    return first._replace(history=QosHistory.KEEP_LAST, depth=PLAYBACK_DEPTH)


def read_metadata(path: str | Path) -> dict[str, Any]:
    """``rosbag2_bagfile_information`` of a rosbag2 folder's metadata.yaml."""
    p = Path(path)
    meta = p / "metadata.yaml" if p.is_dir() else p
    try:
        doc = yaml.safe_load(meta.read_text())
        info: dict[str, Any] = doc["rosbag2_bagfile_information"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise RecordingError(f"{meta} is not the metadata.yaml of a rosbag2 folder: {exc}") from exc
    return info


def trial_bag_dir(campaign_dir: str | Path, trial_id: int) -> Path:
    return Path(campaign_dir) / "bags" / f"trial_{trial_id:04d}"


class TrialBagWriter:
    """A rosbag2 (mcap by default) for one trial; topics are added as their first message arrives, with their
    offered QoS (:data:`OFFERED_QOS_BY_TOPIC`, or ``qos``)."""

    def __init__(
        self,
        path: str | Path,
        storage: str = "mcap",
        topics: dict[str, str] | None = None,
        qos: dict[str, Sequence[Qos]] | None = None,
    ) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise RecordingError(f"{self.path} exists already: a bag is never overwritten")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
        if plugin is None:
            raise RecordingError(f"unknown bag storage {storage!r} (mcap or sqlite3)")
        self.topics = dict(RECORDED_TOPICS if topics is None else topics)
        self.qos = {**OFFERED_QOS_BY_TOPIC, **(qos or {})}
        self.store = bac_typestore()
        self._writer = JazzyWriter(self.path, version=9, storage_plugin=plugin)
        self._writer.open()
        self._connections: dict[str, object] = {}
        self.count = 0

    def write(self, topic: str, stamp_ns: int, data: bytes) -> None:
        """Append one serialized (CDR) message received on ``topic`` at ``stamp_ns``."""
        conn = self._connections.get(topic)
        if conn is None:
            msgtype = self.topics.get(topic)
            if msgtype is None:
                raise RecordingError(f"topic {topic!r} is not one the recorder knows the type of")
            # fully qualified, as ros2 bag record names them
            conn = self._writer.add_connection(
                "/" + topic.lstrip("/"),
                msgtype,
                typestore=self.store,
                offered_qos_profiles=self.qos.get(topic, (OFFERED_QOS,)),
            )
            self._connections[topic] = conn
        self._writer.write(conn, int(stamp_ns), bytes(data))  # type: ignore[arg-type]
        self.count += 1

    def write_many(self, items: Iterable[tuple[str, int, bytes]]) -> None:
        for topic, stamp_ns, data in items:
            self.write(topic, stamp_ns, data)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None  # type: ignore[assignment]

    def __enter__(self) -> TrialBagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
