"""The engine's spectral projected gradient ascent (bilevel.solvers.engine.ascent.projected_ascent) on many instances
at once, in lockstep: every round evaluates one trial point per live instance in one batched call, accepted points get
their gradients in one more, and an instance that stops drops out of the batch.

Per instance the steps are those of projected_ascent with bb="short" and no stop callback (the same first step, Armijo
test, halving, Barzilai-Borwein length, window and stop reasons), so an instance's iterates differ from the one-instance
loop's only by the rounding of the batched evaluations.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ...defaults import param

Points = dict[str, np.ndarray]
"""What an evaluation knows at each of its rows (arrays with the rows on the leading axis), kept at accepted points."""
Value = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, Points]]
"""(rows, X) -> (f at each row of X, -inf where it cannot be evaluated; the points' data)."""
Direction = Callable[[np.ndarray, Points], tuple[np.ndarray, np.ndarray]]
"""(rows, points) -> (gradients, first directions) at the points."""
Project = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(rows, X) -> each row of X projected on its instance's set."""


@dataclass
class BatchAscent:
    """Per instance (row): the last accepted x and f, the data of its point, iterations, evaluations, whether it
    converged, why it stopped (projected_ascent's reasons), the gradient at x and its history of accepted steps."""

    x: np.ndarray
    f: np.ndarray
    points: Points
    iterations: np.ndarray
    evaluations: np.ndarray
    converged: np.ndarray
    why: list[str]
    gradient: np.ndarray
    """The gradient at each row's x (what the direction callback returned there)."""
    history: list[list[dict[str, float]]] = field(default_factory=list)


def _take(points: Points, sel: np.ndarray) -> Points:
    return {k: v[sel] for k, v in points.items()}


def _put(store: Points, rows: np.ndarray, points: Points, sel: np.ndarray | slice) -> None:
    for k, v in points.items():
        if k not in store:
            store[k] = np.zeros((store["_size"].shape[0],) + v.shape[1:], dtype=v.dtype)
        store[k][rows] = v[sel]


def in_chunks(value: Value, rows: np.ndarray, X: np.ndarray, size: int | None = None) -> tuple[np.ndarray, Points]:
    """value(rows, X) computed defaults["batch.chunk"] rows (or `size`) at a time, the results joined (a stacked
    evaluation of a few dozen rows keeps its working set in cache)."""
    size = int(param("batch.chunk", size))
    if rows.size <= size:
        return value(rows, X)
    parts = [value(rows[s: s + size], X[s: s + size]) for s in range(0, rows.size, size)]
    return (np.concatenate([f for f, _ in parts]),
            {k: np.concatenate([p[k] for _, p in parts]) for k in parts[0][1]})


def batched_projected_ascent(value: Value, direction: Direction, project: Project, X0: np.ndarray,
                             scale: np.ndarray, max_iter: int, tol: float, step0: float = 1.0,
                             min_step: float = 1e-8) -> BatchAscent:
    """projected_ascent (bb="short") from each row of X0, scale[i] instance i's length scale (a number per row),
    all rows in lockstep (module docstring); value is called on defaults["batch.chunk"] rows at a time."""
    m = X0.shape[0]
    rows = np.arange(m)
    armijo, window = param("ascent.armijo"), int(param("ascent.window"))
    metric = (np.asarray(scale, dtype=float) ** 2)[:, None]
    x = project(rows, np.asarray(X0, dtype=float))
    fx, pts = in_chunks(value, rows, x)
    store: Points = {"_size": np.zeros(m)}
    _put(store, rows, pts, slice(None))
    why = ["max_iter"] * m
    converged = np.zeros(m, dtype=bool)
    iterations, evaluations = np.zeros(m, dtype=int), np.ones(m, dtype=int)
    accepted = np.zeros((m, max(max_iter, 0) + 1, 3))  # per row: its accepted steps' (iteration, value, step)
    count = np.zeros(m, dtype=int)
    g, d = np.zeros_like(x), np.zeros_like(x)
    live = fx != -np.inf
    for i in np.flatnonzero(~live):
        why[i] = "start"
    if live.any():
        idx = np.flatnonzero(live)
        g[idx], d[idx] = direction(idx, _take(pts, idx))
    alpha = np.full(m, np.nan)  # Barzilai-Borwein length; NaN: the first direction
    lam, move = np.zeros(m), np.zeros_like(x)
    fresh = live.copy()  # instances beginning an iteration
    while live.any():
        begin = np.flatnonzero(fresh & live)
        if begin.size:
            iterations[begin] += 1
            over = begin[iterations[begin] > max_iter]
            iterations[over] = max_iter
            live[over] = False  # why stays "max_iter"
            begin = begin[iterations[begin] <= max_iter] if over.size else begin
            first = np.isnan(alpha[begin])
            step = np.where(first[:, None], d[begin], alpha[begin, None] * (metric[begin] * g[begin]))
            move[begin] = step
            still = ~np.any(step != 0, axis=1)
            for i in begin[still]:
                converged[i], why[i], live[i] = True, "zero step", False
            begin = begin[~still]
            lam[begin] = np.where(first[~still], step0, 1.0)
            fresh[:] = False
        idx = np.flatnonzero(live)
        if idx.size == 0:
            break
        xi = x[idx]  # the rows' points, gathered once per round
        xn = project(idx, xi + lam[idx, None] * move[idx])
        held = np.all(xn == xi, axis=1)
        if held.any():
            for i in idx[held]:
                converged[i], why[i], live[i] = True, "stationary", False
            idx, xn, xi = idx[~held], xn[~held], xi[~held]
        if idx.size == 0:
            continue
        fn, ptsn = in_chunks(value, idx, xn)
        evaluations[idx] += 1
        moved = xn - xi
        rise = np.einsum("ij,ij->i", g[idx], moved)
        ok = (fn >= fx[idx] + armijo * rise) & (fn >= fx[idx])
        acc = np.flatnonzero(ok)
        if acc.size:
            rows_acc = idx[acc]
            gn, dn = direction(rows_acc, _take(ptsn, acc))  # copies: contiguous rows, whose sums round as before
            s, y = moved[acc], gn - g[rows_acc]
            curvature = -np.einsum("ij,ij->i", s, y)
            yy = np.einsum("ij,ij->i", y, metric[rows_acc] * y)
            alpha[rows_acc] = np.where((curvature > 0) & (yy > 0), curvature / np.where(yy > 0, yy, 1.0), np.nan)
            x[rows_acc], fx[rows_acc], g[rows_acc], d[rows_acc] = xn[acc], fn[acc], gn, dn
            _put(store, rows_acc, ptsn, acc)
            accepted[rows_acc, count[rows_acc]] = np.stack([iterations[rows_acc], fx[rows_acc], lam[rows_acc]], axis=1)
            count[rows_acc] += 1
            back = accepted[rows_acc, np.maximum(count[rows_acc] - window, 0), 1]  # the value `window` steps back
            flat = (iterations[rows_acc] >= window) & (fx[rows_acc] - back <= tol * np.maximum(np.abs(fx[rows_acc]),
                                                                                                 1e-12))
            for i in rows_acc[flat]:
                converged[i], why[i], live[i] = True, "window", False
            fresh[rows_acc] = True
        rej = idx[~ok]
        lam[rej] *= 0.5
        for i in rej[lam[rej] < min_step]:
            converged[i], why[i], live[i] = True, "line search", False
    del store["_size"]
    history = [[{"iter": int(it), "value": float(v), "step": float(st)} for it, v, st in accepted[i, :count[i]]]
               for i in range(m)]
    return BatchAscent(x, fx, store, iterations, evaluations, converged, why, g, history)
