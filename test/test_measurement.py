"""Measurement effects (issue #16 item 3): h(xi) beside phi in the EKF, smoother, training, live chunk and ranking.

The drops of the simulator here have a z sensor that reads 1.05 z + 20 um (`simulator.sensor_*`);
the estimator knows nothing of it unless the matching effects are switched on.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from touchdown_ros.core.diagnostics.regressors import effect_regressors
from touchdown_ros.core import effects as fx
from touchdown_ros.core.dynamics import measurement, phi
from touchdown_ros.core.ekf import Belief, ekf, model_measurement, position, state_reading, update, with_jacobian
from touchdown_ros.core.estimate import make_estimator
from touchdown_ros.core.input_policy import InputPolicy, split_record
from touchdown_ros.core.training import loss, make_batch
from touchdown_ros.core.types import STATE_SIZE
from touchdown_ros.io.coefficients import TrainingRecord, load_coefficients, save_coefficients
from touchdown_ros.io.config import load_config
from touchdown_ros.workflows.offline import estimate_record
from touchdown_ros.sim.campaign import CAMPAIGN
from touchdown_ros.sim.simulator import simulate_drop

from conftest import library_effects


GAIN, OFFSET = 1.05, 20e-6  # the z sensor of the simulated drops: 1, m
SENSOR = {"effects.active": ["sensor_gain_z", "sensor_offset_z"],
          "effects.sensor_gain_z.gain": GAIN, "effects.sensor_offset_z.offset": OFFSET}
XI = jnp.array([1e-4, -2e-4, -3e-4, 0.7, 0.01, -0.02, -0.3])


def _scaled_z(xi, p, rig):
    """User measurement effect: the z sensor reads (1 + scale) z."""
    return jnp.stack([0.0 * xi[2], 0.0 * xi[2], p["scale"] * xi[2]])


_scaled_z.parameters = {"scale": (0.0, "1", "relative scale error of z")}
_scaled_z.kind = "measurement"


def test_sensor_effects_change_h_not_phi():
    model = load_config().model()
    values = {"sensor_gain_z": {"gain": GAIN}, "sensor_offset_x": {"offset": OFFSET}}
    sensed = model._replace(effects=library_effects(["sensor_gain_z", "sensor_offset_x"], values))
    assert fx.LIBRARY["sensor_gain_y"].parameters["gain"][1] == "1"
    assert fx.LIBRARY["sensor_offset_y"].parameters["offset"][1] == "m"
    assert all(fx.LIBRARY[f"sensor_{k}_{a}"].kind == fx.MEASUREMENT for k in ("gain", "offset") for a in "xyz")
    n = model.law.state_size
    xi = jnp.zeros(n).at[: len(XI)].set(XI)
    np.testing.assert_array_equal(phi(sensed, xi), phi(model, xi))
    np.testing.assert_allclose(measurement(sensed, XI), [XI[0] + OFFSET, XI[1], GAIN * XI[2]], rtol=1e-15)
    _, H = model_measurement(sensed)(xi)
    np.testing.assert_allclose(H, np.eye(3, n) * np.array([1.0, 1.0, GAIN])[:, None], rtol=1e-15)
    assert model_measurement(model) is position
    with pytest.raises(ValueError, match="kind"):
        fx.Effect("bad", _scaled_z, _scaled_z.parameters, kind="torque")


def test_the_general_update_equals_the_papers_h_when_no_effect_acts():
    """h = (x, y, z) through the general path (H from jacfwd, H P by a product) gives the same
    numbers as H = [I 0] by slicing; so does a sensor effect at gain 1, offset 0."""
    P = jnp.diag(jnp.array([4e-12, 5e-12, 6e-12, 0.1, 1e-6, 2e-6, 3e-6])) + 1e-13
    belief, R, eta = Belief(XI, P), jnp.diag(jnp.full(3, 4e-12)), XI[:3] + 1e-6
    fast = update(belief, eta, R)
    general = update(belief, eta, R, with_jacobian(lambda xi: xi[:3]))
    for a, b in zip(jax.tree.leaves(fast), jax.tree.leaves(general)):
        np.testing.assert_array_equal(a, b)

    config = load_config()
    model, noise, h = config.model(), config.noise, config.sample_period
    identity = model._replace(effects=library_effects(["sensor_gain_z", "sensor_offset_z"]))
    etas = jnp.asarray(np.asarray(XI[:3]) + 2e-6 * np.random.default_rng(0).standard_normal((200, 3)))
    initial = Belief(jnp.zeros(model.law.state_size).at[:4].set(XI[:4]), jnp.diag(noise.initial))
    paper = jax.jit(lambda e: ekf(model, noise, h, initial, e))(etas)
    with_effects = jax.jit(lambda e: ekf(identity, noise, h, initial, e))(etas)
    for a, b in zip(jax.tree.leaves(paper), jax.tree.leaves(with_effects)):
        np.testing.assert_array_equal(a, b)


def test_user_measurement_effect_by_dotted_path_through_yaml_and_coefficient_file(tmp_path):
    config = load_config(overrides={"effects.active": ["scaled_z"], "effects.user.scaled_z": f"{__name__}:_scaled_z",
                                    "effects.scaled_z.scale": 0.05})
    (effect,) = config.effects.effects
    assert effect.kind == fx.MEASUREMENT and config.effects.values() == {"scaled_z": {"scale": 0.05}}
    np.testing.assert_allclose(measurement(config.model(), XI)[2], 1.05 * XI[2], rtol=1e-15)
    path = tmp_path / "c.yaml"
    save_coefficients(path, config.model().coeffs, config, TrainingRecord(bags=[], regularisation=0.0))
    loaded = load_coefficients(path, load_config()).effects
    assert loaded.effects[0].kind == fx.MEASUREMENT and loaded.values() == {"scaled_z": {"scale": 0.05}}


def test_measurement_regressor_is_the_force_it_stands_for():
    """In free flight phi's accelerations do not depend on position or velocity: a z gain g stands
    for the force (g - 1) m zddot = -(g - 1) m g_0, a z offset for none."""
    model = load_config().model()
    free = jnp.zeros((2, model.law.state_size)).at[:, :STATE_SIZE].set(
        [[0.0, 0.0, 0.0, 0.3, 0.0, 0.0, -0.1], [1e-5, 2e-5, -5e-5, 2.0, 0.01, 0.0, 0.2]]
    )
    J, f0 = effect_regressors(fx.LIBRARY["sensor_gain_z"], free, model)
    np.testing.assert_allclose(J[:, 2, 0], -model.rig.mass * model.rig.gravity, rtol=1e-12)
    np.testing.assert_array_equal(J[:, :2], 0.0)
    np.testing.assert_array_equal(f0, 0.0)
    J, _ = effect_regressors(fx.LIBRARY["sensor_offset_z"], free, model)
    np.testing.assert_array_equal(J, 0.0)
    # in axial contact the offset stands for the contact stiffness times it
    contact = jnp.zeros((1, model.law.state_size)).at[0, :4].set([0.0, 0.0, -model.rig.axial_clearance - 1e-6, 0.3])
    J, _ = effect_regressors(fx.LIBRARY["sensor_offset_z"], contact, model)
    np.testing.assert_allclose(J[0, 2, 0], model.nominal.k_Z, rtol=1e-9)


# ---------------------------------------------------------------- a simulated drop with the sensor error


@pytest.fixture(scope="module")
def sensed_drop():
    config = load_config(overrides={"simulator.drop_duration": 0.06, "simulator.sensor_gain_z": GAIN,
                                    "simulator.sensor_offset_z": OFFSET})
    return simulate_drop(config, CAMPAIGN[0], seed=3)


def _estimate(record, config):
    estimator = make_estimator(config.model(), config.noise, config.sample_period)
    record_input = split_record(record.stamps_ns, record.measured, InputPolicy.from_config(config))
    estimate, _ = estimate_record(config, record_input, estimator)
    rows = np.searchsorted(record.stamps_ns, estimate.stamps_ns)
    return estimate, rows


def test_simulated_sensor_error_and_the_effect_that_models_it(sensed_drop):
    record = sensed_drop
    clean = simulate_drop(load_config(overrides={"simulator.drop_duration": 0.06}), CAMPAIGN[0], seed=3)
    step = load_config().quantisation  # the same noise draws, each rounded to the ADC step
    np.testing.assert_allclose(record.measured[:, 2] - (GAIN * record.position[:, 2] + OFFSET),
                               clean.measured[:, 2] - clean.position[:, 2], rtol=0, atol=step * (1 + 1e-9))
    np.testing.assert_array_equal(record.measured[:, :2], clean.measured[:, :2])

    results = {}
    for label, overrides in (("without", {}), ("with", SENSOR)):
        estimate, rows = _estimate(record, load_config(overrides=overrides))
        error = np.asarray(estimate.filtered.state)[:, 2] - record.position[rows, 2]
        used = np.isfinite(np.asarray(estimate.nis))
        S = np.asarray(estimate.innovation_cov)[used]
        nll = np.mean(np.asarray(estimate.nis)[used] + np.log(np.linalg.det(S)))
        predicted = np.asarray(estimate.predicted_output)
        results[label] = (float(np.sqrt(np.mean(error**2))), float(nll), predicted, rows)
    without, with_ = results["without"], results["with"]
    # the filtered z follows the sensor without the effect, the true z with it (measured: 6.5 vs 12.2 um rms;
    # what is left is the reference rig's guessed contact law, not the simulator's)
    assert with_[0] < 0.65 * without[0], (with_[0], without[0])
    assert with_[1] < without[1], (with_[1], without[1])
    print(f"z error {with_[0]:.3g} vs {without[0]:.3g} m rms, innovation NLL {with_[1]:.4g} vs {without[1]:.4g}")
    # the one-step prediction is h(xi_{k,-}): in the sensor's units
    assert np.sqrt(np.mean((with_[2][:, 2] - record.measured[with_[3], 2]) ** 2)) < 20e-6


def _sensed_model_drop(config):
    """The model's own drop (test_streaming) as the z sensor of `GAIN`, `OFFSET` reads it."""
    from test_streaming import model_drop_record

    stamps, measured = model_drop_record(config)
    measured[:, 2] = GAIN * measured[:, 2] + OFFSET
    return stamps, measured


def test_training_loss_is_least_at_the_true_sensor_error():
    """On the model's own drop read by the erring sensor, both eq. 18 losses are lower with the
    sensor effects at the truth than at gain 1, offset 0, and their gradient points to the truth."""
    from test_streaming import CONFIG

    config = dataclasses.replace(CONFIG, effects=library_effects(SENSOR["effects.active"]))
    model, noise, h = config.model(), config.noise, config.sample_period
    _, measured = _sensed_model_drop(config)
    onset = int(round(0.02 / h))
    batch = make_batch([measured[onset : onset + 400]], np.asarray(noise.initial), gates=[(1.0, 1.0)])
    for kind in ("one_step", "nll"):
        @jax.jit
        def value(gain, offset):
            values = {"sensor_gain_z": {"gain": gain}, "sensor_offset_z": {"offset": offset}}
            effects = model.effects.with_values(values)
            return loss(model.coeffs, model, noise, h, batch, 0.0, effects, kind=kind)

        assert value(GAIN, OFFSET) < 0.5 * value(1.0, 0.0), kind
        assert jax.grad(value, argnums=0)(1.0, OFFSET) < 0.0 < jax.grad(value, argnums=0)(1.1, OFFSET), kind
        assert jax.grad(value, argnums=1)(GAIN, 0.0) < 0.0 < jax.grad(value, argnums=1)(GAIN, 2 * OFFSET), kind


def test_the_workbench_k_step_prediction_is_in_the_sensors_units():
    """The held-out k-step error that judges a candidate compares h(xi) k samples ahead with the
    measured: with the true sensor effects it is centred on the sensor noise, not on the offset
    (it compared the position, so a right sensor candidate raised the error by its own size)."""
    from test_streaming import CONFIG

    from touchdown_ros.core.selection import sample_measures

    values = {"sensor_gain_z": {"gain": GAIN}, "sensor_offset_z": {"offset": OFFSET}}
    config = dataclasses.replace(CONFIG, effects=library_effects(SENSOR["effects.active"], values))
    model, noise, h = config.model(), config.noise, config.sample_period
    _, measured = _sensed_model_drop(config)
    onset = int(round(0.02 / h))
    batch = make_batch([measured[onset : onset + 400]], np.asarray(noise.initial), gates=[(1.0, 1.0)])
    error = np.asarray(sample_measures(model, noise, h, batch, 20).k_step_error)[0, :, 2]
    error = error[np.isfinite(error)]
    assert error.size > 300 and abs(np.mean(error)) < 0.2 * OFFSET, np.mean(error)


def test_live_chunk_filter_equals_the_offline_filter_with_a_measurement_effect():
    from test_streaming import CHUNKS, CONFIG, assert_same, offline

    from touchdown_ros.core.streaming import StreamingEstimator, estimate_stream, make_chunk_filter

    values = {"sensor_gain_z": {"gain": GAIN}, "sensor_offset_z": {"offset": OFFSET}}
    sensor = library_effects(SENSOR["effects.active"], values)
    config = dataclasses.replace(CONFIG, effects=sensor)
    stamps, measured = _sensed_model_drop(config)
    reference = offline(stamps, measured, config)
    chunk = make_chunk_filter(config.model(), config.noise, config.sample_period)
    estimator = StreamingEstimator(config.model(), config.noise, config.stream_settings(chunk_sizes=CHUNKS),
                                   chunk)
    stream, _ = estimate_stream(estimator, stamps, measured, [37, 5, 200])
    assert_same(stream, reference)
    # and the effect changed the numbers: the same record without it filters to other states
    plain = offline(stamps, measured)
    assert not np.allclose(np.asarray(plain.filtered.state), np.asarray(reference.filtered.state), rtol=1e-6)


def test_the_filter_starts_from_the_state_the_onset_reading_shows():
    """The onset's reading is the sensor's (gain * z + offset): the filter starts from the position that
    reads it, and its first innovations are the noise's size, not the offset's; `state_reading` inverts a
    gain and an offset and leaves a model without measurement effects alone."""
    from test_streaming import CONFIG

    values = {"sensor_gain_z": {"gain": GAIN}, "sensor_offset_z": {"offset": OFFSET}}
    config = dataclasses.replace(CONFIG, effects=library_effects(SENSOR["effects.active"], values))
    model, noise, h = config.model(), config.noise, config.sample_period
    mean = jnp.zeros(model.law.state_size).at[:3].set(jnp.array([1e-5, -2e-5, -2e-4]))
    np.testing.assert_allclose(state_reading(model, mean)[:3], [1e-5, -2e-5, (-2e-4 - OFFSET) / GAIN], rtol=1e-12)
    assert state_reading(CONFIG.model(), mean) is mean
    _, measured = _sensed_model_drop(config)
    onset = int(round(0.02 / h))
    record = measured[onset : onset + 200]
    initial = Belief(jnp.asarray(np.nanmean(record[:5], axis=0).tolist() + [0.0] * (len(noise.initial) - 3)),
                     jnp.diag(jnp.asarray(noise.initial)))
    outputs = ekf(model, noise, h, initial, jnp.asarray(record))
    assert abs(float(outputs.prior.mean[0, 2]) - (float(initial.mean[2]) - OFFSET) / GAIN) < 1e-9
    first = np.asarray(outputs.innovation)[:5, 2]  # 21 um and more from the reading itself
    assert np.sqrt(np.mean(first**2)) < 2.5 * config.noise_rms, first
