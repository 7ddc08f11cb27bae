"""The generic target's mechanism: method "global" on the user's BilevelProblem bounds the attacker's objective over
its whole budget set; the bound is re-checked by a second global algorithm (MILP, branch-and-bound on the pairs or
SCIP, whichever else accepts the problem). With no second algorithm the bound stands unchecked: `unknown`."""

from __future__ import annotations

import time
from typing import Any

from ..errors import BilevelError
from ..solvers.registry import solve
from .target import Target, register_mechanism
from .verdict import Check, Evidence, Proof

ALGORITHMS = ("milp", "branch-and-bound", "scip")


def _run(problem: Any, algorithm: str, options: dict[str, Any]) -> tuple[str, float, float, bool] | None:
    """(algorithm used, bound on the declared maximum, best value found, proven) of method global, None where the
    algorithm does not accept the problem."""
    try:
        result = solve(problem, method="global", algorithm=algorithm, **options)
    except BilevelError:
        return None
    bound = None if result.certificate is None else result.certificate.global_bound
    if bound is None:
        return None
    return str(result.stats.get("algorithm", algorithm)), bound.upper_bound, bound.lower_bound, bound.proven


def global_bound(target: Target, delta: float | None, options: dict[str, Any]) -> Evidence | None:
    """A proven upper bound on a maximizing upper objective over the declared budget set (module docstring)."""
    problem = target.declaration
    if problem.upper_objective is None or problem.upper_objective.sense != "max":
        return None
    t0 = time.perf_counter()
    solver_options = {k: options[k] for k in ("time_limit", "node_limit", "gap") if k in options}
    first = _run(problem, "auto", solver_options)
    if first is None or not first[3]:
        return Evidence("global", Proof.UNKNOWN, "method global did not prove a bound", {}, Check(False, "no bound"),
                        time.perf_counter() - t0)
    name, bound, best, _ = first
    others = [r for a in ALGORITHMS if not name.startswith(a)
              and (r := _run(problem, a, solver_options)) is not None and r[3] and not r[0].startswith(name)]
    numbers = {"bound": bound, "best": best}
    if not others:
        check = Check(False, f"the bound is {name}'s alone: no second global algorithm accepts this problem")
    else:
        other = others[0]
        tol = float(options.get("gap", 1e-6)) * max(1.0, abs(bound)) * 2
        agree = abs(other[1] - bound) <= tol + abs(bound - best) + abs(other[1] - other[2])
        check = Check(agree, f"{other[0]} bounds the maximum by {other[1]:.10g} against {name}'s {bound:.10g}",
                      {"second_bound": other[1], "tolerance": tol})
        numbers["bound"] = max(bound, other[1])
    return Evidence("global", Proof.BOUNDED, f"the attacker's objective is at most {numbers['bound']:.10g} over the "
                    f"declared budget set (best attack found {best:.10g})", numbers, check, time.perf_counter() - t0)


register_mechanism("generic", global_bound, "global")
