"""A lower QP given by matrices: min 1/2 ||C y - d||^2 + 1/2 y'Py + q'y + r s.t. A y <= b, E y = e.

C, P, A, E are numbers (fixed data); d, q, b, e (and the constant r) are CasADi expressions of the upper variables
and parameters
(the data the attacker moves). No expression of size C x y is ever built: values, KKT systems and the adjoint
R' v are matrix products with the numeric data plus one reverse sweep through the small vector expressions.
This is what lets a dense least squares with thousands of variables be declared and differentiated in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from ..defaults import param
from ..errors import (InvalidData, LowerLevelInfeasible, LowerLevelUnbounded, ModelError, RankDeficientRegressor,
                      SolverFailed)
from ..model import LowerQP
from ..parameters import ParameterSet
from ..real_data import refuse_complex
from .base import ExpressionLower, KKTValues, LowerLevel, LowerSolution
from .least_squares import LeastSquaresLower, factor_solve, hessian_factor
from .polish import polish
from .quadratic import (LinearLower, QPData, QuadraticLower, clarabel_solution, singular_hessian,
                        solve_qp_clarabel)


@dataclass
class MatrixLower(LowerLevel):
    """The lower QP of `BilevelProblem.lower_qp`, or of expressions recognized as one (bilevel.lower.qp_form); bounds
    of y are rows of A (named like declared constraints).

    Kind: least-squares (no constraints, C'C + P positive definite: Cholesky, factored once), lp (no quadratic
    term: HiGHS dual simplex, a vertex with exact duals) or qp (Clarabel). The certificate's re-solve is
    independent of these: Clarabel for LP/QP, an LU solve for least squares.
    """

    x: ca.SX
    y: ca.SX
    qp: LowerQP
    """The declaration, with the bounds of y appended to A and b."""
    g_names: list[str]
    h_names: list[str]
    params: ParameterSet = field(default_factory=ParameterSet, repr=False)
    psd: list = field(default_factory=list)
    psd_names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        qp = self.qp
        self.C, self.P, self.A, self.E, self.d, self.q, self.b, self.e = (qp.C, qp.P, qp.A, qp.E, qp.d, qp.q, qp.b,
                                                                          qp.e)
        self.hess = self.C.T @ self.C + self.P
        self.r = qp.r
        self._vectors = self.params.function("qp_vectors", [self.x], [self.d, self.q, self.b, self.e, self.r])
        v = [ca.SX.sym(n, int(s.numel())) for n, s in (("v_d", self.d), ("v_q", self.q), ("v_b", self.b),
                                                          ("v_e", self.e))]
        adj = sum((ca.jtimes(s, self.x, w, True) for s, w in zip((self.d, self.q, self.b, self.e), v) if s.numel()),
                  ca.SX.zeros(self.n_x))
        self._adjoint = self.params.function("qp_vectors_adjoint", [self.x, *v], [adj])
        self._active: np.ndarray | None = None  # the last solve's active rows (a warm start, verified before use)
        if not self.A.shape[0] and not self.E.shape[0]:
            self.kind = "least-squares" if self.factor is not None else "qp"
        else:
            self.kind = "qp" if np.any(self.hess) else "lp"

    @cached_property
    def factor(self) -> np.ndarray | None:
        """The upper Cholesky factor of C'C + P (fixed data: factored once; the form of
        bilevel.lower.least_squares.hessian_factor), None if it is not positive definite."""
        try:
            return hessian_factor(self.hess)
        except RankDeficientRegressor:
            return None

    @cached_property
    def fixed(self) -> bool:
        return not ca.depends_on(ca.vertcat(self.d, self.q, self.b, self.e), self.x)

    def vectors(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """d, q, b, e at x."""
        return self.values(x)[:4]

    def values(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """d, q, b, e and r (as a 1-vector) at x, one sweep."""
        return tuple(np.asarray(v, dtype=float).ravel() for v in self._vectors(x))

    def linear_term(self, x: np.ndarray) -> np.ndarray:
        """q - C'd at x: the objective is 1/2 y'(C'C + P)y + (q - C'd)'y + const."""
        d, q, _, _ = self.vectors(x)
        return q - self.C.T @ d

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray]]:
        d, q, b, e, r = self.values(x)
        res = self.C @ y - d
        f = 0.5 * float(res @ res) + 0.5 * float(y @ self.P @ y) + float(q @ y) + float(r[0])
        return f, self.A @ y - b, self.E @ y - e, []

    def derivatives(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        return self.hess @ y + self.linear_term(x), self.A, self.E, []

    def hessian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.hess

    def curvatures(self, x: np.ndarray, y: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """None to test: C'C + P is fixed data, P checked PSD at declaration (lower_qp); an eigendecomposition of a
        large dense Hessian per certificate would cost more than the solve."""
        return []

    def kkt_values(self, x: np.ndarray, sol: LowerSolution) -> KKTValues:
        S = self.stationarity(x, sol.y, sol.lam, sol.mu, [])[0]
        _, _, b, e = self.vectors(x)
        return KKTValues(S[:, None], (self.A @ sol.y - b)[:, None], (self.E @ sol.y - e)[:, None], self.hess, self.A,
                         self.E)

    def kkt_x_adjoint(self, x: np.ndarray, sol: LowerSolution, v_s: np.ndarray, v_g: np.ndarray,
                      v_h: np.ndarray) -> np.ndarray:
        """dS/dx = dq/dx - C' dd/dx, dg/dx = -db/dx, dh/dx = -de/dx, so R'v = J_d'(-C v_s) + J_q'v_s - J_b'v_g
        - J_e'v_h."""
        return np.asarray(self._adjoint(x, -(self.C @ v_s), v_s, -v_g, -v_h)).ravel()

    def kkt_solve(self, x: np.ndarray, K: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
        """Least-squares kind: K = C'C + P, solved by its Cholesky factor (factored once); else the default."""
        if self.kind != "least-squares":
            return super().kkt_solve(x, K, rhs)
        return factor_solve(self.factor, rhs), K.shape[0]

    def data(self, x: np.ndarray) -> QPData:
        """The QP coefficients at x in the form of the expression kinds (g = A y - b, h = E y - e)."""
        d, q, b, e, r = self.values(self.check_point(x))
        return QPData(self.hess, q - self.C.T @ d, 0.5 * float(d @ d) + float(r[0]), self.A, -b, self.E, -e)

    def nonunique_at(self, x: np.ndarray) -> str | None:
        return singular_hessian(self.data(x)) if self.kind == "qp" else super().nonunique_at(x)

    def solve(self, x: np.ndarray) -> LowerSolution:
        """Closed form (least squares), HiGHS (LP) or Clarabel (QP) at x."""
        x = self.check_point(x)
        if self.kind == "least-squares":  # C'C + P is positive definite: that is what makes the kind
            y = -factor_solve(self.factor, self.linear_term(x))
            return LowerSolution(y, self.evaluate(x, y)[0], np.zeros(0), np.zeros(0), [], "optimal", "closed-form")
        sol = self._from_active_set(x)
        if sol is None:
            sol = self._solve_highs(x) if self.kind == "lp" else None
            if sol is None or self._violates(x, sol.y):  # Clarabel decides near the edge of the feasible set
                sol = solve_qp_clarabel(self.data(x), "(a matrix QP)", psd_verified=True)
            self._active = np.flatnonzero(sol.lam > param("polish.active_tol"))
        return sol

    def _violates(self, x: np.ndarray, y: np.ndarray) -> bool:
        """Whether y violates a row of A y <= b or E y = e at x by more than defaults["matrix.feas_tol"] of the row's
        scale (1 + |b| + |A| |y|): HiGHS's tolerance is 1e-7 at the least, and the certificate's re-solve (Clarabel)
        finds the lower level infeasible where a row is violated by 1e-10 (Bard's 5.1.1 at x = 4 + 1e-8)."""
        _, _, b, e = self.vectors(x)
        tol, ay = param("matrix.feas_tol"), np.abs(y)
        return bool(np.any(self.A @ y - b > tol * (1.0 + np.abs(b) + np.abs(self.A) @ ay))
                    or np.any(np.abs(self.E @ y - e) > tol * (1.0 + np.abs(e) + np.abs(self.E) @ ay)))

    def _from_active_set(self, x: np.ndarray) -> LowerSolution | None:
        """The solution with the last solve's active set, if it is still optimal at x (None otherwise).

        For data moving in d, q, b, e the optimal active set stays optimal over a region of x (a critical region of
        the parametric QP): one solve of its KKT equations, then primal feasibility and lam >= 0 prove optimality.
        """
        rows = self._active
        if rows is None:
            return None
        d, q, b, e = self.vectors(x)
        A_B, n, na, ne = self.A[rows], self.n_y, rows.size, self.E.shape[0]
        K = np.block([[self.hess, A_B.T, self.E.T], [A_B, np.zeros((na, na + ne))], [self.E, np.zeros((ne, na + ne))]])
        try:
            w = np.linalg.solve(K, np.concatenate([self.C.T @ d - q, b[rows], e]))
        except np.linalg.LinAlgError:
            return None
        y, lam_b = w[:n], w[n:n + na]
        if np.any(lam_b < -param("polish.active_tol")) or not np.all(np.isfinite(w)) or self._violates(x, y):
            return None
        lam = np.zeros(self.A.shape[0])
        lam[rows] = np.maximum(lam_b, 0.0)
        return LowerSolution(y, self.evaluate(x, y)[0], lam, w[n + na:], [], "optimal",
                             "active set of the previous solve, verified optimal")

    def _solve_highs(self, x: np.ndarray) -> LowerSolution:
        d, q, b, e = self.vectors(x)
        res = linprog(q - self.C.T @ d, A_ub=self.A if self.A.size else None, b_ub=b if b.size else None,
                      A_eq=self.E if self.E.size else None, b_eq=e if e.size else None, bounds=(None, None),
                      method="highs-ds")
        if res.status == 2:
            raise LowerLevelInfeasible("the lower LP is infeasible at this upper point (HiGHS)")
        if res.status == 3:
            raise LowerLevelUnbounded("the lower LP is unbounded below at this upper point (HiGHS); bound y")
        if res.status != 0:
            raise SolverFailed(f"HiGHS did not solve the lower LP: {res.message}")
        lam = -np.asarray(res.ineqlin.marginals) if b.size else np.zeros(0)  # d obj / d b = -lam
        mu = -np.asarray(res.eqlin.marginals) if e.size else np.zeros(0)
        y = np.asarray(res.x)
        return LowerSolution(y, self.evaluate(x, y)[0], np.maximum(lam, 0.0), mu, [], "optimal", "highs (dual simplex)")

    def reference_solve(self, x: np.ndarray) -> LowerSolution:
        """Clarabel through cvxpy for LP/QP, polished onto its optimal face as the expression kinds' re-solve is (an
        interior point stops about 1e-6 inside a face that is active with a zero multiplier); for least squares an LU
        solve (not the Cholesky factor the methods use)."""
        x = self.check_point(x)
        if self.kind == "least-squares":
            y = np.linalg.solve(self.hess, -self.linear_term(x))
            return LowerSolution(y, self.evaluate(x, y)[0], np.zeros(0), np.zeros(0), [], "optimal", "LU solve")
        data = self.data(x)
        return polish(data, (), clarabel_solution(data, "(a matrix QP, independent re-solve)", psd_verified=True))

    def symbolic(self) -> ExpressionLower:
        """The same QP as CasADi expressions, for the KKT reduction (ipopt, relaxation, global).

        Its size is that of the data (C y has C.size terms): at thousands of dense variables this takes minutes,
        where the methods on this matrix form take seconds."""
        return self._symbolic

    @cached_property
    def _symbolic(self) -> ExpressionLower:
        y = self.y
        r = ca.mtimes(_dm(self.C), y) - self.d
        f = 0.5 * ca.sumsqr(r) + 0.5 * ca.mtimes(y.T, ca.mtimes(_dm(self.P), y)) + ca.dot(self.q, y) + self.r
        g = ca.mtimes(_dm(self.A), y) - self.b
        h = ca.mtimes(_dm(self.E), y) - self.e
        cls = {"least-squares": LeastSquaresLower, "lp": LinearLower}.get(self.kind, QuadraticLower)
        return cls(self.x, y, f, g, h, [], self.g_names, self.h_names, [], ca.SX(_dm(self.hess)), self.params)


def as_dense(matrix: object, cols: int, what: str) -> np.ndarray:
    """A numeric matrix (numpy or scipy.sparse) as a dense float array with `cols` columns (0 rows if None)."""
    if matrix is None:
        return np.zeros((0, cols))
    refuse_complex(matrix, f"lower_qp: {what}")
    try:
        arr = matrix.toarray() if sp.issparse(matrix) else np.asarray(matrix, dtype=float)
    except (TypeError, ValueError):
        raise ModelError(f"lower_qp: {what} must be a numeric matrix (numpy or scipy.sparse), got "
                         f"{type(matrix).__name__}; only d, q, b, e may be expressions") from None
    arr = arr.reshape(1, -1) if arr.ndim == 1 else arr
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise ModelError(f"lower_qp: {what} has shape {arr.shape}; it needs {cols} columns (one per lower variable)")
    if not np.all(np.isfinite(arr)):
        raise InvalidData(f"lower_qp: {what} contains NaN or inf; clean the data first")
    return arr


def _dm(matrix: np.ndarray) -> ca.DM:
    """A numeric matrix as a CasADi DM with its structural zeros (no 0 * y terms in expressions)."""
    return ca.DM(sp.csc_matrix(matrix))
