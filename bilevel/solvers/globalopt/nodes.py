"""Convex relaxations of a LinearMPCC with some pairs fixed to a side: LPs by HiGHS, QPs by Clarabel.

The LP is one persistent HiGHS model (highspy) whose pair rows change bounds from node to node, so each node
is a warm-started dual simplex (about 5x faster than a fresh scipy.optimize.linprog on 50 pairs).

A node fixes pair i to G_i = 0 or H_i = 0 (its two MPCC branches) and drops complementarity of the free pairs,
keeping G >= 0, H >= 0 and, where big-M bounds are known, the convex hull of the pair on its box,
G_i / M_G,i + H_i / M_H,i <= 1 (valid: one of the two is zero and the other at most its bound).
"""

from __future__ import annotations

from dataclasses import dataclass

import clarabel
import highspy
import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from ...lower.quadratic import clarabel_settings
from .form import LinearMPCC

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
        rows, rhs = [form.A_in], [form.b_in]
        if m_slack is not None and m_mult is not None:
            hull = np.isfinite(m_slack) & np.isfinite(m_mult) & (m_slack > 0) & (m_mult > 0)
            idx = np.flatnonzero(hull)
            rows.append(form.G[idx] / m_slack[idx, None] + form.H[idx] / m_mult[idx, None])
            rhs.append(1.0 - form.g[idx] / m_slack[idx] - form.h[idx] / m_mult[idx])
        self.cuts = (np.vstack(rows), np.concatenate(rhs))
        self.A_ub = np.vstack([self.cuts[0], -form.G, -form.H])
        self.b_ub = np.concatenate([self.cuts[1], form.g, form.h])
        self._highs: highspy._Highs | None = None

    def branch_rows(self, fixed: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(A, b) of the equalities A w = b of a node: A_eq w = b_eq and each fixed pair's side held at zero."""
        f = self.form
        rows = [f.G[i] if side == G_SIDE else f.H[i] for i, side in fixed.items()]
        rhs = [-f.g[i] if side == G_SIDE else -f.h[i] for i, side in fixed.items()]
        A = np.vstack([f.A_eq] + ([np.array(rows)] if rows else []))
        return A, np.concatenate([f.b_eq, np.array(rhs, dtype=float)])

    def solve(self, fixed: dict[int, int]) -> NodeSolution:
        """The relaxation with pairs in `fixed` (index -> G_SIDE or H_SIDE) held on their side."""
        if self.form.linear:
            sol = self._highs_lp(fixed)
            if sol.status != "failed":
                return sol
        A_eq, b_eq = self.branch_rows(fixed)
        return self._lp(A_eq, b_eq) if self.form.linear else self._qp(A_eq, b_eq)

    def _highs_model(self) -> highspy._Highs:
        """min c'w s.t. A_eq w = b_eq, cuts, G w >= -g, H w >= -h, bounds; pair rows come last."""
        f = self.form
        # highspy's core class, silenced first: highspy.Highs() registers callbacks in its constructor, a call that
        # prints HiGHS's banner on stdout before output_flag can be set
        h = highspy._Highs()
        h.setOptionValue("output_flag", False)
        h.setOptionValue("presolve", "off")  # keep the basis between nodes
        inf = highspy.kHighsInf
        h.addVars(f.n, np.where(np.isfinite(f.lb), f.lb, -inf), np.where(np.isfinite(f.ub), f.ub, inf))
        h.changeColsCost(f.n, np.arange(f.n, dtype=np.int32), f.c.astype(float))
        blocks = [(f.A_eq, f.b_eq, f.b_eq), (self.cuts[0], np.full(self.cuts[1].size, -inf), self.cuts[1]),
                  (f.G, -f.g, np.full(f.n_pairs, inf)), (f.H, -f.h, np.full(f.n_pairs, inf))]
        for M, lo, hi in blocks:
            if lo.size:
                M = sp.csr_matrix(M)
                h.addRows(M.shape[0], lo.astype(float), hi.astype(float), M.nnz, M.indptr[:-1].astype(np.int32),
                          M.indices.astype(np.int32), M.data.astype(float))
        first = f.b_eq.size + self.cuts[1].size
        self._pair_rows = np.arange(first, first + 2 * f.n_pairs, dtype=np.int32)
        return h

    def _highs_lp(self, fixed: dict[int, int]) -> NodeSolution:
        """The node LP on the persistent model: pair rows G_i >= 0 (or = 0), H_i >= 0 (or = 0)."""
        sol = self._highs_run(fixed)
        if sol.status == "failed":
            self._highs = None  # rebuild next time; this node falls back to a fresh linprog
        return sol if sol.w is None else NodeSolution(sol.status, sol.value + self.form.c0, sol.w)

    def minimize_linear(self, cost: np.ndarray, fixed: dict[int, int]) -> NodeSolution:
        """min cost'w over the node's polyhedron, whatever the objective (HiGHS; for bounding LPs)."""
        f = self.form
        if self._highs is None:
            self._highs = self._highs_model()
        cols = np.arange(f.n, dtype=np.int32)
        self._highs.changeColsCost(f.n, cols, np.asarray(cost, dtype=float))
        try:
            sol = self._highs_run(fixed)
        finally:
            if self._highs is not None:
                self._highs.changeColsCost(f.n, cols, f.c.astype(float))
        if sol.status == "failed":
            self._highs = None
        return sol

    def _highs_run(self, fixed: dict[int, int]) -> NodeSolution:
        """Set the pair rows' bounds for `fixed`, run HiGHS, map its status (value without the constant c0)."""
        f = self.form
        if self._highs is None:
            self._highs = self._highs_model()
        h, m = self._highs, f.n_pairs
        lo = np.concatenate([-f.g, -f.h])
        hi = np.full(2 * m, highspy.kHighsInf)
        for i, side in fixed.items():
            k = i if side == G_SIDE else m + i
            hi[k] = lo[k]
        if m:
            h.changeRowsBounds(2 * m, self._pair_rows, lo, hi)
        h.run()
        status = h.getModelStatus()
        if status == highspy.HighsModelStatus.kOptimal:
            w = np.asarray(h.getSolution().col_value, dtype=float)
            return NodeSolution("optimal", float(h.getInfo().objective_function_value), w)
        if status == highspy.HighsModelStatus.kInfeasible:
            return NodeSolution("infeasible", np.nan, None)
        if status == highspy.HighsModelStatus.kUnbounded:
            return NodeSolution("unbounded", np.nan, None)
        return NodeSolution("failed", np.nan, None)

    def _lp(self, A_eq: np.ndarray, b_eq: np.ndarray) -> NodeSolution:
        f = self.form
        bounds = np.column_stack([f.lb, f.ub])
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
        sol = clarabel.DefaultSolver(sp.csc_matrix(np.triu(f.Q)), f.c, sp.csc_matrix(A), b, cones,
                                     clarabel_settings()).solve()
        status = str(sol.status)
        if status == "Solved":
            w = np.asarray(sol.x)
            return NodeSolution("optimal", f.objective(w), w)
        if "PrimalInfeasible" in status:
            return NodeSolution("infeasible", np.nan, None)
        if "DualInfeasible" in status:
            return NodeSolution("unbounded", np.nan, None)
        return NodeSolution("failed", np.nan, None)
