"""The node's health, published on /diagnostics: what it reports and how it decides the level.

`DiagnosticsState` collects, between two publications, what the node saw
(estimates, latencies, alarms, events); `statuses()` turns it with the
estimator's counts into `diagnostic_msgs/DiagnosticStatus` entries named
"touchdown_estimator: <part>". docs/node.md lists every key.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from diagnostic_msgs.msg import DiagnosticStatus

from touchdown_ros.core.streaming import StreamCounts, StreamEvent, StreamOutput, TouchdownSummary
from touchdown_ros.ros.messages import diagnostic_status

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
PREFIX = "touchdown_estimator: "
#: Mean NIS above this is a WARN: the 99.9 % point of chi-square with 3 degrees of freedom.
NIS_WARN = 16.27
#: Counts whose increase in a period makes the input status WARN.
INPUT_PROBLEMS = (
    "duplicate", "out_of_order", "off_grid", "non_finite", "saturated", "millimetre",
    "gaps", "missing_samples", "long_gaps", "dropped_rows", "filter_restarts", "reference_refused",
    "clock_jump_forward", "clock_jump_backward", "resyncs",
)  # fmt: skip


@dataclass
class ModelInfo:
    """What the node runs: the constant model or a coefficient file, and whether loading failed."""

    level: bytes
    message: str
    values: dict[str, Any] = field(default_factory=dict)


class LatencyHistogram:
    """Latencies since start in 0.05 ms bins up to 1 s (beyond: the last bin), for percentiles of a whole run."""

    BIN_NS = 50_000
    BINS = 20_000

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS + 1, np.int64)

    def add(self, latencies_ns: np.ndarray) -> None:
        bins = np.clip(np.asarray(latencies_ns) // self.BIN_NS, 0, self.BINS)
        np.add.at(self.counts, bins, 1)  # not bincount: that touches all 20,001 bins per call

    def percentile(self, q: float) -> float:
        """Upper edge of the bin holding the q-th percentile, ms (NaN before any latency)."""
        total = int(self.counts.sum())
        if not total:
            return math.nan
        index = int(np.searchsorted(np.cumsum(self.counts), math.ceil(q / 100.0 * total)))
        return (index + 1) * self.BIN_NS / 1e6

    def copy(self) -> LatencyHistogram:
        """An independent copy (a snapshot to compute percentiles from while this one grows)."""
        snapshot = LatencyHistogram()
        snapshot.counts[:] = self.counts
        return snapshot


@dataclass
class DiagnosticsState:
    """Everything one diagnostics period accumulates; `close()` ends it and begins the next."""

    started: float = field(default_factory=time.monotonic)
    ended: float = math.nan  # time.monotonic() when closed
    counts_at_start: dict[str, int] = field(default_factory=dict)
    messages_at_start: int = 0
    malformed_at_start: int = 0
    latencies_ns: list[np.ndarray] = field(default_factory=list)  # sample stamp -> estimate published
    processing_ns: list[int] = field(default_factory=list)  # oldest sample of a block received -> published
    nis_sum: float = 0.0
    nis_count: int = 0
    process_scale_max: float = math.nan  # the largest factor the filter's adaptive Q reached this period
    alarm_peak: float = math.nan  # N, largest force of the period's force alarms
    radial_contact: bool = False
    axial_contact: bool = False
    events: list[str] = field(default_factory=list)

    def add_estimates(self, estimates: StreamOutput, published_ns: int) -> None:
        """Bookkeeping of a block of published estimates (latency = publish time - sample stamp)."""
        if len(estimates.stamps_ns) == 0:
            return
        self.latencies_ns.append(published_ns - estimates.stamps_ns)
        finite = np.isfinite(estimates.nis)
        self.nis_sum += float(np.sum(estimates.nis[finite]))
        self.nis_count += int(np.count_nonzero(finite))
        self.process_scale_max = float(np.fmax(self.process_scale_max, estimates.process_scale.max()))
        self.radial_contact = bool(estimates.radial_contact[-1])
        self.axial_contact = bool(estimates.axial_contact[-1])

    def add_processing(self, nanoseconds: int) -> None:
        """Time from the arrival of a block's oldest sample to the end of its publication."""
        self.processing_ns.append(nanoseconds)

    def add_event(self, event: StreamEvent) -> None:
        """Remember an estimator event for the contact status (force alarms keep their peak)."""
        if event.kind == "force_alarm":
            self.alarm_peak = event.value if math.isnan(self.alarm_peak) else max(self.alarm_peak, event.value)
        self.events.append(event.message)

    def close(self, counts: StreamCounts, messages: int, malformed: int = 0) -> DiagnosticsState:
        """End this period now (`counts`, `messages` and `malformed` as they are now); returns the next period.

        The closed state no longer changes: `statuses()` may read it in another thread.
        """
        self.ended = time.monotonic()
        return DiagnosticsState(
            counts_at_start=counts.as_dict(),
            messages_at_start=messages,
            malformed_at_start=malformed,
            radial_contact=self.radial_contact,
            axial_contact=self.axial_contact,
        )


def statuses(
    state: DiagnosticsState,
    counts: StreamCounts,
    *,
    phase: str,
    levitated_z: float | None,
    model: ModelInfo,
    summary: TouchdownSummary | None,
    histogram: LatencyHistogram,
    messages: int,
    batch_messages: int,
    malformed: int,
    internal_errors: int,
    pending: int,
    alarm_force: float,
    hardware_id: str,
    scheduling: str = "normal",
) -> list[DiagnosticStatus]:
    """The diagnostic statuses of one publication: `state` is the period (closed, or still open)."""
    end = time.monotonic() if math.isnan(state.ended) else state.ended
    elapsed = max(end - state.started, 1e-9)
    total = counts.as_dict()
    delta = {k: v - state.counts_at_start.get(k, 0) for k, v in total.items()}
    out = []

    problems = {k: delta[k] for k in INPUT_PROBLEMS if delta[k]}
    if malformed > state.malformed_at_start:  # this period's, not the total since start
        problems["malformed_messages"] = malformed - state.malformed_at_start
    rate = delta["received"] / elapsed
    refused = sum(counts.rejected.values())
    input_level = ERROR if internal_errors else WARN if problems else OK
    detail = ", ".join(f"{v} {k}" for k, v in problems.items())
    failed = f"; {internal_errors} estimator failure(s), see the log" if internal_errors else ""
    out.append(
        diagnostic_status(
            PREFIX + "input",
            input_level,
            f"{rate:.0f} samples/s" + (f"; this period: {detail}" if detail else "") + failed,
            {
                "rate_hz": rate,
                "received": counts.received,
                "messages": messages,
                "batch_messages": batch_messages,
                "accepted": counts.accepted,
                "rejected": refused,
                **{f"rejected.{k}": v for k, v in counts.rejected.items()},
                "gaps": counts.gaps,
                "missing_samples": counts.missing_samples,
                "long_gaps": counts.long_gaps,
                "dropped_rows": counts.dropped_rows,
                "filter_restarts": counts.filter_restarts,
                "reference_refused": counts.reference_refused,
                "clock_jump_forward": counts.clock_jump_forward,
                "clock_jump_backward": counts.clock_jump_backward,
                "resyncs": counts.resyncs,
                "malformed_messages": malformed,
                "estimator_failures": internal_errors,
                "pending": pending,
            },
            hardware_id,
        )
    )

    mean_nis = state.nis_sum / state.nis_count if state.nis_count else math.nan
    latencies = np.concatenate(state.latencies_ns) / 1e6 if state.latencies_ns else np.empty(0)
    p50, p99, worst = (np.percentile(latencies, [50, 99, 100]) if latencies.size else (math.nan,) * 3)
    processing = np.asarray(state.processing_ns) / 1e6
    in_node_p99 = float(np.percentile(processing, 99)) if processing.size else math.nan
    filter_level = WARN if mean_nis > NIS_WARN else OK
    out.append(
        diagnostic_status(
            PREFIX + "filter",
            filter_level,
            "no estimate this period" if not state.nis_count and not latencies.size
            else f"mean NIS {mean_nis:.3g} (3 expected)",
            {
                "mean_nis": mean_nis,
                "process_noise_scale_max": state.process_scale_max,
                "estimated": counts.estimated,
                "estimated_period": delta["estimated"],
                "latency_p50_ms": float(p50),
                "latency_p99_ms": float(p99),
                "latency_max_ms": float(worst),
                "in_node_p99_ms": in_node_p99,
                "latency_total_p50_ms": histogram.percentile(50),
                "latency_total_p99_ms": histogram.percentile(99),
                "scheduling": scheduling,
            },
            hardware_id,
        )
    )

    alarm = delta["alarm_samples"] > 0 or not math.isnan(state.alarm_peak)
    if alarm:
        contact_message = f"contact force {state.alarm_peak:.4g} N above the alarm limit {alarm_force:.4g} N"
    elif phase == "touchdown":
        flags = [name for name, on in (("radial", state.radial_contact), ("axial", state.axial_contact)) if on]
        contact_message = "touchdown: " + (" and ".join(flags) + " contact" if flags else "no contact")
    else:
        contact_message = phase
    out.append(
        diagnostic_status(
            PREFIX + "contact",
            ERROR if alarm else OK,
            contact_message,
            {
                "phase": phase,
                "radial_contact": state.radial_contact and phase == "touchdown",
                "axial_contact": state.axial_contact and phase == "touchdown",
                "drops": counts.drops,
                "relevitations": counts.relevitations,
                "levitated_z_m": math.nan if levitated_z is None else levitated_z,
                "alarm_limit_N": alarm_force,
                "alarm_samples_period": delta["alarm_samples"],
                "alarm_samples": counts.alarm_samples,
                "events": "; ".join(state.events[-5:]),
            },
            hardware_id,
        )
    )

    out.append(diagnostic_status(PREFIX + "model", model.level, model.message, model.values, hardware_id))

    if summary is not None:
        out.append(
            diagnostic_status(
                PREFIX + "last touchdown",
                OK,
                f"{summary.axial_impacts} axial impacts, peak axial {summary.peak_axial_force:.4g} N, "
                f"peak radial {summary.peak_radial_force:.4g} N ({summary.end_reason})",
                {
                    "onset_stamp_ns": summary.onset_stamp_ns,
                    "end_stamp_ns": summary.end_stamp_ns,
                    "duration_s": (summary.end_stamp_ns - summary.onset_stamp_ns) / 1e9,
                    "samples": summary.samples,
                    "missing_samples": summary.missing_samples,
                    "axial_impacts": summary.axial_impacts,
                    "radial_impacts": summary.radial_impacts,
                    "peak_axial_force_N": summary.peak_axial_force,
                    "peak_radial_force_N": summary.peak_radial_force,
                    "mean_nis": summary.mean_nis,
                    "process_noise_scale_mean": summary.process_scale_mean,
                    "process_noise_scale_max": summary.process_scale_max,
                    "end_reason": summary.end_reason,
                    "filter_restarts": summary.filter_restarts,
                },
                hardware_id,
            )
        )
    return out
