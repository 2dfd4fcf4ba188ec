"""Writing a campaign's recordings: one rosbag2 (mcap) per trial, with ``rosbags``.

Pure Python (no rclpy): the recorder node hands over serialized CDR bytes as
they arrived on the wire, so the bags hold exactly what the graph saw and
``ros2 bag``, Foxglove and rclpy read them back like any other bag.

Layout inside a campaign folder::

    <campaign_dir>/bags/trial_0001/       a rosbag2 folder (metadata.yaml + trial_0001_0.mcap)
    <campaign_dir>/bags/trial_0002/
    ...
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from functools import lru_cache
from pathlib import Path

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


def trial_bag_dir(campaign_dir: str | Path, trial_id: int) -> Path:
    return Path(campaign_dir) / "bags" / f"trial_{trial_id:04d}"


class TrialBagWriter:
    """A rosbag2 (mcap by default) for one trial; topics are added as their first message arrives."""

    def __init__(self, path: str | Path, storage: str = "mcap", topics: dict[str, str] | None = None) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise RecordingError(f"{self.path} exists already: a bag is never overwritten")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
        if plugin is None:
            raise RecordingError(f"unknown bag storage {storage!r} (mcap or sqlite3)")
        self.topics = dict(RECORDED_TOPICS if topics is None else topics)
        self.store = bac_typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
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
            conn = self._writer.add_connection("/" + topic.lstrip("/"), msgtype, typestore=self.store)
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
