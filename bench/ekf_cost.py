"""EKF cost per sample: JAX per call, JAX inside lax.scan, the live node's chunk, and filterpy.

All filter the same 1500-sample touchdown record with the same PKBKR model
(reference rig, random but fixed alpha; `--friction spinning_ring`: the ring's speed as an
eighth state). Medians of repeated runs, side by side in one process. The JAX rows are
measured three times, each in a child process: with XLA's default CPU runtime, with the
small-loop option (`core.xla`: the whole scan compiled into one function), and with that and
the small matrix products kept inline (`core.xla.LIBRARY_DOT_OPTIONS`), as importing
`touchdown_ros.core` sets both.
`lax.scan(..., unroll=k)` rows show what unrolling the loop gives.
Run: `make bench` or `.venv/bin/python bench/ekf_cost.py`.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from touchdown_ros.cli import parameter_overrides
from touchdown_ros.core.dynamics import rk4_step
from touchdown_ros.core.effects import Effects
from touchdown_ros.core.ekf import Belief, ekf, ekf_step
from touchdown_ros.core.streaming import chunk_buffer, flat_belief, make_chunk_filter
from touchdown_ros.core.xla import LIBRARY_DOT_OPTIONS, SMALL_LOOP_OPTION, with_options, with_small_loop_flag
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.config import load_config

from numpy_ekf import filterpy_innovations  # bench/numpy_ekf.py


def make_data(model, h, n, seed=0):
    step = jax.jit(lambda s: rk4_step(model, s, h / 10))
    xi = jnp.zeros(model.law.state_size).at[:2].set([2e-6, -1e-6])
    states = []
    for _ in range(n):
        for _ in range(10):
            xi = step(xi)
        states.append(np.asarray(xi))
    states = np.array(states)
    return states[:, :3] + 2e-6 * np.random.default_rng(seed).standard_normal((n, 3))


def median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def jax_rows(model, noise, h, etas, initial, repeats, unrolls) -> dict[str, float]:
    """Seconds per sample of the JAX variants (in this process's XLA configuration)."""
    n = len(etas)
    rows = {}
    # The model is closed over, as the node and `touchdown estimate` do: its constants fold at compile time.
    scan = jax.jit(lambda e: ekf(model, noise, h, initial, e))
    etas_device = jnp.asarray(etas)
    jax.block_until_ready(scan(etas_device))
    rows["JAX EKF inside lax.scan (`core.ekf.ekf`)"] = median_time(
        lambda: jax.block_until_ready(scan(etas_device)), repeats) / n

    for unroll in unrolls:
        def unrolled(e, unroll=unroll):
            body = lambda prior, eta: ekf_step(model, noise, h, prior, eta)  # noqa: E731
            return jax.lax.scan(body, initial, e, unroll=unroll)[1]

        fn = jax.jit(unrolled)
        jax.block_until_ready(fn(etas_device))
        rows[f"JAX EKF inside lax.scan, unroll={unroll}"] = median_time(
            lambda: jax.block_until_ready(fn(etas_device)), repeats) / n

    # The live node's chunk: EKF + filtered signals + NIS packed per row, padded chunk of fixed length; with Q as
    # given and with Q adapted to the innovations (the reference rig's `filter.adaptive_process_noise`), in turn.
    chunks = {"": make_chunk_filter(model, noise, h),
              ", adaptive Q": make_chunk_filter(model, noise, h, adaptation=load_config().adaptation)}
    for size in (512, 16):
        buffer = chunk_buffer(etas[:size], size, flat_belief(initial))
        calls = max(1, n // size)
        for chunk in chunks.values():
            jax.block_until_ready(chunk(buffer))
        times = {label: [] for label in chunks}
        for _ in range(repeats):  # the two in turn, repeat by repeat: a busy moment hits both
            for label, chunk in chunks.items():
                times[label].append(median_time(lambda: [np.asarray(chunk(buffer)) for _ in range(calls)], 1))
        for label, seconds in times.items():
            rows[f"node chunk of {size}{label} (`make_chunk_filter`, EKF + signals, per call incl. dispatch)"] = \
                statistics.median(seconds) / (calls * size)

    step = jax.jit(lambda belief, eta: ekf_step(model, noise, h, belief, eta)[0])
    samples = list(etas)

    def per_call():
        belief = initial
        for eta in samples:
            belief = step(belief, eta)
        jax.block_until_ready(belief)

    per_call()
    rows["JAX EKF, jitted step per call"] = median_time(per_call, repeats) / n
    return rows


def setup(samples: int, friction: str = "paper", params: list[str] | None = None):
    """The filter's inputs; `params` (NAME:=VALUE) change the filtered model, e.g. switch on effects: the record is
    the paper's model's touchdown either way."""
    config = load_config(overrides={"contact.friction": friction, **parameter_overrides(params or [])})
    rng = np.random.default_rng(1)
    zeros = Coefficients.zeros(config.kernel)
    coeffs = Coefficients(0.1 * rng.standard_normal(zeros.alpha_R.shape),
                          0.1 * rng.standard_normal(zeros.alpha_Z.shape))
    model, noise, h = config.model(coeffs), config.noise, config.sample_period
    etas = make_data(model._replace(effects=Effects()), h, samples)
    initial = Belief(jnp.asarray(np.concatenate([etas[0], np.zeros(len(noise.initial) - 3)])), jnp.diag(noise.initial))
    return model, noise, h, etas, initial


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=1500)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--baseline-samples", type=int, default=300, help="filterpy is slow: time it on fewer samples")
    parser.add_argument("--unroll", type=int, nargs="*", default=[2, 4, 8], help="lax.scan unroll factors to time")
    parser.add_argument("--friction", default="paper", help="contact.friction (spinning_ring: an eighth state)")
    parser.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="a rig parameter override of the filtered model (e.g. effects.active:=[amb_release])")
    parser.add_argument("--jax-only", action="store_true", help="print the JAX rows as JSON (for the child processes)")
    args = parser.parse_args()

    model, noise, h, etas, initial = setup(args.samples, args.friction, args.param)
    if args.jax_only:
        print(json.dumps(jax_rows(model, noise, h, etas, initial, args.repeats, args.unroll)))
        return
    child = [sys.executable, __file__, "--jax-only", "--samples", str(args.samples), "--repeats", str(args.repeats),
             "--friction", args.friction, "--unroll", *map(str, args.unroll),
             *(a for p in args.param for a in ("-p", p))]
    # importing touchdown_ros.core sets each option unless XLA_FLAGS already names it
    library_dots = " --xla_cpu_experimental_ynn_fusion_type=individual_dot"
    flags = {
        "default": f"--xla_backend_extra_options={SMALL_LOOP_OPTION}=1024" + library_dots,
        "small": with_small_loop_flag("") + library_dots,
        "inline": with_options(with_small_loop_flag(""), LIBRARY_DOT_OPTIONS),
    }

    def run_child(flag: str) -> dict[str, float]:
        env = dict(os.environ, XLA_FLAGS=flag)
        return json.loads(subprocess.run(child, env=env, check=True, capture_output=True, text=True).stdout)

    rows = {name: run_child(flag) for name, flag in flags.items()}

    def baseline():
        filterpy_innovations(model, noise, h, etas[: args.baseline_samples], initial.mean, initial.cov)

    # the numpy baseline is written for the paper's seven states and model
    paper_model = model.law.state_size == 7 and not model.effects
    base = median_time(baseline, max(3, args.repeats // 2)) / args.baseline_samples if paper_model else float("nan")
    effects = f", effects {', '.join(model.effects.names)}" if model.effects else ""
    print(f"EKF cost per sample ({args.samples} samples, friction {args.friction}{effects}, median of {args.repeats}; "
          f"jax {jax.__version__}; load average {os.getloadavg()[0]:.1f}):")
    print("| implementation | us per sample, XLA default | small-loop option | small loops + inline dots | "
          "speed-up vs filterpy (best) |")
    print("|---|---:|---:|---:|---:|")
    for name in rows["default"]:
        times = [rows[setting][name] for setting in flags]
        speed_up = f"{base / min(times):.0f}x" if paper_model else "-"
        print(f"| {name} | " + " | ".join(f"{t * 1e6:.1f}" for t in times) + f" | {speed_up} |")
    if paper_model:
        print(f"| filterpy EKF, numpy model, FD Jacobian | {base * 1e6:.1f} | - | - | 1x |")


if __name__ == "__main__":
    main()
