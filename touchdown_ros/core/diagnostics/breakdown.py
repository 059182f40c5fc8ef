"""Where the model fails: contact phases, the deformations of eq. 5 and 7 along states, and errors
broken down by label, by window and over the (deformation, velocity) planes."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from touchdown_ros.core.dynamics import polar
from touchdown_ros.core.types import Rig

AXES = ("x", "y", "z")
PHASES = ("free flight", "axial only", "radial only", "both")


def contact_phase(radial_contact: np.ndarray, axial_contact: np.ndarray) -> np.ndarray:
    """0 free flight, 1 axial contact only, 2 radial contact only, 3 both (`PHASES`)."""
    return np.asarray(axial_contact, bool).astype(int) + 2 * np.asarray(radial_contact, bool).astype(int)


def deformations(rig: Rig, states: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Radial deformation r - r0, radial velocity rdot (eq. 13e), axial compression -(z + z0) and
    z velocity of states (..., n), as `core.dynamics.contact_forces` computes them (`polar`, eq. 4e):
    each positive deformation is a contact."""
    states = np.asarray(states)
    r, cos_a, sin_a = (np.asarray(v) for v in polar(states[..., 0], states[..., 1]))
    rdot = cos_a * states[..., 4] + sin_a * states[..., 5]
    return r - rig.radial_clearance, rdot, -(states[..., 2] + rig.axial_clearance), states[..., 6]


def rms_by_label(error: np.ndarray, labels: np.ndarray, values: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """RMS of error (N, c) per label value: (len(values), c) and the sample counts."""
    error = np.asarray(error, float)
    out = np.full((len(values), error.shape[1]), np.nan)
    counts = np.zeros(len(values), int)
    for i, v in enumerate(values):
        rows = (labels == v) & np.all(np.isfinite(error), axis=1)
        counts[i] = rows.sum()
        if counts[i]:
            out[i] = np.sqrt(np.mean(error[rows] ** 2, axis=0))
    return out, counts


def binned_rms(
    error: np.ndarray, a: np.ndarray, b: np.ndarray, a_edges: np.ndarray, b_edges: np.ndarray, min_count: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """RMS of a scalar error over the cells of the (a, b) plane (e.g. deformation, velocity):
    (len(a_edges) - 1, len(b_edges) - 1), NaN where fewer than min_count samples; and the counts."""
    error, a, b = (np.asarray(v, float) for v in (error, a, b))
    ok = np.isfinite(error) & np.isfinite(a) & np.isfinite(b)
    squares, _, _ = np.histogram2d(a[ok], b[ok], [a_edges, b_edges], weights=error[ok] ** 2)
    counts, _, _ = np.histogram2d(a[ok], b[ok], [a_edges, b_edges])
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(squares / counts)
    return np.where(counts >= min_count, rms, np.nan), counts.astype(int)


def windowed_rms(error: np.ndarray, window: int) -> np.ndarray:
    """RMS of error (N, c) over consecutive windows of `window` samples: (ceil(N / window), c)."""
    error = np.asarray(error, float)
    rows = []
    for start in range(0, len(error), window):
        block = error[start : start + window]
        ok = np.all(np.isfinite(block), axis=1)
        rows.append(np.sqrt(np.mean(block[ok] ** 2, axis=0)) if ok.any() else np.full(error.shape[1], np.nan))
    return np.array(rows)


def region_edges(values: np.ndarray, bins: int) -> np.ndarray:
    """bins + 1 equal edges between the 1st and 99th percentiles of values."""
    lo, hi = np.nanpercentile(values, [1, 99])
    if not np.isfinite(lo) or hi <= lo:
        hi = lo + 1e-9
    return np.linspace(lo, hi, bins + 1)


def regions(
    rig: Rig, states: np.ndarray, error: np.ndarray, deformation_bins: int, velocity_bins: int
) -> dict[str, Any]:
    """RMS of a scalar error (N,), e.g. the k-step error's norm, over the (deformation, velocity)
    plane of each contact (axial, radial), in contact only (a contact with fewer than 10 samples
    is left out)."""
    d_r, v_r, d_z, v_z = deformations(rig, states)
    out = {}
    for name, d, v in (("axial", d_z, v_z), ("radial", d_r, v_r)):
        contact = d > 0
        if contact.sum() < 10:
            continue
        d_edges = region_edges(d[contact], deformation_bins)
        v_edges = region_edges(v[contact], velocity_bins)
        rms, counts = binned_rms(np.where(contact, error, np.nan), d, v, d_edges, v_edges)
        out[name] = {
            "deformation_edges_m": d_edges.tolist(),
            "velocity_edges_mps": v_edges.tolist(),
            "k_step_rmse_m": np.where(np.isfinite(rms), rms, None).tolist(),
            "counts": counts.tolist(),
        }
    return out
