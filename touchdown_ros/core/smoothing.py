"""How much process noise the smoothed answer wants: leave-one-out cross-validation of the RTS smoother.

The likelihood that stage 1 maximises fits Q for one-step prediction, which is what the live
filter does. The offline answer is the smoothed estimate, and there a smaller Q often serves
better: the smoother then averages the sensor noise over more samples where the model holds
(docs/calibration.md, "Process noise for the smoothed answer"). Which factor on Q is right is
decided on displacements alone, by how well the smoother predicts each sample from all the
others. For a linear(ised) smoother that needs no refit per sample: with y_k = h(xi_k) + v_k,
v_k ~ N(0, R), the smoothed estimate moves with y_k by H P_{k|N} H^T R^-1, so the residual of
y_k from the smoother fitted without it is

    e_k = (I - H P_{k|N} H^T R^-1)^-1 (y_k - h(xi_{k|N}))

(the Kalman update of the leave-one-out estimate with y_k, solved for it), as generalised
cross-validation does for smoothing splines.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.dynamics import at_time, contact_forces, rk4_step
from touchdown_ros.core.ekf import Belief, Measurement, ekf, inverse_and_det_3x3, model_measurement, rts_smoother
from touchdown_ros.core.training import Batch
from touchdown_ros.core.types import OUTPUT_SIZE, VELOCITY, FilterNoise, Model


def leave_one_out_residuals(measure: Measurement, smoothed: Belief, etas: Array, R: Array) -> Array:
    """(N, 3) m: the residual of each measurement (N, 3) from the smoother fitted to all the others
    (module docstring), from the smoothed beliefs of a record, its measurement function h and R (3, 3);
    NaN where y_k is missing."""

    def one(mean: Array, cov: Array, eta: Array) -> Array:
        expected, H = measure(mean)
        influence = H @ cov @ H.T @ inverse_and_det_3x3(R)[0]
        return inverse_and_det_3x3(jnp.eye(OUTPUT_SIZE, dtype=mean.dtype) - influence)[0] @ (eta - expected)

    return jax.vmap(one)(smoothed.mean, smoothed.cov, etas)


def over_smoothed_records(
    model: Model, noise: FilterNoise, h: float, batch: Batch, measure: Callable[[Model, Belief, Array, Array], Any]
) -> Any:
    """`measure(gated model, smoothed beliefs, etas, valid)` of every record of the batch, stacked: filter and
    smoother of each record with `noise`, the model with the record's effects' gates."""

    def one(etas: Array, mean: Array, cov: Array, gates: Array, valid: Array) -> Any:
        gated = model._replace(effects=model.effects.with_gates(gates))
        return measure(gated, rts_smoother(ekf(gated, noise, h, Belief(mean, cov), etas)), etas, valid)

    return jax.vmap(one)(batch.etas, batch.initial_mean, batch.initial_cov, batch.gates, batch.valid)


@jax.jit
def leave_one_out_squares(model: Model, noise: FilterNoise, h: float, batch: Batch) -> Array:
    """(records, N) m^2: each sample's squared leave-one-out residual, summed over the axes, 0 where the
    sample is not valid: filter and smoother of every record with `noise`, each with its effects' gates."""
    R = jnp.diag(noise.measurement)

    def squares(gated: Model, smoothed: Belief, etas: Array, valid: Array) -> Array:
        residuals = leave_one_out_residuals(model_measurement(gated), smoothed, etas, R)
        return jnp.where(valid, jnp.sum(residuals * residuals, axis=1), 0.0)

    return over_smoothed_records(model, noise, h, batch, squares)


@jax.jit
def missing_force_squares(model: Model, noise: FilterNoise, h: float, batch: Batch) -> tuple[Array, Array]:
    """The force the smoother adds to the model to follow the displacements: per record and sample,
    (m w_k / h)^2 per axis (N^2), w_k the velocity part of xi_{k+1|N} - f(xi_{k|N}) (f the filter's RK4
    step), and where it counts: k and k + 1 valid and the model in contact at xi_{k|N} ((records, N, 3),
    (records, N) bool; the last sample never counts).

    Its mean over the counted samples is the model's own force error in contact at the resolution the
    displacements support: `force_model_variance`'s m^2 Q_v / h^2 reads the white process noise of a
    single sample as a force, which the data cannot resolve and a smooth model error does not have."""

    def squares(gated: Model, belief: Belief, etas: Array, valid: Array) -> tuple[Array, Array]:
        smoothed = belief.mean
        times = h * jnp.arange(smoothed.shape[0] - 1)
        predicted = jax.vmap(lambda xi, t: rk4_step(at_time(gated, t), xi, h))(smoothed[:-1], times)
        force = gated.rig.mass * (smoothed[1:] - predicted)[:, VELOCITY] / h
        forces = jax.vmap(lambda xi: contact_forces(gated, xi))(smoothed[:-1])
        counted = valid[:-1] & valid[1:] & (forces.radial_contact | forces.axial_contact)
        pad = jnp.zeros((1, 3), force.dtype)
        return jnp.concatenate([force * force, pad]), jnp.append(counted, False)

    return over_smoothed_records(model, noise, h, batch, squares)


def mean_missing_force_variance(squares: Array, counted: Array) -> np.ndarray | None:
    """(3,) N^2: the mean of `missing_force_squares`' squares over its counted samples; None if none count."""
    counted = np.asarray(counted, dtype=bool)
    if not counted.any():
        return None
    return np.asarray(squares)[counted].mean(axis=0)


#: Samples per block for the standard error of a mean over records (10 ms at 10 kHz). The smoothed
#: residuals stay correlated over tens of samples: on soft_bearing's training bags the standard error of
#: a fall grows 1.3x from single samples to blocks of 10, 2.5x to 100 and 2.7x to 400 (docs/calibration.md).
BLOCK_SAMPLES = 100


def mean_fall_and_standard_error(before: np.ndarray, after: np.ndarray, valid: np.ndarray,
                                 block: int = BLOCK_SAMPLES) -> tuple[float, float]:
    """The mean over the valid samples of before - after ((records, N) arrays, e.g. squared residuals)
    and its standard error by batch means: the spread of the means of consecutive blocks of `block`
    valid samples of each record (the samples' correlation stays inside a block; a last, shorter block
    left out). The standard error is inf with fewer than two blocks."""
    differences = [d[ok] for d, ok in zip(np.asarray(before) - np.asarray(after), np.asarray(valid, dtype=bool))]
    means = np.asarray([d[i : i + block].mean() for d in differences for i in range(0, len(d) - block + 1, block)])
    fall = float(np.concatenate(differences).mean()) if any(len(d) for d in differences) else float("nan")
    if len(means) < 2:
        return fall, float("inf")
    return fall, float(means.std(ddof=1) / np.sqrt(len(means)))
