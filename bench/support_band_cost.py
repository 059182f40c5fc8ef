"""What a law constant pair's uncertainty in the force band costs the live node: one EKF chunk call
(16 rows, paced every 1.6 ms as at 10 kHz), wall time and CPU per call, side by side in rounds.

Three models of the same drop (the reference rig with random but fixed PKBKR coefficients, as
bench/ekf_cost.py), for the pair `--pair`:
- support (default): the support rigid; yielding at half the drop's axial force peak, known
  exactly; and the same support with a covariance of (ln preload, ln span) (`support_log_covariance`,
  as stage 1 leaves it), which adds the force's derivative by the support's two parameters to every
  row. The chunk holds the 16 rows around the axial peak (in contact, all but the first above the knee).
- stribeck: the ring's friction (`spinning_ring`) without a drop; with a drop of 0.33 over 0.05 m/s,
  known exactly; and the same drop with a covariance of (ln drop, ln v_s) (`stribeck_log_covariance`,
  a fitted drop's). The chunk holds the 16 rows where the drop widens the band on the most rows.

Run: .venv/bin/python bench/support_band_cost.py [--pair support|stribeck] [--seconds 5] [--rounds 5]
"""
from __future__ import annotations

import argparse
import statistics

import jax
import jax.numpy as jnp
import numpy as np
from chunk_dispatch import PERIOD, paced_rounds  # bench/chunk_dispatch.py
from ekf_cost import setup  # bench/ekf_cost.py

from touchdown_ros.core.estimate import make_estimator, stribeck_force_covariance
from touchdown_ros.core.streaming import chunk_buffer, flat_belief, make_chunk_filter
from touchdown_ros.core.streaming.outputs import unpack

SIZE = 16
LOG_COVARIANCE = ((6.2, -57.0), (-57.0, 530.0))  # lossy_contact's stage 1 (ln-sd 2.5 and 23, correlation -0.999)
#: stiff_quiet's fitted drop (0.274 +- 6 %, v_s 0.050 +- 5 %; 2026-12-04), its correlation taken as -0.5
STRIBECK_LOG_COVARIANCE = ((3.4e-3, -8.7e-4), (-8.7e-4, 2.8e-3))
DROP, STRIBECK_VELOCITY = 0.33, 0.05  # the family simulator's ceramic balls: 0.24 / 0.18 - 1, m/s


def support_laws(model, filtered) -> tuple[dict, int]:
    """The three support models and the chunk's first row: around the axial peak, the knee at half of it."""
    peak = int(np.argmax(np.asarray(filtered.F_z)))
    knee = 0.5 * float(np.asarray(filtered.F_z)[peak])
    laws = {
        "rigid support": model.law,
        "yielding at half the peak, exact": model.law.with_support(knee, knee),
        "yielding at half the peak, uncertain": model.law.with_support(knee, knee, LOG_COVARIANCE),
    }
    return laws, max(1, peak - SIZE // 2)


def stribeck_laws(model, filtered) -> tuple[dict, int]:
    """The three friction models and the chunk's first row: the 16 rows where the drop's uncertainty adds most to
    the band, relative to it (on this record the ring has not caught up: a little; the cost is the same)."""
    laws = {
        "ring friction, no drop": model.law,
        f"drop {DROP:g} over {STRIBECK_VELOCITY:g} m/s, exact": model.law.with_stribeck(DROP, STRIBECK_VELOCITY),
        f"drop {DROP:g} over {STRIBECK_VELOCITY:g} m/s, uncertain": model.law.with_stribeck(
            DROP, STRIBECK_VELOCITY, STRIBECK_LOG_COVARIANCE
        ),
    }
    uncertain = model._replace(law=list(laws.values())[2])
    added = jax.vmap(lambda xi: stribeck_force_covariance(uncertain, xi))(jnp.asarray(filtered.state))
    band = np.trace(np.asarray(filtered.force_cov), axis1=1, axis2=2)
    part = np.asarray(jnp.trace(added, axis1=1, axis2=2))
    relative = np.divide(part, band, out=np.zeros_like(band), where=band > 0)  # out of contact both are 0
    sums = np.convolve(relative, np.ones(SIZE), mode="valid")
    return laws, max(1, int(np.argmax(sums)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=5.0, help="s per variant and round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--pair", choices=("support", "stribeck"), default="support")
    args = parser.parse_args()
    model, noise, h, etas, initial = setup(1500, "spinning_ring" if args.pair == "stribeck" else "paper")
    filtered = make_estimator(model, noise, h)(np.arange(len(etas)) * int(h * 1e9), etas).filtered
    laws, start = (support_laws if args.pair == "support" else stribeck_laws)(model, filtered)
    prior = flat_belief(type(initial)(np.asarray(filtered.state)[start - 1], np.asarray(filtered.state_cov)[start - 1]))
    buffer = chunk_buffer(etas[start:start + SIZE], SIZE, prior)
    calls, force_trace = {}, {}
    for name, law in laws.items():
        chunk = make_chunk_filter(model._replace(law=law), noise, h)
        calls[name] = lambda chunk=chunk: np.asarray(chunk(buffer))
        rows = unpack(np.zeros(SIZE, np.int64), etas[start:start + SIZE], calls[name]()[:SIZE])
        force_trace[name] = np.trace(rows.force_cov, axis1=1, axis2=2)  # N^2
    exact, uncertain = force_trace[list(laws)[1]], force_trace[list(laws)[2]]
    widened = int(np.sum(uncertain > 1.01 * exact))
    most = float(np.max(uncertain / np.maximum(exact, 1e-300))) - 1.0
    if args.pair == "support":
        assert widened >= SIZE // 2, "the chunk should lie above the knee, where the support widens the band"
    else:
        assert most > 0.0, "the drop's uncertainty should widen the band on some row"
    results, idle_cpu = paced_rounds(calls, args.rounds, args.seconds)
    base = None
    print(
        f"chunk of {SIZE} rows every {PERIOD * 1e3:.1f} ms ({widened} with their band widened by over 1 % by the "
        f"{args.pair}'s uncertainty, at most {most:.2g} of its variance), medians of {args.rounds} rounds of "
        f"{args.seconds:g} s\n"
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
