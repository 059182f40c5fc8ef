"""rosbag2 (MCAP storage) reading, validation and atomic writing of the package's topics.

Reads rosbag2 directories (metadata.yaml + .mcap) and bare .mcap files with rosbags'
AnyReader; writes rosbag2 directories in MCAP storage. No ROS installation needed.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_T = TYPESTORE.types

#: Short message names this module writes, and where their 3-vector lives.
MESSAGE_TYPES = {
    "PointStamped": "geometry_msgs/msg/PointStamped",
    "Vector3Stamped": "geometry_msgs/msg/Vector3Stamped",
    "WrenchStamped": "geometry_msgs/msg/WrenchStamped",
    "TwistWithCovarianceStamped": "geometry_msgs/msg/TwistWithCovarianceStamped",
    "AccelWithCovarianceStamped": "geometry_msgs/msg/AccelWithCovarianceStamped",
}
DISPLACEMENT_TYPE = MESSAGE_TYPES["PointStamped"]
#: |displacement| above this is not metres of a rotor in a ~0.25 mm clearance: millimetres.
MILLIMETRE_LIMIT = 0.01


class BagError(ValueError):
    """A bag cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class DisplacementSeries:
    """The displacement topic of one bag: one row per sensor sample."""

    path: Path
    topic: str
    frame_id: str
    stamps_ns: np.ndarray  # (N,) int64, header.stamp
    xyz: np.ndarray  # (N, 3) float64, m


@dataclass(frozen=True)
class VectorSeries:
    """A stamped 3-vector topic (point, vector, force, linear twist or acceleration)."""

    topic: str
    msgtype: str
    stamps_ns: np.ndarray  # (N,) int64
    values: np.ndarray  # (N, 3)
    covariance: np.ndarray | None  # (N, 3, 3) linear block, for *WithCovarianceStamped


@dataclass(frozen=True)
class Truth:
    """Truth topics of a simulated bag, on the velocity topic's stamps."""

    stamps_ns: np.ndarray  # (N,) int64
    velocity: np.ndarray  # (N, 3) m/s
    acceleration: np.ndarray  # (N, 3) m/s^2
    contact_force: np.ndarray  # (N, 3) N


@dataclass(frozen=True)
class TopicSeries:
    """A topic to write: one message per row."""

    topic: str
    msgtype: str  # a key of MESSAGE_TYPES
    stamps_ns: np.ndarray  # (N,) int64
    values: np.ndarray  # (N, 3)
    covariance: np.ndarray | None = None  # (N, 3, 3), *WithCovarianceStamped only
    frame_id: str = ""


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _vector_of(msg: Any, msgtype: str) -> tuple[Any, np.ndarray | None]:
    if msgtype == MESSAGE_TYPES["PointStamped"]:
        return msg.point, None
    if msgtype == MESSAGE_TYPES["Vector3Stamped"]:
        return msg.vector, None
    if msgtype == MESSAGE_TYPES["WrenchStamped"]:
        return msg.wrench.force, None
    if msgtype == MESSAGE_TYPES["TwistWithCovarianceStamped"]:
        return msg.twist.twist.linear, np.asarray(msg.twist.covariance).reshape(6, 6)[:3, :3]
    if msgtype == MESSAGE_TYPES["AccelWithCovarianceStamped"]:
        return msg.accel.accel.linear, np.asarray(msg.accel.covariance).reshape(6, 6)[:3, :3]
    raise BagError(f"message type {msgtype} is not a stamped 3-vector this package reads")


def _read_topic(path: Path, topic: str, expected_type: str | None) -> tuple[str, list[tuple[str, Any]]] | None:
    """(msgtype, [(frame_id, message)]) of one topic; None when the bag has no such topic."""
    if not path.exists():
        raise BagError(f"{path}: no such bag (file or directory)")
    try:
        with AnyReader([path], default_typestore=TYPESTORE) as reader:
            connections = [c for c in reader.connections if c.topic == topic]
            if not connections:
                return None
            msgtype = connections[0].msgtype
            if expected_type is not None and msgtype != expected_type:
                raise BagError(f"{path}: topic {topic} has type {msgtype}, expected {expected_type}")
            messages = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=connections)]
    except BagError:
        raise
    except Exception as error:  # rosbags/mcap raise many types for truncated or corrupt files
        raise BagError(f"{path}: cannot read bag (truncated or corrupt?): {type(error).__name__}: {error}") from None
    return msgtype, messages


def list_topics(path: str | Path) -> dict[str, str]:
    """Topic name -> message type of a bag."""
    path = Path(path)
    try:
        with AnyReader([path], default_typestore=TYPESTORE) as reader:
            return {c.topic: c.msgtype for c in reader.connections}
    except Exception as error:
        raise BagError(f"{path}: cannot read bag (truncated or corrupt?): {type(error).__name__}: {error}") from None


def read_displacement(path: str | Path, topic: str = "/amb/displacement", validate: bool = True) -> DisplacementSeries:
    """The displacement topic (PointStamped, m), validated unless validate=False."""
    path = Path(path)
    found = _read_topic(path, topic, DISPLACEMENT_TYPE)
    if found is None:
        topics = ", ".join(f"{t} ({m})" for t, m in list_topics(path).items()) or "none"
        raise BagError(f"{path}: no topic {topic}; the bag has: {topics}")
    _, messages = found
    if not messages:
        raise BagError(f"{path}: topic {topic} has no messages")
    stamps = np.array([_stamp_ns(m.header) for m in messages], dtype=np.int64)
    xyz = np.array([[m.point.x, m.point.y, m.point.z] for m in messages], dtype=np.float64)
    series = DisplacementSeries(path, topic, messages[0].header.frame_id, stamps, xyz)
    if validate:
        problems = displacement_problems(series)
        if problems:
            raise BagError(f"{path}: topic {topic}: " + "; ".join(problems))
    return series


def displacement_problems(series: DisplacementSeries) -> list[str]:
    """What makes a displacement series unusable: non-finite values, stamps out of order, mm."""
    problems = []
    finite = np.isfinite(series.xyz).all(axis=1)
    if not finite.all():
        first = int(np.argmin(finite))
        problems.append(
            f"{int((~finite).sum())} sample(s) with NaN or inf, first at index {first} (stamp {series.stamps_ns[first]} ns)"
        )
    steps = np.diff(series.stamps_ns)
    if (steps <= 0).any():
        first = int(np.argmax(steps <= 0)) + 1
        kind = "duplicate" if steps[first - 1] == 0 else "decreasing"
        problems.append(
            f"header stamps not increasing: {int((steps <= 0).sum())} {kind} or out-of-order stamp(s), "
            f"first at index {first} (stamp {series.stamps_ns[first]} ns)"
        )
    largest = float(np.nanmax(np.abs(np.where(np.isfinite(series.xyz), series.xyz, 0.0)))) if len(series.xyz) else 0.0
    if largest > MILLIMETRE_LIMIT:
        problems.append(
            f"displacements up to {largest:g} look like millimetres, not metres (limit {MILLIMETRE_LIMIT} m): "
            "convert the recording to SI units"
        )
    return problems


def read_vector_topic(path: str | Path, topic: str) -> VectorSeries | None:
    """A stamped 3-vector topic of a bag; None when the bag does not have it."""
    path = Path(path)
    found = _read_topic(path, topic, None)
    if found is None:
        return None
    msgtype, messages = found
    vectors = [_vector_of(m, msgtype) for m in messages]
    stamps = np.array([_stamp_ns(m.header) for m in messages], dtype=np.int64)
    values = np.array([[v.x, v.y, v.z] for v, _ in vectors], dtype=np.float64).reshape(-1, 3)
    covariance = np.array([c for _, c in vectors]) if vectors and vectors[0][1] is not None else None
    return VectorSeries(topic, msgtype, stamps, values, covariance)


def read_truth(
    path: str | Path,
    velocity_topic: str = "/truth/velocity",
    acceleration_topic: str = "/truth/acceleration",
    contact_force_topic: str = "/truth/contact_force",
) -> Truth | None:
    """The truth topics of a simulated bag; None when it has none (a real drop test)."""
    velocity = read_vector_topic(path, velocity_topic)
    if velocity is None:
        return None
    acceleration = read_vector_topic(path, acceleration_topic)
    force = read_vector_topic(path, contact_force_topic)
    for name, series in ((acceleration_topic, acceleration), (contact_force_topic, force)):
        if series is None or not np.array_equal(series.stamps_ns, velocity.stamps_ns):
            raise BagError(f"{path}: truth topic {name} is missing or not on the stamps of {velocity_topic}")
    return Truth(velocity.stamps_ns, velocity.values, acceleration.values, force.values)


def _header(stamp_ns: int, frame_id: str) -> Any:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _T["std_msgs/msg/Header"](stamp=_T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id)


def _covariance6(block: np.ndarray | None) -> np.ndarray:
    full = np.zeros((6, 6))
    if block is not None:
        full[:3, :3] = block
    return full.ravel()


def make_message(msgtype: str, stamp_ns: int, value: np.ndarray, covariance: np.ndarray | None, frame_id: str) -> Any:
    """One message of a MESSAGE_TYPES kind holding value (3,) (and its 3x3 covariance)."""
    header = _header(stamp_ns, frame_id)
    x, y, z = (float(v) for v in value)
    Vector3, zero = _T["geometry_msgs/msg/Vector3"], _T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    if msgtype == "PointStamped":
        return _T[MESSAGE_TYPES[msgtype]](header=header, point=_T["geometry_msgs/msg/Point"](x=x, y=y, z=z))
    if msgtype == "Vector3Stamped":
        return _T[MESSAGE_TYPES[msgtype]](header=header, vector=Vector3(x=x, y=y, z=z))
    if msgtype == "WrenchStamped":
        wrench = _T["geometry_msgs/msg/Wrench"](force=Vector3(x=x, y=y, z=z), torque=zero)
        return _T[MESSAGE_TYPES[msgtype]](header=header, wrench=wrench)
    if msgtype == "TwistWithCovarianceStamped":
        twist = _T["geometry_msgs/msg/Twist"](linear=Vector3(x=x, y=y, z=z), angular=zero)
        body = _T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=_covariance6(covariance))
        return _T[MESSAGE_TYPES[msgtype]](header=header, twist=body)
    if msgtype == "AccelWithCovarianceStamped":
        accel = _T["geometry_msgs/msg/Accel"](linear=Vector3(x=x, y=y, z=z), angular=zero)
        body = _T["geometry_msgs/msg/AccelWithCovariance"](accel=accel, covariance=_covariance6(covariance))
        return _T[MESSAGE_TYPES[msgtype]](header=header, accel=body)
    raise ValueError(f"cannot write message type {msgtype!r}; known: {', '.join(MESSAGE_TYPES)}")


def _check(series: TopicSeries) -> None:
    n = len(series.stamps_ns)
    if series.msgtype not in MESSAGE_TYPES:
        raise ValueError(f"{series.topic}: cannot write message type {series.msgtype!r}")
    if np.shape(series.values) != (n, 3):
        raise ValueError(f"{series.topic}: {n} stamps but values of shape {np.shape(series.values)}")
    if series.covariance is not None and np.shape(series.covariance) != (n, 3, 3):
        raise ValueError(f"{series.topic}: covariance must be ({n}, 3, 3), got {np.shape(series.covariance)}")


def write_bag(path: str | Path, series: Sequence[TopicSeries], overwrite: bool = False) -> Path:
    """Write topics to a rosbag2 directory in MCAP storage, messages in stamp order.

    Atomic: the bag is written into a temporary sibling directory and renamed into place,
    so a failed or interrupted write leaves nothing at path (or the old bag, when overwriting).
    """
    path = Path(path)
    for s in series:
        _check(s)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; refusing to overwrite it")
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        staged = staging / path.name
        order = sorted(
            ((int(stamp), t, row) for t, s in enumerate(series) for row, stamp in enumerate(s.stamps_ns)),
            key=lambda item: (item[0], item[1]),
        )
        with Writer(staged, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            connections = [writer.add_connection(s.topic, MESSAGE_TYPES[s.msgtype], typestore=TYPESTORE) for s in series]
            for stamp, t, row in order:
                s = series[t]
                covariance = None if s.covariance is None else s.covariance[row]
                message = make_message(s.msgtype, stamp, s.values[row], covariance, s.frame_id)
                writer.write(connections[t], stamp, TYPESTORE.serialize_cdr(message, MESSAGE_TYPES[s.msgtype]))
        if path.exists():
            trash = staging / ".replaced"
            os.replace(path, trash)
        os.replace(staged, path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return path
