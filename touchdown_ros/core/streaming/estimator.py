"""The streaming estimator's phase machine: waiting for a levitated window, levitated, touchdown.

`StreamingEstimator` does live what `core.estimate` does offline on a whole record: the
samples go on the grid (`grid.StampGrid`), the levitated mean and the drop onset come from
the offline rule (`DropDetector`), the EKF starts with `initial_belief` at the onset and
runs on every grid row from there on, in chunks (`chunk_filter`). A touchdown ends at the
return to levitation, a backward clock jump or a resync; long gaps and forward jumps restart
its filter from the data after them, as the offline tools do (`core.input_policy`).
"""
from __future__ import annotations

import functools
from typing import Sequence

import jax
import numpy as np

from touchdown_ros.core.dynamics import measures
from touchdown_ros.core.ekf import Belief, NoiseAdaptation, state_reading
from touchdown_ros.core.estimate import initial_belief
from touchdown_ros.core.input_policy import bridge_rows, window_is_clean
from touchdown_ros.core.streaming.chunk_filter import ChunkFunction, chunk_buffer, flat_belief, make_chunk_filter
from touchdown_ros.core.streaming.grid import GridBreak, StampGrid, run_lengths
from touchdown_ros.core.streaming.outputs import StreamCounts, StreamEvent, StreamOutput, StreamUpdate, unpack
from touchdown_ros.core.streaming.settings import StreamSettings
from touchdown_ros.core.streaming.touchdown import TouchdownTally
from touchdown_ros.core.types import FilterNoise, Model

#: Phases of the stream.
WAITING = "waiting"  # collecting the levitated window (no reference yet)
LEVITATED = "levitated"  # levitated reference known, watching for the drop
TOUCHDOWN = "touchdown"  # drop detected, EKF running on every grid row


class StreamingEstimator:
    """Live touchdown estimator: `push` samples (stamp ns, x, y, z in m), get estimates and events.

    Compiles the EKF chunk for each of `settings.chunk_sizes` on first use; call
    `warm_up()` to compile them all before the first sample arrives.
    """

    def __init__(
        self,
        model: Model,
        noise: FilterNoise,
        settings: StreamSettings,
        chunk_filter: ChunkFunction | None = None,
        model_variance: np.ndarray | None = None,
        adaptation: NoiseAdaptation | None = None,
    ):
        """`chunk_filter`: a `make_chunk_filter` of the same model, noise, period and adaptation, to share its
        compilations; `model_variance` (3,) N^2: the model's own force error in contact; `adaptation`: Q moved by
        the innovations, from its factor 1 at each drop onset (both `make_chunk_filter`'s)."""
        if not settings.chunk_sizes or min(settings.chunk_sizes) < 1:
            raise ValueError("chunk_sizes must be positive lengths")
        self.model, self.noise, self.settings = model, noise, settings
        self._sizes = tuple(sorted(set(int(c) for c in settings.chunk_sizes)))
        self._chunk = chunk_filter or make_chunk_filter(
            model, noise, settings.sample_period, model_variance, adaptation
        )
        self._initial_cov = np.asarray(noise.initial)
        # with measurement effects the onset's reading is moved to the state that reads it, as offline
        self._reading = jax.jit(functools.partial(state_reading, model)) if measures(model) else None
        self.counts = StreamCounts()
        self._grid = StampGrid(settings.policy, settings.resync_after, self.counts)
        self._events: list[StreamEvent] = []
        self._outputs: list[StreamOutput] = []
        self._start_waiting()

    # ---------------------------------------------------------------- public
    @property
    def phase(self) -> str:
        """waiting (collecting the levitated window), levitated, or touchdown."""
        return self._phase

    @property
    def levitated_reference(self) -> np.ndarray | None:
        """Levitated mean (x, y, z), m; z as `DropDetector.reference` computes it. None while waiting."""
        return None if self._reference is None else self._reference.copy()

    @property
    def drop_level(self) -> float | None:
        """z, m, below which a sample reveals a drop (levitated mean minus the threshold);
        None unless levitated."""
        if self._phase != LEVITATED or self._reference is None:
            return None
        return float(self._reference[2] - self.settings.drop.threshold)

    def warm_up(self) -> None:
        """Compile the EKF chunk of every configured length (a few seconds each, cached by JAX)."""
        prior = flat_belief(self._onset_belief(np.zeros((1, 3)), samples=1))
        for size in self._sizes:
            jax.block_until_ready(self._chunk(chunk_buffer(np.empty((0, 3)), size, prior)))

    def push(self, stamps_ns: np.ndarray | Sequence[int], xyz: np.ndarray) -> StreamUpdate:
        """Add samples in arrival order: stamps (n,) int ns and displacements (n, 3) m."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if len(stamps_ns) != len(xyz):
            raise ValueError(f"{len(stamps_ns)} stamps for {len(xyz)} samples")
        self.counts.received += len(stamps_ns)
        self._ingest(stamps_ns, xyz)
        self._run_filter(final=False)
        return self._collect()

    def finish(self) -> StreamUpdate:
        """End of stream: filter what is still held and close a touchdown in progress."""
        if self._phase == TOUCHDOWN:
            self._run_filter(final=True)
            self._end_touchdown("end_of_stream")
        return self._collect()

    def _ingest(self, stamps: np.ndarray, xyz: np.ndarray) -> None:
        """Place the samples on the grid and hand its rows to the phases; restart or reset at its breaks."""
        for piece in self._grid.place(stamps, xyz):
            if isinstance(piece, GridBreak):
                (self._reset if piece.starts_over else self._restart)(piece.kind, piece.stamp_ns, piece.message)
                continue
            if piece.millimetre and self._phase != TOUCHDOWN:
                # values in other units: the levitated reference (made of the same stream) cannot be trusted
                self._start_waiting()
            self._advance(piece.stamps_ns, piece.etas)

    # ---------------------------------------------------------------- phases
    def _start_waiting(self) -> None:
        self._phase = WAITING
        self._reference: np.ndarray | None = None
        self._buffer_stamps = np.empty(0, np.int64)
        self._buffer_etas = np.empty((0, 3))
        self._buffer_first = 0  # phase-relative index of the buffer's first row

    def _advance(self, stamps: np.ndarray, etas: np.ndarray) -> None:
        while len(stamps):
            if self._phase == TOUCHDOWN:
                stamps, etas = self._advance_touchdown(stamps, etas)
            else:
                stamps, etas = self._advance_levitated(stamps, etas)

    def _advance_levitated(self, stamps: np.ndarray, etas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Levitated reference over the first window rows, then the first crossing (`DropDetector.onset`)."""
        settings = self.settings
        buffer_stamps = np.concatenate([self._buffer_stamps, stamps])
        buffer_etas = np.concatenate([self._buffer_etas, etas])
        while self._reference is None and len(buffer_etas) >= settings.drop.window_samples:
            window = buffer_etas[: settings.drop.window_samples]
            if not window_is_clean(window, settings.drop.threshold):  # saturated, pinned, other units, missing
                self.counts.reference_refused += 1
                unusable = np.flatnonzero(~np.isfinite(window).all(axis=1))
                drop = int(unusable[-1]) + 1 if unusable.size else max(1, settings.drop.window_samples // 2)
                buffer_stamps, buffer_etas = buffer_stamps[drop:], buffer_etas[drop:]
                self._buffer_first += drop
                continue
            z = window[:, 2]
            finite = np.isfinite(z)
            reference_z = float(np.mean(z[finite])) if finite.any() else 0.0
            xy = [float(np.mean(col[np.isfinite(col)])) if np.isfinite(col).any() else 0.0 for col in window[:, :2].T]
            self._reference = np.array([xy[0], xy[1], reference_z])
            self._phase = LEVITATED
            self._events.append(
                StreamEvent("levitated", int(buffer_stamps[settings.drop.window_samples - 1]),
                            f"levitated mean z {reference_z * 1e6:.1f} um", reference_z)
            )
            break
        if self._reference is not None:
            z = buffer_etas[:, 2]
            below = np.flatnonzero(np.isfinite(z) & (z < self.drop_level))
            if below.size:
                # the buffer keeps fall_samples rows before the new ones once levitated (the phase's start or a
                # refused window's end before that): the onset never reaches before it
                onset = max(0, int(below[0]) - settings.drop.fall_samples)
                self._start_touchdown(int(buffer_stamps[onset]))
                rest = buffer_stamps[onset:], buffer_etas[onset:]
                self._buffer_stamps, self._buffer_etas = np.empty(0, np.int64), np.empty((0, 3))
                return rest
            keep_from = max(0, len(buffer_etas) - settings.drop.fall_samples)
            self._buffer_first += keep_from
            buffer_stamps, buffer_etas = buffer_stamps[keep_from:], buffer_etas[keep_from:]
        self._buffer_stamps, self._buffer_etas = buffer_stamps, buffer_etas
        return np.empty(0, np.int64), np.empty((0, 3))

    def _start_touchdown(self, onset_stamp_ns: int) -> None:
        self._phase = TOUCHDOWN
        self.counts.drops += 1
        self._belief: np.ndarray | None = None  # prior of the next row, as a chunk buffer's last row
        self._queue_stamps: list[np.ndarray] = []
        self._queue_etas: list[np.ndarray] = []
        self._queue_restart: list[bool] = []  # the filter restarts at the piece's first row
        self._unusable_run = 0  # unusable rows in a row at the end of the queue (input policy's bridge)
        self._left_band = False
        self._band_run = 0
        self._touchdown = TouchdownTally(onset_stamp_ns)
        self._events.append(StreamEvent("drop", onset_stamp_ns, "drop detected: touchdown estimation started"))

    def _advance_touchdown(self, stamps: np.ndarray, etas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Queue rows for the EKF until the rotor has been back in the levitated band for a window."""
        assert self._reference is not None
        inside = np.all(np.abs(etas - self._reference) <= self.settings.relevitation_band, axis=1)
        if self._left_band and not inside.any():  # on the bearing: the usual case in a touchdown
            self._band_run = 0
            self._queue(stamps, etas)
            return np.empty(0, np.int64), np.empty((0, 3))
        counting = np.ones(len(inside), bool)
        if not self._left_band:
            outside = np.flatnonzero(~inside)
            if outside.size == 0:
                counting[:] = False
            else:
                counting[: outside[0]] = False
                self._left_band = True
        runs = run_lengths(inside & counting, self._band_run)
        ended = np.flatnonzero(runs >= self.settings.relevitation_samples)
        stop = int(ended[0]) + 1 if ended.size else len(stamps)
        self._band_run = int(runs[stop - 1])
        self._queue(stamps[:stop], etas[:stop])
        if not ended.size:
            return np.empty(0, np.int64), np.empty((0, 3))
        self._run_filter(final=True)
        self.counts.relevitations += 1
        self._end_touchdown("relevitated")
        return stamps[stop:], etas[stop:]

    def _queue(self, stamps: np.ndarray, etas: np.ndarray) -> None:
        """Queue rows for the EKF under the input policy: of a run of unusable rows (missing, refused) the
        first bridge_gap are kept (predict-only), the rest dropped; the filter restarts at the next usable row."""
        usable = np.isfinite(etas).all(axis=1)
        if usable.all() and self._unusable_run == 0:  # the usual case
            self._queue_stamps.append(stamps)
            self._queue_etas.append(etas)
            self._queue_restart.append(False)
            return
        runs = bridge_rows(usable, self.settings.policy, self._unusable_run)
        self._unusable_run = runs.run
        self.counts.dropped_rows += int(np.count_nonzero(~runs.keep))
        cuts = np.concatenate([[0], np.flatnonzero(runs.restart), [len(stamps)]])
        for first, stop in zip(cuts[:-1], cuts[1:]):
            kept = np.flatnonzero(runs.keep[first:stop]) + first
            if len(kept) or first > 0:
                self._queue_stamps.append(stamps[kept])
                self._queue_etas.append(etas[kept])
                self._queue_restart.append(bool(runs.restart[first]) if first < len(stamps) else False)

    def _restart(self, kind: str, stamp_ns: int, why: str) -> None:
        """A hole the policy does not bridge (long gap, clock jump): nothing allocated, the grid re-anchored
        at the next sample; a touchdown in progress continues, its filter restarted from the data after."""
        if self._phase == TOUCHDOWN:
            self._run_filter(final=True)
            self._queue_stamps.append(np.empty(0, np.int64))
            self._queue_etas.append(np.empty((0, 3)))
            self._queue_restart.append(True)
            self._unusable_run = 0
            action = "touchdown filter restarted from the data after it"
        elif self._reference is not None:
            self._buffer_stamps, self._buffer_etas, self._buffer_first = np.empty(0, np.int64), np.empty((0, 3)), 0
            action = "levitated reference kept"
        else:
            self._start_waiting()
            action = "levitated window started again"
        self._events.append(StreamEvent(kind, stamp_ns, f"{why}; grid re-anchored, {action}"))

    def _end_touchdown(self, reason: str) -> None:
        summary = self._touchdown.summary(reason)
        self._events.append(
            StreamEvent(
                "touchdown_end",
                summary.end_stamp_ns,
                f"touchdown ended ({reason}): {summary.samples} samples, {summary.axial_impacts} axial impacts, "
                f"peak axial {summary.peak_axial_force:.4g} N, peak radial {summary.peak_radial_force:.4g} N",
                summary.peak_axial_force,
                summary,
            )
        )
        self._start_waiting()

    def _reset(self, kind: str, stamp_ns: int, why: str) -> None:
        """Clock jump or resync: close a touchdown in progress, re-anchor the grid, wait for levitation."""
        if self._phase == TOUCHDOWN:
            self._run_filter(final=True)
            self._end_touchdown(kind)
        else:
            self._start_waiting()
        self._events.append(StreamEvent(kind, stamp_ns, why + "; estimator reset"))

    # ---------------------------------------------------------------- filter
    def _run_filter(self, final: bool) -> None:
        """Filter the queued rows in chunks; the first rows (of the touchdown or after a restart) wait for
        the initial position."""
        if self._phase != TOUCHDOWN or not self._queue_stamps:
            return
        groups: list[tuple[list[np.ndarray], list[np.ndarray], bool]] = [([], [], False)]
        for stamps, etas, restart in zip(self._queue_stamps, self._queue_etas, self._queue_restart):
            if restart:
                groups.append(([], [], True))
            groups[-1][0].append(stamps)
            groups[-1][1].append(etas)
        self._queue_stamps, self._queue_etas, self._queue_restart = [], [], []
        for k, (stamps, etas, restart) in enumerate(groups):
            if restart:
                self._belief = None
                self.counts.filter_restarts += 1
                self._touchdown.restarts += 1
            self._filter_rows(np.concatenate(stamps) if stamps else np.empty(0, np.int64),
                              np.concatenate(etas) if etas else np.empty((0, 3)), final or k < len(groups) - 1)

    def _onset_belief(self, etas: np.ndarray, samples: int) -> Belief:
        """`initial_belief` of the first `samples` rows, its position the state that reads them (`state_reading`)."""
        belief = initial_belief(etas, self._initial_cov, samples=samples)
        if self._reading is None:
            return belief
        return belief._replace(mean=np.asarray(self._reading(belief.mean)))

    def _filter_rows(self, stamps: np.ndarray, etas: np.ndarray, final: bool) -> None:
        """Filter rows of one stretch; without a belief, wait (unless final) for the initial position."""
        if len(stamps) == 0:
            return
        if self._belief is None:
            if not np.isfinite(etas).all(axis=1).any():
                if not final:
                    self._queue_stamps, self._queue_etas, self._queue_restart = [stamps], [etas], [False]
                return  # nothing to start a filter from
            samples = self._initial_samples(etas, final)
            if samples is None:
                self._queue_stamps, self._queue_etas, self._queue_restart = [stamps], [etas], [False]
                return
            self._belief = flat_belief(self._onset_belief(etas, samples))

        packed_parts = []
        belief, done, largest = self._belief, 0, self._sizes[-1]
        while done < len(etas):
            count = min(len(etas) - done, largest)
            size = next(c for c in self._sizes if c >= count)
            start_time = (int(stamps[done]) - self._touchdown.onset_stamp_ns) * 1e-9  # s after the drop onset
            result = np.asarray(self._chunk(chunk_buffer(etas[done : done + count], size, belief, start_time)))
            packed_parts.append(result[:count])
            belief = result[size, : len(belief)]
            done += count
        self._belief = belief
        out = unpack(stamps, etas, np.concatenate(packed_parts))
        self.counts.estimated += len(stamps)
        self._touchdown.add(out)
        self._check_alarm(out)
        self._outputs.append(out)

    def _initial_samples(self, etas: np.ndarray, final: bool) -> int | None:
        """Rows averaged for the initial position: `initial_samples` as offline, more if an axis has no value."""
        wanted = self.settings.initial_samples
        if len(etas) < wanted:
            return len(etas) if final else None
        seen = np.logical_or.accumulate(np.isfinite(etas), axis=0).all(axis=1)
        enough = np.flatnonzero(seen[wanted - 1 :])
        if enough.size:
            return wanted + int(enough[0])
        return len(etas) if final else None

    def _check_alarm(self, out: StreamOutput) -> None:
        squared = np.einsum("ij,ij->i", out.force_xyz, out.force_xyz)
        above = (squared > self.settings.alarm_force**2) & out.used  # measured rows only, as the peaks
        if above.any():
            magnitude = np.sqrt(squared)
            self.counts.alarm_samples += int(np.count_nonzero(above))
            first = int(np.argmax(above))
            peak = float(np.max(magnitude))
            self._events.append(
                StreamEvent(
                    "force_alarm",
                    int(out.stamps_ns[first]),
                    f"contact force {peak:.4g} N above the alarm limit {self.settings.alarm_force:.4g} N",
                    peak,
                )
            )

    def _collect(self) -> StreamUpdate:
        update = StreamUpdate(StreamOutput.concatenate(self._outputs), tuple(self._events))
        self._outputs, self._events = [], []
        return update


def estimate_stream(
    estimator: StreamingEstimator, stamps_ns: np.ndarray, xyz: np.ndarray, batch_sizes: Sequence[int] | None = None
) -> tuple[StreamOutput, list[StreamEvent]]:
    """Push a whole record (in batches of the given sizes, cycled; one batch if None), then finish."""
    outputs, events = [], []
    if batch_sizes is None:
        batch_sizes = [max(1, len(stamps_ns))]
    start, turn = 0, 0
    while start < len(stamps_ns):
        stop = start + int(batch_sizes[turn % len(batch_sizes)])
        update = estimator.push(stamps_ns[start:stop], xyz[start:stop])
        outputs.append(update.estimates)
        events.extend(update.events)
        start, turn = stop, turn + 1
    update = estimator.finish()
    outputs.append(update.estimates)
    events.extend(update.events)
    return StreamOutput.concatenate(outputs), events
