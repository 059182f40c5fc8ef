"""Training the 21-bag campaign: wall time and peak memory, ours vs scipy least_squares (FD Jacobian).

All minimise the same eq. 18 loss from the constant model (all alpha = 0). Ours:
L-BFGS on the reverse-mode AD gradient through the filter. Baseline: scipy
`least_squares` (trust-region reflective) on the residual vector whose squared norm is
the same loss, its Jacobian by 2-point finite differences (150 forward passes each),
with the residuals computed two ways:
- by our jitted JAX filter (a strong baseline: only the optimiser differs), run to the
  end: it stops when it reaches our final loss or its time budget, and counts its
  residual evaluations;
- by filterpy's EKF on the numpy model (`numpy_ekf.py`, the conventional way and the
  baseline of `ekf_cost.py`): one evaluation over the whole campaign is timed on a
  share of every record, and the run is extrapolated as that time x the evaluations
  the first baseline needed (a full run would take hours).
Each method runs in its own process (peak memory = that process's max RSS). Wall
times include JAX compilation. The model is the paper's (its friction, seven states, as `numpy_ekf.py` writes it),
whatever friction the rig YAML names. Run: `.venv/bin/python bench/train_cost.py [--bags DIR]`.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: The paper's model: the baselines are written for its seven states.
PAPER = {"contact.friction": "paper"}


def simulate_campaign(out: Path) -> list[Path]:
    subprocess.run([sys.executable, "-m", "touchdown_ros.cli", "simulate", "--campaign", "-o", str(out)], check=True)
    return sorted(out.glob("exp_*"))


def run_ours(bags: list[Path], steps: int) -> dict:
    """Stage 2 alone (`workflows.train.fit`) on the reference rig's constants, eq. 18 as published
    (`training.loss: one_step`) on all samples (no held-out blocks): the loss the baselines minimise.
    `touchdown train` itself runs stage 1 first and requires convergence; bench/calibration_cost.py
    times that."""
    from touchdown_ros.io.config import load_config
    from touchdown_ros.workflows.train import fit, load_training_data

    start = time.perf_counter()
    config = load_config(overrides={**PAPER, "training.loss": "one_step", "training.held_out_every": 0})
    result = fit(config, load_training_data(config, bags), min(config.regularisation), max_steps=steps)
    return {
        "seconds": time.perf_counter() - start,
        "final_loss": result.final_loss,
        "initial_loss": result.initial_loss,
        "steps": result.steps,
        "peak_rss_MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def run_baseline(bags: list[Path], target: float, budget: float) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    import scipy.optimize

    from touchdown_ros.core.pkbkr import gram
    from touchdown_ros.core.training import make_batch, prediction_errors
    from touchdown_ros.core.types import Coefficients
    from touchdown_ros.io.config import load_config
    from touchdown_ros.workflows.train import load_training_data

    start = time.perf_counter()
    config = load_config(overrides=PAPER)
    data = load_training_data(config, bags)
    batch = make_batch(list(data.records), np.asarray(config.noise.initial))
    model, noise, h, lam = config.model(), config.training_noise(), config.sample_period, min(config.regularisation)
    count = float(np.sum(batch.valid))
    K_R, K_Z = gram(config.kernel)
    L_R, L_Z = np.linalg.cholesky(np.asarray(K_R) + 1e-10 * np.eye(len(K_R))), np.linalg.cholesky(
        np.asarray(K_Z) + 1e-10 * np.eye(len(K_Z))
    )
    zeros = Coefficients.zeros(config.kernel)
    split = zeros.alpha_R.size

    @jax.jit
    def output_residuals(theta):
        coeffs = Coefficients(theta[:split].reshape(zeros.alpha_R.shape), theta[split:].reshape(zeros.alpha_Z.shape))
        errors = prediction_errors(model._replace(coeffs=coeffs), noise, h, batch)
        scaled = jnp.where(batch.valid[..., None], errors / jnp.sqrt(noise.measurement), 0.0)
        return scaled.ravel() / jnp.sqrt(count)

    def residuals(theta):
        alpha_R = theta[:split].reshape(zeros.alpha_R.shape)
        alpha_Z = theta[split:].reshape(zeros.alpha_Z.shape)
        penalty = np.sqrt(lam) * np.concatenate([(alpha_R @ L_R).ravel(), (alpha_Z @ L_Z).ravel()])
        return np.concatenate([np.asarray(output_residuals(theta)), penalty])

    reached = {"seconds": None}
    best = {"loss": float("inf")}
    evaluations = {"count": 0}

    def tracked(theta):
        evaluations["count"] += 1
        r = residuals(theta)
        value = float(r @ r)
        best["loss"] = min(best["loss"], value)
        if value <= target and reached["seconds"] is None:
            reached["seconds"] = time.perf_counter() - start
            raise StopIteration
        if time.perf_counter() - start > budget:
            raise TimeoutError
        return r

    theta0 = np.zeros(split + zeros.alpha_Z.size)
    initial_loss = float(residuals(theta0) @ residuals(theta0))
    try:
        scipy.optimize.least_squares(tracked, theta0, jac="2-point", method="trf")
    except (StopIteration, TimeoutError):
        pass
    return {
        "seconds": time.perf_counter() - start,
        "reached_target_seconds": reached["seconds"],
        "best_loss": best["loss"],
        "initial_loss": initial_loss,
        "evaluations": evaluations["count"],
        "peak_rss_MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def run_numpy_evaluation(bags: list[Path], share: int) -> dict:
    """Seconds for one residual evaluation over the campaign by filterpy's EKF, from the
    first `share` samples of every record, and its agreement with our filter there."""
    import numpy as np

    from numpy_ekf import filterpy_innovations  # bench/numpy_ekf.py
    from touchdown_ros.core.training import make_batch, prediction_errors
    from touchdown_ros.io.config import load_config
    from touchdown_ros.workflows.train import load_training_data

    config = load_config(overrides=PAPER)
    data = load_training_data(config, bags)
    model, noise, h = config.model(), config.training_noise(), config.sample_period
    batch = make_batch(list(data.records), np.asarray(config.noise.initial))
    total = int(np.sum(batch.valid))
    ours = np.asarray(prediction_errors(model, noise, h, batch))
    seconds, timed, theirs_sq, ours_sq = 0.0, 0, 0.0, 0.0
    for b in range(len(data.records)):
        valid = np.asarray(batch.valid[b])[:share]
        etas = np.asarray(batch.etas[b])[:share][valid]
        start = time.perf_counter()
        theirs = filterpy_innovations(model, noise, h, etas, batch.initial_mean[b], batch.initial_cov[b])
        seconds += time.perf_counter() - start
        timed += len(etas)
        theirs_sq += float(np.sum(theirs**2 / np.asarray(noise.measurement)))
        ours_sq += float(np.sum(ours[b, :share][valid] ** 2 / np.asarray(noise.measurement)))
    return {
        "seconds_per_evaluation": seconds / timed * total,
        "samples_timed": timed,
        "samples_total": total,
        "loss_share_relative_difference": abs(theirs_sq - ours_sq) / ours_sq,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bags", type=Path, help="directory of exp_* bags (default: simulate the campaign)")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--budget", type=float, default=1200.0, help="baseline time budget, s")
    parser.add_argument("--share", type=int, default=200, help="samples per record timed with filterpy")
    parser.add_argument("--worker", choices=("ours", "baseline", "numpy"), help=argparse.SUPPRESS)
    parser.add_argument("--target", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.worker:
        bags = sorted(args.bags.glob("exp_*"))
        if args.worker == "ours":
            result = run_ours(bags, args.steps)
        elif args.worker == "baseline":
            result = run_baseline(bags, args.target, args.budget)
        else:
            result = run_numpy_evaluation(bags, args.share)
        print(json.dumps(result))
        return

    with tempfile.TemporaryDirectory() as tmp:
        bag_dir = args.bags or Path(tmp) / "bags"
        if args.bags is None:
            simulate_campaign(bag_dir)
        common = [sys.executable, __file__, "--bags", str(bag_dir), "--steps", str(args.steps), "--budget",
                  str(args.budget), "--share", str(args.share)]

        def worker(*extra: str) -> dict:
            return json.loads(subprocess.run([*common, *extra], check=True, capture_output=True, text=True).stdout)

        ours = worker("--worker", "ours")
        baseline = worker("--worker", "baseline", "--target", str(ours["final_loss"]))
        numpy_eval = worker("--worker", "numpy")
    base_time = baseline["reached_target_seconds"]
    ratio = (
        f"{base_time / ours['seconds']:.1f}x"
        if base_time
        else f"> {baseline['seconds'] / ours['seconds']:.0f}x (not reached)"
    )
    print(f"Training the 21-bag campaign to loss {ours['final_loss']:.5g} (from {ours['initial_loss']:.5g}):")
    print("| method | wall time / s | peak memory / MiB | loss reached |")
    print("|---|---:|---:|---:|")
    print(
        f"| ours: L-BFGS, AD gradient ({ours['steps']} steps) | {ours['seconds']:.1f} | {ours['peak_rss_MiB']:.0f} "
        f"| {ours['final_loss']:.5g} |"
    )
    shown = f"{base_time:.1f}" if base_time else f"> {baseline['seconds']:.0f} (budget)"
    print(
        f"| scipy least_squares, FD Jacobian, residuals by our jitted JAX filter | {shown} "
        f"| {baseline['peak_rss_MiB']:.0f} | {baseline['best_loss']:.5g} |"
    )
    numpy_seconds = numpy_eval["seconds_per_evaluation"] * baseline["evaluations"]
    print(f"| scipy least_squares, FD Jacobian, filterpy EKF residuals (extrapolated: {baseline['evaluations']} "
          f"evaluations x {numpy_eval['seconds_per_evaluation']:.1f} s) | {numpy_seconds:.0f} | - | - |")
    print(f"speed-up: {ratio} vs the JAX-residual baseline, {numpy_seconds / ours['seconds']:.0f}x vs the filterpy one")
    print(f"filterpy timed on {numpy_eval['samples_timed']} of {numpy_eval['samples_total']} samples; its loss there "
          f"differs from ours by {numpy_eval['loss_share_relative_difference']:.1e} (relative)")


if __name__ == "__main__":
    main()
