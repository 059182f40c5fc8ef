"""Figures and tables built from what core returns (matplotlib, no display needed)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from touchdown_ros.offline import BagEstimate  # noqa: E402

AXES = ("x", "y", "z")


def _time(result: BagEstimate) -> np.ndarray:
    stamps = result.estimate.stamps_ns
    return (stamps - stamps[0]) * 1e-9


def plot_estimate(result: BagEstimate, out: Path) -> list[Path]:
    """Displacement (paper Fig. 2-4), velocity and contact force (Fig. 6) figures of one bag."""
    out.mkdir(parents=True, exist_ok=True)
    t = _time(result)
    est, truth = result.estimate, result.truth
    name = result.path.name
    written = []

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, est.measured[:, i] * 1e3, ".", ms=1.5, color="0.6", label=f"{AXES[i]} measured")
        ax.plot(t, np.asarray(est.filtered.state)[:, i] * 1e3, lw=1, label=f"{AXES[i]} estimated (EKF)")
        ax.set_ylabel(f"{AXES[i]} / mm")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{name}: measured and estimated displacement")
    written.append(_save(fig, out / "displacement.png"))

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
    written.append(_save(fig, out / "velocity.png"))

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    force = np.asarray(est.filtered.force_xyz)
    panels = [("axial force F_z", force[:, 2], None), ("radial force |F_xy|", np.hypot(force[:, 0], force[:, 1]), None)]
    if truth is not None:
        panels = [
            (label, value, true)
            for (label, value, _), true in zip(
                panels, (truth.contact_force[:, 2], np.hypot(truth.contact_force[:, 0], truth.contact_force[:, 1]))
            )
        ]
    for ax, (label, value, true) in zip(axes, panels):
        if true is not None:
            ax.plot(t, true / 1e3, color="k", lw=1.5, label="truth")
        ax.plot(t, value / 1e3, lw=1, label="EKF")
        ax.set_ylabel(f"{label} / kN")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time after drop onset / s")
    fig.suptitle(f"{name}: contact force")
    written.append(_save(fig, out / "contact_force.png"))
    return written


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def summary_table(results: Sequence[BagEstimate]) -> str:
    """Markdown table of the per-bag summaries."""
    header = (
        "| bag | samples | RMSE x / um | RMSE y / um | RMSE z / um | peak F_z / kN | peak F_r / kN "
        "| velocity RMSE / (mm/s) | force RMSE / N | peak F_z error |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
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
            f"| {result.path.name} | {s['samples']} | {' | '.join(rms)} | {s['peak_axial_force_N'] / 1e3:.2f} "
            f"| {s['peak_radial_force_N'] / 1e3:.2f} | {velocity} | {force} | {peak} |"
        )
    return header + "\n".join(rows) + "\n"


def write_summaries(results: Sequence[BagEstimate], out: Path, extra: dict[str, Any] | None = None) -> None:
    """summary.json (all numbers) and summary.md (the table) in out."""
    out.mkdir(parents=True, exist_ok=True)
    document = {"bags": {str(r.path): r.summary for r in results}, **(extra or {})}
    (out / "summary.json").write_text(json.dumps(document, indent=2))
    (out / "summary.md").write_text(summary_table(results))
