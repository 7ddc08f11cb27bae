"""Dense matrices that are Toeplitz up to a few entries are applied by FFT convolution (bilevel.toeplitz): the
products and adjoint products equal the dense ones, other matrices stay dense, and a VRFT declaration with the
regressor's filter matrices gives the values and hypergradients of the same declaration applied by BLAS."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import bilevel as bl
import bilevel.toeplitz as toeplitz
from bilevel.linear_maps import Operator
from bilevel.lower.images import ImageLower
from bilevel.problems.vrft_instance import attack_instance
from bilevel.solvers.engine.prepared import prepare
from bilevel.toeplitz import ToeplitzBank, toeplitz_split

from .test_linear_maps import _phi_and_gradient, _vrft


def _toeplitz(t: np.ndarray, m: int, n: int) -> np.ndarray:
    return np.array([[t[i - j + n - 1] for j in range(n)] for i in range(m)])


@pytest.mark.parametrize("m, n", [(300, 400), (400, 300)])
def test_split_finds_the_diagonals_and_the_corrections_at_either_corner(m: int, n: int) -> None:
    rng = np.random.default_rng(0)
    t = rng.standard_normal(m + n - 1)
    A = _toeplitz(t, m, n)
    A[:5, :2] += 1.0  # boundary columns of a filter matrix: read the diagonals off the other corner
    t_found, R, _ = toeplitz_split(A)
    assert np.array_equal(t_found, t) and R.nnz == 10
    B = _toeplitz(t, m, n)
    B[-3:, -4:] = 0.0  # a corrected bottom-right corner: read off the top-left
    t_found, R, _ = toeplitz_split(B)
    assert np.array_equal(t_found, t) and R.nnz == 12
    assert toeplitz_split(rng.standard_normal((m, n))) is None
    assert toeplitz_split(A[:100, :100]) is None  # too small to gain
    assert toeplitz_split(_toeplitz(rng.standard_normal(7_009), 10, 7_000)) is None  # too thin


@pytest.mark.parametrize("rows, boundary", [((260, 300), "columns"), ((280, 280), "columns"), ((260, 300), "rows")])
def test_bank_products_equal_the_dense_ones(rows: tuple[int, int], boundary: str) -> None:
    rng = np.random.default_rng(1)
    mats = []
    for m in rows:
        A = _toeplitz(rng.standard_normal(m + 256 - 1), m, 256)
        if boundary == "columns":  # three dense boundary columns (products by a dense block)
            A[:, :3] = rng.standard_normal((m, 3))
        else:  # two boundary rows (products by the sparse correction)
            A[:2] = rng.standard_normal((2, 256))
        mats.append(A)
    bank = ToeplitzBank([toeplitz_split(A) for A in mats], 256)
    S = np.vstack(mats)
    x, X = rng.standard_normal(256), rng.standard_normal((256, 3))
    g, G = rng.standard_normal(S.shape[0]), rng.standard_normal((S.shape[0], 2))
    for got, want in ((bank.apply(x), S @ x), (bank.apply(X), S @ X), (bank.adjoint(g), S.T @ g),
                      (bank.adjoint(G), S.T @ G)):
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()


def test_a_bank_of_delays_of_one_filter_shares_its_convolution() -> None:
    """Lagged copies of one filter matrix (a regressor's columns: delays of 0, 1, 3 and -2 samples), each with its own
    boundary columns and the delay's first rows, are applied by one convolution read at each delay: the products equal
    the dense ones; kernels that are no delays of the first keep one convolution each."""
    rng = np.random.default_rng(4)
    m, n = 300, 256
    t = rng.standard_normal(m + n - 1 + 8)
    mats = []
    for lag in (0, 1, 3, -2):
        A = _toeplitz(t[4 - lag:4 - lag + m + n - 1], m, n)
        A[:, :3] = rng.standard_normal((m, 3))
        mats.append(A)
    bank = ToeplitzBank([toeplitz_split(A) for A in mats], n)
    assert bank._delays is not None and bank.spectra.shape[0] == 1
    S = np.vstack(mats)
    x, X = rng.standard_normal(n), rng.standard_normal((n, 3))
    g, G = rng.standard_normal(S.shape[0]), rng.standard_normal((S.shape[0], 2))
    for got, want in ((bank.apply(x), S @ x), (bank.apply(X), S @ X), (bank.adjoint(g), S.T @ g),
                      (bank.adjoint(G), S.T @ G)):
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    other = [_toeplitz(rng.standard_normal(m + n - 1), m, n) for _ in range(2)]
    assert ToeplitzBank([toeplitz_split(A) for A in other], n)._delays is None


def test_vrft_filter_matrices_are_convolutions_with_the_dense_values_and_hypergradients(monkeypatch) -> None:
    N = 256
    atk = attack_instance("maxmin", "B", 0.1, 0.057, 0, N)
    for T in atk.setting.regressor.dense(N):
        op = Operator(T, "T")
        assert op.kind == "toeplitz"
        assert set(op.bank.correction.nonzero()[1]) <= {0, 1, 2}  # the virtual reference's advance: 3 columns
    x = np.random.default_rng(3).standard_normal(2 * N) * 0.05
    p = _vrft(0, N, np.asarray)
    lift = prepare(p).canon.lower.lift
    assert isinstance(prepare(p).canon.lower, ImageLower) and isinstance(lift._stacked[0], ToeplitzBank)
    phi, g = _phi_and_gradient(p, x)
    monkeypatch.setattr(toeplitz, "MIN_ENTRIES", np.inf)
    phi0, g0 = _phi_and_gradient(_vrft(0, N, np.asarray), x)
    assert phi == pytest.approx(phi0, rel=1e-11)
    assert np.abs(g - g0).max() <= 1e-9 * np.abs(g0).max()


# -- recognition trusts each entry's own scale (issue 44, item 2) -------------------------------------------------------
def _engine_least_squares(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, str]:
    """The engine's w = argmin ||A w - b|| (A declared with linear_map, solved by the lower level at x = 1) and the
    kind the linear map took."""
    p = bl.BilevelProblem("ls")
    x = p.upper_variable("x", lb=0, ub=1)
    w = p.lower_variable("w", A.shape[1])
    T = p.linear_map(A)
    p.minimize_lower(ca.sumsqr(T @ w - b * x))
    p.minimize_upper(ca.sumsqr(w))
    sol = prepare(p).canon.lower.solve(np.array([1.0]))
    return np.asarray(sol.y, dtype=float).ravel(), T.operator.kind


def _reference(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """numpy's lstsq of the column-equilibrated matrix (A D) v = b, w = D v: accurate whatever the columns' scales
    (the SVD of A itself is accurate only to eps max|A|, 0.2 where one entry is 1e15); (w, 1 / D, cond(A D))."""
    d = 1.0 / np.linalg.norm(A, axis=0)
    v, _, _, sv = np.linalg.lstsq(A * d, b, rcond=None)
    return v * d, 1.0 / d, float(sv[0] / sv[-1])


def _agrees(A: np.ndarray, b: np.ndarray) -> str:
    w, kind = _engine_least_squares(A, b)
    ref, unscale, cond = _reference(A, b)
    error = np.linalg.norm((w - ref) * unscale) / np.linalg.norm(ref * unscale)
    assert error <= 1e-9 * cond, (kind, error, cond)
    return kind


def test_a_dense_matrix_with_one_huge_entry_is_no_toeplitz_matrix() -> None:
    """The issue's regressor: random 300 x 256 with one entry 1e15. Judged against max|A|, every other entry was
    rounding and the matrix was taken as Toeplitz plus one correction (|w - lstsq| 0.58); per entry it is dense."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((300, 256))
    A[17, 40] = 1e15
    assert toeplitz_split(A) is None
    assert _agrees(A, rng.standard_normal(300)) == "dense"


def test_a_small_row_is_reproduced_to_its_own_scale() -> None:
    """A banded filter matrix (kernel h_0 .. h_4 on the diagonals i - j = 0 .. 4) whose first sample h_0 = 1e-4 is
    small: row 0 holds h_0 alone. Its entry moved by a relative 1e-10 (1e-14 absolute) was rounding against max|A|
    (2^-46 * 1 = 1.4e-14) and the operator returned the old value, 1e-10 off in that row; against the row's own scale
    it is a correction, and the operator reproduces every row to 1e-12 of its size (zero rows to the FFT's rounding)."""
    m, n = 300, 256
    t = np.zeros(m + n - 1)
    t[n - 1:n + 4] = [1e-4, 1.0, -0.7, 0.3, 0.1]  # t[i - j + n - 1] = h_{i - j}
    A = _toeplitz(t, m, n)
    A[0, 0] *= 1 + 1e-10
    op = Operator(A, "A")
    assert op.kind == "toeplitz"
    assert _reproduces(op, A, 1e-12)


def _reproduces(op: Operator, A: np.ndarray, rtol: float) -> bool:
    """Whether op's matrix is A to rtol of each entry's scale (the smaller of its row's and column's largest
    magnitude), and to the FFT's rounding, 2^-52 * 16 * max|A|, in zero rows and columns."""
    r, c = toeplitz.entry_scales(A)
    tol = rtol * np.minimum(r[:, None], c[None, :]) + 2.0 ** -52 * 16 * r.max()
    return bool(np.all(np.abs(op.apply(np.eye(A.shape[1])) - A) <= tol))


@st.composite
def _near_toeplitz(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    """A 300 x 256 Toeplitz matrix of a random kernel at a random scale, then one adversarial change: an outlier entry
    (10^3 .. 10^15 times the scale), a few entries moved by a relative 10^-15 .. 10^-6, a column rescaled by 10^-9
    .. 10^9, a huge corner of an exact Toeplitz matrix, or boundary columns (a filter matrix); and a right side b."""
    seed = draw(st.integers(0, 2 ** 32 - 1))
    rng = np.random.default_rng(seed)
    m, n = 300, 256
    scale = 10.0 ** draw(st.floats(-6, 6))
    A = scale * _toeplitz(rng.standard_normal(m + n - 1), m, n)
    kind = draw(st.sampled_from(["outlier", "relative", "column", "corner", "boundary"]))
    i, j = int(rng.integers(m)), int(rng.integers(n))
    if kind == "outlier":
        A[i, j] = scale * 10.0 ** draw(st.floats(3, 15))
    elif kind == "relative":
        rows, cols = rng.integers(m, size=5), rng.integers(n, size=5)
        A[rows, cols] *= 1 + 10.0 ** draw(st.floats(-15, -6)) * rng.choice([-1.0, 1.0], 5)
    elif kind == "column":
        A[:, j] *= 10.0 ** draw(st.floats(-9, 9))
    elif kind == "corner":
        A[m - 1, 0] = scale * 10.0 ** draw(st.floats(3, 15))
        A[m - 2, 0] = A[m - 1, 1] = 0.0
    else:
        A[:, :3] = scale * rng.standard_normal((m, 3))
    return A, scale * rng.standard_normal(m)


@settings(max_examples=10, deadline=None, derandomize=True)
@given(_near_toeplitz())
def test_near_toeplitz_least_squares_agree_with_numpy(case: tuple[np.ndarray, np.ndarray]) -> None:
    """Whatever the engine recognizes, its least squares is numpy's (column-equilibrated lstsq) to 1e-9 cond, and a
    recognized operator reproduces every entry of A to 1e-9 of its scale (entry_scales)."""
    A, b = case
    _agrees(A, b)
    op = Operator(A, "A")
    if op.kind == "toeplitz":
        assert _reproduces(op, A, 1e-9)
