"""`touchdown report`'s training report: what `touchdown train` found, from the coefficient file alone.

training.md (the calibrated constants beside the guess with their standard errors, the contact laws
screened, the lambda path, the noise and the NIS per bag, the notes) and figures/ (the constants'
ratio to the guess with their 95 % intervals, the laws' criteria, the loss and held-out loss per
step, the mean NIS per bag, the learned parameters' maps), with the learned functions' lowest and highest value
over the constants and where each is reached.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from matplotlib.ticker import MaxNLocator

from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.coefficients import CoefficientFile
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.report.evaluation import parameter_maps, plot_parameter_maps
from touchdown_ros.workflows.report.plotting import plt, save

#: The six contact constants f0 of stage 1, in the paper's order.
CONSTANTS = ("k_R", "c_R", "mu", "k_Z", "c_Z", "k_ZR")
#: Mean NIS per bag of a consistent filter: the measurement's size (x, y, z).
CONSISTENT_NIS = 3.0
#: A learned function within this of its constant everywhere counts as not moved by stage 2.
UNMOVED = 1.0e-9
#: What the report writes in its output directory.
REPORT_FILES = ("training.md", "figures")


def constant_rows(calibration: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Per contact constant: the guess, the calibrated value, their ratio, the relative standard error
    (sd of ln value) and whether the prior held it."""
    guess, calibrated = calibration.get("guess") or {}, calibration.get("calibrated") or {}
    errors, held = calibration.get("relative_standard_error") or {}, set(calibration.get("held_by_prior") or ())
    rows = []
    for name in CONSTANTS:
        if name not in calibrated:
            continue
        start, value = guess.get(name), float(calibrated[name])
        rows.append({
            "name": name, "guess": start, "calibrated": value,
            "ratio": value / start if start else None,
            "relative_sd": errors.get(name), "held_by_prior": name in held,
        })
    return rows


def _number(value: Any, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        return f"{value:.{digits}g}"
    return str(value)


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_number(v) for v in row) + " |" for row in rows]
    return lines


def _convergence(record: Mapping[str, Any]) -> str:
    if not record:
        return "not recorded"
    state = "converged" if record.get("converged") else "NOT converged"
    return (f"{state} after {record.get('steps')} steps ({record.get('reason')}); loss "
            f"{_number(record.get('initial_loss'), 7)} -> {_number(record.get('final_loss'), 7)} "
            f"in {_number(record.get('seconds'), 3)} s")


def markdown(loaded: CoefficientFile, config: Config, source: Path, figures: Sequence[str] = ()) -> str:
    """training.md of the coefficient file `loaded` (read from `source`; `config`: the rig as it calibrated it),
    naming the `figures` beside it."""
    document, training = loaded.document, loaded.training
    extra = training.extra
    lines = [f"# Training report: {source.name}", ""]
    lines.append(
        f"Written {document.get('created')} by touchdown_ros {document.get('software_version')} from "
        f"{len(training.bags)} bag(s); loss `{extra.get('loss', '-')}`; "
        f"{_number(extra.get('seconds'), 4)} s of training."
    )
    lines += ["", "## Stage 1: the contact law and its constants", ""]
    lines += _stage1_lines(extra.get("calibration") or {}, document)
    lines += ["", "## Stage 2: PKBKR", ""]
    lines += _stage2_lines(extra, training.regularisation)
    lines += ["", *_learned_range_lines(config, loaded.coeffs)]
    lines += ["", "## Noise and consistency", ""]
    lines += _noise_lines(extra, config)
    lines += ["", "## Bags", ""]
    lines += _table(["bag", "SHA-256"], [[b.get("path"), str(b.get("sha256", ""))[:16]] for b in training.bags])
    if figures:
        lines += ["", "Figures in `figures/`: " + ", ".join(figures) + "."]
    return "\n".join(lines) + "\n"


def _stage1_lines(calibration: Mapping[str, Any], document: Mapping[str, Any]) -> list[str]:
    """The chosen law, the constants against the guess, what the bags left open, the candidates and the effects."""
    if not calibration:
        return ["No stage-1 record in this file (written without calibration)."]
    lines = [f"Chosen: **{calibration.get('law')}**, friction `{calibration.get('friction')}`. Its last fit "
             f"{_convergence(calibration)}.", ""]
    rows = constant_rows(calibration)
    lines += _table(
        ["constant", "guess", "calibrated", "calibrated / guess", "standard error, %", "held by the prior"],
        [[r["name"], r["guess"], r["calibrated"], r["ratio"],
          None if r["relative_sd"] is None else 100 * r["relative_sd"], r["held_by_prior"]] for r in rows],
    )
    units = (document.get("contact") or {}).get("units")
    if units:
        lines += ["", f"Units: {units}."]
    others = {k: v for k, v in (calibration.get("relative_standard_error") or {}).items() if k not in CONSTANTS}
    if others:
        lines += ["", "Standard errors of the other stage-1 coordinates (sd of ln value, %): "
                  + ", ".join(f"{k} {100 * v:.3g}" for k, v in others.items())]
    correlations = calibration.get("strongest_correlations") or []
    if correlations:
        lines += ["", "Strongest correlations: " + ", ".join(f"{a} / {b} {r:+.2f}" for a, b, r in correlations)]
    notes = calibration.get("notes") or []
    if notes:
        lines += ["", "What the bags left open:", *[f"- {note}" for note in notes]]
    candidates = calibration.get("candidates") or []
    if candidates:
        lines += ["", "Candidates screened (criterion above the best; the lowest is refined on all bags):", ""]
        lines += _table(["candidate", "loss per sample", "criterion above the best", "steps"],
                        [[c.get("law"), c.get("loss"), c.get("criterion_above_best"), c.get("steps")]
                         for c in candidates])
    frictions = calibration.get("friction_models") or []
    if frictions:
        lines += ["", "Friction models (`training.friction_models`):", ""]
        lines += _table(["friction", "law", "loss", "criterion above the best", "s"],
                        [[f.get("friction"), f.get("law"), f.get("loss"), f.get("criterion_above_best"),
                          f.get("seconds")] for f in frictions])
    starts = calibration.get("friction_starts") or []
    if starts:
        lines += ["", "Friction starts (`training.friction_start: both`; final loss per sample):", ""]
        lines += _table(["law", "from the screened friction", "from the grid's pair", "kept"],
                        [[s.get("law"), _number(s.get("screened_loss"), 7), _number(s.get("grid_loss"), 7),
                          s.get("kept")] for s in starts])
    plain = calibration.get("process_noise_pass")
    if plain:
        lines += ["", f"The process noise comes from a stage 1 without the Stribeck drop ({plain.get('law')}): "
                  f"{_convergence(plain)}."]
    effects = document.get("effects") or {}
    if effects:
        lines += ["", "Add-on effects fitted:", ""]
        lines += _table(["effect", "acts where", "parameters"],
                        [[name, e.get("when") or "every bag",
                          ", ".join(f"{k} {_number(v)}" for k, v in (e.get("parameters") or {}).items())]
                         for name, e in effects.items()])
    return lines


def _stage2_lines(extra: Mapping[str, Any], regularisation: float) -> list[str]:
    """The chosen lambda, how its fit ended, the lambda path and the kernel's notes."""
    path = extra.get("regularisation_path") or {}
    lines = [f"lambda {_number(regularisation)}; the fit {_convergence(extra.get('pkbkr') or {})}."]
    tried = path.get("tried") or []
    if tried:
        lines += ["", "The lambda path (the held-out loss at each fit's kept step chooses):", ""]
        lines += _table(["lambda", "steps", "kept step", "held-out loss at the start", "held-out loss kept", "chosen"],
                        [[t.get("regularisation"), t.get("steps"), t.get("kept_step"), t.get("held_out_loss_start"),
                          t.get("held_out_loss"), t.get("regularisation") == path.get("chosen")] for t in tried])
    notes = extra.get("kernel_notes") or []
    if notes:
        lines += ["", *[f"- {note}" for note in notes]]
    return lines


def learned_range_rows(config: Config, coeffs: Coefficients) -> list[dict[str, Any]]:
    """Per PKBKR parameter (`parameter_maps`'s grid): its lowest and highest value over the calibrated constant
    and the deformation (um) and velocity (mm/s) where each is reached."""
    rows = []
    for name, D, V, relative in parameter_maps(config, coeffs):
        row: dict[str, Any] = {"name": name}
        for end, index in (("lowest", np.argmin(relative)), ("highest", np.argmax(relative))):
            at = np.unravel_index(index, relative.shape)
            row[end] = float(relative[at])
            row[f"{end}_at"] = (float(D[at]) * 1e6, float(V[at]) * 1e3)
        rows.append(row)
    return rows


def _learned_range_lines(config: Config, coeffs: Coefficients) -> list[str]:
    """The learned functions' range over the kernel's span, or that stage 2 left them at the constants."""
    rows = learned_range_rows(config, coeffs)
    if all(map(_unmoved, rows)):
        return ["The learned functions are the calibrated constants everywhere (stage 2 did not move them)."]
    lines = ["The learned functions over the kernel's span, times the calibrated constant (the deformation from 0 "
             "to the largest centre, the velocity over the centres'; `figures/parameter_maps.png`):", ""]
    lines += _table(
        ["parameter", "lowest", "at um / mm/s", "highest", "at um / mm/s"],
        [[r["name"], r["lowest"], _at(r, "lowest"), r["highest"], _at(r, "highest")] for r in rows],
    )
    lines += ["", "A stiffness higher while a contact closes than while it opens at the same deformation (closing: the "
              "radial velocity above 0, the axial one, zdot, below 0) is a hysteresis loop: it dissipates as damping "
              "does and raises the force while an impact closes, where few samples check it (docs/calibration.md, "
              "\"What the excess buys\")."]
    return lines


def _unmoved(row: Mapping[str, Any]) -> bool:
    return abs(row["lowest"] - 1.0) < UNMOVED and abs(row["highest"] - 1.0) < UNMOVED


def _at(row: Mapping[str, Any], end: str) -> str:
    """Where a `learned_range_rows` row reaches its `end` (um / mm/s); "-" for a function stage 2 left unmoved."""
    if _unmoved(row):
        return "-"
    deformation, velocity = row[f"{end}_at"]
    return f"{deformation:.3g} / {velocity:+.3g}"


def _noise_lines(extra: Mapping[str, Any], config: Config) -> list[str]:
    """R, the model's own force error and the mean NIS per bag."""
    sigma = np.sqrt(np.asarray(config.noise.measurement, dtype=float)) * 1e6
    lines = ["Sensor noise R (sd per axis, from the levitated samples): "
             + ", ".join(f"{a} {v:.2f} um" for a, v in zip("xyz", sigma)) + "."]
    force_error = extra.get("force_model_error") or {}
    if force_error.get("rms_N"):
        lines.append("The model's own force error in contact (rms x / y / z, widens the force band): "
                     + " / ".join(f"{v:.0f}" for v in force_error["rms_N"]) + " N.")
    nis = extra.get("mean_nis") or {}
    if nis:
        lines += ["", f"Mean NIS per bag ({CONSISTENT_NIS:g} when the filter's covariance matches its errors):", ""]
        lines += _table(["bag", "mean NIS"], [[Path(k).name, v] for k, v in nis.items()])
    return lines


def plot_training(loaded: CoefficientFile, config: Config, out: Path) -> list[Path]:
    """The report's figures in `out` (a directory that exists); the rig `config` as the file calibrated it."""
    extra = loaded.training.extra
    calibration = extra.get("calibration") or {}
    written = []
    rows = constant_rows(calibration)
    if rows:
        fig, ax = plt.subplots(figsize=(8, 4))
        positions = np.arange(len(rows))
        ratio = np.array([r["ratio"] or np.nan for r in rows], dtype=float)
        sd = np.array([r["relative_sd"] if r["relative_sd"] is not None else np.nan for r in rows], dtype=float)
        low, high = ratio * (1 - np.exp(-1.96 * sd)), ratio * (np.exp(1.96 * sd) - 1)
        held = np.array([r["held_by_prior"] for r in rows])
        recorded = calibration.get("prior_width")  # files before 2026-12-04 do not record it: the YAML's
        prior = float(np.exp(recorded if recorded is not None else config.training.prior_width))
        source = "" if recorded is not None else "; the rig YAML's training.prior_width"
        ax.axhspan(1 / prior, prior, color="0.9", label=f"the prior's 1 sd (x{prior:.3g} either way{source})")
        ax.axhline(1.0, color="0.5", lw=0.8)
        for mask, style, label in ((~held, "o", "fitted"), (held, "s", "held by the prior")):
            if mask.any():
                ax.errorbar(positions[mask], ratio[mask], yerr=[low[mask], high[mask]], fmt=style, capsize=4,
                            mfc="white" if style == "s" else None, label=label)
        ax.set_yscale("log")
        ax.set_xticks(positions, [r["name"] for r in rows])
        ax.set_ylabel("calibrated / guess")
        ax.set_title("Stage 1: the contact constants against the guess (95 % intervals)")
        ax.legend(fontsize=8)
        written.append(save(fig, out / "constants.png"))
    candidates = calibration.get("candidates") or []
    margins = [(c.get("law"), c.get("criterion_above_best")) for c in candidates
               if c.get("criterion_above_best") is not None]
    if margins:
        fig, ax = plt.subplots(figsize=(8, 2.5 + 0.4 * len(margins)))
        names, values = zip(*margins)
        ax.barh(range(len(values)), np.maximum(values, 0.0), color=["C2" if v == 0 else "C0" for v in values])
        for i, value in enumerate(values):
            if value == 0:
                ax.text(0.05, i, "the best", va="center", fontsize=8)
        ax.set_yticks(range(len(values)), names)
        ax.invert_yaxis()
        ax.set_xscale("symlog", linthresh=1.0)
        ax.axvline(2.0, color="0.4", ls="--", lw=0.8, label="2: as well supported as the best")
        ax.set_xlabel("information criterion above the best")
        ax.set_title("Stage 1: the candidate laws screened")
        ax.legend(fontsize=8)
        written.append(save(fig, out / "candidates.png"))
    written += _convergence_figure(calibration, extra, out)
    nis = extra.get("mean_nis") or {}
    if nis:
        fig, ax = plt.subplots(figsize=(max(5.0, 0.35 * len(nis) + 2), 3.5))
        ax.bar(range(len(nis)), list(nis.values()))
        ax.axhline(CONSISTENT_NIS, color="C3", ls="--", label=f"{CONSISTENT_NIS:g}: consistent")
        ax.set_xticks(range(len(nis)), [Path(k).name for k in nis], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel("mean NIS")
        ax.set_title("Mean normalised innovation squared per training bag")
        ax.legend(fontsize=8)
        written.append(save(fig, out / "nis.png"))
    written.append(plot_parameter_maps(config, loaded.coeffs, out / "parameter_maps.png"))
    return written


def _convergence_figure(calibration: Mapping[str, Any], extra: Mapping[str, Any], out: Path) -> list[Path]:
    """Stage 1's screened candidates' and last fit's loss, and each lambda's loss and held-out loss, per step
    (files from 2026-12-04 on record them)."""
    stage1 = calibration.get("loss_history")
    screened = [c for c in calibration.get("candidates") or () if c.get("loss_history")]
    tried = [t for t in (extra.get("regularisation_path") or {}).get("tried") or () if t.get("loss_history")]
    if not stage1 and not screened and not tried:
        return []
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, candidate in enumerate(screened):
        axes[0].plot(candidate["loss_history"], color=f"C{i}", lw=1, label=f"screened: {candidate['law']}")
    if stage1:
        axes[0].plot(stage1, "k.--", label=f"last fit, all bags: {calibration.get('law')}")
    if all(min(c["loss_history"]) > 0 for c in screened) and (not stage1 or min(stage1) > 0):
        axes[0].set_yscale("log")
    axes[0].set_title("Stage 1: the candidates screened and the last fit")
    if screened or stage1:
        axes[0].legend(fontsize=6)
    axes[0].set_xlabel("step")
    axes[0].set_ylabel("loss per sample")
    for i, t in enumerate(tried):
        colour, loss = f"C{i}", np.asarray(t["loss_history"])
        axes[1].plot(loss - loss[0], color=colour, label=f"lambda {t['regularisation']:g}: fitted samples")
        held_out = np.asarray(t.get("held_out_history") or [], dtype=float)
        if held_out.size:
            axes[1].plot(held_out - held_out[0], color=colour, ls="--", label="held-out blocks")
            if t.get("kept_step") is not None:
                axes[1].plot(t["kept_step"], held_out[t["kept_step"]] - held_out[0], "k*", ms=9)
    axes[1].set_title("Stage 2 per lambda (*: the kept step)")
    axes[1].set_xlabel("step")
    axes[1].set_ylabel("loss per sample, change from step 0")
    if tried:
        axes[1].legend(fontsize=7)
    axes[1].ticklabel_format(axis="y", useOffset=False)
    for ax in axes:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    return [save(fig, out / "convergence.png")]


def write_training_report(loaded: CoefficientFile, config: Config, source: Path, out: Path) -> list[Path]:
    """training.md and figures/ of the coefficient file `loaded` (read from `source`) in `out`."""
    folder = out / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    figures = plot_training(loaded, config, folder)
    (out / "training.md").write_text(markdown(loaded, config, source, [p.name for p in figures]))
    return [out / "training.md", *figures]
