"""The one multistart point generator of every method: declared and suggested starts, then random points.

Order: the problem's suggested starts (BilevelProblem.suggest_start: e.g. an attack's conditioning start),
the declared start, then seeded random points inside the upper bounds whose recognized budget-ball blocks
lie on the ball's sphere. The declared start of an attack (zero poisoning) is a stationary point of the
attacker's objective (the clean learner minimizes it), so the sphere points are never stationary there.
"""

from __future__ import annotations

import numpy as np

from ..sampling import sample_in_bounds
from .base import Prepared


def start_points(prep: Prepared, starts: int, rng: np.random.Generator, scale: float) -> list[np.ndarray]:
    """`starts` upper starts: suggested ones, the declared one, then random ones (balls: on their sphere)."""
    canon = prep.canon
    points = [*canon.x_suggested, canon.x_start][:starts]
    while len(points) < starts:
        x = sample_in_bounds(canon.x_lb, canon.x_ub, rng, scale)
        for ball in prep.balls:
            x[ball.block] = ball.sphere_point(rng)
        points.append(prep.projection(x))
    return points
