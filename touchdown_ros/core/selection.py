"""Choosing the missing effect by what fitting it achieves (issue #16).

Each candidate effect is fitted with the calibrated model's constants (stage 1's coordinates:
ln f0, the Q factors and the candidate's parameters, `core.calibration`) on the fitted samples
of records with held-out time blocks (`core.training.hold_out`), and judged on the held-out
samples against the same fit without any candidate (the baseline):

- the fall of the mean innovation negative log-likelihood (-2 ln L per sample, `nll`);
- the fall of the k-step prediction error (the filtered state propagated k samples, m);
- a Bayesian information criterion on the fitted samples,
  BIC = N_fit * mean(-2 ln L) + p ln N_fit, as a difference to the baseline's, so that a
  candidate gains nothing from its extra parameters alone (negative: better than none).

Every candidate lives in one model (`with_candidates`), switched on by its gate in the batch
(`candidate_gates`): the gates and parameters are traced, so one compilation fits them all.

Collinear candidates (two within a small criterion margin) are told apart by where they act:
held-out errors per contact phase (`contact_phases`): a constant load acts in free flight too,
a stiffness where the rotor is displaced, a contact effect only in contact. A phase tells them
apart only where the two candidates' paired differences over the held-out blocks say so (a
t-test at 5 %); else the criterion's order stands.
"""
from __future__ import annotations

import math
from typing import Mapping, NamedTuple, Sequence

import jax
import numpy as np
import scipy.stats
from jax import Array

from touchdown_ros.core.calibration import filtered_states
from touchdown_ros.core.diagnostics.breakdown import PHASES, contact_phase, deformations
from touchdown_ros.core.diagnostics.prediction import k_step_predictions
from touchdown_ros.core.dynamics import measurement
from touchdown_ros.core.effects import Effect, Effects
from touchdown_ros.core.training import Batch, held_out_blocks, sample_errors, sums_per_block
from touchdown_ros.core.types import FilterNoise, Model, Rig

#: Label of the fit without any candidate, the reference of every difference.
BASELINE = "none"


def with_candidates(
    effects: Effects, candidates: Sequence[Effect], starts: Mapping[str, Mapping[str, float]] | None = None
) -> Effects:
    """The model's effects followed by the candidates at their defaults, or where `starts` (candidate ->
    parameter -> value) puts them, switched on by gates."""
    return Effects(
        effects.effects + tuple(candidates),
        effects.params + tuple(c.defaults() for c in candidates),
        effects.gates + (1.0,) * len(candidates),
    ).with_values(starts or {})


def candidate_gates(model_gates: np.ndarray, count: int, chosen: int | None) -> np.ndarray:
    """(B, E + count) gates: the model's own effects' (B, E) as they are, then candidate `chosen`
    (0-based) on in every record and the other candidates off (None: all off, the baseline)."""
    model_gates = np.asarray(model_gates, dtype=float).reshape(len(model_gates), -1)
    extra = np.zeros((len(model_gates), count))
    if chosen is not None:
        extra[:, chosen] = 1.0
    return np.concatenate([model_gates, extra], axis=1)


def contact_phases(states: np.ndarray, rig: Rig) -> np.ndarray:
    """Contact phase (`diagnostics.PHASES`: 0 free flight, 1 axial only, 2 radial only, 3 both) of
    states (..., n): radial contact where r > r0, axial where -(z + z0) > 0."""
    radial, _, axial, _ = deformations(rig, states)
    return contact_phase(radial > 0.0, axial > 0.0)


class SampleMeasures(NamedTuple):
    """Per-sample measures of one model on a batch."""

    nll: Array  # (B, L) -2 ln L of the innovation (without constants), 0 where no sample
    k_step_error: Array  # (B, L, 3) m, k-step predicted measurement h(xi) minus the measured (NaN where none)
    states: Array  # (B, L, n) filtered states


def sample_measures(model: Model, noise: FilterNoise, h: float, batch: Batch, k: int) -> SampleMeasures:
    """The innovation NLL, the k-step prediction error and the filtered state of every sample."""
    states, _ = filtered_states(model, noise, h, batch)

    def ahead(record_states: Array, gates: Array) -> Array:
        gated = model._replace(effects=model.effects.with_gates(gates))
        return jax.vmap(lambda xi: measurement(gated, xi))(k_step_predictions(gated, record_states, h, k))

    predicted = jax.vmap(ahead)(states, batch.gates)
    return SampleMeasures(sample_errors(model, noise, h, batch, "nll"), predicted - batch.etas, states)


class Errors(NamedTuple):
    """Mean errors over a set of samples."""

    samples: int
    nll: float  # mean -2 ln L per sample
    k_step_rmse: np.ndarray  # (3,) m, per axis
    #: m^2, the squared k-step errors (summed over the axes) of these samples in each held-out block of the
    #: batch (`training.held_out_blocks`, 0 where the block has none): the same blocks for every fit, so
    #: two fits' sums pair up. Empty when the samples are not held-out ones.
    block_squares: np.ndarray = np.zeros(0)

    @property
    def k_step_norm(self) -> float:
        """m, the norm over the axes of the k-step RMSE."""
        return float(np.linalg.norm(self.k_step_rmse))


def errors_over(measures: SampleMeasures, chosen: np.ndarray, blocks: np.ndarray | None = None) -> Errors:
    """Mean NLL and k-step RMSE over the samples where `chosen` (B, L) is true (NaN where none); with
    `blocks` (`training.held_out_blocks`) also their squared k-step errors per block."""
    nll, k_error = np.asarray(measures.nll), np.asarray(measures.k_step_error)
    rows = np.asarray(chosen, bool)
    k_rows = rows & np.all(np.isfinite(k_error), axis=-1)
    mean_nll = float(np.mean(nll[rows])) if rows.any() else float("nan")
    rmse = np.sqrt(np.mean(k_error[k_rows] ** 2, axis=0)) if k_rows.any() else np.full(3, np.nan)
    squares = np.zeros(0)
    if blocks is not None:
        squares = sums_per_block(np.where(k_rows, np.sum(np.nan_to_num(k_error) ** 2, axis=-1), 0.0), blocks)
    return Errors(int(rows.sum()), mean_nll, rmse, squares)


def held_out_errors(measures: SampleMeasures, batch: Batch, phases: np.ndarray) -> dict[str, Errors]:
    """Errors on the held-out valid samples: "all", and per contact phase (`PHASES`), each with its
    squared k-step errors per held-out block."""
    blocks = held_out_blocks(batch)
    held = blocks >= 0
    out = {"all": errors_over(measures, held, blocks)}
    for index, name in enumerate(PHASES):
        out[name] = errors_over(measures, held & (phases == index), blocks)
    return out


def information_criterion(mean_nll: float, samples: int, parameters: int) -> float:
    """BIC of a fit: samples * mean(-2 ln L) + parameters * ln(samples)."""
    return float(samples * mean_nll + parameters * np.log(samples))


def net_of_noise(rmse: np.ndarray, noise_variance: np.ndarray) -> np.ndarray:
    """m, the model's own part of a k-step prediction RMSE per axis: sqrt(max(rmse^2 - R, 0)) with R (m^2)
    the sensor noise's variance. The prediction uses the samples up to k before the one it is compared
    with, so that sample's white noise adds its variance to the mean square and no model removes it."""
    return np.sqrt(np.maximum(np.asarray(rmse) ** 2 - np.asarray(noise_variance), 0.0))


def fall(before: float, after: float) -> float:
    """Relative fall of an error, 1 - after / before (0.5: halved; negative: it rose)."""
    return float(1.0 - after / before) if before else float("nan")


#: An error this many times the baseline's: the candidate's held-out k-step predictions have left the bearing
#: (its k-step RMSE some hundred times a few um), so they diverge and a percentage tells nothing (a contact
#: exponent of 3.89 in the model: changes of 1e59 % were printed, 2026-12-04).
DIVERGED_ERROR_RATIO = 100.0


def diverges(value: float) -> bool:
    """Whether a relative fall (`fall`) is an error risen to `DIVERGED_ERROR_RATIO` times its baseline's or more."""
    return 1.0 - value >= DIVERGED_ERROR_RATIO


def fall_percent(value: float) -> str:
    """A relative fall (`fall`) as a signed percentage ('+12 %': fell by 12 %), or 'diverges' (`diverges`)."""
    return "diverges" if diverges(value) else f"{100 * value:+.0f} %"


#: The best candidate must lower the held-out k-step error (norm over the axes) by more than this share.
#: Zero: how much an effect lowers it depends on the rig's other model errors (a 1e6 N/m magnetic
#: stiffness on a family rig lowers it 3 %, the rest being the contact law's), not on whether it is
#: real; the criterion and the held-out NLL carry the evidence, the phase rule below the physics.
MIN_K_STEP_FALL = 0.0
#: ... and must not raise it by more than this share in any contact phase: a missing effect, once
#: added, predicts better where it acts and no worse elsewhere; a candidate that trades one phase
#: for another compensates something else (e.g. a contact law's error) with a compromise value.
MAX_PHASE_RISE = 0.1
#: Criterion difference (BIC units) below which two candidates explain about equally
#: (10: "very strong" evidence on Kass and Raftery's scale).
COLLINEAR_MARGIN = 10.0
#: Two-sided significance at which a contact phase's held-out k-step errors tell two collinear candidates
#: apart (a paired t-test over the held-out blocks): a difference of a few points of k-step fall between a
#: constant load and a stiffness in free flight is within the blocks' scatter (soft_bearing, 2026-12-01:
#: 65 against 62 %, swapping a criterion 9.3 in the load's favour).
PHASE_SIGNIFICANCE = 0.05
#: The best candidate's criterion must lie at least this far below the baseline's (BIC units), the
#: same "very strong" evidence that tells two candidates apart: a fall of a few units is what two
#: parameters fitted to the rest of the model's error give (an unmodelled once-per-revolution thrust
#: on lossy_contact with the ring's friction: radial_load at -1.3, named while the bar was 0).
MIN_CRITERION_FALL = COLLINEAR_MARGIN


#: Significance at which a candidate's fits bag by bag disagree (`bag_agreement`): 1 %, as the per-bag standard
#: errors count the sensor noise only and the model's own errors move each bag's fit a little more.
BAG_AGREEMENT_SIGNIFICANCE = 0.01


class BagAgreement(NamedTuple):
    """Whether a candidate's fits bag by bag agree within their errors: sum_b (theta_b - mean)' C_b^-1
    (theta_b - mean), the mean weighted by the C_b^-1 (each bag's posterior covariance of the candidate's
    parameters), chi-square with (the covariances' rank) x (bags - 1) degrees of freedom where the candidate is
    one constant of the rig. Two parameters that act only together (a user's force a k d, or the library's contact
    angle before it read the model's normal force: tan_beta k_radial d) are counted once: the posterior has no
    variance across their product (rank 1)."""

    chi_square: float
    degrees: int
    p: float  # the chance of a chi_square this large where the bags agree
    parameter: str  # the parameter whose values disagree most (by its own marginal chi-square)
    values: tuple[tuple[str, float, float], ...]  # its (bag, value, sd)

    @property
    def disagrees(self) -> bool:
        """Whether the bags disagree at `BAG_AGREEMENT_SIGNIFICANCE`."""
        return self.p < BAG_AGREEMENT_SIGNIFICANCE


def bag_agreement(
    per_bag: Mapping[str, Mapping[str, tuple[float, float]]], covariances: Mapping[str, np.ndarray] | None = None
) -> BagAgreement | None:
    """The agreement of a candidate's fits bag by bag (bag -> parameter -> (value, sd)), with each bag's covariance
    of those parameters (bag -> (p, p), in per_bag's order; default diag(sd^2)); None with fewer than two bags or
    where a value or standard error is not a finite number, or a standard error not positive."""
    bags = list(per_bag)
    if len(bags) < 2:
        return None
    names = list(per_bag[bags[0]])
    values = np.array([[per_bag[b][n][0] for n in names] for b in bags])
    sd = np.array([[per_bag[b][n][1] for n in names] for b in bags])
    if not (np.all(np.isfinite(values)) and np.all(np.isfinite(sd)) and np.all(sd > 0.0)):
        return None
    scale = sd.mean(axis=0)  # the parameters on comparable scales before the inverses
    covariances = covariances if covariances and all(b in covariances for b in bags) else None
    scaled_covariances = [
        (np.asarray(covariances[b]) if covariances else np.diag(sd[i] ** 2)) / np.outer(scale, scale)
        for i, b in enumerate(bags)
    ]
    # a direction the data leave free has no variance in a pinv'd posterior (or a huge one): no weight either way
    precisions = [np.linalg.pinv(c, hermitian=True) for c in scaled_covariances]
    scaled = values / scale
    mean = np.linalg.pinv(sum(precisions), hermitian=True) @ sum(w @ v for w, v in zip(precisions, scaled))
    chi_square = float(sum((v - mean) @ w @ (v - mean) for w, v in zip(precisions, scaled)))
    marginal = np.sum((values - np.average(values, axis=0, weights=sd**-2.0)) ** 2 / sd**2, axis=0)
    worst = names[int(np.argmax(marginal))]
    rank = min(int(np.linalg.matrix_rank(c, hermitian=True)) for c in scaled_covariances)
    degrees = rank * (len(bags) - 1)
    if degrees == 0:
        return None
    rows = tuple((b, float(per_bag[b][worst][0]), float(per_bag[b][worst][1])) for b in bags)
    return BagAgreement(chi_square, degrees, float(scipy.stats.chi2.sf(chi_square, degrees)), worst, rows)


class Judged(NamedTuple):
    """One candidate's fit against the baseline's."""

    name: str
    criterion: float  # BIC difference to the baseline (negative: better)
    nll_fall: float  # held-out mean -2 ln L per sample, baseline minus candidate
    k_step_fall: float  # relative fall of the held-out k-step RMSE (norm over the axes)
    phase_k_step_fall: dict[str, float]  # the same per contact phase (PHASES)
    #: m^2, per contact phase the candidate's squared held-out k-step errors per block (`Errors.block_squares`)
    phase_block_squares: Mapping[str, np.ndarray] = {}
    bags: BagAgreement | None = None  # its fits bag by bag (None: not fitted so, or one bag)


def judge(
    name: str,
    fit: tuple[Errors, dict[str, Errors], int],
    baseline: tuple[Errors, dict[str, Errors], int],
    bags: BagAgreement | None = None,
) -> Judged:
    """A candidate's (fitted errors, held-out errors by phase, free parameters) against the baseline's, with
    the agreement of its fits bag by bag where it was fitted so."""
    fitted, held, parameters = fit
    base_fitted, base_held, base_parameters = baseline
    n = fitted.samples
    criterion = information_criterion(fitted.nll, n, parameters) - information_criterion(
        base_fitted.nll, n, base_parameters
    )
    phases = {
        p: fall(base_held[p].k_step_norm, held[p].k_step_norm)
        for p in PHASES
        if held[p].samples and base_held[p].samples
    }
    return Judged(
        name,
        criterion,
        base_held["all"].nll - held["all"].nll,
        fall(base_held["all"].k_step_norm, held["all"].k_step_norm),
        phases,
        {p: held[p].block_squares for p in phases},
        bags,
    )


class PhaseTest(NamedTuple):
    """Two candidates' held-out k-step errors in one contact phase, paired over the held-out blocks."""

    phase: str
    t: float  # the mean per-block difference of squared errors (second minus first) over its standard error
    needed: float  # |t| at which the difference is significant (`PHASE_SIGNIFICANCE`, Student's t)
    blocks: int  # held-out blocks with samples of the phase

    @property
    def tells(self) -> bool:
        """Whether the phase tells the two apart."""
        return abs(self.t) >= self.needed


def phase_tests(first: Judged, second: Judged, significance: float = PHASE_SIGNIFICANCE) -> list[PhaseTest]:
    """Per contact phase both were measured in, the paired t-test of their squared held-out k-step errors per
    block (positive t: `first` predicts better), clearest first. A phase with fewer than two blocks, or whose
    differences do not scatter, cannot tell."""
    tests = []
    for phase in first.phase_k_step_fall:
        a, b = first.phase_block_squares.get(phase), second.phase_block_squares.get(phase)
        if phase not in second.phase_k_step_fall or a is None or b is None or len(a) != len(b):
            continue
        used = (a > 0.0) | (b > 0.0)
        differences = (b - a)[used]
        n = len(differences)
        scatter = float(np.std(differences, ddof=1)) if n > 1 else 0.0
        t = float(np.sqrt(n) * np.mean(differences) / scatter) if scatter > 0.0 else 0.0
        needed = float(scipy.stats.t.ppf(1.0 - significance / 2.0, n - 1)) if n > 1 else float("inf")
        tests.append(PhaseTest(phase, t, needed, n))
    return sorted(tests, key=lambda test: -abs(test.t))


def by_criterion(judged: Sequence[Judged]) -> list[Judged]:
    """Lowest criterion first; one that is not a number (a fit whose filter diverged) last."""
    return sorted(judged, key=lambda j: (not math.isfinite(j.criterion), j.criterion))


def verdict(
    judged: Sequence[Judged],
    min_fall: float = MIN_K_STEP_FALL,
    max_rise: float = MAX_PHASE_RISE,
    margin: float = COLLINEAR_MARGIN,
    min_criterion_fall: float = MIN_CRITERION_FALL,
) -> dict:
    """The missing effect: the candidate with the lowest criterion if it beats the baseline (by at least
    `min_criterion_fall`) and its held-out errors fall clearly (NLL lower, k-step lower by `min_fall`
    and in no contact phase higher by more than `max_rise`); else unexplained. When the runner-up is
    within `margin` of it, the two are named collinear and the contact phase where their held-out
    k-step errors differ most clearly over the held-out blocks decides between them if they differ
    significantly there (`phase_tests`; e.g. free flight, where a constant load acts and a contact
    effect does not); else the criterion's order stands. A candidate of lower criterion that fails the
    held-out tests, or whose fits bag by bag disagree (`BagAgreement.disagrees`), does not hide one that
    passes them: it fits the bags by compensating something else, and is named beside the verdict."""
    order = by_criterion(judged)
    if not order:
        return {"explained": False, "best": None, "margin_to_second": float("nan"), "collinear": None,
                "text": "unexplained: no candidate was fitted"}
    passing = [j for j in order if refusal(j, min_fall, max_rise, min_criterion_fall) is None]
    if passing and passing[0] is not order[0]:
        best = passing[0]
        refused = [j for j in order if j.criterion < best.criterion]
        margin_to_second = passing[1].criterion - best.criterion if len(passing) > 1 else float("nan")
        text = (
            f"missing effect: {best.name} (criterion {best.criterion:+.1f} vs none; "
            f"held-out k-step error -{100 * best.k_step_fall:.0f} %, NLL -{best.nll_fall:.3f} per sample); "
            + "; ".join(
                f"{j.name} fits the bags more closely (criterion {j.criterion:+.1f}) but "
                f"{refusal(j, min_fall, max_rise, min_criterion_fall)}: it compensates something else"
                for j in refused
            )
        )
        return {"explained": True, "best": best.name, "margin_to_second": margin_to_second, "collinear": None,
                "refused": [j.name for j in refused], "text": text}
    margin_to_second = order[1].criterion - order[0].criterion if len(order) > 1 else float("nan")
    collinear = None
    if margin_to_second < margin:
        first, second = order[:2]
        clearest = next(iter(phase_tests(first, second)), None)
        told_apart = clearest is not None and clearest.tells
        if told_apart and clearest.t < 0.0:
            order[:2] = [second, first]
        phase = clearest.phase if clearest else None
        collinear = {
            "candidates": [order[0].name, order[1].name],
            "criterion_margin": margin_to_second,
            "phase": phase,
            "told_apart": told_apart,
            "t": abs(clearest.t) if clearest else float("nan"),
            "t_needed": clearest.needed if clearest else float("nan"),
            "blocks": clearest.blocks if clearest else 0,
            "k_step_fall": {j.name: j.phase_k_step_fall[phase] for j in order[:2]} if phase else {},
        }
    best = order[0]
    why_not = refusal(best, min_fall, max_rise, min_criterion_fall)
    explained = why_not is None
    if explained:
        ahead = "" if collinear else f", the next {margin_to_second:.1f} behind"
        text = (
            f"missing effect: {best.name} (criterion {best.criterion:+.1f} vs none{ahead}; "
            f"held-out k-step error -{100 * best.k_step_fall:.0f} %, NLL -{best.nll_fall:.3f} per sample)"
        )
    else:
        text = (
            f"unexplained: the best fitted candidate ({best.name}, criterion {best.criterion:+.1f}): {why_not}; "
            "see the residual's signature"
        )
    if collinear:
        falls = " vs ".join(f"{100 * v:.0f} % ({n})" for n, v in collinear["k_step_fall"].items())
        text += (
            f"; {collinear['candidates'][1]} explains about as well "
            f"(criterion margin {collinear['criterion_margin']:.1f}), "
        )
        if collinear["told_apart"]:
            text += (
                f"told apart in {collinear['phase']}, where the held-out k-step error falls {falls} "
                f"(t = {collinear['t']:.1f} over {collinear['blocks']} held-out blocks)"
            )
        elif collinear["phase"]:
            text += (
                f"not told apart by any contact phase (the clearest, {collinear['phase']}: the held-out k-step "
                f"error falls {falls}, t = {collinear['t']:.1f} over {collinear['blocks']} held-out blocks, "
                f"{collinear['t_needed']:.1f} needed): the criterion's order stands"
            )
        else:
            text += "not told apart by any contact phase (no held-out blocks to compare): the criterion's order stands"
    return {
        "explained": bool(explained),
        "best": best.name,
        "margin_to_second": margin_to_second,
        "collinear": collinear,
        "refused": [],
        "text": text,
    }


def refusal(
    candidate: Judged,
    min_fall: float = MIN_K_STEP_FALL,
    max_rise: float = MAX_PHASE_RISE,
    min_criterion_fall: float = MIN_CRITERION_FALL,
    bags: bool = True,
) -> str | None:
    """Why a candidate is not the missing effect (None: it is one): its criterion does not beat the
    baseline's by `min_criterion_fall`, its held-out NLL or k-step error does not fall, it raises
    the k-step error in a contact phase by more than `max_rise`, or (with `bags`) its fits bag by bag
    disagree (`BagAgreement.disagrees`)."""
    falls = candidate.phase_k_step_fall
    worst_phase = min(falls, key=falls.get, default=None)
    worst_fall = falls[worst_phase] if worst_phase else 0.0
    if diverges(worst_fall):
        return f"its held-out k-step predictions diverge in {worst_phase} ({1.0 - worst_fall:.2g} times the error)"
    if worst_fall < -max_rise:
        return (
            f"it raises the held-out k-step error in {worst_phase} by {-100 * worst_fall:.0f} % "
            "(it trades one phase for another)"
        )
    if bags and candidate.bags is not None and candidate.bags.disagrees:
        agreement = candidate.bags
        values = ", ".join(f"{value:.4g} +- {sd:.2g} on {bag}" for bag, value, sd in agreement.values)
        return (
            f"its fits bag by bag disagree ({agreement.parameter} {values}; chi-square {agreement.chi_square:.1f} "
            f"on {agreement.degrees}, p = {agreement.p:.2g}): it fits something that differs from drop to drop, "
            "not a constant of the rig"
        )
    failed = []
    if candidate.criterion > -min_criterion_fall:
        failed.append(f"its criterion does not fall by {min_criterion_fall:g} ({candidate.criterion:+.1f})")
    if candidate.nll_fall <= 0.0:
        failed.append(f"its held-out NLL does not fall ({-candidate.nll_fall:+.4f} per sample)")
    if diverges(candidate.k_step_fall):
        failed.append(f"its held-out k-step predictions diverge ({1.0 - candidate.k_step_fall:.2g} times the error)")
    elif candidate.k_step_fall <= min_fall:
        failed.append(
            f"it changes the held-out k-step error by {-100 * candidate.k_step_fall:+.0f} % (it must fall by more "
            f"than {100 * min_fall:.0f} %)"
        )
    return "; ".join(failed) or None
