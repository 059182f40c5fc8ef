"""Bags written here round-trip bit-exactly, are read by the mcap package, the whole-array CDR
codec equals rosbags' per-message serde, bad bags are named, and writes are atomic."""
import errno
from pathlib import Path

import yaml
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer as McapWriter
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer

import touchdown_ros.io.bags as bags
from touchdown_ros.io import atomic_install, cdr
from touchdown_ros.io.bags import (
    MESSAGE_TYPES,
    TYPESTORE,
    BagError,
    DisplacementSeries,
    TopicSeries,
    displacement_problems,
    list_topics,
    read_displacement,
    read_truth,
    read_vector_topic,
    validate_displacement,
    write_bag,
)

START = 1_767_225_600_000_000_000  # 2026-01-01, ns
AWKWARD = np.array(
    [
        [-0.0, 1e-300, 1e-4],
        [2.5e-4, -1.23456789012345e-5, 5e-324],  # 5e-324: smallest subnormal
        [1e300, -1.7976931348623157e308, 0.1 + 0.2 - 0.3],
        [np.pi * 1e-5, -np.e * 1e-6, 7.0],
    ]
)
AWKWARD_STAMPS = np.array([0, 999_999_999, START + 1, (2**31 - 1) * 1_000_000_000 + 999_999_999], dtype=np.int64)


def displacement(n=50, step=100_000, seed=0):
    rng = np.random.default_rng(seed)
    return START + step * np.arange(n, dtype=np.int64), 1e-4 * rng.standard_normal((n, 3))


def record(path, header_stamps, xyz, log_times=None, frame_ids=None, msgtype="PointStamped", little_endian=True):
    """A bag written message by message with rosbags' own serialiser (independent of our codec);
    log times (arrival) may differ from header stamps, frame_ids may differ per message."""
    log_times = header_stamps if log_times is None else log_times
    frame_ids = frame_ids or [""] * len(header_stamps)
    full = MESSAGE_TYPES[msgtype]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/amb/displacement", full, typestore=TYPESTORE)
        for log_time, stamp, row, frame in zip(log_times, header_stamps, xyz, frame_ids):
            message = make_message(msgtype, int(stamp), row, None, frame)
            writer.write(connection, int(log_time), TYPESTORE.serialize_cdr(message, full, little_endian=little_endian))
    return path


def raw_messages(path, topic):
    with AnyReader([path], default_typestore=TYPESTORE) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        return [bytes(raw) for _, _, raw in reader.messages(connections=connections)]


def _header(stamp_ns: int, frame_id: str):
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return TYPESTORE.types["std_msgs/msg/Header"](
        stamp=TYPESTORE.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def _covariance6(block: np.ndarray | None) -> np.ndarray:
    full = np.zeros((6, 6))
    if block is not None:
        full[:3, :3] = block
    return full.ravel()


def make_message(msgtype: str, stamp_ns: int, value: np.ndarray, covariance: np.ndarray | None, frame_id: str):
    """One rosbags message of a MESSAGE_TYPES kind holding value (3,) (and its 3x3 covariance): the
    per-message reference of the numpy encoding."""
    header = _header(stamp_ns, frame_id)
    x, y, z = (float(v) for v in value)
    Vector3, zero = TYPESTORE.types["geometry_msgs/msg/Vector3"], TYPESTORE.types["geometry_msgs/msg/Vector3"](
        x=0.0, y=0.0, z=0.0
    )
    full = cdr.full_type(msgtype)
    if full == MESSAGE_TYPES["PointStamped"]:
        return TYPESTORE.types[full](header=header, point=TYPESTORE.types["geometry_msgs/msg/Point"](x=x, y=y, z=z))
    if full == MESSAGE_TYPES["Vector3Stamped"]:
        return TYPESTORE.types[full](header=header, vector=Vector3(x=x, y=y, z=z))
    if full == MESSAGE_TYPES["WrenchStamped"]:
        return TYPESTORE.types[full](
            header=header, wrench=TYPESTORE.types["geometry_msgs/msg/Wrench"](force=Vector3(x=x, y=y, z=z), torque=zero)
        )
    if full == MESSAGE_TYPES["TwistWithCovarianceStamped"]:
        twist = TYPESTORE.types["geometry_msgs/msg/Twist"](linear=Vector3(x=x, y=y, z=z), angular=zero)
        body = TYPESTORE.types["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist, covariance=_covariance6(covariance)
        )
        return TYPESTORE.types[full](header=header, twist=body)
    if full == MESSAGE_TYPES["AccelWithCovarianceStamped"]:
        accel = TYPESTORE.types["geometry_msgs/msg/Accel"](linear=Vector3(x=x, y=y, z=z), angular=zero)
        body = TYPESTORE.types["geometry_msgs/msg/AccelWithCovariance"](
            accel=accel, covariance=_covariance6(covariance)
        )
        return TYPESTORE.types[full](header=header, accel=body)
    raise ValueError(f"cannot write message type {msgtype!r}; known: {', '.join(MESSAGE_TYPES)}")


def deserialised(raws, msgtype):
    """(stamps, values, covariance) decoded one message at a time by rosbags."""
    messages = [TYPESTORE.deserialize_cdr(raw, msgtype) for raw in raws]
    stamps = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in messages], dtype=np.int64)
    values = np.array([bags._float64_block(m, msgtype)[:3] for m in messages])
    covariance = None
    if msgtype in cdr.COVARIANCE_TYPES:
        covariance = np.array([np.asarray(bags._float64_block(m, msgtype)[6:]).reshape(6, 6)[:3, :3] for m in messages])
    return stamps, values, covariance


def all_types(stamps, values, frame_id="amb"):
    covariance = np.stack([np.diag([1e-9, 2e-9, 3e-9]) + 1e-12 * (i + 1) for i in range(len(stamps))])
    covariance[0, 0, 1] = -0.0
    return [
        TopicSeries("/amb/displacement", "PointStamped", stamps, values, frame_id=frame_id),
        TopicSeries("/v", "Vector3Stamped", stamps, values * 0.5),
        TopicSeries("/f", "WrenchStamped", stamps, values[::-1] * 2.0**-20, frame_id="sensor_frame_é"),
        TopicSeries("/t", "TwistWithCovarianceStamped", stamps, -values, covariance),
        TopicSeries("/a", "geometry_msgs/msg/AccelWithCovarianceStamped", stamps, values / 3, covariance * 2),
    ]


# ------------------------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("name", ["bag", "bare.mcap"])
def test_round_trip_is_bit_exact_for_every_type(tmp_path, name):
    series = all_types(AWKWARD_STAMPS, AWKWARD)
    target = write_bag(tmp_path / name, series)
    assert target.is_file() == name.endswith(".mcap")
    read = read_displacement(target, validate=False)
    assert read.stamps_ns.dtype == np.int64 and read.stamps_ns.tobytes() == AWKWARD_STAMPS.tobytes()
    assert read.xyz.dtype == np.float64 and read.xyz.tobytes() == AWKWARD.tobytes()  # -0.0, subnormals, huge
    assert read.frame_id == "amb" and read.path == target
    for s in series[1:]:
        back = read_vector_topic(target, s.topic)
        assert back.msgtype == cdr.full_type(s.msgtype)
        assert back.stamps_ns.tobytes() == AWKWARD_STAMPS.tobytes()
        assert back.values.tobytes() == np.asarray(s.values, dtype=np.float64).tobytes(), s.topic
        assert back.frame_id == s.frame_id
        if s.covariance is None:
            assert back.covariance is None
        else:
            assert back.covariance.tobytes() == s.covariance.tobytes(), s.topic
    assert read_vector_topic(target, "/absent") is None
    assert list_topics(target) == {s.topic: cdr.full_type(s.msgtype) for s in sorted(series, key=lambda s: s.topic)}


def test_messages_of_all_topics_are_interleaved_in_stamp_order(tmp_path):
    a = TopicSeries("/a", "Vector3Stamped", np.array([30, 10, 20]), np.arange(9.0).reshape(3, 3))
    b = TopicSeries("/b", "PointStamped", np.array([20, 5]), np.ones((2, 3)))
    write_bag(tmp_path / "bag", [a, b])
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    with open(mcap_file, "rb") as handle:  # the order in the file, not re-sorted by the reader
        order = [(c.topic, m.log_time) for _, c, m in make_reader(handle).iter_messages(log_time_order=False)]
    assert order == [("/b", 5), ("/a", 10), ("/a", 20), ("/b", 20), ("/a", 30)]
    back = read_vector_topic(tmp_path / "bag", "/a")
    np.testing.assert_array_equal(back.stamps_ns, [10, 20, 30])
    np.testing.assert_array_equal(back.values, np.arange(9.0).reshape(3, 3)[[1, 2, 0]])


def test_written_bag_is_read_by_the_mcap_reader(tmp_path):
    stamps, xyz = displacement(20)
    series = all_types(stamps, xyz)
    write_bag(tmp_path / "bag", series)
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    metadata = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["storage_identifier"] == "mcap" and metadata["message_count"] == 100
    assert metadata["relative_file_paths"] == [mcap_file.name]
    with open(mcap_file, "rb") as handle:
        reader = make_reader(handle, validate_crcs=True)
        summary = reader.get_summary()
        schemas = {s.id: s for s in summary.schemas.values()}
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {s.topic for s in series}
        for s in series:
            channel = channels[s.topic]
            assert channel.message_encoding == "cdr"
            assert schemas[channel.schema_id].name == cdr.full_type(s.msgtype)
            assert schemas[channel.schema_id].encoding == "ros2msg"
            assert summary.statistics.channel_message_counts[channel.id] == 20
        messages = list(reader.iter_messages())
    assert len(messages) == 100
    assert [m.log_time for _, _, m in messages] == sorted(m.log_time for _, _, m in messages)
    force = [m for _, c, m in messages if c.topic == "/f"]
    decoded = TYPESTORE.deserialize_cdr(force[3].data, MESSAGE_TYPES["WrenchStamped"])
    assert decoded.wrench.force.y == xyz[::-1][3, 1] * 2.0**-20 and decoded.wrench.torque.z == 0.0
    assert decoded.header.frame_id == "sensor_frame_é"
    assert decoded.header.stamp.sec * 1_000_000_000 + decoded.header.stamp.nanosec == stamps[3] == force[3].log_time


def test_bare_mcap_files_are_read(tmp_path):
    """The .mcap inside a bag alone, and one written by the mcap package (zstd chunks, CRCs), not rosbags."""
    stamps, xyz = displacement(10)
    write_bag(tmp_path / "bag", [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)])
    (inner,) = (tmp_path / "bag").glob("*.mcap")
    copied = tmp_path / "copied.mcap"
    copied.write_bytes(inner.read_bytes())
    assert read_displacement(copied).xyz.tobytes() == xyz.tobytes()

    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as handle:
        writer = McapWriter(handle, compression=CompressionType.ZSTD, chunk_size=256)
        writer.start(profile="ros2", library="test")
        msgdef, _ = TYPESTORE.generate_msgdef(bags.DISPLACEMENT_TYPE, ros_version=2)
        schema = writer.register_schema(bags.DISPLACEMENT_TYPE, "ros2msg", msgdef.encode())
        channel = writer.register_channel("/amb/displacement", "cdr", schema)
        for stamp, row in zip(stamps, xyz):
            data = TYPESTORE.serialize_cdr(
                make_message("PointStamped", stamp, row, None, "amb"), bags.DISPLACEMENT_TYPE
            )
            writer.add_message(channel, int(stamp), bytes(data), int(stamp))
        writer.finish()
    read = read_displacement(foreign)
    assert read.xyz.tobytes() == xyz.tobytes() and read.stamps_ns.tobytes() == stamps.tobytes()
    assert read.frame_id == "amb"


# ----------------------------------------------------------------------- codec equals rosbags serde


@pytest.mark.parametrize("msgtype", list(MESSAGE_TYPES))
@pytest.mark.parametrize("frame_id", ["", "a", "abc", "abcd", "sensor_x", "cinq_é", "a" * 13])
def test_numpy_encoding_equals_rosbags_serialisation(msgtype, frame_id):
    series = [
        s for s in all_types(AWKWARD_STAMPS, AWKWARD, frame_id) if cdr.full_type(s.msgtype) == MESSAGE_TYPES[msgtype]
    ]
    (s,) = series
    s = TopicSeries(s.topic, s.msgtype, s.stamps_ns, s.values, s.covariance, frame_id)
    rows = bags.encode_series(s)
    for i, stamp in enumerate(s.stamps_ns):
        covariance = None if s.covariance is None else s.covariance[i]
        message = make_message(msgtype, int(stamp), s.values[i], covariance, frame_id)
        assert rows[i].tobytes() == bytes(TYPESTORE.serialize_cdr(message, MESSAGE_TYPES[msgtype])), (msgtype, i)


@pytest.mark.parametrize("msgtype", list(MESSAGE_TYPES))
def test_fast_reader_equals_per_message_deserialisation(tmp_path, monkeypatch, msgtype):
    decode = cdr.decode
    rng = np.random.default_rng(3)
    stamps = np.sort(rng.integers(0, 2**31 * 10**9, 300))
    values = rng.standard_normal((300, 3)) * 10.0 ** rng.integers(-300, 300, (300, 3))
    covariance = rng.standard_normal((300, 3, 3)) if MESSAGE_TYPES[msgtype] in cdr.COVARIANCE_TYPES else None
    path = write_bag(tmp_path / "bag", [TopicSeries("/x", msgtype, stamps, values, covariance, frame_id="base")])
    raws = raw_messages(path, "/x")
    want_stamps, want_values, want_covariance = deserialised(raws, MESSAGE_TYPES[msgtype])
    decoded = cdr.decode(raws, cdr.FLOAT64_COUNT[MESSAGE_TYPES[msgtype]])
    assert decoded is not None  # the fast path is taken for uniform messages
    assert decoded[0].tobytes() == want_stamps.tobytes() and decoded[1][:, :3].tobytes() == want_values.tobytes()
    fast = []
    monkeypatch.setattr(cdr, "decode", lambda *args: fast.append(decode(*args)) or fast[-1])
    got = read_vector_topic(path, "/x")
    assert len(fast) == 1 and fast[0] is not None  # read_vector_topic took the fast path
    assert got.stamps_ns.tobytes() == want_stamps.tobytes() and got.values.tobytes() == want_values.tobytes()
    if covariance is not None:
        assert got.covariance.tobytes() == want_covariance.tobytes() == covariance.tobytes()


def test_angular_series_fill_the_angular_part_and_read_back_from_it(tmp_path, monkeypatch):
    """A rate (twist.angular) or torque series: rosbags' messages hold it in the angular part and its
    covariance in the angular block of the 6x6, zeros elsewhere; read back with angular=True bit-exactly
    (fast path and per-message fallback), the linear part zero."""
    rng = np.random.default_rng(5)
    stamps = START + 100_000 * np.arange(40, dtype=np.int64)
    rates = rng.standard_normal((40, 3)) * 500.0  # rad/s
    covariance = rng.standard_normal((40, 3, 3))
    series = [
        TopicSeries("/rate", "TwistWithCovarianceStamped", stamps, rates, covariance, frame_id="amb", angular=True),
        TopicSeries("/torque", "WrenchStamped", stamps, rates * 2.0, frame_id="amb", angular=True),
    ]
    path = write_bag(tmp_path / "bag", series)
    for raw, rate, block in zip(raw_messages(path, "/rate"), rates, covariance):
        twist = TYPESTORE.deserialize_cdr(raw, MESSAGE_TYPES["TwistWithCovarianceStamped"]).twist
        angular, linear = twist.twist.angular, twist.twist.linear
        assert [angular.x, angular.y, angular.z] == rate.tolist() and [linear.x, linear.y, linear.z] == [0.0] * 3
        full = np.zeros((6, 6))
        full[3:, 3:] = block
        assert np.asarray(twist.covariance).tobytes() == full.ravel().tobytes()
    for raw, rate in zip(raw_messages(path, "/torque"), rates):
        wrench = TYPESTORE.deserialize_cdr(raw, MESSAGE_TYPES["WrenchStamped"]).wrench
        assert [wrench.torque.x, wrench.torque.y, wrench.torque.z] == (2.0 * rate).tolist()
        assert [wrench.force.x, wrench.force.y, wrench.force.z] == [0.0] * 3

    def check(read_back):
        for s in series:
            back = read_back(s.topic)
            assert back.angular and back.stamps_ns.tobytes() == stamps.tobytes(), s.topic
            assert back.values.tobytes() == s.values.tobytes(), s.topic
            assert (back.covariance is None) == (s.covariance is None)
            if s.covariance is not None:
                assert back.covariance.tobytes() == s.covariance.tobytes()

    check(lambda topic: read_vector_topic(path, topic, angular=True))
    linear = read_vector_topic(path, "/rate")
    assert not linear.angular and not linear.values.any() and not linear.covariance.any()
    monkeypatch.setattr(cdr, "decode", lambda *args: None)  # rosbags, message by message
    check(lambda topic: read_vector_topic(path, topic, angular=True))
    points = write_bag(tmp_path / "points", [TopicSeries("/p", "PointStamped", stamps, rates)])
    with pytest.raises(BagError, match="PointStamped, which has no angular part"):
        read_vector_topic(points, "/p", angular=True)


@pytest.mark.parametrize(
    "frame_ids, little_endian",
    [(["a", "bb", "a", "ccc"] * 5, True), (["ab", "cd"] * 10, True), ([""] * 20, False)],
    ids=["frame_id lengths differ", "frame_ids differ", "big endian"],
)
def test_non_uniform_messages_fall_back_to_rosbags(tmp_path, frame_ids, little_endian):
    stamps, xyz = displacement(20)
    path = record(tmp_path / "bag", stamps, xyz, frame_ids=frame_ids, little_endian=little_endian)
    raws = raw_messages(path, "/amb/displacement")
    assert cdr.decode(raws, 3) is None
    want_stamps, want_values, _ = deserialised(raws, bags.DISPLACEMENT_TYPE)
    got = read_displacement(path)
    assert got.stamps_ns.tobytes() == want_stamps.tobytes() == stamps.tobytes()
    assert got.xyz.tobytes() == want_values.tobytes() == xyz.tobytes()
    assert got.frame_id == frame_ids[0]


# ------------------------------------------------------------------------------------------- bad input


def bag_with(tmp_path, stamps, xyz, msgtype="PointStamped", topic="/amb/displacement"):
    return write_bag(tmp_path / "bad", [TopicSeries(topic, msgtype, stamps, xyz)])


def nan_at(rows):
    def spoil(s, x):
        x = x.copy()
        x[rows, 1] = np.nan
        x[rows[-1], 2] = np.inf
        return s, x

    return spoil


@pytest.mark.parametrize(
    "spoil, message",
    [
        (nan_at([7, 12]), r"2 sample\(s\) with NaN or inf, first at index 7 \(stamp 1767225600000700000 ns\)"),
        (
            lambda s, x: (np.where(np.arange(len(s)) == 9, s[8], s), x),
            r"1 duplicate and 0 decreasing, first at index 9",
        ),
        (lambda s, x: (s, x * 1e3), r"20 sample\(s\) beyond 0.01 m .*first at index 0\): looks like millimetres"),
        (
            lambda s, x: (s, np.where(np.arange(len(x))[:, None] == 4, 0.25, x)),
            r"1 sample\(s\) beyond .*index 4.*millimetres",
        ),
    ],
    ids=["nan", "duplicate", "millimetres", "one millimetre sample"],
)
def test_bad_samples_are_named(tmp_path, spoil, message):
    path = bag_with(tmp_path, *spoil(*displacement(20)))
    with pytest.raises(BagError, match=message) as error:
        read_displacement(path)
    assert str(error.value).startswith(f"{path}: topic /amb/displacement: ")
    series = read_displacement(path, validate=False)  # the non-raising mode: series + problems
    assert len(displacement_problems(series)) == 1


def test_header_stamps_out_of_order_are_named(tmp_path):
    """Logged in arrival order (log time increasing) with header stamps reversed or swapped."""
    stamps, xyz = displacement(10)
    reversed_path = record(tmp_path / "reversed", stamps[::-1], xyz, log_times=stamps)
    with pytest.raises(
        BagError, match=r"0 duplicate and 9 decreasing, first at index 1 \(stamp 1767225600000800000 ns after"
    ):
        read_displacement(reversed_path)
    headers = stamps.copy()
    headers[[5, 6]] = headers[[6, 5]]
    with pytest.raises(BagError, match=r"0 duplicate and 1 decreasing, first at index 6") as error:
        read_displacement(record(tmp_path / "swapped", headers, xyz, log_times=stamps))
    assert "swapped" in str(error.value)


def test_several_problems_are_all_reported():
    stamps, xyz = displacement(10)
    xyz = xyz * 1e3
    xyz[3] = np.nan
    stamps[5] = stamps[4]
    series = DisplacementSeries(bags.Path("mem.mcap"), "/d", "", stamps, xyz)
    problems = displacement_problems(series)
    assert len(problems) == 3
    with pytest.raises(BagError, match=r"^mem.mcap: topic /d: 1 sample.*NaN.*; header stamps.*; .*millimetres"):
        validate_displacement(series)
    validate_displacement(DisplacementSeries(bags.Path("ok"), "/d", "", *displacement(10)))


def test_wrong_type_missing_and_empty_topics(tmp_path):
    stamps, xyz = displacement(5)
    wrong = bag_with(tmp_path, stamps, xyz, msgtype="Vector3Stamped")
    with pytest.raises(
        BagError,
        match=rf"^{wrong}: topic /amb/displacement has type geometry_msgs/msg/Vector3Stamped, expected .*PointStamped",
    ):
        read_displacement(wrong)
    with pytest.raises(
        BagError,
        match=rf"^{wrong}: no topic /other; the bag has: /amb/displacement \(geometry_msgs/msg/Vector3Stamped\)",
    ):
        read_displacement(wrong, topic="/other")
    with pytest.raises(BagError, match="has type .*Vector3Stamped, expected .*WrenchStamped"):
        read_vector_topic(wrong, "/amb/displacement", "WrenchStamped")
    empty = write_bag(tmp_path / "empty", [TopicSeries("/amb/displacement", "PointStamped", stamps[:0], xyz[:0])])
    with pytest.raises(BagError, match=rf"^{empty}: topic /amb/displacement: no messages \(empty topic\)"):
        read_displacement(empty)
    assert len(read_displacement(empty, validate=False).stamps_ns) == 0


def test_unsupported_message_type_is_named(tmp_path):
    path = tmp_path / "string"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/amb/displacement", "std_msgs/msg/String", typestore=TYPESTORE)
        writer.write(
            connection,
            1,
            TYPESTORE.serialize_cdr(TYPESTORE.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"),
        )
    with pytest.raises(BagError, match="has type std_msgs/msg/String, not a stamped 3-vector type"):
        read_vector_topic(path, "/amb/displacement")


def test_corrupt_truncated_and_missing_files(tmp_path):
    path = bag_with(tmp_path, *displacement(200))
    (mcap_file,) = path.glob("*.mcap")
    data = mcap_file.read_bytes()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) // 2])
    truncated_in_bag = tmp_path / "truncated_bag"
    truncated_in_bag.mkdir()
    (truncated_in_bag / "metadata.yaml").write_bytes((path / "metadata.yaml").read_bytes())
    (truncated_in_bag / mcap_file.name).write_bytes(data[: len(data) // 2])
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(np.random.default_rng(0).bytes(4096))
    not_a_bag = tmp_path / "not_a_bag"
    not_a_bag.mkdir()
    (not_a_bag / "notes.txt").write_text("hello")
    empty_file = tmp_path / "empty.mcap"
    empty_file.write_bytes(b"")
    for bad in (truncated, truncated_in_bag, garbage, not_a_bag, empty_file):
        for read in (read_displacement, lambda p: read_vector_topic(p, "/x"), read_truth, list_topics):
            with pytest.raises(
                BagError, match=r"cannot read bag \(not a rosbag2/MCAP bag, or truncated or corrupt\)"
            ) as error:
                read(bad)
            assert str(error.value).startswith(f"{bad}: ")
    with pytest.raises(BagError, match=r"nothing_here: no such bag"):
        read_displacement(tmp_path / "nothing_here")


# ----------------------------------------------------------------------------------------------- truth


def truth_series(stamps, xyz, force_stamps=None):
    return [
        TopicSeries("/truth/velocity", "Vector3Stamped", stamps, xyz),
        TopicSeries("/truth/acceleration", "Vector3Stamped", stamps, 2 * xyz),
        TopicSeries("/truth/contact_force", "WrenchStamped", stamps if force_stamps is None else force_stamps, 3 * xyz),
    ]


def test_truth_is_read_and_aligned_to_displacement_stamps(tmp_path):
    stamps, xyz = displacement(10)
    path = write_bag(
        tmp_path / "sim", [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz), *truth_series(stamps, xyz)]
    )
    truth = read_truth(path)
    assert truth.velocity.tobytes() == xyz.tobytes() and truth.contact_force.tobytes() == (3 * xyz).tobytes()
    np.testing.assert_array_equal(truth.stamps_ns, stamps)
    wanted = np.concatenate([stamps[3:6], [stamps[-1] + 1]])  # the last has no truth
    aligned = read_truth(path, stamps_ns=wanted)
    np.testing.assert_array_equal(aligned.stamps_ns, wanted)
    np.testing.assert_array_equal(aligned.acceleration[:3], 2 * xyz[3:6])
    assert np.isnan(aligned.velocity[3]).all()
    assert read_truth(bag_with(tmp_path, stamps, xyz)) is None


def test_truth_topics_must_agree(tmp_path):
    stamps, xyz = displacement(10)
    shifted = write_bag(tmp_path / "shifted", truth_series(stamps, xyz, force_stamps=stamps + 1))
    with pytest.raises(
        BagError, match=rf"^{shifted}: truth topic /truth/contact_force is not on the stamps of /truth/velocity"
    ):
        read_truth(shifted)
    partial = write_bag(tmp_path / "partial", truth_series(stamps, xyz)[:2])
    with pytest.raises(BagError, match=r"truth topic\(s\) /truth/contact_force missing"):
        read_truth(partial)
    renamed = write_bag(
        tmp_path / "renamed",
        [TopicSeries(f"/sim{s.topic}", s.msgtype, s.stamps_ns, s.values) for s in truth_series(stamps, xyz)],
    )
    assert read_truth(renamed) is None
    truth = read_truth(renamed, "/sim/truth/velocity", "/sim/truth/acceleration", "/sim/truth/contact_force")
    assert truth.acceleration.tobytes() == (2 * xyz).tobytes()


# ------------------------------------------------------------------------------------------ atomic writes


def test_invalid_series_are_refused_before_anything_is_written(tmp_path):
    stamps, xyz = displacement(30)
    target = tmp_path / "bag"
    cases = [
        (TopicSeries("/x", "PointStamped", stamps, xyz[:-1]), "30 stamps but values of shape"),
        (TopicSeries("/x", "Imu", stamps, xyz), "cannot write message type 'Imu'"),
        (TopicSeries("/x", "PointStamped", stamps * 1.0, xyz), "integer array"),
        (TopicSeries("/x", "PointStamped", stamps - START - 1, xyz), r"stamps must lie in \[0"),
        (TopicSeries("/x", "PointStamped", stamps, xyz, np.zeros((30, 3, 3))), "has none"),
        (
            TopicSeries("/x", "TwistWithCovarianceStamped", stamps, xyz, np.zeros((30, 6, 6))),
            r"covariance must be \(30, 3, 3\)",
        ),
        (TopicSeries("/x", "Vector3Stamped", stamps, xyz, angular=True), "Vector3Stamped has no angular part"),
    ]
    good = TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)
    for bad, message in cases:
        with pytest.raises(ValueError, match=message):
            write_bag(target, [good, bad])  # the bad one comes last
        assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="a topic is given twice"):
        write_bag(target, [good, good])
    assert list(tmp_path.iterdir()) == []


def failing_after(monkeypatch, calls):
    """Make rosbags' Writer.write raise after `calls` messages (a failure inside the writer loop)."""
    original, count = Writer.write, {"n": 0}

    def write(self, *args, **kwargs):
        count["n"] += 1
        if count["n"] > calls:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Writer, "write", write)
    return count


def test_write_failing_midway_leaves_nothing(tmp_path, monkeypatch):
    stamps, xyz = displacement(30)
    count = failing_after(monkeypatch, 15)
    for target in (tmp_path / "bag", tmp_path / "bare.mcap"):
        with pytest.raises(KeyboardInterrupt):
            write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)])
        assert count["n"] == 16
        count["n"] = 0
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two renames"])
def test_overwrite_is_refused_unless_asked_and_then_atomic(tmp_path, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr(atomic_install, "_renameat2", lambda *args: False)
    stamps, xyz = displacement(30)
    for target in (tmp_path / "bag", tmp_path / "bare.mcap"):
        first = [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)]
        write_bag(target, first)
        with pytest.raises(FileExistsError, match="refusing to overwrite"):
            write_bag(target, first)
        with monkeypatch.context() as patch:
            failing_after(patch, 10)
            with pytest.raises(KeyboardInterrupt):
                write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, 3 * xyz)], overwrite=True)
        assert read_displacement(target).xyz.tobytes() == xyz.tobytes()  # the old bag is intact
        write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, 2 * xyz)], overwrite=True)
        assert read_displacement(target).xyz.tobytes() == (2 * xyz).tobytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "bare.mcap"]
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == ["bag.mcap", "metadata.yaml"]


@pytest.mark.parametrize("failure", [OSError(errno.EIO, "injected: rename failed"), KeyboardInterrupt()],
                         ids=["OSError", "KeyboardInterrupt"])
def test_overwrite_failing_between_the_two_renames_puts_the_old_bag_back(tmp_path, monkeypatch, failure):
    """Without renameat2 the old bag is moved aside, then the new one renamed into place: a failure of
    the second step leaves the old bag at path (write_bag's promise), the staging directory removed."""
    monkeypatch.setattr(atomic_install, "_renameat2", lambda *args: False)
    stamps, xyz = displacement(30)
    for target in (tmp_path / "bag", tmp_path / "bare.mcap"):
        write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)])
        rename, calls = atomic_install.os.rename, []

        def failing_rename(src, dst, *args, **kwargs):
            calls.append((Path(src), Path(dst)))
            if Path(dst) == target and Path(src).name == target.name:  # the new bag, into place
                raise failure
            return rename(src, dst, *args, **kwargs)

        with monkeypatch.context() as patch:
            patch.setattr(atomic_install.os, "rename", failing_rename)
            with pytest.raises(type(failure)) as raised:
                write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, 3 * xyz)], overwrite=True)
        assert raised.value is failure  # the original exception, not a replacement
        assert read_displacement(target).xyz.tobytes() == xyz.tobytes()  # the old bag, back at its path
        moved_aside, into_place = calls[:2]  # the failure came between the two renames
        assert moved_aside[0] == target and moved_aside[1] != target and into_place[1] == target
        assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "bare.mcap"]
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == ["bag.mcap", "metadata.yaml"]


def test_overwrite_refuses_what_is_not_a_bag(tmp_path):
    stamps, xyz = displacement(5)
    precious = tmp_path / "results"
    precious.mkdir()
    (precious / "thesis.tex").write_text("years of work")
    with pytest.raises(FileExistsError, match="is not a rosbag2 directory or .mcap file"):
        write_bag(precious, [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)], overwrite=True)
    assert (precious / "thesis.tex").read_text() == "years of work"
    assert [p.name for p in tmp_path.iterdir()] == ["results"]


def test_conditions_travel_in_metadata_custom_data(tmp_path):
    from touchdown_ros.io.bags import read_conditions

    stamps = np.arange(3, dtype=np.int64) * 100_000
    series = [TopicSeries("/amb/displacement", "PointStamped", stamps, np.zeros((3, 3)))]
    bag = write_bag(tmp_path / "b", series, custom_data={"condition.axial_load": "true", "operator": "ann"})
    assert read_conditions(bag) == {"axial_load": "true"}
    assert read_displacement(bag).xyz.shape == (3, 3)  # still an ordinary bag
    with pytest.raises(ValueError, match="bare .mcap"):
        write_bag(tmp_path / "b.mcap", series, custom_data={"condition.axial_load": "true"})
    assert not (tmp_path / "b.mcap").exists()
    assert read_conditions(write_bag(tmp_path / "c.mcap", series)) == {}
