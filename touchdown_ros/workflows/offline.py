"""Offline estimation of recorded drops: bag in, core estimate, output bag and summary out."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import jax
import numpy as np

from touchdown_ros.core.calibration import Q_BLOCKS, Q_NAMES, q_factors
from touchdown_ros.core.effects import Effects, gates_for
from touchdown_ros.core.estimate import (
    Estimate,
    Estimator,
    SignalSet,
    force_std,
    make_estimator,
)
from touchdown_ros.core.input_policy import (
    InputPolicy, RecordInput, Segment, split_record, threshold_for_window, window_spread,
)
from touchdown_ros.core.metrics import relative_peak_error, rmse
from touchdown_ros.core.selection import COLLINEAR_MARGIN
from touchdown_ros.core.training import errors_of_innovations
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.bags import (
    BagError,
    TopicSeries,
    Truth,
    read_conditions,
    read_displacement,
    read_truth,
    write_bag,
)
from touchdown_ros.io.coefficients import load_coefficients
from touchdown_ros.io.config import Config
from touchdown_ros.io.estimate_topics import estimate_series


#: Which estimate the offline tools write: the RTS smoother's (uses the whole record, the default)
#: or the EKF's (what the live node can compute: each sample from the samples up to it).
SMOOTHED, FILTERED = "smoothed", "filtered"
ANSWERS = (SMOOTHED, FILTERED)


class NoDropError(ValueError):
    """The record shows no touchdown; `threshold` (m), where not None, is the drop_detection.threshold that would
    take its levitated window."""

    def __init__(self, message: str, threshold: float | None = None):
        super().__init__(message)
        self.threshold = threshold


def check_answer(answer: str) -> str:
    """`answer` if it is one of ANSWERS; ValueError otherwise."""
    if answer not in ANSWERS:
        raise ValueError(f"estimate {answer!r}: expected one of {', '.join(ANSWERS)}")
    return answer


def answer_of(estimate: Estimate, answer: str) -> SignalSet:
    """The signals of `estimate` that `answer` (smoothed | filtered) names."""
    return estimate.smoothed if check_answer(answer) == SMOOTHED else estimate.filtered


@dataclass(frozen=True)
class BagEstimate:
    """One bag's estimate with what it was compared against."""

    path: Path
    estimate: Estimate
    truth: Truth | None  # on the estimate's stamps (rows without truth are NaN)
    summary: dict[str, Any]
    answer: str = SMOOTHED  # which of estimate.smoothed / .filtered is written and summarised
    restarts: tuple[int, ...] = ()  # rows of the estimate where the filter restarted after a gap

    @property
    def written(self) -> SignalSet:
        """The signals written to the output bag and summarised (`answer`)."""
        return answer_of(self.estimate, self.answer)


def estimator_for(
    config: Config, coeffs: Coefficients | None = None, effects: Effects | None = None, answer: str = SMOOTHED
) -> Estimator:
    """The compiled estimator of a rig (constant model unless coefficients are given; the rig's
    effects unless others, e.g. a coefficient file's, are given) for the `answer` it is read for:
    the smoothed one with the offline process noise (`Config.offline_noise`), the filtered one with
    the fitted Q, adapted to the innovations as the live node adapts it (`Config.live_adaptation`). The
    force band adds the coefficient file's measured model force error in contact (`Config.model_variance`), else
    the process noise read as a force."""
    smoothed = check_answer(answer) == SMOOTHED
    noise = config.offline_noise() if smoothed else config.noise
    return make_estimator(config.model(coeffs, effects), noise, config.sample_period, config.model_variance(),
                          None if smoothed else config.live_adaptation)


def bag_effects(config: Config, path: str | Path, effects: Effects) -> Effects:
    """`effects` switched on or off for one bag by its recorded conditions (effects.when.*)."""
    return effects.with_gates(gates_for(effects, read_conditions(path))) if effects else effects


def estimate_bag(
    config: Config,
    path: str | Path,
    estimator: Estimator,
    coeffs: Coefficients | None = None,
    effects: Effects | None = None,
    answer: str = SMOOTHED,
    fit_noise: bool | None = None,
) -> BagEstimate:
    """Read a bag's displacements, find the drop and estimate everything after it, with the
    estimator's model or other coefficients / effects; effects gated by the bag's conditions.
    The summary describes the `answer` (smoothed | filtered) estimate. `fit_noise`: the smoothed estimate
    with Q's blocks scaled as the bag's own likelihood asks (`bag_noise`; default: `filter.bag_process_noise` where
    Q was fitted on training bags); False where models are compared on the same noise (the workbench)."""
    check_answer(answer)
    path = Path(path)
    effects = estimator.model.effects if effects is None else effects
    gated = bag_effects(config, path, effects)
    if coeffs is None and all(g == 1.0 for g in gated.gates) and effects is estimator.model.effects:
        gated = None  # the compiled model as it is
    record = read_record(config, path)
    fit_noise = config.bag_process_noise and config.noise_fitted if fit_noise is None else fit_noise
    noise = BagNoise()
    if fit_noise and answer == SMOOTHED:
        noise = bag_noise(config, record, estimator, path, coeffs, gated)
    scale = noise.process_scale(len(estimator.noise.process))
    estimate, restarts = estimate_record(config, record, estimator, path, coeffs, gated, scale)
    truth = bag_truth(config, path, estimate.stamps_ns)
    summary = summarise(estimate, truth, config, answer)
    summary["input"] = input_summary(record, restarts)
    summary["process_noise_factors"] = noise.as_dict()
    if noise.fitted_mean_nis is not None:  # beside mean_nis, the NIS under the Q the estimate filtered with
        summary["mean_nis_fitted_q"] = noise.fitted_mean_nis
    return BagEstimate(path, estimate, truth, summary, answer, restarts)


#: Factors on a block of Q (`core.calibration.Q_BLOCKS`: radial, axial) that a bag's own likelihood is asked about
#: for its offline estimate: 4, 16 ... 16384, then half and twice the best of them (docs/calibration.md, "Q from the
#: bag's own likelihood").
BAG_NOISE_FACTORS = tuple(4.0**k for k in range(1, 8))


@dataclass(frozen=True)
class BagNoise:
    """The factors on Q's blocks (radial, axial) of one bag's offline estimate, and for each block the best factor
    tried and how much it lowers the bag's -2 ln L against the factors before it (taken where that is at least
    COLLINEAR_MARGIN)."""

    factors: tuple[float, ...] = (1.0,) * len(Q_BLOCKS)
    best: tuple[float, ...] = (1.0,) * len(Q_BLOCKS)
    falls: tuple[float, ...] = (0.0,) * len(Q_BLOCKS)
    fitted_mean_nis: float | None = None  # the bag's mean NIS under the fitted Q, fixed; None: not asked

    def process_scale(self, size: int, relative: float = 1.0) -> np.ndarray:
        """(size,) factors on the diagonal of Q (a spinning ring's speed: 1), times `relative`."""
        return relative * np.asarray(q_factors(np.log(np.asarray(self.factors)), size))

    def as_dict(self) -> dict[str, dict[str, float]]:
        return {
            name: {"factor": f, "best_factor_tried": b, "minus_two_log_likelihood_fall": round(fall, 2)}
            for name, f, b, fall in zip(Q_NAMES, self.factors, self.best, self.falls)
        }


def bag_noise(
    config: Config,
    record: RecordInput,
    estimator: Estimator,
    source: str | Path = "",
    coeffs: Coefficients | None = None,
    effects: Effects | None = None,
) -> BagNoise:
    """Q for one bag's offline estimate: each block of the fitted Q (the live filter's) scaled, one block after the
    other, by the factor (BAG_NOISE_FACTORS, then half and twice the best) under which the bag's displacements are
    most likely, where that lowers its -2 ln L by COLLINEAR_MARGIN or more (a drop unlike the training drops, e.g.
    bouncing where they rolled: the model errs more on it than the fitted Q allows); else the fitted Q. The estimator
    filters with the offline Q (`Config.offline_noise`), the fitted one times `filter.smoothing_noise_scale`, which
    the factors scale in turn."""
    size, segments = len(estimator.noise.process), record_segments(config, record, source)
    fitted, measurement = 1.0 / config.smoothing_noise_scale, np.asarray(estimator.noise.measurement)

    def innovations(noise: BagNoise) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per segment: the innovations (N, 3), their covariances (N, 3, 3) and which are valid, under the fitted Q
        times `noise`'s factors."""
        parts = []
        for segment, start, _, start_time in segments:
            innovation, S = estimator.innovations(segment.etas, start, coeffs, effects, start_time,
                                                  noise.process_scale(size, fitted))
            parts.append((innovation, S, np.isfinite(innovation).all(axis=1)))
        return parts

    def minus_two_log_l(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> float:
        return sum(float(np.sum(errors_of_innovations(e, S, measurement, valid, "nll"))) for e, S, valid in parts)

    as_fitted = innovations(BagNoise())
    fitted_mean_nis = float(np.mean(np.concatenate([
        np.einsum("ni,ni->n", e[valid], np.linalg.solve(S[valid], e[valid][..., None])[..., 0])
        for e, S, valid in as_fitted
    ])))
    factors, best, falls = [1.0] * len(Q_BLOCKS), [], []
    taken = minus_two_log_l(as_fitted)
    for block in range(len(Q_BLOCKS)):  # in turn, each with the factors taken before it
        def with_factor(f: float, block: int = block) -> float:
            return minus_two_log_l(innovations(BagNoise(tuple(factors[:block] + [f] + factors[block + 1:]))))

        tried = {f: with_factor(f) for f in BAG_NOISE_FACTORS}
        coarse = min(tried, key=tried.get)
        tried.update({f: with_factor(f) for f in (coarse / 2.0, coarse * 2.0)})
        most_likely = min(tried, key=tried.get)
        best.append(most_likely)
        falls.append(taken - tried[most_likely])
        if falls[-1] >= COLLINEAR_MARGIN:
            factors[block], taken = most_likely, tried[most_likely]
    return BagNoise(tuple(factors), tuple(best), tuple(falls), fitted_mean_nis)


def force_rmse_against_truth(config: Config, coefficients: str | Path, bags: list[str | Path]) -> float:
    """N, the contact force RMSE (norm over x, y, z) of the smoothed estimates of simulated `bags`
    (their /truth topics) with a coefficient file's model, over all their samples."""
    loaded = load_coefficients(coefficients, config)
    calibrated = loaded.config(config)
    estimator = estimator_for(calibrated, loaded.coeffs, loaded.effects)
    squares = []
    for bag in bags:
        result = estimate_bag(calibrated, bag, estimator, fit_noise=False)  # models compared on the same Q
        if result.truth is None:
            raise ValueError(f"{bag}: no /truth topics to compare the contact force with")
        error = np.asarray(result.estimate.smoothed.force_xyz) - result.truth.contact_force
        squares.append(np.sum(error**2, axis=1))
    return float(np.sqrt(np.nanmean(np.concatenate(squares))))


def record_segments(
    config: Config, record: RecordInput, source: str | Path = ""
) -> list[tuple[Segment, int, int, float]]:
    """The parts of a record under the input policy that are estimated, from its drop onset on: each segment
    after a long gap, clock jump or run of unusable samples with a usable sample after its first row; per part
    (segment, first row, rows without a usable sample, s after the drop onset at the first row)."""
    segment_index, onset = find_onset(record, config, Path(source))
    onset_stamp_ns = int(record.segments[segment_index].stamps_ns[onset])
    parts = []
    for k in range(segment_index, len(record.segments)):
        segment = record.segments[k]
        start = onset if k == segment_index else 0
        if not np.isfinite(segment.etas[start:]).all(axis=1).any():
            continue  # nothing usable to start a filter from
        missing = int(np.count_nonzero(~np.isfinite(segment.etas[start:]).all(axis=1)))
        parts.append((segment, start, missing, (int(segment.stamps_ns[start]) - onset_stamp_ns) * 1e-9))
    return parts


def estimate_record(
    config: Config,
    record: RecordInput,
    estimator: Estimator,
    source: str | Path = "",
    coeffs: Coefficients | None = None,
    effects: Effects | None = None,
    process_scale: np.ndarray | None = None,
) -> tuple[Estimate, tuple[int, ...]]:
    """A record under the input policy estimated from its drop onset on: each segment after a long
    gap, clock jump or run of unusable samples by a filter started afresh from its own data (as the
    live node restarts it). Returns the joined estimate and the rows where the filter restarted.
    `process_scale`: factors on the diagonal of the estimator's Q (default 1)."""
    parts = [
        estimator(segment.stamps_ns, segment.etas, start, missing, coeffs=coeffs, effects=effects,
                  start_time=start_time, process_scale=process_scale)
        for segment, start, missing, start_time in record_segments(config, record, source)
    ]
    restarts = tuple(int(r) for r in np.cumsum([len(p.stamps_ns) for p in parts])[:-1])
    return concatenate_estimates(parts), restarts


def check_bags(config: Config, bags: Sequence[str | Path], training: bool = False) -> None:
    """Check every bag (`check_training_bag` with `training`, else `check_bag`) before any work; where some
    cannot be used, raise one error naming each (the first's type), and where levitated windows were too noisy
    for the threshold, the threshold that takes all of them: a user sees every refusal at once."""
    check = check_training_bag if training else check_bag
    refusals: list[ValueError] = []
    for bag in bags:
        try:
            check(config, bag)
        except ValueError as error:
            refusals.append(error)
    if len(refusals) == 1:
        raise refusals[0]
    if refusals:
        text = f"{len(refusals)} of {len(bags)} bags cannot be used: " + " ".join(
            f"({number}) {error}." for number, error in enumerate(refusals, start=1)
        )
        needed = [e.threshold for e in refusals if isinstance(e, NoDropError) and e.threshold is not None]
        if needed:
            text += (f" The {len(needed)} levitated windows too noisy for drop_detection.threshold are all taken "
                     f"by {_threshold_words(max(needed))}")
        raise type(refusals[0])(text)


def _threshold_words(needed: float) -> str:
    """The drop threshold (m) that takes a levitated window, in words and as the option that gives it."""
    return f"{needed * 1e6:.3g} um or more (-p drop_detection.threshold:={1e-6 * np.ceil(needed * 1e6):.6g})"


def check_bag(config: Config, path: str | Path) -> None:
    """Raise (BagError, GridError or NoDropError, naming the file) unless `estimate_bag` can estimate the
    bag: readable, valid samples, stamps on the grid, a clean levitated window, a drop."""
    path = Path(path)
    find_onset(read_record(config, path), config, path)


def check_training_bag(config: Config, path: str | Path) -> None:
    """`check_bag`, and no gap or clock jump beyond node.bridge_gap (the trainer takes one stretch per
    bag): raise naming the file and the sample."""
    path = Path(path)
    record = read_record(config, path)
    if len(record.segments) > 1:
        if record.breaks:
            index, jump_ns, kind = record.breaks[0]
            where = f"sample {index}: the stamps jump {jump_ns / 1e9:.6g} s ({kind.replace('_', ' ')})"
        else:
            where = f"{record.counts['dropped_rows']} samples in a row without a usable value (saturated or missing)"
        raise BagError(
            f"{path}: {where}, beyond node.bridge_gap = {config.node.bridge_gap:g} s; the trainer needs one "
            "unbroken record per bag: cut the bag there"
        )
    find_onset(record, config, path)


def find_onset(record: RecordInput, config: Config, path: Path) -> tuple[int, int]:
    """(segment, row) of the drop onset in a record under the input policy; the levitated reference
    comes from the first segment's window, which must be clean (`core.input_policy.window_is_clean`)."""
    first, drop = record.segments[0], config.drop_detector()
    window = drop.window_samples
    levitated = first.etas[:window]
    needed = threshold_for_window(levitated)
    if needed is None or needed > drop.threshold or len(first.etas) < window:
        usable_share, spread = window_spread(levitated)
        # a levitated rotor on a noisy sensor (or wobbling under a thrust) may need only a higher threshold
        if needed is not None and not drop.threshold < needed < config.rig.axial_clearance:
            needed = None
        noisy = ("; if the rotor is levitated there, its sensor is this noisy: give drop_detection.threshold "
                 f"{_threshold_words(needed)}" if needed is not None else "")
        raise NoDropError(
            f"{path}: the levitated window (first {drop.levitated_window * 1e3:g} ms) is not clean: "
            f"{100 * usable_share:.0f} % usable samples (saturated, pinned, missing or in other units), "
            f"z spread {spread * 1e6:.3g} um (a third of drop_detection.threshold at most): no levitated reference"
            + noisy,
            threshold=needed,
        )
    reference = drop.reference(first.etas[:, 2])
    for k, segment in enumerate(record.segments):
        onset = drop.onset(segment.etas[:, 2], reference)
        if onset is not None:
            return k, onset
    raise NoDropError(
        f"{path}: no touchdown found (z never falls {config.drop.threshold * 1e6:.0f} um below its levitated mean)"
    )


def concatenate_estimates(parts: list[Estimate]) -> Estimate:
    """One Estimate of consecutive segments' estimates (each filtered and smoothed on its own)."""
    if len(parts) == 1:
        return parts[0]

    def join(*arrays):
        return np.concatenate([np.asarray(a) for a in arrays])

    fields = {
        name: jax.tree.map(join, *[getattr(p, name) for p in parts])
        for name in Estimate._fields
        if name not in ("onset_index", "missing")
    }
    return Estimate(**fields, onset_index=parts[0].onset_index, missing=sum(p.missing for p in parts))


def input_summary(record: RecordInput, restarts: tuple[int, ...]) -> dict[str, Any]:
    """What the input policy did to a record, with counts (summary.json `input`, summary.md)."""
    return {
        **record.counts,
        "filter_restarts": len(restarts),
        "breaks": [{"sample": i, "jump_s": ns / 1e9, "kind": kind} for i, ns, kind in record.breaks],
    }


def read_record(config: Config, path: Path) -> RecordInput:
    """A bag's displacements under the rig's input policy (segments between the breaks it does not bridge)."""
    series = read_displacement(path, config.topics.displacement)
    return split_record(series.stamps_ns, series.xyz, InputPolicy.from_config(config), str(path))


def bag_truth(config: Config, path: Path, stamps_ns: np.ndarray) -> Truth | None:
    """The bag's truth topics on `stamps_ns` (NaN where truth has no sample); None for a real drop test."""
    topics = config.topics
    return read_truth(path, topics.truth_velocity, topics.truth_acceleration, topics.truth_contact_force, stamps_ns)


def summarise(estimate: Estimate, truth: Truth | None, config: Config, answer: str = SMOOTHED) -> dict[str, Any]:
    """Per-bag figures of the `answer` estimate (smoothed | filtered): eq. 19 RMSE per axis, peak
    forces and their 1-sigma, errors against truth; the filter's prediction error and health.

    Keys with `_smoothed` / `_filtered` in their name are of that estimate whichever is written;
    the one-step prediction error and the NIS are the filter's.
    """
    chosen, filtered, smoothed = answer_of(estimate, answer), estimate.filtered, estimate.smoothed
    force, force_cov = np.asarray(chosen.force_xyz), np.asarray(chosen.force_cov)
    radial_force = np.hypot(force[:, 0], force[:, 1])
    measured = np.isfinite(estimate.measured).all(axis=1)  # predict-only rows are left out of the peaks
    peak_axial = int(np.argmax(np.where(measured, force[:, 2], -np.inf)))
    peak_radial = int(np.argmax(np.where(measured, radial_force, -np.inf)))
    summary: dict[str, Any] = {
        "estimate": answer,
        "samples": int(len(estimate.stamps_ns)),
        "missing_samples": int(estimate.missing),
        "predicted_only_samples": int(np.count_nonzero(~measured)),
        "onset_stamp_ns": int(estimate.stamps_ns[0]),
        "rmse_displacement_m": rmse(chosen.state[:, :3], estimate.measured).tolist(),
        "rmse_prediction_m": rmse(estimate.predicted_output, estimate.measured).tolist(),
        "mean_nis": float(np.nanmean(estimate.nis)),
        "process_scale_mean": float(np.mean(estimate.process_scale)),
        "process_scale_max": float(np.max(estimate.process_scale)),
        "peak_axial_force_N": float(force[peak_axial, 2]),
        "peak_radial_force_N": float(radial_force[peak_radial]),
        "peak_axial_force_std_N": float(force_std(force_cov[peak_axial])[2]),
        "peak_radial_force_std_N": float(radial_force_std(force[peak_radial], force_cov[peak_radial])),
    }
    if truth is not None:
        true_radial = np.hypot(truth.contact_force[:, 0], truth.contact_force[:, 1])
        summary["truth"] = {
            "rmse_velocity_mps": rmse(chosen.state[:, 4:7], truth.velocity).tolist(),
            "rmse_velocity_smoothed_mps": rmse(smoothed.state[:, 4:7], truth.velocity).tolist(),
            "rmse_velocity_filtered_mps": rmse(filtered.state[:, 4:7], truth.velocity).tolist(),
            "rmse_acceleration_mps2": rmse(chosen.acceleration, truth.acceleration).tolist(),
            "rmse_contact_force_N": rmse(force, truth.contact_force).tolist(),
            "rmse_contact_force_smoothed_N": rmse(smoothed.force_xyz, truth.contact_force).tolist(),
            "rmse_contact_force_filtered_N": rmse(filtered.force_xyz, truth.contact_force).tolist(),
            "peak_axial_force_true_N": float(np.nanmax(truth.contact_force[:, 2])),
            "peak_radial_force_true_N": float(np.nanmax(true_radial)),
            "peak_axial_force_error": relative_peak_error(
                np.where(measured, np.asarray(chosen.F_z), np.nan), truth.contact_force[:, 2]
            ),
            "peak_radial_force_error": relative_peak_error(np.where(measured, radial_force, np.nan), true_radial),
            "contact_force_within_2_std": within_two_std(
                force, force_cov, truth.contact_force, (force != 0.0) | (truth.contact_force != 0.0)
            ),
            "velocity_within_2_std": within_two_std(
                np.asarray(chosen.state)[:, 4:7], np.asarray(chosen.state_cov)[:, 4:7, 4:7], truth.velocity
            ),
        }
    return summary


def radial_force_std(force_xyz: np.ndarray, force_cov: np.ndarray) -> np.ndarray:
    """1-sigma (N) of the radial force |(F_x, F_y)| from the x/y block of the force covariance,
    linearised along the force's direction; (...,) for force_xyz (..., 3), force_cov (..., 3, 3).
    Where the radial force is zero, the largest standard deviation of the x/y block."""
    xy, block = force_xyz[..., :2], force_cov[..., :2, :2]
    magnitude = np.hypot(xy[..., 0], xy[..., 1])
    direction = xy / np.where(magnitude > 0.0, magnitude, 1.0)[..., None]
    along = np.einsum("...i,...ij,...j->...", direction, block, direction)
    largest = np.linalg.eigvalsh(block)[..., -1]
    return np.sqrt(np.maximum(np.where(magnitude > 0.0, along, largest), 0.0))


def within_two_std(
    values: np.ndarray, cov: np.ndarray, truth: np.ndarray, counted: np.ndarray | bool = True
) -> list[float]:
    """Per sensor axis: the fraction of the samples `counted` ((N, 3) bool, e.g. where the estimate or the
    truth has a contact force on that axis; all by default) with a truth at which it lies within 2 sigma of
    the estimate (95 % if sigma told the whole error); NaN where there are no such samples. values and
    truth (N, 3), cov (N, 3, 3)."""
    involved = np.broadcast_to(counted, np.shape(truth)) & np.isfinite(truth)
    inside = np.abs(values - truth) <= 2.0 * force_std(cov)  # the square root of any covariance's diagonal
    return [float(np.mean(inside[involved[:, i], i])) if involved[:, i].any() else float("nan") for i in range(3)]


def estimate_topics(estimate: Estimate, config: Config, answer: str = SMOOTHED) -> list[TopicSeries]:
    """The `/touchdown/...` topics of an estimate (smoothed or filtered), as the live node publishes
    them (the node's are the filtered ones); the ring's speed with a spinning ring (config.law)."""
    return estimate_series(answer_of(estimate, answer), estimate.stamps_ns, config.topics, config.law)


#: Offline output topic marking the rows without a usable measurement (input policy): Vector3Stamped, one
#: message per such row, 1.0 on each axis that had no usable value (the live node's batched output has `nis`
#: NaN there instead).
PREDICTED_ONLY_TOPIC = "/touchdown/predicted_only"


def predicted_only_topic(estimate: Estimate, config: Config) -> TopicSeries:
    """The predict-only rows of an estimate (gaps bridged, refused values), marked per axis."""
    missing = ~np.isfinite(np.asarray(estimate.measured))
    rows = missing.any(axis=1)
    return TopicSeries(PREDICTED_ONLY_TOPIC, "Vector3Stamped", estimate.stamps_ns[rows], missing[rows].astype(float),
                       frame_id=config.topics.frame_id)


def write_estimate_bag(result: BagEstimate, config: Config, out: Path, overwrite: bool = False) -> Path:
    """Write the estimate topics of one bag (its `answer`: smoothed or filtered) to a rosbag2 MCAP directory,
    with `PREDICTED_ONLY_TOPIC` marking the rows without a usable measurement."""
    topics = estimate_topics(result.estimate, config, result.answer) + [predicted_only_topic(result.estimate, config)]
    write_bag(out, topics, overwrite=overwrite)
    return out
