"""Truth physics of a vertical AMB rotor dropping onto an angular-contact auxiliary bearing.

Richer than the estimator's model (paper eq. 4-8) on purpose, and written
independently of `touchdown_ros.core`:

- Normal contact forces on the bearing bore (radial, d = r - r0) and on the
  inner-ring face (axial, d = -(z + z0)), clipped >= 0 and zero out of contact:
  Hunt-Crossley F = K d^n (1 + D d_dot) (default, n = 1.5: Hertz point contact) or
  Kelvin-Voigt F = K d^n + C d_dot (`damping_law: linear`); the axial force passes
  a preloaded support that yields above its preload (a knee in the axial stiffness).
- The bearing's inner ring is a body of its own with spin speed omega_ring: it is
  at rest before the drop, spun up by friction and slowed by its own drag. Once it
  co-rotates, friction drives the rotor into forward whirl (towards rigid
  co-rotation with the ring: synchronous whirl clinging to the bore).
- Stribeck friction mu(v) = mu_k + (mu_s - mu_k) exp(-(v / v_s)^2), regularised
  with v / sqrt(v^2 + v_reg^2), on the sliding velocity between rotor and ring:
  at the bore the tangential slip (whirl velocity + R omega - (R + r) omega_ring)
  together with z_dot (friction opposing axial sliding during radial contact);
  on the face the uniform lateral slip u = v_xy - omega r t plus the spin slip
  (omega - omega_ring) R_a. The lateral face friction is the tangential force
  proportional to the axial force of the paper's k_ZR, here slip-dependent and
  with a direction defined at r = 0; it is small while the ring still spins up
  and drives forward (F_t < 0) once the ring co-rotates.
- Rotor spin omega with polar inertia, an optional brake, unbalance with the
  e omega_dot term, AMB levitation (PD + gravity/load compensation + partial
  unbalance compensation) whose force decays exponentially at the drop.

Frames and signs follow the estimator: x, y radial, z up, rotor spins
anticlockwise, a = atan2(y, x), F_n > 0 pushes the rotor towards the centre,
F_t > 0 along (sin a, -cos a), F_z > 0 pushes up. All SI units.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

#: Indices into the truth state s = [x y z vx vy vz theta omega omega_ring].
X, Y, Z, VX, VY, VZ, THETA, OMEGA, OMEGA_RING = range(9)
STATE_SIZE = 9
#: Smallest radius used for directions, m (keeps a = atan2(y, x) and n finite at r = 0).
_R_EPS = 1e-12


class Truth(NamedTuple):
    """Constants of one simulated drop (JAX pytree of scalars), SI units."""

    mass: float  # kg
    eccentricity: float  # m
    radial_clearance: float  # r0, m
    axial_clearance: float  # z0, m
    gravity: float  # m/s^2
    journal_radius: float  # R, m: rotor journal inside the inner-ring bore
    face_radius: float  # R_a, m: effective radius of the axial face contact
    polar_inertia: float  # kg m^2, rotor
    ring_inertia: float  # kg m^2, inner ring with its share of the balls
    ring_drag: float  # N m s/rad, viscous drag of the spinning ring
    ring_drag_torque: float  # N m, constant (Coulomb) drag of the ring
    radial_stiffness: float  # K_R, N/m^n (n = radial_exponent)
    radial_damping: float  # D_R, s/m (Hunt-Crossley)
    axial_stiffness: float  # K_Z, N/m^n (n = axial_exponent)
    axial_damping: float  # D_Z, s/m (Hunt-Crossley)
    axial_mount_preload: float  # N, preload of the disc springs under the bearing housing
    axial_mount_span: float  # N, force the yielding support adds at most above its preload
    friction_static: float  # mu_s, 1
    friction_kinetic: float  # mu_k, 1
    stribeck_velocity: float  # v_s, m/s
    regularisation_velocity: float  # v_reg, m/s
    amb_stiffness: float  # N/m per axis
    amb_damping: float  # N s/m per axis
    amb_unbalance_compensation: float  # 1, share of m e omega^2 the AMB cancels
    amb_decay_time: float  # s, time constant of the AMB force after the drop
    brake_deceleration: float  # rad/s^2, 0 = no brake
    brake_time_constant: float  # s, brake engagement
    axial_load: float  # N, downward, 0 = no loader
    drop_time: float  # s
    axial_thrust: float = (
        0.0  # N, amplitude of a once-per-revolution axial force A cos(theta) (a wobbling thrust collar)
    )
    radial_exponent: float = 1.5  # n of the bore contact K d^n, 1
    axial_exponent: float = 1.5  # n of the face contact K d^n, 1
    linear_damping: float = 0.0  # 1.0: Kelvin-Voigt K d^n + C d_dot; 0.0: Hunt-Crossley K d^n (1 + D d_dot)
    radial_viscous_damping: float = 5.0e4  # C_R, N s/m (Kelvin-Voigt only)
    axial_viscous_damping: float = 5.0e4  # C_Z, N s/m (Kelvin-Voigt only)
    # Effects the paper's model lacks, each zero on the reference rig (hidden effects for the workbench):
    radial_load_x: float = 0.0  # N, constant side load along x (the AMB cancels it while levitated)
    radial_load_y: float = 0.0  # N, constant side load along y
    magnetic_stiffness_radial: float = 0.0  # N/m, negative stiffness left by the magnets: k x outward
    magnetic_stiffness_axial: float = 0.0  # N/m, the same along z
    rotor_drag_radial: float = 0.0  # N s/m, viscous drag on the rotor centre (seals, windage), x and y
    rotor_drag_axial: float = 0.0  # N s/m, the same along z
    cross_coupled_stiffness: float = 0.0  # q, N/m: seal / fluid force q (-y, x), driving forward whirl
    contact_angle_tan: float = 0.0  # tan(beta), 1: the bore contact also pushes up, tan(beta) F_nR
    twice_per_rev_force: float = 0.0  # N, radial force A (cos 2 theta, sin 2 theta) (a misaligned coupling)


class Contact(NamedTuple):
    """Contact forces and torques at one state."""

    force: Array  # (3,) force of the bearing on the rotor, sensor x/y/z, N
    F_n: Array  # N, radial component towards the centre
    F_t: Array  # N, component along (sin a, -cos a)
    F_z: Array  # N, axial component, up
    torque_rotor: Array  # N m on the rotor spin
    torque_ring: Array  # N m on the ring spin
    radial_contact: Array  # bool, r > r0
    axial_contact: Array  # bool, z < -z0


def normal_force(
    K: Array, exponent: Array, D: Array, C: Array, linear: Array, deformation: Array, rate: Array
) -> Array:
    """Normal contact force (N) at deformation d (m) and rate d_dot (m/s), zero out of contact, never pulling.

    Hunt-Crossley K d^n (1 + D d_dot) (D in s/m) when `linear` is 0, Kelvin-Voigt
    K d^n + C d_dot (C in N s/m) when it is 1; K in N/m^n. At n = 1.5 the power is
    the same expression as `hunt_crossley`'s, so the default rig's output is unchanged.
    """
    d = jnp.maximum(deformation, 0.0)
    elastic = K * d**exponent
    force = jnp.where(linear > 0.5, elastic + C * rate, elastic * (1.0 + D * rate))
    return jnp.where(deformation > 0.0, jnp.maximum(force, 0.0), 0.0)


def yielding_mount(force: Array, preload: Array, span: Array) -> Array:
    """Force (N) passed by the preloaded axial support of the bearing for a contact force (N).

    Rigid up to `preload`, then the disc springs yield and the force creeps towards
    preload + span: f -> preload + span x / (span + x), x = f - preload. Monotone with
    slope <= 1 and continuous slope at the knee, so applied to a Hunt-Crossley or
    Kelvin-Voigt force it keeps the elastic part conservative and the damping part dissipative.
    """
    excess = jnp.maximum(force - preload, 0.0)
    return jnp.where(force > preload, preload + span * excess / (span + excess), force)


def stribeck(p: Truth, speed: Array) -> Array:
    """Friction coefficient at sliding speed (m/s): mu_k + (mu_s - mu_k) exp(-(v / v_s)^2)."""
    return p.friction_kinetic + (p.friction_static - p.friction_kinetic) * jnp.exp(
        -((speed / p.stribeck_velocity) ** 2)
    )


def contact(p: Truth, s: Array) -> Contact:
    """Bearing forces on the rotor and torques on rotor and ring at state s."""
    x, y, z, vx, vy, vz, _, omega, omega_ring = (s[i] for i in range(STATE_SIZE))
    r = jnp.sqrt(x * x + y * y + _R_EPS**2)
    nx, ny = x / r, y / r  # outward normal; tangent t = (-ny, nx) is the anticlockwise direction
    r_dot = nx * vx + ny * vy
    whirl = -ny * vx + nx * vy  # m/s, > 0 forward (anticlockwise)
    v_reg = p.regularisation_velocity

    # Bore: normal force, friction on the combined tangential/axial slip.
    F_nR = normal_force(
        p.radial_stiffness,
        p.radial_exponent,
        p.radial_damping,
        p.radial_viscous_damping,
        p.linear_damping,
        r - p.radial_clearance,
        r_dot,
    )
    slip_t = whirl + p.journal_radius * omega - (p.journal_radius + r) * omega_ring
    bore_speed = jnp.sqrt(slip_t**2 + vz**2)
    bore_scale = stribeck(p, bore_speed) * F_nR / jnp.sqrt(bore_speed**2 + v_reg**2)
    f_t = bore_scale * slip_t  # N, on the rotor along -t
    F_zR = -bore_scale * vz

    # Face: axial normal force through the yielding mount; friction on lateral slip u and spin slip of rotor vs ring.
    F_zZ = yielding_mount(
        normal_force(
            p.axial_stiffness,
            p.axial_exponent,
            p.axial_damping,
            p.axial_viscous_damping,
            p.linear_damping,
            -(z + p.axial_clearance),
            -vz,
        ),
        p.axial_mount_preload,
        p.axial_mount_span,
    )
    # Rotor face minus ring face: uniform part u (= v - omega r t) plus the spin about the
    # ring axis. Coulomb friction over an annulus spinning at d_omega gives a net lateral
    # force mu F u / (2 d_omega R_a) for small u and mu F u / |u| without spin: hence the 4.
    ux, uy = vx + omega * y, vy - omega * x
    spin = (omega - omega_ring) * p.face_radius
    face_speed = jnp.sqrt(ux * ux + uy * uy + spin * spin)
    face_scale = stribeck(p, face_speed) * F_zZ / jnp.sqrt(ux * ux + uy * uy + 4.0 * spin * spin + v_reg**2)
    face_torque = face_scale * 2.0 * spin * p.face_radius  # N m, on the ring (minus on the rotor)

    Fx = -F_nR * nx + f_t * ny - face_scale * ux
    Fy = -F_nR * ny - f_t * nx - face_scale * uy
    Fz = F_zR + F_zZ + p.contact_angle_tan * F_nR
    return Contact(
        force=jnp.stack([Fx, Fy, Fz]),
        F_n=-(Fx * nx + Fy * ny),
        F_t=Fx * ny - Fy * nx,
        F_z=Fz,
        torque_rotor=-p.journal_radius * f_t - face_torque,
        torque_ring=(p.journal_radius + r) * f_t + face_torque,
        radial_contact=r > p.radial_clearance,
        axial_contact=z < -p.axial_clearance,
    )


def amb_gain(p: Truth, t: Array) -> Array:
    """Share of the AMB force still acting at time t (s): 1 before the drop, exp decay after."""
    return jnp.exp(-jnp.maximum(t - p.drop_time, 0.0) / p.amb_decay_time)


def brake_deceleration(p: Truth, t: Array) -> Array:
    """Brake deceleration of the rotor spin at time t (s), rad/s^2, engaging at the drop."""
    engaged = 1.0 - jnp.exp(-jnp.maximum(t - p.drop_time, 0.0) / p.brake_time_constant)
    return p.brake_deceleration * engaged


def derivative(p: Truth, t: Array, s: Array) -> Array:
    """ds/dt of the truth state at time t (s)."""
    c = contact(p, s)
    theta, omega = s[THETA], s[OMEGA]
    m = p.mass
    omega_dot = c.torque_rotor / p.polar_inertia - brake_deceleration(p, t)
    omega_ring = s[OMEGA_RING]
    ring_drag = p.ring_drag * omega_ring + p.ring_drag_torque * jnp.tanh(omega_ring)
    omega_ring_dot = (c.torque_ring - ring_drag) / p.ring_inertia

    cos_t, sin_t = jnp.cos(theta), jnp.sin(theta)
    unbalance = p.eccentricity * omega**2
    # Geometric centre: m (c + e u(theta))'' = F, so c'' = F / m + e omega^2 u + e omega_dot (sin, -cos).
    ub_x = unbalance * cos_t + p.eccentricity * omega_dot * sin_t
    ub_y = unbalance * sin_t - p.eccentricity * omega_dot * cos_t

    gain = amb_gain(p, t)
    comp = p.amb_unbalance_compensation * m * unbalance
    amb = gain * jnp.stack(
        [
            -p.amb_stiffness * s[X] - p.amb_damping * s[VX] - comp * cos_t - p.radial_load_x,
            -p.amb_stiffness * s[Y] - p.amb_damping * s[VY] - comp * sin_t - p.radial_load_y,
            -p.amb_stiffness * s[Z] - p.amb_damping * s[VZ] + m * p.gravity + p.axial_load,
        ]
    )
    external = jnp.stack([0.0, 0.0, -m * p.gravity - p.axial_load + p.axial_thrust * cos_t]) + hidden_force(p, s)
    accel = (c.force + amb + external) / m + jnp.stack([ub_x, ub_y, 0.0])
    return jnp.concatenate([s[VX : VZ + 1], accel, jnp.stack([omega, omega_dot, omega_ring_dot])])


def hidden_force(p: Truth, s: Array) -> Array:
    """(3,) N on the rotor from the effects the paper's model lacks (side load, magnetic negative
    stiffness, drag, cross-coupled stiffness, twice-per-revolution force); zero on the reference rig."""
    x, y, z, vx, vy, vz, theta = (s[i] for i in range(THETA + 1))
    k_r, k_z, q = p.magnetic_stiffness_radial, p.magnetic_stiffness_axial, p.cross_coupled_stiffness
    c_r, c_z, a2 = p.rotor_drag_radial, p.rotor_drag_axial, p.twice_per_rev_force
    return jnp.stack(
        [
            p.radial_load_x + k_r * x - q * y - c_r * vx + a2 * jnp.cos(2.0 * theta),
            p.radial_load_y + k_r * y + q * x - c_r * vy + a2 * jnp.sin(2.0 * theta),
            k_z * z - c_z * vz,
        ]
    )


def rk4_step(p: Truth, t: Array, s: Array, h: float) -> Array:
    """One classical Runge-Kutta step of length h (s) from time t."""
    k1 = derivative(p, t, s)
    k2 = derivative(p, t + 0.5 * h, s + 0.5 * h * k1)
    k3 = derivative(p, t + 0.5 * h, s + 0.5 * h * k2)
    k4 = derivative(p, t + h, s + h * k3)
    return s + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def levitated_state(p: Truth, theta0: float, speed: float) -> np.ndarray:
    """Periodic state of the levitated rotor at theta = theta0 (rad) and spin speed (rad/s).

    Residual unbalance orbit of the linear AMB loop (with the hidden effects' stiffness, drag and
    twice-per-revolution force), z = 0 (gravity and loads compensated), auxiliary-bearing ring at rest.
    """
    m = float(p.mass)
    force = (1.0 - float(p.amb_unbalance_compensation)) * m * float(p.eccentricity) * speed**2
    # In complex X = x + i y: m X'' + c X' + (k - k_m - i q) X = F e^{i theta} + A e^{2 i theta} (the
    # static side load is cancelled by the AMB); X = sum of the two harmonic responses.
    stiffness = float(p.amb_stiffness) - float(p.magnetic_stiffness_radial) - 1j * float(p.cross_coupled_stiffness)
    damping = float(p.amb_damping) + float(p.rotor_drag_radial)
    orbit = [
        (n, f / (stiffness - m * (n * speed) ** 2 + 1j * n * speed * damping) * np.exp(1j * n * theta0))
        for n, f in ((1, force), (2, float(p.twice_per_rev_force)))
    ]
    position = sum(a for _, a in orbit)
    velocity = sum(1j * n * speed * a for n, a in orbit)
    return np.array([position.real, position.imag, 0.0, velocity.real, velocity.imag, 0.0, theta0, speed, 0.0])
