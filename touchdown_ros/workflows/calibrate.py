"""Stage 1 of `touchdown train`: identify the rig's contact law, constants f0, Q and effect values
from displacement-only bags (core.calibration), with standard errors from the loss curvature."""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from touchdown_ros.core.calibration import (
    CLEARANCE_NAMES,
    CLEARANCE_UNIT,
    HELD_BY_PRIOR,
    RIGID_LOG_SUPPORT,
    STRIBECK_NAMES,
    SUPPORT_NAMES,
    Coordinates,
    Stage1,
    clearance_width,
    convert_guess,
    data_scales,
    effect_coordinates,
    effect_scales,
    filtered_states,
    fit_starts,
    log_nominal,
    log_stribeck_of,
    log_support_of,
    posterior_covariance,
    sensor_noise,
    stage1_flags,
    stage1_gauss_newton,
    stage1_gauss_newton_over,
    stage1_model_and_noise,
    stage1_start,
    stage1_value,
    stage1_value_and_grad,
    stage1_value_and_grad_over,
    stage1_value_over,
    standard_errors_and_correlation,
    strongest_correlations,
    support_law,
)
from touchdown_ros.core.dynamics import normal_force
from touchdown_ros.core.effects import Effects
from touchdown_ros.core.orbit import describe_starts, effects_from_orbits
from touchdown_ros.core.selection import COLLINEAR_MARGIN
from touchdown_ros.core.training import Batch, sample_errors, with_state_size
from touchdown_ros.core.types import EXACT_PAIR, PARAMETER_NAMES, STATE_SIZE, ContactLaw, FilterNoise, Model, Nominal
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.ahead import Ahead
from touchdown_ros.workflows.optimise import (
    DIVERGED_LOSS,
    Convergence,
    DivergedError,
    TrainingError,
    gauss_newton,
    minimise,
    minimise_from_each,
    require_convergence,
)
from touchdown_ros.workflows.progress import STDERR
from touchdown_ros.workflows.training_data import (
    TrainingData,
    note_ungated,
    record_mesh,
    training_batch,
    training_chunks,
)

#: `Ahead` names of the refinement's and the standard errors' program (`stage1_gauss_newton`) and of stage 1's
#: loss alone (`stage1_value`, for the support's start grid and the restarts, as the laws are screened).
GAUSS_NEWTON_PROGRAM = "stage 1's refinement and standard errors"
LOSS_PROGRAM = "stage 1's loss"
#: With a spinning ring, the refinement's loss alone (its trial points and restarts) and, refined by L-BFGS, its
#: loss-and-gradient: the ring's speed a state, other programs than the screening's (the ring turning with the rotor).
RING_RESTART_PROGRAM = "stage 1's loss with the ring's speed"
RING_REFINEMENT_PROGRAM = "stage 1's refinement with the ring's speed"
#: Tolerance to which stage 1 fits each candidate contact law before the finalists are refined.
SCREEN_TOLERANCE = 1.0e-4
#: Criterion (AIC or BIC) behind the best screened candidate within which a candidate is refined too before one is
#: chosen: a screening step stops once a step gains less than SCREEN_TOLERANCE of the loss, which
#: on a few thousand samples is about one criterion unit per step, so close screened scores do not decide.
FINALIST_MARGIN = 20.0
#: Criterion behind the best screened candidate within which the best screened fit of each other contact law is
#: refined too. The laws are screened with a simpler model than the one refined (with a spinning ring, the ring
#: turning with the rotor), and refining moves the criterion by far more than FINALIST_MARGIN: on a rig drawn at
#: random with a Hunt-Crossley n = 10/9 contact the screening put that law 37 behind the linear one, refined it
#: was 54 ahead and its radial peaks within 3 % where the linear law's missed by 11-14 %
#: (docs/calibration.md, "Eight rigs drawn at random"). The paper's campaign screens its laws 500 and more apart.
LAW_FINALIST_MARGIN = 100.0


@dataclass(frozen=True)
class Calibration:
    """Stage 1's result: the rig's contact law, constants, filter noise and effect values."""

    config: Config  # the rig with the calibrated law, f0 and noise (kernel: the YAML's until stage 2 places it)
    effects: Effects
    guess: Nominal  # the starting point, in the chosen law's units
    relative_sd: dict[str, float]  # posterior sd of ln(value): ~ the relative standard error
    held_by_prior: tuple[str, ...]  # parameters the data hardly inform (posterior sd >= HELD_BY_PRIOR prior sd)
    correlations: tuple[tuple[str, str, float], ...]  # strongest correlations of the stage-1 estimates
    convergence: Convergence
    candidates: tuple[dict[str, Any], ...]  # every law x support screened: label, loss, criterion above the best, steps
    sensor_noise: np.ndarray  # (3,) m, per axis, from the levitated samples
    criterion: float = 0.0  # the chosen fit's information criterion (AIC or BIC, up to a constant of the bags)
    # with several `training.friction_models`: each one's fit (friction, law, loss, criterion above the best, s)
    frictions: tuple[dict[str, Any], ...] = ()
    clearance_sd: dict[str, float] = dataclasses.field(default_factory=dict)  # m, posterior sd of r0 and z0
    # with a fitted Stribeck drop: the stage 1 without it whose process noise this one holds (`calibrate_stage1`)
    process_noise_pass: dict[str, Any] | None = None
    # with `training.friction_start: both`: per refined law, both starts' final losses and which was kept
    friction_starts: tuple[dict[str, Any], ...] = ()
    # with `train --start` adding effects: per refined law, the refined losses from the start the screening preferred
    # and from the other start (its label), and which was kept
    effect_starts: tuple[dict[str, Any], ...] = ()

    def clearance_changes(self) -> dict[str, float]:
        """m, the calibrated r0 and z0 minus the rig YAML's (empty where they were not fitted)."""
        if self.config.clearances is None:
            return {}
        calibrated = self.config.contact_rig
        return {n: float(getattr(calibrated, n)) - float(getattr(self.config.rig, n)) for n in CLEARANCE_NAMES}

    def summary(self) -> dict[str, Any]:
        """Plain data for the coefficient file, with the notes `train` prints (`notes`)."""
        nominal = self.config.nominal
        return {
            "law": self.config.law.label,
            "friction": self.config.law.friction,
            "guess": {k: float(v) for k, v in self.guess._asdict().items()},
            "prior_width": float(self.config.training.prior_width),  # sd of ln f0 around the guess
            "calibrated": {k: float(v) for k, v in nominal._asdict().items()},
            "relative_standard_error": {k: round(v, 6) for k, v in self.relative_sd.items()},
            **({"clearances_m": {n: {"calibrated": float(getattr(self.config.contact_rig, n)),
                                     "yaml": float(getattr(self.config.rig, n)),
                                     "standard_error": self.clearance_sd.get(n)}
                                 for n in CLEARANCE_NAMES}} if self.config.clearances is not None else {}),
            "held_by_prior": list(self.held_by_prior),
            "strongest_correlations": [[a, b, round(r, 4)] for a, b, r in self.correlations],
            "sensor_noise_m": [float(v) for v in self.sensor_noise],
            "candidates": list(self.candidates),
            **({"friction_models": list(self.frictions)} if self.frictions else {}),
            **({"process_noise_pass": self.process_noise_pass} if self.process_noise_pass else {}),
            **({"friction_starts": list(self.friction_starts)} if self.friction_starts else {}),
            **({"effect_starts": list(self.effect_starts)} if self.effect_starts else {}),
            "notes": self.notes(),
            **self.convergence.as_dict(),
        }

    def notes(self) -> list[str]:
        """What the bags left open, in words (`law_note`, `support_note`, `friction_note`): `train` prints
        them and the coefficient file keeps them."""
        notes = (self.law_note(), self.support_note(), self.friction_note())
        return [note for note in notes if note is not None]

    def law_note(self) -> str | None:
        """The contact laws whose refined fits the bags hardly tell from the chosen one (within
        UNDECIDED_CRITERION of it), and how to give the bearing's; None when the data choose."""
        chosen = self.config.law.setting
        behind: dict[str, float] = {}
        for c in self.candidates:
            margin = c.get("refined_criterion_above_best")
            if margin is not None and c["contact_law"] != chosen and margin < UNDECIDED_CRITERION:
                behind[c["contact_law"]] = min(margin, behind.get(c["contact_law"], margin))
        if not behind:
            return None
        closest = sorted(behind, key=behind.get)
        rivals = ", ".join(f"{law} ({abs(behind[law]):.2g} {'behind' if behind[law] >= 0 else 'ahead'})"
                           for law in closest)
        return (
            f"contact law: these bags hardly tell {chosen} from {rivals} by the information criterion; "
            "where the bearing's is known, give it (balls: hertz:1.5, rollers: hertz:1.111), "
            f"e.g. -p 'training.contact_laws:=[{closest[0]}]'"
        )

    def friction_note(self) -> str | None:
        """Where the friction came out at `training.friction_ceiling`, that a missing force likely pushed it there;
        where above any bearing contact's (`HIGH_FRICTION`), that it has likely taken up a force the model lacks
        and how to find it; where the paper's friction (the inner ring at rest) came out at hardly any, that a
        freely turning inner ring is the likelier reading and the setting that models it; None otherwise."""
        nominal = self.config.nominal
        ceiling = self.config.training.friction_ceiling
        if friction_at_ceiling(nominal, ceiling):
            return (
                f"friction: mu {float(nominal.mu):.2g} and k_ZR {float(nominal.k_ZR):.2g}, held at "
                f"training.friction_ceiling ({ceiling:g}): the fit would have gone higher, so a force the model lacks "
                "has likely pushed it there; `touchdown diagnose BAGS --coeffs FILE` (with the same ceiling) names "
                "such an effect"
            )
        if friction_above_any_bearings(nominal):
            bore = (" (against a spinning ring the bore's friction opposes axial sliding, so a large mu acts as an "
                    "axial force in radial contact, as a contact angle or an axial thrust would)"
                    if self.config.law.spins_ring else "")
            said = (
                f"friction: mu {float(nominal.mu):.2g} and k_ZR {float(nominal.k_ZR):.2g}, above any bearing contact's "
                f"(dry steel or ceramic on steel slides at 0.1-0.3; above {HIGH_FRICTION:g} is implausible): the "
                f"friction has likely taken up a force the model lacks{bore}. "
            )
            if self.effects:
                return said + (
                    f"With {', '.join(self.effects.names)} switched on it is still that high: another force may be "
                    "missing, or an active effect's form may differ from the rig's and the friction make up the "
                    "difference (then its fitted size is not to be trusted); `touchdown diagnose BAGS --coeffs FILE` "
                    "ranks what is left"
                )
            return said + (
                "`touchdown diagnose BAGS --coeffs FILE` names such an effect, and training with it switched on "
                "(`touchdown train BAGS --start FILE -p 'effects.active:=[NAME]'`) fits the friction again beside it"
            )
        if self.config.law.friction != "paper" or largest_friction(nominal) >= LOW_FRICTION:
            return None
        ring = next((f for f in self.frictions if f["friction"] == "spinning_ring"), None)
        if ring is not None:
            return (
                f"friction: mu {float(nominal.mu):.2g} and k_ZR {float(nominal.k_ZR):.2g}, far below a dry or "
                f"boundary-lubricated contact's (from {LOW_FRICTION:g} up); a spinning ring's friction fitted these "
                f"bags worse ({ring['criterion_above_best']:.4g} behind by the information criterion)"
            )
        return (
            f"friction: mu {float(nominal.mu):.2g} and k_ZR {float(nominal.k_ZR):.2g}, far below a dry or "
            f"boundary-lubricated contact's (from {LOW_FRICTION:g} up): the paper's friction acts against the rotor's "
            "spin as on an inner ring at rest, and these bags do not show that force. A freely turning inner ring, "
            "spun up by the first contacts, exerts little of it, and the contact damping may then come out high, "
            "making up for the friction the model lacks; where the ring turns freely, "
            "-p contact.friction:=spinning_ring models its speed (training takes two to three times as long), and "
            "-p 'training.friction_models:=[paper, spinning_ring]' lets the bags choose"
        )

    def support_note(self) -> str | None:
        """What the bags tell of a fitted yielding axial support, and how to pin what they do not; where the
        chosen law's fit with the other support (rigid or yielding) comes within UNDECIDED_CRITERION, that
        the bags hardly tell the two apart; None when the support is given, or rigid and so chosen."""
        law = self.config.law
        rival, apart = self._support_rival() or (None, None)
        if rival is None and (not law.yields or not all(n in self.relative_sd for n in SUPPORT_NAMES)):
            return None
        if not law.yields:
            preload, span = (rival[n] for n in SUPPORT_NAMES)
            return (
                f"axial support: these bags hardly tell a rigid support from one yielding above {preload / 1e3:.3g} kN "
                f"and passing at most {(preload + span) / 1e3:.3g} kN ({apart:.2g} "
                f"behind by the information criterion); a rigid one is assumed. {GIVE_THE_MOUNT}"
            )
        preload, span = float(law.support_preload), float(law.support_span)
        sd_preload, sd_span = (self.relative_sd[n] for n in SUPPORT_NAMES)
        note = (
            f"axial support: yields above {preload / 1e3:.3g} kN ({_uncertainty(sd_preload)}) and passes at most "
            f"{(preload + span) / 1e3:.3g} kN (the span {span / 1e3:.3g} kN, {_uncertainty(sd_span)})"
        )
        unpinned = max(sd_preload, sd_span) >= UNPINNED_LOG_SD
        if rival is not None:
            note += (f"; these bags hardly tell it from a rigid support ({abs(apart):.2g} "
                     f"{'behind' if apart > 0 else 'ahead'} by the information criterion)")
            if apart <= 0:
                note += ", and the yielding one is kept: it contains the rigid one as its limit"
        if unpinned:
            note += (". These bags hardly tell how much force it passes above its knee, so the contact force's "
                     "band (/touchdown/contact_force_std) is wide there")
        return f"{note}. {GIVE_THE_MOUNT}" if unpinned or rival is not None else note

    def _refined(self, yields: bool) -> dict[str, Any] | None:
        """The refined candidate of the chosen contact law with a yielding or a rigid support, if any."""
        return next((c for c in self.candidates if c.get("refined_criterion_above_best") is not None
                     and c["contact_law"] == self.config.law.setting and c.get("yields") == yields), None)

    def _support_rival(self) -> tuple[dict[str, Any], float] | None:
        """The refined candidate of the chosen contact law with the other support and its criterion above the
        chosen fit's (negative: ahead), if within UNDECIDED_CRITERION of it."""
        law = self.config.law
        chosen, rival = self._refined(law.yields), self._refined(not law.yields)
        if chosen is None or rival is None or (not law.yields and "support_preload" not in rival):
            return None
        apart = rival["refined_criterion_above_best"] - chosen["refined_criterion_above_best"]
        return (rival, apart) if abs(apart) < UNDECIDED_CRITERION else None


def measured_sensor_noise(config: Config, data: TrainingData, stream=STDERR) -> np.ndarray:
    """(3,) sensor noise sd (m) per axis, pooled over the bags' levitated samples; the YAML's
    filter.measurement_noise for an axis with too few of them (with a note)."""
    levitated = [samples for samples in data.levitated if len(samples) > 0]
    sigma = sensor_noise(np.concatenate(levitated)) if levitated else np.full(3, np.nan)
    fallback = np.sqrt(np.asarray(config.noise.measurement))
    if np.isnan(sigma).any():
        print(
            "note: too few levitated samples before the drops to measure the sensor noise; "
            "using filter.measurement_noise",
            file=stream,
        )
    return np.where(np.isnan(sigma), fallback, sigma)


def _per_bag_losses(model: Model, noise: FilterNoise, h: float, batch: Batch, kind: str) -> np.ndarray:
    return np.asarray(jax.jit(lambda b: jnp.sum(sample_errors(model, noise, h, b, kind), axis=1))(batch))


def after_restart(first: Convergence, again: Convergence, restart: str, cap: int) -> Convergence:
    """One fit's convergence from its run before a restart (`restart`: what restarted it) and the run after it:
    both runs' steps, evaluations, seconds and loss histories, the reason saying how the steps add up."""
    return first.then(
        again,
        f"{again.reason}; {first.steps} steps before a {restart} restart and {again.steps} after it, "
        f"at most {cap} each",
    )


def calibrate(config: Config, data: TrainingData, ahead: Ahead, stream=STDERR, hold_q: bool = False) -> Calibration:
    """Stage 1 (core.calibration): for each candidate contact law, rigid and with a yielding axial
    support, fit f0, the Q factors (unless `hold_q`: the config's process noise as it is), the effects'
    parameters (and the support's) from the YAML's guess; keep the candidate with the lowest information
    criterion (`training.search`). The loss alone's and the standard errors' programs (and with a spinning
    ring the refinement's) are compiled in `ahead`'s background thread while the laws are fitted."""
    settings = config.training
    config = started_from_orbits(config, data, stream)
    sigma = measured_sensor_noise(config, data, stream)
    print(
        "sensor noise from the levitated samples: " + ", ".join(f"{a} {v * 1e6:.2f} um" for a, v in zip("xyz", sigma)),
        file=stream,
    )
    noise = config.noise._replace(measurement=jnp.asarray(sigma**2))
    h, kind, mesh = config.sample_period, settings.loss, record_mesh()
    thorough = settings.search == "thorough"
    criterion = aic if thorough else bic
    effects = config.effects
    # The contact laws are screened on a few records (one chunk), then refined on all of them chunk by
    # chunk: batches of one shape, so one compiled program serves the whole of stage 1.
    screen_data, screen_batch, chunks = stage1_batches(config, data, effects)
    note_ungated(effects, chunks, stream)
    scales = start_scales(config.model(), noise, h, chunks)
    n_valid = int(sum(np.sum(np.asarray(chunk.valid)) for chunk in chunks))
    fit_q = kind == "nll" and not hold_q
    fit_clearances = settings.clearance_tolerance > 0.0
    fit_stribeck = config.fits_stribeck_drop
    clearance_prior_sd = clearance_width(settings.clearance_tolerance)

    # Fitted coordinates: f0, the Q factors (nll only) and the effects' parameters, not their gates; the
    # support rigid or as given (held), or yielding (free).
    given = settings.axial_support == "given"  # then the candidate laws carry the YAML's support
    held_support = log_support_of(config.law) if given else RIGID_LOG_SUPPORT
    log_stribeck = jnp.asarray(log_stribeck_of(config.law)) if fit_stribeck else None
    start = stage1_start(jnp.zeros(len(PARAMETER_NAMES)), effects, scales, jnp.asarray(held_support), log_stribeck)

    def flags(support: bool) -> Stage1:
        """The free coordinates of a candidate: f0, Q (nll), the effects, the clearances, the Stribeck drop
        (training.friction_drop: fitted), the support if `support`."""
        return stage1_flags(effects, fit_q, fit_support=support, fit_clearances=fit_clearances,
                            fit_stribeck=True if fit_stribeck else None)

    coordinates = start_coordinates = Coordinates(start, flags(support=False))

    def law_model(law: ContactLaw) -> Model:
        return config.model()._replace(law=law)

    # The refinement's tangents are padded to the most coordinates a candidate frees (with a yielding
    # support), so one program, compiled while the laws are screened, serves every finalist and the
    # chosen one's standard errors.
    most_free = len(Coordinates(start, flags(support=True)).names)
    initial_theta = start_coordinates.theta(start_coordinates.initial())
    guess_log = jnp.asarray(log_nominal(config.nominal))
    static = dict(prior_width=settings.prior_width, h=h, kind=kind, mesh=mesh, clearance_width=clearance_prior_sd)
    chunk_weight = dict(prior_weight=1.0 / len(chunks), **static)
    by_gauss_newton = settings.refinement == "gauss_newton"
    (ahead.compile_first if by_gauss_newton else ahead.compile)(  # Gauss-Newton's: needed before stage 2's
        GAUSS_NEWTON_PROGRAM, stage1_gauss_newton, initial_theta, start_coordinates.directions(most_free), guess_log,
        law_model(settings.contact_laws[0]), noise, scales, chunks[0], **chunk_weight,
    )

    # With the ring's speed as a state the loss far from the rig's constants is rough (the ring sticks
    # and slips as they move): the laws are screened with the ring turning with the rotor (its speed
    # no state), a smooth loss, and the chosen one refined with the ring's state from there.
    spinning = config.law.spins_ring
    screen_noise = noise._replace(process=noise.process[:STATE_SIZE], initial=noise.initial[:STATE_SIZE])
    if spinning:
        print("contact laws screened with the ring turning with the rotor, refined with its speed as a state",
              file=stream)

    def screening(law: ContactLaw) -> ContactLaw:
        return law.with_friction("co_rotating_ring", law.slip_velocity) if spinning else law

    def screened_records(batch: Batch) -> Batch:
        return with_state_size(batch, STATE_SIZE) if spinning else batch

    def describe(x: np.ndarray) -> str:
        """f0 (the first free coordinates), the support when its two are free too (before the clearances), the
        clearances' changes and the Stribeck drop (the last ones, when fitted)."""
        text = "  " + "  ".join(f"{n} {v:.3g}" for n, v in zip(PARAMETER_NAMES, np.exp(x[: len(PARAMETER_NAMES)])))
        clearances = len(CLEARANCE_NAMES) if fit_clearances else 0
        stribeck = len(STRIBECK_NAMES) if fit_stribeck else 0
        end = len(x) - stribeck
        if len(x) == len(start_coordinates.names) + len(SUPPORT_NAMES):
            support = x[end - clearances - len(SUPPORT_NAMES): end - clearances]
            text += "  " + "  ".join(f"{n} {np.exp(c):.3g}" for n, c in zip(SUPPORT_NAMES, support))
        if clearances:
            text += "  " + "  ".join(
                f"{n} {c * CLEARANCE_UNIT * 1e6:+.1f} um" for n, c in zip(CLEARANCE_NAMES, x[end - clearances: end])
            )
        if stribeck:
            text += "  " + "  ".join(f"{n} {np.exp(c):.3g}" for n, c in zip(STRIBECK_NAMES, x[end:]))
        return text

    def bounds_of(coordinates: Coordinates) -> list[tuple[float, float]]:
        """The coordinates' bounds, the friction's below `training.friction_ceiling`."""
        return friction_capped(coordinates.bounds(scales), coordinates.names, settings.friction_ceiling)

    newton_terms: dict[tuple, Any] = {}  # Gauss-Newton's terms on all records by (law, coordinates, x)

    def problem(
        law: ContactLaw, records: tuple[Batch, ...], coordinates: Coordinates = coordinates, screened: bool = False
    ) -> Problem:
        """One contact law's `Problem` on the chunks `records` (`screened`: as the laws are screened)."""
        guess = convert_guess(config.nominal, config.law, law, settings.reference_deformation)
        guess_log = jnp.asarray(log_nominal(guess))
        records = tuple(map(screened_records, records)) if screened else records
        base = law_model(screening(law) if screened else law)
        arguments = (guess_log, base, screen_noise if screened else noise, scales)
        return Problem(
            coordinates.objective(lambda theta: stage1_value_and_grad_over(records, theta, *arguments, **static)),
            coordinates.loss(lambda theta: stage1_value_over(records, theta, *arguments, **static)),
            coordinates.initial(log_f0=guess_log),
            arguments,
        )

    def refine(
        law: ContactLaw, coordinates: Coordinates, x: np.ndarray, label: str, tolerance: float = settings.tolerance,
        records: tuple[Batch, ...] = chunks,
    ) -> tuple[np.ndarray, Convergence]:
        """`law` with `coordinates` fitted on `records` (all by default) from x (`training.refinement`:
        `gauss_newton`, or `minimise`'s L-BFGS)."""
        refined, bounds = problem(law, records, coordinates), bounds_of(coordinates)
        if not by_gauss_newton:
            return minimise(refined.objective, x, settings.calibration_steps, tolerance, label, stream, describe,
                            bounds=bounds)
        directions = coordinates.directions(most_free)
        precision = 1.0 / coordinates.prior_sd(settings.prior_width, clearance_prior_sd) ** 2
        samples = int(sum(np.sum(np.asarray(batch.valid)) for batch in records))

        def terms(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
            """J, its gradient and its Gauss-Newton Hessian at x (the information kept for the standard errors)."""
            got = stage1_gauss_newton_over(records, coordinates.theta(x), directions, *refined.arguments, **static)
            if records is chunks:
                newton_terms[(law.label, coordinates.start.tobytes(), x.tobytes())] = got
            free = len(x)
            return got.value, got.gradient[:free], 2.0 * (got.information[:free, :free] + np.diag(precision)) / samples

        def by_lbfgs(x: np.ndarray, steps: int) -> tuple[np.ndarray, Convergence]:
            ahead.wait(RING_REFINEMENT_PROGRAM)  # with a spinning ring (else none is queued)
            return minimise(refined.objective, x, steps, tolerance, f"{label}, L-BFGS", stream, describe, bounds=bounds)

        return gauss_newton(terms, refined.loss, x, settings.calibration_steps, tolerance, label, stream, describe,
                            bounds=bounds, fallback=by_lbfgs)

    def support_grid(law: ContactLaw, theta: Stage1, records: Batch) -> list[np.ndarray]:
        """ln preload and ln span (N) where a yielding support of `law` may start under theta's constants
        (`support_starts` on the screening's model of `records`); none without axial contact."""
        screened_model = stage1_model_and_noise(theta, law_model(screening(law)), screen_noise, scales)
        return support_starts(config.law, *screened_model, h, screened_records(records))

    def with_support_at(coordinates: Coordinates, theta: Stage1, log_support) -> np.ndarray:
        """The free coordinates of theta's constants (f0, Q, effects) with the support `log_support`."""
        return coordinates.initial(log_f0=theta.log_f0, log_q=theta.log_q, effects=theta.effects,
                                   log_support=jnp.asarray(log_support), clearance=theta.clearance,
                                   log_stribeck=theta.log_stribeck)

    def fit_support(law: ContactLaw, records: Batch, theta_rigid: Stage1, tolerance: float, label: str):
        """(coordinates, x, convergence) of `law` with a yielding axial support fitted on `records`
        from the rigid fit theta_rigid: the best of a grid of supports, then all coordinates
        together; None without axial contact."""
        starts = support_grid(law, theta_rigid, records)
        if not starts:
            return None
        with_support = Coordinates(
            start._replace(log_support=jnp.asarray(starts[0])), flags(support=True)
        )
        supported = problem(law, (records,), with_support, screened=True)
        x0 = min((with_support_at(with_support, theta_rigid, s) for s in starts), key=supported.loss)
        x, convergence = minimise(
            supported.objective, x0, settings.calibration_steps, tolerance, label, stream, describe,
            bounds=bounds_of(with_support),
        )
        return with_support, x, convergence

    def from_new_effects_alone(
        law: ContactLaw, objective: Callable, x0: np.ndarray, fit: tuple[np.ndarray, Convergence]
    ) -> tuple[tuple[np.ndarray, Convergence], tuple[str, np.ndarray]]:
        """The screening's fit `fit` from x0 and the same fit from x0 with `training.effects_alone_first` (the
        effects `train --start` adds) fitted alone first, the start file's calibration held: the one that ends lower,
        and the other's label and end, which is refined too (`from_the_other_start`). Moved together from the file's
        values, the constants' steep directions set the first steps' length and the fit can stop, converged by the
        loss's change, before a new effect has moved (a hidden x sensor offset with the AMB's term and a lead: 0.2 %
        of the truth); but where the file's constants took up the effect (a hidden z gain: mu 2.0), the effect alone
        moves too far. The screened losses did not always rank them as the refined ones do (a hidden drag:
        2026-12-06, docs/workbench.md)."""
        names = settings.effects_alone_first
        alone = effect_coordinates(coordinates.theta(x0), names)
        label = f"calibrate {law.label}, {', '.join(names)} alone"
        x_alone, _ = minimise_from_each(  # from the file's values and each further start of the new effects
            problem(law, (screen_batch,), alone, screened=True).objective, fit_starts(alone, scales, names),
            settings.calibration_steps, screen_tolerance, label, stream, bounds=bounds_of(alone),
        )
        other = minimise(
            objective, coordinates.initial(**alone.theta(x_alone)._asdict()), settings.calibration_steps,
            screen_tolerance, f"{label} first", stream, describe, bounds=bounds_of(coordinates),
        )
        alone_lower = other[1].final_loss < fit[1].final_loss
        print(f"[{label} first] its fit ends at {other[1].final_loss:.7g}, the fit from the file's values at "
              f"{fit[1].final_loss:.7g}; both are refined", file=stream, flush=True)
        start_alone = (f"{', '.join(names)} alone first", other[0])
        start_file = ("the file's values", fit[0])
        return (other, start_file) if alone_lower else (fit, start_alone)

    # Screen every candidate law, rigid and with a yielding axial support (training.axial_support), to
    # a loose tolerance on a few bags; refine the one of the lowest criterion on all.
    if len(screen_data.paths) < len(data.paths):
        print(f"contact laws screened on {len(screen_data.paths)} of the {len(data.paths)} bags", file=stream)
    n_screen = int(np.sum(np.asarray(screen_batch.valid)))
    screen_tolerance = max(settings.tolerance, SCREEN_TOLERANCE)
    screened: list[Candidate] = []
    if spinning:  # needed once the laws are screened (the refinement's trial points), before stage 2's
        refinement = (initial_theta, guess_log, law_model(settings.contact_laws[0]), noise, scales, chunks[0])
        ahead.compile_first(RING_RESTART_PROGRAM, stage1_value, *refinement, **chunk_weight)
        # L-BFGS's: the refinement's own, or (after the others) where Gauss-Newton stalls
        (ahead.compile if by_gauss_newton else ahead.compile_first)(
            RING_REFINEMENT_PROGRAM, stage1_value_and_grad, *refinement, **chunk_weight
        )
    ahead.compile_first(  # needed first: the support's start grid and the restarts after the first law's fit
        LOSS_PROGRAM, stage1_value, initial_theta, guess_log, law_model(screening(settings.contact_laws[0])),
        screen_noise, scales, screened_records(screen_batch), prior_weight=1.0, **static,
    )
    ahead.start()  # the first law's fit compiles stage 1 now, beside them
    for law in settings.contact_laws:
        objective, loss, x0, _ = problem(law, (screen_batch,), screened=True)
        x, convergence = minimise(
            objective, x0, settings.calibration_steps, screen_tolerance, f"calibrate {law.label}", stream, describe,
            bounds=bounds_of(coordinates),
        )
        if convergence.initial_loss >= DIVERGED_LOSS:
            model0, noise0 = stage1_model_and_noise(
                coordinates.theta(x0), law_model(screening(law)), screen_noise, scales
            )
            paths = screen_data.paths
            losses = _per_bag_losses(model0, noise0, h, screened_records(screen_batch), kind)[: len(paths)]
            bad = [str(p) for p, v in zip(paths, losses) if not np.isfinite(v)] or [str(p) for p in paths]
            raise DivergedError(
                f"{', '.join(bad)}: the filter diverges with the guessed contact constants ({law.label}); "
                "give contact.* closer to the bearing's (a data sheet's stiffness within 5x) or check the bag"
            )
        other_start = None
        if settings.effects_alone_first:
            (x, convergence), other_start = from_new_effects_alone(law, objective, x0, (x, convergence))
        ahead.wait(LOSS_PROGRAM)
        restart = damping_restart(
            loss, coordinates.names, x, convergence.final_loss, stream, lambda J: criterion(J, 0, n_screen, kind)
        ) if thorough else None
        if restart is not None:
            x, again = minimise(
                objective, restart, settings.calibration_steps, screen_tolerance,
                f"calibrate {law.label}, restarted", stream, describe, bounds=bounds_of(coordinates),
            )
            convergence = after_restart(convergence, again, "damping", settings.calibration_steps)
        if settings.axial_support != "yielding":
            screened.append(Candidate(
                criterion(convergence.final_loss, 0, n_screen, kind), law, coordinates, x, convergence,
                other_start=other_start,
            ))
        if settings.axial_support in ("auto", "yielding"):
            fitted = fit_support(
                law, screen_batch, coordinates.theta(x), screen_tolerance, f"calibrate {law.label} + yielding support"
            )
            if fitted is not None:
                with_support, x_s, convergence_s = fitted
                score = criterion(convergence_s.final_loss, len(SUPPORT_NAMES), n_screen, kind)
                supported_other = None if other_start is None else (  # its constants with this fit's support
                    other_start[0], with_support_at(
                        with_support, coordinates.theta(other_start[1]), with_support.theta(x_s).log_support
                    ),
                )
                screened.append(Candidate(
                    score, law, with_support, x_s, convergence_s, yields=True, other_start=supported_other
                ))
    if not screened:
        raise TrainingError(
            f"{', '.join(map(str, data.paths))}: no axial contact in the training bags, so a yielding axial support "
            "cannot be fitted; set training.axial_support: auto or rigid"
        )
    screened.sort(key=lambda c: c.score)
    finalists = [c for c in screened if c.score - screened[0].score < FINALIST_MARGIN]
    if thorough:  # the best of each other law, where the screening's ranking of the laws cannot be trusted
        for c in screened:
            if c.score - screened[0].score < LAW_FINALIST_MARGIN and all(
                f.law.setting != c.law.setting for f in finalists
            ):
                finalists.append(c)

    def support_acts(c: Candidate) -> bool:
        """Whether the yielding candidate's own fit, its support made rigid, falls more than
        FINALIST_MARGIN behind it on the screening bags: its knee lies within their forces."""
        theta = c.coordinates.theta(c.x)._replace(log_support=jnp.asarray(RIGID_LOG_SUPPORT))
        rigid_loss = problem(c.law, (screen_batch,), screened=True).loss(coordinates.initial(**theta._asdict()))
        return criterion(rigid_loss, 0, n_screen, kind) - c.score > FINALIST_MARGIN

    # A yielding finalist whose support does not act on the screening bags is judged against its own
    # law rigid, refined alike: the support's fit goes on from the rigid screening fit's end, so on a
    # few bags it can win by the steps the rigid one stopped short of (soft_bearing: 88 ahead
    # screened, its impacts below any knee). Where the support acts, the rigid law is not refined.
    finalists += [
        c for c in screened
        if thorough and not c.yields and c not in finalists
        and any(f.yields and f.law == c.law and not support_acts(f) for f in finalists)
    ]
    if len(screened) > 1:
        print(
            f"contact laws by {criterion.__name__.upper()} (above the best): "
            + ", ".join(f"{c.name} {c.score - screened[0].score:.4g}" for c in screened)
            + "; refined: " + ", ".join(c.name for c in finalists),
            file=stream,
        )

    def support_restart(c: Candidate, refined: Sequence[Candidate]) -> Candidate:
        """A yielding fit refined once more from the support of the lowest loss on the start grid, under
        its own constants and, where it ended above its own law's rigid fit (which it contains as its
        limit), under the rigid fit's with its own support too; the lower of the two fits is kept. The
        knee and the span move the loss only through the impacts above the knee: a knee carried above
        every impact, or a span on a flat stretch, stays where the loss no longer moves it."""
        if not c.yields:
            return c
        theta_c = c.coordinates.theta(c.x)
        r = next((r for r in refined if not r.yields and r.law == c.law), None)
        below = r is not None and r.convergence.final_loss < c.convergence.final_loss
        loss = problem(c.law, chunks, c.coordinates).loss
        started, starts = time.perf_counter(), []
        for theta in (theta_c, r.coordinates.theta(r.x)) if below else (theta_c,):
            own = [theta_c.log_support] if theta is not theta_c else []
            grid = support_grid(c.law, theta, screen_batch)
            starts += [with_support_at(c.coordinates, theta, s) for s in (*own, *grid)]
        start_loss, start = min(((loss(x), x) for x in starts), key=lambda pair: pair[0])
        print(f"[support restart] {c.name}: the lowest loss of {len(starts)} starts on the support grid "
              f"{start_loss:.7g} against the fit's {c.convergence.final_loss:.7g}  "
              f"{time.perf_counter() - started:.1f} s elapsed", file=stream, flush=True)
        if start_loss >= c.convergence.final_loss:
            return c
        constants = f"its own or {r.name}'s constants" if below else "its own constants"
        x, convergence = refine(
            c.law, c.coordinates, start,
            f"calibrate {c.name}, refined from the support grid under {constants} (its loss {start_loss:.7g} "
            f"there, below {c.convergence.final_loss:.7g})",
        )
        if not convergence.converged or convergence.final_loss >= c.convergence.final_loss:
            return c
        score = criterion(convergence.final_loss, len(SUPPORT_NAMES), n_valid, kind)
        convergence = after_restart(c.convergence, convergence, "support grid", settings.calibration_steps)
        return c._replace(score=score, x=x, convergence=convergence)

    if spinning:
        ahead.wait(RING_RESTART_PROGRAM)
        if not by_gauss_newton:
            ahead.wait(RING_REFINEMENT_PROGRAM)
    if by_gauss_newton:
        ahead.wait(GAUSS_NEWTON_PROGRAM)

    # The refinement with the support held: on the screening's bags where they are fewer than all.
    screened_bags = len(screen_data.paths)
    held_records = chunks if screened_bags == len(data.paths) else (screen_batch,)
    held_on = "" if held_records is chunks else f" on the screening's {screened_bags} bag{'s' * (screened_bags > 1)}"

    def refine_finalist(c: Candidate, label: str, required: bool = True) -> Candidate | None:
        """A screened candidate refined on all records (a yielding one first with its support held, on
        `held_records`; with a spinning ring restarted from the friction grid where that lowers its loss); None
        where it does not converge and is not `required` (an extra start)."""
        x = c.x
        if c.yields and thorough:
            # The constants first, the support held at its screened knee: moved together, a constant
            # still far from its optimum (damping, on few bags) can carry the knee above every impact,
            # where the loss no longer depends on it and it stays. (By Gauss-Newton to the screening's tolerance:
            # the fit with the support free goes on from there, which takes fewer steps in all.) On the screening's
            # bags, where they are fewer than all: there its steps cost a chunk's evaluation, not every chunk's, and
            # the constants' long walks (the friction's, on the campaign) are walked there.
            held = Coordinates(c.coordinates.theta(c.x), flags(support=False))
            x_held, held_convergence = refine(
                c.law, held, held.initial(), f"calibrate {label}, refined with the support held{held_on}",
                screen_tolerance if by_gauss_newton else settings.tolerance, records=held_records,
            )
            x = c.coordinates.initial(**held.theta(x_held)._asdict())
        loss = problem(c.law, chunks, c.coordinates).loss
        x_start = x
        x, convergence = refine(c.law, c.coordinates, x, f"calibrate {label}, refined")
        stalled = convergence.steps == 0 and not convergence.converged
        names = c.coordinates.names
        restart = friction_restart(
            loss, names, x, convergence.final_loss, stream, ceiling=settings.friction_ceiling
        ) if spinning else None
        if restart is not None:
            x, again = refine(c.law, c.coordinates, restart, f"calibrate {label}, refined from the friction restart")
            convergence = after_restart(convergence, again, "friction", settings.calibration_steps)
            stalled = False
        if c.yields and thorough:
            if held_records is not chunks:
                # its losses are the screening bags', not the fit's on all: its steps, evaluations and seconds
                # count, its losses start the record at its end, on all records
                at_end = convergence.initial_loss
                held_convergence = dataclasses.replace(
                    held_convergence, initial_loss=at_end, final_loss=at_end, history=()
                )
            if stalled and held_convergence.converged:
                # No step from the held fit's end lowered the loss (the line search gave up there): that end
                # is where the support's coordinates, free, do not move it, so it stands.
                x, convergence = x_start, dataclasses.replace(
                    held_convergence,
                    reason=f"{held_convergence.reason}; then with the support free: {convergence.reason}",
                )
            else:
                held_steps = f"{held_convergence.steps} steps with the support held{held_on}"
                convergence = held_convergence.then(convergence, f"{convergence.reason}; after {held_steps}")
        if not (required or convergence.converged):
            return None
        require_convergence(convergence, f"stage 1 ({c.name})", data.paths, "-p training.calibration_steps:=N")
        score = criterion(convergence.final_loss, len(SUPPORT_NAMES) if c.yields else 0, n_valid, kind)
        return c._replace(score=score, x=x, convergence=convergence)

    def lower_refined(fit: Candidate, other: Candidate | None) -> Candidate:
        """`fit`, or `other` (a refinement from a second start; None: it did not converge) where it ends lower."""
        return fit if other is None or other.convergence.final_loss >= fit.convergence.final_loss else other

    def from_the_friction_grid(c: Candidate, fit: Candidate) -> Candidate:
        """`fit`, or the candidate refined from the restart grid's friction pair that lowers the loss on all
        records at its screened fit, where that ends lower (`training.friction_start: both`)."""
        loss = problem(c.law, chunks, c.coordinates).loss
        start = friction_restart(loss, c.coordinates.names, c.x, loss(c.x), stream, ceiling=settings.friction_ceiling)
        other = None if start is None else refine_finalist(
            c._replace(x=start), f"{c.name} from the friction grid", required=False)
        kept = lower_refined(fit, other)
        which = "grid" if kept is other else "screened"
        friction_starts.append({
            "law": c.name, "screened_loss": float(fit.convergence.final_loss),
            "grid_loss": None if other is None else float(other.convergence.final_loss),
            "kept": which,
        })
        print(f"[friction start] {c.name}: "
              + ("no pair of the grid lowers the screened fit's loss" if start is None else
                 "the refinement from the grid's pair did not converge" if other is None else
                 f"{other.convergence.final_loss:.7g} from the grid's pair against {fit.convergence.final_loss:.7g} "
                 f"from the screened friction; kept: the {which}'s "
                 f"(mu {np.exp(kept.x[c.coordinates.names.index('mu')]):.3g})"),
              file=stream, flush=True)
        return kept

    def from_the_other_start(c: Candidate, fit: Candidate) -> Candidate:
        """`fit`, or the candidate refined from the other screened start of `train --start` (`from_new_effects_alone`)
        where that ends lower."""
        label, start = c.other_start
        other = refine_finalist(c._replace(x=start), f"{c.name} from {label}", required=False)
        kept = lower_refined(fit, other)
        effect_starts.append({
            "law": c.name, "screening_start_loss": float(fit.convergence.final_loss),
            "other_start": label, "other_loss": None if other is None else float(other.convergence.final_loss),
            "kept": "other" if kept is other else "screened",
        })
        print(f"[effect start] {c.name}: "
              + ("the refinement from the other start did not converge" if other is None else
                 f"{other.convergence.final_loss:.7g} refined from {label} against {fit.convergence.final_loss:.7g}"
                 f" from the lower screened fit; kept: the {'other' if kept is other else 'screened'} one"),
              file=stream, flush=True)
        return kept

    refined, friction_starts, effect_starts = [], [], []
    for c in finalists:
        fit = refine_finalist(c, c.name)
        if c.other_start is not None:
            fit = from_the_other_start(c, fit)
        if spinning and settings.friction_start == "both":
            fit = from_the_friction_grid(c, fit)
        refined.append(fit)
    if thorough:
        refined = [support_restart(c, refined) for c in refined]
    refined.sort(key=lambda c: c.score)
    best = undecided_support(refined)
    if len(refined) > 1:
        print(
            f"refined by {criterion.__name__.upper()} (above the best): "
            + ", ".join(f"{c.name} {c.score - best.score:.4g}" for c in refined)
            + f"; chosen: {best.name}"
            + ("" if best is refined[0] else f" (within {UNDECIDED_CRITERION:g} of {refined[0].name}, its limit)"),
            file=stream,
        )
    finals = {c.name: c for c in refined}
    candidates = tuple(
        {"law": c.name, "contact_law": c.law.setting, "yields": c.yields, "loss": c.convergence.final_loss,
         "criterion_above_best": round(c.score - screened[0].score, 3),
         "steps": c.convergence.steps, **c.convergence.histories(),
         **({"refined_loss": finals[c.name].convergence.final_loss,
             "refined_criterion_above_best": round(finals[c.name].score - best.score, 3),
             **refined_support(finals[c.name])} if c.name in finals else {})}
        for c in screened
    )
    law, coordinates, x, convergence = best.law, best.coordinates, best.x, best.convergence
    guess = convert_guess(config.nominal, config.law, law, settings.reference_deformation)
    theta = coordinates.theta(x)
    free = len(coordinates.names)
    started = time.perf_counter()
    ahead.wait(GAUSS_NEWTON_PROGRAM)
    terms = newton_terms.get((law.label, coordinates.start.tobytes(), x.tobytes())) or stage1_gauss_newton_over(
        chunks, theta, coordinates.directions(most_free), *problem(law, chunks, coordinates).arguments, **static
    )
    print(f"[standard errors] the loss's curvature in {free} coordinates on {len(data.paths)} bag(s)  "
          f"{time.perf_counter() - started:.1f} s elapsed", file=stream, flush=True)
    information = terms.information[:free, :free]
    covariance = posterior_covariance(information, coordinates.prior_sd(settings.prior_width, clearance_prior_sd))
    sd, correlation = standard_errors_and_correlation(covariance)
    relative_sd = {n: float(v) for n, v in zip(coordinates.names, sd) if n not in CLEARANCE_NAMES}
    clearance_sd = {n: float(v) * CLEARANCE_UNIT for n, v in zip(coordinates.names, sd) if n in CLEARANCE_NAMES}
    relative_sd.update(effect_relative_sd(relative_sd, theta.effects, scales))
    held = tuple(
        n for n in PARAMETER_NAMES + STRIBECK_NAMES if relative_sd.get(n, 0.0) >= HELD_BY_PRIOR * settings.prior_width
    )
    model, fitted_noise = stage1_model_and_noise(theta, law_model(law), noise, scales)
    if fit_stribeck:
        law = law.with_stribeck(
            float(model.law.friction_drop), float(model.law.stribeck_velocity),
            log_covariance_block(coordinates.names, covariance, STRIBECK_NAMES),
        )
    if not given:  # a given support stays as the user wrote it (not through exp(ln))
        law = law.with_support(
            float(model.law.support_preload), float(model.law.support_span),
            log_covariance_block(coordinates.names, covariance, SUPPORT_NAMES),
        )
    clearances = (float(model.rig.radial_clearance), float(model.rig.axial_clearance)) if fit_clearances else None
    return Calibration(
        config=config.calibrated(
            Nominal(*(float(v) for v in model.nominal)), law, config.kernel, fitted_noise, clearances=clearances
        ),
        effects=model.effects,
        clearance_sd=clearance_sd,
        guess=guess,
        relative_sd=relative_sd,
        held_by_prior=held,
        correlations=tuple(strongest_correlations(coordinates.names, correlation)),
        convergence=convergence,
        candidates=candidates,
        sensor_noise=sigma,
        criterion=best.score,
        friction_starts=tuple(friction_starts),
        effect_starts=tuple(effect_starts),
    )


def calibrate_stage1(config: Config, data: TrainingData, ahead: Ahead, stream=STDERR) -> Calibration:
    """`calibrate`; with a Stribeck drop fitted (training.friction_drop: fitted, a ring friction, the nll loss) in
    two passes: without the drop first, for the process noise, then the drop with that noise held. The drop
    explains radial motion the process noise covers without it, and a Q fitted beside it came out 29-500x smaller
    and too narrow on bags it did not see (docs/calibration.md, "A Stribeck drop of the ring friction")."""
    if not (config.fits_stribeck_drop and config.training.loss == "nll"):
        return calibrate(config, data, ahead, stream)
    print("[friction drop] stage 1 without the drop, for the process noise", file=stream, flush=True)
    with Ahead(stream) as plain_ahead:
        plain = calibrate(config.without_stribeck_fit(), data, plain_ahead, stream)
    held = dataclasses.replace(config, noise=config.noise._replace(process=plain.config.noise.process))
    print("[friction drop] stage 1 with the drop, the process noise held", file=stream, flush=True)
    with_drop = calibrate(held, data, ahead, stream, hold_q=True)
    plain_pass = {"friction_drop": "none", "law": plain.config.law.label, "criterion": plain.criterion,
                  "process_noise": [float(q) for q in plain.config.noise.process], **plain.convergence.as_dict()}
    return dataclasses.replace(with_drop, process_noise_pass=plain_pass)


def calibrate_frictions(config: Config, data: TrainingData, stream=STDERR) -> Calibration:
    """Stage 1 (`calibrate`) with each of `training.friction_models` in turn, each with its own background
    compilations; the fit of the lowest information criterion is kept, every one's listed in its `frictions`.
    The criteria compare: the bags, their samples and the fitted coordinates are the same (a spinning ring's
    speed is a state, not a fitted parameter), only the friction differs."""
    fits, seconds = [], []
    for friction in config.training.friction_models:
        print(f"[friction] stage 1 with contact.friction {friction}", file=stream, flush=True)
        started = time.perf_counter()
        with Ahead(stream) as ahead:
            fits.append(calibrate_stage1(config.with_friction(friction), data, ahead, stream))
        seconds.append(time.perf_counter() - started)
    best = min(fits, key=lambda c: c.criterion)
    rows = tuple(
        {"friction": c.config.law.friction, "law": c.config.law.label, "loss": c.convergence.final_loss,
         "criterion_above_best": round(c.criterion - best.criterion, 3), "seconds": round(s, 1)}
        for c, s in zip(fits, seconds)
    )
    print(
        "[friction] by the information criterion (above the best): "
        + ", ".join(f"{r['friction']} {r['criterion_above_best']:.4g}" for r in rows)
        + f"; chosen: {best.config.law.friction}",
        file=stream, flush=True,
    )
    return dataclasses.replace(best, frictions=rows)


#: Information criterion (AIC or BIC) within which another contact law's refined fit is as good as the
#: chosen one: differences below 2 are the usual "substantial support" for both (Burnham & Anderson).
UNDECIDED_CRITERION = 2.0


def undecided_support(refined: Sequence[Candidate]) -> Candidate:
    """The candidate to keep of `refined` (sorted by the criterion): the first, but where it is rigid and
    its law's yielding fit comes within UNDECIDED_CRITERION, the yielding one. It contains the rigid support
    as its limit, and its knee's and cap's uncertainty reaches the force band, where a rigid support
    would claim to know what the bags do not tell."""
    best = refined[0]
    rival = next((c for c in refined if c.yields and c.law.setting == best.law.setting), None)
    if best.yields or rival is None or rival.score - best.score >= UNDECIDED_CRITERION:
        return best
    return rival


#: Friction coefficient (mu, k_ZR) below which the paper's friction reads as hardly any: boundary-lubricated
#: sliding starts about there, dry steel or ceramic on steel is 0.1-0.3.
LOW_FRICTION = 0.05

#: Friction coefficient (mu, k_ZR) above any bearing contact's: dry steel or ceramic on steel slides at 0.1-0.3,
#: clean unlubricated steel at up to about 0.5-0.6. Stage 1 fits it there when the friction takes the part of
#: a force the model lacks (`Calibration.friction_note`).
HIGH_FRICTION = 0.5


#: The friction coefficients among the stage-1 coordinates' names (`training.friction_ceiling` caps them).
FRICTION_NAMES = ("mu", "k_ZR")


def friction_capped(
    bounds: Sequence[tuple[float, float]], names: Sequence[str], ceiling: float | None
) -> list[tuple[float, float]]:
    """`bounds` of the coordinates `names` with ln mu and ln k_ZR at most ln `ceiling` (None: as they are)."""
    if ceiling is None:
        return list(bounds)
    top = math.log(ceiling)
    return [(low, min(high, top) if name in FRICTION_NAMES else high) for (low, high), name in zip(bounds, names)]


def largest_friction(nominal: Nominal) -> float:
    """The larger of the bore's (mu) and the face's (k_ZR) friction coefficients of these constants."""
    return max(float(nominal.mu), float(nominal.k_ZR))


#: Share of `training.friction_ceiling` within which a fitted friction counts as held there: L-BFGS-B stops by
#: the loss's change a step short of a bound (a hidden z gain's stage 1 ended at mu 0.496 under 0.5).
CEILING_MARGIN = 0.02


def friction_at_ceiling(nominal: Nominal, ceiling: float | None) -> bool:
    """Whether mu or k_ZR of these constants is within `CEILING_MARGIN` of `ceiling` (None: no ceiling)."""
    return ceiling is not None and largest_friction(nominal) >= ceiling * (1.0 - CEILING_MARGIN)


def friction_above_any_bearings(nominal: Nominal) -> bool:
    """Whether mu or k_ZR of these constants is above `HIGH_FRICTION`."""
    return largest_friction(nominal) > HIGH_FRICTION


#: How to give the axial support from the mount's data sheet (the disc springs' preload and the force they
#: add at most until they block), which stage 1 then holds.
GIVE_THE_MOUNT = (
    "The mount's data sheet settles it: -p training.axial_support:=given -p contact.support_preload:=N "
    "-p contact.support_span:=N"
)

#: Standard error of ln(value) from which a support's preload or span counts as not pinned by the bags:
#: one factor of e either way.
UNPINNED_LOG_SD = 1.0


def refined_support(c: Candidate) -> dict[str, float]:
    """A yielding candidate's refined preload and span (N, `support_preload` / `support_span`); {} if rigid."""
    if not c.yields:
        return {}
    law = support_law(c.law, c.coordinates.theta(c.x).log_support)
    return dict(zip(SUPPORT_NAMES, (float(law.support_preload), float(law.support_span))))


def _uncertainty(log_sd: float) -> str:
    """'+-12 %' for a small standard error of ln(value), else that it is not pinned."""
    if log_sd < UNPINNED_LOG_SD:
        return f"+-{100 * log_sd:.0f} %"
    return f"not pinned: the standard error of its logarithm is {log_sd:.2g}"


def log_covariance_block(
    names: Sequence[str], covariance: np.ndarray, pair: Sequence[str]
) -> tuple[tuple[float, float], ...]:
    """(2, 2) block of the coordinates `pair` (SUPPORT_NAMES: ln preload and ln span; STRIBECK_NAMES: ln drop
    and ln velocity) in the posterior covariance of stage 1's coordinates `names`; EXACT_PAIR where they were
    not fitted."""
    if not all(n in names for n in pair):
        return EXACT_PAIR
    index = [list(names).index(n) for n in pair]
    return tuple(tuple(float(v) for v in row) for row in np.asarray(covariance)[np.ix_(index, index)])


class Stage1Batches(NamedTuple):
    """The records stage 1 screens the contact laws on, as one batch, and all records in chunks of
    its shape (one compiled program serves both)."""

    screen_data: TrainingData  # `training.screening_bags` of the bags, spread over the list
    screen: Batch
    chunks: tuple[Batch, ...]


def stage1_batches(config: Config, data: TrainingData, effects: Effects) -> Stage1Batches:
    """`Stage1Batches` of the training records."""
    screen = data.subset(spread(len(data.records), config.training.screening_bags))
    length, size = max(len(r) for r in data.records), len(screen.records)
    return Stage1Batches(
        screen,
        training_batch(config, screen, effects, length, size),
        training_chunks(config, data, effects, size, length),
    )


def filtered_records(
    model: Model, noise: FilterNoise, h: float, chunks: Sequence[Batch]
) -> tuple[np.ndarray, np.ndarray]:
    """`filtered_states` of the records of the chunks (`training_chunks`), their padding dropped:
    (records, L, n) states and (records, L) normalised innovations squared."""
    states, nis = [], []
    for chunk in chunks:
        held = int(np.asarray(chunk.valid).any(axis=1).sum())  # records first, padding (never valid) after
        chunk_states, chunk_nis = jax.device_get(filtered_states(model, noise, h, chunk))
        states.append(np.asarray(chunk_states)[:held])
        nis.append(np.asarray(chunk_nis)[:held])
    return np.concatenate(states), np.concatenate(nis)


def started_from_orbits(config: Config, data: TrainingData, stream=STDERR) -> Config:
    """The rig with its speed effects started where their speed fits the bags' orbits and its x and y
    sensor offsets at the orbits' centre where it shows one (`core.orbit.effects_from_orbits`, each in the
    bags it acts in), said on the stream."""
    effects = config.effects
    started, moved = effects_from_orbits(
        effects, config.rig, data.records, data.gates(effects), config.sample_period
    )
    for line in describe_starts(moved, effects.values()):
        print(line, file=stream)
    return dataclasses.replace(config, effects=started) if moved else config


def start_scales(model: Model, noise: FilterNoise, h: float, chunks: Sequence[Batch]) -> Effects:
    """The scales of the model's effects' parameters in stage 1 (`core.calibration.data_scales`):
    each moves its effect's force by the rotor's weight along the records' states (of all chunks),
    filtered with the starting model (the guess, the effects at their starting values), where the
    effect acts."""
    if not model.effects:
        return effect_scales(model.effects)
    states, acts = [], []
    for batch in chunks:
        valid = np.asarray(batch.valid)
        states.append(np.asarray(filtered_states(model, noise, h, batch)[0])[valid])
        gates = np.broadcast_to(np.asarray(batch.gates)[:, None, :] > 0.5, (*valid.shape, len(model.effects)))
        acts.append(gates[valid])
    return data_scales(model, np.concatenate(states), np.concatenate(acts))


def effect_relative_sd(sd: dict[str, float], scaled: Effects, scales: Effects) -> dict[str, float]:
    """The effects' entries of `sd` (posterior sd of a scaled coordinate, "effect.parameter") as
    the sd of the parameter over its fitted |value| (inf at 0), like the sd of ln f0."""
    out = {}
    for e, values, scale in zip(scaled.effects, scaled.params, scales.params):
        for k, v in values.items():
            name = f"{e.name}.{k}"
            if name in sd:
                value = abs(float(v) * scale[k])
                out[name] = sd[name] * scale[k] / value if value > 0.0 else float("inf")
    return out


class Problem(NamedTuple):
    """Stage 1 for one contact law on some records, as functions of the free coordinates."""

    objective: Callable[[np.ndarray], tuple[float, np.ndarray]]  # the loss and its gradient (for `minimise`)
    loss: Callable[[np.ndarray], float]  # the loss alone (start grids, restarts)
    start: np.ndarray  # the free coordinates at the YAML's guess
    arguments: tuple  # the stage-1 programs' arguments after theta (the law's guess, model, noise, scales)


class Candidate(NamedTuple):
    """One screened stage-1 fit: a contact law, rigid or with a yielding axial support."""

    score: float  # the information criterion (AIC or BIC, `training.search`)
    law: ContactLaw
    coordinates: Coordinates
    x: np.ndarray  # its free coordinates at the end of the screening fit
    convergence: Convergence
    yields: bool = False
    # with `train --start` adding effects: the other screened start's label and free coordinates (refined too)
    other_start: tuple[str, np.ndarray] | None = None

    @property
    def name(self) -> str:
        return self.law.label + (" + yielding support" if self.yields else "")


#: Where a yielding support's fit may start (the lowest loss is taken): preload and span as shares
#: of the largest face force the rigid fit reaches in the data.
SUPPORT_START_PRELOADS = (0.4, 0.55, 0.7, 0.85, 1.0)
SUPPORT_START_SPANS = (0.05, 0.15, 0.4, 1.0)


def support_starts(guess: ContactLaw, model: Model, noise: FilterNoise, h: float, batch: Batch) -> list[np.ndarray]:
    """ln preload and ln span (N) where stage 1 may start a yielding axial support: the YAML's when
    it gives one, otherwise a grid below the largest face force of `model` on the filtered
    records (only data above the preload move it, so it must start inside their range); none
    without axial contact."""
    if guess.yields:
        return [log_support_of(guess)]
    states = np.asarray(filtered_states(model, noise, h, batch)[0])[np.asarray(batch.valid) > 0]
    deepest = float(np.nanmax(-(states[:, 2] + model.rig.axial_clearance), initial=0.0))
    peak = float(normal_force(model.law, model.nominal.k_Z, 0.0, jnp.asarray(deepest), 0.0)) if deepest > 0 else 0.0
    if not peak > 0.0:
        return []
    return [np.log([f * peak, g * peak]) for f in SUPPORT_START_PRELOADS for g in SUPPORT_START_SPANS]


#: Factors on a damping constant from which stage 1 restarts when one of them lowers the loss. From
#: a guess far below the rig's damping the damping force is negligible and the loss hardly depends
#: on it, so its gradient cannot carry it up: on stiff_quiet c_R stopped at 1/60 of the rig's, with
#: -2 ln L 250 above the loss at the rig's value. Above the rig's value the loss does bend, so no
#: factors below 1.
DAMPING_RESTART_FACTORS = (10.0, 100.0, 1000.0)

#: The fall of -2 ln L on the screening bags a damping restart must bring to be taken: the workbench's bar for
#: "very strong" evidence (10). The restart jumps along a direction in which the loss
#: is nearly flat; a jump that gains less is one the drops cannot tell from where the fit stopped, and
#: there the prior holds the damping. drawn_1_2 (rolling training drops, bouncing held-out ones): c_R x10
#: gained 8.2, the refinement took c_R on to 12.5x the rig's at +-75 %, and the held-out drops were
#: tracked 2.2-3.6x the noise where the model stayed on the wall; stiff_quiet's restart gained 250.
DAMPING_RESTART_EVIDENCE = COLLINEAR_MARGIN


def damping_restart(
    loss_of: Callable[[np.ndarray], float], names: Sequence[str], x: np.ndarray, loss: float, stream,
    minus_two_log_l: Callable[[float], float],
) -> np.ndarray | None:
    """x (where the loss is `loss`) with c_R, then c_Z, multiplied by the factor of
    `DAMPING_RESTART_FACTORS` that lowers the loss most (the free coordinates are logarithms); None
    if no factor lowers -2 ln L (`minus_two_log_l` of a loss) by `DAMPING_RESTART_EVIDENCE`."""
    best, best_loss = x, loss
    for name in ("c_R", "c_Z"):
        if name not in names:
            continue
        start, start_loss = best, best_loss
        for factor in DAMPING_RESTART_FACTORS:
            trial = start.copy()
            trial[names.index(name)] += np.log(factor)
            trial_loss = loss_of(trial)
            if trial_loss < best_loss:
                best, best_loss = trial, trial_loss
        if best is start:
            continue
        gain = minus_two_log_l(start_loss) - minus_two_log_l(best_loss)
        factor = float(np.exp(best[names.index(name)] - start[names.index(name)]))
        if gain < DAMPING_RESTART_EVIDENCE:
            print(f"[damping restart] {name} x{factor:g} lowers -2 ln L by {gain:.3g} only (less than "
                  f"{DAMPING_RESTART_EVIDENCE:g}): not taken, the prior holds {name}", file=stream)
            best, best_loss = start, start_loss
        else:
            print(f"[damping restart] {name} x{factor:g} lowers the loss to {best_loss:.7g} "
                  f"(-2 ln L by {gain:.4g})", file=stream)
    return None if best is x else best


#: Friction coefficients (mu and k_ZR, each) from which the refinement restarts with a spinning ring when
#: one lowers the loss: boundary-lubricated to dry steel, `LOW_FRICTION`-0.4. Screened with the ring turning
#: with the rotor, the fit ends with the friction low (0.06 on stiff_quiet, where the ring then hardly
#: spins up), a basin of its own: there mu = k_ZR = 0.2 lowered the NLL from 3.664 to 3.459. On a rig that
#: slides at 0.05 the fit went on down to mu 0.003, k_ZR 0.016, and only the grid's lowest pair lowered the
#: loss (slippery with a hidden cross-coupling, 2026-12-03: 3.1556 -> 3.1182 at once, q +19 % -> +0.5 %).
FRICTION_RESTART_VALUES = (LOW_FRICTION, 0.1, 0.2, 0.4)


def friction_restart_values(ceiling: float | None = None) -> list[float]:
    """The values of `FRICTION_RESTART_VALUES` at most `ceiling` (None: all of them)."""
    return [v for v in FRICTION_RESTART_VALUES if ceiling is None or v <= ceiling]


def friction_restart(
    loss_of: Callable[[np.ndarray], float], names: Sequence[str], x: np.ndarray, loss: float, stream,
    label: str = "friction restart", ceiling: float | None = None,
) -> np.ndarray | None:
    """x (where the loss is `loss`) with mu and k_ZR set to the pair of `FRICTION_RESTART_VALUES`
    at most `ceiling` (`training.friction_ceiling`; None: every pair) that lowers the loss most (the free
    coordinates are logarithms); None if none lowers it. Each pair that lowers it is printed on `stream`
    after `label`."""
    best, best_loss = x, loss
    values = friction_restart_values(ceiling)
    for mu in values:
        for k_ZR in values:
            trial = x.copy()
            trial[names.index("mu")], trial[names.index("k_ZR")] = np.log(mu), np.log(k_ZR)
            trial_loss = loss_of(trial)
            if trial_loss < best_loss:
                best, best_loss = trial, trial_loss
                print(f"[{label}] mu {mu:g}, k_ZR {k_ZR:g} lower the loss to {trial_loss:.7g}", file=stream)
    return None if best is x else best


def bic(loss: float, extra_parameters: int, n_valid: int, kind: str) -> float:
    """Bayesian information criterion of a stage-1 fit (`training.search: standard`): as `aic`
    with the penalty k ln N."""
    return aic(loss, 0, n_valid, kind) + extra_parameters * float(np.log(n_valid))


def aic(loss: float, extra_parameters: int, n_valid: int, kind: str) -> float:
    """Akaike information criterion of a stage-1 fit, up to a constant shared by the candidates:
    -2 ln L + 2 k with k the parameters beyond the common ones. With the nll loss N J is -2 ln L
    up to a constant; with the one-step loss (a sum of squares) -2 ln L is N ln J for Gaussian
    errors of unknown variance. AIC rather than BIC (penalty k ln N): the choice is made for the
    forces of drops not trained on, which is what AIC estimates (the expected held-out -2 ln L).
    A yielding support moves only the few samples of the hardest impacts; on three bags it lowered
    -2 ln L by about 9 at the true knee, below BIC's 2 ln N = 17 (docs/calibration.md)."""
    fit = n_valid * loss if kind == "nll" else n_valid * float(np.log(loss))
    return float(fit + 2.0 * extra_parameters)


def spread(count: int, most: int) -> list[int]:
    """Indices of at most `most` of `count` items, evenly spread from the first to the last (all if most < 1)."""
    if most < 1 or count <= most:
        return list(range(count))
    return sorted({int(i) for i in np.round(np.linspace(0, count - 1, most))})
