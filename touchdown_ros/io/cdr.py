"""Whole-array CDR codec for stamped messages made of a header and a fixed float64 block.

Every message type the bags hold (PointStamped, Vector3Stamped, WrenchStamped,
Twist/AccelWithCovarianceStamped) is laid out in XCDR1 little endian as

    4-byte encapsulation header 00 01 xx xx
    int32 sec, uint32 nanosec, uint32 len(frame_id)+1, frame_id bytes, NUL
    zero padding to 8 bytes (counted from the end of the encapsulation header)
    k float64 values

so with one frame_id all messages of a topic have the same size and are encoded or
decoded as an (N, size) uint8 array at once. Pure numpy: no rosbags, no ROS.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

NS_PER_S = 1_000_000_000
ENCAPSULATION_LE = b"\x00\x01\x00\x00"

#: float64 values after the header, per message type.
FLOAT64_COUNT = {
    "geometry_msgs/msg/PointStamped": 3,  # point
    "geometry_msgs/msg/Vector3Stamped": 3,  # vector
    "geometry_msgs/msg/WrenchStamped": 6,  # force, torque
    "geometry_msgs/msg/TwistWithCovarianceStamped": 42,  # linear, angular, 6x6 covariance
    "geometry_msgs/msg/AccelWithCovarianceStamped": 42,
}


def _align8(offset: int) -> int:
    return (offset + 7) & ~7


@dataclass(frozen=True)
class Layout:
    """Byte layout of one message with a given frame_id length."""

    frame_id_size: int  # len(frame_id bytes) + 1 (the NUL), as written in the string length field
    float64_count: int

    @property
    def values_offset(self) -> int:
        """Offset of the first float64 from the start of the message (encapsulation header included)."""
        return 4 + _align8(12 + self.frame_id_size)

    @property
    def size(self) -> int:
        """Message size in bytes."""
        return self.values_offset + 8 * self.float64_count


def split_stamps(stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sec int32, nanosec uint32) of int64 ns stamps, floor division like divmod; checks the int32 range."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    sec, nanosec = np.divmod(stamps, NS_PER_S)
    if sec.size and (sec.min() < -(2**31) or sec.max() >= 2**31):
        raise ValueError("stamp outside the int32 seconds range of builtin_interfaces/Time")
    return sec.astype("<i4"), nanosec.astype("<u4")


def encode(stamps_ns: np.ndarray, values: np.ndarray, frame_id: str) -> np.ndarray:
    """(N, size) uint8 CDR messages of (N,) stamps and (N, k) float64 values; row i is message i."""
    values = np.ascontiguousarray(values, dtype="<f8")
    n, k = values.shape
    name = frame_id.encode() + b"\x00"
    layout = Layout(len(name), k)
    sec, nanosec = split_stamps(stamps_ns)
    if len(sec) != n:
        raise ValueError(f"{len(sec)} stamps but {n} value rows")
    rows = np.zeros((n, layout.size), dtype=np.uint8)
    rows[:, :4] = np.frombuffer(ENCAPSULATION_LE, dtype=np.uint8)
    rows[:, 4:8] = sec.view(np.uint8).reshape(n, 4)
    rows[:, 8:12] = nanosec.view(np.uint8).reshape(n, 4)
    rows[:, 12:16] = np.frombuffer(np.uint32(len(name)).astype("<u4").tobytes(), dtype=np.uint8)
    rows[:, 16 : 16 + len(name)] = np.frombuffer(name, dtype=np.uint8)
    rows[:, layout.values_offset :] = values.view(np.uint8).reshape(n, 8 * k)
    return rows


def decode(messages: Sequence[bytes], float64_count: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(stamps_ns int64 (N,), values float64 (N, k)) of raw CDR messages, or None when they are
    not all little endian with the same size and the same frame_id bytes (then deserialise each).

    The caller must check that one message deserialises properly with the standard type: the
    rest are then byte-identical to it except in the stamp and the values, decoded here.
    """
    n = len(messages)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, float64_count))
    size = len(messages[0])
    if size < 16 or any(len(m) != size for m in messages):
        return None
    rows = np.frombuffer(b"".join(messages), dtype=np.uint8).reshape(n, size)
    first = rows[0]
    if bytes(first[:2]) != ENCAPSULATION_LE[:2]:
        return None
    layout = Layout(int(first[12:16].view("<u4")[0]), float64_count)
    if layout.frame_id_size == 0 or layout.size > size:
        return None
    name_end = 16 + layout.frame_id_size
    same = rows[:, :2] == first[:2]
    if not (same.all() and (rows[:, 12:name_end] == first[12:name_end]).all()):
        return None
    sec = rows[:, 4:8].copy().view("<i4")[:, 0].astype(np.int64)
    nanosec = rows[:, 8:12].copy().view("<u4")[:, 0].astype(np.int64)
    values = rows[:, layout.values_offset : layout.size].copy().view("<f8").astype(np.float64, copy=False)
    return sec * NS_PER_S + nanosec, values
