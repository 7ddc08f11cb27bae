"""Independent brute-force checker for registered bilevel problems with convex lower levels.

Nothing here uses the package's solvers: the lower level is read off the registered CasADi expressions
numerically (gradient and Hessian in y at y = 0 for a fixed x, which is exact because the lower level
must be quadratic in y with affine or convex-quadratic constraints) and solved with Clarabel directly.

Interior-point solutions are polished: Newton's method on the KKT system of the guessed active set, kept
only if the result is a verified KKT point (hence optimal, the program being convex). This matters at
degenerate solutions, where an interior-point y is only accurate to about the square root of the tolerance.

Optimistic convention: when the lower level has several optimal solutions, the leader picks the one
best for itself. Its value is found by a second convex program that optimises the upper objective over
the lower-level optimal set {y feasible : P y = P y*, q'y = q'y*} (exact characterisation of the optimal
set of a convex QP), relaxed by a tiny tolerance, together with the upper constraints.

All objectives are handled in minimisation form: a maximised objective is negated.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Sequence

import casadi as ca
import clarabel
import numpy as np
import scipy.sparse as sp
from scipy.optimize import minimize, nnls

from bilevel.model import BilevelProblem

_SOLVED = {clarabel.SolverStatus.Solved, clarabel.SolverStatus.AlmostSolved}
_INFEASIBLE = {clarabel.SolverStatus.PrimalInfeasible, clarabel.SolverStatus.AlmostPrimalInfeasible}


class Unsupported(Exception):
    """The problem has a structure this checker does not handle (non-quadratic lower level, ...)."""


@dataclass
class Quadratic:
    """0.5 y'Q y + a'y + c (Q = 0 for affine functions)."""

    Q: np.ndarray
    a: np.ndarray
    c: float

    def __call__(self, y: np.ndarray) -> float:
        return float(0.5 * y @ self.Q @ y + self.a @ y + self.c)


@dataclass
class ConvexProgram:
    """min 0.5 y'Py + q'y  s.t.  A_eq y + b_eq = 0,  A_in y + b_in <= 0,  quad_i(y) <= 0 (each convex)."""

    P: np.ndarray
    q: np.ndarray
    A_eq: np.ndarray
    b_eq: np.ndarray
    A_in: np.ndarray
    b_in: np.ndarray
    quads: list[Quadratic]


def _psd_factor(Q: np.ndarray, what: str) -> np.ndarray:
    """L with Q = L L' (Q symmetric PSD, checked)."""
    Q = 0.5 * (Q + Q.T)
    w, V = np.linalg.eigh(Q)
    scale = max(1.0, float(np.abs(w).max(initial=0.0)))
    if w.min(initial=0.0) < -1e-9 * scale:
        raise Unsupported(f"{what} is not convex in y (Hessian eigenvalue {w.min():.3g})")
    keep = w > 1e-12 * scale
    return V[:, keep] * np.sqrt(w[keep])


def solve_convex(prog: ConvexProgram) -> tuple[str, np.ndarray | None, float]:
    """Solve with Clarabel: returns (status in {"optimal","infeasible","unbounded","failed"}, y, objective)."""
    n = prog.q.size
    rows, rhs, cones = [], [], []
    if prog.A_eq.shape[0]:
        rows.append(prog.A_eq)
        rhs.append(-prog.b_eq)
        cones.append(clarabel.ZeroConeT(prog.A_eq.shape[0]))
    if prog.A_in.shape[0]:
        rows.append(prog.A_in)
        rhs.append(-prog.b_in)
        cones.append(clarabel.NonnegativeConeT(prog.A_in.shape[0]))
    for quad in prog.quads:
        # 0.5 y'Qy + a'y + c <= 0  <=>  |L'y|^2 <= r := -2(a'y + c)  <=>  |(2 L'y, 1 - r)| <= 1 + r
        L = _psd_factor(quad.Q, "a lower-level constraint")
        k = L.shape[1]
        block = np.vstack([2 * quad.a[None, :], -2 * L.T, -2 * quad.a[None, :]])
        rows.append(block)
        rhs.append(np.concatenate([[1 - 2 * quad.c], np.zeros(k), [1 + 2 * quad.c]]))
        cones.append(clarabel.SecondOrderConeT(k + 2))
    if not rows:  # unconstrained: add a vacuous row so that Clarabel has a cone
        rows.append(np.zeros((1, n)))
        rhs.append(np.ones(1))
        cones.append(clarabel.NonnegativeConeT(1))
    A = sp.csc_matrix(np.vstack(rows))
    b = np.concatenate(rhs)
    P = sp.csc_matrix(np.triu(0.5 * (prog.P + prog.P.T)))
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = 1e-10
    settings.tol_gap_rel = 1e-10
    settings.tol_feas = 1e-10
    settings.tol_ktratio = 1e-8
    settings.max_iter = 200
    sol = clarabel.DefaultSolver(P, prog.q.astype(float), A, b, cones, settings).solve()
    if sol.status in _SOLVED:
        return "optimal", np.asarray(sol.x), float(sol.obj_val)
    if sol.status in _INFEASIBLE:
        return "infeasible", None, np.inf
    if sol.status in {clarabel.SolverStatus.DualInfeasible, clarabel.SolverStatus.AlmostDualInfeasible}:
        return "unbounded", None, -np.inf
    return "failed", None, np.nan


def _constraint_list(prog: ConvexProgram) -> tuple[list[Quadratic], list[Quadratic]]:
    """(equalities, inequalities) of `prog` as Quadratic objects (function <= 0 / == 0)."""
    n = prog.q.size
    zero = np.zeros((n, n))
    eqs = [Quadratic(zero, prog.A_eq[i], float(prog.b_eq[i])) for i in range(prog.A_eq.shape[0])]
    ins = [Quadratic(zero, prog.A_in[i], float(prog.b_in[i])) for i in range(prog.A_in.shape[0])]
    return eqs, ins + list(prog.quads)


def polish(prog: ConvexProgram, y0: np.ndarray, active_tol: float = 1e-6) -> np.ndarray | None:
    """Refine an interior-point solution by Newton's method on the KKT system of the guessed active set.

    Returns the refined point only if it is verified to be a KKT point of `prog` (primal feasible, inequality
    multipliers >= 0, stationary) to 1e-9; for a convex program that certifies optimality. None otherwise.
    """
    n = prog.q.size
    P = 0.5 * (prog.P + prog.P.T)
    eqs, ins = _constraint_list(prog)
    scale = 1.0 + float(np.abs(y0).max(initial=0.0))
    active = eqs + [c for c in ins if c(y0) >= -active_tol * scale]
    n_eq = len(eqs)
    y = y0.copy()

    def jac(y: np.ndarray) -> np.ndarray:
        return np.array([c.Q @ y + c.a for c in active]).reshape(len(active), n)

    grad = P @ y + prog.q
    J = jac(y)
    lam = -np.linalg.lstsq(J.T, grad, rcond=None)[0] if active else np.zeros(0)
    linear = not any(np.any(c.Q) for c in active)
    rtol = 1e-13 * scale * (1.0 + np.abs(P).max(initial=0.0) + np.abs(prog.q).max(initial=0.0))
    for _ in range(2 if linear else 30):  # a linear KKT system is solved by one Newton step
        grad = P @ y + prog.q
        J = jac(y)
        r = np.concatenate([grad + J.T @ lam, [c(y) for c in active]])
        if np.abs(r).max(initial=0.0) < rtol:
            break
        H = P + sum((l * c.Q for l, c in zip(lam, active)), np.zeros((n, n)))
        K = np.block([[H, J.T], [J, np.zeros((len(active), len(active)))]])
        step = np.linalg.lstsq(K, -r, rcond=None)[0]
        y = y + step[:n]
        lam = lam + step[n:]
    grad = P @ y + prog.q
    J = jac(y)
    tol = 1e-9 * scale * (1.0 + np.abs(P).max(initial=0.0) + np.abs(prog.q).max(initial=0.0))
    if np.abs(grad + J.T @ lam).max(initial=0.0) > tol:
        return None
    if np.any(lam[n_eq:] < -tol):
        return None
    if any(abs(c(y)) > tol for c in eqs) or any(c(y) > tol for c in ins):
        return None
    return y


def solve_polished(prog: ConvexProgram) -> tuple[str, np.ndarray | None, float]:
    """solve_convex, then `polish` the solution when the active-set KKT system certifies a better one."""
    status, y, val = solve_convex(prog)
    if status == "optimal":
        yp = polish(prog, y)
        if yp is not None:
            y = yp
            val = float(0.5 * y @ prog.P @ y + prog.q @ y)
    return status, y, val


class ConvexNLP:
    """A convex lower level that is not quadratic in y, solved at fixed x: with one lower variable and rows affine in
    y, by bisection on f' over the interval the rows leave (exact to rounding, also where f is flat to high order,
    e.g. (x + 2y - 15)^4); otherwise by SLSQP from the box centre (tolerance 1e-14). The follower's response is
    taken as unique (every registered convex-NLP lower level has a strictly convex objective or a unique minimizer
    along its feasible set, as the problems' docstrings derive)."""

    def __init__(self, X: ca.SX, Y: ca.SX, f: ca.SX, g_in: list[ca.SX], y_lb: np.ndarray, y_ub: np.ndarray) -> None:
        g = ca.vertcat(*g_in) if g_in else ca.SX(0, 1)
        self.f = ca.Function("f", [X, Y], [f, ca.gradient(f, Y)])
        self.g = ca.Function("g", [X, Y], [g, ca.jacobian(g, Y)])
        self.ny = int(Y.numel())
        self.affine_rows = not ca.depends_on(ca.jacobian(g, Y), Y)
        self.start = np.where(np.isfinite(y_lb) & np.isfinite(y_ub), 0.5 * (np.nan_to_num(y_lb) + np.nan_to_num(y_ub)),
                              np.clip(0.0, y_lb, y_ub))

    def _f(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
        value, grad = self.f(x, y)
        return float(value), np.asarray(grad, dtype=float).ravel()

    def _interval(self, x: np.ndarray) -> tuple[float, float]:
        """The feasible interval of a single y under rows a_i y + c_i <= 0."""
        c, a = (np.asarray(v, dtype=float).ravel() for v in self.g(x, np.zeros(1)))
        lo, hi = -np.inf, np.inf
        for ai, ci in zip(a, c):
            if ai > 0:
                hi = min(hi, -ci / ai)
            elif ai < 0:
                lo = max(lo, -ci / ai)
            elif ci > 0:
                return np.inf, -np.inf
        return lo, hi

    def solve(self, x: np.ndarray) -> tuple[str, np.ndarray | None, float]:
        """(status, y, f(x, y)) of the lower level at x."""
        x = np.asarray(x, dtype=float)
        if self.ny == 1 and self.affine_rows:
            lo, hi = self._interval(x)
            if lo > hi:
                return "infeasible", None, np.inf
            slope = lambda v: self._f(x, np.array([v]))[1][0]  # noqa: E731
            if np.isfinite(lo) and slope(lo) >= 0:
                y = lo
            elif np.isfinite(hi) and slope(hi) <= 0:
                y = hi
            else:
                a, b = (lo if np.isfinite(lo) else -1e6), (hi if np.isfinite(hi) else 1e6)
                for _ in range(200):
                    mid = 0.5 * (a + b)
                    a, b = (mid, b) if slope(mid) < 0 else (a, mid)
                y = 0.5 * (a + b)
            point = np.array([y])
            return "optimal", point, self._f(x, point)[0]
        rows = lambda y: -np.asarray(self.g(x, y)[0], dtype=float).ravel()  # noqa: E731
        jac = lambda y: -np.asarray(self.g(x, y)[1], dtype=float).reshape(-1, self.ny)  # noqa: E731
        res = minimize(lambda y: self._f(x, y), self.start, jac=True, method="SLSQP",
                       constraints=[{"type": "ineq", "fun": rows, "jac": jac}], options={"ftol": 1e-14, "maxiter": 500})
        if rows(res.x).min(initial=0.0) < -1e-9:
            return ("infeasible" if res.success else "failed"), None, np.inf
        if not res.success and not self._kkt(x, res.x, rows(res.x), jac(res.x)):
            return "failed", None, np.inf
        return "optimal", np.asarray(res.x), self._f(x, res.x)[0]

    def _kkt(self, x: np.ndarray, y: np.ndarray, slack: np.ndarray, jac: np.ndarray) -> bool:
        """Whether feasible y is a KKT point (so optimal: the level is convex), for SLSQP runs that stall at the
        optimum without declaring success (e.g. "Positive directional derivative for linesearch", which with
        ftol 1e-14 depends on the BLAS's rounding): multipliers >= 0 of the active rows by nonnegative least
        squares, stationarity to 1e-8 of the gradient's scale."""
        grad = self._f(x, y)[1]
        active = slack <= 1e-9 * (1.0 + np.abs(y).max(initial=0.0))
        residual = nnls(jac[active].T, grad)[1] if active.any() else float(np.linalg.norm(grad))
        return residual <= 1e-8 * (1.0 + float(np.linalg.norm(grad)))


def _vec(vars_: Sequence[Any]) -> ca.SX:
    return ca.vertcat(*[ca.vec(v.sym) for v in vars_]) if vars_ else ca.SX(0, 1)


def flatten_point(variables: Sequence[Any], values: dict[str, Any]) -> np.ndarray:
    """Flatten {name: value} over `variables` (column-major, as the model does)."""
    parts = []
    for v in variables:
        if v.name not in values:
            raise KeyError(f"solution has no value for variable {v.name!r}")
        arr = np.asarray(values[v.name], dtype=float)
        arr = arr.reshape(-1, order="F") if arr.ndim == 2 else arr.reshape(-1)
        if arr.size != v.size:
            raise ValueError(f"solution value of {v.name!r} has {arr.size} entries, expected {v.size}")
        parts.append(arr)
    return np.concatenate(parts) if parts else np.zeros(0)


class QuadraticPart:
    """Numerical (Q, a, c) of a list of scalar expressions that are quadratic in Y, at given X (Y = 0)."""

    def __init__(self, exprs: list[ca.SX], X: ca.SX, Y: ca.SX, what: str) -> None:
        self.n = len(exprs)
        self.affine = []
        outs = []
        for e in exprs:
            grad = ca.gradient(e, Y)
            hess = ca.jacobian(grad, Y)
            if ca.depends_on(hess, Y):
                raise Unsupported(f"{what} is not quadratic in the lower variables: {e}")
            self.affine.append(not ca.depends_on(grad, Y) or hess.is_zero())
            outs += [ca.densify(hess), ca.densify(grad), e]
        self.fun = ca.Function("quad", [X, Y], outs) if exprs else None
        self.ny = Y.numel()

    def at(self, x: np.ndarray) -> list[Quadratic]:
        if not self.n:
            return []
        out = self.fun(x, np.zeros(self.ny))
        res = []
        for i in range(self.n):
            Q, a, c = out[3 * i: 3 * i + 3]
            res.append(Quadratic(np.array(Q, dtype=float).reshape(self.ny, self.ny),
                                 np.array(a, dtype=float).reshape(-1), float(c)))
        return res


class BruteForce:
    """Exact lower-level solves and optimistic leader values of a registered problem at fixed x."""

    def __init__(self, problem: BilevelProblem) -> None:
        if problem.lower_psd_constraints:
            raise Unsupported("LMI lower constraints are not handled by the brute-force checker")
        self.problem = problem
        self.upper = problem.upper_variables
        self.lower = problem.lower_variables
        self.X = _vec(self.upper)
        self.Y = _vec(self.lower)
        self.nx, self.ny = self.X.numel(), self.Y.numel()
        self.x_lb = np.concatenate([v.lb for v in self.upper])
        self.x_ub = np.concatenate([v.ub for v in self.upper])
        y_lb = np.concatenate([v.lb for v in self.lower])
        y_ub = np.concatenate([v.ub for v in self.lower])

        lo, up = problem.lower_objective, problem.upper_objective
        self.f_sign = 1.0 if lo.sense == "min" else -1.0
        self.F_sign = 1.0 if up.sense == "min" else -1.0
        self.f_expr = self.f_sign * lo.expr
        self.F_expr = self.F_sign * up.expr

        g_in = [c.body[i] for c in problem.lower_constraints if c.kind == "<=" for i in range(c.body.numel())]
        g_eq = [c.body[i] for c in problem.lower_constraints if c.kind == "==" for i in range(c.body.numel())]
        for j in range(self.ny):  # bounds of lower variables are lower-level constraints
            if np.isfinite(y_ub[j]):
                g_in.append(self.Y[j] - y_ub[j])
            if np.isfinite(y_lb[j]):
                g_in.append(y_lb[j] - self.Y[j])
        G_in = [c.body[i] for c in problem.upper_constraints if c.kind == "<=" for i in range(c.body.numel())]
        G_eq = [c.body[i] for c in problem.upper_constraints if c.kind == "==" for i in range(c.body.numel())]

        try:
            self.f_part = QuadraticPart([self.f_expr], self.X, self.Y, "the lower objective")
            self.g_in = QuadraticPart(g_in, self.X, self.Y, "a lower inequality")
            self.nlp: ConvexNLP | None = None
        except Unsupported:  # exp, quartic, cubic, ... in y: a convex NLP, solved by ConvexNLP
            self.nlp = ConvexNLP(self.X, self.Y, self.f_expr, g_in, y_lb, y_ub)
        self.g_eq = QuadraticPart(g_eq, self.X, self.Y, "a lower equality")
        if not all(self.g_eq.affine):
            raise Unsupported("a lower-level equality is not affine in y")
        try:
            self.F_part: QuadraticPart | None = QuadraticPart([self.F_expr], self.X, self.Y, "F")
        except Unsupported:
            self.F_part = None  # fine as long as the lower solution is unique
        try:
            self.G_in: QuadraticPart | None = QuadraticPart(G_in, self.X, self.Y, "G")
            self.G_eq: QuadraticPart | None = QuadraticPart(G_eq, self.X, self.Y, "G")
        except Unsupported:
            self.G_in = self.G_eq = None
        self.G_depends_on_y = any(ca.depends_on(e, self.Y) for e in G_in + G_eq)

        XY = [self.X, self.Y]
        self.F_fun = ca.Function("F", XY, [self.F_expr])
        self.f_fun = ca.Function("f", XY, [self.f_expr])
        self.g_in_fun = ca.Function("g_in", XY, [ca.vertcat(*g_in) if g_in else ca.SX(0, 1)])
        self.g_eq_fun = ca.Function("g_eq", XY, [ca.vertcat(*g_eq) if g_eq else ca.SX(0, 1)])
        self.G_in_fun = ca.Function("G_in", XY, [ca.vertcat(*G_in) if G_in else ca.SX(0, 1)])
        self.G_eq_fun = ca.Function("G_eq", XY, [ca.vertcat(*G_eq) if G_eq else ca.SX(0, 1)])

    # -- evaluation helpers ---------------------------------------------------------------------
    def F(self, x: np.ndarray, y: np.ndarray) -> float:
        """Upper objective in minimisation form."""
        return float(self.F_fun(x, y))

    def f(self, x: np.ndarray, y: np.ndarray) -> float:
        """Lower objective in minimisation form."""
        return float(self.f_fun(x, y))

    def lower_violation(self, x: np.ndarray, y: np.ndarray) -> float:
        g = np.array(self.g_in_fun(x, y), dtype=float).reshape(-1)
        h = np.array(self.g_eq_fun(x, y), dtype=float).reshape(-1)
        return float(max(np.max(g, initial=0.0), np.max(np.abs(h), initial=0.0)))

    def upper_violation(self, x: np.ndarray, y: np.ndarray) -> float:
        G = np.array(self.G_in_fun(x, y), dtype=float).reshape(-1)
        H = np.array(self.G_eq_fun(x, y), dtype=float).reshape(-1)
        bounds = max(np.max(self.x_lb - x, initial=0.0), np.max(x - self.x_ub, initial=0.0))
        return float(max(np.max(G, initial=0.0), np.max(np.abs(H), initial=0.0), bounds))

    # -- lower level -------------------------------------------------------------------------------
    def lower_program(self, x: np.ndarray) -> tuple[ConvexProgram, float]:
        """The lower level at x as a convex program (and the constant term of its objective)."""
        (fq,) = self.f_part.at(x)
        _psd_factor(fq.Q, "the lower objective")
        ins = self.g_in.at(x)
        lin = [c for c, aff in zip(ins, self.g_in.affine) if aff]
        quads = [c for c, aff in zip(ins, self.g_in.affine) if not aff]
        eqs = self.g_eq.at(x)
        prog = ConvexProgram(
            P=fq.Q, q=fq.a,
            A_eq=np.array([c.a for c in eqs]).reshape(len(eqs), self.ny), b_eq=np.array([c.c for c in eqs]),
            A_in=np.array([c.a for c in lin]).reshape(len(lin), self.ny), b_in=np.array([c.c for c in lin]),
            quads=quads)
        return prog, fq.c

    def lower_solve(self, x: np.ndarray) -> tuple[str, np.ndarray | None, float]:
        """(status, a lower solution, lower optimal value in minimisation form) at x."""
        if self.nlp is not None:
            return self.nlp.solve(x)
        prog, const = self.lower_program(x)
        status, y, val = solve_polished(prog)
        return status, y, val + const

    def leader_value(self, x: np.ndarray, delta: float = 1e-9) -> tuple[float, np.ndarray | None]:
        """Optimistic upper value (minimisation form) at x and the follower response; +inf if x is not admissible.

        If the lower objective is strictly convex the response is unique. Otherwise the leader's best response
        over the lower optimal set {y feasible : P y = P y*, q'y = q'y*}, relaxed by `delta`, is computed; when
        that relaxed set turns out to be a sliver around y* (the response is unique after all), the exact y*
        is used so that the relaxation cannot flatter the leader.
        """
        x = np.asarray(x, dtype=float)
        if np.any(x < self.x_lb - 1e-12) or np.any(x > self.x_ub + 1e-12):
            return np.inf, None
        if self.nlp is not None:  # strictly convex or unique by construction: F at the follower's solution
            status, ystar, _ = self.nlp.solve(x)
            ok = status == "optimal" and self.upper_violation(x, ystar) <= 1e-7
            return (self.F(x, ystar), ystar) if ok else (np.inf, None)
        prog, _ = self.lower_program(x)
        status, ystar, _ = solve_polished(prog)
        if status != "optimal" or ystar is None:
            return np.inf, None
        P = 0.5 * (prog.P + prog.P.T)
        n = self.ny
        unique = n == 0 or np.linalg.eigvalsh(P).min() > 1e-9 * max(1.0, np.abs(P).max())
        ok_at_ystar = self.upper_violation(x, ystar) <= 1e-7
        if unique:
            return (self.F(x, ystar), ystar) if ok_at_ystar else (np.inf, None)
        if self.F_part is None or self.G_in is None or self.G_eq is None:
            raise Unsupported("non-unique lower solutions with an upper level that is not quadratic in y")
        (Fq,) = self.F_part.at(x)
        _psd_factor(Fq.Q, "the upper objective restricted to the lower optimal set")
        scale = 1.0 + float(np.abs(ystar).max(initial=0.0))
        d = delta * scale * (1.0 + np.abs(P).max(initial=0.0) + np.abs(prog.q).max(initial=0.0))
        rows_P = P[np.abs(P).max(axis=1) > 0]
        Gin = self.G_in.at(x)
        Geq = self.G_eq.at(x)
        if any(np.any(c.Q) for c in Geq):
            raise Unsupported("a nonlinear upper equality in y")
        lin_G = [c for c in Gin if not np.any(c.Q)]
        quad_G = [c for c in Gin if np.any(c.Q)]
        A_in = np.vstack([prog.A_in, rows_P, -rows_P, prog.q[None, :],
                          np.array([c.a for c in lin_G]).reshape(len(lin_G), n)])
        b_in = np.concatenate([prog.b_in, -rows_P @ ystar - d, rows_P @ ystar - d,
                               [-(prog.q @ ystar) - d], np.array([c.c for c in lin_G])])
        second = ConvexProgram(
            P=Fq.Q, q=Fq.a,
            A_eq=np.vstack([prog.A_eq, np.array([c.a for c in Geq]).reshape(len(Geq), n)]),
            b_eq=np.concatenate([prog.b_eq, np.array([c.c for c in Geq])]),
            A_in=A_in, b_in=b_in, quads=prog.quads + quad_G)
        status, y, val = solve_polished(second)
        if status != "optimal" or y is None:
            return (self.F(x, ystar), ystar) if ok_at_ystar else (np.inf, None)
        if ok_at_ystar and np.abs(y - ystar).max() <= 1e-4 * scale:
            return self.F(x, ystar), ystar
        return val + Fq.c, y


def grid(box: Sequence[tuple[float, float]], points: int | Sequence[int]) -> np.ndarray:
    """Full tensor grid over `box` with `points` points per dimension."""
    counts = [points] * len(box) if isinstance(points, int) else list(points)
    axes = [np.linspace(lo, hi, k) if k > 1 else np.array([0.5 * (lo + hi)]) for (lo, hi), k in zip(box, counts)]
    return np.array(list(itertools.product(*axes)), dtype=float).reshape(-1, len(box))


@dataclass
class SearchResult:
    best_value: float
    best_x: np.ndarray | None
    evaluated: int
    admissible: int


def search(bf: BruteForce, box: Sequence[tuple[float, float]], points: int | Sequence[int],
           refine: int = 3, seed: int = 0) -> SearchResult:
    """Grid search of the optimistic value over `box`, then finer local grids around the best points."""
    xs = grid(box, points)
    values = np.array([bf.leader_value(x)[0] for x in xs])
    evaluated = len(xs)
    order = [i for i in np.argsort(values) if np.isfinite(values[i])]
    widths = np.array([(hi - lo) / max(k - 1, 1) for (lo, hi), k in
                       zip(box, [points] * len(box) if isinstance(points, int) else points)])
    rng = np.random.default_rng(seed)
    extra_x, extra_v = [], []
    for i in order[:refine]:
        centre = xs[i]
        local_box = [(max(lo, c - w), min(hi, c + w)) for (lo, hi), c, w in zip(box, centre, widths)]
        if len(box) <= 2:
            local = grid(local_box, 11)
        else:
            lo = np.array([b[0] for b in local_box])
            hi = np.array([b[1] for b in local_box])
            local = lo + (hi - lo) * rng.random((150, len(box)))
        for x in local:
            extra_x.append(x)
            extra_v.append(bf.leader_value(x)[0])
    evaluated += len(extra_x)
    all_x = np.vstack([xs] + ([np.array(extra_x)] if extra_x else []))
    all_v = np.concatenate([values, np.array(extra_v)])
    finite = np.isfinite(all_v)
    if not finite.any():
        return SearchResult(np.inf, None, evaluated, 0)
    k = int(np.argmin(np.where(finite, all_v, np.inf)))
    return SearchResult(float(all_v[k]), all_x[k], evaluated, int(finite.sum()))
