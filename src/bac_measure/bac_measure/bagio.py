"""Reading IMU, odometry and bac_msgs recordings from bags into numpy arrays, without a ROS runtime.

Bags are rosbag2 folders (sqlite3 or mcap), bare ``.mcap`` files and ROS 1
``.bag`` files, all read with ``rosbags``. The measurement chain's pure cores
then work on the arrays offline (rescoring, replay, the health report)::

    imu = read_imu("campaign/bags/trial_0003")            # sensor_msgs/Imu -> ImuArrays
    odom = read_odom("campaign/bags/trial_0003")          # nav_msgs/Odometry -> OdomArrays
    trials = read_trials("campaign/bags/trial_0003")      # bac_msgs/Trial -> TrialEvent list

Little-endian CDR ``Imu`` and ``Odometry`` messages (everything ROS 2 records
on x86 and ARM) are decoded vectorized, straight from the bytes, ~10x faster
than deserializing message by message; the first and last message of each
batch are checked against ``rosbags``' own deserializer. Anything else (ROS 1,
big-endian) takes the message-by-message path.

A missing, truncated or garbage bag raises :class:`BagError` saying which and
what to do.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Qos
from rosbags.typesys.store import Typestore

from bac_common import cdr
from bac_common.errors import BacError
from bac_measure.recording import bac_typestore
from bac_measure.segmentation import OdomSeries

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

IMU_TYPE = "sensor_msgs/msg/Imu"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TRIAL_TYPE = "bac_msgs/msg/Trial"
PREFERRED_IMU_TOPICS = ("/imu/data_raw", "/imu/vehicle")
PREFERRED_ODOM_TOPICS = ("/vehicle/odom",)
STATE_READY_TO_DRIVE = 3  # bac_msgs/Trial.STATE_READY_TO_DRIVE
IMU_DOUBLES = cdr.IMU_DOUBLES
ODOM_DOUBLES = cdr.ODOM_DOUBLES


class BagError(BacError, OSError):
    """A bag is missing, truncated, not a bag, or lacks what was asked for."""


@dataclass(frozen=True)
class ImuArrays:
    """sensor_msgs/Imu messages of one topic, in bag order."""

    topic: str
    frame_id: str  # of the first message
    stamp_ns: IntArray  # header stamps, ns
    recv_ns: IntArray  # bag (receive) time, ns
    accel: FloatArray  # (n, 3) linear_acceleration, m/s^2
    gyro: FloatArray  # (n, 3) angular_velocity, rad/s
    has_recv: bool = True  # False: recv_ns are the stamps (a recording without receive times, e.g. MDF)

    @property
    def recv_or_none(self) -> IntArray | None:
        """The receive times when the recording has them (for the arrival jitter), else None."""
        return self.recv_ns if self.has_recv else None

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])


@dataclass(frozen=True)
class OdomArrays:
    """nav_msgs/Odometry messages of one topic: the pose's position (``distance_m`` is its x: bac's odometer with
    ``distance_source: position_x``; y, z default to 0) and the forward speed (twist.linear.x)."""

    topic: str
    frame_id: str
    stamp_ns: IntArray
    recv_ns: IntArray
    distance_m: FloatArray
    speed_mps: FloatArray
    position_y_m: FloatArray | None = None
    position_z_m: FloatArray | None = None

    def __post_init__(self) -> None:
        for name in ("position_y_m", "position_z_m"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(np.shape(self.stamp_ns)))

    def __len__(self) -> int:
        return int(self.stamp_ns.shape[0])

    def series(self) -> OdomSeries:
        """As the segmentation's :class:`~bac_measure.segmentation.OdomSeries` (position and speed)."""
        return OdomSeries(self.stamp_ns, self.distance_m, self.speed_mps, self.position_y_m, self.position_z_m)


@dataclass(frozen=True)
class TrialEvent:
    """A bac_msgs/Trial message, reduced to what identifies a run and its state."""

    recv_ns: int
    stamp_ns: int  # when the state was entered
    campaign_id: str
    trial_id: int
    attempt: int
    state: int
    reason: str


def _norm(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


BAG_KINDS = "a rosbag2 folder, .mcap, .db3 or ROS 1 .bag"
_MAGIC = {
    b"#ROSBAG V2.0": "bag",
    b"\x89MCAP0\r\n": "bag",
    b"SQLite format 3\x00": "bag",
    b"MDF     ": "an MDF measurement file (read it with --channel-map / bac_measure.mdfio)",
    b"UnFinMF ": "an MDF measurement file that was not finalized",
    b"\x89PNG": "a PNG image",
    b"\xff\xd8\xff": "a JPEG image",
    b"GIF8": "a GIF image",
    b"%PDF": "a PDF document",
    b"PK\x03\x04": "a ZIP archive (unpack it first)",
    b"\x1f\x8b": "a gzip archive (unpack it first)",
    b"BZh": "a bzip2 archive (unpack it first)",
    b"(\xb5/\xfd": "a zstd-compressed file (unpack it first)",
    b"\x7fELF": "a program (ELF)",
}


def describe_file(path: Path) -> str:
    """What a file is by its first bytes: "bag" for a bag, else a short description (a PNG image, a text
    file, ...)."""
    with path.open("rb") as f:
        head = f.read(512)
    for magic, what in _MAGIC.items():
        if head.startswith(magic):
            return what
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return "binary data of an unknown kind"
    first = text.strip().splitlines()[0][:60] if text.strip() else ""
    return f"a text file (it begins {first!r})" if first else "a text file of blank lines"


def check_bag_path(path: Path) -> None:
    """Raise BagError saying what was found when ``path`` is not something a bag reader can open."""
    if not path.exists():
        raise BagError(f"no such bag: {path}")
    if path.is_dir():
        if (path / "metadata.yaml").exists() or any(path.glob("*.mcap")) or any(path.glob("*.db3")):
            return
        if (path / "bags").is_dir():
            return
        entries = sorted(p.name for p in path.iterdir())
        shown = ", ".join(entries[:8]) + (", ..." if len(entries) > 8 else "") if entries else "nothing"
        raise BagError(
            f"{path} is a folder but not a rosbag2 (no metadata.yaml, .mcap or .db3 in it; it holds {shown}); "
            f"give {BAG_KINDS}"
        )
    if path.stat().st_size == 0:
        raise BagError(f"{path} is empty (0 bytes): the recording was never written (a recorder that died at start?)")
    kind = describe_file(path)
    if kind != "bag":
        raise BagError(f"{path} is not a bag: it is {kind}; give {BAG_KINDS}")


class _Bag:
    """An open bag with friendly errors."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        check_bag_path(self.path)
        self.store: Typestore = bac_typestore()
        try:
            self.reader = AnyReader([self.path], default_typestore=self.store)
            self.reader.open()
        except Exception as exc:
            raise self._error(exc) from exc

    def _error(self, exc: Exception) -> BagError:
        text = str(exc) or type(exc).__name__
        hint = (
            "the file is truncated or corrupt (a recording that was cut off?): re-index or recover it "
            "(ros2 bag reindex, mcap recover, rosbag reindex) and retry"
        )
        if isinstance(exc, UnicodeDecodeError | ValueError) and "codec" in text:
            hint = f"this is not a bag ({BAG_KINDS})"
        return BagError(f"cannot read bag {self.path}: {text}; {hint}")

    def __enter__(self) -> _Bag:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.reader.close()
        except Exception:
            pass

    def topics(self) -> dict[str, tuple[str, int]]:
        out: dict[str, tuple[str, int]] = {}
        for c in self.reader.connections:
            typ, n = out.get(c.topic, (c.msgtype, 0))
            out[c.topic] = (typ, n + c.msgcount)
        return out

    def pick(self, topic: str | None, msgtype: str, preferred: Sequence[str]) -> str:
        topics = self.topics()
        if topic is not None:
            t = _norm(topic)
            if t not in topics:
                raise BagError(f"{self.path} has no topic {t}; it has: {', '.join(sorted(topics)) or 'nothing'}")
            if topics[t][0] != msgtype:
                raise BagError(f"{self.path}: topic {t} carries {topics[t][0]}, not {msgtype}")
            return t
        cands = sorted(t for t, (typ, n) in topics.items() if typ == msgtype)
        if not cands:
            shown = ", ".join(f"{t} ({typ}, {n})" for t, (typ, n) in sorted(topics.items())) or "none"
            what = {
                IMU_TYPE: "record the IMU driver's sensor_msgs/Imu topic (ros2 bag record /imu/data_raw ...)",
                ODOM_TYPE: "record the odometry (nav_msgs/Odometry) to cut runs, or score the whole recording "
                "(--window whole)",
            }.get(msgtype, "record it")
            raise BagError(f"{self.path} holds no {msgtype} messages; its topics: {shown}; {what}")
        if len(cands) == 1:
            return cands[0]
        for p in preferred:
            if p in cands:
                return p
        raise BagError(f"{self.path} holds {msgtype} on several topics ({', '.join(cands)}): name one")

    def raw(self, topic: str) -> Iterator[tuple[Any, int, bytes]]:
        conns = [c for c in self.reader.connections if c.topic == topic]
        if not conns:  # rosbags reads every message when given no connections
            return
        try:
            yield from self.reader.messages(connections=conns)
        except Exception as exc:
            raise self._error(exc) from exc

    def deserialize(self, raw: bytes, conn: Any) -> Any:
        try:
            return self.reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise BagError(f"{self.path}: a {conn.msgtype} message on {conn.topic} cannot be decoded: {exc}") from exc


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topic -> (message type, count) of a bag."""
    with _Bag(path) as bag:
        return bag.topics()


def offered_qos(path: str | Path) -> dict[str, list[Qos]]:
    """Topic -> the QoS profiles its publishers offered, as the bag recorded them (rosbag2 ``offered_qos_profiles``:
    metadata.yaml, or an mcap channel's metadata); an empty list for a bag that recorded none (bags written by bac
    before 2026-11-24, ROS 1 bags). :func:`bac_measure.recording.playback_qos` gives what ``ros2 bag play``
    offers from them."""
    with _Bag(path) as bag:
        out: dict[str, list[Qos]] = {}
        for c in bag.reader.connections:
            profiles = getattr(getattr(c, "ext", None), "offered_qos_profiles", None) or []
            out.setdefault(c.topic, []).extend(profiles)
        return out


# --- vectorized CDR (bac_common.cdr) ----------------------------------------------------------------------


def _fast_cdr(raws: list[bytes], n_doubles: int, nstrings: int) -> tuple[IntArray, FloatArray] | None:
    return cdr.decode(raws, n_doubles, nstrings)


def _frame(raw: bytes) -> str:
    return cdr.frame_id(raw)


def _stamp(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _imu_arrays(bag: _Bag, t: str, conns: list[Any], recv: list[int], raws: list[bytes]) -> ImuArrays:
    if not raws:
        raise BagError(f"{bag.path}: topic {t} holds no messages")
    recv_ns = np.asarray(recv, dtype=np.int64)
    fast = _fast_cdr(raws, IMU_DOUBLES, 1) if _is_cdr(bag, conns[0]) else None
    if fast is not None:
        stamps, d = fast
        accel, gyro = d[:, cdr.IMU_ACCEL], d[:, cdr.IMU_GYRO]
        for i in (0, len(raws) - 1):  # spot check against rosbags' own decoder
            m = bag.deserialize(raws[i], conns[i])
            got = (accel[i, 0], accel[i, 2], gyro[i, 1], stamps[i])
            want = (m.linear_acceleration.x, m.linear_acceleration.z, m.angular_velocity.y, _stamp(m.header))
            if not all(_same(a, b) for a, b in zip(got, want, strict=True)):
                fast = None
                break
    if fast is not None:
        return ImuArrays(t, _frame(raws[0]), stamps, recv_ns, np.ascontiguousarray(accel), np.ascontiguousarray(gyro))
    stamps = np.zeros(len(raws), np.int64)
    accel = np.zeros((len(raws), 3))
    gyro = np.zeros((len(raws), 3))
    frame = ""
    for i, (c, raw) in enumerate(zip(conns, raws, strict=True)):
        m = bag.deserialize(raw, c)
        stamps[i] = _stamp(m.header)
        la, av = m.linear_acceleration, m.angular_velocity
        accel[i] = (la.x, la.y, la.z)
        gyro[i] = (av.x, av.y, av.z)
        if i == 0:
            frame = str(m.header.frame_id)
    return ImuArrays(t, frame, stamps, recv_ns, accel, gyro)


def _odom_arrays(bag: _Bag, t: str, conns: list[Any], recv: list[int], raws: list[bytes]) -> OdomArrays:
    if not raws:
        raise BagError(f"{bag.path}: topic {t} holds no messages")
    recv_ns = np.asarray(recv, dtype=np.int64)
    fast = _fast_cdr(raws, ODOM_DOUBLES, 2) if _is_cdr(bag, conns[0]) else None
    if fast is not None:
        stamps, d = fast
        for i in (0, len(raws) - 1):
            m = bag.deserialize(raws[i], conns[i])
            got = (d[i, 0], d[i, 1], d[i, 2], d[i, cdr.ODOM_VX], stamps[i])
            p = m.pose.pose.position
            want = (p.x, p.y, p.z, m.twist.twist.linear.x, _stamp(m.header))
            if not all(_same(a, b) for a, b in zip(got, want, strict=True)):
                fast = None
                break
    if fast is not None:
        stamps, d = fast
        pos = d[:, cdr.ODOM_POSITION]
        return OdomArrays(
            t,
            _frame(raws[0]),
            stamps,
            recv_ns,
            pos[:, 0].copy(),
            d[:, cdr.ODOM_VX].copy(),
            pos[:, 1].copy(),
            pos[:, 2].copy(),
        )
    stamps = np.zeros(len(raws), np.int64)
    pos = np.zeros((len(raws), 3))
    speed = np.zeros(len(raws))
    frame = ""
    for i, (c, raw) in enumerate(zip(conns, raws, strict=True)):
        m = bag.deserialize(raw, c)
        stamps[i] = _stamp(m.header)
        p = m.pose.pose.position
        pos[i] = (p.x, p.y, p.z)
        speed[i] = m.twist.twist.linear.x
        if i == 0:
            frame = str(m.header.frame_id)
    return OdomArrays(t, frame, stamps, recv_ns, pos[:, 0].copy(), speed, pos[:, 1].copy(), pos[:, 2].copy())


def _collect(bag: _Bag, topics: list[str]) -> dict[str, tuple[list[Any], list[int], list[bytes]]]:
    """Every message of ``topics`` in one pass over the bag: (connections, bag times, bytes) per topic."""
    out: dict[str, tuple[list[Any], list[int], list[bytes]]] = {t: ([], [], []) for t in topics}
    conns = [c for c in bag.reader.connections if c.topic in out]
    if not conns:  # rosbags reads every message when given no connections
        return out
    try:
        for c, ts, raw in bag.reader.messages(connections=conns):
            cs, rs, bs = out[c.topic]
            cs.append(c)
            rs.append(int(ts))
            bs.append(bytes(raw))
    except Exception as exc:
        raise bag._error(exc) from exc
    return out


def read_imu(path: str | Path, topic: str | None = None) -> ImuArrays:
    """Every sensor_msgs/Imu message of ``topic`` (default: the bag's only IMU topic, or imu/data_raw)."""
    with _Bag(path) as bag:
        t = bag.pick(topic, IMU_TYPE, PREFERRED_IMU_TOPICS)
        return _imu_arrays(bag, t, *_collect(bag, [t])[t])


def read_odom(path: str | Path, topic: str | None = None) -> OdomArrays:
    """Every nav_msgs/Odometry message of ``topic`` (default: the bag's only odometry topic, or vehicle/odom)."""
    with _Bag(path) as bag:
        t = bag.pick(topic, ODOM_TYPE, PREFERRED_ODOM_TOPICS)
        return _odom_arrays(bag, t, *_collect(bag, [t])[t])


def read_run(
    path: str | Path, imu_topic: str | None = None, odom_topic: str | None = None
) -> tuple[ImuArrays, OdomArrays]:
    """IMU and odometry of a bag in one pass (half the time of :func:`read_imu` then :func:`read_odom`)."""
    with _Bag(path) as bag:
        ti = bag.pick(imu_topic, IMU_TYPE, PREFERRED_IMU_TOPICS)
        to = bag.pick(odom_topic, ODOM_TYPE, PREFERRED_ODOM_TOPICS)
        got = _collect(bag, [ti, to])
        return _imu_arrays(bag, ti, *got[ti]), _odom_arrays(bag, to, *got[to])


def _is_cdr(bag: _Bag, conn: Any) -> bool:
    fmt = getattr(getattr(conn, "ext", None), "serialization_format", None)
    return fmt == "cdr" and bag.path.suffix != ".bag"


def _same(a: float, b: float) -> bool:
    return (a == b) or (math.isnan(float(a)) and math.isnan(float(b)))


def read_messages(path: str | Path, topic: str) -> list[tuple[int, Any]]:
    """(bag time ns, message) of every message on ``topic``, deserialized by rosbags (bac_msgs types included)."""
    with _Bag(path) as bag:
        t = _norm(topic)
        topics = bag.topics()
        if t not in topics:
            raise BagError(f"{bag.path} has no topic {t}; it has: {', '.join(sorted(topics)) or 'nothing'}")
        return [(int(ts), bag.deserialize(bytes(raw), c)) for c, ts, raw in bag.raw(t)]


def read_trials(path: str | Path, topic: str = "bac/trial") -> list[TrialEvent]:
    """The bac/trial messages of a bag, in order."""
    out = []
    for ts, m in read_messages(path, topic):
        out.append(
            TrialEvent(
                recv_ns=ts,
                stamp_ns=int(m.stamp.sec) * 1_000_000_000 + int(m.stamp.nanosec),
                campaign_id=str(m.campaign_id),
                trial_id=int(m.trial_id),
                attempt=int(m.attempt),
                state=int(m.state),
                reason=str(m.reason),
            )
        )
    return out


def run_starts(trials: Sequence[TrialEvent]) -> list[TrialEvent]:
    """The first READY_TO_DRIVE message of each run (campaign, trial, attempt): where each run starts."""
    seen: set[tuple[str, int, int]] = set()
    out = []
    for e in trials:
        key = (e.campaign_id, e.trial_id, e.attempt)
        if e.state == STATE_READY_TO_DRIVE and key not in seen:
            seen.add(key)
            out.append(e)
    return out


# --- writing (tests, benchmarks, conversions) ---------------------------------------------------------


def _header(T: Any, ns: int, frame: str) -> Any:
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000)),
        frame_id=frame,
    )


def imu_to_cdr(imu: ImuArrays) -> list[tuple[int, bytes]]:
    """(receive time, ROS 2 CDR bytes of a sensor_msgs/Imu) of every sample: what a driver would have sent."""
    ts = bac_typestore()
    T = ts.types
    zeros9 = np.zeros(9)
    V3, Quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    out = []
    for i in range(len(imu)):
        m = T[IMU_TYPE](
            header=_header(T, int(imu.stamp_ns[i]), imu.frame_id),
            orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.array([-1.0, *zeros9[1:]]),
            angular_velocity=V3(x=float(imu.gyro[i, 0]), y=float(imu.gyro[i, 1]), z=float(imu.gyro[i, 2])),
            angular_velocity_covariance=zeros9,
            linear_acceleration=V3(x=float(imu.accel[i, 0]), y=float(imu.accel[i, 1]), z=float(imu.accel[i, 2])),
            linear_acceleration_covariance=zeros9,
        )
        out.append((int(imu.recv_ns[i]), bytes(ts.serialize_cdr(m, IMU_TYPE))))
    return out


def odom_to_cdr(odom: OdomArrays) -> list[tuple[int, bytes]]:
    """(receive time, ROS 2 CDR bytes of a nav_msgs/Odometry) of every sample: distance (or the pose's x) in
    pose.x with the pose's y and z when the arrays carry them, speed in twist.linear.x, as bac reads them."""
    ts = bac_typestore()
    T = ts.types
    zeros36 = np.zeros(36)
    V3, Quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    P, Pose, PwC = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/PoseWithCovariance"]
    Tw, TwC = T["geometry_msgs/msg/Twist"], T["geometry_msgs/msg/TwistWithCovariance"]
    series = odom.series()
    oy = series.position_y_m if series.position_y_m is not None else np.zeros(len(odom))
    oz = series.position_z_m if series.position_z_m is not None else np.zeros(len(odom))
    out = []
    for i in range(len(odom)):
        m = T[ODOM_TYPE](
            header=_header(T, int(odom.stamp_ns[i]), odom.frame_id),
            child_frame_id="base_link",
            pose=PwC(
                pose=Pose(
                    position=P(x=float(odom.distance_m[i]), y=float(oy[i]), z=float(oz[i])),
                    orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                ),
                covariance=zeros36,
            ),
            twist=TwC(
                twist=Tw(linear=V3(x=float(odom.speed_mps[i]), y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)),
                covariance=zeros36,
            ),
        )
        out.append((int(odom.recv_ns[i]), bytes(ts.serialize_cdr(m, ODOM_TYPE))))
    return out


def write_bag(
    path: str | Path,
    imu: ImuArrays | None = None,
    odom: OdomArrays | None = None,
    storage: str = "mcap",
) -> Path:
    """Write IMU and odometry arrays as a rosbag2 (``storage``: mcap or sqlite3) at ``path`` (a new folder)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
    if plugin is None:
        raise BagError(f"storage must be mcap or sqlite3, got {storage!r}")
    ts = bac_typestore()
    p = Path(path)
    items: list[tuple[int, int, bytes]] = []  # (time, connection number, bytes)
    with Writer(p, version=9, storage_plugin=plugin) as w:
        conns = []
        if imu is not None:
            conns.append(w.add_connection(_norm(imu.topic), IMU_TYPE, typestore=ts))
            items += [(t, len(conns) - 1, b) for t, b in imu_to_cdr(imu)]
        if odom is not None:
            conns.append(w.add_connection(_norm(odom.topic), ODOM_TYPE, typestore=ts))
            items += [(t, len(conns) - 1, b) for t, b in odom_to_cdr(odom)]
        items.sort(key=lambda x: x[0])
        for t_ns, ci, data in items:
            w.write(conns[ci], t_ns, data)
    return p
