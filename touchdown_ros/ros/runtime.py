"""Process plumbing of the live node and the replayer: QoS, executors and spinning, a subscription
taken without an executor, raw publishing, quick logging, quiet shutdown, real-time scheduling,
JAX's dispatch and compilation cache.

Everything that reaches into rclpy's internals (the jazzy wheel's) lives here, each with a
fallback to the public API where those internals differ. Nothing numerical.
"""
from __future__ import annotations

import contextlib
import functools
import math
import os
import time
from typing import Callable

import rclpy
from rclpy import _rclpy_pybind11 as _rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.logging_severity import LoggingSeverity
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.type_support import check_is_valid_msg_type

from touchdown_ros.core import xla


def qos(reliability: str, depth: int) -> QoSProfile:
    """Keep-last QoS of the given reliability (best_effort matches sensor-data publishers)."""
    policy = ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=policy)


class DrainedSubscription:
    """A raw subscription that no executor serves: its owner takes the waiting messages itself.

    Created on the node's handle, so it is the node's subscription in the ROS graph
    (names resolved and remapped by rcl as for any subscription).
    """

    def __init__(self, node: Node, msg_type, topic: str, profile: QoSProfile) -> None:
        self.msg_type = msg_type
        check_is_valid_msg_type(msg_type)  # also loads the type support, as create_subscription does
        with node.handle:
            self.handle = _rclpy.Subscription(node.handle, msg_type, topic, profile.get_c_qos_profile())

    def take(self, limit: int) -> list[bytes]:
        """Up to `limit` waiting messages as serialized bytes, oldest first."""
        taken = []
        with self.handle:
            take_message = self.handle.take_message
            for _ in range(limit):
                message = take_message(self.msg_type, True)
                if message is None:
                    break
                taken.append(message[0])
        return taken

    def destroy(self) -> None:
        self.handle.destroy_when_not_in_use()


def raw_publish(publisher) -> Callable[[bytes], None]:
    """Publish serialized bytes without rclpy's per-call type check and handle guard (~1 us of 5-10).

    The caller holds `publisher.handle`. Falls back to `publisher.publish` if rclpy's
    internals differ from the jazzy wheel's.
    """
    inner = getattr(publisher, "_Publisher__publisher", None)
    return getattr(inner, "publish_raw", None) or publisher.publish


class QuickLog:
    """Log lines for the estimation path, ~20 us each instead of rclpy's ~0.4 ms.

    rclpy's logger finds its caller with `inspect` (reading the source file) on every
    call, even one its throttle then drops; that stalled the worker at each drop onset
    and made a flood of malformed messages cost 0.4 ms each. This one goes straight to
    rcutils (the same outputs and /rosout) under the node's logger name, with a
    throttle per call site; it falls back to rclpy's logger if rclpy's internals differ.
    """

    def __init__(self, logger) -> None:
        self._logger = logger
        self._log = getattr(_rclpy, "rclpy_logging_rcutils_log", None)
        self._last: dict[str, float] = {}

    def __call__(self, severity: LoggingSeverity, message: str, throttle: float = 0.0, site: str = "") -> None:
        """Log `message`; with `throttle` (s), at most once per that time for this `site`."""
        if throttle:
            now = time.monotonic()
            if now - self._last.get(site, -math.inf) < throttle:
                return
            self._last[site] = now
        if not self._logger.is_enabled_for(severity):
            return
        if self._log is None:
            self._logger.log(message, severity)
        else:
            self._log(severity, self._logger.name, message, site or "touchdown_estimator", __file__, 0)


def quiet_at_shutdown(callback):
    """Wrap a callback: a publish failing because a signal has just shut the context down ends it quietly."""

    @functools.wraps(callback)
    def wrapped(self, *args):
        try:
            return callback(self, *args)
        except RCLError:
            if self.context.ok():
                raise

    return wrapped


def make_executor(kind: str, context=None):
    """rclpy EventsExecutor (events) or SingleThreadedExecutor (single)."""
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


def spin(executor, context=None, keep_going=lambda: True) -> None:
    """Spin until the context shuts down (or keep_going() turns False).

    In the jazzy wheel, EventsExecutor.spin() (and spinning without a timeout)
    neither runs timers nor returns at shutdown; spinning in 0.2 s slices does both.
    """
    never = rclpy.task.Future()
    while rclpy.ok(context=context) and keep_going():
        executor.spin_until_future_complete(never, timeout_sec=0.2)


def set_realtime_scheduling(priority: int) -> tuple[str, str]:
    """SCHED_FIFO `priority` for every thread of the process (0: leave it): (what is in effect, as text;
    a warning, empty unless it was refused). Threads created later inherit the policy."""
    if priority == 0:
        return "normal", ""
    try:
        for thread in os.listdir("/proc/self/task"):
            os.sched_setscheduler(int(thread), os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as error:  # EPERM without CAP_SYS_NICE / rtprio limit; not Linux
        for thread in os.listdir("/proc/self/task") if os.path.isdir("/proc/self/task") else ():
            with contextlib.suppress(OSError):
                os.sched_setscheduler(int(thread), os.SCHED_OTHER, os.sched_param(0))
        warning = (f"node.realtime_priority {priority}: SCHED_FIFO refused ({error}); running with normal "
                   "scheduling (needs CAP_SYS_NICE or an rtprio limit)")
        return f"normal (SCHED_FIFO {priority} refused: {error})", warning
    return f"SCHED_FIFO {priority}", ""


def configure_jax() -> None:
    """Before JAX starts: the persistent compilation cache (`core.xla.use_compilation_cache`, every
    program: the node's start-up is what it shortens) and synchronous CPU dispatch.

    The node waits for every EKF chunk it starts; dispatching it to another thread and
    waiting there costs a thread hand-off per chunk (bench/chunk_dispatch.py).
    """
    import jax

    jax.config.update("jax_cpu_enable_async_dispatch", False)
    xla.use_compilation_cache(min_compile_seconds=0.0)
