"""What the process noise Q buys and costs: the family's held-out drops estimated with the trained
Q scaled by a factor, against a displacement-only choice of that factor.

`touchdown train` fits Q by the innovation likelihood (with f0, stage 1). This bench takes the
coefficient files `bench/calibration_family.py --out DIR` wrote, scales their Q by each factor
and estimates the held-out bags (smoothed, stage 1+2) as that bench does: peak force errors and
force band coverage against the truth, and two criteria a user can compute without the truth on
the training bags: the innovation negative log-likelihood (what training minimises, per sample)
and the leave-one-out cross-validated smoothing error (`core.smoothing.leave_one_out_residuals`:
the residual of each sample from the smoother's fit to the others, what `touchdown train` chooses
the smoothed estimate's factor on Q by).

    .venv/bin/python bench/process_noise_scale.py --results DIR [--variants a,b] [--scales file,1,0.3,0.1]

A factor multiplies the fitted Q (the file's `filter.smoothing_noise_scale` replaced, not compounded); `file`
is that factor, the one `touchdown train` chose. The force band's model term is measured again with each
factor on the training bags, as `touchdown train` measures it with the factor it chooses. Prints a markdown
table: rig, Q factor, worst held-out peak F_z / F_r error (%), force RMSE over the peak (%), worst velocity
RMSE (mm/s), the 95 % velocity and force bands' lowest coverage (%), NLL per sample and LOO-CV (um) on the
training bags.
"""
from __future__ import annotations

import argparse
import io
import sys
from dataclasses import replace
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from calibration_family import bag_figures
from touchdown_ros.core.ekf import Belief, position
from touchdown_ros.core.smoothing import leave_one_out_residuals
from touchdown_ros.io.coefficients import load_coefficients
from touchdown_ros.sim.family import VARIANTS, variant, variant_config
from touchdown_ros.workflows.offline import estimate_bag, estimator_for
from touchdown_ros.workflows.train import model_force_error
from touchdown_ros.workflows.training_data import load_training_data, training_batch


def criteria(estimates: list, R: np.ndarray) -> tuple[float, float]:
    """(innovation NLL per sample, LOO-CV smoothing error in m) over the estimates of some bags,
    R (3,) the measurement noise variance per axis, m^2."""
    nll, count, loo = 0.0, 0, []
    for estimate in estimates:
        nis, S = np.asarray(estimate.nis), np.asarray(estimate.innovation_cov)
        used = np.isfinite(nis)
        nll += float(np.sum(nis[used] + np.log(np.linalg.det(S[used]))))
        count += int(np.count_nonzero(used))
        smoothed = Belief(jnp.asarray(estimate.smoothed.state), jnp.asarray(estimate.smoothed.state_cov))
        residual = np.asarray(leave_one_out_residuals(position, smoothed, jnp.asarray(estimate.measured), jnp.diag(R)))
        loo.append(residual[np.isfinite(residual).all(axis=1)])
    return nll / max(count, 1), float(np.sqrt(np.mean(np.concatenate(loo) ** 2)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, required=True, help="the --out directory of calibration_family.py")
    parser.add_argument("--variants", default=",".join(v.name for v in VARIANTS))
    parser.add_argument("--scales", default="file,1,0.3,0.1", help="factors on the fitted Q; file: the file's own")
    parser.add_argument("--train", type=int, default=3, help="bags trained on per rig (the first ones)")
    parser.add_argument("--loss", default="nll")
    args = parser.parse_args(argv)
    print("| rig | Q factor | peak F_z err % | peak F_r err % | force RMSE / peak % | velocity RMSE, mm/s "
          "| 95 % band covers v / F % | training bags: NLL per sample | LOO-CV, um |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in args.variants.split(","):
        config = variant_config(variant(name))
        folder = args.results / name
        loaded = load_coefficients(folder / f"coefficients_{args.loss}.yaml", config)
        calibrated = loaded.config(config)
        bags = sorted(p for p in folder.glob(f"{name}_*") if p.is_dir() or p.suffix == ".mcap")
        train, test = bags[: args.train], bags[args.train:]
        model = calibrated.model(loaded.coeffs, loaded.effects)
        batch = training_batch(calibrated, load_training_data(calibrated, train), loaded.effects)
        for factor in (calibrated.smoothing_noise_scale if s == "file" else float(s) for s in args.scales.split(",")):
            scaled = replace(calibrated, smoothing_noise_scale=factor)  # the smoothed estimate's Q: fitted Q x factor
            noise = scaled.offline_noise()
            model_error = model_force_error(model, noise, calibrated.sample_period, batch, io.StringIO())
            scaled = replace(scaled, force_model_variance=model_error.variance)
            estimator = estimator_for(scaled, loaded.coeffs, loaded.effects)
            results = {bag: estimate_bag(scaled, bag, estimator, fit_noise=False) for bag in bags}  # Q x factor alone
            rows = [bag_figures(results[bag], config.noise_rms) for bag in test]
            fits = [results[bag].estimate for bag in train]
            nll, loo = criteria(fits, np.asarray(noise.measurement))

            def worst(key: str) -> float:
                return max(abs(r[key]) for r in rows)

            def lowest(key: str) -> float:
                return min(r[key] for r in rows)

            print(
                f"| {name} | {factor:g} | {worst('peak_axial_error_percent'):.1f} | "
                f"{worst('peak_radial_error_percent'):.1f} | {worst('force_rmse_percent_of_peak'):.1f} | "
                f"{1e3 * worst('velocity_rmse_m_s'):.3f} | {lowest('velocity_band_coverage_percent'):.0f} / "
                f"{lowest('force_band_coverage_percent'):.0f} | {nll:.4f} | {1e6 * loo:.4f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
