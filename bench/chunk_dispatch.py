"""One EKF chunk call as the live node makes it: wall time and CPU per call, paced.

The node filters a chunk of 16 rows about every 1.6 ms (10 kHz per-sample input) and
waits for each. Between calls XLA's threads go idle, so a call costs more than in a
back-to-back loop (bench/ekf_cost.py). Measured side by side, in rounds:

* the chunk as `make_chunk_filter` compiles it (one buffer in, one out) and the same
  loop called with the prior, the rows and their count as separate arrays, returning
  the prior and the rows separately (the chunk's interface before 2026-11-23);
* JAX's asynchronous CPU dispatch (its default) and synchronous dispatch (what the node
  sets), each in its own process (the setting is read when JAX starts).

CPU per call is the process CPU over a run (all threads) minus that of the same pacing
loop without calls, divided by the calls. Inputs: the reference rig with random but
fixed PKBKR coefficients (as bench/ekf_cost.py).
Run: .venv/bin/python bench/chunk_dispatch.py [--seconds 5] [--rounds 5] [--size 16]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

PERIOD = 0.0016  # s between calls: 16 samples at 10 kHz


def paced(call, seconds: float) -> dict[str, float]:
    """Call every PERIOD for `seconds`: wall time per call (median, p99, s) and process CPU (s) per period."""
    walls = []
    cpu_start, start = time.process_time(), time.perf_counter()
    while time.perf_counter() - start < seconds:
        began = time.perf_counter()
        call()
        walls.append(time.perf_counter() - began)
        while time.perf_counter() - began < PERIOD:
            time.sleep(PERIOD / 8)
    return {"wall_median": statistics.median(walls), "wall_p99": float(np.percentile(walls, 99)),
            "cpu_per_period": (time.process_time() - cpu_start) / len(walls)}


def paced_rounds(calls: dict, rounds: int, seconds: float) -> tuple[dict[str, list[dict]], float]:
    """Each call `paced` for `seconds`, in turn, `rounds` times: name -> its runs, and the median
    process CPU per period of the pacing loop alone (s), to subtract."""
    results: dict[str, list[dict]] = {name: [] for name in calls}
    idle = []
    for _ in range(rounds):
        idle.append(paced(lambda: None, seconds)["cpu_per_period"])
        for name, call in calls.items():
            results[name].append(paced(call, seconds))
    return results, statistics.median(idle)


def child(args: argparse.Namespace) -> None:
    import jax

    jax.config.update("jax_cpu_enable_async_dispatch", args.dispatch == "async")
    from ekf_cost import setup  # bench/ekf_cost.py

    import jax.numpy as jnp

    from touchdown_ros.core.streaming import chunk_buffer, flat_belief, make_chunk_filter

    model, noise, h, etas, initial = setup(args.size)
    node_form = make_chunk_filter(model, noise, h)
    run = node_form.__wrapped__
    buffer = chunk_buffer(etas[: args.size], args.size, flat_belief(initial))

    def separate(mean, cov, etas, count):  # the same loop, called with its parts as separate arrays
        size = etas.shape[0]
        prior = jnp.concatenate([mean, cov.reshape(49), count[None].astype(mean.dtype)])
        rows = jnp.zeros((size + 1, buffer.shape[1])).at[:size, :3].set(etas).at[size, : prior.size].set(prior)
        result = run(rows)
        return result[size, :7], result[size, 7:56].reshape(7, 7), result[:size]

    separate = jax.jit(separate)
    mean, cov = jnp.asarray(initial.mean), jnp.asarray(initial.cov)  # device arrays, as a previous call returns them
    block, count = np.asarray(etas[: args.size]), np.asarray(args.size, np.int64)
    calls = {
        "one buffer in, one out (`make_chunk_filter`)": lambda: np.asarray(node_form(buffer)),
        "prior, rows and count in, prior and rows out": lambda: np.asarray(separate(mean, cov, block, count)[2]),
    }
    for call in calls.values():
        call()
    results, idle_cpu = paced_rounds(calls, args.rounds, args.seconds)
    print(json.dumps({
        name: {key: statistics.median(run[key] for run in runs) for key in runs[0]} | {"idle_cpu": idle_cpu}
        for name, runs in results.items()
    }))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=5.0, help="s per variant and round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--size", type=int, default=16, help="rows per chunk")
    parser.add_argument("--dispatch", choices=("async", "sync"), help=argparse.SUPPRESS)  # child process
    args = parser.parse_args()
    if args.dispatch:
        child(args)
        return 0
    rows = []
    for dispatch in ("async", "sync"):
        command = [sys.executable, __file__, "--dispatch", dispatch, "--seconds", str(args.seconds),
                   "--rounds", str(args.rounds), "--size", str(args.size)]
        print(f"{dispatch} dispatch ...", file=sys.stderr, flush=True)
        found = json.loads(subprocess.run(command, check=True, capture_output=True, text=True).stdout)
        rows += [(dispatch, name, values) for name, values in found.items()]
    print(f"\nChunk of {args.size} rows every {PERIOD * 1e3:.1f} ms, medians of {args.rounds} rounds of "
          f"{args.seconds:.0f} s ({time.strftime('%Y-%m-%d')}, load average {os.getloadavg()[0]:.1f}):\n")
    print("| dispatch | compiled | wall per call, median | wall p99 | CPU per call |")
    print("|---|---|---:|---:|---:|")
    for dispatch, name, v in rows:
        cpu = v["cpu_per_period"] - v["idle_cpu"]
        print(f"| {dispatch} | {name} | {v['wall_median'] * 1e6:.0f} us | {v['wall_p99'] * 1e6:.0f} us | "
              f"{cpu * 1e6:.0f} us |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
