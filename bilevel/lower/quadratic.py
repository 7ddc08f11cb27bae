"""LP and convex QP lower levels: numeric coefficients at a fixed x, solved independently by cvxpy + Clarabel."""

from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import casadi as ca
import clarabel
import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from ..defaults import param
from ..errors import LowerLevelInfeasible, LowerLevelUnbounded, SolverFailed
from ..vech import smat, svec
from ..parameters import CompiledFunction
from .base import ExpressionLower, LowerSolution
from .convexity import require_psd
from .polish import Lmi, polish


def clarabel_tolerances() -> dict[str, float]:
    """Clarabel's tolerances in every lower-level solve, defaults["lower.clarabel_tol"] and
    defaults["lower.clarabel_ktratio"]: tighter than its own (1e-8), since certificates compare against these
    solutions. The one source of Clarabel's settings (clarabel_settings for its own interface)."""
    tol = param("lower.clarabel_tol")
    return {"tol_gap_abs": tol, "tol_gap_rel": tol, "tol_feas": tol, "tol_ktratio": param("lower.clarabel_ktratio")}


def clarabel_settings() -> clarabel.DefaultSettings:
    """Settings of a direct Clarabel solve (its own interface): quiet, at clarabel_tolerances()."""
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    for name, value in clarabel_tolerances().items():
        setattr(settings, name, value)
    return settings


@dataclass(frozen=True)
class QPData:
    """f = 1/2 y'Py + q'y + r, g = A y + b <= 0, h = E y + e = 0 at a fixed upper point."""

    P: np.ndarray
    q: np.ndarray
    r: float
    A: np.ndarray
    b: np.ndarray
    E: np.ndarray
    e: np.ndarray

    def objective(self, y: np.ndarray) -> float:
        """f(y) = 1/2 y'Py + q'y + r."""
        return float(0.5 * y @ self.P @ y + self.q @ y + self.r)


def singular_hessian(data: QPData) -> str | None:
    """Why a QP's solution may not be unique (its Hessian is singular, not strictly convex), or None where the
    Hessian is positive definite (smallest eigenvalue above defaults["lower.unique_rtol"] * max(1, max |P|))."""
    P = data.P
    if np.linalg.eigvalsh(0.5 * (P + P.T))[0] > param("lower.unique_rtol") * max(1.0, float(np.abs(P).max())):
        return None
    return "a QP lower level whose Hessian is singular at the start (not strictly convex)"


def point_context(x: np.ndarray) -> str:
    """'at x = [...]' for error messages, summarized to its first and last three entries (formatting x in full costs
    about 5 us an entry at every solve)."""
    return f"at x = {np.array2string(np.asarray(x), precision=4, threshold=10, edgeitems=3)}"


def solve_quietly(problem: cp.Problem, **options: Any) -> None:
    """problem.solve(**options) without cvxpy's "Solution may be inaccurate" warning: callers read the status, accept
    OPTIMAL_INACCURATE and carry it into their result, whose residuals are checked."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Solution may be inaccurate")
        problem.solve(**options)


def solve_clarabel(problem: cp.Problem, what: str, infeasible_hint: str = "",
                   options: dict[str, Any] | None = None) -> None:
    """Solve a cvxpy problem with Clarabel at clarabel_tolerances() (overridable); map every non-optimal status
    to a named error: LowerLevelInfeasible, LowerLevelUnbounded or SolverFailed."""
    try:
        solve_quietly(problem, solver=cp.CLARABEL, **{**clarabel_tolerances(), **(options or {})})
    except cp.error.SolverError as exc:
        raise SolverFailed(f"Clarabel failed on {what} ({exc}); rescale the data or loosen tolerances") from exc
    if problem.status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE):
        raise LowerLevelInfeasible(f"{what} is infeasible (status {problem.status}){infeasible_hint}")
    if problem.status in (cp.UNBOUNDED, cp.UNBOUNDED_INACCURATE):
        raise LowerLevelUnbounded(f"{what} is unbounded below (status {problem.status})")
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
        raise SolverFailed(f"Clarabel returned status {problem.status!r} on {what}, no usable point")


def solve_qp_clarabel(d: QPData, context: str, lmis: tuple[Lmi, ...] = (),
                      psd_verified: bool = False) -> LowerSolution:
    """The QP's solution (clarabel_direct without LMIs, else clarabel_solution) polished onto its optimal face where
    that lowers its KKT residual, else unchanged (see polish.py)."""
    sol = clarabel_solution(d, context, lmis, psd_verified) if lmis else clarabel_direct(d, context, psd_verified)
    return polish(d, lmis, sol)


def _convex_hessian(d: QPData, context: str, psd_verified: bool) -> np.ndarray | None:
    """P symmetrized, verified PSD first (NonConvexLowerLevel naming its eigenvalue otherwise) unless psd_verified
    says the caller checked this matrix already; None where the objective is linear."""
    if not np.any(d.P):
        return None
    return 0.5 * (d.P + d.P.T) if psd_verified else require_psd(d.P, "the lower objective", context)


def clarabel_direct(d: QPData, context: str, psd_verified: bool = False, lmis: tuple[Lmi, ...] = ()) -> LowerSolution:
    """A QP/LP, with LMIs M0 + sum_j y_j M_j >= 0 if given, handed to Clarabel's own interface (no cvxpy
    canonicalization per solve: the methods solve at every upper point): A y + s = -b, s >= 0, E y + s = -e, s = 0
    and svec(M(y)) = s in the PSD triangle cone; its duals are lam, mu and Z_k = smat(z_k) directly."""
    n = d.q.size
    P = _convex_hessian(d, context, psd_verified)
    P = sp.csc_matrix((n, n)) if P is None else sp.triu(sp.csc_matrix(P), format="csc")
    rows, rhs = [d.E, d.A], [-d.e, -d.b]
    cones = ([clarabel.ZeroConeT(d.e.size)] if d.e.size else []) + \
        ([clarabel.NonnegativeConeT(d.b.size)] if d.b.size else [])
    for m0, jac in lmis:  # Clarabel reads the upper triangle column by column: svec (row by row) of the transpose
        k = m0.shape[0]
        rows.append(-svec(jac.T.reshape(-1, k, k)).T)  # row j of jac.T is vec(M_j), so its C-order reshape is M_j'
        rhs.append(svec(np.asarray(m0).T))
        cones.append(clarabel.PSDTriangleConeT(k))
    A = sp.csc_matrix(np.vstack(rows)) if sum(r.shape[0] for r in rows) else sp.csc_matrix((0, n))
    out = clarabel.DefaultSolver(P, d.q, A, np.concatenate(rhs), cones, clarabel_settings()).solve()
    status = str(out.status)
    where = f"the lower level {context}"
    if status in ("PrimalInfeasible", "AlmostPrimalInfeasible"):
        raise LowerLevelInfeasible(f"{where} is infeasible (Clarabel: {status})")
    if status in ("DualInfeasible", "AlmostDualInfeasible"):
        raise LowerLevelUnbounded(f"{where} is unbounded below (Clarabel: {status})")
    if status not in ("Solved", "AlmostSolved"):
        raise SolverFailed(f"Clarabel returned status {status!r} on {where}, no usable point; rescale the data")
    y, z = np.asarray(out.x, dtype=float), np.asarray(out.z, dtype=float)
    zs, start = [], d.e.size + d.b.size
    for m0, _ in lmis:
        k = m0.shape[0]
        size = k * (k + 1) // 2
        zs.append(smat(z[start: start + size], k))
        start += size
    return LowerSolution(y, d.objective(y), np.maximum(z[d.e.size:d.e.size + d.b.size], 0.0), z[:d.e.size], zs,
                         "optimal" if status == "Solved" else "optimal_inaccurate", "clarabel")


def clarabel_solution(d: QPData, context: str, lmis: tuple[Lmi, ...] = (),
                      psd_verified: bool = False) -> LowerSolution:
    """Solve a convex QP/LP (with LMIs M0 + sum_j y_j M_j >= 0 given as (M0, d vec(M)/dy)) by cvxpy + Clarabel.

    P is verified PSD first (NonConvexLowerLevel naming its eigenvalue otherwise) unless psd_verified says the
    caller checked this same fixed matrix already (lower_qp's data, checked at declaration). Raises on
    infeasible/unbounded and fails loudly on any other non-optimal status. A problem with LMIs whose shapes and P
    recur is stated once with its data as cvxpy Parameters (_statement): cvxpy canonicalizes it once.
    """
    P = _convex_hessian(d, context, psd_verified)
    data = [d.q, d.A, d.b, d.E, d.e, *(part for lmi in lmis for part in lmi)]
    stated = _statement(d.q.size, P, data, len(lmis))
    if stated is None:
        prob, y, cons = _state(d.q.size, P, data, len(lmis))
        solve_clarabel(prob, f"the lower level {context}", options=DROP_ZEROS)
        return _solution(d, y, cons, prob.status)
    with stated[3]:
        for slot, value in zip(stated[2], data):
            if isinstance(slot, cp.Parameter):
                slot.value = value
        solve_clarabel(stated[0], f"the lower level {context}", options=DROP_ZEROS)
        return _solution(d, stated[1], stated[0].constraints, stated[0].status)


DROP_ZEROS: dict[str, Any] = {"input_sparse_dropzeros": True}
"""clarabel_solution's Clarabel option: cvxpy stores every entry of a Parameter (and of a dense constant) in the
constraint matrix, zeros included; Clarabel drops them and factors its KKT system at the data's own sparsity (the
Willems learner's SDP at N = 50: 8,400 stored entries, 2,956 nonzero; the solve takes about half the time). With the
zeros, its answer on the lqr-r learner's two-LMI SDP was suboptimal or missing in 15 of 28 design tasks (certificates
failing on lower_gap), and cvxpy updated the previous solve's solver, so a re-solve depended on what the process had
solved before; without them, neither."""


def _state(n: int, P: np.ndarray | None, data: list, n_lmis: int) -> tuple[cp.Problem, cp.Variable, list]:
    """min q'y + 1/2 y'Py s.t. A y + b <= 0, E y + e = 0, sym(M0_k + mat(J_k y)) >= 0 over data = [q, A, b, E, e,
    M0_1, J_1, ...] (arrays, or cvxpy Parameters of their shapes); rows without entries are left out."""
    q, A, b, E, e = data[:5]
    y = cp.Variable(n)
    objective = q @ y
    if P is not None:  # psd_wrap only of a matrix verified PSD (clipped at rounding level), never on trust
        objective = objective + 0.5 * cp.quad_form(y, cp.psd_wrap(P))
    cons = []
    if b.shape[0]:
        cons.append(A @ y + b <= 0)
    if e.shape[0]:
        cons.append(E @ y + e == 0)
    for k in range(n_lmis):
        m0, jac = data[5 + 2 * k: 7 + 2 * k]
        size = m0.shape[0]
        expr = m0 + cp.reshape(jac @ y, (size, size), order="F")
        cons.append(0.5 * (expr + expr.T) >> 0)
    return cp.Problem(cp.Minimize(objective), cons), y, cons


def _solution(d: QPData, y: cp.Variable, cons: list, status: str) -> LowerSolution:
    """The solved statement's y and multipliers (lam of A y + b <= 0, mu of E y + e = 0, Z_k of the LMIs)."""
    n_lin = int(d.b.size > 0) + int(d.e.size > 0)
    lam = np.maximum(np.asarray(cons[0].dual_value).ravel(), 0.0) if d.b.size else np.zeros(0)
    mu = np.asarray(cons[n_lin - 1].dual_value).ravel() if d.e.size else np.zeros(0)
    zs = [np.asarray(c.dual_value) for c in cons[n_lin:]]
    yv = np.asarray(y.value).ravel()
    return LowerSolution(yv, d.objective(yv), lam, mu, zs, status, "cvxpy+clarabel")


STATED_KEPT = 4
"""Statements with Parameters (_statement) a process keeps, the most recently used."""
STATED_MAX_ENTRIES = 200_000
"""Larger data are stated plainly: cvxpy's canonicalization with Parameters grows with their entries."""
_STATED: dict[tuple, Any] = {}
_STATED_LOCK = threading.Lock()


def _statement(n: int, P: np.ndarray | None, data: list, n_lmis: int) -> tuple | None:
    """(problem, y, Parameters of data, lock) stating a problem with LMIs of these shapes and this P with its data as
    Parameters (canonicalized by cvxpy once, then a parameter update per solve: the certificate's re-solves of one
    learner on many data sets), kept from the second time the shapes and P recur; None for the first time, no LMIs
    or large data (then the problem is stated with its numbers, which is cheaper once)."""
    if not n_lmis or sum(np.size(v) for v in data) > STATED_MAX_ENTRIES:
        return None
    key = (n, tuple(np.shape(v) for v in data), None if P is None else hash(P.tobytes()))
    with _STATED_LOCK:
        kept = _STATED.pop(key, None)
        if kept is None or kept == "seen":
            if kept == "seen":
                params = [cp.Parameter(np.shape(v)) if np.size(v) else v for v in data]  # no empty Parameters
                prob, y, _ = _state(n, P, params, n_lmis)
                kept = (prob, y, params, threading.Lock())
            else:
                kept = "seen"
        _STATED[key] = kept
        while len(_STATED) > STATED_KEPT:
            del _STATED[next(iter(_STATED))]
    return None if kept == "seen" else kept


@dataclass
class QuadraticLower(ExpressionLower):
    """Convex quadratic objective and affine constraints in y (an LP when the Hessian vanishes)."""

    kind = "qp"

    @cached_property
    def _coeffs(self) -> CompiledFunction:
        """x -> the QP coefficients, built on first use: the symbolic form of a matrix QP (MatrixLower.symbolic, for
        the KKT reduction) never solves itself, and the constraints' Jacobians cost seconds at 1,000 x 100."""
        zero = ca.DM.zeros(self.n_y)
        grad = ca.gradient(self.f, self.y)
        outs = [self.hess_f, grad, self.f, ca.jacobian(self.g, self.y), self.g,
                ca.jacobian(self.h, self.y), self.h]
        outs = [ca.substitute(o, self.y, zero) for o in outs]
        return self.params.function("qp_coeffs", [self.x], outs)

    def data(self, x: np.ndarray) -> QPData:
        """The QP coefficients at upper point x."""
        P, q, r, A, b, E, e = (np.asarray(v) for v in self._coeffs(self.check_point(x)))
        return QPData(np.atleast_2d(P).reshape(self.n_y, self.n_y), q.ravel(), float(np.asarray(r).ravel()[0]),
                      A.reshape(-1, self.n_y), b.ravel(), E.reshape(-1, self.n_y), e.ravel())

    @cached_property
    def constant_hessian(self) -> bool:
        """Whether the Hessian does not depend on x: the declaration's convexity check (re-run after set_value) then
        covers every x, and the solves skip the per-point PSD test."""
        return not ca.depends_on(self.hess_f, self.x)

    def nonunique_at(self, x: np.ndarray) -> str | None:
        return singular_hessian(self.data(x)) if self.kind == "qp" else super().nonunique_at(x)

    def solve(self, x: np.ndarray) -> LowerSolution:
        """Solve at x with Clarabel (independent of the reduction)."""
        return solve_qp_clarabel(self.data(x), point_context(x),
                                 psd_verified=self.constant_hessian and self.convexity_probe is not None)

    def reference_solve(self, x: np.ndarray) -> LowerSolution:
        """The certificate's re-solve: the QP stated through cvxpy (its own canonicalization) and solved by Clarabel."""
        data = self.data(x)
        return polish(data, (), clarabel_solution(data, "(independent re-solve)"))


@dataclass
class LinearLower(QuadraticLower):
    """Linear objective and affine constraints in y."""

    kind = "lp"
