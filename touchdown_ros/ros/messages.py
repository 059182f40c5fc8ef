"""ROS messages of the node and the replayer: per-sample messages as raw CDR, PointCloud2 batches, diagnostics.

Per-sample messages are fixed-layout (a header with a fixed frame_id, then float64
fields), so whole blocks of them are encoded and decoded with numpy (`io.cdr`, the
codec the bags use too) and published as serialized bytes (`Publisher.publish(bytes)`,
subscriptions with `raw=True`): that is what lets a Python node keep up with 10 kHz.
Nothing numerical happens here.
"""
from __future__ import annotations

import array
from typing import Mapping, Sequence

import geometry_msgs.msg
import numpy as np

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import PointCloud2, PointField

from touchdown_ros.core.estimate import force_std
from touchdown_ros.core.types import VELOCITY
from touchdown_ros.io import cdr
from touchdown_ros.io.cdr import NS_PER_S, MessageError

#: Fields of the batched input cloud (sensor_msgs/PointCloud2, FLOAT64): t is s after header.stamp.
BATCH_INPUT_FIELDS = ("t", "x", "y", "z")
#: Fields of the batched output cloud, one point per estimated sample.
BATCH_OUTPUT_FIELDS = (
    "t", "x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az", "fx", "fy", "fz", "fn", "ft", "nis",
    "var_vx", "var_vy", "var_vz", "var_ax", "var_ay", "var_az", "radial_contact", "axial_contact",
    "std_fx", "std_fy", "std_fz",
)  # fmt: skip
#: Appended to BATCH_OUTPUT_FIELDS where the ring's speed is a state (contact.friction: spinning_ring): rad/s.
RING_OUTPUT_FIELDS = ("omega_ring", "std_omega_ring")


def message_class(msgtype: str) -> type:
    """The rclpy class of a geometry_msgs type (short or full name)."""
    return getattr(geometry_msgs.msg, cdr.full_type(msgtype).rsplit("/", 1)[1])


def float64_count(msgtype: str) -> int:
    """float64 values after the header of a message type (short or full name)."""
    return cdr.FLOAT64_COUNT[cdr.full_type(msgtype)]


def encode_stamped(msgtype: str, stamps_ns: np.ndarray, vector: np.ndarray, covariance: np.ndarray | None,
                   frame_id: str, angular: bool = False) -> list[bytes]:
    """Serialized messages of `msgtype`, one per row of vector (n, 3) (and covariance (n, 3, 3)), stamped (n,) ns;
    the vector in the linear part, or with `angular` the angular part (`io.cdr.float64_block`)."""
    if len(stamps_ns) == 0:
        return []
    return cdr.serialized(cdr.encode(stamps_ns, cdr.float64_block(msgtype, vector, covariance, angular), frame_id))


def decode_point(data: bytes) -> tuple[int, float, float, float]:
    """(stamp ns, x, y, z) of a serialized geometry_msgs/PointStamped."""
    stamp, (x, y, z) = cdr.decode_one(data, 3, "PointStamped")
    return stamp, x, y, z


def decode_points(data: Sequence[bytes]) -> tuple[np.ndarray, np.ndarray, list[MessageError]]:
    """Stamps (n,) int ns and xyz (n, 3) m of serialized PointStamped messages, and the errors of those refused."""
    return cdr.decode_each(data, 3, "PointStamped")


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


def estimate_cloud(out, frame_id: str, ring: bool = False) -> PointCloud2:
    """The batched estimate output (`BATCH_OUTPUT_FIELDS`, then with `ring`, a friction model with the ring's speed
    as a state, `RING_OUTPUT_FIELDS`) of a `core.streaming.StreamOutput`, one point per row, stamped at its first
    row (t in s after it); SI units, variances on the diagonal of each covariance."""
    stamps = out.stamps_ns
    t = (stamps - stamps[0]) / 1e9
    velocity_variance = np.diagonal(out.state_cov[:, VELOCITY, VELOCITY], axis1=1, axis2=2)
    acceleration_variance = np.diagonal(out.acceleration_cov, axis1=1, axis2=2)
    columns = [
        t, out.state[:, :3], out.state[:, VELOCITY], out.acceleration, out.force_xyz, out.F_n, out.F_t, out.nis,
        velocity_variance, acceleration_variance, out.radial_contact, out.axial_contact, force_std(out.force_cov),
    ]  # fmt: skip
    names = BATCH_OUTPUT_FIELDS
    if ring:
        columns += [out.ring_speed, out.ring_speed_std]
        names += RING_OUTPUT_FIELDS
    return cloud(int(stamps[0]), frame_id, names, np.column_stack(columns))


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
