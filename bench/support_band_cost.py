"""What the axial support's uncertainty in the force band costs the live node: one EKF chunk call
(16 rows, paced every 1.6 ms as at 10 kHz), wall time and CPU per call, side by side in rounds.

Three models of the same drop (the reference rig with random but fixed PKBKR coefficients, as
bench/ekf_cost.py): the support rigid; yielding at half the drop's axial force peak, known
exactly; and the same support with a covariance of (ln preload, ln span) (`support_log_covariance`,
as stage 1 leaves it), which adds the force's derivative by the support's two parameters to every
row. The chunk holds the 16 rows around the axial peak (in contact, all but the first above the knee).

Run: .venv/bin/python bench/support_band_cost.py [--seconds 5] [--rounds 5]
"""
from __future__ import annotations

import argparse
import statistics

import numpy as np
from chunk_dispatch import PERIOD, paced_rounds  # bench/chunk_dispatch.py
from ekf_cost import setup  # bench/ekf_cost.py

from touchdown_ros.core.estimate import make_estimator
from touchdown_ros.core.streaming import chunk_buffer, flat_belief, make_chunk_filter
from touchdown_ros.core.streaming.outputs import unpack

SIZE = 16
LOG_COVARIANCE = ((6.2, -57.0), (-57.0, 530.0))  # lossy_contact's stage 1 (ln-sd 2.5 and 23, correlation -0.999)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=5.0, help="s per variant and round")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    model, noise, h, etas, initial = setup(1500)
    filtered = make_estimator(model, noise, h)(np.arange(len(etas)) * int(h * 1e9), etas).filtered
    peak = int(np.argmax(np.asarray(filtered.F_z)))
    knee = 0.5 * float(np.asarray(filtered.F_z)[peak])
    start = max(0, peak - SIZE // 2)
    prior = flat_belief(type(initial)(np.asarray(filtered.state)[start - 1], np.asarray(filtered.state_cov)[start - 1]))
    buffer = chunk_buffer(etas[start:start + SIZE], SIZE, prior)
    laws = {
        "rigid support": model.law,
        "yielding at half the peak, exact": model.law.with_support(knee, knee),
        "yielding at half the peak, uncertain": model.law.with_support(knee, knee, LOG_COVARIANCE),
    }
    calls, force_variance = {}, {}
    for name, law in laws.items():
        chunk = make_chunk_filter(model._replace(law=law), noise, h)
        calls[name] = lambda chunk=chunk: np.asarray(chunk(buffer))
        rows = unpack(np.zeros(SIZE, np.int64), etas[start:start + SIZE], calls[name]()[:SIZE])
        force_variance[name] = rows.force_cov[:, 2, 2]  # F_z's, N^2
    exact, uncertain = force_variance[list(laws)[1]], force_variance[list(laws)[2]]
    widened = int(np.sum(uncertain > 1.01 * exact))
    assert widened >= SIZE // 2, "the chunk should lie above the knee, where the support widens the band"
    results, idle_cpu = paced_rounds(calls, args.rounds, args.seconds)
    base = None
    print(
        f"chunk of {SIZE} rows every {PERIOD * 1e3:.1f} ms ({widened} above the knee, their band widened), "
        f"medians of {args.rounds} rounds of {args.seconds:g} s\n"
    )
    print("| model | wall per call / us | p99 / us | CPU per call / us | CPU ratio |")
    print("|---|---|---|---|---|")
    for name, runs in results.items():
        wall = statistics.median(r["wall_median"] for r in runs)
        p99 = statistics.median(r["wall_p99"] for r in runs)
        cpu = statistics.median(r["cpu_per_period"] for r in runs) - idle_cpu
        base = cpu if base is None else base
        print(f"| {name} | {wall * 1e6:.0f} | {p99 * 1e6:.0f} | {cpu * 1e6:.0f} | {cpu / base:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
