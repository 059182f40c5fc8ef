"""The smoother's leave-one-out residuals (core.smoothing) and the factor on Q the trainer chooses by them."""
import jax.numpy as jnp
import numpy as np
import pytest

from touchdown_ros.core.ekf import Belief, extended_kalman_filter, position, rts_smoother
from touchdown_ros.core.smoothing import leave_one_out_residuals, mean_fall_and_standard_error


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


def test_mean_fall_and_its_standard_error_come_from_block_means_of_the_valid_samples():
    """The fall before - after per valid sample (all of them), and its standard error from the means of
    blocks of consecutive valid samples of each record (a short last block left out), as computed by hand."""
    rng = np.random.default_rng(5)
    before, after = rng.normal(1.0, 0.3, (2, 250)), rng.normal(0.9, 0.3, (2, 250))
    valid = np.ones((2, 250), dtype=bool)
    valid[1, 40:60] = False  # a gap: record 1 keeps 230 samples, two blocks of 100
    fall, standard_error = mean_fall_and_standard_error(before, after, valid, block=100)
    d0, d1 = before[0] - after[0], (before[1] - after[1])[valid[1]]
    means = np.array([d0[:100].mean(), d0[100:200].mean(), d1[:100].mean(), d1[100:200].mean()])
    assert fall == pytest.approx(np.concatenate([d0, d1]).mean())
    assert standard_error == pytest.approx(means.std(ddof=1) / 2.0)
    # a constant fall of many standard errors is told from one within the noise
    assert mean_fall_and_standard_error(before, before - 0.5, valid, block=100) == pytest.approx((0.5, 0.0), abs=1e-12)
    # fewer than two blocks: no standard error to tell by
    few = mean_fall_and_standard_error(before[:1, :150], after[:1, :150], valid[:1, :150], block=100)
    assert few == (pytest.approx(d0[:150].mean()), np.inf)
