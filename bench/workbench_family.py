"""The workbench on physics it was never tuned to: one hidden effect at a time on the rig family.

For each case (a hidden effect on one rig of `touchdown_ros.sim.family`), simulate two drops
with the effect in the truth, identify the rig from them (`touchdown train --steps 0`: stage 1,
the constant model the workbench starts from; the rig YAML's contact constants are only a
guess), run `touchdown diagnose --coeffs`, and read its verdict: the candidate it names (or
"unexplained"), the margin to the second, the fitted parameters against the truth, and the
held-out k-step prediction error of the baseline and with the named candidate.

    .venv/bin/python bench/workbench_family.py [--cases a,b] [--out DIR]

Writes DIR/workbench.json and DIR/workbench.md (the table of docs/workbench.md) and prints it.
A case passes when the verdict is right, every parameter is within 10 % of the truth (10 % of
the largest component for a vector such as a side load) and the held-out k-step error falls to
at most half; for an effect no candidate models, when the verdict is "unexplained".
"""
from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import shutil
import sys
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Callable, Mapping, NamedTuple

import numpy as np

from touchdown_ros.cli import main as touchdown
from touchdown_ros.sim.family import variant, variant_config, write_variant_bags
from touchdown_ros.sim.params import simulator_parameters, truth_constants
from touchdown_ros.sim.physics import Truth

DROPS = 2
SPEED = 5000.0 * 2.0 * math.pi / 60.0  # rad/s, the family's drop speed


class Case(NamedTuple):
    """A hidden effect on a family rig: the simulator keys that put it in the truth and the
    library effect (None: no candidate models it) with its parameters as the truth gives them."""

    name: str
    rig: str
    simulator: Mapping[str, float]
    effect: str | None
    truth: Callable[[Truth], Mapping[str, float]]
    brake: bool = False
    axial_load: bool = False


CASES: tuple[Case, ...] = (
    Case("axial load", "soft_bearing", {}, "axial_load", lambda t: {"force": t.axial_load}, axial_load=True),
    Case(
        "side load", "stiff_quiet", {"radial_load_x": 300.0, "radial_load_y": -200.0}, "radial_load",
        lambda t: {"force_x": t.radial_load_x, "force_y": t.radial_load_y},
    ),
    Case(
        "magnetic negative stiffness", "kelvin_voigt_light",
        {"magnetic_stiffness_radial": 1.0e6, "magnetic_stiffness_axial": 1.0e6}, "magnetic_stiffness",
        lambda t: {"k_radial": t.magnetic_stiffness_radial, "k_axial": t.magnetic_stiffness_axial},
    ),
    Case(
        "cross-coupled stiffness", "slippery", {"cross_coupled_stiffness": 5.0e5}, "cross_coupled_stiffness",
        lambda t: {"q": t.cross_coupled_stiffness},
    ),
    Case(
        "viscous drag", "grippy_heavy", {"rotor_drag_radial": 3000.0, "rotor_drag_axial": 3000.0}, "viscous_friction",
        lambda t: {"c_radial": t.rotor_drag_radial, "c_axial": t.rotor_drag_axial},
    ),
    Case(
        "contact angle", "linear_spring", {"contact_angle_tan": 0.2}, "contact_angle_coupling",
        lambda t: {"tan_beta": t.contact_angle_tan, "k_radial": t.radial_stiffness},
    ),
    Case("braked rotor", "roller_noisy", {}, "brake_decay", lambda t: {"rate": t.brake_deceleration / SPEED},
         brake=True),
    Case("z sensor gain", "lossy_contact", {"sensor_gain_z": 1.05}, "sensor_gain_z", lambda t: {"gain": 1.05}),
    Case("x sensor offset", "soft_bearing", {"sensor_offset_x": 3.0e-5}, "sensor_offset_x",
         lambda t: {"offset": 3.0e-5}),
    Case("once-per-revolution axial thrust", "lossy_contact", {"axial_thrust": 500.0}, None, lambda t: {}),
    Case("twice-per-revolution radial force", "kelvin_voigt_light", {"twice_per_rev_force": 300.0}, None,
         lambda t: {}),
)


def simulate(case: Case, out: Path) -> tuple[list[Path], Path, list[Truth]]:
    """The case's drops, its rig file and each drop's truth constants."""
    base = variant(case.rig)
    rig = dataclasses.replace(
        base,
        brake=case.brake,
        axial_load=case.axial_load,
        overrides={**base.overrides, **{f"simulator.{k}": v for k, v in case.simulator.items()}},
    )
    bags = write_variant_bags(rig, out, n_drops=DROPS, overwrite=True)
    config = variant_config(rig)
    params = simulator_parameters(config)
    truths = []
    for number in range(1, DROPS + 1):
        condition = rig.condition(number)
        rng = np.random.default_rng(np.random.SeedSequence([number, number]))  # as simulate_variant with seed 0
        truths.append(truth_constants(config, params, condition.ball, condition.brake, condition.axial_load, 0.0, rng))
    return bags, out / "rig.yaml", truths


def _run(args: list[str], log: io.StringIO) -> None:
    with redirect_stdout(log), redirect_stderr(log):
        code = touchdown(args)
    if code != 0:
        raise RuntimeError(f"touchdown {' '.join(args)} exited {code}:\n{log.getvalue()[-2000:]}")


def run_case(case: Case, out: Path) -> dict:
    """Stage 1 on the case's drops, then diagnose; the figures of its row."""
    started = time.perf_counter()
    shutil.rmtree(out, ignore_errors=True)
    bags, rig, truths = simulate(case, out)
    log = io.StringIO()
    calibrated = out / "calibrated.yaml"
    _run(["train", *map(str, bags), "-o", str(calibrated), "--overwrite", "--steps", "0", "--config", str(rig)], log)
    diagnosis = out / "diagnosis"
    _run(["diagnose", *map(str, bags), "--config", str(rig), "--coeffs", str(calibrated), "--out", str(diagnosis)], log)
    (out / "log.txt").write_text(log.getvalue())
    verdict = json.loads((diagnosis / "diagnosis.json").read_text())["models"][0]["verdict"]
    truth = {k: float(np.mean([case.truth(t)[k] for t in truths])) for k in case.truth(truths[0])}
    rows = {c["candidate"]: c for c in verdict["candidates"]}
    named = rows.get(verdict["best"]) if verdict["explained"] else None
    true_row = rows.get(case.effect) if case.effect else None
    fitted = {k: v["value"] for k, v in true_row["parameters"].items()} if true_row and true_row["fitted"] else {}
    scale = max((abs(v) for v in truth.values()), default=1.0)
    errors = {k: (fitted[k] - v) / (abs(v) if abs(v) > 0.1 * scale else scale) for k, v in truth.items() if k in fitted}
    before = np.asarray(verdict["held_out"]["baseline_k_step_rmse_m"])
    after = np.asarray(named["held_out_k_step_rmse_m"]) if named else before
    ratio = float(np.linalg.norm(after) / np.linalg.norm(before))
    right = verdict["best"] == case.effect if case.effect else not verdict["explained"]
    sized = bool(case.effect is None or (len(errors) == len(truth) and all(abs(e) <= 0.1 for e in errors.values())))
    halved = bool(case.effect is None or (right and ratio <= 0.5))
    return {
        "case": case.name,
        "rig": case.rig,
        "effect": case.effect,
        "verdict": verdict["text"],
        "best": verdict["best"],
        "explained": verdict["explained"],
        "collinear": verdict["collinear"],
        "margin_to_second": verdict["margin_to_second"],
        "second": next((c["candidate"] for c in verdict["candidates"][1:2]), None),
        "truth": truth,
        "fitted": fitted,
        "relative_error": errors,
        "k_step_before_m": before.tolist(),
        "k_step_after_m": after.tolist(),
        "k_step_ratio": ratio,
        "right": bool(right),
        "sized": sized,
        "halved": halved,
        "seconds": round(time.perf_counter() - started, 1),
    }


def _values(values: Mapping[str, float]) -> str:
    return ", ".join(f"{k} {v:.4g}" for k, v in values.items()) or "-"


def table(rows: list[dict]) -> str:
    lines = [
        "| hidden effect | rig | verdict | margin to the second | fitted | truth | error % | held-out k-step x / y / z,"
        " um: baseline -> with it | ratio | right / within 10 % / halved |",
        "|---|---|---|---|---|---|---|---|---:|---|",
    ]
    for r in rows:
        errors = ", ".join(f"{100 * e:+.0f}" for e in r["relative_error"].values()) or "-"
        ks = " / ".join(f"{1e6 * v:.2f}" for v in r["k_step_before_m"]) + " -> " + " / ".join(
            f"{1e6 * v:.2f}" for v in r["k_step_after_m"]
        )
        marks = " / ".join("yes" if r[k] else "NO" for k in ("right", "sized", "halved"))
        margin = r["margin_to_second"]
        lines.append(
            f"| {r['case']} | {r['rig']} | {r['verdict'].split(';')[0][:90]} | "
            f"{'-' if margin is None else f'{margin:.1f}'} ({r['second']}) | {_values(r['fitted'])} | "
            f"{_values(r['truth'])} | {errors} | {ks} | {r['k_step_ratio']:.2f} | {marks} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    parser.add_argument("--out", type=Path, default=Path("results-workbench"))
    args = parser.parse_args(argv)
    chosen = [c for c in CASES if not args.cases or c.name in args.cases.split(",")]
    if not chosen:
        parser.error(f"no such case; choose from {', '.join(c.name for c in CASES)}")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in chosen:
        row = run_case(case, args.out / case.name.replace(" ", "_"))
        rows.append(row)
        print(f"{case.name} on {case.rig}: {row['verdict'][:120]} ({row['seconds']} s)", file=sys.stderr, flush=True)
        (args.out / "workbench.json").write_text(json.dumps(rows, indent=1))
    text = table(rows)
    (args.out / "workbench.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
