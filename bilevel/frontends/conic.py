"""cvxpy's own parametrized conic form of a problem, read as CasADi: coefficients affine in a parameter vector.

cvxpy's Clarabel chain up to (not including) the solver ends in a ParamConeProg,
min 1/2 z'Pz + q'z + d s.t. A_k z + b_k in K_k, whose tensors map the parameter vector (each Parameter
flattened column-major, then a 1) to (P, q, d, A, b). The canonicalization is cvxpy's, not ours.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import cvxpy as cp
import numpy as np
import scipy.sparse as sp
from cvxpy.constraints import PSD, SOC, ExpCone, NonNeg, PowCone3D, PowConeND, Zero
from cvxpy.constraints.constraint import Constraint
from cvxpy.constraints.psd import SvecPSD
from cvxpy.lin_ops.lin_op import CONSTANT_ID
from cvxpy.reductions.cvx_attr2constr import CvxAttr2Constr, recover_value_for_leaf
from cvxpy.reductions.dcp2cone.cone_matrix_stuffing import ParamConeProg
from cvxpy.reductions.reduction import Reduction
from cvxpy.reductions.solution import Solution
from cvxpy.utilities.psd_utils import TriangleKind, tri_to_full

from ..errors import ModelError

CONE_HINTS = {
    ExpCone: "exponential cone (from exp, log, entr, kl_div, logistic, log_sum_exp, ...)",
    PowCone3D: "power cone (from power, pnorm or geo_mean with approx=False; the default approx=True gives SOCs)",
    PowConeND: "power cone (from power, pnorm or geo_mean with approx=False; the default approx=True gives SOCs)",
}


@dataclass(frozen=True)
class ConeBlock:
    """Rows A z + b of one cvxpy cone constraint: kind 'zero', 'nonneg', 'soc' or 'psd', and the cone sizes
    (SOC: the length of each (t, u) row group; PSD: the matrix side, rows = vec of the symmetric matrix)."""

    kind: str
    A: ca.SX
    b: ca.SX
    sizes: tuple[int, ...]


@dataclass(frozen=True)
class ConicForm:
    """min 1/2 z'Pz + q'z + d s.t. blocks, lb <= z <= ub; `user` maps z linearly to each user Variable (F order)."""

    P: ca.SX
    q: ca.SX
    d: ca.SX
    blocks: tuple[ConeBlock, ...]
    lb: np.ndarray
    ub: np.ndarray
    user: dict[int, sp.csr_array]
    minimize: bool

    @property
    def n(self) -> int:
        return int(self.lb.size)


def _tensor(tensor: sp.spmatrix | sp.sparray, pvec: ca.SX, rows: int) -> ca.SX:
    """The coefficient matrix (rows x cols, F order) of a cvxpy tensor applied to the parameter vector."""
    flat = ca.mtimes(ca.DM(sp.csc_matrix(tensor)), pvec)
    return ca.reshape(flat, rows, int(flat.numel()) // rows)


def _user_map(problem: cp.Problem, chain: list[Reduction], inverse: list[Any], n: int) -> dict[int, sp.csr_array]:
    """The linear map z -> each user Variable, by inverting cvxpy's own chain on unit vectors (linear once the
    projection of values onto variable bounds, in CvxAttr2Constr's invert, is left out)."""
    columns: dict[int, list[np.ndarray]] = {v.id: [] for v in problem.variables()}
    for j in range(n + 1):
        z = np.zeros(n)
        if j < n:
            z[j] = 1.0
        sol = Solution(cp.OPTIMAL, 0.0, {0: z}, {}, {})
        for red, inv in zip(reversed(chain), reversed(inverse)):
            if isinstance(red, CvxAttr2Constr) and inv:  # its invert projects onto the bounds: not linear
                new, old, _ = inv
                values = {vid: recover_value_for_leaf(var, sol.primal_vars[new[vid].id], project=False)
                          for vid, var in old.items() if new[vid].id in sol.primal_vars}
                sol = Solution(cp.OPTIMAL, 0.0, values, {}, {})
            else:
                sol = red.invert(sol, inv)
        for v in problem.variables():
            columns[v.id].append(np.asarray(sol.primal_vars[v.id], dtype=float).reshape(-1, order="F"))
    out = {}
    for vid, cols in columns.items():
        if np.any(cols[-1]):
            raise ModelError("cvxpy maps the conic variables to a user Variable with an offset; "
                             "this front end needs a linear map (please report the problem)")
        out[vid] = sp.csr_array(np.column_stack(cols[:-1]))
    return out


def _psd_operator(n: int, triangle: TriangleKind, sqrt2: bool) -> np.ndarray:
    """The n^2 x n(n+1)/2 matrix taking cvxpy's scaled triangle (solver convention) to vec of the full matrix."""
    k = n * (n + 1) // 2
    return np.column_stack([tri_to_full(np.eye(k)[i], n, triangle, sqrt2).reshape(-1, order="F") for i in range(k)])


def _parameter_vector(prog: ParamConeProg, values: dict[int, ca.SX]) -> ca.SX:
    """cvxpy's parameter vector (each Parameter column-major at its column, then the constant 1) from `values`."""
    parts = []
    for pid, _ in sorted(prog.param_id_to_col.items(), key=lambda item: item[1]):
        if pid == CONSTANT_ID:
            parts.append(ca.SX(1))
        elif pid in values:
            parts.append(ca.vec(values[pid]))
        else:
            raise ModelError("a cvxpy Parameter with a structural attribute (symmetric, PSD, NSD, diag, sparsity) "
                             "was replaced by cvxpy's canonicalization; declare it without the attribute")
    return ca.vertcat(*parts)


def conic_form(problem: cp.Problem, values: dict[int, ca.SX]) -> ConicForm:
    """Apply cvxpy's Clarabel chain minus the solver and read its ParamConeProg, Parameter id -> `values` (SX)."""
    _, chain, _ = problem.get_problem_data(cp.CLARABEL)
    reductions = chain.reductions[:-1]
    prog, inverse = problem, []
    for red in reductions:
        prog, inv = red.apply(prog)
        inverse.append(inv)
    n = int(prog.x.size)
    pvec = _parameter_vector(prog, values) if prog.param_id_to_col else ca.SX(1)
    qd = _tensor(prog.q, pvec, 1)
    P = _tensor(prog.P, pvec, n) if prog.P is not None else ca.SX(n, n)
    Ab = _tensor(prog.A, pvec, prog.constr_size) if prog.constr_size else ca.SX(0, n + 1)
    context = next((r.solver_context for r in reductions if hasattr(r, "solver_context")), None)
    blocks, start = [], 0
    for con in prog.constraints:
        size = int(con.size)
        rows = Ab[start:start + size, :]
        start += size
        kind, sizes, op = _cone(con, size, context)
        rows = rows if op is None else ca.mtimes(ca.DM(sp.csc_matrix(op)), rows)
        blocks.append(ConeBlock(kind, rows[:, :n], rows[:, n], sizes))
    lb = np.full(n, -np.inf) if prog.lower_bounds is None else np.asarray(prog.lower_bounds, dtype=float)
    ub = np.full(n, np.inf) if prog.upper_bounds is None else np.asarray(prog.upper_bounds, dtype=float)
    return ConicForm(P, qd[:, :n].T, qd[:, n], tuple(blocks), lb, ub, _user_map(problem, reductions, inverse, n),
                     isinstance(problem.objective, cp.Minimize))


def _cone(con: Constraint, size: int, context: Any) -> tuple[str, tuple[int, ...], sp.sparray | None]:
    """(kind, sizes, operator on the constraint's rows or None for identity) of one cvxpy cone constraint."""
    if isinstance(con, Zero):
        return "zero", (size,), None
    if isinstance(con, NonNeg):
        return "nonneg", (size,), None
    if isinstance(con, SOC):
        cones = int(con.args[0].size)
        dim = (size - cones) // cones
        # rows: t (one per cone), then the u of every cone stacked (column j of u, F order) -> (t_j, u_j) groups
        order = [k for j in range(cones) for k in [j, *range(cones + j * dim, cones + (j + 1) * dim)]]
        return "soc", (dim + 1,) * cones, sp.csr_array(np.eye(size)[order])
    if isinstance(con, (SvecPSD, PSD)):
        side = int(con.args[0].shape[-1]) if isinstance(con, PSD) else int(con._n)
        if isinstance(con, PSD):  # vec of the full matrix: its symmetric part, as cvxpy's PSD constraint means
            swap = np.arange(side * side).reshape(side, side).T.ravel()
            one = 0.5 * (np.eye(side * side) + np.eye(side * side)[swap])
            count = size // (side * side)
        else:  # cvxpy's scaled triangle in the solver's convention (context), back to the full symmetric matrix
            one = _psd_operator(side, context.psd_triangle_kind, context.psd_sqrt2_scaling)
            count = size // (side * (side + 1) // 2)
        return "psd", (side,) * count, sp.block_diag([sp.csr_array(one)] * count, format="csr")
    what = next((hint for cls, hint in CONE_HINTS.items() if isinstance(con, cls)), type(con).__name__)
    raise ModelError(f"the cvxpy lower level uses the {what}; bilevel reduces zero, nonnegative, "
                     "second-order and PSD cones only: rewrite that term with those cones, or declare a "
                     "smooth convex lower objective directly with minimize_lower")
