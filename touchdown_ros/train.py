"""Fit the PKBKR coefficients of eq. 18 over many bags (L-BFGS on the AD gradient)."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jax import Array
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from touchdown_ros.core.calibration import (
    HELD_BY_PRIOR,
    contact_samples,
    filtered_states,
    kernel_from_data,
    Q_NAMES,
    Q_PRIOR_WIDTH,
    Stage1,
    apply_scales,
    convert_guess,
    effect_scales,
    log_nominal,
    sensor_noise,
    stage1_model_and_noise,
    stage1_objective,
    standard_errors,
    strongest_correlations,
)
from touchdown_ros.core.effects import Effects, gates_for
from touchdown_ros.core.estimate import detect_drop, to_grid
from touchdown_ros.core.training import RECORDS, Batch, loss, make_batch, pad_records, sample_errors
from touchdown_ros.core.types import PARAMETER_NAMES, Coefficients, ContactLaw, FilterNoise, Model, Nominal
from touchdown_ros.io.bags import read_conditions, read_displacement
from touchdown_ros.io.coefficients import TrainingRecord, load_coefficients, save_coefficients, sha256_of
from touchdown_ros.io.config import Config
from touchdown_ros.offline import NoDropError


@dataclass(frozen=True)
class TrainingData:
    """Records from the drop onset on, with the bags they came from."""

    paths: tuple[Path, ...]
    records: tuple[np.ndarray, ...]  # each (N_b, 3) m, NaN rows for missing samples
    conditions: tuple[dict[str, str], ...] = ()  # each bag's recorded test conditions (condition.*)
    levitated: tuple[np.ndarray, ...] = ()  # each bag's samples before the drop onset, (M_b, 3) m

    def subset(self, keep: Sequence[int]) -> "TrainingData":
        """The bags at the indices `keep`, with all they carry."""
        pick = lambda items: tuple(items[i] for i in keep) if items else ()  # noqa: E731
        return TrainingData(pick(self.paths), pick(self.records), pick(self.conditions), pick(self.levitated))


@dataclass(frozen=True)
class Convergence:
    """How one minimisation ended."""

    converged: bool
    reason: str  # the optimiser's own words
    steps: int
    initial_loss: float
    final_loss: float
    seconds: float
    history: tuple[float, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        return {
            "converged": self.converged,
            "reason": self.reason,
            "steps": self.steps,
            "initial_loss": self.initial_loss,
            "final_loss": self.final_loss,
            "seconds": round(self.seconds, 2),
        }


@dataclass(frozen=True)
class TrainingResult:
    coeffs: Coefficients
    effects: Effects
    initial_loss: float
    final_loss: float
    steps: int
    seconds: float
    history: tuple[float, ...]
    convergence: Convergence | None = None


def load_training_data(config: Config, paths: Sequence[str | Path], duration: float | None = None) -> TrainingData:
    """Read and validate every bag (all of them before any work), keep the samples after the drop
    and, apart, the levitated samples before it (for the sensor noise)."""
    records, conditions, levitated = [], [], []
    for path in paths:
        conditions.append(read_conditions(path))
        series = read_displacement(path, config.topics.displacement)
        grid = to_grid(series.stamps_ns, series.xyz, config.sample_period)
        onset = detect_drop(
            grid.etas[:, 2], config.sample_period, config.drop.threshold, config.drop.levitated_window, config.rig.gravity
        )
        if onset is None:
            raise NoDropError(f"{path}: no touchdown found, cannot train on it")
        record = grid.etas[onset:]
        if duration is not None:
            record = record[: int(round(duration / config.sample_period))]
        records.append(record)
        levitated.append(grid.etas[:onset])
    return TrainingData(tuple(Path(p) for p in paths), tuple(records), tuple(conditions), tuple(levitated))


class Trainable(NamedTuple):
    """What the trainer fits: the PKBKR coefficients and the active effects' parameters."""

    coeffs: Coefficients
    effects: Effects


def record_mesh() -> Mesh | None:
    """The host's XLA devices (one per usable core, `core.xla`) as one mesh axis over the
    records of a batch; None with a single device."""
    devices = jax.devices()
    return Mesh(np.array(devices), (RECORDS,)) if len(devices) > 1 else None


def place(batch: Batch, mesh: Mesh | None) -> Batch:
    """The batch padded to a multiple of the mesh size and split over its devices."""
    if mesh is None:
        return batch
    return jax.device_put(pad_records(batch, mesh.size), NamedSharding(mesh, P(RECORDS)))


def training_batch(config: Config, data: TrainingData, effects: Effects, length: int | None = None) -> Batch:
    """The records as one batch on `record_mesh()`, each with its effects' gates."""
    conditions = data.conditions or ({},) * len(data.records)
    gates = [gates_for(effects, c) for c in conditions]
    return place(make_batch(list(data.records), np.asarray(config.noise.initial), length, gates), record_mesh())


def _note_ungated(effects: Effects, batch: Batch, stream) -> None:
    gates = np.asarray(batch.gates)[np.asarray(batch.valid).any(axis=1)]
    for index, name in enumerate(effects.names):
        if not gates[:, index].any():
            print(
                f"note: effect {name} acts in none of the bags (it needs condition "
                f"{effects.effects[index].when!r}); its parameters stay at their starting values",
                file=stream,
            )


def make_objective(config: Config, regularisation: float) -> Callable:
    """Jitted (loss, gradient) of eq. 18 in (coefficients, scaled effect parameters), the records
    spread over `record_mesh()`; the batch is an argument (`place`d on that mesh), so batches of
    one shape (e.g. cross-validation folds) share one compilation."""
    model, mesh, kind = config.model(), record_mesh(), config.training.loss

    def objective(trainable: Trainable, scales: Effects, batch: Batch) -> jax.Array:
        effects = apply_scales(trainable.effects, scales)
        noise = config.training_noise()
        return loss(trainable.coeffs, model, noise, config.sample_period, batch, regularisation, effects, mesh, kind)

    return jax.jit(jax.value_and_grad(objective))


def minimise(
    value_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
    theta0: np.ndarray,
    max_steps: int,
    tolerance: float,
    label: str,
    stream=sys.stderr,
    describe: Callable[[np.ndarray], str] = lambda theta: "",
    on_step: Callable[[int, float, np.ndarray], None] | None = None,
) -> tuple[np.ndarray, Convergence]:
    """L-BFGS-B from theta0 until the loss changes by less than `tolerance` (relative) or the
    projected gradient is below it, at most `max_steps` iterations; progress on `stream`.

    A non-finite loss (the filter diverged at a trial point) counts as a very high one, so the
    line search steps back instead of stopping.
    """
    start = time.perf_counter()
    history: list[float] = []
    last: dict[bytes, tuple[float, np.ndarray]] = {}  # L-BFGS asks again for the point it starts from

    def fun(theta: np.ndarray) -> tuple[float, np.ndarray]:
        key = theta.tobytes()
        if key not in last:
            value, grad = value_and_grad(theta)
            if not (np.isfinite(value) and np.all(np.isfinite(grad))):
                value, grad = DIVERGED_LOSS, np.zeros_like(theta)
            last.clear()
            last[key] = float(value), np.asarray(grad, dtype=float)
        return last[key]

    def callback(intermediate_result) -> None:
        history.append(float(intermediate_result.fun))
        step = len(history)
        elapsed = time.perf_counter() - start
        print(
            f"[{label} step {step}/<={max_steps}] loss {intermediate_result.fun:.7g}{describe(intermediate_result.x)}  "
            f"{elapsed:.1f} s elapsed",
            file=stream,
            flush=True,
        )
        if on_step is not None:
            on_step(step, float(intermediate_result.fun), intermediate_result.x)

    initial_loss = fun(np.asarray(theta0, dtype=float))[0]
    print(f"[{label} step 0] loss {initial_loss:.7g} (compiled in {time.perf_counter() - start:.1f} s)", file=stream, flush=True)
    if max_steps == 0:
        return theta0, Convergence(False, "no steps asked for", 0, initial_loss, initial_loss, time.perf_counter() - start)
    result = scipy.optimize.minimize(
        fun,
        np.asarray(theta0, dtype=float),
        jac=True,
        method="L-BFGS-B",
        callback=callback,
        options={"maxiter": max_steps, "ftol": tolerance, "gtol": tolerance, "maxls": 40},
    )
    reason = str(result.message)
    converged = bool(result.success) and result.fun < DIVERGED_LOSS
    recent = np.asarray(history[-4:])
    if not converged and "ABNORMAL" in reason and len(recent) == 4:
        change = np.max(np.abs(np.diff(recent))) / max(abs(recent[-1]), 1.0)
        if change < 10.0 * tolerance:
            converged = True
            reason += f" (the line search found no lower loss; the last steps changed it by {change:.1e}: at its noise floor)"
    convergence = Convergence(
        converged, reason, int(result.nit), initial_loss, float(result.fun), time.perf_counter() - start, tuple(history)
    )
    print(
        f"[{label}] {'converged' if converged else 'NOT converged'} after {result.nit} steps: {reason}",
        file=stream,
        flush=True,
    )
    return np.asarray(result.x), convergence


#: Loss reported for a trial point where the filter diverged (the optimiser steps back from it).
DIVERGED_LOSS = 1.0e30
#: Tolerance to which stage 1 fits each candidate contact law before the best one is refined.
SCREEN_TOLERANCE = 1.0e-4


def fit(
    config: Config,
    data: TrainingData,
    regularisation: float,
    initial: Coefficients | Trainable | None = None,
    max_steps: int = 40,
    on_step: Callable[[int, float, Trainable], None] | None = None,
    stream=sys.stderr,
    objective: Callable | None = None,
    length: int | None = None,
    tolerance: float | None = None,
) -> TrainingResult:
    """Stage 2: minimise eq. 18 (with the rig's `training.loss`) with L-BFGS from `initial`
    (default: all alpha = 0, the constant model, and the rig's effects at their configured values).

    objective: a `make_objective` result to reuse; length: pad records to this many samples;
    tolerance: stop criterion (default `training.tolerance`).
    """
    if initial is None or isinstance(initial, Coefficients):
        initial = Trainable(initial if initial is not None else Coefficients.zeros(config.kernel), config.effects)
    scales = effect_scales(initial.effects)
    batch = training_batch(config, data, initial.effects, length)
    _note_ungated(initial.effects, batch, stream)
    objective = objective or make_objective(config, regularisation)
    theta0, unravel = ravel_pytree(Trainable(initial.coeffs, apply_scales(initial.effects, scales, inverse=True)))
    # (the effects' gates ride along in theta, but the loss replaces them by each record's gates,
    # so their gradient is zero and they never move)

    def physical(theta: np.ndarray) -> Trainable:
        scaled = unravel(theta)
        return Trainable(scaled.coeffs, apply_scales(scaled.effects, scales))

    def value_and_grad(theta: np.ndarray):
        value, grad = objective(unravel(theta), scales, batch)
        return float(value), np.asarray(ravel_pytree(jax.device_get(grad))[0], dtype=float)

    def describe(theta: np.ndarray) -> str:
        return "".join(f"  {e}.{k} {v:.5g}" for e, p in physical(theta).effects.values().items() for k, v in p.items())

    step_hook = None if on_step is None else (lambda step, value, theta: on_step(step, value, physical(theta)))
    theta, convergence = minimise(
        value_and_grad,
        np.asarray(theta0, dtype=float),
        max_steps,
        config.training.tolerance if tolerance is None else tolerance,
        "PKBKR",
        stream,
        describe,
        step_hook,
    )
    if convergence.initial_loss >= DIVERGED_LOSS:
        raise FloatingPointError("training loss is not finite at the start; check the bags and the noise settings")
    fitted = physical(theta)
    return TrainingResult(
        coeffs=fitted.coeffs,
        effects=fitted.effects,
        initial_loss=convergence.initial_loss,
        final_loss=convergence.final_loss,
        steps=convergence.steps,
        seconds=convergence.seconds,
        history=convergence.history,
        convergence=convergence,
    )


def _merge_effects(active: Effects, started: Effects) -> Effects:
    """The rig's active effects, starting from a warm-start file's values where it has them.

    The rig YAML decides which effects are fitted; an effect of the file that the rig does not
    switch on is dropped, with a note, rather than silently kept."""
    dropped = sorted(set(started.names) - set(active.names))
    if dropped:
        print(f"note: the warm-start file's effect(s) {', '.join(dropped)} are not active in the rig; not fitted", file=sys.stderr)
    return active.with_values(started.values())


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
    candidates: tuple[dict[str, Any], ...]  # every law tried: label, loss, converged
    sensor_noise: np.ndarray  # (3,) m, per axis, from the levitated samples

    def summary(self) -> dict[str, Any]:
        """Plain data for the coefficient file."""
        nominal = self.config.nominal
        return {
            "law": self.config.law.label,
            "guess": {k: float(v) for k, v in self.guess._asdict().items()},
            "calibrated": {k: float(v) for k, v in nominal._asdict().items()},
            "relative_standard_error": {k: round(v, 6) for k, v in self.relative_sd.items()},
            "held_by_prior": list(self.held_by_prior),
            "strongest_correlations": [[a, b, round(r, 4)] for a, b, r in self.correlations],
            "sensor_noise_m": [float(v) for v in self.sensor_noise],
            "candidates": list(self.candidates),
            **self.convergence.as_dict(),
        }


class TrainingError(ValueError):
    """Training cannot give a trustworthy coefficient file from these bags and settings."""


class DivergedError(TrainingError):
    """The filter diverges from the starting guess on a bag."""


class NotConvergedError(TrainingError):
    """A training stage reached its step cap before converging."""


def _require_convergence(convergence: Convergence, stage: str, paths: Sequence[Path], knob: str) -> None:
    if not convergence.converged:
        raise NotConvergedError(
            f"{', '.join(map(str, paths))}: {stage} did not converge in {convergence.steps} steps "
            f"({convergence.reason}); allow more with {knob}, or check that these bags are drops of this rig"
        )


def measured_sensor_noise(config: Config, data: TrainingData, stream=sys.stderr) -> np.ndarray:
    """(3,) sensor noise sd (m) per axis, pooled over the bags' levitated samples; the YAML's
    filter.measurement_noise for an axis with too few of them (with a note)."""
    levitated = [l for l in data.levitated if len(l) > 0]
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


def calibrate(config: Config, data: TrainingData, stream=sys.stderr) -> Calibration:
    """Stage 1 (core.calibration): for each candidate contact law, fit f0, the Q factors and the
    effects' parameters from the YAML's guess; keep the law with the lowest loss."""
    settings = config.training
    sigma = measured_sensor_noise(config, data, stream)
    print("sensor noise from the levitated samples: " + ", ".join(f"{a} {v * 1e6:.2f} um" for a, v in zip("xyz", sigma)), file=stream)
    noise = config.noise._replace(measurement=jnp.asarray(sigma**2))
    h, kind, mesh = config.sample_period, settings.loss, record_mesh()
    effects = config.effects
    scales = effect_scales(effects)
    batch = training_batch(config, data, effects)
    _note_ungated(effects, batch, stream)
    n_valid = int(np.sum(np.asarray(batch.valid)))
    fit_q = kind == "nll"

    @jax.jit
    def batch_value_and_grad(theta: Stage1, guess: Array, law_model: Model, records: Batch):
        return jax.value_and_grad(stage1_objective)(
            theta, guess, settings.prior_width, law_model, noise, scales, h, records, kind, mesh
        )

    def value_and_grad(theta: Stage1, guess: Array, law_model: Model):
        return batch_value_and_grad(theta, guess, law_model, batch)

    template, unravel = ravel_pytree(Stage1(jnp.zeros(len(PARAMETER_NAMES)), jnp.zeros(2), apply_scales(effects, scales, inverse=True)))
    free = np.ones(template.shape, bool)
    free[len(PARAMETER_NAMES) : len(PARAMETER_NAMES) + 2] = fit_q  # Q factors: nll only
    full0 = np.asarray(template, dtype=float)

    def expand(x: np.ndarray) -> np.ndarray:
        full = full0.copy()
        full[free] = x
        return full

    def describe(x: np.ndarray) -> str:
        values = np.exp(np.asarray(unravel(expand(x)).log_f0))
        return "  " + "  ".join(f"{n} {v:.3g}" for n, v in zip(PARAMETER_NAMES, values))

    def problem(law: ContactLaw):
        """(guess, objective of the free coordinates, their start) for one contact law."""
        guess = convert_guess(config.nominal, config.law, law, settings.reference_deformation)
        guess_log, base = jnp.asarray(log_nominal(guess)), config.model()._replace(law=law)

        def objective(x: np.ndarray):
            value, grad = value_and_grad(unravel(expand(x)), guess_log, base)
            return float(value), np.asarray(ravel_pytree(jax.device_get(grad))[0], dtype=float)[free]

        x0 = full0.copy()
        x0[: len(PARAMETER_NAMES)] = np.asarray(guess_log)
        return guess, objective, x0[free]

    # Screen every candidate law to a loose tolerance, then refine the best one.
    screened = []
    for law in settings.contact_laws:
        guess, objective, x0 = problem(law)
        x, convergence = minimise(
            objective, x0, settings.calibration_steps, max(settings.tolerance, SCREEN_TOLERANCE),
            f"calibrate {law.label}", stream, describe,
        )
        if convergence.initial_loss >= DIVERGED_LOSS:
            model0, noise0 = stage1_model_and_noise(unravel(expand(x0)), config.model()._replace(law=law), noise, scales)
            losses = _per_bag_losses(model0, noise0, h, batch, kind)[: len(data.paths)]
            bad = [str(p) for p, v in zip(data.paths, losses) if not np.isfinite(v)] or [str(p) for p in data.paths]
            raise DivergedError(
                f"{', '.join(bad)}: the filter diverges with the guessed contact constants ({law.label}); "
                "give contact.* closer to the bearing's (a data sheet's stiffness within 5x) or check the bag"
            )
        screened.append((convergence.final_loss, law, x, convergence))
    screened.sort(key=lambda t: t[0])
    candidates = tuple({"law": law.label, "loss": loss, "steps": c.steps} for loss, law, _, c in screened)
    law = screened[0][1]
    if len(screened) > 1:
        print("contact laws by loss: " + ", ".join(f"{c['law']} {c['loss']:.6g}" for c in candidates) + f"; chosen: {law.label}", file=stream)
    guess, objective, _ = problem(law)
    x, convergence = minimise(
        objective, screened[0][2], settings.calibration_steps, settings.tolerance, f"calibrate {law.label}, refined", stream, describe
    )
    _require_convergence(convergence, f"stage 1 ({law.label})", data.paths, "-p training.calibration_steps:=N")
    theta = unravel(expand(x))
    hessian = _hessian(objective, x)
    names = [n for n, f in zip([*PARAMETER_NAMES, *Q_NAMES, *_effect_names(effects)], free) if f]
    prior_sd = [settings.prior_width if n in PARAMETER_NAMES else Q_PRIOR_WIDTH if n in Q_NAMES else np.inf for n in names]
    sd, correlation = standard_errors(hessian, n_valid, np.asarray(prior_sd))
    relative_sd = {n: float(v) for n, v in zip(names, sd)}
    held = tuple(n for n in PARAMETER_NAMES if relative_sd[n] >= HELD_BY_PRIOR * settings.prior_width)
    model, fitted_noise = stage1_model_and_noise(theta, config.model()._replace(law=law), noise, scales)
    calibrated = config.calibrated(model.nominal, law, config.kernel, fitted_noise)
    calibrated = replace(calibrated, nominal=Nominal(*(float(v) for v in model.nominal)))
    return Calibration(
        config=calibrated,
        effects=model.effects,
        guess=guess,
        relative_sd=relative_sd,
        held_by_prior=held,
        correlations=tuple(strongest_correlations(names, correlation)),
        convergence=convergence,
        candidates=candidates,
        sensor_noise=sigma,
    )


def _effect_names(effects: Effects) -> list[str]:
    return [f"{e}.{k}" for e, p in effects.values().items() for k in p]


def _hessian(objective: Callable[[np.ndarray], tuple[float, np.ndarray]], x: np.ndarray, step: float = 1e-4) -> np.ndarray:
    """Hessian of a loss at x by central differences of its AD gradient (2 n gradients, no extra
    compilation)."""
    columns = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = step
        columns.append((objective(x + e)[1] - objective(x - e)[1]) / (2.0 * step))
    return np.array(columns)


def checkpoint_path(out: Path) -> Path:
    return out.with_name(out.name + ".checkpoint")


@dataclass(frozen=True)
class TrainOutcome:
    """Both stages of `train`: the calibration (None when warm-started) and the PKBKR fit."""

    calibration: Calibration | None
    pkbkr: TrainingResult
    config: Config  # the calibrated rig the coefficients belong to
    mean_nis: tuple[float, ...]  # per bag, with the final model (3 for a consistent filter)
    seconds: float


def train(
    config: Config,
    bags: Sequence[str | Path],
    out: Path,
    regularisation: float | None = None,
    init: Path | None = None,
    resume: bool = False,
    max_steps: int | None = None,
    duration: float | None = None,
    stream=sys.stderr,
) -> TrainOutcome:
    """Validate all bags, identify the rig (stage 1, `calibrate`), place the kernel centres on the
    data, fit PKBKR around the calibrated constants (stage 2, `fit`) and write the coefficient file
    (a checkpoint after every stage-2 step). With `init` or `resume`, stage 1 is taken from that file."""
    start = time.perf_counter()
    lam = config.regularisation if regularisation is None else regularisation
    steps = config.training.pkbkr_steps if max_steps is None else max_steps
    data = load_training_data(config, bags, duration)
    start_from = checkpoint_path(out) if resume else init
    calibration, notes = None, []
    if start_from is not None:
        if resume and not start_from.exists():
            raise FileNotFoundError(f"{start_from}: no checkpoint to resume from")
        loaded = load_coefficients(start_from, config)
        calibrated = loaded.config(config)
        initial = Trainable(loaded.coeffs, _merge_effects(config.effects, loaded.effects))
        stage1 = dict(loaded.training.extra.get("calibration") or {}, taken_from=str(start_from))
    else:
        calibration = calibrate(config, data, stream)
        calibrated = calibration.config
        stage1 = calibration.summary()
        if config.training.placement == "data":
            states, _ = filtered_states(
                calibrated.model(effects=calibration.effects), calibrated.noise, config.sample_period,
                training_batch(calibrated, data, calibration.effects),
            )
            radial, axial = contact_samples(calibrated.model(), np.asarray(states)[: len(data.records)])
            kernel, notes = kernel_from_data(calibrated.kernel, radial, axial)
            calibrated = replace(calibrated, kernel=kernel)
            for note in notes:
                print(f"note: {note}", file=stream)
        initial = Trainable(Coefficients.zeros(calibrated.kernel), calibration.effects)
    calibrated = replace(calibrated, effects=initial.effects)
    hashes = [{"path": str(p), "sha256": sha256_of(p)} for p in data.paths]

    def record(steps: int, final_loss: float | None, **extra) -> TrainingRecord:
        return TrainingRecord(
            bags=hashes, regularisation=lam, final_loss=final_loss, steps=steps, extra={"calibration": stage1, **extra}
        )

    def on_step(step: int, value: float, fitted: Trainable) -> None:
        save_coefficients(
            checkpoint_path(out), fitted.coeffs, calibrated, record(step, value, checkpoint=True), fitted.effects
        )

    result = fit(calibrated, data, lam, initial, steps, on_step, stream)
    if steps > 0:
        _require_convergence(
            result.convergence, "stage 2 (PKBKR)", data.paths, f"--steps N (then --resume continues from {checkpoint_path(out)})"
        )
    final = calibrated.model(result.coeffs, result.effects)
    _, nis = filtered_states(final, calibrated.noise, config.sample_period, training_batch(calibrated, data, result.effects))
    mean_nis = tuple(float(np.nanmean(row)) for row in np.asarray(nis)[: len(data.records)])
    seconds = time.perf_counter() - start
    save_coefficients(
        out,
        result.coeffs,
        calibrated,
        record(
            result.steps,
            result.final_loss,
            initial_loss=result.initial_loss,
            seconds=round(seconds, 2),
            loss=config.training.loss,
            pkbkr=result.convergence.as_dict() if result.convergence else {},
            kernel_notes=notes,
            mean_nis={str(p): round(v, 3) for p, v in zip(data.paths, mean_nis)},
        ),
        result.effects,
    )
    checkpoint_path(out).unlink(missing_ok=True)
    return TrainOutcome(calibration, result, calibrated, mean_nis, seconds)
