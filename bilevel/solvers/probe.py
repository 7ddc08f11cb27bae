"""Local evidence that a returned point is a local solution: feasible points around it, none better.

A stationary point of the reduced objective need not be a minimum: zero poisoning is stationary for every
attack (the clean learner minimizes the attacker's loss) and is its *worst* point. Around x the probe draws
seeded random directions, scaled per entry (a recognized ball's radius on its block, else 1), projects
x + h d onto the box and balls for a few radii h, solves the lower level there independently, and reports
the best upper-feasible point whose upper objective is lower than at x by more than REL_TOL (relative): at a
stationary point the change is second order, so the tolerance sits at the lower solves' noise, not above it.
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
    canon = prep.canon
    rng = np.random.default_rng(seed)
    scale = budget_scale(canon, prep.balls)
    threshold = objective - REL_TOL * max(1.0, abs(objective))
    best: Probe | None = None
    for _ in range(DIRECTIONS):
        d = rng.standard_normal(x.size) * scale
        d /= max(float(np.linalg.norm(d / scale)), 1e-300)
        for h in RADII:
            xp = projection(x + h * d)
            try:
                y = canon.lower.solve(xp).y
            except BilevelError:
                continue
            F, G, H, _ = (np.asarray(v, dtype=float).ravel() for v in canon.functions(xp, y))
            if np.any(G > FEAS_TOL) or np.any(np.abs(H) > FEAS_TOL) or not np.isfinite(F[0]):
                continue
            if F[0] < threshold and (best is None or F[0] < best.objective):
                best = Probe(xp, float(F[0]), h)
    return best
