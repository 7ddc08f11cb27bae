"""A LinearMPCC with a linear objective and derived big-M bounds as a MILP for HiGHS (scipy.optimize.milp).

One binary z_i per pair (Fortuny-Amat & McCarl 1981, J. Oper. Res. Soc. 32:783-792): G_i <= M_G,i (1 - z_i) and
H_i <= M_H,i z_i. HiGHS's solution is then made exact by re-solving its branch (every pair fixed to the side z
selects), and HiGHS's dual bound is the proven lower bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp

from .bb import SearchOutcome
from .bigm import BigM
from .nodes import G_SIDE, H_SIDE, Relaxation

MILP_ENDED = {0: "proven", 1: "time_or_node_limit", 2: "infeasible", 3: "unbounded"}
"""scipy.optimize.milp status -> how the search ended (anything else: "failed")."""


@dataclass(frozen=True)
class MILPForm:
    """c'[w; z] with rows lb <= A [w; z] <= ub, bounds, and integrality (1 on z)."""

    c: np.ndarray
    A: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    bounds: Bounds
    integrality: np.ndarray


def milp_form(relax: Relaxation, big_m: BigM) -> MILPForm:
    """The big-M MILP of relax.form (which must be linear, with every bound finite)."""
    f = relax.form
    m, n = f.n_pairs, f.n
    z_lo, z_hi = np.zeros(m), np.ones(m)  # sides fixed by derive_big_m: z_i = 1 (G_i = 0) or z_i = 0 (H_i = 0)
    for i, side in big_m.fixed.items():
        if side == G_SIDE:
            z_lo[i] = 1.0
        else:
            z_hi[i] = 0.0
    blocks = [
        (np.hstack([f.A_eq, np.zeros((f.b_eq.size, m))]), f.b_eq, f.b_eq),
        (np.hstack([relax.A_ub, np.zeros((relax.b_ub.size, m))]), np.full(relax.b_ub.size, -np.inf), relax.b_ub),
        (np.hstack([f.G, np.diag(big_m.slack)]), np.full(m, -np.inf), big_m.slack - f.g),   # G <= M_G (1 - z)
        (np.hstack([f.H, -np.diag(big_m.multiplier)]), np.full(m, -np.inf), -f.h),          # H <= M_H z
    ]
    A = np.vstack([b[0] for b in blocks]) if m or f.b_eq.size or relax.b_ub.size else np.zeros((0, n + m))
    return MILPForm(np.concatenate([f.c, np.zeros(m)]), A, np.concatenate([b[1] for b in blocks]),
                    np.concatenate([b[2] for b in blocks]),
                    Bounds(np.concatenate([f.lb, z_lo]), np.concatenate([f.ub, z_hi])),
                    np.concatenate([np.zeros(n), np.ones(m)]))


def solve_milp(relax: Relaxation, big_m: BigM, gap_tol: float, time_limit: float, node_limit: int) -> SearchOutcome:
    """Solve the big-M MILP with HiGHS; polish its point on its branch; bounds in minimization form."""
    f = relax.form
    form = milp_form(relax, big_m)
    res = milp(form.c, constraints=LinearConstraint(form.A, form.lo, form.hi) if form.A.size else None,
               integrality=form.integrality, bounds=form.bounds,
               options={"time_limit": float(time_limit), "node_limit": int(node_limit), "mip_rel_gap": gap_tol * 1e-2,
                        "disp": False})
    nodes = int(getattr(res, "mip_node_count", 0) or 0)
    ended = MILP_ENDED.get(res.status, "failed")
    dual = getattr(res, "mip_dual_bound", None)
    lower = float(dual) + f.c0 if dual is not None and np.isfinite(dual) else -np.inf
    if ended == "infeasible":
        return SearchOutcome(None, np.inf, np.inf, nodes, "infeasible")
    if ended == "unbounded":
        return SearchOutcome(None, -np.inf, -np.inf, nodes, "unbounded")
    if res.x is None:
        return SearchOutcome(None, lower, np.inf, nodes, ended)
    z = np.asarray(res.x)[f.n:]
    exact = relax.solve({i: G_SIDE if z[i] > 0.5 else H_SIDE for i in range(f.n_pairs)})
    if exact.status != "optimal":  # HiGHS's branch does not re-solve exactly: report its point unpolished
        w, upper = np.asarray(res.x)[:f.n], float(res.fun) + f.c0
    else:
        w, upper = exact.w, exact.value
    if ended == "proven":
        lower = min(lower, upper) if np.isfinite(lower) else float(res.fun) + f.c0
    return SearchOutcome(w, min(lower, upper), upper, nodes, ended)
