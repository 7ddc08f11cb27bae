"""Numeric linear maps in a declaration: `T = p.linear_map(matrix)`, then `T @ expr` is a symbol standing for the
product, and the matrix stays data.

Written into a CasADi expression (`ca.mtimes(ca.DM(T), x)`), a numeric N x N matrix becomes N^2 scalar nodes that
every derivative and every evaluation walks. A linear map keeps it a matrix (numpy, scipy.sparse or a scipy
LinearOperator): the engine computes `T @ arg(x)` and the adjoint products `T' v` with BLAS or the operator's own
code, and the expressions stay as small as the symbols they are written with. A dense matrix that is Toeplitz up to a
few entries (a filter matrix) is applied by FFT convolution (bilevel.toeplitz).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator

from .defaults import param
from .errors import InvalidData, ModelError
from .real_data import refuse_complex
from .toeplitz import ToeplitzBank, toeplitz_split

if TYPE_CHECKING:  # pragma: no cover
    from .model import BilevelProblem


class Gather:
    """A sparse matrix with at most one nonzero per row (a slice, shift or scaling of a signal) applied to a vector as
    a gather, (J v)_i = J_ic v_c: what scipy's product computes (from 0.0, so a -0.0 product is 0.0), without its
    per-call overhead, which the hypergradient pays several times per evaluation. Where the entries form a few runs
    of consecutive rows reading consecutive columns (forward or reversed) with one value each (signals lifted, sliced
    or read backwards), the runs are copied as slices, not gathered entry by entry."""

    def __init__(self, J: sp.csr_matrix) -> None:
        self.shape = J.shape
        self._rows = np.flatnonzero(np.diff(J.indptr))
        self._full = self._rows.size == J.shape[0]  # every row has its entry: no scatter
        self._columns, self._values = J.indices.copy(), J.data.copy()
        self._runs = _runs(self._rows, self._columns, self._values)

    @classmethod
    def of(cls, J: sp.csr_matrix) -> Gather | sp.csr_matrix:
        """J as a Gather where every row has at most one nonzero, else J itself."""
        return cls(J) if np.all(np.diff(J.indptr) <= 1) else J

    def sparse(self) -> sp.csr_matrix:
        """J as a scipy CSR matrix."""
        return sp.csr_matrix((self._values, (self._rows, self._columns)), shape=self.shape)

    def __matmul__(self, v: np.ndarray) -> np.ndarray:
        """J v for a vector v or the columns of a matrix v."""
        if v.ndim not in (1, 2):
            raise ValueError(f"Gather applies to vectors and matrices, got an array of shape {v.shape}")
        if self._runs is not None:
            runs, value = self._runs
            out = (np.empty if self._full else np.zeros)((self.shape[0],) + v.shape[1:])
            for rows, columns, scale in runs:
                if value is None and scale != 1.0:
                    np.multiply(v[columns], scale, out=out[rows])
                else:
                    out[rows] = v[columns]
            if value is not None and value != 1.0:
                out *= value
            out += 0.0  # as scipy's sum from 0.0
            return out
        product = self._values * v[self._columns] if v.ndim == 1 else self._values[:, None] * v[self._columns]
        product += 0.0  # as scipy's sum from 0.0
        if self._full:
            return product
        out = np.zeros((self.shape[0],) + v.shape[1:])
        out[self._rows] = product
        return out


MAX_RUNS = 16
"""A Gather with at most this many runs (and at least 32 entries per run on average) copies them as slices."""


def _runs(rows: np.ndarray, columns: np.ndarray,
          values: np.ndarray) -> tuple[list[tuple[slice, slice, float]], float | None] | None:
    """(runs, value): (rows, columns, scale) slices covering the entries, runs of consecutive rows whose columns step by
    +1 or -1 with one scale, and the scale of all of them where they share one (else None); None where there are more
    than MAX_RUNS runs or they are short (the gather is cheaper)."""
    if rows.size == 0:
        return None
    step = np.diff(columns)
    joins = (np.diff(rows) == 1) & (np.abs(step) == 1) & (values[1:] == values[:-1])
    joins[1:] &= ~joins[:-1] | (step[1:] == step[:-1])  # a run keeps one direction
    starts = np.concatenate([[0], np.flatnonzero(~joins) + 1])
    if starts.size > MAX_RUNS or rows.size < 32 * starts.size:
        return None
    runs = []
    for a, b in zip(starts, np.append(starts[1:], rows.size)):
        c0, c1 = int(columns[a]), int(columns[b - 1])
        direction = 1 if c1 >= c0 else -1
        stop = c1 + direction
        runs.append((slice(int(rows[a]), int(rows[b - 1]) + 1),
                     slice(c0, None if stop < 0 else stop, direction), float(values[a])))
    shared = {scale for _, _, scale in runs}
    return runs, (shared.pop() if len(shared) == 1 else None)


def jacobian_nonzeros_exceed(expr: ca.SX, x: ca.SX, limit: float, sample: int = 32) -> bool:
    """Whether d expr / dx has more than `limit` nonzeros. Judged first on `sample` evenly spaced columns (their count
    scaled to all columns): an estimate above twice the limit refuses without forming the whole pattern, which for a
    recursion over N samples (a dense lower triangle) costs O(N^2) time and memory; otherwise the exact count."""
    n = int(x.numel())
    if n > sample:
        columns = np.unique(np.linspace(0, n - 1, sample).round().astype(int))
        seen = ca.jacobian_sparsity(expr, ca.vertcat(*[x[int(i)] for i in columns])).nnz()
        if seen * n / columns.size > 2 * limit:
            return True
    return ca.jacobian_sparsity(expr, x).nnz() > limit


def affine_in(expr: ca.SX, x: ca.SX, fixed: ca.SX) -> tuple[Gather | sp.csr_matrix, ca.SX,
                                                            Gather | sp.csr_matrix] | None:
    """(J, b, J') with expr = J x + b, J sparse and numeric (a Gather where it is one, both ways; reading neither x
    nor the symbols `fixed`, the parameters), b an expression in `fixed` alone, when expr is affine in x that way
    (signals the leader moves, the clean signals parameters); else None."""
    jac = ca.jacobian(expr, x)
    if ca.depends_on(jac, x) or ca.depends_on(jac, fixed):
        return None
    J = sp.csr_matrix(ca.evalf(jac).sparse())
    return Gather.of(J), ca.substitute(expr, x, ca.DM.zeros(int(x.numel()))), Gather.of(J.T.tocsr())


def affine_parts(expr: ca.SX, x: ca.SX, fixed: ca.SX) -> tuple[Gather | sp.csr_matrix, np.ndarray,
                                                               Gather | sp.csr_matrix] | None:
    """(J, b, J') with expr = J x + b, J sparse (a Gather where it is one), when expr reads none of the symbols `fixed`
    (parameters) and is affine in x (signals the leader moves, sliced, shifted or mapped): one sparse product each way
    instead of a sweep; else None."""
    parts = None if ca.depends_on(expr, fixed) else affine_in(expr, x, fixed)
    if parts is None:
        return None
    J, offset, Jt = parts
    return J, np.asarray(ca.evalf(offset), dtype=float).ravel(), Jt


class Operator:
    """A numeric matrix or linear operator with products by columns: apply (A X) and adjoint (A' Y). kind: "dense",
    "sparse", "operator" (a LinearOperator) or "toeplitz" (a dense matrix applied as a ToeplitzBank of one, `bank`)."""

    def __init__(self, matrix: Any, what: str) -> None:
        refuse_complex(matrix, f"{what}: the matrix")
        if isinstance(matrix, LinearOperator):
            self.kind, self.data = "operator", matrix
        elif sp.issparse(matrix):
            self.kind, self.data = "sparse", sp.csr_matrix(matrix, dtype=float)
        else:
            try:
                arr = np.asarray(matrix, dtype=float)
            except (TypeError, ValueError):
                raise ModelError(f"{what}: expected a numeric matrix (numpy, scipy.sparse) or a scipy LinearOperator, "
                                 f"got {type(matrix).__name__}") from None
            if arr.ndim != 2:
                raise ModelError(f"{what}: expected a 2-D matrix, got an array of shape {arr.shape}")
            self.kind, self.data = "dense", np.ascontiguousarray(arr)
        self.shape = tuple(int(n) for n in self.data.shape)
        if min(self.shape) < 1:
            raise ModelError(f"{what}: the matrix has shape {self.shape}; it needs at least one row and column")
        values = self.data.data if self.kind == "sparse" else self.data if self.kind == "dense" else np.zeros(0)
        if not np.all(np.isfinite(values)):
            raise InvalidData(f"{what}: the matrix contains NaN or inf; clean the data first")
        split = toeplitz_split(self.data) if self.kind == "dense" else None
        if split is not None:
            self.kind, self.bank = "toeplitz", ToeplitzBank([split], self.shape[1])
        self.what = what
        if self.kind == "operator":  # its code is the user's: one product each way now, so a broken one fails here
            self.apply(np.ones(self.shape[1]))
            self.adjoint(np.ones(self.shape[0]))

    @classmethod
    def stacked(cls, operators: list["Operator"]) -> "Operator | ToeplitzBank | None":
        """[A_1; A_2; ...] with apply and adjoint, for operators that are all dense or all toeplitz with equal column
        counts (a filter bank applied to one signal: one product each way), else None."""
        kinds = {op.kind for op in operators}
        if len(kinds) != 1 or len({op.shape[1] for op in operators}) != 1:
            return None
        if kinds == {"toeplitz"}:
            return ToeplitzBank.stack([op.bank for op in operators])
        if kinds != {"dense"}:
            return None
        out = cls.__new__(cls)
        out.kind, out.data = "dense", np.vstack([op.data for op in operators])
        out.shape = out.data.shape
        return out

    def apply(self, X: np.ndarray) -> np.ndarray:
        """A X (X of shape (n,) or (n, k))."""
        if self.kind == "toeplitz":
            return self.bank.apply(X)
        if self.kind == "operator":
            return self._checked(lambda: self.data.matmat(X) if X.ndim == 2 else self.data.matvec(X), X,
                                 (self.shape[0],) + X.shape[1:], "matvec")
        return self.data @ X

    def _checked(self, product: Any, arg: np.ndarray, shape: tuple[int, ...], which: str) -> np.ndarray:
        """A LinearOperator's product (the user's code) of `arg` as a real array of `shape`, finite where `arg` is;
        InvalidData otherwise."""
        try:
            out = product()
        except ValueError as exc:  # scipy's own shape check of what the user's code returned
            raise InvalidData(f"{self.what}: the LinearOperator's {which} failed ({exc}); it must return an array of "
                              f"shape {shape}") from None
        refuse_complex(out, f"{self.what}: the LinearOperator's {which} output")
        out = np.asarray(out, dtype=float).reshape(shape) if np.size(out) == math.prod(shape) else None
        if out is None:
            raise InvalidData(f"{self.what}: the LinearOperator's {which} returned the wrong number of entries; it "
                              f"must return an array of shape {shape}")
        if not np.all(np.isfinite(out)) and np.all(np.isfinite(arg)):
            raise InvalidData(f"{self.what}: the LinearOperator's {which} returned NaN or inf of finite input")
        return out

    def adjoint(self, Y: np.ndarray) -> np.ndarray:
        """A' Y (Y of shape (m,) or (m, k))."""
        if self.kind == "operator":
            return self._checked(lambda: self.data.rmatmat(Y) if Y.ndim == 2 else self.data.rmatvec(Y), Y,
                                 (self.shape[1],) + Y.shape[1:], "rmatvec")
        if self.kind == "toeplitz":
            return self.bank.adjoint(Y)
        return self.data.T @ Y

    def dense(self, what: str) -> np.ndarray:
        """The matrix as a dense array (an operator is applied to the identity, up to
        defaults["linear_maps.dense_limit"] entries)."""
        if self.kind in ("dense", "toeplitz"):
            return self.data
        if self.kind == "sparse":
            return self.data.toarray()
        if self.shape[0] * self.shape[1] > param("linear_maps.dense_limit"):
            raise ModelError(f"{what} is a LinearOperator of shape {self.shape}, too large to form as a matrix for the "
                             "KKT reformulation; use method='hypergradient', which applies it by its products")
        return self.apply(np.eye(self.shape[1]))

    def casadi(self, what: str) -> ca.DM:
        """The matrix as a CasADi DM with its structural zeros (for the expanded, KKT form)."""
        return ca.DM(sp.csc_matrix(self.data) if self.kind == "sparse" else sp.csc_matrix(self.dense(what)))


@dataclass(frozen=True)
class Image:
    """z = A @ arg: a linear map applied to an expression of the upper variables and parameters (level "upper": data
    the leader moves) or to a linear expression of the lower variables (level "lower": a least-squares learner's
    regressor); z is a symbol of the shape of the product, arg the expression (columns mapped one by one)."""

    name: str
    sym: ca.SX
    operator: Operator
    arg: ca.SX
    level: str = "upper"


class LinearMap:
    """A numeric matrix or linear operator declared on a problem (BilevelProblem.linear_map): `T @ expr` returns a
    symbol for the product, to write with; the product is computed numerically, never expanded into the graph."""

    def __init__(self, problem: "BilevelProblem", matrix: Any, name: str) -> None:
        self.problem, self.name = problem, name
        self.operator = Operator(matrix, f"linear_map({name!r})")
        self.shape = self.operator.shape
        self._count = 0

    def __matmul__(self, expr: Any) -> ca.SX:
        from .model import _expression

        arg = _expression(expr, f"linear_map({self.name!r}) @ ...", "a CasADi expression of upper variables")
        if arg.size1() != self.shape[1]:
            raise ModelError(f"linear_map({self.name!r}) has {self.shape[1]} columns but the expression has "
                             f"{arg.size1()} rows; the product needs equal sizes")
        name = f"{self.name}_{self._count}"
        self._count += 1
        return self.problem._image(name, self.operator, arg)

    def __repr__(self) -> str:
        return f"LinearMap({self.name!r}, shape={self.shape}, {self.operator.kind})"


@dataclass(frozen=True)
class Images:
    """A problem's images stacked: z (column-major, image by image), and z(x) = [A_i arg_i(x)] with its adjoint."""

    items: tuple[Image, ...]

    @property
    def sym(self) -> ca.SX:
        return ca.vertcat(*[ca.vec(i.sym) for i in self.items])

    @property
    def size(self) -> int:
        return sum(int(i.sym.numel()) for i in self.items)
