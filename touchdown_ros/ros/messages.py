"""Message encoding for the node and the replayer: raw CDR for the per-sample topics, PointCloud2 batches.

Per-sample messages are fixed-layout (a header with a fixed frame_id, then float64
fields), so whole blocks of them are encoded and decoded with numpy and published
as serialized bytes (`Publisher.publish(bytes)`, subscriptions with `raw=True`):
that is what lets a Python node keep up with 10 kHz. Layouts follow the OMG XCDR1
encoding ROS 2 uses (4-byte encapsulation header, then the message with natural
alignment counted from the end of that header). Nothing numerical happens here.
"""
from __future__ import annotations

import array
import functools
import struct
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import PointCloud2, PointField

CDR_LE = b"\x00\x01\x00\x00"
CDR_BE = b"\x00\x00\x00\x00"
NS_PER_S = 1_000_000_000

#: float64 fields after the header, per message type (all our per-sample types).
FLOAT64_FIELDS = {
    "PointStamped": 3,  # point x y z
    "Vector3Stamped": 3,  # vector x y z
    "WrenchStamped": 6,  # force xyz, torque xyz
    "TwistWithCovarianceStamped": 42,  # linear xyz, angular xyz, covariance 6x6 row-major
    "AccelWithCovarianceStamped": 42,
}
#: Fields of the batched input cloud (sensor_msgs/PointCloud2, FLOAT64): t is s after header.stamp.
BATCH_INPUT_FIELDS = ("t", "x", "y", "z")
#: Fields of the batched output cloud, one point per estimated sample.
BATCH_OUTPUT_FIELDS = (
    "t", "x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az", "fx", "fy", "fz", "fn", "ft", "nis",
    "var_vx", "var_vy", "var_vz", "var_ax", "var_ay", "var_az", "radial_contact", "axial_contact",
    "std_fx", "std_fy", "std_fz",
)  # fmt: skip


class MessageError(ValueError):
    """A received message does not have the expected layout."""


def _align(offset: int, to: int) -> int:
    return (offset + to - 1) // to * to


def _values_offset(frame_length: int) -> int:
    """Offset of the first float64 after a header whose frame_id takes `frame_length` bytes (with the NUL).

    4 bytes of encapsulation, then stamp (sec, nanosec), string length and string, the
    float64 aligned to 8 from the end of the encapsulation.
    """
    return 4 + _align(12 + frame_length, 8)


@dataclass(frozen=True)
class FixedLayout:
    """Byte layout of `<header with frame_id> + count float64` messages."""

    frame_id: str
    count: int

    @property
    def values_offset(self) -> int:
        """Offset of the first float64 from the start of the serialized bytes."""
        return _values_offset(len(self.frame_id.encode()) + 1)

    @property
    def size(self) -> int:
        return self.values_offset + 8 * self.count

    def dtype(self) -> np.dtype:
        return _stamped_values(self.size, self.values_offset, self.count)

    def prefix(self) -> np.ndarray:
        """Encapsulation header, zero stamp and frame_id (uint8), the bytes every message starts with."""
        return _prefix(self)


def _record(size: int, **fields: tuple) -> np.dtype:
    """Structured dtype of `size`-byte records: name=(format, byte offset)."""
    return np.dtype({"names": list(fields), "formats": [f for f, _ in fields.values()],
                     "offsets": [o for _, o in fields.values()], "itemsize": size})


@functools.lru_cache(maxsize=64)
def _stamped_values(size: int, values_offset: int, count: int) -> np.dtype:
    """Record of a `size`-byte header (stamp sec, nanosec) + `count` float64 message."""
    return _record(size, sec=("<i4", 4), nanosec=("<u4", 8), values=(("<f8", (count,)), values_offset))


@functools.lru_cache(maxsize=64)
def _prefix(layout: FixedLayout) -> np.ndarray:
    """Encapsulation header, zero stamp and the frame_id string (length includes the NUL), as uint8."""
    frame = layout.frame_id.encode() + b"\x00"
    return np.frombuffer(CDR_LE + struct.pack("<iII", 0, 0, len(frame)) + frame, np.uint8)


def encode_fixed(layout: FixedLayout, stamps_ns: np.ndarray, values: np.ndarray) -> list[bytes]:
    """Serialized messages, one per row of values (n, layout.count), stamped stamps_ns (n,)."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps_ns)
    if n == 0:
        return []
    records = np.zeros(n, dtype=layout.dtype())
    prefix = layout.prefix()
    records.view(np.uint8).reshape(n, layout.size)[:, : len(prefix)] = prefix
    seconds, nanoseconds = np.divmod(stamps_ns, NS_PER_S)
    records["sec"] = seconds
    records["nanosec"] = nanoseconds
    records["values"] = values
    blob = records.tobytes()
    size = layout.size
    return [blob[i : i + size] for i in range(0, n * size, size)]


def decode_fixed(data: bytes, count: int, kind: str = "message") -> tuple[int, tuple[float, ...]]:
    """(stamp ns, count float64 values) of one serialized header + float64 message (`kind` names it in errors)."""
    if len(data) < 16:
        raise MessageError(f"{kind} of {len(data)} bytes is too short")
    order = "<" if data[1] & 1 else ">"
    sec, nanosec, length = struct.unpack_from(order + "iII", data, 4)
    offset = _values_offset(length)
    if offset + 8 * count > len(data):
        raise MessageError(f"{kind} of {len(data)} bytes is too short for {count} float64 values")
    return sec * NS_PER_S + nanosec, struct.unpack_from(f"{order}{count}d", data, offset)


def decode_point(data: bytes) -> tuple[int, float, float, float]:
    """(stamp ns, x, y, z) of a serialized geometry_msgs/PointStamped."""
    stamp, (x, y, z) = decode_fixed(data, 3, "PointStamped")
    return stamp, x, y, z


def decode_points(data: Sequence[bytes]) -> tuple[np.ndarray, np.ndarray, list[MessageError]]:
    """Stamps (n,) int ns and xyz (n, 3) m of serialized PointStamped messages, and the errors of those refused.

    The usual stream (one length, little-endian, one frame_id length) is decoded at once;
    anything else message by message (`decode_point`), in order.
    """
    size = len(data[0]) if data else 0
    if size >= 16 and all(len(d) == size for d in data):
        joined = b"".join(data)
        header = np.frombuffer(joined, _record(size, flags=("u1", 1), frame_length=("<u4", 12)))
        frame_length = int(header["frame_length"][0])
        offset = _values_offset(frame_length)
        if offset + 24 <= size and (header["flags"] & 1).all() and (header["frame_length"] == frame_length).all():
            point = np.frombuffer(joined, _stamped_values(size, offset, 3))
            return point["sec"].astype(np.int64) * NS_PER_S + point["nanosec"], point["values"].copy(), []
    stamps, xyz, errors = [], [], []
    for message in data:
        try:
            stamp, x, y, z = decode_point(message)
        except MessageError as error:
            errors.append(error)
            continue
        stamps.append(stamp)
        xyz.append((x, y, z))
    return np.array(stamps, np.int64), np.array(xyz, np.float64).reshape(-1, 3), errors


def covariance6(linear: np.ndarray | None, n: int) -> np.ndarray:
    """(n, 36) row-major 6x6 covariances: the 3x3 linear block given, zeros elsewhere (as `io.bags` writes)."""
    out = np.zeros((n, 6, 6))
    if linear is not None:
        out[:, :3, :3] = linear
    return out.reshape(n, 36)


def time_msg(stamp_ns: int) -> Time:
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def stamp_ns_of(stamp: Time) -> int:
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def cloud(stamp_ns: int, frame_id: str, names: Sequence[str], columns: np.ndarray) -> PointCloud2:
    """A PointCloud2 of FLOAT64 fields `names`, one point per row of columns (n, len(names))."""
    columns = np.ascontiguousarray(columns, dtype="<f8")
    n, width = columns.shape
    message = PointCloud2()
    message.header.stamp = time_msg(stamp_ns)
    message.header.frame_id = frame_id
    message.height, message.width = 1, n
    message.fields = [PointField(name=name, offset=8 * i, datatype=PointField.FLOAT64, count=1)
                      for i, name in enumerate(names)]
    message.is_bigendian = False
    message.point_step = 8 * width
    message.row_step = 8 * width * n
    message.data = array.array("B", columns.tobytes())
    message.is_dense = True
    return message


def cloud_columns(message: PointCloud2, names: Sequence[str]) -> np.ndarray:
    """The named FLOAT64 fields of a PointCloud2 as (n, len(names)); MessageError if absent or malformed."""
    fields = {f.name: f for f in message.fields}
    missing = [name for name in names if name not in fields]
    if missing:
        raise MessageError(f"PointCloud2 lacks field(s) {', '.join(missing)} (needs FLOAT64 {', '.join(names)})")
    for name in names:
        if fields[name].datatype != PointField.FLOAT64 or fields[name].count not in (0, 1):
            raise MessageError(f"PointCloud2 field {name!r} must be one FLOAT64")
    n = message.width * message.height
    step = message.point_step
    if n == 0:
        return np.empty((0, len(names)))
    if step < 8 or len(message.data) < (n - 1) * step + max(fields[name].offset for name in names) + 8:
        raise MessageError(f"PointCloud2 data of {len(message.data)} bytes is too short for {n} points")
    if message.height > 1 and message.row_step != step * message.width:
        raise MessageError("PointCloud2 rows with padding are not supported")
    dtype = np.dtype(
        {
            "names": list(names),
            "formats": [(">f8" if message.is_bigendian else "<f8")] * len(names),
            "offsets": [fields[name].offset for name in names],
            "itemsize": step,
        }
    )
    data = np.frombuffer(message.data, dtype=np.uint8, count=n * step if len(message.data) >= n * step else -1)
    if len(data) < n * step:  # the last point may be shorter than point_step
        data = np.concatenate([data, np.zeros(n * step - len(data), np.uint8)])
    records = data.view(dtype)
    return np.stack([records[name].astype(np.float64) for name in names], axis=1)


def batch_samples(message: PointCloud2) -> tuple[np.ndarray, np.ndarray]:
    """(stamps ns (n,), xyz (n, 3) m) of a batched displacement cloud: stamp = header.stamp + t."""
    columns = cloud_columns(message, BATCH_INPUT_FIELDS)
    t = columns[:, 0]
    if not np.isfinite(t).all():
        raise MessageError("PointCloud2 field t holds non-finite times")
    stamps = stamp_ns_of(message.header.stamp) + np.rint(t * 1e9).astype(np.int64)
    return stamps, columns[:, 1:]


def batch_cloud(stamp_ns: int, frame_id: str, stamps_ns: np.ndarray, xyz: np.ndarray) -> PointCloud2:
    """A batched displacement cloud (the node's batch input) of samples stamps_ns (n,), xyz (n, 3)."""
    t = (np.asarray(stamps_ns, np.int64) - int(stamp_ns)) / 1e9
    return cloud(stamp_ns, frame_id, BATCH_INPUT_FIELDS, np.column_stack([t, xyz]))


def diagnostic_status(
    name: str, level: bytes, message: str, values: Mapping[str, object], hardware_id: str = ""
) -> DiagnosticStatus:
    """One DiagnosticStatus; values become KeyValue strings (floats with 6 significant digits)."""

    def text(value: object) -> str:
        if isinstance(value, float):
            return f"{value:.6g}"
        return str(value)

    return DiagnosticStatus(
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=str(k), value=text(v)) for k, v in values.items()],
    )


def diagnostic_array(stamp_ns: int, statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
    message = DiagnosticArray()
    message.header.stamp = time_msg(stamp_ns)
    message.status = list(statuses)
    return message


def status_values(status: DiagnosticStatus) -> dict[str, str]:
    """KeyValue list of a status as a dict."""
    return {kv.key: kv.value for kv in status.values}
