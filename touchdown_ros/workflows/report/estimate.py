"""`touchdown estimate`'s report: figures of one bag, the summary table, summary.json and summary.md."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from touchdown_ros.core.diagnostics.breakdown import AXES
from touchdown_ros.core.estimate import force_std
from touchdown_ros.workflows.offline import BagEstimate, radial_force_std
from touchdown_ros.workflows.report.plotting import plt, save, seconds

#: How figures and summary.md name the written estimate.
ANSWER_LABELS = {"smoothed": "RTS smoother", "filtered": "EKF"}


def plot_estimate(result: BagEstimate, out: Path) -> list[Path]:
    """Displacement (paper Fig. 2-4), velocity and contact force (Fig. 6) figures of one bag; the
    written estimate (`result.answer`), its contact force with a +-2 sigma band."""
    out.mkdir(parents=True, exist_ok=True)
    t = seconds(result)
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
    written_files.append(save(fig, out / "displacement.png"))

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
    written_files.append(save(fig, out / "velocity.png"))

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    force, force_cov = np.asarray(written.force_xyz), np.asarray(written.force_cov)
    panels = [
        (
            "axial force F_z",
            force[:, 2],
            force_std(force_cov)[:, 2],
            None if truth is None else truth.contact_force[:, 2],
        ),
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
    fig.suptitle(f"{name}: contact force ({label}; band: $\\pm 2\\sigma$, state covariance and model error)")
    written_files.append(save(fig, out / "contact_force.png"))
    return written_files


def summary_table(
    results: Sequence[BagEstimate],
    process_noise: str | None = None,
    notes: Sequence[str] = (),
    force_band: str | None = None,
) -> str:
    """Markdown: which estimate the figures are of (and with which process noise and model error in the force
    band), what the calibration said the bags left open (`notes`, the coefficient file's), then a table of
    the per-bag summaries."""
    answers = sorted({result.answer for result in results})
    which = " and ".join(f"{ANSWER_LABELS[a]} ({a})" for a in answers)
    intro = (
        f"Estimate written and summarised: **{which}**. The RTS smoother uses the whole record; the EKF "
        "(`--filtered`) only the samples up to each one, as the live node does. sigma: 1-sigma of the "
        "contact force, linearised through the estimate's covariance, plus the model's own error in contact."
        + (f" Process noise: {process_noise}." if process_noise else "")
        + " Q x r / z: the factors on the radial and axial blocks of Q with which the bag's own displacements are most"
        " likely, taken where they lower its -2 ln L by 10 or more (a drop unlike the training drops;"
        " `filter.bag_process_noise`, smoothed estimate of a trained rig only; 1 / 1: Q as fitted), and the bag's"
        " mean NIS under Q as fitted (3 when the fitted Q holds on this bag). The filtered estimate, the live"
        " node's, scales Q as its innovations ask instead (`filter.adaptive_process_noise`): the mean and largest"
        " factor it took."
        + (f" The force band's model error in contact: {force_band}." if force_band else "")
        + "\n\n"
        + "".join(f"- Calibration: {note}\n" for note in notes)
        + ("\n" if notes else "")
    )
    header = (
        "| bag | estimate | samples | RMSE x / um | RMSE y / um | RMSE z / um | peak F_z / kN | sigma at peak F_z / kN "
        "| peak F_r / kN | velocity RMSE / (mm/s) | force RMSE / N | peak F_z error | 2-sigma band covers v / F, % "
        "| Q x r / z | input (docs/input_policy.md) |\n"
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n"
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
            bands = ("velocity_within_2_std", "contact_force_within_2_std")  # F: where either has a force
            covers = " / ".join(f"{100 * np.nanmean(truth[k]):.0f}" for k in bands)
        else:
            velocity = force = peak = covers = "-"
        rows.append(
            f"| {result.path.name} | {result.answer} | {s['samples']} | {' | '.join(rms)} "
            f"| {s['peak_axial_force_N'] / 1e3:.2f} | {s['peak_axial_force_std_N'] / 1e3:.2f} "
            f"| {s['peak_radial_force_N'] / 1e3:.2f} | {velocity} | {force} | {peak} | {covers} | {q_factors_text(s)} "
            f"| {input_text(s)} |"
        )
    return intro + header + "\n".join(rows) + "\n"


def q_factors_text(summary: dict[str, Any]) -> str:
    """The factors on Q's radial and axial blocks of one bag's estimate ("1 / 1": Q as fitted), with the fall of
    -2 ln L they bought and the bag's mean NIS under Q as fitted; for the filtered answer whose filter adapted Q
    (`filter.adaptive_process_noise`), the mean and largest factor it took."""
    if summary.get("estimate") == "filtered" and summary.get("process_scale_max", 1.0) > 1.0:
        return f"adapted: mean x{summary['process_scale_mean']:.2g}, max x{summary['process_scale_max']:.3g}"
    blocks = (summary.get("process_noise_factors") or {}).values()
    if not blocks:
        return "-"
    text = " / ".join(f"{b['factor']:g}" for b in blocks)
    fall = sum(b["minus_two_log_likelihood_fall"] for b in blocks if b["factor"] != 1.0)
    notes = ([f"-2 ln L -{fall:.0f}"] if fall else []) + (
        [f"NIS as fitted {summary['mean_nis_fitted_q']:.2f}"] if "mean_nis_fitted_q" in summary else [])
    return text + (f" ({'; '.join(notes)})" if notes else "")


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
    extra = extra or {}
    document = {"bags": {str(r.path): r.summary for r in results}, **extra}
    (out / "summary.json").write_text(json.dumps(document, indent=2))
    (out / "summary.md").write_text(
        summary_table(
            results, extra.get("process_noise"), extra.get("calibration_notes", ()), extra.get("force_band_model_error")
        )
    )
