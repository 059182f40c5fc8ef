"""The workbench on physics it was never tuned to: one hidden effect at a time on the rig family.

For each case (a hidden effect on one rig of `touchdown_ros.sim.family`), simulate two drops
with the effect in the truth, identify the rig from them (`touchdown train --steps 0`: stage 1,
the constant model the workbench starts from; the rig YAML's contact constants are only a
guess), run `touchdown diagnose --coeffs`, and read its verdict: the candidate it names (or
"unexplained"), the margin to the second, the fitted parameters against the truth, and the
held-out k-step prediction error of the baseline and with the named candidate.

    .venv/bin/python bench/workbench_family.py [--cases a,b] [--rig NAME] [--out DIR] [--fit N] [--from-guess]
        [-p NAME:=VALUE ...]

--fit N is passed to every `touchdown diagnose` call (default: diagnose's own, 10 since 2026-11-25); each call's wall
time is kept in the row ("diagnose_seconds"). --scale K makes each chosen case's hidden effect K times
as large (a sensor gain's deviation from 1): how large an effect must be for the gate to hold.
-p NAME:=VALUE overrides a rig parameter in every `touchdown` call, as the command's own -p does (e.g.
-p contact.friction:=co_rotating_ring). --simulator NAME:=VALUE changes the simulated truth of every chosen case
(a key under the rig YAML's `simulator.`, e.g. --simulator ceramic.friction_static:=0.18: no Stribeck drop on the
family's ceramic balls), to see what another physical effect does to a case; the case's name says so.
--rig NAME runs every chosen case on that rig instead of its own: another of the family, or one drawn at random
(`drawn_<seed>_<index>`, `touchdown_ros.sim.family.drawn_variant`) whose constants nobody has looked at.
Effects given with -p effects.active:=[...] (the rig's own terms, e.g. amb_release with the AMB's constants as
-p rig.amb_stiffness:=...) stay switched on beside those the rounds add.

Writes DIR/workbench.json and DIR/workbench.md (the table of docs/workbench.md) and prints it.
Then stage 1 again with the true effect switched on beside the effects the rounds added
(`-p effects.active:=[added..., effect]`), from the last diagnosed file's calibration as a user goes on after
diagnose (`touchdown train --start FILE`; each round's stage 1 too; `--from-guess`: from the rig YAML's guess, as the
bench did until 2026-12-05): its fitted parameters against the truth, and the contact
force RMSE of the smoothed estimate against the truth without and with it; when the rounds added
any, stage 1 with the true effect alone as well ("alone:" in the table), to see what the effects
added first take from it. A case passes when the verdict is right, every parameter is within
10 % of the truth (of the largest component for a vector such as a side load) and the held-out
k-step error on the axes where the effect acts or the contact force error falls to at most half;
for an effect no candidate models, when the verdict is "unexplained". The k-step error is judged
net of the sensor noise (sqrt(RMSE^2 - R) per axis, R the coefficient file's, measured on the
levitated samples: `core.selection.net_of_noise`), the model's own error; the raw RMSE is in the
table beside it.
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

import jax
import numpy as np
import yaml

from touchdown_ros.cli import main as touchdown
from touchdown_ros.cli import parameter_overrides
from touchdown_ros.io.config import load_config
from touchdown_ros.workflows.offline import force_rmse_against_truth
from touchdown_ros.sim.family import variant, variant_config, write_variant_bags
from touchdown_ros.sim.params import simulator_parameters, truth_constants
from touchdown_ros.sim.physics import Truth

DROPS = 2
MAX_ROUNDS = 3
SPEED = 5000.0 * 2.0 * math.pi / 60.0  # rad/s, the family's drop speed


class Case(NamedTuple):
    """A hidden effect on a family rig: the simulator keys that put it in the truth and the
    library effect (None: no candidate models it) with its parameters as the truth gives them."""

    name: str
    rig: str
    simulator: Mapping[str, float]
    effect: str | None
    truth: Callable[[Truth], Mapping[str, float]]
    axes: str = "xyz"  # where it acts: the k-step error is judged on these axes
    brake: bool = False
    axial_load: bool = False


CASES: tuple[Case, ...] = (
    Case("axial load", "soft_bearing", {}, "axial_load", lambda t: {"force": t.axial_load}, "z", axial_load=True),
    Case(
        "side load", "stiff_quiet", {"radial_load_x": 300.0, "radial_load_y": -200.0}, "radial_load",
        lambda t: {"force_x": t.radial_load_x, "force_y": t.radial_load_y}, "xy",
    ),
    Case(
        "magnetic negative stiffness", "kelvin_voigt_light",
        {"magnetic_stiffness_radial": 1.0e6, "magnetic_stiffness_axial": 1.0e6}, "magnetic_stiffness",
        lambda t: {"k_radial": t.magnetic_stiffness_radial, "k_axial": t.magnetic_stiffness_axial},
    ),
    Case(
        "cross-coupled stiffness", "slippery", {"cross_coupled_stiffness": 5.0e5}, "cross_coupled_stiffness",
        lambda t: {"q": t.cross_coupled_stiffness}, "xy",
    ),
    Case(
        "viscous drag", "grippy_heavy", {"rotor_drag_radial": 3000.0, "rotor_drag_axial": 3000.0}, "viscous_friction",
        lambda t: {"c_radial": t.rotor_drag_radial, "c_axial": t.rotor_drag_axial},
    ),
    Case(
        "contact angle", "linear_spring", {"contact_angle_tan": 0.2}, "contact_angle_coupling",
        lambda t: {"tan_beta": t.contact_angle_tan}, "z",
    ),
    Case("braked rotor", "roller_noisy", {}, "brake_decay", lambda t: {"rate": t.brake_deceleration / SPEED},
         "xy", brake=True),
    Case("z sensor gain", "lossy_contact", {"sensor_gain_z": 1.05}, "sensor_gain_z", lambda t: {"gain": 1.05}, "z"),
    Case("x sensor offset", "soft_bearing", {"sensor_offset_x": 3.0e-5}, "sensor_offset_x",
         lambda t: {"offset": 3.0e-5}, "x"),
    Case("no hidden effect", "soft_bearing", {}, None, lambda t: {}),
    Case("no hidden effect", "grippy_heavy", {}, None, lambda t: {}),
    Case("once-per-revolution axial thrust", "lossy_contact", {"axial_thrust": 500.0}, None, lambda t: {}),
    Case("twice-per-revolution radial force", "kelvin_voigt_light", {"twice_per_rev_force": 300.0}, None,
         lambda t: {}),
)


def scaled(case: Case, factor: float) -> Case:
    """The case with its hidden effect `factor` times as large (a sensor gain's deviation from 1);
    ValueError for a case whose effect has no simulator size (the loader, no hidden effect)."""
    if not case.simulator:
        raise ValueError(f"{case.name!r} on {case.rig} has no simulator size to scale")
    simulator = {
        k: 1.0 + factor * (v - 1.0) if k.startswith("sensor_gain_") else factor * v for k, v in case.simulator.items()
    }
    truth = case.truth
    sensor = {k.split("_")[1]: v for k, v in simulator.items() if k.startswith("sensor_")}
    if sensor:  # a sensor error is not in `Truth`: its size is the simulator's
        truth = lambda t, values=sensor: dict(values)  # noqa: E731
    return case._replace(name=f"{case.name} x{factor:g}", simulator=simulator, truth=truth)


def simulate(case: Case, out: Path, drops: int = DROPS) -> tuple[list[Path], Path, list[Truth]]:
    """The case's drops (numbered 1..drops), its rig file and each drop's truth constants."""
    base = variant(case.rig)
    rig = dataclasses.replace(
        base,
        brake=case.brake,
        axial_load=case.axial_load,
        overrides={**base.overrides, **{f"simulator.{k}": v for k, v in case.simulator.items()}},
    )
    bags = write_variant_bags(rig, out, n_drops=drops, overwrite=True)
    config = variant_config(rig)
    params = simulator_parameters(config)
    truths = []
    for number in range(1, drops + 1):
        condition = rig.condition(number)
        rng = np.random.default_rng(np.random.SeedSequence([number, number]))  # as simulate_variant with seed 0
        truths.append(truth_constants(config, params, condition.ball, condition.brake, condition.axial_load, 0.0, rng))
    return bags, out / "rig.yaml", truths


def _run(args: list[str], log: io.StringIO) -> None:
    with redirect_stdout(log), redirect_stderr(log):
        code = touchdown(args)
    if code != 0:
        raise RuntimeError(f"touchdown {' '.join(args)} exited {code}:\n{log.getvalue()[-2000:]}")


def fitted_effect(path: Path, effect: str) -> dict[str, float]:
    """The parameters of `effect` in a coefficient file."""
    document = yaml.safe_load(path.read_text())
    return {k: float(v) for k, v in document["effects"][effect]["parameters"].items()}


def force_rmse(config_path: Path, coefficients: Path, bags: list[Path], params: list[str] = ()) -> float:
    """N, contact force RMSE (norm over x, y, z) of the smoothed estimate against the truth, all bags."""
    return force_rmse_against_truth(load_config(config_path, parameter_overrides(params)), coefficients, bags)


def _relative_errors(fitted: Mapping[str, float], truth: Mapping[str, float]) -> dict[str, float]:
    """(fitted - truth) / |truth|, or over the largest |truth| for a component near zero."""
    scale = max((abs(v) for v in truth.values()), default=1.0)
    return {k: (fitted[k] - v) / (abs(v) if abs(v) > 0.1 * scale else scale) for k, v in truth.items() if k in fitted}


def _second(verdict: dict) -> str | None:
    """The best candidate other than the one the verdict names (or, unexplained, the best fitted):
    the collinearity rule may name the runner-up by criterion."""
    names = [c["candidate"] for c in verdict["candidates"]]
    first = verdict["best"] or (names[0] if names else None)
    return next((n for n in names if n != first), None)


def given_effects(params: list[str]) -> list[str]:
    """The effects a `-p effects.active:=[a,b]` among the overrides switches on (the last such override)."""
    given: list[str] = []
    for p in params:
        name, _, value = p.partition(":=")
        if name.strip() == "effects.active":
            given = [e.strip().strip("'\"") for e in value.strip().strip("[]").split(",") if e.strip()]
    return given


def run_case(
    case: Case, out: Path, fit: int | None = None, params: list[str] = (), from_guess: bool = False, drops: int = DROPS
) -> dict:
    """Stage 1 on the case's drops, diagnose (adding what it names, as a user would), stage 1 with the
    true effect switched on, from the diagnosed file's calibration (`train --start`; `from_guess`: from the rig
    YAML's guess, as before 2026-12-05); the figures of its row."""
    started = time.perf_counter()
    shutil.rmtree(out, ignore_errors=True)
    bags, rig, truths = simulate(case, out, drops)
    log = io.StringIO()
    given = given_effects(params)  # the rig's own terms (-p effects.active:=[...]), kept beside those added
    overrides = [a for p in params for a in ("-p", p)]

    def train(path: Path, effects: list[str], start: Path | None = None) -> Path:
        effects = [*given, *effects]
        active = ["-p", f"effects.active:=[{','.join(effects)}]"] if effects else []
        started = ["--start", str(start)] if start is not None and not from_guess else []
        _run(["train", *map(str, bags), "-o", str(path), "--steps", "0", "--config", str(rig), *overrides, *active,
              *started], log)
        return path

    # The workbench's loop as a user runs it: diagnose; when it names an effect, add it and
    # diagnose again, until it names the hidden one or says unexplained (at most MAX_ROUNDS).
    added: list[str] = []
    verdicts = []
    diagnose_seconds = []
    fit_option = [] if fit is None else ["--fit", str(fit)]
    calibrated = None
    for round_ in range(1, MAX_ROUNDS + 1):
        calibrated = train(out / f"calibrated_{round_}.yaml", added, start=calibrated)
        diagnosis = out / f"diagnosis_{round_}"
        diagnose_started = time.perf_counter()
        _run(["diagnose", *map(str, bags), "--config", str(rig), "--coeffs", str(calibrated), "--out",
              str(diagnosis), *fit_option, *overrides], log)
        diagnose_seconds.append(round(time.perf_counter() - diagnose_started, 1))
        verdict = json.loads((diagnosis / "diagnosis.json").read_text())["models"][0]["verdict"]
        verdicts.append(verdict)
        if not verdict["explained"] or verdict["best"] == case.effect or round_ == MAX_ROUNDS:
            break
        added.append(verdict["best"])
    truth = {k: float(np.mean([case.truth(t)[k] for t in truths])) for k in case.truth(truths[0])}
    rows = {c["candidate"]: c for c in verdict["candidates"]}
    named = rows.get(verdict["best"]) if verdict["explained"] else None
    true_row = rows.get(case.effect) if case.effect else None
    judged = true_row if true_row and true_row["fitted"] else named
    fitted = {k: v["value"] for k, v in judged["parameters"].items()} if judged is true_row and judged else {}
    axes = ["xyz".index(a) for a in case.axes]
    before = np.asarray(verdict["held_out"]["baseline_k_step_rmse_m"])
    after = np.asarray(judged["held_out_k_step_rmse_m"]) if judged else before
    k_step_ratio = float(np.linalg.norm(after[axes]) / np.linalg.norm(before[axes]))
    noise = np.asarray(verdict["held_out"]["measurement_noise_rms_m"])
    before_net = np.asarray(verdict["held_out"]["baseline_k_step_rmse_net_m"])
    after_net = np.asarray(judged["held_out_k_step_rmse_net_m"]) if judged else before_net
    k_step_net_ratio = float(np.linalg.norm(after_net[axes]) / np.linalg.norm(before_net[axes]))
    force_before = force_rmse(rig, calibrated, bags, params)
    trained, alone, force_after = {}, {}, force_before
    if case.effect:
        with_effect = train(out / "with_effect.yaml", [*added, case.effect], start=calibrated)
        trained = fitted_effect(with_effect, case.effect)
        force_after = force_rmse(rig, with_effect, bags, params)
        if added:  # what the effects added first take from it: stage 1 with the hidden effect alone
            alone_file = train(out / "with_effect_alone.yaml", [case.effect], start=out / "calibrated_1.yaml")
            alone = fitted_effect(alone_file, case.effect)
    (out / "log.txt").write_text(log.getvalue())
    errors, trained_errors = _relative_errors(fitted, truth), _relative_errors(trained, truth)
    alone_errors = _relative_errors(alone, truth)
    right = verdict["explained"] and verdict["best"] == case.effect if case.effect else not verdict["explained"]
    force_ratio = force_after / force_before
    return {
        "case": case.name,
        "rig": case.rig,
        "effect": case.effect,
        "verdict": verdict["text"],
        "added_first": added,
        "earlier_verdicts": [v["text"] for v in verdicts[:-1]],
        "best": verdict["best"],
        "explained": verdict["explained"],
        "collinear": verdict["collinear"],
        "margin_to_second": verdict["margin_to_second"],
        "second": _second(verdict),
        "truth": truth,
        "fitted": fitted,
        "relative_error": errors,
        "trained": trained,
        "trained_relative_error": trained_errors,
        "trained_alone": alone,
        "trained_alone_relative_error": alone_errors,
        "axes": case.axes,
        "k_step_before_m": before.tolist(),
        "k_step_after_m": after.tolist(),
        "k_step_ratio": k_step_ratio,
        "measurement_noise_rms_m": noise.tolist(),
        "k_step_before_net_m": before_net.tolist(),
        "k_step_after_net_m": after_net.tolist(),
        "k_step_net_ratio": k_step_net_ratio,
        "force_rmse_before_N": force_before,
        "force_rmse_after_N": force_after,
        "force_ratio": force_ratio,
        "right": bool(right),
        "sized": bool(case.effect is None or (len(errors) == len(truth) and max(map(abs, errors.values())) <= 0.1)),
        "trained_sized": bool(case.effect is None or all(abs(e) <= 0.1 for e in trained_errors.values())),
        "halved": bool(case.effect is None or (right and min(k_step_net_ratio, force_ratio) <= 0.5)),
        "fit": fit,
        "diagnose_seconds": diagnose_seconds,
        "seconds": round(time.perf_counter() - started, 1),
    }


def _values(values: Mapping[str, float]) -> str:
    return ", ".join(f"{k} {v:.4g}" for k, v in values.items()) or "-"


def table(rows: list[dict]) -> str:
    lines = [
        "| hidden effect | rig | verdict | margin to the second | diagnose fits | stage 1 with it fits | truth | "
        "held-out k-step on its axes, um: baseline -> with it | the same net of the sensor noise | "
        "contact force RMSE, N: without -> with | right / within 10 % (diagnose, train) / halved |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        axes = ["xyz".index(a) for a in r["axes"]]
        ks = "{} ({}) -> {} ({:.2f}x)".format(
            " / ".join(f"{1e6 * r['k_step_before_m'][i]:.2f}" for i in axes), r["axes"],
            " / ".join(f"{1e6 * r['k_step_after_m'][i]:.2f}" for i in axes), r["k_step_ratio"],
        )
        net = "{} -> {} ({:.2f}x)".format(
            " / ".join(f"{1e6 * r['k_step_before_net_m'][i]:.2f}" for i in axes),
            " / ".join(f"{1e6 * r['k_step_after_net_m'][i]:.2f}" for i in axes), r["k_step_net_ratio"],
        )
        force = f"{r['force_rmse_before_N']:.0f} -> {r['force_rmse_after_N']:.0f} ({r['force_ratio']:.2f}x)"
        marks = " / ".join("yes" if r[k] else "NO" for k in ("right", "sized", "trained_sized", "halved"))
        margin = r["margin_to_second"]
        lines.append(
            f"| {r['case']} | {r['rig']} | {_added(r)}{r['verdict'].split(';')[0].split(' (')[0]} | "
            f"{'-' if margin is None else f'{margin:.1f}'} ({r['second']}) | "
            f"{_fits(r['fitted'], r['relative_error'])} | "
            f"{_fits(r['trained'], r['trained_relative_error'])}{_alone(r)} | {_values(r['truth'])} | {ks} | "
            f"{net} | {force} | {marks} |"
        )
    return "\n".join(lines)


def _added(row: dict) -> str:
    """The effects named and added in earlier rounds, if any."""
    added = row.get("added_first", [])
    return f"after adding {', '.join(added)}: " if added else ""


def _alone(row: dict) -> str:
    """Stage 1's fit with the hidden effect alone, when earlier rounds had added others."""
    alone = row["trained_alone"]
    return f"; alone: {_fits(alone, row['trained_alone_relative_error'])}" if alone else ""


def _fits(values: Mapping[str, float], errors: Mapping[str, float]) -> str:
    return ", ".join(f"{k} {v:.4g} ({100 * errors[k]:+.0f} %)" for k, v in values.items() if k in errors) or "-"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default="", help="comma-separated case or rig names (default: all)")
    parser.add_argument("--out", type=Path, default=Path("results-workbench"))
    parser.add_argument(
        "--fit", type=int, default=None,
        help="passed to every `touchdown diagnose` call: fit FROLS's best N candidates (default: diagnose's own)",
    )
    parser.add_argument("--from-guess", action="store_true",
                        help="train each effect from the rig YAML's guess, not from the diagnosed file (`--start`)")
    parser.add_argument("--scale", type=float, default=None, help="each chosen hidden effect this many times as large")
    parser.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="a rig parameter override passed to every touchdown call")
    parser.add_argument("--simulator", action="append", default=[], metavar="NAME:=VALUE",
                        help="a change of every chosen case's simulated truth (a key under simulator.)")
    parser.add_argument("--drops", type=int, default=DROPS, help=f"drops per case (default {DROPS})")
    parser.add_argument("--rig", help="run every chosen case on this rig instead of its own (a family name or a "
                                      "rig drawn at random, drawn_<seed>_<index>)")
    args = parser.parse_args(argv)
    if args.drops < 1:
        parser.error(f"--drops: {args.drops}: at least one drop")
    chosen = [c for c in CASES if not args.cases or c.name in args.cases.split(",") or c.rig in args.cases.split(",")]
    if not chosen:
        parser.error(f"no such case; choose from {', '.join(c.name for c in CASES)}")
    if args.rig:
        try:
            variant(args.rig)
        except ValueError as error:
            parser.error(f"--rig: {error}")
        chosen = list({c.name: c._replace(rig=args.rig) for c in chosen}.values())  # one per name ("no hidden effect")
    if args.scale is not None:
        try:
            chosen = [scaled(c, args.scale) for c in chosen]
        except ValueError as error:
            parser.error(f"--scale: {error}")
    if args.simulator:
        try:
            truth = {k.removeprefix("simulator."): v for k, v in parameter_overrides(args.simulator).items()}
        except ValueError as error:
            parser.error(f"--simulator: {error}")
        said = ", ".join(f"{k} {v}" for k, v in truth.items())
        chosen = [c._replace(name=f"{c.name} ({said})", simulator={**c.simulator, **truth}) for c in chosen]
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in chosen:
        row = run_case(case, args.out / f"{case.name.replace(' ', '_')}_{case.rig}", args.fit, args.param,
                       args.from_guess, args.drops)
        rows.append(row)
        # Each case compiles its own rig's programs; kept, they grew this process by about 1.4 GB a case
        # (11 GB after eight cases, 2026-12-02). The persistent compilation cache stays on disk.
        jax.clear_caches()
        seconds = f"{row['seconds']} s, diagnose {row['diagnose_seconds']} s"
        print(f"{case.name} on {case.rig}: {row['verdict'][:120]} ({seconds})", file=sys.stderr, flush=True)
        (args.out / "workbench.json").write_text(json.dumps(rows, indent=1))
    text = table(rows)
    (args.out / "workbench.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
