"""`touchdown evaluate`'s report: the paper's figures 2-8 and the parameter maps, evaluation.csv/.md/.json."""
from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from touchdown_ros.core.diagnostics.breakdown import AXES
from touchdown_ros.core.metrics import impacts
from touchdown_ros.core.pkbkr import axial_parameters, radial_parameters
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.evaluate import IMPACT_THRESHOLD, BagComparison
from touchdown_ros.workflows.report.plotting import plt, save, seconds

METHODS = ("constant", "pkbkr")


def write_evaluation(
    comparisons: Sequence[BagComparison],
    config,
    coeffs,
    out: Path,
    coefficients: Path,
    cross_validated: bool = True,
    example: str = "exp_11",
) -> dict[str, Any]:
    """evaluation.md, evaluation.csv (`write_tables`), evaluation.json and the figures (`plot_evaluation`,
    the time series of the bag named `example`, else the first) in out; returns the aggregate."""
    out.mkdir(parents=True, exist_ok=True)
    aggregate = write_tables(comparisons, out, coefficients=str(coefficients), cross_validated=cross_validated)
    names = [c.path.name for c in comparisons]
    index = names.index(example) if example in names else 0
    plot_evaluation(comparisons, config, coeffs, out / "figures", index)
    (out / "evaluation.json").write_text(
        json.dumps(
            {
                "cross_validated": cross_validated,
                "coefficients": str(coefficients),
                "aggregate": aggregate,
                "bags": {c.path.name: c.metrics for c in comparisons},
            },
            indent=2,
        )
    )
    return aggregate


def plot_evaluation(comparisons, config, coeffs, out: Path, example: int = 0) -> list[Path]:
    """The paper's Fig. 2-8 for a cross-validated campaign, and maps of the learned parameters."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    c = comparisons[example]
    t = seconds(c.constant)

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, c.constant.estimate.measured[:, i] * 1e3, ".", ms=1.5, color="0.6", label="measured")
        ax.plot(t, np.asarray(c.constant.estimate.filtered.state)[:, i] * 1e3, lw=1, label="constant [13]")
        ax.plot(t, np.asarray(c.pkbkr.estimate.filtered.state)[:, i] * 1e3, lw=1, ls="--", label="PKBKR")
        ax.set_ylabel(f"{AXES[i]} / mm")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{c.path.name}: measured and estimated displacement (paper Fig. 2-4)")
    written.append(save(fig, out / "fig2-4_displacement.png"))

    fig, axes = plt.subplots(1, 3, figsize=(12, 4), sharey=True)
    index = np.arange(len(comparisons))
    for i, ax in enumerate(axes):
        for offset, method in ((-0.2, "constant"), (0.2, "pkbkr")):
            values = [x.metrics[method][f"rmse_{AXES[i]}_m"] * 1e3 for x in comparisons]
            ax.bar(index + offset, values, width=0.4, label=method)
        ax.axhline(0.02, color="r", lw=0.8, ls=":", label="0.02 mm")
        ax.set_title(f"{AXES[i]}")
        ax.set_xlabel("experiment")
        ax.set_xticks(index, [x.path.name.removeprefix("exp_") for x in comparisons], fontsize=6, rotation=90)
    axes[0].set_ylabel("displacement RMSE (eq. 19) / mm")
    axes[0].legend(fontsize=8)
    fig.suptitle("Displacement estimation error per experiment, held-out (paper Fig. 5)")
    written.append(save(fig, out / "fig5_rmse_per_experiment.png"))

    if c.constant.truth is not None:
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        truth = c.constant.truth.contact_force
        for ax, label, pick in (
            (axes[0], "axial F_z / kN", lambda f: f[:, 2]),
            (axes[1], "radial |F_xy| / kN", lambda f: np.hypot(f[:, 0], f[:, 1])),
        ):
            ax.plot(t, pick(truth) / 1e3, color="k", lw=1.5, label="truth")
            ax.plot(t, pick(np.asarray(c.constant.estimate.filtered.force_xyz)) / 1e3, lw=1, label="constant [13]")
            ax.plot(t, pick(np.asarray(c.pkbkr.estimate.filtered.force_xyz)) / 1e3, lw=1, ls="--", label="PKBKR")
            ax.set_ylabel(label)
            ax.legend(loc="upper right", fontsize=8)
        axes[-1].set_xlabel("time after drop onset / s")
        fig.suptitle(f"{c.path.name}: estimated and true contact force (paper Fig. 6)")
        written.append(save(fig, out / "fig6_force.png"))

    for name, pick, figure in (
        ("axial", lambda f: f[:, 2], "fig7_axial_peaks.png"),
        ("normal (radial)", lambda f: np.hypot(f[:, 0], f[:, 1]), "fig8_normal_peaks.png"),
    ):
        per_number: dict[int, list[float]] = {}
        for x in comparisons:
            force = pick(np.asarray(x.pkbkr.estimate.filtered.force_xyz))
            for number, (_, _, _, peak) in enumerate(impacts(force, IMPACT_THRESHOLD), start=1):
                per_number.setdefault(number, []).append(peak / 1e3)
        if not per_number:
            continue
        numbers = sorted(per_number)[:15]
        fig, ax = plt.subplots(figsize=(9, 4))
        ax.boxplot([per_number[n] for n in numbers], tick_labels=[str(n) for n in numbers])
        ax.set_xlabel("impact number")
        ax.set_ylabel(f"peak {name} force / kN")
        ax.set_title(f"Estimated peak {name} force per impact, all experiments (PKBKR)")
        written.append(save(fig, out / figure))

    written.append(plot_parameter_maps(config, coeffs, out / "parameter_maps.png"))
    return written


class ParameterMap(NamedTuple):
    """One PKBKR parameter over a grid of deformation (m) and velocity (m/s), relative to its calibrated constant."""

    name: str
    deformation: np.ndarray
    velocity: np.ndarray
    relative: np.ndarray


def parameter_maps(config: Config, coeffs: Coefficients, points: int = 60) -> list[ParameterMap]:
    """The six PKBKR parameters (k_R, c_R, mu, k_Z, c_Z, k_ZR) on a points x points grid from zero deformation to
    the kernel's largest centre and over its centres' velocities, each over its calibrated constant (`config`: the
    rig as the coefficient file calibrated it)."""
    kernel, nominal = config.kernel, config.nominal

    def span(T, scale):
        deformation = np.linspace(0.0, float(np.max(T[:, 0])) * scale[0], points)
        velocity = np.linspace(float(np.min(T[:, 1])) * scale[1], float(np.max(T[:, 1])) * scale[1], points)
        return np.meshgrid(deformation, velocity, indexing="ij")

    D_R, V_R = span(np.asarray(kernel.T_R), np.asarray(kernel.scale_R))
    D_Z, V_Z = span(np.asarray(kernel.T_Z), np.asarray(kernel.scale_Z))
    maps = [(name, D_R, V_R, value)
            for name, value in zip(("k_R", "c_R", "mu"), radial_parameters(kernel, nominal, coeffs, D_R, V_R))]
    maps += [(name, D_Z, V_Z, value)
             for name, value in zip(("k_Z", "c_Z", "k_ZR"), axial_parameters(kernel, nominal, coeffs, D_Z, V_Z))]
    return [ParameterMap(name, D, V, np.asarray(value) / getattr(nominal, name)) for name, D, V, value in maps]


def plot_parameter_maps(config: Config, coeffs: Coefficients, path: Path) -> Path:
    """The six PKBKR parameters over deformation and velocity, relative to their calibrated constants, where the
    kernel centres reach (`parameter_maps`)."""
    fig, axes = plt.subplots(2, 3, figsize=(12, 7))
    for ax, (name, D, V, relative) in zip(axes.ravel(), parameter_maps(config, coeffs)):
        image = ax.pcolormesh(V, D * 1e6, relative, shading="auto", cmap="viridis")
        fig.colorbar(image, ax=ax, label=f"{name} / nominal")
        ax.set_title(f"{name}(deformation, velocity)")
        ax.set_xlabel("velocity / (m/s)")
        ax.set_ylabel("deformation / um")
    fig.suptitle("Learned PKBKR parameters relative to their nominal values")
    return save(fig, path)


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
            "ratio_pkbkr_to_constant": float(
                np.mean(np.abs(values["pkbkr"])) / max(np.mean(np.abs(values["constant"])), 1e-300)
            ),
        }
    held_out = (
        "leave-one-out: each bag is estimated with PKBKR coefficients retrained without it, warm-started from "
        "these (filtered estimate)"
        if cross_validated
        else "in-sample (--no-cv): these coefficients on every bag, including the bags they were trained on "
        "(filtered estimate)"
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
    lines += [
        "| bag | method | " + " | ".join(label for _, _, label in columns) + " |",
        "|---|---|" + "---:|" * len(columns),
    ]
    for c in comparisons:
        for method in METHODS:
            cells = " | ".join(f"{c.metrics[method][k] * s:.3g}" for k, s, _ in columns)
            lines.append(f"| {c.path.name} | {method} | {cells} |")
    lines += [
        "",
        "| figure | constant (mean) | PKBKR (mean) | PKBKR (worst bag) | PKBKR / constant |",
        "|---|---:|---:|---:|---:|",
    ]
    for key, a in aggregate.items():
        lines.append(
            f"| {a['label']} | {a['constant_mean']:.3g} | {a['pkbkr_mean']:.3g} | {a['pkbkr_max']:.3g} "
            f"| {a['ratio_pkbkr_to_constant']:.2f} |"
        )
    (out / "evaluation.md").write_text("\n".join(lines) + "\n")
    return aggregate
