"""Fit the PKBKR coefficients of eq. 18 over many bags (L-BFGS on the AD gradient)."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import jax
import numpy as np
import scipy.optimize
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from touchdown_ros.core.effects import Effects, gates_for
from touchdown_ros.core.estimate import detect_drop, to_grid
from touchdown_ros.core.training import RECORDS, Batch, loss, make_batch, pad_records
from touchdown_ros.core.types import Coefficients
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


@dataclass(frozen=True)
class TrainingResult:
    coeffs: Coefficients
    effects: Effects
    initial_loss: float
    final_loss: float
    steps: int
    seconds: float
    history: tuple[float, ...]


def load_training_data(config: Config, paths: Sequence[str | Path], duration: float | None = None) -> TrainingData:
    """Read and validate every bag (all of them before any work), keep the samples after the drop."""
    records, conditions = [], []
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
    return TrainingData(tuple(Path(p) for p in paths), tuple(records), tuple(conditions))


class Trainable(NamedTuple):
    """What the trainer fits: the PKBKR coefficients and the active effects' parameters."""

    coeffs: Coefficients
    effects: Effects


def _scales(effects: Effects) -> Effects:
    """Each effect parameter's magnitude (its starting value, at least 1e-6): the optimiser works
    on parameter / scale so that a load in N and a ratio share one step length."""
    return Effects(effects.effects, tuple({k: max(abs(float(v)), 1e-6) for k, v in p.items()} for p in effects.params))


def _apply_scale(scaled: Effects, scales: Effects, inverse: bool = False) -> Effects:
    combine = (lambda v, s: v / s) if inverse else (lambda v, s: v * s)
    return Effects(
        scaled.effects, tuple({k: combine(v, s[k]) for k, v in p.items()} for p, s in zip(scaled.params, scales.params))
    )


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


def make_objective(config: Config, regularisation: float) -> Callable:
    """Jitted (loss, gradient) of eq. 18 in (coefficients, scaled effect parameters), the records
    spread over `record_mesh()`; the batch is an argument (`place`d on that mesh), so batches of
    one shape (e.g. cross-validation folds) share one compilation."""
    model, mesh = config.model(), record_mesh()

    def objective(trainable: Trainable, scales: Effects, batch: Batch) -> jax.Array:
        effects = _apply_scale(trainable.effects, scales)
        noise = config.training_noise()
        return loss(trainable.coeffs, model, noise, config.sample_period, batch, regularisation, effects, mesh)

    return jax.jit(jax.value_and_grad(objective))


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
) -> TrainingResult:
    """Minimise eq. 18 with L-BFGS from `initial` (default: all alpha = 0, the constant model,
    and the rig's effects at their configured values).

    objective: a `make_objective` result to reuse; length: pad records to this many samples.
    """
    start = time.perf_counter()
    if initial is None or isinstance(initial, Coefficients):
        initial = Trainable(initial if initial is not None else Coefficients.zeros(config.kernel), config.effects)
    scales = _scales(initial.effects)
    conditions = data.conditions or ({},) * len(data.records)
    gates = [gates_for(initial.effects, c) for c in conditions]
    mesh = record_mesh()
    batch = place(make_batch(list(data.records), np.asarray(config.noise.initial), length, gates), mesh)
    for index, name in enumerate(initial.effects.names):
        if not any(g[index] for g in gates):
            print(
                f"note: effect {name} acts in none of the bags (it needs condition "
                f"{initial.effects.effects[index].when!r}); its parameters stay at their starting values",
                file=stream,
            )
    objective = objective or make_objective(config, regularisation)
    theta0, unravel = ravel_pytree(Trainable(initial.coeffs, _apply_scale(initial.effects, scales, inverse=True)))
    # (the effects' gates ride along in theta, but the loss replaces them by each record's gates,
    # so their gradient is zero and they never move)
    theta0 = np.asarray(theta0, dtype=float)

    def physical(theta: np.ndarray) -> Trainable:
        scaled = unravel(theta)
        return Trainable(scaled.coeffs, _apply_scale(scaled.effects, scales))

    history: list[float] = []
    last: dict[bytes, tuple[float, np.ndarray]] = {}  # L-BFGS asks again for the point we start from

    def fun(theta: np.ndarray):
        key = theta.tobytes()
        if key in last:
            return last[key]
        value, grad = objective(unravel(theta), scales, batch)
        value = float(value)
        if not np.isfinite(value):
            raise FloatingPointError("training loss is not finite; check the bags and the noise settings")
        last.clear()
        last[key] = value, np.asarray(ravel_pytree(jax.device_get(grad))[0], dtype=float)
        return last[key]

    def callback(intermediate_result):
        history.append(float(intermediate_result.fun))
        step = len(history)
        elapsed = time.perf_counter() - start
        left = elapsed / step * (max_steps - step)
        effects = physical(intermediate_result.x).effects
        shown = "".join(f"  {e}.{k} {v:.5g}" for e, p in effects.values().items() for k, v in p.items())
        print(
            f"[step {step}/{max_steps}] loss {intermediate_result.fun:.6g}{shown}  "
            f"{elapsed:.1f} s elapsed, <= ~{left:.0f} s left",
            file=stream,
            flush=True,
        )
        if on_step is not None:
            on_step(step, float(intermediate_result.fun), physical(intermediate_result.x))

    initial_loss = fun(theta0)[0]
    print(f"[step 0/{max_steps}] loss {initial_loss:.6g} (compiled in {time.perf_counter() - start:.1f} s)", file=stream)
    result = scipy.optimize.minimize(
        fun, theta0, jac=True, method="L-BFGS-B", callback=callback, options={"maxiter": max_steps}
    )
    fitted = physical(result.x)
    return TrainingResult(
        coeffs=fitted.coeffs,
        effects=fitted.effects,
        initial_loss=initial_loss,
        final_loss=float(result.fun),
        steps=int(result.nit),
        seconds=time.perf_counter() - start,
        history=tuple(history),
    )


def _merge_effects(active: Effects, started: Effects) -> Effects:
    """The rig's active effects, starting from a warm-start file's values where it has them.

    The rig YAML decides which effects are fitted; an effect of the file that the rig does not
    switch on is dropped, with a note, rather than silently kept."""
    dropped = sorted(set(started.names) - set(active.names))
    if dropped:
        print(f"note: the warm-start file's effect(s) {', '.join(dropped)} are not active in the rig; not fitted", file=sys.stderr)
    return active.with_values(started.values())


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
        loaded = load_coefficients(start_from, config)
        initial = Trainable(loaded.coeffs, _merge_effects(config.effects, loaded.effects))
    hashes = [{"path": str(p), "sha256": sha256_of(p)} for p in data.paths]

    def record(steps: int, final_loss: float | None, **extra) -> TrainingRecord:
        return TrainingRecord(bags=hashes, regularisation=lam, final_loss=final_loss, steps=steps, extra=extra)

    def on_step(step: int, value: float, fitted: Trainable) -> None:
        save_coefficients(
            checkpoint_path(out), fitted.coeffs, config, record(step, value, checkpoint=True), fitted.effects
        )

    result = fit(config, data, lam, initial, max_steps, on_step)
    save_coefficients(
        out,
        result.coeffs,
        config,
        record(result.steps, result.final_loss, initial_loss=result.initial_loss, seconds=round(result.seconds, 2)),
        result.effects,
    )
    checkpoint_path(out).unlink(missing_ok=True)
    return result
