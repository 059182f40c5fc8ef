"""`touchdown diagnose`: where the model fails and which physical effect it lacks (issue #5).

Orchestration only: bags are read and estimated as `touchdown estimate` does, every number
comes from `core.diagnostics` (pure functions), the tables and figures are written by
`report.diagnosis`. With two coefficient sets (before / after) everything is computed for
both and shown side by side.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from touchdown_ros.core import effects as fx
from touchdown_ros.core.diagnostics.breakdown import contact_phase, regions, windowed_rms
from touchdown_ros.core.diagnostics.frols import RecordRegressors, Ranking, frols_verdict, rank_effects, ranking_rows
from touchdown_ros.core.diagnostics.missing_force import MissingForce, disturbance_smoother, missing_force_table
from touchdown_ros.core.diagnostics.prediction import error_metrics, k_step_predictions
from touchdown_ros.core.diagnostics.regressors import coefficient_regressors, library_regressors
from touchdown_ros.core.diagnostics.residuals import residual_tests
from touchdown_ros.core.diagnostics.signature import signature
from touchdown_ros.core.dynamics import measurement as expected_output
from touchdown_ros.core.estimate import PAD_BUCKET, initial_belief
from touchdown_ros.core.impacts import impact_numbers
from touchdown_ros.core.orbit import candidate_starts, describe_starts
from touchdown_ros.core.types import Model
from touchdown_ros.io.bags import read_conditions
from touchdown_ros.io.coefficients import load_coefficients
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.candidates import FitSettings, candidates_to_fit, fit_candidates, fitted_verdict
from touchdown_ros.workflows.offline import BagEstimate, bag_effects, estimate_bag, estimator_for
from touchdown_ros.workflows.progress import STDERR, progress
from touchdown_ros.workflows.report.diagnosis import CONSTANT_MODEL, write_diagnosis
from touchdown_ros.workflows.training_data import load_training_data


@dataclass(frozen=True)
class Settings:
    k: int = 20  # samples ahead of the k-step prediction (20 = 2 ms at 10 kHz)
    force_walk: float = 30.0  # N rms per sample: random walk of the missing-force states
    threshold: float = 0.5  # best candidate's ERR below this: "unexplained" (FROLS alone, fitted = 0)
    fitted: int = 3  # FROLS's best this many candidates are fitted and judged on held-out samples (0: none)
    max_lag: int = 100  # samples of the residual tests
    window: float = 0.005  # s, windows of the error-over-time table
    deformation_bins: int = 8
    velocity_bins: int = 8


@dataclass
class BagDiagnosis:
    path: Path
    result: BagEstimate
    k_step: np.ndarray  # (N, 3) m, k-step-ahead predicted measurement h(xi)
    missing: MissingForce  # numpy fields
    phase: np.ndarray  # (N,) 0..3 (PHASES)
    impact: np.ndarray  # (N,) impact number, 0 before the first
    conditions: dict[str, str]
    model: Model  # the gated model of this bag
    metrics: dict[str, Any] = field(default_factory=dict)


@dataclass
class Diagnosis:
    label: str
    coefficients: str  # the coefficient file, or CONSTANT_MODEL
    effects: dict
    bags: list[BagDiagnosis]
    metrics: dict[str, Any]
    ranking: Ranking
    verdict: dict[str, Any]
    signature: dict[str, Any]
    tests: dict[str, Any]
    notes: list[str] = field(default_factory=list)  # what qualifies the verdict (`verdict_notes`)


def verdict_notes(calibration_notes: Sequence[str], friction: str, verdict: dict[str, Any]) -> list[str]:
    """What qualifies a diagnosis: the coefficient file's calibration notes, and, where the paper's friction
    (an inner ring at rest) meets a verdict for cross_coupled_stiffness, that this candidate also stands in
    for the forward whirl drive of friction against a turning inner ring, which that friction lacks."""
    notes = [f"Calibration: {note}" for note in calibration_notes]
    if friction == "paper" and verdict.get("explained") and verdict.get("best") == "cross_coupled_stiffness":
        notes.append(
            "cross_coupled_stiffness also stands in for the forward whirl drive of friction against an inner ring "
            "the rotor has spun up, which the paper's friction (a ring at rest) lacks; where the ring turns freely, "
            "diagnose a model trained with contact.friction: spinning_ring before reading it as a seal's or fluid's "
            "cross-coupling (docs/workbench.md)"
        )
    return notes


# ---------------------------------------------------------------- compiled pieces (cached per model)

class _Compiled:
    """Jitted k-step prediction, disturbance smoother and regressors; the model is an argument,
    so one compilation serves every model of the same structure (`_compiled` caches them per
    settings), and records are padded to PAD_BUCKET samples so bags of similar length
    share it too."""

    def __init__(self, h: float, k: int, force_walk: float, process: tuple, measurement: tuple):
        process, measurement = np.asarray(process), np.asarray(measurement)
        self.k_step = jax.jit(lambda m, s: jax.vmap(lambda x: expected_output(m, x))(k_step_predictions(m, s, h, k)))
        self.smooth = jax.jit(
            lambda m, init, etas: disturbance_smoother(m, process, measurement, init, etas, h, force_walk)
        )
        self.coefficient_regressors = jax.jit(coefficient_regressors)
        self.library_regressors = jax.jit(
            lambda m, s, at: library_regressors(fx.LIBRARY, s, m, at, h * jnp.arange(s.shape[0]))
        )


@functools.lru_cache(maxsize=4)
def _compiled_for(h: float, k: int, force_walk: float, process: tuple, measurement: tuple) -> _Compiled:
    return _Compiled(h, k, force_walk, process, measurement)


def _compiled(config: Config, settings: Settings) -> _Compiled:
    noise = config.noise
    return _compiled_for(
        float(config.sample_period),
        int(settings.k),
        float(settings.force_walk),
        tuple(float(v) for v in np.asarray(noise.process)),
        tuple(float(v) for v in np.asarray(noise.measurement)),
    )


def _pad(a: np.ndarray, repeat: bool = False) -> np.ndarray:
    """a padded to a multiple of PAD_BUCKET rows: NaN rows (measurements: predict only) or
    repeats of the last row (states: the padding stays physical)."""
    size = -(-len(a) // PAD_BUCKET) * PAD_BUCKET
    padded = np.empty((size, *a.shape[1:]), dtype=float)
    padded[: len(a)] = a
    padded[len(a) :] = a[-1] if repeat else np.nan
    return padded


def _diagnose_bag(config: Config, path: Path, estimator, compiled: _Compiled, settings: Settings) -> BagDiagnosis:
    result = estimate_bag(config, path, estimator, fit_noise=False)  # every model on the same Q
    est = result.estimate
    n = len(est.measured)
    model = estimator.model._replace(effects=bag_effects(config, path, estimator.model.effects))
    filtered = np.asarray(est.filtered.state)
    k_step = np.asarray(compiled.k_step(model, jnp.asarray(_pad(filtered, repeat=True))))[:n]
    init = initial_belief(est.measured, np.asarray(config.noise.initial))
    missing = compiled.smooth(model, init, jnp.asarray(_pad(est.measured)))
    missing = MissingForce(*(np.asarray(a)[:n] for a in missing))
    smoothed = est.smoothed
    phase = contact_phase(np.asarray(smoothed.radial_contact), np.asarray(smoothed.axial_contact))
    impact = impact_numbers(phase > 0)
    return BagDiagnosis(Path(path), result, k_step, missing, phase, impact, read_conditions(path), model)


def _stack(bags: Sequence[BagDiagnosis], getter) -> np.ndarray:
    return np.concatenate([getter(b) for b in bags])


def _force_error(b: BagDiagnosis) -> np.ndarray | None:
    truth = b.result.truth
    if truth is None:
        return None
    return np.asarray(b.result.estimate.filtered.force_xyz) - truth.contact_force


def _regressors(b: BagDiagnosis, compiled: _Compiled, at: dict[str, dict[str, float]]) -> RecordRegressors:
    """The regressors of FROLS along one bag's smoothed states (padded, so that bags share compilations),
    the candidates linearised at their defaults or where `at` puts them."""
    n = len(b.phase)
    states = jnp.asarray(_pad(b.missing.state, repeat=True))
    coefficients = np.asarray(compiled.coefficient_regressors(b.model, states))[:n]
    regressors = compiled.library_regressors(b.model, states, at)
    effects = {name: tuple(np.asarray(a)[:n] for a in pair) for name, pair in regressors.items()}
    return RecordRegressors(b.missing.force, b.missing.force_std, coefficients, effects)


# ---------------------------------------------------------------- one model over all bags

def diagnose(
    config: Config,
    bags: Sequence[Path],
    coefficient_file: Path | None = None,
    settings: Settings = Settings(),
    label: str = "model",
    stream=STDERR,
) -> Diagnosis:
    """Estimate every bag with one model and compute all the diagnostics."""
    coeffs = effects = None
    calibration_notes: list[str] = []
    if coefficient_file is not None:
        loaded = load_coefficients(coefficient_file, config)
        coeffs, effects, config = loaded.coeffs, loaded.effects, loaded.config(config)
        calibration_notes = loaded.calibration_notes
    estimator = estimator_for(config, coeffs, effects)
    compiled = _compiled(config, settings)
    results = []
    for path in progress(bags, len(bags), f"diagnose {label}", stream=stream):
        results.append(_diagnose_bag(config, Path(path), estimator, compiled, settings))

    for b in results:
        est = b.result.estimate
        b.metrics = error_metrics(
            est.measured, np.asarray(est.predicted_output), b.k_step, _force_error(b), b.phase, b.impact
        )
    has_truth = all(b.result.truth is not None for b in results)
    metrics = error_metrics(
        _stack(results, lambda b: b.result.estimate.measured),
        _stack(results, lambda b: np.asarray(b.result.estimate.predicted_output)),
        _stack(results, lambda b: b.k_step),
        _stack(results, _force_error) if has_truth else None,
        _stack(results, lambda b: b.phase),
        _stack(results, lambda b: b.impact),
    )
    metrics["missing_force"] = missing_force_table(
        _stack(results, lambda b: b.missing.force),
        _stack(results, lambda b: b.missing.force_std),
        _stack(results, lambda b: b.phase),
    )
    windows = max(1, int(round(settings.window / config.sample_period)))
    metrics["k_step_rmse_over_time_m"] = {
        b.path.name: windowed_rms(b.k_step - b.result.estimate.measured, windows).tolist() for b in results
    }
    metrics["regions"] = regions(
        config.contact_rig,
        _stack(results, lambda b: np.asarray(b.result.estimate.smoothed.state)),
        np.linalg.norm(_stack(results, lambda b: b.k_step - b.result.estimate.measured), axis=1),
        settings.deformation_bins,
        settings.velocity_bins,
    )
    tests = residual_tests(
        config.contact_rig,
        [b.result.estimate.innovation for b in results],
        [b.result.estimate.smoothed.state for b in results],
        settings.max_lag,
    )
    # A speed effect's force is far from linear in its parameters (a braked rotor's unbalance lags by
    # radians): it is ranked (linearised) and fitted from where its speed fits the bags' orbits, when they show
    # it, and then fitted whatever its rank (`candidates_to_fit`). So is a sensor offset the orbits' centre
    # shows: from zero its fit moves only with the contact constants and can stop on the way.
    library = [e for name, e in fx.LIBRARY.items() if name not in estimator.model.effects.names]
    starts = candidate_starts(library, config.rig, [b.result.estimate.measured for b in results], config.sample_period)
    for line in describe_starts(starts, {name: fx.LIBRARY[name].defaults() for name in starts}):
        print(f"[diagnose {label}] {line}", file=stream, flush=True)
    print(f"[diagnose {label}] ranking candidate effects (FROLS)", file=stream, flush=True)
    ranking = rank_effects([_regressors(b, compiled, starts) for b in results], fx.LIBRARY, starts)
    rows = ranking_rows(ranking, fx.LIBRARY, [b.path.name for b in results])
    verdict = frols_verdict(ranking, rows, settings.threshold)
    if settings.fitted:
        names = candidates_to_fit([row["candidate"] for row in rows], settings.fitted, list(starts))
        shown = names[settings.fitted:]
        print(
            f"[diagnose {label}] fitting the {settings.fitted} best candidates"
            + (f" and {', '.join(shown)} (the orbits show its speed)" if shown else "")
            + " (held-out blocks)",
            file=stream,
            flush=True,
        )
        selection = fit_candidates(
            config, estimator.model, load_training_data(config, bags), names,
            FitSettings(k=settings.k, friction_grid=True), stream, starts,
        )
        verdict = fitted_verdict(verdict, selection)
    missing_signature = signature(
        config.contact_rig,
        config.sample_period,
        [b.missing.force for b in results],
        [b.missing.state for b in results],
        [b.phase for b in results],
    )
    return Diagnosis(
        label=label,
        coefficients=str(coefficient_file) if coefficient_file else CONSTANT_MODEL,
        effects=estimator.model.effects.values(),
        bags=results,
        metrics=metrics,
        ranking=ranking,
        verdict=verdict,
        signature=missing_signature,
        tests=tests,
        notes=verdict_notes(calibration_notes, config.law.friction, verdict),
    )


def run(
    config: Config,
    bags: Sequence[Path],
    out: Path,
    coeffs: Path | None = None,
    compare: Path | None = None,
    settings: Settings = Settings(),
    stream=STDERR,
) -> dict[str, Any]:
    """Diagnose the model of `coeffs` (default: the rig's constant model) and, with `compare`,
    a second coefficient file (after) side by side; write everything to out."""
    diagnoses = [diagnose(config, bags, coeffs, settings, "before" if compare else "model", stream)]
    if compare is not None:
        diagnoses.append(diagnose(config, bags, compare, settings, "after", stream))
    return write_diagnosis(diagnoses, config, out, settings)
