"""rosbag2 (MCAP storage) reading, validation and atomic writing of the package's topics.

Reads rosbag2 directories (metadata.yaml + .mcap) and bare .mcap files with rosbags'
AnyReader; writes rosbag2 directories in MCAP storage (or a bare .mcap file when the
target ends in .mcap). Messages of the standard layout are decoded and encoded as whole
numpy arrays (`touchdown_ros.io.cdr`), bit-identical to rosbags' per-message serde, which
is the fallback. No ROS installation needed; nothing here imports rclpy.

Every problem with an input bag raises `BagError` (a ValueError) naming the file.
"""
from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from touchdown_ros.io import cdr
from touchdown_ros.io.atomic_install import check_target, fsync, fsync_tree, install

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

#: Short message names this module writes and reads (all hold a stamped 3-vector), and their full names.
MESSAGE_TYPES = {full.rsplit("/", 1)[1]: full for full in cdr.FLOAT64_COUNT}
DISPLACEMENT_TYPE = MESSAGE_TYPES["PointStamped"]
DISPLACEMENT_TOPIC = "/amb/displacement"
TRUTH_VELOCITY_TOPIC = "/truth/velocity"
TRUTH_ACCELERATION_TOPIC = "/truth/acceleration"
TRUTH_CONTACT_FORCE_TOPIC = "/truth/contact_force"
#: |displacement| above this (m) is not a rotor in a ~0.25 mm clearance: the bag is in millimetres.
MILLIMETRE_LIMIT = 0.01


class BagError(ValueError):
    """A bag cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class DisplacementSeries:
    """The displacement topic of one bag: one row per sensor sample."""

    path: Path
    topic: str
    frame_id: str  # of the first message
    stamps_ns: np.ndarray  # (N,) int64, header.stamp
    xyz: np.ndarray  # (N, 3) float64, m


@dataclass(frozen=True)
class VectorSeries:
    """A stamped 3-vector topic (point, vector, force, linear twist or acceleration; with `angular`
    the torque, angular twist or acceleration)."""

    topic: str
    msgtype: str  # full name, e.g. geometry_msgs/msg/PointStamped
    stamps_ns: np.ndarray  # (N,) int64, header.stamp
    values: np.ndarray  # (N, 3) float64
    covariance: np.ndarray | None  # (N, 3, 3) block of values in the 6x6, *WithCovarianceStamped only
    frame_id: str = ""  # of the first message
    angular: bool = False  # values are the angular part of the message (rad/s for a twist), not the linear


@dataclass(frozen=True)
class Truth:
    """Truth topics of a simulated bag, on common stamps (rows without truth are NaN)."""

    stamps_ns: np.ndarray  # (N,) int64
    velocity: np.ndarray  # (N, 3) m/s
    acceleration: np.ndarray  # (N, 3) m/s^2
    contact_force: np.ndarray  # (N, 3) N, sensor x/y/z


@dataclass(frozen=True)
class TopicSeries:
    """A topic to write: one message per row, header.stamp = log time = stamps_ns."""

    topic: str
    msgtype: str  # a key of MESSAGE_TYPES (or its full name)
    stamps_ns: np.ndarray  # (N,) int64
    values: np.ndarray  # (N, 3)
    covariance: np.ndarray | None = None  # (N, 3, 3) block of values in the 6x6, *WithCovarianceStamped only
    frame_id: str = ""
    angular: bool = False  # values fill the angular part (torque, angular twist or acceleration), the linear zero


# ------------------------------------------------------------------------------------------------ reading


def _existing(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag (file or directory)")
    return path


def _unreadable(path: Path, error: Exception) -> BagError:
    return BagError(
        f"{path}: cannot read bag (not a rosbag2/MCAP bag, or truncated or corrupt): {type(error).__name__}: {error}"
    )


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * cdr.NS_PER_S + int(header.stamp.nanosec)


def _float64_block(msg: Any, msgtype: str) -> list[float]:
    """The float64 fields after the header, in CDR order (what `cdr.decode` returns)."""
    def xyz(v: Any) -> list[float]:
        return [v.x, v.y, v.z]

    if msgtype == MESSAGE_TYPES["PointStamped"]:
        return xyz(msg.point)
    if msgtype == MESSAGE_TYPES["Vector3Stamped"]:
        return xyz(msg.vector)
    if msgtype == MESSAGE_TYPES["WrenchStamped"]:
        return xyz(msg.wrench.force) + xyz(msg.wrench.torque)
    if msgtype == MESSAGE_TYPES["TwistWithCovarianceStamped"]:
        t = msg.twist
        return xyz(t.twist.linear) + xyz(t.twist.angular) + list(np.asarray(t.covariance, dtype=np.float64))
    if msgtype == MESSAGE_TYPES["AccelWithCovarianceStamped"]:
        a = msg.accel
        return xyz(a.accel.linear) + xyz(a.accel.angular) + list(np.asarray(a.covariance, dtype=np.float64))
    raise AssertionError(msgtype)


def _decode_topic(topic: str, msgtype: str, raws: list[bytes], store: Any, angular: bool = False) -> VectorSeries:
    """VectorSeries of a topic's raw CDR messages (their angular part with `angular`): whole-array fast
    path, else rosbags per message."""
    k = cdr.FLOAT64_COUNT[msgtype]
    frame_id = ""
    decoded = None
    if raws:
        first = store.deserialize_cdr(raws[0], msgtype)  # also proves the common layout is valid
        frame_id = first.header.frame_id
        if store.hash_rihs01(msgtype) == TYPESTORE.hash_rihs01(msgtype):  # standard definition in the bag
            decoded = cdr.decode(raws, k)
    if decoded is not None:
        stamps, block = decoded
    else:
        messages = [store.deserialize_cdr(raw, msgtype) for raw in raws]
        stamps = np.array([_stamp_ns(m.header) for m in messages], dtype=np.int64)
        block = np.array([_float64_block(m, msgtype) for m in messages], dtype=np.float64).reshape(-1, k)
    return VectorSeries(topic, msgtype, stamps, *cdr.vector_and_covariance(msgtype, block, angular), frame_id, angular)


def _read_topics(
    path: str | Path, topics: Iterable[str], expected: dict[str, str] | None = None, angular: Iterable[str] = ()
) -> tuple[dict[str, str], dict[str, VectorSeries]]:
    """(every topic -> type, the wanted topics present in the bag), in one pass over the bag.

    expected maps a topic to the only full type accepted for it; otherwise any MESSAGE_TYPES type.
    The topics in `angular` are read from their messages' angular part.
    """
    path = _existing(path)
    wanted, expected, angular = set(topics), expected or {}, set(angular)
    try:
        with AnyReader([path], default_typestore=TYPESTORE) as reader:
            available: dict[str, set[str]] = {}
            for c in reader.connections:
                available.setdefault(c.topic, set()).add(c.msgtype)
            for topic in wanted & available.keys():
                _check_topic_type(path, topic, available[topic], expected.get(topic), topic in angular)
            connections = [c for c in reader.connections if c.topic in wanted]
            for c in connections:
                if (encoding := getattr(c.ext, "serialization_format", "ros1")) != "cdr":
                    raise BagError(f"{path}: topic {c.topic} is serialised as {encoding}, not cdr (ROS 2)")
            raws: dict[str, list[bytes]] = {c.topic: [] for c in connections}
            if connections:  # AnyReader.messages(connections=[]) would yield every message of the bag
                for connection, _, raw in reader.messages(connections=connections):
                    raws[connection.topic].append(raw)
            found = {
                t: _decode_topic(t, next(iter(available[t])), r, reader.typestore, t in angular)
                for t, r in raws.items()
            }
    except BagError:
        raise
    except Exception as error:  # rosbags/mcap/lz4/yaml raise many types for corrupt or truncated files
        raise _unreadable(path, error) from error
    return {t: ", ".join(sorted(m)) for t, m in sorted(available.items())}, found


def _check_topic_type(path: Path, topic: str, msgtypes: set[str], expected: str | None, angular: bool) -> None:
    if len(msgtypes) > 1:
        raise BagError(f"{path}: topic {topic} carries several message types: {', '.join(sorted(msgtypes))}")
    (msgtype,) = msgtypes
    if expected is not None and msgtype != expected:
        raise BagError(f"{path}: topic {topic} has type {msgtype}, expected {expected}")
    if msgtype not in cdr.FLOAT64_COUNT:
        raise BagError(
            f"{path}: topic {topic} has type {msgtype}, not a stamped 3-vector type this package reads "
            f"({', '.join(MESSAGE_TYPES.values())})"
        )
    if angular and cdr.FLOAT64_COUNT[msgtype] < 6:
        raise BagError(f"{path}: topic {topic} has type {msgtype}, which has no angular part to read")


def list_topics(path: str | Path) -> dict[str, str]:
    """Topic name -> message type of a bag (types joined by ', ' if a topic has several)."""
    return _read_topics(path, ())[0]


def _missing_topic(path: Path, topic: str, available: dict[str, str]) -> BagError:
    there = ", ".join(f"{t} ({m})" for t, m in available.items()) or "no topics at all"
    return BagError(f"{path}: no topic {topic}; the bag has: {there}")


def read_displacement(path: str | Path, topic: str = DISPLACEMENT_TOPIC, validate: bool = True) -> DisplacementSeries:
    """The displacement topic (PointStamped, m, header.stamp = sample time).

    Raises BagError for an unreadable bag, a missing topic or a wrong type; with validate=True
    also for the problems of `displacement_problems` (validate=False: call it yourself).
    """
    path = Path(path)
    available, found = _read_topics(path, [topic], {topic: DISPLACEMENT_TYPE})
    if topic not in found:
        raise _missing_topic(path, topic, available)
    v = found[topic]
    series = DisplacementSeries(path, topic, v.frame_id, v.stamps_ns, v.values)
    if validate:
        validate_displacement(series)
    return series


def displacement_problems(series: DisplacementSeries, limit: float = MILLIMETRE_LIMIT) -> list[str]:
    """What makes a displacement series unusable (empty): no samples, NaN/inf, header stamps not
    strictly increasing, values in millimetres. Each names how many and the first index."""
    stamps, xyz = series.stamps_ns, series.xyz
    if len(stamps) == 0:
        return ["no messages (empty topic)"]
    problems = []
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        first = int(np.argmin(finite))
        problems.append(
            f"{int((~finite).sum())} sample(s) with NaN or inf, first at index {first} (stamp {stamps[first]} ns)"
        )
    steps = np.diff(stamps)
    if (steps <= 0).any():
        first = int(np.argmax(steps <= 0)) + 1
        problems.append(
            f"header stamps not strictly increasing: {int((steps == 0).sum())} duplicate and "
            f"{int((steps < 0).sum())} decreasing, first at index {first} "
            f"(stamp {stamps[first]} ns after {stamps[first - 1]} ns)"
        )
    large = np.abs(np.where(np.isfinite(xyz), xyz, 0.0)) > limit
    if large.any():
        rows = large.any(axis=1)
        first = int(np.argmax(rows))
        largest = float(np.max(np.abs(xyz[np.isfinite(xyz)])))
        problems.append(
            f"{int(rows.sum())} sample(s) beyond {limit:g} m (largest {largest:g}, first at index {first}): "
            "looks like millimetres, not metres; convert the recording to SI units"
        )
    return problems


def validate_displacement(series: DisplacementSeries, limit: float = MILLIMETRE_LIMIT) -> None:
    """Raise BagError naming the file, the topic and every problem of `displacement_problems`."""
    problems = displacement_problems(series, limit)
    if problems:
        raise BagError(f"{series.path}: topic {series.topic}: " + "; ".join(problems))


def read_vector_topic(
    path: str | Path, topic: str, msgtype: str | None = None, angular: bool = False
) -> VectorSeries | None:
    """A stamped 3-vector topic of a bag (any of MESSAGE_TYPES, or only msgtype); None when absent.

    angular: read the angular part (e.g. `twist.angular`, rad/s, and its covariance block) instead of
    the linear; BagError for a type without one.
    """
    expected = {topic: cdr.full_type(msgtype)} if msgtype else None
    return _read_topics(path, [topic], expected, [topic] if angular else ())[1].get(topic)


def read_truth(
    path: str | Path,
    velocity_topic: str = TRUTH_VELOCITY_TOPIC,
    acceleration_topic: str = TRUTH_ACCELERATION_TOPIC,
    contact_force_topic: str = TRUTH_CONTACT_FORCE_TOPIC,
    stamps_ns: np.ndarray | None = None,
) -> Truth | None:
    """The truth topics of a simulated bag; None when it has none (a real drop test).

    The three topics must share their stamps. With stamps_ns (e.g. the displacement stamps) the
    truth is returned on those stamps, NaN where it has no sample with that exact stamp.
    """
    path = Path(path)
    kinds = {
        velocity_topic: "Vector3Stamped",
        acceleration_topic: "Vector3Stamped",
        contact_force_topic: "WrenchStamped",
    }
    _, found = _read_topics(path, kinds, {t: MESSAGE_TYPES[k] for t, k in kinds.items()})
    if not found:
        return None
    if missing := [t for t in kinds if t not in found]:
        raise BagError(f"{path}: truth topic(s) {', '.join(missing)} missing while {', '.join(found)} present")
    velocity, acceleration, force = (found[t] for t in kinds)
    for name, series in ((acceleration_topic, acceleration), (contact_force_topic, force)):
        if not np.array_equal(series.stamps_ns, velocity.stamps_ns):
            raise BagError(f"{path}: truth topic {name} is not on the stamps of {velocity_topic}")
    truth = Truth(velocity.stamps_ns, velocity.values, acceleration.values, force.values)
    return truth if stamps_ns is None else align_truth(truth, stamps_ns)


def align_truth(truth: Truth, stamps_ns: np.ndarray) -> Truth:
    """truth on the given stamps: rows matched by exact stamp, NaN where truth has none."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    order = np.argsort(truth.stamps_ns, kind="stable")
    sorted_stamps = truth.stamps_ns[order]
    pos = np.minimum(np.searchsorted(sorted_stamps, stamps_ns), max(len(order) - 1, 0))
    matched = (sorted_stamps[pos] == stamps_ns) if len(order) else np.zeros(len(stamps_ns), dtype=bool)
    rows = order[pos] if len(order) else pos

    def take(values: np.ndarray) -> np.ndarray:
        out = np.full((len(stamps_ns), 3), np.nan)
        out[matched] = values[rows[matched]]
        return out

    return Truth(stamps_ns, take(truth.velocity), take(truth.acceleration), take(truth.contact_force))


# ------------------------------------------------------------------------------------------------ writing


def encode_series(series: TopicSeries) -> np.ndarray:
    """(N, size) uint8: the CDR messages of a topic, row i = message i (checks the series first)."""
    check_series(series)
    msgtype = cdr.full_type(series.msgtype)
    block = cdr.float64_block(msgtype, series.values, series.covariance, series.angular)
    return cdr.encode(series.stamps_ns, block, series.frame_id)


def check_series(series: TopicSeries) -> None:
    """Raise ValueError unless the series can be written as it says."""
    where = f"topic {series.topic}"
    msgtype = cdr.full_type(series.msgtype)
    if msgtype not in cdr.FLOAT64_COUNT:
        raise ValueError(f"{where}: cannot write message type {series.msgtype!r}; known: {', '.join(MESSAGE_TYPES)}")
    stamps = np.asarray(series.stamps_ns)
    if stamps.ndim != 1 or not (stamps.dtype.kind in "iu" or stamps.size == 0):
        raise ValueError(f"{where}: stamps_ns must be a 1-D integer array (ns), got {stamps.dtype} {stamps.shape}")
    n = len(stamps)
    if np.shape(series.values) != (n, 3):
        raise ValueError(f"{where}: {n} stamps but values of shape {np.shape(series.values)}")
    if series.covariance is not None:
        if msgtype not in cdr.COVARIANCE_TYPES:
            raise ValueError(f"{where}: a covariance is given but {msgtype} has none")
        if np.shape(series.covariance) != (n, 3, 3):
            raise ValueError(f"{where}: covariance must be ({n}, 3, 3), got {np.shape(series.covariance)}")
    if series.angular and cdr.FLOAT64_COUNT[msgtype] < 6:
        raise ValueError(f"{where}: angular values but {msgtype} has no angular part")
    if n and (stamps.min() < 0 or stamps.max() >= 2**31 * cdr.NS_PER_S):
        raise ValueError(f"{where}: stamps must lie in [0, 2^31 s) ns (log times are unsigned, seconds int32)")


def _write_messages(
    target: Path, series: Sequence[TopicSeries], encoded: Sequence[np.ndarray], custom_data: Mapping[str, str]
) -> None:
    """A rosbag2 MCAP directory at target (which must not exist), messages of all topics in stamp order."""
    stamps = [np.asarray(s.stamps_ns, dtype=np.int64) for s in series]
    all_stamps = np.concatenate(stamps) if stamps else np.zeros(0, dtype=np.int64)
    topic_of = np.concatenate([np.full(len(s), t) for t, s in enumerate(stamps)]) if stamps else np.zeros(0, int)
    row_of = np.concatenate([np.arange(len(s)) for s in stamps]) if stamps else np.zeros(0, int)
    order = np.lexsort((row_of, topic_of, all_stamps))
    blobs = [memoryview(rows.tobytes()) for rows in encoded]
    sizes = [rows.shape[1] for rows in encoded]
    with Writer(target, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for key, value in custom_data.items():
            writer.set_custom_data(key, value)
        connections = [writer.add_connection(s.topic, cdr.full_type(s.msgtype), typestore=TYPESTORE) for s in series]
        for stamp, t, row in zip(all_stamps[order].tolist(), topic_of[order].tolist(), row_of[order].tolist()):
            size = sizes[t]
            writer.write(connections[t], stamp, blobs[t][row * size : (row + 1) * size])


def write_bag(
    path: str | Path,
    series: Sequence[TopicSeries],
    overwrite: bool = False,
    custom_data: Mapping[str, str] | None = None,
) -> Path:
    """Write topics to a rosbag2 directory in MCAP storage (a bare MCAP file if path ends in .mcap).

    custom_data: string pairs for metadata.yaml's `custom_data` (e.g. the test conditions,
    `condition.<name>`); a bare .mcap file has no metadata.yaml, so they are refused there.

    Messages of all topics are interleaved in stamp order (ties: the order of `series`).
    Atomic: written into a temporary sibling directory, flushed to disk and renamed into place,
    so a failed or interrupted write leaves nothing at path (or the old bag, when overwriting).
    Raises FileExistsError if path exists (unless overwrite, and then only if it is a bag).
    """
    path = Path(path)
    topics = [s.topic for s in series]
    if len(set(topics)) != len(topics):
        raise ValueError(f"{path}: a topic is given twice: {topics}")
    encoded = [encode_series(s) for s in series]
    custom_data = dict(custom_data or {})
    if not all(isinstance(k, str) and isinstance(v, str) for k, v in custom_data.items()):
        raise ValueError(f"{path}: custom_data keys and values must be strings")
    check_target(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    bare = path.suffix == ".mcap"
    if bare and custom_data:
        raise ValueError(f"{path}: a bare .mcap file has no metadata.yaml for custom_data; write a bag directory")
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        bag = staging / (path.stem if bare else path.name)
        _write_messages(bag, series, encoded, custom_data)
        built = bag / f"{bag.name}.mcap" if bare else bag
        fsync_tree(built)
        install(built, path, overwrite)
        fsync(path.parent)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return path


CONDITION_PREFIX = "condition."


def read_conditions(path: str | Path) -> dict[str, str]:
    """The test conditions a bag was recorded under: metadata.yaml `custom_data` entries
    `condition.<name>: <value>` (e.g. condition.axial_load: "true"); {} for a bare .mcap file."""
    path = _existing(path)
    if not path.is_dir():
        return {}
    try:
        metadata = yaml.safe_load((path / "metadata.yaml").read_text())
        custom = metadata["rosbag2_bagfile_information"].get("custom_data") or {}
    except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError) as error:
        raise BagError(f"{path}: metadata.yaml is unreadable: {error}") from None
    return {
        str(k).removeprefix(CONDITION_PREFIX): str(v) for k, v in custom.items() if str(k).startswith(CONDITION_PREFIX)
    }
