"""Streaming touchdown estimation: samples in one at a time or in batches, the offline numbers out.

`StreamingEstimator` does live what `core.estimate` does offline on a whole record, to
round-off (the filtered signals; the streaming estimator has no smoother), and on top of it
classifies and counts what a live sensor stream can do wrong, detects the return to
levitation, summarises each touchdown and raises a force alarm. No ROS in here.

- `settings`: `StreamSettings` (built by `Config.stream_settings()`).
- `outputs`: what comes out (estimates, events, touchdown summaries, counts) and the packed row layout.
- `chunk_filter`: the EKF over a chunk of rows as one compiled loop.
- `grid`: stamps placed on the sensor grid, values screened by the input policy (plain numpy).
- `touchdown`: running figures of the touchdown in progress.
- `estimator`: the phase machine (waiting, levitated, touchdown) and `estimate_stream`.
"""
from touchdown_ros.core.streaming.chunk_filter import chunk_buffer, flat_belief, make_chunk_filter
from touchdown_ros.core.streaming.estimator import LEVITATED, TOUCHDOWN, WAITING, StreamingEstimator, estimate_stream
from touchdown_ros.core.streaming.outputs import StreamCounts, StreamEvent, StreamOutput, StreamUpdate, TouchdownSummary
from touchdown_ros.core.streaming.settings import StreamSettings

__all__ = [
    "LEVITATED",
    "TOUCHDOWN",
    "WAITING",
    "StreamCounts",
    "StreamEvent",
    "StreamOutput",
    "StreamSettings",
    "StreamUpdate",
    "StreamingEstimator",
    "TouchdownSummary",
    "chunk_buffer",
    "estimate_stream",
    "flat_belief",
    "make_chunk_filter",
]
