"""Cost of `touchdown train` on the paper's 21-bag campaign: stage 1 alone and both stages to
convergence, wall time including JAX compilation and peak memory, each run in its own process.
Each run starts with an empty compilation cache (TOUCHDOWN_XLA_CACHE, a fresh folder), and the
defaults run once more on the cache the first filled ("warm": what a second `train` of the
same shapes costs).

    .venv/bin/python bench/calibration_cost.py [--bags DIR] [--runs 1] [--with COMMIT_CHECKOUT]
        [--against COMMIT_CHECKOUT] [--guess-scale 3] [--cold-only] [--frictions paper,spinning_ring]
        [-p NAME:=VALUE ...]

Without `--bags` the campaign is simulated first. `--with DIR` adds, run by run in turn, the
trainer of another checkout (e.g. `git worktree add /tmp/old <commit>`) with `--steps 40`, the
earlier release's default, so the two are measured side by side on the same machine state.
`--against DIR` adds that checkout's trainer with the same defaults and an empty cache of its own, run
in turn with this one's (an A/B of two versions); `--guess-scale 3` starts from the reference
guess's six contact constants times 3 (docs/calibration.md's campaign case); `--cold-only` runs only
the defaults with an empty cache (and the other checkouts). `--frictions A,B` adds, in turn with the
defaults, a cold run that lets the bags choose the friction model (`training.friction_models: [A, B]`).
`-p NAME:=VALUE` changes a rig parameter for this checkout's runs only (e.g. `-p training.refinement:=gauss_newton
--against DIR`, DIR a checkout of the same commit: the two refinements in turn).
The campaign is trained with the axial loader as a conditional effect (issue 15's campaign case; `make demo`
trains the brake beside it since 2026-11-28, which these figures leave out so that they compare over time).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LOADER = ["-p", "effects.active:=[axial_load]", "-p", "effects.when.axial_load:=axial_load"]


def timed(command: list[str], env: dict[str, str] | None = None, cwd: str | None = None) -> dict:
    """Wall seconds, CPU seconds (user + system: less moved by other jobs on a shared machine), peak
    RSS (MiB, GNU time's %M) and exit code of one child process."""
    start = time.perf_counter()
    done = subprocess.run(["/usr/bin/time", "-f", "%U %S %M", *command], env=env, cwd=cwd,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - start
    lines = done.stderr.strip().splitlines()
    fields = lines[-1].split() if lines else []
    measured = len(fields) == 3 and fields[2].isdigit()
    return {"seconds": seconds, "cpu_seconds": float(fields[0]) + float(fields[1]) if measured else None,
            "peak_rss_MiB": int(fields[2]) / 1024 if measured else None,
            "exit": done.returncode, "message": lines[-2] if len(lines) > 1 else ""}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bags", type=Path)
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--with", dest="other", type=Path, help="another checkout, trained with --steps 40")
    parser.add_argument("--against", type=Path, help="another checkout, trained with the same defaults")
    parser.add_argument("--guess-scale", type=float, default=1.0, help="the reference contact guess times this")
    parser.add_argument("--cold-only", action="store_true", help="only the defaults with an empty cache")
    parser.add_argument("--frictions", help="friction models the bags choose from, comma-separated (a run of its own)")
    parser.add_argument("-p", dest="parameters", action="append", default=[], metavar="NAME:=VALUE",
                        help="a rig parameter for this checkout's runs (not --against's or --with's)")
    args = parser.parse_args()
    python = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        bags_dir = args.bags or Path(tmp) / "campaign"
        if args.bags is None:
            subprocess.run(
                [python, "-m", "touchdown_ros.cli", "simulate", "--campaign", "-o", str(bags_dir)], check=True
            )
        bags = [str(b) for b in sorted(bags_dir.glob("exp_*"))]
        out = str(Path(tmp) / "c.yaml")
        guess = scaled_guess(args.guess_scale) if args.guess_scale != 1.0 else []
        train = [python, "-m", "touchdown_ros.cli", "train", *bags, "-o", out, "--overwrite", *LOADER, *guess]
        ours = [*train, *(a for value in args.parameters for a in ("-p", value))]
        filled = {"cache": ""}  # the folder the last cold run of the defaults filled

        def with_cache(folder: str) -> dict[str, str]:
            return dict(os.environ, TOUCHDOWN_XLA_CACHE=folder)

        def cold(*extra: str) -> dict:
            filled["cache"] = tempfile.mkdtemp(dir=tmp, prefix="cache-")
            return timed([*ours, *extra], env=with_cache(filled["cache"]))

        cases = {
            "stage 1 only (--steps 0), cold cache": lambda: cold("--steps", "0"),
            "stage 1 + stage 2 (defaults), cold cache": cold,
            "stage 1 + stage 2 (defaults), warm cache": lambda: timed(ours, env=with_cache(filled["cache"])),
        }
        if args.cold_only:
            cases = {"stage 1 + stage 2 (defaults), cold cache": cold}
        if args.frictions:
            models = ", ".join(args.frictions.split(","))
            cases[f"the friction chosen by the bags ([{models}]), cold cache"] = lambda: cold(
                "-p", f"training.friction_models:=[{models}]")
        if args.against is not None:
            cases[f"{args.against}: defaults, cold cache"] = lambda: timed(
                train, env=dict(os.environ, PYTHONPATH=str(args.against),
                                TOUCHDOWN_XLA_CACHE=tempfile.mkdtemp(dir=tmp, prefix="cache-")),
                cwd=str(args.against))
        if args.other is not None:
            env = dict(os.environ, PYTHONPATH=str(args.other), TOUCHDOWN_XLA_CACHE="off")
            cases[f"{args.other}: 40 steps (its default)"] = lambda: timed(
                [python, "-m", "touchdown_ros.cli", "train", *bags, "-o", out, "--overwrite", "--steps", "40", *LOADER],
                env=env, cwd=str(args.other))
        results = in_turn(cases, args.runs)
    print_table(results, "run")
    if args.against is not None:
        print_ratios(results["stage 1 + stage 2 (defaults), cold cache"],
                     results[f"{args.against}: defaults, cold cache"], args.against)
    return 0


def print_ratios(ours: list[dict], theirs: list[dict], other: object, case: str = "") -> None:
    """Wall and CPU time of each of our runs over the other checkout's run in the same turn, and their median."""
    for key in ("seconds", "cpu_seconds"):
        pairs = [a[key] / b[key] for a, b in zip(ours, theirs) if a.get(key) and b.get(key)]
        if pairs:
            print(f"{case}{key}: this / {other}, run by run {', '.join(f'{r:.2f}' for r in pairs)}; "
                  f"median {statistics.median(pairs):.2f}")


def scaled_guess(factor: float) -> list[str]:
    """`-p` options setting the reference rig's six contact constants times factor."""
    from touchdown_ros.io.config import load_config

    nominal = load_config().nominal
    return [a for k, v in nominal._asdict().items() for a in ("-p", f"contact.{k}:={v * factor:.6g}")]


def in_turn(cases: dict, runs: int) -> dict[str, list[dict]]:
    """Each case's `timed` result, the cases run in turn `runs` times (a drift of the machine hits all alike)."""
    results: dict[str, list[dict]] = {name: [] for name in cases}
    for _ in range(runs):
        for name, run in cases.items():
            results[name].append(run())
            print(name, json.dumps(results[name][-1]), file=sys.stderr, flush=True)
    return results


def print_table(results: dict[str, list[dict]], title: str) -> None:
    """Markdown table: per case the median wall time, the largest peak memory and the exit codes."""
    print(f"| {title} | wall time / s (median) | CPU time / s (median) | peak memory / MiB | exit |\n"
          "|---|---:|---:|---:|---:|")
    for name, runs in results.items():
        cpu = [r["cpu_seconds"] for r in runs if r.get("cpu_seconds") is not None]
        print(f"| {name} | {statistics.median(r['seconds'] for r in runs):.1f} | "
              f"{statistics.median(cpu) if cpu else float('nan'):.1f} | "
              f"{max(r['peak_rss_MiB'] or 0 for r in runs):.0f} | {','.join(str(r['exit']) for r in runs)} |")


if __name__ == "__main__":
    sys.exit(main())
