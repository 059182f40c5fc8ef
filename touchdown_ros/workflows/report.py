"""Figures and tables built from what core returns (matplotlib, no display needed)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from touchdown_ros.core.estimate import force_std  # noqa: E402
from touchdown_ros.workflows.offline import BagEstimate, radial_force_std  # noqa: E402

AXES = ("x", "y", "z")


def _time(result: BagEstimate) -> np.ndarray:
    stamps = result.estimate.stamps_ns
    return (stamps - stamps[0]) * 1e-9


#: How figures and summary.md name the written estimate.
ANSWER_LABELS = {"smoothed": "RTS smoother", "filtered": "EKF"}


def plot_estimate(result: BagEstimate, out: Path) -> list[Path]:
    """Displacement (paper Fig. 2-4), velocity and contact force (Fig. 6) figures of one bag; the
    written estimate (`result.answer`), its contact force with a +-2 sigma band."""
    out.mkdir(parents=True, exist_ok=True)
    t = _time(result)
    est, truth, written = result.estimate, result.truth, result.written
    label = ANSWER_LABELS[result.answer]
    name = result.path.name
    written_files = []

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, est.measured[:, i] * 1e3, ".", ms=1.5, color="0.6", label=f"{AXES[i]} measured")
        ax.plot(t, np.asarray(written.state)[:, i] * 1e3, lw=1, label=f"{AXES[i]} estimated ({label})")
        ax.set_ylabel(f"{AXES[i]} / mm")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{name}: measured and estimated displacement")
    written_files.append(_save(fig, out / "displacement.png"))

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i, ax in enumerate(axes):
        if truth is not None:
            ax.plot(t, truth.velocity[:, i], color="k", lw=1.5, label="truth")
        ax.plot(t, np.asarray(est.filtered.state)[:, 4 + i], lw=1, label="EKF")
        ax.plot(t, np.asarray(est.smoothed.state)[:, 4 + i], lw=1, ls="--", label="RTS smoother")
        ax.set_ylabel(f"v{AXES[i]} / (m/s)")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{name}: velocity")
    written_files.append(_save(fig, out / "velocity.png"))

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    force, force_cov = np.asarray(written.force_xyz), np.asarray(written.force_cov)
    panels = [
        ("axial force F_z", force[:, 2], force_std(force_cov)[:, 2], None if truth is None else truth.contact_force[:, 2]),
        (
            "radial force |F_xy|",
            np.hypot(force[:, 0], force[:, 1]),
            radial_force_std(force, force_cov),
            None if truth is None else np.hypot(truth.contact_force[:, 0], truth.contact_force[:, 1]),
        ),
    ]
    for ax, (quantity, value, std, true) in zip(axes, panels):
        ax.fill_between(t, (value - 2 * std) / 1e3, (value + 2 * std) / 1e3, color="C0", alpha=0.3, lw=0,
                        label=f"{label} $\\pm 2\\sigma$")
        if true is not None:
            ax.plot(t, true / 1e3, color="k", lw=1.5, label="truth")
        ax.plot(t, value / 1e3, lw=1, color="C0", label=label)
        ax.set_ylabel(f"{quantity} / kN")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{name}: contact force ({label}; band: $\\pm 2\\sigma$ linearised through the state covariance)")
    written_files.append(_save(fig, out / "contact_force.png"))
    return written_files


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def summary_table(results: Sequence[BagEstimate]) -> str:
    """Markdown: which estimate the figures are of, then a table of the per-bag summaries."""
    answers = sorted({result.answer for result in results})
    which = " and ".join(f"{ANSWER_LABELS[a]} ({a})" for a in answers)
    intro = (
        f"Estimate written and summarised: **{which}**. The RTS smoother uses the whole record; the EKF "
        "(`--filtered`) only the samples up to each one, as the live node does. sigma: 1-sigma of the "
        "contact force, linearised through the estimate's covariance.\n\n"
    )
    header = (
        "| bag | estimate | samples | RMSE x / um | RMSE y / um | RMSE z / um | peak F_z / kN | sigma at peak F_z / kN "
        "| peak F_r / kN | velocity RMSE / (mm/s) | force RMSE / N | peak F_z error | input (docs/input_policy.md) |\n"
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n"
    )
    rows = []
    for result in results:
        s = result.summary
        rms = [f"{v * 1e6:.2f}" for v in s["rmse_displacement_m"]]
        truth = s.get("truth")
        if truth:
            velocity = f"{np.linalg.norm(truth['rmse_velocity_mps']) * 1e3:.2f}"
            force = f"{np.linalg.norm(truth['rmse_contact_force_N']):.0f}"
            peak = f"{truth['peak_axial_force_error'] * 100:+.1f} %"
        else:
            velocity = force = peak = "-"
        rows.append(
            f"| {result.path.name} | {result.answer} | {s['samples']} | {' | '.join(rms)} "
            f"| {s['peak_axial_force_N'] / 1e3:.2f} | {s['peak_axial_force_std_N'] / 1e3:.2f} "
            f"| {s['peak_radial_force_N'] / 1e3:.2f} | {velocity} | {force} | {peak} | {input_text(s)} |"
        )
    return intro + header + "\n".join(rows) + "\n"


def input_text(summary: dict[str, Any]) -> str:
    """What the input policy did to one bag, in words with counts ('clean' when nothing)."""
    counts = summary.get("input") or {}
    parts = []
    if summary.get("predicted_only_samples"):
        parts.append(f"{summary['predicted_only_samples']} predict-only rows (left out of the peaks)")
    for key, words in (
        ("saturated", "saturated or pinned samples"),
        ("non_finite", "non-finite samples"),
        ("bridged_gaps", "gaps bridged"),
        ("gaps", "gaps beyond node.bridge_gap"),
        ("clock_jump_forward", "clock jumps forward"),
        ("clock_jump_backward", "clock jumps back"),
        ("unusable_runs", "runs of unusable samples beyond node.bridge_gap"),
        ("dropped_rows", "rows not estimated"),
        ("filter_restarts", "filter restarts"),
    ):
        if counts.get(key):
            parts.append(f"{counts[key]} {words}")
    return "; ".join(parts) or "clean"


def write_summaries(results: Sequence[BagEstimate], out: Path, extra: dict[str, Any] | None = None) -> None:
    """summary.json (all numbers) and summary.md (the table) in out."""
    out.mkdir(parents=True, exist_ok=True)
    document = {"bags": {str(r.path): r.summary for r in results}, **(extra or {})}
    (out / "summary.json").write_text(json.dumps(document, indent=2))
    (out / "summary.md").write_text(summary_table(results))


def plot_evaluation(comparisons, config, coeffs, out: Path, example: int = 0) -> list[Path]:
    """The paper's Fig. 2-8 for a cross-validated campaign, and maps of the learned parameters."""
    from touchdown_ros.core.pkbkr import axial_parameters, radial_parameters

    out.mkdir(parents=True, exist_ok=True)
    written = []
    c = comparisons[example]
    t = _time(c.constant)

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, c.constant.estimate.measured[:, i] * 1e3, ".", ms=1.5, color="0.6", label="measured")
        ax.plot(t, np.asarray(c.constant.estimate.filtered.state)[:, i] * 1e3, lw=1, label="constant [13]")
        ax.plot(t, np.asarray(c.pkbkr.estimate.filtered.state)[:, i] * 1e3, lw=1, ls="--", label="PKBKR")
        ax.set_ylabel(f"{AXES[i]} / mm")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{c.path.name}: measured and estimated displacement (paper Fig. 2-4)")
    written.append(_save(fig, out / "fig2-4_displacement.png"))

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
    written.append(_save(fig, out / "fig5_rmse_per_experiment.png"))

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
        written.append(_save(fig, out / "fig6_force.png"))

    from touchdown_ros.core.metrics import impacts
    from touchdown_ros.workflows.evaluate import IMPACT_THRESHOLD

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
        written.append(_save(fig, out / figure))

    kernel, nominal = config.kernel, config.nominal

    def span(T, scale):
        deformation = np.linspace(0.0, float(np.max(T[:, 0])) * scale[0], 60)
        velocity = np.linspace(float(np.min(T[:, 1])) * scale[1], float(np.max(T[:, 1])) * scale[1], 60)
        return np.meshgrid(deformation, velocity, indexing="ij")

    D_R, V_R = span(np.asarray(kernel.T_R), np.asarray(kernel.scale_R))
    D_Z, V_Z = span(np.asarray(kernel.T_Z), np.asarray(kernel.scale_Z))
    maps = [(name, D_R, V_R, value) for name, value in zip(("k_R", "c_R", "mu"), radial_parameters(kernel, nominal, coeffs, D_R, V_R))]
    maps += [(name, D_Z, V_Z, value) for name, value in zip(("k_Z", "c_Z", "k_ZR"), axial_parameters(kernel, nominal, coeffs, D_Z, V_Z))]
    fig, axes = plt.subplots(2, 3, figsize=(12, 7))
    for ax, (name, D, V, value) in zip(axes.ravel(), maps):
        relative = np.asarray(value) / getattr(nominal, name)
        image = ax.pcolormesh(V, D * 1e6, relative, shading="auto", cmap="viridis")
        fig.colorbar(image, ax=ax, label=f"{name} / nominal")
        ax.set_title(f"{name}(deformation, velocity)")
        ax.set_xlabel("velocity / (m/s)")
        ax.set_ylabel("deformation / um")
    fig.suptitle("Learned PKBKR parameters relative to their nominal values")
    written.append(_save(fig, out / "parameter_maps.png"))
    return written


# ---------------------------------------------------------------- touchdown diagnose

def plot_diagnosis(diagnoses, config, out: Path) -> list[Path]:
    """Figures of `touchdown diagnose`, one or two models (before / after) overlaid."""
    from touchdown_ros.core import diagnostics as dg

    out.mkdir(parents=True, exist_ok=True)
    written = []
    colours = ("tab:red", "tab:blue")
    example = [d.bags[0] for d in diagnoses]  # the first bag, as each model saw it
    t = _time(example[0].result)
    name = example[0].path.name

    # measured vs one-step and k-step prediction
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, example[0].result.estimate.measured[:, i] * 1e6, ".", ms=1.5, color="0.6", label="measured")
        for d, b, c in zip(diagnoses, example, colours):
            ax.plot(t, b.k_step[:, i] * 1e6, lw=1, color=c, label=f"{d.label}: k-step prediction")
        ax.set_ylabel(f"{AXES[i]} / um")
        ax.legend(loc="upper right", fontsize=7)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{name}: measurement vs k-step-ahead prediction (model alone, no update)")
    written.append(_save(fig, out / "prediction.png"))

    # errors by phase (k-step, and contact force vs truth)
    has_force = all("force_rmse_N" in d.metrics["phases"][dg.PHASES[0]] for d in diagnoses)
    fig, axes = plt.subplots(1, 2 if has_force else 1, figsize=(12 if has_force else 7, 4), squeeze=False)
    width = 0.8 / (3 * len(diagnoses))
    for panel, (key, scale, unit) in enumerate((("k_step_rmse_m", 1e6, "um"), ("force_rmse_N", 1.0, "N"))[: 2 if has_force else 1]):
        ax = axes[0, panel]
        for j, d in enumerate(diagnoses):
            for i, axis in enumerate(AXES):
                values = [np.nan_to_num(np.asarray(d.metrics["phases"][p][key], float)[i]) * scale for p in dg.PHASES]
                offset = (j * 3 + i) * width - 0.4
                ax.bar(np.arange(4) + offset, values, width, color=colours[j], alpha=0.4 + 0.2 * i, label=f"{d.label} {axis}")
        ax.set_xticks(np.arange(4), dg.PHASES)
        ax.set_ylabel(("k-step RMSE" if panel == 0 else "contact-force RMSE vs truth") + f" / {unit}")
        ax.legend(fontsize=7, ncol=2)
    fig.suptitle("errors by contact phase")
    written.append(_save(fig, out / "errors_by_phase.png"))

    # residual tests: autocorrelation of innovations and cross-correlation with velocity
    fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharey="row")
    for i, axis in enumerate(AXES):
        for d, b, c in zip(diagnoses, example, colours):
            e = np.asarray(b.result.estimate.innovation)[:, i]
            r, band = dg.autocorrelation(e, 60)
            axes[0, i].plot(r, color=c, label=d.label)
            lags, rx, _ = dg.cross_correlation(e, np.asarray(b.result.estimate.smoothed.state)[:, 4 + i], 60)
            axes[1, i].plot(lags, rx, color=c, label=d.label)
        for row in (0, 1):
            axes[row, i].axhspan(-band, band, color="0.85", label="99 % band")
        axes[0, i].set_title(f"{AXES[i]}: innovation autocorrelation")
        axes[1, i].set_title(f"{AXES[i]}: x-corr with v{AXES[i]}")
        axes[1, i].set_xlabel("lag / samples")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{name}: residual tests")
    written.append(_save(fig, out / "residual_tests.png"))

    # missing force with its uncertainty
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for i, ax in enumerate(axes):
        for d, b, c in zip(diagnoses, example, colours):
            f, s = b.missing.force[:, i], b.missing.force_std[:, i]
            ax.fill_between(t, f - 2 * s, f + 2 * s, color=c, alpha=0.2)
            ax.plot(t, f, color=c, lw=1, label=f"{d.label} (+-2 std)")
        phase = example[0].phase
        ax.fill_between(t, 0, 1, where=phase > 0, transform=ax.get_xaxis_transform(), color="0.9", label="contact")
        ax.set_ylabel(f"F_{AXES[i]} missing / N")
        ax.legend(loc="upper right", fontsize=7)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{name}: the force the model lacks (smoothed disturbance states)")
    written.append(_save(fig, out / "missing_force.png"))

    # candidate ranking
    fig, axes = plt.subplots(1, len(diagnoses), figsize=(6 * len(diagnoses), 4), squeeze=False)
    for ax, d, c in zip(axes[0], diagnoses, colours):
        rows = d.verdict["candidates"]
        ax.barh([r["candidate"] for r in rows][::-1], [r["err_percent"] for r in rows][::-1], color=c)
        ax.axvline(d.verdict["threshold_percent"], color="k", ls="--", lw=1, label="verdict threshold")
        ax.set_xlim(0, 100)
        ax.set_xlabel("ERR / % of the missing force not absorbed by the PKBKR coefficients")
        ax.set_title(f"{d.label}: {'explained' if d.verdict['explained'] else 'UNEXPLAINED'}")
        ax.legend(fontsize=7)
    written.append(_save(fig, out / "ranking.png"))

    # error over time and by impact
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    window = max(1, int(round(0.005 / config.sample_period)))
    for d, b, c in zip(diagnoses, example, colours):
        w = dg.windowed_rms(b.k_step - b.result.estimate.measured, window)
        axes[0].plot(np.arange(len(w)) * window * config.sample_period, np.linalg.norm(np.nan_to_num(w), axis=1) * 1e6, "o-", color=c, label=d.label)
        imp = d.metrics["impacts"]
        axes[1].plot([m["impact"] for m in imp], [np.linalg.norm(np.nan_to_num(m["k_step_rmse_m"])) * 1e6 for m in imp], "o-", color=c, label=d.label)
    axes[0].set_xlabel("time after drop onset / s")
    axes[0].set_ylabel(f"k-step RMSE per {window * config.sample_period * 1e3:.0f} ms / um")
    axes[1].set_xlabel("impact number (all bags)")
    axes[1].set_ylabel("k-step RMSE / um")
    for ax in axes:
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    written.append(_save(fig, out / "error_over_time.png"))

    # regions of the (deformation, velocity) planes
    planes = [(d, p) for d in diagnoses for p in ("axial", "radial") if p in d.metrics["regions"]]
    if planes:
        fig, axes = plt.subplots(1, len(planes), figsize=(5 * len(planes), 4), squeeze=False)
        for ax, (d, p) in zip(axes[0], planes):
            r = d.metrics["regions"][p]
            grid = np.array([[np.nan if v is None else v for v in row] for row in r["k_step_rmse_m"]], float) * 1e6
            de, ve = np.asarray(r["deformation_edges_m"]) * 1e6, np.asarray(r["velocity_edges_mps"]) * 1e3
            mesh = ax.pcolormesh(de, ve, grid.T, cmap="viridis")
            fig.colorbar(mesh, ax=ax, label="k-step RMSE / um")
            ax.set_xlabel(f"{p} deformation / um")
            ax.set_ylabel(f"{p} velocity / (mm/s)")
            ax.set_title(f"{d.label}: {p} contact")
        written.append(_save(fig, out / "regions.png"))

    # signature: spectrum of the missing force
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    rotor = config.rig.speed / (2 * np.pi)
    for i, ax in enumerate(axes):
        for d, b, c in zip(diagnoses, example, colours):
            x = b.missing.force[:, i] - np.mean(b.missing.force[:, i])
            spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
            ax.semilogy(np.fft.rfftfreq(len(x), config.sample_period), spectrum + 1e-9, color=c, lw=1, label=d.label)
        for harmonic in (1, 2):
            ax.axvline(harmonic * rotor, color="k", ls=":", lw=1)
        ax.set_xlim(0, 6 * rotor)
        ax.set_xlabel("frequency / Hz (dotted: 1x, 2x rotor speed)")
        ax.set_title(f"missing F_{AXES[i]} spectrum")
        ax.legend(fontsize=7)
    written.append(_save(fig, out / "signature.png"))
    return written
