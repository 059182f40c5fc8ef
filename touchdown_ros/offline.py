"""Offline estimation of recorded drops: bag in, core estimate, output bag and summary out."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from touchdown_ros.core.effects import Effects, gates_for
from touchdown_ros.core.estimate import Estimate, Estimator, detect_drop, make_estimator, to_grid
from touchdown_ros.core.metrics import relative_peak_error, rmse
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.bags import CONDITION_PREFIX, TopicSeries, read_conditions, read_displacement, read_truth, write_bag
from touchdown_ros.io.config import Config


class NoDropError(ValueError):
    """The record shows no touchdown."""


@dataclass(frozen=True)
class AlignedTruth:
    """Truth signals at the estimate's stamps (rows without truth are NaN)."""

    velocity: np.ndarray  # (N, 3) m/s
    acceleration: np.ndarray  # (N, 3) m/s^2
    contact_force: np.ndarray  # (N, 3) N


@dataclass(frozen=True)
class BagEstimate:
    """One bag's estimate with what it was compared against."""

    path: Path
    estimate: Estimate
    truth: AlignedTruth | None
    summary: dict[str, Any]


def estimator_for(config: Config, coeffs: Coefficients | None = None, effects: Effects | None = None) -> Estimator:
    """The compiled estimator of a rig (constant model unless coefficients are given; the rig's
    effects unless others, e.g. a coefficient file's, are given)."""
    return make_estimator(config.model(coeffs, effects), config.noise, config.sample_period)


def bag_effects(config: Config, path: str | Path, effects: Effects) -> Effects:
    """`effects` switched on or off for one bag by its recorded conditions (effects.when.*)."""
    return effects.with_gates(gates_for(effects, read_conditions(path))) if effects else effects


def estimate_bag(
    config: Config,
    path: str | Path,
    estimator: Estimator,
    coeffs: Coefficients | None = None,
    effects: Effects | None = None,
) -> BagEstimate:
    """Read a bag's displacements, find the drop and estimate everything after it, with the
    estimator's model or other coefficients / effects; effects gated by the bag's conditions."""
    path = Path(path)
    effects = estimator.model.effects if effects is None else effects
    gated = bag_effects(config, path, effects)
    if coeffs is None and all(g == 1.0 for g in gated.gates) and effects is estimator.model.effects:
        gated = None  # the compiled model as it is
    series = read_displacement(path, config.topics.displacement)
    grid = to_grid(series.stamps_ns, series.xyz, config.sample_period)
    onset = detect_drop(
        grid.etas[:, 2], config.sample_period, config.drop.threshold, config.drop.levitated_window, config.rig.gravity
    )
    if onset is None:
        raise NoDropError(
            f"{path}: no touchdown found (z never falls {config.drop.threshold * 1e6:.0f} um below its levitated mean)"
        )
    estimate = estimator(grid.stamps_ns, grid.etas, onset, grid.missing, coeffs=coeffs, effects=gated)
    truth = _aligned_truth(path, config, estimate.stamps_ns)
    return BagEstimate(path, estimate, truth, summarise(estimate, truth, config))


def _aligned_truth(path: Path, config: Config, stamps_ns: np.ndarray) -> AlignedTruth | None:
    truth = read_truth(
        path,
        velocity_topic=config.topics.truth_velocity,
        acceleration_topic=config.topics.truth_acceleration,
        contact_force_topic=config.topics.truth_contact_force,
    )
    if truth is None:
        return None
    rows = np.searchsorted(truth.stamps_ns, stamps_ns)
    rows = np.minimum(rows, len(truth.stamps_ns) - 1)
    matched = truth.stamps_ns[rows] == stamps_ns

    def take(values: np.ndarray) -> np.ndarray:
        return np.where(matched[:, None], values[rows], np.nan)

    return AlignedTruth(take(truth.velocity), take(truth.acceleration), take(truth.contact_force))


def summarise(estimate: Estimate, truth: AlignedTruth | None, config: Config) -> dict[str, Any]:
    """Per-bag figures: eq. 19 RMSE per axis, prediction error, filter health, errors against truth."""
    filtered, smoothed = estimate.filtered, estimate.smoothed
    radial_force = np.hypot(filtered.force_xyz[:, 0], filtered.force_xyz[:, 1])
    summary: dict[str, Any] = {
        "samples": int(len(estimate.stamps_ns)),
        "missing_samples": int(estimate.missing),
        "onset_stamp_ns": int(estimate.stamps_ns[0]),
        "rmse_displacement_m": rmse(filtered.state[:, :3], estimate.measured).tolist(),
        "rmse_prediction_m": rmse(estimate.predicted_output, estimate.measured).tolist(),
        "mean_nis": float(np.nanmean(estimate.nis)),
        "peak_axial_force_N": float(np.max(filtered.F_z)),
        "peak_radial_force_N": float(np.max(radial_force)),
    }
    if truth is not None:
        true_radial = np.hypot(truth.contact_force[:, 0], truth.contact_force[:, 1])
        summary["truth"] = {
            "rmse_velocity_mps": rmse(filtered.state[:, 4:], truth.velocity).tolist(),
            "rmse_velocity_smoothed_mps": rmse(smoothed.state[:, 4:], truth.velocity).tolist(),
            "rmse_acceleration_mps2": rmse(filtered.acceleration, truth.acceleration).tolist(),
            "rmse_contact_force_N": rmse(filtered.force_xyz, truth.contact_force).tolist(),
            "rmse_contact_force_smoothed_N": rmse(smoothed.force_xyz, truth.contact_force).tolist(),
            "peak_axial_force_true_N": float(np.nanmax(truth.contact_force[:, 2])),
            "peak_radial_force_true_N": float(np.nanmax(true_radial)),
            "peak_axial_force_error": relative_peak_error(filtered.F_z, truth.contact_force[:, 2]),
            "peak_radial_force_error": relative_peak_error(radial_force, true_radial),
        }
    return summary


def estimate_topics(estimate: Estimate, config: Config) -> list[TopicSeries]:
    """The `/touchdown/...` topics of an estimate, as the live node publishes them."""
    topics, frame = config.topics, config.topics.frame_id
    filtered, stamps = estimate.filtered, estimate.stamps_ns
    state, cov = np.asarray(filtered.state), np.asarray(filtered.state_cov)
    return [
        TopicSeries(topics.displacement_estimate, "PointStamped", stamps, state[:, :3], frame_id=frame),
        TopicSeries(topics.velocity, "TwistWithCovarianceStamped", stamps, state[:, 4:], cov[:, 4:, 4:], frame_id=frame),
        TopicSeries(
            topics.acceleration,
            "AccelWithCovarianceStamped",
            stamps,
            np.asarray(filtered.acceleration),
            np.asarray(filtered.acceleration_cov),
            frame_id=frame,
        ),
        TopicSeries(topics.contact_force, "WrenchStamped", stamps, np.asarray(filtered.force_xyz), frame_id=frame),
    ]


def write_estimate_bag(result: BagEstimate, config: Config, out: Path, overwrite: bool = False) -> Path:
    """Write the estimate topics of one bag to a rosbag2 MCAP directory."""
    write_bag(out, estimate_topics(result.estimate, config), overwrite=overwrite)
    return out


def conditions_of(condition) -> dict[str, str]:
    """A Table 1 row as the bag's `condition.*` custom data (what an experimenter logs)."""
    return {
        f"{CONDITION_PREFIX}{name}": (str(value).lower() if isinstance(value, bool) else str(value))
        for name, value in vars(condition).items()
    }


def write_drop_bag(record, config: Config, out: Path, overwrite: bool = False) -> Path:
    """A simulated drop as a bag: `/amb/displacement` plus the `/truth/...` topics, and the
    experiment's conditions (brake, axial load, ball) in metadata.yaml (not for a bare .mcap)."""
    topics, frame, stamps = config.topics, config.topics.frame_id, record.stamps_ns
    write_bag(
        out,
        [
            TopicSeries(topics.displacement, "PointStamped", stamps, record.measured, frame_id=frame),
            TopicSeries(topics.truth_velocity, "Vector3Stamped", stamps, record.velocity, frame_id=frame),
            TopicSeries(topics.truth_acceleration, "Vector3Stamped", stamps, record.acceleration, frame_id=frame),
            TopicSeries(topics.truth_contact_force, "WrenchStamped", stamps, record.contact_force, frame_id=frame),
        ],
        overwrite=overwrite,
        custom_data=None if Path(out).suffix == ".mcap" else conditions_of(record.condition),
    )
    return out
