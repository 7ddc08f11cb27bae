"""Methods over the upper box of a problem whose lower level ignores the upper variables (solved once): random signs
at the bounds (a budget-matched baseline) and the batched, screened ascent of a spectral-radius objective over a
symmetric box (bilevel.solvers.engine.ascent.batched_box_ascent). Passed to bilevel.solve as callables (the Willems
attacks, bilevel.attacks.willems)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..defaults import param
from ..errors import ModelError
from ..reduction import KKTPoint
from ..result import Status
from ..solvers.engine.ascent import batched_box_ascent
from ..solvers.engine.prepared import MethodRun, Prepared, check_options
from ..solvers.engine.implicit import shared_oracle
from ..solvers.engine.options import check_common_options, check_counts


def random_signs(prep: Prepared, *, seed: Any = 0, **unknown: Any) -> MethodRun:
    """Method: every upper entry at a bound, the side drawn by a fair coin seeded by `seed` (a budget-matched
    baseline)."""
    check_options("random-signs", unknown, random_signs)
    canon = prep.canon
    sign = np.random.default_rng(seed).choice([-1.0, 1.0], size=canon.x_lb.size)
    ev = shared_oracle(prep).evaluate(np.where(sign > 0, canon.x_ub, canon.x_lb))
    w = prep.pack(KKTPoint(ev.x, ev.lower.y, ev.lower.lam, ev.lower.mu, ev.lower.Z))
    return MethodRun(w, Status.INACCURATE, "random signs at the budget (a baseline, not an optimizer)")


def destabilize(prep: Prepared, *, starts: int | None = None, seed: Any = 0, max_iter: int | None = None,
                pool: int | None = None, **unknown: Any) -> MethodRun:
    """Method: maximize a spectral-radius objective over a symmetric box where the lower level ignores x: `starts`
    points ascend together (batched_box_ascent) for up to max_iter steps, the box's centre and the largest-rho points of
    a pool of `pool` random ones (half uniform, half vertices, drawn from `seed`). Returns the ascents' best point (not
    a certified local maximum). None takes the registry's value, defaults["destabilize.NAME"] (bilevel.defaults)."""
    check_options("destabilize", unknown, destabilize)
    starts, max_iter = param("destabilize.starts", starts), param("destabilize.max_iter", max_iter)
    pool = param("destabilize.pool", pool)
    check_common_options({"starts": starts, "seed": seed, "max_iter": max_iter})
    check_counts({"pool": pool}, ("pool",))
    engine, bound = shared_oracle(prep), prep.canon.x_ub
    if prep.canon.spectral is None or not engine.low.fixed or not np.array_equal(prep.canon.x_lb, -bound):
        raise ModelError("destabilize needs a spectral-radius objective, a lower level that ignores the upper "
                         "variables (Willems: poison='u' with design 'lqr' or 'stabilizing') and a box |x| <= b; "
                         "otherwise use method='hypergradient'")
    candidates = np.random.default_rng(seed).uniform(-1.0, 1.0, (max(pool, starts - 1), bound.size)) * bound
    candidates[: candidates.shape[0] // 2] = np.sign(candidates[: candidates.shape[0] // 2]) * bound
    screened = np.argsort(engine.spectral_values(candidates.T), kind="stable")[: starts - 1]  # F minimized

    def values(xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # the objective maximized, -F, and its gradient
        f, g, _ = engine.spectral_batch(xs.T)
        return -f, -g.T

    xs, rho, iters, evaluations = batched_box_ascent(values, bound, np.vstack([np.zeros(bound.size),
                                                                              candidates[screened]]), max_iter)
    best = int(np.nanargmax(rho))
    ev = engine.evaluate(xs[best])
    w = prep.pack(KKTPoint(ev.x, ev.lower.y, ev.lower.lam, ev.lower.mu, ev.lower.Z))
    return MethodRun(w, Status.INACCURATE, f"largest objective {rho[best]:.6g} over {starts} batched ascents (their "
                     "best point, not a certified local maximum)", iters,
                     stats={"best_start": best, "start_values": rho.tolist(),
                            "evaluations": evaluations + candidates.shape[0]})
