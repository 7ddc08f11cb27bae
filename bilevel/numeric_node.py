"""A numeric vector function of matrices as a CasADi call node with its exact first derivatives.

`numeric_node(name, evaluate, in_shapes, size)` makes a CasADi Function out of a numpy function
evaluate(*inputs, jacobian) -> (values (size,), [d values / d input_j as arrays (size, *in_shapes[j])] or None): it
can be called on SX or MX expressions like any Function (a call node, never expanded), and its reverse derivative
(what CasADi's jacobian and gradient of an expression calling it use, row by row) is the seed times the Jacobian that
`evaluate` returns, computed once per point and kept for the other rows. No second derivatives: a problem that calls
one takes first-order methods (e.g. `reduced` with its limited-memory Hessian).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np

Evaluate = Callable[..., tuple[np.ndarray, Sequence[np.ndarray] | None]]


class _Point:
    """The last point's values and Jacobian blocks, shared by a node and its reverse."""

    def __init__(self, evaluate: Evaluate, shapes: Sequence[tuple[int, int]]) -> None:
        self.evaluate, self.shapes = evaluate, shapes
        self.key: bytes | None = None
        self.values: np.ndarray | None = None
        self.blocks: Sequence[np.ndarray] | None = None

    def at(self, args: Sequence[memoryview], jacobian: bool) -> tuple[np.ndarray, Sequence[np.ndarray] | None]:
        """Values and (with jacobian) Jacobian blocks at the inputs in CasADi's (column-major) buffers."""
        key = b"".join(bytes(a) for a in args)
        if key != self.key or (jacobian and self.blocks is None):
            mats = [np.frombuffer(a, dtype=np.float64).reshape(s, order="F").copy() for a, s in zip(args, self.shapes)]
            self.key = key
            self.values, self.blocks = self.evaluate(*mats, jacobian=jacobian)
            if self.blocks is not None:  # as (rows, input entries in CasADi's order) for the seeds' products
                self.blocks = [b.transpose(0, 2, 1).reshape(len(self.values), -1) for b in self.blocks]
        return self.values, self.blocks


class _Node(ca.Callback):
    def __init__(self, name: str, point: _Point, size: int) -> None:
        ca.Callback.__init__(self)
        self.point, self.size = point, size
        self._reverse: list[_Reverse] = []  # CasADi keeps no Python reference
        self.construct(name, {"enable_fd": False})

    def get_n_in(self) -> int:
        return len(self.point.shapes)

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(*self.point.shapes[i])

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self.size, 1)

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg: tuple[memoryview, ...], res: tuple[memoryview, ...]) -> int:
        np.frombuffer(res[0], dtype=np.float64)[:] = self.point.at(arg, False)[0]
        return 0

    def has_reverse(self, nadj: int) -> bool:
        return True

    def get_reverse(self, nadj: int, name: str, inames: list[str], onames: list[str], opts: dict[str, Any]
                    ) -> ca.Callback:
        rev = _Reverse(name, self.point, self.size, nadj, opts)
        self._reverse.append(rev)
        return rev


class _Reverse(ca.Callback):
    """(inputs, output, nadj seeds) -> nadj sensitivities per input: seed' * Jacobian."""

    def __init__(self, name: str, point: _Point, size: int, nadj: int, opts: dict[str, Any]) -> None:
        ca.Callback.__init__(self)
        self.point, self.size, self.nadj = point, size, nadj
        self.construct(name, opts)

    def get_n_in(self) -> int:
        return len(self.point.shapes) + 2

    def get_n_out(self) -> int:
        return len(self.point.shapes)

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        k = len(self.point.shapes)
        return ca.Sparsity.dense(*self.point.shapes[i]) if i < k else \
            ca.Sparsity.dense(self.size, 1 if i == k else self.nadj)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        rows, cols = self.point.shapes[i]
        return ca.Sparsity.dense(rows, cols * self.nadj)

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg: tuple[memoryview, ...], res: tuple[memoryview, ...]) -> int:
        k = len(self.point.shapes)
        _, blocks = self.point.at(arg[:k], True)
        seeds = np.frombuffer(arg[k + 1], dtype=np.float64).reshape(self.nadj, self.size)  # column j: direction j
        for out, block in zip(res, blocks):
            np.frombuffer(out, dtype=np.float64).reshape(self.nadj, -1)[:] = seeds @ block
        return 0


def numeric_node(name: str, evaluate: Evaluate, in_shapes: Sequence[tuple[int, int]], size: int) -> ca.Function:
    """The CasADi Function of `evaluate` (module docstring)."""
    return _Node(name, _Point(evaluate, tuple(in_shapes)), size)
