"""Finite-horizon Toeplitz operators of SISO LTI filters on length-N signals, applied in O(N).

``LTIOperator`` is the N x N Toeplitz matrix with entries ``h[i - j + advance]`` (zero for a
negative index), where h is the impulse response of a proper filter: ``advance = 0`` is the
causal response with zero initial conditions (the paper's T_G), ``advance = d > 0`` reads the
input d samples ahead and treats samples beyond the record as zero ("zero final conditions").
The non-causal inverse of a reference model, T_{M_r^{-1}}, is such an operator.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.signal
from numpy.typing import ArrayLike

from bilevel.errors import InvalidData, ReferenceModelError
from bilevel.ddc.systems import SystemLike, num_den

_UNIT_CIRCLE_TOL = 1e-9


def _signal(x: ArrayLike) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim not in (1, 2):
        raise InvalidData(f"signals must have shape (N,) or (N, k), got shape {x.shape}")
    return x


def filter_columns(b: np.ndarray, a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """scipy.signal.lfilter(b, a, x, axis=0) bit for bit; a FIR filter (a = [1, 0, ...]) as its taps summed in lfilter's
    order and a running sum (b = [1], a = [1, -1, 0, ...]) as cumsum, on finite x (no per-sample loop)."""
    x = np.asarray(x, dtype=float)
    if a[0] != 1.0 or x.ndim == 0 or x.shape[0] == 0 or not np.isfinite(x).all():
        return scipy.signal.lfilter(b, a, x, axis=0)
    if b.size <= a.size and b[0] == 1.0 and not np.any(b[1:]) and a.size > 1 and a[1] == -1.0 and not np.any(a[2:]):
        return np.cumsum(x, axis=0)
    if b.size == a.size and not np.any(a[1:]):
        n = x.shape[0]
        y = np.zeros_like(x)
        for k in range(b.size - 1, -1, -1):
            if k < n:
                y[k:] += b[k] * x[: n - k]
        return y
    return scipy.signal.lfilter(b, a, x, axis=0)


class LTIOperator:
    """Toeplitz operator of a proper SISO filter on length-N signals (columns of an (N, k) array)."""

    def __init__(self, system: SystemLike, advance: int = 0) -> None:
        num, den = num_den(system)
        if num.size > den.size and np.any(num):
            raise InvalidData(
                f"filter is improper (numerator degree {num.size - 1} > denominator degree "
                f"{den.size - 1}); only proper filters have a causal realization"
            )
        if advance < 0:
            raise InvalidData(f"advance must be >= 0, got {advance}")
        self.num, self.den, self.advance = num, den, int(advance)
        self._b = np.concatenate([np.zeros(den.size - num.size), num]) if np.any(num) else np.zeros(1)

    def __repr__(self) -> str:
        return f"LTIOperator(num={self.num.tolist()}, den={self.den.tolist()}, advance={self.advance})"

    def apply(self, x: ArrayLike) -> np.ndarray:
        """T x: response over the record, zero initial conditions (and zero final ones if advanced)."""
        x = _signal(x)
        d = self.advance
        if d == 0:
            return filter_columns(self._b, self.den, x)
        padded = np.concatenate([x, np.zeros((d,) + x.shape[1:])], axis=0)
        return filter_columns(self._b, self.den, padded)[d:]

    def adjoint(self, y: ArrayLike) -> np.ndarray:
        """T^T y, by filtering the time-reversed signal (a square Toeplitz T satisfies T^T = J T J)."""
        y = _signal(y)
        return self.apply(y[::-1])[::-1]

    def impulse(self, n: int) -> np.ndarray:
        """First n samples h_0..h_{n-1} of the causal filter's impulse response."""
        delta = np.zeros(n)
        delta[0] = 1.0
        return scipy.signal.lfilter(self._b, self.den, delta)

    def dense(self, n: int) -> np.ndarray:
        """The n x n matrix (for tests and small n only: O(n^2) memory)."""
        d = self.advance
        h = self.impulse(n + d)
        first_row = np.zeros(n)
        first_row[: min(d + 1, n)] = h[d::-1][: min(d + 1, n)]
        return scipy.linalg.toeplitz(h[d:d + n], first_row)


def _validate_reference(reference: SystemLike) -> tuple[np.ndarray, np.ndarray, int]:
    try:
        num, den = num_den(reference)
    except InvalidData as exc:
        raise ReferenceModelError(f"reference model M_r is unusable: {exc}") from None
    if not np.any(num):
        raise ReferenceModelError(
            "reference model M_r is identically zero, so it has no inverse; "
            "choose M_r with a nonzero gain (e.g. M_r(1) = 1 for unit static gain)"
        )
    d = den.size - num.size
    if d < 0:
        raise ReferenceModelError(
            f"reference model M_r is improper (numerator degree {num.size - 1} > denominator "
            f"degree {den.size - 1}); a closed loop can only match a proper M_r"
        )
    poles = np.roots(den)
    bad_poles = poles[np.abs(poles) >= 1 - _UNIT_CIRCLE_TOL]
    if bad_poles.size:
        raise ReferenceModelError(
            f"reference model M_r is not stable: poles {np.round(bad_poles, 6).tolist()} are on or "
            "outside the unit circle; choose a stable M_r (all poles with |p| < 1)"
        )
    zeros = np.roots(num)
    bad_zeros = zeros[np.abs(zeros) >= 1 - _UNIT_CIRCLE_TOL]
    if bad_zeros.size:
        raise ReferenceModelError(
            f"reference model M_r is not minimum phase: zeros {np.round(bad_zeros, 6).tolist()} are on "
            "or outside the unit circle, so M_r^{-1} is unstable and the virtual reference diverges; "
            "choose an M_r whose zeros lie strictly inside the unit circle"
        )
    return num, den, d


def reference_inverse(reference: SystemLike) -> LTIOperator:
    """T_{M_r^{-1}}: r_t = H(q) y_{t+d} with H = A/(z^d B) for M_r = B/A of relative degree d, y_t = 0 for t >= N."""
    num, den, d = _validate_reference(reference)
    return LTIOperator((den, np.concatenate([num, np.zeros(d)])), advance=d)


def virtual_error_operator(reference: SystemLike) -> LTIOperator:
    """T_{M_r^{-1}} - I: the virtual error e = r - y, as one advanced filter (A - B)/(z^d B)."""
    num, den, d = _validate_reference(reference)
    return LTIOperator((np.polysub(den, num), np.concatenate([num, np.zeros(d)])), advance=d)
