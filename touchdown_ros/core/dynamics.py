"""The paper's touchdown model: contact forces (eq. 5-8), phi (eq. 12), the RK4 step f (eq. 15)
and the measurement h (eq. 15f: the sensor reads x, y, z, plus any measurement effects).

One deliberate sign choice: eq. 6c prints F_zR = mu sign(zdot) F_nR, which with
eq. 4c (zddot = F_z / m - g) would push the rotor along its axial velocity. Friction
opposes sliding, so here F_zR = -mu sign(zdot) F_nR.
"""
from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from touchdown_ros.core.effects import FORCE, MEASUREMENT, SPEED
from touchdown_ros.core.pkbkr import axial_parameters, radial_parameters
from touchdown_ros.core.types import (
    OMEGA_RING, OUTPUT_SIZE, STATE_SIZE, THETA, X, XDOT, YDOT, Z, ZDOT, ContactForces, ContactLaw, Model, Rig,
)


def polar(x: Array, y: Array) -> tuple[Array, Array, Array]:
    """r, cos(alpha), sin(alpha) with alpha = atan2(y, x) (eq. 4e); alpha = 0 at r = 0.

    The double `where` keeps gradients finite at the centre, where sqrt is not differentiable.
    """
    r2 = x * x + y * y
    at_centre = r2 == 0.0
    r = jnp.sqrt(jnp.where(at_centre, 1.0, r2))
    cos_a = jnp.where(at_centre, 1.0, x / r)
    sin_a = jnp.where(at_centre, 0.0, y / r)
    return jnp.where(at_centre, 0.0, r), cos_a, sin_a


def normal_force(law: ContactLaw, k: Array, c: Array, deformation: Array, rate: Array) -> Array:
    """Normal contact force (N) at deformation d > 0 (m) and its rate (m/s): k d^n + c d^m d_dot
    (linear, eq. 6a / 8c: n = 1, m = 0; hertz: n = m; kelvin_voigt: m = 0; both floored at 0); 0 out of
    contact."""
    in_contact = deformation > 0.0
    d = jnp.where(in_contact, deformation, 1.0)
    force = k * d**law.stiffness_exponent + c * d**law.damping_exponent * rate
    force = jnp.where(law.floored > 0.0, jnp.maximum(force, 0.0), force)
    return jnp.where(in_contact, force, 0.0)


def yielding_support(law: ContactLaw, force: Array) -> Array:
    """Face force (N) passed by the axial support: as it is up to the preload P; above it the
    preloaded disc springs yield and pass P + S x / (S + x), x = F - P, creeping towards P + S
    (degressive, with a continuous slope at the knee). Exactly F when rigid (P = inf)."""
    excess = jnp.maximum(force - law.support_preload, 0.0)
    return force - excess**2 / (law.support_span + excess)


def stribeck_factor(law: ContactLaw, slip_squared: Array) -> Array:
    """The friction coefficient over mu at a slip speed s (m/s, given as s^2): 1 + drop exp(-(s / v_s)^2),
    the law's Stribeck drop and velocity; exactly 1 without a drop."""
    return 1.0 + law.friction_drop * jnp.exp(-slip_squared / law.stribeck_velocity**2)


def friction(
    law: ContactLaw, speed: Array, mu: Array, k_ZR: Array, F_nR: Array, F_zZ: Array,
    r: Array, rdot: Array, whirl: Array, zdot: Array,
) -> tuple[Array, Array, Array]:
    """F_n, F_t, F_z (N) from the normal forces F_nR (bore) and F_zZ (face) and the friction.

    The paper's (the inner ring at rest): F_t = mu F_nR + k_ZR F_zZ (eq. 6b, 8b), F_zR = -mu
    sign(zdot) F_nR (eq. 6c). Against a ring spinning with the rotor (its speed omega, rad/s), the rotor
    slides on it at u = centre velocity - omega x centre position: tangentially at
    s_t = whirl - omega r, radially at rdot, axially at zdot. Coulomb friction opposes that slip
    with mu F_nR in the bore (on (s_t, zdot)) and k_ZR F_zZ on the face (on (s_t, rdot)),
    regularised below the law's slip velocity, each coefficient times the law's Stribeck factor at its slip
    (`stribeck_factor`). It drives the rotor towards forward synchronous whirl.
    A ring whose speed is a state: `ring_friction`.
    """
    if law.friction == "paper":  # static: the law's friction model is pytree aux data
        return F_nR, mu * F_nR + k_ZR * F_zZ, F_zZ - mu * jnp.sign(zdot) * F_nR
    if law.spins_ring:
        raise ValueError("friction against a spinning ring needs its speed: use ring_friction")
    v = law.slip_velocity
    slip_t = whirl - speed * r
    bore_slip, face_slip = slip_t**2 + zdot**2, slip_t**2 + rdot**2
    bore = mu * stribeck_factor(law, bore_slip) * F_nR / jnp.sqrt(bore_slip + v**2)
    face = k_ZR * stribeck_factor(law, face_slip) * F_zZ / jnp.sqrt(face_slip + v**2)
    return F_nR + face * rdot, (bore + face) * slip_t, F_zZ - bore * zdot


def ring_friction(
    law: ContactLaw, rig: Rig, speed: Array, ring_speed: Array, mu: Array, k_ZR: Array, F_nR: Array, F_zZ: Array,
    r: Array, rdot: Array, whirl: Array, zdot: Array,
) -> tuple[Array, Array, Array, Array]:
    """F_n, F_t, F_z (N) on the rotor and the friction torque (N m) on an inner ring turning at
    ring_speed (rad/s), Coulomb friction regularised below the law's slip velocity.

    Bore (journal radius R): the rotor's surface slides on the ring's tangentially at
    s_t = whirl + R omega - (R + r) omega_ring and axially at zdot; mu F_nR opposes (s_t, zdot).
    Face (mean radius R_a): the rotor spins against the ring at (omega - omega_ring) R_a and its
    centre moves at (whirl - omega r, rdot); k_ZR F_zZ opposes that slip (the spin counted twice
    for the annulus' mean torque arm). Both torques turn the ring towards the rotor's speed. Each
    coefficient is times the law's Stribeck factor at its slip speed (`stribeck_factor`).
    """
    v = law.slip_velocity
    slip_t = whirl + rig.journal_radius * speed - (rig.journal_radius + r) * ring_speed
    bore_slip = slip_t**2 + zdot**2
    bore = mu * stribeck_factor(law, bore_slip) * F_nR / jnp.sqrt(bore_slip + v**2)
    lateral_t = whirl - speed * r
    spin = (speed - ring_speed) * rig.face_radius
    lateral = lateral_t**2 + rdot**2
    face = k_ZR * stribeck_factor(law, lateral + spin**2) * F_zZ / jnp.sqrt(lateral + 4.0 * spin**2 + v**2)
    torque = (rig.journal_radius + r) * bore * slip_t + face * 2.0 * spin * rig.face_radius
    return F_nR + face * rdot, bore * slip_t + face * lateral_t, F_zZ - bore * zdot, torque


class _ContactState(NamedTuple):
    """What the friction models need at one state: geometry, normal forces and friction coefficients."""

    speed: Array  # rotor, rad/s
    mu: Array
    k_ZR: Array
    F_nR: Array  # N, bore normal force
    F_zZ: Array  # N, face normal force (through the support)
    r: Array  # m
    rdot: Array  # m/s
    whirl: Array  # m/s
    zdot: Array  # m/s
    cos_a: Array
    sin_a: Array
    radial_deformation: Array  # m
    axial_deformation: Array  # m

    @property
    def sliding(self) -> tuple[Array, ...]:
        """The friction models' arguments after the speeds: mu, k_ZR, F_nR, F_zZ, r, rdot, whirl, zdot."""
        return self.mu, self.k_ZR, self.F_nR, self.F_zZ, self.r, self.rdot, self.whirl, self.zdot


def _contact_state(model: Model, xi: Array) -> _ContactState:
    if xi.shape[-1] != model.law.state_size:  # static: JAX would read a missing ring speed as another entry
        raise ValueError(
            f"a state of {xi.shape[-1]} entries for contact.friction {model.law.friction}, "
            f"whose state has {model.law.state_size}"
        )
    rig = model.rig
    x, y, z, _, xdot, ydot, zdot = xi[:STATE_SIZE]
    r, cos_a, sin_a = polar(x, y)
    rdot = cos_a * xdot + sin_a * ydot  # eq. 13e

    radial_deformation = r - rig.radial_clearance
    axial_deformation = -(z + rig.axial_clearance)

    k_R, c_R, mu = radial_parameters(model.kernel, model.nominal, model.coeffs, radial_deformation, rdot)
    k_Z, c_Z, k_ZR = axial_parameters(model.kernel, model.nominal, model.coeffs, axial_deformation, zdot)

    F_nR = normal_force(model.law, k_R, c_R, radial_deformation, rdot)  # eq. 6a
    F_zZ = normal_force(model.law, k_Z, c_Z, axial_deformation, -zdot)  # eq. 8c: -k_Z (z + z0) - c_Z zdot
    F_zZ = yielding_support(model.law, F_zZ)
    whirl = cos_a * ydot - sin_a * xdot  # m/s, centre velocity along the anticlockwise tangent
    speed = rotor_speed(model, xi)[0]
    return _ContactState(
        speed, mu, k_ZR, F_nR, F_zZ, r, rdot, whirl, zdot, cos_a, sin_a, radial_deformation, axial_deformation
    )


def _ring_torque(model: Model, c: _ContactState, ring_speed: Array) -> Array:
    return ring_friction(model.law, model.rig, c.speed, ring_speed, *c.sliding)[3]


def contact_forces(model: Model, xi: Array) -> ContactForces:
    """F_n, F_t, F_z on the rotor at state xi (eq. 5-8), with the PKBKR parameters of eq. 9."""
    c = _contact_state(model, xi)
    if model.law.spins_ring:
        F_n, F_t, F_z, torque = ring_friction(model.law, model.rig, c.speed, xi[OMEGA_RING], *c.sliding)
    else:
        F_n, F_t, F_z = friction(model.law, c.speed, *c.sliding)
        torque = jnp.zeros((), xi.dtype)
    effects = getattr(model, "effects", None)
    if effects and effects.act_through_contact():  # static: a force through the contact (a contact angle)
        extra = effects.force(xi, model.rig, contact=True, normal=jnp.stack([c.F_nR, c.F_zZ]))
        F_n = F_n - (extra[0] * c.cos_a + extra[1] * c.sin_a)
        F_t = F_t + extra[0] * c.sin_a - extra[1] * c.cos_a
        F_z = F_z + extra[2]
    return ContactForces(
        F_n=F_n,
        F_t=F_t,
        F_z=F_z,
        F_x=-F_n * c.cos_a + F_t * c.sin_a,
        F_y=-F_n * c.sin_a - F_t * c.cos_a,
        radial_contact=c.radial_deformation > 0.0,  # eq. 5 criterion r <= r0 is "no contact"
        axial_contact=c.axial_deformation > 0.0,  # eq. 7 criterion z >= -z0 is "no contact"
        ring_torque=torque,
    )


def normal_forces(model: Model, xi: Array) -> Array:
    """(F_nR, F_zZ), N: the model's normal contact forces at xi in the bore and on the face (eq. 6a, 8c; what a
    force through the contact may read, `Effect.normal`)."""
    c = _contact_state(model, xi)
    return jnp.stack([c.F_nR, c.F_zZ])


def contact_force_xyz(forces: ContactForces) -> Array:
    """(F_x, F_y, F_z) of `forces`: the contact force on the rotor in sensor axes, N."""
    return jnp.stack([forces.F_x, forces.F_y, forces.F_z])


def contact_forces_and_jacobian(model: Model, xi: Array) -> tuple[ContactForces, Array]:
    """`contact_forces(model, xi)` and d (F_x, F_y, F_z) / d xi (3, n), N per state unit.

    Reverse mode, as `phi_and_jacobian`: one forward pass (the forces) and three pullbacks, one
    per force component. Equal to `jax.jacfwd` of the stacked components to round-off, and
    cheaper in the live node's chunk, to which jacfwd (seven tangents) added three to four
    times as much per row (docs/node.md). Out of contact the forces are constant zero: the
    Jacobian is exactly zero.
    """

    def forces_xyz(state: Array) -> tuple[Array, ContactForces]:
        forces = contact_forces(model, state)
        return contact_force_xyz(forces), forces

    _, pullback, forces = jax.vjp(forces_xyz, xi, has_aux=True)
    (jacobian,) = jax.vmap(pullback)(jnp.eye(3, dtype=xi.dtype))
    return forces, jacobian


def clocked(model: Model) -> bool:
    """Whether the model has clocked effects (static: without, the time is not traced at all)."""
    effects = getattr(model, "effects", None)
    return bool(effects) and effects.clocked


def at_time(model: Model, t: Array | float) -> Model:
    """The model t s after the drop onset: what its clocked effects read (`Effect.clocked`); the model
    itself when it has none."""
    return model._replace(effects=model.effects.at_time(t)) if clocked(model) else model


def later(model: Model, dt: Array | float) -> Model:
    """`at_time` dt s after the model's own time (an RK4 stage within a step)."""
    return at_time(model, model.effects.time + dt) if clocked(model) else model


def rotor_speed(model: Model, xi: Array) -> tuple[Array, Array]:
    """The rotor's speed (rad/s) and its unbalance's angle (rad) at xi: the rig's constant speed and
    theta (eq. 12), unless speed effects move them (static: without, the paper's model unchanged)."""
    effects = getattr(model, "effects", None)
    if effects and effects.acts_on(SPEED):
        return effects.speed(xi, model.rig)
    return jnp.asarray(model.rig.speed, dtype=xi.dtype), xi[THETA]


def unbalance_change(model: Model, xi: Array) -> Array:
    """(3,) N: how much the speed effects move the unbalance force m e omega^2 (cos, sin) angle from the
    constant speed's at xi (zero without speed effects)."""
    rig = model.rig
    omega, angle = rotor_speed(model, xi)
    me = rig.mass * rig.eccentricity
    return jnp.stack([
        me * (omega**2 * jnp.cos(angle) - rig.speed**2 * jnp.cos(xi[THETA])),
        me * (omega**2 * jnp.sin(angle) - rig.speed**2 * jnp.sin(xi[THETA])),
        jnp.zeros((), xi.dtype),
    ])


def phi(model: Model, xi: Array) -> Array:
    """State derivative d xi / dt of eq. 12, xi = [x y z theta xdot ydot zdot]; the unbalance turns at
    `rotor_speed` (the rig's constant speed unless a speed effect moves it). With a spinning ring
    (xi[7] its speed) the ring's angular acceleration, friction torque over its inertia, follows."""
    rig = model.rig
    forces = contact_forces(model, xi)
    speed, angle = rotor_speed(model, xi)
    unbalance = rig.eccentricity * speed**2
    F_x, F_y, F_z = forces.F_x, forces.F_y, forces.F_z
    effects = getattr(model, "effects", None)
    if effects and effects.acts_on(FORCE):  # static: no force effects -> the paper's phi, unchanged
        extra = effects.force(xi, rig, contact=False)  # those through the contact are in `forces`
        F_x, F_y, F_z = F_x + extra[0], F_y + extra[1], F_z + extra[2]
    return jnp.stack(
        [
            xi[XDOT],
            xi[YDOT],
            xi[ZDOT],
            jnp.asarray(rig.speed, dtype=xi.dtype),
            F_x / rig.mass + unbalance * jnp.cos(angle),
            F_y / rig.mass + unbalance * jnp.sin(angle),
            F_z / rig.mass - rig.gravity,
        ]
        + ([forces.ring_torque / rig.ring_inertia] if model.law.spins_ring else [])
    )


def measures(model: Model) -> bool:
    """Whether the model has measurement effects (static): without, h(xi) = (x, y, z) exactly."""
    return bool(model.effects) and model.effects.acts_on(MEASUREMENT)


def measurement(model: Model, xi: Array) -> Array:
    """h(xi): the sensor output (3,), m, expected at state xi: (x, y, z) plus the measurement effects."""
    position = xi[:OUTPUT_SIZE]
    if measures(model):
        return position + model.effects.measurement(xi, model.rig)
    return position


def rk4(rate: Callable[[Array, float], Array], xi: Array, h: float) -> Array:
    """One classical Runge-Kutta step of length h (s) of d xi / dt = rate(xi, s) (eq. 15), s the stage's time
    after the step's start (0, h / 2, h / 2, h)."""
    k1 = h * rate(xi, 0.0)
    k2 = h * rate(xi + 0.5 * k1, 0.5 * h)
    k3 = h * rate(xi + 0.5 * k2, 0.5 * h)
    k4 = h * rate(xi + k3, h)
    return xi + (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0


def _stage_rate(model: Model, rate: Callable[[Model, Array], Array] | None = None) -> Callable[[Array, float], Array]:
    """(state, s) -> the model's rate (phi unless `rate` is given) s seconds into the step."""
    return lambda state, s: (rate or phi)(later(model, s), state)


#: Bisections of the ring's implicit update: its bracket, at most h T / J wide (about 13 rad/s under 20 kN on the
#: face), to 2^-40 of that before the last (Newton) step.
RING_BISECTION_STEPS = 40


def spin_acceleration(model: Model, xi: Array) -> Array:
    """d omega / dt (rad/s^2), the rotor's spin acceleration at xi: zero at the rig's constant speed;
    with a speed effect, its speed's rate along the kinematic rows (positions at their velocities,
    theta at the rig's speed), e.g. -rate omega_0 of a braked rotor."""
    effects = getattr(model, "effects", None)
    if not (effects and effects.acts_on(SPEED)):  # static: the paper's model, no change to its program
        return jnp.zeros((), xi.dtype)
    kinematic = jnp.zeros_like(xi).at[X:Z + 1].set(xi[XDOT:ZDOT + 1]).at[THETA].set(model.rig.speed)
    return jax.jvp(lambda state: rotor_speed(model, state)[0], (xi,), (kinematic,))[1]


def ring_speed_after(model: Model, xi: Array, h: float) -> Array:
    """The ring's speed (rad/s) after its implicit part of a step of h s, with the rotor held at xi:
    backward Euler on its speed relative to the rotor's, w - omega, whose rate is T(w) / J -
    d omega / dt: w = w0 - h d omega / dt + h T(w) / J. The rotor's RK4 step then carries the ring
    along at d omega / dt (`held_rate`), so that over the step it gains h T(w) / J and its slip is
    the balanced one throughout (held at w instead, a braked rotor's ring lagged by h d omega / dt
    at every step: 4 mm/s of bore slip at 400 rad/s^2, 0.1 ms, and a forward friction of ~900 N).

    The ring is light against the friction torque that holds it to the rotor, a stiff equation
    (rate about 1e6 /s stuck to the rotor: explicit RK4 at 0.1 ms diverges); backward Euler is
    stable for any h. T falls with w, so the root lies between w0' = w0 - h d omega / dt and the
    explicit step w0' + h T(w0') / J: bisection within that bracket, the residual being monotone.
    (30 Newton steps safeguarded by bisection, used until 2026-12-05, could end far from the root
    where the ring reaches the rotor's speed within the step, the residual flat on one side of the
    stick and steep on the other: 0.75 rad/s from it, its residual 11 rad/s, on a campaign drop;
    28.6 rad/s in `test_the_rings_implicit_update_solves_its_equation_wherever_the_ring_meets_the_rotor`.
    The filter's prediction there jumped as the constants moved.) The loop runs on values only; one
    Newton step from its result, differentiable, carries the exact first derivative (implicit function
    theorem: the residual is zero there).
    """
    J = model.rig.ring_inertia
    w0 = xi[OMEGA_RING] - h * spin_acceleration(model, xi)
    c = _contact_state(model, xi)
    held_model, held, start = jax.lax.stop_gradient((model, c, w0))

    def residual(w: Array) -> Array:
        return w - start - h * _ring_torque(held_model, held, w) / J

    explicit = start - residual(start)

    def bisect(_, bracket):
        lo, hi = bracket
        middle = 0.5 * (lo + hi)
        below = residual(middle) < 0.0
        return jnp.where(below, middle, lo), jnp.where(below, hi, middle)

    lo, hi = jax.lax.fori_loop(
        0, RING_BISECTION_STEPS, bisect, (jnp.minimum(start, explicit), jnp.maximum(start, explicit))
    )
    root = 0.5 * (lo + hi)
    T, dT = jax.jvp(lambda u: _ring_torque(model, c, u), (root,), (jnp.ones_like(root),))
    return root - (root - w0 - h * T / J) / (1.0 - h * dT / J)


def held_rate(model: Model, xi: Array) -> Array:
    """phi with the ring carried along at the rotor's spin acceleration (`spin_acceleration`): the
    rate of the rotor's part of a step after the ring's implicit update (`ring_speed_after`)."""
    return phi(model, xi).at[OMEGA_RING].set(spin_acceleration(model, xi))


def rk4_step(model: Model, xi: Array, h: float) -> Array:
    """f of eq. 15: one RK4 step of phi, of length h (s). With a spinning ring its speed is updated
    implicitly first (`ring_speed_after`), then carried along with the rotor's speed (`held_rate`)."""
    if model.law.spins_ring:
        return rk4(_stage_rate(model, held_rate), xi.at[OMEGA_RING].set(ring_speed_after(model, xi, h)), h)
    return rk4(_stage_rate(model), xi, h)


def ring_update_jacobian(model: Model, held: Array, h: float) -> Array:
    """d xi_held / d xi (n, n) of the ring's implicit update xi -> xi with omega_ring replaced by w,
    w = omega_ring - h a(rotor) + h T(w, rotor) / J (`ring_speed_after`, a the spin acceleration), at
    its result `held`: the identity but for the ring's row, by the implicit function theorem from one
    gradient of the torque T (and of a, with a speed effect):
    dw / d xi = (e_ring - h da / d rotor + h / J dT / d rotor) / (1 - h / J dT / dw)."""
    J = model.rig.ring_inertia
    dT = jax.grad(lambda state: contact_forces(model, state).ring_torque)(held)  # (n,): rotor, then w
    rotor = dT.at[OMEGA_RING].set(0.0)
    numerator = jnp.zeros_like(held).at[OMEGA_RING].set(1.0) + h / J * rotor
    if model.effects and model.effects.acts_on(SPEED):  # static: a depends on the rotor's state only
        numerator = numerator - h * jax.grad(lambda state: spin_acceleration(model, state))(held)
    row = numerator / (1.0 - h / J * dT[OMEGA_RING])
    return jnp.eye(held.shape[0], dtype=held.dtype).at[OMEGA_RING].set(row)


def transition_jacobian(model: Model, xi: Array, h: float) -> Array:
    """Phi_k = df/dxi at xi (eq. 16), exact by forward-mode automatic differentiation."""
    return jax.jacfwd(rk4_step, argnums=1)(model, xi, h)


def phi_and_jacobian(model: Model, xi: Array, rate: Callable[[Array], Array] | None = None) -> tuple[Array, Array]:
    """phi(xi) and d phi / d xi (n, n) from one forward and three (four with a spinning ring)
    reverse-mode passes; `rate` instead of phi if given (its kinematic rows phi's).

    Rows 1-4 of the Jacobian are constant (xdot, ydot, zdot, omega); only the acceleration rows
    need automatic differentiation.
    """
    value, pullback = jax.vjp(rate or (lambda state: phi(model, state)), xi)
    (acceleration_rows,) = jax.vmap(pullback)(jnp.eye(xi.shape[0], dtype=xi.dtype)[XDOT:])
    kinematic = jnp.zeros((4, xi.shape[0]), xi.dtype).at[0, XDOT].set(1.0).at[1, YDOT].set(1.0).at[2, ZDOT].set(1.0)
    return value, jnp.concatenate([kinematic, acceleration_rows])


#: RK4 stages of eq. 15: stage i evaluates phi at xi + shift_i k_{i-1} and enters f with weight_i / 6.
_STAGE_SHIFT = (0.0, 0.5, 0.5, 1.0)
_STAGE_WEIGHT = (1.0, 2.0, 2.0, 1.0)


def step_with_jacobian_and_rate(model: Model, xi: Array, h: float) -> tuple[Array, Array, Array, Array]:
    """f(xi) (eq. 15), Phi_k by the chain rule through the RK4 stages (eq. 16), and the first
    stage's phi(xi) and d phi / d xi (the filtered state's acceleration and its Jacobian).

    d phi / d xi at each stage comes from automatic differentiation; equal to
    `transition_jacobian` to round-off, at about half its cost. The four stages run as a
    `lax.scan` (eq. 16b-e are one recursion): the same arithmetic in the same order as
    writing them out, with a quarter of the program to compile. With a spinning ring its speed is
    updated implicitly first (`rk4_step`); Phi_k is the held RK4 step's times `ring_update_jacobian`
    (about a third of `transition_jacobian`'s cost).
    """
    if model.law.spins_ring:
        return *_ring_step_with_jacobian(model, xi, h), *phi_and_jacobian(model, xi)
    return _rk4_with_jacobian(model, xi, h)


def _ring_step_with_jacobian(model: Model, xi: Array, h: float) -> tuple[Array, Array]:
    """f(xi) and Phi_k with a spinning ring: its implicit speed update, then the held RK4 step."""
    held = xi.at[OMEGA_RING].set(ring_speed_after(model, xi, h))
    mean, Phi, _, _ = _rk4_with_jacobian(model, held, h, held_rate)
    return mean, Phi @ ring_update_jacobian(model, held, h)


def _rk4_with_jacobian(
    model: Model, xi: Array, h: float, rate_function: Callable[[Model, Array], Array] | None = None
) -> tuple[Array, Array, Array, Array]:
    I = jnp.eye(xi.shape[0], dtype=xi.dtype)  # noqa: E741 (the identity, as in the paper)

    def stage(carry, shift_and_weight):
        k, dk, total, dtotal = carry
        shift, weight = shift_and_weight
        staged = later(model, shift * h)
        rate, A = phi_and_jacobian(
            staged, xi + shift * k, functools.partial(rate_function, staged) if rate_function else None
        )
        k, dk = h * rate, h * A @ (I + shift * dk)  # eq. 15b-e, 16b-e
        return (k, dk, total + weight * k, dtotal + weight * dk), (rate, A)

    zero, zeros = jnp.zeros_like(xi), jnp.zeros_like(I)
    stages = (jnp.asarray(_STAGE_SHIFT, xi.dtype), jnp.asarray(_STAGE_WEIGHT, xi.dtype))
    (_, _, total, dtotal), (rates, jacobians) = jax.lax.scan(stage, (zero, zeros, zero, zeros), stages)
    return xi + total / 6.0, I + dtotal / 6.0, rates[0], jacobians[0]


def step_with_jacobian(model: Model, xi: Array, h: float) -> tuple[Array, Array]:
    """f(xi) (eq. 15) and Phi_k (eq. 16); see `step_with_jacobian_and_rate`. Without its phi(xi) and d phi / d xi,
    which a spinning ring's step evaluates apart: the filter's programs then trace about a sixth faster (stage 1's
    value and gradient 17.0 s against 20.6 s, 2026-12-03), the same arithmetic."""
    if model.law.spins_ring:
        return _ring_step_with_jacobian(model, xi, h)
    mean, Phi, _, _ = _rk4_with_jacobian(model, xi, h)
    return mean, Phi
