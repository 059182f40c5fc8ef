"""Error measures of estimates against measurements or truth."""
from __future__ import annotations

import numpy as np

from touchdown_ros.core.impacts import MERGE_GAP, impact_spans


def rmse(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Root mean square error per column over the rows where both are finite (paper eq. 19)."""
    estimate, reference = np.asarray(estimate, float), np.asarray(reference, float)
    error = estimate - reference
    finite = np.isfinite(error)
    return np.sqrt(np.sum(np.where(finite, error, 0.0) ** 2, axis=0) / np.maximum(finite.sum(axis=0), 1))


def relative_peak_error(estimate: np.ndarray, reference: np.ndarray) -> float:
    """(max |estimate| - max |reference|) / max |reference|."""
    peak = np.nanmax(np.abs(reference))
    return float((np.nanmax(np.abs(estimate)) - peak) / peak)


def impacts(force: np.ndarray, threshold: float, merge_gap: int = MERGE_GAP) -> list[tuple[int, int, int, float]]:
    """Impacts as (start, end, peak index, peak force): `core.impacts` of force > threshold (N)."""
    force = np.asarray(force)
    result = []
    for start, end in zip(*impact_spans(force > threshold, merge_gap)):
        peak = int(start) + int(np.argmax(force[start:end]))
        result.append((int(start), int(end), peak, float(force[peak])))
    return result


def peak_errors_per_impact(
    estimated: np.ndarray, true: np.ndarray, threshold: float, merge_gap: int = MERGE_GAP, margin: int = 5
) -> list[tuple[int, float, float]]:
    """For each true impact: (impact number from 1, true peak N, relative error of the estimated peak nearby)."""
    errors = []
    for number, (start, end, _, peak) in enumerate(impacts(true, threshold, merge_gap), start=1):
        window = estimated[max(0, start - margin) : end + margin]
        errors.append((number, peak, float((np.max(window) - peak) / peak)))
    return errors
