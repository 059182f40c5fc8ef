"""Extended Kalman filter (eq. 17) and Rauch-Tung-Striebel smoother, as pure functions.

Convention: the carried belief is the prior of the current sample; a step updates it
with the sample's measurement (eq. 17b-c, e-f) and predicts the next prior (eq. 17a, d)
with Phi_k from automatic differentiation (eq. 16). A sample with any non-finite value
is not used: the step only predicts. Covariances are symmetrised after each update.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from touchdown_ros.core.dynamics import step_with_jacobian, step_with_jacobian_and_rate
from touchdown_ros.core.types import OUTPUT_SIZE, FilterNoise, Model


class Belief(NamedTuple):
    """Gaussian belief over the state: mean (7,) and covariance (7, 7)."""

    mean: Array
    cov: Array


class StepOutput(NamedTuple):
    """What one EKF step returns for its sample."""

    prior: Belief  # xi_{k,-}, P_{k,-}
    filtered: Belief  # xi_k, P_k
    innovation: Array  # eta_k - H xi_{k,-}, m (NaN when the sample was not used)
    innovation_cov: Array  # H P_{k,-} H^T + R
    Phi: Array  # df/dxi at xi_k, maps this sample to the next
    used: Array  # bool, measurement used


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


def update(belief: Belief, eta: Array, R: Array) -> tuple[Belief, Array, Array, Array]:
    """Measurement update (eq. 17b, c, e, f); skipped when eta is not finite.

    H selects x, y, z, so H P is the first three rows of P.
    """
    used = jnp.all(jnp.isfinite(eta))
    predicted_output = belief.mean[:OUTPUT_SIZE]
    innovation = jnp.where(used, eta, predicted_output) - predicted_output
    HP = belief.cov[:OUTPUT_SIZE]
    S = HP[:, :OUTPUT_SIZE] + R
    K = HP.T @ _inverse_3x3(S)  # eq. 17e
    cov = belief.cov - K @ HP  # eq. 17f
    filtered = Belief(belief.mean + K @ innovation, 0.5 * (cov + cov.T))
    filtered = jax.tree.map(lambda new, old: jnp.where(used, new, old), filtered, belief)
    return filtered, jnp.where(used, innovation, jnp.nan), S, used


def predict(model: Model, belief: Belief, Q: Array, h: float) -> tuple[Belief, Array]:
    """Time update (eq. 17a, d): xi_{k+1,-} = f(xi_k), P_{k+1,-} = Phi P Phi^T + Q."""
    mean, Phi = step_with_jacobian(model, belief.mean, h)
    return Belief(mean, Phi @ belief.cov @ Phi.T + Q), Phi


def predict_with_rate(model: Model, belief: Belief, Q: Array, h: float) -> tuple[Belief, Array, Array, Array]:
    """`predict`, plus phi and d phi / d xi at the filtered mean: (next prior, Phi, phi(xi), dphi/dxi).

    The first RK4 stage is what the filtered signals need (acceleration phi(xi)[4:] and
    its Jacobian for the covariance): the live estimator takes them from here instead of
    evaluating phi and its Jacobian at xi a second time. Equal to `predict` (the same operations).
    """
    mean, Phi, rate, rate_jacobian = step_with_jacobian_and_rate(model, belief.mean, h)
    return Belief(mean, Phi @ belief.cov @ Phi.T + Q), Phi, rate, rate_jacobian


def ekf_step(model: Model, noise: FilterNoise, h: float, prior: Belief, eta: Array) -> tuple[Belief, StepOutput]:
    """One sample: update the prior with eta (3,), m, then predict the next prior."""
    filtered, innovation, S, used = update(prior, eta, jnp.diag(noise.measurement))
    next_prior, Phi = predict(model, filtered, jnp.diag(noise.process), h)
    return next_prior, StepOutput(prior, filtered, innovation, S, Phi, used)


def ekf(
    model: Model, noise: FilterNoise, h: float, initial: Belief, etas: Array, checkpoint: bool = False
) -> StepOutput:
    """Filter a whole record etas (N, 3) with lax.scan; fields of the result are stacked over N.

    checkpoint: differentiating through the filter recomputes each step in the backward
    pass instead of storing its intermediates (`jax.checkpoint`); the same numbers, and
    here about half the time of the gradient, which is bound by memory traffic.
    """

    def body(prior: Belief, eta: Array) -> tuple[Belief, StepOutput]:
        return ekf_step(model, noise, h, prior, eta)

    if checkpoint:
        body = jax.checkpoint(body)
    _, outputs = jax.lax.scan(body, initial, etas)
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
