"""Whole-array CDR codec for stamped messages made of a header and a fixed float64 block.

Every message type the package reads and writes (PointStamped, Vector3Stamped, WrenchStamped,
Twist/AccelWithCovarianceStamped), in bags and on the live topics, is laid out in XCDR1 as

    4-byte encapsulation header 00 01 xx xx (little endian)
    int32 sec, uint32 nanosec, uint32 len(frame_id)+1, frame_id bytes, NUL
    zero padding to 8 bytes (counted from the end of the encapsulation header)
    k float64 values

so with one frame_id all messages of a topic have the same size and are encoded or
decoded as a numpy record array at once. `float64_block` and `vector_and_covariance` say
which float64 values each type holds, and which of them a 3-vector fills: the linear part, or the
angular part of the types that have one (a rotation rate in `twist.angular`). Pure numpy: no rosbags, no ROS.
"""
from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from typing import Sequence

import numpy as np

NS_PER_S = 1_000_000_000
ENCAPSULATION_LE = b"\x00\x01\x00\x00"

#: float64 values after the header, per message type (full name).
FLOAT64_COUNT = {
    "geometry_msgs/msg/PointStamped": 3,  # point
    "geometry_msgs/msg/Vector3Stamped": 3,  # vector
    "geometry_msgs/msg/WrenchStamped": 6,  # force, torque
    "geometry_msgs/msg/TwistWithCovarianceStamped": 42,  # linear, angular, 6x6 covariance
    "geometry_msgs/msg/AccelWithCovarianceStamped": 42,
}
#: The types whose block ends in a 6x6 covariance (row-major) of (linear, angular).
COVARIANCE_TYPES = frozenset(
    {"geometry_msgs/msg/TwistWithCovarianceStamped", "geometry_msgs/msg/AccelWithCovarianceStamped"}
)


class MessageError(ValueError):
    """Serialized bytes do not hold the expected message layout."""


def full_type(msgtype: str) -> str:
    """geometry_msgs/msg/<name> of a short name; a full name as it is."""
    return msgtype if "/" in msgtype else f"geometry_msgs/msg/{msgtype}"


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


@functools.lru_cache(maxsize=64)
def _record(size: int, frame_id_size: int, float64_count: int) -> np.dtype:
    """Structured dtype of `size`-byte messages: encapsulation, stamp, frame_id (with its length), values."""
    layout = Layout(frame_id_size, float64_count)
    fields = {
        "encapsulation": (">u2", 0),
        "sec": ("<i4", 4),
        "nanosec": ("<u4", 8),
        "frame_id_size": ("<u4", 12),
        "frame_id": (("u1", (frame_id_size,)), 16),
        "values": (("<f8", (float64_count,)), layout.values_offset),
    }
    return np.dtype({"names": list(fields), "formats": [f for f, _ in fields.values()],
                     "offsets": [o for _, o in fields.values()], "itemsize": size})


@functools.lru_cache(maxsize=64)
def _encoding(frame_id: str, float64_count: int) -> tuple[np.dtype, np.ndarray]:
    """(record dtype of stamp and values, uint8 bytes every message starts with: encapsulation header,
    zero stamp, frame_id string with its size and NUL) of messages with this frame_id."""
    name = frame_id.encode() + b"\x00"
    layout = Layout(len(name), float64_count)
    dtype = np.dtype({"names": ["sec", "nanosec", "values"], "formats": ["<i4", "<u4", ("<f8", (float64_count,))],
                      "offsets": [4, 8, layout.values_offset], "itemsize": layout.size})
    return dtype, np.frombuffer(ENCAPSULATION_LE + struct.pack("<iII", 0, 0, len(name)) + name, np.uint8)


def encode(stamps_ns: np.ndarray, values: np.ndarray, frame_id: str) -> np.ndarray:
    """(N, size) uint8 CDR messages of (N,) stamps (ns, within the int32 seconds of builtin_interfaces/Time:
    not checked here) and (N, k) float64 values; row i is message i."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    n, k = np.shape(values)
    if len(stamps_ns) != n:
        raise ValueError(f"{len(stamps_ns)} stamps but {n} value rows")
    dtype, prefix = _encoding(frame_id, k)
    records = np.zeros(n, dtype=dtype)
    rows = records.view(np.uint8).reshape(n, dtype.itemsize)
    rows[:, : len(prefix)] = prefix
    sec, nanosec = np.divmod(stamps_ns, NS_PER_S)
    records["sec"] = sec
    records["nanosec"] = nanosec
    records["values"] = values
    return rows


def serialized(rows: np.ndarray) -> list[bytes]:
    """The messages of `encode` as one bytes object each."""
    blob, size = rows.tobytes(), rows.shape[1]
    return [blob[i : i + size] for i in range(0, len(blob), size)]


def decode(messages: Sequence[bytes], float64_count: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(stamps_ns int64 (N,), values float64 (N, k)) of raw CDR messages, or None when they are
    not all little endian with the same size and the same frame_id bytes (then decode each).

    The caller must know that one message holds the standard type (a typed subscription,
    or deserialised once): the rest are then byte-identical to it except in the stamp and
    the values, decoded here.
    """
    n = len(messages)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, float64_count))
    first = messages[0]
    size = len(first)
    if size < 16 or first[:2] != ENCAPSULATION_LE[:2] or any(len(m) != size for m in messages):
        return None
    (frame_id_size,) = struct.unpack_from("<I", first, 12)
    if frame_id_size == 0 or Layout(frame_id_size, float64_count).size > size:
        return None
    records = np.frombuffer(b"".join(messages), _record(size, frame_id_size, float64_count))
    if not ((records["encapsulation"] == 1).all() and (records["frame_id_size"] == frame_id_size).all()
            and (records["frame_id"] == records["frame_id"][0]).all()):
        return None
    return records["sec"].astype(np.int64) * NS_PER_S + records["nanosec"], records["values"].copy()


def decode_one(data: bytes, float64_count: int, kind: str = "message") -> tuple[int, tuple[float, ...]]:
    """(stamp ns, float64 values) of one message of either byte order; MessageError (naming `kind`) if too short."""
    if len(data) < 16:
        raise MessageError(f"{kind} of {len(data)} bytes is too short")
    order = "<" if data[1] & 1 else ">"
    sec, nanosec, frame_id_size = struct.unpack_from(order + "iII", data, 4)
    layout = Layout(frame_id_size, float64_count)
    if layout.size > len(data):
        raise MessageError(f"{kind} of {len(data)} bytes is too short for {float64_count} float64 values")
    return sec * NS_PER_S + nanosec, struct.unpack_from(f"{order}{float64_count}d", data, layout.values_offset)


def decode_each(messages: Sequence[bytes], float64_count: int, kind: str = "message"):
    """(stamps (n,) int64 ns, values (n, k), errors): `decode` at once when it can, else message by
    message (`decode_one`) in order; the messages refused are left out, their MessageErrors listed."""
    decoded = decode(messages, float64_count)
    if decoded is not None:
        return (*decoded, [])
    stamps, values, errors = [], [], []
    for message in messages:
        try:
            stamp, row = decode_one(message, float64_count, kind)
        except MessageError as error:
            errors.append(error)
            continue
        stamps.append(stamp)
        values.append(row)
    return np.array(stamps, np.int64), np.array(values, np.float64).reshape(-1, float64_count), errors


def _part(msgtype: str, angular: bool) -> slice:
    """The float64 values of the 3-vector a topic fills: the linear part (the point, vector, force,
    linear twist or acceleration) or, with `angular`, the angular part (torque, angular twist or
    acceleration) of the types that have one."""
    if not angular:
        return slice(0, 3)
    if FLOAT64_COUNT[msgtype] < 6:
        raise ValueError(f"{msgtype} has no angular part")
    return slice(3, 6)


def float64_block(
    msgtype: str, vector: np.ndarray, covariance: np.ndarray | None = None, angular: bool = False
) -> np.ndarray:
    """(N, k) float64 values of messages of `msgtype` holding vector (N, 3): the point, vector, force
    (torque zero) or linear twist / acceleration (angular zero, covariance (N, 3, 3) in the linear
    block of the 6x6, zeros elsewhere); with `angular`, the torque or angular twist / acceleration
    instead (linear zero, covariance in the angular block)."""
    vector = np.asarray(vector, dtype=np.float64)
    n, msgtype = len(vector), full_type(msgtype)
    count = FLOAT64_COUNT[msgtype]
    part = _part(msgtype, angular)
    if count == 3:
        return vector
    block = np.zeros((n, count))
    block[:, part] = vector
    if msgtype in COVARIANCE_TYPES and covariance is not None:
        block[:, 6:].reshape(n, 6, 6)[:, part, part] = covariance
    return block


def vector_and_covariance(
    msgtype: str, block: np.ndarray, angular: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """The (N, 3) vector of `float64_block` values and, for the covariance types, its (N, 3, 3) block of
    the 6x6: the linear ones, or with `angular` the angular ones."""
    part = _part(full_type(msgtype), angular)
    covariance = None
    if full_type(msgtype) in COVARIANCE_TYPES:
        covariance = block[:, 6:].reshape(-1, 6, 6)[:, part, part].copy()
    return np.ascontiguousarray(block[:, part]), covariance
