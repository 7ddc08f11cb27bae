"""Unconstrained strictly convex quadratic lower level (e.g. regularized least squares): closed form."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg.lapack
from scipy.linalg.lapack import dpotrf, dpotrs

from ..errors import RankDeficientRegressor
from .base import LowerSolution
from .quadratic import QPData, QuadraticLower


def hessian_factor(P: np.ndarray) -> np.ndarray:
    """The upper Cholesky factor of the lower Hessian P (LAPACK potrf called directly: the hypergradient factors at
    every evaluation, and scipy's cho_factor wrapper costs ten times the factorization of a small P); raises
    RankDeficientRegressor if P is not positive definite."""
    P = np.asarray(P, dtype=float)
    if not np.all(np.isfinite(P)):
        raise ValueError("the least-squares lower level's Hessian has NaN or inf entries at this x")
    factor, info = dpotrf(0.5 * (P + P.T), lower=False, clean=False)
    if info != 0:
        raise RankDeficientRegressor(
            "the least-squares lower level has a singular Hessian at this x, so its solution is not "
            "unique; add regularization or declare constraints so that it is solved as a QP")
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
        """The closed form (the QP route of QuadraticLower would state a dense least squares through cvxpy)."""
        return self.solve(x)
