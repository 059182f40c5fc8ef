"""Typed containers of the estimator's model; all are JAX pytrees (NamedTuples), SI units."""
from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from touchdown_ros.core.effects import Effects

#: Indices into the state xi = [x y z theta xdot ydot zdot] (paper eq. 11), and the inner ring's
#: speed omega_ring (rad/s) that follows them when the friction model spins the ring
#: (`ContactLaw.state_size`).
X, Y, Z, THETA, XDOT, YDOT, ZDOT, OMEGA_RING = range(8)
STATE_SIZE = 7  # the paper's state; with a spinning ring, 8
VELOCITY = slice(XDOT, ZDOT + 1)  # xdot, ydot, zdot in xi; phi(xi)[VELOCITY] is the acceleration
OUTPUT_SIZE = 3
#: Names of the six learned parameters, in the paper's order alpha_1..alpha_6 (eq. 9).
PARAMETER_NAMES = ("k_R", "c_R", "mu", "k_Z", "c_Z", "k_ZR")
RADIAL_PARAMETERS = PARAMETER_NAMES[:3]
AXIAL_PARAMETERS = PARAMETER_NAMES[3:]


class Rig(NamedTuple):
    """Rotor and bearing geometry the estimator's model needs."""

    mass: float  # m, kg
    eccentricity: float  # e, m
    speed: float  # omega, rad/s
    radial_clearance: float  # r0, m
    axial_clearance: float  # z0, m
    gravity: float = 9.80665  # g, m/s^2
    journal_radius: float = 0.1  # R, m: the rotor's journal in the bore (friction torque on a spinning ring)
    face_radius: float = 0.1  # R_a, m: mean radius of the face contact
    ring_inertia: float = 3.0e-3  # J, kg m^2: the inner ring's polar moment with what spins with it
    # the AMB controller as it was at the drop (what the `amb_release` effect lets go of; none by default)
    amb_stiffness: float = 0.0  # N/m, its PD law's proportional gain about the bearing's centre
    amb_damping: float = 0.0  # N s/m, its PD law's derivative gain
    amb_unbalance_compensation: float = 0.0  # 1, share of the unbalance force m e omega^2 it cancels


class Nominal(NamedTuple):
    """Nominal constant contact parameters f_0,1..f_0,6 (the baseline of the paper's ref. [13])."""

    k_R: float  # radial stiffness, N/m
    c_R: float  # radial damping, N s/m
    mu: float  # friction coefficient, 1
    k_Z: float  # axial stiffness, N/m
    c_Z: float  # axial damping, N s/m
    k_ZR: float  # tangential force per axial contact force, 1


#: The log covariance of a pair of the law's constants known exactly (`ContactLaw.support_log_covariance`,
#: `stribeck_log_covariance`: rigid, none, given, or from an older file).
EXACT_PAIR = ((0.0, 0.0), (0.0, 0.0))


class ContactLaw(NamedTuple):
    """Normal-force law of the contacts: F = k d^n + c d^m d_dot, floored at 0 where `floored`.

    linear (the paper's eq. 6a, 8c): n = 1, m = 0, not floored; k in N/m, c in N s/m.
    hertz: n = m (1.5 for balls, 10/9 for rollers), floored (Hertz with Hunt-Crossley
    damping, F = d^n (k + c d_dot), never pulling); k in N/m^n, c in N s/m^(n+1).
    kelvin_voigt: n > 1, m = 0, floored (a Hertzian spring beside a viscous damper, F = k d^n +
    c d_dot, never pulling: damping that does not vanish at first touch); k in N/m^n, c in N s/m.
    The face force passes the bearing's axial support (`dynamics.yielding_support`): rigid by
    default, or preloaded disc springs under the housing that yield above the preload P and
    pass at most P + S (degressive). The exponents and the support are traced numbers, so one
    compiled filter serves every law.

    Friction (`dynamics.friction`, FRICTION_MODELS[friction_model]): the paper's (eq. 6b, 6c, 8b:
    the ring at rest, F_t = mu F_n + k_ZR F_zZ); "co_rotating_ring", Coulomb friction on the slip
    against an inner ring spinning with the rotor; "spinning_ring", the same against a ring whose
    speed is an eighth state, spun up by the friction's torque (`dynamics.ring_friction`). Coulomb
    friction is regularised below `slip_velocity` (m/s). The choice is static (pytree aux data,
    registered below): a program holds one friction model, not several selected per sample
    (two had cost stage 1 about 40 % of its compilation and a third of its step: docs/calibration.md,
    "Cost").
    """

    stiffness_exponent: float = 1.0  # n
    damping_exponent: float = 0.0  # m
    floored: float = 0.0  # 1: the force never pulls; 0: as printed
    support_preload: float = float("inf")  # N, face force above which the axial support yields; inf: rigid
    support_span: float = float("inf")  # N, force the yielding support adds at most above its preload
    #: covariance of (ln P, ln S) as stage 1 left it (displacements say little about a support beyond
    #: the knee, docs/calibration.md); the force band carries it (`estimate.support_force_covariance`)
    support_log_covariance: tuple[tuple[float, float], tuple[float, float]] = EXACT_PAIR
    friction_model: int = 0  # index into FRICTION_MODELS; 0: the paper's
    slip_velocity: float = 0.01  # m/s, slip above which ring friction reaches mu (regularised Coulomb)
    #: Stribeck drop against a ring: the coefficient is mu (1 + friction_drop exp(-(s / stribeck_velocity)^2))
    #: at slip speed s, mu_s / mu_k - 1 at rest; 0: Coulomb's (mu at every slip)
    friction_drop: float = 0.0
    stribeck_velocity: float = 0.02  # m/s, slip over which the drop fades
    #: covariance of (ln friction_drop, ln stribeck_velocity) where stage 1 fitted them; the force band carries
    #: it (`estimate.law_force_covariance`)
    stribeck_log_covariance: tuple[tuple[float, float], tuple[float, float]] = EXACT_PAIR

    @staticmethod
    def of(name: str, exponent: float | None = None) -> "ContactLaw":
        """The law called `name` ("linear", "hertz" or "kelvin_voigt", exponent default 1.5); ValueError
        if unknown."""
        if name == "linear":
            if exponent not in (None, 1.0):
                raise ValueError("the linear contact law has exponent 1")
            return ContactLaw()
        if name not in CONTACT_LAWS:
            raise ValueError(f"contact law must be one of {', '.join(CONTACT_LAWS)}, got {name!r}")
        n = 1.5 if exponent is None else float(exponent)
        if name == "kelvin_voigt" and not 1.0 < n <= 3.0:  # at n = 1 it is the linear law, floored
            raise ValueError(f"the kelvin_voigt law's exponent must be in (1, 3], got {exponent!r}")
        if not 1.0 <= n <= 3.0:
            raise ValueError(f"contact exponent must be in [1, 3], got {exponent!r}")
        return ContactLaw(n, n if name == "hertz" else 0.0, 1.0)

    @property
    def name(self) -> str:
        if float(self.damping_exponent) != 0.0:
            return "hertz"
        return "linear" if float(self.stiffness_exponent) == 1.0 else "kelvin_voigt"

    @property
    def exponent(self) -> float:
        return float(self.stiffness_exponent)

    @property
    def yields(self) -> bool:
        """Whether the axial support yields (a finite preload)."""
        return math.isfinite(float(self.support_preload))

    def with_support(
        self, preload: float = float("inf"), span: float = float("inf"), log_covariance=EXACT_PAIR
    ) -> "ContactLaw":
        """The same law with an axial support preloaded to `preload` (N; inf: rigid) that passes at most
        preload + span (N), known to `log_covariance` ((2, 2), of ln preload and ln span; zero: exactly)."""
        return self._replace(support_preload=preload, support_span=span, support_log_covariance=log_covariance)

    @property
    def support_uncertain(self) -> bool:
        """Whether the support yields and its preload or span carries an uncertainty (static: concrete values)."""
        return self.yields and any(float(v) != 0.0 for row in self.support_log_covariance for v in row)

    def with_friction(self, friction: str, slip_velocity: float = 0.01) -> "ContactLaw":
        """The same law with friction `friction` (one of FRICTION_MODELS) regularised below `slip_velocity` m/s."""
        if friction not in FRICTION_MODELS:
            raise ValueError(f"friction must be one of {', '.join(FRICTION_MODELS)}, got {friction!r}")
        if not slip_velocity > 0.0:
            raise ValueError(f"slip_velocity must be > 0 m/s, got {slip_velocity!r}")
        return self._replace(friction_model=FRICTION_MODELS.index(friction), slip_velocity=slip_velocity)

    def with_stribeck(self, drop: float, velocity: float, log_covariance=EXACT_PAIR) -> "ContactLaw":
        """The same law whose ring friction falls from mu (1 + drop) at rest to mu over slips of about
        `velocity` m/s (Stribeck's curve, `dynamics.stribeck_factor`); drop 0: Coulomb's. Known to
        `log_covariance` ((2, 2), of ln drop and ln velocity; zero: exactly)."""
        if not drop >= 0.0:
            raise ValueError(f"friction_drop must be >= 0 (mu_s / mu_k - 1), got {drop!r}")
        if not velocity > 0.0:
            raise ValueError(f"stribeck_velocity must be > 0 m/s, got {velocity!r}")
        return self._replace(friction_drop=drop, stribeck_velocity=velocity, stribeck_log_covariance=log_covariance)

    @property
    def stribeck_uncertain(self) -> bool:
        """Whether there is a drop and it carries an uncertainty (static: concrete values)."""
        return float(self.friction_drop) > 0.0 and any(
            float(v) != 0.0 for row in self.stribeck_log_covariance for v in row
        )

    def with_friction_of(self, other: "ContactLaw") -> "ContactLaw":
        """The same law with `other`'s friction: its model, slip velocity and Stribeck drop."""
        return self.with_friction(other.friction, other.slip_velocity).with_stribeck(
            other.friction_drop, other.stribeck_velocity, other.stribeck_log_covariance
        )

    @property
    def friction(self) -> str:
        """One of FRICTION_MODELS: 'paper', 'co_rotating_ring', 'spinning_ring'."""
        return FRICTION_MODELS[self.friction_model]

    @property
    def spins_ring(self) -> bool:
        """Whether the inner ring's speed is a state (static: the friction model is aux data)."""
        return self.friction == "spinning_ring"

    @property
    def state_size(self) -> int:
        """Length of the state xi under this law: 7, or 8 when the ring's speed is a state."""
        return STATE_SIZE + self.spins_ring

    @property
    def setting(self) -> str:
        """'linear', 'hertz:1.5' or 'kelvin_voigt:1.5': the law as `training.contact_laws` spells it."""
        return "linear" if self.name == "linear" else f"{self.name}:{self.exponent:.4g}"

    @property
    def label(self) -> str:
        """'linear', 'hertz n=1.5' or 'hertz n=1.5, support yields above 35.2 kN (at most 45.1 kN)'."""
        law = self.name if self.name == "linear" else f"{self.name} n={self.exponent:.4g}"
        if not self.yields:
            return law
        preload, span = float(self.support_preload), float(self.support_span)
        return f"{law}, support yields above {preload / 1e3:.3g} kN (at most {(preload + span) / 1e3:.3g} kN)"


_LAW_FIELDS = tuple(f for f in ContactLaw._fields if f != "friction_model")


def _flatten_law(law: ContactLaw) -> tuple[tuple, int]:
    return tuple(getattr(law, f) for f in _LAW_FIELDS), int(law.friction_model)


def _unflatten_law(friction_model: int, children: tuple) -> ContactLaw:
    return ContactLaw(**dict(zip(_LAW_FIELDS, children)), friction_model=friction_model)


jax.tree_util.register_pytree_node(ContactLaw, _flatten_law, _unflatten_law)

CONTACT_LAWS = ("linear", "hertz", "kelvin_voigt")
#: Friction models: the paper's (ring at rest), Coulomb friction against a ring spinning with the rotor,
#: and against a ring spun up by the friction (its speed a state).
FRICTION_MODELS = ("paper", "co_rotating_ring", "spinning_ring")


class Kernel(NamedTuple):
    """PKBKR kernel: Gaussian Q on normalised rho = (r - r0, rdot) and zeta = (-(z + z0), zdot).

    zeta's first component is the axial compression -(z + z0) (the paper's z + z0 with
    its sign turned), so both deformations are >= 0 in contact and both centre grids
    read as deformation >= 0. Centres are in the normalised coordinates of the kernel
    inputs: (deformation, velocity) / scale, with one scale per centre set.
    """

    T_R: Array  # (m_R, 2) radial centre set, normalised
    T_Z: Array  # (m_Z, 2) axial centre set, normalised
    width: float  # Gaussian width sigma in normalised units
    scale_R: Array  # (2,) m, m/s per normalised unit of rho
    scale_Z: Array  # (2,) m, m/s per normalised unit of zeta


class Coefficients(NamedTuple):
    """PKBKR coefficients alpha_1..alpha_6, dimensionless (relative to each nominal value)."""

    alpha_R: Array  # (3, m_R): alpha_1 (k_R), alpha_2 (c_R), alpha_3 (mu)
    alpha_Z: Array  # (3, m_Z): alpha_4 (k_Z), alpha_5 (c_Z), alpha_6 (k_ZR)

    @staticmethod
    def zeros(kernel: Kernel) -> "Coefficients":
        """All alpha = 0: the PKBKR model equals the constant model."""
        return Coefficients(
            alpha_R=jnp.zeros((3, kernel.T_R.shape[0])),
            alpha_Z=jnp.zeros((3, kernel.T_Z.shape[0])),
        )


class Model(NamedTuple):
    """Everything phi (eq. 12) depends on."""

    rig: Rig
    nominal: Nominal
    kernel: Kernel
    coeffs: Coefficients
    effects: Effects = Effects()  # add-on force terms (core.effects); none: the paper's model
    law: ContactLaw = ContactLaw()  # normal-force law; default: the paper's linear spring-damper


class FilterNoise(NamedTuple):
    """EKF noise and initialisation (eq. 17): Q, R and P_0 as diagonals."""

    process: Array  # (n,) diagonal of Q, state units^2 per sample (n: `ContactLaw.state_size`)
    measurement: Array  # (3,) diagonal of R, m^2
    initial: Array  # (n,) diagonal of P_0


class ContactForces(NamedTuple):
    """Contact forces on the rotor at one state (eq. 5-8), N, with the contact flags."""

    F_n: Array  # radial (normal) force, positive pushes the rotor towards the centre
    F_t: Array  # tangential force, positive along (sin a, -cos a)
    F_z: Array  # axial force, positive upwards
    F_x: Array  # F_n, F_t resolved on the sensor x axis (eq. 4a times m)
    F_y: Array  # ... on the sensor y axis (eq. 4b times m)
    radial_contact: Array  # bool, r > r0
    axial_contact: Array  # bool, z < -z0
    ring_torque: Array = 0.0  # N m, friction torque on a spinning ring (spinning_ring only)
