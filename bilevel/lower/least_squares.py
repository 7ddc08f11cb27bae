"""Unconstrained strictly convex quadratic lower level (e.g. regularized least squares): closed form."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np
import scipy.linalg.lapack
from scipy.linalg.lapack import dpotrf, dpotrs

from ..errors import RankDeficientRegressor
from ..parameters import CompiledFunction
from .base import LowerSolution
from .quadratic import QPData, QuadraticLower

SINGULAR = ("the least-squares lower level has a singular Hessian at this x, so its solution is not unique; add "
            "regularization or declare constraints so that it is solved as a QP")


def hessian_factor(P: np.ndarray) -> np.ndarray:
    """The upper Cholesky factor of the lower Hessian P (LAPACK potrf called directly: the hypergradient factors at
    every evaluation, and scipy's cho_factor wrapper costs ten times the factorization of a small P); raises
    RankDeficientRegressor if P is not positive definite."""
    P = np.asarray(P, dtype=float)
    if not np.all(np.isfinite(P)):
        raise ValueError("the least-squares lower level's Hessian has NaN or inf entries at this x")
    factor, info = dpotrf(0.5 * (P + P.T), lower=False, clean=False)
    if info != 0:
        raise RankDeficientRegressor(SINGULAR)
    return factor


def factor_solve(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """P^{-1} rhs (a vector or the columns of a matrix) from factor = hessian_factor(P)."""
    solution, info = dpotrs(factor, np.asarray(rhs, dtype=float), lower=False)
    if info != 0:  # pragma: no cover - potrs fails only on malformed arguments
        raise ValueError(f"LAPACK potrs failed with info = {info}")
    return solution


def thin_qr(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q, R) with phi = Q R, Q (rows x cols) orthonormal, R upper triangular, for a tall phi: LAPACK geqrf and orgqr
    called directly (what np.linalg.qr computes, without its per-call overhead, which the attacks pay per step)."""
    qr, tau, _, info = scipy.linalg.lapack.dgeqrf(phi)
    if info != 0:  # pragma: no cover - geqrf fails only on malformed arguments
        raise ValueError(f"LAPACK geqrf failed with info = {info}")
    r = np.triu(qr[: phi.shape[1]])
    q, _, info = scipy.linalg.lapack.dorgqr(qr, tau, overwrite_a=True)
    if info != 0:  # pragma: no cover
        raise ValueError(f"LAPACK orgqr failed with info = {info}")
    return q, r


def sum_of_squares(f: ca.SX, y: ca.SX) -> tuple[ca.SX, ca.SX] | None:
    """(r, c) with f = 1/2 ||r||^2 + c, r affine in y and c free of y, read from f's top-level sum of weighted squares
    (a least squares); None if f is not of that form (a term with y that is not a square, a square with a negative
    weight, or a squared expression nonlinear in y)."""
    rows, scales, rest, stack = [], [], [], [(f, 1.0)]
    while stack:
        e, w = stack.pop()
        if e.is_constant():
            rest.append(w * e)
        elif e.is_op(ca.OP_ADD) or e.is_op(ca.OP_SUB):
            stack += [(e.dep(0), w), (e.dep(1), w if e.is_op(ca.OP_ADD) else -w)]
        elif e.is_op(ca.OP_NEG):
            stack.append((e.dep(0), -w))
        elif e.is_op(ca.OP_MUL) and (e.dep(0).is_constant() or e.dep(1).is_constant()):
            const, other = (e.dep(0), e.dep(1)) if e.dep(0).is_constant() else (e.dep(1), e.dep(0))
            stack.append((other, w * float(ca.evalf(const))))
        elif e.is_op(ca.OP_DIV) and e.dep(1).is_constant():
            stack.append((e.dep(0), w / float(ca.evalf(e.dep(1)))))
        elif e.is_op(ca.OP_SQ) or (e.is_op(ca.OP_MUL) and ca.is_equal(e.dep(0), e.dep(1), 1)):
            if w < 0:
                return None
            if w > 0:
                rows.append(e.dep(0))
                scales.append(math.sqrt(2.0 * w))
        elif ca.depends_on(e, y):
            return None
        else:
            rest.append(w * e)
    if not rows:
        return None
    r = ca.vertcat(*rows)
    if any(ca.which_depends(r, y, 2, False)):
        return None
    return r * ca.DM(scales), (ca.sum1(ca.vertcat(*rest)) if rest else ca.SX(0.0))  # one elementwise product


@dataclass
class LeastSquaresLower(QuadraticLower):
    """min_y 1/2 y'P(x)y + q(x)'y + r(x) with P(x) positive definite: y*(x) = -P(x)^{-1} q(x)."""

    kind = "least-squares"

    def factor(self, x: np.ndarray) -> tuple[QPData, np.ndarray]:
        """The coefficients at x and the Cholesky factor of P(x); raises if P(x) is not positive definite."""
        d = self.data(x)
        return d, hessian_factor(d.P)

    def kkt_solve(self, x: np.ndarray, K: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
        """K = P(x): P(x)^{-1} rhs by its Cholesky factor, full rank; RankDeficientRegressor where P(x) is singular to
        working precision (a learner the attacker made singular: y*(x) has no derivative there, and the methods
        treat x as a point that fails)."""
        return factor_solve(hessian_factor(K), rhs), K.shape[0]

    def solve(self, x: np.ndarray) -> LowerSolution:
        """Closed form via a Cholesky factorization; raises if P(x) is not positive definite."""
        d, factor = self.factor(x)
        y = -factor_solve(factor, d.q)
        return LowerSolution(y, d.objective(y), np.zeros(0), np.zeros(0), [], "optimal", "closed-form")

    def reference_solve(self, x: np.ndarray) -> LowerSolution:
        """The certificate's re-solve: where f is a sum of squares of residuals affine in y (sum_of_squares), LAPACK's
        SVD-based lstsq on the residual's C(x), d(x), with f evaluated from the declaration: the closed form's normal
        equations square the condition number of C (an IV learner with cond(Z'Phi) = 1e8 kept no digit of theta, and
        its f = 1/2 y'Py + q'y + r came out negative); else the closed form (the QP route of QuadraticLower would state
        a dense least squares through cvxpy)."""
        if self._residual is None:
            return self.solve(x)
        C, d = (np.asarray(v, dtype=float) for v in self._residual(x))
        y, _, rank, _ = np.linalg.lstsq(C, d.ravel(), rcond=None)
        if rank < self.n_y:
            raise RankDeficientRegressor(SINGULAR)
        return LowerSolution(y, self.evaluate(x, y)[0], np.zeros(0), np.zeros(0), [], "optimal", "lstsq (SVD)")

    @cached_property
    def _residual(self) -> CompiledFunction | None:
        """x -> (C(x), d(x)) with f = 1/2 ||C(x) y - d(x)||^2 + c(x) where f is a sum of squares, else None."""
        form = sum_of_squares(self.f, self.y)
        if form is None:
            return None
        r = form[0]
        return self.params.function("reference_residual", [self.x], [ca.jacobian(r, self.y),
                                                                    -ca.substitute(r, self.y, ca.DM.zeros(self.n_y))])
