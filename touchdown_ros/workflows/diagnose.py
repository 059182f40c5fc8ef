"""`touchdown diagnose`: where the model fails and which physical effect it lacks (issue #5).

Orchestration only: bags are read and estimated as `touchdown estimate` does, every number
comes from `core.diagnostics` (pure functions), tables and figures are written here and by
`report_diagnosis` below. With two coefficient sets (before / after) everything is
computed for both and shown side by side.
"""
from __future__ import annotations

import csv
import functools
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from touchdown_ros.core import diagnostics as dg
from touchdown_ros.core import effects as fx
from touchdown_ros.core.dynamics import measurement as expected_output
from touchdown_ros.core.estimate import PAD_BUCKET, initial_belief
from touchdown_ros.core.impacts import impact_numbers
from touchdown_ros.core.metrics import rmse
from touchdown_ros.core.types import Model
from touchdown_ros.io.bags import read_conditions
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.offline import BagEstimate, bag_effects, estimate_bag, estimator_for
from touchdown_ros.workflows.progress import progress

AXES = ("x", "y", "z")


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
    missing: dg.MissingForce  # numpy fields
    phase: np.ndarray  # (N,) 0..3 (dg.PHASES)
    impact: np.ndarray  # (N,) impact number, 0 before the first
    conditions: dict[str, str]
    model: Model  # the gated model of this bag
    metrics: dict[str, Any] = field(default_factory=dict)


@dataclass
class Diagnosis:
    label: str
    coefficients: str
    effects: dict
    bags: list[BagDiagnosis]
    metrics: dict[str, Any]
    ranking: dg.Ranking
    verdict: dict[str, Any]
    signature: dict[str, Any]
    tests: dict[str, Any]


# ---------------------------------------------------------------- compiled pieces (cached per model)

class _Compiled:
    """Jitted k-step prediction, disturbance smoother and regressors; the model is an argument,
    so one compilation serves every model of the same structure (`_compiled` caches them per
    settings), and records are padded to PAD_BUCKET samples so bags of similar length
    share it too."""

    def __init__(self, h: float, k: int, force_walk: float, process: tuple, measurement: tuple):
        process, measurement = np.asarray(process), np.asarray(measurement)
        self.k_step = jax.jit(lambda m, s: jax.vmap(lambda x: expected_output(m, x))(dg.k_step_predictions(m, s, h, k)))
        self.smooth = jax.jit(
            lambda m, init, etas: dg.disturbance_smoother(m, process, measurement, init, etas, h, force_walk)
        )
        self.coefficient_regressors = jax.jit(dg.coefficient_regressors)
        self.effect_regressors = {
            name: jax.jit(lambda m, s, e=e: dg.effect_regressors(e, s, m)) for name, e in fx.LIBRARY.items()
        }


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
    result = estimate_bag(config, path, estimator)
    est = result.estimate
    n = len(est.measured)
    model = estimator.model._replace(effects=bag_effects(config, path, estimator.model.effects))
    filtered = np.asarray(est.filtered.state)
    k_step = np.asarray(compiled.k_step(model, jnp.asarray(_pad(filtered, repeat=True))))[:n]
    init = initial_belief(est.measured, np.asarray(config.noise.initial))
    missing = compiled.smooth(model, init, jnp.asarray(_pad(est.measured)))
    missing = dg.MissingForce(*(np.asarray(a)[:n] for a in missing))
    smoothed = est.smoothed
    phase = dg.contact_phase(np.asarray(smoothed.radial_contact), np.asarray(smoothed.axial_contact))
    impact = impact_numbers(phase > 0)
    return BagDiagnosis(Path(path), result, k_step, missing, phase, impact, read_conditions(path), model)


# ---------------------------------------------------------------- metrics

def _deformations(config: Config, state: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Radial deformation r - r0, radial velocity, axial compression -(z + z0), z velocity."""
    x, y, z, vx, vy, vz = (state[:, i] for i in (0, 1, 2, 4, 5, 6))
    r = np.hypot(x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        rdot = np.where(r > 0, (x * vx + y * vy) / r, 0.0)
    return r - config.rig.radial_clearance, rdot, -(z + config.rig.axial_clearance), vz


def _error_metrics(measured, one_step, k_step, force_error, phase, impact) -> dict[str, Any]:
    ek = k_step - measured
    by_phase, counts = dg.rms_by_label(ek, phase, range(4))
    force_phase = dg.rms_by_label(force_error, phase, range(4))[0] if force_error is not None else None
    impacts = [i for i in range(1, min(int(impact.max()) if impact.size else 0, 12) + 1)]
    by_impact, impact_counts = dg.rms_by_label(ek, impact, impacts)
    metrics: dict[str, Any] = {
        "samples": int(len(measured)),
        "one_step": {"rmse_m": rmse(one_step, measured).tolist(), "fit_percent": dg.fit_percent(measured, one_step).tolist()},
        "k_step": {"rmse_m": rmse(k_step, measured).tolist(), "fit_percent": dg.fit_percent(measured, k_step).tolist()},
        "phases": {
            name: {
                "samples": int(counts[i]),
                "k_step_rmse_m": by_phase[i].tolist(),
                **({"force_rmse_N": force_phase[i].tolist()} if force_phase is not None else {}),
            }
            for i, name in enumerate(dg.PHASES)
        },
        "impacts": [
            {"impact": n, "samples": int(c), "k_step_rmse_m": v.tolist()} for n, v, c in zip(impacts, by_impact, impact_counts)
        ],
    }
    metrics["k_step"]["rmse_norm_m"] = float(np.linalg.norm(metrics["k_step"]["rmse_m"]))
    metrics["one_step"]["rmse_norm_m"] = float(np.linalg.norm(metrics["one_step"]["rmse_m"]))
    if force_error is not None:
        force_rmse = rmse(force_error, np.zeros_like(force_error))
        metrics["contact_force"] = {"rmse_N": force_rmse.tolist(), "rmse_norm_N": float(np.linalg.norm(force_rmse))}
    return metrics


def _stack(bags: Sequence[BagDiagnosis], getter) -> np.ndarray:
    return np.concatenate([getter(b) for b in bags])


def _force_error(b: BagDiagnosis) -> np.ndarray | None:
    truth = b.result.truth
    if truth is None:
        return None
    return np.asarray(b.result.estimate.filtered.force_xyz) - truth.contact_force


def _residual_tests(config: Config, bags: Sequence[BagDiagnosis], max_lag: int) -> dict[str, Any]:
    """Whiteness of the innovations and their cross-correlation with velocity and deformation,
    per axis, pooled over bags (each bag's sequence tested, then the statistics averaged)."""
    tests: dict[str, Any] = {}
    for i, axis in enumerate(AXES):
        white, velocity, deformation = [], [], []
        for b in bags:
            e = np.asarray(b.result.estimate.innovation)[:, i]
            state = np.asarray(b.result.estimate.smoothed.state)
            d_r, _, d_z, _ = _deformations(config, state)
            white.append(dg.whiteness(e, max_lag))
            for store, u in ((velocity, state[:, 4 + i]), (deformation, d_z if axis == "z" else d_r)):
                _, r, band = dg.cross_correlation(e, u, max_lag)
                store.append({"max_abs": float(np.max(np.abs(r))), "outside_share": float(np.mean(np.abs(r) > band))})
        mean = lambda rows, key: float(np.mean([r[key] for r in rows]))  # noqa: E731
        tests[axis] = {
            "whiteness_outside_share": mean(white, "outside_share"),
            "whiteness_max_abs": mean(white, "max_abs"),
            "band": mean(white, "band"),
            "velocity_xcorr_max_abs": mean(velocity, "max_abs"),
            "velocity_xcorr_outside_share": mean(velocity, "outside_share"),
            "deformation_xcorr_max_abs": mean(deformation, "max_abs"),
            "deformation_xcorr_outside_share": mean(deformation, "outside_share"),
        }
    return tests


def _missing_force_table(bags: Sequence[BagDiagnosis]) -> dict[str, Any]:
    force = _stack(bags, lambda b: b.missing.force)
    std = _stack(bags, lambda b: b.missing.force_std)
    phase = _stack(bags, lambda b: b.phase)
    table = {}
    for i, name in enumerate(dg.PHASES):
        rows = phase == i
        if rows.any():
            table[name] = {
                "samples": int(rows.sum()),
                "mean_N": force[rows].mean(axis=0).tolist(),
                "rms_N": np.sqrt(np.mean(force[rows] ** 2, axis=0)).tolist(),
                "std_of_estimate_N": std[rows].mean(axis=0).tolist(),
            }
    table["all"] = {
        "samples": int(len(force)),
        "mean_N": force.mean(axis=0).tolist(),
        "rms_N": np.sqrt(np.mean(force**2, axis=0)).tolist(),
        "std_of_estimate_N": std.mean(axis=0).tolist(),
    }
    return table


# ---------------------------------------------------------------- ranking and signature

def _ranking(config: Config, bags: Sequence[BagDiagnosis], compiled: _Compiled) -> tuple[dg.Ranking, dict]:
    ys, forced, groups, blocks, offsets = [], [], [], {name: [] for name in fx.LIBRARY}, {}
    f0s, js = {name: [] for name in fx.LIBRARY}, {name: [] for name in fx.LIBRARY}
    for g, b in enumerate(bags):
        n = len(b.phase)
        weight = 1.0 / np.maximum(b.missing.force_std, 1e-9)  # rows weighted by the estimate's certainty
        states = jnp.asarray(_pad(b.missing.state, repeat=True))
        ys.append((b.missing.force * weight).reshape(-1))
        groups.append(np.full(3 * n, g))
        C = np.asarray(compiled.coefficient_regressors(b.model, states))[:n]
        forced.append((C * weight[..., None]).reshape(3 * n, -1))
        for name, function in compiled.effect_regressors.items():
            J, f0 = (np.asarray(a)[:n] for a in function(b.model, states))
            blocks[name].append((J * weight[..., None]).reshape(3 * n, -1))
            js[name].append(J)
            f0s[name].append(f0)
    for name, effect in fx.LIBRARY.items():
        p0 = np.array(list(effect.defaults().values()))
        offsets[name] = dg.linearisation_offset(np.concatenate(js[name]), np.concatenate(f0s[name]), p0)
    ranking = dg.frols(
        np.concatenate(ys),
        {name: np.concatenate(v) for name, v in blocks.items()},
        np.concatenate(forced),
        offsets,
        np.concatenate(groups),
    )
    return ranking, {name: list(e.parameters) for name, e in fx.LIBRARY.items()}


def _candidate_rows(ranking: dg.Ranking, parameter_names: dict, bags: Sequence[BagDiagnosis]) -> list[dict]:
    rows = []
    for rank, c in enumerate(ranking.candidates, start=1):
        names = parameter_names[c.name]
        rows.append(
            {
                "rank": rank,
                "candidate": c.name,
                "err_percent": 100.0 * c.err,
                "parameters": {
                    p: {
                        "value": float(c.values[j]),
                        "std": float(c.std[j]),
                        "ci95": [float(c.values[j] - 1.96 * c.std[j]), float(c.values[j] + 1.96 * c.std[j])],
                        "unit": fx.LIBRARY[c.name].parameters[p][1],
                        "per_bag": {b.path.name: float(c.group_values[g, j]) for g, b in enumerate(bags)},
                        "per_bag_std": {b.path.name: float(c.group_std[g, j]) for g, b in enumerate(bags)},
                    }
                    for j, p in enumerate(names)
                },
            }
        )
    return rows


def _signature(config: Config, bags: Sequence[BagDiagnosis]) -> dict[str, Any]:
    """What the missing force looks like: spectrum peak per axis vs rotor speed, and its
    dependence on contact phase, deformation and velocity (correlation coefficients)."""
    h = config.sample_period
    rotor_hz = config.rig.speed / (2.0 * np.pi)
    signature: dict[str, Any] = {"rotor_frequency_Hz": rotor_hz, "axes": {}}
    force = _stack(bags, lambda b: b.missing.force)
    state = _stack(bags, lambda b: b.missing.state)
    phase = _stack(bags, lambda b: b.phase)
    d_r, v_r, d_z, v_z = _deformations(config, state)
    for i, axis in enumerate(AXES):
        peaks = [dg.spectrum_peak(b.missing.force[:, i], h) for b in bags]
        freq = float(np.median([p[0] for p in peaks]))
        share = float(np.mean([p[1] for p in peaks]))
        # rotor angle of the model (omega t from the onset; each bag's phase fitted separately)
        harmonics = {
            n: float(np.nanmean([dg.harmonic_share(b.missing.force[:, i], b.missing.state[:, 3], n) for b in bags]))
            for n in (1, 2)
        }
        corr = {}
        for label, u in (
            ("axial deformation", d_z),
            ("axial velocity", v_z),
            ("radial deformation", d_r),
            ("radial velocity", v_r),
        ):
            ok = np.isfinite(u) & np.isfinite(force[:, i])
            corr[label] = float(np.corrcoef(force[ok, i], u[ok])[0, 1]) if np.std(u[ok]) > 0 else 0.0
        means = {dg.PHASES[p]: float(force[phase == p, i].mean()) for p in range(4) if (phase == p).any()}
        signature["axes"][axis] = {
            "peak_Hz": freq,
            "peak_per_revolution": freq / rotor_hz,
            "peak_energy_share": share,
            "once_per_revolution_share": harmonics[1],
            "twice_per_revolution_share": harmonics[2],
            "correlation": corr,
            "mean_by_phase_N": means,
            "rms_N": float(np.sqrt(np.mean(force[:, i] ** 2))),
        }
    strongest = max(signature["axes"], key=lambda a: signature["axes"][a]["rms_N"])
    s = signature["axes"][strongest]
    words = [f"largest on {strongest} ({s['rms_N']:.0f} N rms)"]
    words.append(
        f"{100 * s['once_per_revolution_share']:.0f} % of its variance once per revolution, "
        f"{100 * s['twice_per_revolution_share']:.0f} % twice"
    )
    if s["peak_energy_share"] > 0.2:
        words.append(f"spectrum peak at {s['peak_Hz']:.1f} Hz ({s['peak_per_revolution']:.2f} x rotor speed)")
    top = max(s["correlation"], key=lambda k: abs(s["correlation"][k]))
    words.append(f"most correlated with {top} (r = {s['correlation'][top]:+.2f})")
    words.append("mean by phase " + ", ".join(f"{k} {v:.0f} N" for k, v in s["mean_by_phase_N"].items()))
    signature["summary"] = "; ".join(words)
    return signature


# ---------------------------------------------------------------- one model over all bags

def diagnose(
    config: Config,
    bags: Sequence[Path],
    coefficient_file: Path | None = None,
    settings: Settings = Settings(),
    label: str = "model",
    stream=sys.stderr,
) -> Diagnosis:
    """Estimate every bag with one model and compute all the diagnostics."""
    coeffs = effects = None
    if coefficient_file is not None:
        from touchdown_ros.io.coefficients import load_coefficients

        loaded = load_coefficients(coefficient_file, config)
        coeffs, effects, config = loaded.coeffs, loaded.effects, loaded.config(config)
    estimator = estimator_for(config, coeffs, effects)
    compiled = _compiled(config, settings)
    results = []
    for path in progress(bags, len(bags), f"diagnose {label}", stream=stream):
        results.append(_diagnose_bag(config, Path(path), estimator, compiled, settings))

    for b in results:
        est = b.result.estimate
        b.metrics = _error_metrics(est.measured, np.asarray(est.predicted_output), b.k_step, _force_error(b), b.phase, b.impact)
    has_truth = all(b.result.truth is not None for b in results)
    metrics = _error_metrics(
        _stack(results, lambda b: b.result.estimate.measured),
        _stack(results, lambda b: np.asarray(b.result.estimate.predicted_output)),
        _stack(results, lambda b: b.k_step),
        _stack(results, _force_error) if has_truth else None,
        _stack(results, lambda b: b.phase),
        _stack(results, lambda b: b.impact),
    )
    metrics["missing_force"] = _missing_force_table(results)
    windows = max(1, int(round(settings.window / config.sample_period)))
    metrics["k_step_rmse_over_time_m"] = {
        b.path.name: dg.windowed_rms(b.k_step - b.result.estimate.measured, windows).tolist() for b in results
    }
    metrics["regions"] = _regions(config, results, settings)
    tests = _residual_tests(config, results, settings.max_lag)
    print(f"[diagnose {label}] ranking candidate effects (FROLS)", file=stream, flush=True)
    ranking, parameter_names = _ranking(config, results, compiled)
    rows = _candidate_rows(ranking, parameter_names, results)
    best = rows[0]
    explained = best["err_percent"] >= 100.0 * settings.threshold
    verdict = {
        "explained": bool(explained),
        "best": best["candidate"],
        "best_err_percent": best["err_percent"],
        "threshold_percent": 100.0 * settings.threshold,
        "forced_err_percent": 100.0 * ranking.forced_err,
        "order": [{"candidate": n, "err_percent": 100 * e, "cumulative_percent": 100 * c} for n, e, c in ranking.order],
        "candidates": rows,
        "text": (
            f"missing effect: {best['candidate']} explains {best['err_percent']:.1f} % of the missing force "
            f"the model's own coefficients cannot absorb"
            if explained
            else f"unexplained: the best candidate ({best['candidate']}) explains only {best['err_percent']:.1f} % "
            f"(< {100 * settings.threshold:.0f} %) of the missing force; see its signature"
        ),
    }
    if settings.fitted:
        from touchdown_ros.workflows.candidates import FitSettings, fit_candidates, fitted_verdict
        from touchdown_ros.workflows.training_data import load_training_data

        print(f"[diagnose {label}] fitting the {settings.fitted} best candidates (held-out blocks)", file=stream, flush=True)
        names = [row["candidate"] for row in rows[: settings.fitted]]
        selection = fit_candidates(config, estimator.model, load_training_data(config, bags), names, FitSettings(k=settings.k), stream)
        verdict = fitted_verdict(verdict, selection)
    signature = _signature(config, results)
    return Diagnosis(
        label=label,
        coefficients=str(coefficient_file) if coefficient_file else "constant model (rig nominal values)",
        effects=estimator.model.effects.values(),
        bags=results,
        metrics=metrics,
        ranking=ranking,
        verdict=verdict,
        signature=signature,
        tests=tests,
    )


def _region_edges(values: np.ndarray, bins: int) -> np.ndarray:
    lo, hi = np.nanpercentile(values, [1, 99])
    if not np.isfinite(lo) or hi <= lo:
        hi = lo + 1e-9
    return np.linspace(lo, hi, bins + 1)


def _regions(config: Config, bags: Sequence[BagDiagnosis], settings: Settings) -> dict[str, Any]:
    """k-step error (norm) over the (deformation, velocity) planes, in contact only."""
    state = _stack(bags, lambda b: np.asarray(b.result.estimate.smoothed.state))
    error = np.linalg.norm(_stack(bags, lambda b: b.k_step - b.result.estimate.measured), axis=1)
    d_r, v_r, d_z, v_z = _deformations(config, state)
    regions = {}
    for name, d, v in (("axial", d_z, v_z), ("radial", d_r, v_r)):
        contact = d > 0
        if contact.sum() < 10:
            continue
        d_edges = _region_edges(d[contact], settings.deformation_bins)
        v_edges = _region_edges(v[contact], settings.velocity_bins)
        rms, counts = dg.binned_rms(np.where(contact, error, np.nan), d, v, d_edges, v_edges)
        regions[name] = {
            "deformation_edges_m": d_edges.tolist(),
            "velocity_edges_mps": v_edges.tolist(),
            "k_step_rmse_m": np.where(np.isfinite(rms), rms, None).tolist(),
            "counts": counts.tolist(),
        }
    return regions


# ---------------------------------------------------------------- outputs

def _json_ready(diagnosis: Diagnosis, settings: Settings) -> dict[str, Any]:
    return {
        "label": diagnosis.label,
        "coefficients": diagnosis.coefficients,
        "effects": diagnosis.effects,
        "metrics": diagnosis.metrics,
        "residual_tests": diagnosis.tests,
        "verdict": diagnosis.verdict,
        "signature": diagnosis.signature,
        "bags": {
            b.path.name: {"path": str(b.path), "conditions": b.conditions, **b.metrics} for b in diagnosis.bags
        },
    }


def _ratio(after: float, before: float) -> float | None:
    return float(after / before) if before else None


def comparison(before: Diagnosis, after: Diagnosis) -> dict[str, Any]:
    """after / before of the headline errors (a ratio below 1 is an improvement)."""
    mb, ma = before.metrics, after.metrics
    out = {
        "k_step_rmse_norm": _ratio(ma["k_step"]["rmse_norm_m"], mb["k_step"]["rmse_norm_m"]),
        "one_step_rmse_norm": _ratio(ma["one_step"]["rmse_norm_m"], mb["one_step"]["rmse_norm_m"]),
        "k_step_rmse_per_axis": [_ratio(a, b) for a, b in zip(ma["k_step"]["rmse_m"], mb["k_step"]["rmse_m"])],
        "k_step_rmse_per_phase": {
            p: [_ratio(a, b) for a, b in zip(ma["phases"][p]["k_step_rmse_m"], mb["phases"][p]["k_step_rmse_m"])]
            for p in dg.PHASES
            if mb["phases"][p]["samples"]
        },
        "missing_force_rms": [
            _ratio(a, b) for a, b in zip(ma["missing_force"]["all"]["rms_N"], mb["missing_force"]["all"]["rms_N"])
        ],
    }
    if "contact_force" in mb and "contact_force" in ma:
        out["contact_force_rmse_norm"] = _ratio(ma["contact_force"]["rmse_norm_N"], mb["contact_force"]["rmse_norm_N"])
        out["contact_force_rmse_per_axis"] = [
            _ratio(a, b) for a, b in zip(ma["contact_force"]["rmse_N"], mb["contact_force"]["rmse_N"])
        ]
    return out


def write_outputs(diagnoses: Sequence[Diagnosis], config: Config, out: Path, settings: Settings) -> dict[str, Any]:
    """diagnosis.json, diagnosis.md, errors.csv, ranking.csv and the figures in out."""
    from touchdown_ros.workflows.report import plot_diagnosis

    out.mkdir(parents=True, exist_ok=True)
    document: dict[str, Any] = {
        "settings": {
            "k_step_samples": settings.k,
            "k_step_seconds": settings.k * config.sample_period,
            "force_walk_N_per_sample": settings.force_walk,
            "unexplained_below_err_percent": 100 * settings.threshold,
            "fitted_candidates": settings.fitted,
        },
        "models": [_json_ready(d, settings) for d in diagnoses],
    }
    if len(diagnoses) == 2:
        document["comparison"] = comparison(*diagnoses)
    (out / "diagnosis.json").write_text(json.dumps(document, indent=2, allow_nan=True))
    _write_csv(diagnoses, out)
    (out / "diagnosis.md").write_text(markdown(document))
    plot_diagnosis(diagnoses, config, out / "figures")
    return document


def _write_csv(diagnoses: Sequence[Diagnosis], out: Path) -> None:
    with open(out / "errors.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["model", "bag", "phase", "axis", "samples", "k_step_rmse_m", "force_rmse_N"])
        for d in diagnoses:
            for bag, metrics in [("ALL", d.metrics)] + [(b.path.name, b.metrics) for b in d.bags]:
                for phase, p in [("all", None)] + list(metrics["phases"].items()):
                    for i, axis in enumerate(AXES):
                        if p is None:
                            k, f, n = metrics["k_step"]["rmse_m"][i], metrics.get("contact_force", {}).get("rmse_N", [None] * 3)[i], metrics["samples"]
                        else:
                            k, f, n = p["k_step_rmse_m"][i], p.get("force_rmse_N", [None] * 3)[i], p["samples"]
                        writer.writerow([d.label, bag, phase, axis, n, k, f])
    with open(out / "ranking.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["model", "rank", "candidate", "err_percent", "parameter", "value", "std", "ci95_low", "ci95_high", "unit"])
        for d in diagnoses:
            for row in d.verdict["candidates"]:
                for name, p in row["parameters"].items():
                    writer.writerow(
                        [d.label, row["rank"], row["candidate"], f"{row['err_percent']:.3f}", name, p["value"], p["std"], *p["ci95"], p["unit"]]
                    )


def _um(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v * 1e6:.2f}"


def markdown(document: dict[str, Any]) -> str:
    """The report as Markdown: errors, residual tests, missing force, ranking, verdict (side by side)."""
    models = document["models"]
    labels = [m["label"] for m in models]
    s = document["settings"]
    lines = ["# touchdown diagnose\n", f"k-step prediction: {s['k_step_samples']} samples ({s['k_step_seconds'] * 1e3:.1f} ms) ahead, no update.\n"]
    lines += [f"- **{m['label']}**: {m['coefficients']}; effects {m['effects'] or 'none'}" for m in models]
    lines.append("")

    def row(name: str, values: list[str]) -> str:
        return f"| {name} | " + " | ".join(values) + " |"

    head = "| | " + " | ".join(labels) + (" | after / before |" if len(models) == 2 else " |")
    rule = "|---|" + "---:|" * (len(models) + (1 if len(models) == 2 else 0))
    lines += ["## Errors per axis", "", head, rule]

    def ratio(a, b):
        return f"{a / b:.2f}" if (a is not None and b) else "-"

    for kind, title in (("one_step", "one-step"), ("k_step", "k-step")):
        for i, axis in enumerate(AXES):
            vals = [m["metrics"][kind]["rmse_m"][i] for m in models]
            fits = [m["metrics"][kind]["fit_percent"][i] for m in models]
            cells = [f"{_um(v)} um, fit {f:.1f} %" for v, f in zip(vals, fits)]
            if len(models) == 2:
                cells.append(ratio(vals[1], vals[0]))
            lines.append(row(f"{title} {axis} RMSE (eq. 19)", cells))
    if all("contact_force" in m["metrics"] for m in models):
        for i, axis in enumerate(AXES):
            vals = [m["metrics"]["contact_force"]["rmse_N"][i] for m in models]
            cells = [f"{v:.0f} N" for v in vals] + ([ratio(vals[1], vals[0])] if len(models) == 2 else [])
            lines.append(row(f"contact force {axis} RMSE vs truth", cells))
        vals = [m["metrics"]["contact_force"]["rmse_norm_N"] for m in models]
        lines.append(row("contact force RMSE (norm) vs truth", [f"{v:.0f} N" for v in vals] + ([ratio(vals[1], vals[0])] if len(models) == 2 else [])))
    vals = [m["metrics"]["k_step"]["rmse_norm_m"] for m in models]
    lines.append(row("**k-step RMSE (norm)**", [f"{_um(v)} um" for v in vals] + ([ratio(vals[1], vals[0])] if len(models) == 2 else [])))

    lines += ["", "## k-step RMSE by contact phase (x / y / z, um)", "", head, rule]
    for phase in models[0]["metrics"]["phases"]:
        ps = [m["metrics"]["phases"][phase] for m in models]
        cells = [f"{' / '.join(_um(v) for v in p['k_step_rmse_m'])} ({p['samples']})" for p in ps]
        if len(models) == 2:
            a, b = (np.linalg.norm(np.nan_to_num(p["k_step_rmse_m"])) for p in ps[::-1])
            cells.append(ratio(a, b))
        lines.append(row(phase, cells))
    if all("force_rmse_N" in m["metrics"]["phases"][dg.PHASES[0]] for m in models):
        lines += ["", "## Contact-force RMSE vs truth by phase (x / y / z, N)", "", head, rule]
        for phase in models[0]["metrics"]["phases"]:
            ps = [m["metrics"]["phases"][phase] for m in models]
            cells = [" / ".join("-" if v is None or not np.isfinite(v) else f"{v:.0f}" for v in p["force_rmse_N"]) for p in ps]
            if len(models) == 2:
                a, b = (np.linalg.norm(np.nan_to_num(p["force_rmse_N"])) for p in ps[::-1])
                cells.append(ratio(a, b))
            lines.append(row(phase, cells))

    lines += ["", "## k-step RMSE by impact (norm, um)", "", head, rule]
    n_impacts = max(len(m["metrics"]["impacts"]) for m in models)
    for k in range(min(n_impacts, 10)):
        cells = []
        for m in models:
            imp = m["metrics"]["impacts"]
            cells.append(_um(np.linalg.norm(imp[k]["k_step_rmse_m"])) if k < len(imp) else "-")
        if len(models) == 2:
            cells.append("")
        lines.append(row(f"impact {k + 1}", cells))

    lines += ["", "## Residual tests (innovations; 99 % band, white: ~1 % of lags outside)", "", head, rule]
    for axis in AXES:
        for key, title in (
            ("whiteness_outside_share", "autocorrelation: lags outside band"),
            ("velocity_xcorr_outside_share", "x-corr with velocity: lags outside"),
            ("deformation_xcorr_outside_share", "x-corr with deformation: lags outside"),
        ):
            vals = [m["residual_tests"][axis][key] for m in models]
            lines.append(row(f"{axis} {title}", [f"{100 * v:.0f} %" for v in vals] + ([""] if len(models) == 2 else [])))

    lines += ["", "## Missing force (smoothed disturbance states): mean +- rms of the estimate's std, N", "", head, rule]
    for phase in list(dg.PHASES) + ["all"]:
        cells = []
        for m in models:
            t = m["metrics"]["missing_force"].get(phase)
            cells.append(
                "-" if t is None else " / ".join(f"{mu:.0f}+-{sd:.0f}" for mu, sd in zip(t["mean_N"], t["std_of_estimate_N"]))
            )
        if len(models) == 2:
            cells.append("")
        lines.append(row(f"{phase} (x / y / z)", cells))

    for m in models:
        v = m["verdict"]
        lines += [
            "",
            f"## Which effect is missing ({m['label']})",
            "",
            f"**{v['text']}**",
            "",
        ]
        if "frols" in v:
            from touchdown_ros.workflows.candidates import markdown as fitted_markdown

            lines += [*fitted_markdown(v), "", f"FROLS (the first pass that chose them): {v['frols_text']}.", ""]
        lines += [
            f"The model's own PKBKR coefficients (forced first) can absorb {v['forced_err_percent']:.1f} % of the "
            f"missing-force energy; the ERR below are shares of the rest. FROLS threshold: {v['threshold_percent']:.0f} %.",
            "",
            "| rank | candidate | ERR | parameters (linearised fit, +- 1 std, pooled; per bag) |",
            "|---:|---|---:|---|",
        ]
        for c in v.get("frols", v["candidates"]):
            params = "; ".join(
                f"{n} = {p['value']:.4g} +- {p['std']:.2g} {p['unit']} ("
                + ", ".join(f"{bag} {val:.4g}" for bag, val in p["per_bag"].items())
                + ")"
                for n, p in c["parameters"].items()
            )
            lines.append(f"| {c['rank']} | {c['candidate']} | {c['err_percent']:.1f} % | {params} |")
        lines.append("")
        lines.append("FROLS order: " + ", ".join(f"{o['candidate']} (+{o['err_percent']:.1f} %, {o['cumulative_percent']:.1f} %)" for o in v["order"]))
        lines += ["", f"Residual signature: {m['signature']['summary']}."]
    if "comparison" in document:
        c = document["comparison"]
        lines += ["", "## After / before", ""]
        lines.append(f"- k-step RMSE (norm): x {c['k_step_rmse_norm']:.2f}")
        if "contact_force_rmse_norm" in c:
            lines.append(f"- contact-force RMSE vs truth (norm): x {c['contact_force_rmse_norm']:.2f}")
        lines.append("- missing force rms per axis: " + " / ".join(f"x {v:.2f}" for v in c["missing_force_rms"]))
    return "\n".join(lines) + "\n"


def run(
    config: Config,
    bags: Sequence[Path],
    out: Path,
    coeffs: Path | None = None,
    compare: Path | None = None,
    settings: Settings = Settings(),
    stream=sys.stderr,
) -> dict[str, Any]:
    """Diagnose the model of `coeffs` (default: the rig's constant model) and, with `compare`,
    a second coefficient file (after) side by side; write everything to out."""
    diagnoses = [diagnose(config, bags, coeffs, settings, "before" if compare else "model", stream)]
    if compare is not None:
        diagnoses.append(diagnose(config, bags, compare, settings, "after", stream))
    return write_outputs(diagnoses, config, out, settings)
