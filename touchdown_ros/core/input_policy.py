"""One policy for imperfect sensor input, shared by the offline tools and the live node.

What a displacement sample or a hole between samples gets (docs/input_policy.md has the table):

- a value that is not finite, at or beyond `sensor_range` (saturated), pinned at a rail
  (`rail_samples` identical values in a row beyond half the sensor range) or beyond
  `millimetre_limit` (millimetres) is treated as missing: its grid row is predict-only;
- a hole of up to `bridge_gap` is bridged: its grid points become predict-only rows, flagged
  and left out of the peak forces;
- a longer hole (a gap) or any stamp jump beyond `max_gap` either way (a clock jump) is never
  allocated as grid rows: the grid is re-anchored at the next sample and the filter restarts
  from the data after it (a touchdown in progress continues with the same levitated reference);
- the levitated reference is taken only from a window whose rows are at least
  `CLEAN_WINDOW_FRACTION` usable: a stream in millimetres (or stuck) never gets one, so it
  never shows a drop.

Pure numpy, no ROS, no JAX.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

#: Fraction of the levitated window's rows that must hold usable values for a levitated reference.
CLEAN_WINDOW_FRACTION = 0.9
#: The levitated window's z may spread (standard deviation) at most this fraction of the drop threshold:
#: beyond it the threshold would be crossed by the spread alone (a stream in other units, or not levitated).
WINDOW_SPREAD_OF_THRESHOLD = 1.0 / 3.0
#: Kinds of hole between two consecutive samples.
CONTIGUOUS, BRIDGED, GAP, CLOCK_JUMP_FORWARD, CLOCK_JUMP_BACKWARD = range(5)


class GridError(ValueError):
    """Sample stamps do not fit the configured sample period."""


@dataclass(frozen=True)
class InputPolicy:
    """Limits of the input policy; SI units. `from_config` reads them from the rig YAML (`node.*`)."""

    sample_period: float  # s, the sensor grid
    sensor_range: float = 1.0e-3  # m: |value| at or beyond it is saturated
    millimetre_limit: float = 0.01  # m: |value| beyond it is taken for millimetres
    rail_samples: int = 10  # identical values in a row (beyond half the range) that mark a pinned sensor
    bridge_gap: float = 0.002  # s: holes up to this are bridged by predict-only rows
    max_gap: float = 0.05  # s: a stamp jump beyond it (either way) is a clock jump
    grid_tolerance: float = 0.25  # sample periods a stamp may sit off the grid

    @staticmethod
    def from_config(config: Any) -> "InputPolicy":
        """The policy of a rig YAML (`sensor.sample_period`, `node.*`)."""
        node = config.node
        return InputPolicy(
            sample_period=config.sample_period,
            sensor_range=node.sensor_range,
            millimetre_limit=node.millimetre_limit,
            rail_samples=node.rail_samples,
            bridge_gap=node.bridge_gap,
            max_gap=node.max_gap,
            grid_tolerance=node.grid_tolerance,
        )

    @property
    def bridge_rows(self) -> int:
        """Most missing grid points in a row that are bridged."""
        return int(np.floor(self.bridge_gap / self.sample_period + 1e-9))

    @property
    def max_gap_rows(self) -> float:
        """A stamp jump of more grid periods than this is a clock jump."""
        return self.max_gap / self.sample_period


class ValueFlags(NamedTuple):
    """Why each sample's value is not used; (n,) bool each, exclusive in this order."""

    non_finite: np.ndarray
    millimetre: np.ndarray
    saturated: np.ndarray  # at or beyond the range, or pinned at a rail
    rail_run: np.ndarray  # (3,) int: identical values in a row at the end, per axis (carry to the next call)
    last: np.ndarray  # (3,) the last values (carry to the next call)

    @property
    def refused(self) -> np.ndarray:
        return self.non_finite | self.millimetre | self.saturated


def value_flags(
    values: np.ndarray, policy: InputPolicy, rail_run: np.ndarray | None = None, last: np.ndarray | None = None
) -> ValueFlags:
    """Classify samples (n, 3) m in arrival order; `rail_run` / `last` carry a rail across calls."""
    values = np.asarray(values, dtype=np.float64).reshape(-1, 3)
    rail_run = np.zeros(3, np.int64) if rail_run is None else np.asarray(rail_run, np.int64)
    last = np.full(3, np.nan) if last is None else np.asarray(last, np.float64)
    finite = np.isfinite(values)
    non_finite = ~finite.all(axis=1)
    magnitude = np.abs(np.where(finite, values, 0.0))
    millimetre = ~non_finite & (magnitude > policy.millimetre_limit).any(axis=1)
    beyond = (magnitude >= policy.sensor_range).any(axis=1)
    if len(values) == 0:
        empty = np.zeros(0, bool)
        return ValueFlags(empty, empty, empty, rail_run, last)
    previous = np.concatenate([last[None], values[:-1]])
    same = (values == previous) & (magnitude >= 0.5 * policy.sensor_range)
    runs = np.empty(values.shape, np.int64)  # identical values in a row ending here, per axis
    for axis in range(3):
        runs[:, axis] = _run_lengths(same[:, axis], int(rail_run[axis])) + 1
    pinned = (runs >= policy.rail_samples).any(axis=1)
    saturated = ~non_finite & ~millimetre & (beyond | pinned)
    return ValueFlags(non_finite, millimetre, saturated, runs[-1] - 1, values[-1].copy())


def _run_lengths(flags: np.ndarray, carried: int) -> np.ndarray:
    """Length of the run of True ending at each element, continuing a run of `carried` before."""
    index = np.arange(len(flags))
    last_out = np.maximum.accumulate(np.where(flags, -1, index))
    return np.where(flags, np.where(last_out >= 0, index - last_out, carried + index + 1), 0)


def jump_kind(step_rows: np.ndarray, policy: InputPolicy) -> np.ndarray:
    """Kind of hole (CONTIGUOUS .. CLOCK_JUMP_BACKWARD) for grid steps between consecutive samples
    (1: the next grid point)."""
    step_rows = np.asarray(step_rows, dtype=np.float64)
    kind = np.full(step_rows.shape, CONTIGUOUS, np.int64)
    kind[step_rows > 1] = BRIDGED
    kind[step_rows - 1 > policy.bridge_rows] = GAP
    kind[step_rows > policy.max_gap_rows] = CLOCK_JUMP_FORWARD
    kind[-step_rows > policy.max_gap_rows] = CLOCK_JUMP_BACKWARD
    return kind


class RowRuns(NamedTuple):
    """What `bridge_rows` makes of a stretch of grid rows; (n,) bool each."""

    keep: np.ndarray  # rows filtered (usable, or within the bridge of a run of unusable rows)
    restart: np.ndarray  # usable rows after a run longer than the bridge: the filter restarts here
    run: int  # unusable rows in a row at the end (carry to the next call)


def bridge_rows(usable: np.ndarray, policy: InputPolicy, carried: int = 0) -> RowRuns:
    """Runs of unusable rows (missing, refused) on the grid: the first `policy.bridge_rows` of a
    run are kept (predict-only, bridged), the rest dropped, and the filter restarts at the next
    usable row. The same rows for a record at once and for a stream row by row (`carried`)."""
    usable = np.asarray(usable, bool)
    runs = _run_lengths(~usable, carried)
    keep = runs <= policy.bridge_rows
    before = np.concatenate([[carried], runs[:-1]])
    restart = usable & (before > policy.bridge_rows)
    return RowRuns(keep, restart, int(runs[-1]) if len(runs) else carried)


def window_is_clean(etas: np.ndarray, drop_threshold: float) -> bool:
    """Whether a levitated window (rows with NaN where refused or missing) may give the reference: at
    least CLEAN_WINDOW_FRACTION usable rows, and z spread below WINDOW_SPREAD_OF_THRESHOLD x the drop
    threshold (m)."""
    needed = threshold_for_window(etas)
    return needed is not None and needed <= drop_threshold


def threshold_for_window(etas: np.ndarray) -> float | None:
    """The least drop threshold (m) at which a levitated window is clean (`window_is_clean`): its z spread over
    WINDOW_SPREAD_OF_THRESHOLD; None where fewer than CLEAN_WINDOW_FRACTION of its rows are usable."""
    usable_share, spread = window_spread(etas)
    return None if usable_share < CLEAN_WINDOW_FRACTION else spread / WINDOW_SPREAD_OF_THRESHOLD


def window_spread(etas: np.ndarray) -> tuple[float, float]:
    """A levitated window's share of usable rows (no NaN; 0 without rows) and the z spread (m, sd) of those (NaN
    without any)."""
    etas = np.asarray(etas).reshape(-1, 3)
    usable = np.isfinite(etas).all(axis=1)
    if not usable.any():
        return 0.0, float("nan")
    return float(np.mean(usable)), float(np.std(etas[usable, 2]))


class Segment(NamedTuple):
    """A stretch of samples on one grid (no hole longer than the bridge inside)."""

    first_sample: int  # index of its first sample in the record
    stamps_ns: np.ndarray  # (N,) int64 grid stamps
    etas: np.ndarray  # (N, 3) m, NaN where missing or refused
    bridged_rows: np.ndarray  # (N,) bool, grid points without a sample (bridged; refused values are NaN rows too)


class RecordInput(NamedTuple):
    """A whole record under the policy: its segments and what was done, with counts."""

    segments: tuple[Segment, ...]
    counts: dict[str, int]  # non_finite, saturated, millimetre, bridged_gaps, bridged_rows, gaps, clock_jumps...
    breaks: tuple[tuple[int, int, str], ...]  # (sample index, jump ns, kind) where a new segment starts


def split_record(stamps_ns: np.ndarray, xyz: np.ndarray, policy: InputPolicy, source: str = "") -> RecordInput:
    """Apply the policy to a whole record (stamps strictly increasing): refused values NaN, short
    holes bridged, longer ones and clock jumps start a new segment (nothing allocated for them).

    Raises GridError (naming `source` and the sample) for a stamp off the grid."""
    where = f"{source}: " if source else ""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(stamps_ns) == 0:
        raise GridError(f"{where}no samples")
    flags = value_flags(xyz, policy)
    etas = np.where(flags.refused[:, None], np.nan, xyz)
    etas[~np.isfinite(etas)] = np.nan
    period_ns = policy.sample_period * 1e9
    steps = np.diff(stamps_ns) / period_ns
    kinds = jump_kind(steps, policy)
    starts = np.concatenate([[0], np.flatnonzero(kinds >= GAP) + 1, [len(stamps_ns)]])
    segments, bridged_gaps, bridged, dropped_rows, refused_runs = [], 0, 0, 0, 0
    for begin, end in zip(starts[:-1], starts[1:]):
        offsets = (stamps_ns[begin:end] - stamps_ns[begin]) / period_ns
        index = np.rint(offsets).astype(np.int64)
        jitter = np.abs(offsets - index)
        if np.any(jitter > policy.grid_tolerance):
            bad = int(np.argmax(jitter > policy.grid_tolerance))
            raise GridError(
                f"{where}sample {begin + bad} (stamp {stamps_ns[begin + bad]} ns): {jitter[bad]:.2f} periods off the "
                f"{policy.sample_period} s grid (is sensor.sample_period right?)"
            )
        if np.any(np.diff(index) <= 0):
            bad = int(np.argmax(np.diff(index) <= 0)) + 1
            raise GridError(
                f"{where}sample {begin + bad} (stamp {stamps_ns[begin + bad]} ns): not after the previous one on the "
                f"{policy.sample_period} s grid (is sensor.sample_period right?)"
            )
        rows = int(index[-1]) + 1
        grid = np.full((rows, 3), np.nan)
        grid[index] = etas[begin:end]
        missing = np.ones(rows, bool)
        missing[index] = False
        bridged_gaps += int(np.count_nonzero(np.diff(index) > 1))
        grid_stamps = stamps_ns[begin] + np.rint(np.arange(rows) * period_ns).astype(np.int64)
        runs = bridge_rows(np.isfinite(grid).all(axis=1), policy)
        cuts = np.concatenate([[0], np.flatnonzero(runs.restart), [rows]])
        for first, stop in zip(cuts[:-1], cuts[1:]):
            kept = np.flatnonzero(runs.keep[first:stop]) + first
            refused_runs += int(first > 0)
            segments.append(Segment(int(begin), grid_stamps[kept], grid[kept], missing[kept]))
        dropped_rows += int(np.count_nonzero(~runs.keep))
        bridged += int(np.count_nonzero(~np.isfinite(grid).all(axis=1) & runs.keep))
    names = {GAP: "gap", CLOCK_JUMP_FORWARD: "clock_jump_forward", CLOCK_JUMP_BACKWARD: "clock_jump_backward"}
    breaks = tuple(
        (int(i) + 1, int(stamps_ns[i + 1] - stamps_ns[i]), names[int(kinds[i])]) for i in np.flatnonzero(kinds >= GAP)
    )
    counts = {
        "non_finite": int(flags.non_finite.sum()),
        "saturated": int(flags.saturated.sum()),
        "millimetre": int(flags.millimetre.sum()),
        "bridged_gaps": bridged_gaps,
        "predicted_only_rows": bridged,  # rows kept without a usable value (missing or refused), predict-only
        "gaps": sum(1 for b in breaks if b[2] == "gap"),
        "clock_jump_forward": sum(1 for b in breaks if b[2] == "clock_jump_forward"),
        "clock_jump_backward": sum(1 for b in breaks if b[2] == "clock_jump_backward"),
        "unusable_runs": refused_runs,  # runs of unusable rows longer than the bridge (filter restarted after)
        "dropped_rows": dropped_rows,  # their rows beyond the bridge, not estimated
    }
    return RecordInput(tuple(segments), counts, breaks)
