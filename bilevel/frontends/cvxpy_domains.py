"""The domain a cvxpy Parameter's attributes promise (nonneg, pos, nonpos, neg, bounds; PSD, NSD, boolean, ...)
for a Parameter bound to an expression of upper variables: the learner is DCP only on that domain, so the leader
must stay in it. Sign attributes and bounds become upper-level constraints; attributes with no upper-level
counterpart (an LMI, integrality, structure, complex values) are refused unless the expression is constant."""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import cvxpy as cp
import numpy as np

from ..errors import InvalidData, ModelError

if TYPE_CHECKING:  # pragma: no cover
    from ..model import BilevelProblem

UNSUPPORTED = ("PSD", "NSD", "boolean", "integer", "symmetric", "diag", "hermitian", "complex", "imag", "sparsity")
"""Attributes with no upper-level constraint here: only a constant expression may be bound to such a Parameter."""

ROUNDING = 1e-6
"""Relative violation of a sign or bound that is moved onto the domain when the value is handed back to cvxpy: the
certificate's default feasibility tolerance, so a point that passes upper_feasibility can be re-solved."""


def _interval(param: cp.Parameter) -> tuple[np.ndarray, np.ndarray]:
    """Elementwise [lo, hi] (column-major, as the bound expression) that the Parameter's attributes allow."""
    n = int(np.prod(param.shape, dtype=int))
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    if param.is_nonneg():  # nonneg, pos, boolean
        lo = np.zeros(n)
    if param.is_nonpos():  # nonpos, neg
        hi = np.zeros(n)
    bounds = param.attributes.get("bounds")
    if bounds is not None:
        lo = np.maximum(lo, np.broadcast_to(np.asarray(bounds[0], dtype=float), param.shape).ravel(order="F"))
        hi = np.minimum(hi, np.broadcast_to(np.asarray(bounds[1], dtype=float), param.shape).ravel(order="F"))
    return lo, hi


def constrain_domain(problem: "BilevelProblem", param: cp.Parameter, expr: ca.SX, label: str, name: str) -> None:
    """Declare the upper constraints lo <= expr <= hi that keep a bound Parameter in its declared domain, or raise
    ModelError (an attribute without upper-level counterpart on a non-constant expression, or a constant that
    violates the domain)."""
    flat = ca.vec(expr)
    given = [a for a in UNSUPPORTED if param.attributes.get(a)]
    lo, hi = _interval(param)
    if flat.is_constant():
        value = np.asarray(ca.DM(flat), dtype=float).ravel()
        if np.any(value < lo) or np.any(value > hi):
            raise ModelError(f"lower_cvxpy: {label} is bound to a constant outside its declared domain "
                             f"[{lo.min():g}, {hi.max():g}]; change the value or the Parameter's attributes")
        return
    if given:
        raise ModelError(f"lower_cvxpy: {label} has the attribute {given[0]!r} and is bound to an expression of the "
                         "upper variables; the upper level cannot keep it in that domain (no upper-level LMI, "
                         "integrality or structure constraint), so the leader could leave the set on which the "
                         "learner is convex; bind a Parameter without the attribute (and state what is needed as "
                         "upper constraints), or bind a constant")
    rows = [(np.isfinite(lo), lambda e, b: e >= b, "min"), (np.isfinite(hi), lambda e, b: e <= b, "max")]
    for mask, compare, side in rows:
        idx = np.flatnonzero(mask).tolist()
        if idx:
            bound = lo if side == "min" else hi
            problem.upper_constraint(compare(flat[idx], ca.DM(bound[idx])), name=f"{name}.{param.name()}.{side}")


def in_domain(param: cp.Parameter, value: np.ndarray, label: str) -> np.ndarray:
    """value (the Parameter's shape) moved onto the Parameter's domain when it is off by ROUNDING at most; InvalidData
    when it is farther (the point leaves the set on which the learner is convex: the re-solve must not clip it)."""
    lo, hi = (v.reshape(param.shape, order="F") for v in _interval(param))
    slack = ROUNDING * (1.0 + np.abs(value))
    if np.any(value < lo - slack) or np.any(value > hi + slack):
        raise InvalidData(f"{label} takes the value {np.array2string(value, precision=4)} here, outside its declared "
                          "domain; the cvxpy learner is not defined there")
    return np.clip(value, lo, hi)
