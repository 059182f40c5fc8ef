"""Regressors along a trajectory: how the model's force moves with its PKBKR coefficients and with
each candidate effect's parameters (`core.effects.regressors`; a measurement effect enters by the
force it stands for, `force_equivalent`), for the ranking of `frols` and the candidates' scales."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.flatten_util import ravel_pytree

from touchdown_ros.core.diagnostics.missing_force import model_force
from touchdown_ros.core.dynamics import phi
from touchdown_ros.core.effects import FORCE, Effect, regressors
from touchdown_ros.core.types import Model


def coefficient_regressors(model: Model, states: Array) -> Array:
    """(N, 3, n_alpha): d (model force) / d (PKBKR coefficients, flattened R then Z) at each
    state: the directions in which re-training the model's own coefficients moves its force."""
    flat, unravel = ravel_pytree(model.coeffs)

    def force(theta: Array, xi: Array) -> Array:
        return model_force(model._replace(coeffs=unravel(theta)), xi)

    return jax.vmap(lambda xi: jax.jacfwd(force)(flat, xi))(jnp.asarray(states))


def force_equivalent(effect: Effect, model: Model) -> Effect:
    """A measurement effect as the force it stands for; a force effect as it is.

    A measurement effect that changes the sensor output by D(xi) (m) makes a model without it
    follow the state xi + (D, 0, dD/dt), whose motion needs the extra force (first order in D)
    m (d^2 D / dt^2 - A (D, 0, dD/dt)), A = d phi[4:] / d xi, the time derivatives along the
    model's phi: what the missing force shows of it. E.g. a z gain g in free flight: the constant
    -(g - 1) m g_0; a z offset: zero in free flight, the contact stiffness times it in contact.
    """
    if effect.kind == FORCE:
        return effect
    mass = model.rig.mass

    def rate(xi: Array) -> Array:
        return phi(model, xi)

    def force(xi: Array, params, rig) -> Array:
        def change_rate(state: Array) -> Array:
            return jax.jvp(lambda s: effect.function(s, params, rig), (state,), (rate(state),))[1]

        change = jnp.asarray(effect.function(xi, params, rig), xi.dtype)
        change_velocity, change_acceleration = jax.jvp(change_rate, (xi,), (rate(xi),))
        shift = jnp.concatenate([change, jnp.zeros(1, xi.dtype), change_velocity])
        _, acceleration_shift = jax.jvp(lambda s: rate(s)[4:], (xi,), (shift,))
        return mass * (change_acceleration - acceleration_shift)

    return dataclasses.replace(effect, function=force, kind=FORCE)


def effect_regressors(effect: Effect, states: Array, model: Model, values: dict | None = None) -> tuple[Array, Array]:
    """(N, 3, p) d force / d parameters of one candidate effect along the states, linearised at
    `values` (default: its defaults), and (N, 3) its force there (for the offset of
    nonlinear-in-parameter effects). A measurement effect's force is `force_equivalent`'s."""
    effect, rig = force_equivalent(effect, model), model.rig
    p0 = values or effect.defaults()
    params = {k: jnp.asarray(v) for k, v in p0.items()}
    J = jax.vmap(lambda xi: regressors(effect, xi, rig, p0))(jnp.asarray(states))
    f0 = jax.vmap(lambda xi: jnp.asarray(effect.function(xi, params, rig), dtype=xi.dtype))(jnp.asarray(states))
    return J, f0


def linearisation_offset(J: np.ndarray, f0: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """For y ~ J b with J = d force / d p at p0: the physical p = b + p0 - c, where
    force(p0) ~ J c (one Gauss-Newton step from p0; c = p0 for a linear-in-parameter effect)."""
    A = np.asarray(J, float).reshape(-1, J.shape[-1])
    c, *_ = np.linalg.lstsq(A, np.asarray(f0, float).reshape(-1), rcond=None)
    return np.asarray(p0, float) - c
