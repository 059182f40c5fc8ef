"""`touchdown diagnose`'s report: diagnosis.json, diagnosis.md, errors.csv, ranking.csv and the figures."""
from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from touchdown_ros.core.diagnostics.breakdown import AXES, PHASES
from touchdown_ros.core.diagnostics.prediction import comparison
from touchdown_ros.core.selection import BAG_AGREEMENT_SIGNIFICANCE, fall_percent
from touchdown_ros.io.config import Config
from touchdown_ros.workflows.report.diagnosis_figures import plot_diagnosis

if TYPE_CHECKING:  # the workflow imports this module to write its results
    from touchdown_ros.workflows.diagnose import Diagnosis, Settings

CONSTANT_MODEL = "constant model (rig nominal values)"  # what a diagnosis without a coefficient file is of
#: Relative half-width of a 95 % interval below which the report calls a fitted size pinned (issue 16's 10 %).
SIZE_TOLERANCE = 0.10
#: Squared posterior correlation from which a fitted parameter is said to move with another coordinate of its fit:
#: that coordinate then accounts for half its variance or more.
SHARED_VARIANCE = 0.5
#: The stage-1 coordinates a named effect's parameter can move with, in words.
COORDINATE_WORDS = {
    "k_R": "the bore contact's stiffness", "c_R": "the bore contact's damping", "mu": "the bore's friction",
    "k_Z": "the face contact's stiffness", "c_Z": "the face contact's damping", "k_ZR": "the face's friction",
    "q_radial": "the radial process noise", "q_axial": "the axial process noise",
    "support_preload": "the axial support's knee", "support_span": "the axial support's span",
    "radial_clearance": "the radial clearance", "axial_clearance": "the axial clearance",
    "friction_drop": "the friction's Stribeck drop", "stribeck_velocity": "the Stribeck velocity",
}


def write_diagnosis(diagnoses: Sequence[Diagnosis], config: Config, out: Path, settings: Settings) -> dict[str, Any]:
    """diagnosis.json, diagnosis.md, errors.csv, ranking.csv and the figures in out."""
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
        document["comparison"] = comparison(diagnoses[0].metrics, diagnoses[1].metrics)
    (out / "diagnosis.json").write_text(json.dumps(document, indent=2, allow_nan=True))
    _write_csv(diagnoses, out)
    (out / "diagnosis.md").write_text(markdown(document))
    plot_diagnosis(diagnoses, config, out / "figures")
    return document


def _json_ready(diagnosis: Diagnosis, settings: Settings) -> dict[str, Any]:
    return {
        "label": diagnosis.label,
        "coefficients": diagnosis.coefficients,
        "effects": diagnosis.effects,
        "metrics": diagnosis.metrics,
        "residual_tests": diagnosis.tests,
        "verdict": diagnosis.verdict,
        "signature": diagnosis.signature,
        "notes": diagnosis.notes,
        "bags": {
            b.path.name: {"path": str(b.path), "conditions": b.conditions, **b.metrics} for b in diagnosis.bags
        },
    }


def _write_csv(diagnoses: Sequence[Diagnosis], out: Path) -> None:
    with open(out / "errors.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["model", "bag", "phase", "axis", "samples", "k_step_rmse_m", "force_rmse_N"])
        for d in diagnoses:
            for bag, metrics in [("ALL", d.metrics)] + [(b.path.name, b.metrics) for b in d.bags]:
                for phase, p in [("all", None)] + list(metrics["phases"].items()):
                    for i, axis in enumerate(AXES):
                        if p is None:
                            k, f, n = (
                                metrics["k_step"]["rmse_m"][i],
                                metrics.get("contact_force", {}).get("rmse_N", [None] * 3)[i],
                                metrics["samples"],
                            )
                        else:
                            k, f, n = p["k_step_rmse_m"][i], p.get("force_rmse_N", [None] * 3)[i], p["samples"]
                        writer.writerow([d.label, bag, phase, axis, n, k, f])
    with open(out / "ranking.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(
            ["model", "rank", "candidate", "err_percent", "parameter", "value", "std", "ci95_low", "ci95_high", "unit",
             "most_correlated_with", "correlation"]
        )
        for d in diagnoses:
            for row in d.verdict["candidates"]:
                for name, p in row["parameters"].items():
                    writer.writerow(
                        [
                            d.label,
                            row["rank"],
                            row["candidate"],
                            f"{row['err_percent']:.3f}",
                            name,
                            p["value"],
                            p["std"],
                            *p["ci95"],
                            p["unit"],
                            *((p["correlated_with"]["coordinate"], p["correlated_with"]["r"]) if "correlated_with" in p
                              else ("", "")),
                        ]
                    )


def _um(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v * 1e6:.2f}"


def markdown(document: dict[str, Any]) -> str:
    """The report as Markdown: errors, residual tests, missing force, ranking, verdict (side by side)."""
    models = document["models"]
    labels = [m["label"] for m in models]
    s = document["settings"]
    lines = [
        "# touchdown diagnose\n",
        f"k-step prediction: {s['k_step_samples']} samples ({s['k_step_seconds'] * 1e3:.1f} ms) ahead, no update.\n",
    ]
    for m in models:
        lines.append(f"- **{m['label']}**: {m['coefficients']}; effects {m['effects'] or 'none'}")
        lines += [f"  - {note}" for note in m["notes"]]
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
        lines.append(
            row(
                "contact force RMSE (norm) vs truth",
                [f"{v:.0f} N" for v in vals] + ([ratio(vals[1], vals[0])] if len(models) == 2 else []),
            )
        )
    vals = [m["metrics"]["k_step"]["rmse_norm_m"] for m in models]
    lines.append(
        row(
            "**k-step RMSE (norm)**",
            [f"{_um(v)} um" for v in vals] + ([ratio(vals[1], vals[0])] if len(models) == 2 else []),
        )
    )

    lines += ["", "## k-step RMSE by contact phase (x / y / z, um)", "", head, rule]
    for phase in models[0]["metrics"]["phases"]:
        ps = [m["metrics"]["phases"][phase] for m in models]
        cells = [f"{' / '.join(_um(v) for v in p['k_step_rmse_m'])} ({p['samples']})" for p in ps]
        if len(models) == 2:
            a, b = (np.linalg.norm(np.nan_to_num(p["k_step_rmse_m"])) for p in ps[::-1])
            cells.append(ratio(a, b))
        lines.append(row(phase, cells))
    if all("force_rmse_N" in m["metrics"]["phases"][PHASES[0]] for m in models):
        lines += ["", "## Contact-force RMSE vs truth by phase (x / y / z, N)", "", head, rule]
        for phase in models[0]["metrics"]["phases"]:
            ps = [m["metrics"]["phases"][phase] for m in models]
            cells = [
                " / ".join("-" if v is None or not np.isfinite(v) else f"{v:.0f}" for v in p["force_rmse_N"])
                for p in ps
            ]
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
            lines.append(
                row(f"{axis} {title}", [f"{100 * v:.0f} %" for v in vals] + ([""] if len(models) == 2 else []))
            )

    lines += [
        "",
        "## Missing force (smoothed disturbance states): mean +- rms of the estimate's std, N",
        "",
        head,
        rule,
    ]
    for phase in list(PHASES) + ["all"]:
        cells = []
        for m in models:
            t = m["metrics"]["missing_force"].get(phase)
            cells.append(
                "-"
                if t is None
                else " / ".join(f"{mu:.0f}+-{sd:.0f}" for mu, sd in zip(t["mean_N"], t["std_of_estimate_N"]))
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
        step = next_step(m)
        if step:
            lines += [step, ""]
        sized = how_well_sized(m)
        if sized:
            lines += [sized, ""]
        if "frols" in v:
            lines += [*fitted_markdown(v), "", f"FROLS (the first pass that chose them): {v['frols_text']}.", ""]
        lines += [
            f"The model's own PKBKR coefficients (forced first) can absorb {v['forced_err_percent']:.1f} % of the "
            f"missing-force energy; the ERR below are shares of the rest. "
            f"FROLS threshold: {v['threshold_percent']:.0f} %.",
            "",
            "| rank | candidate | ERR | parameters (linearised fit, +- 1 std, pooled; per bag) |",
            "|---:|---|---:|---|",
        ]
        for c in v.get("frols", v["candidates"]):
            params = "; ".join(
                f"{_value_sd(n, p)} ("
                + ", ".join(f"{bag} {val:.4g}" for bag, val in p["per_bag"].items())
                + ")"
                for n, p in c["parameters"].items()
            )
            lines.append(f"| {c['rank']} | {c['candidate']} | {c['err_percent']:.1f} % | {params} |")
        lines.append("")
        lines.append(
            "FROLS order: "
            + ", ".join(
                f"{o['candidate']} (+{o['err_percent']:.1f} %, {o['cumulative_percent']:.1f} %)" for o in v["order"]
            )
        )
        lines += ["", f"Residual signature: {m['signature']['summary']}."]
    if "comparison" in document:
        c = document["comparison"]
        lines += ["", "## After / before", ""]
        lines.append(f"- k-step RMSE (norm): x {c['k_step_rmse_norm']:.2f}")
        if "contact_force_rmse_norm" in c:
            lines.append(f"- contact-force RMSE vs truth (norm): x {c['contact_force_rmse_norm']:.2f}")
        lines.append("- missing force rms per axis: " + " / ".join(f"x {v:.2f}" for v in c["missing_force_rms"]))
    return "\n".join(lines) + "\n"


def next_step(model: dict[str, Any]) -> str | None:
    """How to add the effect a model's verdict names (`touchdown train --start` from the diagnosed file, the effects
    it has kept beside the new one) and compare; None where the verdict names none."""
    verdict = model["verdict"]
    if not verdict["explained"]:
        return None
    best, coefficients = verdict["best"], model["coefficients"]
    active = ", ".join([*model["effects"], best])
    from_file = coefficients != CONSTANT_MODEL
    start, before = (f" --start {coefficients}", f" --coeffs {coefficients}") if from_file else ("", "")
    return (f"To add it: `touchdown train BAG... -o with_{best}.yaml{start} -p 'effects.active:=[{active}]'`, then "
            f"`touchdown diagnose BAG...{before} --compare with_{best}.yaml` (docs/workbench.md).")


def _unit_suffix(unit: str) -> str:
    """The unit to print after a value, with its space; nothing for a dimensionless one (unit "1")."""
    return "" if unit == "1" else f" {unit}"


def _value_sd(name: str, parameter: dict[str, Any]) -> str:
    """A fitted parameter as `name = value +- sd unit`."""
    return f"{name} = {parameter['value']:.4g} +- {parameter['std']:.2g}{_unit_suffix(parameter['unit'])}"


def how_well_sized(model: dict[str, Any], tolerance: float = SIZE_TOLERANCE) -> str | None:
    """How tightly the model's bags pin the named effect's fitted parameters (their `ci95`, relative), and where one
    is wider than +- `tolerance`, about how many drops like these would narrow it to that (the interval narrows as
    1 / sqrt(drops) if each drop adds as much information; a bias does not narrow so), and the other terms of the fit
    a parameter shares `SHARED_VARIANCE` of its variance or more with (`correlated_with`); None where the verdict names
    no fitted effect."""
    verdict = model["verdict"]
    if not verdict.get("explained"):
        return None
    row = next((r for r in verdict.get("candidates", ()) if r.get("fitted") and r["candidate"] == verdict["best"]),
               None)
    if row is None:
        return None
    widths, loose = [], []
    for name, p in row["parameters"].items():
        value, (low, high) = float(p["value"]), map(float, p["ci95"])
        unit = _unit_suffix(p["unit"])
        if not np.isfinite(high - low):
            widths.append(f"{name} {value:.4g}{unit} (no standard error)")
            continue
        if value == 0.0:  # at a bound: the interval in the parameter's unit
            widths.append(f"{name} 0 +- {(high - low) / 2:.2g}{unit}")
            continue
        half = (high - low) / 2 / abs(value)
        percent = f"{100 * half:.0f}" if half >= 0.1 else f"{100 * half:.2g}"
        widths.append(f"{name} {value:.4g}{unit} +- {percent} %")
        if half > tolerance:
            loose.append((name, half))
    drops = len(model["bags"])
    pin = "drop pins" if drops == 1 else "drops pin"
    text = f"How tightly {drops} {pin} its size (95 % intervals): {', '.join(widths)}."
    if loose:
        names = " and ".join(name for name, _ in loose)
        needed = int(np.ceil(drops * max(half for _, half in loose) ** 2 / tolerance ** 2))
        text += (f" {names} {'is' if len(loose) == 1 else 'are'} not pinned to +- {100 * tolerance:.0f} %: about "
                 f"{needed} drops like these would be (the interval narrows as 1 / sqrt(drops)). The intervals are "
                 "the fit's scatter; a bias from a force the model lacks does not narrow.")
    pairs, said = [], set()
    for name, p in row["parameters"].items():
        partner = p.get("correlated_with")
        pair = frozenset({f"{row['candidate']}.{name}", partner["coordinate"]}) if partner else None
        if partner and partner["r"] ** 2 >= SHARED_VARIANCE and pair not in said:
            said.add(pair)
            pairs.append(f"{name} with {_coordinate_words(partner['coordinate'], row['candidate'])} (posterior "
                         f"correlation {partner['r']:+.2f})")
    if pairs:
        text += (f" Its size moves with another term of the fit: {'; '.join(pairs)}. The drops tell such a pair's "
                 "joint effect better than either, and where the model's form of the one differs from the rig's, the "
                 "other's size makes up for it.")
    return text


def _coordinate_words(coordinate: str, effect: str) -> str:
    """A fit's coordinate (`core.calibration.Coordinates.names`) in words, for a parameter of `effect`."""
    if "." in coordinate:
        owner, parameter = coordinate.split(".", 1)
        return f"its {parameter}" if owner == effect else f"{owner}'s {parameter}"
    return f"{coordinate}, {COORDINATE_WORDS[coordinate]}" if coordinate in COORDINATE_WORDS else coordinate


def fitted_markdown(v: dict[str, Any]) -> list[str]:
    """The fitted candidates' table of a verdict (`fitted_verdict`), as Markdown lines."""
    held = v["held_out"]
    lines = [
        f"Candidates fitted with the model's constants (ln f0, Q factors) on the samples outside the held-out blocks "
        f"(one {held['block_samples']}-sample block in {held['every']}), judged on the held-out ones against the same "
        f"fit without any (criterion: BIC difference, negative is better). The k-step error net of the sensor "
        f"noise is the model's own part, sqrt(RMSE^2 - R) per axis (R's sd "
        + " / ".join(map(_um, held["measurement_noise_rms_m"]))
        + " um on x / y / z; the baseline's held-out k-step RMSE "
        + " / ".join(map(_um, held["baseline_k_step_rmse_m"]))
        + " um, net "
        + " / ".join(map(_um, held["baseline_k_step_rmse_net_m"]))
        + " um). Per bag: the candidate fitted to each bag alone, the constants held; the bags disagree where "
        f"those values differ beyond their standard errors (chi-square, p < {BAG_AGREEMENT_SIGNIFICANCE:g}), and "
        "such a candidate, fitting something that differs from drop to drop, is not named.",
        "",
        "| candidate | criterion | held-out NLL fall | k-step error fall | net of sensor noise | fitted value +- sd "
        "| per bag |",
        "|---|---:|---:|---:|---:|---|---|",
    ]
    for row in v["candidates"]:
        if not row["fitted"]:
            continue
        values = "; ".join(_value_sd(n, p) for n, p in row["parameters"].items())
        per_bag = "; ".join(
            ", ".join(f"{bag} {value:.4g} +- {p['per_bag_std'][bag]:.2g}" for bag, value in p["per_bag"].items())
            for p in row["parameters"].values()
            if p["per_bag"]
        )
        if row.get("bag_agreement"):
            agreement = row["bag_agreement"]
            per_bag += f" ({'disagree' if agreement['disagrees'] else 'agree'}: p = {agreement['p']:.2g})"
        lines.append(
            f"| {row['candidate']} | {row['criterion']:+.1f} | {row['held_out_nll_fall']:+.3f} | "
            f"{fall_percent(row['k_step_fall'])} | {fall_percent(row['k_step_fall_net'])} | {values} | "
            f"{per_bag or '-'} |"
        )
    phases = sorted(
        {p for row in v["candidates"] if row["fitted"] for p in row["k_step_fall_by_phase"]}, key=PHASES.index
    )
    lines += ["", "Held-out k-step error fall by contact phase:", "", "| candidate | " + " | ".join(phases) + " |",
              "|---|" + "---:|" * len(phases)]
    for row in v["candidates"]:
        if row["fitted"]:
            falls = row["k_step_fall_by_phase"]
            lines.append(
                f"| {row['candidate']} | "
                + " | ".join(fall_percent(falls[p]) if p in falls else "-" for p in phases)
                + " |"
            )
    return lines
