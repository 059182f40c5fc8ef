"""The live node and the replayer over real DDS: separate processes on loopback, one ROS_DOMAIN_ID per test.

Nothing of rclpy is mocked. The node runs as `python -m touchdown_ros.ros.node`,
the replayer as `python -m touchdown_ros.ros.replay`; the test process joins the
same domain with its own rclpy context to publish crafted input and to read
/diagnostics. Every wait is bounded.
"""
from __future__ import annotations

import json

import os
import re
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2

from touchdown_ros.cli import main as touchdown
from touchdown_ros.core.estimate import force_std
from touchdown_ros.core.types import VELOCITY, Coefficients
from touchdown_ros.io import cdr
from touchdown_ros.io.bags import TopicSeries, list_topics, read_vector_topic, write_bag
from touchdown_ros.io.coefficients import TrainingRecord, load_coefficients, save_coefficients
from touchdown_ros.io.config import load_config, reference_rig_path
from touchdown_ros.workflows.offline import FILTERED, estimate_bag, estimate_topics, estimator_for
from touchdown_ros.ros import messages
from touchdown_ros.ros.health import LatencyHistogram
from touchdown_ros.ros.replay import pace

from test_streaming import model_drop_record

CONFIG = load_config()
RIG = str(reference_rig_path())
PERIOD_NS = int(round(CONFIG.sample_period * 1e9))
NODE_START_TIMEOUT = 150.0  # s: imports + EKF compilation (cached by JAX after the first run)
#: Fewer compiled chunk lengths than the default: the same code path, less compilation in tests.
FAST_NODE = ["-p", "node.chunk_sizes:=[16,64,256]", "-p", "node.diagnostics_period:=0.5"]
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
#: The DDS tests run one after another on one test worker (their domain ids come from its pid).
pytestmark = pytest.mark.xdist_group("dds")

INPUT = "touchdown_estimator: input"
MODEL = "touchdown_estimator: model"
CONTACT = "touchdown_estimator: contact"
LAST = "touchdown_estimator: last touchdown"
FILTER = "touchdown_estimator: filter"


def domain(offset: int) -> int:
    """A ROS_DOMAIN_ID for this test run (10..109), different per test (offset 0..4)."""
    return 10 + (os.getpid() % 20) * 5 + offset


def ros_env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


class NodeProcess:
    """`touchdown_estimator` in its own process; stopped with SIGINT (then SIGKILL) on exit."""

    def __init__(self, tmp_path: Path, domain_id: int, args: list[str]):
        self.log_path = tmp_path / f"node_{domain_id}.log"
        self.command = [sys.executable, "-m", "touchdown_ros.ros.node", *args]
        self.env = ros_env(domain_id)

    def __enter__(self) -> "NodeProcess":
        self.log_file = open(self.log_path, "w")
        self.process = subprocess.Popen(self.command, env=self.env, stdout=self.log_file, stderr=subprocess.STDOUT)
        return self

    def __exit__(self, *exc) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        self.log_file.close()

    def log(self) -> str:
        self.log_file.flush()
        return self.log_path.read_text()

    def alive(self) -> bool:
        return self.process.poll() is None


class Peer:
    """The test's own participant: crafted input publishers and a /diagnostics listener."""

    def __init__(self, domain_id: int):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("test_peer", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.latest: dict[str, dict] = {}  # status name -> {"level", "message", "values"}
        self.history: list[dict] = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 100)
        reliable = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
        self.points = self.node.create_publisher(PointStamped, CONFIG.topics.displacement, reliable)
        self.batches = self.node.create_publisher(PointCloud2, CONFIG.node.batch_topic, reliable)

    def _on_diagnostics(self, message: DiagnosticArray) -> None:
        for status in message.status:
            entry = {"level": status.level, "message": status.message, "values": messages.status_values(status)}
            self.latest[status.name] = entry
            self.history.append({"name": status.name, **entry})

    def wait_for(self, predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
            if predicate():
                return True
        return predicate()

    def value(self, status: str, key: str) -> str | None:
        return self.latest.get(status, {}).get("values", {}).get(key)

    def count(self, key: str) -> int:
        value = self.value(INPUT, key)
        return -1 if value is None else int(value)

    def wait_ready(self, node: NodeProcess) -> None:
        ready = self.wait_for(lambda: MODEL in self.latest and self.points.get_subscription_count() > 0
                              or not node.alive(), NODE_START_TIMEOUT)
        assert ready and node.alive(), "node did not come up:\n" + node.log()
        self.wait_for(lambda: False, 0.5)  # let matching settle before the first sample

    def publish_points(self, stamps_ns: np.ndarray, xyz: np.ndarray, spacing: float | None = None) -> None:
        """Raw PointStamped samples, paced in real time by their stamps, or `spacing` s apart."""
        blobs = messages.encode_stamped("PointStamped", stamps_ns, xyz, None, "amb_sensor")
        sent = [0]

        def until(due: int) -> None:
            for blob in blobs[sent[0] : due]:
                self.points.publish(blob)
            sent[0] = due

        offsets = (np.asarray(stamps_ns) - stamps_ns[0]) / 1e9 if spacing is None else spacing * np.arange(len(blobs))
        pace(offsets, until)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)

    def __enter__(self) -> "Peer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@pytest.fixture(autouse=True)
def loopback(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)


def drop_bag(path: Path) -> tuple[Path, str]:
    """A drop-test bag: the simulator's experiment 11 when touchdown_ros.sim is there, else the model's own drop."""
    try:
        from conftest import write_simulated_bag
    except ImportError:
        stamps, measured = model_drop_record()
        write_bag(path, [TopicSeries(CONFIG.topics.displacement, "PointStamped", stamps, measured,
                                     frame_id=CONFIG.topics.frame_id)])
        return path, "core model"
    write_simulated_bag(path, 11, seed=11, config=CONFIG)
    return path, "simulator experiment 11"


def assert_close(actual: np.ndarray, expected: np.ndarray, what: str, rtol: float = 1e-9) -> None:
    assert actual.shape == expected.shape, what
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * np.max(np.abs(expected)), err_msg=what)


# ---------------------------------------------------------------------------------------------- messages (no DDS)
@pytest.mark.parametrize("frame_id", ["", "a", "amb1", "amb_sensor", "frame_of_8"])  # amb1: 4- and 8-alignment differ
def test_raw_messages_match_rclpy_serialisation(frame_id):
    from geometry_msgs.msg import AccelWithCovarianceStamped, TwistWithCovarianceStamped, Vector3Stamped, WrenchStamped

    rng = np.random.default_rng(0)
    stamps = np.array([1_700_000_000_123_456_789, 42], np.int64)
    for name, cls in [("PointStamped", PointStamped), ("TwistWithCovarianceStamped", TwistWithCovarianceStamped),
                      ("AccelWithCovarianceStamped", AccelWithCovarianceStamped), ("WrenchStamped", WrenchStamped),
                      ("Vector3Stamped", Vector3Stamped)]:
        count = messages.float64_count(name)
        values = rng.standard_normal((2, count))
        blobs = cdr.serialized(cdr.encode(stamps, values, frame_id))
        for blob, stamp, row in zip(blobs, stamps, values):
            message = deserialize_message(blob, cls)
            assert message.header.frame_id == frame_id
            assert messages.stamp_ns_of(message.header.stamp) == stamp
            again = serialize_message(message)
            decoded_stamp, decoded = cdr.decode_one(again, count)
            assert decoded_stamp == stamp and np.array_equal(decoded, row), name
    point = PointStamped()
    point.header.frame_id, point.header.stamp.sec, point.point.z = frame_id, 3, -2.5e-4
    assert messages.decode_point(serialize_message(point)) == (3_000_000_000, 0.0, 0.0, -2.5e-4)
    with pytest.raises(messages.MessageError):
        messages.decode_point(b"\x00\x01\x00\x00\x01")


def test_an_angular_rate_fills_twist_angular_and_its_covariance_entry_35():
    """A rate about z published as TwistWithCovarianceStamped (the ring's speed): rclpy reads it in
    twist.angular.z and its variance in covariance[35] (row-major 6x6), every other value zero."""
    from geometry_msgs.msg import TwistWithCovarianceStamped

    stamps = np.array([42, 1_700_000_000_123_456_789], np.int64)
    rates = np.array([[0.0, 0.0, 523.5], [0.0, 0.0, -1.25]])  # rad/s
    covariance = np.zeros((2, 3, 3))
    covariance[:, 2, 2] = [0.01, 4.0]
    blobs = messages.encode_stamped("TwistWithCovarianceStamped", stamps, rates, covariance, "amb_sensor",
                                    angular=True)
    for blob, stamp, rate, variance in zip(blobs, stamps, rates[:, 2], covariance[:, 2, 2]):
        message = deserialize_message(blob, TwistWithCovarianceStamped)
        assert messages.stamp_ns_of(message.header.stamp) == stamp and message.header.frame_id == "amb_sensor"
        twist = message.twist.twist
        assert (twist.angular.x, twist.angular.y, twist.angular.z) == (0.0, 0.0, rate)
        assert (twist.linear.x, twist.linear.y, twist.linear.z) == (0.0, 0.0, 0.0)
        expected = np.zeros(36)
        expected[35] = variance
        np.testing.assert_array_equal(np.asarray(message.twist.covariance), expected)


def test_points_decoded_at_once_equal_one_by_one():
    """decode_points: the usual stream at once, anything else (another frame_id, truncated) one by one, in order."""
    rng = np.random.default_rng(3)

    def serialized(frame_id: str, sec: int, nanosec: int, xyz) -> bytes:
        point = PointStamped()
        point.header.frame_id, point.header.stamp.sec, point.header.stamp.nanosec = frame_id, sec, nanosec
        point.point.x, point.point.y, point.point.z = map(float, xyz)
        return serialize_message(point)

    stream = [serialized("amb", 1_700_000_000 + k, 999_999_999 - k, rng.standard_normal(3) * 1e-4) for k in range(50)]
    stamps, xyz, errors = messages.decode_points(stream)
    expected = [messages.decode_point(data) for data in stream]
    assert errors == [] and stamps.dtype == np.int64
    assert stamps.tolist() == [e[0] for e in expected] and xyz.tolist() == [list(e[1:]) for e in expected]

    mixed = [stream[0], serialized("rotor_sensor_frame", 5, 6, (1e-5, 2e-5, 3e-5)), stream[1][:20], stream[2]]
    stamps, xyz, errors = messages.decode_points(mixed)
    assert stamps.tolist() == [expected[0][0], 5_000_000_006, expected[2][0]]
    assert xyz[1].tolist() == [1e-5, 2e-5, 3e-5] and len(errors) == 1 and "too short" in str(errors[0])
    big_endian = b"\x00\x00\x00\x00" + struct.pack(">iII", 7, 8, 4) + b"amb\x00" + struct.pack(">3d", 1, 2, 3)
    assert len(big_endian) == len(stream[0]) and messages.decode_point(big_endian) == (7_000_000_008, 1.0, 2.0, 3.0)
    stamps, xyz, errors = messages.decode_points([stream[0], big_endian])  # one length, not all little-endian
    assert stamps.tolist() == [expected[0][0], 7_000_000_008] and xyz[1].tolist() == [1.0, 2.0, 3.0] and not errors
    assert messages.decode_points([])[0].shape == (0,)


def test_latency_histogram_percentiles_over_several_adds():
    histogram = LatencyHistogram()
    assert np.isnan(histogram.percentile(50))
    latencies_ns = np.arange(1, 1001) * 10_000  # 0.01 .. 10 ms
    for part in np.split(latencies_ns, [3, 500, 501]):  # five values per bin: repeats within a call all count
        histogram.add(part)
    histogram.add(np.array([5 * 10**9, 7 * 10**9]))  # beyond 1 s: the last bin
    assert int(histogram.counts.sum()) == 1002
    # the 50th percentile of the 1002 values is the 501st: 5.01 ms, in the bin [5.00, 5.05) ms
    assert histogram.percentile(50) == pytest.approx(5.05)
    assert histogram.percentile(99.9) == pytest.approx(1000.05)


def test_batch_cloud_round_trip():
    stamps = 1_700_000_000_000_000_000 + np.arange(100, dtype=np.int64) * PERIOD_NS
    xyz = np.random.default_rng(1).standard_normal((100, 3)) * 1e-4
    cloud = deserialize_message(serialize_message(messages.batch_cloud(int(stamps[0]), "amb", stamps, xyz)),
                                PointCloud2)
    got_stamps, got_xyz = messages.batch_samples(cloud)
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_array_equal(got_xyz, xyz)
    cloud.fields = cloud.fields[:3]
    with pytest.raises(messages.MessageError, match="lacks field"):
        messages.batch_samples(cloud)


# ---------------------------------------------------------------------------------------------- over DDS
def test_replayed_drop_through_the_node_equals_the_offline_estimate(tmp_path):
    """Replay at real time (10 kHz) into the node with its default best-effort input: same numbers, none lost."""
    bag, source = drop_bag(tmp_path / "drop")
    rng = np.random.default_rng(0)
    zeros = Coefficients.zeros(CONFIG.kernel)
    coeffs = Coefficients(0.2 * rng.standard_normal(zeros.alpha_R.shape),
                          0.2 * rng.standard_normal(zeros.alpha_Z.shape))
    notes = ["axial support: yields above 36 kN (+-3 %) ...", "friction: mu 0.0004 and k_ZR 0.0012, ..."]
    coefficient_file = save_coefficients(tmp_path / "coefficients.yaml", coeffs, CONFIG,
                                         TrainingRecord(extra={"calibration": {"notes": notes}}))
    fitted = load_coefficients(coefficient_file, CONFIG).config(CONFIG)  # as the node reads it: Q fitted, adapted
    expected = estimate_bag(fitted, bag, estimator_for(fitted, coeffs, answer=FILTERED), answer=FILTERED)
    n_samples = int(expected.estimate.onset_index + len(expected.estimate.stamps_ns))
    recorded, recorded_batched = tmp_path / "live", tmp_path / "live_batched"
    d = domain(0)
    with Peer(d) as peer, NodeProcess(tmp_path, d, ["--config", RIG, "--ros-args", "-p",
                                                    f"node.coefficients:={coefficient_file}", *FAST_NODE]) as node:
        peer.wait_ready(node)
        assert peer.latest[MODEL]["level"] == OK
        assert str(coefficient_file) in peer.latest[MODEL]["message"]
        assert peer.value(MODEL, "calibration_notes") == " | ".join(notes)  # what training left open
        replay = subprocess.run(
            [sys.executable, "-m", "touchdown_ros.ros.replay", str(bag), "--record", str(recorded), "--timeout", "30"],
            env=ros_env(d), capture_output=True, text=True, timeout=240,
        )
        assert replay.returncode == 0, f"{replay.stdout}\n{replay.stderr}\nnode:\n{node.log()}"
        assert peer.wait_for(lambda: peer.count("received") == n_samples, 20), (peer.latest.get(INPUT), node.log())
        for key in ("rejected", "gaps", "missing_samples", "malformed_messages"):
            assert peer.count(key) == 0, (key, peer.latest[INPUT])
        assert peer.value(CONTACT, "drops") == "1"

        # Again, as PointCloud2 batches at twice real time: the stamps jump back to the bag's start,
        # the node closes the touchdown (clock jump), starts over and gives the same estimates.
        again = subprocess.run(
            [sys.executable, "-m", "touchdown_ros.ros.replay", str(bag), "--record", str(recorded_batched),
             "--batch", "100", "--rate", "2", "--timeout", "30"],
            env=ros_env(d), capture_output=True, text=True, timeout=240,
        )
        assert again.returncode == 0, f"{again.stdout}\n{again.stderr}\nnode:\n{node.log()}"
        assert peer.wait_for(lambda: peer.count("received") == 2 * n_samples, 20), peer.latest.get(INPUT)
        assert peer.count("clock_jump_backward") == 1 and peer.count("batch_messages") == -(-n_samples // 100)
        assert peer.value(LAST, "end_reason") == "clock_jump" and peer.value(CONTACT, "drops") == "2"
        # the first touchdown's summary: the live filter's factor on Q as the offline filtered answer's (6 digits)
        factor = np.asarray(expected.estimate.process_scale)
        assert float(peer.value(LAST, "process_noise_scale_max")) == pytest.approx(factor.max(), rel=1e-5)
        assert float(peer.value(LAST, "process_noise_scale_mean")) == pytest.approx(factor.mean(), rel=1e-5)
        assert peer.count("gaps") == 0 and peer.count("rejected") == 0
        # the ring's speed topic only where the friction model spins the ring (the paper's friction has none)
        assert peer.node.count_publishers(CONFIG.topics.velocity) == 1
        assert peer.node.count_publishers(CONFIG.topics.ring_speed) == int(CONFIG.law.spins_ring)
        assert node.alive()

    for bag_out in (recorded, recorded_batched):
        assert_recorded_estimates(bag_out, expected.estimate, source)

    # The bag `touchdown estimate --filtered` writes holds what the node published, the force's std included.
    offline = tmp_path / "offline"
    assert touchdown(["estimate", str(bag), "--coeffs", str(coefficient_file), "--filtered", "--no-figures",
                      "-o", str(offline)]) == 0
    for series in estimate_topics(expected.estimate, CONFIG, FILTERED):
        written = read_vector_topic(offline / "drop_estimate", series.topic)
        live = read_vector_topic(recorded, series.topic)
        assert written.msgtype == live.msgtype, series.topic
        np.testing.assert_array_equal(live.stamps_ns, written.stamps_ns, err_msg=series.topic)
        assert_close(live.values, written.values, f"{series.topic}: node vs touchdown estimate --filtered")
    std = read_vector_topic(recorded, CONFIG.topics.contact_force_std)
    assert std.msgtype == "geometry_msgs/msg/Vector3Stamped" and std.values.max() > 0.0
    # its summary gives the factor the adaptive Q took (the coefficient file's Q is fitted: `Config.live_adaptation`)
    (summary,) = json.loads((offline / "summary.json").read_text())["bags"].values()
    assert summary["process_scale_max"] == pytest.approx(float(factor.max()), rel=1e-12) and factor.max() > 1.0
    assert f"adapted: mean x{factor.mean():.2g}, max x{factor.max():.3g}" in (offline / "summary.md").read_text()


def fifo_allowed() -> bool:
    """Whether a process here may switch itself to SCHED_FIFO (root or CAP_SYS_NICE / an rtprio limit)."""
    probe = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


def assert_recorded_estimates(bag: Path, estimate, source: str, config=CONFIG) -> None:
    """The /touchdown/* topics recorded in `bag` are those of config's friction model and equal the offline
    filtered estimate (stamps exactly, values to 1e-9)."""
    topics = estimate_topics(estimate, config, FILTERED)
    names = [series.topic for series in topics]
    assert config.topics.contact_force_std in names
    assert (config.topics.ring_speed in names) == (config.law.friction == "spinning_ring")
    assert sorted(list_topics(bag)) == sorted(names)
    for series in topics:
        got = read_vector_topic(bag, series.topic, angular=series.angular)
        assert got is not None and got.msgtype.endswith(series.msgtype), series.topic
        np.testing.assert_array_equal(got.stamps_ns, series.stamps_ns, err_msg=f"{series.topic} ({source})")
        assert_close(got.values, np.asarray(series.values), series.topic)
        if series.covariance is not None:
            assert_close(got.covariance, np.asarray(series.covariance), series.topic + " covariance")


def test_with_a_spinning_ring_the_node_publishes_the_rings_speed(tmp_path):
    """contact.friction: spinning_ring in the rig YAML of the node and the replayer: the node advertises
    /touchdown/ring_speed (TwistWithCovarianceStamped) and the recording holds it with the other topics, equal
    to `touchdown estimate --filtered`'s ring speed and variance; the batched output (`node.output_mode: both`)
    carries it too (`omega_ring`, `std_omega_ring`)."""
    rig, named = re.subn(r"(?m)^(\s+friction: )\w+ ", r"\1spinning_ring ", Path(RIG).read_text())
    assert named == 1
    ring_rig = tmp_path / "ring_rig.yaml"
    ring_rig.write_text(rig)
    config = load_config(ring_rig)
    assert config.law.friction == "spinning_ring" and config.topics == CONFIG.topics
    bag, source = drop_bag(tmp_path / "drop")
    expected = estimate_bag(config, bag, estimator_for(config, answer=FILTERED), answer=FILTERED).estimate
    recorded = tmp_path / "live"
    clouds: list[PointCloud2] = []
    d = domain(2)
    args = ["--config", str(ring_rig), "--ros-args", "-p", "node.output_mode:=both", *FAST_NODE]
    with Peer(d) as peer, NodeProcess(tmp_path, d, args) as node:
        peer.node.create_subscription(PointCloud2, config.node.batch_output_topic, clouds.append,
                                      QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE))
        peer.wait_ready(node)
        assert peer.wait_for(lambda: peer.node.count_publishers(config.topics.ring_speed) == 1, 5)
        ring_types = dict(peer.node.get_topic_names_and_types())[config.topics.ring_speed]
        assert ring_types == ["geometry_msgs/msg/TwistWithCovarianceStamped"]
        replay = subprocess.run(
            [sys.executable, "-m", "touchdown_ros.ros.replay", str(bag), "--config", str(ring_rig),
             "--record", str(recorded), "--timeout", "30"],
            env=ros_env(d), capture_output=True, text=True, timeout=240,
        )
        assert replay.returncode == 0, f"{replay.stdout}\n{replay.stderr}\nnode:\n{node.log()}"
        assert node.alive()
        assert peer.wait_for(lambda: sum(c.width for c in clouds) == len(expected.stamps_ns), 20), node.log()
    assert_recorded_estimates(recorded, expected, source, config)
    ring = read_vector_topic(recorded, config.topics.ring_speed, angular=True)
    assert abs(ring.values[-1, 2] - config.rig.speed) < 0.01 * config.rig.speed  # spun up to the rotor's speed
    batched = np.concatenate([messages.cloud_columns(c, messages.RING_OUTPUT_FIELDS) for c in clouds])
    assert_close(batched, np.column_stack([expected.filtered.ring_speed, expected.filtered.ring_speed_std]),
                 "omega_ring/std_omega_ring")


@pytest.mark.parametrize("receive,output_mode", [("callback", "per_sample"), ("inline", "per_sample"),
                                                 ("drain", "batch")])
def test_every_receive_mode_and_the_batched_output_give_the_offline_estimate(tmp_path, receive, output_mode):
    """The other `node.receive` modes, and the batched output (one PointCloud2 per EKF run) with drain."""
    bag, source = drop_bag(tmp_path / "drop")
    expected = estimate_bag(CONFIG, bag, estimator_for(CONFIG, Coefficients.zeros(CONFIG.kernel), answer=FILTERED),
                            answer=FILTERED).estimate
    recorded = tmp_path / "live"
    clouds: list[PointCloud2] = []
    d = domain(4)
    args = ["--ros-args", "-p", f"node.receive:={receive}", "-p", f"node.output_mode:={output_mode}", *FAST_NODE]
    realtime = receive == "drain"  # and SCHED_FIFO where this machine allows it
    if realtime:
        args += ["-p", "node.realtime_priority:=5"]
    with Peer(d) as peer, NodeProcess(tmp_path, d, args) as node:
        peer.node.create_subscription(PointCloud2, CONFIG.node.batch_output_topic, clouds.append,
                                      QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE))
        peer.wait_ready(node)
        record = ["--record", str(recorded)] if output_mode == "per_sample" else []
        replay = subprocess.run(
            [sys.executable, "-m", "touchdown_ros.ros.replay", str(bag), *record, "--timeout", "30"],
            env=ros_env(d),
            capture_output=True,
            text=True,
            timeout=240,
        )
        assert replay.returncode == 0, f"{replay.stdout}\n{replay.stderr}\nnode:\n{node.log()}"
        n_samples = int(expected.onset_index + len(expected.stamps_ns))
        assert peer.wait_for(lambda: peer.count("received") == n_samples, 20), (peer.latest.get(INPUT), node.log())
        if output_mode == "batch":
            n_estimates = len(expected.stamps_ns)
            assert peer.wait_for(lambda: sum(c.width for c in clouds) == n_estimates, 20), node.log()
        assert "receive: " + receive in node.log()
        if realtime:
            scheduling = peer.value(FILTER, "scheduling")
            if fifo_allowed():
                assert scheduling == "SCHED_FIFO 5", scheduling
                threads = list(Path(f"/proc/{node.process.pid}/task").iterdir())
                assert len(threads) > 3 and all(os.sched_getscheduler(int(t.name)) == os.SCHED_FIFO for t in threads)
            else:
                assert scheduling.startswith("normal (SCHED_FIFO 5 refused"), scheduling
                assert "SCHED_FIFO refused" in node.log()
    if output_mode == "per_sample":
        assert_recorded_estimates(recorded, expected, source)
        return
    ring = CONFIG.law.spins_ring
    fields = messages.BATCH_OUTPUT_FIELDS + (messages.RING_OUTPUT_FIELDS if ring else ())
    columns = np.concatenate([messages.cloud_columns(c, fields) for c in clouds])
    stamps = np.concatenate(
        [
            messages.stamp_ns_of(c.header.stamp)
            + np.rint(messages.cloud_columns(c, ("t",))[:, 0] * 1e9).astype(np.int64)
            for c in clouds
        ]
    )
    np.testing.assert_array_equal(stamps, expected.stamps_ns)
    field = {name: i for i, name in enumerate(fields)}
    filtered = expected.filtered
    compared = ((("x", "y", "z"), np.asarray(filtered.state)[:, :3]),
                (("vx", "vy", "vz"), np.asarray(filtered.state)[:, VELOCITY]),
                (("ax", "ay", "az"), np.asarray(filtered.acceleration)),
                (("fx", "fy", "fz"), np.asarray(filtered.force_xyz)),
                (("fn", "ft"), np.column_stack([filtered.F_n, filtered.F_t])),
                (("nis",), np.asarray(expected.nis)[:, None]),
                (("var_vx", "var_vy", "var_vz"),
                 np.diagonal(np.asarray(filtered.state_cov)[:, VELOCITY, VELOCITY], axis1=1, axis2=2)),
                (("var_ax", "var_ay", "var_az"), np.diagonal(np.asarray(filtered.acceleration_cov), axis1=1, axis2=2)),
                (("radial_contact", "axial_contact"),
                 np.column_stack([filtered.radial_contact, filtered.axial_contact]).astype(float)),
                (("std_fx", "std_fy", "std_fz"), force_std(np.asarray(filtered.force_cov))))
    if ring:
        compared += ((messages.RING_OUTPUT_FIELDS, np.column_stack([filtered.ring_speed, filtered.ring_speed_std])),)
    # every field of the batched output but t (checked through the stamps above), each against the offline estimate
    assert {n for names, _ in compared for n in names} == set(fields) - {"t"}
    assert {f.name for f in clouds[0].fields} == set(fields)  # the ring's speed only where the friction spins it
    for names, values in compared:
        assert_close(columns[:, [field[n] for n in names]], values, "/".join(names))


def test_drop_relevitation_alarm_and_every_bad_input_counted(tmp_path):
    """Parameter-file form, missing coefficient file, crafted input through the real topics."""
    missing = tmp_path / "no_such_coefficients.yaml"
    args = ["--ros-args", "--params-file", RIG, "-p", f"node.coefficients:={missing}",
            "-p", "node.input_reliability:=reliable", "-p", "node.alarm_force:=1.0e+4", *FAST_NODE]
    d = domain(1)
    with Peer(d) as peer, NodeProcess(tmp_path, d, args) as node:
        peer.wait_ready(node)
        model = peer.latest[MODEL]
        assert model["level"] == ERROR and "not found" in model["message"] and "constant model" in model["message"]
        assert "not found" in node.log()

        # 1. Levitation, a drop, back to levitation: one touchdown with its summary and a force alarm.
        stamps, first = model_drop_record(seed=4, duration=0.05)
        ramp = np.linspace(first[-1], [0.0, 0.0, 0.0], 50)
        settle = CONFIG.noise_rms * np.random.default_rng(5).standard_normal((300, 3))
        xyz = np.concatenate([first, ramp, settle])
        stamps = stamps[0] + np.arange(len(xyz), dtype=np.int64) * PERIOD_NS
        peer.publish_points(stamps, xyz)
        assert peer.wait_for(lambda: LAST in peer.latest, 20), (peer.latest, node.log())
        summary = peer.latest[LAST]["values"]
        assert summary["end_reason"] == "relevitated" and int(summary["axial_impacts"]) >= 1
        assert float(summary["peak_axial_force_N"]) > 1.0e4
        assert any(h["name"] == CONTACT and h["level"] == ERROR and "alarm" in h["message"] for h in peer.history)
        assert peer.wait_for(lambda: peer.count("received") == len(xyz), 10)
        assert peer.value(CONTACT, "relevitations") == "1" and peer.value(CONTACT, "drops") == "1"
        assert peer.latest[INPUT]["level"] == OK

        # 2. Every kind of bad sample, continuing the same grid.
        k = [len(xyz)]
        last = [int(stamps[-1])]

        def good(n):
            out = []
            for _ in range(n):
                last[0] += PERIOD_NS
                out.append((last[0], [0.0, 0.0, 0.0]))
            return out

        bad = good(20)
        bad += [(last[0] + PERIOD_NS, [np.nan, 0.0, 0.0]), (last[0] + 2 * PERIOD_NS, [0.0, np.inf, 0.0])]
        last[0] += 2 * PERIOD_NS
        bad += good(1)
        bad += [(last[0], [0.0, 0.0, 0.0]), (last[0], [0.0, 0.0, 0.0])]  # 2 duplicates
        bad += [(last[0] - 5 * PERIOD_NS, [0.0, 0.0, 0.0])]  # out of order
        last[0] += 3 * PERIOD_NS  # a gap of 3 missing samples before the next one
        bad += good(1)
        bad += [(last[0] + PERIOD_NS, [CONFIG.node.sensor_range, 0.0, 0.0])]  # saturated
        bad += [(last[0] + 2 * PERIOD_NS, [0.0, 0.0, 0.25])]  # millimetres
        last[0] += 2 * PERIOD_NS
        bad += [(last[0] + PERIOD_NS + PERIOD_NS // 2, [0.0, 0.0, 0.0])]  # half a period off the grid
        bad += good(10)
        last[0] += 10 * 1_000_000_000  # the sensor clock jumps 10 s forward
        bad += good(60)
        last[0] -= 20 * 1_000_000_000  # and 20 s back
        bad += good(10)
        bad_stamps = np.array([s for s, _ in bad], np.int64)
        peer.publish_points(bad_stamps, np.array([v for _, v in bad]), spacing=0.001)
        peer.points.publish(b"\x00\x01\x00\x00\x07")  # a truncated message
        expected_received = k[0] + len(bad)
        assert peer.wait_for(lambda: peer.count("received") == expected_received, 10), peer.latest.get(INPUT)

        # 3. The batched input: one good batch continuing the grid, one without its z field.
        batch_stamps = last[0] + PERIOD_NS * np.arange(1, 6, dtype=np.int64)
        peer.batches.publish(messages.batch_cloud(int(batch_stamps[0]), "amb_sensor", batch_stamps, np.zeros((5, 3))))
        broken = messages.cloud(int(batch_stamps[-1]), "amb_sensor", ("t", "x", "y"), np.zeros((3, 3)))
        peer.batches.publish(broken)
        expected = {
            "received": expected_received + 5,
            "rejected.non_finite": 2, "rejected.duplicate": 2, "rejected.out_of_order": 1,
            "rejected.saturated": 1, "rejected.millimetre": 1, "rejected.off_grid": 1,
            "gaps": 1, "missing_samples": 3, "clock_jump_forward": 1, "clock_jump_backward": 1, "resyncs": 0,
            "malformed_messages": 2, "batch_messages": 2, "rejected": 8,
        }  # fmt: skip
        assert peer.wait_for(lambda: all(peer.count(key) == value for key, value in expected.items()), 15), (
            {key: (peer.count(key), value) for key, value in expected.items()}, node.log()
        )
        assert any(h["name"] == INPUT and h["level"] == WARN for h in peer.history)  # WARN when it happened
        log = node.log()
        assert "jumped forward" in log and "jumped back" in log and "message refused" in log
        assert node.alive()


def test_mismatched_coefficient_file_runs_the_constant_model_with_an_error(tmp_path):
    other_rig = load_config(overrides={"rig.mass": 300.0})
    zeros = Coefficients.zeros(other_rig.kernel)
    coefficient_file = save_coefficients(tmp_path / "other_rig.yaml", zeros, other_rig, TrainingRecord())
    d = domain(2)
    with Peer(d) as peer, NodeProcess(tmp_path, d, ["--coefficients", str(coefficient_file), "--ros-args",
                                                    "-p", "node.input_reliability:=reliable", *FAST_NODE]) as node:
        peer.wait_ready(node)
        model = peer.latest[MODEL]
        assert model["level"] == ERROR and "another rig" in model["message"] and "rig.mass" in model["message"]
        stamps = 1_700_000_000_000_000_000 + np.arange(100, dtype=np.int64) * PERIOD_NS
        peer.publish_points(stamps, np.zeros((100, 3)))
        assert peer.wait_for(lambda: peer.count("received") == 100 and peer.value(CONTACT, "phase") == "levitated",
                             10), peer.latest
        assert peer.latest[MODEL]["level"] == ERROR  # still reported, every period

        # A replay that gets no estimates back (the rotor never drops) writes no bag and says why.
        levitated, recorded = tmp_path / "levitated", tmp_path / "nothing_recorded"
        write_bag(levitated, [TopicSeries(CONFIG.topics.displacement, "PointStamped", stamps + 10**9,
                                          np.zeros((100, 3)), frame_id=CONFIG.topics.frame_id)])
        replay = subprocess.run(
            [sys.executable, "-m", "touchdown_ros.ros.replay", str(levitated), "--record", str(recorded),
             "--timeout", "2"], env=ros_env(d), capture_output=True, text=True, timeout=120,
        )
        assert replay.returncode == 4 and "no estimates received on /touchdown/" in replay.stderr, replay.stderr
        assert not recorded.exists()
        assert node.alive()


def test_invalid_rig_parameter_stops_the_node_with_a_clear_message(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "touchdown_ros.ros.node", "--ros-args", "-p", "rig.mass:=-1.0"],
        env=ros_env(domain(3)), capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2
    assert "rig.mass" in result.stderr and "must be > 0" in result.stderr


def test_input_policy_live_millimetres_gap_malformed_and_conditional_effect(tmp_path):
    """The input policy over DDS: a millimetre stream gives no drop; a 50 ms gap in a touchdown restarts the
    filter and the touchdown goes on to the re-levitation; one malformed message is this period's WARN only;
    a conditional effect left off by node.conditions is a WARN naming it."""
    with_effect = load_config(overrides={"effects.active": ["axial_load"], "effects.when.axial_load": "axial_load"})
    coefficient_file = save_coefficients(tmp_path / "c.yaml", Coefficients.zeros(with_effect.kernel), with_effect,
                                         TrainingRecord(), effects=with_effect.effects)
    args = ["--coefficients", str(coefficient_file), "--ros-args", "--params-file", RIG,
            "-p", "node.input_reliability:=reliable", *FAST_NODE]
    d = domain(4)
    with Peer(d) as peer, NodeProcess(tmp_path, d, args) as node:
        peer.wait_ready(node)
        model = peer.latest[MODEL]
        assert model["level"] == WARN and "axial_load" in model["message"] and "node.conditions" in model["message"]
        assert "axial_load" in model["values"]["effects_off"]

        # 1. A drop recorded in millimetres: refused, no drop, no force alarm.
        stamps, metres = model_drop_record(seed=6, duration=0.05)
        peer.publish_points(stamps, metres * 1000.0)
        assert peer.wait_for(lambda: peer.count("received") == len(stamps), 10), peer.latest.get(INPUT)
        peer.wait_for(lambda: False, 1.2)  # two more diagnostics periods
        assert peer.value(CONTACT, "drops") == "0" and peer.count("reference_refused") > 0
        assert peer.count("rejected.millimetre") > 0
        assert not any(h["name"] == CONTACT and h["level"] == ERROR for h in peer.history)

        # 2. One malformed message: WARN in its period, OK again in the next ones.
        peer.points.publish(b"\x00\x01\x00\x00\x07")
        assert peer.wait_for(lambda: peer.count("malformed_messages") == 1 and peer.latest[INPUT]["level"] == WARN, 5)
        assert peer.wait_for(lambda: peer.latest[INPUT]["level"] == OK, 5), peer.latest[INPUT]

        # 3. A drop with 50 ms without samples in the touchdown, then back to levitation.
        stamps, first = model_drop_record(seed=4, duration=0.1, t0_ns=int(stamps[-1]) + 10**9)
        ramp = np.linspace(first[-1], [0.0, 0.0, 0.0], 50)
        settle = CONFIG.noise_rms * np.random.default_rng(5).standard_normal((300, 3))
        xyz = np.concatenate([first, ramp, settle])
        stamps = stamps[0] + np.arange(len(xyz), dtype=np.int64) * PERIOD_NS
        keep = np.ones(len(xyz), bool)
        keep[500:1000] = False  # 50 ms in the touchdown (the drop starts at row 200)
        peer.publish_points(stamps[keep], xyz[keep])
        assert peer.wait_for(lambda: LAST in peer.latest, 20), (peer.latest, node.log())
        summary = peer.latest[LAST]["values"]
        assert summary["end_reason"] == "relevitated" and summary["filter_restarts"] == "1", summary
        assert float(summary["duration_s"]) > 0.1  # the whole touchdown, not cut at the gap
        assert peer.value(CONTACT, "drops") == "1" and peer.count("filter_restarts") == 1
        assert node.alive()
