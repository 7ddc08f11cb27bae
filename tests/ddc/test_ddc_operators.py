"""Structured Toeplitz operators: dense equality, adjointness, the non-causal inverse of M_r."""

from __future__ import annotations

import numpy as np
import scipy.signal
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bilevel.ddc.operators import LTIOperator, filter_columns, reference_inverse, virtual_error_operator
from bilevel.ddc.plants import flexible_transmission_reference
from bilevel.ddc.systems import series
from bilevel.errors import InvalidData, ReferenceModelError

SETTINGS = settings(max_examples=40, deadline=None)


def _poly_with_roots(draw, count: int, radius: float) -> np.ndarray:
    """Real monic polynomial with `count` roots of modulus < radius (real roots and conjugate pairs)."""
    roots: list[complex] = []
    while len(roots) < count:
        mod = draw(st.floats(0.0, radius))
        if count - len(roots) >= 2 and draw(st.booleans()):
            ang = draw(st.floats(0.1, 3.0))
            roots += [mod * np.exp(1j * ang), mod * np.exp(-1j * ang)]
        else:
            roots.append(mod * draw(st.sampled_from([-1.0, 1.0])))
    return np.real(np.poly(roots)) if roots else np.ones(1)


@st.composite
def stable_filters(draw):
    """Random proper stable SISO filter (poles |p| < 0.95), as (num, den)."""
    order = draw(st.integers(0, 4))
    den = _poly_with_roots(draw, order, 0.95)
    num_deg = draw(st.integers(0, order))
    num = np.array(draw(st.lists(st.floats(-2, 2), min_size=num_deg + 1, max_size=num_deg + 1)))
    if not np.any(num):
        num[-1] = 1.0
    return num, den


@st.composite
def reference_models(draw):
    """Random stable, minimum-phase M_r (zeros |z| < 0.9, poles |p| < 0.95) of relative degree 0..3."""
    n_zeros = draw(st.integers(0, 3))
    d = draw(st.integers(0, 3))
    gain = draw(st.floats(0.2, 3.0)) * draw(st.sampled_from([-1.0, 1.0]))
    num = gain * _poly_with_roots(draw, n_zeros, 0.9)
    return (num, _poly_with_roots(draw, n_zeros + d, 0.95)), d


signals = st.integers(1, 48).flatmap(
    lambda n: st.lists(st.floats(-10, 10), min_size=n, max_size=n).map(np.array)
)


@SETTINGS
@given(stable_filters(), signals)
def test_apply_equals_dense_toeplitz_product(system, x):
    """T_G x computed by filtering equals the paper's lower-triangular Toeplitz T_{G,N} times x."""
    op = LTIOperator(system)
    np.testing.assert_allclose(op.apply(x), op.dense(x.size) @ x, atol=1e-9 * (1 + np.abs(x).sum()))


@SETTINGS
@given(stable_filters(), signals, st.integers(0, 2**32 - 1))
def test_adjoint_identity(system, x, seed):
    """<T x, y> = <x, T^T y> for the time-reversal adjoint."""
    y = np.random.default_rng(seed).standard_normal(x.size)
    op = LTIOperator(system)
    scale = 1 + np.abs(x).sum() * np.abs(y).sum()
    assert abs(op.apply(x) @ y - x @ op.adjoint(y)) <= 1e-9 * scale
    np.testing.assert_allclose(op.adjoint(y), op.dense(x.size).T @ y, atol=1e-9 * (1 + np.abs(y).sum()))


@SETTINGS
@given(reference_models(), st.integers(8, 48), st.integers(0, 2**32 - 1))
def test_inverse_undoes_reference_model(model, n, seed):
    """T_{M_r^{-1}} T_{M_r} r = r on the first N - d samples (the last d need y_N..: zero-final boundary);
    T_{M_r} T_{M_r^{-1}} y = y exactly for y with y_0..y_{d-1} = 0 (any output of M_r from rest)."""
    reference, d = model
    rng = np.random.default_rng(seed)
    forward, inverse = LTIOperator(reference), reference_inverse(reference)
    assert inverse.advance == d
    r = rng.standard_normal(n)
    recovered = inverse.apply(forward.apply(r))
    np.testing.assert_allclose(recovered[: n - d], r[: n - d], atol=1e-7 * (1 + np.abs(r).max()))
    y = rng.standard_normal(n)
    y[:d] = 0.0
    np.testing.assert_allclose(forward.apply(inverse.apply(y)), y, atol=1e-7 * (1 + np.abs(y).max()))


@SETTINGS
@given(reference_models(), st.integers(1, 40), st.integers(0, 2**32 - 1))
def test_inverse_dense_adjoint_and_error_operator(model, n, seed):
    """Dense T_{M_r^{-1}} equals the structured one; adjointness; virtual error operator = T_{M_r^{-1}} - I."""
    reference, _ = model
    rng = np.random.default_rng(seed)
    inverse, error = reference_inverse(reference), virtual_error_operator(reference)
    y, w = rng.standard_normal(n), rng.standard_normal(n)
    dense = inverse.dense(n)
    tol = 1e-8 * (1 + np.abs(dense).max()) * n
    np.testing.assert_allclose(inverse.apply(y), dense @ y, atol=tol)
    np.testing.assert_allclose(inverse.adjoint(w), dense.T @ w, atol=tol)
    np.testing.assert_allclose(error.apply(y), dense @ y - y, atol=tol)


def test_fir_inverse_of_flexible_transmission_reference():
    """M_r = (1-a)^2/(z (z-a)^2) (pole at 0, so C A^{-1} B is singular): M_r^{-1} is the FIR
    r_t = (y_{t+3} - 2a y_{t+2} + a^2 y_{t+1})/(1-a)^2 with y_t = 0 for t >= N (paper, Sec. 4.2)."""
    a = np.exp(-0.5)
    n = 40
    y = np.random.default_rng(3).standard_normal(n)
    padded = np.concatenate([y, np.zeros(3)])
    t = np.arange(n)
    expected = (padded[t + 3] - 2 * a * padded[t + 2] + a * a * padded[t + 1]) / (1 - a) ** 2
    inverse = reference_inverse(flexible_transmission_reference())
    np.testing.assert_allclose(inverse.apply(y), expected, rtol=1e-12, atol=1e-12)
    y[:3] = 0.0
    forward = LTIOperator(flexible_transmission_reference())
    np.testing.assert_allclose(forward.apply(inverse.apply(y)), y, atol=1e-12)


def test_series_composes_causal_operators_exactly():
    """For causal filters T_A T_B = T_{AB} (lower-triangular Toeplitz matrices commute and multiply)."""
    a, b = ([0.5, 0.1], [1, -0.7, 0.1]), ([1.0, -0.3], [1.0, 0.4])
    x = np.random.default_rng(0).standard_normal((30, 2))
    composed = LTIOperator(series(a, b)).apply(x)
    np.testing.assert_allclose(composed, LTIOperator(a).apply(LTIOperator(b).apply(x)), atol=1e-12)


@pytest.mark.parametrize(
    ("reference", "needle"),
    [
        (([1.0, -1.5], [1.0, 0.0, 0.0]), "minimum phase"),
        (([0.3, 0.3], [1.0, -0.4]), "minimum phase"),
        (([0.1], [1.0, -1.1]), "not stable"),
        (([0.0], [1.0, -0.5]), "identically zero"),
        (([1.0, 0.0, 0.0], [1.0, -0.5]), "improper"),
    ],
)
def test_bad_reference_models_are_named(reference, needle):
    """Non-minimum-phase (zero at 1.5, or at -1 on the circle), unstable, zero and improper M_r are refused."""
    with pytest.raises(ReferenceModelError, match=needle):
        reference_inverse(reference)
    with pytest.raises(ReferenceModelError, match=needle):
        virtual_error_operator(reference)


def test_improper_filter_and_bad_shapes():
    """An improper filter has no causal Toeplitz operator; signals must be (N,) or (N, k)."""
    with pytest.raises(InvalidData, match="improper"):
        LTIOperator(([1.0, 0.0, 0.0], [1.0, 0.5]))
    with pytest.raises(InvalidData, match="shape"):
        LTIOperator(([1.0], [1.0, 0.5])).apply(np.zeros((2, 2, 2)))


@pytest.mark.parametrize("b, a", [([1.0], [1.0, -1.0, 0.0, 0.0, 0.0, 0.0]), ([1.0, 0.0], [1.0, -1.0]),
                                  ([6.46, -7.84, 2.38, -1.0], [1.0, 0.0, 0.0, 0.0]), ([0.5, -0.25], [1.0, 0.0]),
                                  ([1.0], [1.0, -0.5]), ([1.0, 0.3], [1.0, -1.0])])
def test_filter_columns_is_lfilter_bit_for_bit(b, a) -> None:
    """The running-sum and FIR forms (and the lfilter fallback) equal scipy's lfilter exactly, on signals and columns
    of widely ranging magnitude, reversed views, records shorter than the filter, and non-finite samples."""
    rng = np.random.default_rng(3)
    b, a = np.array(b), np.array(a)
    for shape in [(515, 32), (515,), (3, 4), (2,), (1, 5)]:
        for _ in range(10):
            x = rng.standard_normal(shape) * 10.0 ** rng.integers(-6, 6, size=shape)
            for xx in (x, x[::-1]):
                assert np.array_equal(filter_columns(b, a, xx), scipy.signal.lfilter(b, a, xx, axis=0))
    x = rng.standard_normal((20, 3))
    x[4, 1] = np.inf
    np.testing.assert_array_equal(filter_columns(b, a, x), scipy.signal.lfilter(b, a, x, axis=0))
