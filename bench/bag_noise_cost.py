"""What Q from the bag's own likelihood costs `touchdown estimate`: one bag's smoothed estimate with a trained
rig's coefficient file, with the search (`filter.bag_process_noise`, the default) and without it, in turn.

    .venv/bin/python bench/bag_noise_cost.py --results DIR --variant NAME [--bag NAME_04] [--runs 5]

DIR is the --out directory of bench/calibration_family.py (its rig's bags and coefficients_nll.yaml). The first
call of each kind compiles (its wall time is printed apart); the medians are of the calls after it, the two kinds
alternating, so the machine's load changes both alike. Prints the factors the search took.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from touchdown_ros.io.coefficients import load_coefficients
from touchdown_ros.sim.family import variant, variant_config
from touchdown_ros.workflows.offline import estimate_bag, estimator_for


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, required=True, help="the --out directory of calibration_family.py")
    parser.add_argument("--variant", required=True, help="the rig (a folder of --results)")
    parser.add_argument("--bag", help="the bag to estimate (default: the rig's fourth, a held-out one)")
    parser.add_argument("--runs", type=int, default=5, help="timed calls of each kind after the first")
    args = parser.parse_args(argv)
    folder = args.results / args.variant
    config = variant_config(variant(args.variant))
    loaded = load_coefficients(folder / "coefficients_nll.yaml", config)
    calibrated = loaded.config(config)
    estimator = estimator_for(calibrated, loaded.coeffs, loaded.effects)
    bag = folder / (args.bag or f"{args.variant}_04")
    seconds: dict[bool, list[float]] = {False: [], True: []}
    factors = None
    for run in range(args.runs + 1):
        for search in (False, True):
            started = time.perf_counter()
            result = estimate_bag(calibrated, bag, estimator, fit_noise=search)
            seconds[search].append(time.perf_counter() - started)
            if search:
                factors = [b["factor"] for b in result.summary["process_noise_factors"].values()]
    first = {k: v.pop(0) for k, v in seconds.items()}
    median = {k: float(np.median(v)) for k, v in seconds.items()}
    print(f"| {bag.name} | {len(result.estimate.stamps_ns)} samples | first call (compiles): {first[False]:.1f} s "
          f"without, {first[True]:.1f} s with the search | median of {args.runs}: {median[False]:.2f} s without, "
          f"{median[True]:.2f} s with ({median[True] / median[False]:.2f}x) | Q x {factors} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
