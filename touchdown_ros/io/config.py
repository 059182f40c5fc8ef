"""Rig YAML in ROS 2 parameter-file form -> typed configuration.

The file holds ``<node name or /**>: ros__parameters: {...}``; nested keys are
the dotted ROS parameter names (``rig.mass``). Unknown or missing keys, wrong
types and non-physical values are refused with a message naming the key.
"""
from __future__ import annotations

import hashlib
import json
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import ArrayLike
import yaml

from touchdown_ros.core import effects as effects_library
from touchdown_ros.core.effects import Effects
from touchdown_ros.core.ekf import NoiseAdaptation
from touchdown_ros.core.estimate import DropDetector
from touchdown_ros.core.input_policy import InputPolicy
from touchdown_ros.core.streaming.settings import StreamSettings
from touchdown_ros.core.types import (
    CONTACT_LAWS, FRICTION_MODELS, STATE_SIZE, Coefficients, ContactLaw, FilterNoise, Kernel, Model, Nominal, Rig,
)
from touchdown_ros.io.parameters import ConfigError, ParameterReader, flatten_parameters

REFERENCE_RIG_NAME = "reference_rig.yaml"


@dataclass(frozen=True)
class Topics:
    displacement: str = "/amb/displacement"
    velocity: str = "/touchdown/velocity"
    acceleration: str = "/touchdown/acceleration"
    contact_force: str = "/touchdown/contact_force"
    contact_force_std: str = "/touchdown/contact_force_std"  # Vector3Stamped, N, 1-sigma per sensor axis
    displacement_estimate: str = "/touchdown/displacement"
    # TwistWithCovarianceStamped, twist.angular.z: rad/s about sensor z, contact.friction: spinning_ring only
    ring_speed: str = "/touchdown/ring_speed"
    truth_velocity: str = "/truth/velocity"
    truth_acceleration: str = "/truth/acceleration"
    truth_contact_force: str = "/truth/contact_force"
    frame_id: str = "amb_sensor"


LOSSES = ("nll", "one_step")
PLACEMENTS = ("data", "fixed")
#: training.search: standard (the support chosen by BIC) or thorough (by AIC, with damping restarts).
SEARCH_CHOICES = ("standard", "thorough")
#: training.friction_start: where stage 1's refinement starts the friction with a spinning ring: screened (the
#: screening's fit) or both (also from the restart grid's pair that lowers the loss on all bags; the lower fit kept).
FRICTION_START_CHOICES = ("screened", "both")
#: training.refinement: how stage 1 refines the chosen law on all bags: gauss_newton (Levenberg-Marquardt on the
#: Fisher information) or lbfgs (L-BFGS-B on the gradient, the optimiser until 2026-12-01).
REFINEMENT_CHOICES = ("gauss_newton", "lbfgs")
#: How stage 2 picks lambda among those tried (`workflows.train.fit_regularisation_path`).
REGULARISATION_CHOICES = ("lowest", "one_standard_error")
#: training.axial_support: auto (try a yielding support, keep it if the data ask for it), rigid, yielding,
#: given (contact.support_preload and support_span as the YAML says, held: a mount's data sheet).
SUPPORT_CHOICES = ("auto", "rigid", "yielding", "given")
#: training.smoothing_noise: the offline estimate's Q: likelihood (the fitted Q as it is, as the live filter) or
#: cross_validation (a factor on the fitted Q, chosen by the smoother's leave-one-out error of the positions; it
#: made the velocity worse and its band too narrow: docs/calibration.md, "The smoothed estimate with the fitted Q").
SMOOTHING_NOISE_CHOICES = ("cross_validation", "likelihood")
#: training.friction_drop: given (contact.friction_drop and stribeck_velocity as the YAML says, held) or fitted
#: (stage 1 fits both from the YAML's as a guess, held by the prior where the data say little; a ring friction only).
FRICTION_DROP_CHOICES = ("given", "fitted")


@dataclass(frozen=True)
class TrainingSettings:
    """`training.*`: how `touchdown train` identifies a rig (stage 1) and fits PKBKR (stage 2)."""

    loss: str = "nll"  # nll: innovation negative log-likelihood; one_step: eq. 18 as published
    # stage-1 candidate contact laws ("linear", "hertz:<n>", "kelvin_voigt:<n>"); the data choose;
    # empty: contact.law only
    contact_laws: tuple[ContactLaw, ...] = ()
    # stage-1 candidate friction models (FRICTION_MODELS): each is calibrated, the data choose; empty:
    # contact.friction only
    friction_models: tuple[str, ...] = ()
    prior_width: float = 1.6  # sd of ln f0 around the guess (ln 5: a guess 5x off is one sd)
    # m, sd of r0 and z0 around rig.*_clearance (drawing tolerances, thermal growth); 0: given exactly, not fitted
    clearance_tolerance: float = 0.0
    reference_deformation: float = 20.0e-6  # m, where a guess is carried over between contact laws
    placement: str = "data"  # kernel centres: data (from the calibrated estimates) | fixed (kernel.* grid)
    calibration_steps: int = 200  # cap on stage-1 L-BFGS iterations (it stops at convergence first)
    screening_bags: int = 6  # stage 1 screens the contact laws on this many bags, spread over all (< 1: all)
    pkbkr_steps: int = 200  # cap on stage-2 L-BFGS iterations
    tolerance: float = 1.0e-6  # relative loss change, and gradient norm, that count as converged
    held_out_every: int = 5  # stage 2: one block in this many is held out of the loss (< 2: none)
    held_out_block: float = 0.005  # s, length of those blocks
    patience: int = 10  # stage 2 stops when the held-out loss has not fallen for this many steps
    regularisation_choice: str = "lowest"  # stage 2's lambda (REGULARISATION_CHOICES)
    axial_support: str = "auto"  # stage 1: fit a yielding axial support (auto: kept if the criterion falls) or not
    search: str = "thorough"  # stage 1: thorough (AIC, damping restarts; docs/calibration.md) | standard (BIC)
    refinement: str = "lbfgs"  # stage 1's optimiser on all bags (REFINEMENT_CHOICES)
    friction_start: str = "screened"  # stage 1's refinement with a spinning ring (FRICTION_START_CHOICES)
    friction_ceiling: float | None = None  # stage 1 fits mu and k_ZR at most this (None, .inf in YAML: unbounded)
    smoothing_noise: str = "likelihood"  # the offline estimate's Q (SMOOTHING_NOISE_CHOICES)
    friction_drop: str = "given"  # stage 1: the ring friction's Stribeck drop (FRICTION_DROP_CHOICES)
    # not a YAML parameter: the effects `train --start` switches on that its file did not fit, which stage 1 also fits
    # alone first, the file's calibration held (both starts refined, the lower kept)
    effects_alone_first: tuple[str, ...] = ()


@dataclass(frozen=True)
class DropDetection:
    threshold: float  # m below the levitated mean of z
    levitated_window: float  # s
    lead: float = 0.0  # s the record starts before the free fall: in levitation, the AMB's release modelled


EXECUTORS = ("events", "single")
RECEIVE_MODES = ("drain", "callback", "inline")
RELIABILITIES = ("best_effort", "reliable")
OUTPUT_MODES = ("per_sample", "batch", "both")
#: Parameters of earlier versions, and what replaces them.
RENAMED = {"node.worker": "replaced by node.receive (true: drain or callback, false: inline)"}


@dataclass(frozen=True)
class NodeSettings:
    """The live node's `node.*` parameters (touchdown_estimator); SI units."""

    coefficients: str = ""  # PKBKR coefficient file; empty: the constant model
    executor: str = "events"  # events (rclpy EventsExecutor) | single (SingleThreadedExecutor)
    input_reliability: str = "best_effort"  # QoS of the displacement subscriptions
    input_depth: int = 10000  # keep-last history depth of the input subscriptions (1 s at 10 kHz)
    batch_topic: str = "/amb/displacement_batch"  # sensor_msgs/PointCloud2 with fields t, x, y, z
    output_mode: str = "per_sample"  # per_sample (the /touchdown/* topics) | batch | both
    batch_output_topic: str = "/touchdown/estimate_batch"  # PointCloud2, one message per EKF run
    output_reliability: str = "reliable"
    output_depth: int = 10000  # keep-last depth of the output publishers (1 s at 10 kHz)
    flush_period: float = 0.002  # s between timer runs of the EKF on the pending samples
    flush_samples: int = 16  # pending samples that run the EKF at once (without waiting for the timer)
    # drain: a worker thread takes the waiting samples itself, many per wake-up, and runs the EKF;
    # callback: the executor hands over one sample per callback, a worker thread runs the EKF;
    # inline: the executor's callbacks and timer run the EKF too (no worker thread)
    receive: str = "drain"
    realtime_priority: int = 0  # SCHED_FIFO priority (1-99) of the node's threads; 0: normal scheduling
    chunk_sizes: tuple[int, ...] = StreamSettings.chunk_sizes  # compiled EKF chunk lengths
    diagnostics_period: float = 1.0  # s
    alarm_force: float = StreamSettings.alarm_force  # N, |contact force| that raises an ERROR diagnostic
    sensor_range: float = InputPolicy.sensor_range  # m, |value| at or beyond it is saturated
    millimetre_limit: float = InputPolicy.millimetre_limit  # m, |value| beyond it is taken for a value in mm
    grid_tolerance: float = InputPolicy.grid_tolerance  # sample periods a stamp may sit off the grid
    max_gap: float = InputPolicy.max_gap  # s, a longer stamp jump (either way) is a clock jump (filter restarted)
    bridge_gap: float = InputPolicy.bridge_gap  # s, holes up to this are bridged by predict-only rows; longer: restart
    rail_samples: int = InputPolicy.rail_samples  # identical values in a row beyond half the range: pinned at a rail
    resync_after: int = StreamSettings.resync_after  # consecutive out-of-order / off-grid samples that re-anchor
    relevitation_band: float = StreamSettings.relevitation_band  # m around the levitated mean that counts as levitated
    relevitation_window: float = StreamSettings.relevitation_window  # s in the band that ends a touchdown
    conditions: tuple[str, ...] = ()  # test conditions on during this run (switch effects with a `when`)


@dataclass(frozen=True)
class Config:
    """Everything one rig YAML says, typed and validated."""

    rig: Rig
    nominal: Nominal
    kernel: Kernel
    noise: FilterNoise
    sample_period: float  # s
    noise_rms: float  # m
    quantisation: float  # m
    drop: DropDetection
    regularisation: tuple[float, ...]  # lambda of eq. 18; several: stage 2 chooses by its held-out loss
    topics: Topics
    training_noise_scale: float = 1.0  # factor on Q while training (smaller: model errors show in the innovations)
    smoothing_noise_scale: float = 1.0  # factor on Q of the offline estimate (a coefficient file's, `offline_noise`)
    # the offline estimate's Q blocks scaled where a bag's own likelihood asks for it (`workflows.offline.bag_noise`),
    # where Q was fitted on training bags (`noise_fitted`)
    bag_process_noise: bool = True
    # the live filter's Q moved by its innovations (`filter.adaptive_process_noise`); None: Q as it is
    adaptation: NoiseAdaptation | None = None
    noise_fitted: bool = False  # Q from training bags (a coefficient file's calibration), not the YAML's guess
    # N^2 per axis: the model's own force error in contact, measured on the training bags (a coefficient
    # file's, `core.smoothing.missing_force_squares`); None: m^2 Q_v / h^2 (`core.estimate.force_model_variance`)
    force_model_variance: tuple[float, float, float] | None = None
    law: ContactLaw = field(default_factory=ContactLaw)  # contact.law / contact.exponent
    training: TrainingSettings = field(default_factory=TrainingSettings)
    simulator: Mapping[str, Any] = field(default_factory=dict)
    source: str = "<built-in>"
    parameters: Mapping[str, Any] = field(default_factory=dict)  # flat dotted ROS parameters
    node: NodeSettings = field(default_factory=NodeSettings)  # the live node's node.* parameters
    effects: Effects = field(default_factory=Effects)  # add-on force terms switched on in effects.*
    # m, (r0, z0) as stage 1 calibrated them (a coefficient file's); None: rig.*_clearance as the YAML gives them
    clearances: tuple[float, float] | None = None

    def model(self, coeffs: Coefficients | None = None, effects: Effects | None = None) -> Model:
        """The estimator's model: all alpha = 0 (constant baseline) unless coeffs are given,
        with this rig's effects unless others are given (a coefficient file's)."""
        return Model(
            self.contact_rig,
            self.nominal,
            self.kernel,
            coeffs or Coefficients.zeros(self.kernel),
            self.effects if effects is None else effects,
            self.law,
        )

    @property
    def contact_rig(self) -> Rig:
        """The rig the model's contacts see: the YAML's, with the calibrated clearances where a file gives them."""
        if self.clearances is None:
            return self.rig
        return self.rig._replace(radial_clearance=self.clearances[0], axial_clearance=self.clearances[1])

    def training_noise(self) -> FilterNoise:
        """The filter noise used by the training loss: Q scaled by training.process_noise_scale."""
        return self.noise._replace(process=np.asarray(self.noise.process) * self.training_noise_scale)

    def offline_noise(self) -> FilterNoise:
        """The filter noise of the offline (smoothed) estimate: Q scaled by the factor the training chose
        for smoothing (`workflows.train.choose_smoothing_scale`; 1 without a coefficient file). The live
        node filters with `noise` as it is."""
        return self.noise._replace(process=np.asarray(self.noise.process) * self.smoothing_noise_scale)

    def held_out_block_samples(self) -> int:
        """training.held_out_block (s) as a whole number of samples, at least one."""
        return max(1, round(self.training.held_out_block / self.sample_period))

    def drop_detector(self) -> DropDetector:
        """The drop onset rule of `drop_detection.*` on this rig's sample grid."""
        return DropDetector(
            self.sample_period, self.drop.threshold, self.drop.levitated_window, self.rig.gravity, self.drop.lead
        )

    def stream_settings(self, **overrides: Any) -> StreamSettings:
        """The streaming estimator's settings (`drop_detection.*`, `sensor.*`, `node.*`); `overrides` by field name."""
        node = self.node
        settings = StreamSettings(
            policy=InputPolicy.from_config(self),
            drop=self.drop_detector(),
            resync_after=node.resync_after,
            relevitation_band=node.relevitation_band,
            relevitation_window=node.relevitation_window,
            alarm_force=node.alarm_force,
            chunk_sizes=tuple(node.chunk_sizes),
        )
        return replace(settings, **overrides)

    def fingerprint(self) -> str:
        """SHA-256 of the rig a coefficient file is valid for (`model_identity`)."""
        return hashlib.sha256(json.dumps(self.model_identity(), sort_keys=True).encode()).hexdigest()

    def model_identity(self) -> dict[str, Any]:
        """The rig values a coefficient file is only valid for, as plain JSON-able data: the
        rotor and the sample period, and a `drop_detection.lead` where there is one (the records' start, from
        which clocked effects such as amb_release's release are timed). The contact law, its constants, the
        kernel and the filter noise are what the file itself carries (calibrated), not the YAML's guesses."""
        lead = {"drop_detection.lead": self.drop.lead} if self.drop.lead else {}
        return {"rig": dict(self.rig._asdict()), "sample_period": self.sample_period, **lead}

    def calibrated(
        self,
        nominal: Nominal,
        law: ContactLaw,
        kernel: Kernel,
        noise: FilterNoise,
        smoothing_noise_scale: float = 1.0,
        force_model_variance: tuple[float, float, float] | None = None,
        clearances: tuple[float, float] | None = None,
    ) -> "Config":
        """This rig with identified contact constants, law, kernel, filter noise (fitted: `noise_fitted`), the
        model's force error and clearances (m, r0 and z0; None: the YAML's) (a coefficient file's)."""
        if not len(noise.process) == len(noise.initial) == law.state_size:
            raise ValueError(
                f"contact.friction {law.friction} has a state of {law.state_size}, the filter noise "
                f"{len(noise.process)} (Q) and {len(noise.initial)} (P_0)"
            )
        return replace(
            self, nominal=nominal, law=law, kernel=kernel, noise=noise, smoothing_noise_scale=smoothing_noise_scale,
            force_model_variance=force_model_variance, clearances=clearances, noise_fitted=True,
        )

    @property
    def live_adaptation(self) -> NoiseAdaptation | None:
        """The live filter's adaptive Q (`adaptation`) where Q was fitted on training bags (a coefficient file's);
        None (Q as given) for the YAML's guess, as the offline search of `bag_process_noise`: on the untrained
        guess of the reference rig a wider Q lets the state follow the samples and the model's own force, far off,
        decides the force (exp 11: force RMSE 6.7 kN against 4.0 kN with Q as given, 2026-12-08)."""
        return self.adaptation if self.noise_fitted else None

    def with_friction(self, friction: str) -> "Config":
        """This rig with contact.friction `friction` (one of FRICTION_MODELS) in its law and its candidate laws;
        the filter noise follows the state (a spinning ring's speed is an eighth state, with the YAML's
        filter.ring_process_noise and ring_initial_covariance)."""
        law = self.law.with_friction(friction, self.law.slip_velocity)
        process, initial = state_noise(
            self.noise.process, self.noise.initial, law.spins_ring,
            self.parameters.get("filter.ring_process_noise", RING_PROCESS_NOISE),
            self.parameters.get("filter.ring_initial_covariance", RING_INITIAL_COVARIANCE),
        )
        noise = self.noise._replace(process=process, initial=initial)
        laws = tuple(c.with_friction(friction, c.slip_velocity) for c in self.training.contact_laws)
        return replace(self, law=law, noise=noise, training=replace(self.training, contact_laws=laws))

    @property
    def fits_stribeck_drop(self) -> bool:
        """Whether stage 1 fits the Stribeck drop: training.friction_drop: fitted, against a ring (the paper's
        friction has no slip for it to act on)."""
        return self.training.friction_drop == "fitted" and self.law.friction != "paper"

    def without_stribeck_fit(self) -> "Config":
        """This rig with no Stribeck drop, given (`training.friction_drop: given`), in its law and candidate laws."""
        laws = tuple(c.with_stribeck(0.0, c.stribeck_velocity) for c in self.training.contact_laws)
        return replace(
            self, law=self.law.with_stribeck(0.0, self.law.stribeck_velocity),
            training=replace(self.training, contact_laws=laws, friction_drop="given"),
        )

    def model_variance(self) -> np.ndarray | None:
        """(3,) N^2 the force band adds in contact: the coefficient file's measured one, else None (the
        estimators then read the process noise as a force, `core.estimate.force_model_variance`)."""
        return None if self.force_model_variance is None else np.asarray(self.force_model_variance, dtype=float)


def _adaptation(read: ParameterReader, sample_period: float) -> NoiseAdaptation | None:
    """The live filter's adaptive Q (`filter.adaptive_process_noise` and its `filter.adaptation_*`), None if off."""
    gain = read.number("filter.adaptation_gain", 0.1, positive=True)
    memory = read.number("filter.adaptation_memory", 0.01, positive=True)
    max_scale = read.number("filter.adaptation_max_scale", 64.0, positive=True)
    if not read.flag("filter.adaptive_process_noise", True):
        return None
    if memory < sample_period:
        raise ConfigError(f"filter.adaptation_memory = {memory:g} s is shorter than one sample ({sample_period:g} s)")
    if max_scale < 1.0:
        raise ConfigError(f"filter.adaptation_max_scale = {max_scale:g} must be at least 1 (Q as fitted)")
    return NoiseAdaptation(gain=gain, leak=sample_period / memory, max_scale=max_scale)


def reference_rig_path() -> Path:
    """The packaged default rig: the repo's config/ or the installed share/touchdown_ros/config/."""
    candidates = [
        Path(__file__).resolve().parents[2] / "config" / REFERENCE_RIG_NAME,
        Path(sys.prefix) / "share" / "touchdown_ros" / "config" / REFERENCE_RIG_NAME,
    ]
    for path in candidates:
        if path.is_file():
            return path
    raise ConfigError(f"reference rig not found; looked in: {', '.join(map(str, candidates))}")


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """Load a rig YAML (the reference rig when path is None); overrides are dotted keys."""
    path = Path(path) if path is not None else reference_rig_path()
    try:
        document = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: rig file not found") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from None
    parameters = _ros_parameters(document, path)
    flat = dict(flatten_parameters(parameters))
    flat.update(overrides or {})
    return config_from_parameters(flat, source=str(path))


def _ros_parameters(document: Any, path: Path) -> dict[str, Any]:
    if not isinstance(document, dict) or not document:
        raise ConfigError(f"{path}: expected a ROS 2 parameter file '<node>: ros__parameters: ...'")
    for node, body in document.items():
        if isinstance(body, dict) and isinstance(body.get("ros__parameters"), dict):
            return body["ros__parameters"]
    raise ConfigError(f"{path}: no '<node>: ros__parameters:' section found")


def _grid(deformation: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    d, v = np.meshgrid(deformation, velocity, indexing="ij")
    return np.stack([d.ravel(), v.ravel()], axis=1)


#: A spinning ring's speed (contact.friction: spinning_ring): Q per sample and P_0, (rad/s)^2, unless
#: filter.ring_process_noise / filter.ring_initial_covariance say otherwise. The ring is at rest at the
#: drop (mean 0) give or take 1 rad/s; an unmodelled torque of about 1 N m changes its speed by about
#: 0.03 rad/s per sample (config/reference_rig.yaml). Q of 1 rad/s per sample had made the friction of a
#: rolling ring, which turns on slips of 0.01 m/s, noise: force RMSE 6-7 % instead of 1-2 %.
RING_PROCESS_NOISE = 1.0e-3
RING_INITIAL_COVARIANCE = 1.0


def state_noise(
    rotor_q: ArrayLike, rotor_p0: ArrayLike, spins_ring: bool, ring_q: float, ring_p0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Q per sample and P_0 of the filter's state: the rotor's (its first STATE_SIZE entries), then, when the
    ring spins, its speed's ((rad/s)^2)."""
    ring = ([ring_q], [ring_p0]) if spins_ring else ([], [])
    return (np.append(np.asarray(rotor_q, dtype=float)[:STATE_SIZE], ring[0]),
            np.append(np.asarray(rotor_p0, dtype=float)[:STATE_SIZE], ring[1]))


def config_from_parameters(flat: Mapping[str, Any], source: str = "<parameters>") -> Config:
    """Build a Config from flat dotted ROS parameters (as the node receives them)."""
    read = ParameterReader(flat, source)
    rig = Rig(
        mass=read.number("rig.mass", positive=True),
        eccentricity=read.number("rig.eccentricity", non_negative=True),
        speed=read.number("rig.speed"),
        radial_clearance=read.number("rig.radial_clearance", positive=True),
        axial_clearance=read.number("rig.axial_clearance", positive=True),
        gravity=read.number("rig.gravity", 9.80665, non_negative=True),
        journal_radius=read.number("rig.journal_radius", Rig._field_defaults["journal_radius"], positive=True),
        face_radius=read.number("rig.face_radius", Rig._field_defaults["face_radius"], positive=True),
        ring_inertia=read.number("rig.ring_inertia", Rig._field_defaults["ring_inertia"], positive=True),
        **{
            name: read.number(f"rig.{name}", 0.0, non_negative=True)
            for name in ("amb_stiffness", "amb_damping", "amb_unbalance_compensation")
        },
    )
    nominal = Nominal(*(read.number(f"contact.{name}", non_negative=True) for name in Nominal._fields))
    law = _contact_law(read)
    scale = np.array(
        [read.number("kernel.deformation_scale", positive=True), read.number("kernel.velocity_scale", positive=True)]
    )
    kernel = Kernel(
        T_R=_grid(read.numbers("kernel.radial_deformation_centres"), read.numbers("kernel.radial_velocity_centres")),
        T_Z=_grid(read.numbers("kernel.axial_deformation_centres"), read.numbers("kernel.axial_velocity_centres")),
        width=read.number("kernel.width", positive=True),
        scale_R=scale,
        scale_Z=scale.copy(),
    )
    measurement_sigma = read.number("filter.measurement_noise", positive=True)
    ring_q = read.number("filter.ring_process_noise", RING_PROCESS_NOISE, non_negative=True)
    ring_p0 = read.number("filter.ring_initial_covariance", RING_INITIAL_COVARIANCE, non_negative=True)
    rotor_q = read.numbers("filter.process_noise", STATE_SIZE, non_negative=True)
    rotor_p0 = read.numbers("filter.initial_covariance", STATE_SIZE, non_negative=True)
    process, initial = state_noise(rotor_q, rotor_p0, law.spins_ring, ring_q, ring_p0)
    noise = FilterNoise(process=process, measurement=np.full(3, measurement_sigma**2), initial=initial)
    drop = DropDetection(
        threshold=read.number("drop_detection.threshold", 20e-6, positive=True),
        levitated_window=read.number("drop_detection.levitated_window", 0.005, positive=True),
        lead=read.number("drop_detection.lead", 0.0, non_negative=True),
    )
    effects = _effects(read, flat, drop.lead)
    config = Config(
        rig=rig,
        nominal=nominal,
        kernel=kernel,
        noise=noise,
        sample_period=read.number("sensor.sample_period", positive=True),
        noise_rms=read.number("sensor.noise_rms", non_negative=True),
        quantisation=read.number("sensor.quantisation", 0.0, non_negative=True),
        drop=drop,
        regularisation=_regularisation(read),
        training_noise_scale=read.number("training.process_noise_scale", 1.0, positive=True),
        bag_process_noise=read.flag("filter.bag_process_noise", True),
        adaptation=_adaptation(read, read.number("sensor.sample_period", positive=True)),
        law=law,
        training=_training_settings(read, law),
        topics=Topics(**{name: read.text(f"topics.{name}", default) for name, default in Topics().__dict__.items()}),
        simulator={k.removeprefix("simulator."): v for k, v in flat.items() if k.startswith("simulator.")},
        source=source,
        parameters=dict(flat),
        node=_node_settings(read),
        effects=effects,
    )
    read.used.update(k for k in flat if k.startswith("simulator."))
    unknown = sorted(set(flat) - read.used)
    if unknown:
        hints = "".join(f"; {name}: {RENAMED[name]}" for name in unknown if name in RENAMED)
        raise ConfigError(f"{source}: unknown parameter(s): {', '.join(unknown)}{hints}")
    return config


def parse_contact_law(text: str) -> ContactLaw:
    """'linear', 'hertz' or 'kelvin_voigt' (n = 1.5), or with ':<n>' -> ContactLaw; ValueError names what is
    wrong."""
    name, _, exponent = str(text).partition(":")
    if name not in CONTACT_LAWS:
        raise ValueError(
            f"contact law {text!r}: use one of linear, hertz, hertz:<exponent>, kelvin_voigt, kelvin_voigt:<exponent>"
        )
    if name == "linear" and exponent:
        raise ValueError(f"contact law {text!r}: the linear law takes no exponent")
    try:
        n = float(exponent) if exponent else None
    except ValueError:
        raise ValueError(f"contact law {text!r}: the exponent must be a number") from None
    return ContactLaw.of(name, n)


def _contact_law(read: ParameterReader) -> ContactLaw:
    """contact.law (linear | hertz | kelvin_voigt), contact.exponent (not linear; default 1.5), the axial
    support: contact.support_preload (N, default .inf: rigid) and contact.support_span (N), and the
    friction: contact.friction (paper | co_rotating_ring | spinning_ring), contact.slip_velocity (m/s), and the
    Stribeck drop of a ring's friction: contact.friction_drop (mu_s / mu_k - 1, default 0: none) and
    contact.stribeck_velocity (m/s)."""
    name = read.choice("contact.law", "linear", CONTACT_LAWS)
    exponent = read.number("contact.exponent", 1.0 if name == "linear" else 1.5, positive=True)
    rigid = read._get("contact.support_preload", math.inf) == math.inf  # .inf in YAML: a rigid support
    read._get("contact.support_span", math.inf)  # read (a known key) also when rigid, where it plays no part
    preload = math.inf if rigid else read.number("contact.support_preload", positive=True)
    span = math.inf if rigid else read.number("contact.support_span", positive=True)
    friction = read.choice("contact.friction", "paper", FRICTION_MODELS)
    slip_velocity = read.number("contact.slip_velocity", 0.01, positive=True)
    drop = read.number("contact.friction_drop", 0.0, non_negative=True)
    stribeck_velocity = read.number("contact.stribeck_velocity", 0.02, positive=True)
    if drop > 0.0 and friction == "paper":
        raise ConfigError(
            f"{read.source}: contact.friction_drop acts on the slip against a ring (contact.friction: spinning_ring "
            "or co_rotating_ring); the paper's friction has no slip, so the drop would be ignored: set it to 0"
        )
    try:
        return (
            ContactLaw.of(name, exponent).with_support(preload, span).with_friction(friction, slip_velocity)
            .with_stribeck(drop, stribeck_velocity)
        )
    except ValueError as error:
        raise ConfigError(f"{read.source}: contact.law / contact.exponent: {error}") from None


def _regularisation(read: ParameterReader) -> tuple[float, ...]:
    """training.regularisation: one lambda of eq. 18, or a list stage 2 chooses from by its held-out loss."""
    key = "training.regularisation"
    if isinstance(read._get(key, None), list):
        return tuple(float(v) for v in read.numbers(key, non_negative=True))
    return (read.number(key, 1e-3, non_negative=True),)


def _axial_support(read: ParameterReader, law: ContactLaw) -> str:
    """training.axial_support; `given` needs the support in contact.* (a finite preload and span)."""
    choice = read.choice("training.axial_support", TrainingSettings().axial_support, SUPPORT_CHOICES)
    if choice == "given" and not law.yields:
        raise ConfigError(
            f"{read.source}: training.axial_support: given needs the support's contact.support_preload and "
            "contact.support_span (N, finite: the force where the mount starts to yield, and what it adds at most)"
        )
    return choice


def _friction_ceiling(read: ParameterReader) -> float | None:
    """training.friction_ceiling: a positive number, or .inf (YAML; a ROS parameter cannot be null) for none."""
    if read._get("training.friction_ceiling", math.inf) == math.inf:
        return None
    return read.number("training.friction_ceiling", positive=True)


def _training_settings(read: ParameterReader, law: ContactLaw) -> TrainingSettings:
    """The `training.*` keys of the two-stage identification (defaults of TrainingSettings)."""
    d = TrainingSettings()
    laws = read._get("training.contact_laws", ["linear", "hertz:1.5", "hertz:1.111"])
    if not isinstance(laws, list) or not all(isinstance(v, str) for v in laws):
        raise ConfigError(
            f"{read.source}: parameter 'training.contact_laws' must be a list such as [linear, hertz:1.5]"
        )
    try:
        candidates = tuple(
            dict.fromkeys(parse_contact_law(v).with_friction_of(law) for v in laws)
        )
    except ValueError as error:
        raise ConfigError(f"{read.source}: training.contact_laws: {error}") from None
    axial_support = _axial_support(read, law)
    if axial_support == "given":
        candidates = tuple(c.with_support(law.support_preload, law.support_span) for c in candidates)
    return TrainingSettings(
        loss=read.choice("training.loss", d.loss, LOSSES),
        contact_laws=candidates or (law,),
        friction_models=_friction_models(read),
        prior_width=read.number("training.prior_width", d.prior_width, positive=True),
        clearance_tolerance=read.number("training.clearance_tolerance", d.clearance_tolerance, non_negative=True),
        reference_deformation=read.number("training.reference_deformation", d.reference_deformation, positive=True),
        placement=read.choice("kernel.placement", d.placement, PLACEMENTS),
        calibration_steps=read.integer("training.calibration_steps", d.calibration_steps),
        screening_bags=read.integer("training.screening_bags", d.screening_bags, minimum=0),
        pkbkr_steps=read.integer("training.pkbkr_steps", d.pkbkr_steps, minimum=0),
        tolerance=read.number("training.tolerance", d.tolerance, positive=True),
        held_out_every=read.integer("training.held_out_every", d.held_out_every, minimum=0),
        held_out_block=read.number("training.held_out_block", d.held_out_block, positive=True),
        patience=read.integer("training.patience", d.patience, minimum=1),
        regularisation_choice=read.choice(
            "training.regularisation_choice", d.regularisation_choice, REGULARISATION_CHOICES
        ),
        axial_support=axial_support,
        search=read.choice("training.search", d.search, SEARCH_CHOICES),
        friction_start=read.choice("training.friction_start", d.friction_start, FRICTION_START_CHOICES),
        friction_ceiling=_friction_ceiling(read),
        refinement=read.choice("training.refinement", d.refinement, REFINEMENT_CHOICES),
        smoothing_noise=read.choice("training.smoothing_noise", d.smoothing_noise, SMOOTHING_NOISE_CHOICES),
        friction_drop=_friction_drop(read, law),
    )


def _friction_drop(read: ParameterReader, law: ContactLaw) -> str:
    """training.friction_drop; `fitted` needs a ring friction and a guess of the drop > 0 to start from."""
    choice = read.choice("training.friction_drop", TrainingSettings().friction_drop, FRICTION_DROP_CHOICES)
    if choice == "fitted" and law.friction == "paper":
        raise ConfigError(
            f"{read.source}: training.friction_drop: fitted needs friction against a ring (contact.friction: "
            "spinning_ring or co_rotating_ring); the paper's friction has no slip for a Stribeck drop to act on"
        )
    if choice == "fitted" and not float(law.friction_drop) > 0.0:
        raise ConfigError(
            f"{read.source}: training.friction_drop: fitted starts from contact.friction_drop (mu_s / mu_k - 1), "
            "which must then be > 0 (a guess such as 0.3)"
        )
    return choice


def _friction_models(read: ParameterReader) -> tuple[str, ...]:
    """training.friction_models: the friction models stage 1 calibrates in turn for the data to choose."""
    key = "training.friction_models"
    models = _names(read, key)
    unknown = [m for m in models if m not in FRICTION_MODELS]
    if unknown:
        raise ConfigError(f"{read.source}: {key}: {unknown[0]!r} is not one of {', '.join(FRICTION_MODELS)}")
    return tuple(dict.fromkeys(models))


def _effects(read: ParameterReader, flat: Mapping[str, Any], lead: float = 0.0) -> Effects:
    """The `effects.*` section: `active` names, `user.<name>` dotted paths, `<name>.<parameter>` values. A
    clocked effect's `release` (s after the onset, as `amb_release`'s) starts at `lead` (`drop_detection.lead`:
    the record starts that long before the free fall, so the AMB lets go about then); a lead needs a clocked
    force effect, or the model's rotor would fall from the record's start while the AMB still holds it."""
    active = read._get("effects.active", [])
    if (
        not isinstance(active, list)
        or not all(isinstance(n, str) and n for n in active)
        or len(set(active)) < len(active)
    ):
        raise ConfigError(f"{read.source}: parameter 'effects.active' must be a list of distinct effect names")
    user = {k.removeprefix("effects.user."): read.text(k, "") for k in flat if k.startswith("effects.user.")}
    reserved = sorted(set(active) & {"active", "user", "when"})
    if reserved:
        raise ConfigError(f"{read.source}: effects.active: {', '.join(reserved)} is a reserved key, not an effect name")
    when = _effect_when(read, flat)
    try:
        chosen = [effects_library.resolve(user.get(name, name), name=name, when=when.get(name, "")) for name in active]
    except (ValueError, ImportError, AttributeError) as error:
        raise ConfigError(f"{read.source}: effects.active: {error}") from None
    if lead > 0.0 and not any(e.clocked and e.kind == effects_library.FORCE for e in chosen):
        raise ConfigError(
            f"{read.source}: drop_detection.lead = {lead:g} s starts each record in levitation, where the AMB still "
            "holds the rotor: switch on its force (effects.active: [amb_release], with rig.amb_stiffness, "
            "rig.amb_damping and rig.amb_unbalance_compensation as the controller has them) or set the lead to 0"
        )
    values = {}
    for effect in chosen:
        defaults = effect.defaults()
        if effect.clocked and "release" in defaults:
            defaults["release"] = lead
        values[effect.name] = {
            parameter: read.number(f"effects.{effect.name}.{parameter}", default)
            for parameter, default in defaults.items()
        }
    stray = sorted(
        k
        for k in flat
        if k.startswith("effects.") and k not in read.used and not k.startswith(("effects.user.", "effects.when."))
    )
    if stray:
        raise ConfigError(
            f"{read.source}: parameter(s) {', '.join(stray)} belong to no active effect "
            f"(active: {', '.join(active) or 'none'})"
        )
    return Effects(tuple(chosen), tuple(values[e.name] for e in chosen))


def _effect_when(read: ParameterReader, flat: Mapping[str, Any]) -> dict[str, str]:
    """effects.when.<effect>: <condition>: the effect acts only in bags whose condition.<condition> is true."""
    active = flat.get("effects.active", [])
    when = {k.removeprefix("effects.when."): read.text(k, "") for k in flat if k.startswith("effects.when.")}
    unknown = sorted(set(when) - set(active))
    if unknown:
        raise ConfigError(f"{read.source}: effects.when.{unknown[0]}: '{unknown[0]}' is not in effects.active")
    return when


def _node_settings(read: ParameterReader) -> NodeSettings:
    """The optional `node.*` section (defaults of NodeSettings for what is absent)."""
    d = NodeSettings()
    return NodeSettings(
        coefficients=read.text("node.coefficients", d.coefficients, allow_empty=True),
        executor=read.choice("node.executor", d.executor, EXECUTORS),
        input_reliability=read.choice("node.input_reliability", d.input_reliability, RELIABILITIES),
        input_depth=read.integer("node.input_depth", d.input_depth),
        batch_topic=read.text("node.batch_topic", d.batch_topic),
        output_mode=read.choice("node.output_mode", d.output_mode, OUTPUT_MODES),
        batch_output_topic=read.text("node.batch_output_topic", d.batch_output_topic),
        output_reliability=read.choice("node.output_reliability", d.output_reliability, RELIABILITIES),
        output_depth=read.integer("node.output_depth", d.output_depth),
        flush_period=read.number("node.flush_period", d.flush_period, positive=True),
        flush_samples=read.integer("node.flush_samples", d.flush_samples),
        receive=read.choice("node.receive", d.receive, RECEIVE_MODES),
        realtime_priority=read.integer("node.realtime_priority", d.realtime_priority, minimum=0, maximum=99),
        chunk_sizes=read.integers("node.chunk_sizes", d.chunk_sizes),
        diagnostics_period=read.number("node.diagnostics_period", d.diagnostics_period, positive=True),
        alarm_force=read.number("node.alarm_force", d.alarm_force, positive=True),
        sensor_range=read.number("node.sensor_range", d.sensor_range, positive=True),
        millimetre_limit=read.number("node.millimetre_limit", d.millimetre_limit, positive=True),
        grid_tolerance=read.number("node.grid_tolerance", d.grid_tolerance, positive=True),
        max_gap=read.number("node.max_gap", d.max_gap, positive=True),
        bridge_gap=read.number("node.bridge_gap", d.bridge_gap, non_negative=True),
        rail_samples=read.integer("node.rail_samples", d.rail_samples, minimum=2),
        resync_after=read.integer("node.resync_after", d.resync_after),
        relevitation_band=read.number("node.relevitation_band", d.relevitation_band, positive=True),
        relevitation_window=read.number("node.relevitation_window", d.relevitation_window, positive=True),
        conditions=_names(read, "node.conditions"),
    )


def _names(read: ParameterReader, key: str) -> tuple[str, ...]:
    value = read._get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"{read.source}: parameter '{key}' must be a list of names")
    return tuple(value)
