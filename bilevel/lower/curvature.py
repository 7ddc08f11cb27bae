"""Convexity in y by composition rules (disciplined convex programming: Grant, Boyd & Ye (2006), "Disciplined convex
programming", in Global Optimization: From Theory to Implementation, Springer, pp. 155-210).

Each node of a CasADi SX function of (x, y) gets a curvature in y ("const" where it does not depend on y, "affine",
"convex", "concave" or "unknown") and an interval of its values (interval.py) while x and y range over boxes; x
enters as a coefficient whose sign the interval gives. The result is sufficient, never necessary: "convex" is a
proof on the boxes, "unknown" claims nothing. It proves what interval Hessian bounds cannot where a Hessian holds a
product of two equal factors (t * t over an interval containing 0: the Hessian of (x + 2y - 15)^4 is
4 t^2 + (2t)(4t), whose natural enclosure is negative near t = 0).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .interval import Interval, apply

CONST, AFFINE, CONVEX, CONCAVE, UNKNOWN = "const", "affine", "convex", "concave", "unknown"
_FLIP = {CONVEX: CONCAVE, CONCAVE: CONVEX}


def _add(a: str, b: str) -> str:
    if UNKNOWN in (a, b):
        return UNKNOWN
    if a in (CONST, AFFINE):
        return AFFINE if b == CONST else b
    if b in (CONST, AFFINE):
        return a
    return a if a == b else UNKNOWN


def _scale(c: str, k: Interval) -> str:
    """Curvature of c times a coefficient free of y with values in k."""
    if c in (CONST, AFFINE, UNKNOWN):
        return c
    if k[0] >= 0.0:
        return c
    return _FLIP[c] if k[1] <= 0.0 else UNKNOWN


def _power(c: str, v: Interval, p: float) -> str:
    """Curvature of t^p for t of curvature c with values in v."""
    if p == 1.0:
        return c
    even = p == int(p) and int(p) % 2 == 0
    if p > 1.0:  # t^p is convex on R (even p) or on t >= 0, nondecreasing for t >= 0, nonincreasing for t <= 0 (even)
        if c == AFFINE and (even or v[0] >= 0.0):
            return CONVEX
        if c == CONVEX and v[0] >= 0.0:
            return CONVEX
        if c == CONCAVE and even and v[1] <= 0.0:
            return CONVEX
        if c == AFFINE and p == int(p) and v[1] <= 0.0:  # an odd power on t <= 0 is concave
            return CONCAVE
        return UNKNOWN
    if 0.0 < p < 1.0 and v[0] >= 0.0:  # concave, nondecreasing
        return CONCAVE if c in (AFFINE, CONCAVE) else UNKNOWN
    if p < 0.0 and v[0] > 0.0:  # convex, nonincreasing on t > 0
        return CONVEX if c in (AFFINE, CONCAVE) else UNKNOWN
    return UNKNOWN


def _unary(op: int, c: str, v: Interval) -> str:
    """Curvature of op(t) for t of curvature c (not const) with values in v."""
    if op in (ca.OP_ASSIGN, ca.OP_TWICE):
        return c
    if op == ca.OP_NEG:
        return _FLIP.get(c, c)
    if op == ca.OP_SQ:
        return _power(c, v, 2.0)
    if op == ca.OP_EXP:
        return CONVEX if c in (AFFINE, CONVEX) else UNKNOWN
    if (op == ca.OP_LOG and v[0] > 0.0) or (op == ca.OP_SQRT and v[0] >= 0.0):
        return CONCAVE if c in (AFFINE, CONCAVE) else UNKNOWN
    if op == ca.OP_INV:
        return _power(c, v, -1.0) if v[0] > 0.0 else UNKNOWN
    if op == ca.OP_FABS:
        return CONVEX if c == AFFINE else UNKNOWN
    return UNKNOWN


def _binary(op: int, a: str, b: str, va: Interval, vb: Interval) -> str:
    """Curvature of a op b (not both const)."""
    if op == ca.OP_ADD:
        return _add(a, b)
    if op == ca.OP_SUB:
        return _add(a, _FLIP.get(b, b))
    if op == ca.OP_MUL:
        if a == CONST:
            return _scale(b, va)
        return _scale(a, vb) if b == CONST else UNKNOWN
    if op == ca.OP_DIV:
        if b == CONST:
            inverse = apply(ca.OP_INV, [vb])
            return _scale(a, inverse) if inverse is not None and np.isfinite(inverse).all() else UNKNOWN
        return _scale(_unary(ca.OP_INV, b, vb), va) if a == CONST else UNKNOWN
    if op in (ca.OP_CONSTPOW, ca.OP_POW) and b == CONST and vb[0] == vb[1]:
        return _power(a, va, vb[0])
    return UNKNOWN


def curvatures(fun: ca.Function, boxes: list[tuple[np.ndarray, np.ndarray]], varying: int) -> list[str] | None:
    """The curvature in input `varying` of every output nonzero of an SX function (one output, inputs ranging over
    boxes); None if an operation's values cannot be enclosed on the boxes."""
    curv: dict[int, str] = {}
    value: dict[int, Interval] = {}
    out = [UNKNOWN] * fun.nnz_out(0)
    for k in range(fun.n_instructions()):
        op, inp, res = fun.instruction_id(k), fun.instruction_input(k), fun.instruction_output(k)
        if op == ca.OP_CONST:
            c = float(fun.instruction_constant(k))
            curv[res[0]], value[res[0]] = CONST, (c, c)
        elif op == ca.OP_INPUT:
            lo, hi = boxes[inp[0]]
            curv[res[0]] = AFFINE if inp[0] == varying else CONST
            value[res[0]] = (float(lo[inp[1]]), float(hi[inp[1]]))
        elif op == ca.OP_OUTPUT:
            out[res[1]] = curv[inp[0]]
        else:
            v = apply(op, [value[i] for i in inp]) if op != ca.OP_ASSIGN else value[inp[0]]
            if v is None:
                return None
            args = [curv[i] for i in inp]
            if all(a == CONST for a in args):
                curv[res[0]] = CONST
            elif len(inp) == 1:
                curv[res[0]] = _unary(op, args[0], value[inp[0]])
            else:
                curv[res[0]] = _binary(op, args[0], args[1], value[inp[0]], value[inp[1]])
            value[res[0]] = v
    return out


def convex_by_rules(x: ca.SX, y: ca.SX, exprs: ca.SX, x_box: tuple[np.ndarray, np.ndarray],
                    y_box: tuple[np.ndarray, np.ndarray]) -> bool:
    """True when composition rules prove every entry of exprs (in x and y only) convex in y for all x in x_box and
    y in y_box."""
    found = curvatures(ca.Function("curvature", [x, y], [ca.densify(exprs)]), [x_box, y_box], 1)
    return found is not None and all(c in (CONST, AFFINE, CONVEX) for c in found)
