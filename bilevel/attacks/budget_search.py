"""The smallest attack budget that reaches a goal: an increasing budget path, then bisection (any attack, any goal)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

from ..errors import ModelError


@dataclass
class BudgetSearch:
    """The smallest budget at which the attack reached its goal (inf if no budget of the path did), and every run on
    the way: (budget, the attack's outcome) in run order."""

    delta: float
    runs: list[tuple[float, float]] = field(default_factory=list)


def smallest_budget(outcome: Callable[[float], float], reached: Callable[[float], bool], path: Sequence[float],
                    rel_tol: float = 0.05) -> BudgetSearch:
    """Run `outcome(budget)` along the increasing positive `path` until `reached(outcome)`, then bisect between the last
    budget that missed (0 before the path) and the first that reached, to a bracket of rel_tol times its top. Exact
    when reaching the goal is monotone in the budget (as for a global attack); a local attack's search is a bound."""
    path = [float(v) for v in path]
    if not path or path != sorted(path) or path[0] <= 0:
        raise ModelError(f"smallest_budget: path must be increasing and positive, got {tuple(path)}")
    if not rel_tol > 0:
        raise ModelError(f"smallest_budget: rel_tol must be > 0, got {rel_tol}")
    search = BudgetSearch(float("inf"))

    def hits(delta: float) -> bool:
        search.runs.append((delta, float(outcome(delta))))
        return bool(reached(search.runs[-1][1]))

    low = 0.0
    for high in path:
        if hits(high):
            break
        low = high
    else:
        return search
    while high - low > rel_tol * high:
        mid = 0.5 * (low + high)
        low, high = (low, mid) if hits(mid) else (mid, high)
    search.delta = high
    return search
