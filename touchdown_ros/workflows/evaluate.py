"""Compare the constant baseline with PKBKR on every bag, with leave-one-experiment-out training."""
from __future__ import annotations

import csv
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from touchdown_ros.core.effects import Effects
from touchdown_ros.core.metrics import peak_errors_per_impact, relative_peak_error, rmse
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.offline import BagEstimate, estimate_bag, estimator_for
from touchdown_ros.workflows.progress import progress
from touchdown_ros.workflows.train import Trainable, fit, load_training_data, make_objective

#: Force above which a sample counts as part of an impact, N (about a third of the rotor weight).
IMPACT_THRESHOLD = 800.0
METHODS = ("constant", "pkbkr")


@dataclass(frozen=True)
class BagComparison:
    """One bag estimated by both methods; PKBKR trained without this bag when cross-validated."""

    path: Path
    constant: BagEstimate
    pkbkr: BagEstimate
    metrics: dict[str, dict[str, Any]]  # method -> figures


def compare_metrics(result: BagEstimate) -> dict[str, Any]:
    """Figures of one estimate: eq. 19 RMSE, prediction RMSE and, with truth, state and force errors."""
    est, truth = result.estimate, result.truth
    force = np.asarray(est.filtered.force_xyz)
    metrics: dict[str, Any] = {
        "rmse_x_m": None,
        "rmse_prediction_m": rmse(est.predicted_output, est.measured).tolist(),
    }
    metrics["rmse_x_m"], metrics["rmse_y_m"], metrics["rmse_z_m"] = rmse(est.filtered.state[:, :3], est.measured).tolist()
    if truth is not None:
        radial, true_radial = np.hypot(force[:, 0], force[:, 1]), np.hypot(*truth.contact_force[:, :2].T)
        metrics.update(
            rmse_velocity_mps=float(np.linalg.norm(rmse(est.filtered.state[:, 4:], truth.velocity))),
            rmse_acceleration_mps2=float(np.linalg.norm(rmse(est.filtered.acceleration, truth.acceleration))),
            rmse_axial_force_N=float(rmse(force[:, 2:], truth.contact_force[:, 2:])[0]),
            rmse_radial_force_N=float(rmse(radial[:, None], true_radial[:, None])[0]),
            peak_axial_force_error=relative_peak_error(force[:, 2], truth.contact_force[:, 2]),
            peak_radial_force_error=relative_peak_error(radial, true_radial),
            axial_impacts=peak_errors_per_impact(force[:, 2], truth.contact_force[:, 2], IMPACT_THRESHOLD),
            radial_impacts=peak_errors_per_impact(radial, true_radial, IMPACT_THRESHOLD),
        )
    return metrics


def cross_validate(
    config: Config,
    bags: Sequence[Path],
    full: Trainable,
    regularisation: float,
    steps: int,
    duration: float | None = None,
) -> list[Trainable]:
    """Coefficients (and effect parameters) for each bag trained on all the other bags,
    warm-started from the full fit."""
    data = load_training_data(config, bags, duration)
    length = max(len(r) for r in data.records)
    objective = make_objective(config, regularisation)
    folds = []
    for held_out in progress(range(len(bags)), len(bags), "leave-one-out training"):
        keep = [i for i in range(len(bags)) if i != held_out]
        fold = data.subset(keep)
        result = fit(config, fold, regularisation, full, steps, objective=objective, length=length, stream=_Quiet())
        folds.append(Trainable(result.coeffs, result.effects))
    return folds


class _Quiet:
    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass


def compare(config: Config, bags: Sequence[Path], per_bag: Sequence[Trainable]) -> list[BagComparison]:
    """Estimate each bag with the paper's constant model (ref. [13], no add-on effects) and with
    its trained model (PKBKR coefficients and the effects they were fitted with)."""
    estimator = estimator_for(config, effects=Effects())
    results = []
    for path, trained in progress(zip(bags, per_bag), len(bags), "estimate both methods"):
        constant = estimate_bag(config, path, estimator)
        pkbkr = estimate_bag(config, path, estimator, trained.coeffs, trained.effects)
        results.append(
            BagComparison(Path(path), constant, pkbkr, {"constant": compare_metrics(constant), "pkbkr": compare_metrics(pkbkr)})
        )
    return results


SCALAR_COLUMNS = (
    ("rmse_x_m", 1e6, "RMSE x / um"),
    ("rmse_y_m", 1e6, "RMSE y / um"),
    ("rmse_z_m", 1e6, "RMSE z / um"),
    ("rmse_velocity_mps", 1e3, "velocity RMSE / (mm/s)"),
    ("rmse_acceleration_mps2", 1.0, "acceleration RMSE / (m/s^2)"),
    ("rmse_axial_force_N", 1.0, "axial force RMSE / N"),
    ("rmse_radial_force_N", 1.0, "radial force RMSE / N"),
    ("peak_axial_force_error", 100.0, "peak axial force error / %"),
    ("peak_radial_force_error", 100.0, "peak radial force error / %"),
)


def write_tables(
    comparisons: Sequence[BagComparison], out: Path, coefficients: str = "", cross_validated: bool = True
) -> dict[str, Any]:
    """evaluation.csv (one row per bag and method) and evaluation.md (a heading saying which coefficients,
    how they were held out and what the means are, the table, the ratios); returns the aggregate."""
    out.mkdir(parents=True, exist_ok=True)
    columns = [c for c in SCALAR_COLUMNS if c[0] in comparisons[0].metrics["constant"]]
    with open(out / "evaluation.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["bag", "method", *(label for _, _, label in columns)])
        for c in comparisons:
            for method in METHODS:
                writer.writerow([c.path.name, method, *(f"{c.metrics[method][k] * s:.6g}" for k, s, _ in columns)])
    aggregate = {}
    for key, scale, label in columns:
        values = {m: np.array([c.metrics[m][key] for c in comparisons]) for m in METHODS}
        aggregate[key] = {
            "label": label,
            "constant_mean": float(np.mean(np.abs(values["constant"])) * scale),
            "pkbkr_mean": float(np.mean(np.abs(values["pkbkr"])) * scale),
            "pkbkr_max": float(np.max(np.abs(values["pkbkr"])) * scale),
            "ratio_pkbkr_to_constant": float(np.mean(np.abs(values["pkbkr"])) / max(np.mean(np.abs(values["constant"])), 1e-300)),
        }
    held_out = (
        "leave-one-out: each bag is estimated with PKBKR coefficients retrained without it, warm-started from "
        "these (filtered estimate)"
        if cross_validated
        else "in-sample (--no-cv): these coefficients on every bag, including the bags they were trained on (filtered estimate)"
    )
    lines = [
        "# Evaluation: constant model vs PKBKR",
        "",
        f"- Coefficients: `{coefficients or '(not given)'}`; {held_out}.",
        "- Baseline: the constant-parameter model (all alpha = 0) with the same calibrated contact constants.",
        "- The mean rows average the absolute value of each bag's figure (a signed peak error counts by its size); "
        "'worst bag' is the largest absolute value.",
        "",
    ]
    lines += ["| bag | method | " + " | ".join(label for _, _, label in columns) + " |", "|---|---|" + "---:|" * len(columns)]
    for c in comparisons:
        for method in METHODS:
            cells = " | ".join(f"{c.metrics[method][k] * s:.3g}" for k, s, _ in columns)
            lines.append(f"| {c.path.name} | {method} | {cells} |")
    lines += ["", "| figure | constant (mean) | PKBKR (mean) | PKBKR (worst bag) | PKBKR / constant |", "|---|---:|---:|---:|---:|"]
    for key, a in aggregate.items():
        lines.append(
            f"| {a['label']} | {a['constant_mean']:.3g} | {a['pkbkr_mean']:.3g} | {a['pkbkr_max']:.3g} | {a['ratio_pkbkr_to_constant']:.2f} |"
        )
    (out / "evaluation.md").write_text("\n".join(lines) + "\n")
    return aggregate


def log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
