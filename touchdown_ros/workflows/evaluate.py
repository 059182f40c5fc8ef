"""Compare the constant baseline with PKBKR on every bag, with leave-one-experiment-out training."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from touchdown_ros.core.effects import Effects
from touchdown_ros.core.metrics import peak_errors_per_impact, relative_peak_error, rmse
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.offline import FILTERED, BagEstimate, estimate_bag, estimator_for
from touchdown_ros.workflows.progress import progress
from touchdown_ros.workflows.train import Trainable, fit, load_training_data, make_objective

#: Force above which a sample counts as part of an impact, N (about a third of the rotor weight).
IMPACT_THRESHOLD = 800.0


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
    displacement = rmse(est.filtered.state[:, :3], est.measured).tolist()
    metrics["rmse_x_m"], metrics["rmse_y_m"], metrics["rmse_z_m"] = displacement
    if truth is not None:
        radial, true_radial = np.hypot(force[:, 0], force[:, 1]), np.hypot(*truth.contact_force[:, :2].T)
        metrics.update(
            rmse_velocity_mps=float(np.linalg.norm(rmse(est.filtered.state[:, 4:7], truth.velocity))),
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
    objective = make_objective(config)
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
    # the figures are the filtered estimate's, with Q as fitted for both: a comparison of models, not of the live
    # filter's adaptive Q (which widens Q more for the worse model)
    config = dataclasses.replace(config, adaptation=None)
    estimator = estimator_for(config, effects=Effects(), answer=FILTERED)
    results = []
    for path, trained in progress(zip(bags, per_bag), len(bags), "estimate both methods"):
        constant = estimate_bag(config, path, estimator, fit_noise=False)  # both methods on the same Q
        pkbkr = estimate_bag(config, path, estimator, trained.coeffs, trained.effects, fit_noise=False)
        results.append(
            BagComparison(
                Path(path), constant, pkbkr, {"constant": compare_metrics(constant), "pkbkr": compare_metrics(pkbkr)}
            )
        )
    return results
