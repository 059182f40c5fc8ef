"""Extended Kalman filter (eq. 17) and Rauch-Tung-Striebel smoother, as pure functions.

Like dynamax's filters, the filter takes its model as two functions of the state: a
transition xi -> (f(xi), Phi = df/dxi) (eq. 15, 16) and a measurement xi -> (h(xi),
H = dh/dxi) (eq. 15f); `with_jacobian` makes either from a plain function by forward-mode
automatic differentiation. `ekf` and `ekf_step` run the touchdown model with them
(`model_transition`, `model_measurement`).

Convention: the carried belief is the prior of the current sample; a step updates it
with the sample's measurement (eq. 17b-c, e-f) and predicts the next prior (eq. 17a, d).
A sample with any non-finite value is not used: the step only predicts. Covariances
are symmetrised after each update.

With a `NoiseAdaptation` the filter also carries a factor on Q that the innovations move
(`adapted_log_scale`): the live filter's answer to a drop unlike the training drops.
"""
from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from touchdown_ros.core.dynamics import (
    at_time, clocked, measurement, measures, step_with_jacobian, step_with_jacobian_and_rate,
)
from touchdown_ros.core.types import OUTPUT_SIZE, STATE_SIZE, FilterNoise, Model

#: xi -> (f(xi), Phi): the next state's mean and df/dxi (eq. 15, 16); (xi, t) -> ... for a timed one, t the
#: sample's time (s) after the drop onset (`extended_kalman_filter`'s `times`).
Transition = Callable[..., tuple[Array, Array]]
#: xi -> (h(xi), H): the expected measurement (m) and dh/dxi (eq. 15f).
Measurement = Callable[[Array], tuple[Array, Array]]


class Belief(NamedTuple):
    """Gaussian belief over the state: mean (n,) and covariance (n, n); n = 7 for the model's xi."""

    mean: Array
    cov: Array


class StepOutput(NamedTuple):
    """What one EKF step returns for its sample."""

    prior: Belief  # xi_{k,-}, P_{k,-}
    filtered: Belief  # xi_k, P_k
    innovation: Array  # eta_k - h(xi_{k,-}), m (NaN when the sample was not used)
    innovation_cov: Array  # H P_{k,-} H^T + R
    Phi: Array  # df/dxi at xi_k, maps this sample to the next
    used: Array  # bool, measurement used
    process_scale: Array | None = None  # the factor on Q of the next prior's prediction (with a NoiseAdaptation)


class NoiseAdaptation(NamedTuple):
    """Q scaled by a factor the innovations move, sample by sample (covariance matching, as adaptive
    Kalman filters do; `adapted_log_scale`): ln(factor) rises while the NIS is above its expected 3 and
    leaks back to 0 (factor 1, Q as fitted), held between 1 and `max_scale`."""

    gain: float  # per sample: change of ln(factor) per unit of NIS / 3 - 1
    leak: float  # per sample: the fraction of ln(factor) lost (1 / leak samples: its memory)
    max_scale: float  # the largest factor on Q


def adapted_log_scale(adaptation: NoiseAdaptation, log_scale: Array, nis: Array, used: Array) -> Array:
    """ln of Q's factor after a sample of normalised innovation squared `nis` (unchanged where not `used`)."""
    moved = (1.0 - adaptation.leak) * log_scale + adaptation.gain * (nis / OUTPUT_SIZE - 1.0)
    return jnp.where(used, jnp.clip(moved, 0.0, jnp.log(adaptation.max_scale)), log_scale)


def with_jacobian(function: Callable[[Array], Array]) -> Callable[[Array], tuple[Array, Array]]:
    """x -> (function(x), d function / d x) by forward-mode automatic differentiation."""
    return lambda x: (function(x), jax.jacfwd(function)(x))


def position(xi: Array) -> tuple[Array, Array]:
    """The paper's measurement (eq. 15f): h(xi) = (x, y, z), H = [I 0]."""
    return xi[:OUTPUT_SIZE], jnp.eye(OUTPUT_SIZE, xi.shape[0], dtype=xi.dtype)


def inverse_and_det_3x3(A: Array) -> tuple[Array, Array]:
    """Closed-form inverse (adjugate over determinant) and determinant of 3 x 3 matrices (..., 3, 3).

    S is 3 x 3 and this is the hot loop; it also keeps LAPACK calls out of batched losses.
    """
    r0, r1, r2 = A[..., 0, :], A[..., 1, :], A[..., 2, :]
    adjugate = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-1)
    det = jnp.sum(r0 * adjugate[..., :, 0], axis=-1)
    return adjugate / det[..., None, None], det


def _inverse_3x3(A: Array) -> Array:
    return inverse_and_det_3x3(A)[0]


def update(
    belief: Belief, eta: Array, R: Array, measure: Measurement = position
) -> tuple[Belief, Array, Array, Array]:
    """Measurement update (eq. 17b, c, e, f); skipped when eta is not finite.

    With `position` (H = [I 0]) H P is taken as the first three rows of P, without a product.
    """
    used = jnp.all(jnp.isfinite(eta))
    if measure is position:
        predicted_output, HP = belief.mean[:OUTPUT_SIZE], belief.cov[:OUTPUT_SIZE]
        S = HP[:, :OUTPUT_SIZE] + R
    else:
        predicted_output, H = measure(belief.mean)
        HP = H @ belief.cov
        S = HP @ H.T + R
    innovation = jnp.where(used, eta, predicted_output) - predicted_output
    K = HP.T @ _inverse_3x3(S)  # eq. 17e
    cov = belief.cov - K @ HP  # eq. 17f
    filtered = Belief(belief.mean + K @ innovation, 0.5 * (cov + cov.T))
    filtered = jax.tree.map(lambda new, old: jnp.where(used, new, old), filtered, belief)
    return filtered, jnp.where(used, innovation, jnp.nan), S, used


def predict(belief: Belief, Q: Array, transition: Transition) -> tuple[Belief, Array]:
    """Time update (eq. 17a, d): xi_{k+1,-} = f(xi_k), P_{k+1,-} = Phi P Phi^T + Q."""
    mean, Phi = transition(belief.mean)
    return Belief(mean, Phi @ belief.cov @ Phi.T + Q), Phi


def filter_step(
    transition: Transition, measure: Measurement, Q: Array, R: Array, prior: Belief, eta: Array
) -> tuple[Belief, StepOutput]:
    """One sample: update the prior with eta (3,), m, then predict the next prior."""
    filtered, innovation, S, used = update(prior, eta, R, measure)
    next_prior, Phi = predict(filtered, Q, transition)
    return next_prior, StepOutput(prior, filtered, innovation, S, Phi, used)


def adaptive_filter_step(
    transition: Transition,
    measure: Measurement,
    Q: Array,
    R: Array,
    adaptation: NoiseAdaptation,
    carried: tuple[Belief, Array],
    eta: Array,
) -> tuple[tuple[Belief, Array], StepOutput]:
    """`filter_step` with Q scaled by exp(ln factor) carried beside the prior and moved by this sample's NIS."""
    prior, log_scale = carried
    filtered, innovation, S, used = update(prior, eta, R, measure)
    nis = innovation @ (_inverse_3x3(S) @ innovation)
    log_scale = adapted_log_scale(adaptation, log_scale, nis, used)
    next_prior, Phi = predict(filtered, jnp.exp(log_scale) * Q, transition)
    return (next_prior, log_scale), StepOutput(prior, filtered, innovation, S, Phi, used, jnp.exp(log_scale))


def extended_kalman_filter(
    transition: Transition,
    measure: Measurement,
    Q: Array,
    R: Array,
    initial: Belief,
    etas: Array,
    checkpoint: bool = False,
    times: Array | None = None,
    adaptation: NoiseAdaptation | None = None,
) -> StepOutput:
    """Filter a whole record etas (N, 3) with lax.scan; fields of the result are stacked over N.

    checkpoint: differentiating through the filter recomputes each step in the backward
    pass instead of storing its intermediates (`jax.checkpoint`); the same numbers, and
    here about half the time of the gradient, which is bound by memory traffic.
    times: (N,) s, each sample's time, given to the transition as (xi, t) (a model with clocked effects).
    adaptation: Q scaled as the innovations ask (`adaptive_filter_step`), from factor 1 at the first sample.
    """

    def body(carried, inputs: tuple[Array, Array | None]):
        eta, t = inputs
        step = transition if t is None else functools.partial(transition, t=t)
        if adaptation is None:
            return filter_step(step, measure, Q, R, carried, eta)
        return adaptive_filter_step(step, measure, Q, R, adaptation, carried, eta)

    if checkpoint:
        body = jax.checkpoint(body)
    start = initial if adaptation is None else (initial, jnp.zeros((), initial.mean.dtype))
    _, outputs = jax.lax.scan(body, start, (etas, times))
    return outputs


def rts_smoother(outputs: StepOutput) -> Belief:
    """Fixed-interval Rauch-Tung-Striebel smoother over a filtered record."""
    filtered, Phi = outputs.filtered, outputs.Phi
    next_priors = jax.tree.map(lambda a: a[1:], outputs.prior)

    def body(later: Belief, inputs) -> tuple[Belief, Belief]:
        now, Phi_k, next_prior = inputs
        gain = jnp.linalg.solve(next_prior.cov, Phi_k @ now.cov).T  # P_k Phi^T P_{k+1,-}^-1
        mean = now.mean + gain @ (later.mean - next_prior.mean)
        cov = now.cov + gain @ (later.cov - next_prior.cov) @ gain.T
        smoothed = Belief(mean, 0.5 * (cov + cov.T))
        return smoothed, smoothed

    last = jax.tree.map(lambda a: a[-1], filtered)
    earlier = (jax.tree.map(lambda a: a[:-1], filtered), Phi[:-1], next_priors)
    _, smoothed = jax.lax.scan(body, last, earlier, reverse=True)
    return jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]]), smoothed, last)


# ---------------------------------------------------------------- the touchdown model's filter

def model_transition(model: Model, h: float) -> Transition:
    """The model's RK4 step f (eq. 15) of length h (s) with Phi by the chain rule through its stages (eq. 16),
    (xi, t) -> (f, Phi) from t s after the drop onset (0 if not given; only clocked effects read it)."""
    return lambda xi, t=0.0: step_with_jacobian(at_time(model, t), xi, h)


def sample_times(model: Model, h: float, samples: int, start: Array | float = 0.0) -> Array | None:
    """(samples,) s: each sample's time after the drop onset, the first's `start`, where the model has clocked
    effects; None (no time traced) where it has none."""
    return start + h * jnp.arange(samples) if clocked(model) else None


def model_measurement(model: Model) -> Measurement:
    """The model's h (eq. 15f and its measurement effects): `position` when it has none. h reads the
    model's xi, the first 7 entries of a longer (augmented) state."""
    if not measures(model):
        return position
    return with_jacobian(lambda state: measurement(model, state[:STATE_SIZE]))


def state_reading(model: Model, mean: Array, iterations: int = 2) -> Array:
    """The state mean `mean` (n,) with its position moved so that the model's h reads the position it held:
    an initial belief holds the sensors' reading at the onset (`estimate.initial_belief`), which the
    measurement effects tell from the rotor's position (a 30 um x sensor offset started the filter 30 um
    off, 10 sd of P_0, and raised the free flight's k-step error by 41 %, 2026-12-07). Newton's steps on
    h(xi) = reading, exact for a gain and an offset; `mean` itself where the model has no measurement effects."""
    if not measures(model):
        return mean
    reading = mean[:OUTPUT_SIZE]
    output = model_measurement(model)
    for _ in range(iterations):
        expected, H = output(mean)
        mean = mean.at[:OUTPUT_SIZE].add(-jnp.linalg.solve(H[:, :OUTPUT_SIZE], expected - reading))
    return mean


def predict_with_rate(model: Model, belief: Belief, Q: Array, h: float) -> tuple[Belief, Array, Array, Array]:
    """`predict` with the model's f, plus phi and d phi / d xi at the filtered mean:
    (next prior, Phi, phi(xi), dphi/dxi).

    The first RK4 stage is what the filtered signals need (acceleration phi(xi)[4:] and
    its Jacobian for the covariance): the live estimator takes them from here instead of
    evaluating phi and its Jacobian at xi a second time. Equal to `predict` (the same operations).
    """
    mean, Phi, rate, rate_jacobian = step_with_jacobian_and_rate(model, belief.mean, h)
    next_prior, _ = predict(belief, Q, lambda _: (mean, Phi))
    return next_prior, Phi, rate, rate_jacobian


def ekf_step(model: Model, noise: FilterNoise, h: float, prior: Belief, eta: Array) -> tuple[Belief, StepOutput]:
    """`filter_step` with the model's f and h and the noise's Q and R."""
    Q, R = jnp.diag(noise.process), jnp.diag(noise.measurement)
    return filter_step(model_transition(model, h), model_measurement(model), Q, R, prior, eta)


def ekf(
    model: Model,
    noise: FilterNoise,
    h: float,
    initial: Belief,
    etas: Array,
    checkpoint: bool = False,
    start_time: Array | float = 0.0,
    adaptation: NoiseAdaptation | None = None,
) -> StepOutput:
    """`extended_kalman_filter` with the model's f and h and the noise's Q and R (Q adapted with
    `adaptation`); the first sample `start_time` s after the drop onset (what clocked effects read).
    `initial`'s position is the sensors' reading there (`state_reading`)."""
    Q, R = jnp.diag(noise.process), jnp.diag(noise.measurement)
    initial = initial._replace(mean=state_reading(model, initial.mean))
    return extended_kalman_filter(
        model_transition(model, h), model_measurement(model), Q, R, initial, etas, checkpoint,
        sample_times(model, h, etas.shape[0], start_time), adaptation,
    )
