"""The one spectral projected gradient loop (Birgin, Martinez & Raydan 2000), in budget units.

Every first-order method maximizes with it: the generic hypergradient (on the negated reduced objective, with or
without an exact block) and the structured attacks. A value
callback may return -inf for a point it cannot evaluate (e.g. the lower level is infeasible there), and the direction
callback may raise RankDeficientRegressor at a point where the lower level has no unique solution (its derivative does
not exist); the line search then backtracks. batched_box_ascent climbs many starts at once where values and gradients
come in batches (one stacked evaluation per step).
"""

from __future__ import annotations

from typing import Any, Callable, Literal

import numpy as np

from ...defaults import param
from ...errors import RankDeficientRegressor


def budget_direction(g: np.ndarray, radius: float, order: float) -> np.ndarray:
    """Gradient rescaled so a unit step moves about one budget radius."""
    norm = np.linalg.norm(g, order)
    return g * (radius / norm) if norm > 0 and radius > 0 else np.zeros_like(g)


def projected_ascent(f: Callable[[np.ndarray], tuple[float, Any]],
                     direction: Callable[[Any], tuple[np.ndarray, np.ndarray]],
                     project: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, scale: float | np.ndarray,
                     max_iter: int, tol: float, history: list[dict[str, float]], step0: float = 1.0,
                     stop: Callable[[Any], bool] | None = None,
                     bb: Literal["short", "long"] = "short", at: Callable[[Any], np.ndarray] | None = None,
                     why: dict[str, str] | None = None,
                     min_step: float = 1e-8) -> tuple[np.ndarray, float, Any, int, int, bool]:
    """Monotone spectral projected gradient ascent (Birgin, Martinez & Raydan 2000) in budget units z = x / scale.

    direction(aux) returns (gradient, first direction): the first step is step0 * that direction (about one budget
    radius), later ones P(x + lam * alpha * scale^2 * g) with alpha a Barzilai-Borwein length in z (bb: "short" s'y/y'y,
    suits smooth ball-constrained ascents; "long" s's/s'y, Birgin et al.'s choice, reaches the vertices of a box in
    fewer steps; it grows the last step 4x where the ascent sees no negative curvature), and lam halved until an Armijo
    increase (the line search fails below lam = min_step). Stops when the relative gain over the last
    `defaults["ascent.window"]` accepted steps is below tol, or no step is accepted, or the projection holds x still, or
    stop(aux) holds at the start or at an accepted point (the caller's goal). at(aux), if given, is where f actually
    evaluated (a callback that moves an unevaluable point, e.g. into the lower level's domain); why, if given, receives
    the reason under "stop": "window", "line search", "stationary", "stop", "zero step", "max_iter" or "start" (f is
    -inf without a point at the start), and under "singular" the message of the last trial point of the last line
    search at which direction raised RankDeficientRegressor (a trial point that fails, as one f cannot evaluate; at
    the start it propagates). Returns x, f, aux, iterations, evaluations, converged.
    """
    why = {} if why is None else why
    x = project(x0)
    fx, aux = f(x)
    if fx == -np.inf and aux is None:  # the start cannot be evaluated: nothing to climb from
        why["stop"] = "start"
        return x, fx, aux, 0, 1, False
    if at is not None:
        x = at(aux)
    if stop is not None and stop(aux):
        why["stop"] = "stop"
        return x, fx, aux, 0, 1, True
    g, d = direction(aux)
    metric = np.broadcast_to(np.asarray(scale, dtype=float) ** 2, x.shape)
    evals, converged, it = 1, False, 0
    alpha = None  # BB length; None: use the first direction
    why["stop"] = "max_iter"
    for it in range(1, max_iter + 1):
        move = d if alpha is None else alpha * (metric * g)
        if not np.any(move):
            converged, why["stop"] = True, "zero step"
            break
        lam = step0 if alpha is None else 1.0
        why.pop("singular", None)
        while True:
            xn = project(x + lam * move)
            if np.array_equal(xn, x):  # the projection holds x still: stationary on the feasible set
                converged, why["stop"] = True, "stationary"
                break
            fn, auxn = f(xn)
            evals += 1
            if at is not None and np.isfinite(fn):
                xn = at(auxn)
            if fn >= fx + param("ascent.armijo") * float(g @ (xn - x)) and fn >= fx:
                try:
                    gn, dn = direction(auxn)
                    break
                except RankDeficientRegressor as exc:  # no derivative there: the trial point fails
                    why["singular"] = str(exc)
            lam *= 0.5
            if lam < min_step:
                converged, why["stop"] = True, "line search"
                break
        if converged:
            break
        if stop is not None and stop(auxn):
            history.append({"iter": it, "value": fn, "step": lam})
            why["stop"] = "stop"
            return xn, fn, auxn, it, evals, True
        s, y = xn - x, gn - g
        curvature, yy = -float(s @ y), float(y @ (metric * y))  # the ascent's curvature along s, ||y||^2 in z
        if bb == "long":
            ss = float(s @ np.divide(s, metric, out=np.zeros_like(s), where=metric > 0))
            rise = float(s @ g)  # ss / rise: the length of the step just taken
            alpha = ss / curvature if curvature > 0 else (4.0 * ss / rise if rise > 0 else None)
        else:
            alpha = curvature / yy if curvature > 0 and yy > 0 else None
        x, fx, aux, g, d = xn, fn, auxn, gn, dn
        history.append({"iter": it, "value": fx, "step": lam})
        if it >= param("ascent.window") and fx - history[-param("ascent.window")]["value"] <= tol * max(abs(fx), 1e-12):
            converged, why["stop"] = True, "window"
            break
    return x, fx, aux, it, evals, converged


def batched_box_ascent(values: Callable[..., tuple[np.ndarray, np.ndarray]], bound: np.ndarray,
                       starts: np.ndarray, max_iter: int, min_step: float = 1e-6, indexed: bool = False,
                       counts: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Maximize f over the box |x| <= bound from every row of `starts` at once, values(X) giving f and its gradient
    at the rows of X: per start, a step along the gradient scaled to the box (t in budget units along its largest
    entry), kept where f grows (t doubled, at most 2), else halved; a start stops below min_step, or where the
    projection holds it still (every shorter step would too: stationary on the box). Returns each start's best x
    and f, the iterations and the evaluations. bound: one for every row (n,) or one per row (rows x n). indexed:
    values(X, rows) also gets the rows of `starts` that X holds (several problems' starts climbing together, each
    row its own); counts, if given, receives per row "last" (the last iteration it was live, 0 if none) and
    "evaluations" (its points evaluated): a row's climb does not depend on the others', so a group of rows gets the
    iterations and evaluations it would have alone (group_counts)."""
    bound = np.asarray(bound, dtype=float)
    x = np.clip(np.asarray(starts, dtype=float), -bound, bound)
    every = np.arange(x.shape[0])
    f, grad = values(x, every) if indexed else values(x)
    step = np.ones(x.shape[0])
    last, evaluated = np.zeros(x.shape[0], dtype=int), np.ones(x.shape[0], dtype=int)
    it, evaluations = 0, x.shape[0]
    for it in range(1, max_iter + 1):
        live = np.flatnonzero(step >= min_step)
        if live.size == 0:
            break
        last[live] = it
        whole = live.size == step.size
        b = bound if whole or bound.ndim == 1 else bound[live]
        x_live, z = (x, grad * b) if whole else (x[live], grad[live] * b)
        size = np.abs(z).max(axis=1, keepdims=True)
        trial = np.divide(z, size, out=np.zeros(z.shape), where=size > 0)  # the direction, then the trial in place
        np.add(x_live, step[live, None] * b * trial, out=trial)
        np.minimum(np.maximum(trial, -b, out=trial), b, out=trial)
        moved = np.any(trial != x_live, axis=1)
        if not moved.all():
            step[live[~moved]] = 0.0
            live, trial = live[moved], trial[moved]
            if live.size == 0:
                continue
        f_trial, g_trial = values(trial, live) if indexed else values(trial)
        evaluations += live.size
        evaluated[live] += 1
        better = f_trial > f[live]  # NaN never counts as better
        kept = live[better]
        x[kept], f[kept], grad[kept] = trial[better], f_trial[better], g_trial[better]
        step[live] = np.where(better, np.minimum(2.0 * step[live], 2.0), 0.5 * step[live])
    if counts is not None:
        counts.update(last=last, evaluations=evaluated)
    return x, f, it, evaluations


def group_counts(counts: dict[str, np.ndarray], rows: np.ndarray, max_iter: int) -> tuple[int, int]:
    """(iterations, evaluations) that batched_box_ascent returns on the rows `rows` of its starts alone, from the
    per-row counts of a run on more rows (its loop ends after the group's last live iteration, or at max_iter)."""
    return min(int(max_iter), int(counts["last"][rows].max()) + 1), int(counts["evaluations"][rows].sum())
