"""Integrate one drop test (RK4 substeps in `lax.scan`) and sample it like the displacement sensor."""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.io.config import Config
from touchdown_ros.sim.params import SimulatorParameters, check_step_size, simulator_parameters, truth_constants
from touchdown_ros.sim.physics import OMEGA, OMEGA_RING, Truth, contact, derivative, levitated_state, rk4_step
from touchdown_ros.sim.record import DropCondition, DropRecord

RPM = 2.0 * np.pi / 60.0  # rad/s per rpm


@partial(jax.jit, static_argnames=("n_samples", "substeps", "period"))
def integrate(p: Truth, s0: Array, n_samples: int, substeps: int, period: float) -> Array:
    """States (n_samples, 9) at t = k * period (s), k = 0..n_samples-1, from s0 at t = 0."""
    h = period / substeps

    def sample(s: Array, k: Array) -> tuple[Array, Array]:
        t0 = k * period

        def sub(j: int, state: Array) -> Array:
            return rk4_step(p, t0 + j * h, state, h)

        return jax.lax.fori_loop(0, substeps, sub, s), s

    _, states = jax.lax.scan(sample, s0, jnp.arange(n_samples, dtype=s0.dtype))
    return states


@jax.jit
def _observe(p: Truth, t: Array, states: Array):
    """Accelerations and contact quantities at every sample."""
    rates = jax.vmap(lambda tk, sk: derivative(p, tk, sk))(t, states)
    c = jax.vmap(lambda sk: contact(p, sk))(states)
    return rates[:, 3:6], c


def sensor(
    position: np.ndarray,
    noise_rms: float,
    quantisation: float,
    rng: np.random.Generator,
    gain: np.ndarray | float = 1.0,
    offset: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Displacement sensor: gain * truth + offset (per axis; 1, m) + Gaussian noise (m rms, per axis),
    then rounded to the ADC step (m)."""
    measured = gain * position + offset + noise_rms * rng.standard_normal(position.shape)
    if quantisation > 0.0:
        measured = np.round(measured / quantisation) * quantisation
    return measured


def _rng(seed: int, condition: DropCondition) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(condition.number)]))


def simulate_drop(
    config: Config, condition: DropCondition, seed: int = 0, params: SimulatorParameters | None = None
) -> DropRecord:
    """Simulate one drop test under `condition`; the same (config, condition, seed) gives identical records."""
    params = params or simulator_parameters(config)
    if not np.isfinite(condition.speed_rpm) or condition.speed_rpm < 0.0:
        raise ValueError(
            f"experiment {condition.number}: speed_rpm must be finite and >= 0, got {condition.speed_rpm!r}"
        )
    period = config.sample_period
    n_lev = int(round(params.scalars["levitated_time"] / period))
    n_drop = int(round(params.scalars["drop_duration"] / period))
    n_samples = n_lev + n_drop
    drop_time = n_lev * period
    rng = _rng(seed, condition)

    truth = truth_constants(config, params, condition.ball, condition.brake, condition.axial_load, drop_time, rng)
    theta0 = float(rng.uniform(0.0, 2.0 * np.pi))
    speed = condition.speed_rpm * RPM
    check_step_size(params, truth, speed, period, condition.ball)
    s0 = levitated_state(truth, theta0, speed)
    p = Truth(*(jnp.asarray(v, dtype=jnp.float64) for v in truth))
    states = integrate(p, jnp.asarray(s0), n_samples, params.substeps, float(period))
    t = np.arange(n_samples) * period
    acceleration, c = _observe(p, jnp.asarray(t), states)
    states = np.asarray(states)
    if not np.all(np.isfinite(states)):
        raise FloatingPointError(
            f"experiment {condition.number}: the simulation diverged; check the simulator constants"
        )

    position = states[:, :3]
    gain, offset = (np.array([params.scalars[f"sensor_{error}_{a}"] for a in "xyz"]) for error in ("gain", "offset"))
    measured = sensor(position, config.noise_rms, config.quantisation, rng, gain, offset)
    period_ns = int(round(period * 1e9))
    offset_s = (condition.number - 1) * params.scalars["experiment_interval"]
    start_ns = params.start_time_ns + int(round(offset_s * 1e9))
    stamps_ns = start_ns + np.arange(n_samples, dtype=np.int64) * period_ns
    return DropRecord(
        condition=condition,
        stamps_ns=stamps_ns.astype(np.int64),
        t=t,
        drop_time=drop_time,
        measured=measured,
        position=position,
        velocity=states[:, 3:6],
        acceleration=np.asarray(acceleration),
        contact_force=np.asarray(c.force),
        F_n=np.asarray(c.F_n),
        F_t=np.asarray(c.F_t),
        F_z=np.asarray(c.F_z),
        radial_contact=np.asarray(c.radial_contact),
        axial_contact=np.asarray(c.axial_contact),
        omega=states[:, OMEGA],
        omega_ring=states[:, OMEGA_RING],
        seed=int(seed),
    )


__all__ = ["simulate_drop", "integrate", "sensor"]
