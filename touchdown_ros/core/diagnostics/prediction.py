"""The model's own prediction quality. The filtered estimate follows the data whatever the model, so
the model is judged on the one-step prediction H xi_{k,-} and on the k-step prediction: the filtered
state propagated k samples with the model's RK4 f and no measurement update. Errors per axis, per
contact phase and per impact (eq. 19 RMSE, fit %), and the after / before ratios of two models."""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.diagnostics.breakdown import PHASES, rms_by_label
from touchdown_ros.core.dynamics import at_time, rk4_step
from touchdown_ros.core.metrics import rmse
from touchdown_ros.core.types import Model


def fit_percent(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Per column: 100 (1 - |y - y_hat| / |y - mean y|) over rows where both are finite
    (100 % is a perfect fit, 0 % no better than the mean, negative worse)."""
    y, yhat = np.asarray(measured, float), np.asarray(predicted, float)
    ok = np.isfinite(y) & np.isfinite(yhat)
    out = np.full(y.shape[1], np.nan)
    for j in range(y.shape[1]):
        if ok[:, j].sum() < 2:
            continue
        yj, pj = y[ok[:, j], j], yhat[ok[:, j], j]
        spread = np.linalg.norm(yj - yj.mean())
        out[j] = 100.0 * (1.0 - np.linalg.norm(yj - pj) / spread) if spread > 0 else np.nan
    return out


def k_step_predictions(model: Model, states: Array, h: float, k: int) -> Array:
    """(N, n): row i is the filtered state of sample i - k propagated k RK4 steps with the
    model alone (no measurement update); the first k rows are NaN. Row j of `states` is j h s after the
    drop onset (what clocked effects read)."""
    states = jnp.asarray(states)

    def propagate(xi: Array, start: Array) -> Array:
        return jax.lax.fori_loop(0, k, lambda j, s: rk4_step(at_time(model, start + j * h), s, h), xi)

    starts = h * jnp.arange(states.shape[0] - k)
    ahead = jax.vmap(propagate)(states[: states.shape[0] - k], starts) if k > 0 else states
    return jnp.concatenate([jnp.full((k, states.shape[1]), jnp.nan, states.dtype), ahead])


def error_metrics(
    measured: np.ndarray,
    one_step: np.ndarray,
    k_step: np.ndarray,
    force_error: np.ndarray | None,
    phase: np.ndarray,
    impact: np.ndarray,
) -> dict[str, Any]:
    """One-step and k-step predicted measurements (N, 3) against the measured: RMSE and fit per
    axis, the k-step RMSE per contact phase (`PHASES`) and per impact (the first 12), and with the
    truth the contact force error (N, 3) per axis and phase."""
    ek = k_step - measured
    by_phase, counts = rms_by_label(ek, phase, range(4))
    force_phase = rms_by_label(force_error, phase, range(4))[0] if force_error is not None else None
    impacts = [i for i in range(1, min(int(impact.max()) if impact.size else 0, 12) + 1)]
    by_impact, impact_counts = rms_by_label(ek, impact, impacts)
    metrics: dict[str, Any] = {
        "samples": int(len(measured)),
        "one_step": {
            "rmse_m": rmse(one_step, measured).tolist(),
            "fit_percent": fit_percent(measured, one_step).tolist(),
        },
        "k_step": {"rmse_m": rmse(k_step, measured).tolist(), "fit_percent": fit_percent(measured, k_step).tolist()},
        "phases": {
            name: {
                "samples": int(counts[i]),
                "k_step_rmse_m": by_phase[i].tolist(),
                **({"force_rmse_N": force_phase[i].tolist()} if force_phase is not None else {}),
            }
            for i, name in enumerate(PHASES)
        },
        "impacts": [
            {"impact": n, "samples": int(c), "k_step_rmse_m": v.tolist()}
            for n, v, c in zip(impacts, by_impact, impact_counts)
        ],
    }
    metrics["k_step"]["rmse_norm_m"] = float(np.linalg.norm(metrics["k_step"]["rmse_m"]))
    metrics["one_step"]["rmse_norm_m"] = float(np.linalg.norm(metrics["one_step"]["rmse_m"]))
    if force_error is not None:
        force_rmse = rmse(force_error, np.zeros_like(force_error))
        metrics["contact_force"] = {"rmse_N": force_rmse.tolist(), "rmse_norm_N": float(np.linalg.norm(force_rmse))}
    return metrics


def _ratio(after: float, before: float) -> float | None:
    return float(after / before) if before else None


def comparison(before: dict[str, Any], after: dict[str, Any]) -> dict[str, Any]:
    """after / before of the headline errors of two models' metrics (`error_metrics` with the
    `missing_force` table); a ratio below 1 is an improvement."""
    mb, ma = before, after
    out = {
        "k_step_rmse_norm": _ratio(ma["k_step"]["rmse_norm_m"], mb["k_step"]["rmse_norm_m"]),
        "one_step_rmse_norm": _ratio(ma["one_step"]["rmse_norm_m"], mb["one_step"]["rmse_norm_m"]),
        "k_step_rmse_per_axis": [_ratio(a, b) for a, b in zip(ma["k_step"]["rmse_m"], mb["k_step"]["rmse_m"])],
        "k_step_rmse_per_phase": {
            p: [_ratio(a, b) for a, b in zip(ma["phases"][p]["k_step_rmse_m"], mb["phases"][p]["k_step_rmse_m"])]
            for p in PHASES
            if mb["phases"][p]["samples"]
        },
        "missing_force_rms": [
            _ratio(a, b) for a, b in zip(ma["missing_force"]["all"]["rms_N"], mb["missing_force"]["all"]["rms_N"])
        ],
    }
    if "contact_force" in mb and "contact_force" in ma:
        out["contact_force_rmse_norm"] = _ratio(ma["contact_force"]["rmse_norm_N"], mb["contact_force"]["rmse_norm_N"])
        out["contact_force_rmse_per_axis"] = [
            _ratio(a, b) for a, b in zip(ma["contact_force"]["rmse_N"], mb["contact_force"]["rmse_N"])
        ]
    return out
