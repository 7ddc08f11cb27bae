"""algorithm="scip" of method "global": the KKT reformulation of form.py with a nonconvex leader, solved by
SCIP's spatial branch-and-bound (pyscipopt; Bestuzheva et al. (2023), "Global optimization of mixed-integer
nonlinear programs with SCIP 8", J. Glob. Optim. 87:1-24).

The model: the MPCC variables w in the box derived over the relaxed KKT polyhedron R (global_bigm.derive_bounds),
every linear row, the slack s_i = G_i w + g_i and multiplier m_i = H_i w + h_i of each pair with complementarity
written with a binary (big-M, where both derived bounds are finite) or as an SOS1 constraint (where one is not),
and the upper objective F(w), the nonlinear upper rows and the slacks nonlinear in x translated from CasADi to SCIP
expressions. SCIP's point is then projected on the linear branch it selects (every pair on one side, an LP), so
complementarity is exact at the returned point (up to SCIP's tolerance on a slack nonlinear in x), and F is
evaluated there; SCIP's dual bound is the proven lower bound.
"""

from __future__ import annotations

import importlib.util
import operator
import time
from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np
from scipy.optimize import linprog

from ...defaults import param
from ...errors import ModelError
from .bb import SearchOutcome, sides_of
from .bigm import BigM
from .form import Leader
from .nodes import G_SIDE, H_SIDE, Relaxation


INSTALL = "pip install pyscipopt (or pip install 'bilevel[global]')"

SCIP_NO_TIME_LIMIT = 1e20
"""SCIP's largest time limit (seconds), its 'no limit': a longer time_limit is given to SCIP as this."""
SCIP_ENDED = {"optimal": "proven", "gaplimit": "proven", "timelimit": "time_limit", "nodelimit": "node_limit",
              "totalnodelimit": "node_limit", "infeasible": "infeasible", "unbounded": "unbounded",
              "inforunbd": "unbounded", "userinterrupt": "interrupted"}
"""SCIP status -> how the search ended (anything else: "failed")."""


def scip_available() -> bool:
    """True when pyscipopt can be imported."""
    return importlib.util.find_spec("pyscipopt") is not None


def require_scip() -> Any:
    """The pyscipopt module, or a ModelError naming the install command."""
    if not scip_available():
        raise ModelError(f"algorithm 'scip' of method 'global' needs pyscipopt, which is not installed: {INSTALL}")
    import pyscipopt
    return pyscipopt


def _operations(scip: Any) -> dict[int, Callable[..., Any]]:
    """CasADi operation code -> the same operation on SCIP expressions (or floats)."""
    return {ca.OP_ASSIGN: lambda a: a, ca.OP_ADD: operator.add, ca.OP_SUB: operator.sub, ca.OP_MUL: operator.mul,
            ca.OP_DIV: operator.truediv, ca.OP_NEG: operator.neg, ca.OP_SQ: lambda a: a * a,
            ca.OP_TWICE: lambda a: 2.0 * a, ca.OP_INV: lambda a: 1.0 / a, ca.OP_EXP: scip.exp, ca.OP_LOG: scip.log,
            ca.OP_SQRT: scip.sqrt, ca.OP_SIN: scip.sin, ca.OP_COS: scip.cos, ca.OP_CONSTPOW: operator.pow,
            ca.OP_POW: operator.pow}


_UNARY = {ca.OP_ASSIGN, ca.OP_NEG, ca.OP_SQ, ca.OP_TWICE, ca.OP_INV, ca.OP_EXP, ca.OP_LOG, ca.OP_SQRT, ca.OP_SIN,
          ca.OP_COS}


def scip_expressions(exprs: ca.SX, w: ca.SX, variables: list[Any]) -> list[Any]:
    """Each entry of exprs (a CasADi SX column in w, no other symbols) as a SCIP expression in `variables`;
    a ModelError names an operation SCIP has no counterpart for."""
    scip = require_scip()
    fun = ca.Function("to_scip", [w], [ca.densify(exprs)])
    ops = _operations(scip)
    work: list[Any] = [None] * fun.sz_w()
    out: list[Any] = [0.0] * int(exprs.numel())
    for k in range(fun.n_instructions()):
        op, args, res = fun.instruction_id(k), fun.instruction_input(k), fun.instruction_output(k)
        if op == ca.OP_CONST:
            work[res[0]] = float(fun.instruction_constant(k))
        elif op == ca.OP_INPUT:
            work[res[0]] = variables[args[1]]
        elif op == ca.OP_OUTPUT:
            out[res[1]] = work[args[0]]
        elif op in (ca.OP_POW, ca.OP_CONSTPOW) and not isinstance(work[args[1]], float):
            raise ModelError("algorithm 'scip' of method 'global' takes powers with constant exponents only (an "
                             "expression a**b with b depending on the variables is not supported)")
        elif op in ops:
            work[res[0]] = ops[op](*(work[a] for a in args[:1 if op in _UNARY else 2]))
        else:
            raise ModelError(f"algorithm 'scip' of method 'global' cannot pass CasADi operation {op} of the upper "
                             "level to SCIP (supported: + - * /, powers with constant exponents, exp, log, sqrt, sin, "
                             "cos); rewrite the expression or use a local method")
    return out


def unbounded_nonconvex(leader: Leader, box: tuple[np.ndarray, np.ndarray], blocks: dict[str, slice]) -> list[str]:
    """Names (block[index] of the MPCC vector, e.g. x[0]) of the variables in a nonlinear term of the leader whose
    derived box is infinite: SCIP's relaxation of such a term has no finite bound."""
    exprs = ca.vertcat(leader.objective, leader.inequalities, leader.equalities, *(e for _, e in leader.slacks))
    columns = sorted({j for i in range(int(exprs.numel())) for j in ca.hessian(exprs[i], leader.w)[0].sparsity().row()})
    names = []
    for j in columns:
        if not (np.isfinite(box[0][j]) and np.isfinite(box[1][j])):
            block, part = next((b, s) for b, s in blocks.items() if s.start <= j < s.stop)
            names.append(f"{block}[{j - part.start}]")
    return names


def _finite(v: float, infinity: float) -> float | None:
    """v as a SCIP bound: None where infinite."""
    return None if not np.isfinite(v) or abs(v) >= infinity else float(v)


def _build(scip: Any, relax: Relaxation, leader: Leader, big_m: BigM, lo: np.ndarray, hi: np.ndarray
           ) -> tuple[Any, list[Any]]:
    """The SCIP model of the MPCC and its variables w."""
    f = relax.form
    model = scip.Model("bilevel-global")
    model.hideOutput()
    inf = model.infinity()
    w = [model.addVar(f"w{j}", lb=_finite(lo[j], inf), ub=_finite(hi[j], inf)) for j in range(f.n)]

    def linear(row: np.ndarray) -> Any:
        return scip.quicksum(float(a) * w[j] for j, a in enumerate(row) if a != 0.0)

    for row, b in zip(f.A_eq, f.b_eq):
        model.addCons(linear(row) == float(b))
    for row, b in zip(*relax.cuts):
        model.addCons(linear(row) <= float(b))
    slacks = dict(leader.slacks)
    slack_exprs = dict(zip(slacks, scip_expressions(ca.vertcat(*slacks.values()), leader.w, w))) if slacks else {}
    for i in range(f.n_pairs):
        side = big_m.fixed.get(i)
        s = model.addVar(f"slack{i}", lb=0.0, ub=0.0 if side == G_SIDE else _finite(big_m.slack[i], inf))
        m = model.addVar(f"mult{i}", lb=0.0, ub=0.0 if side == H_SIDE else _finite(big_m.multiplier[i], inf))
        model.addCons((slack_exprs[i] if i in slack_exprs else linear(f.G[i]) + float(f.g[i])) == s)
        model.addCons(linear(f.H[i]) + float(f.h[i]) == m)
        if side is not None:
            continue
        if np.isfinite(big_m.slack[i]) and np.isfinite(big_m.multiplier[i]):
            z = model.addVar(f"z{i}", vtype="B")  # z = 1: slack zero; z = 0: multiplier zero
            model.addCons(s <= float(big_m.slack[i]) * (1 - z))
            model.addCons(m <= float(big_m.multiplier[i]) * z)
        else:
            model.addConsSOS1([s, m])
    F, rows_in, rows_eq = (scip_expressions(e, leader.w, w)
                           for e in (leader.objective, leader.inequalities, leader.equalities))
    for e in rows_in:
        model.addCons(e <= 0.0)
    for e in rows_eq:
        model.addCons(e == 0.0)
    t = model.addVar("objective", lb=None, ub=None)
    model.addCons(F[0] - t <= 0.0)
    model.setObjective(t, "minimize")
    return model, w


def nearest_on_branch(relax: Relaxation, w0: np.ndarray) -> np.ndarray | None:
    """The point nearest to w0 (max norm) on the branch w0 selects: every pair held on its side, an LP; None if it
    fails. Every point of that branch satisfies the lower level's KKT conditions exactly, except at a pair whose
    slack is nonlinear in x and zero at w0 (not an LP row: left where SCIP put it)."""
    f = relax.form
    sides = sides_of(relax, w0)
    if f.leader is not None and f.leader.slacks:
        index, exprs = zip(*f.leader.slacks)
        values = np.asarray(ca.Function("slacks", [f.leader.w], [ca.vertcat(*exprs)])(w0), dtype=float).ravel()
        for i, v in zip(index, values):
            if v > f.H[i] @ w0 + f.h[i]:
                sides[i] = H_SIDE
            else:
                del sides[i]
    A_eq, b_eq = relax.branch_rows(sides)
    n = f.n
    eye = np.eye(n)
    A_ub = np.vstack([np.hstack([relax.A_ub, np.zeros((relax.b_ub.size, 1))]),
                      np.hstack([eye, -np.ones((n, 1))]), np.hstack([-eye, -np.ones((n, 1))])])
    b_ub = np.concatenate([relax.b_ub, w0, -w0])
    cost = np.zeros(n + 1)
    cost[-1] = 1.0
    bounds = np.column_stack([np.append(f.lb, 0.0), np.append(f.ub, np.inf)])
    res = linprog(cost, A_ub=A_ub, b_ub=b_ub, A_eq=np.hstack([A_eq, np.zeros((b_eq.size, 1))]) if b_eq.size else None,
                  b_eq=b_eq if b_eq.size else None, bounds=bounds, method="highs")
    return np.asarray(res.x[:n]) if res.status == 0 else None


def solve_scip(relax: Relaxation, big_m: BigM, box: tuple[np.ndarray, np.ndarray], gap_tol: float,
               time_limit: float, node_limit: int) -> SearchOutcome:
    """SCIP on the MPCC of relax.form (whose leader must be set), in the derived box; bounds in minimization form."""
    scip = require_scip()
    f = relax.form
    leader = f.leader
    assert leader is not None, "solve_scip needs a form built with nonconvex_leader=True"
    t0 = time.perf_counter()
    model, w = _build(scip, relax, leader, big_m, *box)
    model.setParam("limits/time", min(max(time_limit - (time.perf_counter() - t0), 1e-3), SCIP_NO_TIME_LIMIT))
    model.setParam("limits/nodes", int(node_limit))
    model.setParam("numerics/feastol", param("global.scip_feastol"))
    model.setParam("limits/gap", gap_tol)      # SCIP's relative gap divides by min(|primal|, |dual|): it closing
    model.setParam("limits/absgap", gap_tol)   # implies ours, which divides by max(1, |upper|)
    try:
        model.optimize()
    except Exception as exc:  # SCIP stopped on an internal error (e.g. unresolved LP numerics): no proof, no point
        return SearchOutcome(None, -np.inf, np.inf, 0, "failed",
                             note=f"SCIP stopped on an internal error ({exc}); a looser "
                                  "defaults['global.scip_feastol'] may get past LP numerics troubles")
    ended = SCIP_ENDED.get(model.getStatus(), "failed")
    nodes = int(model.getNTotalNodes())
    inf = model.infinity()
    dual = float(model.getDualbound())
    lower = -np.inf if dual <= -inf else (np.inf if dual >= inf else dual)
    if ended in ("infeasible", "unbounded"):
        value = np.inf if ended == "infeasible" else -np.inf
        return SearchOutcome(None, value, value, nodes, ended)
    if model.getNSols() == 0:
        return SearchOutcome(None, lower, np.inf, nodes, ended)
    sol = model.getBestSol()
    w_scip = np.array([sol[v] for v in w])
    w_best = nearest_on_branch(relax, w_scip)
    if w_best is None:
        w_best = w_scip
    objective = ca.Function("F", [leader.w], [leader.objective])
    upper = float(objective(w_best))
    return SearchOutcome(w_best, min(lower, upper), upper, nodes, ended,
                         history=[{"node": nodes, "lower": min(lower, upper), "upper": upper}])

