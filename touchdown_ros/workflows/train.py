"""`touchdown train`: identify a rig (stage 1, `calibrate`) and fit the PKBKR coefficients of eq. 18
around it (stage 2, L-BFGS on the AD gradient); the coefficient file."""
from __future__ import annotations

import functools
import glob
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import numpy as np
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh
from scipy.optimize import minimize_scalar

from touchdown_ros.workflows.calibrate import (
    Calibration, calibrate_frictions, calibrate_stage1, filtered_records, stage1_batches,
)
from touchdown_ros.core.calibration import (
    apply_scales,
    contact_samples,
    effect_scales,
    kernel_as_placed,
    kernel_from_data,
    scaled_bounds,
    strongly_typed,
)
from touchdown_ros.core.effects import Effects
from touchdown_ros.core.pkbkr import Whitening, coloured, whitened, whitening
from touchdown_ros.core.smoothing import (
    leave_one_out_squares,
    mean_fall_and_standard_error,
    mean_missing_force_variance,
    missing_force_squares,
)
from touchdown_ros.core.training import (
    Batch,
    held_out_block_sums,
    hold_out,
    loss_and_held_out,
    within_one_standard_error,
)
from touchdown_ros.core.types import OUTPUT_SIZE, Coefficients, FilterNoise, Model
from touchdown_ros.io.coefficients import TrainingRecord, load_coefficients, save_coefficients, sha256_of
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.ahead import Ahead
from touchdown_ros.workflows.optimise import DIVERGED_LOSS, Convergence, DivergedError, minimise, require_convergence
from touchdown_ros.workflows.progress import STDERR
from touchdown_ros.workflows.training_data import (  # noqa: F401  (TrainingData, load_training_data: the trainer's API)
    TrainingData,
    load_training_data,
    note_ungated,
    record_mesh,
    training_batch,
)


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
    held_out_blocks: np.ndarray | None = None  # the kept step's held-out errors per block (`held_out_block_sums`)
    held_out_samples: int = 0  # how many held-out samples those blocks hold


class Trainable(NamedTuple):
    """What the trainer fits: the PKBKR coefficients and the active effects' parameters."""

    coeffs: Coefficients
    effects: Effects


@functools.partial(jax.jit, static_argnames=("h", "kind", "mesh"))
def stage2_value_and_grad(
    trainable: Trainable, scales: Effects, batch: Batch, regularisation: jax.Array, w: Whitening, model: Model,
    noise: FilterNoise, h: float, kind: str, mesh: Mesh | None,
) -> tuple[tuple[jax.Array, tuple[jax.Array, jax.Array]], Trainable]:
    """((loss, (held-out loss, held-out samples' errors)), gradient of the loss) of eq. 18 in (whitened
    coefficients beta, scaled effect parameters). The model and the noise are arguments, not constants of the
    program, so one compilation serves every rig of one shape and can start before stage 1 has calibrated them
    (`compile_stage2_ahead`)."""

    def objective(trainable: Trainable) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        effects = apply_scales(trainable.effects, scales)
        return loss_and_held_out(
            coloured(w, trainable.coeffs), model, noise, h, batch, regularisation, effects, mesh, kind
        )

    return jax.value_and_grad(objective, has_aux=True)(trainable)


def make_objective(config: Config) -> Callable:
    """`stage2_value_and_grad` of this rig's model and training noise, the records spread over
    `record_mesh()`: a function of (trainable, scales, batch, lambda, the kernel's `Whitening`), the
    batch `place`d on that mesh, so batches of one shape (e.g. cross-validation folds) and every lambda
    share one compilation."""
    return functools.partial(
        stage2_value_and_grad,
        model=strongly_typed(config.model()),
        noise=strongly_typed(config.training_noise()),
        h=config.sample_period,
        kind=config.training.loss,
        mesh=record_mesh(),
    )


class Stage2Problem(NamedTuple):
    """Stage 2's start and records, as `stage2_value_and_grad` takes them."""

    theta0: np.ndarray  # the start: whitened coefficients and scaled effect parameters, flat
    unravel: Callable[[np.ndarray], Trainable]  # flat -> (beta, scaled effect parameters)
    scales: Effects  # each effect parameter's scale (`effect_scales`)
    batch: Batch  # the records with their held-out blocks, `place`d on the record mesh
    w: Whitening

    def arguments(self, theta: np.ndarray, regularisation: float) -> tuple:
        """The positional arguments of a `make_objective` result at theta and lambda (every leaf strongly
        typed, so that a program compiled ahead of time is the one called)."""
        lam = np.float64(regularisation)
        return strongly_typed(self.unravel(theta)), strongly_typed(self.scales), self.batch, lam, self.w


def stage2_problem(config: Config, data: TrainingData, initial: Trainable, length: int | None = None) -> Stage2Problem:
    """Stage 2 from `initial` on the records of `data` (padded to `length` samples), one block in every
    `training.held_out_every` held out."""
    scales = effect_scales(initial.effects)
    batch = hold_out(training_batch(config, data, initial.effects, length), config.held_out_block_samples(),
                     config.training.held_out_every)
    w = whitening(config.kernel)
    theta0, unravel = ravel_pytree(
        Trainable(whitened(w, initial.coeffs), apply_scales(initial.effects, scales, inverse=True))
    )
    # (the effects' gates ride along in theta, but the loss replaces them by each record's gates,
    # so their gradient is zero and they never move)
    return Stage2Problem(np.asarray(theta0, dtype=float), unravel, scales, batch, w)


#: `Ahead` names of stage 2's program (`stage2_value_and_grad`), the smoothing noise's (`leave_one_out_squares`)
#: and the model's force error's (`missing_force_squares`).
STAGE2_PROGRAM = "stage 2"
SMOOTHING_PROGRAM = "the smoothing noise's cross-validation"
MISSING_FORCE_PROGRAM = "the model's force error"


def compile_stage2_ahead(ahead: Ahead, config: Config, data: TrainingData) -> None:
    """Queue the compilation of stage 2's program (and the smoothing noise's) for the records of `data`,
    with the kernel shaped as the data will place it and the rig's effects (the calibrated values are
    arguments of the same shapes)."""
    kernel = kernel_as_placed(config.kernel) if config.training.placement == "data" else config.kernel
    shaped = replace(config, kernel=kernel)
    problem = stage2_problem(shaped, data, Trainable(Coefficients.zeros(kernel), config.effects))
    objective = make_objective(shaped)
    ahead.compile(STAGE2_PROGRAM, objective.func, *problem.arguments(problem.theta0, 1.0), **objective.keywords)
    batch = training_batch(shaped, data, config.effects)
    if config.training.smoothing_noise == "cross_validation":
        ahead.compile(SMOOTHING_PROGRAM, leave_one_out_squares, objective.keywords["model"],
                      strongly_typed(config.noise), config.sample_period, batch)
    ahead.compile(MISSING_FORCE_PROGRAM, missing_force_squares, objective.keywords["model"],
                  strongly_typed(config.noise), config.sample_period, batch)


def fit(
    config: Config,
    data: TrainingData,
    regularisation: float,
    initial: Coefficients | Trainable | None = None,
    max_steps: int = 40,
    on_step: Callable[[int, float, Trainable], None] | None = None,
    stream=STDERR,
    objective: Callable | None = None,
    length: int | None = None,
    tolerance: float | None = None,
) -> TrainingResult:
    """Stage 2: minimise eq. 18 (with the rig's `training.loss`) with L-BFGS from `initial`
    (default: all alpha = 0, the constant model, and the rig's effects at their configured values),
    in the whitened coordinates beta = L^T alpha of the coefficients (`core.pkbkr.Whitening`).
    One block of samples in every `training.held_out_every` is left out of the loss; the step where
    their error is lowest is kept (the start included), and the fit stops when it has not fallen
    for `training.patience` steps.

    objective: a `make_objective` result to reuse; length: pad records to this many samples;
    tolerance: stop criterion (default `training.tolerance`).
    """
    if initial is None or isinstance(initial, Coefficients):
        initial = Trainable(initial if initial is not None else Coefficients.zeros(config.kernel), config.effects)
    settings = config.training
    problem = stage2_problem(config, data, initial, length)
    theta0, unravel, scales, batch, w = problem
    note_ungated(initial.effects, (batch,), stream)
    objective = objective or make_objective(config)

    def physical(theta: np.ndarray) -> Trainable:
        scaled = unravel(theta)
        return Trainable(coloured(w, scaled.coeffs), apply_scales(scaled.effects, scales))

    def value_and_grad(theta: np.ndarray):
        (value, (held_out, _)), grad = objective(*problem.arguments(theta, regularisation))
        gradient = np.asarray(ravel_pytree(jax.device_get(grad))[0], dtype=float)
        return (float(value), gradient, float(held_out)) if settings.held_out_every > 1 else (float(value), gradient)

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
        settings.patience,
        scaled_bounds(unravel(theta0), scales),
    )
    if convergence.initial_loss >= DIVERGED_LOSS:
        raise DivergedError(
            f"{', '.join(map(str, data.paths))}: the PKBKR loss is not finite at its start (the filter diverges); "
            "check the bags and the filter noise"
        )
    fitted = physical(theta)
    blocks, samples = None, 0
    if settings.held_out_every > 1 and settings.regularisation_choice == "one_standard_error":
        # the kept step's held-out errors block by block, for the choice of lambda (one more call)
        (_, (_, held_out_errors)), _ = objective(*problem.arguments(theta, regularisation))
        blocks = held_out_block_sums(np.asarray(held_out_errors), batch)
        samples = int(np.sum(np.asarray(batch.held_out) & np.asarray(batch.valid)))
    return TrainingResult(
        coeffs=fitted.coeffs,
        effects=fitted.effects,
        initial_loss=convergence.initial_loss,
        final_loss=convergence.final_loss,
        steps=convergence.steps,
        seconds=convergence.seconds,
        history=convergence.history,
        convergence=convergence,
        held_out_blocks=blocks,
        held_out_samples=samples,
    )


class RegularisationPath(NamedTuple):
    """Stage 2 along lambda: the chosen fit and, per lambda tried, how it went."""

    result: TrainingResult
    regularisation: float  # the chosen lambda
    tried: tuple[dict, ...]  # per lambda: its held-out loss at its start and kept step, steps, kept step

    def as_dict(self) -> dict:
        """As the coefficient file records it (without the held-out blocks' sums, which the checkpoint keeps)."""
        return {"chosen": self.regularisation,
                "tried": [{k: v for k, v in t.items() if k != HELD_OUT_BLOCKS} for t in self.tried]}


#: Key of a tried lambda's held-out errors per block in the path's record (`TrainingResult.held_out_blocks`).
HELD_OUT_BLOCKS = "held_out_block_sums"


class PathProgress(NamedTuple):
    """How far an interrupted lambda path got (`train --resume`)."""

    tried: tuple[dict, ...] = ()  # the finished lambdas, as `RegularisationPath.tried`
    chosen: tuple[TrainingResult, float, float] | None = None  # the lowest so far: (fit, lambda, held-out loss)
    current: Trainable | None = None  # the interrupted lambda's last step, where its fit continues
    fits: tuple[tuple[float, TrainingResult], ...] = ()  # every finished lambda's fit (the one-standard-error rule)


def fit_regularisation_path(
    config: Config,
    data: TrainingData,
    regularisations: Sequence[float],
    initial: Trainable,
    max_steps: int,
    on_step: Callable[[float, int, float, Trainable], None] | None = None,
    stream=STDERR,
    knob: str = "--steps N",
    progress: PathProgress = PathProgress(),
    on_lambda: Callable[[PathProgress], None] | None = None,
) -> RegularisationPath:
    """Stage 2 (`fit`) from `initial` at each lambda of eq. 18, the largest first, while the held-out
    loss (at each fit's kept step) falls: the fit of the lowest. (Each from `initial`, not from the
    fit before: from another lambda's optimum the loss changes too little for L-BFGS to go on.)
    Each fit must converge (else the error names `knob`); `on_step(lambda, step, loss, fitted)`
    after every step, `on_lambda(progress)` after every lambda that does not end the path.
    With `training.regularisation_choice: one_standard_error` the largest lambda tried whose held-out loss is
    within one standard error of the lowest is chosen instead (`core.training.within_one_standard_error`).
    From `progress` (an interrupted path), its finished lambdas are not fitted again and the next one
    continues from `progress.current`.
    Without held-out blocks nothing can choose: the smallest lambda alone, with a note."""
    lambdas = sorted({float(v) for v in regularisations}, reverse=True)
    if max_steps == 0:
        lambdas = lambdas[-1:]
    elif len(lambdas) > 1 and config.training.held_out_every <= 1:
        print(f"note: no held-out blocks (training.held_out_every) to choose lambda by: {lambdas[-1]:g}", file=stream)
        lambdas = lambdas[-1:]
    objective = make_objective(config)
    chosen, tried, current, fits = progress.chosen, list(progress.tried), progress.current, dict(progress.fits)
    done = {t["regularisation"] for t in tried}
    for lam in lambdas:
        if lam in done:
            print(f"[PKBKR] lambda {lam:g}: fitted before the interruption", file=stream, flush=True)
            continue
        if len(lambdas) > 1:
            print(f"[PKBKR] lambda {lam:g}", file=stream, flush=True)
        hook = None if on_step is None else functools.partial(on_step, lam)
        start, current = (initial if current is None else current), None
        result = fit(config, data, lam, start, max_steps, hook, stream, objective=objective)
        if max_steps > 0:
            require_convergence(result.convergence, f"stage 2 (PKBKR, lambda {lam:g})", data.paths, knob)
        convergence = result.convergence
        kept = convergence.kept_step if convergence is not None else None
        held_out = convergence.held_out if kept is not None else (None,)
        loss = held_out[kept or 0]
        tried.append({
            "regularisation": lam, "held_out_loss_start": held_out[0], "held_out_loss": loss,
            "steps": result.steps, "kept_step": kept, **(convergence.histories() if convergence is not None else {}),
            **({HELD_OUT_BLOCKS: result.held_out_blocks.tolist(), "held_out_samples": result.held_out_samples,
                "initial_loss": result.initial_loss, "final_loss": result.final_loss}
               if result.held_out_blocks is not None else {}),  # what a resumed path's choice needs of it
        })
        fits[lam] = result
        if chosen is not None and not loss < chosen[2]:
            break
        chosen = (result, lam, loss)
        if on_lambda is not None:
            on_lambda(PathProgress(tuple(tried), chosen, None, tuple(fits.items())))
    how = "the lowest"
    if config.training.regularisation_choice == "one_standard_error" and len(tried) > 1:
        if all(HELD_OUT_BLOCKS in t for t in tried):
            chosen, how = _within_one_standard_error(tried, fits, chosen)
        else:  # a checkpoint of a path begun with another choice
            how = "the lowest: the held-out blocks of the lambdas fitted before the interruption are not recorded"
    if len(lambdas) > 1:
        text = ", ".join(f"{t['regularisation']:g}: {t['held_out_loss']:.7g}" for t in tried)
        print(f"[PKBKR] held-out loss by lambda {text}; chosen {chosen[1]:g} ({how})", file=stream, flush=True)
    return RegularisationPath(chosen[0], chosen[1], tuple(tried))


def _within_one_standard_error(
    tried: list[dict], fits: dict[float, TrainingResult], lowest: tuple[TrainingResult, float, float]
) -> tuple[tuple[TrainingResult, float, float], str]:
    """(the fit, its lambda and held-out loss) of the largest lambda whose held-out loss is within one standard
    error of the lowest's, and how it was chosen; each tried lambda's record gets its loss above the lowest and
    that standard error."""
    index, above, error = within_one_standard_error(
        [np.asarray(t[HELD_OUT_BLOCKS]) for t in tried], int(tried[0]["held_out_samples"])
    )
    for t, a, e in zip(tried, above, error):
        t.update(held_out_above_lowest=float(a), standard_error=float(e))
    lam = float(tried[index]["regularisation"])
    if lam == lowest[1]:
        return lowest, "the lowest"
    return (fits[lam], lam, float(tried[index]["held_out_loss"])), (
        f"within one standard error of the lowest, {lowest[1]:g}: {above[index]:+.4g} +- {error[index]:.2g} per "
        "held-out sample"
    )


def _merge_effects(active: Effects, started: Effects) -> Effects:
    """The rig's active effects, starting from a warm-start file's values where it has them.

    The rig YAML decides which effects are fitted; an effect of the file that the rig does not
    switch on is dropped, with a note, rather than silently kept."""
    dropped = sorted(set(started.names) - set(active.names))
    if dropped:
        print(
            f"note: the warm-start file's effect(s) {', '.join(dropped)} are not active in the rig; not fitted",
            file=sys.stderr,
        )
    return active.with_values(started.values())


def calibration_started_from(config: Config, path: Path, stream=STDERR) -> Config:
    """`config` with stage 1 started from the coefficient file at `path` (`touchdown train --start`): the file's
    contact law as the one candidate, its constants, friction and process noise as the guess and the start, the rig's
    active effects from the file's values where it fitted them, those it did not fit also from a fit of them alone (as
    diagnose fits a candidate; both starts refined, the lower kept). The rig YAML still says what is fitted (its
    effects, `training.*`); the axial support is fitted again from its grid (`training.axial_support: given`: the
    YAML's)."""
    loaded = load_coefficients(path, config)
    calibrated = loaded.config(config)
    given = config.training.axial_support == "given"
    law = calibrated.law.with_support(
        *((config.law.support_preload, config.law.support_span, config.law.support_log_covariance) if given else ())
    )
    print(f"stage 1 starts from {path}: {law.label}, friction {law.friction}", file=stream, flush=True)
    new = tuple(name for name in config.effects.names if name not in loaded.effects.names)
    return replace(
        calibrated, law=law, effects=_merge_effects(config.effects, loaded.effects),
        training=replace(config.training, contact_laws=(law,), friction_models=(), effects_alone_first=new),
    )


def checkpoint_path(out: Path) -> Path:
    return out.with_name(out.name + ".checkpoint")


def lambda_fit_path(out: Path, lam: float) -> Path:
    """Where an unfinished lambda path keeps a finished lambda's fit that was the lowest when it ended."""
    return out.with_name(f"{out.name}.checkpoint.lambda-{lam:g}")


@dataclass(frozen=True)
class TrainOutcome:
    """Both stages of `train`: the calibration (None when warm-started) and the PKBKR fit."""

    calibration: Calibration | None
    pkbkr: TrainingResult
    config: Config  # the calibrated rig the coefficients belong to
    mean_nis: tuple[float, ...]  # per bag, with the final model (3 for a consistent filter)
    seconds: float


#: The factors on Q the smoothing search may choose (ln-scale bounds) and its tolerance on ln s. At most the
#: likelihood's Q: it is sized for the model's bursts of error in contact, and the smoother wants less of it
#: (docs/calibration.md, "Process noise for the smoothed answer"); a factor above 1, chosen by a fall of the
#: leave-one-out error within its noise, made a held-out estimate worse and its band wider.
SMOOTHING_SCALE_RANGE = (0.02, 1.0)
SMOOTHING_SCALE_TOLERANCE = 0.05


class SmoothingScale(NamedTuple):
    """The factor on the fitted Q for the offline estimate and what chose it."""

    scale: float
    error_at_one: float | None  # m, leave-one-out smoothing error with the fitted Q
    error: float | None  # m, ... with Q times scale
    how: str
    fall: float | None = None  # m^2, mean fall per sample of the squared residual at the best factor found
    fall_standard_error: float | None = None  # m^2, its standard error (`core.smoothing.mean_fall_and_standard_error`)

    def as_dict(self) -> dict:
        def um(value: float | None) -> float | None:
            return None if value is None else round(value * 1e6, 5)

        errors = {"fitted_q": um(self.error_at_one), "chosen": um(self.error)}
        chosen = {"scale": round(self.scale, 4), "how": self.how, "leave_one_out_error_um": errors}
        if self.fall is not None:
            chosen["best_factor_fall_um2"] = {"mean": round(self.fall * 1e12, 6),
                                              "standard_error": round(self.fall_standard_error * 1e12, 6)}
        return chosen


def choose_smoothing_scale(
    model: Model, noise: FilterNoise, h: float, batch: Batch, stream=STDERR
) -> SmoothingScale:
    """The factor s on Q (within SMOOTHING_SCALE_RANGE) of the lowest leave-one-out smoothing error on
    the training records (`core.smoothing`), by a bounded scalar search on ln s, with progress. The
    fitted Q (s = 1) stays unless the best factor's fall of the squared residual exceeds its standard
    error: a fall within the noise of the cross-validation would only move the bands."""
    started = time.perf_counter()
    valid = np.asarray(batch.valid)
    squares: dict[float, np.ndarray] = {}
    typed_model = strongly_typed(model)  # the program `compile_stage2_ahead` queued

    def error(log_scale: float) -> float:
        scaled = noise._replace(process=np.asarray(noise.process) * np.exp(log_scale))
        squares[log_scale] = np.asarray(leave_one_out_squares(typed_model, strongly_typed(scaled), h, batch))
        value = float(np.sqrt(squares[log_scale].sum() / (valid.sum() * OUTPUT_SIZE)))
        print(
            f"[smoothing noise] Q x{np.exp(log_scale):.3g}: leave-one-out error {value * 1e6:.4f} um  "
            f"{time.perf_counter() - started:.1f} s elapsed",
            file=stream,
            flush=True,
        )
        return value

    at_one = error(0.0)
    low, high = (float(np.log(v)) for v in SMOOTHING_SCALE_RANGE)
    found = minimize_scalar(error, bounds=(low, high), method="bounded", options={"xatol": SMOOTHING_SCALE_TOLERANCE})
    if float(found.x) not in squares:
        error(float(found.x))
    fall, standard_error = mean_fall_and_standard_error(squares[0.0], squares[float(found.x)], valid)
    how = f"cross-validation: the lowest leave-one-out smoothing error of Q x{SMOOTHING_SCALE_RANGE[0]:g}..x" \
          f"{SMOOTHING_SCALE_RANGE[1]:g} on the training bags"
    if found.fun < at_one and fall > standard_error:
        scale, best = float(np.exp(found.x)), float(found.fun)
    else:
        scale, best = 1.0, at_one
        how += f", the fitted Q: Q x{np.exp(found.x):.3g}'s fall is within its standard error"
    print(
        f"[smoothing noise] the offline estimate uses Q x{scale:.3g} ({how}; the best factor's fall of the squared "
        f"residual {fall * 1e12:.4g} +- {standard_error * 1e12:.2g} um^2 per sample)",
        file=stream,
        flush=True,
    )
    return SmoothingScale(scale, at_one, best, how, fall, standard_error)


class ModelForceError(NamedTuple):
    """The model's own force error in contact on the training records (`core.smoothing.missing_force_squares`)."""

    variance: tuple[float, float, float] | None  # N^2 per axis; None: no sample in contact
    samples: int  # samples counted (in contact, with the next sample present)

    def as_dict(self) -> dict:
        rms = None if self.variance is None else [round(float(np.sqrt(v)), 1) for v in self.variance]
        return {
            "rms_N": rms,
            "samples": self.samples,
            "how": "the force the smoothed estimate adds to the model in contact on the training bags, "
                   "m (v_{k+1|N} - f(xi_{k|N}))_v / h, its mean square per axis: filter.force_model_variance",
        }


def model_force_error(model: Model, noise: FilterNoise, h: float, batch: Batch, stream=STDERR) -> ModelForceError:
    """The model's own force error in contact on the training records, with the offline estimate's `noise`,
    for the force band (`Config.force_model_variance`), with progress."""
    squares, counted = missing_force_squares(strongly_typed(model), strongly_typed(noise), h, batch)
    variance = mean_missing_force_variance(squares, counted)
    error = ModelForceError(None if variance is None else tuple(float(v) for v in variance), int(np.sum(counted)))
    said = "none in contact: the band reads Q as a force" if variance is None else \
        "rms " + " / ".join(f"{v:.0f}" for v in np.sqrt(variance)) + " N (x / y / z)"
    print(f"[force band] the model's own force error in contact on {error.samples} training samples: {said}",
          file=stream, flush=True)
    return error


def train(
    config: Config,
    bags: Sequence[str | Path],
    out: Path,
    regularisation: float | None = None,
    init: Path | None = None,
    resume: bool = False,
    max_steps: int | None = None,
    duration: float | None = None,
    stream=STDERR,
    start: Path | None = None,
) -> TrainOutcome:
    """Validate all bags, identify the rig (stage 1, `calibrate`), place the kernel centres on the
    data, fit PKBKR around the calibrated constants (stage 2, `fit`) and write the coefficient file
    (a checkpoint after every stage-2 step). With `init`, stage 1 is taken from that file and the
    lambda path (`fit_regularisation_path`) starts from its coefficients. With `start`, stage 1 runs from that
    file's calibration (`calibration_started_from`), as diagnose fits a candidate. With `resume`, stage 1 is
    the checkpoint's and the path goes on where it stopped: the lambdas it finished are not fitted
    again (the lowest of them was kept beside the checkpoint, `lambda_fit_path`), the interrupted
    one continues from the checkpoint's coefficients, the later ones start from stage 1's model.
    Stage 2's program, the standard errors' and the smoothing noise's are compiled in a background thread
    while stage 1 runs (`Ahead`)."""
    with Ahead(stream) as ahead:
        return _train(config, bags, out, regularisation, init, resume, max_steps, duration, stream, ahead, start)


def _train(
    config: Config,
    bags: Sequence[str | Path],
    out: Path,
    regularisation: float | None,
    init: Path | None,
    resume: bool,
    max_steps: int | None,
    duration: float | None,
    stream,
    ahead: Ahead,
    start: Path | None = None,
) -> TrainOutcome:
    started = time.perf_counter()
    lambdas = config.regularisation if regularisation is None else (regularisation,)
    steps = config.training.pkbkr_steps if max_steps is None else max_steps
    data = load_training_data(config, bags, duration)
    start_from = checkpoint_path(out) if resume else init
    calibration, notes, progress = None, [], PathProgress()
    if start_from is not None:
        if resume and not start_from.exists():
            raise FileNotFoundError(f"{start_from}: no checkpoint to resume from")
        loaded = load_coefficients(start_from, config)
        calibrated = loaded.config(config)
        initial = Trainable(loaded.coeffs, _merge_effects(config.effects, loaded.effects))
        stage1 = dict(loaded.training.extra.get("calibration") or {}, taken_from=str(start_from))
        if resume and "stage2_start_effects" in loaded.training.extra:
            initial, progress = _resumed_path(config, calibrated, out, loaded.training.extra, initial)
    else:
        if start is not None:
            config = calibration_started_from(config, start, stream)
        frictions = config.training.friction_models
        if frictions and frictions != (config.law.friction,):
            calibration = calibrate_frictions(config, data, stream)
            compile_stage2_ahead(ahead, calibration.config, data)
            ahead.start()
        else:
            compile_stage2_ahead(ahead, config, data)
            calibration = calibrate_stage1(config, data, ahead, stream)
        calibrated = calibration.config
        stage1 = calibration.summary() if start is None else {**calibration.summary(), "started_from": str(start)}
        if config.training.placement == "data":
            placing = time.perf_counter()
            states, _ = filtered_records(
                calibrated.model(effects=calibration.effects), calibrated.noise, config.sample_period,
                stage1_batches(calibrated, data, calibration.effects).chunks,
            )
            radial, axial = contact_samples(calibrated.model(), states)
            kernel, notes = kernel_from_data(calibrated.kernel, radial, axial)
            calibrated = replace(calibrated, kernel=kernel)
            print(f"[kernel centres] placed on the deformations and velocities the calibrated model filters  "
                  f"{time.perf_counter() - placing:.1f} s elapsed", file=stream, flush=True)
            for note in notes:
                print(f"note: {note}", file=stream)
        initial = Trainable(Coefficients.zeros(calibrated.kernel), calibration.effects)
    calibrated = replace(calibrated, effects=initial.effects)
    hashes = [{"path": str(p), "sha256": sha256_of(p)} for p in data.paths]

    def record(lam: float, steps: int, final_loss: float | None, **extra) -> TrainingRecord:
        return TrainingRecord(
            bags=hashes, regularisation=lam, final_loss=final_loss, steps=steps, extra={"calibration": stage1, **extra}
        )

    finished = [progress]  # the path's progress at its last finished lambda

    def on_step(lam: float, step: int, value: float, fitted: Trainable) -> None:
        so_far = {"tried": list(finished[0].tried), "best": _best_record(finished[0])}
        save_coefficients(
            checkpoint_path(out), fitted.coeffs, calibrated,
            record(lam, step, value, checkpoint=True, stage2_start_effects=initial.effects.values(),
                   regularisation_path_so_far=so_far),
            fitted.effects,
        )

    def on_lambda(so_far: PathProgress) -> None:
        """Keep the lambda just finished, the lowest so far (`fit_regularisation_path` calls this only then)."""
        fitted, lam, _ = so_far.chosen
        save_coefficients(
            lambda_fit_path(out, lam), fitted.coeffs, calibrated, record(lam, fitted.steps, fitted.final_loss),
            fitted.effects,
        )
        finished[0] = so_far

    ahead.wait(STAGE2_PROGRAM)
    path = fit_regularisation_path(
        calibrated, data, lambdas, initial, steps, on_step, stream,
        knob=f"--steps N (then --resume continues from {checkpoint_path(out)})",
        progress=progress, on_lambda=on_lambda,
    )
    result = path.result
    final = calibrated.model(result.coeffs, result.effects)
    batch = training_batch(calibrated, data, result.effects)
    chunks = stage1_batches(calibrated, data, result.effects).chunks  # stage 1's shape: its compiled filter serves
    _, nis = filtered_records(final, calibrated.noise, config.sample_period, chunks)
    if config.training.smoothing_noise == "cross_validation":
        ahead.wait(SMOOTHING_PROGRAM)
        smoothing = choose_smoothing_scale(final, calibrated.noise, config.sample_period, batch, stream)
        calibrated = replace(calibrated, smoothing_noise_scale=smoothing.scale)
    else:
        smoothing = SmoothingScale(1.0, None, None, "likelihood: the fitted Q as it is")
        print("[smoothing noise] the offline estimate uses the fitted Q, as the live filter "
              "(training.smoothing_noise: likelihood)", file=stream, flush=True)
    ahead.wait(MISSING_FORCE_PROGRAM)
    force_error = model_force_error(final, calibrated.offline_noise(), config.sample_period, batch, stream)
    calibrated = replace(calibrated, force_model_variance=force_error.variance)
    mean_nis = tuple(float(np.nanmean(row)) for row in nis)
    seconds = time.perf_counter() - started
    save_coefficients(
        out,
        result.coeffs,
        calibrated,
        record(
            path.regularisation,
            result.steps,
            result.final_loss,
            initial_loss=result.initial_loss,
            seconds=round(seconds, 2),
            loss=config.training.loss,
            pkbkr=result.convergence.as_dict() if result.convergence else {},
            regularisation_path=path.as_dict(),
            kernel_notes=notes,
            mean_nis={str(p): round(v, 3) for p, v in zip(data.paths, mean_nis)},
            smoothing_noise=smoothing.as_dict(),
            force_model_error=force_error.as_dict(),
        ),
        result.effects,
    )
    checkpoint_path(out).unlink(missing_ok=True)
    for kept in out.parent.glob(glob.escape(out.name) + ".checkpoint.lambda-*"):  # `lambda_fit_path`
        kept.unlink()
    return TrainOutcome(calibration, result, calibrated, mean_nis, seconds)


def _best_record(progress: PathProgress) -> dict | None:
    """The checkpoint's note of the lowest fit so far (its coefficients: `lambda_fit_path`)."""
    if progress.chosen is None:
        return None
    fitted, lam, loss = progress.chosen
    return {"regularisation": lam, "held_out_loss": loss, "steps": fitted.steps, "initial_loss": fitted.initial_loss,
            "final_loss": fitted.final_loss}


def _resumed_path(
    config: Config, calibrated: Config, out: Path, extra: Mapping[str, Any], current: Trainable
) -> tuple[Trainable, PathProgress]:
    """(the start of the lambdas not yet begun, the interrupted path) from a checkpoint's record."""
    start = Trainable(Coefficients.zeros(calibrated.kernel), config.effects.with_values(extra["stage2_start_effects"]))
    so_far = extra.get("regularisation_path_so_far") or {}
    best, chosen, fits = so_far.get("best"), None, []
    tried = tuple(so_far.get("tried") or ())

    def kept_fit(record: Mapping[str, Any]) -> TrainingResult:
        """A finished lambda's fit from its file (`lambda_fit_path`) and its record's losses."""
        kept = load_coefficients(lambda_fit_path(out, float(record["regularisation"])), config)
        return TrainingResult(kept.coeffs, _merge_effects(config.effects, kept.effects), record["initial_loss"],
                              record["final_loss"], record["steps"], 0.0, ())

    if best is not None:
        chosen = (kept_fit(best), float(best["regularisation"]), float(best["held_out_loss"]))
    if config.training.regularisation_choice == "one_standard_error":
        # the rule may choose any finished lambda: each was the lowest when it ended, so its fit was kept, and its
        # record carries its losses
        fits = [(float(t["regularisation"]), kept_fit(t)) for t in tried if HELD_OUT_BLOCKS in t]
    return start, PathProgress(tried, chosen, current, tuple(fits))
