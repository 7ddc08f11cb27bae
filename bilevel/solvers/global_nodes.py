"""Convex relaxations of a LinearMPCC with some pairs fixed to a side: LPs by HiGHS, QPs by Clarabel.

A node fixes pair i to G_i = 0 or H_i = 0 (its two MPCC branches) and drops complementarity of the free pairs,
keeping G >= 0, H >= 0 and, where big-M bounds are known, the convex hull of the pair on its box,
G_i / M_G,i + H_i / M_H,i <= 1 (valid: one of the two is zero and the other at most its bound).
"""

from __future__ import annotations

from dataclasses import dataclass

import clarabel
import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from .global_form import LinearMPCC

G_SIDE, H_SIDE = 0, 1


@dataclass(frozen=True)
class NodeSolution:
    """status is "optimal", "infeasible", "unbounded" or "failed"; value includes the objective constant."""

    status: str
    value: float
    w: np.ndarray | None


class Relaxation:
    """The node problems of one LinearMPCC (with optional big-M hull cuts), solved by HiGHS or Clarabel."""

    def __init__(self, form: LinearMPCC, m_slack: np.ndarray | None = None, m_mult: np.ndarray | None = None) -> None:
        self.form = form
        rows, rhs = [form.A_in, -form.G, -form.H], [form.b_in, form.g, form.h]
        if m_slack is not None and m_mult is not None:
            hull = np.isfinite(m_slack) & np.isfinite(m_mult) & (m_slack > 0) & (m_mult > 0)
            idx = np.flatnonzero(hull)
            rows.append(form.G[idx] / m_slack[idx, None] + form.H[idx] / m_mult[idx, None])
            rhs.append(1.0 - form.g[idx] / m_slack[idx] - form.h[idx] / m_mult[idx])
        self.A_ub = np.vstack(rows)
        self.b_ub = np.concatenate(rhs)

    def _fixed_rows(self, fixed: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
        f = self.form
        rows = [f.G[i] if side == G_SIDE else f.H[i] for i, side in fixed.items()]
        rhs = [-f.g[i] if side == G_SIDE else -f.h[i] for i, side in fixed.items()]
        A = np.vstack([f.A_eq] + ([np.array(rows)] if rows else []))
        return A, np.concatenate([f.b_eq, np.array(rhs, dtype=float)])

    def solve(self, fixed: dict[int, int]) -> NodeSolution:
        """The relaxation with pairs in `fixed` (index -> G_SIDE or H_SIDE) held on their side."""
        A_eq, b_eq = self._fixed_rows(fixed)
        return self._lp(A_eq, b_eq) if self.form.linear else self._qp(A_eq, b_eq)

    def _lp(self, A_eq: np.ndarray, b_eq: np.ndarray) -> NodeSolution:
        f = self.form
        bounds = np.column_stack([np.where(np.isfinite(f.lb), f.lb, -np.inf), np.where(np.isfinite(f.ub), f.ub, np.inf)])
        res = linprog(f.c, A_ub=self.A_ub if self.b_ub.size else None, b_ub=self.b_ub if self.b_ub.size else None,
                      A_eq=A_eq if b_eq.size else None, b_eq=b_eq if b_eq.size else None, bounds=bounds,
                      method="highs")
        if res.status == 0:
            return NodeSolution("optimal", float(res.fun) + f.c0, np.asarray(res.x))
        return NodeSolution({2: "infeasible", 3: "unbounded"}.get(res.status, "failed"), np.nan, None)

    def _qp(self, A_eq: np.ndarray, b_eq: np.ndarray) -> NodeSolution:
        f = self.form
        eye = np.eye(f.n)
        lo, hi = np.flatnonzero(np.isfinite(f.lb)), np.flatnonzero(np.isfinite(f.ub))
        A = np.vstack([A_eq, self.A_ub, -eye[lo], eye[hi]])
        b = np.concatenate([b_eq, self.b_ub, -f.lb[lo], f.ub[hi]])
        cones = ([clarabel.ZeroConeT(b_eq.size)] if b_eq.size else []) + [clarabel.NonnegativeConeT(b.size - b_eq.size)]
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = 1e-10
        settings.tol_ktratio = 1e-8
        sol = clarabel.DefaultSolver(sp.csc_matrix(np.triu(f.Q)), f.c, sp.csc_matrix(A), b, cones, settings).solve()
        status = str(sol.status)
        if status == "Solved":
            w = np.asarray(sol.x)
            return NodeSolution("optimal", f.objective(w), w)
        if "PrimalInfeasible" in status:
            return NodeSolution("infeasible", np.nan, None)
        if "DualInfeasible" in status:
            return NodeSolution("unbounded", np.nan, None)
        return NodeSolution("failed", np.nan, None)
