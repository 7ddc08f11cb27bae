"""A De Persis–Tesi LQR design robust to poisoned data (issue 46), by the matrix S-lemma (van Waarde, Camlibel &
Mesbahi, "From noisy data to feedback controllers: non-conservative design via a matrix S-lemma", IEEE TAC 2022;
Bisoffi, De Persis & Tesi, "Data-driven control via Petersen's lemma", Automatica 2022).

The set of plants consistent with poisoned data. A noise-free trajectory of x+ = A x + B u, poisoned into
(X0', U0', X1') = (X0 + DX0, U0 + DU, X1 + DX1), satisfies X1' = Z D' + W with Z = [A B], D' = [X0'; U0'] and
W = DX1 - Z [DX0; DU] = [I, -Z] Delta, Delta = [DX1; DX0; DU]. With the learner's column weights w (column_weights,
0 < w_t <= 1, Omega = diag(w); any weights keep what follows true) and S the 0/1 diagonal selecting the poisoned rows
of Delta (Delta = S Delta):
    (X1' - Z D') Omega^2 (X1' - Z D')' = [I, -Z] Delta Omega^2 Delta' [I, -Z]' <= eps^2 [I, -Z] S [I, -Z]'
for every eps >= ||Delta Omega||_2. The linf budgets of the Willems attacks, |DU_ij| <= delta_u and |Dx_ij| <= delta_x
on the poisoned state samples, give ||Delta Omega||_2 <= ||Delta Omega||_F <= eps with
    eps^2 = sum_t w_t^2 (m delta_u^2 + n delta_x^2 ([x_{t+1} poisoned] + [x_t poisoned]))      (poisoning_energy)
(tight for input poisoning: the rank-one pattern DU = delta_u s 1', s in {-1, 1}^m, reaches ||DU Omega||_2 = eps).
So the true Z lies in Sigma = {Z : [I; Z']' N [I; Z'] >= 0} with (consistency_qmi)
    N = [[eps^2 s_1 I - X1w X1w', X1w Dw'], [Dw X1w', eps^2 E - Dw Dw']],  X1w = X1' Omega, Dw = D' Omega,
s_1 = 1 where X1 is poisoned, E = diag(s_0 I_n, s_u I_m). Sigma is bounded iff N22 < 0 (the data excite more than the
poisoning can hide); the learner abstains otherwise.

The design (robust_lqr_controller). Over P, Y = K P and alpha >= 0: min tr(Qx P) subject to
    [[P - I - alpha N11, -alpha N12, 0], [-alpha N21, -alpha N22, [P; Y]], [0, [P; Y]', P]] >= tau I.
By a Schur complement, G = M - alpha N - diag(I, 0) >= 0 with M = [[P, 0], [0, -[I; K] P [I; K]']], and for every Z in
Sigma [I; Z']' G [I; Z'] >= 0 gives P - (A + B K) P (A + B K)' >= I: the gain stabilizes every plant consistent with the
data and the budget, the true one included, and tr(Qx P) bounds the H2 cost of each (the matrix S-lemma makes the
condition lossless where N has a Slater point). The learner returns a gain only after verify_gain (numpy alone)
re-checks G's smallest eigenvalue above a margin over rounding; where the re-check fails (small budgets make alpha
large, and the Schur complement of alpha N loses the solver's accuracy) it re-solves with tau larger by
robust_willems.margin_factor, at most robust_willems.margin_steps solves; else, or where the SDP is infeasible, it
abstains.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cvxpy as cp
import numpy as np
from numpy.typing import ArrayLike

from bilevel.ddc.depersis_tesi import StateData, check_persistency, column_weights, state_data
from bilevel.defaults import param
from bilevel.errors import InvalidData, LowerLevelInfeasible, SolverFailed
from bilevel.lower.quadratic import solve_clarabel

POISONS = ("u", "x", "xu")
"""Which signals the poisoning may touch (the Willems attacks' `poison`): inputs, states, both."""
CERTIFIED, INFEASIBLE, UNBOUNDED, UNVERIFIED = "certified", "abstain-infeasible", "abstain-unbounded", \
    "abstain-unverified"
"""Outcomes: a verified gain; abstentions where the SDP is infeasible, the consistent set is unbounded (N22 not
negative definite), or the solver's answer failed verify_gain (or the solver failed)."""


def poisoning_energy(data: StateData, weights: np.ndarray, delta_u: float, delta_x: float = 0.0,
                     poison: str = "u", poison_x0: bool = False) -> float:
    """eps >= ||Delta Omega||_2 under the linf budgets (module docstring): sqrt(sum_t w_t^2 (m delta_u^2 +
    n delta_x^2 (number of poisoned samples among x_t, x_{t+1}))); x_0 is poisoned only with poison_x0."""
    if poison not in POISONS:
        raise InvalidData(f"poison={poison!r} is not one of {', '.join(POISONS)}")
    (n, horizon), m = data.x0.shape, data.u0.shape[0]
    per_sample = np.full(horizon, m * delta_u ** 2 if "u" in poison else 0.0)
    if "x" in poison:
        poisoned_x0 = np.ones(horizon)
        poisoned_x0[0] = float(poison_x0)
        per_sample = per_sample + n * delta_x ** 2 * (1.0 + poisoned_x0)
    return float(np.sqrt(np.sum(weights ** 2 * per_sample)))


def consistency_qmi(data: StateData, weights: np.ndarray, eps: float, poison: str = "u") -> np.ndarray:
    """N of Sigma = {[A B] : [I; Z']' N [I; Z'] >= 0}, the plants consistent with the weighted data and a poisoning
    with ||Delta Omega||_2 <= eps (module docstring); (2n + m) x (2n + m)."""
    n, m = data.x0.shape[0], data.u0.shape[0]
    x1w = data.x1 * weights
    dw = np.vstack([data.x0, data.u0]) * weights
    selector = np.concatenate([np.full(n, float("x" in poison)), np.full(m, float("u" in poison))])
    top = np.hstack([eps ** 2 * float("x" in poison) * np.eye(n) - x1w @ x1w.T, x1w @ dw.T])
    bottom = np.hstack([dw @ x1w.T, eps ** 2 * np.diag(selector) - dw @ dw.T])
    n_mat = np.vstack([top, bottom])
    return (n_mat + n_mat.T) / 2


def lifted_lyapunov(k: np.ndarray, p: np.ndarray, alpha: float, n_mat: np.ndarray) -> np.ndarray:
    """G = [[P, 0], [0, -[I; K] P [I; K]']] - alpha N - diag(I, 0): G >= 0 proves P - (A + BK) P (A + BK)' >= I for
    every [A B] in Sigma (module docstring)."""
    n = p.shape[0]
    ik = np.vstack([np.eye(n), k])
    g = -alpha * n_mat
    g[:n, :n] += p - np.eye(n)
    g[n:, n:] -= ik @ p @ ik.T
    return (g + g.T) / 2


def verify_gain(k: np.ndarray, p: np.ndarray, alpha: float, n_mat: np.ndarray,
                rel_margin: float | None = None) -> tuple[bool, float, float]:
    """Numpy's re-check of a robust gain (no SDP solver): (passed, smallest eigenvalue of G and of P, the margin). It
    passes where both are at least the margin, rel_margin (defaults["robust_willems.check_margin"]) times the scale
    ||P|| (1 + ||K||)^2 + alpha ||N|| + 1 of G's terms: far above the rounding of forming G and of eigvalsh, which are
    ~1e-16 times that scale; G's margin also covers any error below margin / alpha in N itself."""
    rel_margin = param("robust_willems.check_margin", rel_margin)
    if not (alpha >= 0 and np.all(np.isfinite(k)) and np.all(np.isfinite(p))):
        return False, float("nan"), float("nan")
    scale = np.linalg.norm(p, 2) * (1 + np.linalg.norm(k, 2)) ** 2 + alpha * np.linalg.norm(n_mat, 2) + 1.0
    margin = rel_margin * scale
    low = min(float(np.linalg.eigvalsh(lifted_lyapunov(k, p, alpha, n_mat))[0]),
              float(np.linalg.eigvalsh((p + p.T) / 2)[0]))
    return low >= margin, low, margin


@dataclass(frozen=True)
class RobustController:
    """The robust learner's answer: status (CERTIFIED or an abstention), and where certified the gain K (u = K x), the
    Lyapunov matrix P, the multiplier alpha, the SDP value tr(Qx P) (a bound on the H2 cost of every consistent
    plant) and verify_gain's smallest eigenvalue and margin; eps and N describe the consistent set."""

    status: str
    eps: float
    n_mat: np.ndarray
    k: np.ndarray | None = None
    p: np.ndarray | None = None
    alpha: float | None = None
    value: float = float("inf")
    check: float = float("nan")
    margin: float = float("nan")

    @property
    def certified(self) -> bool:
        return self.status == CERTIFIED


def robust_lqr_controller(x: ArrayLike, u: ArrayLike, delta_u: float, delta_x: float = 0.0, *, poison: str = "u",
                          poison_x0: bool = False, qx: ArrayLike | None = None, balance: bool = True,
                          solver_options: Mapping[str, Any] | None = None) -> RobustController:
    """The robust design (module docstring) on data (X, U) at the design budgets delta_u, delta_x (linf, the Willems
    attacks' budgets on the signals `poison`): a gain verified to stabilize every plant consistent with the data and
    the budget, or an abstention. balance: the column weights of column_weights (ones otherwise)."""
    data = state_data(x, u)
    check_persistency(data)
    n, m = data.x0.shape[0], data.u0.shape[0]
    qx = np.eye(n) if qx is None else np.asarray(qx, dtype=float)
    if qx.shape != (n, n):
        raise InvalidData(f"Qx must be {n} x {n}; got {qx.shape}")
    if min(delta_u, delta_x) < 0 or not np.isfinite(delta_u + delta_x):
        raise InvalidData(f"the design budgets must be finite and >= 0; got delta_u={delta_u}, delta_x={delta_x}")
    w = column_weights(data, balance)
    eps = poisoning_energy(data, w, delta_u, delta_x, poison, poison_x0)
    n_mat = consistency_qmi(data, w, eps, poison)
    if np.linalg.eigvalsh(n_mat[n:, n:])[-1] >= 0:
        return RobustController(UNBOUNDED, eps, n_mat)
    p = cp.Variable((n, n), symmetric=True)
    y = cp.Variable((m, n))
    alpha = cp.Variable(nonneg=True)
    py = cp.vstack([p, y])
    lmi = cp.bmat([[p - np.eye(n) - alpha * n_mat[:n, :n], -alpha * n_mat[:n, n:], np.zeros((n, n))],
                   [-alpha * n_mat[n:, :n], -alpha * n_mat[n:, n:], py],
                   [np.zeros((n, n)), py.T, p]])
    tau = cp.Parameter(nonneg=True)
    problem = cp.Problem(cp.Minimize(cp.trace(qx @ p)), [(lmi + lmi.T) / 2 >> tau * np.eye(3 * n + m)])
    answer = RobustController(INFEASIBLE, eps, n_mat)
    for step in range(param("robust_willems.margin_steps")):
        tau.value = param("robust_willems.lmi_margin") * param("robust_willems.margin_factor") ** step
        try:
            solve_clarabel(problem, "the robust De Persis-Tesi SDP", options=dict(solver_options or {}))
        except LowerLevelInfeasible:
            return answer if step == 0 else dataclasses.replace(answer, status=UNVERIFIED)
        except SolverFailed:
            return RobustController(UNVERIFIED, eps, n_mat)
        p_val = (p.value + p.value.T) / 2
        k = np.linalg.solve(p_val, y.value.T).T
        passed, low, margin = verify_gain(k, p_val, float(alpha.value), n_mat)
        answer = RobustController(CERTIFIED if passed else UNVERIFIED, eps, n_mat, k, p_val, float(alpha.value),
                                  float(problem.value), low, margin)
        if passed:
            break
    return answer
