"""Vectorized decoding of little-endian CDR sensor_msgs/Imu and nav_msgs/Odometry messages.

Both the nodes (which take their high-rate topics as raw bytes in batches) and
``bac_measure.bagio`` (which reads bags) decode with numpy straight from the
bytes instead of one message object at a time: the layout of a message made
of a Header (stamp, frame_id), optionally one more string, then only float64
fields depends on nothing but the string lengths, so messages are grouped by
layout and each group is one ``np.frombuffer``.

CDR (XCDR1, what ROS 2 puts on the wire and in bags): a 4-byte encapsulation
header (``00 01`` = little-endian), then the payload, each field aligned to
its size relative to the payload start.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

IMU_DOUBLES = 37  # orientation 4, covariance 9, angular velocity 3, covariance 9, linear acceleration 3, covariance 9
IMU_GYRO = slice(13, 16)
IMU_ACCEL = slice(25, 28)
ODOM_DOUBLES = 85  # pose: position 3, orientation 4, covariance 36; twist: linear 3, angular 3, covariance 36
ODOM_X = 0  # pose.pose.position.x
ODOM_POSITION = slice(0, 3)  # pose.pose.position x, y, z
ODOM_VX = 43  # twist.twist.linear.x


def _align(n: int, a: int) -> int:
    return (n + a - 1) // a * a


def _u32(mat: npt.NDArray[np.uint8], col: int) -> IntArray:
    return np.asarray(mat[:, col : col + 4].copy().view("<u4")[:, 0], dtype=np.int64)


def _batches(raws: Sequence[bytes], nstrings: int) -> Iterator[tuple[IntArray, int, npt.NDArray[np.uint8]]]:
    """Group messages by layout: (indices, byte offset of the first double, byte matrix of the group)."""
    lengths = np.fromiter((len(r) for r in raws), dtype=np.int64, count=len(raws))
    for length in np.unique(lengths):
        idx = np.flatnonzero(lengths == length)
        if length < 16:
            yield idx, -1, np.zeros((idx.size, 0), np.uint8)
            continue
        mat = np.frombuffer(b"".join(raws[int(i)] for i in idx), dtype=np.uint8).reshape(idx.size, int(length))
        l1 = _u32(mat, 12)  # frame_id length (payload offset 8)
        keys = [l1]
        if nstrings == 2:
            l2 = np.full(idx.size, -1, np.int64)
            for a in np.unique(l1):
                sel = l1 == a
                p = 4 + _align(12 + int(a), 4)  # second string's length, in bytes from the message start
                if p + 4 <= length:
                    l2[sel] = _u32(mat[sel], p)
            keys.append(l2)
        combo = np.stack(keys, axis=1)
        for key in np.unique(combo, axis=0):
            sel = np.all(combo == key, axis=1)
            p = 12 + int(key[0])
            if nstrings == 2:
                p = _align(p, 4) + 4 + int(key[1])
            yield idx[sel], 4 + _align(p, 8), mat[sel]


def decode(raws: Sequence[bytes], n_doubles: int, nstrings: int) -> tuple[IntArray, FloatArray] | None:
    """(header stamps in ns, the float64 fields (n, n_doubles)) of little-endian CDR messages made of a
    Header, ``nstrings - 1`` more strings and ``n_doubles`` doubles; None when the bytes do not fit
    that layout (big-endian, another type): decode those one by one."""
    if not raws or any(r[:2] != b"\x00\x01" for r in raws):
        return None
    n = len(raws)
    stamps = np.zeros(n, np.int64)
    doubles = np.zeros((n, n_doubles))
    for idx, off, mat in _batches(raws, nstrings):
        if off < 0 or off + 8 * n_doubles != mat.shape[1]:
            return None
        sec = mat[:, 4:8].copy().view("<i4")[:, 0].astype(np.int64)
        nsec = _u32(mat, 8)
        stamps[idx] = sec * 1_000_000_000 + nsec
        doubles[idx] = mat[:, off:].copy().view("<f8")
    return stamps, doubles


def imu(raws: Sequence[bytes]) -> tuple[IntArray, FloatArray, FloatArray] | None:
    """(stamps ns, accel (n, 3), gyro (n, 3)) of CDR sensor_msgs/Imu messages, or None (not decodable here)."""
    d = decode(raws, IMU_DOUBLES, 1)
    if d is None:
        return None
    return d[0], np.ascontiguousarray(d[1][:, IMU_ACCEL]), np.ascontiguousarray(d[1][:, IMU_GYRO])


def odometry(raws: Sequence[bytes]) -> tuple[IntArray, FloatArray, FloatArray] | None:
    """(stamps ns, pose.pose.position (n, 3), twist.twist.linear.x) of CDR nav_msgs/Odometry messages, or None."""
    d = decode(raws, ODOM_DOUBLES, 2)
    if d is None:
        return None
    return d[0], np.ascontiguousarray(d[1][:, ODOM_POSITION]), d[1][:, ODOM_VX].copy()


def frame_id(raw: bytes) -> str:
    """The header's frame_id of a CDR message."""
    n = int.from_bytes(raw[12:16], "little")
    return raw[16 : 16 + max(n - 1, 0)].decode(errors="replace")
