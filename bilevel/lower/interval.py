"""Interval evaluation of a CasADi SX function: enclosures of its outputs when its inputs range over boxes.

Natural interval extension, operation by operation, of the function's algorithm (no directed rounding: an
enclosure up to floating-point rounding). Operations it does not know make it return None (nothing is claimed).
Used to prove a lower-level Hessian PSD on a box (convexity.py) and to follow curvature (curvature.py).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

Interval = tuple[float, float]
_WHOLE = (-math.inf, math.inf)


def _mul(a: Interval, b: Interval) -> Interval:
    prods = [0.0 if (p == 0.0 or q == 0.0) else p * q for p in a for q in b]  # 0 * inf is 0 for an enclosure
    return min(prods), max(prods)


def _div(a: Interval, b: Interval) -> Interval:
    if b[0] <= 0.0 <= b[1]:
        return _WHOLE
    return _mul(a, (1.0 / b[1], 1.0 / b[0]))


def _monotone(fun, a: Interval, increasing: bool = True) -> Interval:
    lo, hi = fun(a[0]), fun(a[1])
    return (lo, hi) if increasing else (hi, lo)


def _safe(fun):
    """fun extended to +-inf by its limits (math functions raise on overflow)."""
    def call(v: float) -> float:
        try:
            return fun(v)
        except OverflowError:
            return math.inf if v > 0 else -math.inf
    return call


def _power(a: Interval, c: float) -> Interval | None:
    """a^c for a constant exponent c; None where it is not real on all of a."""
    if c == int(c):
        k = int(c)
        if k == 0:
            return 1.0, 1.0
        if k < 0:
            return _div((1.0, 1.0), _power(a, -k))
        ends = [_safe(lambda v: v ** k)(a[0]), _safe(lambda v: v ** k)(a[1])]
        if k % 2 == 1:
            return ends[0], ends[1]
        low = 0.0 if a[0] <= 0.0 <= a[1] else min(ends)
        return low, max(ends)
    if a[0] < 0.0:
        return None
    return _monotone(_safe(lambda v: v ** c), a, c > 0)


def _sq(a: Interval) -> Interval:
    return _power(a, 2.0)


def _unary(op: int, a: Interval) -> Interval | None:
    """Enclosure of a unary operation over a (None if unknown or not defined on all of a)."""
    exp = _safe(math.exp)
    table = {
        ca.OP_NEG: lambda: (-a[1], -a[0]),
        ca.OP_TWICE: lambda: (2.0 * a[0], 2.0 * a[1]),
        ca.OP_SQ: lambda: _sq(a),
        ca.OP_EXP: lambda: _monotone(exp, a),
        ca.OP_EXPM1: lambda: _monotone(lambda v: exp(v) - 1.0, a),
        ca.OP_LOG: lambda: None if a[1] <= 0.0 else (math.log(a[0]) if a[0] > 0 else -math.inf, math.log(a[1])),
        ca.OP_LOG1P: lambda: None if a[1] <= -1.0 else (math.log1p(a[0]) if a[0] > -1 else -math.inf,
                                                        math.log1p(a[1])),
        ca.OP_SQRT: lambda: None if a[0] < 0.0 else (math.sqrt(a[0]), math.sqrt(a[1])),
        ca.OP_INV: lambda: _div((1.0, 1.0), a),
        ca.OP_SIN: lambda: (-1.0, 1.0),
        ca.OP_COS: lambda: (-1.0, 1.0),
        ca.OP_TANH: lambda: _monotone(math.tanh, a),
        ca.OP_ATAN: lambda: _monotone(math.atan, a),
        ca.OP_ERF: lambda: _monotone(math.erf, a),
        ca.OP_SINH: lambda: _monotone(_safe(math.sinh), a),
        ca.OP_COSH: lambda: (1.0 if a[0] <= 0.0 <= a[1] else min(_safe(math.cosh)(a[0]), _safe(math.cosh)(a[1])),
                             max(_safe(math.cosh)(a[0]), _safe(math.cosh)(a[1]))),
        ca.OP_FABS: lambda: (0.0 if a[0] <= 0.0 <= a[1] else min(abs(a[0]), abs(a[1])), max(abs(a[0]), abs(a[1]))),
    }
    return table[op]() if op in table else None


def _binary(op: int, a: Interval, b: Interval) -> Interval | None:
    """Enclosure of a binary operation (None if unknown or not defined everywhere)."""
    if op == ca.OP_ADD:
        return a[0] + b[0], a[1] + b[1]
    if op == ca.OP_SUB:
        return a[0] - b[1], a[1] - b[0]
    if op == ca.OP_MUL:
        return _mul(a, b)
    if op == ca.OP_DIV:
        return _div(a, b)
    if op == ca.OP_FMIN:
        return min(a[0], b[0]), min(a[1], b[1])
    if op == ca.OP_FMAX:
        return max(a[0], b[0]), max(a[1], b[1])
    if op in (ca.OP_CONSTPOW, ca.OP_POW) and b[0] == b[1]:
        return _power(a, b[0])
    return None


def enclose(fun: ca.Function, boxes: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """Enclosures [lo, hi] of every output's nonzeros (column-major) of an SX function whose input i ranges over
    boxes[i] = (lo, hi); None if an operation is not supported or not defined on the whole box."""
    work: dict[int, Interval] = {}
    outs = [(np.zeros(fun.nnz_out(k)), np.zeros(fun.nnz_out(k))) for k in range(fun.n_out())]
    for k in range(fun.n_instructions()):
        op, inp, out = fun.instruction_id(k), fun.instruction_input(k), fun.instruction_output(k)
        if op == ca.OP_CONST:
            c = float(fun.instruction_constant(k))
            work[out[0]] = (c, c)
        elif op == ca.OP_INPUT:
            lo, hi = boxes[inp[0]]
            work[out[0]] = (float(lo[inp[1]]), float(hi[inp[1]]))
        elif op == ca.OP_OUTPUT:
            outs[out[0]][0][out[1]], outs[out[0]][1][out[1]] = work[inp[0]]
        elif op == ca.OP_ASSIGN:
            work[out[0]] = work[inp[0]]
        else:
            value = apply(op, [work[i] for i in inp])
            if value is None:
                return None
            work[out[0]] = value
    return outs


def apply(op: int, args: list[Interval]) -> Interval | None:
    """Enclosure of CasADi operation `op` on argument intervals (None if unknown or not defined on all of them)."""
    value = _unary(op, args[0]) if len(args) == 1 else _binary(op, args[0], args[1])
    return None if value is None or any(math.isnan(v) for v in value) else value
