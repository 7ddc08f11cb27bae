"""The exact-block mode of `hypergradient` (and method `block-exact`): one block of upper variables is optimized
globally in closed form at every evaluation, the others by spectral projected hypergradient steps on the resulting
value function (Danskin).

A block x_S (a recognized ball ||x_S - c|| <= r, no other bound or constraint on it) is exact when
  - the lower level is an unconstrained strictly convex quadratic (least squares): y*(x) = -P(x)^{-1} q(x),
  - P does not depend on x_S and q is affine in x_S, so y*(x) = y_c + M z with z = x_S - c,
  - F does not depend on x_S and is quadratic in y (any curvature).
Then min_z F(y_c + M z) over ||z|| <= r is a trust-region subproblem in the row space of M (dimension
<= n_y), solved globally (More & Sorensen 1983). This is the exact input step of the VRFT attacks
(the learner's targets are affine in the input poisoning), found from the declared structure: lower levels
declared by expressions or by `lower_qp` (whose Hessian C'C + P is numeric and gradient q - C'd affine in d, q).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from dataclasses import replace
from typing import Any, Callable

import casadi as ca
import numpy as np
import scipy.sparse as sp
from scipy.linalg.lapack import dpocon, dpotrf, dtrtri

from ...canonical import CanonicalBilevel
from ...defaults import param
from ...errors import BilevelError, RankDeficientRegressor
from ...linear_maps import Gather
from ...lower.base import ExpressionLower, KKTValues, LowerLevel, LowerSolution
from ...lower.residual import ResidualLeastSquares
from ...lower.least_squares import factor_solve, hessian_factor
from ...lower.matrix import MatrixLower
from ...reduction import KKTPoint
from ...result import Status
from .ascent import projected_ascent
from .prepared import MethodRun, Prepared, best_of
from .implicit import Evaluation, shared_oracle
from .limits import Deadline, progress, stopped
from .projections import Blocks, Projection
from .starts import start_points
from .structure import Ball, budget_scale, depends
from .trust_region import maximize_quadratic_on_ball

SINGULAR_LEARNER = "singular_learner"
"""The key of a start record (a bool in every record of hypergradient and block-exact): the start could not begin,
or its ascent ended, on a learner without a unique solution (RankDeficientRegressor: at the start, or at every trial
point of the last line search)."""


def quadratic_block_step(M: np.ndarray, grad: np.ndarray, hess: np.ndarray, radius: float,
                         prefer: np.ndarray | None = None) -> np.ndarray:
    """The global minimizer z of F(y_c + M z) over ||z|| <= radius, F quadratic with gradient `grad` and Hessian
    `hess` at y_c: a trust-region subproblem, in the row space of M when M has far fewer rows than columns.
    Where several z tie (the hard case, e.g. +-z at a stationary centre) the one closest to `prefer` is returned."""
    if 2 * M.shape[0] > M.shape[1]:  # no reduction worth a decomposition: the subproblem in z itself
        return maximize_quadratic_on_ball(-0.5 * (M.T @ hess @ M), -0.5 * (M.T @ grad), radius, prefer)
    gram = M @ M.T  # M M' = L L': z = M' L^{-T} v has ||z|| = ||v|| and M z = L v ...
    L, info = dpotrf(gram, lower=True, clean=True)
    if info == 0 and dpocon(L, float(np.abs(gram).sum(axis=0).max()), uplo="L")[0] > 1e-10:
        inverse = dtrtri(L, lower=True)[0]
        reduced = None if prefer is None else inverse @ (M @ prefer)  # z . prefer = v . (L^{-1} M prefer)
        v = maximize_quadratic_on_ball(-0.5 * (L.T @ hess @ L), -0.5 * (L.T @ grad), radius, reduced)
        return M.T @ (inverse.T @ v)
    U, s, Vt = np.linalg.svd(M, full_matrices=False)  # ... unless M is ill-conditioned: the Gram matrix squares it
    keep = s > 1e-12 * max(float(s[0]) if s.size else 0.0, 1e-300)
    U, s, Vt = U[:, keep], s[keep], Vt[keep]
    A = -0.5 * (s[:, None] * (U.T @ hess @ U) * s[None, :])
    reduced = None if prefer is None else Vt @ prefer  # z . prefer = v . (Vt prefer) for z = Vt' v
    return Vt.T @ maximize_quadratic_on_ball(A, -0.5 * s * (U.T @ grad), radius, reduced)


@dataclass
class ExactBlock:
    """A ball block on which the reduced upper objective is a quadratic of a ball-constrained vector."""

    ball: Ball
    data: Callable
    """x -> (P, q, dq/dx_S, g, H): the lower Hessian, the lower gradient at y = 0 and its Jacobian in the block, the
    upper objective's gradient in y at y = 0 and its (constant in y) Hessian in y."""
    factor: np.ndarray | None = None
    """hessian_factor(P) when P is constant (the matrix form factors it once), else None: factored per evaluation."""

    def solve(self, x: np.ndarray) -> tuple[np.ndarray, LowerSolution, KKTValues]:
        """x with its block replaced by the global minimizer of F(x, y*(x)) over the ball (other entries fixed),
        the lower solution there (y*(x) = y_c + M z in closed form; its objective NaN, read with F by the
        hypergradient oracle) and its KKT values (an unconstrained minimizer with Hessian P)."""
        b = self.ball
        x = np.array(x, dtype=float)
        here = x[b.block] - b.center  # ties between optimal z are broken towards the block's current point
        prefer = here if np.any(here) else np.ones_like(here)
        x[b.block] = b.center
        P, q, jac_q, grad0, hess = self.data(x)
        factor = hessian_factor(P) if self.factor is None else self.factor  # P(x) for every z of the block
        y_c = -factor_solve(factor, q.ravel())
        jac_q = np.asarray(jac_q, dtype=float)
        if jac_q.shape[1] > jac_q.shape[0]:  # P^{-1} by n_y solves, then one product: a triangular solve with the
            M = -(factor_solve(factor, np.eye(jac_q.shape[0])) @ jac_q)  # block's many columns is far slower
        else:
            M = -factor_solve(factor, jac_q)
        z = quadratic_block_step(M, grad0.ravel() + hess @ y_c, hess, b.radius, prefer)  # F is quadratic in y
        x[b.block] = b.center + z
        y = y_c + M @ z
        sol = LowerSolution(y, np.nan, np.zeros(0), np.zeros(0), [], "optimal", "closed-form (exact block)")
        return x, sol, KKTValues.unconstrained(P, factor)


def _lower_gradient_parts(low: LowerLevel, y: ca.SX) -> tuple[ca.SX, ca.SX]:
    """The lower Hessian as an expression, and the expressions the lower gradient at y = 0 is affine in (for the
    matrix form d and q: its gradient q - C'd is never built as an expression, its size is that of the data)."""
    if isinstance(low, MatrixLower):
        return ca.SX(low.hess.shape[0], low.hess.shape[1]), ca.vertcat(low.d, low.q)
    low = low.inner_kind  # expressions of [x; z] with linear maps
    if isinstance(low, ResidualLeastSquares):  # P = C'C moves with x where C does; q = -C'd is affine where d is
        return low.C_expr, low.d_expr
    return low.hess_f, ca.substitute(ca.gradient(low.f, y), y, ca.DM.zeros(int(y.numel())))


def _block_data(canon: CanonicalBilevel, S: slice, hess_F: ca.SX, q: ca.SX) -> Callable:
    """ExactBlock.data for block S (q from _lower_gradient_parts): one compiled sweep, plus C'd assembled from the
    numbers for the matrix form."""
    low, x, y = canon.lower, canon.x, canon.y
    zero = ca.DM.zeros(int(y.numel()))
    grad0 = ca.substitute(ca.gradient(canon.F, y), y, zero)
    inner = low.inner_kind
    if isinstance(inner, ResidualLeastSquares):  # dq/dx_S = -C' dd/dx_S
        return _residual_block_data(canon, inner, S, grad0, hess_F)
    if not isinstance(low, MatrixLower):  # with linear maps, data of [x; z] at lift_point(x): the block does not
        fun = canon.params.function("exact_block_data", [inner.x],  # reach the maps (find_exact_block)
                                    [ca.substitute(inner.hess_f, y, zero), q, ca.jacobian(q, x[S]), grad0, hess_F])
        return lambda xv: fun(low.lift_point(xv))
    parts = canon.params.function("exact_block_data", [x], [low.d, low.q, ca.jacobian(low.d, x[S]),
                                                            ca.jacobian(low.q, x[S]), grad0, hess_F])

    def data(xv: np.ndarray) -> tuple:
        d, q, jac_d, jac_q, g0, hF = parts(xv)
        return low.hess, q.ravel() - low.C.T @ d.ravel(), jac_q - low.C.T @ jac_d, g0, hF

    return data


def _residual_block_data(canon: CanonicalBilevel, inner: ResidualLeastSquares, S: slice, grad0: ca.SX,
                         hess_F: ca.SX) -> Callable:
    """ExactBlock.data for a residual-form learner: C and d by its own evaluation; dd/dx_S a constant matrix where d
    is affine in x_S (else a reverse sweep seeded with C's columns); grad0 and hess_F evaluated once per parameter
    revision where they do not depend on x (else with the sweep)."""
    low, x = canon.lower, canon.x
    lift = low.lift_point
    jac_d = ca.jacobian(inner.d_expr, x[S])
    constant_jac = not ca.depends_on(jac_d, inner.x) and not ca.depends_on(jac_d, canon.params.sym)
    jac_d_t = Gather.of(sp.csr_matrix(ca.evalf(jac_d).sparse().T)) if constant_jac else None  # (dd/dx_S)'
    constant_F = not ca.depends_on(ca.vertcat(grad0, ca.vec(hess_F)), x)
    V = ca.SX.sym("V", int(inner.d_expr.numel()), inner.n_y)
    outputs = ([] if constant_jac else [ca.jtimes(inner.d_expr, x[S], V, True)]) + ([] if constant_F else
                                                                                    [grad0, hess_F])
    sweep = canon.params.function("exact_block_data", [inner.x, V], outputs) if outputs else None
    upper_parts = canon.params.function("exact_block_upper", [], [grad0, hess_F]) if constant_F else None
    kept: dict[str, Any] = {}

    def residual_data(xv: np.ndarray) -> tuple:
        xt = lift(xv)
        C, d, _ = inner.data(xt)
        swept = [] if sweep is None else sweep(xt, C)
        swept = swept if isinstance(swept, list) else [swept]
        jd = (jac_d_t @ C).T if constant_jac else np.asarray(swept.pop(0)).T
        if constant_F:
            if kept.get("revision") != canon.params.revision:
                kept.update(revision=canon.params.revision, parts=upper_parts())
            g0, hF = kept["parts"]
        else:
            g0, hF = swept
        return C.T @ C, -(C.T @ d), -jd, g0, hF

    return residual_data


def find_exact_block(canon: CanonicalBilevel, balls: list[Ball]) -> tuple[ExactBlock | None, list[str]]:
    """The largest ball block that is exact (see the module docstring), and why each other one is not."""
    low = canon.lower
    if not isinstance(low.inner_kind, (ExpressionLower, MatrixLower, ResidualLeastSquares)):
        return None, [f"the lower level ({type(low).__name__}) is neither declared by expressions nor by lower_qp"]
    if not low.closed_form:
        return None, [f"the lower level is {low.kind}, not an unconstrained strictly convex quadratic"]
    balls = [b for b in balls if b.norm == 2]
    if not balls:
        return None, ["no upper constraint is a Euclidean ball on a block of upper variables"]
    x, y = canon.x, canon.y
    hess_F = ca.hessian(canon.F, y)[0]
    if ca.depends_on(hess_F, y):
        return None, ["the upper objective is not quadratic in the lower variables"]
    hess_f, q = _lower_gradient_parts(low, y)
    in_P = depends(hess_f, x)
    mapped = np.zeros(int(x.numel()), dtype=bool)  # entries of x that reach the lower level through linear maps
    if arguments := low.linear_map_arguments:
        mapped = depends(ca.vertcat(*[ca.vec(arg) for arg in arguments]), x)
    in_F = depends(canon.F, x)
    why: list[str] = []
    best: Ball | None = None
    for ball in balls:
        S = ball.block
        others = [canon.G[i] for i in range(int(canon.G.numel())) if i != ball.row] + [canon.H]
        reason = ("has finite bounds" if np.isfinite(canon.x_lb[S]).any() or np.isfinite(canon.x_ub[S]).any()
                  else "enters the upper objective" if in_F[S].any()
                  else "enters another upper constraint" if depends(ca.vertcat(*others), x)[S].any()
                  else "enters the lower level through a linear map" if mapped[S].any()
                  else "enters the lower Hessian" if in_P[S].any()
                  else "enters the lower gradient nonlinearly" if depends(q, x[S], 2).any() else "")
        if reason:
            why.append(f"x[{S.start}:{S.stop}] {reason}")
        elif best is None or S.stop - S.start > best.block.stop - best.block.start:
            best = ball
    if best is None:
        return None, why or ["no upper constraint is a Euclidean ball on a block of upper variables"]
    return ExactBlock(best, _block_data(canon, best.block, hess_F, q),
                      low.factor if isinstance(low, MatrixLower) else None), why


def exact_block_of(prep: Prepared) -> tuple[ExactBlock | None, list[str]]:
    """The problem's exact block at the current parameter values (its symbolic set-up kept on `prep`), and why each
    other candidate is not exact."""
    if prep.canon.spectral is not None:
        return None, ["a spectral-radius objective is no quadratic of any block"]
    balls = prep.balls
    exact, why = prep.cached(("block-exact", tuple((b.row, b.block.start, b.block.stop) for b in balls)),
                             lambda: find_exact_block(prep.canon, balls))
    if exact is not None:  # the symbolic set-up is shared; center and radius follow the parameter values
        exact = replace(exact, ball=next(b for b in balls if b.row == exact.ball.row))
    return exact, why


def ascend_with_exact_block(prep: Prepared, exact: ExactBlock | None, why: list[str], starts: int | None = None,
                            seed: Any = 0, scale: float | None = None, penalty: float | None = None,
                            gain_tol: float | None = None, max_iter: int | None = None, verbose: bool = False,
                            time_limit: float | None = None,
                            oracle: Any = None, projection: Projection | None = None,
                            weights: np.ndarray | None = None) -> MethodRun:
    """Multistart ascent of the other upper variables (the engine's loop, bilevel.solvers.engine.ascent) on phi with the
    exact block at its global optimum at every evaluation (exact None: every upper variable ascends); gain_tol:
    relative gain over the loop's window; at time_limit (seconds) the best point so far, status MAX_ITERATIONS. None
    takes the registry's value (hypergradient.starts, .scale, .max_iter, implicit.penalty, block_exact.gain_tol).
    A structured problem passes its own oracle (evaluate(*exact.solve(x)) or evaluate(x) -> a point with x, phi, F
    and lower; gradient(point)[0] = grad phi; optionally hessian_parts for the conditioning start), projection (a set narrower than the declared one, then the run's
    feasible_set) and weights (per-entry length scales; default: ball radii, else 1)."""
    starts, scale = int(param("hypergradient.starts", starts)), float(param("hypergradient.scale", scale))
    tol, max_iter = float(param("block_exact.gain_tol", gain_tol)), int(param("hypergradient.max_iter", max_iter))
    balls = prep.balls
    if oracle is None:
        oracle = shared_oracle(prep, float(param("implicit.penalty", penalty)),
                               projected_rows=tuple(b.row for b in balls))
    S = slice(0, 0) if exact is None else exact.ball.block
    mask = np.ones(int(prep.canon.x.numel()), dtype=bool)
    mask[S] = False
    kept = np.flatnonzero(mask)  # the other variables, as a slice where contiguous (a view, not a copy)
    rest = slice(kept[0], kept[-1] + 1) if kept.size and kept[-1] - kept[0] + 1 == kept.size else mask
    weights = (budget_scale(prep.canon, balls) if weights is None else np.asarray(weights, dtype=float))[rest]
    project_full = prep.projection if projection is None else projection

    def full(xr: np.ndarray) -> np.ndarray:
        if exact is None:
            return xr
        x = np.empty(mask.size)
        x[rest], x[S] = xr, exact.ball.center
        return x

    failure: list[BilevelError | None] = [None]  # why the last point could not be evaluated

    def value(xr: np.ndarray) -> tuple[float, Evaluation | None]:
        try:
            ev = oracle.evaluate(xr) if exact is None else oracle.evaluate(*exact.solve(full(xr)))
        except BilevelError as exc:
            failure[0] = exc
            return -np.inf, None
        return -ev.phi, ev

    squared = weights ** 2

    def direction(ev: Evaluation) -> tuple[np.ndarray, np.ndarray]:
        g = -oracle.gradient(ev)[0][rest]  # Danskin: the block is at its optimum
        unit = float(np.linalg.norm(g * weights))
        return g, (g * squared / unit if unit > 0 else np.zeros_like(g))

    own = project_full.on(rest) if isinstance(project_full, Blocks) and isinstance(rest, slice) else None
    project = own if own is not None else lambda xr: project_full(full(xr))[rest]  # the other variables' sets
    rng = np.random.default_rng(seed)
    limit, label = Deadline(time_limit), "hypergradient" + ("" if exact is None else ", exact block")
    ends, records, nit = [], [], 0
    for k, x0 in enumerate(start_points(prep, starts, rng, scale, getattr(oracle, "hessian_parts", None))):
        if k and limit.expired():
            break
        t0, history, reason, calls = time.perf_counter(), [], {}, [0]

        def stop(ev: Evaluation, k: int = k, calls: list[int] = calls) -> bool:
            """Progress at the start and each accepted point; the deadline."""
            if verbose:
                progress(verbose, label, f"start {k + 1}/{starts}, iteration {calls[0]}: phi = "
                         f"{prep.declared(ev.phi):.8g}")
            calls[0] += 1
            return limit.expired()

        try:
            _, fx, ev, it, evals, converged = projected_ascent(value, direction, project, x0[rest], weights,
                                                               max_iter, tol, history, stop=stop, why=reason)
        except RankDeficientRegressor as exc:  # the learner is singular at the start: no step can begin
            fx, ev, it, evals, converged = -np.inf, None, 0, 1, False
            reason, failure[0] = {"stop": "start"}, exc
        converged = converged and reason["stop"] != "stop"  # stop() holds only at the deadline
        singular = (reason["stop"] == "line search" and "singular" in reason) or (
            reason["stop"] == "start" and isinstance(failure[0], RankDeficientRegressor))
        nit += it
        records.append({"start": k, "objective": None if ev is None else ev.F, "iterations": it,
                        "evaluations": evals, "converged": converged, SINGULAR_LEARNER: singular,
                        "time": time.perf_counter() - t0})
        progress(verbose, label, f"start {k + 1}/{starts}: phi = {prep.declared(-fx):.8g} after {it} steps")
        if ev is not None:
            ends.append((fx, ev, converged, history, k))
    if not ends:
        return multistart_run(None, starts, nit, records)
    fx, ev, converged, history, k = ends[best_of([(None, -end[0], 0.0) for end in ends])]
    w = prep.pack(KKTPoint(ev.x, ev.lower.y, ev.lower.lam, ev.lower.mu, ev.lower.Z))
    g = oracle.gradient(ev)[0][rest]
    pg = float(np.linalg.norm(project(ev.x[rest] - g) - ev.x[rest]))  # ||P(x - grad phi) - x||, as the descent
    low = prep.canon.lower  # a lower level with linear maps solves the local probe's points in one lift
    run = multistart_run((w, converged, k, history, pg), starts, nit, records, None if exact is None else S, why,
                         feasible_set=projection, lower_solve=low.rows_solver if low.closed_form else None)
    return stopped(run, limit, len(records), starts)


def multistart_run(best: tuple[np.ndarray, bool, int, list, float] | None, starts: int, nit: int, records: list[dict],
                   block: slice | None = None, why: list[str] | None = None, **fields: Any) -> MethodRun:
    """The MethodRun of a multistart ascent (ascend_with_exact_block's and its batched form's): best = (packed point,
    converged, start index, history, projected gradient norm) of the best start, None where no start could be
    evaluated (status ERROR); block: the exact block's slice; fields: further MethodRun fields."""
    if best is None:
        return MethodRun(None, Status.ERROR, f"the lower level could not be solved at any of {starts} starts", nit,
                         [], records, **fields)
    w, converged, k, history, pg = best
    head = "" if block is None else f"exact block x[{block.start}:{block.stop}]; "
    return MethodRun(w, Status.SOLVED if converged else Status.MAX_ITERATIONS, f"{head}best of {starts} starts: "
                     f"start {k} ({'converged' if converged else 'max_iter'})", nit, history, records,
                     {"best_start": k, "exact_block": None if block is None else [block.start, block.stop],
                      "projected_gradient_norm": pg, "not_exact": [] if why is None else why}, **fields)
