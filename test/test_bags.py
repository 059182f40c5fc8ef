"""Bags written here round-trip bit-exactly, are read by the mcap reader, and bad bags are named."""
import numpy as np
import pytest
from mcap.reader import make_reader

import touchdown_ros.io.bags as bags
from touchdown_ros.io.bags import (
    TYPESTORE,
    BagError,
    TopicSeries,
    read_displacement,
    read_truth,
    read_vector_topic,
    write_bag,
)

AWKWARD = np.array([[-0.0, 1e-300, 1e-4], [2.5e-4, -1.23456789012345e-5, 5e-324], [1e-3, -1e-3, 0.1 + 0.2 - 0.3]])


def displacement(n=50, start=1_767_225_600_000_000_000, step=100_000, seed=0):
    rng = np.random.default_rng(seed)
    stamps = start + step * np.arange(n, dtype=np.int64)
    return stamps, 1e-4 * rng.standard_normal((n, 3))


def test_round_trip_is_bit_exact_for_every_type(tmp_path):
    stamps, xyz = displacement(3)
    xyz = AWKWARD
    covariance = np.stack([np.diag([1e-9, 2e-9, 3e-9]) + 1e-12] * 3)
    series = [
        TopicSeries("/amb/displacement", "PointStamped", stamps, xyz, frame_id="amb"),
        TopicSeries("/v", "Vector3Stamped", stamps, xyz * 7),
        TopicSeries("/f", "WrenchStamped", stamps, xyz * 1e9),
        TopicSeries("/t", "TwistWithCovarianceStamped", stamps, xyz, covariance),
        TopicSeries("/a", "AccelWithCovarianceStamped", stamps, xyz, covariance),
    ]
    write_bag(tmp_path / "bag", series)
    read = read_displacement(tmp_path / "bag", validate=False)
    np.testing.assert_array_equal(read.stamps_ns, stamps)
    assert read.xyz.tobytes() == xyz.tobytes()  # bit-exact, -0.0 and subnormals included
    assert read.frame_id == "amb"
    for s in series[1:]:
        back = read_vector_topic(tmp_path / "bag", s.topic)
        assert back.values.tobytes() == np.asarray(s.values, dtype=float).tobytes()
        np.testing.assert_array_equal(back.stamps_ns, stamps)
        if s.covariance is not None:
            assert back.covariance.tobytes() == covariance.tobytes()
    assert read_vector_topic(tmp_path / "bag", "/absent") is None


def test_written_bag_is_read_by_the_mcap_reader(tmp_path):
    stamps, xyz = displacement(20)
    write_bag(tmp_path / "bag", [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)])
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    assert (tmp_path / "bag" / "metadata.yaml").is_file()
    with open(mcap_file, "rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        (schema,) = summary.schemas.values()
        (channel,) = summary.channels.values()
        assert schema.name == "geometry_msgs/msg/PointStamped"
        assert channel.topic == "/amb/displacement" and channel.message_encoding == "cdr"
        messages = list(reader.iter_messages())
    assert len(messages) == 20
    _, _, first = messages[0]
    decoded = TYPESTORE.deserialize_cdr(first.data, "geometry_msgs/msg/PointStamped")
    assert decoded.point.x == xyz[0, 0] and first.log_time == stamps[0]


def test_bare_mcap_file_is_read(tmp_path):
    stamps, xyz = displacement(10)
    write_bag(tmp_path / "bag", [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)])
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    bare = tmp_path / "bare.mcap"
    bare.write_bytes(mcap_file.read_bytes())
    np.testing.assert_array_equal(read_displacement(bare).xyz, xyz)


def _bag_with(tmp_path, stamps, xyz, msgtype="PointStamped", topic="/amb/displacement"):
    path = tmp_path / "bad"
    write_bag(path, [TopicSeries(topic, msgtype, stamps, xyz)])
    return path


@pytest.mark.parametrize(
    "spoil, message",
    [
        (lambda s, x: (s, np.where(np.arange(len(x))[:, None] == 7, np.nan, x)), r"1 sample\(s\) with NaN or inf, first at index 7"),
        (lambda s, x: (np.where(np.arange(len(s)) == 9, s[8], s), x), r"duplicate .* first at index 9"),
        (lambda s, x: (s, x * 1e3), "look like millimetres"),
    ],
)
def test_bad_samples_are_named(tmp_path, spoil, message):
    stamps, xyz = spoil(*displacement(20))
    path = _bag_with(tmp_path, stamps, xyz)
    with pytest.raises(BagError, match=message) as error:
        read_displacement(path)
    assert str(path) in str(error.value)


def test_header_stamps_out_of_recording_order_are_named(tmp_path):
    """Recorded in arrival order (log time increasing) with header stamps 5 and 6 swapped."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    stamps, xyz = displacement(10)
    headers = stamps.copy()
    headers[[5, 6]] = headers[[6, 5]]
    path = tmp_path / "swapped"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/amb/displacement", bags.DISPLACEMENT_TYPE, typestore=TYPESTORE)
        for log_time, header, row in zip(stamps, headers, xyz):
            message = bags.make_message("PointStamped", header, row, None, "")
            writer.write(connection, int(log_time), TYPESTORE.serialize_cdr(message, bags.DISPLACEMENT_TYPE))
    with pytest.raises(BagError, match=r"decreasing or out-of-order stamp\(s\), first at index 6"):
        read_displacement(path)


def test_wrong_type_missing_and_empty_topics(tmp_path):
    stamps, xyz = displacement(5)
    wrong = _bag_with(tmp_path, stamps, xyz, msgtype="Vector3Stamped")
    with pytest.raises(BagError, match="has type geometry_msgs/msg/Vector3Stamped, expected .*PointStamped"):
        read_displacement(wrong)
    with pytest.raises(BagError, match=r"no topic /other; the bag has: /amb/displacement"):
        read_displacement(wrong, topic="/other")
    empty = tmp_path / "empty"
    write_bag(empty, [TopicSeries("/amb/displacement", "PointStamped", stamps[:0], xyz[:0])])
    with pytest.raises(BagError, match="has no messages"):
        read_displacement(empty)


def test_corrupt_truncated_and_missing_files(tmp_path):
    stamps, xyz = displacement(200)
    path = _bag_with(tmp_path, stamps, xyz)
    (mcap_file,) = path.glob("*.mcap")
    data = mcap_file.read_bytes()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) // 2])
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(np.random.default_rng(0).bytes(4096))
    for bad in (truncated, garbage):
        with pytest.raises(BagError, match="cannot read bag") as error:
            read_displacement(bad)
        assert bad.name in str(error.value)
    with pytest.raises(BagError, match="no such bag"):
        read_displacement(tmp_path / "nothing_here")


def test_truth_requires_aligned_topics(tmp_path):
    stamps, xyz = displacement(10)
    path = tmp_path / "truth"
    write_bag(
        path,
        [
            TopicSeries("/truth/velocity", "Vector3Stamped", stamps, xyz),
            TopicSeries("/truth/acceleration", "Vector3Stamped", stamps, 2 * xyz),
            TopicSeries("/truth/contact_force", "WrenchStamped", stamps[:-1], 3 * xyz[:-1]),
        ],
    )
    with pytest.raises(BagError, match="/truth/contact_force is missing or not on the stamps"):
        read_truth(path)
    plain = _bag_with(tmp_path, stamps, xyz)
    assert read_truth(plain) is None


def test_failed_write_leaves_nothing_and_refuses_overwrite(tmp_path, monkeypatch):
    stamps, xyz = displacement(30)
    target = tmp_path / "bag"
    with pytest.raises(ValueError, match="30 stamps but values of shape"):
        write_bag(target, [TopicSeries("/x", "PointStamped", stamps, xyz[:-1])])
    assert list(tmp_path.iterdir()) == []

    calls = {"n": 0}
    original = bags.make_message

    def fail_midway(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 15:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(bags, "make_message", fail_midway)
    with pytest.raises(KeyboardInterrupt):
        write_bag(target, [TopicSeries("/x", "PointStamped", stamps, xyz)])
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(bags, "make_message", original)

    write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)])
    with pytest.raises(FileExistsError):
        write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, xyz)])
    write_bag(target, [TopicSeries("/amb/displacement", "PointStamped", stamps, 2 * xyz)], overwrite=True)
    np.testing.assert_array_equal(read_displacement(target).xyz, 2 * xyz)
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]
