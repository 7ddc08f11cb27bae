"""The local probe (bilevel.solvers.verdict.probe.probe_neighbours, with a structured lower solve) on many instances of
one declaration at once: every instance's probe points built as the probe builds them (its seeded random directions
and the negative hypergradient, scaled per entry by its balls' radii, projected on its own set at the probe's radii),
then the lower solutions and upper objectives at all the points of all instances in one batched call of the method's
ProbeParts, and each instance's verdict by the probe's rule (better than both F at x and the baseline by more than
defaults["probe.rel_tol"] along random directions, defaults["probe.descent_rel_tol"] along first-order ones).

It covers the probe's first round of radii on problems whose upper constraints are all recognized l2 balls (G_i =
||x_S - c||^2 - r^2, no equality); an instance for which the first round leaves no probed point feasible, or a problem
outside that class, gets None, and finalize then runs the one-instance probe.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ...defaults import param
from ..engine.projections import Projection
from ..engine.structure import Ball
from .probe import Probe, ProbeOutcome, radii


@dataclass(frozen=True)
class ProbeParts:
    """What a batched method knows of its instances' lower level and objective: solve(instances, X) -> (Y, ok), the
    unique lower solutions at the rows of X (row j of instance instances[j]; ok False where there is none);
    objective(instances, X, Y) -> F (canonical sense) at those points; gradient(i) -> the canonical grad F(x, y*(x))
    at instance i's point (None where it has none)."""

    solve: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    objective: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    gradient: Callable[[int], np.ndarray | None]


@dataclass(frozen=True)
class ProbeInstance:
    """One instance as the probe reads it: its point x and F there (canonical), its feasible set, per-entry scale
    (budget_scale) and balls (the upper constraints)."""

    x: np.ndarray
    objective: float
    projection: Projection
    scale: np.ndarray
    balls: list[Ball]


def covered(balls: list[Ball], n_G: int, n_H: int, n_x: int) -> bool:
    """Whether probe_many covers a problem: every upper constraint a recognized l2 ball, no equalities, and more upper
    entries than defaults["probe.coordinates"] (below it the probe also tries coordinates and kinks)."""
    return (n_H == 0 and len(balls) == n_G and all(b.norm == 2 for b in balls)
            and n_x > param("probe.coordinates"))


def _on_balls(P: np.ndarray, balls: list[Ball]) -> np.ndarray:
    """Each row of P projected on the l2 balls on their blocks (the other entries free): an instance's set where its
    upper constraints are these balls and its box is free."""
    P = P.copy()
    for b in balls:
        D = P[:, b.block] - b.center
        norm = np.sqrt(np.sum(D * D, axis=1))
        outside = norm > b.radius
        P[outside, b.block] = b.center + D[outside] * (b.radius / norm[outside])[:, None]
    return P


def probe_many(instances: list[ProbeInstance], parts: ProbeParts, seed: int = 0,
               balls_only: bool = False) -> list[ProbeOutcome | None]:
    """probe_neighbours' outcome for each instance (module docstring), None where the batched probe does not decide;
    balls_only: each instance's feasible set is its balls (a free box), projected on in one stacked call. The
    instances go through in groups of about defaults["batch.chunk"] probe points (their data stay in cache)."""
    if not instances:
        return []
    rng = np.random.default_rng(seed)
    draws = [rng.standard_normal(instances[0].x.size) for _ in range(param("probe.directions"))]
    group = max(1, int(param("batch.chunk")) // (3 * (len(draws) + 1) + 1))
    out: list[ProbeOutcome | None] = []
    for s in range(0, len(instances), group):
        out += _probe_group(instances, range(s, min(s + group, len(instances))), parts, draws, balls_only)
    return out


def _probe_group(instances: list[ProbeInstance], group: range, parts: ProbeParts, draws: list[np.ndarray],
                 balls_only: bool) -> list[ProbeOutcome | None]:
    """probe_many on the instances of `group`: their points solved and judged together."""
    round_radii, feas_tol = radii(), param("probe.feas_tol")
    owner, points, where = [], [], []  # per instance: x's index, its probes (point index, radius, tolerances)
    for i in group:
        inst = instances[i]
        directions = [(z * inst.scale, "probe.rel_tol") for z in draws]
        g = parts.gradient(i)
        if g is not None and np.all(np.isfinite(g)) and np.any(g):
            directions.append((-g * inst.scale ** 2, "probe.descent_rel_tol"))
        kinds: dict[bytes, tuple[np.ndarray, frozenset[str]]] = {}
        for d, tol in directions:
            d = d / max(float(np.linalg.norm(d / inst.scale)), 1e-300)
            key = np.round(d / inst.scale, 12).tobytes()
            kinds[key] = (d, kinds.get(key, (d, frozenset()))[1] | {tol})
        index: dict[bytes, int] = {}

        def point(xp: np.ndarray) -> int:
            key = xp.tobytes()
            if key not in index:
                index[key] = len(points)
                owner.append(i)
                points.append(xp)
            return index[key]

        here = point(inst.x)
        trials = [(inst.x + h * d, h, tols) for d, tols in kinds.values() for h in round_radii]
        moved = _on_balls(np.array([t for t, _, _ in trials]), inst.balls) if balls_only else [
            inst.projection(t) for t, _, _ in trials]
        where.append((here, [(point(xp), h, tols) for xp, (_, h, tols) in zip(moved, trials)]))
    owner_a, X = np.array(owner), np.array(points)
    F = np.full(len(points), np.nan)
    Y, ok = parts.solve(owner_a, X)
    if ok.any():
        F[ok] = parts.objective(owner_a[ok], X[ok], Y[ok])
    feasible = ok & np.isfinite(F)
    for i in group:
        rows = owner_a == i
        for b in instances[i].balls:
            D = X[rows][:, b.block] - b.center
            feasible[rows] &= np.sum(D * D, axis=1) - b.radius ** 2 <= feas_tol
    out: list[ProbeOutcome | None] = []
    for i, (here, probes) in zip(group, where):
        if not feasible[here]:
            out.append(ProbeOutcome(None))
            continue
        if not any(feasible[j] for j, _, _ in probes):
            out.append(None)  # the probe's next rounds (smaller radii): the one-instance probe
            continue
        reference = min(instances[i].objective, float(F[here]))
        bars = {tol: reference - param(tol) * max(1.0, abs(reference))
                for tol in ("probe.rel_tol", "probe.descent_rel_tol")}
        best: Probe | None = None
        for j, h, tols in probes:
            value, bar = float(F[j]), min(bars[tol] for tol in tols)
            if feasible[j] and value < bar and (best is None or value < best.objective):
                best = Probe(X[j], value, h)
        out.append(ProbeOutcome(best))
    return out
