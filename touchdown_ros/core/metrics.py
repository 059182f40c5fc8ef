"""Error measures of estimates against measurements or truth."""
from __future__ import annotations

import numpy as np


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
