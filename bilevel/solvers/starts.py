"""The one multistart point generator of every method: declared and suggested starts, then random points.

Order: the problem's suggested starts (BilevelProblem.suggest_start: e.g. an attack's conditioning start), for a
least-squares lower level whose Hessian moves with x the conditioning start (below), the declared start, then
seeded random points inside the upper bounds whose recognized budget-ball blocks lie on the ball's sphere. The
declared start of an attack (zero poisoning) is a stationary point of the attacker's objective (the clean learner
minimizes it), so the sphere points are never stationary there.

Conditioning start: a least-squares learner's solution y* = -P(x)^{-1} q(x) moves most for a small change of its
data where P(x) is nearly singular, so the start descends the smallest eigenvalue of P(x) (gradient v'(dP/dx)v for
its eigenvector v) by CONDITIONING_STEPS projected steps of one budget radius (balls) or half-width (boxes) each.
"""

from __future__ import annotations

from typing import Callable

import casadi as ca
import numpy as np

from ..lower.base import ExpressionLower
from ..lower.images import ImageLower
from ..lower.residual import ResidualLeastSquares
from ..sampling import sample_in_bounds
from .base import Prepared
from .structure import budget_scale, depends

CONDITIONING_STEPS = 10


def _hessian_and_adjoint(prep: Prepared) -> tuple[Callable, Callable] | None:
    """(x -> P(x), (x, v) -> d(v'P(x)v)/dx) for a least-squares lower level whose Hessian P depends on x, else None."""
    low = prep.canon.lower
    inner = low.inner if isinstance(low, ImageLower) else low
    if isinstance(inner, ResidualLeastSquares) and not inner.fixed:
        if isinstance(low, ImageLower):
            return (lambda x: inner.gram(low.lift(x)),
                    lambda x, v: low.lift.pullback(x, inner.gram_adjoint(low.lift(x), v)))
        return inner.gram, inner.gram_adjoint
    if low.kind != "least-squares" or not isinstance(inner, ExpressionLower):
        return None
    P = ca.substitute(inner.hess_f, inner.y, ca.DM.zeros(inner.n_y))
    if not depends(P, inner.x).any():
        return None
    V = ca.SX.sym("V", inner.n_y, inner.n_y)
    hessian = prep.canon.params.function("conditioning_P", [inner.x], [P])
    adjoint = prep.canon.params.function("conditioning_adjoint", [inner.x, V],
                                         [ca.jtimes(ca.vec(P), inner.x, ca.vec(V), True)])
    if isinstance(low, ImageLower):
        lift = low.lift
        return (lambda x: np.asarray(hessian(lift(x)), dtype=float),
                lambda x, v: lift.pullback(x, np.asarray(adjoint(lift(x), np.outer(v, v)), dtype=float).ravel()))
    return (lambda x: np.asarray(hessian(x), dtype=float),
            lambda x, v: np.asarray(adjoint(x, np.outer(v, v)), dtype=float).ravel())


def conditioning_start(prep: Prepared) -> np.ndarray | None:
    """The conditioning start (module docstring) from the declared start, or None where it does not apply."""
    parts = prep.cached(("conditioning-start",), lambda: _hessian_and_adjoint(prep))
    if parts is None:
        return None
    hessian, adjoint = parts
    canon = prep.canon
    balls = budget_scale(canon, prep.balls)
    half = np.where(np.isfinite(canon.x_ub - canon.x_lb), 0.5 * (canon.x_ub - canon.x_lb), 1.0)
    scale = np.where(np.isin(np.arange(balls.size), [i for b in prep.balls for i in range(b.block.start,
                                                                                          b.block.stop)]),
                     balls, half)
    x = prep.projection(canon.x_start)
    for _ in range(CONDITIONING_STEPS):
        P = hessian(x)
        grad = adjoint(x, np.linalg.eigh(0.5 * (P + P.T))[1][:, 0])
        unit = float(np.linalg.norm(grad * scale))
        if not unit > 0 or not np.isfinite(unit):
            break
        x = prep.projection(x - grad * scale ** 2 / unit)
    return x


def start_points(prep: Prepared, starts: int, rng: np.random.Generator, scale: float) -> list[np.ndarray]:
    """`starts` upper starts: suggested ones, the conditioning start (where it applies), the declared one, then random
    ones (balls: on their sphere)."""
    canon = prep.canon
    conditioning = conditioning_start(prep) if starts > len(canon.x_suggested) else None
    points = [*canon.x_suggested, *([] if conditioning is None else [conditioning]), canon.x_start][:starts]
    while len(points) < starts:
        x = sample_in_bounds(canon.x_lb, canon.x_ub, rng, scale)
        for ball in prep.balls:
            x[ball.block] = ball.sphere_point(rng)
        points.append(prep.projection(x))
    return points
