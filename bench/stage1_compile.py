"""Compilation time and call time of stage 1's loss-and-gradient (`core.calibration.stage1_value_and_grad`)
on two drops, in this process: what a change to the model's graph costs the trainer and diagnose.

    .venv/bin/python bench/stage1_compile.py [--bags BAG BAG] [--calls 8] [--friction spinning_ring]

Without `--bags` Table 1's experiments 9 and 11 are simulated first. Prints the tracing and lowering
time, XLA's compilation time (`.lower(...).compile()`; the script does not use the persistent cache),
the median of `--calls` calls and the loss (which a change that keeps the model must keep). Run it
with XLA_FLAGS set to compare XLA options, or on two checkouts (PYTHONPATH) one after the other.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from touchdown_ros.core.calibration import (
    RIGID_LOG_SUPPORT,
    log_nominal,
    stage1_start,
    stage1_value_and_grad,
)
from touchdown_ros.io.config import load_config
from touchdown_ros.workflows.calibrate import stage1_batches, start_scales
from touchdown_ros.workflows.training_data import load_training_data, record_mesh


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bags", nargs="+", type=Path)
    parser.add_argument("--calls", type=int, default=8)
    parser.add_argument("--friction", help="contact.friction of the model (default: the rig's)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bags = args.bags
        if not bags:
            simulate = [sys.executable, "-m", "touchdown_ros.cli", "simulate", "--experiment", "9", "11", "-o", tmp]
            subprocess.run(simulate, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            bags = [Path(tmp) / "exp_09", Path(tmp) / "exp_11"]
        config = load_config(overrides={"contact.friction": args.friction} if args.friction else None)
        data = load_training_data(config, bags)
        _, batch, chunks = stage1_batches(config, data, config.effects)
        h, noise = config.sample_period, config.noise
        scales = start_scales(config.model(), noise, h, chunks)
        guess = jnp.asarray(log_nominal(config.nominal))
        theta = stage1_start(guess, config.effects, scales, jnp.asarray(RIGID_LOG_SUPPORT))
        arguments = (theta, guess, config.model(), noise, scales, batch)
        static = dict(prior_width=config.training.prior_width, h=h, kind=config.training.loss, mesh=record_mesh())
        start = time.perf_counter()
        lowered = stage1_value_and_grad.lower(*arguments, **static)
        traced = time.perf_counter()
        lowered.compile()
        compiled = time.perf_counter()
        value, _ = jax.block_until_ready(stage1_value_and_grad(*arguments, **static))
        seconds = []
        for _ in range(args.calls):
            started = time.perf_counter()
            jax.block_until_ready(stage1_value_and_grad(*arguments, **static))
            seconds.append(time.perf_counter() - started)
    print(f"records {tuple(batch.etas.shape)}: tracing and lowering {traced - start:.1f} s, compilation "
          f"{compiled - traced:.1f} s, a call {1e3 * float(np.median(seconds)):.0f} ms (median of {args.calls}), "
          f"loss {float(value):.6f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
