"""The `simulator:` section of the rig YAML: validation and per-experiment truth constants."""
from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Mapping

import numpy as np

from touchdown_ros.io.config import Config, ConfigError
from touchdown_ros.io.parameters import number_text_hint
from touchdown_ros.sim.physics import Truth

BALLS = ("ceramic", "steel")
#: `simulator.damping_law`: Hunt-Crossley K d^n (1 + D d_dot) or Kelvin-Voigt K d^n + C d_dot.
DAMPING_LAWS = ("hunt_crossley", "linear")

# name: (default, lower bound, upper bound, lower bound inclusive). Defaults are the reference
# rig's values (config/reference_rig.yaml, where each is documented with its unit).
_SCALARS: dict[str, tuple[float, float, float, bool]] = {
    "levitated_time": (0.02, 0.0, 10.0, False),
    "drop_duration": (0.15, 0.0, 10.0, False),
    "experiment_interval": (600.0, 0.0, math.inf, True),
    "variation": (0.03, 0.0, 0.2, True),
    "journal_radius": (0.1, 0.0, 10.0, False),
    "face_radius": (0.1, 0.0, 10.0, False),
    "rotor_polar_inertia": (2.7, 0.0, math.inf, False),
    "amb_stiffness": (2.0e6, 0.0, math.inf, False),
    "amb_damping": (2.0e4, 0.0, math.inf, True),
    "amb_unbalance_compensation": (0.7, 0.0, 1.0, True),
    "amb_decay_time": (1.0e-3, 0.0, 1.0, False),
    "brake_deceleration": (400.0, 0.0, math.inf, True),
    "brake_time_constant": (5.0e-3, 0.0, 1.0, False),
    "axial_load": (2000.0, 0.0, math.inf, True),
    "axial_thrust": (0.0, 0.0, math.inf, True),
    "axial_mount_preload": (3.6e4, 0.0, math.inf, False),
    "axial_mount_span": (1.0e4, 0.0, math.inf, False),
    "regularisation_velocity": (0.01, 0.0, 1.0, False),
    # hidden effects the paper's model lacks (physics.Truth), all off on the reference rig
    "radial_load_x": (0.0, -math.inf, math.inf, True),
    "radial_load_y": (0.0, -math.inf, math.inf, True),
    "magnetic_stiffness_radial": (0.0, 0.0, math.inf, True),
    "magnetic_stiffness_axial": (0.0, 0.0, math.inf, True),
    "rotor_drag_radial": (0.0, 0.0, math.inf, True),
    "rotor_drag_axial": (0.0, 0.0, math.inf, True),
    "cross_coupled_stiffness": (0.0, -math.inf, math.inf, True),
    "contact_angle_tan": (0.0, 0.0, 1.0, True),
    "twice_per_rev_force": (0.0, 0.0, math.inf, True),
    **{f"sensor_gain_{axis}": (1.0, 0.0, 10.0, False) for axis in "xyz"},
    **{f"sensor_offset_{axis}": (0.0, -0.01, 0.01, True) for axis in "xyz"},
}
_BALL_BOUNDS: dict[str, tuple[float, float, bool]] = {
    "radial_stiffness": (0.0, math.inf, False),
    "radial_damping": (0.0, math.inf, True),
    "axial_stiffness": (0.0, math.inf, False),
    "axial_damping": (0.0, math.inf, True),
    "friction_static": (0.0, 2.0, True),
    "friction_kinetic": (0.0, 2.0, True),
    "stribeck_velocity": (0.0, math.inf, False),
    "ring_inertia": (0.0, math.inf, False),
    "ring_drag": (0.0, math.inf, True),
    "ring_drag_torque": (0.0, math.inf, True),
    "contact_exponent": (1.0, 2.0, True),
    "radial_viscous_damping": (0.0, math.inf, True),
    "axial_viscous_damping": (0.0, math.inf, True),
}
#: Each ball's contact constants where `simulator.<ball>.*` does not set them (config/reference_rig.yaml: the same).
BALL_DEFAULTS: dict[str, dict[str, float]] = {
    "ceramic": {
        "radial_stiffness": 3.0e11,
        "radial_damping": 20.0,
        "axial_stiffness": 3.0e11,
        "axial_damping": 6.0,
        "friction_static": 0.24,
        "friction_kinetic": 0.18,
        "stribeck_velocity": 0.05,
        "ring_inertia": 3.0e-3,
        "ring_drag": 1.0e-3,
        "ring_drag_torque": 0.5,
        "contact_exponent": 1.5,
        "radial_viscous_damping": 5.0e4,
        "axial_viscous_damping": 5.0e4,
    },
    "steel": {
        "radial_stiffness": 2.6e11,
        "radial_damping": 25.0,
        "axial_stiffness": 2.6e11,
        "axial_damping": 8.0,
        "friction_static": 0.28,
        "friction_kinetic": 0.22,
        "stribeck_velocity": 0.05,
        "ring_inertia": 4.5e-3,
        "ring_drag": 1.5e-3,
        "ring_drag_torque": 0.8,
        "contact_exponent": 1.5,
        "radial_viscous_damping": 5.0e4,
        "axial_viscous_damping": 5.0e4,
    },
}
#: Constants that vary from experiment to experiment by `variation` (relative standard deviation).
#: The Kelvin-Voigt dampings C take the factor drawn for the Hunt-Crossley D of their direction
#: (no draw of their own: the random stream, hence the default rig's drops, stay as they were).
_VARIED = (
    "radial_stiffness",
    "radial_damping",
    "axial_stiffness",
    "axial_damping",
    "friction_static",
    "friction_kinetic",
    "ring_inertia",
    "amb_decay_time",
    "brake_deceleration",
)
_SHARES_FACTOR_OF = {"radial_viscous_damping": "radial_damping", "axial_viscous_damping": "axial_damping"}
_DEFAULT_START = "2026-01-01T00:00:00Z"


@dataclass(frozen=True)
class SimulatorParameters:
    """Validated `simulator.*` values; `balls` maps ball type -> its contact constants."""

    substeps: int
    scalars: Mapping[str, float]
    balls: Mapping[str, Mapping[str, float]]
    start_time_ns: int  # ns since the Unix epoch, first experiment's first sample
    damping_law: str = "hunt_crossley"  # one of DAMPING_LAWS


def _number(key: str, value: Any, low: float, high: float, low_inclusive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        hint = number_text_hint(value)
        raise ConfigError(f"parameter 'simulator.{key}' must be a finite number, got {value!r}{hint}")
    below = value < low if low_inclusive else value <= low
    if below or value > high:
        bracket = "[" if low_inclusive else "("
        raise ConfigError(f"parameter 'simulator.{key}' must be in {bracket}{low:g}, {high:g}], got {value!r}")
    return float(value)


def simulator_parameters(config: Config) -> SimulatorParameters:
    """Validate `config.simulator` (flat dotted keys); unknown keys and bad values name the key."""
    raw = dict(config.simulator)
    known = {"substeps", "start_time", "damping_law", *_SCALARS, *(f"{b}.{k}" for b in BALLS for k in _BALL_BOUNDS)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError("unknown simulator parameter(s): " + ", ".join(f"'simulator.{k}'" for k in unknown))

    substeps = raw.get("substeps", 100)
    if isinstance(substeps, float) and substeps.is_integer():
        substeps = int(substeps)
    if isinstance(substeps, bool) or not isinstance(substeps, int) or not 1 <= substeps <= 1000:
        raise ConfigError(f"parameter 'simulator.substeps' must be an integer in [1, 1000], got {substeps!r}")
    scalars = {k: _number(k, raw.get(k, d), lo, hi, inc) for k, (d, lo, hi, inc) in _SCALARS.items()}
    balls = {
        b: {
            k: _number(f"{b}.{k}", raw.get(f"{b}.{k}", BALL_DEFAULTS[b][k]), lo, hi, inc)
            for k, (lo, hi, inc) in _BALL_BOUNDS.items()
        }
        for b in BALLS
    }
    for b in BALLS:
        if balls[b]["friction_kinetic"] > balls[b]["friction_static"]:
            raise ConfigError(f"parameter 'simulator.{b}.friction_kinetic' must not exceed '{b}.friction_static'")

    damping_law = raw.get("damping_law", DAMPING_LAWS[0])
    if damping_law not in DAMPING_LAWS:
        raise ConfigError(
            f"parameter 'simulator.damping_law' must be one of {', '.join(DAMPING_LAWS)}, got {damping_law!r}"
        )

    start = raw.get("start_time", _DEFAULT_START)
    try:
        stamp = datetime.fromisoformat(str(start).replace("Z", "+00:00"))
    except ValueError:
        raise ConfigError(f"parameter 'simulator.start_time' must be an ISO 8601 time, got {start!r}") from None
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=timezone.utc)
    start_ns = int(stamp.timestamp()) * 1_000_000_000 + stamp.microsecond * 1000

    period = config.sample_period
    for key in ("levitated_time", "drop_duration"):
        if scalars[key] < 10 * period:
            raise ConfigError(f"parameter 'simulator.{key}' must cover at least 10 sensor samples ({10 * period:g} s)")
    return SimulatorParameters(substeps, scalars, balls, start_ns, damping_law)


def truth_constants(
    config: Config,
    params: SimulatorParameters,
    ball: str,
    brake: bool,
    axial_load: bool,
    drop_time: float,
    rng: np.random.Generator,
) -> Truth:
    """The truth constants of one experiment: nominal values varied by `variation`, as floats."""
    if ball not in BALLS:
        raise ValueError(f"unknown ball type {ball!r}; expected one of {BALLS}")
    values: dict[str, float] = {**params.scalars, **params.balls[ball]}
    factors = {name: float(np.clip(1.0 + values["variation"] * rng.standard_normal(), 0.5, 1.5)) for name in _VARIED}
    factors.update({name: factors[like] for name, like in _SHARES_FACTOR_OF.items()})
    for name, factor in factors.items():
        values[name] *= factor
    load = values["axial_load"] * float(np.clip(1.0 + 0.5 * values["variation"] * rng.standard_normal(), 0.5, 1.5))
    rig = config.rig
    return Truth(
        mass=rig.mass,
        eccentricity=rig.eccentricity,
        radial_clearance=rig.radial_clearance,
        axial_clearance=rig.axial_clearance,
        gravity=rig.gravity,
        journal_radius=values["journal_radius"],
        face_radius=values["face_radius"],
        polar_inertia=values["rotor_polar_inertia"],
        ring_inertia=values["ring_inertia"],
        ring_drag=values["ring_drag"],
        ring_drag_torque=values["ring_drag_torque"],
        radial_stiffness=values["radial_stiffness"],
        radial_damping=values["radial_damping"],
        axial_stiffness=values["axial_stiffness"],
        axial_damping=values["axial_damping"],
        axial_mount_preload=values["axial_mount_preload"],
        axial_mount_span=values["axial_mount_span"],
        friction_static=max(values["friction_static"], values["friction_kinetic"]),
        friction_kinetic=values["friction_kinetic"],
        stribeck_velocity=values["stribeck_velocity"],
        regularisation_velocity=values["regularisation_velocity"],
        amb_stiffness=values["amb_stiffness"],
        amb_damping=values["amb_damping"],
        amb_unbalance_compensation=values["amb_unbalance_compensation"],
        amb_decay_time=values["amb_decay_time"],
        brake_deceleration=values["brake_deceleration"] if brake else 0.0,
        brake_time_constant=values["brake_time_constant"],
        axial_load=load if axial_load else 0.0,
        drop_time=drop_time,
        axial_thrust=values["axial_thrust"],
        radial_exponent=values["contact_exponent"],
        axial_exponent=values["contact_exponent"],
        linear_damping=1.0 if params.damping_law == "linear" else 0.0,
        radial_viscous_damping=values["radial_viscous_damping"],
        axial_viscous_damping=values["axial_viscous_damping"],
        **{name: values[name] for name in HIDDEN_EFFECTS},
    )


#: hidden effects the paper's model lacks: `simulator.<name>` keys passed to physics.Truth as they are.
HIDDEN_EFFECTS = (
    "radial_load_x",
    "radial_load_y",
    "magnetic_stiffness_radial",
    "magnetic_stiffness_axial",
    "rotor_drag_radial",
    "rotor_drag_axial",
    "cross_coupled_stiffness",
    "contact_angle_tan",
    "twice_per_rev_force",
)

#: h * rate below which classical RK4 is stable with margin (its limit is ~2.8 on the real and imaginary axes).
_RK4_LIMIT = 2.5


def impact_speed_bound(truth: Truth, speed: float) -> float:
    """m/s, a bound on the speed at which the rotor meets the bearing: a free fall over the axial
    clearance under gravity and load, plus the rotor's rim speed over the radial clearance, r0 omega."""
    fall = truth.gravity + (truth.axial_load + truth.axial_thrust) / truth.mass
    return math.sqrt(2.0 * fall * truth.axial_clearance) + truth.radial_clearance * abs(speed)


def contact_rate(
    stiffness: float, exponent: float, damping: float, viscous_damping: float, linear: bool, mass: float, impact: float
) -> float:
    """1/s, the fastest rate of the rotor on one contact of K d^n (N/m^n): |eigenvalue| of
    m x'' + c x' + k x with k, c the contact's slopes dF/dd, dF/dd_dot at the deformation d*
    that stores the kinetic energy of an impact at `impact` m/s (K d*^(n+1) / (n + 1) = m v^2 / 2),
    the largest a drop can reach; the rate grows with d for n >= 1.

    Hunt-Crossley (D in s/m): k = n K d^(n-1) (1 + D v), c = K d^n D; Kelvin-Voigt: k = n K d^(n-1), c = C.
    """
    energy = 0.5 * mass * impact**2
    d = ((exponent + 1.0) * energy / stiffness) ** (1.0 / (exponent + 1.0))
    k = exponent * stiffness * d ** (exponent - 1.0)
    if linear:
        c = viscous_damping
    else:
        k *= 1.0 + damping * impact
        c = stiffness * d**exponent * damping
    half = c / (2.0 * mass)
    return half + math.sqrt(half * half + k / mass)


def stiffest_rates(truth: Truth, speed: float) -> dict[str, float]:
    """1/s, the fastest rate of each stiff mode of a drop at `speed` rad/s: "ring", "radial", "axial".

    The ring stuck to the rotor by friction:
    rate ~ mu_s F (R + r0)^2 / (v_reg J_ring) + mu_s F / (m v_reg) with F = 1.5 m r0 omega^2
    (synchronous whirl with margin). The bore and face contacts: `contact_rate` at the
    deformation an impact at `impact_speed_bound` reaches (a stiffer or more damped contact,
    a higher exponent at a large deformation or a lighter rotor are faster).
    """
    force = 1.5 * truth.mass * truth.radial_clearance * speed**2
    slip_gain = truth.friction_static * force / truth.regularisation_velocity
    ring_rate = slip_gain * (truth.journal_radius + truth.radial_clearance) ** 2 / truth.ring_inertia
    ring_rate += slip_gain / truth.mass
    impact = impact_speed_bound(truth, speed)
    linear = truth.linear_damping > 0.5
    return {
        "ring": ring_rate,
        "radial": contact_rate(
            truth.radial_stiffness, truth.radial_exponent, truth.radial_damping, truth.radial_viscous_damping,
            linear, truth.mass, impact,
        ),
        "axial": contact_rate(
            truth.axial_stiffness, truth.axial_exponent, truth.axial_damping, truth.axial_viscous_damping,
            linear, truth.mass, impact,
        ),
    }


def required_substeps(truth: Truth, speed: float, period: float) -> int:
    """The fewest RK4 substeps per sensor period (s) that keep h * rate within the limit for every
    mode of `stiffest_rates`."""
    return int(math.ceil(period * max(stiffest_rates(truth, speed).values()) / _RK4_LIMIT))


def check_step_size(
    params: SimulatorParameters, truth: Truth, speed: float, period: float, ball: str = "<ball>"
) -> None:
    """Refuse a substep too long for the stiffest mode of the drop (RK4 needs h * rate < 2.5;
    the modes: `stiffest_rates`). `ball` (the experiment's ball) names the keys in the message."""
    rates = stiffest_rates(truth, speed)
    stiffest = max(rates, key=rates.__getitem__)
    rate = rates[stiffest]
    h = period / params.substeps
    if h * rate <= _RK4_LIMIT:
        return
    needed = required_substeps(truth, speed, period)
    head = f"parameter 'simulator.substeps' = {params.substeps} is too few for "
    if stiffest == "ring":
        raise ConfigError(
            head + f"these friction and ring constants (stiff ring-rotor stick: h * rate = {h * rate:.1f} > "
            f"{_RK4_LIMIT}); use at least {needed}, or raise 'simulator.regularisation_velocity' or the ring inertia"
        )
    impact = impact_speed_bound(truth, speed)
    damping = "viscous_damping" if truth.linear_damping > 0.5 else "damping"
    raise ConfigError(
        head + f"the {stiffest} contact of the {ball} ball (stiff contact at {impact:.2g} m/s impact: h * rate = "
        f"{h * rate:.1f} > {_RK4_LIMIT}); use at least {needed}, or lower 'simulator.{ball}.{stiffest}_stiffness', "
        f"'simulator.{ball}.{stiffest}_{damping}' or 'simulator.{ball}.contact_exponent'"
    )
