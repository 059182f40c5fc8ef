"""Minimising a training loss: L-BFGS with progress and a record of how it stopped."""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import scipy.optimize

from touchdown_ros.workflows.progress import STDERR


@dataclass(frozen=True)
class Convergence:
    """How one minimisation ended."""

    converged: bool
    reason: str  # the optimiser's own words
    steps: int
    initial_loss: float
    final_loss: float
    seconds: float
    history: tuple[float, ...] = ()
    kept_step: int | None = None  # the step returned, when a held-out loss chose it
    held_out: tuple[float, ...] = ()  # held-out loss at step 0, 1, ...
    evaluations: int = 0  # loss evaluations, the line searches' trial points included (0: not counted)

    @property
    def diverged(self) -> bool:
        """Whether the filter diverged wherever the minimisation went: no finite loss to end at."""
        return self.final_loss >= DIVERGED_LOSS

    def then(self, after: Convergence, reason: str) -> Convergence:
        """One fit from this run and the run that went on after it (from where this one ended or from a restart):
        the steps, evaluations, seconds and loss histories of both, the loss from this run's start, `after`'s end."""
        return dataclasses.replace(
            after, reason=reason, steps=self.steps + after.steps, initial_loss=self.initial_loss,
            seconds=self.seconds + after.seconds, history=self.history + after.history,
            evaluations=self.evaluations + after.evaluations,
        )

    def as_dict(self) -> dict[str, Any]:
        record = {
            "converged": self.converged,
            "reason": self.reason,
            "steps": self.steps,
            "initial_loss": self.initial_loss,
            "final_loss": self.final_loss,
            "seconds": round(self.seconds, 2),
        }
        if self.evaluations:
            record["evaluations"] = self.evaluations
        if self.kept_step is not None:
            record.update(kept_step=self.kept_step, held_out_initial=self.held_out[0],
                          held_out_kept=self.held_out[self.kept_step])
        record.update(self.histories())
        return record

    def histories(self) -> dict[str, list[float]]:
        """The loss at step 0, 1, ... (`loss_history`) and the held-out loss (`held_out_history`), where recorded:
        what `touchdown report` draws."""
        record = {}
        if self.history:
            record["loss_history"] = [float(self.initial_loss), *map(float, self.history)]
        if self.held_out:
            record["held_out_history"] = [float(v) for v in self.held_out]
        return record


class TrainingError(ValueError):
    """Training cannot give a trustworthy coefficient file from these bags and settings."""


class DivergedError(TrainingError):
    """The filter diverges from the starting guess on a bag."""


class NotConvergedError(TrainingError):
    """A training stage reached its step cap before converging."""


def require_convergence(convergence: Convergence, stage: str, paths: Sequence[Path], knob: str) -> None:
    if not convergence.converged:
        raise NotConvergedError(
            f"{', '.join(map(str, paths))}: {stage} did not converge in {convergence.steps} steps "
            f"({convergence.reason}); allow more with {knob}, or check that these bags are drops of this rig"
        )


#: Loss reported for a trial point where the filter diverged (the optimiser steps back from it).
DIVERGED_LOSS = 1.0e30
#: `gauss_newton` goes on along a step that lowered the loss as predicted up to this many times its length.
MAX_EXTENSION = 16.0
#: A kept step whose loss fell by at least this share of its predicted fall agreed with the Gauss-Newton model
#: (the usual bar of a successful trust-region step); a smaller fall below the tolerance is a stall, not convergence.
GOOD_AGREEMENT = 0.25
#: Kept steps in a row damped at or above the curvature's own diagonal: the Gauss-Newton model is not trusted
#: where it points, and the steps creep (a misfitted model's Fisher information is not its loss's curvature).
STALL_STEPS = 10


def minimise(
    value_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
    theta0: np.ndarray,
    max_steps: int,
    tolerance: float,
    label: str,
    stream=STDERR,
    describe: Callable[[np.ndarray], str] = lambda theta: "",
    on_step: Callable[[int, float, np.ndarray], None] | None = None,
    patience: int = 0,
    bounds: Sequence[tuple[float, float]] | None = None,
    restarts: int = 0,
) -> tuple[np.ndarray, Convergence]:
    """L-BFGS-B from theta0 (within `bounds`, (low, high) per coordinate, if given) until the loss
    changes by less than `tolerance` (relative) or the projected gradient is below it, at most
    `max_steps` iterations; progress on `stream`. Stopped by the loss's change, it starts again from
    where it stopped (its curvature memory cleared) up to `restarts` times, while a restart lowers
    the loss by more than `tolerance` (relative): on a rough loss one short step can stop it early.

    `value_and_grad` may return a third value, a held-out loss at theta (data not in the loss).
    Then the step with the lowest held-out loss is returned (step 0, the start, included), and
    the minimisation also stops, converged, when it has not fallen for `patience` steps
    (early stopping: the fit no longer generalises). A non-finite loss (the filter diverged at a
    trial point) counts as a very high one, so the line search steps back instead of stopping.
    """
    start = time.perf_counter()
    history: list[float] = []
    held_out: list[float] = []
    best: dict[str, Any] = {}
    last: dict[bytes, tuple] = {}  # L-BFGS asks again for the point it starts from
    evaluations = 0

    def evaluate(theta: np.ndarray) -> tuple:
        nonlocal evaluations
        key = theta.tobytes()
        if key not in last:
            evaluations += 1
            value, grad, *monitored = value_and_grad(theta)
            if not (np.isfinite(value) and np.all(np.isfinite(grad))):
                value, grad, monitored = DIVERGED_LOSS, np.zeros_like(theta), [np.inf] * len(monitored)
            last.clear()
            last[key] = (float(value), np.asarray(grad, dtype=float), *map(float, monitored))
        return last[key]

    def fun(theta: np.ndarray) -> tuple[float, np.ndarray]:
        return evaluate(theta)[:2]

    def watch(step: int, theta: np.ndarray) -> str:
        """Record the held-out loss of this step; stop when it has not fallen for `patience` steps."""
        monitored = evaluate(theta)[2:]
        if not monitored:
            return ""
        held_out.append(monitored[0])
        if not best or monitored[0] < best["loss"]:
            best.update(loss=monitored[0], step=step, theta=np.array(theta))
        elif patience and step - best["step"] >= patience:
            best["stopped"] = True
            raise StopIteration
        return f"  held-out {monitored[0]:.7g}"

    def callback(intermediate_result) -> None:
        history.append(float(intermediate_result.fun))
        step = len(history)
        elapsed = time.perf_counter() - start
        held = watch(step, intermediate_result.x) if held_out else ""
        print(
            f"[{label} step {step}/<={max_steps}] loss {intermediate_result.fun:.7g}{held}"
            f"{describe(intermediate_result.x)}  "
            f"{elapsed:.1f} s elapsed",
            file=stream,
            flush=True,
        )
        if on_step is not None:
            on_step(step, float(intermediate_result.fun), intermediate_result.x)

    theta0 = np.asarray(theta0, dtype=float)
    if bounds is not None:
        theta0 = np.clip(theta0, *np.asarray(bounds, dtype=float).T)
    initial_loss = fun(theta0)[0]
    watch(0, theta0)
    print(
        f"[{label} step 0] loss {initial_loss:.7g} (compiled in {time.perf_counter() - start:.1f} s)",
        file=stream,
        flush=True,
    )
    if max_steps == 0:
        return theta0, Convergence(
            False, "no steps asked for", 0, initial_loss, initial_loss, time.perf_counter() - start,
            evaluations=evaluations,
        )

    def run(theta: np.ndarray, steps: int):
        return scipy.optimize.minimize(
            fun,
            theta,
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            callback=callback,
            options={"maxiter": steps, "ftol": tolerance, "gtol": tolerance, "maxls": 40},
        )

    result = run(theta0, max_steps)
    for _ in range(restarts):
        if "REDUCTION OF F" not in str(result.message) or len(history) >= max_steps or best.get("stopped"):
            break
        stopped = float(result.fun)
        again = run(np.asarray(result.x), max_steps - len(history))
        if again.fun < result.fun:
            result = again
        if stopped - float(result.fun) <= tolerance * max(abs(stopped), 1.0):
            break
        print(f"[{label}] restarted where the loss's change stopped it: {stopped:.7g} -> {float(result.fun):.7g}",
              file=stream, flush=True)
    reason = str(result.message)
    converged = bool(result.success) and result.fun < DIVERGED_LOSS
    recent = np.asarray(history[-4:])
    if not converged and "ABNORMAL" in reason and len(recent) == 4:
        change = np.max(np.abs(np.diff(recent))) / max(abs(recent[-1]), 1.0)
        if change < 10.0 * tolerance:
            converged = True
            reason += (
                f" (the line search found no lower loss; the last steps changed it by {change:.1e}: at its noise floor)"
            )
    theta, final_loss, kept_step = np.asarray(result.x), float(result.fun), None
    if best:
        if best.get("stopped"):
            converged = True
            reason = f"the held-out loss did not fall for {patience} steps after step {best['step']}"
        theta, kept_step = best["theta"], best["step"]
        final_loss = history[kept_step - 1] if kept_step else initial_loss
        reason += f"; kept step {kept_step}, the lowest held-out loss"
    steps = len(history)
    convergence = Convergence(
        converged,
        reason,
        steps,
        initial_loss,
        final_loss,
        time.perf_counter() - start,
        tuple(history),
        kept_step,
        tuple(held_out),
        evaluations,
    )
    print(
        f"[{label}] {'converged' if converged else 'NOT converged'} after {steps} steps ({evaluations} loss "
        f"evaluations): {reason}",
        file=stream,
        flush=True,
    )
    return theta, convergence


def minimise_from_each(
    value_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
    starts: Sequence[tuple[str, np.ndarray]],
    max_steps: int,
    tolerance: float,
    label: str,
    stream=STDERR,
    bounds: Sequence[tuple[float, float]] | None = None,
) -> tuple[np.ndarray, Convergence]:
    """`minimise` from each of `starts` (label, theta0; the first the fit's own start, the others further ones
    such as `core.calibration.fit_starts`'): the lowest end, saying so where a further start gave it; the own
    start's where the others end lower by no more than `tolerance` (relative), which stops a fit too."""
    ends = [
        (*minimise(value_and_grad, theta0, max_steps, tolerance, label + where, stream, bounds=bounds), where)
        for where, theta0 in starts
    ]
    own = ends[0][1].final_loss
    x, convergence, where = min(ends, key=lambda end: end[1].final_loss)
    if own - convergence.final_loss <= tolerance * max(abs(own), 1.0):
        x, convergence, where = ends[0]
    if where != starts[0][0]:
        print(f"[{label}] kept the start{where}: loss {convergence.final_loss:.7g} against "
              f"{ends[0][1].final_loss:.7g} from its own", file=stream, flush=True)
    return x, convergence


def gauss_newton(
    terms: Callable[[np.ndarray], tuple[float, np.ndarray, np.ndarray]],
    value: Callable[[np.ndarray], float],
    theta0: np.ndarray,
    max_steps: int,
    tolerance: float,
    label: str,
    stream=STDERR,
    describe: Callable[[np.ndarray], str] = lambda theta: "",
    bounds: Sequence[tuple[float, float]] | None = None,
    fallback: Callable[[np.ndarray, int], tuple[np.ndarray, Convergence]] | None = None,
) -> tuple[np.ndarray, Convergence]:
    """Levenberg-Marquardt from theta0 on a loss whose `terms(theta)` are (loss, gradient, Gauss-Newton
    Hessian) and `value(theta)` the loss alone (the trial points): the step solves (H + mu diag H) d = -g,
    coordinates at a bound that the gradient pushes outward held; a step is kept when it lowers the loss,
    mu then falling by the agreement of the actual and the predicted fall (Nielsen's rule), else mu grows.
    Converged when a kept step lowers the loss by at most `tolerance` (relative, as `minimise`'s) or the
    undamped step's predicted fall is below it; at most `max_steps` kept steps. A trial point whose terms are
    not finite (the filter's tangents diverge where its loss does not) is not kept. Near a minimum of a
    likelihood the Gauss-Newton Hessian is the curvature, so it takes fewer steps than L-BFGS (on the campaign
    22 against 35, each a forward pass with one tangent per coordinate) and does not stop short on a flat
    stretch as L-BFGS's relative-reduction test does (docs/calibration.md, "Stage 1 refined by Gauss-Newton").
    Where the Gauss-Newton model fails instead (a kept step's fall below the tolerance and far below its prediction,
    `STALL_STEPS` damped steps in a row, or no lower loss along the damped steps short of the noise floor),
    `fallback(theta, steps left)` (L-BFGS, say) goes on from there, and the convergence is both runs'."""
    start = time.perf_counter()
    low, high = (np.full(len(theta0), -np.inf), np.full(len(theta0), np.inf)) if bounds is None else (
        np.asarray(bounds, dtype=float).T
    )
    theta = np.clip(np.asarray(theta0, dtype=float), low, high)
    evaluations = 0

    def finite_terms(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        nonlocal evaluations
        evaluations += 1
        f, g, H = terms(x)
        if not (np.isfinite(f) and np.all(np.isfinite(g)) and np.all(np.isfinite(H))):
            return DIVERGED_LOSS, np.zeros_like(x), np.zeros((len(x), len(x)))
        return float(f), np.asarray(g, dtype=float), 0.5 * (np.asarray(H, dtype=float) + np.asarray(H).T)

    loss, gradient, hessian = finite_terms(theta)
    initial_loss = loss
    print(f"[{label} step 0] loss {loss:.7g} (compiled in {time.perf_counter() - start:.1f} s)", file=stream,
          flush=True)
    history: list[float] = []
    mu, growth, converged, reason = 1.0e-3, 2.0, False, f"reached {max_steps} steps"
    stalled, damped = False, 0
    if loss >= DIVERGED_LOSS:
        max_steps, reason = 0, "the loss is not finite at the start (the filter diverges)"
    elif max_steps == 0:
        reason = "no steps asked for"

    def direction(mu: float) -> np.ndarray:
        """The step of damping mu (zero along the coordinates held at a bound)."""
        held = ((theta <= low) & (gradient > 0)) | ((theta >= high) & (gradient < 0))
        free = ~held
        block = hessian[np.ix_(free, free)]
        scale = np.maximum(np.diag(block), 1e-12 * max(np.max(np.abs(np.diag(block)), initial=0.0), 1e-300))
        d = np.zeros_like(theta)
        d[free] = np.linalg.lstsq(block + mu * np.diag(scale), -gradient[free], rcond=None)[0]
        return d

    def predicted_fall(trial: np.ndarray) -> float:
        moved = trial - theta
        return -(gradient @ moved + 0.5 * moved @ hessian @ moved)

    def loss_at(x: np.ndarray) -> float:
        nonlocal evaluations
        evaluations += 1
        got = value(x)
        return float(got) if np.isfinite(got) else DIVERGED_LOSS

    while len(history) < max_steps:
        if predicted_fall(np.clip(theta + direction(0.0), low, high)) <= tolerance * max(abs(loss), 1.0):
            converged, reason = True, "the undamped step's predicted fall of the loss is below the tolerance"
            break
        d = direction(mu)
        trial = np.clip(theta + d, low, high)
        predicted, trial_loss = predicted_fall(trial), loss_at(trial)
        if predicted > 0 and trial_loss < loss:
            agreement = (loss - trial_loss) / predicted
            # Where the loss falls as predicted or more, the curvature may be overstated (a misfitted model's
            # Fisher information can exceed the Hessian): go on along the step while the loss keeps falling.
            length = 1.0
            while agreement > 0.75 and length < MAX_EXTENSION:
                longer = np.clip(theta + 2.0 * length * d, low, high)
                longer_loss = loss_at(longer)
                if not longer_loss < trial_loss:
                    break
                trial, trial_loss, length = longer, longer_loss, 2.0 * length
            new_terms = finite_terms(trial)
            if new_terms[0] < DIVERGED_LOSS:
                mu, growth = mu * max(1.0 / 3.0, 1.0 - (2.0 * agreement - 1.0) ** 3), 2.0
                before, theta = loss, trial
                loss, gradient, hessian = new_terms
                history.append(loss)
                print(f"[{label} step {len(history)}/<={max_steps}] loss {loss:.7g}{describe(theta)}  "
                      f"(step x{length:g}, fall/predicted {agreement:.2f}, damping {mu:.1e})  "
                      f"{time.perf_counter() - start:.1f} s elapsed", file=stream, flush=True)
                if before - loss <= tolerance * max(abs(before), abs(loss), 1.0):
                    if agreement >= GOOD_AGREEMENT or fallback is None:
                        converged, reason = True, "a kept step lowered the loss by less than the tolerance (relative)"
                    else:
                        stalled, reason = True, (f"a kept step lowered the loss by less than the tolerance, "
                                                 f"{agreement:.2f} of its predicted fall")
                    break
                damped = damped + 1 if mu >= 1.0 else 0
                if damped >= STALL_STEPS and fallback is not None:
                    stalled, reason = True, f"{STALL_STEPS} kept steps in a row damped at or above the curvature"
                    break
                continue
        mu, growth = mu * growth, growth * 2.0
        if mu > 1.0e12:
            recent = np.asarray([initial_loss, *history][-4:])
            change = np.max(np.abs(np.diff(recent))) / max(abs(recent[-1]), 1.0) if len(recent) > 1 else np.inf
            converged = change < 10.0 * tolerance
            stalled = not converged and fallback is not None
            reason = (f"no lower loss along the damped steps; the last steps changed it by {change:.1e}"
                      + (": at its noise floor" if converged else ""))
            break
    steps = len(history)
    if stalled and steps < max_steps:
        print(f"[{label}] Gauss-Newton stalled after {steps} steps ({reason}): L-BFGS goes on from there",
              file=stream, flush=True)
        before = Convergence(False, reason, steps, initial_loss, loss, time.perf_counter() - start, tuple(history),
                             evaluations=evaluations)
        theta, after = fallback(theta, max_steps - steps)
        return theta, before.then(
            after,
            f"{after.reason}; L-BFGS's {after.steps} steps after {steps} of Gauss-Newton, which stalled ({reason})",
        )
    convergence = Convergence(converged, reason, steps, initial_loss, loss, time.perf_counter() - start, tuple(history),
                              evaluations=evaluations)
    print(f"[{label}] {'converged' if converged else 'NOT converged'} after {steps} steps ({evaluations} loss "
          f"evaluations): {reason}", file=stream, flush=True)
    return theta, convergence
