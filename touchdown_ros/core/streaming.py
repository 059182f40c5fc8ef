"""Streaming touchdown estimation: samples in one at a time or in batches, the offline numbers out.

`StreamingEstimator` does live what `core.estimate` does offline on a whole record:
places samples on the sensor's regular time grid (`to_grid`, gaps become NaN rows),
keeps the levitated mean of z and finds the drop onset exactly as `detect_drop`,
starts the EKF with `initial_belief` at the onset and filters every grid row from
there on. The EKF runs in chunks of a few compiled lengths (`lax.scan`, NaN padding
and a mask so that padding never advances the belief), so the per-sample Python
cost stays small. Results equal `make_estimator(...)` on the same record to
round-off (the filtered signals; the streaming estimator has no smoother).

On top of the offline pipeline it classifies and counts what a live sensor stream
can do wrong (duplicate, out-of-order and off-grid stamps, gaps, clock jumps,
non-finite, saturated, pinned and millimetre values) and treats gaps, clock jumps and
refused values by the input policy the offline tools apply (`core.input_policy`),
detects the return to levitation, summarises each touchdown and raises a force alarm.
No ROS in here.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.dynamics import contact_force_xyz, contact_forces_and_jacobian
from touchdown_ros.core.ekf import Belief, _inverse_3x3, model_measurement, predict_with_rate, update
from touchdown_ros.core.estimate import initial_belief
from touchdown_ros.core.input_policy import InputPolicy, bridge_rows, value_flags, window_is_clean
from touchdown_ros.core.types import FilterNoise, Model

if TYPE_CHECKING:  # only for the type hint of StreamSettings.from_config; core never imports io at run time
    from touchdown_ros.io.config import Config

#: Phases of the stream.
WAITING = "waiting"  # collecting the levitated window (no reference yet)
LEVITATED = "levitated"  # levitated reference known, watching for the drop
TOUCHDOWN = "touchdown"  # drop detected, EKF running on every grid row

#: Reasons a sample's stamp is refused (the sample is not placed on the grid).
STAMP_REJECTIONS = ("duplicate", "out_of_order", "off_grid")
#: Reasons a sample's values are not used (its grid row becomes predict-only).
VALUE_REJECTIONS = ("non_finite", "saturated", "millimetre")


@dataclass(frozen=True)
class StreamSettings:
    """What the streaming estimator needs besides the model; SI units."""

    sample_period: float  # s, sensor grid
    drop_threshold: float  # m below the levitated mean of z (drop_detection.threshold)
    levitated_window: float  # s of levitation averaged for the reference
    gravity: float  # m/s^2, for the free-fall time of the threshold
    initial_samples: int = 5  # samples averaged for the initial position (as offline)
    grid_tolerance: float = 0.25  # periods a stamp may sit off the grid (as `to_grid`)
    max_gap: float = 0.05  # s; a longer forward or backward stamp jump is a clock jump (filter restarted)
    bridge_gap: float = 0.002  # s; holes up to this are bridged (predict-only rows); longer: filter restarted
    rail_samples: int = 10  # identical values in a row beyond half the sensor range: pinned (saturated)
    resync_after: int = 20  # consecutive out-of-order / off-grid samples that re-anchor the grid
    sensor_range: float = math.inf  # m; |value| at or beyond it is saturated
    millimetre_limit: float = 0.01  # m; |value| beyond it is taken for a value in mm
    relevitation_band: float = 20e-6  # m around the levitated mean (x, y and z)
    relevitation_window: float = 0.005  # s inside the band that ends a touchdown
    alarm_force: float = math.inf  # N, |contact force| that raises a force alarm
    chunk_sizes: tuple[int, ...] = (8, 16, 32, 64, 128, 256, 512)  # compiled EKF chunk lengths

    @staticmethod
    def from_config(config: "Config", **overrides: Any) -> "StreamSettings":
        """Settings of a rig YAML (`drop_detection.*`, `sensor.*`, `node.*`)."""
        node = getattr(config, "node", None)
        values: dict[str, Any] = dict(
            sample_period=config.sample_period,
            drop_threshold=config.drop.threshold,
            levitated_window=config.drop.levitated_window,
            gravity=config.rig.gravity,
        )
        if node is not None:
            values.update(
                grid_tolerance=node.grid_tolerance,
                max_gap=node.max_gap,
                bridge_gap=node.bridge_gap,
                rail_samples=node.rail_samples,
                resync_after=node.resync_after,
                sensor_range=node.sensor_range,
                millimetre_limit=node.millimetre_limit,
                relevitation_band=node.relevitation_band,
                relevitation_window=node.relevitation_window,
                alarm_force=node.alarm_force,
                chunk_sizes=tuple(node.chunk_sizes),
            )
        values.update(overrides)
        return StreamSettings(**values)

    @property
    def policy(self) -> InputPolicy:
        """The input policy shared with the offline tools (`core.input_policy`): its fields of these settings."""
        return InputPolicy(**{f.name: getattr(self, f.name) for f in fields(InputPolicy)})

    @property
    def window_samples(self) -> int:
        """Grid rows of the levitated window (as `detect_drop`)."""
        return max(1, int(round(self.levitated_window / self.sample_period)))

    @property
    def fall_samples(self) -> int:
        """Rows the onset is moved back from the threshold crossing: sqrt(2 threshold / g) (as `detect_drop`)."""
        return int(round(np.sqrt(2.0 * self.drop_threshold / self.gravity) / self.sample_period))

    @property
    def relevitation_samples(self) -> int:
        return max(1, int(round(self.relevitation_window / self.sample_period)))


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
    axial_impacts: int  # rising edges of the axial contact flag
    radial_impacts: int  # rising edges of the radial contact flag
    peak_axial_force: float  # max F_z, N
    peak_radial_force: float  # max |(F_x, F_y)|, N
    mean_nis: float  # mean normalised innovation squared (3 expected)
    end_reason: str  # relevitated | clock_jump (back) | resync | end_of_stream
    filter_restarts: int = 0  # restarts after long gaps, clock jumps or runs of unusable samples


class StreamEvent(NamedTuple):
    """Something the stream noticed; `summary` is set when a touchdown ends."""

    kind: str  # levitated | drop | touchdown_end | clock_jump | resync | force_alarm
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


# Column layout of the packed chunk result (one float64 row per sample).
_LAYOUT = (
    ("state", 7),
    ("state_cov", 49),
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
)
_PACKED_WIDTH = sum(width for _, width in _LAYOUT)
_SHAPES = {"state_cov": (7, 7), "acceleration_cov": (3, 3), "force_cov": (3, 3), "innovation_cov": (3, 3)}


#: One packed row as a record: a field per column group, in the shapes of StreamOutput.
_RECORD = np.dtype([(name, np.float64, _SHAPES.get(name, (width,) if width > 1 else ())) for name, width in _LAYOUT])
_FLAGS = ("radial_contact", "axial_contact", "used")  # packed as 0.0 / 1.0


def _unpack(stamps_ns: np.ndarray, measured: np.ndarray, packed: np.ndarray) -> StreamOutput:
    """StreamOutput of packed rows (n, _PACKED_WIDTH): views of them, the flags as bool."""
    records = np.ascontiguousarray(packed).view(_RECORD).reshape(-1)
    columns = {name: records[name] for name in _RECORD.names}
    for name in _FLAGS:
        columns[name] = columns[name].astype(bool)
    return StreamOutput(stamps_ns=stamps_ns, measured=measured, **columns)


_EMPTY = _unpack(np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, _PACKED_WIDTH)))
for _array in _EMPTY:  # shared by every update without estimates
    _array.flags.writeable = False

ChunkFunction = Callable[[np.ndarray], Array]

#: Last row of a chunk buffer: the prior (mean 7, covariance 49 row-major), then the count of real rows.
_PRIOR = slice(0, 7 + 49)
_COUNT = 7 + 49
assert _PACKED_WIDTH > _COUNT, "a chunk buffer's row must hold the prior and the count"


def make_chunk_filter(model: Model, noise: FilterNoise, sample_period: float) -> ChunkFunction:
    """Jitted `buffer (C + 1, width) -> buffer`: the EKF over C rows, one compiled loop, one array each way.

    In: rows 0..C-1 hold the measurements eta (m) in columns 0-2 (NaN: predict only);
    row C holds the prior and, in column `_COUNT`, the number of real rows. Out: row k
    holds the packed results of row k (`_LAYOUT`), row C the prior after the last real
    row. Each row is the EKF step (`update`, then `predict_with_rate`) and the filtered
    signals of `estimate.signals` (acceleration and its covariance from the first RK4
    stage of the prediction, contact forces and their covariance through the forces'
    Jacobian), innovation and NIS. Rows at and after the
    count are padding (the compiled shape never changes): skipped, their result rows are
    NaN and the prior carried on is the one after the last real row. The results equal
    `make_estimator`'s to round-off (the acceleration Jacobian comes from reverse- instead
    of forward-mode differentiation). One compilation per C.

    Everything stays inside the loop body (no LAPACK call: the 3 x 3 inverse is closed
    form) so that XLA's CPU backend compiles the whole loop into one function (the
    small-loop option `core.xla` sets). One array each way because each argument and
    result costs dispatch time: called every 1.6 ms as the node does, a chunk of 16 rows
    takes 7-16 % less CPU than with the prior, rows and count as separate arrays
    (bench/chunk_dispatch.py).
    """
    R, Q = jnp.diag(noise.measurement), jnp.diag(noise.process)
    measure = model_measurement(model)

    def row(prior: Belief, eta: Array) -> tuple[Belief, Array]:
        filtered, innovation, S, used = update(prior, eta, R, measure)
        next_prior, _, rate, rate_jacobian = predict_with_rate(model, filtered, Q, sample_period)
        J = rate_jacobian[4:]
        forces, J_force = contact_forces_and_jacobian(model, filtered.mean)
        nis = innovation @ (_inverse_3x3(S) @ innovation)  # NaN where the sample was not used
        packed = jnp.concatenate(
            [
                filtered.mean,
                filtered.cov.reshape(49),
                rate[4:],
                (J @ filtered.cov @ J.T).reshape(9),
                contact_force_xyz(forces),
                (J_force @ filtered.cov @ J_force.T).reshape(9),
                jnp.stack([forces.F_n, forces.F_t, forces.F_z]),
                jnp.stack([forces.radial_contact, forces.axial_contact]).astype(eta.dtype),
                innovation,
                S.reshape(9),
                nis[None],
                used[None].astype(eta.dtype),
            ]
        )
        return next_prior, packed

    def run(buffer: Array) -> Array:
        last = buffer.shape[0] - 1
        count = buffer[last, _COUNT]

        def real(carried: Array, eta: Array) -> tuple[Array, Array]:
            next_prior, packed = row(Belief(carried[:7], carried[7:_COUNT].reshape(7, 7)), eta)
            return jnp.concatenate([next_prior.mean, next_prior.cov.reshape(49)]), packed

        def padding(carried: Array, eta: Array) -> tuple[Array, Array]:
            return carried, jnp.full(_PACKED_WIDTH, jnp.nan, eta.dtype)

        def body(carried: Array, inputs: tuple[Array, Array]) -> tuple[Array, Array]:
            eta, k = inputs
            # a branch, not a select: padding rows cost nothing (a block of 19 in a chunk of 32: 360 -> 258 us)
            return jax.lax.cond(k < count, real, padding, carried, eta)

        # scan's outputs are written in place; updating the buffer row by row in a loop made XLA copy it per row
        carried, rows = jax.lax.scan(body, buffer[last, _PRIOR], (buffer[:last, :3], jnp.arange(last)))
        return jnp.concatenate([rows, buffer[last].at[_PRIOR].set(carried)[None]])

    return jax.jit(run)


def flat_belief(belief: Belief) -> np.ndarray:
    """(56,) mean and row-major covariance, as the last row of a chunk buffer holds them."""
    return np.concatenate([np.asarray(belief.mean), np.asarray(belief.cov).reshape(49)])


def chunk_buffer(etas: np.ndarray, size: int, prior: np.ndarray) -> np.ndarray:
    """Input of a chunk filter of `size` rows: etas (n <= size, 3) m, NaN padding, the prior (`flat_belief`) and n."""
    buffer = np.zeros((size + 1, _PACKED_WIDTH))
    buffer[: len(etas), :3] = etas
    buffer[len(etas) : size, :3] = np.nan
    buffer[size, _PRIOR] = prior
    buffer[size, _COUNT] = len(etas)
    return buffer


class _Touchdown:
    """Running figures of the touchdown in progress."""

    def __init__(self, onset_stamp_ns: int):
        self.onset_stamp_ns = onset_stamp_ns
        self.end_stamp_ns = onset_stamp_ns
        self.samples = self.missing = self.axial_impacts = self.radial_impacts = 0
        self.peak_axial = self.peak_radial = -math.inf
        self.nis_sum, self.nis_count = 0.0, 0
        self.last_axial = self.last_radial = False
        self.restarts = 0

    def add(self, out: StreamOutput) -> None:
        n = len(out.stamps_ns)
        if n == 0:
            return
        used = out.used
        n_used = int(np.count_nonzero(used))
        self.samples += n
        self.missing += n - n_used
        self.end_stamp_ns = int(out.stamps_ns[-1])
        self.axial_impacts += _rising_edges(out.axial_contact, self.last_axial)
        self.radial_impacts += _rising_edges(out.radial_contact, self.last_radial)
        self.last_axial, self.last_radial = bool(out.axial_contact[-1]), bool(out.radial_contact[-1])
        if n_used:  # predict-only rows (gaps, refused values) are left out of the peaks, as offline
            self.peak_axial = max(self.peak_axial, float(out.F_z[used].max()))
            fx, fy = out.force_xyz[used, 0], out.force_xyz[used, 1]
            self.peak_radial = max(self.peak_radial, math.sqrt(float((fx * fx + fy * fy).max())))
        if n_used:  # NIS is NaN exactly where the measurement was not used
            self.nis_sum += float(out.nis[used].sum())
            self.nis_count += n_used

    def summary(self, end_reason: str) -> TouchdownSummary:
        return TouchdownSummary(
            onset_stamp_ns=self.onset_stamp_ns,
            end_stamp_ns=self.end_stamp_ns,
            samples=self.samples,
            missing_samples=self.missing,
            axial_impacts=self.axial_impacts,
            radial_impacts=self.radial_impacts,
            peak_axial_force=self.peak_axial if self.nis_count else math.nan,
            peak_radial_force=self.peak_radial if self.nis_count else math.nan,
            mean_nis=self.nis_sum / self.nis_count if self.nis_count else math.nan,
            end_reason=end_reason,
            filter_restarts=self.restarts,
        )


def _rising_edges(flags: np.ndarray, previous: bool) -> int:
    """False -> True transitions in flags, the element before flags[0] being `previous`."""
    return int(np.count_nonzero(flags[1:] & ~flags[:-1])) + int(bool(flags[0]) and not previous)


def _run_lengths(inside: np.ndarray, carried: int) -> np.ndarray:
    """Length of the run of True ending at each element, continuing a run of `carried` before."""
    index = np.arange(len(inside))
    last_out = np.maximum.accumulate(np.where(inside, -1, index))
    return np.where(inside, np.where(last_out >= 0, index - last_out, carried + index + 1), 0)


class StreamingEstimator:
    """Live touchdown estimator: `push` samples (stamp ns, x, y, z in m), get estimates and events.

    Compiles the EKF chunk for each of `settings.chunk_sizes` on first use; call
    `warm_up()` to compile them all before the first sample arrives.
    """

    def __init__(
        self, model: Model, noise: FilterNoise, settings: StreamSettings, chunk_filter: ChunkFunction | None = None
    ):
        """`chunk_filter`: a `make_chunk_filter` of the same model, noise and period, to share its compilations."""
        if not settings.chunk_sizes or min(settings.chunk_sizes) < 1:
            raise ValueError("chunk_sizes must be positive lengths")
        self.model, self.noise, self.settings = model, noise, settings
        self._sizes = tuple(sorted(set(int(c) for c in settings.chunk_sizes)))
        self._chunk = chunk_filter or make_chunk_filter(model, noise, settings.sample_period)
        self._period_ns = settings.sample_period * 1e9
        self._max_gap_rows = settings.max_gap / settings.sample_period
        self._policy = settings.policy
        self._rail_run, self._rail_last = np.zeros(3, np.int64), np.full(3, np.nan)
        self._initial_cov = np.asarray(noise.initial)
        self.counts = StreamCounts()
        self._events: list[StreamEvent] = []
        self._outputs: list[StreamOutput] = []
        self._clear_grid()
        self._start_waiting()

    # ---------------------------------------------------------------- public
    @property
    def phase(self) -> str:
        """waiting (collecting the levitated window), levitated, or touchdown."""
        return self._phase

    @property
    def levitated_reference(self) -> np.ndarray | None:
        """Levitated mean (x, y, z), m; z as `detect_drop` computes it. None while waiting."""
        return None if self._reference is None else self._reference.copy()

    @property
    def drop_level(self) -> float | None:
        """z, m, below which a sample reveals a drop (levitated mean minus the threshold);
        None unless levitated."""
        if self._phase != LEVITATED or self._reference is None:
            return None
        return float(self._reference[2] - self.settings.drop_threshold)

    def warm_up(self) -> None:
        """Compile the EKF chunk of every configured length (a few seconds each, cached by JAX)."""
        prior = flat_belief(initial_belief(np.zeros((1, 3)), self._initial_cov, samples=1))
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

    def push_one(self, stamp_ns: int, x: float, y: float, z: float) -> StreamUpdate:
        """One sample (stamp ns, displacement m)."""
        return self.push(np.array([stamp_ns], np.int64), np.array([[x, y, z]]))

    def finish(self) -> StreamUpdate:
        """End of stream: filter what is still held and close a touchdown in progress."""
        if self._phase == TOUCHDOWN:
            self._run_filter(final=True)
            self._end_touchdown("end_of_stream")
        return self._collect()

    # ---------------------------------------------------------------- grid placement
    def _clear_grid(self) -> None:
        self._origin: int | None = None  # stamp of grid row 0, ns
        self._last_index = -1  # grid index of the last placed sample
        self._refused_streak = 0  # consecutive out-of-order / off-grid samples

    def _ingest(self, stamps: np.ndarray, xyz: np.ndarray) -> None:
        """Classify samples, place the accepted ones on the grid, hand the rows on; reset at clock jumps."""
        if self._origin is not None and len(stamps) and self._place_in_order(stamps, xyz):
            return
        start = 0
        while start < len(stamps):
            if self._origin is None:
                self._origin, self._last_index = int(stamps[start]), -1
            s, v = stamps[start:], xyz[start:]
            offsets = (s - self._origin) / self._period_ns
            index = np.rint(offsets).astype(np.int64)
            on_grid = np.abs(offsets - index) <= self.settings.grid_tolerance
            # Highest placed index before each sample (accepted samples strictly increase).
            candidates = np.where(on_grid, index, np.iinfo(np.int64).min)
            before = np.maximum.accumulate(np.concatenate([[self._last_index], candidates[:-1]]))
            back_jump = (before - index) > self._max_gap_rows
            forward_jump = (index - before) > self._max_gap_rows
            # a hole the policy does not bridge (before < 0: the first sample of a grid)
            long_gap = (before >= 0) & ((index - before - 1) > self._policy.bridge_rows) & ~forward_jump
            out_of_order = (index < before) & ~back_jump
            duplicate = on_grid & (index == before)
            off_grid = ~on_grid & (index >= before) & ~forward_jump & ~long_gap
            refused = out_of_order | off_grid
            streak = _run_lengths(refused, self._refused_streak)
            resync = refused & (streak >= self.settings.resync_after)
            event = back_jump | forward_jump | long_gap | resync
            stop = int(np.argmax(event)) if event.any() else len(s)

            accepted = on_grid[:stop] & (index[:stop] > before[:stop])
            self.counts.duplicate += int(np.count_nonzero(duplicate[:stop]))
            self.counts.out_of_order += int(np.count_nonzero(out_of_order[:stop]))
            self.counts.off_grid += int(np.count_nonzero(off_grid[:stop]))
            self._refused_streak = int(streak[stop - 1]) if stop else self._refused_streak
            if accepted.any():
                self._place(index[:stop][accepted], v[:stop][accepted])
            if stop == len(s):
                return
            jump_s = (int(s[stop]) - (self._origin + before[stop] * self._period_ns)) / 1e9
            if back_jump[stop]:
                self.counts.clock_jump_backward += 1  # the stream starts over (a replay, a restarted sensor)
                self._reset("clock_jump", int(s[stop]), f"stamp jumped back by {-jump_s:.4g} s (more than max_gap)")
            elif forward_jump[stop]:
                self.counts.clock_jump_forward += 1
                self._restart("clock_jump", int(s[stop]), f"stamp jumped forward by {jump_s:.4g} s (more than max_gap)")
            elif long_gap[stop]:
                self.counts.long_gaps += 1
                self._restart("gap", int(s[stop]), f"no sample for {jump_s:.4g} s (more than bridge_gap)")
            else:
                self.counts.resyncs += 1
                self._reset("resync", int(s[stop]), f"{self.settings.resync_after} refused stamps in a row")
            start += stop  # the sample that triggered the reset starts the new grid

    def _place_in_order(self, stamps: np.ndarray, xyz: np.ndarray) -> bool:
        """Fast path of the usual case: every sample on the next grid point. False if it does not apply."""
        offsets = (stamps - self._origin) / self._period_ns
        index = np.rint(offsets).astype(np.int64)
        if index[0] != self._last_index + 1 or index[-1] != self._last_index + len(index):
            return False
        if len(index) > 1 and not (np.diff(index) == 1).all():
            return False
        if not (np.abs(offsets - index) <= self.settings.grid_tolerance).all():
            return False
        self._refused_streak = 0
        self._place(index, xyz)
        return True

    def _place(self, index: np.ndarray, values: np.ndarray) -> None:
        """Grid rows from the last placed index + 1 to index[-1]: values where given, NaN elsewhere."""
        if index[-1] - self._last_index != len(index):  # not contiguous: gaps
            previous = np.concatenate([[self._last_index], index[:-1]])
            skipped = index - previous - 1
            self.counts.gaps += int(np.count_nonzero(skipped))
            self.counts.missing_samples += int(skipped.sum())
        self.counts.accepted += len(index)

        clean_limit = min(self.settings.millimetre_limit, 0.5 * self.settings.sensor_range)
        if np.all(np.abs(values) < clean_limit):  # finite and well inside the range (never pinned): the usual case
            self._rail_run[:] = 0
            self._rail_last = values[-1].copy()
            self._emit_rows(index, values)
            return
        flags = value_flags(values, self._policy, self._rail_run, self._rail_last)
        self._rail_run, self._rail_last = flags.rail_run, flags.last
        self.counts.non_finite += int(np.count_nonzero(flags.non_finite))
        self.counts.millimetre += int(np.count_nonzero(flags.millimetre))
        self.counts.saturated += int(np.count_nonzero(flags.saturated))
        values = values.copy()
        values[~np.isfinite(values)] = np.nan  # partial rows keep their finite components, as offline
        values[flags.millimetre | flags.saturated] = np.nan
        if flags.millimetre.any() and self._phase != TOUCHDOWN:
            # values in other units: the levitated reference (made of the same stream) cannot be trusted
            self._start_waiting()
        self._emit_rows(index, values)

    def _emit_rows(self, index: np.ndarray, values: np.ndarray) -> None:
        """Grid rows from the last placed index + 1 to index[-1] (NaN where no value) on to the phases."""
        first = self._last_index + 1
        rows = np.arange(first, index[-1] + 1)
        etas = np.full((len(rows), 3), np.nan)
        etas[index - first] = values
        stamps = self._origin + np.rint(rows * self._period_ns).astype(np.int64)
        self._last_index = int(index[-1])
        self.counts.rows += len(rows)
        self._advance(stamps, etas)

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
        """Levitated reference over the first window rows, then the first crossing (`detect_drop`)."""
        settings = self.settings
        buffer_stamps = np.concatenate([self._buffer_stamps, stamps])
        buffer_etas = np.concatenate([self._buffer_etas, etas])
        while self._reference is None and len(buffer_etas) >= settings.window_samples:
            window = buffer_etas[: settings.window_samples]
            if not window_is_clean(window, settings.drop_threshold):  # saturated, pinned, other units, missing
                self.counts.reference_refused += 1
                unusable = np.flatnonzero(~np.isfinite(window).all(axis=1))
                drop = int(unusable[-1]) + 1 if unusable.size else max(1, settings.window_samples // 2)
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
                StreamEvent("levitated", int(buffer_stamps[settings.window_samples - 1]),
                            f"levitated mean z {reference_z * 1e6:.1f} um", reference_z)
            )
            break
        if self._reference is not None:
            z = buffer_etas[:, 2]
            below = np.flatnonzero(np.isfinite(z) & (z < self.drop_level))
            if below.size:
                # the buffer keeps fall_samples rows before the new ones once levitated (the phase's start or a
                # refused window's end before that): the onset never reaches before it
                onset = max(0, int(below[0]) - settings.fall_samples)
                self._start_touchdown(int(buffer_stamps[onset]))
                rest = buffer_stamps[onset:], buffer_etas[onset:]
                self._buffer_stamps, self._buffer_etas = np.empty(0, np.int64), np.empty((0, 3))
                return rest
            keep_from = max(0, len(buffer_etas) - settings.fall_samples)
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
        self._touchdown = _Touchdown(onset_stamp_ns)
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
        runs = _run_lengths(inside & counting, self._band_run)
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
        runs = bridge_rows(usable, self._policy, self._unusable_run)
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
        self._clear_grid()
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
        self._clear_grid()
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
            self._belief = flat_belief(initial_belief(etas, self._initial_cov, samples=samples))

        packed_parts = []
        belief, done, largest = self._belief, 0, self._sizes[-1]
        while done < len(etas):
            count = min(len(etas) - done, largest)
            size = next(c for c in self._sizes if c >= count)
            result = np.asarray(self._chunk(chunk_buffer(etas[done : done + count], size, belief)))
            packed_parts.append(result[:count])
            belief = result[size, _PRIOR]
            done += count
        self._belief = belief
        out = _unpack(stamps, etas, np.concatenate(packed_parts))
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
