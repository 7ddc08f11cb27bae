"""What every method receives (a prepared problem) and returns (a MethodRun), and how runs become results."""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Callable, Iterable

import casadi as ca
import numpy as np

from ...canonical import (CanonicalBilevel, Canonicalize, NormalizeSense, in_sense, kkt_solution, objectives,
                         suggested_starts)
from ...certificate import LOCAL_EVIDENCE, Certificate, GlobalBound, certify_point
from ...defaults import param
from ...errors import BilevelError, LowerLevelUnbounded, ModelError, UnknownOption, did_you_mean
from ...model import BilevelProblem
from ...mpcc import MPCC
from ...reduction import Chain, KKTInverse, KKTPoint, SingleLevelReduction
from ...result import BilevelResult, Status
from ..verdict.optimistic import optimistic_selection
from .options import RENAMED_OPTIONS
from ..verdict.probe import LowerSolve, probe_neighbours
from .projections import Projection
from .structure import Ball, ball_forms, find_balls, upper_projection


@dataclass
class Prepared:
    """A problem after canonicalization and sense normalization, with its (lazily built) MPCC.

    It is kept on the problem and reused by the next solve while no declaration changes; quantities that depend
    on parameter values (balls, projection) are recomputed after a set_value, the symbolic set-ups are not.
    """

    problem: BilevelProblem
    canon: CanonicalBilevel
    front: Chain
    front_inverse: list[Any]
    memo: dict[str, Any] = field(default_factory=dict)
    """Methods' symbolic set-ups (compiled functions), built once per declaration."""
    values_revision: int = 0
    runs: int = 0
    """Solves begun on this preparation (bilevel.solve counts them): state a method keeps between evaluations, such as
    the SDP continuation's last solution, is not carried into another solve, so a result depends on its call only."""

    def cached(self, key: tuple[Any, ...], build: Any) -> Any:
        """memo[key], built by build() on first use (a method's symbolic set-up, shared by later solves)."""
        if key not in self.memo:
            self.memo[key] = build()
        return self.memo[key]

    def refresh(self) -> None:
        """Bring value-dependent caches up to date with the problem's parameter values and suggested starts."""
        canon = self.canon
        canon.x_suggested = suggested_starts(self.problem, canon.x_start, canon.x_lb, canon.x_ub)
        if canon.params.revision != self.values_revision:
            canon.lower.check_convexity()  # the declaration's convexity check, on the new values
            for name in ("balls", "projection"):
                self.__dict__.pop(name, None)
            self.values_revision = canon.params.revision

    def rebox(self, lb: np.ndarray, ub: np.ndarray) -> None:
        """Give the upper variables the box [lb, ub] (flat), in the declaration and here: every later method, the
        certificate and the probe use it, while the symbolic set-ups, the lower level and its solutions are kept
        (attacks on one instance at several budgets)."""
        canon = self.canon
        lb, ub = np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)
        if lb.shape != canon.x_lb.shape or ub.shape != canon.x_ub.shape or np.any(lb > ub):
            raise ModelError(f"rebox: lb and ub must be {canon.x_lb.size} bounds with lb <= ub")
        start = 0
        for v in canon.upper_vars:
            v.lb[:], v.ub[:] = lb[start: start + v.size], ub[start: start + v.size]  # the declared (frozen) variable
            start += v.size
        canon.x_lb, canon.x_ub = lb.copy(), ub.copy()
        canon.x_start = np.clip(canon.x_start, lb, ub)
        for name in ("balls", "projection", "reduction"):
            self.__dict__.pop(name, None)
        self.refresh()

    @cached_property
    def balls(self) -> list[Ball]:
        """Upper constraints recognized as Euclidean balls on blocks of x (projected on, not penalized)."""
        return find_balls(self.canon, self.cached(("ball-forms",), lambda: ball_forms(self.canon)))

    @cached_property
    def projection(self) -> Projection:
        """Projection onto the upper box intersected with the recognized balls."""
        return upper_projection(self.canon, self.balls)

    @cached_property
    def reduction(self) -> tuple[MPCC, KKTInverse]:
        if self.canon.spectral is not None:
            raise ModelError(f"{self.problem.name}: a numeric objective of a matrix (maximize_spectral_radius, "
                             "maximize_matrix_function) has no CasADi expression for the KKT reformulation of methods "
                             "ipopt, relaxation and global; use method 'hypergradient' or 'differential-evolution'")
        return SingleLevelReduction().apply(self.canon)

    @property
    def mpcc(self) -> MPCC:
        return self.reduction[0]

    @cached_property
    def layout(self) -> KKTInverse:
        """Where x, y and the multipliers sit in the MPCC vector (known without building the MPCC)."""
        return SingleLevelReduction.layout(self.canon)

    def declared(self, F: float) -> float:
        """A canonical (minimized) upper objective value in the problem's declared sense, as results report it."""
        return in_sense(F, self.problem.upper_objective.sense)

    def point(self, w: np.ndarray) -> KKTPoint:
        """The canonical point of an MPCC vector."""
        return SingleLevelReduction().invert(w, self.layout)

    def pack(self, point: KKTPoint) -> np.ndarray:
        """The MPCC vector of a canonical point."""
        return SingleLevelReduction.pack(point, self.layout)

    def lower_point(self, x: np.ndarray) -> KKTPoint:
        """Upper point x with the lower level solved there (independent solver) and its multipliers."""
        sol = self.canon.lower.solve(x)
        return KKTPoint(np.asarray(x, dtype=float), sol.y, sol.lam, sol.mu, sol.Z)


def _declaration_key(problem: BilevelProblem) -> tuple[Any, ...]:
    return (problem.revision, len(problem.variables), len(problem.upper_constraints), len(problem.lower_constraints),
            len(problem.lower_psd_constraints), len(problem.parameters), id(problem.upper_objective),
            id(problem.lower_objective), id(problem.lower_matrices))


def prepare(problem: BilevelProblem) -> Prepared:
    """Canonicalize and normalize senses; classification and convexity checks of the lower level run here.

    The preparation is cached on the problem: a solve after set_value (or suggest_start) reuses it.
    """
    key = _declaration_key(problem)
    cached = problem.__dict__.get("_prepared")
    if cached is not None and cached[0] == key:
        cached[1].refresh()
        return cached[1]
    _ = problem.parameters.value  # every parameter needs a value before anything is built
    front = Chain([Canonicalize(), NormalizeSense()])
    canon, inverse = front.apply(problem)
    _ = canon.lower  # classify now so a bad lower level fails before any solve
    prep = Prepared(problem, canon, front, inverse, values_revision=canon.params.revision)
    problem.__dict__["_prepared"] = (key, prep)
    return prep


@dataclass
class MethodRun:
    """A method's raw outcome: its best MPCC vector (or None) and its own view of convergence. The "objective" of its
    history and start_records (one per multistart start) is the canonical (minimized) upper objective; finalize
    reports it declared."""

    w: np.ndarray | None
    status: Status
    message: str
    nit: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)
    start_records: list[dict[str, Any]] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    feasible_set: Projection | None = None
    """The upper set the method searched when narrower than the declared one (a `projection` option)."""
    global_bound: GlobalBound | None = None
    at_goal: bool = False
    """Whether the caller's callback ended the method where its goal was reached (not at a local solution)."""
    lower_solve: LowerSolve | None = None
    """The method's own solver of a unique lower solution (a structured learner's), which the local probe uses in
    place of the lower level's."""


def unbounded_lower(prep: Prepared, x: np.ndarray) -> str | None:
    """Why a method found no KKT point, where the reason is that the lower level is unbounded below at x (its KKT
    system then has no solution, which is not an infeasible problem); None otherwise."""
    try:
        prep.canon.lower.solve(x)
    except LowerLevelUnbounded as exc:
        return (f"lower level unbounded, not an infeasible problem: {exc}; the KKT system has no solution there "
                "(bound the lower variables or add lower constraints)")
    except BilevelError:
        pass
    return None


def best_of(candidates: list[tuple[np.ndarray, float, float]]) -> int:
    """Index of the feasible candidate (residual <= defaults["solvers.feasibility_tol"]) with the lowest objective, else
    the least infeasible one. Objectives within defaults["solvers.tie_rtol"] (relative) of the lowest are tied, and
    the first of them wins: starts that reach one local solution differ in the last bits, which the BLAS kernel
    decides (deepc-tracking's default: start 5 under one OpenBLAS kernel, 6 under another)."""
    tol = param("solvers.feasibility_tol")
    feasible = [i for i, (_, _, r) in enumerate(candidates) if r <= tol]
    values = [candidates[i][1] for i in feasible]
    if any(v == v for v in values):  # some objective that is not NaN
        lowest = min(v for v in values if v == v)
        bar = lowest + param("solvers.tie_rtol") * max(1.0, abs(lowest)) if np.isfinite(lowest) else lowest
        return next(i for i, v in zip(feasible, values) if v <= bar)
    if feasible:
        return feasible[0]
    return min(range(len(candidates)), key=lambda i: candidates[i][2])


def options_of(method: Callable[..., Any]) -> frozenset[str]:
    """The options a method accepts: the keyword-only parameters of its signature (scipy's _minimize_* style)."""
    return frozenset(name for name, p in inspect.signature(method).parameters.items()
                     if p.kind is inspect.Parameter.KEYWORD_ONLY)


def check_options(method: str, given: dict[str, Any], accepted: Callable[..., Any] | Iterable[str]) -> None:
    """Raise UnknownOption naming the options `given` that a method does not accept, and those it accepts: the
    keyword-only parameters of `accepted` where it is the method's function (given: what its **unknown collected),
    else the names listed; an option renamed within the last release names its new name (RENAMED_OPTIONS)."""
    allowed = options_of(accepted) if callable(accepted) else frozenset(accepted)
    unknown = sorted(set(given) - allowed)
    if not unknown:
        return
    renamed = [f"{old} was renamed: use {RENAMED_OPTIONS[method][old]}" for old in unknown
               if old in RENAMED_OPTIONS.get(method, {})]
    if renamed:
        raise UnknownOption(f"method {method!r}: option {'; option '.join(renamed)}")
    raise UnknownOption(f"method {method!r} does not take option(s) {', '.join(unknown)}; "
                        f"{did_you_mean(unknown[0], allowed)}it accepts: {', '.join(sorted(allowed))}")


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
                   status: Status, message: str) -> tuple[Status, str]:
    """NOT_LOCALLY_OPTIMAL when a lower solution at x gives a lower F than the method's (a non-unique lower
    level: the optimistic selection) or the probe finds a better feasible neighbour; else the status as is."""
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
    outcome = probe_neighbours(prep, point.x, F, run.feasible_set or prep.projection, optimistic=ambiguous,
                               lower_solve=run.lower_solve)
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


def finalize(prep: Prepared, run: MethodRun, method: str, wall_time: float, tol: float | None = None) -> BilevelResult:
    """Certify the run's point (up to tol; None: defaults["certificate.tol"]), map it back to declared names and
    senses, and decide the status."""
    run = replace(run, history=list(_declared_records(prep, run.history)),
                  start_records=list(_declared_records(prep, run.start_records)))
    if run.w is None or not np.all(np.isfinite(run.w)):
        bounds = None if run.global_bound is None else Certificate.bounds_only(run.global_bound)
        return BilevelResult(run.status if run.status is not Status.SOLVED else Status.ERROR, run.message, method,
                             prep.problem.name, {}, {}, {}, None, None, bounds, wall_time, run.nit,
                             tuple(run.history), tuple(run.start_records), run.stats)
    point = prep.point(run.w)
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
        status, message = _local_verdict(prep, run, point, cert, stats, status, message)
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
