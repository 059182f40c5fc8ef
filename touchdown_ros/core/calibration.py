"""Stage 1 of identification: the nominal contact law and its constants f0 from displacements.

The six constants (k_R, c_R, mu, k_Z, c_Z, k_ZR: positive) are fitted on a log scale,
together with two factors on the process noise Q (radial and axial block, `nll` loss only),
the active effects' parameters (each divided by the change that moves its effect's force by
the rotor's weight rms along the data, `data_scales`; no prior) and the changes of the radial and
axial clearances r0, z0 from the rig YAML's (in units of CLEARANCE_UNIT), by minimising

    J = [sum over samples of the output error (core.training)
         + sum_i ((ln f0_i - ln guess_i) / prior_width)^2 + sum_j (ln q_j / Q_PRIOR_WIDTH)^2
         + sum_c (delta_c / clearance_width)^2] / N

that is, with the `nll` loss, twice the negative log-posterior per sample under a
log-normal prior around the rig YAML's guess. The prior holds what the data cannot
tell (damping, friction) near the guess instead of letting it wander; where the data
speak (stiffness) it is negligible. Standard errors come from the curvature of J, its
Gauss-Newton part (the Fisher information of the innovations, `stage1_information`).

Also here: the sensor noise from the levitated samples, carrying a guess from one
contact law to another, and kernel centres placed where the data are.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from touchdown_ros.core.diagnostics.breakdown import deformations
from touchdown_ros.core.diagnostics.regressors import library_regressors
from touchdown_ros.core.effects import Effects
from touchdown_ros.core.ekf import Belief, ekf, inverse_and_det_3x3
from touchdown_ros.core.training import RECORDS, Batch, errors_of_innovations, innovations, output_error
from touchdown_ros.core.types import PARAMETER_NAMES, STATE_SIZE, ContactLaw, FilterNoise, Kernel, Model, Nominal, Rig

#: Which Q entries each noise factor scales: radial (x, y, xdot, ydot) and axial (z, zdot); theta stays.
Q_BLOCKS = ((0, 1, 4, 5), (2, 6))
Q_NAMES = ("q_radial", "q_axial")
#: Prior width of ln q: the YAML's Q is a rough guess (e^3 = 20x either way is one sd).
Q_PRIOR_WIDTH = 3.0
#: Parameters whose posterior sd is at least this share of the prior sd are "held by the prior".
HELD_BY_PRIOR = 0.5
#: Names of the clearance coordinates (`Stage1.clearance`): the changes of r0 and z0 from the rig YAML's.
CLEARANCE_NAMES = ("radial_clearance", "axial_clearance")
#: Metres per clearance coordinate: a step of one moves a contact of tens of micrometres' deformation
#: about as much as a step of one in ln k does.
CLEARANCE_UNIT = 1.0e-5
#: Stiffness and damping of the normal force, by position in `PARAMETER_NAMES`.
_STIFFNESS, _DAMPING = (0, 3), (1, 4)


class Stage1(NamedTuple):
    """What stage 1 fits, in the optimiser's coordinates."""

    log_f0: Array  # (6,) ln of k_R, c_R, mu, k_Z, c_Z, k_ZR in the law's units
    log_q: Array  # (2,) ln of the factors on Q's radial and axial blocks
    effects: Effects  # active effects, parameters divided by their scales
    log_support: Array | None = None  # (2,) ln of the axial support's preload and span (N); None: the law's;
    # +inf: rigid (so rigid and yielding candidates are one program: `RIGID_LOG_SUPPORT`)
    clearance: Array | None = None  # (2,) r0 and z0 minus the rig YAML's, in CLEARANCE_UNIT; None: the YAML's
    log_stribeck: Array | None = None  # (2,) ln of the ring friction's Stribeck drop and velocity (1, m/s); None:
    # the law's


#: Names of the axial support's coordinates (`Stage1.log_support`).
SUPPORT_NAMES = ("support_preload", "support_span")


#: Names of the Stribeck coordinates (`Stage1.log_stribeck`).
STRIBECK_NAMES = ("friction_drop", "stribeck_velocity")


#: `Stage1.log_support` of a rigid support (preload and span infinite).
RIGID_LOG_SUPPORT = (float("inf"), float("inf"))


def support_law(law: ContactLaw, log_support: Array) -> ContactLaw:
    """`law` with the axial support of `log_support` (ln preload, ln span; N; +inf: rigid)."""
    finite = jnp.isfinite(log_support)
    # exp of a finite stand-in where +inf, so the (unused) gradient there is 0, not inf * 0
    values = jnp.where(finite, jnp.exp(jnp.where(finite, log_support, 0.0)), jnp.inf)
    return law.with_support(values[0], values[1])


def stribeck_law(law: ContactLaw, log_stribeck: Array) -> ContactLaw:
    """`law` with the ring friction's Stribeck drop and velocity exp(log_stribeck) (1, m/s)."""
    return law._replace(friction_drop=jnp.exp(log_stribeck[0]), stribeck_velocity=jnp.exp(log_stribeck[1]))


def log_support_of(law: ContactLaw) -> np.ndarray:
    """ln of `law`'s axial support preload and span (N; +inf where rigid)."""
    return np.log([float(law.support_preload), float(law.support_span)])


def log_stribeck_of(law: ContactLaw) -> np.ndarray:
    """ln of `law`'s Stribeck drop and velocity, where stage 1 starts them and centres their prior;
    ValueError without a drop (no logarithm)."""
    values = np.asarray([float(law.friction_drop), float(law.stribeck_velocity)])
    if not np.all(values > 0.0):
        raise ValueError(
            "a Stribeck drop fitted in stage 1 needs a guess > 0: contact.friction_drop (mu_s / mu_k - 1) and "
            "contact.stribeck_velocity (m/s)"
        )
    return np.log(values)


def q_factors(log_q: Array, size: int = STATE_SIZE) -> Array:
    """(size,) factors on the diagonal of Q from the two block factors (a spinning ring's speed: 1)."""
    factors = jnp.ones(size, dtype=log_q.dtype)
    for j, block in enumerate(Q_BLOCKS):
        factors = factors.at[jnp.asarray(block)].set(jnp.exp(log_q[j]))
    return factors


def nominal_of(log_f0: Array) -> Nominal:
    return Nominal(*(jnp.exp(log_f0[i]) for i in range(len(PARAMETER_NAMES))))


def log_nominal(nominal: Nominal) -> np.ndarray:
    values = np.asarray([float(v) for v in nominal], dtype=float)
    if np.any(values <= 0.0):
        zero = [n for n, v in zip(PARAMETER_NAMES, values) if v <= 0.0]
        raise ValueError(f"contact guess {', '.join(zero)} must be > 0 to be calibrated on a log scale")
    return np.log(values)


def effect_scales(effects: Effects) -> Effects:
    """Each effect parameter's magnitude (its starting value, at least 1e-6): the optimiser works
    on parameter / scale. The fallback of `force_scaled` for a parameter that moves no force."""
    return Effects(effects.effects, tuple({k: max(abs(float(v)), 1e-6) for k, v in p.items()} for p in effects.params))


def force_scaled(scales: Effects, names: Sequence[str], states: Array, model: Model, force: float) -> Effects:
    """`scales` (`effect_scales`) with the named effects' parameter scales replaced by the change
    that moves the effect's force by `force` N rms along the states (N, n), linearised at the
    effect's values in `model.effects` (its defaults if it is not there): every coordinate then
    moves the model alike, whatever its unit (a stiffness in N/m, a load in N, a drag in N s/m
    started at 10 for 3000); a parameter that moves no force there keeps its scale. A clocked effect is
    linearised at the drop onset (its decay time then moves no force and keeps its scale)."""
    values = dict(zip(model.effects.names, model.effects.params))
    named = {e.name: e for e in scales.effects if e.name in names}
    at = {n: {k: float(v) for k, v in values[n].items()} for n in named if n in values}
    # One compiled program for all of them: run eagerly, op by op, the Jacobians cost 4x as much.
    regressors = jax.jit(lambda along: library_regressors(named, along, model, at))(jnp.asarray(states))
    params = []
    for e, p in zip(scales.effects, scales.params):
        if e.name not in named:
            params.append(p)
            continue
        jacobian = np.asarray(regressors[e.name][0])  # (N, 3, p) in parameter order
        rms = np.sqrt(np.nanmean(np.sum(jacobian**2, axis=1), axis=0)) if len(jacobian) else np.zeros(len(p))
        params.append({k: float(force / r) if np.isfinite(r) and r > 0.0 else p[k] for k, r in zip(e.parameters, rms)})
    return Effects(scales.effects, tuple(params), scales.gates)


def data_scales(model: Model, states: np.ndarray, acts: np.ndarray) -> Effects:
    """Stage 1's scales of `model.effects`' parameters: `force_scaled` by the rotor's weight along
    the states (N, n) where each effect acts (acts (N, E): its gate on), from its values there."""
    weight = float(model.rig.mass) * float(model.rig.gravity)
    scales = effect_scales(model.effects)
    for i, name in enumerate(model.effects.names):
        scales = force_scaled(scales, [name], jnp.asarray(states[acts[:, i]]), model, weight)
    return scales


def apply_scales(scaled: Effects, scales: Effects, inverse: bool = False) -> Effects:
    """Scaled parameters -> physical (or back with inverse=True)."""
    combine = (lambda v, s: v / s) if inverse else (lambda v, s: v * s)
    return Effects(
        scaled.effects,
        tuple({k: combine(v, s[k]) for k, v in p.items()} for p, s in zip(scaled.params, scales.params)),
        scaled.gates,
    )


def stage1_start(
    log_f0: Array, effects: Effects, scales: Effects, log_support: Array | None = None,
    log_stribeck: Array | None = None,
) -> Stage1:
    """Stage 1's coordinates at the start: ln f0 as given, Q as the YAML's (factors 1), the effects'
    parameters over their scales, the support as given (None: the law's), the clearances the YAML's."""
    scaled = apply_scales(effects, scales, inverse=True)
    return Stage1(
        jnp.asarray(log_f0), jnp.zeros(len(Q_NAMES)), scaled, log_support, jnp.zeros(len(CLEARANCE_NAMES)), log_stribeck
    )


def clearance_width(tolerance: float) -> float:
    """Prior sd of the clearance coordinates for `training.clearance_tolerance` (m); 1 where they are not
    fitted (0: held at the YAML's, where the prior adds nothing)."""
    return tolerance / CLEARANCE_UNIT if tolerance > 0.0 else 1.0


def with_clearances(rig: Rig, clearance: Array | None) -> Rig:
    """`rig` with r0 and z0 moved by the clearance coordinates (`Stage1.clearance`; None: as it is)."""
    if clearance is None:
        return rig
    return rig._replace(
        radial_clearance=rig.radial_clearance + CLEARANCE_UNIT * clearance[0],
        axial_clearance=rig.axial_clearance + CLEARANCE_UNIT * clearance[1],
    )


def scaled_bounds(tree, scales: Effects) -> list[tuple[float, float]]:
    """(low, high) of every entry of ``ravel_pytree(tree)``, a tree holding scaled `Effects` (a
    `Stage1`, stage 2's trainable): an effect parameter's `Effect.bounds` over its scale, every
    other entry unbounded (for L-BFGS-B)."""

    def side(index: int):
        def limits(node):
            if not isinstance(node, Effects):
                return np.full(np.shape(node), (-np.inf, np.inf)[index])
            params = tuple(
                {k: e.bounds.get(k, (-np.inf, np.inf))[index] / s[k] for k in p}
                for e, p, s in zip(node.effects, node.params, scales.params)
            )
            return Effects(node.effects, params, ((-np.inf, np.inf)[index],) * len(node))

        limited = jax.tree_util.tree_map(limits, tree, is_leaf=lambda n: isinstance(n, Effects))
        return np.asarray(ravel_pytree(limited)[0])

    return list(zip(side(0).tolist(), side(1).tolist()))


def stage1_model_and_noise(
    theta: Stage1, base: Model, noise: FilterNoise, scales: Effects
) -> tuple[Model, FilterNoise]:
    """The model (constant parameters, alpha = 0) and filter noise at stage-1 coordinates theta."""
    law = base.law if theta.log_support is None else support_law(base.law, theta.log_support)
    law = law if theta.log_stribeck is None else stribeck_law(law, theta.log_stribeck)
    model = base._replace(
        rig=with_clearances(base.rig, theta.clearance),
        law=law,
        nominal=nominal_of(theta.log_f0),
        coeffs=base.coeffs._replace(
            alpha_R=jnp.zeros_like(base.coeffs.alpha_R), alpha_Z=jnp.zeros_like(base.coeffs.alpha_Z)
        ),
        effects=apply_scales(theta.effects, scales),
    )
    return model, noise._replace(process=noise.process * q_factors(theta.log_q, len(noise.process)))


def stage1_objective(
    theta: Stage1,
    guess_log_f0: Array,
    prior_width: float,
    base: Model,
    noise: FilterNoise,
    scales: Effects,
    h: float,
    batch: Batch,
    kind: str,
    mesh=None,
    prior_weight: float | Array = 1.0,
    clearance_width: float = 1.0,
) -> Array:
    """J of the module docstring at theta (per valid sample), the prior weighted by prior_weight
    (1/C for each of C chunks of the records: `stage1_value_and_grad_over`)."""
    model, fitted_noise = stage1_model_and_noise(theta, base, noise, scales)
    data = output_error(model, fitted_noise, h, batch, mesh, kind)
    prior = stage1_prior(theta, guess_log_f0, prior_width, clearance_width, base.law)
    return data + prior_weight * prior / jnp.sum(batch.valid)


def stage1_prior(
    theta: Stage1,
    guess_log_f0: Array,
    prior_width: float,
    clearance_width: float = 1.0,
    guess: ContactLaw | None = None,
) -> Array:
    """The prior's part of J before its division by the samples (module docstring): -2 ln of the prior
    density at theta, without constants. A Stribeck drop, where fitted, is held like f0 (prior_width) around
    the `guess` law's."""
    prior = jnp.sum(((theta.log_f0 - guess_log_f0) / prior_width) ** 2) + jnp.sum((theta.log_q / Q_PRIOR_WIDTH) ** 2)
    if theta.clearance is not None:
        prior = prior + jnp.sum((theta.clearance / clearance_width) ** 2)
    if theta.log_stribeck is not None and guess is not None:
        centre = jnp.log(jnp.stack([guess.friction_drop, guess.stribeck_velocity]))
        prior = prior + jnp.sum(((theta.log_stribeck - centre) / prior_width) ** 2)
    return prior


@functools.partial(jax.jit, static_argnames=("prior_width", "h", "kind", "mesh", "clearance_width"))
def stage1_value(
    theta: Stage1,
    guess_log_f0: Array,
    base: Model,
    noise: FilterNoise,
    scales: Effects,
    batch: Batch,
    *,
    prior_width: float,
    h: float,
    kind: str,
    mesh: Mesh | None = None,
    prior_weight: float | Array = 1.0,
    clearance_width: float = 1.0,
) -> Array:
    """`stage1_objective`, compiled once per (prior width, h, loss, mesh) and batch shape: the model,
    noise, scales, records (their effects' gates too) and prior weight are traced, so other values
    reuse it. Alone where only losses are compared (start grids, restarts): the filter without its
    gradient, about a quarter of `stage1_value_and_grad`'s call (23 against 99 ms on six campaign
    records) and a seventh of its compilation."""
    return stage1_objective(
        theta, guess_log_f0, prior_width, base, noise, scales, h, batch, kind, mesh, prior_weight, clearance_width
    )


@functools.partial(jax.jit, static_argnames=("prior_width", "h", "kind", "mesh", "clearance_width"))
def stage1_value_and_grad(theta: Stage1, *arguments, **static) -> tuple[Array, Stage1]:
    """`stage1_value` (the same arguments) and its gradient by theta."""
    return jax.value_and_grad(stage1_value.__wrapped__)(theta, *arguments, **static)


def _over_chunks(chunks: Sequence[Batch], call: Callable[[Batch, float], Any]) -> list[tuple[float, Any]]:
    """(share, host result of `call(chunk, prior_weight)`) of each chunk, its share its valid samples'.
    One chunk at a time, nothing else on the devices between them: with the chunks' programs and
    the sums of their results in flight together, the all-reduce deadlocked (`core.xla`). Each
    chunk is waited for on every device: fetching its result reads the first device's copy only."""
    counts = np.array([np.sum(np.asarray(chunk.valid)) for chunk in chunks], dtype=float)
    return [
        (share, jax.device_get(jax.block_until_ready(call(chunk, 1.0 / len(chunks)))))
        for chunk, share in zip(chunks, counts / counts.sum())
    ]


def stage1_value_and_grad_over(
    chunks: Sequence[Batch], theta: Stage1, guess_log_f0: Array, base: Model, noise: FilterNoise, scales: Effects,
    **static,
) -> tuple[float, Stage1]:
    """`stage1_value_and_grad` of the records of all `chunks` (batches of one shape, so one program
    serves them all, e.g. the few records the contact laws are screened on and, chunk by chunk, all
    of them): the chunks' J weighted by their valid samples, the prior counted once; on the host."""
    value, grad = 0.0, None
    for share, (v, g) in _over_chunks(chunks, lambda chunk, weight: stage1_value_and_grad(
        theta, guess_log_f0, base, noise, scales, chunk, prior_weight=weight, **static
    )):
        value += share * float(v)
        scaled = jax.tree.map(lambda leaf: share * np.asarray(leaf, dtype=float), g)
        grad = scaled if grad is None else jax.tree.map(np.add, grad, scaled)
    return value, grad


def stage1_value_over(
    chunks: Sequence[Batch], theta: Stage1, guess_log_f0: Array, base: Model, noise: FilterNoise, scales: Effects,
    **static,
) -> float:
    """`stage1_value_and_grad_over`'s value alone (`stage1_value`)."""
    return sum(share * float(v) for share, v in _over_chunks(chunks, lambda chunk, weight: stage1_value(
        theta, guess_log_f0, base, noise, scales, chunk, prior_weight=weight, **static
    )))


class Coordinates:
    """The stage-1 coordinates an optimiser moves: the entries of a `Stage1` flagged free (flag 1),
    as one flat vector; the other entries keep their values in `start`."""

    def __init__(self, start: Stage1, flags: Stage1):
        if start.clearance is None:  # a start without clearance coordinates: the YAML's r0 and z0, held
            flags = flags._replace(clearance=None)
        flat, self._unravel = ravel_pytree(start)
        self.start = np.asarray(flat, dtype=float)
        leaves, self._treedef = jax.tree_util.tree_flatten(start)
        self._shapes = [np.shape(leaf) for leaf in leaves]
        self._splits = np.cumsum([int(np.prod(shape)) for shape in self._shapes])[:-1]
        self.free = np.asarray(ravel_pytree(flags)[0]) > 0.5
        labels = Stage1(
            list(PARAMETER_NAMES),
            list(Q_NAMES),
            Effects(
                start.effects.effects,
                tuple({k: f"{e.name}.{k}" for k in p} for e, p in zip(start.effects.effects, start.effects.params)),
                tuple(f"{e.name}.gate" for e in start.effects.effects),
            ),
            None if start.log_support is None else list(SUPPORT_NAMES),
            None if start.clearance is None else list(CLEARANCE_NAMES),
            None if start.log_stribeck is None else list(STRIBECK_NAMES),
        )
        self.names = [n for n, f in zip(jax.tree_util.tree_leaves(labels), self.free) if f]

    def initial(self, **fields: Array) -> np.ndarray:
        """The free coordinates at the start, with the given `Stage1` fields replaced (e.g. log_f0=...)."""
        return self.flat(self._unravel(self.start)._replace(**fields))

    def theta(self, x: np.ndarray) -> Stage1:
        """The `Stage1` with the free coordinates x and the others from the start (numpy leaves, built
        on the host: `ravel_pytree`'s unravel runs a JAX operation per leaf, 0.77 ms against 0.08 ms a
        call for 13 coordinates)."""
        full = self.start.copy()
        full[self.free] = x
        parts = np.split(full, self._splits)
        return self._treedef.unflatten([part.reshape(shape) for part, shape in zip(parts, self._shapes)])

    def flat(self, tree: Stage1) -> np.ndarray:
        """The free coordinates of a `Stage1` of this layout (e.g. a gradient), in the order of `theta`."""
        leaves = jax.tree_util.tree_leaves(jax.device_get(tree))
        return np.concatenate([np.ravel(np.asarray(leaf, dtype=float)) for leaf in leaves])[self.free]

    def directions(self, count: int | None = None) -> Stage1:
        """One unit step along each free coordinate: a `Stage1` whose leaves have a leading axis of
        that many (the tangents of `stage1_information`), padded with zero steps to `count` (so fits
        with different free coordinates share one compiled program)."""
        steps = np.eye(len(self.start))[self.free]
        padding = np.zeros((max(0, (count or 0) - len(steps)), len(self.start)))
        return jax.vmap(self._unravel)(jnp.asarray(np.concatenate([steps, padding])))

    def objective(
        self, value_and_grad: Callable[[Stage1], tuple[Array, Stage1]]
    ) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
        """A loss of `Stage1` with its gradient as a function of the free coordinates (for `minimise`)."""

        def of_free(x: np.ndarray) -> tuple[float, np.ndarray]:
            value, grad = value_and_grad(self.theta(x))
            return float(value), self.flat(grad)

        return of_free

    def loss(self, value: Callable[[Stage1], Array]) -> Callable[[np.ndarray], float]:
        """A loss of `Stage1` alone as a function of the free coordinates."""
        return lambda x: float(value(self.theta(x)))

    def bounds(self, scales: Effects) -> list[tuple[float, float]]:
        """(low, high) of each free coordinate (`scaled_bounds`)."""
        return [b for b, free in zip(scaled_bounds(self._unravel(self.start), scales), self.free) if free]

    def prior_sd(self, prior_width: float, clearance_width: float = 1.0) -> np.ndarray:
        """Prior sd of each free coordinate: prior_width for ln f0 and the Stribeck drop, Q_PRIOR_WIDTH for ln q,
        clearance_width for the clearances, none (inf) for effects and the support."""
        widths = {**dict.fromkeys(PARAMETER_NAMES + STRIBECK_NAMES, prior_width),
                  **dict.fromkeys(Q_NAMES, Q_PRIOR_WIDTH),
                  **dict.fromkeys(CLEARANCE_NAMES, clearance_width)}
        return np.asarray([widths.get(n, np.inf) for n in self.names])


def stage1_flags(
    effects: Effects,
    fit_q: bool,
    fit_f0: bool = True,
    fitted_effects: Sequence[str] | None = None,
    fit_support: bool | None = None,
    fit_clearances: bool = False,
    fit_stribeck: bool | None = None,
) -> Stage1:
    """Which stage-1 coordinates are free: ln f0 (fit_f0), ln q (fit_q), the parameters of the
    effects named in fitted_effects (default: all), never the gates, the axial support
    (fit_support True: free, False: held at its start's `log_support`, None: the start has none),
    the clearances (fit_clearances) and the Stribeck drop (fit_stribeck, as fit_support)."""
    chosen = effects.names if fitted_effects is None else tuple(fitted_effects)
    return Stage1(
        jnp.full(len(PARAMETER_NAMES), float(fit_f0)),
        jnp.full(len(Q_NAMES), float(fit_q)),
        Effects(
            effects.effects,
            tuple({k: float(e.name in chosen) for k in p} for e, p in zip(effects.effects, effects.params)),
            (0.0,) * len(effects),
        ),
        None if fit_support is None else jnp.full(len(SUPPORT_NAMES), float(fit_support)),
        jnp.full(len(CLEARANCE_NAMES), float(fit_clearances)),
        None if fit_stribeck is None else jnp.full(len(STRIBECK_NAMES), float(fit_stribeck)),
    )


def effect_coordinates(start: Stage1, names: Sequence[str]) -> Coordinates:
    """The coordinates of the effects `names` alone, everything else held at `start` (its constants, Q, other
    effects, and the support and Stribeck drop where it has them): a new effect fitted to a calibrated model."""
    return Coordinates(start, stage1_flags(
        start.effects, False, fit_f0=False, fitted_effects=names,
        fit_support=None if start.log_support is None else False,
        fit_stribeck=None if start.log_stribeck is None else False,
    ))


def further_starts(theta: Stage1, scales: Effects, names: Sequence[str]) -> list[tuple[str, Stage1]]:
    """`theta` with one parameter of one of the effects `names` at each of its further starts (`Effect.starts`;
    `scales` as the coordinates'), each with a label (", from brake_decay.rate 1")."""
    starts = []
    for name in names:
        index = theta.effects.names.index(name)
        for parameter, values in theta.effects.effects[index].starts.items():
            scale = scales.params[index][parameter]
            starts += [
                (f", from {name}.{parameter} {value:g}",
                 theta._replace(effects=theta.effects.with_values({name: {parameter: value / scale}})))
                for value in values
            ]
    return starts


def fit_starts(coordinates: Coordinates, scales: Effects, names: Sequence[str]) -> list[tuple[str, np.ndarray]]:
    """The free coordinates where a fit of the effects `names` starts: its own start (label ""), then each of the
    effects' further starts (`further_starts`), for `workflows.optimise.minimise_from_each`."""
    own = coordinates.initial()
    further = further_starts(coordinates.theta(own), scales, names)
    return [("", own)] + [(where, coordinates.initial(**theta._asdict())) for where, theta in further]


def convert_guess(nominal: Nominal, source: ContactLaw, target: ContactLaw, reference_deformation: float) -> Nominal:
    """A guess of one contact law carried to another: the same spring force and the same damping
    force at the reference deformation d (m): k' = k d^(n - n'), c' = c d^(m - m'), with m the
    power of d in the damping force (0 linear and kelvin_voigt, n hertz)."""
    d = reference_deformation
    stiffness = d ** (float(source.stiffness_exponent) - float(target.stiffness_exponent))
    damping = d ** (float(source.damping_exponent) - float(target.damping_exponent))
    values = list(nominal)
    for i in _STIFFNESS:
        values[i] = values[i] * stiffness
    for i in _DAMPING:
        values[i] = values[i] * damping
    return Nominal(*values)


def sensor_noise(levitated: np.ndarray) -> np.ndarray:
    """(3,) sensor noise sd per axis (m) from levitated samples (N, 3), NaN rows allowed.

    From second differences, which cancel the slow levitated orbit (an unbalance orbit of a
    few um at the rotor speed moves ~1e-8 m between three samples at 10 kHz): for white noise
    var(x[k+1] - 2 x[k] + x[k-1]) = 6 sigma^2. The sd of the differences within 5 robust sd
    (1.4826 MAD) of their median: as efficient as the sd, not thrown by a few outliers.
    """
    second = levitated[2:] - 2.0 * levitated[1:-1] + levitated[:-2]
    sigma = np.full(3, np.nan)
    for axis in range(3):
        values = second[:, axis][np.isfinite(second[:, axis])]
        if values.size >= 20:
            centre = np.median(values)
            spread = 1.4826 * np.median(np.abs(values - centre))
            kept = values[np.abs(values - centre) <= 5.0 * spread] if spread > 0 else values
            sigma[axis] = np.sqrt(np.mean((kept - centre) ** 2) / 6.0)
    return sigma


@functools.partial(jax.jit, static_argnames=("h", "kind", "mesh"))
def stage1_information(
    theta: Stage1, directions: Stage1, base: Model, noise: FilterNoise, scales: Effects, h: float, batch: Batch,
    kind: str, mesh: Mesh | None = None,
) -> Array:
    """`fisher_information` of the records of `batch`; with a mesh, each device takes its share of the
    records (`place`d on it) and the sums are added."""
    if mesh is None:
        return fisher_information(theta, directions, base, noise, scales, h, batch, kind)

    def share(*args) -> Array:
        return jax.lax.psum(fisher_information(*args[:5], h, args[5], kind), RECORDS)

    replicated = jax.tree.map(jnp.asarray, (theta, directions, base, noise, scales))
    return jax.shard_map(share, mesh=mesh, in_specs=(P(),) * 5 + (P(RECORDS),), out_specs=P(), check_vma=False)(
        *replicated, batch
    )


def stage1_information_over(
    chunks: Sequence[Batch], theta: Stage1, directions: Stage1, base: Model, noise: FilterNoise, scales: Effects,
    h: float, kind: str, mesh: Mesh | None = None,
) -> np.ndarray:
    """`stage1_information` of the records of all `chunks`, summed on the host; one chunk at a time,
    each waited for on every device (as `stage1_value_and_grad_over`, and for the same reason)."""
    total = np.zeros((len(jax.tree_util.tree_leaves(directions)[0]),) * 2)
    for chunk in chunks:
        total += np.asarray(jax.device_get(jax.block_until_ready(
            stage1_information(theta, directions, base, noise, scales, h, chunk, kind, mesh)
        )))
    return total


def fisher_information(
    theta: Stage1, directions: Stage1, base: Model, noise: FilterNoise, scales: Effects, h: float, batch: Batch,
    kind: str,
) -> Array:
    """(p, p) Fisher information of the data along p directions of the stage-1 coordinates (`directions`:
    a `Stage1` whose leaves have a leading axis p, `Coordinates.directions`), summed over the valid
    samples of `batch` that are not held out: sum_k dnu_i^T S^-1 dnu_j + tr(S^-1 dS_i S^-1 dS_j) / 2,
    with nu, S the innovations and their covariance (`nll`; `one_step`: dnu_i^T R^-1 dnu_j). That is
    the Gauss-Newton part of N/2 times J's Hessian, positive semi-definite, from one forward pass with
    p tangents (the derivatives by forward-mode AD through the filter)."""

    def moments(t: Stage1) -> tuple[Array, Array]:
        return innovations(*stage1_model_and_noise(t, base, noise, scales), h, batch)

    (_, S), (d_nu, d_S) = jax.vmap(lambda d: jax.jvp(moments, (theta,), (d,)), out_axes=(None, 0))(directions)
    return _information(S, d_nu, d_S, noise.measurement, batch, kind)


def _information(S: Array, d_nu: Array, d_S: Array, measurement: Array, batch: Batch, kind: str) -> Array:
    """`fisher_information` from the innovations' covariances S (B, L, 3, 3) and the p tangents of the
    innovations d_nu (p, B, L, 3) and of S (p, B, L, 3, 3)."""
    counted = (batch.valid & ~batch.held_out)[None, ..., None]
    d_nu = jnp.where(counted, d_nu, 0.0)
    if kind == "one_step":
        return jnp.einsum("pblk,qblk->pq", d_nu / measurement, d_nu)
    S = jnp.where(counted[0, ..., None], S, jnp.eye(3))
    S_inverse = jnp.linalg.inv(S)
    whitened = jnp.einsum("blij,pblj->pbli", S_inverse, d_nu)
    mean_part = jnp.einsum("pbli,qbli->pq", d_nu, whitened)
    d_S = jnp.where(counted[..., None], d_S, 0.0)
    spread = jnp.einsum("blij,pbljk->pblik", S_inverse, d_S)
    return mean_part + 0.5 * jnp.einsum("pblik,qblki->pq", spread, spread)


class GaussNewtonTerms(NamedTuple):
    """J (the module docstring's, per sample), its derivatives along p directions of the stage-1 coordinates
    and the data's Fisher information along them (`fisher_information`): J's Gauss-Newton Hessian is
    2 (information + the prior's precision) / N."""

    value: Array  # ()
    gradient: Array  # (p,)
    information: Array  # (p, p)


def _data_terms(
    theta: Stage1, directions: Stage1, base: Model, noise: FilterNoise, scales: Effects, h: float, batch: Batch,
    kind: str,
) -> tuple[Array, Array, Array]:
    """(sum of the output error over the fitted samples, its derivatives along `directions`, the Fisher
    information along them) from one forward pass with p tangents."""
    fitted = batch.valid & ~batch.held_out

    def moments(t: Stage1) -> tuple[Array, Array, Array]:
        model, fitted_noise = stage1_model_and_noise(t, base, noise, scales)
        nu, S = innovations(model, fitted_noise, h, batch)
        errors = errors_of_innovations(nu, S, fitted_noise.measurement, batch.valid, kind)
        return jnp.sum(jnp.where(fitted, errors, 0.0)), nu, S

    (total, _, S), (d_total, d_nu, d_S) = jax.vmap(
        lambda d: jax.jvp(moments, (theta,), (d,)), out_axes=(None, 0)
    )(directions)
    return total, d_total, _information(S, d_nu, d_S, noise.measurement, batch, kind)


@functools.partial(jax.jit, static_argnames=("prior_width", "h", "kind", "mesh", "clearance_width"))
def stage1_gauss_newton(
    theta: Stage1,
    directions: Stage1,
    guess_log_f0: Array,
    base: Model,
    noise: FilterNoise,
    scales: Effects,
    batch: Batch,
    *,
    prior_width: float,
    h: float,
    kind: str,
    mesh: Mesh | None = None,
    prior_weight: float | Array = 1.0,
    clearance_width: float = 1.0,
) -> GaussNewtonTerms:
    """`GaussNewtonTerms` of `stage1_value` (the same arguments, and the p `directions` as in
    `fisher_information`); with a mesh, each device takes its share of the records and the sums are added.
    Forward-mode AD: on the campaign's 21 records about twice the time of `stage1_value_and_grad` for 16
    directions (4.9 against 2.3 s), and the information comes with it."""
    if mesh is None:
        total, d_total, information = _data_terms(theta, directions, base, noise, scales, h, batch, kind)
    else:
        def share(*args) -> tuple[Array, Array, Array]:
            return jax.lax.psum(_data_terms(*args[:5], h, args[5], kind), RECORDS)

        replicated = jax.tree.map(jnp.asarray, (theta, directions, base, noise, scales))
        total, d_total, information = jax.shard_map(
            share, mesh=mesh, in_specs=(P(),) * 5 + (P(RECORDS),), out_specs=P(), check_vma=False
        )(*replicated, batch)

    def prior_of(t: Stage1) -> Array:
        return stage1_prior(t, guess_log_f0, prior_width, clearance_width, base.law)

    prior, d_prior = jax.vmap(lambda d: jax.jvp(prior_of, (theta,), (d,)), out_axes=(None, 0))(directions)
    fitted = jnp.sum(batch.valid & ~batch.held_out)
    weight = prior_weight / jnp.sum(batch.valid)
    return GaussNewtonTerms(total / fitted + weight * prior, d_total / fitted + weight * d_prior, information)


def stage1_gauss_newton_over(
    chunks: Sequence[Batch], theta: Stage1, directions: Stage1, guess_log_f0: Array, base: Model, noise: FilterNoise,
    scales: Effects, **static,
) -> GaussNewtonTerms:
    """`stage1_gauss_newton` of the records of all `chunks` (as `stage1_value_and_grad_over`: J and its
    derivatives weighted by the chunks' valid samples, the prior counted once; the information summed)."""
    value, gradient, information = 0.0, 0.0, 0.0
    for share, terms in _over_chunks(chunks, lambda chunk, weight: stage1_gauss_newton(
        theta, directions, guess_log_f0, base, noise, scales, chunk, prior_weight=weight, **static
    )):
        value += share * float(terms.value)
        gradient = gradient + share * np.asarray(terms.gradient, dtype=float)
        information = information + np.asarray(terms.information, dtype=float)
    return GaussNewtonTerms(value, gradient, information)


def posterior_covariance(information: np.ndarray, prior_sd: np.ndarray | None = None) -> np.ndarray:
    """Posterior covariance of stage-1 coordinates: the inverse of the data's information
    (`stage1_information`, or N H / 2 of J's data part) plus the prior's precision, diag(1 / prior_sd^2)
    (inf: no prior). All NaN where the information is not finite (a fit whose filter diverged)."""
    prior = np.zeros(len(information)) if prior_sd is None else 1.0 / np.asarray(prior_sd, dtype=float) ** 2
    precision = 0.5 * (information + information.T) + np.diag(prior)
    if not np.all(np.isfinite(precision)):
        return np.full(precision.shape, np.nan)
    return np.linalg.pinv(precision, hermitian=True)


def information_standard_errors(
    information: np.ndarray, prior_sd: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Posterior sd and correlation matrix of stage-1 coordinates (`posterior_covariance`)."""
    return standard_errors_and_correlation(posterior_covariance(information, prior_sd))


def standard_errors_and_correlation(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sd and correlation matrix of a covariance (correlation 0 where an sd is 0)."""
    sd = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.outer(sd, sd)
    return sd, np.nan_to_num(correlation)


def strongest_correlations(names: list[str], correlation: np.ndarray, count: int = 5) -> list[tuple[str, str, float]]:
    """The `count` largest |correlations| between distinct coordinates, strongest first."""
    pairs = [
        (names[i], names[j], float(correlation[i, j])) for i in range(len(names)) for j in range(i + 1, len(names))
    ]
    return sorted(pairs, key=lambda p: -abs(p[2]))[:count]


def strongest_partner(names: Sequence[str], correlation: np.ndarray, index: int) -> tuple[str, float]:
    """The coordinate other than `names[index]` most correlated with it (by |correlation|), and that correlation."""
    partner = max((j for j in range(len(names)) if j != index), key=lambda j: abs(correlation[index, j]))
    return names[partner], float(correlation[index, partner])


#: Percentile of the in-contact deformations where the top row of kernel centres is placed.
DEFORMATION_PERCENTILE = 95.0


#: Kernel centres per input axis that `place_centres` lays on the data (count^2 per centre set).
PLACED_CENTRES = 5


def place_centres(
    deformation: np.ndarray, velocity: np.ndarray, count: int = PLACED_CENTRES
) -> tuple[np.ndarray, np.ndarray] | None:
    """A count x count grid of kernel centres over in-contact samples (deformation m > 0, velocity
    m/s): deformation from 0 to its 95th percentile, velocity over its 1st-99th percentiles.

    The few samples of an impact's peak cannot tell a local correction (10 % of the peak force
    moves a sample by about 0.1 um against 1-5 um of sensor noise), so centres there were set by
    the regulariser and the optimiser's path, not the data (docs/calibration.md, "Friction against
    a co-rotating ring, and where the learned functions act"): the peaks are left to stage 1's law.

    Returns (T (count^2, 2) in normalised units, scale (2,) m and m/s): one normalised unit is
    one grid spacing, so a width of 1 lets neighbouring centres overlap as on the YAML grid.
    None when fewer than 20 samples are in contact.
    """
    keep = np.isfinite(deformation) & np.isfinite(velocity) & (deformation > 0.0)
    if np.count_nonzero(keep) < 20:
        return None
    d, v = deformation[keep], velocity[keep]
    d_top = float(np.percentile(d, DEFORMATION_PERCENTILE))
    v_low, v_high = (float(x) for x in np.percentile(v, [1.0, 99.0]))
    if v_high - v_low <= 0.0 or d_top <= 0.0:
        return None
    scale = np.array([d_top / (count - 1), (v_high - v_low) / (count - 1)])
    d_centres = np.arange(count, dtype=float)
    v_centres = v_low / scale[1] + np.arange(count, dtype=float)
    grid_d, grid_v = np.meshgrid(d_centres, v_centres, indexing="ij")
    return np.stack([grid_d.ravel(), grid_v.ravel()], axis=1), scale


def kernel_as_placed(kernel: Kernel, count: int = PLACED_CENTRES) -> Kernel:
    """`kernel` with both centre sets shaped as `kernel_from_data` places them (count^2 centres on a unit
    grid, unit scales): a stand-in of the right shapes for compiling stage 2 before the data place them."""
    grid_d, grid_v = np.meshgrid(np.arange(count, dtype=float), np.arange(count, dtype=float), indexing="ij")
    T, scale = jnp.asarray(np.stack([grid_d.ravel(), grid_v.ravel()], axis=1)), jnp.ones(2)
    return kernel._replace(T_R=T, T_Z=T, scale_R=scale, scale_Z=scale)


def strongly_typed(tree):
    """`tree` with every leaf a strongly typed array: a constant of the YAML (a Python float) and a
    fitted value (an array) then hit the same compiled program instead of compiling it twice."""
    return jax.tree.map(lambda leaf: jnp.asarray(leaf, dtype=jnp.result_type(leaf)), tree)


def filtered_states(model: Model, noise: FilterNoise, h: float, batch: Batch) -> tuple[Array, Array]:
    """(B, L, n) filtered states of every record and (B, L) normalised innovations squared."""
    return _filtered_states(strongly_typed(model), strongly_typed(noise), h, batch)


@jax.jit
def _filtered_states(model: Model, noise: FilterNoise, h: float, batch: Batch) -> tuple[Array, Array]:

    def one(etas: Array, mean: Array, cov: Array, gates: Array):
        out = ekf(model._replace(effects=model.effects.with_gates(gates)), noise, h, Belief(mean, cov), etas)
        nu = jnp.where(out.used[:, None], out.innovation, 0.0)
        nis = jnp.einsum("ni,nij,nj->n", nu, inverse_and_det_3x3(out.innovation_cov)[0], nu)
        return out.filtered.mean, jnp.where(out.used, nis, jnp.nan)

    return jax.vmap(one)(batch.etas, batch.initial_mean, batch.initial_cov, batch.gates)


def contact_samples(
    model: Model, states: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """(radial deformation r - r0, rdot) and (axial compression -(z + z0), zdot) of states (..., n),
    flattened, m and m/s (the kernel inputs rho and zeta of eq. 10)."""
    states = np.asarray(states)
    states = states.reshape(-1, states.shape[-1])
    radial, rdot, axial, zdot = deformations(model.rig, states[np.all(np.isfinite(states), axis=1)])
    return (radial, rdot), (axial, zdot)


def kernel_from_data(
    kernel: Kernel, radial: tuple[np.ndarray, np.ndarray], axial: tuple[np.ndarray, np.ndarray],
    count: int = PLACED_CENTRES,
) -> tuple[Kernel, list[str]]:
    """`kernel` with centre sets placed on the in-contact (deformation, velocity) samples of each
    contact (`place_centres`); a set without enough contact keeps the given grid (and says so)."""
    notes = []
    placed_R, placed_Z = place_centres(*radial, count), place_centres(*axial, count)
    T_R, scale_R, T_Z, scale_Z = kernel.T_R, kernel.scale_R, kernel.T_Z, kernel.scale_Z
    if placed_R is None:
        notes.append("radial contact too rare in the data to place the radial centres; the kernel.* grid is kept")
    else:
        T_R, scale_R = placed_R
    if placed_Z is None:
        notes.append("axial contact too rare in the data to place the axial centres; the kernel.* grid is kept")
    else:
        T_Z, scale_Z = placed_Z
    return (
        kernel._replace(
            T_R=jnp.asarray(T_R), T_Z=jnp.asarray(T_Z), scale_R=jnp.asarray(scale_R), scale_Z=jnp.asarray(scale_Z)
        ),
        notes,
    )
