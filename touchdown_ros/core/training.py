"""Training loss of eq. 18 over a batch of records, and its gradient by reverse-mode AD.

loss(alpha) = sum over bags and valid samples of |eta_k - H xi_{k,-}|^2 / sigma^2, divided
by the number of valid samples, + lambda * sum_k alpha_k^T K alpha_k.

The output error is the one-step prediction of eq. 17b (the filtered estimate alone
would follow the data whatever the model), measured in units of the sensor noise so
that lambda is dimensionless.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.effects import Effects
from touchdown_ros.core.ekf import Belief, ekf
from touchdown_ros.core.estimate import initial_belief
from touchdown_ros.core.pkbkr import rkhs_distance
from touchdown_ros.core.types import Coefficients, FilterNoise, Model


class Batch(NamedTuple):
    """Records of equal length (shorter ones padded with NaN samples, which are not used)."""

    etas: Array  # (B, L, 3) m
    initial_mean: Array  # (B, 7)
    initial_cov: Array  # (B, 7, 7)
    valid: Array  # (B, L) bool, sample present and counted in the loss
    gates: Array  # (B, E) which of the model's E effects act in each record (1 on, 0 off)


def make_batch(
    records: list[np.ndarray],
    initial_cov: np.ndarray,
    length: int | None = None,
    gates: list[tuple[float, ...]] | None = None,
) -> Batch:
    """Stack records (each (N_b, 3), from its drop onset) into a padded batch; gates per record
    (default: no effects)."""
    length = length or max(len(r) for r in records)
    etas = np.full((len(records), length, 3), np.nan)
    means, covs = [], []
    for b, record in enumerate(records):
        record = record[:length]
        etas[b, : len(record)] = record
        belief = initial_belief(record, initial_cov)
        means.append(np.asarray(belief.mean))
        covs.append(np.asarray(belief.cov))
    valid = np.all(np.isfinite(etas), axis=-1)
    gates = np.asarray(gates if gates is not None else [()] * len(records), dtype=float).reshape(len(records), -1)
    return Batch(
        jnp.asarray(etas), jnp.asarray(np.array(means)), jnp.asarray(np.array(covs)), jnp.asarray(valid), jnp.asarray(gates)
    )


def prediction_errors(model: Model, noise: FilterNoise, h: float, batch: Batch) -> Array:
    """(B, L, 3) one-step prediction errors eta_k - H xi_{k,-}, m (NaN where no sample)."""

    def one(etas: Array, mean: Array, cov: Array, gates: Array) -> Array:
        gated = model._replace(effects=model.effects.with_gates(gates))
        return ekf(gated, noise, h, Belief(mean, cov), etas).innovation

    return jax.vmap(one)(batch.etas, batch.initial_mean, batch.initial_cov, batch.gates)


def output_error(model: Model, noise: FilterNoise, h: float, batch: Batch) -> Array:
    """Mean squared one-step prediction error over valid samples, in units of the noise variance."""
    errors = prediction_errors(model, noise, h, batch)
    squared = jnp.where(batch.valid[..., None], errors**2 / noise.measurement, 0.0)
    return jnp.sum(squared) / jnp.sum(batch.valid)


def loss(
    coeffs: Coefficients,
    model: Model,
    noise: FilterNoise,
    h: float,
    batch: Batch,
    lam: float,
    effects: Effects | None = None,
) -> Array:
    """Eq. 18 with the output error normalised as in output_error; `effects` (with their
    physical parameters, not penalised) replace the model's when given."""
    trained = model._replace(coeffs=coeffs, effects=model.effects if effects is None else effects)
    return output_error(trained, noise, h, batch) + lam * rkhs_distance(model.kernel, coeffs)
