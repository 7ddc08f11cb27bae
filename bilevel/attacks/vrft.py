"""The VRFT learner in structured form, as the engine's oracle: its least-squares fit on poisoned data by a thin QR,
the attacker's hypergradient by the adjoint of the filters, and the exact input step (a trust-region subproblem).

Everything is O(N nk) per evaluation (the instance, its data and objective: bilevel.problems.vrft_instance).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from ..ddc.vrft import thin_qr
from ..errors import ModelError, RankDeficientRegressor
from ..lower.base import LowerSolution
from ..lower.least_squares import factor_solve
from ..problems.vrft_instance import VRFTAttack
from ..solvers.block_exact import quadratic_block_step
from ..solvers.structure import Ball

EMPTY = np.zeros(0)


@dataclass
class State:
    """The learner's fit on poisoned data: regressor Phi', targets t', theta' and the thin QR of Phi'."""

    a_u: np.ndarray
    a_y: np.ndarray
    phi: np.ndarray
    target: np.ndarray
    theta: np.ndarray
    R: np.ndarray
    Q: np.ndarray


def state(atk: VRFTAttack, a_u: np.ndarray, a_y: np.ndarray) -> State:
    """The learner's least-squares fit on (u + a_u, y + a_y)."""
    target = atk.t0 + atk.setting.regressor.targets(a_u) if np.any(a_u) else atk.t0
    return _fit(atk, a_u, a_y, target)


def _fit(atk: VRFTAttack, a_u: np.ndarray, a_y: np.ndarray, target: np.ndarray) -> State:
    """Thin QR of Phi(y + a_y) and theta' for the given targets."""
    phi = atk.phi0 + atk.setting.regressor(a_y) if np.any(a_y) else atk.phi0
    Q, R = thin_qr(phi)
    theta, info = scipy.linalg.lapack.dtrtrs(R, Q.T @ target)  # R theta = Q't (LAPACK directly: once per step)
    if info != 0:
        raise RankDeficientRegressor(f"the poisoned regressor Phi' has rank below {R.shape[1]} (R[{info - 1}, "
                                     f"{info - 1}] = 0): the learner's least squares has no unique solution")
    return State(a_u, a_y, phi, target, theta, R, Q)


def hypergradient(atk: VRFTAttack, s: State) -> tuple[np.ndarray, np.ndarray]:
    """(dJ/da_u, dJ/da_y) at state s, by implicit differentiation of the normal equations.

    With w = (Phi'^T Phi')^{-1} dJ/dtheta and r' = t' - Phi' theta':
    dJ/da_u = targets^T (Phi' w),  dJ/da_y = sum_i T_i^T (w_i r' - theta'_i Phi' w).
    """
    w = factor_solve(s.R, atk.grad_theta(s.theta))  # (R'R)^{-1} g, R'R = Phi'^T Phi'
    pw = s.phi @ w
    residual = s.target - s.phi @ s.theta
    g_y = atk.setting.regressor.adjoint(residual[:, None] * w - pw[:, None] * s.theta)
    return atk.setting.regressor.targets_adjoint(pw, atk.N), g_y


def exact_input(atk: VRFTAttack) -> str:
    """Why the exact input step does not apply to `atk` ("" where it does)."""
    if atk.objective == "destabilize":
        return "the destabilize objective is not quadratic in theta"
    if atk.budget_u.norm != "l2" or atk.budget_u.rho is not None:
        return f"the input budget {atk.budget_u} is not a plain l2 ball"
    return ""


def best_input_attack(atk: VRFTAttack, a_y: np.ndarray) -> tuple[np.ndarray, State]:
    """Globally optimal a_u for fixed a_y when J is quadratic in theta and the budget is a plain l2 ball.

    theta' = theta'_0 + S v and a_u = B v with ||a_u|| = ||v||, where Phi' = QR, W = targets^T Q,
    S = R^{-1} (W'W)^{1/2}, B = W (W'W)^{-1/2}; a k-dimensional trust-region subproblem in v.
    """
    if why := exact_input(atk):
        raise ModelError(f"the exact input step needs a quadratic objective (maxmin/targeted) and a plain l2 budget on "
                         f"a_u: {why}; use the joint attack")
    zero = np.zeros(atk.N)
    s0 = _fit(atk, zero, a_y, atk.t0)
    if atk.delta_u == 0:
        return zero, s0
    reg = atk.setting.regressor
    if reg.prefilter is None:  # targets(a) = a[:n]: W = [Q; 0] has orthonormal columns already
        S = scipy.linalg.lapack.dtrtri(s0.R)[0]  # R^{-1}
        B = None
    else:
        W = reg.targets_adjoint(s0.Q, atk.N)
        lam, V = np.linalg.eigh(W.T @ W)
        lam = np.maximum(lam, 1e-14 * lam.max())
        S = scipy.linalg.solve_triangular(s0.R, (V * np.sqrt(lam)) @ V.T)
        B = W @ ((V / np.sqrt(lam)) @ V.T)
    # theta = s0.theta + S v over ||v|| <= delta_u: the framework's exact block step on -J (quadratic in theta)
    if atk.objective == "maxmin":  # J = ||t0 - Phi0 theta||^2 / n, via Phi0's Gram matrix
        grad, hess = -2.0 * (atk.cross0 - atk.gram0 @ s0.theta) / atk.n, 2.0 * atk.gram0 / atk.n
    else:  # J = -||theta_a - theta||^2 / k
        k = atk.theta_target.size
        grad, hess = 2.0 * (atk.theta_target - s0.theta) / k, -2.0 * np.eye(k) / k
    v = quadratic_block_step(S, -grad, -hess, atk.delta_u)
    if B is None:  # a_u = [Q v; 0] and targets(a_u) = Q v
        qv = s0.Q @ v
        a_u = zero
        a_u[: atk.n] = qv
        target = s0.target + qv
    else:
        a_u = B @ v
        target = s0.target + reg.targets(a_u)
    return a_u, State(a_u, a_y, s0.phi, target, s0.theta + S @ v, s0.R, s0.Q)


@dataclass
class Point:
    """An evaluated attack as the engine's ascent reads it: x = (a_u, a_y), phi = F = -J, the learner's solution."""

    state: State
    phi: float

    @property
    def x(self) -> np.ndarray:
        return np.concatenate([self.state.a_u, self.state.a_y])

    @property
    def F(self) -> float:
        return self.phi

    @property
    def lower(self) -> LowerSolution:
        return LowerSolution(self.state.theta, np.nan, EMPTY, EMPTY, [], "optimal", "thin QR")


@dataclass
class Oracle:
    """The attacker's criterion -J(theta(x)) and its gradient, for bilevel.solvers.block_exact's ascent."""

    atk: VRFTAttack

    def evaluate(self, x: np.ndarray, s: State | None = None, kkt: None = None) -> Point:
        """The fit at x (or the known one, s) and -J there."""
        s = state(self.atk, x[: self.atk.N], x[self.atk.N:]) if s is None else s
        return Point(s, -self.atk.value(s.theta))

    def gradient(self, p: Point) -> tuple[np.ndarray]:
        """(grad of -J in x,)."""
        return (-np.concatenate(hypergradient(self.atk, p.state)),)

    @property
    def hessian_parts(self) -> tuple[Callable, Callable]:
        """The learner's Hessian Phi'^T Phi' (up to its factor 2/n) and the x-gradient of v' Phi'^T Phi' v, for the
        engine's conditioning start (bilevel.solvers.starts)."""
        atk, N, last = self.atk, self.atk.N, {}

        def regressor(x: np.ndarray) -> np.ndarray:  # the engine asks for both parts at each point
            if last.get("x") is None or not np.array_equal(last["x"], x):
                last.update(x=x.copy(), phi=atk.phi0 + atk.setting.regressor(x[N:]))
            return last["phi"]

        def adjoint(x: np.ndarray, v: np.ndarray) -> np.ndarray:
            return np.concatenate([np.zeros(N), 2.0 * atk.setting.regressor.adjoint(np.outer(regressor(x) @ v, v))])

        return lambda x: regressor(x).T @ regressor(x), adjoint


@dataclass
class InputStep:
    """The exact input step as the engine's exact block: a_u (block `ball`) at its optimum for the given a_y."""

    atk: VRFTAttack
    ball: Ball

    def solve(self, x: np.ndarray) -> tuple[np.ndarray, State, None]:
        """x (overwritten) with a_u replaced by the best input poisoning, and the fit there."""
        a_u, s = best_input_attack(self.atk, x[self.atk.N:])
        x[: self.atk.N] = a_u
        return x, s, None
