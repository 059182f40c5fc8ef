"""Regressors along a trajectory: how the model's force moves with its PKBKR coefficients and with
each candidate effect's parameters (a measurement or speed effect enters by the force it stands for,
`force_equivalent`), for the ranking of `frols` and the candidates' scales."""
from __future__ import annotations

from typing import Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.flatten_util import ravel_pytree

from touchdown_ros.core.diagnostics.missing_force import model_force
from touchdown_ros.core.dynamics import at_time, normal_forces, phi, rotor_speed
from touchdown_ros.core.effects import FORCE, MEASUREMENT, SPEED, Effect, Effects
from touchdown_ros.core.types import OMEGA_RING, STATE_SIZE, VELOCITY, Model


def coefficient_regressors(model: Model, states: Array) -> Array:
    """(N, 3, n_alpha): d (model force) / d (PKBKR coefficients, flattened R then Z) at each
    state: the directions in which re-training the model's own coefficients moves its force."""
    flat, unravel = ravel_pytree(model.coeffs)

    def force(theta: Array, xi: Array) -> Array:
        return model_force(model._replace(coeffs=unravel(theta)), xi)

    return jax.vmap(lambda xi: jax.jacfwd(force)(flat, xi))(jnp.asarray(states))


class Motion(NamedTuple):
    """The model's rate phi(xi) (n,) and its Jacobian A = d phi / d xi (n, n) at one state: what every
    measurement effect's force equivalent needs, computed once for all of them."""

    rate: Array
    A: Array


def motion(model: Model, xi: Array) -> Motion:
    """`Motion` of the model at state xi."""
    return Motion(phi(model, xi), jax.jacfwd(lambda s: phi(model, s))(xi))


def force_equivalent(
    effect: Effect, xi: Array, params, model: Model, at: Motion | None, t: Array | float = 0.0
) -> Array:
    """(3,) N: a measurement effect as the force it stands for at xi; a force effect's force as it is;
    a speed effect's as the change of the model's force on the rotor it makes, m (phi with it - phi
    without it) in the accelerations (the unbalance and, against a co-rotating ring, the friction). A
    spinning ring follows the rotor's speed: each side keeps the state's slip of the ring against its
    own rotor (held at the state's speed instead, the steep regularised friction read a change of
    speed as a change of slip, R d omega, and a brake's force per unit rate as ~1e6 N: 2026-12-02).

    A measurement effect that changes the sensor output by D(xi) (m) makes a model without it
    follow the state xi + (D, 0, dD/dt), whose motion needs the extra force (first order in D)
    m (d^2 D / dt^2 - A (D, 0, dD/dt)), A = d phi[VELOCITY] / d xi, the time derivatives along the
    model's phi: dD/dt = J_D phi, d^2 D / dt^2 = phi^T H_D phi + J_D A phi (J_D, H_D: D's first and
    second derivatives). E.g. a z gain g in free flight: the constant -(g - 1) m g_0; a z offset:
    zero in free flight, the contact stiffness times it in contact.
    """
    rig, mass = model.rig, model.rig.mass
    if effect.kind == FORCE:  # t: s after the drop onset, what a clocked effect reads
        normal = normal_forces(model, xi) if effect.normal else None  # static
        return jnp.asarray(effect(xi, params, rig, t, None, normal), xi.dtype)
    if effect.kind == SPEED:
        def acceleration(effects: Effects) -> Array:
            moved = model._replace(effects=effects)
            state = xi
            if model.law.spins_ring:  # static
                state = xi.at[OMEGA_RING].add(rotor_speed(moved, xi)[0] - rotor_speed(model, xi)[0])
            return phi(moved, state)[VELOCITY]

        return mass * (acceleration(Effects((effect,), (params,), time=t)) - acceleration(Effects()))

    def change(state: Array) -> Array:
        return jnp.asarray(effect(state, params, rig, t), xi.dtype)

    def change_rate(state: Array) -> Array:
        return jax.jacfwd(change)(state) @ at.rate

    change_velocity = change_rate(xi)
    curvature = jax.jvp(change_rate, (xi,), (at.rate,))[1]  # phi^T H_D phi
    change_acceleration = curvature + jax.jacfwd(change)(xi) @ (at.A @ at.rate)
    # theta and a spinning ring's speed (the state's tail) are not what the sensor reads: unshifted
    shift = jnp.concatenate([change(xi), jnp.zeros(1, xi.dtype), change_velocity, jnp.zeros(len(xi) - STATE_SIZE)])
    return mass * (change_acceleration - at.A[VELOCITY] @ shift)


def effect_regressors(effect: Effect, states: Array, model: Model, values: dict | None = None) -> tuple[Array, Array]:
    """(N, 3, p) d force / d parameters of one candidate effect along the states, linearised at
    `values` (default: its defaults), and (N, 3) its force there (for the offset of
    nonlinear-in-parameter effects). A measurement effect's force is `force_equivalent`'s."""
    return library_regressors({effect.name: effect}, states, model, {effect.name: values} if values else None)[
        effect.name
    ]


def library_regressors(
    effects: Mapping[str, Effect],
    states: Array,
    model: Model,
    values: Mapping[str, dict] | None = None,
    times: Array | None = None,
) -> dict[str, tuple[Array, Array]]:
    """`effect_regressors` of several effects at once, name -> (J (N, 3, p), f0 (N, 3)): the model's
    rate and its Jacobian along the states (`motion`) are computed once for all measurement effects.
    `times` (N,) s: each state's time after the drop onset, what clocked effects read (0 if not given)."""
    states = jnp.asarray(states)
    times = jnp.zeros(states.shape[0], states.dtype) if times is None else jnp.asarray(times, states.dtype)
    measuring = any(e.kind == MEASUREMENT for e in effects.values())
    motions = jax.vmap(lambda xi, t: motion(at_time(model, t), xi))(states, times) if measuring else None
    out = {}
    for name, effect in effects.items():
        p0 = (values or {}).get(name) or effect.defaults()
        params = {k: jnp.asarray(v, states.dtype) for k, v in p0.items()}
        names = list(params)

        def force(xi: Array, at: Motion | None, t: Array, p=params, e=effect) -> Array:
            return force_equivalent(e, xi, p, model, at, t)

        def jacobian(xi: Array, at: Motion | None, t: Array, p=params, e=effect) -> Array:
            J = jax.jacfwd(lambda q: force_equivalent(e, xi, q, model, at, t))(p)
            return jnp.stack([J[k] for k in names], axis=-1)

        out[name] = (jax.vmap(jacobian)(states, motions, times), jax.vmap(force)(states, motions, times))
    return out


def linearisation_offset(J: np.ndarray, f0: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """For y ~ J b with J = d force / d p at p0: the physical p = b + p0 - c, where
    force(p0) ~ J c (one Gauss-Newton step from p0; c = p0 for a linear-in-parameter effect)."""
    A = np.asarray(J, float).reshape(-1, J.shape[-1])
    c, *_ = np.linalg.lstsq(A, np.asarray(f0, float).reshape(-1), rcond=None)
    return np.asarray(p0, float) - c
