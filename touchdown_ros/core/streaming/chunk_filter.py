"""The EKF over a chunk of grid rows as one compiled loop: one array in, one array out.

A chunk buffer has C rows of measurements and a last row with the prior (and the adaptive Q's
factor) and the count of real rows; the compiled function returns the packed results
(`outputs.PACKED_LAYOUT`) of each row and the prior after the last real row. A few compiled
lengths C serve any number of rows (NaN padding that never advances the belief).
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.dynamics import at_time, contact_force_xyz, contact_forces_and_jacobian
from touchdown_ros.core.ekf import (
    Belief, NoiseAdaptation, _inverse_3x3, adapted_log_scale, model_measurement, predict_with_rate, update,
)
from touchdown_ros.core.estimate import force_covariance, force_model_variance, law_force_covariance
from touchdown_ros.core.streaming.outputs import PACKED_WIDTH
from touchdown_ros.core.types import OMEGA_RING, STATE_SIZE, VELOCITY, FilterNoise, Model

ChunkFunction = Callable[[np.ndarray], Array]

# A chunk buffer's last row holds the prior (mean, covariance row-major, ln of Q's factor), the count of real rows
# and the first row's time after the drop onset; the largest state is 8 (a spinning ring's).
assert PACKED_WIDTH > 8 + 64 + 1 + 2, "a chunk buffer's row must hold the prior, Q's factor, the count and the time"


def prior_columns(size: int) -> tuple[slice, int]:
    """Columns of a chunk buffer's last row that hold the prior of a state of `size` with ln of Q's factor after
    it, and the count (the first row's time after the drop onset, s, in the column after it)."""
    return slice(0, size + size * size + 1), size + size * size + 1


def make_chunk_filter(
    model: Model,
    noise: FilterNoise,
    sample_period: float,
    model_variance: np.ndarray | None = None,
    adaptation: NoiseAdaptation | None = None,
) -> ChunkFunction:
    """Jitted `buffer (C + 1, width) -> buffer`: the EKF over C rows, one compiled loop, one array each way.

    In: rows 0..C-1 hold the measurements eta (m) in columns 0-2 (NaN: predict only);
    row C holds the prior and, in the columns after it (`prior_columns`), the number of real rows and row 0's
    time after the drop onset (s; row k's is k sample periods later, what clocked effects read). Out: row k
    holds the packed results of row k (`outputs.PACKED_LAYOUT`), row C the prior after the last real
    row. Each row is the EKF step (`update`, then `predict_with_rate`) and the filtered
    signals of `estimate.signals` (acceleration and its covariance from the first RK4
    stage of the prediction, contact forces and their covariance through the forces'
    Jacobian), innovation and NIS. Rows at and after the
    count are padding (the compiled shape never changes): skipped, their result rows are
    NaN and the prior carried on is the one after the last real row. The results equal
    `make_estimator`'s to round-off (the acceleration Jacobian comes from reverse- instead
    of forward-mode differentiation). One compilation per C.

    Everything stays inside the loop body (no LAPACK call: the 3 x 3 inverse is closed
    form) so that XLA's CPU backend compiles the whole loop into one function (the
    small-loop option `core.xla` sets). One array each way because each argument and
    result costs dispatch time: called every 1.6 ms as the node does, a chunk of 16 rows
    takes 7-16 % less CPU than with the prior, rows and count as separate arrays
    (bench/chunk_dispatch.py). `model_variance`, `adaptation` (Q moved by the innovations; its ln factor is
    carried after the prior's covariance and written in `process_scale`): as `estimate.make_estimator`'s.
    """
    R, Q = jnp.diag(noise.measurement), jnp.diag(noise.process)
    size = len(noise.process)
    prior_slice, count_column = prior_columns(size)
    ring = model.law.spins_ring
    measure = model_measurement(model)
    if model_variance is None:
        model_variance = force_model_variance(model, noise, sample_period)

    def row(prior: Belief, log_scale: Array, eta: Array, t: Array) -> tuple[Belief, Array, Array]:
        timed = at_time(model, t)
        filtered, innovation, S, used = update(prior, eta, R, measure)
        nis = innovation @ (_inverse_3x3(S) @ innovation)  # NaN where the sample was not used
        if adaptation is not None:
            log_scale = adapted_log_scale(adaptation, log_scale, nis, used)
        next_prior, _, rate, rate_jacobian = predict_with_rate(timed, filtered, jnp.exp(log_scale) * Q, sample_period)
        J = rate_jacobian[VELOCITY]
        forces, J_force = contact_forces_and_jacobian(timed, filtered.mean)
        packed = jnp.concatenate(
            [
                filtered.mean[:STATE_SIZE],
                filtered.cov[:STATE_SIZE, :STATE_SIZE].reshape(STATE_SIZE**2),
                jnp.stack([filtered.mean[OMEGA_RING], jnp.sqrt(filtered.cov[OMEGA_RING, OMEGA_RING])])
                if ring else jnp.full(2, jnp.nan, eta.dtype),
                rate[VELOCITY],
                (J @ filtered.cov @ J.T).reshape(9),
                contact_force_xyz(forces),
                force_covariance(
                    forces, J_force, filtered.cov, model_variance, law_force_covariance(timed, filtered.mean)
                ).reshape(9),
                jnp.stack([forces.F_n, forces.F_t, forces.F_z]),
                jnp.stack([forces.radial_contact, forces.axial_contact]).astype(eta.dtype),
                innovation,
                S.reshape(9),
                nis[None],
                used[None].astype(eta.dtype),
                jnp.exp(log_scale)[None],
            ]
        )
        return next_prior, log_scale, packed

    def run(buffer: Array) -> Array:
        last = buffer.shape[0] - 1
        count, start = buffer[last, count_column], buffer[last, count_column + 1]

        def real(carried: Array, eta: Array, t: Array) -> tuple[Array, Array]:
            prior = Belief(carried[:size], carried[size:-1].reshape(size, size))
            next_prior, log_scale, packed = row(prior, carried[-1], eta, t)
            return jnp.concatenate([next_prior.mean, next_prior.cov.reshape(size * size), log_scale[None]]), packed

        def padding(carried: Array, eta: Array, t: Array) -> tuple[Array, Array]:
            return carried, jnp.full(PACKED_WIDTH, jnp.nan, eta.dtype)

        def body(carried: Array, inputs: tuple[Array, Array]) -> tuple[Array, Array]:
            eta, k = inputs
            # a branch, not a select: padding rows cost nothing (a block of 19 in a chunk of 32: 360 -> 258 us)
            return jax.lax.cond(k < count, real, padding, carried, eta, start + k * sample_period)

        # scan's outputs are written in place; updating the buffer row by row in a loop made XLA copy it per row
        carried, rows = jax.lax.scan(body, buffer[last, prior_slice], (buffer[:last, :3], jnp.arange(last)))
        return jnp.concatenate([rows, buffer[last].at[prior_slice].set(carried)[None]])

    return jax.jit(run)


def flat_belief(belief: Belief, log_scale: float = 0.0) -> np.ndarray:
    """(n + n^2 + 1,) mean, row-major covariance and ln of Q's factor, as the last row of a chunk buffer holds
    them."""
    return np.concatenate([np.asarray(belief.mean), np.asarray(belief.cov).reshape(-1), [log_scale]])


def chunk_buffer(etas: np.ndarray, size: int, prior: np.ndarray, start_time: float = 0.0) -> np.ndarray:
    """Input of a chunk filter of `size` rows: etas (n <= size, 3) m, NaN padding, the prior (`flat_belief`), n
    and the first row's time after the drop onset (s)."""
    buffer = np.zeros((size + 1, PACKED_WIDTH))
    buffer[: len(etas), :3] = etas
    buffer[len(etas) : size, :3] = np.nan
    buffer[size, : len(prior)] = prior
    buffer[size, len(prior)] = len(etas)
    buffer[size, len(prior) + 1] = start_time
    return buffer
