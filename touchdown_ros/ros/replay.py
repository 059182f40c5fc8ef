"""`touchdown replay`: publish a bag's displacements in (scaled) real time, optionally record the estimates.

    touchdown replay BAG [--rate R | --fast] [--batch N] [--record OUT] [--config RIG.yaml] [--ros-args ...]

Publishes the bag's displacement topic (geometry_msgs/PointStamped, the bag's own
stamps) on the live topic, paced by the stamps: real time, `--rate` times faster,
or `--fast` (as fast as possible: a best-effort subscriber that cannot keep up then
loses samples, which the node counts as gaps). `--batch N` publishes PointCloud2
batches of N samples on the node's batch topic instead. `--record OUT` subscribes
to the node's /touchdown/* topics, waits until the estimate of the last replayed
stamp has arrived on every topic (or `--timeout`), and writes them to a new
rosbag2 MCAP bag with `io.bags.write_bag`: the same topics and types as
`touchdown estimate` writes offline (the ring's speed with `contact.friction: spinning_ring`,
in the rig YAML or in the coefficient file its `node.coefficients` names, as the node reads them).
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

import rclpy
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from touchdown_ros.io import cdr
from touchdown_ros.io.config import Config, ConfigError, load_config
from touchdown_ros.io.estimate_topics import published_topics
from touchdown_ros.ros import messages
from touchdown_ros.ros.node_model import load_node_model
from touchdown_ros.ros.runtime import make_executor, qos, spin

EXIT_OK, EXIT_USAGE, EXIT_BAD_INPUT, EXIT_INCOMPLETE = 0, 2, 3, 4


@dataclass
class _Track:
    """Messages recorded on one topic."""

    topic: str
    msgtype: str
    stamps: list[int] = field(default_factory=list)
    values: list[tuple[float, ...]] = field(default_factory=list)
    frame_id: str = ""
    angular: bool = False  # the values of interest are the messages' angular part


class Recorder:
    """Raw subscriptions to the node's estimate topics under config's contact law (`published_topics`);
    decoded values kept in arrival order."""

    def __init__(self, node: Node, config: Config, reliability: str = "reliable", depth: int = 10000):
        self.tracks: dict[str, _Track] = {}
        self.subscriptions = []
        self.last_message = 0.0
        for estimate_topic in published_topics(config.law):
            topic, msgtype = getattr(config.topics, estimate_topic.name), estimate_topic.msgtype
            track = _Track(topic, msgtype, frame_id=config.topics.frame_id, angular=estimate_topic.angular)
            self.tracks[topic] = track
            on_message = self._callback(track, messages.float64_count(msgtype))
            self.subscriptions.append(node.create_subscription(messages.message_class(msgtype), topic, on_message,
                                                               qos(reliability, depth), raw=True))

    def _callback(self, track: _Track, count: int):
        def on_message(data: bytes) -> None:
            stamp, values = cdr.decode_one(data, count)
            track.stamps.append(stamp)
            track.values.append(values)
            self.last_message = time.monotonic()

        return on_message

    def connected(self) -> bool:
        return not self.unpublished()

    def unpublished(self) -> list[str]:
        """The recorded topics nobody publishes yet."""
        return [s.topic_name for s in self.subscriptions if s.get_publisher_count() == 0]

    def reached(self, stamp_ns: int) -> bool:
        """Every topic has a message stamped at or after stamp_ns."""
        return all(t.stamps and max(t.stamps[-8:]) >= stamp_ns for t in self.tracks.values())

    def counts(self) -> dict[str, int]:
        return {topic: len(track.stamps) for topic, track in self.tracks.items()}

    def series(self) -> list:
        """The recorded topics as `io.bags.TopicSeries` (sorted by stamp, repeated stamps once)."""
        from touchdown_ros.io.bags import TopicSeries

        out = []
        for track in self.tracks.values():
            stamps = np.asarray(track.stamps, dtype=np.int64)
            block = np.asarray(track.values, dtype=np.float64).reshape(
                len(stamps), messages.float64_count(track.msgtype)
            )
            stamps, first = np.unique(stamps, return_index=True)
            vector, covariance = cdr.vector_and_covariance(track.msgtype, block[first], track.angular)
            out.append(TopicSeries(track.topic, track.msgtype, stamps, vector, covariance, frame_id=track.frame_id,
                                   angular=track.angular))
        return out


def pace(offsets_s: np.ndarray, publish_until, stop: threading.Event | None = None) -> float:
    """Call publish_until(j) whenever publications before j are due (offsets s from now); returns the duration."""
    start = time.perf_counter()
    done, n = 0, len(offsets_s)
    while done < n and not (stop and stop.is_set()):
        now = time.perf_counter() - start
        due = int(np.searchsorted(offsets_s, now, side="right"))
        if due > done:
            publish_until(due)
            done = due
        else:
            time.sleep(min(max(offsets_s[done] - now, 0.0), 0.001))
    return time.perf_counter() - start


def make_source(
    node: Node,
    config: Config,
    stamps_ns: np.ndarray,
    xyz: np.ndarray,
    frame_id: str,
    rate: float | None,
    batch: int = 0,
    reliability: str = "reliable",
    depth: int = 10000,
):
    """(publisher, due offsets s (k,), publish_until(j)) for k publications: samples, or batches of `batch`.

    Offsets are the stamps relative to the first, divided by rate (all 0 when rate is
    None: as fast as possible); a batch is due with its last sample.
    """
    stamps_ns = np.asarray(stamps_ns, np.int64)
    offsets = (stamps_ns - stamps_ns[0]) / 1e9 / rate if rate else np.zeros(len(stamps_ns))
    if batch:
        publisher = node.create_publisher(PointCloud2, config.node.batch_topic, qos(reliability, depth))
        starts = np.arange(0, len(stamps_ns), batch)
        ends = np.minimum(starts + batch, len(stamps_ns))
        units = [messages.batch_cloud(int(stamps_ns[a]), frame_id, stamps_ns[a:b], xyz[a:b])
                 for a, b in zip(starts, ends)]
        offsets = offsets[ends - 1]
    else:
        publisher = node.create_publisher(PointStamped, config.topics.displacement, qos(reliability, depth))
        units = messages.encode_stamped("PointStamped", stamps_ns, xyz, None, frame_id)
    sent = [0]

    def publish_until(due: int) -> None:
        publish = publisher.publish
        for unit in units[sent[0] : due]:
            publish(unit)
        sent[0] = due

    return publisher, offsets, publish_until


def wait_until(condition, timeout: float, interval: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(interval)
    return condition()


def replay(
    config: Config,
    stamps_ns: np.ndarray,
    xyz: np.ndarray,
    frame_id: str,
    *,
    rate: float | None = 1.0,
    batch: int = 0,
    record: bool = False,
    timeout: float = 10.0,
    discovery_timeout: float = 30.0,
    reliability: str = "reliable",
    log=print,
) -> Recorder | None:
    """Publish samples to a running node (rclpy must be initialised); return the recorder if record.

    Waits up to discovery_timeout s for the node to subscribe (and, when recording, to
    publish), then paces the samples, then waits up to timeout s for the estimate of
    the last sample on every estimate topic.
    """
    node = rclpy.create_node("touchdown_replay")
    executor = make_executor("events")
    executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=spin, args=(executor, None, lambda: not stop.is_set()), daemon=True)
    recorder = Recorder(node, config) if record else None
    publisher, offsets, publish_until = make_source(node, config, stamps_ns, xyz, frame_id, rate, batch, reliability)
    spinner.start()
    try:
        if not wait_until(lambda: publisher.get_subscription_count() > 0, discovery_timeout):
            raise TimeoutError(f"no subscriber on {publisher.topic_name} after {discovery_timeout:.0f} s")
        if recorder and not wait_until(recorder.connected, discovery_timeout):
            raise TimeoutError(f"no publisher on {', '.join(recorder.unpublished())} after {discovery_timeout:.0f} s "
                               "(is the node running with this rig's topics and contact.friction?)")
        time.sleep(0.5)  # let the other side finish matching before the first sample
        seconds = pace(offsets, publish_until)
        log(f"published {len(stamps_ns)} samples in {seconds:.2f} s ({len(stamps_ns) / max(seconds, 1e-9):.0f}/s)")
        if recorder:
            last = int(stamps_ns[-1]) - int(config.node.grid_tolerance * config.sample_period * 1e9)
            if not wait_until(lambda: recorder.reached(last), timeout):
                log(f"warning: estimates of the last sample not received within {timeout:.0f} s: "
                    f"{recorder.counts()}")
            else:
                time.sleep(0.05)
        return recorder
    finally:
        stop.set()
        spinner.join(timeout=2.0)
        executor.shutdown()
        node.destroy_node()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="touchdown replay",
        description="Publish a bag's displacement topic in (scaled) real time; optionally record the node's estimates.",
    )
    parser.add_argument("bag", type=Path, help="rosbag2 directory or .mcap file")
    parser.add_argument("--config", type=Path, help="rig YAML (topics, sample period; default: the reference rig)")
    parser.add_argument("--topic", help="displacement topic in the bag (default: topics.displacement)")
    speed = parser.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=float, default=1.0, help="speed factor over real time (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as possible (may overrun a best-effort subscriber)")
    parser.add_argument("--batch", type=int, default=0, metavar="N",
                        help="publish PointCloud2 batches of N samples on node.batch_topic")
    parser.add_argument("--record", type=Path, metavar="OUT", help="record the /touchdown/* estimates to this MCAP bag")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUT")
    parser.add_argument("--timeout", type=float, default=10.0, help="s to wait for the last estimate (default 10)")
    parser.add_argument("--discovery-timeout", type=float, default=30.0, help="s to wait for the node (default 30)")
    parser.add_argument("--reliability", choices=("reliable", "best_effort"), default="reliable",
                        help="QoS of the published samples (default reliable; matches any subscriber)")
    return parser


def _ignore(message: str) -> None:
    """Drop a message the node reports itself (a refused coefficient file)."""


def replay_main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `touchdown replay` (and `python -m touchdown_ros.ros.replay`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    own = rclpy.utilities.remove_ros_args([sys.argv[0], *argv])[1:]
    args = build_parser().parse_args(own)
    if args.rate is not None and args.rate <= 0:
        print("touchdown replay: error: --rate must be > 0", file=sys.stderr)
        return EXIT_USAGE
    if args.record and args.record.exists() and not args.overwrite:
        print(f"touchdown replay: error: {args.record} exists; pass --overwrite to replace it", file=sys.stderr)
        return EXIT_BAD_INPUT
    from touchdown_ros.io.bags import BagError, displacement_problems, read_displacement, write_bag

    try:
        config = load_config(args.config)
        series = read_displacement(args.bag, args.topic or config.topics.displacement, validate=False)
    except (ConfigError, BagError, FileNotFoundError, ValueError) as error:
        print(f"touchdown replay: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.record:  # the contact law the node runs (its coefficient file's) says which topics it publishes
        config = load_node_model(config, _ignore, _ignore).config
    for problem in displacement_problems(series):  # replayed as recorded: the node counts and reports them
        print(f"touchdown replay: warning: {args.bag}: {problem}", file=sys.stderr)
    if len(series.stamps_ns) == 0:
        print(f"touchdown replay: error: {args.bag} has no samples on {series.topic}", file=sys.stderr)
        return EXIT_BAD_INPUT
    rclpy.init(args=[sys.argv[0], *argv])
    try:
        recorder = replay(
            config, series.stamps_ns, series.xyz, series.frame_id or config.topics.frame_id,
            rate=None if args.fast else args.rate, batch=args.batch, record=args.record is not None,
            timeout=args.timeout, discovery_timeout=args.discovery_timeout, reliability=args.reliability,
        )
    except TimeoutError as error:
        print(f"touchdown replay: error: {error}", file=sys.stderr)
        return EXIT_INCOMPLETE
    except KeyboardInterrupt:
        return 130
    finally:
        if rclpy.ok():
            rclpy.shutdown()
    if recorder is None:
        return EXIT_OK
    last = int(series.stamps_ns[-1]) - int(config.node.grid_tolerance * config.sample_period * 1e9)
    silent = [topic for topic, count in recorder.counts().items() if count == 0]
    if silent:
        print(f"touchdown replay: error: no estimates received on {', '.join(silent)}; {args.record} not written",
              file=sys.stderr)
        return EXIT_INCOMPLETE
    write_bag(args.record, recorder.series(), overwrite=args.overwrite)
    print(f"recorded {recorder.counts()} to {args.record}")
    return EXIT_OK if recorder.reached(last) else EXIT_INCOMPLETE


if __name__ == "__main__":
    sys.exit(replay_main())
