"""De Persis & Tesi (IEEE TAC 2020, "Formulas for data-driven control") state-feedback learners, via cvxpy + Clarabel.

From one trajectory, U0 = [u_0..u_{T-1}], X0 = [x_0..x_{T-1}], X1 = [x_1..x_T]. With
rank [U0; X0] = n + m every closed loop is A + B K = X1 Q (X0 Q)^{-1}, K = U0 Q (X0 Q)^{-1}
(u = K x). Theorem 3 finds a stabilizing Q; Theorem 4 solves the LQR / H2 problem.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cvxpy as cp
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike

from bilevel.errors import InvalidData, ModelError, NotPersistentlyExciting, SolverFailed
from bilevel.lower.quadratic import solve_clarabel, solve_quietly

# Clarabel's defaults (1e-8) leave ~1e-4 error in K (the SDP value is flat around the optimal gain), so the
# learner uses (through solve_clarabel) the same tightened tolerances as the lower-level certificates.

SOLVERS = ("clarabel", "scs")
"""SDP solvers a learner can use; the solver decides which of the non-unique optimal Q the learner returns."""
SCS_TOLERANCES = {"eps_abs": 1e-7, "eps_rel": 1e-7, "max_iters": 100_000}

_INFEASIBLE_HINT = (": these data admit no certified controller; check that the data come from a stabilizable "
                    "system and are noise-free or more informative")


@dataclass(frozen=True)
class StateData:
    """Data matrices of one trajectory: U0 (m x T), X0 (n x T), X1 (n x T)."""

    u0: np.ndarray
    x0: np.ndarray
    x1: np.ndarray

    @property
    def horizon(self) -> int:
        """Number of samples T."""
        return self.u0.shape[1]


def state_data(x: ArrayLike, u: ArrayLike) -> StateData:
    """Split states X (n x (T+1)) and inputs U (m x T) into (U0, X0, X1), checking shapes and finiteness."""
    x, u = np.asarray(x, dtype=float), np.atleast_2d(np.asarray(u, dtype=float))
    if x.ndim != 2 or x.shape[1] != u.shape[1] + 1:
        raise InvalidData(
            f"X must be n x (T+1) and U m x T; got X {x.shape} and U {u.shape} "
            "(X holds one more sample, x_T, than U)"
        )
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(u))):
        raise InvalidData("state or input data contain NaN/inf; remove or interpolate them")
    return StateData(u0=u, x0=x[:, :-1], x1=x[:, 1:])


def check_persistency(data: StateData) -> int:
    """rank [U0; X0]; raises NotPersistentlyExciting unless it equals n + m."""
    n, m = data.x0.shape[0], data.u0.shape[0]
    rank = int(np.linalg.matrix_rank(np.vstack([data.u0, data.x0])))
    if rank < n + m:
        raise NotPersistentlyExciting(
            f"rank [U0; X0] = {rank} but n + m = {n + m} is needed (T = {data.horizon} samples); "
            f"use a persistently exciting input of order n + 1 and at least T >= {n + m} samples "
            "(in practice T >= (m + 1) n + m)"
        )
    return rank


def min_norm_q(seen: np.ndarray, q: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
    """Q projected onto the row space of the data rows `seen` (D): the minimum-norm Q with the same D Q.
    Singular values of D below rtol * the largest count as zero (clean [X0; X1] has rank n + m)."""
    _, sing, vt = np.linalg.svd(seen, full_matrices=False)
    basis = vt[sing > rtol * sing[0]]
    return basis.T @ (basis @ q)


@dataclass(frozen=True)
class DPTController:
    """A data-driven state-feedback gain u = K x with its certificate Q and the SDP outcome."""

    k: np.ndarray
    q: np.ndarray
    value: float
    status: str
    closed_loop: np.ndarray
    spectral_radius: float


def _controller(data: StateData, q: np.ndarray, value: float, status: str, what: str) -> DPTController:
    s = data.x0 @ q
    s = (s + s.T) / 2
    k = scipy.linalg.solve(s, (data.u0 @ q).T, assume_a="sym").T
    acl = scipy.linalg.solve(s, (data.x1 @ q).T, assume_a="sym").T
    rho = float(np.max(np.abs(np.linalg.eigvals(acl))))
    if rho >= 1:
        raise SolverFailed(
            f"{what} returned Q (status {status}) whose data-based closed loop X1 Q (X0 Q)^-1 has "
            f"spectral radius {rho:.6g} >= 1; the SDP solution is not a valid certificate"
        )
    return DPTController(k=k, q=q, value=value, status=status, closed_loop=acl, spectral_radius=rho)


def _solve(problem: cp.Problem, solver: str, what: str, options: dict[str, Any]) -> None:
    """Solve with Clarabel (solve_clarabel's tolerances and status map) or SCS (tight tolerances, same map)."""
    if solver == "clarabel":
        solve_clarabel(problem, what, _INFEASIBLE_HINT, options)
        return
    if solver != "scs":
        raise ModelError(f"solver={solver!r} is not one of {', '.join(SOLVERS)}")
    try:
        solve_quietly(problem, solver=cp.SCS, **{**SCS_TOLERANCES, **options})
    except cp.error.SolverError as exc:
        raise SolverFailed(f"SCS failed on {what} ({exc}); rescale the data or use solver='clarabel'") from exc
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or _missing_values(problem):
        raise SolverFailed(f"SCS returned status {problem.status!r} on {what}, no usable point"
                           f"{_INFEASIBLE_HINT if 'infeasible' in str(problem.status) else ''}")


def _missing_values(problem: cp.Problem) -> bool:
    """Whether a solved cvxpy problem left any variable without a value."""
    return any(v.value is None for v in problem.variables())


def column_weights(data: StateData, balance: bool) -> np.ndarray:
    """w_t = 1 / max(1, ||(x_t, x_{t+1})||) (ones unless balance). The learner solves for Q~ = diag(w)^-1 Q:
    the same SDP in a variable whose data columns are balanced. States of the unstable batch reactor grow like
    1.22^t (to ~2e4 at T = 50); unbalanced, SCS ends 'optimal_inaccurate' there. States only: input poisoning
    leaves the weights, and so the appendix learner's Q, unchanged."""
    if not balance:
        return np.ones(data.horizon)
    return 1.0 / np.maximum(1.0, np.linalg.norm(np.vstack([data.x0, data.x1]), axis=0))


def _symmetric(block: cp.Expression) -> cp.Expression:
    return (block + block.T) / 2


def stabilizing_controller(
    x: ArrayLike, u: ArrayLike, *, solver: str = "clarabel", balance: bool = True,
    solver_options: Mapping[str, Any] | None = None
) -> DPTController:
    """Theorem 3: Q with [[X0 Q, X1 Q], [Q^T X1^T, X0 Q]] >= I, min trace(X0 Q); K = U0 Q (X0 Q)^-1.
    `solver` ("clarabel" or "scs") and `balance` (column_weights) decide which optimal Q the learner returns."""
    data = state_data(x, u)
    check_persistency(data)
    n, horizon = data.x0.shape
    w = column_weights(data, balance)
    x0, x1 = data.x0 * w, data.x1 * w
    q = cp.Variable((horizon, n))
    s = cp.Variable((n, n), symmetric=True)
    lmi = cp.bmat([[s, x1 @ q], [(x1 @ q).T, s]])
    problem = cp.Problem(
        cp.Minimize(cp.trace(s)),
        [x0 @ q == s, _symmetric(lmi) >> np.eye(2 * n)],
    )
    _solve(problem, solver, "the De Persis-Tesi stabilization LMI", dict(solver_options or {}))
    return _controller(data, w[:, None] * q.value, float(problem.value), problem.status,
                       "De Persis-Tesi stabilization LMI")


def lqr_controller(
    x: ArrayLike,
    u: ArrayLike,
    qx: ArrayLike | None = None,
    r: ArrayLike | None = None,
    *,
    input_cost: bool = True,
    solver: str = "clarabel",
    balance: bool = True,
    solver_options: Mapping[str, Any] | None = None,
) -> DPTController:
    """Theorem 4: min trace(Qx X0 Q) + trace(X) s.t. its two LMIs; input_cost=False drops X (paper appendix).
    `solver` ("clarabel" or "scs") and `balance` (column_weights) decide which optimal Q the learner returns."""
    data = state_data(x, u)
    check_persistency(data)
    n, horizon = data.x0.shape
    m = data.u0.shape[0]
    qx = np.eye(n) if qx is None else np.asarray(qx, dtype=float)
    r = np.eye(m) if r is None else np.asarray(r, dtype=float)
    if qx.shape != (n, n) or r.shape != (m, m):
        raise InvalidData(f"Qx must be {n} x {n} and R {m} x {m}; got {qx.shape} and {r.shape}")
    w = column_weights(data, balance)
    x0, x1 = data.x0 * w, data.x1 * w
    q = cp.Variable((horizon, n))
    s = cp.Variable((n, n), symmetric=True)
    gramian_lmi = cp.bmat([[s - np.eye(n), x1 @ q], [(x1 @ q).T, s]])
    constraints = [x0 @ q == s, _symmetric(gramian_lmi) >> 0]
    objective = cp.trace(qx @ s)
    if input_cost:
        big_x = cp.Variable((m, m), symmetric=True)
        weighted = scipy.linalg.sqrtm(r).real @ (data.u0 * w) @ q
        constraints.append(_symmetric(cp.bmat([[big_x, weighted], [weighted.T, s]])) >> 0)
        objective = objective + cp.trace(big_x)
    problem = cp.Problem(cp.Minimize(objective), constraints)
    _solve(problem, solver, "the De Persis-Tesi LQR SDP", dict(solver_options or {}))
    return _controller(data, w[:, None] * q.value, float(problem.value), problem.status, "De Persis-Tesi LQR SDP")
