"""Eq. 18 training: the gradient is right and fitting recovers a known model."""
import dataclasses
import io

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import compilations

from touchdown_ros.core.dynamics import rk4_step
from touchdown_ros.core.pkbkr import coloured, rkhs_distance, whitened, whitening
from touchdown_ros.core.training import hold_out, loss, make_batch, prediction_errors
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.config import load_config
from touchdown_ros.workflows.train import Trainable, TrainingData, fit, fit_regularisation_path

CONFIG = load_config()
H = CONFIG.sample_period


def records_of(coeffs, count=3, samples=500, seed=0):
    model = CONFIG.model(coeffs)
    step = jax.jit(lambda s: rk4_step(model, s, H / 10))
    rng = np.random.default_rng(seed)
    records = []
    for b in range(count):
        xi = jnp.zeros(model.law.state_size).at[:2].set([3e-6 * b, -2e-6])
        states = []
        for _ in range(samples):
            for _ in range(10):
                xi = step(xi)
            states.append(np.asarray(xi[:3]))
        records.append(np.array(states) + CONFIG.noise_rms * rng.standard_normal((samples, 3)))
    return records


def true_coeffs():
    rng = np.random.default_rng(3)
    zeros = Coefficients.zeros(CONFIG.kernel)
    return Coefficients(0.6 * rng.standard_normal(zeros.alpha_R.shape), 0.6 * rng.standard_normal(zeros.alpha_Z.shape))


def test_loss_gradient_matches_finite_differences():
    records = records_of(true_coeffs(), count=2, samples=300)
    batch = make_batch(records, np.asarray(CONFIG.noise.initial))
    model = CONFIG.model()
    coeffs = Coefficients.zeros(CONFIG.kernel)
    f = jax.jit(lambda c: loss(c, model, CONFIG.noise, H, batch, 1e-3))
    grad = jax.grad(lambda c: loss(c, model, CONFIG.noise, H, batch, 1e-3))(coeffs)
    for field, index in (("alpha_Z", (0, 2)), ("alpha_Z", (1, 7)), ("alpha_R", (0, 12))):
        step = 1e-6
        plus = coeffs._replace(**{field: getattr(coeffs, field).at[index].add(step)})
        minus = coeffs._replace(**{field: getattr(coeffs, field).at[index].add(-step)})
        fd = (float(f(plus)) - float(f(minus))) / (2 * step)
        assert np.isclose(float(getattr(grad, field)[index]), fd, rtol=1e-4, atol=1e-6), (field, index)


def test_loss_is_the_mean_output_error_plus_lambda_times_the_rkhs_distance():
    """Eq. 18 taken apart: loss = sum over valid samples of |eta - h(xi_-)|^2 / sigma^2 divided by their
    number, + lambda * sum_k alpha_k^T K alpha_k with K = Q(T, T) written out here, not taken from pkbkr."""
    records = records_of(true_coeffs(), count=2, samples=120)
    batch = make_batch(records, np.asarray(CONFIG.noise.initial))
    model = CONFIG.model()
    rng = np.random.default_rng(18)
    zeros = Coefficients.zeros(CONFIG.kernel)
    coeffs = Coefficients(
        0.3 * rng.standard_normal(zeros.alpha_R.shape), 0.3 * rng.standard_normal(zeros.alpha_Z.shape)
    )
    kernel = CONFIG.kernel

    def gram(T):
        T = np.asarray(T)
        return np.exp(-np.sum((T[:, None] - T[None]) ** 2, axis=-1) / (2.0 * kernel.width**2))

    distance = sum(
        float(a @ gram(T) @ a)
        for alpha, T in ((coeffs.alpha_R, kernel.T_R), (coeffs.alpha_Z, kernel.T_Z))
        for a in np.asarray(alpha)
    )
    assert distance > 1.0

    errors = np.asarray(prediction_errors(model._replace(coeffs=coeffs), CONFIG.noise, H, batch))
    valid = np.asarray(batch.valid)
    data = np.sum((errors**2 / np.asarray(CONFIG.noise.measurement))[valid]) / np.sum(valid)

    lam1, lam2 = 1e-3, 0.25
    loss1 = float(loss(coeffs, model, CONFIG.noise, H, batch, lam1))
    loss2 = float(loss(coeffs, model, CONFIG.noise, H, batch, lam2))
    np.testing.assert_allclose(loss2 - loss1, (lam2 - lam1) * distance, rtol=1e-9)
    np.testing.assert_allclose(loss1, data + lam1 * distance, rtol=1e-9)
    np.testing.assert_allclose(float(loss(coeffs, model, CONFIG.noise, H, batch, 0.0)), data, rtol=1e-9)


def test_fit_recovers_the_loss_of_the_true_model():
    truth = true_coeffs()
    records = records_of(truth)
    data = TrainingData((), tuple(records))
    result = fit(CONFIG, data, regularisation=1e-5, max_steps=20)
    batch = make_batch(records, np.asarray(CONFIG.noise.initial))
    true_loss = float(loss(truth, CONFIG.model(), CONFIG.noise, H, batch, 0.0))
    assert result.initial_loss > 1.05 * true_loss  # the constant model is measurably wrong here
    assert result.final_loss < true_loss + 0.05 * (result.initial_loss - true_loss)
    assert result.history == tuple(sorted(result.history, reverse=True))
    # the fit runs in whitened coordinates: the coefficients it returns are the ones its loss belongs to
    train_batch = hold_out(batch, CONFIG.held_out_block_samples(), CONFIG.training.held_out_every)
    fitted = float(loss(result.coeffs, CONFIG.model(), CONFIG.training_noise(), H, train_batch, 1e-5,
                        kind=CONFIG.training.loss))
    assert fitted == pytest.approx(result.final_loss, rel=1e-9)


def test_whitened_coordinates_turn_the_rkhs_distance_into_a_squared_norm():
    """beta_k = L^T alpha_k with K = L L^T: |beta|^2 is eq. 18's penalty, and alpha comes back from beta."""
    rng = np.random.default_rng(7)
    zeros = Coefficients.zeros(CONFIG.kernel)
    alpha = Coefficients(rng.standard_normal(zeros.alpha_R.shape), rng.standard_normal(zeros.alpha_Z.shape))
    w = whitening(CONFIG.kernel)
    beta = whitened(w, alpha)
    norm = float(jnp.sum(beta.alpha_R**2) + jnp.sum(beta.alpha_Z**2))
    assert norm == pytest.approx(float(rkhs_distance(CONFIG.kernel, alpha)), rel=1e-7)  # (L L^T = K + 1e-9 I)
    back = coloured(w, beta)
    np.testing.assert_allclose(back.alpha_R, alpha.alpha_R, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(back.alpha_Z, alpha.alpha_Z, rtol=1e-9, atol=1e-9)


def test_lambda_is_chosen_by_the_held_out_loss():
    """Stage 2 along lambda (training.regularisation as a list): a model with large PKBKR terms is
    held back by a large lambda, so the held-out loss falls on at the small one, which is chosen;
    both fits start from the same coefficients."""
    records = records_of(true_coeffs(), count=3, samples=400)
    data = TrainingData((), tuple(records))
    start = Trainable(Coefficients.zeros(CONFIG.kernel), CONFIG.effects)
    lambdas = []
    config = dataclasses.replace(CONFIG, training=dataclasses.replace(CONFIG.training, patience=3))
    path = fit_regularisation_path(
        config, data, [1e-5, 1e2], start, 100, on_step=lambda lam, *_: lambdas.append(lam), stream=io.StringIO()
    )
    first, second = path.tried
    assert [first["regularisation"], second["regularisation"]] == [1e2, 1e-5]
    assert lambdas[0] == 1e2 and lambdas[-1] == 1e-5 and sorted(lambdas, reverse=True) == lambdas
    assert second["held_out_loss_start"] == pytest.approx(first["held_out_loss_start"], rel=1e-12)
    assert second["held_out_loss"] < first["held_out_loss"] and second["kept_step"] > 0
    assert path.regularisation == 1e-5 and path.result.steps == second["steps"]


def test_the_one_standard_error_rule_takes_the_simplest_fit_the_held_out_blocks_cannot_tell_from_the_best():
    """`within_one_standard_error`: fits from the most to the least regularised, by their held-out errors' block
    sums. A simpler fit above the best by less than the paired differences' standard error is chosen; one above it
    by more is not; the numbers are the paired mean and standard error per held-out sample. `held_out_block_sums`
    adds up each held-out run of valid samples of each record."""
    from touchdown_ros.core.training import held_out_block_sums, within_one_standard_error

    rng = np.random.default_rng(7)
    best = 100.0 + rng.standard_normal(40)
    noise = rng.standard_normal(40)
    close = best + 0.05 + noise  # above by 0.05 a block on average, sd 1: within one standard error (0.16)
    far = best + 2.0 + noise  # above by 2 a block: not
    chosen, above, error = within_one_standard_error([far, close, best], samples=400)
    assert chosen == 1
    differences = close - best
    assert above[1] == pytest.approx(differences.sum() / 400, rel=1e-12)
    assert error[1] == pytest.approx(np.sqrt(40) * np.std(differences, ddof=1) / 400, rel=1e-12)
    assert above[2] == 0.0 and above[0] > error[0] > 0.0
    assert within_one_standard_error([far, best, close], samples=400)[0] == 1  # the best itself
    assert within_one_standard_error([far, best], samples=400)[0] == 1

    batch = make_batch([np.zeros((12, 3)), np.zeros((10, 3))], np.asarray(CONFIG.noise.initial))
    batch = hold_out(batch, block=2, every=3)._replace(valid=jnp.asarray(np.arange(12) != 5)[None, :].repeat(2, 0))
    errors = np.arange(24.0).reshape(2, 12)
    held = np.asarray(batch.held_out) & np.asarray(batch.valid)
    sums = held_out_block_sums(errors, batch)
    # record 0 holds out samples 4-5 (5 not valid) and 10-11, record 1 samples 2-3 and 8-9 (`hold_out`'s shift)
    assert sums.sum() == errors[held].sum() and len(sums) == 4
    np.testing.assert_array_equal(sums, [4.0, 21.0, 29.0, 41.0])


def test_the_path_by_one_standard_error_records_each_lambdas_distance_from_the_lowest():
    """With `training.regularisation_choice: one_standard_error` the path records each lambda's held-out loss
    above the lowest and its standard error, and chooses by them; the block sums add up to the held-out loss the
    optimiser kept. (Here, large PKBKR terms in the truth, the smaller lambda's fall is about one standard error
    of its 4 blocks: the rule asks a lot of few held-out blocks.)"""
    records = records_of(true_coeffs(), count=3, samples=400)
    data = TrainingData((), tuple(records))
    start = Trainable(Coefficients.zeros(CONFIG.kernel), CONFIG.effects)
    config = dataclasses.replace(
        CONFIG, training=dataclasses.replace(CONFIG.training, patience=3, regularisation_choice="one_standard_error")
    )
    stream = io.StringIO()
    path = fit_regularisation_path(config, data, [1e-5, 1e2], start, 100, stream=stream)
    first, second = path.tried
    for t in path.tried:
        assert np.sum(t["held_out_block_sums"]) / t["held_out_samples"] == pytest.approx(t["held_out_loss"], rel=1e-9)
    assert second["held_out_loss"] < first["held_out_loss"] and second["held_out_above_lowest"] == 0.0
    assert first["held_out_above_lowest"] == pytest.approx(first["held_out_loss"] - second["held_out_loss"], rel=1e-9)
    assert first["standard_error"] > 0.0
    if first["held_out_above_lowest"] <= first["standard_error"]:
        assert path.regularisation == 1e2 and "chosen 100 (within one standard error of the lowest, 1e-05" in (
            stream.getvalue()
        )
        assert path.result.steps == first["steps"]
    else:
        assert path.regularisation == 1e-5 and "chosen 1e-05 (the lowest)" in stream.getvalue()
    assert "held_out_block_sums" not in path.as_dict()["tried"][0]
    chosen = next(t for t in path.tried if t["regularisation"] == path.regularisation)
    assert chosen["final_loss"] == path.result.final_loss  # what a resumed path's choice rebuilds the fit's record from


def test_an_interrupted_lambda_path_goes_on_where_it_stopped():
    """Resumed after its first lambda (as `train --resume` does from the checkpoint's record), the path
    fits only the lambdas it had not finished and ends where the uninterrupted path ends."""
    from touchdown_ros.workflows.train import PathProgress

    records = records_of(true_coeffs(), count=3, samples=300)
    data = TrainingData((), tuple(records))
    start = Trainable(Coefficients.zeros(CONFIG.kernel), CONFIG.effects)
    config = dataclasses.replace(CONFIG, training=dataclasses.replace(CONFIG.training, patience=3))
    lambdas, saved = [1e2, 1e-1, 1e-5], []
    whole = fit_regularisation_path(config, data, lambdas, start, 100, stream=io.StringIO(), on_lambda=saved.append)
    assert [t["regularisation"] for t in whole.tried] == [1e2, 1e-1, 1e-5] and len(saved) >= 2
    fitted = []
    resumed = fit_regularisation_path(
        config, data, lambdas, start, 100, on_step=lambda lam, *_: fitted.append(lam), stream=io.StringIO(),
        progress=PathProgress(saved[0].tried, saved[0].chosen),
    )
    assert set(fitted) == {1e-1, 1e-5}
    assert resumed.tried == whole.tried and resumed.regularisation == whole.regularisation
    np.testing.assert_allclose(resumed.result.coeffs.alpha_Z, whole.result.coeffs.alpha_Z, rtol=1e-9, atol=1e-12)
    # interrupted within lambda 0.1: it continues from where it stood, not from the start
    middle = saved[1].chosen[0]
    interrupted = PathProgress(saved[0].tried, saved[0].chosen, Trainable(middle.coeffs, middle.effects))
    fitted.clear()
    fit_regularisation_path(
        config, data, lambdas, start, 100, on_step=lambda lam, step, value, _: fitted.append((lam, value)),
        stream=io.StringIO(), progress=interrupted,
    )
    assert fitted[0][0] == 1e-1 and fitted[0][1] <= middle.final_loss + 1e-12


def test_records_spread_over_devices_give_the_same_loss_and_gradient():
    """The trainer's sharded loss (one share of the records per XLA host device, batch padded
    with uncounted copies) equals the plain one."""
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    from touchdown_ros.core.training import RECORDS, pad_records

    records = records_of(true_coeffs(), count=3, samples=200)
    batch = make_batch(records, np.asarray(CONFIG.noise.initial))
    mesh = Mesh(np.array(jax.devices()), (RECORDS,))
    padded = pad_records(batch, 2 * mesh.size)  # 3 records -> 4 or more: uncounted copies included
    assert padded.etas.shape[0] > 3 and padded.etas.shape[0] % mesh.size == 0
    assert int(np.sum(padded.valid)) == int(np.sum(batch.valid))
    padded = jax.device_put(padded, NamedSharding(mesh, P(RECORDS)))
    model, coeffs = CONFIG.model(), true_coeffs()

    def plain(c):
        return loss(c, model, CONFIG.noise, H, batch, 1e-3)

    def sharded(c):
        return loss(c, model, CONFIG.noise, H, padded, 1e-3, mesh=mesh)

    value, grad = jax.jit(jax.value_and_grad(plain))(coeffs)
    value_s, grad_s = jax.jit(jax.value_and_grad(sharded))(coeffs)
    np.testing.assert_allclose(float(value_s), float(value), rtol=1e-12)
    for a, b in zip(jax.tree.leaves(grad_s), jax.tree.leaves(grad)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12 * float(np.max(np.abs(b))))


def test_held_out_blocks_are_left_out_of_the_loss_and_measured_apart():
    """hold_out: one block in `every` per record, shifted from record to record; the fitted and
    held-out errors are the means over their own samples and add up to the whole record's."""
    from touchdown_ros.core.training import hold_out, output_errors

    records = records_of(true_coeffs(), count=3, samples=300)
    batch = make_batch(records, np.asarray(CONFIG.noise.initial))
    held = hold_out(batch, block=20, every=5)
    mask = np.asarray(held.held_out)
    assert mask.mean() == np.float64(0.2)
    first_held = [int(np.argmax(row)) for row in mask]
    assert first_held == [80, 60, 40]  # block 4, then 3, then 2: a different phase per record
    assert all(np.all(np.diff(np.flatnonzero(row)[:20]) == 1) for row in mask)  # contiguous blocks

    model = CONFIG.model(true_coeffs())
    whole, none = output_errors(model, CONFIG.noise, H, batch, kind="nll")
    fitted, held_error = output_errors(model, CONFIG.noise, H, held, kind="nll")
    assert np.isnan(float(none))
    assert float(fitted) != float(whole) and np.isfinite(float(held_error))
    np.testing.assert_allclose(0.8 * float(fitted) + 0.2 * float(held_error), float(whole), rtol=1e-12)
    assert float(loss(true_coeffs(), CONFIG.model(), CONFIG.noise, H, held, 0.0, kind="nll")) == float(fitted)


def test_minimise_keeps_the_step_with_the_lowest_held_out_loss_and_stops_on_patience():
    """Early stopping: a loss that keeps falling while the held-out loss rises from the start
    keeps the start and stops after `patience` steps; one that falls then rises keeps its minimum."""
    import io

    from scipy.optimize import rosen, rosen_der

    from touchdown_ros.workflows.optimise import minimise

    start = np.array([-1.2, 1.0, -0.5, 0.8])

    def rising(theta):
        return rosen(theta), rosen_der(theta), float(np.sum((theta - start) ** 2))

    theta, convergence = minimise(rising, start, 200, 1e-9, "test", io.StringIO(), patience=4)
    assert convergence.converged and convergence.kept_step == 0 and convergence.steps == 4
    np.testing.assert_array_equal(theta, start)
    assert convergence.final_loss == convergence.initial_loss

    target = np.array([0.0, 0.0, 0.2, 0.0])

    def valley(theta):
        return rosen(theta), rosen_der(theta), float(np.sum((theta - target) ** 2))

    theta, convergence = minimise(valley, start, 200, 1e-9, "test", io.StringIO(), patience=5)
    kept = convergence.kept_step
    assert 0 < kept < convergence.steps and convergence.held_out[kept] == min(convergence.held_out)
    assert convergence.final_loss == convergence.history[kept - 1]
    assert float(np.sum((theta - target) ** 2)) == min(convergence.held_out)


def test_minimise_counts_the_loss_evaluations_its_line_searches_took():
    """The convergence record counts each point the loss was evaluated at (L-BFGS's line searches take more than one
    a step): on Rosenbrock's function as many as scipy's L-BFGS-B counts alone, and more than the steps; the
    coefficient file's record has them, and the closing line says them."""
    import io

    from scipy.optimize import minimize, rosen, rosen_der

    from touchdown_ros.workflows.optimise import minimise

    start = np.array([-1.2, 1.0, -0.5, 0.8])
    calls = []

    def loss(theta):
        calls.append(np.array(theta))
        return rosen(theta), rosen_der(theta)

    log = io.StringIO()
    _, convergence = minimise(loss, start, 200, 1e-12, "rosen", log)
    reference = minimize(lambda x: (rosen(x), rosen_der(x)), start, jac=True, method="L-BFGS-B",
                         options={"maxiter": 200, "ftol": 1e-12, "gtol": 1e-12, "maxls": 40})
    assert convergence.evaluations == len(calls) == reference.nfev, (convergence.evaluations, reference.nfev)
    assert convergence.evaluations > convergence.steps + 1
    assert convergence.as_dict()["evaluations"] == convergence.evaluations
    assert f"after {convergence.steps} steps ({convergence.evaluations} loss evaluations)" in log.getvalue()


def test_minimise_restarted_where_the_losss_change_stopped_it_goes_on_down_the_valley():
    """`restarts`: L-BFGS-B stopped by the relative-reduction test on a short step starts again from there, its
    curvature memory cleared, while a restart lowers the loss by more than the tolerance (diagnose's fits from the
    friction grid, `FRICTION_START_RESTARTS`). On Rosenbrock's valley at a loose tolerance the first run stops after
    a few steps far from the minimum; the restarts walk the valley."""
    import io

    from scipy.optimize import rosen, rosen_der

    from touchdown_ros.workflows.optimise import minimise

    def loss(theta):
        return rosen(theta), rosen_der(theta)

    start = np.array([-1.2, 1.0])
    _, once = minimise(loss, start, 200, 1.0e-2, "rosen", io.StringIO())
    log = io.StringIO()
    theta, restarted = minimise(loss, start, 200, 1.0e-2, "rosen", log, restarts=3)
    assert "REDUCTION OF F" in once.reason and once.final_loss > 1.0
    assert "restarted where the loss's change stopped it" in log.getvalue()
    assert restarted.final_loss < 0.01 * once.final_loss and restarted.steps > once.steps
    assert restarted.final_loss == rosen(theta) and len(restarted.history) == restarted.steps


def test_a_fit_restarted_records_both_runs_steps_and_losses():
    """A fit restarted (stage 1's damping or friction restart) is one record of both runs: its loss history has a
    loss for each of the steps it counts, from the first run's start to the second's end, as `touchdown report`
    draws it; the evaluations and seconds of both add up."""
    import io

    from scipy.optimize import rosen, rosen_der

    from touchdown_ros.workflows.calibrate import after_restart
    from touchdown_ros.workflows.optimise import minimise

    def loss(theta):
        return rosen(theta), rosen_der(theta)

    log = io.StringIO()
    theta, first = minimise(loss, np.array([-1.2, 1.0, -0.5, 0.8]), 5, 1e-12, "first", log)
    _, again = minimise(loss, theta + 0.3, 200, 1e-12, "again", log)
    record = after_restart(first, again, "friction", 200).as_dict()
    assert record["steps"] == first.steps + again.steps == 5 + again.steps
    assert len(record["loss_history"]) == record["steps"] + 1
    assert record["loss_history"][0] == first.initial_loss
    assert record["loss_history"][5] == first.final_loss
    assert record["loss_history"][-1] == record["final_loss"] == again.final_loss
    assert record["evaluations"] == first.evaluations + again.evaluations
    assert "5 steps before a friction restart" in record["reason"]


def test_gauss_newton_finds_a_nonlinear_least_squares_minimum_in_a_few_steps_within_its_bounds():
    """Levenberg-Marquardt on J = |r(theta)|^2 / N of a decaying oscillation (a nonlinear least squares problem,
    J's Gauss-Newton Hessian 2 A^T A / N): the minimum scipy's least_squares finds, in a few steps where L-BFGS
    takes many more; with a bound the minimum lies beyond, it stops on the bound, which the gradient pushes
    against; a start where the loss is not finite is reported, not stepped from."""
    from scipy.optimize import least_squares

    from touchdown_ros.workflows.optimise import DIVERGED_LOSS, gauss_newton, minimise

    t = np.linspace(0.0, 1.0, 200)
    rng = np.random.default_rng(2)
    data = 2.0 * np.exp(-3.0 * t) * np.cos(7.0 * t) + 0.01 * rng.standard_normal(t.size)

    def residual(theta):
        a, b, w = theta
        return a * np.exp(-b * t) * np.cos(w * t) - data

    def jacobian(theta):
        a, b, w = theta
        e = np.exp(-b * t)
        return np.stack([e * np.cos(w * t), -a * t * e * np.cos(w * t), -a * t * e * np.sin(w * t)], axis=1)

    def terms(theta):
        r, A = residual(theta), jacobian(theta)
        return float(r @ r) / t.size, 2.0 * A.T @ r / t.size, 2.0 * A.T @ A / t.size

    def value(theta):
        r = residual(theta)
        return float(r @ r) / t.size

    start = np.array([1.0, 1.0, 6.0])
    expected = least_squares(residual, start, jac=jacobian, xtol=1e-14, ftol=1e-14).x
    theta, convergence = gauss_newton(terms, value, start, 100, 1e-10, "decay", io.StringIO())
    assert convergence.converged and convergence.final_loss < convergence.initial_loss
    np.testing.assert_allclose(theta, expected, rtol=1e-5)
    _, by_lbfgs = minimise(lambda x: terms(x)[:2], start, 500, 1e-10, "decay", io.StringIO())
    assert convergence.steps < 15 and convergence.steps * 2 < by_lbfgs.steps

    bounded, at_bound = gauss_newton(terms, value, start, 100, 1e-10, "decay", io.StringIO(),
                                     bounds=[(-np.inf, np.inf), (0.0, 2.5), (-np.inf, np.inf)])
    assert at_bound.converged and bounded[1] == 2.5 and terms(bounded)[1][1] < 0.0
    assert at_bound.final_loss > convergence.final_loss

    def spotty(theta):  # the tangents diverge beyond a = 1.9 (short of the minimum) where the loss does not
        return (np.nan, *terms(theta)[1:]) if theta[0] > 1.9 else terms(theta)

    held_back, spotted = gauss_newton(spotty, value, start, 100, 1e-10, "spotty", io.StringIO())
    assert held_back[0] <= 1.9 and spotted.final_loss == value(held_back) < spotted.initial_loss

    text = io.StringIO()
    _, diverged = gauss_newton(lambda x: (np.nan, x, np.eye(3)), value, start, 100, 1e-10, "nan", text)
    assert not diverged.converged and diverged.steps == 0 and diverged.initial_loss == DIVERGED_LOSS
    assert "not finite at the start" in text.getvalue()


def test_gauss_newton_hands_a_stalled_fit_to_its_fallback():
    """Where the information understates the curvature and misses a coupling (a misfitted model's Fisher
    information), Levenberg-Marquardt creeps along the valley of a quadratic heavily damped and reaches its step
    cap short of the minimum; with L-BFGS as its fallback it hands over after STALL_STEPS such steps and the fit
    ends at the minimum, the steps and history both runs'. A step far below its predicted fall is a stall too."""
    from touchdown_ros.workflows.optimise import STALL_STEPS, gauss_newton, minimise

    A, b = np.array([[1.0, 0.999], [0.999, 1.0]]), np.array([1.0, -0.5])

    def value(x):
        return float(0.5 * x @ A @ x - b @ x)

    def terms(x):
        return value(x), A @ x - b, np.eye(2) / 20.0

    def by_lbfgs(x, steps):
        return minimise(lambda y: (value(y), A @ y - b), x, steps, 1e-12, "valley, L-BFGS", io.StringIO())

    start, minimum = np.array([3.0, -2.0]), np.linalg.solve(A, b)
    _, alone = gauss_newton(terms, value, start, 100, 1e-12, "valley", io.StringIO())
    assert not alone.converged and alone.steps == 100 and alone.final_loss > value(minimum) + 100.0
    text = io.StringIO()
    theta, handed = gauss_newton(terms, value, start, 100, 1e-12, "valley", text, fallback=by_lbfgs)
    assert handed.converged and "stalled" in handed.reason and "L-BFGS goes on" in text.getvalue()
    np.testing.assert_allclose(theta, minimum, rtol=1e-6)
    assert STALL_STEPS < handed.steps == len(handed.history) < 100 and handed.final_loss == handed.history[-1]

    # An information half the curvature: the first step overshoots the minimum to nearly the other side, its loss
    # falling 1 % of the predicted fall and below the tolerance: alone that ends the fit as if converged; it is a
    # stall, and the fallback goes on to the minimum.
    def square(x):
        return float(0.5 * x @ x)

    def overshooting(x):
        return square(x), x.copy(), np.eye(1) / 1.99

    def by_lbfgs_1d(x, steps):
        return minimise(lambda y: (square(y), y.copy()), x, steps, 0.05, "square, L-BFGS", io.StringIO())

    far, fooled = gauss_newton(overshooting, square, np.array([1.0]), 100, 0.05, "square", io.StringIO())
    assert fooled.steps == 1 and fooled.final_loss > 0.45 and far[0] < -0.9
    near, handed = gauss_newton(overshooting, square, np.array([1.0]), 100, 0.05, "square", io.StringIO(),
                                fallback=by_lbfgs_1d)
    assert handed.converged and "of its predicted fall" in handed.reason and abs(near[0]) < 0.05


def test_progress_reaches_stderr_as_it_is_when_written(monkeypatch):
    """The workflows' default progress stream looks sys.stderr up at each write, so a redirection made
    after the modules were imported (a notebook, a test's capture) receives the lines."""
    from touchdown_ros.workflows.optimise import minimise

    redirected = io.StringIO()
    monkeypatch.setattr("sys.stderr", redirected)
    theta, convergence = minimise(lambda x: (float(x @ x), 2.0 * x), np.array([1.0, -2.0]), 20, 1e-9, "quadratic")
    assert convergence.converged and np.allclose(theta, 0.0, atol=1e-6)
    assert "[quadratic step 1/<=20]" in redirected.getvalue() and "[quadratic] converged" in redirected.getvalue()


def test_a_compilation_queued_first_ahead_is_compiled_before_those_queued_earlier():
    """`Ahead.compile_first` puts a program needed sooner (stage 1's loss alone) before the ones queued
    before it (stage 2's), so the call that needs it first does not wait behind them."""
    from touchdown_ros.workflows.ahead import Ahead

    def later(x):
        return x * 3.0

    def sooner(x):
        return x + 3.0

    def run() -> None:
        with Ahead(io.StringIO()) as ahead:
            ahead.compile("later", jax.jit(later), np.zeros(7))
            ahead.compile_first("sooner", jax.jit(sooner), np.zeros(7))
            ahead.start()
            ahead.wait("sooner")
            ahead.wait("later")

    _, compiled = compilations({"jit(later)", "jit(sooner)"}, run)
    assert [name for name, _ in compiled] == ["jit(sooner)", "jit(later)"]


def test_a_compilation_left_under_way_by_an_earlier_test_is_not_counted_as_the_runs():
    """`Ahead.close` lets a compilation under way finish in the background; one that an earlier test left
    (its `train` ended early) and that ends during a later test's run is not that run's (a fresh clone's
    CI, 2026-12-03: stage 2's program counted twice). One in a thread the run starts is."""
    import threading

    from touchdown_ros.workflows.ahead import THREAD_NAME

    def leftover(x):
        return x * 11.0

    def own(x):
        return x * 13.0

    release = threading.Event()
    earlier = threading.Thread(target=lambda: release.wait(20.0) and jax.jit(leftover).lower(np.zeros(3)).compile(),
                               name=f"{THREAD_NAME}_0")
    earlier.start()

    def run() -> None:
        release.set()
        earlier.join()
        started = threading.Thread(target=lambda: jax.jit(own).lower(np.zeros(3)).compile(), name=f"{THREAD_NAME}_0")
        started.start()
        started.join()

    try:
        _, compiled = compilations({"jit(leftover)", "jit(own)"}, run)
    finally:
        release.set()
    assert compiled == [("jit(own)", f"{THREAD_NAME}_0")]


def test_a_compilation_waited_for_before_its_turn_is_compiled_at_once_beside_the_one_under_way():
    """A program needed while the background thread still compiles another (with a spinning ring, stage
    1's standard errors while stage 2's compiles) is compiled at once beside it, not after it."""
    import threading

    from touchdown_ros.workflows.ahead import THREAD_NAME, Ahead

    release, finished = threading.Event(), threading.Event()

    class Lengthy:
        """A program whose compilation lasts until released (at most 20 s)."""

        def lower(self, *args, **kwargs) -> "Lengthy":
            return self

        def compile(self) -> None:
            release.wait(20.0)
            finished.set()

    def needed(x):
        return x - 5.0

    def run() -> bool:
        """Whether the lengthy compilation was still under way when the needed one was done."""
        try:
            with Ahead(io.StringIO()) as ahead:
                ahead.compile("under way", Lengthy())
                ahead.compile("needed", jax.jit(needed), np.zeros(5))
                ahead.start()
                ahead.wait("needed")
                under_way_meanwhile = not finished.is_set()
                release.set()
                ahead.wait("under way")
            return under_way_meanwhile
        finally:
            release.set()

    under_way_meanwhile, compiled = compilations({"jit(needed)"}, run)
    assert under_way_meanwhile
    assert compiled == [("jit(needed)", f"{THREAD_NAME}-needed_0")]


def test_a_wait_for_a_compilation_ahead_is_reported_when_it_blocks(monkeypatch):
    """Where the work waits for a program compiled ahead (the trainer's silent stretches), `Ahead.wait`
    says how long and for which; a program already compiled when needed is not reported."""
    import time

    from touchdown_ros.workflows import ahead as ahead_module

    monkeypatch.setattr(ahead_module, "REPORTED_WAIT", 0.1)

    class Slow:
        """A program whose compilation takes 0.4 s."""

        def lower(self, *args, **kwargs) -> "Slow":
            return self

        def compile(self) -> None:
            time.sleep(0.4)

    class Quick(Slow):
        def compile(self) -> None:
            pass

    stream = io.StringIO()
    with ahead_module.Ahead(stream) as ahead:
        ahead.compile("the quick program", Quick())
        ahead.compile("the slow program", Slow())
        ahead.start()
        ahead.wait("the quick program")
        ahead.wait("the slow program")
    lines = stream.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("[compile] waited ") and lines[0].endswith(" s for the slow program")
    assert 0.1 <= float(lines[0].split()[2]) < 5.0, lines


def test_a_compilation_ahead_that_fails_leaves_a_note_and_the_call_compiles_it():
    """`Ahead` is an optimisation: a program it cannot compile is reported and compiled when called."""
    from touchdown_ros.workflows.ahead import Ahead

    def halve(x):
        if x.shape[0] != 4:
            raise ValueError(f"no program for {x.shape[0]} samples")
        return x / 2

    stream = io.StringIO()
    program = jax.jit(halve)
    with Ahead(stream) as ahead:
        ahead.compile("the halving program", program, np.zeros(3))
        ahead.compile("a program waited for before the start", program, np.zeros(2))
        ahead.wait("a program waited for before the start")  # dropped: the call compiles it
        ahead.start()
        ahead.wait("the halving program")
        ahead.wait("a program never queued")  # nothing to wait for
    assert "compiling the halving program ahead failed (ValueError: no program for 3 samples)" in stream.getvalue()
    assert "2 samples" not in stream.getvalue()
    np.testing.assert_array_equal(program(np.full(4, 2.0)), np.ones(4))


def test_the_smoothing_factor_never_takes_more_process_noise_than_the_likelihood_fitted():
    """`choose_smoothing_scale` searches Q x0.02..x1: where the model's Q is far too small (here 1e-3 of the rig's
    on drops of another model), so that Q x3 smooths the training records with a lower leave-one-out error than Q
    x1, it still keeps at most the fitted Q (a factor above 1 chosen on a fall of 1.3 standard errors made
    soft_bearing's held-out estimate worse, docs/calibration.md)."""
    from touchdown_ros.core.smoothing import leave_one_out_squares
    from touchdown_ros.workflows.train import choose_smoothing_scale

    batch = make_batch(records_of(true_coeffs(), count=2, samples=300), np.asarray(CONFIG.noise.initial))
    model, noise = CONFIG.model(), CONFIG.noise._replace(process=np.asarray(CONFIG.noise.process) * 1e-3)

    def error(factor: float) -> float:
        return float(np.sum(leave_one_out_squares(model, noise._replace(process=noise.process * factor), H, batch)))

    assert error(3.0) < error(1.0)  # a wider search would choose more than the fitted Q here
    chosen = choose_smoothing_scale(model, noise, H, batch, stream=io.StringIO())
    assert chosen.scale <= 1.0 and "x0.02..x1 " in chosen.how, chosen


def _two_wells(shallow: float):
    """A loss with a well of depth `shallow` at -0.06 and one of depth 1 at 0.78, and its gradient."""
    def loss(x):
        near, deep = np.exp(-((x[0] + 0.06) / 0.2) ** 2), np.exp(-((x[0] - 0.78) / 0.2) ** 2)
        grad = shallow * 2 * (x[0] + 0.06) / 0.04 * near + 2 * (x[0] - 0.78) / 0.04 * deep
        return float(-shallow * near - deep), np.array([grad])
    return loss


def test_minimise_from_each_start_keeps_the_lowest_end_and_says_which_start_gave_it():
    """A loss with two minima in one coordinate (a braked rotor's rate: its unbalance's phase lags by radians):
    from 0.1 the fit ends in the shallow one near 0, from 1 in the deep one at 0.78."""
    from touchdown_ros.workflows.optimise import minimise_from_each

    loss = _two_wells(0.2)
    log = io.StringIO()
    x, convergence = minimise_from_each(loss, [("", np.array([0.1])), (", from 1", np.array([1.0]))], 100, 1e-12,
                                        "rate", log)
    assert abs(x[0] - 0.78) < 1e-3 and convergence.final_loss < -0.99
    assert "[rate] kept the start, from 1" in log.getvalue()
    alone, _ = minimise_from_each(loss, [("", np.array([0.1]))], 100, 1e-12, "rate", io.StringIO())
    assert abs(alone[0] + 0.06) < 0.05

    # minima whose depths differ by less than the tolerance: the own start's end, and nothing said
    log = io.StringIO()
    own, _ = minimise_from_each(_two_wells(0.999), [("", np.array([0.1])), (", from 0.75", np.array([0.75]))], 100,
                                1e-2, "rate", log)
    assert abs(own[0] + 0.06) < 0.05 and "kept" not in log.getvalue()
