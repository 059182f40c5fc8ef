"""What the streaming estimator returns: per-row estimates, events, touchdown summaries, counts;
and the packed row layout the compiled chunk filter writes them in."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import NamedTuple, Sequence

import numpy as np

#: Reasons a sample's stamp is refused (the sample is not placed on the grid).
STAMP_REJECTIONS = ("duplicate", "out_of_order", "off_grid")
#: Reasons a sample's values are not used (its grid row becomes predict-only).
VALUE_REJECTIONS = ("non_finite", "saturated", "millimetre")


@dataclass
class StreamCounts:
    """Running counts of everything the stream did; `as_dict()` for reports."""

    received: int = 0  # samples given to push()
    accepted: int = 0  # samples placed on the grid
    rows: int = 0  # grid rows (accepted samples + missing grid points)
    estimated: int = 0  # rows the EKF has filtered
    duplicate: int = 0  # stamp on an already filled grid point
    out_of_order: int = 0  # stamp older than the last placed sample
    off_grid: int = 0  # stamp more than grid_tolerance periods off the grid
    non_finite: int = 0  # NaN or inf value (row kept, predict-only)
    saturated: int = 0  # |value| at the sensor range or pinned at a rail (row kept, predict-only)
    millimetre: int = 0  # |value| > millimetre_limit (row kept, predict-only)
    gaps: int = 0  # places where grid points were missing, bridged (up to bridge_gap)
    missing_samples: int = 0  # missing grid points (predict-only rows)
    long_gaps: int = 0  # holes longer than bridge_gap (up to max_gap): nothing allocated, filter restarted
    dropped_rows: int = 0  # rows of unusable runs beyond bridge_gap in a touchdown: not filtered
    filter_restarts: int = 0  # touchdown filters restarted from the data after a long gap, jump or unusable run
    reference_refused: int = 0  # levitated windows refused as not clean (saturated, pinned, millimetres, missing)
    clock_jump_forward: int = 0  # forward stamp jumps > max_gap (nothing allocated, filter restarted)
    clock_jump_backward: int = 0  # backward stamp jumps > max_gap (the stream starts over: touchdown closed)
    resyncs: int = 0  # grid re-anchored after resync_after refused stamps
    drops: int = 0  # touchdowns detected
    relevitations: int = 0  # touchdowns ended by the return to levitation
    alarm_samples: int = 0  # estimates with |contact force| > alarm_force

    @property
    def rejected(self) -> dict[str, int]:
        """Samples not used, per reason."""
        return {name: getattr(self, name) for name in STAMP_REJECTIONS + VALUE_REJECTIONS}

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class TouchdownSummary(NamedTuple):
    """One touchdown, from the drop onset to its end."""

    onset_stamp_ns: int
    end_stamp_ns: int
    samples: int  # grid rows filtered
    missing_samples: int  # predict-only rows among them (gaps and refused values)
    axial_impacts: int  # impacts of the axial contact flag (`core.impacts`)
    radial_impacts: int  # impacts of the radial contact flag (`core.impacts`)
    peak_axial_force: float  # max F_z, N
    peak_radial_force: float  # max |(F_x, F_y)|, N
    mean_nis: float  # mean normalised innovation squared (3 expected)
    end_reason: str  # relevitated | clock_jump (back) | resync | end_of_stream
    filter_restarts: int = 0  # restarts after long gaps, clock jumps or runs of unusable samples
    process_scale_mean: float = math.nan  # the filter's factor on Q, mean over the rows (1: Q as fitted)
    process_scale_max: float = math.nan  # ... and its largest (`filter.adaptive_process_noise`)


class StreamEvent(NamedTuple):
    """Something the stream noticed; `summary` is set when a touchdown ends."""

    kind: str  # levitated | drop | touchdown_end | clock_jump | gap | resync | force_alarm
    stamp_ns: int
    message: str
    value: float = math.nan  # levitated mean z (m), peak force (N), ...
    summary: TouchdownSummary | None = None


class StreamOutput(NamedTuple):
    """Per-row estimates (filtered), stacked over the rows; SI units."""

    stamps_ns: np.ndarray  # (n,) int64, grid stamps
    measured: np.ndarray  # (n, 3) m, NaN where missing or refused
    state: np.ndarray  # (n, 7) [x y z theta xdot ydot zdot]
    state_cov: np.ndarray  # (n, 7, 7)
    ring_speed: np.ndarray  # (n,) rad/s, a spinning ring's speed (NaN unless the friction model has it)
    ring_speed_std: np.ndarray  # (n,) rad/s
    acceleration: np.ndarray  # (n, 3) m/s^2
    acceleration_cov: np.ndarray  # (n, 3, 3)
    force_xyz: np.ndarray  # (n, 3) contact force on the rotor, sensor axes, N
    force_cov: np.ndarray  # (n, 3, 3) N^2, its covariance linearised about the state (`estimate.signals`)
    F_n: np.ndarray  # (n,) N
    F_t: np.ndarray
    F_z: np.ndarray
    radial_contact: np.ndarray  # (n,) bool
    axial_contact: np.ndarray
    innovation: np.ndarray  # (n, 3) m, NaN when the row was not used
    innovation_cov: np.ndarray  # (n, 3, 3) m^2
    nis: np.ndarray  # (n,)
    used: np.ndarray  # (n,) bool, measurement used
    process_scale: np.ndarray  # (n,) the filter's factor on Q after the row (1 unless it adapts Q)

    @staticmethod
    def empty() -> "StreamOutput":
        return _EMPTY

    @staticmethod
    def concatenate(outputs: Sequence["StreamOutput"]) -> "StreamOutput":
        outputs = [o for o in outputs if len(o.stamps_ns)] or [StreamOutput.empty()]
        if len(outputs) == 1:
            return outputs[0]
        return StreamOutput(*(np.concatenate(parts) for parts in zip(*outputs)))


class StreamUpdate(NamedTuple):
    """What one push() produced: the new estimates and the events."""

    estimates: StreamOutput
    events: tuple[StreamEvent, ...]


#: Column groups of a packed row (one float64 row per sample), in order: name, width.
PACKED_LAYOUT = (
    ("state", 7),
    ("state_cov", 49),
    ("ring_speed", 1),
    ("ring_speed_std", 1),
    ("acceleration", 3),
    ("acceleration_cov", 9),
    ("force_xyz", 3),
    ("force_cov", 9),
    ("F_n", 1),
    ("F_t", 1),
    ("F_z", 1),
    ("radial_contact", 1),
    ("axial_contact", 1),
    ("innovation", 3),
    ("innovation_cov", 9),
    ("nis", 1),
    ("used", 1),
    ("process_scale", 1),
)
PACKED_WIDTH = sum(width for _, width in PACKED_LAYOUT)
_SHAPES = {"state_cov": (7, 7), "acceleration_cov": (3, 3), "force_cov": (3, 3), "innovation_cov": (3, 3)}
#: One packed row as a record: a field per column group, in the shapes of StreamOutput.
_RECORD = np.dtype(
    [(name, np.float64, _SHAPES.get(name, (width,) if width > 1 else ())) for name, width in PACKED_LAYOUT]
)
_FLAGS = ("radial_contact", "axial_contact", "used")  # packed as 0.0 / 1.0


def unpack(stamps_ns: np.ndarray, measured: np.ndarray, packed: np.ndarray) -> StreamOutput:
    """StreamOutput of packed rows (n, PACKED_WIDTH): views of them, the flags as bool."""
    records = np.ascontiguousarray(packed).view(_RECORD).reshape(-1)
    columns = {name: records[name] for name in _RECORD.names}
    for name in _FLAGS:
        columns[name] = columns[name].astype(bool)
    return StreamOutput(stamps_ns=stamps_ns, measured=measured, **columns)


_EMPTY = unpack(np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, PACKED_WIDTH)))
for _array in _EMPTY:  # shared by every update without estimates
    _array.flags.writeable = False
