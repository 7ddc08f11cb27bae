"""Methods over the upper box of a problem whose lower level ignores the upper variables (solved once): random signs
at the bounds (a budget-matched baseline) and the batched, screened ascent of a spectral-radius objective over a
symmetric box (bilevel.solvers.engine.ascent.batched_box_ascent). Passed to bilevel.solve as callables (the Willems
attacks, bilevel.attacks.willems)."""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from ..defaults import param
from ..errors import ModelError
from ..reduction import KKTPoint
from ..result import Status
from ..solvers.batch import BatchMethod, in_groups, register_batch
from ..solvers.engine.ascent import batched_box_ascent, group_counts
from ..solvers.engine.prepared import MethodRun, Prepared, check_options
from ..solvers.engine.implicit import affine_stack, shared_oracle
from ..solvers.engine.options import check_common_options, check_counts
from ..spectral_radius import spectral_radius


def random_signs(prep: Prepared, *, seed: Any = 0, **unknown: Any) -> MethodRun:
    """Method: every upper entry at a bound, the side drawn by a fair coin seeded by `seed` (a budget-matched
    baseline)."""
    check_options("random-signs", unknown, random_signs)
    canon = prep.canon
    sign = np.random.default_rng(seed).choice([-1.0, 1.0], size=canon.x_lb.size)
    ev = shared_oracle(prep).evaluate(np.where(sign > 0, canon.x_ub, canon.x_lb))
    w = prep.pack(KKTPoint(ev.x, ev.lower.y, ev.lower.lam, ev.lower.mu, ev.lower.Z))
    return MethodRun(w, Status.INACCURATE, "random signs at the budget (a baseline, not an optimizer)")


class Climb(NamedTuple):
    """One loaded instance of method destabilize, ready to climb: its packing, the lower solution (one for every x),
    the box bound, the starts, the affine map vec M = m0 + jx x of its spectral objective (sign: F = sign * rho(M)),
    max_iter and the points screened for the starts."""

    prep: Prepared
    engine: Any
    lower: Any
    bound: np.ndarray
    starts: np.ndarray
    m0: np.ndarray | None
    jx: np.ndarray | None
    sign: float
    max_iter: int
    screened: int


def _climb(prep: Prepared, starts: int | None, seed: Any, max_iter: int | None, pool: int | None) -> Climb:
    """destabilize's options checked and its starts drawn and screened on the loaded instance (its docstring)."""
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
    affine = engine.spectral_map() or (None, None)  # None: M not affine in x, values point by point (alone only)
    return Climb(prep, engine, engine.evaluate(np.zeros(bound.size)).lower, bound,
                 np.vstack([np.zeros(bound.size), candidates[screened]]), affine[0], affine[1],
                 float(prep.canon.spectral_sign), int(max_iter), candidates.shape[0])


def _climbed(c: Climb, xs: np.ndarray, rho: np.ndarray, iters: int, evaluations: int) -> MethodRun:
    """destabilize's run from its ascents' points xs and objectives rho: the best one, not certified."""
    best = int(np.nanargmax(rho))
    low = c.lower
    w = c.prep.pack(KKTPoint(xs[best], low.y, low.lam, low.mu, low.Z))
    return MethodRun(w, Status.INACCURATE, f"largest objective {rho[best]:.6g} over {len(rho)} batched ascents (their "
                     "best point, not a certified local maximum)", iters,
                     stats={"best_start": best, "start_values": rho.tolist(), "evaluations": evaluations + c.screened})


def _values(climbs: Sequence[Climb], owner: np.ndarray) -> Callable[[np.ndarray, np.ndarray], tuple]:
    """The ascent's objective -F and its gradient at rows X of the stacked starts (rows: their indices, owner[row]
    the instance): each instance's M by its own product, one stacked eigendecomposition for all, per matrix the same
    operations as one instance alone. Identical to rounding: numpy's complex division and inversion may round a
    matrix's entries differently with its place in the stack (vectorized body or tail), so an instance's values can
    differ in the last digit from its run alone (seen on 1 of 256 paper attacks; benchmarks/bench_willems_batch.py).
    An instance without an affine map (alone) goes through its engine's spectral_batch."""
    n = int(climbs[0].prep.canon.spectral.size1())

    def radii(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rho of each matrix of the stack and its gradient in vec M (one row per matrix)."""
        r = spectral_radius(stack)
        return r.value, r.gradient.transpose(0, 2, 1).reshape(stack.shape[0], -1)

    def signed(c: Climb, rho: np.ndarray, grads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """F = sign * rho of instance c's rows and its gradient in x (through vec M = m0 + jx x)."""
        return c.sign * rho, (c.sign * (c.jx.T @ grads.T)).T

    def values(xs: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(climbs) == 1 and climbs[0].m0 is not None:  # one instance (destabilize alone): no parts to gather
            c = climbs[0]
            f, g = signed(c, *radii(affine_stack(c.m0, c.jx, xs.T, n)))
            return -f, -g
        parts = np.split(np.arange(rows.size), np.flatnonzero(np.diff(owner[rows])) + 1)  # one run per instance
        mine = [climbs[owner[rows[p[0]]]] for p in parts]
        if mine[0].m0 is None:
            f, g, _ = mine[0].engine.spectral_batch(xs.T)
            return -f, -g.T
        rho, grads = radii(np.concatenate([affine_stack(c.m0, c.jx, xs[p].T, n) for c, p in zip(mine, parts)]))
        pieces = [signed(c, rho[p], grads[p]) for c, p in zip(mine, parts)]
        return -np.concatenate([f for f, _ in pieces]), -np.vstack([g for _, g in pieces])
    return values


def climb_together(climbs: Sequence[Climb]) -> list[MethodRun]:
    """destabilize's runs of several loaded instances of one shape, their starts in one batched_box_ascent (each
    instance's rows climb as they would alone, to rounding (_values): its points, iterations and evaluations)."""
    owner = np.repeat(np.arange(len(climbs)), [c.starts.shape[0] for c in climbs])
    bound = np.vstack([np.broadcast_to(c.bound, c.starts.shape) for c in climbs])
    max_iter = max(c.max_iter for c in climbs)
    if any(c.max_iter != max_iter for c in climbs):
        raise ModelError("climb_together: the instances' max_iter differ; climb each group of one max_iter together")
    counts: dict[str, np.ndarray] = {}
    xs, rho, _, _ = batched_box_ascent(_values(climbs, owner), bound, np.vstack([c.starts for c in climbs]),
                                       max_iter, indexed=True, counts=counts)
    runs = []
    for i, c in enumerate(climbs):
        rows = np.flatnonzero(owner == i)
        runs.append(_climbed(c, xs[rows], rho[rows], *group_counts(counts, rows, max_iter)))
    return runs


def destabilize(prep: Prepared, *, starts: int | None = None, seed: Any = 0, max_iter: int | None = None,
                pool: int | None = None, **unknown: Any) -> MethodRun:
    """Method: maximize a spectral-radius objective over a symmetric box where the lower level ignores x: `starts`
    points ascend together (batched_box_ascent) for up to max_iter steps, the box's centre and the largest-rho points of
    a pool of `pool` random ones (half uniform, half vertices, drawn from `seed`). Returns the ascents' best point (not
    a certified local maximum). None takes the registry's value, defaults["destabilize.NAME"] (bilevel.defaults)."""
    check_options("destabilize", unknown, destabilize)
    return climb_together([_climb(prep, starts, seed, max_iter, pool)])[0]


def _gather(prep: Prepared, options: dict[str, Any]) -> Climb | None:
    """The loaded instance's climb (destabilize's options), None (alone) where its M is not affine in x."""
    check_options("destabilize", {k: v for k, v in options.items() if k not in ("starts", "seed", "max_iter", "pool")},
                  destabilize)
    prep.runs += 1  # a run of its own, as solve starts one: its learner is not continued from another instance's
    c = _climb(prep, options.get("starts"), options.get("seed", 0), options.get("max_iter"), options.get("pool"))
    return None if c.m0 is None else c


def _run_together(climbs: list[Climb], options: dict[str, Any]) -> list[MethodRun]:
    """climb_together on groups of at most defaults["batch.max_rows"] instances of one max_iter."""
    return in_groups(climbs, lambda c: c.max_iter, climb_together)


register_batch(destabilize, BatchMethod(_gather, _run_together))
