"""Fit the PKBKR coefficients of eq. 18 over many bags (L-BFGS on the AD gradient)."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import jax
import numpy as np
import scipy.optimize

from touchdown_ros.core.estimate import detect_drop, to_grid
from touchdown_ros.core.training import Batch, loss, make_batch
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.bags import read_displacement
from touchdown_ros.io.coefficients import TrainingRecord, load_coefficients, save_coefficients, sha256_of
from touchdown_ros.io.config import Config
from touchdown_ros.offline import NoDropError


@dataclass(frozen=True)
class TrainingData:
    """Records from the drop onset on, with the bags they came from."""

    paths: tuple[Path, ...]
    records: tuple[np.ndarray, ...]  # each (N_b, 3) m, NaN rows for missing samples


@dataclass(frozen=True)
class TrainingResult:
    coeffs: Coefficients
    initial_loss: float
    final_loss: float
    steps: int
    seconds: float
    history: tuple[float, ...]


def load_training_data(config: Config, paths: Sequence[str | Path], duration: float | None = None) -> TrainingData:
    """Read and validate every bag (all of them before any work), keep the samples after the drop."""
    records = []
    for path in paths:
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
    return TrainingData(tuple(Path(p) for p in paths), tuple(records))


def _flatten(coeffs: Coefficients) -> np.ndarray:
    return np.concatenate([np.ravel(coeffs.alpha_R), np.ravel(coeffs.alpha_Z)])


def _unflatten(theta: np.ndarray, template: Coefficients) -> Coefficients:
    split = np.size(template.alpha_R)
    return Coefficients(
        np.reshape(theta[:split], np.shape(template.alpha_R)), np.reshape(theta[split:], np.shape(template.alpha_Z))
    )


def make_objective(config: Config, regularisation: float) -> Callable:
    """Jitted (loss, gradient) of eq. 18 in the coefficients; the batch is an argument, so
    batches of one shape (e.g. the folds of a cross-validation) share one compilation."""
    model = config.model()

    @jax.jit
    def value_and_grad(coeffs: Coefficients, batch: Batch):
        return jax.value_and_grad(loss)(coeffs, model, config.noise, config.sample_period, batch, regularisation)

    return value_and_grad


def fit(
    config: Config,
    data: TrainingData,
    regularisation: float,
    initial: Coefficients | None = None,
    max_steps: int = 40,
    on_step: Callable[[int, float, Coefficients], None] | None = None,
    stream=sys.stderr,
    objective: Callable | None = None,
    length: int | None = None,
) -> TrainingResult:
    """Minimise eq. 18 with L-BFGS from initial (default all alpha = 0, the constant model).

    objective: a `make_objective` result to reuse; length: pad records to this many samples.
    """
    start = time.perf_counter()
    template = initial if initial is not None else Coefficients.zeros(config.kernel)
    batch = make_batch(list(data.records), np.asarray(config.noise.initial), length)
    objective = objective or make_objective(config, regularisation)
    history: list[float] = []

    def fun(theta: np.ndarray):
        value, grad = objective(_unflatten(theta, template), batch)
        value = float(value)
        if not np.isfinite(value):
            raise FloatingPointError("training loss is not finite; check the bags and the noise settings")
        return value, _flatten(jax.device_get(grad)).astype(float)

    def callback(intermediate_result):
        history.append(float(intermediate_result.fun))
        step = len(history)
        elapsed = time.perf_counter() - start
        left = elapsed / step * (max_steps - step)
        print(
            f"[step {step}/{max_steps}] loss {intermediate_result.fun:.6g}  {elapsed:.1f} s elapsed, <= ~{left:.0f} s left",
            file=stream,
            flush=True,
        )
        if on_step is not None:
            on_step(step, float(intermediate_result.fun), _unflatten(intermediate_result.x, template))

    theta0 = _flatten(template)
    initial_loss = fun(theta0)[0]
    print(f"[step 0/{max_steps}] loss {initial_loss:.6g} (compiled in {time.perf_counter() - start:.1f} s)", file=stream)
    result = scipy.optimize.minimize(
        fun, theta0, jac=True, method="L-BFGS-B", callback=callback, options={"maxiter": max_steps}
    )
    return TrainingResult(
        coeffs=_unflatten(result.x, template),
        initial_loss=initial_loss,
        final_loss=float(result.fun),
        steps=int(result.nit),
        seconds=time.perf_counter() - start,
        history=tuple(history),
    )


def checkpoint_path(out: Path) -> Path:
    return out.with_name(out.name + ".checkpoint")


def train(
    config: Config,
    bags: Sequence[str | Path],
    out: Path,
    regularisation: float | None = None,
    init: Path | None = None,
    resume: bool = False,
    max_steps: int = 40,
    duration: float | None = None,
) -> TrainingResult:
    """Validate all bags, fit, and write the coefficient file (with a checkpoint after every step)."""
    lam = config.regularisation if regularisation is None else regularisation
    data = load_training_data(config, bags, duration)
    initial = None
    start_from = checkpoint_path(out) if resume else init
    if start_from is not None:
        if resume and not start_from.exists():
            raise FileNotFoundError(f"{start_from}: no checkpoint to resume from")
        initial = load_coefficients(start_from, config).coeffs
    hashes = [{"path": str(p), "sha256": sha256_of(p)} for p in data.paths]

    def record(steps: int, final_loss: float | None, **extra) -> TrainingRecord:
        return TrainingRecord(bags=hashes, regularisation=lam, final_loss=final_loss, steps=steps, extra=extra)

    def on_step(step: int, value: float, coeffs: Coefficients) -> None:
        save_coefficients(checkpoint_path(out), coeffs, config, record(step, value, checkpoint=True))

    result = fit(config, data, lam, initial, max_steps, on_step)
    save_coefficients(
        out,
        result.coeffs,
        config,
        record(result.steps, result.final_loss, initial_loss=result.initial_loss, seconds=round(result.seconds, 2)),
    )
    checkpoint_path(out).unlink(missing_ok=True)
    return result
