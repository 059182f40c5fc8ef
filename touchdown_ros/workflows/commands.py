"""The `touchdown` subcommands as functions with typed arguments (the CLI parses, calls one, prints).

Nothing partial: each checks every bag and the output place before the work, and what it creates
is removed again if it fails (`outputs.OutputGuard`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from touchdown_ros.io.coefficients import CoefficientFile, load_coefficients
from touchdown_ros.io.config import Config
from touchdown_ros.sim.bags import write_drop_bag
from touchdown_ros.sim.campaign import CAMPAIGN
from touchdown_ros.sim.family import Variant, bag_name, write_variant_bags
from touchdown_ros.sim.simulator import simulate_drop
from touchdown_ros.workflows.diagnose import Settings as DiagnoseSettings
from touchdown_ros.workflows.diagnose import run as run_diagnosis
from touchdown_ros.workflows.evaluate import BagComparison, compare, cross_validate
from touchdown_ros.workflows.offline import (
    FILTERED,
    SMOOTHED,
    BagEstimate,
    check_bags,
    estimate_bag,
    estimator_for,
    write_estimate_bag,
)
from touchdown_ros.workflows.outputs import OutputGuard, check_writable
from touchdown_ros.workflows.progress import progress
from touchdown_ros.workflows.report.estimate import plot_estimate, write_summaries
from touchdown_ros.workflows.report.evaluation import write_evaluation
from touchdown_ros.workflows.report.training import REPORT_FILES, write_training_report
from touchdown_ros.workflows.train import TrainOutcome, Trainable, train

#: What `diagnose_bags` writes in its output directory.
DIAGNOSIS_FILES = ("diagnosis.md", "diagnosis.json", "errors.csv", "ranking.csv", "figures")
#: What `evaluate_bags` writes in its output directory.
EVALUATION_FILES = ("evaluation.md", "evaluation.csv", "evaluation.json", "figures")


def refuse_existing(path: Path, overwrite: bool) -> None:
    """FileExistsError when path exists and may not be overwritten."""
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass --overwrite to replace it")


def simulate_campaign(
    config: Config, out: Path, numbers: Sequence[int] | None = None, seed: int = 0, overwrite: bool = False
) -> list[Path]:
    """Table 1's experiments `numbers` (None: all of them) simulated into bags out/exp_NN, experiment N
    with seed + N; returns the bag paths."""
    numbers = [c.number for c in CAMPAIGN] if numbers is None else list(numbers)
    conditions = [c for c in CAMPAIGN if c.number in numbers]
    missing = sorted(set(numbers) - {c.number for c in conditions})
    if missing:
        raise ValueError(f"no experiment numbered {missing} in the campaign (1-{len(CAMPAIGN)})")
    out.mkdir(parents=True, exist_ok=True)
    targets = [out / f"exp_{c.number:02d}" for c in conditions]
    for target in targets:
        refuse_existing(target, overwrite)
    for condition, target in progress(zip(conditions, targets), len(conditions), "simulate"):
        record = simulate_drop(config, condition, seed=seed + condition.number)
        write_drop_bag(record, config, target, overwrite=overwrite)
    return targets


def simulate_variant(
    v: Variant, out: Path, numbers: Sequence[int] | None = None, seed: int = 0, overwrite: bool = False
) -> list[Path]:
    """The drops `numbers` (None: all) of the rig variant v as bags NAME_NN in out, its rig.yaml next
    to them; returns the bag paths."""
    chosen = sorted(set(numbers or range(1, v.drops + 1)))
    if chosen[0] < 1:
        raise ValueError(f"experiment numbers of a variant start at 1, got {chosen[0]}")
    for number in chosen:
        refuse_existing(out / bag_name(v, number), overwrite)
    paths = []
    for number in progress(chosen, len(chosen), f"simulate {v.name}"):
        paths += write_variant_bags(v, out, seed=seed, numbers=[number], overwrite=overwrite)
    return paths


def _with_coefficients(config: Config, coefficients: Path | None) -> tuple[Config, CoefficientFile | None]:
    """The rig of a coefficient file (its calibrated constants on `config`) and the file; `config` alone
    without one."""
    if coefficients is None:
        return config, None
    loaded = load_coefficients(coefficients, config)
    return loaded.config(config), loaded


def estimate_bags(
    config: Config,
    bags: Sequence[Path],
    out: Path,
    coefficients: Path | None = None,
    filtered: bool = False,
    figures: bool = True,
    overwrite: bool = False,
) -> list[BagEstimate]:
    """Each bag estimated (the RTS smoother's estimate, or the EKF's with `filtered`) with the model of
    `coefficients` (default: the constant model) into a bag out/NAME_estimate, its figures in
    out/figures/NAME, and summary.json / summary.md of all in out."""
    config, loaded = _with_coefficients(config, coefficients)
    check_writable(out, directory=True)
    targets = [out / f"{Path(bag).name.removesuffix('.mcap')}_estimate" for bag in bags]
    for target in targets:
        refuse_existing(target, overwrite)
    check_bags(config, bags)  # every bag is checked before anything is written
    answer = FILTERED if filtered else SMOOTHED
    estimator = estimator_for(config, *((loaded.coeffs, loaded.effects) if loaded else (None, None)), answer=answer)
    figure_dirs = [out / "figures" / Path(bag).name for bag in bags]
    written = [out, *targets, out / "figures", *figure_dirs, out / "summary.json", out / "summary.md"]
    results = []
    with OutputGuard(written):
        out.mkdir(parents=True, exist_ok=True)
        for bag, target, figure in progress(zip(bags, targets, figure_dirs), len(bags), "estimate"):
            result = estimate_bag(config, bag, estimator, answer=answer)
            write_estimate_bag(result, config, target, overwrite=overwrite)
            if figures:
                plot_estimate(result, figure)
            results.append(result)
        write_summaries(
            results,
            out,
            {
                "coefficients": str(coefficients) if coefficients else "constant model",
                "calibration_notes": loaded.calibration_notes if loaded else [],
                "estimate": answer,
                "process_noise": (
                    f"the fitted Q x {config.smoothing_noise_scale:.3g} (filter.smoothing_noise_scale)"
                    if answer == SMOOTHED
                    else "the fitted Q, as the live node's"
                    + (", scaled by a factor its innovations move (filter.adaptive_process_noise)"
                       if config.live_adaptation else "")
                ),
                "force_band_model_error": force_band_source(config),
            },
        )
    return results


def force_band_source(config: Config) -> str:
    """In words: what the force band adds in contact for the model's own error (`Config.model_variance`)."""
    variance = config.model_variance()
    if variance is None:
        return "the process noise read as a force, m^2 Q_v / h^2 (no filter.force_model_variance)"
    rms = " / ".join(f"{v:.0f}" for v in np.sqrt(variance))
    return f"rms {rms} N (x / y / z), measured on the training bags (filter.force_model_variance)"


def train_bags(
    config: Config,
    bags: Sequence[Path],
    out: Path,
    regularisation: float | None = None,
    init: Path | None = None,
    resume: bool = False,
    steps: int | None = None,
    duration: float | None = None,
    overwrite: bool = False,
    start: Path | None = None,
) -> TrainOutcome:
    """`train` on the bags into the coefficient file out, after checking every bag, the warm-start
    or start file and the output place; the checkpoint stays when training stops (`resume` continues from
    it), the file is written at the end, atomically."""
    if out.exists() and not (overwrite or resume):
        raise FileExistsError(f"{out} exists; pass --overwrite to replace it or --resume to continue")
    if start is not None and (init is not None or resume):
        raise ValueError("--start runs stage 1 from a file's calibration; --init and --resume skip stage 1: "
                         "give one of them")
    check_writable(out, directory=False)
    for given in (init, start):
        if given is not None:
            load_coefficients(given, config)
    check_bags(config, bags, training=True)  # every bag is checked before the work
    with OutputGuard([out]):
        return train(
            config,
            bags,
            out,
            regularisation=regularisation,
            init=init,
            resume=resume,
            start=start,
            max_steps=steps,
            duration=duration,
        )


def evaluate_bags(
    config: Config,
    bags: Sequence[Path],
    coefficients: Path,
    out: Path,
    cross_validated: bool = True,
    cv_steps: int = 12,
    example: str = "exp_11",
) -> list[BagComparison]:
    """The constant model against the trained model of `coefficients` on every bag, PKBKR retrained
    without each bag (leave-one-out, `cv_steps` L-BFGS steps warm-started from the file) unless not
    `cross_validated`; tables, evaluation.json and figures (time series of `example`) in out."""
    config, full = _with_coefficients(config, coefficients)
    trained = Trainable(full.coeffs, full.effects)
    check_writable(out, directory=True)
    check_bags(config, bags, training=True)  # every bag is checked before the work
    if cross_validated:
        per_bag = cross_validate(config, bags, trained, full.training.regularisation, cv_steps)
    else:
        per_bag = [trained] * len(bags)
    comparisons = compare(config, bags, per_bag)
    with OutputGuard([out, *(out / name for name in EVALUATION_FILES)]):
        write_evaluation(comparisons, config, full.coeffs, out, coefficients, cross_validated, example)
    return comparisons


def diagnose_bags(
    config: Config,
    bags: Sequence[Path],
    out: Path,
    coefficients: Path | None = None,
    compare_with: Path | None = None,
    settings: DiagnoseSettings = DiagnoseSettings(),
) -> dict:
    """Where the model of `coefficients` (default: the constant model) fails and which effect it lacks,
    side by side with the model of `compare_with` when given; diagnosis.*, errors.csv, ranking.csv and
    figures in out. Returns diagnosis.json's document."""
    check_writable(out, directory=True)
    check_bags(config, bags)  # every bag is checked before the work
    with OutputGuard([out, *(out / name for name in DIAGNOSIS_FILES)]):
        return run_diagnosis(config, bags, out, coeffs=coefficients, compare=compare_with, settings=settings)


def report_training(config: Config, coefficients: Path, out: Path) -> list[Path]:
    """What `touchdown train` found, from the coefficient file alone: training.md and figures/ in out
    (the file checked against the rig first, as every command does)."""
    config, loaded = _with_coefficients(config, coefficients)
    check_writable(out, directory=True)
    with OutputGuard([out, *(out / name for name in REPORT_FILES)]):
        return write_training_report(loaded, config, coefficients, out)
