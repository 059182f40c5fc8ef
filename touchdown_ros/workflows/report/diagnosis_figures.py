"""`touchdown diagnose`'s figures, one or two models (before / after) overlaid."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from touchdown_ros.core.diagnostics.breakdown import AXES, PHASES, windowed_rms
from touchdown_ros.core.diagnostics.residuals import autocorrelation, cross_correlation
from touchdown_ros.workflows.report.plotting import plt, save, seconds


def plot_diagnosis(diagnoses, config, out: Path) -> list[Path]:
    """Figures of `touchdown diagnose`, one or two models (before / after) overlaid."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    colours = ("tab:red", "tab:blue")
    example = [d.bags[0] for d in diagnoses]  # the first bag, as each model saw it
    t = seconds(example[0].result)
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
    written.append(save(fig, out / "prediction.png"))

    # errors by phase (k-step, and contact force vs truth)
    has_force = all("force_rmse_N" in d.metrics["phases"][PHASES[0]] for d in diagnoses)
    fig, axes = plt.subplots(1, 2 if has_force else 1, figsize=(12 if has_force else 7, 4), squeeze=False)
    width = 0.8 / (3 * len(diagnoses))
    for panel, (key, scale, unit) in enumerate(
        (("k_step_rmse_m", 1e6, "um"), ("force_rmse_N", 1.0, "N"))[: 2 if has_force else 1]
    ):
        ax = axes[0, panel]
        for j, d in enumerate(diagnoses):
            for i, axis in enumerate(AXES):
                values = [np.nan_to_num(np.asarray(d.metrics["phases"][p][key], float)[i]) * scale for p in PHASES]
                offset = (j * 3 + i) * width - 0.4
                ax.bar(
                    np.arange(4) + offset,
                    values,
                    width,
                    color=colours[j],
                    alpha=0.4 + 0.2 * i,
                    label=f"{d.label} {axis}",
                )
        ax.set_xticks(np.arange(4), PHASES)
        ax.set_ylabel(("k-step RMSE" if panel == 0 else "contact-force RMSE vs truth") + f" / {unit}")
        ax.legend(fontsize=7, ncol=2)
    fig.suptitle("errors by contact phase")
    written.append(save(fig, out / "errors_by_phase.png"))

    # residual tests: autocorrelation of innovations and cross-correlation with velocity
    fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharey="row")
    for i, axis in enumerate(AXES):
        for d, b, c in zip(diagnoses, example, colours):
            e = np.asarray(b.result.estimate.innovation)[:, i]
            r, band = autocorrelation(e, 60)
            axes[0, i].plot(r, color=c, label=d.label)
            lags, rx, _ = cross_correlation(e, np.asarray(b.result.estimate.smoothed.state)[:, 4 + i], 60)
            axes[1, i].plot(lags, rx, color=c, label=d.label)
        for row in (0, 1):
            axes[row, i].axhspan(-band, band, color="0.85", label="99 % band")
        axes[0, i].set_title(f"{AXES[i]}: innovation autocorrelation")
        axes[1, i].set_title(f"{AXES[i]}: x-corr with v{AXES[i]}")
        axes[1, i].set_xlabel("lag / samples")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{name}: residual tests")
    written.append(save(fig, out / "residual_tests.png"))

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
    written.append(save(fig, out / "missing_force.png"))

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
    written.append(save(fig, out / "ranking.png"))

    # error over time and by impact
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    window = max(1, int(round(0.005 / config.sample_period)))
    for d, b, c in zip(diagnoses, example, colours):
        w = windowed_rms(b.k_step - b.result.estimate.measured, window)
        axes[0].plot(
            np.arange(len(w)) * window * config.sample_period,
            np.linalg.norm(np.nan_to_num(w), axis=1) * 1e6,
            "o-",
            color=c,
            label=d.label,
        )
        imp = d.metrics["impacts"]
        axes[1].plot(
            [m["impact"] for m in imp],
            [np.linalg.norm(np.nan_to_num(m["k_step_rmse_m"])) * 1e6 for m in imp],
            "o-",
            color=c,
            label=d.label,
        )
    axes[0].set_xlabel("time after drop onset / s")
    axes[0].set_ylabel(f"k-step RMSE per {window * config.sample_period * 1e3:.0f} ms / um")
    axes[1].set_xlabel("impact number (all bags)")
    axes[1].set_ylabel("k-step RMSE / um")
    for ax in axes:
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    written.append(save(fig, out / "error_over_time.png"))

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
        written.append(save(fig, out / "regions.png"))

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
    written.append(save(fig, out / "signature.png"))
    return written
