"""EKF cost per sample: JAX per call, JAX inside lax.scan, the live node's chunk, and filterpy.

All filter the same 1500-sample touchdown record with the same PKBKR model
(reference rig, random but fixed alpha). Medians of repeated runs, side by side in
one process. The JAX rows are measured twice, each in a child process: with XLA's
default CPU runtime and with the small-loop option that importing `touchdown_ros.core`
sets (`core.xla`: the whole scan compiled into one function).
`lax.scan(..., unroll=k)` rows show what unrolling the loop gives.
Run: `make bench` or `.venv/bin/python bench/ekf_cost.py`.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from touchdown_ros.core.dynamics import rk4_step
from touchdown_ros.core.ekf import Belief, ekf, ekf_step
from touchdown_ros.core.streaming import make_chunk_filter
from touchdown_ros.core.xla import SMALL_LOOP_OPTION, with_small_loop_flag
from touchdown_ros.core.types import Coefficients
from touchdown_ros.io.config import load_config


def numpy_model(model):
    """The same eq. 5-12 model written with numpy, for the filterpy baseline."""
    rig, p, kernel, coeffs = model[:4]
    T_R, T_Z = np.asarray(kernel.T_R), np.asarray(kernel.T_Z)
    a_R, a_Z = np.asarray(coeffs.alpha_R), np.asarray(coeffs.alpha_Z)

    def q(deformation, velocity, T):
        s = np.array([deformation / kernel.deformation_scale, velocity / kernel.velocity_scale])
        return np.exp(-np.sum((s - T) ** 2, axis=1) / (2 * kernel.width**2))

    def phi(xi):
        x, y, z, theta, xd, yd, zd = xi
        r = math.hypot(x, y)
        c, s = (x / r, y / r) if r > 0 else (1.0, 0.0)
        rdot = c * xd + s * yd
        F_n = F_t = F_z = 0.0
        if r > rig.radial_clearance:
            Q = q(r - rig.radial_clearance, rdot, T_R)
            k_R, c_R, mu = (max(f0 * (1 + Q @ a), 0.0) for f0, a in zip((p.k_R, p.c_R, p.mu), a_R))
            F_n = k_R * (r - rig.radial_clearance) + c_R * rdot
            F_t = mu * F_n
            F_z = -mu * np.sign(zd) * F_n
        if z < -rig.axial_clearance:
            Q = q(z + rig.axial_clearance, zd, T_Z)
            k_Z, c_Z, k_ZR = (max(f0 * (1 + Q @ a), 0.0) for f0, a in zip((p.k_Z, p.c_Z, p.k_ZR), a_Z))
            F_zZ = -k_Z * (z + rig.axial_clearance) - c_Z * zd
            F_t += k_ZR * F_zZ
            F_z += F_zZ
        u = rig.eccentricity * rig.speed**2
        return np.array(
            [xd, yd, zd, rig.speed,
             (-F_n * c + F_t * s) / rig.mass + u * math.cos(theta),
             (-F_n * s - F_t * c) / rig.mass + u * math.sin(theta),
             F_z / rig.mass - rig.gravity]
        )

    return phi


def numpy_rk4(phi, xi, h):
    k1 = h * phi(xi)
    k2 = h * phi(xi + 0.5 * k1)
    k3 = h * phi(xi + 0.5 * k2)
    k4 = h * phi(xi + k3)
    return xi + (k1 + 2 * k2 + 2 * k3 + k4) / 6


def fd_jacobian(f, xi, steps):
    J = np.empty((7, 7))
    for j in range(7):
        d = np.zeros(7)
        d[j] = steps[j]
        J[:, j] = (f(xi + d) - f(xi - d)) / (2 * steps[j])
    return J


def make_data(model, h, n, seed=0):
    step = jax.jit(lambda s: rk4_step(model, s, h / 10))
    xi = jnp.array([2e-6, -1e-6, 0.0, 0.0, 0.0, 0.0, 0.0])
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

    # The live node's chunk: EKF + filtered signals + NIS packed per row, padded chunk of fixed length.
    chunk = make_chunk_filter(model, noise, h)
    for size in (512, 16):
        block = np.asarray(etas[:size])
        count = np.asarray(size, np.int64)
        jax.block_until_ready(chunk(initial, block, count))
        calls = max(1, n // size)
        seconds = median_time(lambda: [np.asarray(chunk(initial, block, count)[1]) for _ in range(calls)], repeats)
        rows[f"node chunk of {size} (`make_chunk_filter`, EKF + signals, per call incl. dispatch)"] = \
            seconds / (calls * size)

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


def setup(samples: int):
    config = load_config()
    rng = np.random.default_rng(1)
    zeros = Coefficients.zeros(config.kernel)
    coeffs = Coefficients(0.1 * rng.standard_normal(zeros.alpha_R.shape),
                          0.1 * rng.standard_normal(zeros.alpha_Z.shape))
    model, noise, h = config.model(coeffs), config.noise, config.sample_period
    etas = make_data(model, h, samples)
    initial = Belief(jnp.asarray(np.concatenate([etas[0], np.zeros(4)])), jnp.diag(noise.initial))
    return model, noise, h, etas, initial


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=1500)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--baseline-samples", type=int, default=300, help="filterpy is slow: time it on fewer samples")
    parser.add_argument("--unroll", type=int, nargs="*", default=[2, 4, 8], help="lax.scan unroll factors to time")
    parser.add_argument("--jax-only", action="store_true", help="print the JAX rows as JSON (for the second process)")
    args = parser.parse_args()

    model, noise, h, etas, initial = setup(args.samples)
    if args.jax_only:
        print(json.dumps(jax_rows(model, noise, h, etas, initial, args.repeats, args.unroll)))
        return
    child = [sys.executable, __file__, "--jax-only", "--samples", str(args.samples), "--repeats", str(args.repeats),
             "--unroll", *map(str, args.unroll)]
    # importing touchdown_ros.core raises the option unless XLA_FLAGS already names it
    xla_default = f"--xla_backend_extra_options={SMALL_LOOP_OPTION}=1024"
    env_default = dict(os.environ, XLA_FLAGS=xla_default)
    env_small = dict(os.environ, XLA_FLAGS=with_small_loop_flag(""))
    default = json.loads(subprocess.run(child, env=env_default, check=True, capture_output=True, text=True).stdout)
    small = json.loads(subprocess.run(child, env=env_small, check=True, capture_output=True, text=True).stdout)

    phi = numpy_model(model)
    f = lambda xi: numpy_rk4(phi, xi, h)  # noqa: E731
    steps = np.array([1e-9, 1e-9, 1e-9, 1e-6, 1e-6, 1e-6, 1e-6])
    Hm = np.eye(3, 7)

    class Baseline(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = f(self.x[:, 0])[:, None]

    def baseline():
        kf = Baseline(dim_x=7, dim_z=3)
        kf.x = np.asarray(initial.mean)[:, None].copy()
        kf.P, kf.Q, kf.R = np.diag(noise.initial), np.diag(noise.process), np.diag(noise.measurement)
        for eta in etas[: args.baseline_samples]:
            kf.update(eta[:, None], lambda x: Hm, lambda x: Hm @ x)
            kf.F = fd_jacobian(f, kf.x[:, 0], steps)
            kf.predict()

    base = median_time(baseline, max(3, args.repeats // 2)) / args.baseline_samples
    print(f"EKF cost per sample ({args.samples} samples, median of {args.repeats}; jax {jax.__version__}; "
          f"load average {os.getloadavg()[0]:.1f}):")
    print("| implementation | us per sample, XLA default | us per sample, small-loop option | "
          "speed-up vs filterpy (best) |")
    print("|---|---:|---:|---:|")
    for name, seconds in default.items():
        best = min(seconds, small[name])
        print(f"| {name} | {seconds * 1e6:.1f} | {small[name] * 1e6:.1f} | {base / best:.0f}x |")
    print(f"| filterpy EKF, numpy model, FD Jacobian | {base * 1e6:.1f} | - | 1x |")


if __name__ == "__main__":
    main()
