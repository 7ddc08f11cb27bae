"""The learner of a VRFT instance in structured form: its least-squares fit on poisoned data, the attacker's
hypergradient by implicit differentiation, and the exact input step.

Everything is O(N nk) per evaluation: Phi by filtering, theta by a thin QR, gradients by adjoints
(the instance, its data and objective: bilevel.problems.vrft_instance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from ..ddc.vrft import thin_qr
from ..errors import ModelError, RankDeficientRegressor
from ..lower.least_squares import factor_solve
from ..problems.vrft_instance import VRFTAttack
from ..solvers.block_exact import quadratic_block_step


@dataclass
class State:
    """The learner's fit on poisoned data: Phi', targets t', theta' and the thin QR of Phi'."""

    a_u: np.ndarray
    a_y: np.ndarray
    phi: np.ndarray
    target: np.ndarray
    theta: np.ndarray
    R: np.ndarray
    Q: np.ndarray


def state(atk: VRFTAttack, a_u: np.ndarray, a_y: np.ndarray) -> State:
    """The learner's least-squares fit on (u + a_u, y + a_y)."""
    reg = atk.setting.regressor
    target = atk.t0 + reg.targets(a_u) if np.any(a_u) else atk.t0
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


def targets_adjoint(atk: VRFTAttack, g: np.ndarray) -> np.ndarray:
    """Adjoint of a -> targets(a) (applied to a vector or to columns): pad the dropped rows, then L^T."""
    reg = atk.setting.regressor
    padded = np.concatenate([g, np.zeros((atk.N - g.shape[0],) + g.shape[1:])])
    return padded if reg.prefilter is None else reg.prefilter.adjoint(padded)


def hypergradient(atk: VRFTAttack, s: State) -> tuple[np.ndarray, np.ndarray]:
    """(dJ/da_u, dJ/da_y) at state s, by implicit differentiation of the normal equations.

    With w = (Phi'^T Phi')^{-1} dJ/dtheta and r' = t' - Phi' theta':
    dJ/da_u = targets^T (Phi' w),  dJ/da_y = sum_i T_i^T (w_i r' - theta'_i Phi' w).
    """
    w = factor_solve(s.R, atk.grad_theta(s.theta))  # (R'R)^{-1} g, R'R = Phi'^T Phi'
    pw = s.phi @ w
    residual = s.target - s.phi @ s.theta
    g_y = atk.setting.regressor.adjoint(residual[:, None] * w - pw[:, None] * s.theta)
    return targets_adjoint(atk, pw), g_y


def best_input_attack(atk: VRFTAttack, a_y: np.ndarray) -> tuple[np.ndarray, State]:
    """Globally optimal a_u for fixed a_y when J is quadratic in theta and the budget is a plain l2 ball.

    theta' = theta'_0 + S v and a_u = B v with ||a_u|| = ||v||, where Phi' = QR, W = targets^T Q,
    S = R^{-1} (W'W)^{1/2}, B = W (W'W)^{-1/2}; a k-dimensional trust-region subproblem in v.
    """
    if atk.objective == "destabilize" or atk.budget_u.norm != "l2" or atk.budget_u.rho is not None:
        raise ModelError("the exact input step needs a quadratic objective (maxmin/targeted) and a plain l2 "
                         "budget on a_u; use the conditional-gradient step otherwise")
    zero = np.zeros(atk.N)
    s0 = _fit(atk, zero, a_y, atk.t0)
    if atk.delta_u == 0:
        return zero, s0
    reg = atk.setting.regressor
    if reg.prefilter is None:  # targets(a) = a[:n]: W = [Q; 0] has orthonormal columns already
        S = scipy.linalg.lapack.dtrtri(s0.R)[0]  # R^{-1}
        B = None
    else:
        W = targets_adjoint(atk, s0.Q)
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
