"""The smoother's leave-one-out residuals (core.smoothing) and the factor on Q the trainer chooses by them;
the model's own force error in contact the force band carries."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from touchdown_ros.core.dynamics import contact_force_xyz, contact_forces, rk4_step
from touchdown_ros.core.ekf import Belief, ekf, extended_kalman_filter, position, rts_smoother
from touchdown_ros.core.smoothing import (
    leave_one_out_residuals,
    mean_fall_and_standard_error,
    mean_missing_force_variance,
    missing_force_squares,
)
from touchdown_ros.core.training import make_batch
from touchdown_ros.io.config import load_config


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


def _drop_of(model, n=800, seed=7):
    """A drop of the model itself from the bearing's centre (10 kHz, 2 um sensor noise): true states and
    measurements."""
    step = jax.jit(lambda xi: rk4_step(model, xi, 1e-5))
    xi, states = jnp.zeros(model.law.state_size).at[:2].set([3e-6, -2e-6]), []
    for _ in range(n):
        for _ in range(10):
            xi = step(xi)
        states.append(np.asarray(xi))
    states = np.array(states)
    return states, states[:, :3] + 2e-6 * np.random.default_rng(seed).standard_normal(states[:, :3].shape)


def test_the_missing_force_in_contact_is_the_contact_force_error_of_the_smoothed_estimate():
    """On a drop of a bearing twice as stiff axially as the filter's model, the force the smoother adds to
    the model in contact (rms per axis) is the smoothed estimate's own contact force error against the
    truth: on z between half of it and a little more (the smoother sees a short impact's force in part);
    with the right model a small fraction of that. Out of contact nothing counts. With the paper's friction, whose
    face friction k_ZR F_z carries the axial error sideways; with a spinning ring's the error on x is 3 N rms, below
    what the smoother adds on the noise alone (70 N with the right model)."""
    config = load_config(overrides={"contact.friction": "paper"})
    truth_model = config.model()._replace(nominal=config.nominal._replace(k_Z=2.0 * config.nominal.k_Z))
    states, etas = _drop_of(truth_model)
    batch = make_batch([etas], np.asarray(config.noise.initial))
    h = config.sample_period
    rms = {}
    for name, model in (("wrong", config.model()), ("right", truth_model)):
        squares, counted = missing_force_squares(model, config.noise, h, batch)
        counted = np.asarray(counted)[0]
        assert 100 < counted.sum() < len(etas) - 50  # the free fall before the impact does not count
        rms[name] = np.sqrt(mean_missing_force_variance(squares, counted[None]))
        smoothed = rts_smoother(ekf(model, config.noise, h, Belief(batch.initial_mean[0], batch.initial_cov[0]),
                                    batch.etas[0])).mean
        error = contact_force_xyz(jax.vmap(lambda xi: contact_forces(model, xi))(smoothed)) - \
            contact_force_xyz(jax.vmap(lambda xi: contact_forces(truth_model, xi))(jnp.asarray(states)))
        true_rms = np.sqrt(np.mean(np.asarray(error).T[counted] ** 2, axis=0))
        assert np.all(rms[name] < 1.2 * true_rms), (name, rms[name], true_rms)
        if name == "wrong":
            assert true_rms[2] > 0.3 * config.rig.mass * config.rig.gravity  # more than 0.3 of the weight
            assert rms[name][2] > 0.5 * true_rms[2], (rms[name], true_rms)
    assert rms["right"][2] < 0.2 * rms["wrong"][2], rms
