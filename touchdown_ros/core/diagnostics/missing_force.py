"""The missing force. The state is augmented with three force states d (N, random walk) acting on
the rotor besides the model's forces; the EKF + Rauch-Tung-Striebel smoother of `core.ekf` over
that augmented phi (RK4 by `dynamics.rk4`, the model's measurement h) give d(t) with its standard
deviation. The data, not the model, decide d: what the model lacks, per axis, with uncertainty."""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.diagnostics.breakdown import PHASES
from touchdown_ros.core.dynamics import (
    at_time, contact_forces, later, phi, ring_speed_after, rk4, spin_acceleration, unbalance_change,
)
from touchdown_ros.core.ekf import (
    Belief, Transition, extended_kalman_filter, model_measurement, rts_smoother, sample_times, state_reading,
)
from touchdown_ros.core.effects import SPEED
from touchdown_ros.core.types import OMEGA_RING, VELOCITY, Model


class MissingForce(NamedTuple):
    """Smoothed estimate of the force the model lacks, and the state it was estimated with."""

    force: Array  # (N, 3) N, on the rotor, sensor x/y/z
    force_std: Array  # (N, 3) N, one standard deviation
    state: Array  # (N, n) smoothed state of the augmented filter
    state_cov: Array  # (N, n, n)
    model_force: Array  # (N, 3) N, the model's contact + effect forces at the smoothed state


def augmented_transition(model: Model, h: float) -> Transition:
    """RK4 step (h, s) of the state s = (xi, d) augmented with a force d (3,), N, on the rotor that
    stays constant over the step: d xi / dt = phi(xi) + (0, d / m), and its Jacobian (jacfwd), from
    t s after the drop onset ((s, t) -> ...; 0 if not given). A spinning ring's speed is updated first and
    carried along with the rotor's, as in `rk4_step`."""
    mass, size = model.rig.mass, model.law.state_size
    spinning = model.law.spins_ring

    def step(s: Array, t: Array | float) -> Array:
        start = at_time(model, t)

        def phi_aug(state: Array, stage: float) -> Array:
            staged = later(start, stage)
            rate = phi(staged, state[:size]).at[VELOCITY].add(state[size:] / mass)
            if spinning:
                rate = rate.at[OMEGA_RING].set(spin_acceleration(staged, state[:size]))
            return jnp.concatenate([rate, jnp.zeros(3, state.dtype)])

        if spinning:
            s = s.at[OMEGA_RING].set(ring_speed_after(start, s[:size], h))
        return rk4(phi_aug, s, h)

    return lambda s, t=0.0: (step(s, t), jax.jacfwd(step)(s, t))


def model_force(model: Model, xi: Array) -> Array:
    """(3,) N: the model's contact force plus its effects' forces on the rotor at xi (a speed effect's:
    how it moves the unbalance force; the contact force already slips at its speed)."""
    c = contact_forces(model, xi)
    force = jnp.stack([c.F_x, c.F_y, c.F_z])
    if model.effects:
        force = force + model.effects.force(xi, model.rig, contact=False)  # those through the contact are in c
        if model.effects.acts_on(SPEED):
            force = force + unbalance_change(model, xi)
    return force


def disturbance_smoother(
    model: Model,
    process: Array,
    measurement: Array,
    initial: Belief,
    etas: Array,
    h: float,
    force_walk: float,
    force_initial: float = 1.0e3,
) -> MissingForce:
    """EKF + RTS smoother of the state augmented with a force d (3,) on the rotor (random walk
    of force_walk N rms per sample, starting at 0 +- force_initial N). Returns d(t) with its
    standard deviation: the force the model lacks, decided by the data."""
    Q = jnp.diag(jnp.concatenate([jnp.asarray(process), jnp.full(3, force_walk**2)]))
    R = jnp.diag(jnp.asarray(measurement))
    mean0 = jnp.concatenate([state_reading(model, initial.mean), jnp.zeros(3)])
    cov0 = jax.scipy.linalg.block_diag(initial.cov, force_initial**2 * jnp.eye(3))
    transition, measure = augmented_transition(model, h), model_measurement(model)
    times = sample_times(model, h, len(etas))
    outputs = extended_kalman_filter(transition, measure, Q, R, Belief(mean0, cov0), jnp.asarray(etas), times=times)
    smoothed = rts_smoother(outputs)
    size = model.law.state_size
    state = smoothed.mean[:, :size]
    forces = jax.vmap(lambda s, t: model_force(at_time(model, t), s))(state, h * jnp.arange(len(state)))
    return MissingForce(
        force=smoothed.mean[:, size:],
        force_std=jnp.sqrt(jnp.diagonal(smoothed.cov, axis1=1, axis2=2)[:, size:]),
        state=state,
        state_cov=smoothed.cov[:, :size, :size],
        model_force=forces,
    )


def missing_force_table(force: np.ndarray, force_std: np.ndarray, phase: np.ndarray) -> dict[str, Any]:
    """Mean, rms and mean standard deviation of the missing force (N, 3) per contact phase
    (`PHASES`, those with samples) and over all samples."""
    table = {}
    for i, name in enumerate(PHASES):
        rows = phase == i
        if rows.any():
            table[name] = {
                "samples": int(rows.sum()),
                "mean_N": force[rows].mean(axis=0).tolist(),
                "rms_N": np.sqrt(np.mean(force[rows] ** 2, axis=0)).tolist(),
                "std_of_estimate_N": force_std[rows].mean(axis=0).tolist(),
            }
    table["all"] = {
        "samples": int(len(force)),
        "mean_N": force.mean(axis=0).tolist(),
        "rms_N": np.sqrt(np.mean(force**2, axis=0)).tolist(),
        "std_of_estimate_N": force_std.mean(axis=0).tolist(),
    }
    return table
