"""A large least squares kept in residual form: f = 1/2 ||r(x, y)||^2 + c(x), r = C(x) y - d(x) affine in y.

Written as a sum of squares (`ca.sumsqr(target - ca.mtimes(Phi, theta))`, ridge terms included), a learner with
many rows has a symbolic Hessian C'C of rows x n_y^2 nodes: building and differentiating it dominated the solve of
identification problems (T = 10,000 rows, 64 Hessian entries). This kind evaluates C(x) and d(x) (one sparse product
where they are affine in x, as for signals the leader moves; else one sweep of the size of r) and forms C'C by BLAS;
the implicit derivative's x-adjoint is the transposed product, or one reverse sweep through r and C v.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import casadi as ca
import numpy as np
import scipy.sparse as sp

from ..defaults import param
from ..errors import BilevelError
from ..linear_maps import Gather, affine_in, jacobian_nonzeros_exceed
from ..parameters import CompiledFunction, ParameterSet, scalar
from .base import ExpressionLower, KKTValues, LowerLevel, LowerSolution
from .least_squares import LeastSquaresLower, factor_solve, hessian_factor, sum_of_squares


@dataclass(frozen=True)
class NumericSquares:
    """f(y) = sign * (1/2 ||A y + r0||^2 + c) with numeric A (dense, or sparse when mostly zeros), r0 and c."""

    sign: float
    A: np.ndarray | sp.csr_matrix
    r0: np.ndarray
    c: float

    def __call__(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f(y) as a 1 x 1 array and its gradient as a column."""
        r = self.A @ y + self.r0
        return np.array([[self.sign * (0.5 * float(r @ r) + self.c)]]), (self.sign * (self.A.T @ r))[:, None]


def numeric_squares(f: ca.SX, y: ca.SX, others: ca.SX) -> NumericSquares | None:
    """f as NumericSquares when it reads none of `others` and is (minus) a sum of squares of expressions affine in y
    (sum_of_squares) with at least defaults["residual.numeric_squares_size"] coefficients, else None."""
    if ca.depends_on(f, others):
        return None
    for sign in (1.0, -1.0):
        form = sum_of_squares(sign * f, y)
        if form is not None:
            r, c = form
            jac = ca.jacobian(r, y)
            if jac.nnz() < param("residual.numeric_squares_size"):
                return None
            A = sp.csr_matrix(ca.evalf(jac).sparse())
            A = A if jac.nnz() < param("residual.sparse_squares") * jac.numel() else A.toarray()
            r0 = np.asarray(ca.evalf(ca.substitute(r, y, ca.DM.zeros(int(y.numel())))), dtype=float).ravel()
            return NumericSquares(sign, A, r0, float(ca.evalf(c)))
    return None


class MovingAdjoint:
    """J'[vec(a v' + y b'); -b] by columns of V and B for affine data [vec C(x); d(x)] = J x + c, C (rows x n_y),
    from J' (n_x x (rows n_y + rows)): with C(x) = C0 + sum_i x_i E_i and d likewise, it is M1(a) V + M2(y) B with
    M1(a)_i = (E_i'a)' and M2(y)_i = (E_i y - d_i)' (d_i = dd/dx_i), sparse on the entries that move with x. Their
    patterns are fixed: each call sums the moving entries' weights into them (a learner's C is mostly structural
    zeros, e.g. block diagonal over its outputs, so no seed of the size of C is formed). Where J' is a Gather and at
    least half of C moves (signals lifted through linear maps) the seeds are formed on all of [vec C; d] and
    gathered: contiguous products and one gather cost half the sums."""

    def __init__(self, Jt: Gather | sp.csr_matrix, rows: int, n_y: int) -> None:
        coo = (Jt.sparse() if isinstance(Jt, Gather) else sp.csr_matrix(Jt)).tocoo()
        cut = rows * n_y
        in_C = coo.col < cut
        self._seeded = Jt if isinstance(Jt, Gather) and 2 * np.count_nonzero(in_C) >= cut else None
        if self._seeded is not None:
            return
        self._values_C, self._x_C = coo.data[in_C], coo.row[in_C]
        self._p, self._q = coo.col[in_C] % rows, coo.col[in_C] // rows
        self._minus_d = -coo.data[~in_C]
        self._M1, self._slots1 = self._pattern(self._x_C, self._q, Jt.shape[0], n_y)
        self._M2, self._slots2 = self._pattern(np.concatenate([self._x_C, coo.row[~in_C]]),
                                               np.concatenate([self._p, coo.col[~in_C] - cut]), Jt.shape[0], rows)

    @staticmethod
    def _pattern(i: np.ndarray, j: np.ndarray, n: int, m: int) -> tuple[sp.csr_matrix, np.ndarray]:
        """An n x m CSR matrix with the distinct (i, j) pairs as its entries, and each pair's index in its data."""
        keys, slots = np.unique(i.astype(np.int64) * m + j, return_inverse=True)
        indptr = np.searchsorted(keys // m, np.arange(n + 1))
        return sp.csr_matrix((np.zeros(keys.size), keys % m, indptr), shape=(n, m)), slots.ravel()

    def __call__(self, y: np.ndarray, V: np.ndarray, a: np.ndarray, B: np.ndarray) -> np.ndarray:
        """M1(a) V + M2(y) B (V: n_y x k, B: rows x k)."""
        if self._seeded is not None:
            return self._from_seeds(y, V, a, B)
        M1, M2 = self._M1, self._M2
        M1.data[:] = np.bincount(self._slots1, self._values_C * a[self._p], minlength=M1.data.size)
        M2.data[:] = np.bincount(self._slots2, np.concatenate([self._values_C * y[self._q], self._minus_d]),
                                 minlength=M2.data.size)
        return M1 @ V + M2 @ B

    def _from_seeds(self, y: np.ndarray, V: np.ndarray, a: np.ndarray, B: np.ndarray) -> np.ndarray:
        """J'[vec(V_j a' + y B_j'); -B_j] by columns, the seeds on all of [vec C; d] (column-major vec C)."""
        if V.shape[1] == 1:  # one column: outer products of vectors
            seed = np.empty(a.size * V.shape[0] + a.size)
            np.add(np.outer(V[:, 0], a), np.outer(y, B[:, 0]), out=seed[:-a.size].reshape(V.shape[0], a.size))
            np.negative(B[:, 0], out=seed[-a.size:])
            return (self._seeded @ seed)[:, None]
        seed = np.empty((a.size * V.shape[0] + a.size, V.shape[1]))
        block = seed[:-a.size].reshape(V.shape[0], a.size, V.shape[1])
        np.multiply(V[:, None, :], a[None, :, None], out=block)
        block += y[:, None, None] * B[None, :, :]
        np.negative(B, out=seed[-a.size:])
        return self._seeded @ seed


class BlockGram:
    """C'C for a C of a fixed sparsity whose rows fall into groups of one column support each, the supports disjoint
    (a learner's C over its outputs and its separate fits: C'C is block diagonal over the groups): one batched product
    of the groups' dense blocks, padded with a structural zero of C. `of` builds it, or gives None where the pattern
    has no such groups or they would not save three quarters of the dense product's work."""

    def __init__(self, flat: np.ndarray, source: np.ndarray, target: np.ndarray, n: int) -> None:
        self._flat, self._source, self._target, self._n = flat, source, target, n

    @classmethod
    def of(cls, sparsity: ca.Sparsity) -> BlockGram | None:
        """The BlockGram of C's pattern, or None where the class docstring says."""
        m, n = sparsity.shape
        rows, cols = (np.asarray(v, dtype=int) for v in sparsity.get_triplet())
        mask = np.zeros((m, n), dtype=bool)
        mask[rows, cols] = True
        supports, group = np.unique(mask, axis=0, return_inverse=True)
        members = [np.flatnonzero(group.ravel() == g) for g in range(len(supports)) if supports[g].any()]
        supports = supports[supports.any(axis=1)]
        if len(supports) < 2 or np.any(supports.sum(axis=0) > 1):
            return None
        size, width = max(len(r) for r in members), int(supports.sum(axis=1).max())
        if 4 * len(members) * size * width ** 2 > m * n ** 2:
            return None
        flat = np.full((len(members), size, width), np.flatnonzero(~mask.ravel(order="F"))[0])
        source, target = [], []
        for g, (r, support) in enumerate(zip(members, supports)):
            c = np.flatnonzero(support)
            flat[g, :r.size, :c.size] = r[:, None] + m * c[None, :]
            source.append(g * width ** 2 + (np.arange(c.size)[:, None] * width + np.arange(c.size)).ravel())
            target.append((c[:, None] * n + c).ravel())
        return cls(flat, np.concatenate(source), np.concatenate(target), n)

    def __call__(self, C: np.ndarray) -> np.ndarray:
        """C'C (C of the pattern, any memory order)."""
        A = np.take(C.ravel(order="F"), self._flat)
        P = np.zeros(self._n * self._n)
        P[self._target] = np.matmul(A.transpose(0, 2, 1), A).ravel()[self._source]
        return P.reshape(self._n, self._n)


@dataclass
class ResidualLeastSquares(LowerLevel):
    """min_y 1/2 ||C(x) y - d(x)||^2 + c(x), C(x)'C(x) positive definite; y* by Cholesky of C'C (a QR solve in the
    independent re-solve)."""

    x: ca.SX
    y: ca.SX
    f: ca.SX
    r: ca.SX
    c: ca.SX
    params: ParameterSet = field(default_factory=ParameterSet, repr=False)
    psd: list = field(default_factory=list)
    g_names: list[str] = field(default_factory=list)
    h_names: list[str] = field(default_factory=list)
    psd_names: list[str] = field(default_factory=list)
    kind = "least-squares"

    @classmethod
    def recognize(cls, x: ca.SX, y: ca.SX, f: ca.SX, x_samples: list[np.ndarray],
                  params: ParameterSet) -> "ResidualLeastSquares | None":
        """The residual form of an unconstrained lower objective when f is a sum of squares of expressions affine in y
        with more than defaults["residual.form_size"] Hessian terms and C'C positive definite at the samples; else
        None."""
        form = sum_of_squares(f, y)
        if form is None or int(form[0].numel()) * int(y.numel()) ** 2 <= param("residual.form_size"):
            return None
        low = cls(x, y, f, *form, params=params)
        check = params.function("residual_check", [x, y], [f])
        rng = np.random.default_rng(0)
        for xs in x_samples:
            ys = rng.standard_normal(low.n_y)
            value = float(np.asarray(check(xs, ys)).ravel()[0])
            if not np.isclose(low.evaluate(xs, ys)[0], value, rtol=1e-9, atol=1e-12 * (1 + abs(value))):
                return None  # the decomposition does not reproduce f: leave it to the expression kinds
            try:
                hessian_factor(low.gram(xs))
            except (ValueError, np.linalg.LinAlgError, BilevelError):
                return None
        return low

    def __post_init__(self) -> None:
        zero = ca.DM.zeros(self.n_y)
        self.C_expr = ca.jacobian(self.r, self.y)
        self.d_expr = -ca.substitute(self.r, self.y, zero)
        self.n_r = int(self.r.numel())
        """Number of residual rows (read at every evaluation: kept, not recounted)."""
        self._affine = self._affine_data(ca.vertcat(ca.vec(self.C_expr), self.d_expr))
        moves = ca.depends_on(self.c, self.x) or ca.depends_on(self.c, self.params.sym)
        self._c = self.params.function("residual_c", [self.x], [self.c]) if moves else float(ca.evalf(self.c))
        """c(x): a constant, or its function (the affine path evaluates it alone, not the sweep of C and d)."""
        self._offset_value: tuple[int, np.ndarray] | None = None
        self._last: tuple[tuple[bytes, int], tuple[np.ndarray, np.ndarray, float]] | None = None
        self._seen: np.ndarray | None = None
        self._gram: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
        """(C, C'C, its Cholesky factor or None) at the last point: the solve and the implicit derivative share them."""

    @cached_property
    def _data(self) -> CompiledFunction:
        """x -> C(x), d(x), c(x), one sweep of the expressions."""
        return self.params.function("residual_data", [self.x], [self.C_expr, self.d_expr, self.c])

    @cached_property
    def _adjoint(self) -> CompiledFunction:
        """(x, y, v, a, b) -> d/dx of a'C(x)v + b'r(x, y), one reverse sweep."""
        v, a, b = ca.SX.sym("v", self.n_y), ca.SX.sym("a", self.n_r), ca.SX.sym("b", self.n_r)
        return self.params.function("residual_adjoint", [self.x, self.y, v, a, b],
                                    [ca.jtimes(ca.mtimes(self.C_expr, v), self.x, a, True)
                                     + ca.jtimes(self.r, self.x, b, True)])

    def _affine_data(self, data: ca.SX) -> tuple[Gather | sp.csr_matrix, np.ndarray | CompiledFunction,
                                                Gather | sp.csr_matrix] | None:
        """(J, b, J') with [vec C(x); d(x)] = J x + b when the data are affine in x with a J that reads no parameters
        and has at most defaults["residual.affine_fill"] nonzeros per operation of their expressions (signals the
        leader moves, sliced or mapped; b, the clean signals, may be parameters: then b is their function, evaluated
        once per parameter revision): C and d cost one sparse product, their x-adjoint one transposed one; else None
        (the expressions are evaluated)."""
        if jacobian_nonzeros_exceed(data, self.x, param("residual.affine_fill") * self._data.n_instructions()):
            return None  # e.g. a recursive filter: a few operations per sample, a dense lower-triangular Jacobian
        parts = affine_in(data, self.x, self.params.sym)
        if parts is None:
            return None
        J, b, Jt = parts
        if ca.depends_on(b, self.params.sym):
            return J, self.params.function("residual_offset", [self.x], [b]), Jt  # b ignores x: any x will do
        return J, np.asarray(ca.evalf(b), dtype=float).ravel(), Jt

    def _offset(self, x: np.ndarray) -> np.ndarray:
        """b of the affine data at the current parameter values (kept per revision)."""
        b = self._affine[1]
        if isinstance(b, np.ndarray):
            return b
        revision = self.params.revision
        if self._offset_value is None or self._offset_value[0] != revision:
            self._offset_value = (revision, np.asarray(b(x), dtype=float).ravel())
        return self._offset_value[1]

    def _x_adjoint(self, x: np.ndarray, y: np.ndarray, v: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """d/dx of a'C(x)v + b'(C(x)y - d(x))."""
        if self._affine is None:
            return np.asarray(self._adjoint(x, y, v, a, b), dtype=float).ravel()
        return self._moving(y, v[:, None], a, b[:, None]).ravel()

    @cached_property
    def _moving(self) -> MovingAdjoint:
        """The x-adjoint of affine data, (y, V, a, B) -> d/dx of a'C(x)v_j + b_j'(C(x)y - d(x)) by columns j
        (MovingAdjoint)."""
        return MovingAdjoint(self._affine[2], self.n_r, self.n_y)

    @cached_property
    def fixed(self) -> bool:
        return not ca.depends_on(self.r, self.x) and not ca.depends_on(self.c, self.x)

    def data(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """C(x), d(x) and c(x) (the last point's are kept: one sweep serves the calls at a point; a read-only x, as
        a lifted point, is known again by identity)."""
        revision = self.params.revision  # the data may read parameters
        if x is self._seen and self._last[0][1] == revision:
            return self._last[1]
        given, x = x, np.asarray(x, dtype=float).ravel()
        key = (x.tobytes(), revision)
        if self._last is None or self._last[0] != key:
            if self._affine is not None:
                v, m = self._affine[0] @ x + self._offset(x), self.n_r
                C, d = v[:m * self.n_y].reshape((m, self.n_y), order="F"), v[m * self.n_y:]
                c = self._c if isinstance(self._c, float) else scalar(self._c(x))
            else:
                C, d, c = self._data(x)
            self._last = (key, (np.asarray(C, dtype=float).reshape(-1, self.n_y), np.asarray(d, dtype=float).ravel(),
                                float(np.asarray(c).ravel()[0])))
        self._seen = given if isinstance(given, np.ndarray) and not given.flags.writeable else None
        return self._last[1]

    def gram(self, x: np.ndarray) -> np.ndarray:
        """The Hessian C(x)'C(x) (the last point's kept, known by its C): by blocks where C's pattern has them
        (BlockGram), else by BLAS."""
        C = self.data(x)[0]
        if self._gram is None or self._gram[0] is not C:
            self._gram = (C, C.T @ C if self._block_gram is None else self._block_gram(C), None)
        return self._gram[1]

    @cached_property
    def _block_gram(self) -> BlockGram | None:
        return BlockGram.of(self.C_expr.sparsity())

    def _factored(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """C(x)'C(x) and its Cholesky factor (the last point's kept); raises if it is not positive definite."""
        P = self.gram(x)
        if self._gram[2] is None:
            self._gram = (self._gram[0], P, hessian_factor(P))
        return P, self._gram[2]

    def gram_adjoint(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """d(v'C(x)'C(x)v)/dx = 2 (d(C v)/dx)'(C v)."""
        Cv = self.data(x)[0] @ v
        return 2.0 * self._x_adjoint(x, np.zeros(self.n_y), v, Cv, np.zeros_like(Cv))

    def moving_hessian(self) -> tuple[Callable[[np.ndarray], np.ndarray],
                                      Callable[[np.ndarray, np.ndarray], np.ndarray]] | None:
        """(gram, gram_adjoint): P = C'C formed numerically, where C moves with x."""
        return (self.gram, self.gram_adjoint) if ca.depends_on(self.C_expr, self.x) else None

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, list[np.ndarray]]:
        C, d, c = self.data(x)
        r = C @ y - d
        return 0.5 * float(r @ r) + c, np.zeros(0), np.zeros(0), []

    def derivatives(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        C, d, _ = self.data(x)
        return C.T @ (C @ y - d), np.zeros((0, self.n_y)), np.zeros((0, self.n_y)), []

    def hessian(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.gram(x)

    def kkt_values(self, x: np.ndarray, sol: LowerSolution) -> KKTValues:
        S = self.derivatives(x, sol.y)[0]
        values = KKTValues.unconstrained(*self._factored(x))
        return values._replace(stationarity=S[:, None])

    def kkt_x_adjoint(self, x: np.ndarray, sol: LowerSolution, v_s: np.ndarray, v_g: np.ndarray,
                      v_h: np.ndarray) -> np.ndarray:
        """d/dx of v'C'(C y - d) = (d(C v)/dx)'r + (dr/dx)'(C v), one reverse sweep."""
        C, d, _ = self.data(x)
        return self._x_adjoint(x, sol.y, v_s, C @ sol.y - d, C @ v_s)

    def kkt_x_adjoint_columns(self, x: np.ndarray, sol: LowerSolution, V_s: np.ndarray, V_g: np.ndarray,
                              V_h: np.ndarray) -> np.ndarray:
        """Where the data are affine in x: two sparse products for all columns (MovingAdjoint, a = r = C y - d and
        b_j = C v_j); else one reverse sweep per column."""
        if self._affine is None or not V_s.shape[1]:
            return super().kkt_x_adjoint_columns(x, sol, V_s, V_g, V_h)
        C, d, _ = self.data(x)
        return self._moving(sol.y, V_s, C @ sol.y - d, C @ V_s)

    def kkt_solve(self, x: np.ndarray, K: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
        return factor_solve(hessian_factor(K), rhs), K.shape[0]

    def solve(self, x: np.ndarray) -> LowerSolution:
        """Closed form by a Cholesky factorization of C'C; raises if it is not positive definite."""
        x = self.check_point(x)
        C, d, c = self.data(x)
        y = factor_solve(self._factored(x)[1], C.T @ d)
        return LowerSolution(y, self.evaluate(x, y)[0], np.zeros(0), np.zeros(0), [], "optimal", "closed-form")

    def reference_solve(self, x: np.ndarray) -> LowerSolution:
        """The certificate's re-solve: least squares by LAPACK's SVD-based lstsq on C, d (not the normal equations)."""
        x = self.check_point(x)
        C, d, _ = self.data(x)
        y = np.linalg.lstsq(C, d, rcond=None)[0]
        return LowerSolution(y, self.evaluate(x, y)[0], np.zeros(0), np.zeros(0), [], "optimal", "lstsq (SVD)")

    def symbolic(self) -> ExpressionLower:
        """The expression form (its Hessian built symbolically), for the KKT reformulation."""
        return self._symbolic

    @cached_property
    def _symbolic(self) -> ExpressionLower:
        return LeastSquaresLower(self.x, self.y, self.f, ca.SX(0, 1), ca.SX(0, 1), [], [], [], [], None, self.params)
