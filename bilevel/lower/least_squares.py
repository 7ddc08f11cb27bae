"""Unconstrained strictly convex quadratic lower level (e.g. regularized least squares): closed form."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..errors import RankDeficientRegressor
from .base import LowerSolution
from .quadratic import QPData, QuadraticLower


def hessian_factor(P: np.ndarray) -> tuple[np.ndarray, bool]:
    """The Cholesky factor of the lower Hessian P; raises RankDeficientRegressor if P is not positive definite."""
    try:
        return sla.cho_factor(0.5 * (P + P.T))
    except np.linalg.LinAlgError as exc:
        raise RankDeficientRegressor(
            "the least-squares lower level has a singular Hessian at this x, so its solution is not "
            "unique; add regularization or declare constraints so that it is solved as a QP"
        ) from exc


@dataclass
class LeastSquaresLower(QuadraticLower):
    """min_y 1/2 y'P(x)y + q(x)'y + r(x) with P(x) positive definite: y*(x) = -P(x)^{-1} q(x)."""

    kind = "least-squares"

    def factor(self, x: np.ndarray) -> tuple[QPData, tuple[np.ndarray, bool]]:
        """The coefficients at x and the Cholesky factor of P(x); raises if P(x) is not positive definite."""
        d = self.data(x)
        return d, hessian_factor(d.P)

    def kkt_solve(self, x: np.ndarray, K: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
        """K = P(x) is positive definite: P(x)^{-1} rhs by its Cholesky factor, full rank."""
        return sla.cho_solve(hessian_factor(K), rhs), K.shape[0]

    def solve(self, x: np.ndarray) -> LowerSolution:
        """Closed form via a Cholesky factorization; raises if P(x) is not positive definite."""
        d, factor = self.factor(x)
        y = -sla.cho_solve(factor, d.q)
        fval = float(0.5 * y @ d.P @ y + d.q @ y + d.r)
        return LowerSolution(y, fval, np.zeros(0), np.zeros(0), [], "optimal", "closed-form")
