"""Which effect is missing: orthogonal forward regression (Billings' FROLS) of the missing force on
candidate regressor blocks (one block per candidate effect, `regressors`), after the terms the model
can already adjust (forced first: the PKBKR coefficients' regressors), ranked by error-reduction
ratio, with the fitted parameters and their standard errors; the first-pass verdict."""
from __future__ import annotations

from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

from touchdown_ros.core.diagnostics.regressors import linearisation_offset
from touchdown_ros.core.diagnostics.residuals import effective_samples
from touchdown_ros.core.effects import Effect


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


class RecordRegressors(NamedTuple):
    """One record's missing force and the regressors along its smoothed states."""

    force: np.ndarray  # (N, 3) N, the missing force
    force_std: np.ndarray  # (N, 3) N, its standard deviation
    coefficients: np.ndarray  # (N, 3, q) d (model force) / d (PKBKR coefficients), `coefficient_regressors`
    effects: Mapping[str, tuple[np.ndarray, np.ndarray]]  # name -> (J (N, 3, p), f0 (N, 3)), `effect_regressors`


def rank_effects(
    records: Sequence[RecordRegressors],
    library: Mapping[str, Effect],
    at: Mapping[str, Mapping[str, float]] | None = None,
) -> Ranking:
    """`frols` of the missing force of all records on the candidates of `library` (in its order), each
    record a group, the rows weighted by the missing force's certainty (1 / its standard deviation);
    each candidate's linear coefficients offset to physical values at its defaults, or where `at` puts it
    (the point its regressors were linearised at)."""
    ys, forced, groups, blocks = [], [], [], {name: [] for name in library}
    for g, record in enumerate(records):
        n = len(record.force)
        weight = 1.0 / np.maximum(record.force_std, 1e-9)  # rows weighted by the estimate's certainty
        ys.append((record.force * weight).reshape(-1))
        groups.append(np.full(3 * n, g))
        forced.append((record.coefficients * weight[..., None]).reshape(3 * n, -1))
        for name in library:
            J = record.effects[name][0]
            blocks[name].append((J * weight[..., None]).reshape(3 * n, -1))
    offsets = {}
    for name, effect in library.items():
        p0 = np.array(list({**effect.defaults(), **(at or {}).get(name, {})}.values()))
        J = np.concatenate([record.effects[name][0] for record in records])
        f0 = np.concatenate([record.effects[name][1] for record in records])
        offsets[name] = linearisation_offset(J, f0, p0)
    return frols(
        np.concatenate(ys),
        {name: np.concatenate(v) for name, v in blocks.items()},
        np.concatenate(forced),
        offsets,
        np.concatenate(groups),
    )


def ranking_rows(ranking: Ranking, library: Mapping[str, Effect], groups: Sequence[str]) -> list[dict]:
    """The ranking's candidates as plain data (diagnosis.json `verdict.candidates`): rank, ERR and each
    parameter's value, standard error, 95 % interval, unit and the values per group (bag name)."""
    rows = []
    for rank, c in enumerate(ranking.candidates, start=1):
        names = list(library[c.name].parameters)
        rows.append(
            {
                "rank": rank,
                "candidate": c.name,
                "err_percent": 100.0 * c.err,
                "parameters": {
                    p: {
                        "value": float(c.values[j]),
                        "std": float(c.std[j]),
                        "ci95": [float(c.values[j] - 1.96 * c.std[j]), float(c.values[j] + 1.96 * c.std[j])],
                        "unit": library[c.name].parameters[p][1],
                        "per_bag": {name: float(c.group_values[g, j]) for g, name in enumerate(groups)},
                        "per_bag_std": {name: float(c.group_std[g, j]) for g, name in enumerate(groups)},
                    }
                    for j, p in enumerate(names)
                },
            }
        )
    return rows


def frols_verdict(ranking: Ranking, rows: list[dict], threshold: float) -> dict[str, Any]:
    """FROLS's verdict: the best candidate explains the missing force when its ERR reaches
    `threshold` (a share); with the greedy order and the rows (`ranking_rows`)."""
    best = rows[0]
    explained = best["err_percent"] >= 100.0 * threshold
    return {
        "explained": bool(explained),
        "best": best["candidate"],
        "best_err_percent": best["err_percent"],
        "threshold_percent": 100.0 * threshold,
        "forced_err_percent": 100.0 * ranking.forced_err,
        "order": [{"candidate": n, "err_percent": 100 * e, "cumulative_percent": 100 * c} for n, e, c in ranking.order],
        "candidates": rows,
        "text": (
            f"missing effect: {best['candidate']} explains {best['err_percent']:.1f} % of the missing force "
            f"the model's own coefficients cannot absorb"
            if explained
            else f"unexplained: the best candidate ({best['candidate']}) explains only {best['err_percent']:.1f} % "
            f"(< {100 * threshold:.0f} %) of the missing force; see its signature"
        ),
    }
