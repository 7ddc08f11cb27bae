"""Projected hypergradient descent on the reduced objective phi(x) = F(x, y*(x)), y*(x) solved exactly.

At each upper point the lower level is solved by its own solver and polished by one Newton step on its
active-set KKT equations (exact for LP/QP, kept only if it lowers the KKT residual). dy*/dx comes from
implicit differentiation of those equations: stationarity grad_y L = 0, g_A = 0, h = 0, with A the
inequalities having lam_i > active_tol or |g_i| <= active_tol. If some g_i = 0 has lam_i <= active_tol
(no strict complementarity) or the system is singular (no LICQ, e.g. a degenerate LP vertex), only the
strictly active rows are kept and the system is solved in the least-squares (minimum-norm) sense; y* is
then not differentiable there and the result is one element of a generalized derivative. The gradient
is computed by the adjoint: grad phi = grad_x phi - R' z with K' z = (grad_y phi, 0), K the KKT matrix
and R its x-derivative, which equals grad_x phi + (dy/dx)' grad_y phi without forming dy/dx.
A lower level with LMIs is polished and differentiated through its conic KKT system instead (stationarity,
lam * g, h and vech((M_k Z_k + Z_k M_k) / 2), bilevel.lower.sdp.ConicKKT: the same code as the Willems
attacks); it needs a unique, strictly complementary lower solution (e.g. a strictly convex objective).
Upper constraints recognized as balls (bilevel.solvers.structure) are projected on, not penalized.

Upper constraints other than the box and the balls are handled by an exact penalty: phi = F + penalty *
(sum max(G, 0) + sum |H|), exact once the penalty exceeds the upper multipliers (default 1e4); where
some |G_i| or |H_j| <= 1e-9 the least-norm subgradient of the penalty is used. A point is reported
feasible when max(G, 0) and |H| are <= 1e-6. The iteration is x+ = P(x - t grad phi), P the projection
onto the option `projection` (see projections.py) intersected with the declared box, with a
Barzilai-Borwein first trial step and Armijo backtracking along the projection arc,
phi(x+) <= phi(x) - 1e-4 / t * ||x+ - x||^2. A trial point at which the lower level is infeasible is moved to
the nearest upper point (in the box) where it is feasible, found by IPOPT on
min ||x - v||^2 s.t. g(x, y) <= 0, h(x, y) = 0, then projected again: with the default box projection
and jointly convex lower constraints this makes P the projection onto the lower level's domain.
Stops when ||x - P(x - grad phi)|| <= tol (P without the lower solve of the restoration; with it, asked only
when the line search fails) or the relative decrease of phi is <= ftol (SOLVED), at
max_iter (MAX_ITERATIONS), or when backtracking finds no decrease (INACCURATE: x is then typically at a
kink of y*(x), where the generalized gradient is not a descent direction).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import casadi as ca
import numpy as np
from scipy.optimize import lsq_linear

from ..errors import BilevelError, LowerLevelInfeasible, ModelError
from ..lower.base import KKTValues, LowerSolution
from ..parameters import CompiledFunction
from ..reduction import KKTPoint
from ..result import Status
from .base import MethodRun, Prepared, check_options
from .ipopt import best_of
from .starts import start_points
from .projections import Projection

DEFAULT_PENALTY = 1e4
ACTIVE_TOL = 1e-6
KINK_TOL = 1e-9
ARMIJO = 1e-4
MAX_BACKTRACKS = 60
STEP_RANGE = (1e-12, 1e12)


@dataclass
class Evaluation:
    """An upper point with its (polished) lower solution, penalized objective phi, F and upper violation.

    `upper` holds F, G, H and their partial derivatives in x and y; `kkt` the lower KKT values there (None for a
    closed-form lower level until a gradient needs them).
    """

    x: np.ndarray
    phi: float
    F: float
    violation: float
    lower: LowerSolution
    upper: list[np.ndarray]
    kkt: KKTValues | None


def _shaped(values: list[ca.DM], shapes: list[tuple[int, int]]) -> list[np.ndarray]:
    return [np.asarray(v, dtype=float).reshape(s, order="F") for v, s in zip(values, shapes)]


class Hypergradient:
    """The reduced objective phi(x) = F(x, y*(x)) + penalty * (sum max(G, 0) + sum |H|) and its gradient."""

    def __init__(self, prep: Prepared, penalty: float = DEFAULT_PENALTY, active_tol: float = ACTIVE_TOL,
                 projected_rows: tuple[int, ...] = ()) -> None:
        canon = prep.canon
        low = canon.lower
        if not penalty >= 0:
            raise ModelError(f"penalty must be >= 0, got {penalty}")
        self.canon, self.low, self.penalty, self.active_tol = canon, low, float(penalty), float(active_tol)
        x, y, H = canon.x, canon.y, canon.H
        kept = [i for i in range(int(canon.G.numel())) if i not in set(projected_rows)]
        G = ca.vertcat(*[canon.G[i] for i in kept]) if kept else ca.SX(0, 1)  # projected rows need no penalty
        self._upper_outputs = [canon.F, G, H, ca.gradient(canon.F, x), ca.gradient(canon.F, y), ca.jacobian(G, x),
                               ca.jacobian(G, y), ca.jacobian(H, x), ca.jacobian(H, y)]
        self._upper = canon.params.function("upper", [x, y], self._upper_outputs)
        nx, ny, nG, nH = low.n_x, low.n_y, int(G.numel()), int(H.numel())
        self._upper_shapes = [(1, 1), (nG, 1), (nH, 1), (nx, 1), (ny, 1), (nG, nx), (nG, ny), (nH, nx), (nH, ny)]
        self._fixed: tuple[int, LowerSolution, KKTValues | None] | None = None  # (parameter revision, ...)
        self.conic = bool(low.psd)  # LMIs: the lower level's conic KKT system (bilevel.lower.sdp.ConicKKT)

    @cached_property
    def _upper_and_f(self) -> CompiledFunction:
        """The upper sweep with the lower objective f as a last output, for lower solutions that come without it
        (the exact block's); built on first use, so other solves keep the shorter sweep."""
        canon = self.canon
        return canon.params.function("upper_and_f", [canon.x, canon.y], [*self._upper_outputs, self.low.f])

    def active_set(self, g: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, bool]:
        """Rows with lam_i > active_tol, and whether some other row has |g_i| <= active_tol (degenerate)."""
        strict = lam > self.active_tol
        return np.flatnonzero(strict), bool(np.any(~strict & (g.ravel() >= -self.active_tol)))

    @staticmethod
    def _system(vals: KKTValues, rows: np.ndarray) -> np.ndarray:
        """The KKT matrix K of (stationarity, g_A, h) in (y, lam_A, mu)."""
        hyy, jg, jh = vals.hessian, vals.jac_g, vals.jac_h
        na, nh = rows.size, jh.shape[0]
        return np.block([[hyy, jg[rows].T, jh.T],
                         [jg[rows], np.zeros((na, na + nh))],
                         [jh, np.zeros((nh, na + nh))]])

    def _x_adjoint(self, x: np.ndarray, sol: LowerSolution, rows: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """R' Z, R the x-derivative of (stationarity, g_A, h), one reverse sweep per column of Z."""
        ny, na = self.low.n_y, rows.size
        out = np.empty((self.low.n_x, Z.shape[1]))
        for j in range(Z.shape[1]):
            vg = np.zeros(self.low.n_g)
            vg[rows] = Z[ny:ny + na, j]
            out[:, j] = self.low.kkt_x_adjoint(x, sol, Z[:ny, j], vg, Z[ny + na:, j])
        return out

    @staticmethod
    def _residual(vals: KKTValues, lam: np.ndarray) -> float:
        S, g, h = vals.stationarity.ravel(), vals.g.ravel(), vals.h.ravel()
        parts = [np.abs(S), np.maximum(g, 0.0), np.abs(h), np.abs(lam * g)]
        return max((float(p.max()) for p in parts if p.size), default=0.0)

    def _polish(self, x: np.ndarray, sol: LowerSolution) -> tuple[LowerSolution, KKTValues | None]:
        """One Newton step on the active-set KKT equations; kept if it keeps lam >= 0 and lowers the residual."""
        if self.low.kind == "least-squares":  # a closed form: nothing to polish; KKT values wait for a gradient
            return sol, None
        vals = self.low.kkt_values(x, sol)
        rows, _ = self.active_set(vals.g, sol.lam)
        K = self._system(vals, rows)
        lam0 = np.zeros_like(sol.lam)
        lam0[rows] = sol.lam[rows]
        S0 = vals.stationarity.ravel() - vals.jac_g.T @ (sol.lam - lam0)
        step = np.linalg.lstsq(K, -np.concatenate([S0, vals.g.ravel()[rows], vals.h.ravel()]), rcond=None)[0]
        ny, na = self.low.n_y, rows.size
        lam1 = lam0.copy()
        lam1[rows] += step[ny:ny + na]
        if np.any(lam1 < -self.active_tol):
            return sol, vals
        new = LowerSolution(sol.y + step[:ny], 0.0, np.maximum(lam1, 0.0), sol.mu + step[ny + na:], [],
                            sol.status, f"{sol.solver} + active-set Newton polish")
        new_vals = self.low.kkt_values(x, new)
        if self._residual(new_vals, new.lam) >= self._residual(vals, sol.lam):
            return sol, vals
        new.objective = self.low.evaluate(x, new.y)[0]
        return new, new_vals

    def evaluate(self, x: np.ndarray, lower: LowerSolution | None = None,
                 kkt: KKTValues | None | None = None) -> Evaluation:
        """Solve (and polish) the lower level at x, or take its known solution `lower` (and KKT values `kkt`, if
        known), and evaluate phi there; raises if the lower solve fails. A given solution's objective is read from
        the same sweep as F when it is NaN."""
        x = self.low.check_point(x)
        revision = self.low.params.revision
        if self._fixed is not None and self._fixed[0] == revision:
            _, sol, vals = self._fixed
        elif lower is not None:
            sol, vals = lower, kkt
        elif self.conic:
            sol, vals = self.low.newton_polish(x, self.low.solve(x))[0], None
        else:
            sol, vals = self._polish(x, self.low.solve(x))
        if self.low.fixed:  # y* constant in x: solved once, no adjoint
            self._fixed = (revision, sol, vals)
        if np.isnan(sol.objective):  # F and f share subexpressions: one sweep gives both
            *upper, f = _shaped(self._upper_and_f(x, sol.y), self._upper_shapes + [(1, 1)])
            sol.objective = float(f[0, 0])
        else:
            upper = _shaped(self._upper(x, sol.y), self._upper_shapes)
        F, G, H = float(upper[0][0, 0]), upper[1].ravel(), upper[2].ravel()
        phi = F + self.penalty * (float(np.maximum(G, 0.0).sum()) + float(np.abs(H).sum()))
        violation = max([0.0, *np.maximum(G, 0.0), *np.abs(H)])
        return Evaluation(x, phi, F, violation, sol, upper, vals)

    def gradient(self, ev: Evaluation) -> tuple[np.ndarray, bool, int]:
        """grad phi at an evaluated point, whether the active set was degenerate, and its size.

        Where some |G_i| or |H_j| <= KINK_TOL the penalty is not differentiable: the least-norm element of
        its subdifferential (coefficients in [0, penalty] or [-penalty, penalty]) is returned.
        """
        _, G, H, gxF, gyF, Gx, Gy, Hx, Hy = ev.upper
        total = np.hstack([gxF, Gx.T, Hx.T])  # columns: d/dx of F, G_i, H_j along y*(x)
        weak, rows, rank, size = False, np.zeros(0, dtype=int), 0, 0
        if not self.low.fixed:  # dy*/dx = 0 otherwise
            if self.conic:
                (K, R), rows = self.low.jacobians(ev.x, ev.lower), np.flatnonzero(ev.lower.lam > 0)
            else:
                kkt = ev.kkt if ev.kkt is not None else self.low.kkt_values(ev.x, ev.lower)
                rows, weak = self.active_set(kkt.g, ev.lower.lam)
                K = self._system(kkt, rows)
            rhs = np.vstack([np.hstack([gyF, Gy.T, Hy.T]), np.zeros((K.shape[0] - gyF.size, 1 + G.size + H.size))])
            Z, rank = self.low.kkt_solve(ev.x, K, rhs)
            total = total - (R.T @ Z if self.conic else self._x_adjoint(ev.x, ev.lower, rows, Z))
            size = K.shape[0]
        values = np.concatenate([G, H]).ravel()
        kink = np.abs(values) <= KINK_TOL
        coef = self.penalty * np.concatenate([(G.ravel() > 0).astype(float), np.sign(H.ravel())])
        grad = total[:, 0] + total[:, 1:] @ np.where(kink, 0.0, coef)
        if kink.any():
            lo = np.where(np.arange(values.size) < G.size, 0.0, -self.penalty)[kink]
            t = lsq_linear(total[:, 1:][:, kink], -grad, bounds=(lo, np.full(lo.size, self.penalty))).x
            grad = grad + total[:, 1:][:, kink] @ t
        return grad, bool(weak or rank < size), int(rows.size)

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray, LowerSolution]:
        """(phi(x), grad phi(x), lower solution at x)."""
        ev = self.evaluate(x)
        return ev.phi, self.gradient(ev)[0], ev.lower


def hypergradient(prep: Prepared, x: np.ndarray, penalty: float = DEFAULT_PENALTY,
                  active_tol: float = ACTIVE_TOL) -> tuple[float, np.ndarray, LowerSolution]:
    """(phi(x), d phi/dx, lower solution) at x (raises if the lower level cannot be solved there); the compiled
    functions are kept on `prep` for later calls."""
    return shared_oracle(prep, penalty, active_tol)(x)


def shared_oracle(prep: Prepared, penalty: float = DEFAULT_PENALTY, active_tol: float = ACTIVE_TOL,
                  projected_rows: tuple[int, ...] = ()) -> Hypergradient:
    """The Hypergradient of these settings kept on `prep`: its compiled functions serve every later solve."""
    key = ("hypergradient", float(penalty), float(active_tol), tuple(projected_rows))
    return prep.cached(key, lambda: Hypergradient(prep, penalty, active_tol, projected_rows))


class _Restoration:
    """The nearest upper point in the box at which the lower level is feasible (IPOPT over (x, y))."""

    def __init__(self, prep: Prepared) -> None:
        canon, low = prep.canon, prep.canon.lower.symbolic()
        v = ca.SX.sym("v", canon.x.numel())
        nlp = {"x": ca.vertcat(canon.x, canon.y), "p": ca.vertcat(v, canon.params.sym),
               "f": 0.5 * ca.sumsqr(canon.x - v),
               "g": ca.vertcat(low.g, low.h)}
        opts = {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes", "tol": 1e-12,
                                               "bound_relax_factor": 0.0, "max_iter": 500}}
        self._solver = ca.nlpsol("restoration", "ipopt", nlp, opts)
        ng, nh = low.n_g, low.n_h
        ny = int(canon.y.numel())
        self._bounds = dict(lbx=np.concatenate([canon.x_lb, np.full(ny, -np.inf)]),
                            ubx=np.concatenate([canon.x_ub, np.full(ny, np.inf)]),
                            lbg=np.concatenate([np.full(ng, -np.inf), np.zeros(nh)]), ubg=np.zeros(ng + nh))
        self._y0 = np.zeros(ny) if canon.y_start is None else canon.y_start
        self._nx = int(canon.x.numel())
        self._params = canon.params

    def __call__(self, v: np.ndarray) -> np.ndarray | None:
        """The restored point, or None if IPOPT finds none."""
        sol = self._solver(x0=np.concatenate([v, self._y0]), p=np.concatenate([v, self._params.value]),
                           **self._bounds)
        if self._solver.stats()["return_status"] not in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
            return None
        return np.asarray(sol["x"]).ravel()[: self._nx]


class _Arc:
    """Points P(v) of the projection arc, evaluated; restored into the lower level's domain when needed."""

    def __init__(self, prep: Prepared, oracle: Hypergradient, projection: Projection) -> None:
        self.prep, self.oracle, self.project = prep, oracle, projection
        self._restoration: _Restoration | None = None

    def __call__(self, v: np.ndarray) -> Evaluation | None:
        """The evaluated point P(v), or None if no lower-feasible point was found near it."""
        x = self.project(v)
        try:
            return self.oracle.evaluate(x)
        except LowerLevelInfeasible:
            pass
        except BilevelError:
            return None
        if self._restoration is None:
            self._restoration = _Restoration(self.prep)
        restored = self._restoration(x)
        if restored is None:
            return None
        try:
            return self.oracle.evaluate(self.project(restored))
        except BilevelError:
            return None


@dataclass
class _Descent:
    """The outcome of one start: final point, status, message, accepted steps and per-iterate records."""

    point: Evaluation
    status: Status
    message: str
    nit: int
    history: list[dict[str, Any]]


def _backtrack(arc: _Arc, cur: Evaluation, grad: np.ndarray, t: float) -> tuple[Evaluation | None, float]:
    """Armijo backtracking along the arc from step t: the accepted point and step, or (None, t) if none."""
    for _ in range(MAX_BACKTRACKS):
        trial = arc(cur.x - t * grad)
        if trial is not None:
            moved = float(np.sum((trial.x - cur.x) ** 2))
            if moved <= (1e-15 * (1.0 + np.linalg.norm(cur.x))) ** 2:
                return None, t
            if trial.phi <= cur.phi - ARMIJO / t * moved:
                return trial, t
        t *= 0.5
    return None, t


def _domain_stationary(arc: _Arc, cur: Evaluation, grad: np.ndarray, tol: float) -> bool:
    """Whether the projected gradient step is <= tol once the projection is restored into the lower level's
    domain (the arc's P(x - grad)): asked only when the line search fails, as it costs a lower solve."""
    unit = arc(cur.x - grad)
    return unit is not None and float(np.linalg.norm(unit.x - cur.x)) <= tol


def _descend(arc: _Arc, start: Evaluation, tol: float, ftol: float, max_iter: int) -> _Descent:
    """Projected gradient with Barzilai-Borwein trial steps and Armijo backtracking along the arc."""
    cur, history, decrease, it = start, [], np.inf, 0
    grad, degenerate, n_active = arc.oracle.gradient(cur)
    alpha = 1.0 / max(1.0, float(np.abs(grad).max(initial=0.0)))
    while True:
        pstep = float(np.linalg.norm(arc.project(cur.x - grad) - cur.x))  # no lower solve: see _domain_stationary
        history.append({"iter": it, "objective": cur.phi, "step": 0.0, "grad_norm": float(np.linalg.norm(grad)),
                        "projected_step_norm": pstep, "active": n_active, "degenerate": degenerate})
        if pstep <= tol:
            return _Descent(cur, Status.SOLVED, f"projected gradient step {pstep:.2e} <= tol", it, history)
        if decrease <= ftol * max(1.0, abs(cur.phi)):
            return _Descent(cur, Status.SOLVED, f"relative decrease {decrease:.2e} <= ftol", it, history)
        if it == max_iter:
            return _Descent(cur, Status.MAX_ITERATIONS, f"max_iter = {max_iter} reached", it, history)
        trial, t = _backtrack(arc, cur, grad, alpha)
        if trial is None and _domain_stationary(arc, cur, grad, tol):
            return _Descent(cur, Status.SOLVED, "projected gradient step <= tol on the lower level's domain", it,
                            history)
        if trial is None:
            return _Descent(cur, Status.INACCURATE, "line search found no decrease (x is likely at a kink of "
                            "y*(x), where the generalized gradient is not a descent direction)", it, history)
        history[-1]["step"] = t
        new_grad, degenerate, n_active = arc.oracle.gradient(trial)
        s, dg = trial.x - cur.x, new_grad - grad
        alpha = float(np.clip(s @ s / (s @ dg), *STEP_RANGE)) if s @ dg > 0 else min(2.0 * t, STEP_RANGE[1])
        decrease = cur.phi - trial.phi
        cur, grad, it = trial, new_grad, it + 1


def _projection(prep: Prepared, projection: Any) -> Projection:
    """The option `projection` intersected with the declared box (by default the box and the recognized balls)."""
    canon = prep.canon
    if projection is None:
        return prep.projection
    if not isinstance(projection, Projection):
        raise ModelError(f"option projection must be a Projection from bilevel.solvers.projections (Box, NormBall, "
                         f"SparseNormBall, Blocks), got {type(projection).__name__}")
    proj = projection.with_box(canon.x_lb, canon.x_ub)
    if proj(canon.x_start).shape != canon.x_start.shape:
        raise ModelError(f"the projection maps the {canon.x_start.size} upper entries to a vector of another size")
    return proj


def solve_hypergradient(prep: Prepared, **options: Any) -> MethodRun:
    """Multistart projected hypergradient descent (options: starts, seed, scale, projection, penalty, tol,
    ftol, max_iter, active_tol, verbose); recognized balls are projected on, other upper constraints penalized."""
    check_options("hypergradient", options, {"starts", "seed", "scale", "projection", "penalty", "tol", "ftol",
                                             "max_iter", "active_tol", "verbose"})
    starts, penalty = int(options.get("starts", 4)), float(options.get("penalty", DEFAULT_PENALTY))
    projected = tuple(b.row for b in prep.balls) if options.get("projection") is None else ()
    active_tol = float(options.get("active_tol", ACTIVE_TOL))
    oracle = shared_oracle(prep, penalty, active_tol, projected)
    arc = _Arc(prep, oracle, _projection(prep, options.get("projection")))
    tol, ftol = float(options.get("tol", 1e-7)), float(options.get("ftol", 1e-12))
    max_iter = int(options.get("max_iter", 500))
    rng = np.random.default_rng(options.get("seed", 0))
    records, runs, candidates = [], [], []
    for k, x0 in enumerate(start_points(prep, starts, rng, float(options.get("scale", 10.0)))):
        t0 = time.perf_counter()
        start = arc(x0)
        if start is None:
            records.append({"start": k, "x0": x0.tolist(), "status": Status.ERROR.value, "iterations": 0,
                            "message": "no upper point near the start where the lower level can be solved",
                            "time": time.perf_counter() - t0})
            continue
        run = _descend(arc, start, tol, ftol, max_iter)
        p = run.point
        w = prep.pack(KKTPoint(p.x, p.lower.y, p.lower.lam, p.lower.mu, p.lower.Z))
        runs.append((k, run))
        candidates.append((w, p.F, p.violation))
        records.append({"start": k, "x0": x0.tolist(), "status": run.status.value, "message": run.message,
                        "objective": p.F, "residual": p.violation, "iterations": run.nit,
                        "time": time.perf_counter() - t0})
        if options.get("verbose"):
            print(f"[hypergradient] start {k + 1}/{starts}: {run.status.value}, F = {p.F:.6g}, "
                  f"upper violation {p.violation:.1e} ({run.message})", flush=True)
    nit = sum(r["iterations"] for r in records)
    if not runs:
        return MethodRun(None, Status.ERROR, f"all {starts} starts failed: the lower level could not be solved "
                         "near any start", nit, [], records)
    i = best_of(candidates)
    k, best = runs[i]
    return MethodRun(candidates[i][0], best.status, f"best of {starts} starts: start {k} ({best.message})", nit,
                     best.history, records, {"best_start": k, "penalty": penalty,
                                             "projected_gradient_norm": best.history[-1]["projected_step_norm"]},
                     feasible_set=None if options.get("projection") is None else arc.project)
