"""Training losses over a batch of records, and their gradients by reverse-mode AD.

Two output errors, both from the one-step predictions of eq. 17b (the filtered
estimate alone would follow the data whatever the model), per valid sample:

- ``one_step`` (eq. 18 as published): |eta_k - h(xi_{k,-})|^2 / sigma^2, the squared
  prediction error in units of the sensor noise variance (h = H xi, H = [I 0], without
  measurement effects);
- ``nll``: the innovation negative log-likelihood nu^T S^-1 nu + ln det(S R^-1), times 2
  and without constants, with S = H P_{k,-} H^T + R from the filter (H = dh/dxi): the same number as
  ``one_step`` where S = R, but it weighs each sample by what the filter expects and
  can also fit Q.

loss(alpha) = output error summed over bags and valid samples, divided by the number of
valid samples, + lambda * sum_k alpha_k^T K alpha_k (eq. 18).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from touchdown_ros.core.effects import Effects
from touchdown_ros.core.ekf import Belief, ekf, inverse_and_det_3x3
from touchdown_ros.core.estimate import initial_belief
from touchdown_ros.core.pkbkr import rkhs_distance
from touchdown_ros.core.types import Coefficients, FilterNoise, Model

#: Mesh axis over which `output_error` spreads the records of a batch.
RECORDS = "records"


class Batch(NamedTuple):
    """Records of equal length (shorter ones padded with NaN samples, which are not used)."""

    etas: Array  # (B, L, 3) m
    initial_mean: Array  # (B, n)
    initial_cov: Array  # (B, n, n)
    valid: Array  # (B, L) bool, sample present and counted in the loss
    gates: Array  # (B, E) which of the model's E effects act in each record (1 on, 0 off)
    held_out: Array  # (B, L) bool, sample filtered but counted in the held-out error, not the loss


def with_state_size(batch: Batch, size: int) -> Batch:
    """The batch with its initial beliefs cut to the first `size` states (a spinning ring's dropped)."""
    return batch._replace(initial_mean=batch.initial_mean[:, :size], initial_cov=batch.initial_cov[:, :size, :size])


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
        jnp.asarray(etas),
        jnp.asarray(np.array(means)),
        jnp.asarray(np.array(covs)),
        jnp.asarray(valid),
        jnp.asarray(gates),
        jnp.zeros(valid.shape, dtype=bool),
    )


def hold_out(batch: Batch, block: int, every: int) -> Batch:
    """The batch with one block of `block` samples in every `every` held out of the loss (`held_out`).

    The filter still runs through the held-out samples, so their one-step errors measure how
    well the model predicts data it was not fitted to. The pattern is shifted by one block from
    record to record, so that drops of similar timing do not all hold out the same phase.
    """
    if every < 2:
        return batch
    records, length = batch.valid.shape
    blocks = np.arange(length)[None, :] // block + np.arange(records)[:, None]
    return batch._replace(held_out=jnp.asarray(blocks % every == every - 1))


LOSSES = ("one_step", "nll")


def innovations(model: Model, noise: FilterNoise, h: float, batch: Batch) -> tuple[Array, Array]:
    """(B, L, 3) one-step prediction errors eta_k - h(xi_{k,-}), m (NaN where no sample), and
    (B, L, 3, 3) their covariances S_k, m^2; f and h are the model's (its force and measurement
    effects gated per record)."""

    def one(etas: Array, mean: Array, cov: Array, gates: Array) -> tuple[Array, Array]:
        gated = model._replace(effects=model.effects.with_gates(gates))
        out = ekf(gated, noise, h, Belief(mean, cov), etas, checkpoint=True)
        return out.innovation, out.innovation_cov

    return jax.vmap(one)(batch.etas, batch.initial_mean, batch.initial_cov, batch.gates)


def prediction_errors(model: Model, noise: FilterNoise, h: float, batch: Batch) -> Array:
    """(B, L, 3) one-step prediction errors eta_k - h(xi_{k,-}), m (NaN where no sample)."""
    return innovations(model, noise, h, batch)[0]


def sample_errors(model: Model, noise: FilterNoise, h: float, batch: Batch, kind: str = "one_step") -> Array:
    """(B, L) output error of each sample (module docstring), 0 where the sample is not valid."""
    errors, S = innovations(model, noise, h, batch)
    return errors_of_innovations(errors, S, noise.measurement, batch.valid, kind)


def errors_of_innovations(errors: Array, S: Array, measurement: Array, valid: Array, kind: str) -> Array:
    """`sample_errors` from the innovations (B, L, 3), their covariances (B, L, 3, 3) and the sensor
    noise variances R (3,), m^2; 0 where `valid` is False."""
    if kind == "one_step":
        value = jnp.sum(errors**2 / measurement, axis=-1)
    elif kind == "nll":
        safe = jnp.where(valid[..., None], errors, 0.0)
        scaled = S / jnp.sqrt(measurement[:, None] * measurement[None, :])  # S R^-1 up to similarity
        inverse, det = inverse_and_det_3x3(scaled)
        whitened = safe / jnp.sqrt(measurement)
        mahalanobis = jnp.einsum("...i,...ij,...j->...", whitened, inverse, whitened)
        value = mahalanobis + jnp.log(jnp.where(valid, det, 1.0))
    else:
        raise ValueError(f"unknown loss {kind!r}: use one of {', '.join(LOSSES)}")
    return jnp.where(valid, value, 0.0)


def _sums_and_held_out_errors(
    model: Model, noise: FilterNoise, h: float, batch: Batch, kind: str
) -> tuple[Array, Array]:
    """(2,) sums of the output error over the fitted and the held-out valid samples, and the (B, L) errors
    of the held-out samples (0 elsewhere)."""
    errors = sample_errors(model, noise, h, batch, kind)
    held_out = jnp.where(batch.held_out, errors, 0.0)
    return jnp.stack([jnp.sum(jnp.where(batch.held_out, 0.0, errors)), jnp.sum(held_out)]), held_out


def output_errors(
    model: Model, noise: FilterNoise, h: float, batch: Batch, mesh: Mesh | None = None, kind: str = "one_step"
) -> tuple[Array, Array]:
    """Mean output error (`sample_errors`; one_step: in units of the noise variance) over the fitted
    and over the held-out valid samples (`hold_out`; NaN when none is held out), from one filter pass.

    With a mesh (one axis, `RECORDS`), each device filters its share of the records in its
    own loop and the sums are added (the batch size must be a multiple of the mesh size:
    `pad_records`); the same numbers as without.
    """
    return output_errors_and_held_out(model, noise, h, batch, mesh, kind)[:2]


def output_errors_and_held_out(
    model: Model, noise: FilterNoise, h: float, batch: Batch, mesh: Mesh | None = None, kind: str = "one_step"
) -> tuple[Array, Array, Array]:
    """`output_errors` and the (B, L) output errors of the held-out samples (0 elsewhere), from the same pass:
    the per-block errors that `held_out_block_sums` adds up."""
    if mesh is None:
        totals, held_out = _sums_and_held_out_errors(model, noise, h, batch, kind)
    else:

        def share(local: Model, local_noise: FilterNoise, records: Batch) -> tuple[Array, Array]:
            sums, held_out = _sums_and_held_out_errors(local, local_noise, h, records, kind)
            return jax.lax.psum(sums, RECORDS), held_out

        # check_vma off: the identity cotangents of dynamics.phi_and_jacobian are built
        # inside and carry no varying-axis type; nothing here is replicated across devices.
        totals, held_out = jax.shard_map(
            share, mesh=mesh, in_specs=(P(), P(), P(RECORDS)), out_specs=(P(), P(RECORDS)), check_vma=False
        )(jax.tree.map(jnp.asarray, model), jax.tree.map(jnp.asarray, noise), batch)
    held = batch.valid & batch.held_out
    held_count = jnp.sum(held)
    fitted = totals[0] / jnp.sum(batch.valid & ~batch.held_out)
    return fitted, jnp.where(held_count > 0, totals[1] / held_count, jnp.nan), held_out


def held_out_blocks(batch: Batch) -> np.ndarray:
    """(B, L) the held-out block (`hold_out`: a run of held-out valid samples of one record) each sample
    belongs to, numbered record after record from 0; -1 where the sample is not held out."""
    held = np.asarray(batch.held_out) & np.asarray(batch.valid)
    starts = held & ~np.pad(held, ((0, 0), (1, 0)))[:, :-1]
    return np.where(held, np.cumsum(starts.ravel()).reshape(held.shape) - 1, -1)


def sums_per_block(values: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """`values` (B, L) summed over each held-out block of `blocks` (`held_out_blocks`), one sum per block
    (0 for a block whose values are all 0)."""
    held = blocks >= 0
    return np.bincount(blocks[held], weights=np.asarray(values, dtype=float)[held], minlength=int(blocks.max()) + 1)


def held_out_block_sums(errors: np.ndarray, batch: Batch) -> np.ndarray:
    """The held-out errors (B, L) summed over each held-out block (`held_out_blocks`): the same blocks for
    every model of one batch, so two models' sums pair up."""
    return sums_per_block(errors, held_out_blocks(batch))


def within_one_standard_error(block_sums: list[np.ndarray], samples: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The one-standard-error rule on fits ordered from the most to the least regularised, each given by its
    held-out errors' block sums (`held_out_block_sums`: the same blocks, `samples` held-out samples in all): the
    first fit whose held-out loss is above the lowest's by at most one standard error of their paired per-block
    differences, the simplest model the held-out data cannot tell from the best. Returns (its index, each
    fit's held-out loss above the lowest's, each difference's standard error), per held-out sample."""
    sums = np.asarray(block_sums, dtype=float)
    blocks = sums.shape[1]
    differences = sums - sums[int(np.argmin(sums.sum(axis=1)))]
    above = differences.sum(axis=1) / samples
    error = np.sqrt(blocks) * differences.std(axis=1, ddof=1) / samples if blocks > 1 else np.zeros(len(sums))
    chosen = next(i for i in range(len(sums)) if above[i] <= error[i])
    return chosen, above, error


def output_error(
    model: Model, noise: FilterNoise, h: float, batch: Batch, mesh: Mesh | None = None, kind: str = "one_step"
) -> Array:
    """Mean output error over the fitted valid samples (`output_errors`)."""
    return output_errors(model, noise, h, batch, mesh, kind)[0]


def pad_records(batch: Batch, multiple: int) -> Batch:
    """The batch with copies of its first record appended, counted nowhere (valid False),
    until its size is a multiple of `multiple`: loss and gradient are unchanged.

    Copies rather than NaN records, so that the unused rows stay finite and cannot turn
    the gradient into NaN through `where`.
    """
    extra = -batch.etas.shape[0] % multiple
    if extra == 0:
        return batch
    padded = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[:1], extra, axis=0)]), batch)
    return padded._replace(valid=padded.valid.at[-extra:].set(False))


def loss_and_held_out(
    coeffs: Coefficients,
    model: Model,
    noise: FilterNoise,
    h: float,
    batch: Batch,
    lam: float,
    effects: Effects | None = None,
    mesh: Mesh | None = None,
    kind: str = "one_step",
) -> tuple[Array, tuple[Array, Array]]:
    """Eq. 18 with the output error `kind` normalised as in output_errors, and (not part of the loss) the
    held-out output error and the (B, L) errors of the held-out samples (`output_errors_and_held_out`);
    `effects` (with their physical parameters, not penalised) replace the model's when given; `mesh` spreads
    the records over devices (`output_errors`)."""
    trained = model._replace(coeffs=coeffs, effects=model.effects if effects is None else effects)
    fitted, held_out, held_out_errors = output_errors_and_held_out(trained, noise, h, batch, mesh, kind)
    return fitted + lam * rkhs_distance(model.kernel, coeffs), (held_out, held_out_errors)


def loss(*args, **kwargs) -> Array:
    """Eq. 18 alone: the first value of `loss_and_held_out`, which takes the same arguments."""
    return loss_and_held_out(*args, **kwargs)[0]
