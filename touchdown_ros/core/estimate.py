"""Offline estimation of one drop record: grid, drop detection, EKF, smoother, derived signals."""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.dynamics import (
    at_time, contact_force_xyz, contact_forces, contact_forces_and_jacobian, measurement, phi,
)
from touchdown_ros.core.effects import Effects
from touchdown_ros.core.ekf import Belief, NoiseAdaptation, StepOutput, ekf, rts_smoother
from touchdown_ros.core.input_policy import GridError, InputPolicy, split_record
from touchdown_ros.core.types import OMEGA_RING, VELOCITY, Coefficients, ContactForces, FilterNoise, Model


class SampleGrid(NamedTuple):
    """Samples placed on the sensor's regular time grid; missing samples are NaN rows."""

    stamps_ns: np.ndarray  # (N,) int64
    etas: np.ndarray  # (N, 3) m, NaN where no sample arrived
    missing: int  # number of grid points without a sample


class SignalSet(NamedTuple):
    """Per-sample signals derived from one state trajectory (filtered or smoothed)."""

    state: Array  # (N, n)
    state_cov: Array  # (N, n, n)
    acceleration: Array  # (N, 3) m/s^2
    acceleration_cov: Array  # (N, 3, 3)
    F_n: Array  # (N,) N
    F_t: Array
    F_z: Array
    force_xyz: Array  # (N, 3) contact force on the rotor in sensor axes, N
    force_cov: Array  # (N, 3, 3) N^2, covariance of force_xyz: J P J^T, J = d force_xyz / d state
    radial_contact: Array  # (N,) bool
    axial_contact: Array

    @property
    def ring_speed(self) -> np.ndarray:
        """(N,) rad/s: a spinning ring's speed, the state's eighth column (NaN when the state has none),
        as `StreamOutput.ring_speed`."""
        state = np.asarray(self.state)
        return state[:, OMEGA_RING] if state.shape[1] > OMEGA_RING else np.full(len(state), np.nan)

    @property
    def ring_speed_std(self) -> np.ndarray:
        """(N,) rad/s: the 1-sigma of `ring_speed` (NaN when the state has no ring)."""
        cov = np.asarray(self.state_cov)
        return np.sqrt(cov[:, OMEGA_RING, OMEGA_RING]) if cov.shape[1] > OMEGA_RING else np.full(len(cov), np.nan)


class Estimate(NamedTuple):
    """Everything estimated for one record, from the drop onset on."""

    stamps_ns: np.ndarray  # (N,) int64
    measured: np.ndarray  # (N, 3) m, NaN where missing
    filtered: SignalSet
    smoothed: SignalSet
    predicted_output: Array  # (N, 3) h(xi_{k,-}): one-step prediction, m
    innovation: Array  # (N, 3) m
    innovation_cov: Array  # (N, 3, 3)
    nis: Array  # (N,) normalised innovation squared
    process_scale: Array  # (N,) the filter's factor on Q after each sample (1 unless it adapts Q)
    onset_index: int  # index of the drop onset in the input grid
    missing: int


def to_grid(
    stamps_ns: np.ndarray,
    etas: np.ndarray,
    sample_period: float,
    tolerance: float = 0.25,
    policy: InputPolicy | None = None,
    source: str = "",
) -> SampleGrid:
    """Place samples on the regular grid of sample_period (s) under the input policy
    (`core.input_policy`; its defaults unless given): refused values (saturated, pinned,
    millimetres) and bridged holes become NaN rows.

    Refuses (GridError naming `source` and the sample) stamps that are off the grid by more than
    tolerance of a period, duplicate or decreasing stamps, and holes the policy does not bridge
    (a gap or clock jump: `split_record` gives the segments around them).
    """
    policy = policy or InputPolicy(sample_period, grid_tolerance=tolerance)
    record = split_record(stamps_ns, etas, policy, source)
    if len(record.segments) > 1:
        where = f"{source}: " if source else ""
        if record.breaks:
            index, jump_ns, kind = record.breaks[0]
            what = f"sample {index}: the stamps jump {jump_ns / 1e9:.6g} s ({kind.replace('_', ' ')})"
        else:
            what = f"{record.counts['dropped_rows']} samples in a row without a usable value"
        raise GridError(f"{where}{what}, more than node.bridge_gap = {policy.bridge_gap:g} s; cut the record there")
    segment = record.segments[0]
    return SampleGrid(segment.stamps_ns, segment.etas, int(segment.bridged_rows.sum()))


class DropDetector(NamedTuple):
    """How a drop onset is found in z: it leaves its levitated mean by `threshold`; SI units.

    One rule for the offline tools and the live node (`Config.drop_detector()` builds it
    from a rig YAML's `drop_detection.*`).
    """

    sample_period: float  # s, the sensor grid
    threshold: float  # m below the levitated mean of z
    levitated_window: float  # s of levitation averaged for the reference
    gravity: float  # m/s^2, for the free-fall time of the threshold
    lead: float = 0.0  # s the onset lies before the free fall's start as well: the record starts in levitation

    @property
    def window_samples(self) -> int:
        """Grid rows of the levitated window."""
        return max(1, int(round(self.levitated_window / self.sample_period)))

    @property
    def fall_samples(self) -> int:
        """Rows the onset lies before the threshold crossing: the free-fall time sqrt(2 threshold / g)
        and the `lead`."""
        return int(round((np.sqrt(2.0 * self.threshold / self.gravity) + self.lead) / self.sample_period))

    def reference(self, z: np.ndarray) -> float:
        """Mean of the finite z (m) over the levitated window (0 if none)."""
        window = z[: self.window_samples]
        finite = np.isfinite(window)
        return float(np.mean(window[finite])) if finite.any() else 0.0

    def onset(self, z: np.ndarray, reference: float | None = None) -> int | None:
        """Index of the drop onset: the first finite z below `reference` - threshold, moved back by
        `fall_samples` (the free fall's time and the `lead`); None if z never falls that far. `reference`: the
        levitated mean z (m) when known (a later segment of a record); else `self.reference(z)`."""
        if reference is None:
            reference = self.reference(z)
        below = np.flatnonzero(np.isfinite(z) & (z < reference - self.threshold))
        if below.size == 0:
            return None
        return max(0, int(below[0]) - self.fall_samples)


def initial_belief(etas: np.ndarray, initial_cov: np.ndarray, samples: int = 5) -> Belief:
    """Prior at the onset: measured position (mean of the first samples), at rest, theta = 0 (and a
    spinning ring at rest: the state's length is initial_cov's).

    numpy arrays (JAX takes them as they are): the live node builds one at each drop onset,
    where three JAX dispatches cost ~0.8 ms.
    """
    position = np.nanmean(etas[:samples], axis=0)
    mean = np.concatenate([position, np.zeros(len(initial_cov) - len(position))])
    return Belief(mean, np.diag(np.asarray(initial_cov, dtype=np.float64)))


def force_model_variance(model: Model, noise: FilterNoise, sample_period: float) -> Array:
    """(3,) N^2 per sensor axis: the variance of the contact force the model itself leaves out,
    the process noise on the velocities read as a force, m^2 Q_v / h^2 (the filter's own
    account of its acceleration error over one sample). Where no better figure is known: a
    coefficient file carries the one measured on its training bags (`core.smoothing.missing_force_squares`),
    which this one overstates several times (the white noise of a sample is not a smooth model error)."""
    return model.rig.mass**2 * jnp.asarray(noise.process)[VELOCITY] / sample_period**2


def _pair_force_covariance(model: Model, xi: Array, pair: tuple[str, str], log_covariance) -> Array:
    """(3, 3) N^2: J C J^T, J the contact force's derivative at xi by the logarithms of the law's two
    constants named `pair`, C their covariance (`log_covariance`)."""
    law = model.law

    def force(log_scale: Array) -> Array:
        scaled = law._replace(**{name: getattr(law, name) * jnp.exp(log_scale[i]) for i, name in enumerate(pair)})
        return contact_force_xyz(contact_forces(model._replace(law=scaled), xi))

    J = jax.jacfwd(force)(jnp.zeros(2))
    return J @ jnp.asarray(log_covariance) @ J.T


def support_force_covariance(model: Model, xi: Array) -> Array | None:
    """(3, 3) N^2: the contact force's covariance at xi from the axial support's uncertainty,
    J_s C J_s^T with J_s the force's derivative by (ln preload, ln span) and C the law's
    `support_log_covariance`. Zero below the support's knee (there the force does not depend on it);
    None (nothing computed) when the law's support is rigid or exact (`ContactLaw.support_uncertain`)."""
    if not model.law.support_uncertain:
        return None
    return _pair_force_covariance(model, xi, ("support_preload", "support_span"), model.law.support_log_covariance)


def stribeck_force_covariance(model: Model, xi: Array) -> Array | None:
    """(3, 3) N^2: the contact force's covariance at xi from the Stribeck drop's uncertainty, the
    force's derivative by (ln friction_drop, ln stribeck_velocity) through the law's
    `stribeck_log_covariance`; None when there is no drop or it is exact (`ContactLaw.stribeck_uncertain`)."""
    if not model.law.stribeck_uncertain:
        return None
    return _pair_force_covariance(
        model, xi, ("friction_drop", "stribeck_velocity"), model.law.stribeck_log_covariance
    )


def law_force_covariance(model: Model, xi: Array) -> Array | None:
    """(3, 3) N^2: the contact force's covariance at xi from the law's uncertain constants beyond f0, the
    support's (`support_force_covariance`) plus the Stribeck drop's (`stribeck_force_covariance`; their
    correlation left out); None when neither is uncertain."""
    support, stribeck = support_force_covariance(model, xi), stribeck_force_covariance(model, xi)
    if support is None:
        return stribeck
    return support if stribeck is None else support + stribeck


def force_covariance(
    forces: ContactForces, J_force: Array, cov: Array, model_variance: Array | None, law_part: Array | None = None
) -> Array:
    """(3, 3) N^2: the force's covariance through its Jacobian (J P J^T), plus `model_variance`
    on the diagonal while a contact is on (out of contact the force is zero and known to be),
    plus `law_part` (`law_force_covariance`) unless None."""
    covariance = J_force @ cov @ J_force.T
    if model_variance is not None:
        in_contact = jnp.logical_or(forces.radial_contact, forces.axial_contact)
        covariance = covariance + jnp.where(in_contact, jnp.diag(model_variance), 0.0)
    return covariance if law_part is None else covariance + law_part


def signals(
    model: Model, states: Belief, model_variance: Array | None = None, times: Array | None = None
) -> SignalSet:
    """Accelerations (phi at the state) and contact forces, each with its covariance linearised
    about the state (J P J^T, J by automatic differentiation); the force's with `model_variance`
    (`force_model_variance`) added in contact. `times` (N,) s: each state's time after the drop onset
    (what clocked effects read; 0 if not given)."""

    def one(mean: Array, cov: Array, t: Array):
        timed = at_time(model, t)
        acceleration = phi(timed, mean)[VELOCITY]
        J = jax.jacfwd(lambda s: phi(timed, s)[VELOCITY])(mean)
        forces, J_force = contact_forces_and_jacobian(timed, mean)
        law_part = law_force_covariance(timed, mean)
        return acceleration, J @ cov @ J.T, forces, force_covariance(forces, J_force, cov, model_variance, law_part)

    if times is None:
        times = jnp.zeros(states.mean.shape[0], states.mean.dtype)
    acceleration, acceleration_cov, forces, force_cov = jax.vmap(one)(states.mean, states.cov, times)
    return SignalSet(
        state=states.mean,
        state_cov=states.cov,
        acceleration=acceleration,
        acceleration_cov=acceleration_cov,
        F_n=forces.F_n,
        F_t=forces.F_t,
        F_z=forces.F_z,
        force_xyz=jnp.stack([forces.F_x, forces.F_y, forces.F_z], axis=-1),
        force_cov=force_cov,
        radial_contact=forces.radial_contact,
        axial_contact=forces.axial_contact,
    )


def force_std(force_cov: np.ndarray) -> np.ndarray:
    """(N, 3) N: 1-sigma of the contact force per sensor axis, sqrt of the diagonal of force_cov (N, 3, 3).

    Round-off can leave a diagonal element a hair below zero where it is zero: read as 0.
    """
    return np.sqrt(np.maximum(np.diagonal(np.asarray(force_cov), axis1=-2, axis2=-1), 0.0))


Estimator = Callable[..., Estimate]
#: Records are padded to a multiple of this many samples before filtering (fewer compilations).
PAD_BUCKET = 512


def make_estimator(
    model: Model,
    noise: FilterNoise,
    sample_period: float,
    model_variance: np.ndarray | None = None,
    adaptation: NoiseAdaptation | None = None,
) -> Estimator:
    """Compile the filter + smoother for one model; the returned function estimates many records.

    `model_variance` (3,) N^2: the model's own force error in contact, added to the force band
    (default `force_model_variance`).

    The model is closed over so its constants fold at compile time (about 1.4x faster
    than passing it as an argument); compilation happens once per record length.
    `estimate(..., coeffs=C, effects=E)` runs other coefficients (and effect parameters) of the
    same rig through a second compiled function that takes them as arguments (one compilation
    for many sets). `process_scale` (n,): factors on the diagonal of Q for one record (default 1);
    `estimate.innovations(...)` runs the filter alone and returns its innovations and their covariances.
    `adaptation`: Q moved by the innovations as the live node's filter moves it (`ekf.NoiseAdaptation`).
    """

    def scaled(process_scale: Array) -> FilterNoise:
        return noise._replace(process=jnp.asarray(noise.process) * process_scale)

    def run(model: Model, initial: Belief, etas: Array, start_time: Array, process_scale: Array):
        outputs: StepOutput = ekf(
            model, scaled(process_scale), sample_period, initial, etas, start_time=start_time, adaptation=adaptation
        )
        smoothed = rts_smoother(outputs)
        nis = jnp.einsum("ni,nij,nj->n", outputs.innovation, jnp.linalg.inv(outputs.innovation_cov), outputs.innovation)
        variance = force_model_variance(model, noise, sample_period) if model_variance is None else model_variance
        times = start_time + sample_period * jnp.arange(etas.shape[0])
        return (
            signals(model, outputs.filtered, variance, times),
            signals(model, smoothed, variance, times),
            jax.vmap(lambda xi: measurement(model, xi))(outputs.prior.mean),
            outputs.innovation,
            outputs.innovation_cov,
            nis,
            jnp.ones(etas.shape[0]) if outputs.process_scale is None else outputs.process_scale,
        )

    def filter_only(model: Model, initial: Belief, etas: Array, start_time: Array, process_scale: Array):
        outputs = ekf(
            model, scaled(process_scale), sample_period, initial, etas, start_time=start_time, adaptation=adaptation
        )
        return outputs.innovation, outputs.innovation_cov

    def compiled(function: Callable) -> Callable:
        """`function(model, ...)` compiled with the model folded in, and with its coefficients and effects as
        arguments: called as (coeffs | None, effects | None, ...)."""
        folded = jax.jit(lambda *args: function(model, *args))
        opened = jax.jit(lambda coeffs, effects, *args: function(model._replace(coeffs=coeffs, effects=effects), *args))

        def call(coeffs: Coefficients | None, effects: Effects | None, *args):
            if coeffs is None and effects is None:
                return folded(*args)
            return opened(model.coeffs if coeffs is None else coeffs, model.effects if effects is None else effects,
                          *args)

        return call

    run_compiled, filter_compiled = compiled(run), compiled(filter_only)

    def inputs(etas: np.ndarray, process_scale: np.ndarray | None) -> tuple[Belief, Array, Array]:
        """The prior, the samples padded to a bucketed length (records of similar length share one
        compilation; the NaN rows come after the record, predict-only, and are cut off again) and Q's factors."""
        padded = np.full((-(-len(etas) // PAD_BUCKET) * PAD_BUCKET, 3), np.nan)
        padded[: len(etas)] = etas
        scale = np.ones(len(noise.process)) if process_scale is None else np.asarray(process_scale, dtype=float)
        return initial_belief(etas, np.asarray(noise.initial)), jnp.asarray(padded), jnp.asarray(scale)

    def estimate(
        stamps_ns: np.ndarray,
        etas: np.ndarray,
        onset_index: int = 0,
        missing: int = 0,
        coeffs: Coefficients | None = None,
        effects: Effects | None = None,
        start_time: float = 0.0,
        process_scale: np.ndarray | None = None,
    ) -> Estimate:
        """Filter and smooth samples on a regular grid (NaN rows = missing) from onset_index on,
        with the compiled model or with other coefficients / effects of the same rig; the row at onset_index
        `start_time` s after the drop onset (a later segment's; what clocked effects read)."""
        stamps_ns, etas = stamps_ns[onset_index:], etas[onset_index:]
        initial, padded, scale = inputs(etas, process_scale)
        outputs = run_compiled(coeffs, effects, initial, padded, start_time, scale)
        trimmed = jax.tree.map(lambda a: a[: len(etas)], jax.device_get(outputs))
        filtered, smoothed, predicted, innovation, innovation_cov, nis, factor = trimmed
        return Estimate(
            stamps_ns=stamps_ns,
            measured=etas,
            filtered=filtered,
            smoothed=smoothed,
            predicted_output=predicted,
            innovation=innovation,
            innovation_cov=innovation_cov,
            nis=nis,
            process_scale=factor,
            onset_index=onset_index,
            missing=missing,
        )

    def innovations(
        etas: np.ndarray,
        onset_index: int = 0,
        coeffs: Coefficients | None = None,
        effects: Effects | None = None,
        start_time: float = 0.0,
        process_scale: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The filter's innovations (N, 3) m (NaN where no sample) and their covariances (N, 3, 3) m^2 from
        onset_index on, as `estimate` would filter them."""
        etas = etas[onset_index:]
        initial, padded, scale = inputs(etas, process_scale)
        outputs = filter_compiled(coeffs, effects, initial, padded, start_time, scale)
        return tuple(np.asarray(a)[: len(etas)] for a in jax.device_get(outputs))

    estimate.innovations = innovations
    estimate.model = model  # what it was compiled for (estimate_bag gates its effects per bag)
    estimate.noise = noise
    return estimate
