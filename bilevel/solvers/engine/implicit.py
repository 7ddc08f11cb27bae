"""The implicit-differentiation engine: phi(x) = F(x, y*(x)) and its gradient, y*(x) solved exactly.

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
lam * g, h and vech((M_k Z_k + Z_k M_k) / 2), bilevel.lower.sdp.ConicKKT, and SemidefiniteLower.adjoint; a new
point's solution is first sought by Newton continuation from the last one (SemidefiniteLower.continue_from, else
SemidefiniteLower.solve: Newton-polished, once where the SDP ignores x, or the learner's chosen solution), after
which y is projected off the directions the SDP sees only through a ridge (SemidefiniteLower.select: the
minimum-norm selection of a non-unique solution, or the exact ridge solution, unless min_norm is off); it needs a
strictly complementary lower solution, unique up to those directions.

A numeric upper objective of a matrix (BilevelProblem.maximize_matrix_function) is evaluated and differentiated by
its own function, F = sign * f(M(x, y)) with the function's d f / dM chained through the Jacobians of M; for the
spectral radius (maximize_spectral_radius) d rho / dM comes from the top eigenvectors (bilevel.spectral_radius), and
where the lower level ignores x and M is affine in x, spectral_batch evaluates many points by one matrix product and
one stacked eigendecomposition.

Upper constraints other than the projected ones are handled by an exact penalty: phi = F + penalty *
(sum max(G, 0) + sum |H|), exact once the penalty exceeds the upper multipliers (default 1e4); where
some |G_i| or |H_j| <= 1e-9 the least-norm subgradient of the penalty is used. The methods built on it:
`hypergradient` (bilevel.solvers.hypergradient) and its exact-block mode (bilevel.solvers.engine.block_exact).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np
from scipy.optimize import lsq_linear

from ...defaults import param
from ...errors import ModelError
from ...lower.base import ExpressionLower, KKTValues, LowerSolution
from ...lower.least_squares import factor_solve
from ...parameters import CompiledFunction, ValueAndJacobian
from ...spectral_radius import radius, rho_and_gradient, spectral_radius
from .prepared import Prepared


@dataclass
class Evaluation:
    """An upper point with its (polished) lower solution, penalized objective phi, F and upper violation.

    `upper` holds F, G, H, then (appended once a derivative needs them, Hypergradient.partials) their partial
    derivatives in x and y; `kkt` the lower KKT values there (None for a closed-form lower level until a gradient
    needs them).
    """

    x: np.ndarray
    phi: float
    F: float
    violation: float
    lower: LowerSolution
    upper: list[np.ndarray]
    kkt: KKTValues | None


NO_ROWS = np.zeros(0, dtype=int)
"""No active lower constraints."""


def _shaped(values: list[ca.DM], shapes: list[tuple[int, int]]) -> list[np.ndarray]:
    return [np.asarray(v, dtype=float).reshape(s, order="F") for v, s in zip(values, shapes)]


def shared_cores(rows: ca.SX, wrt: ca.SX) -> tuple[ca.SX, np.ndarray, np.ndarray]:
    """(cores, index, sign) with rows[i] = sign[i] * cores[index[i]] + terms free of wrt: rows that differ only by
    such terms and sign (the two sides of lo <= e <= hi, declared as two constraints) share one core, whose
    derivatives are swept once."""
    cores: list[ca.SX] = []
    index, sign, seen = [], [], {}
    for i in range(int(rows.numel())):
        e, s = rows[i], 1.0
        while e.is_op(ca.OP_NEG) or e.is_op(ca.OP_ADD) or e.is_op(ca.OP_SUB):
            if e.is_op(ca.OP_NEG):
                e, s = e.dep(0), -s
            elif not ca.depends_on(e.dep(1), wrt):
                e = e.dep(0)
            elif not ca.depends_on(e.dep(0), wrt):
                e, s = e.dep(1), (s if e.is_op(ca.OP_ADD) else -s)
            else:
                break
        key = e.element_hash()
        if key not in seen:
            seen[key] = len(cores)
            cores.append(e)
        index.append(seen[key])
        sign.append(s)
    return (ca.vertcat(*cores) if cores else ca.SX(0, 1)), np.array(index, dtype=int), np.array(sign)


def row_jacobian(rows: ca.SX, wrt: ca.SX) -> ca.SX:
    """d rows / d wrt; row by row where rows call Functions (call nodes): a joint reverse sweep runs each call node's
    adjoint in every direction, row by row only for the rows that read the node."""
    trace = ca.Function("rows", [wrt], [rows], {"allow_free": True})
    if rows.numel() < 2 or not any(trace.instruction_id(i) == ca.OP_CALL for i in range(trace.n_instructions())):
        return ca.jacobian(rows, wrt)
    return ca.vertcat(*(ca.jacobian(rows[i], wrt) for i in range(int(rows.numel()))))


class Hypergradient:
    """The reduced objective phi(x) = F(x, y*(x)) + penalty * (sum max(G, 0) + sum |H|) and its gradient."""

    def __init__(self, prep: Prepared, penalty: float | None = None, active_tol: float | None = None,
                 projected_rows: tuple[int, ...] = ()) -> None:
        """penalty and active_tol: None takes defaults["implicit.penalty"] and defaults["implicit.active_tol"]."""
        penalty, active_tol = param("implicit.penalty", penalty), param("implicit.active_tol", active_tol)
        canon = prep.canon
        low = canon.lower
        if not penalty >= 0:
            raise ModelError(f"penalty must be >= 0, got {penalty}")
        self.canon, self.low, self.penalty, self.active_tol = canon, low, float(penalty), float(active_tol)
        self._prep = prep
        x, y, H = canon.x, canon.y, canon.H
        kept = [i for i in range(int(canon.G.numel())) if i not in set(projected_rows)]
        G = ca.vertcat(*[canon.G[i] for i in kept]) if kept else ca.SX(0, 1)  # projected rows need no penalty
        nx, ny, nG, nH = low.n_x, low.n_y, int(G.numel()), int(H.numel())
        cores, self._G_index, self._G_sign = shared_cores(G, ca.vertcat(x, y))
        self._G_shared = len(self._G_index) > int(cores.numel()) or bool(np.any(self._G_sign < 0))
        nC = int(cores.numel())
        JC, JH = row_jacobian(cores, ca.vertcat(x, y)), row_jacobian(H, ca.vertcat(x, y))  # x and y in one sweep
        self._upper_outputs = [canon.F, G, H, ca.gradient(canon.F, x), ca.gradient(canon.F, y), JC[:, :nx],
                               JC[:, nx:], JH[:, :nx], JH[:, nx:]]
        """F, G, H, then the partials: of F, of G's distinct cores (shared_cores) and of H, in x and y."""
        self._squares = canon.squares  # F by BLAS where it is numeric squares of y, not swept
        swept = self._upper_outputs if self._squares is None else \
            [ca.SX(1, 1), G, H, ca.SX(nx, 1), ca.SX(ny, 1), *self._upper_outputs[5:]]
        self._values = canon.params.function("upper_values", [x, y], swept[:3])
        self._partials = canon.params.function("upper_partials", [x, y], swept[3:])
        self._upper_shapes = [(1, 1), (nG, 1), (nH, 1), (nx, 1), (ny, 1), (nC, nx), (nC, ny), (nH, nx), (nH, ny)]
        """The shapes of _upper_outputs (G's partials by core: _expanded gives them by row)."""
        self._unswept = [np.zeros(shape) for shape in self._upper_shapes[:5]] + \
            [np.zeros((nG, nx)), np.zeros((nG, ny)), np.zeros((nH, nx)), np.zeros((nH, ny))]
        """The sweep's outputs where F (numeric squares) is all there is: zeros, shared read-only."""
        for part in self._unswept:
            part.flags.writeable = False
        self._fixed: tuple[int, LowerSolution, KKTValues | None] | None = None  # (parameter revision, ...)
        self._batches: dict[tuple[int, int], ca.Function] = {}  # batch_phi's sweep, by batch size and revision
        self.conic = bool(low.psd)  # LMIs: the lower level's conic KKT system (bilevel.lower.sdp.ConicKKT)
        self._last_conic: tuple[int, LowerSolution] | None = None  # (prep.runs, the last conic solution of that run)
        self._spectral: ValueAndJacobian | None = None  # a spectral objective's vec M and dM/dx
        self._affine: tuple[int, np.ndarray, np.ndarray] | None = None  # (revision, M(0, y*), dM/dx) when fixed
        if canon.spectral is not None:
            m = ca.vec(canon.spectral)
            self._spectral = ValueAndJacobian(canon.params, "spectral", [x, y], m, 0)
            self.spectral_affine = low.fixed and not any(ca.which_depends(m, x, 2, True))  # no entry nonlinear in x

    @cached_property
    def _spectral_y(self) -> CompiledFunction:
        """(x, y) -> d vec(M)/dy of a spectral objective, built on first use: only a lower level that moves with x
        needs it (on large SDPs M = A + B V S^-1 makes this Jacobian costly)."""
        canon = self.canon
        return canon.params.function("spectral_y", [canon.x, canon.y], [ca.jacobian(ca.vec(canon.spectral), canon.y)])

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
        if na + nh == 0:  # unconstrained at the solution (least squares, the exact block): K is the Hessian
            return hyy
        return np.block([[hyy, jg[rows].T, jh.T],
                         [jg[rows], np.zeros((na, na + nh))],
                         [jh, np.zeros((nh, na + nh))]])

    def _x_adjoint(self, x: np.ndarray, sol: LowerSolution, rows: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """R' Z, R the x-derivative of (stationarity, g_A, h), by the lower level's product over the columns of Z."""
        ny, na = self.low.n_y, rows.size
        V_g = np.zeros((self.low.n_g, Z.shape[1]))
        V_g[rows] = Z[ny:ny + na]
        return self.low.kkt_x_adjoint_columns(x, sol, Z[:ny], V_g, Z[ny + na:])

    @staticmethod
    def _residual(vals: KKTValues, lam: np.ndarray) -> float:
        S, g, h = vals.stationarity.ravel(), vals.g.ravel(), vals.h.ravel()
        parts = [np.abs(S), np.maximum(g, 0.0), np.abs(h), np.abs(lam * g)]
        return max((float(p.max()) for p in parts if p.size), default=0.0)

    def active_set_newton(self, x: np.ndarray, sol: LowerSolution) -> tuple[LowerSolution, KKTValues | None]:
        """One Newton step on the active-set KKT equations at x from sol; kept if it keeps lam >= 0 and lowers the
        residual."""
        if self.low.closed_form:  # a closed form: no active set; KKT values wait for a gradient
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
        """Solve (and refine by active_set_newton) the lower level at x, or take its known solution `lower` (and KKT
        values `kkt`, if known), and evaluate phi there; raises if the lower solve fails. A given solution's objective is read from
        the same sweep as F when it is NaN."""
        x = self.low.check_point(x)
        revision = self.low.params.revision
        if self._fixed is not None and self._fixed[0] == revision:
            _, sol, vals = self._fixed
        elif lower is not None:
            sol, vals = lower, kkt
        elif self.conic:  # Newton continuation from this run's last solution, else the SDP's own solve
            last = self._last_conic
            near = None if last is None or last[0] != self._prep.runs else self.low.continue_from(x, last[1])
            sol, vals = (self.low.solve(x) if near is None else self.low.select(x, near[0])), None
            self._last_conic = (self._prep.runs, sol)
        else:
            sol, vals = self.active_set_newton(x, self.low.solve(x))
        if self.low.fixed:  # y* constant in x: solved once, no adjoint
            self._fixed = (revision, sol, vals)
        if np.isnan(sol.objective) and isinstance(self.low, ExpressionLower):  # F and f share subexpressions
            *upper, f = _shaped(self._upper_and_f(x, sol.y), self._upper_shapes + [(1, 1)])
            upper[3:] = self._expanded(upper[3:])
            sol.objective = float(f[0, 0])
        else:
            if np.isnan(sol.objective):  # the matrix form evaluates f numerically
                sol.objective = float(self.low.evaluate(x, sol.y)[0])
            if self._squares is None or self._upper_shapes[1][0] + self._upper_shapes[2][0] > 0:
                upper = _shaped(self._values(x, sol.y), self._upper_shapes[:3])  # partials when a derivative asks
            else:  # F is all there is: nothing to sweep
                upper = list(self._unswept)
            if self._squares is not None:
                value, gradient = self._squares(sol.y)  # one BLAS evaluation gives both
                upper[0] = value
                if len(upper) > 3:  # the unswept zeros, partials included
                    upper[4] = gradient
        if self._spectral is not None:  # its derivatives when a derivative asks (partials), like the others'
            upper = self._with_spectral(x, sol.y, upper) if len(upper) > 3 else [self._spectral_value(x, sol.y),
                                                                                  *upper[1:]]
        F, G, H = float(upper[0][0, 0]), upper[1].ravel(), upper[2].ravel()
        if G.size + H.size == 0:  # nothing penalized
            return Evaluation(x, F, F, 0.0, sol, upper, vals)
        phi = float(self.penalized(upper[0], upper[1], upper[2])[0])
        violation = max([0.0, *np.maximum(G, 0.0), *np.abs(H)])
        return Evaluation(x, phi, F, violation, sol, upper, vals)

    def partials(self, x: np.ndarray, y: np.ndarray, upper: list[np.ndarray]) -> list[np.ndarray]:
        """An evaluation's `upper` at (x, y) with the partial derivatives of F, G and H appended (one sweep) if it has
        only the values; the same list."""
        if len(upper) == 3:
            upper += self._expanded(_shaped(self._partials(x, y), self._upper_shapes[3:]))
            if self._squares is not None:
                upper[4] = self._squares(y)[1]
            if self._spectral is not None:
                upper[:] = self._with_spectral(x, y, upper)
        return upper

    def _spectral_value(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """F of the spectral objective at (x, y) (1 x 1), without its derivatives."""
        m = np.asarray(self._spectral.value(x, y), dtype=float)
        return np.array([[self.canon.spectral_sign * float(self.canon.matrix_function(
            m.reshape(self.canon.spectral.shape, order="F"))[0])]])

    def _expanded(self, partials: list[np.ndarray]) -> list[np.ndarray]:
        """The swept partials with G's by row from those of its distinct cores."""
        if not self._G_shared:
            return partials
        sign = self._G_sign[:, None]
        return [partials[0], partials[1], sign * partials[2][self._G_index], sign * partials[3][self._G_index],
                *partials[4:]]

    def _with_spectral(self, x: np.ndarray, y: np.ndarray, upper: list[np.ndarray]) -> list[np.ndarray]:
        """The upper sweep with F, dF/dx and dF/dy of the spectral objective in place of the NaN expression's (dF/dy
        NaN on a lower level that ignores x: its gradient never reads it)."""
        m, jx = (np.asarray(v, dtype=float) for v in self._spectral(x, y))
        value, gradient = self.canon.matrix_function(m.reshape(self.canon.spectral.shape, order="F"))
        sign = self.canon.spectral_sign
        g = sign * np.asarray(gradient, dtype=float).ravel(order="F")
        gy = np.full((self.low.n_y, 1), np.nan) if self.low.fixed else \
            (np.asarray(self._spectral_y(x, y), dtype=float).T @ g)[:, None]
        return [np.array([[sign * float(value)]]), upper[1], upper[2], (jx.T @ g)[:, None], gy, *upper[5:]]

    def spectral_batch(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F = sign * rho(M), dF/dx (n_x x S) and the tie counts at each column of xs (n_x x S), for a spectral
        objective on a lower level that ignores x; M affine in x: one product and one stacked eigendecomposition."""
        stack = self._spectral_stack(xs)
        sign = self.canon.spectral_sign
        if stack is None:
            evs = [self.evaluate(x) for x in np.asarray(xs, dtype=float).T]
            return (np.array([ev.F for ev in evs]), np.column_stack([self.gradient(ev)[0] for ev in evs]),
                    np.ones(len(evs), dtype=int))
        r = spectral_radius(stack)
        grads = r.gradient.transpose(0, 2, 1).reshape(stack.shape[0], -1)
        return sign * r.value, sign * (self._affine[2].T @ grads.T), r.ties

    def spectral_values(self, xs: np.ndarray) -> np.ndarray:
        """spectral_batch's F alone, from the eigenvalues only where M is affine in x (about half the cost)."""
        stack = self._spectral_stack(xs)
        return self.spectral_batch(xs)[0] if stack is None else self.canon.spectral_sign * radius(stack)

    def _spectral_stack(self, xs: np.ndarray) -> np.ndarray | None:
        """M at each column of xs (S x n x n) where it is affine in x (one product), None where it is not or the
        function of M is not the spectral radius; ModelError unless the objective is a matrix's and the lower level
        ignores x."""
        if self._spectral is None or not self.low.fixed:
            raise ModelError("spectral_batch needs a spectral-radius upper objective (maximize_spectral_radius) and a "
                             "lower level that does not depend on the upper variables; use evaluate and gradient")
        affine = self.spectral_map()
        return None if affine is None else affine_stack(*affine, xs, int(self.canon.spectral.size1()))

    def spectral_map(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(vec M at x = 0, dvec M/dx) of a spectral-radius objective affine in x on a lower level that ignores x (for
        the current parameter values), None where M is not affine or the function of M is not the spectral radius."""
        if not self.spectral_affine or self.canon.matrix_function is not rho_and_gradient:
            return None
        revision = self.low.params.revision
        if self._affine is None or self._affine[0] != revision:
            zero = np.zeros(self.low.n_x)
            m0, jx = (np.asarray(v, dtype=float) for v in self._spectral(zero, self.evaluate(zero).lower.y))
            self._affine = (revision, m0.ravel(), jx)
        return self._affine[1], self._affine[2]

    def batch_phi(self, xs: np.ndarray) -> np.ndarray:
        """phi at each column of xs (n_x x S) by one mapped sweep, for a lower level that ignores x (solved once)."""
        if not self.low.fixed:
            raise ModelError("batch_phi needs a lower level that does not depend on the upper variables; evaluate "
                             "the points one by one")
        y = self.evaluate(xs[:, 0]).lower.y
        canon, n = self.canon, xs.shape[1]
        key = (n, self.low.params.revision)
        if key not in self._batches:  # F, G, H of every column, y and the parameters folded in as numbers
            known = ca.vertcat(canon.y, canon.params.sym)
            values = ca.DM(np.concatenate([y, canon.params.value]))
            sweep = ca.Function("upper_FGH", [canon.x], [ca.substitute(e, known, values)
                                                          for e in self._upper_outputs[:3]])
            self._batches = {key: sweep.map(n)}
        F, G, H = (np.asarray(v, dtype=float) for v in self._batches[key](xs))
        if self._spectral is not None:
            F = self.spectral_values(xs)
        return self.penalized(F.reshape(1, n), G.reshape(-1, n), H.reshape(-1, n))

    def penalized(self, F: np.ndarray, G: np.ndarray, H: np.ndarray) -> np.ndarray:
        """phi = F + penalty * (sum max(G, 0) + sum |H|) per column of (1 x S, nG x S, nH x S) arrays."""
        return F.ravel() + self.penalty * (np.maximum(G, 0.0).sum(axis=0) + np.abs(H).sum(axis=0))

    def jacobian(self, ev: Evaluation) -> tuple[np.ndarray, bool, int]:
        """The total x-derivatives of F, G_i and H_j along y*(x) at an evaluated point (columns of an n_x x (1 + nG +
        nH) array, one adjoint solve for all), whether the active set was degenerate, and its size."""
        _, G, H, gxF, gyF, Gx, Gy, Hx, Hy = self.partials(ev.x, ev.lower.y, ev.upper)
        penalized = G.size + H.size > 0
        total = np.hstack([gxF, Gx.T, Hx.T]) if penalized else gxF  # columns: d/dx of F, G_i, H_j along y*(x)
        weak, rows = False, NO_ROWS
        if not self.low.fixed:  # dy*/dx = 0 otherwise
            cols = np.hstack([gyF, Gy.T, Hy.T]) if penalized else gyF
            if self.conic:
                rows = np.flatnonzero(ev.lower.lam > 0)
                adjoint, singular = self.low.adjoint(ev.x, ev.lower, cols)
            else:
                kkt = ev.kkt if ev.kkt is not None else self.low.kkt_values(ev.x, ev.lower)
                if self.low.n_g + self.low.n_h:
                    rows, weak = self.active_set(kkt.g, ev.lower.lam)
                    K = self._system(kkt, rows)
                    rhs = np.vstack([cols, np.zeros((K.shape[0] - gyF.size, cols.shape[1]))])
                else:  # unconstrained (least squares, the exact block): K is the Hessian
                    K, rhs = kkt.hessian, cols
                Z, rank = (self.low.kkt_solve(ev.x, K, rhs) if kkt.factor is None  # the solve's factor, if it has one
                           else (factor_solve(kkt.factor, rhs), K.shape[0]))
                adjoint, singular = self._x_adjoint(ev.x, ev.lower, rows, Z), rank < K.shape[0]
            total = total - adjoint
            weak = weak or singular
        return total, bool(weak), int(rows.size)

    def gradient(self, ev: Evaluation) -> tuple[np.ndarray, bool, int]:
        """grad phi at an evaluated point, whether the active set was degenerate, and its size.

        Where some |G_i| or |H_j| <= defaults["implicit.kink_tol"] the penalty is not differentiable: the least-norm
        element of its subdifferential (coefficients in [0, penalty] or [-penalty, penalty]) is returned.
        """
        total, weak, n_active = self.jacobian(ev)
        G, H = ev.upper[1], ev.upper[2]
        if G.size + H.size == 0:  # nothing penalized: grad phi = grad F
            return total[:, 0], weak, n_active
        values = np.concatenate([G, H]).ravel()
        kink = np.abs(values) <= param("implicit.kink_tol")
        coef = self.penalty * np.concatenate([(G.ravel() > 0).astype(float), np.sign(H.ravel())])
        grad = total[:, 0] + total[:, 1:] @ np.where(kink, 0.0, coef)
        if kink.any():
            lo = np.where(np.arange(values.size) < G.size, 0.0, -self.penalty)[kink]
            t = lsq_linear(total[:, 1:][:, kink], -grad, bounds=(lo, np.full(lo.size, self.penalty))).x
            grad = grad + total[:, 1:][:, kink] @ t
        return grad, weak, n_active

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray, LowerSolution]:
        """(phi(x), grad phi(x), lower solution at x)."""
        ev = self.evaluate(x)
        return ev.phi, self.gradient(ev)[0], ev.lower


def hypergradient(prep: Prepared, x: np.ndarray, penalty: float | None = None,
                  active_tol: float | None = None) -> tuple[float, np.ndarray, LowerSolution]:
    """(phi(x), d phi/dx, lower solution) at x (raises if the lower level cannot be solved there); the compiled
    functions are kept on `prep` for later calls."""
    return shared_oracle(prep, penalty, active_tol)(x)


def shared_oracle(prep: Prepared, penalty: float | None = None, active_tol: float | None = None,
                  projected_rows: tuple[int, ...] = ()) -> Hypergradient:
    """The Hypergradient of these settings (None: the registry's implicit.penalty and implicit.active_tol) kept on
    `prep`: its compiled functions serve every later solve."""
    penalty, active_tol = param("implicit.penalty", penalty), param("implicit.active_tol", active_tol)
    key = ("hypergradient", float(penalty), float(active_tol), tuple(projected_rows))
    return prep.cached(key, lambda: Hypergradient(prep, penalty, active_tol, projected_rows))


def affine_stack(m0: np.ndarray, jx: np.ndarray, xs: np.ndarray, n: int) -> np.ndarray:
    """The n x n matrices M with vec M = m0 + jx x (column-major vec) at each column x of xs: an (S, n, n) stack."""
    return (m0[:, None] + jx @ np.asarray(xs, dtype=float)).T.reshape(-1, n, n).transpose(0, 2, 1)
