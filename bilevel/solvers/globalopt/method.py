"""method="global": a proven global optimum for LP / convex-QP lower levels (scope in form.py).

Big-M bounds are derived by LPs (bigm.py). A linear upper objective with every bound finite goes to HiGHS
as a MILP (milp.py); otherwise (a convex-quadratic upper objective, or a pair with no finite bound) the
pairs are branched on directly (bb.py). A nonconvex leader (bilinear or polynomial upper objective,
nonlinear upper constraints), lower constraints nonlinear in x and an x-dependent lower Hessian go to SCIP's spatial
branch-and-bound on the same reformulation (scip.py).
The KKT reformulation is exact for these lower levels, so its global optimum is the optimistic bilevel optimum,
also when the lower solution is not unique.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ...certificate import GlobalBound
from ...defaults import param
from ...errors import BilevelError, ModelError
from ...result import Status
from ..engine.prepared import MethodRun, Prepared, check_options, unbounded_lower
from .bb import Guess, SearchOutcome, branch_and_bound, relative_gap, sides_of
from .bigm import derive_big_m, derive_bounds
from .form import linear_mpcc
from .milp import solve_milp
from .nodes import G_SIDE, Relaxation
from .scip import require_scip, scip_available, solve_scip, unbounded_nonconvex
from .slater import bound_multipliers, curved_rows
from ..engine.limits import progress

ALGORITHMS = ("auto", "milp", "branch-and-bound", "scip")


def _declared(outcome: SearchOutcome, sense: str) -> tuple[float, float]:
    """(lower bound, upper bound) on the optimal upper value in the declared sense."""
    if sense == "max":
        return -outcome.upper, -outcome.lower
    return outcome.lower, outcome.upper


def lower_response_guess(prep: Prepared, relax: Relaxation) -> Guess:
    """Guess: solve the lower level at the relaxation's x (independent solver); its KKT point selects a branch."""
    def guess(w: np.ndarray) -> dict[int, int] | None:
        try:
            return sides_of(relax, prep.pack(prep.lower_point(prep.point(w).x)))
        except BilevelError:  # lower level infeasible or failing at this x: no proposal
            return None

    return guess


def _verdict(outcome: SearchOutcome, name: str, summary: str, proven: bool) -> tuple[Status, str]:
    """Status and message of a finished search."""
    if outcome.ended == "infeasible":
        return Status.INFEASIBLE, f"{name}: the single-level problem is infeasible"
    if outcome.ended == "unbounded":
        return Status.ERROR, (f"{name}: the bilevel problem is unbounded (a branch's relaxation has no finite "
                              "optimum); add bounds on the upper variables")
    if proven:
        return Status.SOLVED, f"globally optimal (proven): {summary}"
    if outcome.ended == "failed":
        return Status.ERROR, f"{name} failed: {summary}"
    return Status.MAX_ITERATIONS, f"stopped ({outcome.ended}) before the gap closed: {summary}"


def solve_global(prep: Prepared, *, algorithm: str = "auto", time_limit: float | None = None,
                 node_limit: int | None = None, gap: float | None = None, starts: int | None = None, seed: Any = None,
                 verbose: bool = False, **unknown: Any) -> MethodRun:
    """Global optimum with a proof. An option left None takes the registry's value, defaults["global.NAME"]
    (bilevel.defaults).

    algorithm: "auto" | "milp" | "branch-and-bound" | "scip" (auto takes scip for a nonconvex leader when pyscipopt
    is installed); time_limit (seconds) and node_limit: the search stops there, status MAX_ITERATIONS; gap: it stops
    once (upper - lower bound) / max(1, |best|) is below this; verbose: a line per phase; starts and seed are
    accepted (the other methods' options, e.g. in a comparison) and unused: the method is deterministic."""
    check_options("global", unknown, solve_global)
    time_limit, node_limit = float(param("global.time_limit", time_limit)), int(param("global.node_limit", node_limit))
    gap_tol = float(param("global.gap", gap))
    if algorithm not in ALGORITHMS:
        raise ModelError(f"unknown algorithm {algorithm!r} for method 'global'; choose one of {', '.join(ALGORITHMS)}")
    if time_limit <= 0 or node_limit <= 0 or not 0 < gap_tol < 1:
        raise ModelError("method 'global' needs time_limit > 0, node_limit > 0 and 0 < gap < 1; got "
                         f"{time_limit}, {node_limit}, {gap_tol}")
    if algorithm == "scip":
        require_scip()
    t0 = time.perf_counter()
    form = linear_mpcc(prep, nonconvex_leader=algorithm == "scip" or (algorithm == "auto" and scip_available()))
    use_scip = algorithm == "scip" or (form.leader is not None and bool(form.leader.nonconvex))
    base = Relaxation(form)
    if base.solve({}).status == "infeasible":
        if (why := unbounded_lower(prep, prep.projection(prep.canon.x_start))) is not None:
            return MethodRun(None, Status.ERROR, why)
        return MethodRun(None, Status.INFEASIBLE, "the KKT reformulation is infeasible even without complementarity: "
                         "no upper point has a feasible lower level satisfying the upper constraints")
    big_m = derive_big_m(base)
    if big_m is None:
        return MethodRun(None, Status.INFEASIBLE, "the KKT reformulation is infeasible: some pair has both its slack "
                         "and its multiplier bounded away from zero on the relaxed KKT polyhedron")
    relax = Relaxation(form, big_m.slack, big_m.multiplier)
    progress(verbose, "global", f"big-M bounds derived for {form.n_pairs} pairs "
             f"({time.perf_counter() - t0:.1f} s)")
    use_milp = form.linear and big_m.finite and form.n_pairs > 0 and not use_scip
    if algorithm == "milp" and not use_milp:
        raise ModelError("algorithm 'milp' needs a linear upper objective and a finite derived big-M for every pair "
                         f"(here: linear objective {form.linear}, all bounds finite {big_m.finite}); use "
                         "algorithm='branch-and-bound' or 'auto'")
    use_milp = use_milp and algorithm != "branch-and-bound"
    remaining = max(time_limit - (time.perf_counter() - t0), 1e-3)
    free: list[str] = []
    slater = None
    if use_scip:
        name = "scip (spatial branch-and-bound, derived bounds)"
        box = derive_bounds(relax, big_m.fixed)
        free = unbounded_nonconvex(form.leader, box, prep.mpcc.blocks) if form.leader.nonconvex else []
        multipliers = [v for v in free if not v.startswith(("x[", "y["))]
        if multipliers or (prep.canon.lower.nonlinear and curved_rows(prep)):  # Slater: KKT exact, bounds
            box, big_m, slater = bound_multipliers(prep, form, box, big_m, multipliers)
            free = unbounded_nonconvex(form.leader, box, prep.mpcc.blocks)
            progress(verbose, "global", f"multiplier bounds from a Slater point ({time.perf_counter() - t0:.1f} s)")
        leaders = [v for v in free if v.startswith("x[")]
        if leaders and not form.leader.nonlinear_rows:  # with nonlinear rows, SCIP's propagation may bound them
            raise ModelError(f"algorithm 'scip' of method 'global' needs finite bounds on the leader's variables in "
                             f"nonconvex terms; {', '.join(leaders)} (canonical upper variables) have none, declared or "
                             "derived over the relaxed KKT polyhedron: declare bounds on them (lb=..., ub=... in "
                             "upper_variable); a box that holds an optimum leaves the optimal value unchanged")
        remaining = max(time_limit - (time.perf_counter() - t0), 1e-3)
        outcome = solve_scip(relax, big_m, box, gap_tol, remaining, node_limit)
    elif use_milp:
        name = "milp (HiGHS, derived big-M)"
        outcome = solve_milp(relax, big_m, gap_tol, remaining, node_limit)
    else:
        name = "branch-and-bound on the pairs"
        outcome = branch_and_bound(relax, gap_tol, remaining, node_limit, lower_response_guess(prep, relax),
                                   big_m.fixed)
    gap = relative_gap(outcome.lower, outcome.upper)
    proven = outcome.ended == "proven" and gap <= gap_tol
    sense = prep.problem.upper_objective.sense
    low, high = _declared(outcome, sense)
    used = "big-M used where finite, SOS1 elsewhere" if use_scip else ("big-M used" if use_milp else
                                                                        "big-M not used (hull cuts only)")
    justification = (used + ": each bound is an LP "
                     "maximum over the relaxed KKT polyhedron R; a side is forced where the other's LP minimum "
                     "over R is positive",) + big_m.justification() + (slater.justification() if slater else ())
    bound = GlobalBound(low, high, gap, gap_tol, proven, name, outcome.nodes, justification)
    stats = {"algorithm": name, "ended": outcome.ended, "nodes": outcome.nodes, "lower_bound": low,
             "upper_bound": high, "gap": gap, "failed_nodes": outcome.failed_nodes,
             "big_m_slack": big_m.slack.tolist(), "big_m_multiplier": big_m.multiplier.tolist(),
             "fixed_by_lp": {form.labels[i]: "G = 0" if side == G_SIDE else "H = 0" for i, side in big_m.fixed.items()}}
    history = [h if sense == "min" else {"node": h["node"], "lower": -h["upper"], "upper": -h["lower"]}
               for h in outcome.history]  # the bounds' trajectory, in the declared sense like the bounds
    summary = f"{name}: bounds [{low:.10g}, {high:.10g}], relative gap {gap:.2e}, {outcome.nodes} nodes"
    if outcome.note:
        summary += f"; {outcome.note}"
    if use_scip and free and not proven:
        summary += (f"; {', '.join(free)} enter nonconvex terms with no finite bound, which SCIP's relaxation needs: "
                    "declare bounds on them")
    status, message = _verdict(outcome, name, summary, proven)
    progress(verbose, "global", f"{summary} ({outcome.ended}, {time.perf_counter() - t0:.1f} s)")
    w = None if outcome.w is None or status is Status.INFEASIBLE else np.asarray(outcome.w, dtype=float)
    return MethodRun(w, status, message, outcome.nodes, history, [], stats, global_bound=bound)
