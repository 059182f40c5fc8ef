"""Wall time of `touchdown diagnose` on two 0.15 s drops (Table 1's experiments 9 and 11, the axial
loader on) from their stage-1 calibration, compilation included, each run in its own process:
with the candidates fitted (the default, --fit 10; and 3, the default before 2026-11-25) and the
FROLS pass alone (--fit 0), from an empty compilation cache and once more on the cache the first
run filled.

    .venv/bin/python bench/diagnose_cost.py [--runs 1] [--fits 10,3,0] [--against COMMIT_CHECKOUT]

`--against DIR` runs that checkout's `touchdown diagnose` (e.g. `git worktree add /tmp/old <commit>`) in
turn with this one's, each with its own cache, from the same calibration (this checkout's stage 1), and
prints the ratios run by run.

Target (issue 16): <= 20 s per model.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from calibration_cost import in_turn, print_ratios, print_table, timed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--fits", default="10,3,0", help="the --fit values to run, comma-separated")
    parser.add_argument("--against", type=Path, help="another checkout, run in turn with the same options")
    args = parser.parse_args()
    fits = [int(v) for v in args.fits.split(",")]
    python = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        bags_dir = Path(tmp) / "bags"
        touchdown = [python, "-m", "touchdown_ros.cli"]
        subprocess.run([*touchdown, "simulate", "--experiment", "9", "11", "-o", str(bags_dir)], check=True)
        bags = [str(bags_dir / "exp_09"), str(bags_dir / "exp_11")]
        calibrated = str(Path(tmp) / "calibrated.yaml")
        subprocess.run(
            [*touchdown, "train", *bags, "-o", calibrated, "--steps", "0"], check=True, stderr=subprocess.DEVNULL
        )

        def diagnose(fit: int, cache: str, checkout: Path | None = None) -> dict:
            out = str(Path(tmp) / "diagnosis")
            env = dict(os.environ, TOUCHDOWN_XLA_CACHE=cache)
            if checkout is not None:
                env["PYTHONPATH"] = str(checkout)
            return timed(
                [*touchdown, "diagnose", *bags, "--coeffs", calibrated, "--out", out, "--fit", str(fit)], env=env,
                cwd=None if checkout is None else str(checkout),
            )

        cases = {}
        for fit in fits:
            for checkout in [None] if args.against is None else [None, args.against]:
                cache = str(Path(tmp) / f"cache_{fit}_{'other' if checkout else 'this'}")
                name = f"{checkout}: " if checkout else ""
                cases[f"{name}--fit {fit}, empty compilation cache"] = (
                    lambda fit=fit, cache=cache, checkout=checkout: diagnose(fit, _emptied(cache), checkout))
                cases[f"{name}--fit {fit}, warm compilation cache"] = (
                    lambda fit=fit, cache=cache, checkout=checkout: diagnose(fit, cache, checkout))
        results = in_turn(cases, args.runs)
    print_table(results, "diagnose, 2 bags x 0.15 s")
    if args.against is not None:
        for name in [n for n in results if not n.startswith(f"{args.against}: ")]:
            print_ratios(results[name], results[f"{args.against}: {name}"], args.against, case=f"{name}: ")
    return 0


def _emptied(folder: str) -> str:
    """The folder, emptied of a compilation cache a previous run left."""
    import shutil

    shutil.rmtree(folder, ignore_errors=True)
    return folder


if __name__ == "__main__":
    sys.exit(main())
