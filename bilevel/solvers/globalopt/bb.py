"""Branch-and-bound over the complementarity pairs of a LinearMPCC, best bound first, no big-M needed.

Each node fixes some pairs to a side (G_i = 0 or H_i = 0) and solves the convex relaxation of the rest
(nodes.py). A node whose relaxation is complementary is closed by re-solving it with every pair fixed to
the side its point selects (an exact MPCC point, the incumbent candidate); otherwise the most violated pair
(largest min(G_i, H_i)) is branched on. This is the classical scheme of Bard & Moore (1990), "A branch and bound
algorithm for the bilevel programming problem", SIAM J. Sci. Stat. Comput. 11:281-292, with relaxations solved
by HiGHS (LP) or Clarabel (QP) and node selection by the lowest bound.
"""

from __future__ import annotations

import heapq
import itertools
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ...defaults import param
from .nodes import G_SIDE, H_SIDE, Relaxation


@dataclass
class SearchOutcome:
    """Best point found, proven bounds on the optimal value (minimization form), and how the search ended.

    ended: "proven" (tree exhausted or gap closed), "infeasible", "unbounded", "time_limit" or "node_limit".
    """

    w: np.ndarray | None
    lower: float
    upper: float
    nodes: int
    ended: str
    failed_nodes: int = 0
    history: list[dict[str, float]] = field(default_factory=list)
    note: str = ""
    """Why a search "failed", where the solver said (e.g. SCIP's error)."""


def relative_gap(lower: float, upper: float) -> float:
    """(upper - lower) / max(1, |upper|): the gap the status is judged by (inf without an incumbent)."""
    if not np.isfinite(upper) or not np.isfinite(lower):
        return np.inf
    return max(upper - lower, 0.0) / max(1.0, abs(upper))


def sides_of(relax: Relaxation, w: np.ndarray) -> dict[int, int]:
    """The branch a point selects: G_i = 0 where G_i <= H_i, else H_i = 0."""
    f = relax.form
    G, H = f.G @ w + f.g, f.H @ w + f.h
    return {i: G_SIDE if G[i] <= H[i] else H_SIDE for i in range(f.n_pairs)}


Guess = Callable[[np.ndarray], "dict[int, int] | None"]
"""A heuristic: from a relaxation point, the sides of a branch likely to hold a good MPCC point (or None)."""


def branch_and_bound(relax: Relaxation, gap_tol: float, time_limit: float, node_limit: int,
                     guess: Guess | None = None, root: dict[int, int] | None = None) -> SearchOutcome:
    """Best-bound search until the relative gap is <= gap_tol, the tree is empty, or a limit is hit.

    `guess` (e.g. the lower level solved at the relaxation's x) proposes branches at the root and every 10th node;
    every point of a branch with all pairs fixed is MPCC-feasible, so each proposal can only improve the incumbent.
    `root` holds sides known to hold at every feasible point (derive_big_m's fixings).
    """
    f = relax.form
    t0 = time.perf_counter()
    best_w, upper = None, np.inf
    tie = itertools.count()
    heap: list[tuple[float, int, int, dict[int, int]]] = [(-np.inf, 0, next(tie), dict(root or {}))]
    closed_below = np.inf  # smallest bound of nodes dropped because they could not improve by more than the gap
    nodes = failed = 0
    history: list[dict[str, float]] = []
    unbounded = False

    def tolerance() -> float:
        return gap_tol * max(1.0, abs(upper)) if np.isfinite(upper) else 0.0

    def try_incumbent(fixed: dict[int, int]) -> None:
        nonlocal best_w, upper
        sol = relax.solve(fixed)
        if sol.status == "optimal" and sol.value < upper:
            best_w, upper = sol.w, sol.value

    ended = "proven"
    while heap:
        bound, _, _, fixed = heap[0]
        if bound >= upper - tolerance():
            closed_below = min(closed_below, bound)
            heapq.heappop(heap)
            continue
        if time.perf_counter() - t0 > time_limit:
            ended = "time_limit"
            break
        if nodes >= node_limit:
            ended = "node_limit"
            break
        heapq.heappop(heap)
        nodes += 1
        sol = relax.solve(fixed)
        if sol.status == "infeasible":
            continue
        if sol.status == "failed":  # unresolved: its parent's bound stays in the proof
            failed += 1
            closed_below = min(closed_below, bound)
            continue
        free = [i for i in range(f.n_pairs) if i not in fixed]
        if sol.status == "unbounded":
            if not free:
                unbounded = True
                break
            i = free[0]
            for side in (G_SIDE, H_SIDE):
                heapq.heappush(heap, (-np.inf, -len(fixed) - 1, next(tie), {**fixed, i: side}))
            continue
        if sol.value >= upper - tolerance():
            closed_below = min(closed_below, sol.value)
            continue
        w = sol.w
        G, H = f.G @ w + f.g, f.H @ w + f.h
        violation = {i: min(G[i], H[i]) for i in free}
        scale = 1.0 + float(np.abs(w).max(initial=0.0))
        worst = max(violation, key=violation.get) if free else None
        if worst is None or violation[worst] <= param("global.complementarity_tol") * scale:
            exact = {**sides_of(relax, w), **fixed}
            try_incumbent(exact)
            if upper <= sol.value + tolerance() or not free:
                closed_below = min(closed_below, sol.value)
                continue
        elif nodes == 1 or nodes % 10 == 0:  # heuristics for an early incumbent
            try_incumbent({**sides_of(relax, w), **fixed})
            proposal = guess(w) if guess is not None else None
            if proposal is not None:
                try_incumbent(proposal)
        for side in (G_SIDE, H_SIDE):
            heapq.heappush(heap, (sol.value, -len(fixed) - 1, next(tie), {**fixed, worst: side}))
        if nodes & (nodes - 1) == 0 or nodes % 1000 == 0:  # the bounds' trajectory at nodes 1, 2, 4, ... and every 1000
            history.append({"node": nodes, "lower": min(upper, closed_below, heap[0][0]), "upper": upper})
    if unbounded:
        return SearchOutcome(None, -np.inf, -np.inf, nodes, "unbounded", failed, history)
    lower = min([upper, closed_below] + [b for b, *_ in heap])
    if best_w is None and not heap and failed == 0:
        return SearchOutcome(None, np.inf, np.inf, nodes, "infeasible", failed, history)
    if ended == "proven" and failed:
        ended = "proven" if relative_gap(lower, upper) <= gap_tol else "unresolved_nodes"
    return SearchOutcome(best_w, lower, upper, nodes, ended, failed, history)
