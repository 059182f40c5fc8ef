"""The `touchdown` command: simulate, estimate, train, evaluate, demo (and replay)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import yaml

from touchdown_ros import __version__
from touchdown_ros.core import xla
from touchdown_ros.io.bags import BagError
from touchdown_ros.io.coefficients import CoefficientFileError
from touchdown_ros.io.config import Config, ConfigError, load_config
from touchdown_ros.sim.family import RIG_FILE, variant, variant_names
from touchdown_ros.workflows.outputs import OutputError

EXIT_USAGE = 2  # wrong command line (argparse)
EXIT_BAD_INPUT = 3  # a bag, rig YAML, coefficient file or argument is refused (docs/input_policy.md)
EXIT_OUTPUT = 5  # the output cannot be written (read-only, disk full, a file where a directory goes)


def _add_config(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", type=Path, default=None, help="rig YAML in ROS 2 parameter-file form (default: the reference rig)"
    )
    parser.add_argument(
        "-p",
        "--param",
        action="append",
        default=[],
        metavar="NAME:=VALUE",
        help="override one rig parameter, ROS style (value in YAML), e.g. -p 'effects.active:=[axial_load]'",
    )


def _parameter(text: str) -> tuple[str, object]:
    name, separator, value = text.partition(":=")
    if not separator or not name:
        raise ConfigError(f"-p {text!r}: expected NAME:=VALUE, e.g. -p training.regularisation:=1.0e-3")
    try:
        return name.strip(), yaml.safe_load(value)
    except yaml.YAMLError as error:
        raise ConfigError(f"-p {text!r}: the value is not valid YAML: {error}") from None


def _config(args: argparse.Namespace) -> Config:
    """The rig of --config with the -p overrides."""
    return load_config(args.config, parameter_overrides(args.param))


def parameter_overrides(parameters: Sequence[str]) -> dict[str, object]:
    """-p NAME:=VALUE options as the overrides of `load_config` (a later one of a name wins)."""
    return dict(_parameter(p) for p in parameters)


def _commands():
    """The workflows, imported when a command runs (matplotlib, scipy and the workflows add about 2 s
    to the start that --help does not need)."""
    from touchdown_ros.workflows import commands  # lazy: start-up time of the CLI

    return commands


def cmd_simulate(args: argparse.Namespace) -> int:
    if args.variant:
        v = variant(args.variant)
        if args.campaign:
            raise ValueError(
                "--campaign is Table 1 of the reference rig; with --variant pick drops with --experiment N..."
            )
        if args.config is not None or args.param:
            raise ValueError(
                "--variant brings its own rig (the reference rig with its overrides); drop --config and -p"
            )
        paths = _commands().simulate_variant(v, args.out, args.experiment, args.seed, args.overwrite)
        print(f"wrote {len(paths)} bag(s) of rig variant {v.name} ({v.description}) and its {RIG_FILE} to {args.out}")
        return 0
    if not args.campaign and not args.experiment:
        raise ValueError("pass --campaign, --experiment N... or --variant NAME")
    numbers = None if args.campaign else args.experiment
    _simulated(_commands().simulate_campaign(_config(args), args.out, numbers, args.seed, args.overwrite), args.out)
    return 0


def _simulated(paths: Sequence[Path], out: Path) -> None:
    print(f"wrote {len(paths)} bag(s) to {out}")


def cmd_estimate(args: argparse.Namespace) -> int:
    _commands().estimate_bags(
        _config(args), args.bags, args.out, args.coeffs, args.filtered, not args.no_figures, args.overwrite
    )
    _estimated(args.out)
    return 0


def _estimated(out: Path) -> None:
    print((out / "summary.md").read_text(), end="")
    print(f"estimates, summary.json/.md and figures in {out}")


def cmd_train(args: argparse.Namespace) -> int:
    outcome = _commands().train_bags(
        _config(args),
        args.bags,
        args.out,
        regularisation=args.regularisation,
        init=args.init,
        resume=args.resume,
        start=args.start,
        steps=args.steps,
        duration=args.duration,
        overwrite=args.overwrite,
    )
    _trained(outcome, len(args.bags), args.out)
    return 0


def _trained(outcome, bags: int, out: Path, report_hint: bool = True) -> None:
    """What both training stages did, in a few lines."""
    calibration, pkbkr = outcome.calibration, outcome.pkbkr
    if calibration is not None:
        nominal, law = outcome.config.nominal, outcome.config.law
        friction = f", friction {law.friction}" if law.friction != "paper" or calibration.frictions else ""
        if "friction_drop" in calibration.relative_sd:
            sd = calibration.relative_sd
            friction += (f" with a Stribeck drop {float(law.friction_drop):.3g} (+-{100 * sd['friction_drop']:.0f} %) "
                         f"over {float(law.stribeck_velocity):.3g} m/s (+-{100 * sd['stribeck_velocity']:.0f} %)")
        print(
            f"stage 1 ({'converged' if calibration.convergence.converged else 'NOT converged'}, "
            f"{calibration.convergence.steps} steps): {law.label}{friction}, "
            + ", ".join(
                f"{k} {v:.4g} (+-{100 * calibration.relative_sd[k]:.0f} %)" for k, v in nominal._asdict().items()
            )
            + (f"; held by the prior: {', '.join(calibration.held_by_prior)}" if calibration.held_by_prior else "")
        )
        changes = calibration.clearance_changes()
        if changes:
            rig = outcome.config.contact_rig
            print("clearances (the rig YAML's + the fitted change): " + ", ".join(
                f"{name} {getattr(rig, name) * 1e6:.1f} um ({change * 1e6:+.1f}, "
                f"+-{calibration.clearance_sd.get(name, float('nan')) * 1e6:.1f} um)"
                for name, change in changes.items()
            ))
        for note in calibration.notes():
            print(note)
    converged = pkbkr.convergence is not None and pkbkr.convergence.converged
    kept = pkbkr.convergence.kept_step if pkbkr.convergence is not None else None
    kept_note = ""
    if kept is not None:
        kept_note = (
            f", kept step {kept} by the held-out error" if kept
            else ", no step lowered the held-out error: PKBKR alpha = 0 kept"
        )
    print(
        f"stage 2 ({'converged' if converged else 'NOT converged'}, {pkbkr.steps} steps{kept_note}): loss "
        f"{pkbkr.initial_loss:.6g} -> {pkbkr.final_loss:.6g}; mean NIS per bag "
        f"{min(outcome.mean_nis):.2f}-{max(outcome.mean_nis):.2f} (3 when consistent)"
    )
    print(f"trained on {bags} bag(s) in {outcome.seconds:.1f} s; wrote {out}")
    if report_hint:
        print(f"tables and figures of what it found: touchdown report {out} -o DIR")


def cmd_evaluate(args: argparse.Namespace) -> int:
    _commands().evaluate_bags(
        _config(args), args.bags, args.coeffs, args.out, not args.no_cv, args.cv_steps, args.example
    )
    _evaluated(args.out)
    return 0


def _evaluated(out: Path) -> None:
    print((out / "evaluation.md").read_text(), end="")
    print(f"tables, evaluation.json and figures in {out}")


def cmd_report(args: argparse.Namespace) -> int:
    _commands().report_training(_config(args), args.coeffs, args.out)
    print((args.out / "training.md").read_text(), end="")
    print(f"training.md and figures in {args.out}")
    return 0


def cmd_diagnose(args: argparse.Namespace) -> int:
    commands = _commands()
    config = _config(args)
    if args.k < 1 or args.force_walk <= 0 or not 0 < args.threshold < 100 or args.fit < 0:
        raise ValueError("--k must be >= 1, --force-walk > 0, --threshold in (0, 100) and --fit >= 0")
    settings = commands.DiagnoseSettings(
        k=args.k, force_walk=args.force_walk, threshold=args.threshold / 100.0, fitted=args.fit
    )
    commands.diagnose_bags(config, args.bags, args.out, args.coeffs, args.compare, settings)
    print((args.out / "diagnosis.md").read_text(), end="")
    print(f"diagnosis.md/.json, errors.csv, ranking.csv and figures in {args.out}")
    return 0


#: What `touchdown demo` trains beside PKBKR: Table 1's axial loader and brake are recorded test conditions, so
#: each is fitted where it was on (docs/workbench.md shows how the workbench finds the loader as a missing effect).
DEMO_EFFECTS = {
    "effects.active": ["axial_load", "brake_decay"],
    "effects.when.axial_load": "axial_load",
    "effects.when.brake_decay": "brake",
}


def demo_training_config(path: Path | None, overrides: dict, paper_model: bool = False) -> Config:
    """The rig `touchdown demo` trains: `DEMO_EFFECTS` switched on, unless the user's `-p` sets any `effects.*`:
    then the user's effects alone. `paper_model`: the paper's model, its friction (the inner ring at rest) and
    no effects but the user's; a `-p contact.friction` of the user's wins."""
    if paper_model:
        return load_config(path, {"contact.friction": "paper", **overrides})
    chosen = any(name.startswith("effects.") for name in overrides)
    return load_config(path, overrides if chosen else {**DEMO_EFFECTS, **overrides})


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate the 21-experiment campaign, train PKBKR, evaluate it leave-one-out, estimate exp 11."""
    commands = _commands()
    out: Path = args.out
    bags = out / "bags"
    overrides = parameter_overrides(args.param)
    config = load_config(args.config, overrides)
    _simulated(commands.simulate_campaign(config, bags, [11] if args.quick else None, args.seed, overwrite=True), bags)
    all_bags = sorted(bags.glob("exp_*"))
    coeffs = None
    if not args.quick:
        trained = demo_training_config(args.config, overrides, args.paper_model)
        coeffs = out / "coefficients.yaml"
        _trained(
            commands.train_bags(trained, all_bags, coeffs, steps=args.steps, overwrite=True), len(all_bags), coeffs,
            report_hint=False,
        )
        commands.report_training(trained, coeffs, out / "training")
        print(f"what training found: {out / 'training' / 'training.md'} and its figures")
        commands.evaluate_bags(trained, all_bags, coeffs, out / "evaluation", cv_steps=args.cv_steps, example="exp_11")
        _evaluated(out / "evaluation")
    commands.estimate_bags(config, [bags / "exp_11"], out / "estimate", coeffs, overwrite=True)
    _estimated(out / "estimate")
    report = "" if args.quick else f"evaluation report in {out / 'evaluation'}, "
    print(f"demo done: {report}figures of exp_11 in {out / 'estimate' / 'figures' / 'exp_11'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="touchdown",
        description="AMB rotor touchdown: simulate drop tests, estimate velocity, acceleration, force.",
    )
    parser.add_argument("--version", action="version", version=f"touchdown_ros {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate drop tests into rosbag2 MCAP bags (with truth topics)")
    _add_config(p)
    which = p.add_mutually_exclusive_group()
    which.add_argument("--campaign", action="store_true", help="all 21 experiments of the paper's Table 1")
    which.add_argument(
        "--experiment", type=int, nargs="+", metavar="N",
        help="experiment number(s) of Table 1, or with --variant of the variant's drops (1, 2, ...)",
    )
    p.add_argument(
        "--variant",
        metavar="NAME",
        help="a rig of the family that differs from the reference rig (touchdown_ros.sim.family): "
        "bags NAME_NN (default: its 3 drops) and the variant's rig.yaml in --out; one of: "
        + ", ".join(variant_names()),
    )
    p.add_argument("--seed", type=int, default=0, help="base random seed (experiment N uses seed + N)")
    p.add_argument("-o", "--out", type=Path, required=True, help="directory for the bags exp_NN/ (or NAME_NN/)")
    p.add_argument("--overwrite", action="store_true", help="replace existing bags")
    p.set_defaults(run=cmd_simulate)

    p = sub.add_parser("estimate", help="estimate velocity, acceleration and contact force of recorded drops")
    _add_config(p)
    p.add_argument("bags", type=Path, nargs="+", metavar="BAG", help="rosbag2 directory or .mcap file")
    p.add_argument("--coeffs", type=Path, help="trained PKBKR coefficient file (default: the constant model)")
    p.add_argument("-o", "--out", type=Path, required=True, help="output directory")
    p.add_argument("--overwrite", action="store_true", help="replace existing output bags")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument(
        "--filtered", action="store_true",
        help="write and summarise the EKF's estimate (what the live node publishes: each sample from the samples "
        "up to it) instead of the RTS smoother's (each sample from the whole record, the default)",
    )
    p.set_defaults(run=cmd_estimate)

    p = sub.add_parser("train", help="fit PKBKR coefficients (eq. 18) over drop-test bags")
    _add_config(p)
    p.add_argument("bags", type=Path, nargs="+", metavar="BAG", help="rosbag2 directory or .mcap file")
    p.add_argument("-o", "--out", type=Path, required=True, help="coefficient file to write (YAML)")
    p.add_argument(
        "--lambda", dest="regularisation", type=float, help="eq. 18 lambda (default: training.regularisation)"
    )
    p.add_argument("--init", type=Path, help="warm-start from this coefficient file")
    p.add_argument(
        "--start", type=Path, metavar="COEFFS",
        help="run stage 1 from this coefficient file's calibration (its contact law, constants, friction and Q), "
        "with the rig's active effects fitted beside them (those the file did not fit also alone first; both starts "
        "refined, the lower kept): after `touchdown diagnose --coeffs COEFFS` named one",
    )
    p.add_argument("--resume", action="store_true", help="continue from OUT.checkpoint of an interrupted run")
    p.add_argument(
        "--steps", type=int, default=None,
        help="cap on stage-2 (PKBKR) L-BFGS iterations; it stops at convergence first (default training.pkbkr_steps)",
    )
    p.add_argument("--duration", type=float, help="use only this many seconds after each drop")
    p.add_argument("--overwrite", action="store_true", help="replace an existing coefficient file")
    p.set_defaults(run=cmd_train)

    p = sub.add_parser("evaluate", help="constant baseline vs PKBKR per bag, leave-one-experiment-out")
    _add_config(p)
    p.add_argument("bags", type=Path, nargs="+", metavar="BAG")
    p.add_argument("--coeffs", type=Path, required=True, help="coefficients trained on all the bags")
    p.add_argument("-o", "--out", type=Path, required=True, help="output directory for tables and figures")
    p.add_argument("--no-cv", action="store_true", help="use --coeffs on every bag (in-sample, not cross-validated)")
    p.add_argument("--cv-steps", type=int, default=12, help="L-BFGS steps per held-out fold (warm-started)")
    p.add_argument("--example", default="exp_11", help="bag shown in the time-series figures (default exp_11)")
    p.set_defaults(run=cmd_evaluate)

    p = sub.add_parser("report", help="what training found, from a coefficient file: training.md and figures")
    _add_config(p)
    p.add_argument("coeffs", type=Path, metavar="COEFFS", help="coefficient file written by touchdown train")
    p.add_argument("-o", "--out", type=Path, required=True, help="output directory for training.md and figures")
    p.set_defaults(run=cmd_report)

    p = sub.add_parser(
        "diagnose", help="where the model fails, the force it lacks and which candidate effect explains it"
    )
    _add_config(p)
    p.add_argument("bags", type=Path, nargs="+", metavar="BAG", help="rosbag2 directory or .mcap file")
    p.add_argument("--coeffs", type=Path, help="coefficient file to diagnose (default: the rig's constant model)")
    p.add_argument("--compare", type=Path, help="a second coefficient file (after), shown side by side with --coeffs")
    p.add_argument("--out", "-o", type=Path, required=True, help="output directory for tables and figures")
    p.add_argument("--k", type=int, default=20, help="samples ahead of the k-step prediction (default 20 = 2 ms)")
    p.add_argument(
        "--force-walk",
        type=float,
        default=30.0,
        help="random walk of the missing-force states, N per sample (default 30)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=50.0,
        help="ERR %% below which the missing force is 'unexplained' (default 50)",
    )
    p.add_argument(
        "--fit", type=int, default=10,
        help="fit FROLS's best N candidates with the model's constants and judge them on held-out samples "
        "(default 10; 0: the FROLS ranking alone decides)",
    )
    p.set_defaults(run=cmd_diagnose)

    # measured on the 2-core machine: --quick 10.5 s (2026-11-24); the demo 11 min 48 s, its training 359 s (2026-12-04)
    demo_text = (
        "simulate the campaign, train, evaluate leave-one-out, estimate exp 11 (about 12 min on 2 cores, "
        "training about 6 min of it; --quick: about 10 s)"
    )
    p = sub.add_parser("demo", help=demo_text, description=demo_text[0].upper() + demo_text[1:] + ".")
    _add_config(p)
    p.add_argument("--out", type=Path, default=Path("results"), help="output directory (default: results)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--steps", type=int, default=None, help="cap on stage-2 training steps (default training.pkbkr_steps)"
    )
    p.add_argument("--cv-steps", type=int, default=12, help="L-BFGS steps per leave-one-out fold")
    p.add_argument("--quick", action="store_true", help="only simulate and estimate experiment 11 (constant model)")
    p.add_argument(
        "--paper-model",
        action="store_true",
        help="train the paper's model alone: its friction (the inner ring at rest, eq. 6b, 6c, 8b; unless -p "
        "contact.friction:=...) without the Table 1 axial-load and brake effects",
    )
    p.set_defaults(run=cmd_demo)

    # `touchdown replay` needs rclpy; it has its own parser (touchdown_ros.ros.replay), reached in main.
    sub.add_parser("replay", add_help=False, help="publish a bag's displacements over ROS 2 (live node tests, demos)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["replay"]:
        from touchdown_ros.ros.replay import replay_main  # lazy: rclpy, needed by replay alone

        return replay_main(argv[1:])
    args = build_parser().parse_args(argv)
    xla.use_compilation_cache()
    try:
        return args.run(args)
    except (ConfigError, BagError, CoefficientFileError, FileExistsError, FileNotFoundError, ValueError) as error:
        print(f"touchdown {args.command}: error: {_one_line(error)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ArithmeticError as error:  # a filter that diverged on data the checks let through
        print(f"touchdown {args.command}: error: numerical failure ({type(error).__name__}: {_one_line(error)}); "
              "check the bags with touchdown estimate first", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as error:  # writing the output: read-only, disk full, a file where a directory goes
        where = f"{error.filename}: " if getattr(error, "filename", None) and not isinstance(error, OutputError) else ""
        text = error.strerror if where and error.strerror else str(error)
        print(f"touchdown {args.command}: error: {where}{_one_line(text)}", file=sys.stderr)
        return EXIT_OUTPUT


def _one_line(error: object) -> str:
    """An error as one line (YAML and rosbags messages can span several)."""
    return " ".join(str(error).split())


if __name__ == "__main__":
    sys.exit(main())
