"""What every method receives (a prepared problem) and returns (a MethodRun); the verdict on a run is
bilevel.solvers.verdict.finalize."""

from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from typing import Any, Callable, Iterable

import casadi as ca
import numpy as np

from ...canonical import (CanonicalBilevel, Canonicalize, NormalizeSense, in_sense, kkt_solution, objectives,
                          suggested_starts)
from ...certificate import LOCAL_EVIDENCE, Certificate, GlobalBound, certify_point
from ...defaults import param
from ...errors import (RENAMES_REMOVED_IN, BilevelError, LowerLevelUnbounded, ModelError, UnknownOption, did_you_mean,
                       renamed)
from ...model import BilevelProblem
from ...mpcc import MPCC
from ...reduction import Chain, KKTInverse, KKTPoint, SingleLevelReduction
from ...result import BilevelResult, Status
from .options import RENAMED_OPTIONS
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
    bounds_revision: int = 0
    """The problem's bounds_revision whose box canon holds (BilevelProblem.set_bounds)."""
    runs: int = 0
    """Solves begun on this preparation (bilevel.solve counts them): state a method keeps between evaluations, such as
    the SDP continuation's last solution, is not carried into another solve, so a result depends on its call only."""

    def cached(self, key: tuple[Any, ...], build: Any) -> Any:
        """memo[key], built by build() on first use (a method's symbolic set-up, shared by later solves)."""
        if key not in self.memo:
            self.memo[key] = build()
        return self.memo[key]

    def refresh(self) -> None:
        """Bring value-dependent caches up to date with the problem's parameter values, upper box (set_bounds) and
        suggested starts."""
        canon = self.canon
        if self.problem.bounds_revision != self.bounds_revision:
            self._read_box()
        canon.x_suggested = suggested_starts(self.problem, canon.x_start, canon.x_lb, canon.x_ub)
        if canon.params.revision != self.values_revision:
            canon.lower.check_convexity()  # the declaration's convexity check, on the new values
            for name in ("balls", "projection"):
                self.__dict__.pop(name, None)
            self.values_revision = canon.params.revision

    def _read_box(self) -> None:
        """The upper box from the declared variables after set_bounds, the start clipped into it: every later
        method, the certificate and the probe use it, while the symbolic set-ups, the lower level and its solutions
        are kept (attacks on one instance at several budgets); balls, projection and the MPCC are rebuilt on use."""
        canon = self.canon
        canon.x_lb = np.concatenate([v.lb for v in canon.upper_vars]) if canon.upper_vars else np.zeros(0)
        canon.x_ub = np.concatenate([v.ub for v in canon.upper_vars]) if canon.upper_vars else np.zeros(0)
        canon.x_start = np.clip(canon.x_start, canon.x_lb, canon.x_ub)
        for name in ("balls", "projection", "reduction"):
            self.__dict__.pop(name, None)
        self.bounds_revision = self.problem.bounds_revision

    def rebox(self, lb: np.ndarray, ub: np.ndarray) -> None:
        """Deprecated (removed in bilevel 0.2.0): the flat box [lb, ub] of all upper variables, given to the problem by
        BilevelProblem.set_bounds per variable, which is what to call instead."""
        warnings.warn(f"Prepared.rebox is deprecated and will be removed in bilevel {RENAMES_REMOVED_IN}: declare the "
                      "box with BilevelProblem.set_bounds(name, lb, ub)", DeprecationWarning, stacklevel=2)
        canon = self.canon
        lb, ub = np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)
        if lb.shape != canon.x_lb.shape or ub.shape != canon.x_ub.shape or np.any(lb > ub):
            raise ModelError(f"rebox: lb and ub must be {canon.x_lb.size} bounds with lb <= ub")
        for name, part in self.problem.upper_layout().items():
            self.problem.set_bounds(name, lb[part], ub[part])
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
    prep = Prepared(problem, canon, front, inverse, values_revision=canon.params.revision,
                    bounds_revision=problem.bounds_revision)
    problem.__dict__["_prepared"] = (key, prep)
    return prep


LowerSolve = Callable[[np.ndarray], "list[np.ndarray | None]"]
"""A structured solver of a lower level with a unique solution: the rows of a matrix of upper points -> y* at each
(None where it has none)."""


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
    """The options a method accepts: the keyword-only parameters of its signature (scipy's _minimize_* style); kept
    per method (a batch checks every instance's options, and inspect.signature costs about 0.3 ms)."""
    try:
        return _keyword_only(method)
    except TypeError:  # an unhashable callable: not kept
        return _keyword_only.__wrapped__(method)


@lru_cache(maxsize=256)
def _keyword_only(method: Callable[..., Any]) -> frozenset[str]:
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
    moved = [renamed(old, RENAMED_OPTIONS[method][old]) for old in unknown if old in RENAMED_OPTIONS.get(method, {})]
    if moved:
        raise UnknownOption(f"method {method!r}: option {'; option '.join(moved)}")
    raise UnknownOption(f"method {method!r} does not take option(s) {', '.join(unknown)}; "
                        f"{did_you_mean(unknown[0], allowed)}it accepts: {', '.join(sorted(allowed))}")
