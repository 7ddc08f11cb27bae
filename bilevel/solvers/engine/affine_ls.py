"""The engine's ascent on a lower level of kind AffineLeastSquares (bilevel.lower.affine_least_squares) under an upper
objective J(theta) to maximize: the oracle ascend_with_exact_block reads (phi = -J and its gradient by the kind's
adjoints, O(rows k) per evaluation), and the target block as its exact block where J is quadratic in theta and the
target signals have a plain ball budget (a trust-region subproblem in the block's isometric coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Hashable

import numpy as np

from ...lower.affine_least_squares import AffineLeastSquares, Fit
from ...lower.base import LowerSolution
from .block_exact import quadratic_block_step
from .starts import ConditioningParts
from .structure import Ball

EMPTY = np.zeros(0)


@dataclass
class UpperObjective:
    """J(theta) to maximize, its gradient and, where J is quadratic, its constant Hessian (else None)."""

    value: Callable[[np.ndarray], float]
    gradient: Callable[[np.ndarray], np.ndarray]
    hessian: np.ndarray | None = None


@dataclass
class Point:
    """An evaluated point as the engine's ascent reads it: x = (a, b), phi = F = -J, the learner's solution."""

    fit: Fit
    phi: float

    @property
    def x(self) -> np.ndarray:
        return np.concatenate([self.fit.a, self.fit.b])

    @property
    def F(self) -> float:
        return self.phi

    @property
    def lower(self) -> LowerSolution:
        return LowerSolution(self.fit.theta, np.nan, EMPTY, EMPTY, [], "optimal", "thin QR")


@dataclass
class Oracle:
    """phi(x) = -J(theta*(x)) and its gradient, for bilevel.solvers.engine.block_exact's ascent."""

    learner: AffineLeastSquares
    upper: UpperObjective
    start_key: Hashable | None = None
    """Names the conditioning start of hessian_parts (ConditioningParts.key): the data, the moving block's set."""

    def evaluate(self, x: np.ndarray, fit: Fit | None = None, kkt: None = None) -> Point:
        """The fit at x (or the known one) and -J there."""
        n = self.learner.n_a
        fit = self.learner.fit(x[:n], x[n:]) if fit is None else fit
        return Point(fit, -self.upper.value(fit.theta))

    def gradient(self, p: Point) -> tuple[np.ndarray]:
        """(grad phi in x,)."""
        return (-np.concatenate(self.learner.gradient(p.fit, self.upper.gradient(p.fit.theta))),)

    @property
    def hessian_parts(self) -> ConditioningParts:
        """The learner's Hessian C'C and the x-gradient of v'C'C v, for the engine's conditioning start
        (bilevel.solvers.engine.starts), keyed by start_key."""
        low, n, last = self.learner, self.learner.n_a, {}

        def regressor(x: np.ndarray) -> np.ndarray:  # the engine asks for both parts at each point
            if last.get("x") is None or not np.array_equal(last["x"], x):
                last.update(x=x.copy(), C=low.C0 + low.maps.regressor(x[n:]))
            return last["C"]

        def adjoint(x: np.ndarray, v: np.ndarray) -> np.ndarray:
            return np.concatenate([np.zeros(n), low.gram_adjoint(x[n:], regressor(x), v)])

        def hessian(x: np.ndarray) -> np.ndarray:
            C = regressor(x)
            return C.T @ C

        return ConditioningParts(hessian, adjoint, self.start_key)


@dataclass
class TargetBlock:
    """The exact block a (ball `ball`, radius `radius`) at its global optimum for the given b, J quadratic."""

    learner: AffineLeastSquares
    upper: UpperObjective
    ball: Ball
    radius: float

    def solve(self, x: np.ndarray) -> tuple[np.ndarray, Fit, None]:
        """x (overwritten) with a replaced by its best value for this b, and the fit there."""
        low, n = self.learner, self.learner.n_a
        if self.radius == 0:
            fit = low.fit(np.zeros(n), x[n:], low.d0)
        else:
            s0, S, B = low.target_block(x[n:])
            v = quadratic_block_step(S, -self.upper.gradient(s0.theta), -self.upper.hessian, self.radius)
            fit = low.moved(s0, S, B, v)
        x[:n] = fit.a
        return x, fit, None
