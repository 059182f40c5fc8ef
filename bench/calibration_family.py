"""Identification on rigs nobody tuned the estimator to: the simulated rig family.

For each rig of `touchdown_ros.sim.family` (constants differing widely from the
reference: stiffness, damping law, friction, contact exponent, mass, noise), simulate
drops, run `touchdown train` with its defaults on the first bags from the reference
rig's contact guess, and estimate the other bags (smoothed; `--answer filtered`: the live filter's) with
- guess: the rig YAML's nominal constants as they are (constant model),
- stage 1: the calibrated contact law and constants (alpha = 0),
- stage 1+2: the calibrated constants with the PKBKR functions of the coefficient file,
against the simulator's truth.

    .venv/bin/python bench/calibration_family.py [--variants a,b] [--drawn N [--draw-seed S]] [--train 3] [--test 2]
        [--loss nll|one_step] [--out DIR] [-p contact.friction:=spinning_ring ...]
        [--truth simulator.ceramic.ring_inertia:=9.0e-3 --truth rig.radial_clearance:=0.26e-3 ...] [--reuse]
        [--answer smoothed|filtered]

With --reuse, each rig's bags and coefficient file already in DIR (an earlier run's) are estimated again
without simulating or training: for a change to the estimate alone, measured on the same files. With
--answer filtered the figures are the filter's (the fitted Q adapted to the innovations, as the live node filters;
no bag search; `-p filter.adaptive_process_noise:=false`: Q as fitted), written to
DIR/family_LOSS_filtered.*.

Writes DIR/family.json and DIR/family.md (the table of docs/calibration.md) and prints it.
Figures per held-out bag: peak axial / radial force error (%), force RMSE over the peak force
(%), displacement RMSE over the sensor noise, and the share of samples where the 95 % band
of velocity and of force covers the truth (%), and of force on the contact samples alone (out of
contact the estimate and the truth are both 0 inside a 0 band, which counts as covered). A second
table puts each held-out bag's peak errors beside the estimate at the truth's peak sample and the
estimate's own 1-sigma at its peak (% of the truth's peak): a miss within that sigma is what the
displacements cannot tell.
"""
from __future__ import annotations

import argparse
import io
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from touchdown_ros.cli import parameter_overrides
from touchdown_ros.core.metrics import relative_peak_error
from touchdown_ros.io.config import load_config
from touchdown_ros.io.coefficients import load_coefficients
from touchdown_ros.workflows.offline import ANSWERS, SMOOTHED, estimate_bag, estimator_for
from touchdown_ros.sim.family import VARIANTS, bag_name, drawn_variants, variant, write_variant_bags
from touchdown_ros.workflows.train import train

Z95 = 1.959964


def _coverage(
    estimate: np.ndarray, cov: np.ndarray | None, truth: np.ndarray, samples: np.ndarray | None = None
) -> float | None:
    """% of finite samples and axes where |estimate - truth| <= 1.96 sd (of `samples` (N,) bool, if given)."""
    if cov is None:
        return None
    sd = np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0.0, None))
    ok = np.isfinite(truth) & np.isfinite(estimate)
    if samples is not None:
        ok &= samples[:, None]
    return float(100.0 * np.mean((np.abs(estimate - truth) <= Z95 * sd)[ok]))


def _peak_anatomy(series: dict[str, tuple[np.ndarray, np.ndarray]], summary: dict) -> dict[str, float]:
    """Per axis of `series` (axis -> (estimated, true) force, N): the estimate at the truth's peak sample
    against the truth's peak (%), and the estimate's own 1-sigma at its peak (the bag summary's) over the
    truth's peak (%): whether a peak error is a bias or lies within what the estimate says it knows."""
    figures: dict[str, float] = {}
    for axis, (estimate, truth) in series.items():
        true_peak = summary["truth"][f"peak_{axis}_force_true_N"]
        at_true_peak = float(estimate[int(np.nanargmax(truth))])
        figures[f"{axis}_at_true_peak_error_percent"] = 100.0 * (at_true_peak - true_peak) / true_peak
        figures[f"{axis}_peak_std_percent"] = 100.0 * summary[f"peak_{axis}_force_std_N"] / true_peak
    return figures


def bag_figures(result, noise_rms: float) -> dict[str, float | None]:
    """The figures of one held-out bag, from its written estimate (smoothed or filtered: `result.answer`)."""
    estimate, truth = getattr(result.estimate, result.answer), result.truth
    force, true_force = np.asarray(estimate.force_xyz), truth.contact_force
    radial, true_radial = np.hypot(force[:, 0], force[:, 1]), np.hypot(true_force[:, 0], true_force[:, 1])
    peak = float(np.nanmax(np.linalg.norm(true_force, axis=1)))
    force_rmse = float(np.sqrt(np.nanmean(np.sum((force - true_force) ** 2, axis=1))))
    position, velocity = np.asarray(estimate.state)[:, :3], np.asarray(estimate.state)[:, 4:7]
    measured = result.estimate.measured
    force_cov = getattr(estimate, "force_cov", None)
    force_cov = None if force_cov is None else np.asarray(force_cov)
    in_contact = (np.linalg.norm(true_force, axis=1) > 0.0) | (np.linalg.norm(force, axis=1) > 0.0)
    return {
        **_peak_anatomy({"axial": (force[:, 2], true_force[:, 2]), "radial": (radial, true_radial)}, result.summary),
        "peak_axial_error_percent": 100.0 * relative_peak_error(force[:, 2], true_force[:, 2]),
        "peak_radial_error_percent": 100.0 * relative_peak_error(radial, true_radial),
        "force_rmse_percent_of_peak": 100.0 * force_rmse / peak,
        "displacement_rmse_over_noise": float(np.sqrt(np.nanmean((position - measured) ** 2)) / noise_rms),
        "velocity_rmse_m_s": float(np.sqrt(np.nanmean((velocity - truth.velocity) ** 2))),
        "velocity_band_coverage_percent": _coverage(
            velocity, np.asarray(estimate.state_cov)[:, 4:7, 4:7], truth.velocity
        ),
        "force_band_coverage_percent": _coverage(force, force_cov, true_force),
        "process_noise_factors": [b["factor"] for b in result.summary.get("process_noise_factors", {}).values()],
        # out of contact the estimate and the truth are both 0 with a 0 band, which counts as covered
        "force_band_coverage_in_contact_percent": _coverage(force, force_cov, true_force, in_contact),
        # per axis x / y / z: the axial band is the one impacts stretch (docs/calibration.md)
        "force_band_coverage_in_contact_per_axis_percent": None if force_cov is None else [
            _coverage(force[:, [i]], force_cov[:, [i]][:, :, [i]], true_force[:, [i]], in_contact) for i in range(3)
        ],
    }


def run_variant(
    name: str, out: Path, n_train: int, n_test: int, loss: str, log, search: str = "thorough",
    overrides: dict | None = None, truth: dict | None = None, reuse: bool = False, answer: str = SMOOTHED,
) -> dict:
    """Simulate, train and estimate one rig; `overrides` (dotted keys) change the estimator's
    configuration (the rig's guess, its friction model, ...), not the simulator's; `truth`
    (`simulator.*` or `rig.*` keys) changes the rig's truth only: the estimator keeps the variant's
    rig YAML (a user's drawing that is off). `reuse`: the bags and coefficient file of an earlier run in
    `out`, estimated again. `answer`: the smoothed estimate or the filtered (live) one."""
    told = variant(name)
    v = replace(told, overrides={**told.overrides, **(truth or {})})
    config = load_config(overrides={**dict(told.overrides), **(overrides or {})})
    config = replace(config, training=replace(config.training, loss=loss, search=search))
    coeffs_path = out / name / f"coefficients_{loss}.yaml"
    if reuse:
        bags = [out / name / bag_name(v, n) for n in range(1, n_train + n_test + 1)]
        outcome, seconds = None, None
    else:
        bags = write_variant_bags(v, out / name, n_drops=n_train + n_test, seed=0)
        started = time.perf_counter()
        outcome = train(config, bags[:n_train], coeffs_path, stream=log)
        seconds = round(time.perf_counter() - started, 1)
    loaded = load_coefficients(coeffs_path, config)
    calibrated = loaded.config(config)
    models = {
        "guess": (config, estimator_for(config, answer=answer)),
        "stage 1": (calibrated, estimator_for(calibrated, effects=loaded.effects, answer=answer)),
        "stage 1+2": (calibrated, estimator_for(calibrated, loaded.coeffs, loaded.effects, answer=answer)),
    }
    noise_rms = config.noise_rms
    figures = {
        label: [bag_figures(estimate_bag(cfg, bag, est, answer=answer), noise_rms) for bag in bags[n_train:]]
        for label, (cfg, est) in models.items()
    }
    cal = outcome.calibration if outcome else None
    return {
        "variant": name,
        "description": v.description,
        "loss": loss,
        "answer": answer,
        "overrides": overrides or {},
        "truth": truth or {},
        "train_seconds": seconds,
        "law": calibrated.law.label + ("" if calibrated.law.friction == "paper" else f"; {calibrated.law.friction}"),
        "friction_models": list(cal.frictions) if cal else [],
        "calibrated": {k: float(x) for k, x in calibrated.nominal._asdict().items()},
        "relative_standard_error": cal.relative_sd if cal else {},
        "held_by_prior": list(cal.held_by_prior) if cal else [],
        "stage1_converged": bool(cal and cal.convergence.converged),
        "stage2_converged": bool(outcome and outcome.pkbkr.convergence and outcome.pkbkr.convergence.converged),
        "mean_nis": list(outcome.mean_nis) if outcome else [],
        "held_out": [bag.name for bag in bags[n_train:]],
        "figures": figures,
    }


def _worst(rows: list[dict], key: str) -> float | None:
    values = [abs(r[key]) for r in rows if r[key] is not None]
    return max(values) if values else None


def table(results: list[dict]) -> str:
    """Markdown: per rig and model, the worst held-out bag of each figure."""
    lines = [
        "| rig | model | law | peak F_z err % | peak F_r err % | force RMSE / peak % | disp. RMSE / noise "
        "| 95 % band covers v / F % | F band covers in contact, % (both bags) |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for result in results:
        for label, rows in result["figures"].items():
            law = result["law"] if label != "guess" else "linear (guess)"
            cover_v = [r["velocity_band_coverage_percent"] for r in rows]
            cover_f = [r["force_band_coverage_percent"] for r in rows]
            coverage = f"{min(cover_v):.0f}" + (f" / {min(cover_f):.0f}" if None not in cover_f else " / -")
            in_contact = [r["force_band_coverage_in_contact_percent"] for r in rows]
            coverage += " | " + (" / ".join(f"{c:.1f}" for c in in_contact) if None not in in_contact else "-")
            lines.append(
                f"| {result['variant']} ({result['loss']}) | {label} | {law} "
                f"| {_worst(rows, 'peak_axial_error_percent'):.1f} | "
                f"{_worst(rows, 'peak_radial_error_percent'):.1f} | {_worst(rows, 'force_rmse_percent_of_peak'):.1f} | "
                f"{_worst(rows, 'displacement_rmse_over_noise'):.2f} | {coverage} |"
            )
    return "\n".join(lines) + "\n"


def anatomy_table(results: list[dict]) -> str:
    """Markdown: per rig and model, each held-out bag's peak error beside the estimate at the truth's peak
    sample and the estimate's own 1-sigma at its peak (all % of the truth's peak), axial | radial."""
    lines = [
        "| rig | model | held-out bag | F_z: peak err / at true peak / 1-sigma % "
        "| F_r: peak err / at true peak / 1-sigma % |",
        "|---|---|---|---:|---:|",
    ]

    def cell(row: dict, axis: str) -> str:
        return (f"{row[f'peak_{axis}_error_percent']:+.1f} / {row[f'{axis}_at_true_peak_error_percent']:+.1f} / "
                f"{row[f'{axis}_peak_std_percent']:.1f}")

    for result in results:
        for label, rows in result["figures"].items():
            for bag, row in zip(result["held_out"], rows):
                axial, radial = cell(row, "axial"), cell(row, "radial")
                lines.append(f"| {result['variant']} | {label} | {bag} | {axial} | {radial} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", help="rigs by name, comma-separated (default: the family, unless --drawn)")
    parser.add_argument("--drawn", type=int, default=0, metavar="N",
                        help="also rigs drawn_SEED_1..N, drawn at random from the family's ranges (sim.family)")
    parser.add_argument("--draw-seed", type=int, default=1, metavar="SEED", help="the drawn rigs' seed")
    parser.add_argument("--train", type=int, default=3, help="bags to train on per rig")
    parser.add_argument("--test", type=int, default=2, help="held-out bags per rig")
    parser.add_argument("--loss", default="nll", choices=("nll", "one_step"))
    parser.add_argument("--search", default="thorough", choices=("standard", "thorough"), help="training.search")
    parser.add_argument("--out", type=Path, default=Path("results-family"))
    parser.add_argument("--verbose", action="store_true", help="show the trainer's progress")
    parser.add_argument("-p", dest="parameters", action="append", default=[], metavar="NAME:=VALUE",
                        help="estimator parameter for every rig (e.g. contact.friction:=spinning_ring)")
    parser.add_argument("--reuse", action="store_true",
                        help="estimate the bags and coefficient file already in --out again (no simulation, training)")
    parser.add_argument("--answer", default=SMOOTHED, choices=ANSWERS,
                        help="the estimate the figures are of: smoothed (offline) or filtered (the live node's)")
    parser.add_argument("--truth", action="append", default=[], metavar="NAME:=VALUE",
                        help="the rig's truth for every rig, simulated but not told to the estimator "
                             "(e.g. simulator.ceramic.ring_inertia:=9.0e-3, rig.radial_clearance:=0.26e-3)")
    args = parser.parse_args(argv)
    overrides = parameter_overrides(args.parameters)
    truth = parameter_overrides(args.truth)
    if any(not key.startswith(("simulator.", "rig.")) for key in truth):
        parser.error("--truth takes simulator.* and rig.* names only (the estimator's settings are -p)")
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.loss + ("" if args.answer == SMOOTHED else f"_{args.answer}")
    results = []
    if args.variants:
        names = args.variants.split(",")
    else:
        names = [] if args.drawn else [v.name for v in VARIANTS]
    names += [v.name for v in drawn_variants(args.draw_seed, args.drawn)]
    for name in names:
        log = sys.stderr if args.verbose else io.StringIO()
        doing = "estimating again" if args.reuse else f"simulating, training on {args.train} bags, estimating"
        print(
            f"[{name}] {doing} {args.test} ...",
            file=sys.stderr,
            flush=True,
        )
        results.append(
            run_variant(name, args.out, args.train, args.test, args.loss, log, args.search, overrides, truth,
                        args.reuse, args.answer)
        )
        print(table(results[-1:]), file=sys.stderr, flush=True)
        (args.out / f"family_{stem}.json").write_text(json.dumps(results, indent=1))
    text = table(results) + "\n" + anatomy_table(results)
    (args.out / f"family_{stem}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
