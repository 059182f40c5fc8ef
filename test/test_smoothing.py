"""The smoother's leave-one-out residuals (core.smoothing) and the factor on Q the trainer chooses by them."""
import jax.numpy as jnp
import numpy as np

from touchdown_ros.core.ekf import Belief, extended_kalman_filter, position, rts_smoother
from touchdown_ros.core.smoothing import leave_one_out_residuals


def _random_covariance(rng, n, scale):
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T + n * np.eye(n))


def _linear_record(rng, N=60):
    """A 6-state constant-velocity model with 3 positions measured, random Q, R, P0 (as test_core's RTS check)."""
    n, m, h = 6, 3, 0.1
    F = np.block([[np.eye(3), h * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
    Q, R, P0 = _random_covariance(rng, n, 1e-3), _random_covariance(rng, m, 1e-2), _random_covariance(rng, n, 1.0)
    m0 = rng.standard_normal(n)
    x = m0 + np.linalg.cholesky(P0) @ rng.standard_normal(n)
    etas = np.empty((N, m))
    for k in range(N):
        etas[k] = x[:m] + np.linalg.cholesky(R) @ rng.standard_normal(m)
        x = F @ x + np.linalg.cholesky(Q) @ rng.standard_normal(n)
    return F, Q, R, Belief(jnp.asarray(m0), jnp.asarray(P0)), etas


def _smooth(F, Q, R, initial, etas):
    transition = lambda xi: (jnp.asarray(F) @ xi, jnp.asarray(F))  # noqa: E731
    return rts_smoother(extended_kalman_filter(transition, position, jnp.asarray(Q), jnp.asarray(R), initial,
                                               jnp.asarray(etas)))


def test_leave_one_out_residuals_equal_refitting_without_each_sample():
    """For a linear model the formula is exact: each sample's residual equals that from the smoother run
    again with the sample left out (NaN), for samples at the start, inside and at the end."""
    F, Q, R, initial, etas = _linear_record(np.random.default_rng(3))
    residuals = np.asarray(leave_one_out_residuals(position, _smooth(F, Q, R, initial, etas), jnp.asarray(etas),
                                                   jnp.asarray(R)))
    plain = etas - np.asarray(_smooth(F, Q, R, initial, etas).mean)[:, :3]
    for k in (0, 1, 17, 30, 58, 59):
        without = etas.copy()
        without[k] = np.nan
        expected = etas[k] - np.asarray(_smooth(F, Q, R, initial, without).mean)[k, :3]
        np.testing.assert_allclose(residuals[k], expected, rtol=1e-8, atol=1e-12)
        assert np.linalg.norm(expected - plain[k]) > 0.05 * np.linalg.norm(plain[k])  # leaving it out matters
