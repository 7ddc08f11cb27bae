"""Dense matrices that are Toeplitz up to a few entries are applied by FFT convolution (bilevel.toeplitz): the
products and adjoint products equal the dense ones, other matrices stay dense, and a VRFT declaration with the
regressor's filter matrices gives the values and hypergradients of the same declaration applied by BLAS."""

from __future__ import annotations

import numpy as np
import pytest

import bilevel.toeplitz as toeplitz
from bilevel.linear_maps import Operator
from bilevel.lower.images import ImageLower
from bilevel.problems.vrft_instance import attack_instance
from bilevel.solvers.base import prepare
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
    t_found, R = toeplitz_split(A)
    assert np.array_equal(t_found, t) and R.nnz == 10
    B = _toeplitz(t, m, n)
    B[-3:, -4:] = 0.0  # a corrected bottom-right corner: read off the top-left
    t_found, R = toeplitz_split(B)
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
