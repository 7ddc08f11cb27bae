"""The one multistart point generator of every method: declared and suggested starts, then random points.

Order: the problem's suggested starts (BilevelProblem.suggest_start: e.g. an attack's conditioning start), for a
least-squares lower level whose Hessian moves with x the conditioning start (below), the declared start, then
seeded random points inside the upper bounds whose recognized budget-ball blocks lie on the ball's sphere. The
declared start of an attack (zero poisoning) is a stationary point of the attacker's objective (the clean learner
minimizes it), so the sphere points are never stationary there.

Conditioning start: a least-squares learner's solution y* = -P(x)^{-1} q(x) moves most for a small change of its data
where P(x) is nearly singular, so the start descends the smallest eigenvalue of P(x) (gradient v'(dP/dx)v for its
eigenvector v) by defaults["starts.conditioning_steps"] projected steps of one budget radius (balls) or half-width
(boxes) each.
"""

from __future__ import annotations

from typing import Callable, Hashable, NamedTuple

import numpy as np

from ...defaults import param
from ...kept import kept
from ...sampling import sample_in_bounds
from .prepared import Prepared


class ConditioningParts(NamedTuple):
    """A structured lower level's x -> P(x) (up to a positive factor) and (x, v) -> d(v'P(x)v)/dx for the
    conditioning start; key, where given, names all the start depends on besides the declared start and the step
    count (the data, the set the moving block is projected on): equal keys give equal starts, so the process keeps the
    last KEPT_STARTS by key."""

    hessian: Callable[[np.ndarray], np.ndarray]
    adjoint: Callable[[np.ndarray, np.ndarray], np.ndarray]
    key: Hashable | None = None


KEPT_STARTS = 16
_KEPT: dict[Hashable, np.ndarray] = {}


def _hessian_and_adjoint(prep: Prepared) -> ConditioningParts | None:
    """The parts (x -> P(x), (x, v) -> d(v'P(x)v)/dx) for a least-squares lower level whose Hessian P depends on x, else None
    (LowerLevel.moving_hessian; a lower level with linear maps differentiates over [x; z] and pulls back to x)."""
    parts = prep.canon.lower.moving_hessian()
    return None if parts is None else ConditioningParts(*parts)


def conditioning_start(prep: Prepared, parts: ConditioningParts | None = None) -> np.ndarray | None:
    """The conditioning start (module docstring) from the declared start, or None where it does not apply; parts:
    a structured lower level's ConditioningParts (a keyed start is kept in the process by key, declared start and step
    count) (default: from the declaration, whose start is kept on prep for the parameter values, box, declared start
    and step count it was found at: a re-solve reuses it)."""
    if parts is not None:
        if parts.key is None:
            return _conditioning_descent(prep, parts)
        return kept(_KEPT, conditioning_key(prep, parts), lambda: _conditioning_descent(prep, parts),
                    KEPT_STARTS)[0].copy()
    declared = prep.cached(("conditioning-start",), lambda: _hessian_and_adjoint(prep))
    if declared is None:
        return None
    canon = prep.canon
    key = (canon.params.revision, param("starts.conditioning_steps"), canon.x_start.tobytes(), canon.x_lb.tobytes(),
           canon.x_ub.tobytes())  # set_bounds changes the box and the start without a new revision
    found = prep.memo.get(("conditioning-start-point",))
    if found is None or found[0] != key:
        found = prep.memo[("conditioning-start-point",)] = (key, _conditioning_descent(prep, declared))
    return found[1].copy()


def conditioning_key(prep: Prepared, parts: ConditioningParts) -> Hashable:
    """The key under which the process keeps the conditioning start of keyed parts (parts.key not None)."""
    return parts.key, param("starts.conditioning_steps"), prep.canon.x_start.tobytes()


def kept_conditioning_start(key: Hashable) -> np.ndarray | None:
    """A copy of the conditioning start kept under `key` (conditioning_key), or None."""
    x = _KEPT.get(key)
    return None if x is None else x.copy()


def keep_conditioning_start(key: Hashable, x: np.ndarray) -> None:
    """Keep a conditioning start found elsewhere (a batch's: bilevel.solvers.engine.affine_ls_batch) under `key`, as
    conditioning_start keeps the ones it finds."""
    kept(_KEPT, key, lambda: np.array(x, dtype=float), KEPT_STARTS)


def _conditioning_descent(prep: Prepared, parts: ConditioningParts) -> np.ndarray:
    """The conditioning start's projected steps from the declared start, with parts (x -> P(x), (x, v) ->
    d(v'P(x)v)/dx)."""
    hessian, adjoint = parts.hessian, parts.adjoint
    canon = prep.canon
    scale = np.where(np.isfinite(canon.x_ub - canon.x_lb), 0.5 * (canon.x_ub - canon.x_lb), 1.0)
    for ball in prep.balls:
        scale[ball.block] = max(ball.radius, 1e-300)
    x = prep.projection(canon.x_start)
    for _ in range(param("starts.conditioning_steps")):
        P = hessian(x)
        grad = adjoint(x, np.linalg.eigh(0.5 * (P + P.T))[1][:, 0])
        unit = float(np.linalg.norm(grad * scale))
        if not unit > 0 or not np.isfinite(unit):
            break
        x = prep.projection(x - grad * scale ** 2 / unit)
    return x


def start_points(prep: Prepared, starts: int, rng: np.random.Generator, scale: float,
                 parts: ConditioningParts | None = None, conditioning: np.ndarray | None = None) -> list[np.ndarray]:
    """`starts` upper starts: suggested ones, the conditioning start (where it applies; parts as conditioning_start
    takes them; `conditioning` where the caller has it, e.g. a placeholder a batch fills with the starts it finds
    together: at index len(prep.canon.x_suggested)), the declared one, then random ones (balls: on their sphere)."""
    canon = prep.canon
    if starts <= len(canon.x_suggested):
        conditioning = None
    elif conditioning is None:
        conditioning = conditioning_start(prep, parts)
    points = [*canon.x_suggested, *([] if conditioning is None else [conditioning]), canon.x_start][:starts]
    return points + random_starts(prep, starts - len(points), rng, scale)


def random_starts(prep: Prepared, count: int, rng: np.random.Generator, scale: float) -> list[np.ndarray]:
    """start_points' random starts: seeded points inside the upper bounds (half-width `scale` where a bound is
    infinite) whose recognized budget-ball blocks lie on the ball's sphere, projected on the upper set."""
    canon, points = prep.canon, []
    for _ in range(max(count, 0)):
        x = sample_in_bounds(canon.x_lb, canon.x_ub, rng, scale)
        for ball in prep.balls:
            x[ball.block] = ball.sphere_point(rng)
        points.append(prep.projection(x))
    return points
