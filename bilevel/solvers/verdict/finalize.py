"""The verdict on a method's run: certify its point, probe its neighbourhood, check the optimistic selection, and
decide the result's status (finalize)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import casadi as ca
import numpy as np

from ...canonical import kkt_solution, objectives
from ...certificate import LOCAL_EVIDENCE, Certificate, certify_point
from ...defaults import param
from ...errors import BilevelError
from ...reduction import KKTPoint
from ...result import BilevelResult, Status
from ..engine.prepared import MethodRun, Prepared
from .optimistic import optimistic_selection
from .probe import ProbeOutcome, probe_neighbours


def _final_status(run: MethodRun, passed: bool) -> tuple[Status, str]:
    if passed and run.global_bound is not None:  # a global run's status is its verdict on the bound
        return run.status, f"{run.message}; certificate passed"
    if passed:
        if run.status is Status.SOLVED:
            return Status.SOLVED, "converged; certificate passed (a local solution of the bilevel problem)"
        return Status.INACCURATE, f"backend stopped with {run.status.value} ({run.message}); certificate passed"
    if run.status in (Status.SOLVED, Status.INACCURATE):
        return Status.CERTIFICATE_FAILED, f"backend reported {run.status.value} but the certificate failed"
    return run.status, run.message


def _local_verdict(prep: Prepared, run: MethodRun, point: KKTPoint, cert: Certificate, stats: dict[str, Any],
                   status: Status, message: str, probed: ProbeOutcome | None = None) -> tuple[Status, str]:
    """NOT_LOCALLY_OPTIMAL when a lower solution at x gives a lower F than the method's (a non-unique lower
    level: the optimistic selection) or the probe finds a better feasible neighbour; else the status as is.
    probed: the probe's outcome at the point, found beforehand (bilevel.solvers.verdict.batch_probe), used where the
    lower solution is unique."""
    F = objectives(prep.canon, point)[0]
    # the lower solution set at x may hold better responses (LMI lower levels: not checked, IPOPT cannot take them)
    ambiguous = not cert.lower_unique and not prep.canon.lower.psd
    if ambiguous:
        starts = [point.y] + ([np.asarray(cert.lower_reference_y)] if np.all(np.isfinite(cert.lower_reference_y))
                              else [])
        sel = optimistic_selection(prep, point.x, cert.lower_reference, starts)
        stats["optimistic"] = None if sel is None else {"y": sel.y, "objective": prep.declared(sel.objective)}
        if sel is not None and sel.improves(F):
            return Status.NOT_LOCALLY_OPTIMAL, (
                f"not a local solution of the optimistic bilevel problem: the lower solution is not unique at x and "
                f"the method's selection is not the optimistic one; the lower solution in stats['optimistic'] gives "
                f"upper objective {prep.declared(sel.objective):.8g} (here {prep.declared(F):.8g}) ({message})")
    outcome = probed if probed is not None and not ambiguous else probe_neighbours(
        prep, point.x, F, run.feasible_set or prep.projection, optimistic=ambiguous, lower_solve=run.lower_solve)
    better = outcome.better
    stats["probe"] = None if better is None else {"x": better.x, "objective": prep.declared(better.objective),
                                                  "radius": better.radius}
    if better is None and outcome.nonconvex is not None:
        xp, radius, why = outcome.nonconvex
        stats["probe"] = {"x": xp, "nonconvex": why, "radius": radius}
        return Status.INACCURATE, (
            f"{message}; but the lower level is not convex at a neighbour at relative distance {radius:g} ({why}): "
            "x is at the edge of where it is convex, and beyond that edge the lower solutions, hence the upper "
            "objective, are not what the method computes, so x is not shown to be a local solution (the point is in "
            "stats['probe'])")
    if better is None:
        return status, message
    advice = ("the method stopped where the callback's goal was reached, not at a local solution" if run.at_goal
              else "try more starts or another method")
    return Status.NOT_LOCALLY_OPTIMAL, (
        f"not a local solution: a feasible point at relative distance {better.radius:g} has upper objective "
        f"{prep.declared(better.objective):.8g} (here {prep.declared(F):.8g}), so the method's point is not optimal "
        f"({message}); {advice}")


def _not_a_lower_solution(prep: Prepared, point: KKTPoint, cert: Certificate) -> bool:
    """Whether the certificate shows that the method's y is not a lower solution at x where its independent re-solve
    found one (finite y_ref): y differs from the unique re-solved y through F (lower_solution), breaks a lower
    constraint (lower_feasibility), or its lower objective exceeds the re-solve's (lower_gap; where y's is the lower
    one, the re-solve is the suspect). finalize then reports (x, y_ref), so that a result's objective is always the
    one its x gets from the lower level, whatever the status (an IV learner solved by normal equations at
    cond(Z'Phi) = 1e8 gave F = 79.4 where the learner gives 48.7)."""
    if not np.all(np.isfinite(cert.lower_reference_y)):
        return False
    if {"lower_solution", "lower_feasibility"} & set(cert.failed):
        return True
    f, f_ref = float(prep.canon.lower.evaluate(point.x, point.y)[0]), cert.lower_reference
    return "lower_gap" in cert.failed and f_ref < f - cert.tolerance * (1.0 + abs(f_ref))


def _declared_records(prep: Prepared, records: list[dict[str, Any]]) -> tuple[dict[str, Any], ...]:
    """A run's per-start or per-iteration records with their upper "objective" in the declared sense."""
    return tuple(r | {"objective": prep.declared(r["objective"])} if r.get("objective") is not None else r
                 for r in records)


def _start_spread(prep: Prepared, records: list[dict[str, Any]]) -> dict[str, Any] | None:
    """How far apart a multistart's feasible starts ended (declared-sense objectives), where some start ended more
    than defaults["solvers.spread_rtol"] (relative; at least the feasibility tolerance, absolute) from the best; None
    where they agree or there is one start."""
    tol = param("solvers.feasibility_tol")
    values = [float(r["objective"]) for r in records
              if r.get("objective") is not None and np.isfinite(r["objective"]) and r.get("residual", 0.0) <= tol]
    if len(values) < 2:
        return None
    sign = -1.0 if prep.problem.upper_objective.sense == "max" else 1.0  # sign * value: lower is better
    ordered = sorted(values, key=lambda v: sign * v)
    best = ordered[0]  # apart: farther than spread_rtol relative, and than the feasibility tolerance absolute
    bar = max(param("solvers.spread_rtol") * abs(best), tol)
    apart = [v for v in ordered if abs(v - best) > bar]
    if not apart:
        return None
    return {"starts": len(values), "best": best, "reached_best": len(values) - len(apart), "second": apart[0],
            "worst": apart[-1]}


def finalize(prep: Prepared, run: MethodRun, method: str, wall_time: float, tol: float | None = None,
             probed: ProbeOutcome | None = None) -> BilevelResult:
    """Certify the run's point (up to tol; None: defaults["certificate.tol"]), map it back to declared names and
    senses, and decide the status; probed: the local probe's outcome at the run's point where it is known (a batch's,
    bilevel.solvers.verdict.batch_probe), else the probe runs here."""
    run = replace(run, history=list(_declared_records(prep, run.history)),
                  start_records=list(_declared_records(prep, run.start_records)))
    if run.w is None or not np.all(np.isfinite(run.w)):
        bounds = None if run.global_bound is None else Certificate.bounds_only(run.global_bound)
        return BilevelResult(run.status if run.status is not Status.SOLVED else Status.ERROR, run.message, method,
                             prep.problem.name, {}, {}, {}, None, None, bounds, wall_time, run.nit,
                             tuple(run.history), tuple(run.start_records), run.stats)
    point = own = prep.point(run.w)
    try:
        cert = certify_point(prep.canon, point, tol, prep.problem.upper_objective.sense)
        if run.global_bound is not None:
            cert = replace(cert, global_bound=run.global_bound)
    except BilevelError as exc:  # evaluation failed: keep the point, say why
        cert = None
        run = MethodRun(run.w, Status.ERROR, f"certificate could not be computed: {exc}", run.nit, run.history,
                        run.start_records, run.stats)
    status, message = _final_status(run, cert is not None and cert.passed)
    if status is Status.SOLVED and cert is not None and not cert.convexity_proven:
        status, message = Status.INACCURATE, f"{message}; {LOCAL_EVIDENCE}"
    if cert is not None and not cert.passed:
        message += f"; certificate failed on {cert.describe_failures()}"
    stats = dict(run.stats)
    if cert is not None and _not_a_lower_solution(prep, point, cert):
        # report the bilevel-feasible point (x, y_ref): the objective is the one the lower level gives at x
        method_F = prep.front.invert(kkt_solution(prep.canon, point), prep.front_inverse).upper_objective
        stats |= {"method_y": point.y.tolist(), "method_upper_objective": method_F}
        point = replace(point, y=np.asarray(cert.lower_reference_y), lam=np.zeros_like(point.lam),
                        mu=np.zeros_like(point.mu), Z=[np.zeros_like(z) for z in point.Z])
        message += ("; y and the upper objective are reported at the re-solved lower solution (bilevel feasible), "
                    "multipliers zeroed; the method's y is in stats['method_y']")
    proven = run.global_bound is not None and run.global_bound.proven  # a global proof needs no local probe
    if status in (Status.SOLVED, Status.INACCURATE) and not proven:
        status, message = _local_verdict(prep, run, point, cert, stats, status, message,
                                         probed if point is own else None)  # not at the re-solved y
    if not proven and (spread := _start_spread(prep, run.start_records)) is not None:
        stats["starts_spread"] = spread
        message += (f"; the {spread['starts']} feasible starts ended apart: {spread['reached_best']} at the best "
                    f"{spread['best']:.6g}, the others between {spread['worst']:.6g} and {spread['second']:.6g} "
                    f"(several local answers; more starts, e.g. starts={4 * spread['starts']}, may find a better one)")
    sol = prep.front.invert(kkt_solution(prep.canon, point), prep.front_inverse)
    values = np.concatenate([point.x, point.y, prep.canon.params.value])

    def evaluate(expr: Any) -> Any:  # the symbols are gathered on use: for thousands of entries that takes ms
        syms = ca.vertcat(prep.canon.x, prep.canon.y, prep.canon.params.sym)
        return ca.evalf(ca.substitute(prep.problem.explicit(expr), syms, ca.DM(values)))

    return BilevelResult(status, message, method, prep.problem.name, sol.x, sol.y, sol.multipliers,
                         sol.upper_objective, sol.lower_objective, cert, wall_time, run.nit, tuple(run.history),
                         tuple(run.start_records), stats, evaluate)
