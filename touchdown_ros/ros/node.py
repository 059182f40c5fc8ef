"""`touchdown_estimator`: the live node. Displacements in, touchdown estimates and diagnostics out.

A thin adapter around `core.streaming.StreamingEstimator`: it decodes samples from
`/amb/displacement` (geometry_msgs/PointStamped, one per sample) and from the
batched input (sensor_msgs/PointCloud2, fields t x y z), hands them to the
estimator in small blocks (every `node.flush_samples` samples, every
`node.flush_period` s, and at once when a sample reveals a drop), and publishes what
comes back on the `/touchdown/*` topics (the same topics and types as the offline
output bags) and `/diagnostics`.

With `node.receive: drain` (the default) a worker thread takes the per-sample
messages itself, all that are waiting at each wake-up, so the executor's per-message
dispatch is not paid at 10 kHz; the executor runs the timers and the batched input.

Run:  touchdown_estimator [--config RIG.yaml] [--coefficients FILE] [--ros-args --params-file RIG.yaml ...]

Parameters are the rig YAML's (ROS 2 parameter-file form); `--config` loads a rig
file as the base and `--ros-args` parameters override it. A coefficient file that is
missing or made for another rig does not stop the node: it logs the error, runs the
constant model and reports ERROR in the "model" diagnostic until restarted with a
good file (see docs/node.md). An invalid rig configuration does stop it (exit 2).
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import sys
import threading
import time
from pathlib import Path
from typing import Sequence

import numpy as np

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException
from rclpy.impl.logging_severity import LoggingSeverity
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from touchdown_ros.core.streaming import StreamEvent, StreamingEstimator, StreamOutput
from touchdown_ros.io.config import Config, ConfigError, config_from_parameters, load_config
from touchdown_ros.io.estimate_topics import published_topics
from touchdown_ros.ros import messages
from touchdown_ros.ros.inbox import Inbox
from touchdown_ros.ros.health import DiagnosticsState, LatencyHistogram, statuses
from touchdown_ros.ros.node_model import load_node_model
from touchdown_ros.ros.runtime import (
    DrainedSubscription,
    configure_jax,
    QuickLog,
    make_executor,
    qos,
    quiet_at_shutdown,
    raw_publish,
    set_realtime_scheduling,
    spin,
)

NODE_NAME = "touchdown_estimator"
#: Parameters every rclpy node has; they are not part of the rig configuration.
ROS_PARAMETERS = ("use_sim_time", "start_type_description_service")
#: Minimum time between two event-triggered diagnostics messages, s.
EVENT_DIAGNOSTICS_INTERVAL = 0.1
EXIT_CONFIG = 2
#: Most per-sample messages taken at one wake-up (`receive: drain`); a backlog is estimated in such blocks.
DRAIN_LIMIT = 512


class EstimatorNode(Node):
    """The live estimator node; see the module docstring."""

    def __init__(self, base_config: Path | None = None, coefficients: str | None = None, **kwargs):
        super().__init__(NODE_NAME, automatically_declare_parameters_from_overrides=True, **kwargs)
        self.config = self._configure(base_config, coefficients)
        node = self.config.node
        logger = self.get_logger()
        self.config, model, self.model_info = load_node_model(self.config, logger.error, logger.warning)
        if notes := self.model_info.values.get("calibration_notes"):
            logger.info(f"calibration notes of the coefficient file: {notes}")
        settings = self.config.stream_settings()
        self.estimator = StreamingEstimator(
            model, self.config.noise, settings, model_variance=self.config.model_variance(),
            adaptation=self.config.live_adaptation,
        )
        # Before warm_up and the worker start: threads created later inherit the policy.
        self.scheduling, refused = set_realtime_scheduling(node.realtime_priority)
        if refused:
            self.get_logger().warning(refused)
        started = time.monotonic()
        self.estimator.warm_up()
        self.get_logger().info(
            f"EKF compiled for chunks {list(settings.chunk_sizes)} in {time.monotonic() - started:.1f} s"
        )

        topics = self.config.topics
        self.frame_id = topics.frame_id
        out_qos = qos(node.output_reliability, node.output_depth)
        self.per_sample = node.output_mode in ("per_sample", "both")
        self.batched = node.output_mode in ("batch", "both")
        if self.per_sample:
            self._estimate_publishers = [
                (
                    self.create_publisher(messages.message_class(topic.msgtype), getattr(topics, topic.name), out_qos),
                    topic,
                )
                for topic in published_topics(self.config.law)  # the ring's speed only with a spinning ring
            ]
        if self.batched:
            self.pub_batch = self.create_publisher(PointCloud2, node.batch_output_topic, out_qos)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)

        self._inbox = Inbox()
        self._log = QuickLog(self.get_logger())
        self._lock = threading.Lock()  # estimator, publishers of estimates and diagnostics state
        self._wake = threading.Event()
        self._stopping = False
        self.messages = self.batch_messages = self.malformed = self.internal_errors = 0
        self._summary = None
        self._diagnostics = DiagnosticsState(counts_at_start=self.estimator.counts.as_dict())
        self._latency = LatencyHistogram()
        self._last_diagnostics = 0.0
        self._event_diagnostics_due = False
        # A sample below it reveals a drop: the estimator runs at once, not at the next flush.
        self._drop_level: float | None = None

        in_qos = qos(node.input_reliability, node.input_depth)
        self._drained: DrainedSubscription | None = None
        if node.receive == "drain":
            self._drained = DrainedSubscription(self, PointStamped, topics.displacement, in_qos)
        else:
            self.create_subscription(PointStamped, topics.displacement, self._on_sample, in_qos, raw=True)
        self.create_subscription(PointCloud2, node.batch_topic, self._on_batch, in_qos)
        worker = node.receive != "inline"
        # Without a worker the timer runs the EKF on what is pending; with one, it only sends event diagnostics.
        timer_period = EVENT_DIAGNOSTICS_INTERVAL / 2 if worker else node.flush_period
        self.create_timer(timer_period, self._on_flush_timer)
        self.create_timer(node.diagnostics_period, self.publish_diagnostics)
        self._worker = None
        if worker:
            # Two busy threads share the GIL: switch every 0.5 ms instead of 5 ms, or latency waits on it.
            sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
            self._worker = threading.Thread(target=self._work, name="touchdown_ekf", daemon=True)
            self._worker.start()
        self.get_logger().info(
            f"listening on {topics.displacement} (PointStamped, receive: {node.receive}) and {node.batch_topic} "
            f"(PointCloud2), {node.input_reliability}; scheduling {self.scheduling}; model: {self.model_info.message}"
        )
        self.publish_diagnostics()

    # ------------------------------------------------------------------ setup
    def _configure(self, base_config: Path | None, coefficients: str | None) -> Config:
        """Rig parameters: the base file (--config, else the reference rig) under the ROS parameters."""
        base = load_config(base_config)
        for name, value in base.parameters.items():
            if not self.has_parameter(name):
                self.declare_parameter(name, value)
        flat = {
            name: parameter.value
            for name, parameter in self.get_parameters_by_prefix("").items()
            if name not in ROS_PARAMETERS and not name.startswith("qos_overrides.")
        }
        if "coefficients" in flat:  # `-p coefficients:=FILE` is accepted as node.coefficients
            flat["node.coefficients"] = flat.pop("coefficients")
        if coefficients is not None:
            flat["node.coefficients"] = coefficients
        source = str(base_config) if base_config else base.source
        return config_from_parameters(flat, source=f"{source} + ROS parameters of {self.get_fully_qualified_name()}")

    # ------------------------------------------------------------------ input
    @quiet_at_shutdown
    def _on_sample(self, data: bytes) -> None:
        self.messages += 1
        try:
            stamp, x, y, z = messages.decode_point(data)
        except messages.MessageError as error:
            self._refuse_message(error)
            return
        pending = self._inbox.add_sample(stamp, x, y, z)
        if pending >= self.config.node.flush_samples or self._reveals_drop(z):
            self._due()

    @quiet_at_shutdown
    def _on_batch(self, message: PointCloud2) -> None:
        self.batch_messages += 1
        try:
            stamps, xyz = messages.batch_samples(message)
        except messages.MessageError as error:
            self._refuse_message(error)
            return
        pending = self._inbox.add_block(stamps, xyz)
        if pending >= self.config.node.flush_samples or self._reveals_drop(xyz[:, 2]):
            self._due()

    def _take_waiting(self) -> tuple[int, bool]:
        """Move the waiting per-sample messages (`receive: drain`) to the inbox: (taken, one reveals a drop)."""
        taken = self._drained.take(DRAIN_LIMIT)
        if not taken:
            return 0, False
        self.messages += len(taken)
        stamps, xyz, errors = messages.decode_points(taken)
        for error in errors:
            self._refuse_message(error)
        if not len(stamps):
            return len(taken), False
        self._inbox.add_block(stamps, xyz)
        return len(taken), self._reveals_drop(xyz[:, 2])

    def _reveals_drop(self, z: float | np.ndarray) -> bool:
        """A sample this low (z, m; NaN ignored) shows the rotor falling: estimate now, not at the next flush."""
        level = self._drop_level
        return level is not None and np.fmin.reduce(np.atleast_1d(z), initial=np.inf) < level

    def _wait_before_flush(self) -> float:
        """0 when the pending samples should be estimated now, else how long to wait for more, s."""
        node = self.config.node
        pending = self._inbox.count
        age = (time.monotonic_ns() - self._inbox.oldest_ns) / 1e9 if pending else 0.0
        if pending >= node.flush_samples or age >= node.flush_period:
            return 0.0
        return min(node.flush_period - age, (node.flush_samples - pending) * self.config.sample_period)

    def _refuse_message(self, error: Exception) -> None:
        self.malformed += 1
        self._log(LoggingSeverity.WARN, f"message refused: {error}", throttle=1.0, site="refused")

    def _due(self) -> None:
        """Enough samples are pending: run the estimator (in the worker thread when there is one)."""
        if self._worker is not None:
            self._wake.set()
        else:
            self.flush()

    @quiet_at_shutdown
    def _on_flush_timer(self) -> None:
        if self._worker is None:
            self.flush()
        if self._event_diagnostics_due and time.monotonic() - self._last_diagnostics >= EVENT_DIAGNOSTICS_INTERVAL:
            self.publish_diagnostics()

    def _work(self) -> None:
        """Worker thread: the EKF (which releases the GIL) runs while the executor serves the rest.

        With `receive: drain` it also takes the per-sample messages, all that wait at each
        wake-up, and sleeps until a flush's worth is expected (or a batch wakes it); while
        none arrive it looks every `flush_period`.
        """
        period = self.config.node.flush_period
        while not self._stopping:
            try:
                if self._drained is None:
                    self._wake.wait(timeout=period)
                else:
                    taken, crossed = self._take_waiting()
                    if crossed:
                        wait = 0.0
                    elif not taken and not self._inbox.count:  # per-sample input idle: no polling at its rate
                        wait = period
                    else:
                        wait = self._wait_before_flush()
                    if wait > 0.0:
                        self._wake.wait(timeout=wait)
                        self._wake.clear()
                        continue
                self._wake.clear()
                self.flush()
            except RCLError:
                if self.context.ok():
                    raise
                return
            except Exception as error:  # a bug must not stop the estimates: report it loudly, keep going
                self.internal_errors += 1
                self._log(LoggingSeverity.ERROR, f"worker: {error!r}", throttle=1.0, site="worker")
                time.sleep(period)

    def stop_worker(self) -> None:
        if self._worker is not None:
            self._stopping = True
            self._wake.set()
            self._worker.join(timeout=5.0)
            self._worker = None

    def destroy_node(self) -> None:
        self.stop_worker()
        if self._drained is not None:
            self._drained.destroy()
            self._drained = None
        super().destroy_node()

    # ------------------------------------------------------------------ estimation and output
    def flush(self) -> None:
        """Run the estimator on the pending samples and publish what it returns."""
        taken = self._inbox.take()
        if taken is None:
            return
        stamps, xyz, oldest_ns = taken
        with self._lock:
            try:
                update = self.estimator.push(stamps, xyz)
            except Exception as error:  # a bug must not stop the node: report it loudly, keep going
                self.internal_errors += 1
                self._log(LoggingSeverity.ERROR, f"estimator failed on {len(stamps)} samples: {error!r}",
                          throttle=1.0, site="estimator")
                return
            self._publish(update.estimates)
            self._handle(update.events)
            self._diagnostics.add_processing(time.monotonic_ns() - oldest_ns)
            self._drop_level = self.estimator.drop_level

    def finish(self) -> None:
        """End of input: publish what is held and close a touchdown in progress."""
        self.stop_worker()
        if self._drained is not None:
            while self._take_waiting()[0]:
                self.flush()
        self.flush()
        with self._lock:
            update = self.estimator.finish()
            self._publish(update.estimates)
            self._handle(update.events)
        self.publish_diagnostics()

    def _publish(self, out: StreamOutput) -> None:
        n = len(out.stamps_ns)
        if n == 0:
            return
        stamps = out.stamps_ns
        if self.per_sample:
            # A volatile topic nobody subscribes to is neither encoded nor sent (~5 us per message saved).
            listened = [(publisher, topic) for publisher, topic in self._estimate_publishers
                        if publisher.get_subscription_count()]
            if listened:
                blobs = [messages.encode_stamped(topic.msgtype, stamps, topic.vector(out),
                                                 topic.covariance and topic.covariance(out), self.frame_id,
                                                 topic.angular)
                         for _, topic in listened]
                with contextlib.ExitStack() as handles:
                    for publisher, _ in listened:
                        handles.enter_context(publisher.handle)
                    sends = [raw_publish(publisher) for publisher, _ in listened]
                    for row in zip(*blobs):  # sample by sample, all topics, as a bag replays them
                        for send, blob in zip(sends, row):
                            send(blob)
        if self.batched:
            self.pub_batch.publish(messages.estimate_cloud(out, self.frame_id, self.config.law.spins_ring))
        published = time.time_ns()
        self._diagnostics.add_estimates(out, published)
        self._latency.add(published - stamps)

    def _handle(self, events: Sequence[StreamEvent]) -> None:
        for event in events:
            self._diagnostics.add_event(event)
            if event.kind == "touchdown_end":
                self._summary = event.summary
                self._log(LoggingSeverity.INFO, event.message, site=event.kind)
            elif event.kind == "force_alarm":
                self._log(LoggingSeverity.ERROR, event.message, throttle=1.0, site=event.kind)
            elif event.kind in ("clock_jump", "resync"):
                self._log(LoggingSeverity.WARN, event.message, site=event.kind)
            else:
                self._log(LoggingSeverity.INFO, event.message, site=event.kind)
            self._event_diagnostics_due = True

    @quiet_at_shutdown
    def publish_diagnostics(self) -> None:
        """Publish /diagnostics now and start a new period.

        Only the snapshot is taken under the estimator's lock; building the statuses and
        publishing them (~0.4 ms) would otherwise hold up the worker's next block.
        """
        with self._lock:
            report = self._close_period()
        self.pub_diagnostics.publish(messages.diagnostic_array(time.time_ns(), statuses(**report)))

    def _close_period(self) -> dict:
        """End the diagnostics period; returns the arguments of `statuses` for it. Holds the lock."""
        node = self.config.node
        period = self._diagnostics
        self._diagnostics = period.close(self.estimator.counts, self.messages, self.malformed)
        self._last_diagnostics = time.monotonic()
        self._event_diagnostics_due = False
        levitated = self.estimator.levitated_reference
        return dict(
            state=period,
            counts=copy.copy(self.estimator.counts),
            phase=self.estimator.phase,
            levitated_z=None if levitated is None else float(levitated[2]),
            model=self.model_info,
            summary=self._summary,
            histogram=self._latency.copy(),
            messages=self.messages,
            batch_messages=self.batch_messages,
            malformed=self.malformed,
            internal_errors=self.internal_errors,
            pending=self._inbox.count,
            alarm_force=node.alarm_force,
            hardware_id=self.config.source.split(" + ")[0],
            scheduling=self.scheduling,
        )


def parse_arguments(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="touchdown_estimator",
        description="Live touchdown estimator: /amb/displacement in, /touchdown/* and /diagnostics out.",
        epilog="ROS arguments go after --ros-args, e.g. --ros-args --params-file rig.yaml -p node.alarm_force:=2.0e+4",
    )
    parser.add_argument("--config", type=Path, help="rig YAML (ROS 2 parameter-file form) used as the base parameters")
    parser.add_argument("--coefficients", help="PKBKR coefficient file (overrides node.coefficients)")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else [sys.argv[0], *argv])
    args = parse_arguments(rclpy.utilities.remove_ros_args(argv)[1:])
    configure_jax()
    rclpy.init(args=argv)
    node = None
    try:
        node = EstimatorNode(args.config, args.coefficients)
        executor = make_executor(node.config.node.executor)
        executor.add_node(node)
        node.get_logger().info(f"ready ({node.config.node.executor} executor)")
        spin(executor)
    except ConfigError as error:
        print(f"touchdown_estimator: configuration error: {error}", file=sys.stderr)
        return EXIT_CONFIG
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        if rclpy.ok():
            raise
        # a signal shut the context down while a callback was publishing: a normal stop
    finally:
        if node is not None:
            node.stop_worker()
            if rclpy.ok():
                try:
                    node.finish()
                except Exception as error:  # shutting down: report, do not mask the exit
                    print(f"touchdown_estimator: while finishing: {error}", file=sys.stderr)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
