"""Residual tests of the innovations: whiteness and cross-correlation with velocity and deformation,
with the 99 % band +-2.58 / sqrt(N) of a white sequence (in the spirit of MATLAB `resid`)."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from touchdown_ros.core.diagnostics.breakdown import AXES, deformations
from touchdown_ros.core.types import Rig

#: 99 % two-sided band of a white sequence's normalised autocorrelation: +-Z99 / sqrt(N).
Z99 = 2.576


def autocorrelation(e: np.ndarray, max_lag: int) -> tuple[np.ndarray, float]:
    """Normalised autocorrelation r(0..max_lag) of e (NaN rows dropped) and the 99 % band
    half-width Z99 / sqrt(N) a white sequence stays within."""
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    e = e - e.mean()
    n = len(e)
    denominator = float(np.dot(e, e)) or 1.0
    r = np.array([np.dot(e[: n - lag], e[lag:]) / denominator for lag in range(max_lag + 1)])
    return r, Z99 / np.sqrt(max(n, 1))


def cross_correlation(e: np.ndarray, u: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Normalised cross-correlation r_eu(tau) = sum e(t + tau) u(t) / (|e| |u|) for tau in
    -max_lag..max_lag (rows where both are finite) and the 99 % band of an independent pair."""
    e, u = np.asarray(e, float), np.asarray(u, float)
    ok = np.isfinite(e) & np.isfinite(u)
    e, u = e[ok] - e[ok].mean(), u[ok] - u[ok].mean()
    n = len(e)
    scale = float(np.linalg.norm(e) * np.linalg.norm(u)) or 1.0
    lags = np.arange(-max_lag, max_lag + 1)
    r = np.array(
        [(np.dot(e[lag:], u[: n - lag]) if lag >= 0 else np.dot(e[: n + lag], u[-lag:])) / scale for lag in lags]
    )
    return lags, r, Z99 / np.sqrt(max(n, 1))


def whiteness(e: np.ndarray, max_lag: int) -> dict:
    """Summary of the whiteness test: share of lags 1..max_lag outside the 99 % band and the
    largest |r| (a white residual has about 1 % outside)."""
    r, band = autocorrelation(e, max_lag)
    outside = np.abs(r[1:]) > band
    return {"band": float(band), "outside_share": float(outside.mean()), "max_abs": float(np.max(np.abs(r[1:])))}


def effective_samples(residual: np.ndarray, max_lag: int = 200) -> float:
    """N / (1 + 2 sum of the residual's autocorrelation up to its first non-positive lag)."""
    r, _ = autocorrelation(residual, min(max_lag, max(len(residual) - 2, 1)))
    positive = r[1:]
    stop = np.flatnonzero(positive <= 0.0)
    tau = 1.0 + 2.0 * float(np.sum(positive[: stop[0]] if stop.size else positive))
    return max(len(residual) / tau, 1.0)


def residual_tests(
    rig: Rig, innovations: Sequence[np.ndarray], states: Sequence[np.ndarray], max_lag: int
) -> dict[str, Any]:
    """Whiteness of the innovations (N, 3) and their cross-correlation with velocity and deformation
    (from the states (N, n)), per axis, pooled over records (each record's sequence tested, then the
    statistics averaged)."""
    tests: dict[str, Any] = {}
    for i, axis in enumerate(AXES):
        white, velocity, deformation = [], [], []
        for innovation, state in zip(innovations, states):
            e = np.asarray(innovation)[:, i]
            state = np.asarray(state)
            d_r, _, d_z, _ = deformations(rig, state)
            white.append(whiteness(e, max_lag))
            for store, u in ((velocity, state[:, 4 + i]), (deformation, d_z if axis == "z" else d_r)):
                _, r, band = cross_correlation(e, u, max_lag)
                store.append({"max_abs": float(np.max(np.abs(r))), "outside_share": float(np.mean(np.abs(r) > band))})
        mean = lambda rows, key: float(np.mean([r[key] for r in rows]))  # noqa: E731
        tests[axis] = {
            "whiteness_outside_share": mean(white, "outside_share"),
            "whiteness_max_abs": mean(white, "max_abs"),
            "band": mean(white, "band"),
            "velocity_xcorr_max_abs": mean(velocity, "max_abs"),
            "velocity_xcorr_outside_share": mean(velocity, "outside_share"),
            "deformation_xcorr_max_abs": mean(deformation, "max_abs"),
            "deformation_xcorr_outside_share": mean(deformation, "outside_share"),
        }
    return tests
