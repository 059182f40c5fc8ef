"""Model diagnostics (issue #5): where the model fails and which physical effect it lacks.

Pure functions over arrays (no ROS, no files):

- `fit_percent`, `k_step_predictions`: the model's own prediction quality. The filtered
  estimate follows the data whatever the model, so the model is judged on the one-step
  prediction H xi_{k,-} and on the k-step prediction: the filtered state propagated k
  samples with the model's RK4 f and no measurement update.
- `autocorrelation`, `cross_correlation`: residual tests with the 99 % band
  +-2.58 / sqrt(N) of a white sequence (in the spirit of MATLAB `resid`).
- `contact_phase`, `binned_rms`, `windowed_rms`: where it fails (impact numbers: `core.impacts`).
- `disturbance_smoother`: the missing force. The state is augmented with three force
  states d (N, random walk) acting on the rotor besides the model's forces; the EKF +
  Rauch-Tung-Striebel smoother of `core.ekf` over that augmented phi (RK4 by
  `dynamics.rk4`, the model's measurement h) give d(t) with its standard deviation.
  The data, not the model, decide d: what the model lacks, per axis, with uncertainty.
- `frols`: which effect is missing. Orthogonal forward regression (Billings' FROLS) of the
  missing force on candidate regressor blocks (one block per candidate effect: its force's
  derivative with respect to its parameters, `core.effects.regressors`; a measurement
  effect enters by the force it stands for, `force_equivalent`), after the terms
  the model can already adjust (forced first: the PKBKR coefficients' regressors), ranked
  by error-reduction ratio, with the fitted parameters and their standard errors.
- `spectrum_peak`, `harmonic_share`: the residual's signature when no candidate explains it.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from touchdown_ros.core.dynamics import contact_forces, phi, rk4, rk4_step
from touchdown_ros.core.effects import FORCE, Effect, regressors
from touchdown_ros.core.ekf import (
    Belief,
    Transition,
    extended_kalman_filter,
    model_measurement,
    rts_smoother,
    with_jacobian,
)
from touchdown_ros.core.types import STATE_SIZE, Model

#: 99 % two-sided band of a white sequence's normalised autocorrelation: +-Z99 / sqrt(N).
Z99 = 2.576
PHASES = ("free flight", "axial only", "radial only", "both")


# ---------------------------------------------------------------- prediction quality

def fit_percent(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Per column: 100 (1 - |y - y_hat| / |y - mean y|) over rows where both are finite
    (100 % is a perfect fit, 0 % no better than the mean, negative worse)."""
    y, yhat = np.asarray(measured, float), np.asarray(predicted, float)
    ok = np.isfinite(y) & np.isfinite(yhat)
    out = np.full(y.shape[1], np.nan)
    for j in range(y.shape[1]):
        if ok[:, j].sum() < 2:
            continue
        yj, pj = y[ok[:, j], j], yhat[ok[:, j], j]
        spread = np.linalg.norm(yj - yj.mean())
        out[j] = 100.0 * (1.0 - np.linalg.norm(yj - pj) / spread) if spread > 0 else np.nan
    return out


def k_step_predictions(model: Model, states: Array, h: float, k: int) -> Array:
    """(N, 7): row i is the filtered state of sample i - k propagated k RK4 steps with the
    model alone (no measurement update); the first k rows are NaN."""
    states = jnp.asarray(states)

    def propagate(xi: Array) -> Array:
        return jax.lax.fori_loop(0, k, lambda _, s: rk4_step(model, s, h), xi)

    ahead = jax.vmap(propagate)(states[: states.shape[0] - k]) if k > 0 else states
    return jnp.concatenate([jnp.full((k, states.shape[1]), jnp.nan, states.dtype), ahead])


# ---------------------------------------------------------------- residual tests

def autocorrelation(e: np.ndarray, max_lag: int) -> tuple[np.ndarray, float]:
    """Normalised autocorrelation r(0..max_lag) of e (NaN rows dropped) and the 99 % band
    half-width Z99 / sqrt(N) a white sequence stays within."""
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    e = e - e.mean()
    n = len(e)
    denominator = float(np.dot(e, e)) or 1.0
    r = np.array([np.dot(e[: n - lag], e[lag:]) / denominator for lag in range(max_lag + 1)])
    return r, Z99 / np.sqrt(max(n, 1))


def cross_correlation(e: np.ndarray, u: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Normalised cross-correlation r_eu(tau) = sum e(t + tau) u(t) / (|e| |u|) for tau in
    -max_lag..max_lag (rows where both are finite) and the 99 % band of an independent pair."""
    e, u = np.asarray(e, float), np.asarray(u, float)
    ok = np.isfinite(e) & np.isfinite(u)
    e, u = e[ok] - e[ok].mean(), u[ok] - u[ok].mean()
    n = len(e)
    scale = float(np.linalg.norm(e) * np.linalg.norm(u)) or 1.0
    lags = np.arange(-max_lag, max_lag + 1)
    r = np.array([(np.dot(e[lag:], u[: n - lag]) if lag >= 0 else np.dot(e[: n + lag], u[-lag:])) / scale for lag in lags])
    return lags, r, Z99 / np.sqrt(max(n, 1))


def whiteness(e: np.ndarray, max_lag: int) -> dict:
    """Summary of the whiteness test: share of lags 1..max_lag outside the 99 % band and the
    largest |r| (a white residual has about 1 % outside)."""
    r, band = autocorrelation(e, max_lag)
    outside = np.abs(r[1:]) > band
    return {"band": float(band), "outside_share": float(outside.mean()), "max_abs": float(np.max(np.abs(r[1:])))}


# ---------------------------------------------------------------- where it fails

def contact_phase(radial_contact: np.ndarray, axial_contact: np.ndarray) -> np.ndarray:
    """0 free flight, 1 axial contact only, 2 radial contact only, 3 both (`PHASES`)."""
    return np.asarray(axial_contact, bool).astype(int) + 2 * np.asarray(radial_contact, bool).astype(int)


def rms_by_label(error: np.ndarray, labels: np.ndarray, values: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """RMS of error (N, c) per label value: (len(values), c) and the sample counts."""
    error = np.asarray(error, float)
    out = np.full((len(values), error.shape[1]), np.nan)
    counts = np.zeros(len(values), int)
    for i, v in enumerate(values):
        rows = (labels == v) & np.all(np.isfinite(error), axis=1)
        counts[i] = rows.sum()
        if counts[i]:
            out[i] = np.sqrt(np.mean(error[rows] ** 2, axis=0))
    return out, counts


def binned_rms(
    error: np.ndarray, a: np.ndarray, b: np.ndarray, a_edges: np.ndarray, b_edges: np.ndarray, min_count: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """RMS of a scalar error over the cells of the (a, b) plane (e.g. deformation, velocity):
    (len(a_edges) - 1, len(b_edges) - 1), NaN where fewer than min_count samples; and the counts."""
    error, a, b = (np.asarray(v, float) for v in (error, a, b))
    ok = np.isfinite(error) & np.isfinite(a) & np.isfinite(b)
    squares, _, _ = np.histogram2d(a[ok], b[ok], [a_edges, b_edges], weights=error[ok] ** 2)
    counts, _, _ = np.histogram2d(a[ok], b[ok], [a_edges, b_edges])
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(squares / counts)
    return np.where(counts >= min_count, rms, np.nan), counts.astype(int)


def windowed_rms(error: np.ndarray, window: int) -> np.ndarray:
    """RMS of error (N, c) over consecutive windows of `window` samples: (ceil(N / window), c)."""
    error = np.asarray(error, float)
    rows = []
    for start in range(0, len(error), window):
        block = error[start : start + window]
        ok = np.all(np.isfinite(block), axis=1)
        rows.append(np.sqrt(np.mean(block[ok] ** 2, axis=0)) if ok.any() else np.full(error.shape[1], np.nan))
    return np.array(rows)


# ---------------------------------------------------------------- the missing force

class MissingForce(NamedTuple):
    """Smoothed estimate of the force the model lacks, and the state it was estimated with."""

    force: Array  # (N, 3) N, on the rotor, sensor x/y/z
    force_std: Array  # (N, 3) N, one standard deviation
    state: Array  # (N, 7) smoothed state of the augmented filter
    state_cov: Array  # (N, 7, 7)
    model_force: Array  # (N, 3) N, the model's contact + effect forces at the smoothed state


def augmented_transition(model: Model, h: float) -> Transition:
    """RK4 step (h, s) of the state s = (xi, d) augmented with a force d (3,), N, on the rotor that
    stays constant over the step: d xi / dt = phi(xi) + (0, d / m), and its Jacobian (jacfwd)."""
    mass = model.rig.mass

    def phi_aug(s: Array) -> Array:
        rate = phi(model, s[:STATE_SIZE])
        return jnp.concatenate([rate.at[4:].add(s[STATE_SIZE:] / mass), jnp.zeros(3, s.dtype)])

    return with_jacobian(lambda s: rk4(phi_aug, s, h))


def model_force(model: Model, xi: Array) -> Array:
    """(3,) N: the model's contact force plus its effects' forces on the rotor at xi."""
    c = contact_forces(model, xi)
    force = jnp.stack([c.F_x, c.F_y, c.F_z])
    if model.effects:
        force = force + model.effects.force(xi, model.rig)
    return force


def disturbance_smoother(
    model: Model,
    process: Array,
    measurement: Array,
    initial: Belief,
    etas: Array,
    h: float,
    force_walk: float,
    force_initial: float = 1.0e3,
) -> MissingForce:
    """EKF + RTS smoother of the state augmented with a force d (3,) on the rotor (random walk
    of force_walk N rms per sample, starting at 0 +- force_initial N). Returns d(t) with its
    standard deviation: the force the model lacks, decided by the data."""
    Q = jnp.diag(jnp.concatenate([jnp.asarray(process), jnp.full(3, force_walk**2)]))
    R = jnp.diag(jnp.asarray(measurement))
    mean0 = jnp.concatenate([initial.mean, jnp.zeros(3)])
    cov0 = jax.scipy.linalg.block_diag(initial.cov, force_initial**2 * jnp.eye(3))
    transition, measure = augmented_transition(model, h), model_measurement(model)
    outputs = extended_kalman_filter(transition, measure, Q, R, Belief(mean0, cov0), jnp.asarray(etas))
    smoothed = rts_smoother(outputs)
    state = smoothed.mean[:, :STATE_SIZE]
    forces = jax.vmap(lambda s: model_force(model, s))(state)
    return MissingForce(
        force=smoothed.mean[:, 7:],
        force_std=jnp.sqrt(jnp.diagonal(smoothed.cov, axis1=1, axis2=2)[:, 7:]),
        state=state,
        state_cov=smoothed.cov[:, :STATE_SIZE, :STATE_SIZE],
        model_force=forces,
    )


# ---------------------------------------------------------------- which effect: FROLS

class Candidate(NamedTuple):
    """One candidate's result in the ranking."""

    name: str
    err: float  # error-reduction ratio alone (after the forced terms): share of the remaining energy
    values: np.ndarray  # (p,) fitted physical parameters, shared by all groups (bags)
    std: np.ndarray  # (p,) their standard errors (corrected for the residual's autocorrelation)
    group_values: np.ndarray  # (G, p) fitted per group (bag)
    group_std: np.ndarray  # (G, p)


class Ranking(NamedTuple):
    candidates: list  # [Candidate], best first (ERR alone after the forced terms)
    order: list  # FROLS greedy selection: [(name, ERR of this step, cumulative ERR)]
    forced_err: float  # share of the missing-force energy the forced terms (PKBKR refit) explain
    energy: float  # sum of squares of the weighted missing force left after the forced terms


def _orthogonalise(block: np.ndarray, basis: np.ndarray | None) -> np.ndarray:
    if basis is None or basis.shape[1] == 0:
        return block
    return block - basis @ (basis.T @ block)


def _orthonormal(block: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    """An orthonormal basis of the block's column span (drops dependent columns)."""
    if block.shape[1] == 0:
        return block
    u, s, _ = np.linalg.svd(block, full_matrices=False)
    keep = s > tol * max(s[0], 1e-300)
    return u[:, keep]


def effective_samples(residual: np.ndarray, max_lag: int = 200) -> float:
    """N / (1 + 2 sum of the residual's autocorrelation up to its first non-positive lag)."""
    r, _ = autocorrelation(residual, min(max_lag, max(len(residual) - 2, 1)))
    positive = r[1:]
    stop = np.flatnonzero(positive <= 0.0)
    tau = 1.0 + 2.0 * float(np.sum(positive[: stop[0]] if stop.size else positive))
    return max(len(residual) / tau, 1.0)


def _per_group(block: np.ndarray, groups: np.ndarray | None) -> np.ndarray:
    """The block with separate columns per group (zero outside the group's rows)."""
    if groups is None:
        return block
    labels = np.unique(groups)
    return np.concatenate([np.where((groups == g)[:, None], block, 0.0) for g in labels], axis=1)


def frols(
    y: np.ndarray,
    blocks: dict,
    forced: np.ndarray | None = None,
    offsets: dict | None = None,
    groups: np.ndarray | None = None,
    max_terms: int = 3,
) -> Ranking:
    """Rank candidate regressor blocks by how much of y they explain (FROLS, block-wise).

    y (M,): the (weighted, stacked over axes and bags) missing force; blocks: name -> (M, p)
    d force / d parameters of each candidate (same weighting); forced (M, q): terms taken in
    first (what the model can already adjust). offsets: name -> (p,) added to the linear
    coefficients to give the physical values (`linearisation_offset`). groups (M,): a label
    per row (the bag); when given, each candidate may take other values in each group (an
    effect that acts in some bags only, e.g. a loader), and its ERR is computed so.
    ERR of a block = |projection of the remaining y on its orthogonalised span|^2 / |remaining y|^2.
    """
    y = np.asarray(y, float)
    offsets = offsets or {}
    total = float(y @ y) or 1.0
    basis = _orthonormal(forced) if forced is not None and forced.shape[1] else np.zeros((len(y), 0))
    y_left = y - basis @ (basis.T @ y)
    forced_err = 1.0 - float(y_left @ y_left) / total
    energy = float(y_left @ y_left) or 1.0
    expanded = {name: _per_group(np.asarray(block, float), groups) for name, block in blocks.items()}

    candidates = []
    for name, block in blocks.items():
        q = _orthonormal(_orthogonalise(expanded[name], basis))
        explained = float(np.sum((q.T @ y_left) ** 2))
        offset = offsets.get(name)
        values, std = _fit(y_left, np.asarray(block, float), basis, offset)
        p = np.asarray(block).shape[1]
        if groups is None:
            group_values, group_std = values[None], std[None]
        else:
            fitted, fitted_std = _fit(y_left, expanded[name], basis, None)
            group_values = fitted.reshape(-1, p) + (0.0 if offset is None else np.asarray(offset, float))
            group_std = fitted_std.reshape(-1, p)
        candidates.append(Candidate(name, explained / energy, values, std, group_values, group_std))
    candidates.sort(key=lambda c: -c.err)

    order, selected, cumulative, remaining = [], basis, 0.0, dict(expanded)
    for _ in range(min(max_terms, len(blocks))):
        best, best_err, best_q = None, -1.0, None
        for name, block in remaining.items():
            q = _orthonormal(_orthogonalise(block, selected))
            err = float(np.sum((q.T @ y_left) ** 2)) / energy
            if err > best_err:
                best, best_err, best_q = name, err, q
        cumulative += best_err
        order.append((best, best_err, cumulative))
        selected = np.concatenate([selected, best_q], axis=1)
        remaining.pop(best)
    return Ranking(candidates, order, forced_err, energy)


def _fit(y_left: np.ndarray, block: np.ndarray, basis: np.ndarray, offset) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares b of y ~ basis a + block b, given y_left = y minus its projection on the
    (orthonormal) basis; standard errors from the residual variance, inflated by N / N_eff for
    the residual's autocorrelation."""
    y = y_left
    block = np.asarray(block, float)
    X = _orthogonalise(block, basis)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    residual = y - X @ coef
    n_eff = effective_samples(residual)
    dof = max(len(y) - basis.shape[1] - X.shape[1], 1)
    # ordinary least squares covariance, inflated by N / N_eff for the correlated residual rows
    cov = float(residual @ residual) / dof * np.linalg.pinv(X.T @ X) * (len(y) / n_eff)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    if offset is not None:
        coef = coef + np.asarray(offset, float)
    return coef, std


# ---------------------------------------------------------------- signature

def spectrum_peak(signal: np.ndarray, h: float, min_frequency: float = 20.0) -> tuple[float, float]:
    """Frequency (Hz) of the largest peak of the Hann-windowed power spectrum above
    min_frequency (and above 3 frequency bins), and the share of the spectrum's energy in
    that band lying within +-2 bins of the peak."""
    x = np.asarray(signal, float)
    x = x[np.isfinite(x)]
    if len(x) < 16:
        return float("nan"), float("nan")
    x = x - np.polyval(np.polyfit(np.arange(len(x)), x, 1), np.arange(len(x)))
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x)))) ** 2
    freqs = np.fft.rfftfreq(len(x), h)
    band = freqs >= max(min_frequency, 3.0 * freqs[1])
    if not band.any() or spectrum[band].sum() == 0:
        return float("nan"), float("nan")
    peak = int(np.flatnonzero(band)[np.argmax(spectrum[band])])
    near = band & (np.abs(np.arange(len(freqs)) - peak) <= 2)
    share = spectrum[near].sum() / spectrum[band].sum()
    return float(freqs[peak]), float(share)


def harmonic_share(signal: np.ndarray, angle: np.ndarray, harmonic: int = 1) -> float:
    """Share of the variance of signal explained by cos(harmonic angle), sin(harmonic angle)
    (least squares with a constant): how much of it is `harmonic` times per revolution when
    angle is the rotor angle (robust on records too short for a fine spectrum)."""
    x, a = np.asarray(signal, float), np.asarray(angle, float)
    ok = np.isfinite(x) & np.isfinite(a)
    x, a = x[ok], a[ok]
    if len(x) < 4 or np.std(x) == 0:
        return float("nan")
    A = np.stack([np.ones_like(a), np.cos(harmonic * a), np.sin(harmonic * a)], axis=1)
    coef, *_ = np.linalg.lstsq(A, x, rcond=None)
    residual = x - A @ coef
    return float(1.0 - np.var(residual) / np.var(x))


# ---------------------------------------------------------------- regressors along a trajectory

def coefficient_regressors(model: Model, states: Array) -> Array:
    """(N, 3, n_alpha): d (model force) / d (PKBKR coefficients, flattened R then Z) at each
    state: the directions in which re-training the model's own coefficients moves its force."""
    from jax.flatten_util import ravel_pytree

    flat, unravel = ravel_pytree(model.coeffs)

    def force(theta: Array, xi: Array) -> Array:
        return model_force(model._replace(coeffs=unravel(theta)), xi)

    return jax.vmap(lambda xi: jax.jacfwd(force)(flat, xi))(jnp.asarray(states))


def force_equivalent(effect: Effect, model: Model) -> Effect:
    """A measurement effect as the force it stands for; a force effect as it is.

    A measurement effect that changes the sensor output by D(xi) (m) makes a model without it
    follow the state xi + (D, 0, dD/dt), whose motion needs the extra force (first order in D)
    m (d^2 D / dt^2 - A (D, 0, dD/dt)), A = d phi[4:] / d xi, the time derivatives along the
    model's phi: what the missing force shows of it. E.g. a z gain g in free flight: the constant
    -(g - 1) m g_0; a z offset: zero in free flight, the contact stiffness times it in contact.
    """
    if effect.kind == FORCE:
        return effect
    mass = model.rig.mass

    def rate(xi: Array) -> Array:
        return phi(model, xi)

    def force(xi: Array, params, rig) -> Array:
        def change_rate(state: Array) -> Array:
            return jax.jvp(lambda s: effect.function(s, params, rig), (state,), (rate(state),))[1]

        change = jnp.asarray(effect.function(xi, params, rig), xi.dtype)
        change_velocity, change_acceleration = jax.jvp(change_rate, (xi,), (rate(xi),))
        shift = jnp.concatenate([change, jnp.zeros(1, xi.dtype), change_velocity])
        _, acceleration_shift = jax.jvp(lambda s: rate(s)[4:], (xi,), (shift,))
        return mass * (change_acceleration - acceleration_shift)

    return dataclasses.replace(effect, function=force, kind=FORCE)


def effect_regressors(effect: Effect, states: Array, model: Model, values: dict | None = None) -> tuple[Array, Array]:
    """(N, 3, p) d force / d parameters of one candidate effect along the states, linearised at
    `values` (default: its defaults), and (N, 3) its force there (for the offset of
    nonlinear-in-parameter effects). A measurement effect's force is `force_equivalent`'s."""
    effect, rig = force_equivalent(effect, model), model.rig
    p0 = values or effect.defaults()
    params = {k: jnp.asarray(v) for k, v in p0.items()}
    J = jax.vmap(lambda xi: regressors(effect, xi, rig, p0))(jnp.asarray(states))
    f0 = jax.vmap(lambda xi: jnp.asarray(effect.function(xi, params, rig), dtype=xi.dtype))(jnp.asarray(states))
    return J, f0


def linearisation_offset(J: np.ndarray, f0: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """For y ~ J b with J = d force / d p at p0: the physical p = b + p0 - c, where
    force(p0) ~ J c (one Gauss-Newton step from p0; c = p0 for a linear-in-parameter effect)."""
    A = np.asarray(J, float).reshape(-1, J.shape[-1])
    c, *_ = np.linalg.lstsq(A, np.asarray(f0, float).reshape(-1), rcond=None)
    return np.asarray(p0, float) - c
