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
from touchdown_ros.io.config import ConfigError, load_config
from touchdown_ros.workflows.outputs import OutputError, OutputGuard, check_writable
from touchdown_ros.workflows.progress import progress

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


def _config(args: argparse.Namespace):
    """The rig of --config with the -p overrides."""
    return load_config(args.config, dict(_parameter(p) for p in getattr(args, "param", [])))


def _refuse_existing(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass --overwrite to replace it")


def cmd_simulate(args: argparse.Namespace) -> int:
    from touchdown_ros.workflows.offline import write_drop_bag
    from touchdown_ros.sim.campaign import CAMPAIGN
    from touchdown_ros.sim.simulator import simulate_drop

    if getattr(args, "variant", None):
        return _simulate_variant(args)
    if not args.campaign and not args.experiment:
        raise ValueError("pass --campaign, --experiment N... or --variant NAME")
    config = _config(args)
    numbers = [c.number for c in CAMPAIGN] if args.campaign else args.experiment
    conditions = [c for c in CAMPAIGN if c.number in numbers]
    missing = sorted(set(numbers) - {c.number for c in conditions})
    if missing:
        raise ValueError(f"no experiment numbered {missing} in the campaign (1-{len(CAMPAIGN)})")
    args.out.mkdir(parents=True, exist_ok=True)
    targets = [args.out / f"exp_{c.number:02d}" for c in conditions]
    for target in targets:
        _refuse_existing(target, args.overwrite)
    for condition, target in progress(zip(conditions, targets), len(conditions), "simulate"):
        record = simulate_drop(config, condition, seed=args.seed + condition.number)
        write_drop_bag(record, config, target, overwrite=args.overwrite)
    print(f"wrote {len(targets)} bag(s) to {args.out}")
    return 0


def _simulate_variant(args: argparse.Namespace) -> int:
    """`simulate --variant NAME`: the variant's drops as bags NAME_NN, its rig.yaml next to them."""
    from touchdown_ros.sim.family import RIG_FILE, bag_name, variant, write_variant_bags

    v = variant(args.variant)
    if args.campaign:
        raise ValueError("--campaign is Table 1 of the reference rig; with --variant pick drops with --experiment N...")
    if args.config is not None or args.param:
        raise ValueError("--variant brings its own rig (the reference rig with its overrides); drop --config and -p")
    numbers = sorted(set(args.experiment or range(1, v.drops + 1)))
    if numbers[0] < 1:
        raise ValueError(f"experiment numbers of a variant start at 1, got {numbers[0]}")
    for number in numbers:
        _refuse_existing(args.out / bag_name(v, number), args.overwrite)
    paths = []
    for number in progress(numbers, len(numbers), f"simulate {v.name}"):
        paths += write_variant_bags(v, args.out, seed=args.seed, numbers=[number], overwrite=args.overwrite)
    print(f"wrote {len(paths)} bag(s) of rig variant {v.name} ({v.description}) and its {RIG_FILE} to {args.out}")
    return 0


def cmd_estimate(args: argparse.Namespace) -> int:
    from touchdown_ros.workflows.offline import FILTERED, SMOOTHED, check_bag, estimate_bag, estimator_for, write_estimate_bag
    from touchdown_ros.workflows.report.estimate import plot_estimate, write_summaries

    config = _config(args)
    coeffs = effects = None
    if args.coeffs is not None:
        from touchdown_ros.io.coefficients import load_coefficients

        loaded = load_coefficients(args.coeffs, config)
        coeffs, effects, config = loaded.coeffs, loaded.effects, loaded.config(config)
    check_writable(args.out, directory=True)
    targets = [args.out / f"{Path(bag).name.removesuffix('.mcap')}_estimate" for bag in args.bags]
    for target in targets:
        _refuse_existing(target, args.overwrite)
    for bag in args.bags:  # every bag is checked before anything is written
        check_bag(config, bag)
    estimator = estimator_for(config, coeffs, effects)
    answer = FILTERED if args.filtered else SMOOTHED
    figures = [args.out / "figures" / Path(bag).name for bag in args.bags]
    written = [args.out, *targets, args.out / "figures", *figures, args.out / "summary.json", args.out / "summary.md"]
    results = []
    with OutputGuard(written):
        args.out.mkdir(parents=True, exist_ok=True)
        for bag, target, figure in progress(zip(args.bags, targets, figures), len(args.bags), "estimate"):
            result = estimate_bag(config, bag, estimator, answer=answer)
            write_estimate_bag(result, config, target, overwrite=args.overwrite)
            if not args.no_figures:
                plot_estimate(result, figure)
            results.append(result)
        write_summaries(
            results, args.out, {"coefficients": str(args.coeffs) if args.coeffs else "constant model", "estimate": answer}
        )
    print((args.out / "summary.md").read_text(), end="")
    print(f"estimates, summary.json/.md and figures in {args.out}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from touchdown_ros.workflows.train import train

    from touchdown_ros.workflows.offline import check_training_bag

    config = _config(args)
    if args.out.exists() and not (args.overwrite or args.resume):
        raise FileExistsError(f"{args.out} exists; pass --overwrite to replace it or --resume to continue")
    check_writable(args.out, directory=False)
    if args.init is not None:
        from touchdown_ros.io.coefficients import load_coefficients

        load_coefficients(args.init, config)
    for bag in args.bags:  # every bag is checked before the work
        check_training_bag(config, bag)
    # the checkpoint stays when training stops (--resume continues from it); the file is written at the end, atomically
    with OutputGuard([args.out]):
        outcome = train(
            config,
            args.bags,
            args.out,
            regularisation=args.regularisation,
            init=args.init,
            resume=args.resume,
            max_steps=args.steps,
            duration=args.duration,
        )
    calibration, pkbkr = outcome.calibration, outcome.pkbkr
    if calibration is not None:
        nominal = outcome.config.nominal
        print(
            f"stage 1 ({'converged' if calibration.convergence.converged else 'NOT converged'}, "
            f"{calibration.convergence.steps} steps): {outcome.config.law.label}, "
            + ", ".join(f"{k} {v:.4g} (+-{100 * calibration.relative_sd[k]:.0f} %)" for k, v in nominal._asdict().items())
            + (f"; held by the prior: {', '.join(calibration.held_by_prior)}" if calibration.held_by_prior else "")
        )
    converged = pkbkr.convergence is not None and pkbkr.convergence.converged
    kept = pkbkr.convergence.kept_step if pkbkr.convergence is not None else None
    kept_note = "" if kept is None else (
        f", kept step {kept} by the held-out error" if kept else ", no step lowered the held-out error: PKBKR alpha = 0 kept"
    )
    print(
        f"stage 2 ({'converged' if converged else 'NOT converged'}, {pkbkr.steps} steps{kept_note}): loss "
        f"{pkbkr.initial_loss:.6g} -> {pkbkr.final_loss:.6g}; mean NIS per bag "
        f"{min(outcome.mean_nis):.2f}-{max(outcome.mean_nis):.2f} (3 when consistent)"
    )
    print(f"trained on {len(args.bags)} bag(s) in {outcome.seconds:.1f} s; wrote {args.out}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from touchdown_ros.workflows.evaluate import compare, cross_validate
    from touchdown_ros.io.coefficients import load_coefficients
    from touchdown_ros.workflows.offline import check_training_bag
    from touchdown_ros.workflows.train import Trainable

    config = _config(args)
    full = load_coefficients(args.coeffs, config)
    config = full.config(config)
    lam = full.training.regularisation
    trained = Trainable(full.coeffs, full.effects)
    check_writable(args.out, directory=True)
    for bag in args.bags:  # every bag is checked before the work
        check_training_bag(config, bag)
    if args.no_cv:
        per_bag = [trained] * len(args.bags)
    else:
        per_bag = cross_validate(config, args.bags, trained, lam, args.cv_steps)
    comparisons = compare(config, args.bags, per_bag)
    with OutputGuard([args.out, *(args.out / n for n in ("evaluation.md", "evaluation.csv", "evaluation.json", "figures"))]):
        _write_evaluation(args, comparisons, config, full)
    print((args.out / "evaluation.md").read_text(), end="")
    print(f"tables, evaluation.json and figures in {args.out}")
    return 0


def _write_evaluation(args: argparse.Namespace, comparisons, config, full) -> None:
    from touchdown_ros.workflows.report.evaluation import write_evaluation

    write_evaluation(comparisons, config, full.coeffs, args.out, args.coeffs, not args.no_cv, args.example)


def cmd_diagnose(args: argparse.Namespace) -> int:
    from touchdown_ros.workflows.diagnose import Settings, run

    config = _config(args)
    settings = Settings(k=args.k, force_walk=args.force_walk, threshold=args.threshold / 100.0, fitted=args.fit)
    if args.k < 1 or args.force_walk <= 0 or not 0 < args.threshold < 100 or args.fit < 0:
        raise ValueError("--k must be >= 1, --force-walk > 0, --threshold in (0, 100) and --fit >= 0")
    from touchdown_ros.workflows.offline import check_bag

    check_writable(args.out, directory=True)
    for bag in args.bags:  # every bag is checked before the work
        check_bag(config, bag)
    names = ("diagnosis.md", "diagnosis.json", "errors.csv", "ranking.csv", "figures")
    with OutputGuard([args.out, *(args.out / name for name in names)]):
        run(config, args.bags, args.out, coeffs=args.coeffs, compare=args.compare, settings=settings)
    print((args.out / "diagnosis.md").read_text(), end="")
    print(f"diagnosis.md/.json, errors.csv, ranking.csv and figures in {args.out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate the 21-experiment campaign, train PKBKR, evaluate it leave-one-out, estimate exp 11."""
    out: Path = args.out
    bags = out / "bags"
    numbers = [11] if args.quick else None
    cmd_simulate(
        argparse.Namespace(
            config=args.config, param=args.param, out=bags, campaign=not args.quick, experiment=numbers,
            seed=args.seed, overwrite=True,
        )
    )
    all_bags = sorted(bags.glob("exp_*"))
    # Table 1's axial loader is a recorded test condition: fit its force where it was on
    # (docs/workbench.md shows how the workbench finds this missing effect).
    effect = [] if args.paper_model else ["effects.active:=[axial_load]", "effects.when.axial_load:=axial_load"]
    if not args.quick:
        coeffs = out / "coefficients.yaml"
        cmd_train(
            argparse.Namespace(
                config=args.config, param=args.param + effect, bags=all_bags, out=coeffs, regularisation=None, init=None,
                resume=False,
                steps=args.steps, duration=None, overwrite=True,
            )
        )
        cmd_evaluate(
            argparse.Namespace(
                config=args.config, param=args.param + effect, bags=all_bags, coeffs=coeffs, out=out / "evaluation",
                no_cv=False,
                cv_steps=args.cv_steps, example="exp_11",
            )
        )
    cmd_estimate(
        argparse.Namespace(
            config=args.config, param=args.param, bags=[bags / "exp_11"],
            coeffs=None if args.quick else out / "coefficients.yaml",
            out=out / "estimate", overwrite=True, no_figures=False, filtered=False,
        )
    )
    report = "" if args.quick else f"evaluation report in {out / 'evaluation'}, "
    print(f"demo done: {report}figures of exp_11 in {out / 'estimate' / 'figures' / 'exp_11'}")
    return 0


def _variant_names() -> list[str]:
    from touchdown_ros.sim.family import VARIANTS

    return [v.name for v in VARIANTS]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="touchdown", description="AMB rotor touchdown: simulate drop tests, estimate velocity, acceleration, force."
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
        "--variant", metavar="NAME",
        help="a rig of the family that differs from the reference rig (touchdown_ros.sim.family): "
        "bags NAME_NN (default: its 3 drops) and the variant's rig.yaml in --out; one of: " + ", ".join(_variant_names()),
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
    p.add_argument("--lambda", dest="regularisation", type=float, help="eq. 18 lambda (default: training.regularisation)")
    p.add_argument("--init", type=Path, help="warm-start from this coefficient file")
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
        "--force-walk", type=float, default=30.0, help="random walk of the missing-force states, N per sample (default 30)"
    )
    p.add_argument(
        "--threshold", type=float, default=50.0, help="ERR %% below which the missing force is 'unexplained' (default 50)"
    )
    p.add_argument(
        "--fit", type=int, default=3,
        help="fit FROLS's best N candidates with the model's constants and judge them on held-out samples "
        "(default 3; 0: the FROLS ranking alone decides)",
    )
    p.set_defaults(run=cmd_diagnose)

    # measured 2026-11-24 on the 2-core machine: --quick 10.5 s; the full demo's stage-1 calibration alone 2 min 15 s
    demo_text = (
        "simulate the campaign, train, evaluate leave-one-out, estimate exp 11 (several minutes: training's "
        "stage 1 alone takes about 2 min on 2 cores; --quick: about 10 s)"
    )
    p = sub.add_parser("demo", help=demo_text, description=demo_text[0].upper() + demo_text[1:] + ".")
    _add_config(p)
    p.add_argument("--out", type=Path, default=Path("results"), help="output directory (default: results)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None, help="cap on stage-2 training steps (default training.pkbkr_steps)")
    p.add_argument("--cv-steps", type=int, default=12, help="L-BFGS steps per leave-one-out fold")
    p.add_argument("--quick", action="store_true", help="only simulate and estimate experiment 11 (constant model)")
    p.add_argument(
        "--paper-model", action="store_true", help="train the paper's model alone (without the Table 1 axial-load effect)"
    )
    p.set_defaults(run=cmd_demo)

    # `touchdown replay` needs rclpy; it has its own parser (touchdown_ros.ros.replay), reached in main.
    sub.add_parser("replay", add_help=False, help="publish a bag's displacements over ROS 2 (live node tests, demos)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["replay"]:
        from touchdown_ros.ros.replay import replay_main

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
