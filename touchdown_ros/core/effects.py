"""Add-on physical effects: named terms added to the paper's model (issue #5, #16).

An effect is a plain jnp function ``function(xi, params, rig) -> (3,)`` at state
xi = [x y z theta xdot ydot zdot], with ``params`` a dict name -> scalar of its physical
parameters and ``rig`` the `Rig`. Its `kind` says where it acts:

- ``"force"``: the force on the rotor in N along the sensor x, y, z axes;
  `dynamics.phi` adds sum(forces) / m to the accelerations;
- ``"measurement"``: the change of the sensor's output in m; the measurement model is
  h(xi) = (x, y, z) + sum(changes) (`dynamics.measurement`), used by the EKF's update;
- ``"speed"``: the rotor's speed omega (rad/s) and its unbalance's angle (rad), (2,), where the
  model holds the rig's constant speed and the angle theta = omega t; `dynamics.phi`'s unbalance
  m e omega^2 (cos, sin) angle and the friction's slip against a co-rotating ring use them
  (`dynamics.rotor_speed`). theta stays the clock: d theta / dt is the rig's speed.

A `clocked` effect is a function of the time since the drop onset as well,
``function(xi, params, rig, t)`` with t in s (the step's time in the filter's scan and in each
RK4 stage, `dynamics.at_time`): a term that starts at the drop, such as the AMB's force as it
lets go (`amb_release`). A force through the contact may read the model's own normal contact forces
(`Effect.normal`): the contact angle's axial push is tan(beta) times the bore's normal force, whatever the
contact law, so tan(beta) is the one parameter and means the same on every rig.

`Effects` is the JAX container held by `Model.effects`: the functions (and names) are
static aux data, the parameter values are traced children, so jit/grad/vmap see the
parameters and a change of which effects are active recompiles. With no effects
(the default) phi and h are the paper's model unchanged, at the same cost.

Library (`LIBRARY`): force effects axial_load, radial_load, magnetic_stiffness,
cross_coupled_stiffness, contact_exponent, viscous_friction, contact_angle_coupling; measurement
effects sensor_gain_x/y/z (gain, 1) and sensor_offset_x/y/z (offset, m): the sensor reads
gain * position + offset on that axis; the speed effect brake_decay (a braked rotor). Beside it,
`RIG_TERMS`, which the user switches on and the workbench does not search for: the clocked force
amb_release (the AMB's force decaying after the drop, its PD law the rig's `amb_*`; until it lets go it
carries the weight and the other force effects' static part, `Effect.holds`).

A user-written effect is registered by dotted path ``"package.module:function"``;
the function carries its parameters as an attribute ``parameters`` (name ->
(default, unit, description)), optionally ``bounds`` (name -> (low, high)) and ``starts`` (name -> further
values its fit starts from), for a
measurement effect ``kind = "measurement"`` and for a clocked one ``clocked = True`` (it takes the time
since the onset as a fourth argument; an AMB's force that also carries the other force effects' static part
until it lets go ``holds = True`` as well, with that force (N) as a fifth; a force through the contact
``contact = True``, and if it reads the model's normal contact forces (F_nR, F_zZ) there ``normal = True``, with
them (N) as a fourth), or is made by the `effect` decorator below.
"""
from __future__ import annotations

import dataclasses
import importlib
import math
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
from jax import Array

# state indices as in core.types (not imported: types imports this module)
X, Y, Z, THETA, XDOT, YDOT, ZDOT = range(7)

EffectFunction = Callable[[Array, Mapping[str, Array], object], Array]
ENTRY_POINT_GROUP = "touchdown_ros.effects"
FORCE, MEASUREMENT, SPEED = "force", "measurement", "speed"
KINDS = (FORCE, MEASUREMENT, SPEED)
HOLD_ANGLES = 4  # unbalance angles the static part of a force is averaged over (`Effects.static_force`)


@dataclass(frozen=True)
class Effect:
    """A named term with named physical parameters (name -> (default, unit, description)): a force
    on the rotor (N), a change of the sensor output (m) or the rotor's speed and unbalance angle
    (rad/s, rad), by `kind`; `bounds` (name -> (low, high), in the parameter's unit) keeps a fitted
    parameter where it means something (a drag is never negative); `starts` (name -> values, in its unit) are
    further values its fit starts from, the lowest loss kept, where the loss has more than one minimum in it (a
    braked rotor's rate: its unbalance's phase lags by radians)."""

    name: str
    function: EffectFunction
    parameters: Mapping[str, tuple[float, str, str]]
    description: str = ""
    source: str = ""  # how to find it again: a library name, "module:function" or an entry point name
    when: str = ""  # the bag condition that switches it on (condition.<when> true); "" acts always
    kind: str = FORCE  # one of KINDS
    bounds: Mapping[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    contact: bool = False  # a force through the bearing's contact (a contact angle): part of the contact force
    clocked: bool = False  # a function of the time since the drop onset too: function(xi, params, rig, t)
    # an AMB's force: until it lets go it also carries the other force effects' static part, as its integral action
    # did in levitation: function(xi, params, rig, t, held), held (3,) N (`Effects.static_force`); clocked
    holds: bool = False
    starts: Mapping[str, tuple[float, ...]] = dataclasses.field(default_factory=dict)
    # a force through the contact that reads the model's own normal contact forces there: function(xi, params, rig,
    # normal), normal (2,) N: (F_nR, F_zZ), the bore's and the face's (a contact angle: tan(beta) F_nR)
    normal: bool = False

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"effect {self.name!r}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.holds and not (self.kind == FORCE and self.clocked and not self.contact):
            raise ValueError(f"effect {self.name!r}: only a clocked force off the contact (an AMB's) holds loads")
        if self.contact and self.kind != FORCE:
            raise ValueError(f"effect {self.name!r}: only a force acts through the contact, not a {self.kind} effect")
        if self.contact and self.clocked:
            raise ValueError(f"effect {self.name!r}: a force through the contact cannot be clocked")
        if self.normal and not self.contact:
            raise ValueError(f"effect {self.name!r}: only a force through the contact reads its normal forces")
        for key, (low, high) in self.bounds.items():
            if key not in self.parameters or not low < high:
                raise ValueError(f"effect {self.name!r}: bounds {key}: ({low}, {high}) name no parameter or are empty")
            if not low <= self.parameters[key][0] <= high:
                raise ValueError(f"effect {self.name!r}: the default of {key} lies outside its bounds ({low}, {high})")
        for key, values in self.starts.items():
            low, high = self.bounds.get(key, (-math.inf, math.inf))
            if key not in self.parameters or not all(low <= v <= high for v in values):
                raise ValueError(f"effect {self.name!r}: starts {key}: {values} name no parameter or leave its bounds")

    def defaults(self) -> dict[str, float]:
        return {k: float(v[0]) for k, v in self.parameters.items()}

    def __call__(
        self, xi: Array, params: Mapping[str, Array], rig, t: Array | float = 0.0, held: Array | None = None,
        normal: Array | None = None,
    ) -> Array:
        """The effect at state xi and time t (s since the drop onset; only a clocked effect reads it); `held`
        (3,) N: the static force an effect that `holds` carries beside the weight (none if not given); `normal`
        (2,) N: the model's normal contact forces (F_nR, F_zZ) at xi, what an effect that reads them needs."""
        if self.normal:
            if normal is None:
                raise ValueError(f"effect {self.name!r} reads the model's normal contact forces: none were given")
            return self.function(xi, params, rig, normal)
        if self.holds:
            return self.function(xi, params, rig, t, jnp.zeros(3, xi.dtype) if held is None else held)
        return self.function(xi, params, rig, t) if self.clocked else self.function(xi, params, rig)


def effect(
    name: str,
    parameters: Mapping[str, tuple[float, str, str]],
    description: str = "",
    kind: str = FORCE,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    contact: bool = False,
    clocked: bool = False,
    holds: bool = False,
    starts: Mapping[str, tuple[float, ...]] | None = None,
    normal: bool = False,
):
    """Decorator making a plain function into an `Effect` of `kind` (usable by dotted path); `starts`: further
    values a parameter's fit starts from (`Effect.starts`); `contact`: a
    force through the bearing's contact, published as part of the contact force; `clocked`: the function
    takes the time since the drop onset (s) as a fourth argument; `holds`: an AMB's clocked force that also
    carries the other force effects' static part (a fifth argument, `Effect.holds`); `normal`: a force through the
    contact that takes the model's normal contact forces (F_nR, F_zZ), N, as a fourth argument."""

    def wrap(function: EffectFunction) -> Effect:
        text = description or (function.__doc__ or "")
        return Effect(
            name, function, dict(parameters), text, kind=kind, bounds=dict(bounds or {}), contact=contact,
            clocked=clocked, holds=holds, starts=dict(starts or {}), normal=normal,
        )

    return wrap


@jax.tree_util.register_pytree_node_class
class Effects:
    """Active effects: static (names, functions); traced parameters (tuple of dicts), gates
    (one factor per effect: 1 acts, 0 switched off, e.g. in a bag recorded without the loader) and
    the time since the drop onset (s) at which clocked effects act."""

    def __init__(
        self,
        effects: tuple[Effect, ...] = (),
        params: tuple[Mapping[str, Array], ...] | None = None,
        gates: tuple | None = None,
        time: Array | float = 0.0,
    ):
        self.effects = tuple(effects)
        if params is None:
            params = tuple(e.defaults() for e in self.effects)
        self.params = tuple(dict(p) for p in params)
        self.gates = tuple(gates) if gates is not None else (1.0,) * len(self.effects)
        self.time = time

    # pytree protocol: the functions are aux data (hashable by identity), the values children; the time only
    # where a clocked effect reads it (without, the tree is what it was before there were clocked effects)
    def tree_flatten(self):
        if self.clocked:
            return (self.params, self.gates, self.time), self.effects
        return (self.params, self.gates), self.effects

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.effects = aux
        obj.params, obj.gates = tuple(children[0]), tuple(children[1])
        obj.time = children[2] if len(children) > 2 else 0.0
        return obj

    def __len__(self) -> int:
        return len(self.effects)

    def __bool__(self) -> bool:
        return bool(self.effects)

    def __repr__(self) -> str:
        return f"Effects({', '.join(e.name for e in self.effects)})"

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    def values(self) -> dict[str, dict[str, float]]:
        """{effect name: {parameter: value}} as plain floats (for coefficient files and reports)."""
        return {e.name: {k: float(v) for k, v in p.items()} for e, p in zip(self.effects, self.params)}

    def with_values(self, values: Mapping[str, Mapping[str, float]]) -> "Effects":
        params = tuple({k: values.get(e.name, {}).get(k, p[k]) for k in p} for e, p in zip(self.effects, self.params))
        return Effects(self.effects, params, self.gates, self.time)

    def with_params(self, params: tuple[Mapping[str, Array], ...]) -> "Effects":
        return Effects(self.effects, params, self.gates, self.time)

    def with_gates(self, gates) -> "Effects":
        """The same effects switched on (1) or off (0) each; gates may be a traced (n,) array."""
        return Effects(self.effects, self.params, tuple(gates[i] for i in range(len(self.effects))), self.time)

    def at_time(self, t: Array | float) -> "Effects":
        """The same effects at t s after the drop onset (what clocked effects read)."""
        return Effects(self.effects, self.params, self.gates, t)

    @property
    def clocked(self) -> bool:
        """Whether a clocked effect is among them (static: without, the time is never read)."""
        return any(e.clocked for e in self.effects)

    def acts_on(self, kind: str) -> bool:
        """Whether an effect of `kind` is among them (static: decides what is traced)."""
        return any(e.kind == kind for e in self.effects)

    def _sum(
        self, kind: str, xi: Array, rig, contact: bool | None = None, holding: bool | None = None,
        normal: Array | None = None,
    ) -> Array:
        """`contact`, `holding`: only the effects with that `Effect.contact`, `Effect.holds` (None: any); `normal`:
        the model's normal contact forces at xi (`Effect.normal`)."""
        total = jnp.zeros(3, dtype=xi.dtype)
        for e, p, gate in zip(self.effects, self.params, self.gates):
            if e.kind == kind and contact in (None, e.contact) and holding in (None, e.holds):
                held = self.static_force(xi, rig) if e.holds else None
                total = total + gate * jnp.asarray(e(xi, p, rig, self.time, held, normal), dtype=xi.dtype)
        return total

    def static_force(self, xi: Array, rig) -> Array:
        """(3,) N: the force effects' static part, off the contact, but for those that hold: their mean at the
        bearing's centre at rest over HOLD_ANGLES equally spaced unbalance angles (a once- or twice-per-revolution
        force averages out). What an AMB's integral action carried in levitation (`Effect.holds`)."""
        rest = jnp.zeros(xi.shape, xi.dtype)  # built anew, not from xi: no derivative along xi to carry
        angles = (2.0 * math.pi * k / HOLD_ANGLES for k in range(HOLD_ANGLES))
        at_rest = (rest.at[THETA].set(angle) for angle in angles)
        return sum(self._sum(FORCE, state, rig, contact=False, holding=False) for state in at_rest) / HOLD_ANGLES

    def force(self, xi: Array, rig, contact: bool | None = None, normal: Array | None = None) -> Array:
        """Sum of the active force effects (3,), N, each times its gate; `contact` True: only those through
        the bearing's contact (`Effect.contact`), False: only the others; `normal` (2,) N: the model's normal
        contact forces (F_nR, F_zZ) at xi, for the effects that read them (`Effect.normal`)."""
        return self._sum(FORCE, xi, rig, contact, normal=normal)

    def act_through_contact(self) -> bool:
        """Whether a force through the bearing's contact is among them (static: decides what is traced)."""
        return any(e.contact for e in self.effects)

    def measurement(self, xi: Array, rig) -> Array:
        """Sum of the active measurement effects' changes of the sensor output (3,), m, each times its gate."""
        return self._sum(MEASUREMENT, xi, rig)

    def speed(self, xi: Array, rig) -> tuple[Array, Array]:
        """(omega, angle): the rotor's speed (rad/s) and its unbalance's angle (rad) at xi, the rig's
        constant speed and theta moved by each active speed effect times its gate."""
        omega, angle = jnp.asarray(rig.speed, xi.dtype), xi[THETA]
        for e, p, gate in zip(self.effects, self.params, self.gates):
            if e.kind == SPEED:
                moved = jnp.asarray(e(xi, p, rig, self.time), dtype=xi.dtype)
                omega = omega + gate * (moved[0] - rig.speed)
                angle = angle + gate * (moved[1] - xi[THETA])
        return omega, angle


def gates_for(effects: Effects, conditions: Mapping[str, str]) -> tuple[float, ...]:
    """1.0 for an effect that acts in a bag with these conditions, else 0.0: an effect with a
    `when` acts where that condition is "true", "yes", "on" or "1"; one without always acts."""
    on = {name for name, value in conditions.items() if str(value).strip().lower() in ("true", "yes", "on", "1")}
    return tuple(1.0 if not e.when or e.when in on else 0.0 for e in effects.effects)


# ---------------------------------------------------------------- library

def _axial_load(xi, p, rig):
    """Constant downward axial load (e.g. a test-rig load cell), N."""
    return jnp.stack([0.0 * xi[Z], 0.0 * xi[Z], -p["force"] + 0.0 * xi[Z]])


def _radial_load(xi, p, rig):
    """Constant radial load in the sensor frame, N."""
    zero = 0.0 * xi[Z]
    return jnp.stack([p["force_x"] + zero, p["force_y"] + zero, zero])


def _magnetic_stiffness(xi, p, rig):
    """Residual AMB / permanent-magnet negative stiffness: force k_m * displacement outward (x, y, z)."""
    return jnp.stack([p["k_radial"] * xi[X], p["k_radial"] * xi[Y], p["k_axial"] * xi[Z]])


def _cross_coupled_stiffness(xi, p, rig):
    """Seal / fluid cross-coupled stiffness: force q (-y, x), tangential, driving forward whirl for q > 0."""
    return jnp.stack([-p["q"] * xi[Y], p["q"] * xi[X], 0.0 * xi[Z]])


def _contact_exponent(xi, p, rig):
    """Hertz-like correction of the axial contact: + K d^n (d axial deformation) in contact."""
    d = -(xi[Z] + rig.axial_clearance)
    dd = jnp.where(d > 0.0, d, 0.0)
    safe = jnp.where(d > 0.0, dd / 1e-5, 1.0)
    f = jnp.where(d > 0.0, p["K"] * safe ** p["n"], 0.0)  # K in N at 10 um deformation
    zero = 0.0 * xi[Z]
    return jnp.stack([zero, zero, f])


def _viscous_friction(xi, p, rig):
    """Velocity-dependent (viscous / windage) drag on the rotor centre, N s/m."""
    return jnp.stack([-p["c_radial"] * xi[XDOT], -p["c_radial"] * xi[YDOT], -p["c_axial"] * xi[ZDOT]])


def _contact_angle_coupling(xi, p, rig, normal):
    """Axial force from radial contact through the contact angle: F_z = tan(beta) F_nR, the model's own
    normal force in the bore (N)."""
    zero = 0.0 * xi[Z]
    return jnp.stack([zero, zero, p["tan_beta"] * normal[0]])


def _brake_decay(xi, p, rig):
    """A braked rotor: speed omega_t = omega (1 - rate t) from the drop onset, t = theta / omega.

    Its unbalance turns at that speed, m e omega_t^2 (cos, sin) phi, the angle phi = theta - rate
    omega t^2 / 2 lagging the model's (by 4.5 rad after 0.15 s at 0.77 1/s and 5000 rpm), and a ring
    spinning with the rotor slips against it at omega_t.
    """
    t = xi[THETA] / rig.speed
    w = rig.speed * jnp.maximum(1.0 - p["rate"] * t, 0.0)
    return jnp.stack([w, xi[THETA] - 0.5 * p["rate"] * rig.speed * t * t])


def _amb_release(xi, p, rig, t, held):
    """The AMB's force as it lets go after the drop: its PD law about the bearing's centre (the rig's
    amb_stiffness, N/m, and amb_damping, N s/m), its cancelling of the unbalance force (the rig's
    amb_unbalance_compensation of m e omega^2 along theta) and its support of the weight (m g) and of the
    other force effects' static part `held` (N: a loader's thrust, a side load; what its integral action
    carried in levitation), all times share exp(-max(t - release, 0) / decay_time), t the time since the drop
    onset (s): held until the release, which lies after the onset where the record starts in levitation
    (`drop_detection.lead`)."""
    gain = p["share"] * jnp.exp(-jnp.maximum(t - p["release"], 0.0) / p["decay_time"])
    k, c = rig.amb_stiffness, rig.amb_damping
    compensation = rig.amb_unbalance_compensation * rig.mass * rig.eccentricity * rig.speed**2
    return gain * jnp.stack([
        -k * xi[X] - c * xi[XDOT] - compensation * jnp.cos(xi[THETA]) - held[0],
        -k * xi[Y] - c * xi[YDOT] - compensation * jnp.sin(xi[THETA]) - held[1],
        -k * xi[Z] - c * xi[ZDOT] + rig.mass * rig.gravity - held[2],
    ])


def _sensor_error(axis: int, parameter: str, change: Callable[[Array, Array], Array]) -> EffectFunction:
    def function(xi, p, rig):
        return jnp.zeros(3, xi.dtype).at[axis].set(change(p[parameter], xi[axis]))

    return function


#: Sensor errors per axis a, each a measurement effect sensor_<parameter>_<a>: parameter ->
#: (default, unit, description, change of the output (value, displacement along a) -> m).
_SENSOR_ERRORS = {
    "gain": (1.0, "1", "scale error of the {a} sensor: it reads gain * {a}", lambda gain, d: (gain - 1.0) * d),
    "offset": (0.0, "m", "zero error of the {a} sensor: it reads {a} + offset", lambda offset, d: offset + 0.0 * d),
}


LIBRARY: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "axial_load", _axial_load, {"force": (1000.0, "N", "constant downward axial load")}, _axial_load.__doc__
        ),
        Effect(
            "radial_load",
            _radial_load,
            {"force_x": (100.0, "N", "radial load along x"), "force_y": (100.0, "N", "radial load along y")},
            _radial_load.__doc__,
        ),
        Effect(
            "magnetic_stiffness",
            _magnetic_stiffness,
            {
                "k_radial": (1.0e5, "N/m", "radial negative stiffness"),
                "k_axial": (1.0e5, "N/m", "axial negative stiffness"),
            },
            _magnetic_stiffness.__doc__,
        ),
        Effect(
            "cross_coupled_stiffness",
            _cross_coupled_stiffness,
            {"q": (1.0e5, "N/m", "cross-coupled stiffness (tangential force per radial displacement)")},
            _cross_coupled_stiffness.__doc__,
        ),
        Effect(
            "contact_exponent",
            _contact_exponent,
            {"K": (100.0, "N", "force at 10 um axial deformation"), "n": (1.5, "1", "contact exponent")},
            _contact_exponent.__doc__,
            contact=True,
        ),
        Effect(
            "viscous_friction",
            _viscous_friction,
            {"c_radial": (10.0, "N s/m", "radial drag"), "c_axial": (10.0, "N s/m", "axial drag")},
            _viscous_friction.__doc__,
            bounds={"c_radial": (0.0, math.inf), "c_axial": (0.0, math.inf)},
        ),
        Effect(
            "contact_angle_coupling",
            _contact_angle_coupling,
            {"tan_beta": (0.1, "1", "tangent of the contact angle")},
            _contact_angle_coupling.__doc__,
            contact=True,
            normal=True,
        ),
        Effect(
            "brake_decay", _brake_decay, {"rate": (0.1, "1/s", "relative speed decay per second")},
            _brake_decay.__doc__, kind=SPEED,
            # from 0.1 or 0.3 a fit to drawn_1_1's braked drops (0.766 1/s) ended at -0.06 with the loss of no
            # brake; from 1 or 3 at 0.783, 0.094 per sample lower (2026-12-07)
            starts={"rate": (1.0, 3.0)},
        ),
        *(
            Effect(
                f"sensor_{parameter}_{a}",
                _sensor_error(axis, parameter, change),
                {parameter: (default, unit, text.format(a=a))},
                text.format(a=a).capitalize() + ".",
                kind=MEASUREMENT,
            )
            for parameter, (default, unit, text, change) in _SENSOR_ERRORS.items()
            for axis, a in enumerate("xyz")
        ),
    )
}


#: Terms a user switches on from what they know of the rig (`effects.active`), which the workbench does not
#: search for: the AMB letting go after the drop (its PD law the rig's `amb_*`).
RIG_TERMS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "amb_release",
            _amb_release,
            {
                "share": (1.0, "1", "share of the AMB's force acting at the drop onset and until the release"),
                "decay_time": (1.0e-3, "s", "time constant of the AMB's force after the drop"),
                "release": (0.0, "s", "when the AMB starts to let go, after the onset (starts at drop_detection.lead)"),
            },
            _amb_release.__doc__,
            bounds={"share": (0.0, 2.0), "decay_time": (1.0e-6, 1.0), "release": (0.0, 0.1)},
            clocked=True,
            holds=True,
        ),
    )
}


def resolve(spec: str, name: str | None = None, when: str = "") -> Effect:
    """A library effect by name, a user effect by dotted path "module:attr", or an entry point
    of group `touchdown_ros.effects`; `name` renames it (the key of its parameters), `when`
    makes it act only in bags recorded with that condition on."""
    found = _lookup(spec)
    return dataclasses.replace(found, name=name or found.name, source=spec, when=when)


def _lookup(spec: str) -> Effect:
    known = {**LIBRARY, **RIG_TERMS}
    if spec in known:
        return known[spec]
    if ":" in spec:
        module, _, attr = spec.partition(":")
        try:
            obj = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as error:
            raise ValueError(f"effect {spec!r} cannot be imported: {error}") from None
        if isinstance(obj, Effect):
            return obj
        if callable(obj):
            parameters = getattr(obj, "parameters", None)
            if not parameters:
                raise ValueError(
                    f"effect {spec!r}: the function needs a 'parameters' attribute (name -> (default, unit, text))"
                )
            return Effect(
                attr, obj, dict(parameters), obj.__doc__ or "", kind=getattr(obj, "kind", FORCE),
                bounds=dict(getattr(obj, "bounds", {})), contact=bool(getattr(obj, "contact", False)),
                clocked=bool(getattr(obj, "clocked", False)), holds=bool(getattr(obj, "holds", False)),
                starts=dict(getattr(obj, "starts", {})), normal=bool(getattr(obj, "normal", False)),
            )
        raise ValueError(f"effect {spec!r} is neither an Effect nor a function")
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == spec:
            return _lookup(ep.value)
    raise ValueError(
        f"unknown effect {spec!r}: use one of {', '.join(sorted(known))}, 'module:function' "
        f"or an entry point of group {ENTRY_POINT_GROUP}"
    )


def regressors(
    effect_: Effect, xi: Array, rig, values: Mapping[str, float] | None = None, t: Array | float = 0.0,
    normal: Array | None = None,
) -> Array:
    """d function / d parameters at xi (and t s after the onset; `normal`, the model's normal contact forces there,
    for an effect that reads them): (3, n_params), N (force) or m (measurement) per parameter unit; (2, n_params)
    for a speed effect (rad/s and rad per parameter unit)."""
    p0 = {k: jnp.asarray(v, dtype=xi.dtype) for k, v in (values or effect_.defaults()).items()}
    jac = jax.jacfwd(lambda p: effect_(xi, p, rig, t, None, normal))(p0)
    return jnp.stack([jac[k] for k in p0], axis=-1)
