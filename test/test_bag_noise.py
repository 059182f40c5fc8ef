"""Q from the bag's own likelihood (`workflows.offline.bag_noise`): the offline estimate of a trained rig scales
Q's blocks where a bag's displacements ask for more process noise than the training bags did."""
from dataclasses import replace

import numpy as np
import pytest

from touchdown_ros.core.calibration import Q_BLOCKS
from touchdown_ros.core.selection import COLLINEAR_MARGIN
from touchdown_ros.io.config import load_config
from touchdown_ros.workflows.offline import FILTERED, estimate_bag, estimator_for
from touchdown_ros.workflows.report.estimate import summary_table

CONFIG = load_config()
RADIAL = list(Q_BLOCKS[0])


def _trained(process: np.ndarray, smoothing_noise_scale: float = 1.0):
    """The reference rig as a coefficient file would give it, its Q `process` (as if fitted on training bags)."""
    noise = CONFIG.noise._replace(process=np.asarray(process, dtype=float))
    return CONFIG.calibrated(CONFIG.nominal, CONFIG.law, CONFIG.kernel, noise, smoothing_noise_scale)


def _velocity_band_coverage(result) -> float:
    """% of samples and axes where the smoothed velocity lies within 1.96 sigma of the truth."""
    smoothed = result.estimate.smoothed
    error = np.asarray(smoothed.state)[:, 4:7] - result.truth.velocity
    sd = np.sqrt(np.diagonal(np.asarray(smoothed.state_cov)[:, 4:7, 4:7], axis1=1, axis2=2))
    ok = np.isfinite(error)
    return float(100.0 * np.mean((np.abs(error) <= 1.96 * sd)[ok]))


@pytest.fixture(scope="module")
def too_small_q(experiment_11_bag):
    """Experiment 11 estimated with a Q whose radial block is four times smaller than the YAML's (which is already
    smaller than the constant model's errors on this loaded, braked drop ask for), both ways."""
    process = np.asarray(CONFIG.noise.process, dtype=float).copy()
    process[RADIAL] /= 4.0
    config = _trained(process)
    estimator = estimator_for(config)
    return config, estimate_bag(config, experiment_11_bag, estimator, fit_noise=False), \
        estimate_bag(config, experiment_11_bag, estimator)


def test_a_q_too_small_for_the_bag_is_scaled_up_and_its_velocity_band_covers_more(too_small_q):
    _, as_fitted, own = too_small_q
    radial = own.summary["process_noise_factors"]["q_radial"]
    assert radial["factor"] >= 16.0 and radial["minus_two_log_likelihood_fall"] >= COLLINEAR_MARGIN, radial
    assert as_fitted.summary["process_noise_factors"]["q_radial"]["factor"] == 1.0
    assert _velocity_band_coverage(own) > _velocity_band_coverage(as_fitted) + 5.0
    assert f"| {radial['factor']:g} / " in summary_table([own])
    # the NIS the live filter (Q as fitted) has on the bag, beside the scaled filter's
    assert own.summary["mean_nis_fitted_q"] > own.summary["mean_nis"]
    assert f"NIS as fitted {own.summary['mean_nis_fitted_q']:.2f}" in summary_table([own])


def test_the_factors_scale_the_fitted_q_not_the_smoothings(too_small_q, experiment_11_bag):
    """Where the offline estimate smooths with half the fitted Q, the bag's likelihood is still asked about the
    fitted Q times each factor: the same factors."""
    trained, _, own = too_small_q
    halved = replace(trained, smoothing_noise_scale=0.5)
    again = estimate_bag(halved, experiment_11_bag, estimator_for(halved)).summary["process_noise_factors"]
    assert [b["factor"] for b in again.values()] == [b["factor"] for b in own.summary["process_noise_factors"].values()]


def test_q_is_as_given_for_the_yamls_guess_the_filtered_answer_or_when_switched_off(experiment_11_bag, too_small_q):
    """Without training bags behind Q, for the live node's answer, and with filter.bag_process_noise false."""
    trained, as_fitted, own = too_small_q
    untrained = estimate_bag(CONFIG, experiment_11_bag, estimator_for(CONFIG))
    fixed = replace(trained, adaptation=None)  # the live filter with Q as fitted, not adapted to the bag
    filtered = estimate_bag(fixed, experiment_11_bag, estimator_for(fixed, answer=FILTERED), answer=FILTERED)
    switched_off = replace(trained, bag_process_noise=False)
    off = estimate_bag(switched_off, experiment_11_bag, estimator_for(switched_off))
    for result in (untrained, filtered, off):
        assert [b["factor"] for b in result.summary["process_noise_factors"].values()] == [1.0, 1.0]
        assert "mean_nis_fitted_q" not in result.summary
    # the search's NIS under Q as fitted is the filtered answer's with Q fixed
    assert own.summary["mean_nis_fitted_q"] == pytest.approx(filtered.summary["mean_nis"], rel=1e-6)
    np.testing.assert_array_equal(np.asarray(off.estimate.smoothed.state),
                                  np.asarray(as_fitted.estimate.smoothed.state))
    assert load_config(overrides={"filter.bag_process_noise": False}).bag_process_noise is False
