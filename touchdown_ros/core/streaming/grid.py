"""Samples in arrival order placed on the sensor's regular time grid, the way a live stream needs it.

`StampGrid.place` classifies each stamp (on the next grid point, duplicate, out of order,
off the grid, after a bridged hole, a long gap or a clock jump), screens the values by the
input policy (`core.input_policy`) and returns, in order, the grid rows to estimate and the
breaks where the grid was re-anchored. Plain numpy; counts go to the stream's `StreamCounts`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from touchdown_ros.core.input_policy import InputPolicy, value_flags
from touchdown_ros.core.streaming.outputs import StreamCounts


class GridRows(NamedTuple):
    """Consecutive grid rows."""

    stamps_ns: np.ndarray  # (n,) int64, grid stamps
    etas: np.ndarray  # (n, 3) m, NaN where no sample arrived or its value was refused
    millimetre: bool  # some value was taken for millimetres (the stream's units are in doubt)


class GridBreak(NamedTuple):
    """A hole the input policy does not bridge or a re-anchoring: the grid starts again at `stamp_ns`."""

    kind: str  # clock_jump | gap | resync, the StreamEvent kind
    stamp_ns: int  # stamp of the sample that starts the new grid
    message: str
    starts_over: bool  # True: the stream starts over (backward jump, resync); False: the filter restarts


def run_lengths(flags: np.ndarray, carried: int) -> np.ndarray:
    """Length of the run of True ending at each element, continuing a run of `carried` before."""
    index = np.arange(len(flags))
    last_false = np.maximum.accumulate(np.where(flags, -1, index))
    return np.where(flags, np.where(last_false >= 0, index - last_false, carried + index + 1), 0)


class ValueScreen:
    """The input policy's verdict on sample values, carrying the rail runs from call to call."""

    def __init__(self, policy: InputPolicy, counts: StreamCounts):
        self._policy, self._counts = policy, counts
        self._clean_limit = min(policy.millimetre_limit, 0.5 * policy.sensor_range)  # m
        self._rail_run, self._rail_last = np.zeros(3, np.int64), np.full(3, np.nan)

    def screen(self, values: np.ndarray) -> tuple[np.ndarray, bool]:
        """(values (n, 3) m with the refused components NaN, whether some were millimetres)."""
        if np.all(np.abs(values) < self._clean_limit):  # finite and well inside the range (never pinned)
            self._rail_run[:] = 0
            self._rail_last = values[-1].copy()
            return values, False
        flags = value_flags(values, self._policy, self._rail_run, self._rail_last)
        self._rail_run, self._rail_last = flags.rail_run, flags.last
        self._counts.non_finite += int(np.count_nonzero(flags.non_finite))
        self._counts.millimetre += int(np.count_nonzero(flags.millimetre))
        self._counts.saturated += int(np.count_nonzero(flags.saturated))
        values = values.copy()
        values[~np.isfinite(values)] = np.nan  # partial rows keep their finite components, as offline
        values[flags.millimetre | flags.saturated] = np.nan
        return values, bool(flags.millimetre.any())


class StampGrid:
    """The grid of one stream: its origin, the last placed row and the streak of refused stamps."""

    def __init__(self, policy: InputPolicy, resync_after: int, counts: StreamCounts):
        """`resync_after`: consecutive out-of-order / off-grid stamps that re-anchor the grid."""
        self._policy, self._resync_after, self._counts = policy, resync_after, counts
        self._period_ns = policy.sample_period * 1e9
        self._values = ValueScreen(policy, counts)
        self._clear()

    def _clear(self) -> None:
        self._origin: int | None = None  # stamp of grid row 0, ns
        self._last_index = -1  # grid index of the last placed sample
        self._refused_streak = 0  # consecutive out-of-order / off-grid samples

    def place(self, stamps: np.ndarray, xyz: np.ndarray) -> list[GridRows | GridBreak]:
        """Rows and breaks of samples (stamps (n,) int ns, xyz (n, 3) m) in arrival order."""
        if self._origin is not None and len(stamps):
            in_order = self._place_in_order(stamps, xyz)
            if in_order is not None:
                return [in_order]
        pieces: list[GridRows | GridBreak] = []
        counts, policy = self._counts, self._policy
        start = 0
        while start < len(stamps):
            if self._origin is None:
                self._origin, self._last_index = int(stamps[start]), -1
            s, v = stamps[start:], xyz[start:]
            offsets = (s - self._origin) / self._period_ns
            index = np.rint(offsets).astype(np.int64)
            on_grid = np.abs(offsets - index) <= policy.grid_tolerance
            # Highest placed index before each sample (accepted samples strictly increase).
            candidates = np.where(on_grid, index, np.iinfo(np.int64).min)
            before = np.maximum.accumulate(np.concatenate([[self._last_index], candidates[:-1]]))
            back_jump = (before - index) > policy.max_gap_rows
            forward_jump = (index - before) > policy.max_gap_rows
            # a hole the policy does not bridge (before < 0: the first sample of a grid)
            long_gap = (before >= 0) & ((index - before - 1) > policy.bridge_rows) & ~forward_jump
            out_of_order = (index < before) & ~back_jump
            duplicate = on_grid & (index == before)
            off_grid = ~on_grid & (index >= before) & ~forward_jump & ~long_gap
            refused = out_of_order | off_grid
            streak = run_lengths(refused, self._refused_streak)
            resync = refused & (streak >= self._resync_after)
            event = back_jump | forward_jump | long_gap | resync
            stop = int(np.argmax(event)) if event.any() else len(s)

            accepted = on_grid[:stop] & (index[:stop] > before[:stop])
            counts.duplicate += int(np.count_nonzero(duplicate[:stop]))
            counts.out_of_order += int(np.count_nonzero(out_of_order[:stop]))
            counts.off_grid += int(np.count_nonzero(off_grid[:stop]))
            self._refused_streak = int(streak[stop - 1]) if stop else self._refused_streak
            if accepted.any():
                pieces.append(self._rows(index[:stop][accepted], v[:stop][accepted]))
            if stop == len(s):
                return pieces
            stamp = int(s[stop])
            jump_s = (stamp - (self._origin + before[stop] * self._period_ns)) / 1e9
            if back_jump[stop]:
                counts.clock_jump_backward += 1  # the stream starts over (a replay, a restarted sensor)
                why = f"stamp jumped back by {-jump_s:.4g} s (more than max_gap)"
                pieces.append(GridBreak("clock_jump", stamp, why, starts_over=True))
            elif forward_jump[stop]:
                counts.clock_jump_forward += 1
                why = f"stamp jumped forward by {jump_s:.4g} s (more than max_gap)"
                pieces.append(GridBreak("clock_jump", stamp, why, starts_over=False))
            elif long_gap[stop]:
                counts.long_gaps += 1
                pieces.append(GridBreak("gap", stamp, f"no sample for {jump_s:.4g} s (more than bridge_gap)", False))
            else:
                counts.resyncs += 1
                why = f"{self._resync_after} refused stamps in a row"
                pieces.append(GridBreak("resync", stamp, why, starts_over=True))
            self._clear()
            start += stop  # the sample that triggered the break starts the new grid
        return pieces

    def _place_in_order(self, stamps: np.ndarray, xyz: np.ndarray) -> GridRows | None:
        """Fast path of the usual case: every sample on the next grid point. None if it does not apply."""
        offsets = (stamps - self._origin) / self._period_ns
        index = np.rint(offsets).astype(np.int64)
        if index[0] != self._last_index + 1 or index[-1] != self._last_index + len(index):
            return None
        if len(index) > 1 and not (np.diff(index) == 1).all():
            return None
        if not (np.abs(offsets - index) <= self._policy.grid_tolerance).all():
            return None
        self._refused_streak = 0
        return self._rows(index, xyz)

    def _rows(self, index: np.ndarray, values: np.ndarray) -> GridRows:
        """Grid rows from the last placed index + 1 to index[-1]: the screened values where given, NaN elsewhere."""
        counts = self._counts
        if index[-1] - self._last_index != len(index):  # not contiguous: gaps
            previous = np.concatenate([[self._last_index], index[:-1]])
            skipped = index - previous - 1
            counts.gaps += int(np.count_nonzero(skipped))
            counts.missing_samples += int(skipped.sum())
        counts.accepted += len(index)
        values, millimetre = self._values.screen(values)
        first = self._last_index + 1
        rows = np.arange(first, index[-1] + 1)
        etas = np.full((len(rows), 3), np.nan)
        etas[index - first] = values
        stamps = self._origin + np.rint(rows * self._period_ns).astype(np.int64)
        self._last_index = int(index[-1])
        counts.rows += len(rows)
        return GridRows(stamps, etas, millimetre)
