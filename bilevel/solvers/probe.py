"""Local evidence that a returned point is a local solution: feasible points around it, none better.

A stationary point of the reduced objective need not be a minimum: zero poisoning is stationary for every
attack (the clean learner minimizes the attacker's loss) and is its *worst* point; and a method may stop short
of stationarity (IPOPT on the Willems KKT route, 1.6e-4 below the vertex next to it). Around x the probe tries
seeded random directions and the negative hypergradient, scaled per entry (a recognized ball's radius on its
block, else 1), projects x + h d onto the box and balls for a few radii h, solves the lower level there
independently (and at x itself, the baseline: with a non-unique lower solution F depends on the solver's
choice), and reports the best upper-feasible point whose upper objective is lower than both F at x and the
baseline by more than REL_TOL (relative; DESCENT_REL_TOL along the hypergradient): at a stationary point the
change is second order, so the tolerance sits at the lower solves' noise, not above it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import BilevelError
from .projections import Projection
from .structure import budget_scale

if TYPE_CHECKING:  # pragma: no cover
    from .base import Prepared

DIRECTIONS = 4
RADII = (1e-1, 1e-2, 1e-3)
REL_TOL = 1e-8
FEAS_TOL = 1e-9
DESCENT_REL_TOL = 1e-5
"""Along the descent direction the change is first order: a point counts as better only by more than this
(relative), the scale of the methods' default stopping tolerances, so a point solved to tolerance passes."""


@dataclass(frozen=True)
class Probe:
    """A better feasible point found near x: where, its upper objective (canonical sense), and the radius."""

    x: np.ndarray
    objective: float
    radius: float


def improving_neighbour(prep: "Prepared", x: np.ndarray, objective: float, projection: Projection,
                        seed: int = 0) -> Probe | None:
    """The best neighbour of x in `projection`'s set, upper-feasible, with upper objective
    < objective - REL_TOL max(1, |objective|); None if the probe finds none."""
    low = prep.canon.lower
    try:  # the same lower solver as at the probes: a non-unique lower solution must not pass for a better point
        fixed_y = low.solve(x).y if low.fixed else None  # a lower level that ignores x is solved once
    except BilevelError:
        return None
    baseline = _feasible_objective(prep, x, fixed_y)
    if baseline is None:
        return None
    reference = min(objective, baseline)
    threshold = reference - REL_TOL * max(1.0, abs(reference))
    rng = np.random.default_rng(seed)
    scale = budget_scale(prep.canon, prep.balls)
    best: Probe | None = None
    directions = [(rng.standard_normal(x.size) * scale, threshold) for _ in range(DIRECTIONS)]
    descent = _descent_direction(prep, x, scale)
    if descent is not None:
        directions.append((descent, reference - DESCENT_REL_TOL * max(1.0, abs(reference))))
    for d, bar in directions:
        d /= max(float(np.linalg.norm(d / scale)), 1e-300)
        for h in RADII:
            xp = projection(x + h * d)
            F = _feasible_objective(prep, xp, fixed_y)
            if F is not None and F < bar and (best is None or F < best.objective):
                best = Probe(xp, F, h)
    return best


def _descent_direction(prep: "Prepared", x: np.ndarray, scale: np.ndarray) -> np.ndarray | None:
    """-grad F(x, y*(x)) in budget units (the hypergradient, balls projected on), or None where it cannot be had:
    a method that stopped short of stationarity (an interior point next to a better vertex) is caught by it."""
    from .implicit import shared_oracle  # implicit imports base, which imports this module

    rows = tuple(b.row for b in prep.balls)
    try:
        grad = shared_oracle(prep, projected_rows=rows)(x)[1]
    except (BilevelError, np.linalg.LinAlgError, ValueError):
        return None
    return -grad * scale ** 2 if np.all(np.isfinite(grad)) and np.any(grad) else None


def _feasible_objective(prep: "Prepared", x: np.ndarray, y: np.ndarray | None = None) -> float | None:
    """F(x, y), y from the lower level's own solver unless given; None if that fails or (x, y) is
    upper-infeasible."""
    try:
        y = prep.canon.lower.solve(x).y if y is None else y
    except BilevelError:
        return None
    F, G, H = (np.asarray(v, dtype=float).ravel() for v in prep.canon.functions(x, y))
    if np.any(G > FEAS_TOL) or np.any(np.abs(H) > FEAS_TOL) or not np.isfinite(F[0]):
        return None
    return float(F[0])
