"""Dense matrices that are Toeplitz up to a few entries (filter matrices: a convolution whose boundary rows or columns
differ), applied by FFT convolution plus a sparse correction: O(L log L + corrections) per product instead of m n.

A matrix is recognized once (O(m n)): its diagonals are read off one corner (last row and column, or first row and
column) and the entries that differ from that Toeplitz matrix by more than ROUNDING times their own scale form the
correction; it is used when the correction has at most CORRECTION_PER_EDGE * (m + n) entries. An entry's scale is the
smaller of its row's and its column's largest magnitude (`entry_scales`): the recognized operator then reproduces
every row and every column of A to ROUNDING relative to that row's or column's own size, as a backward-stable
factorization does, so a least squares solved with it is the least squares of A (a few large entries elsewhere in the
matrix widen no other entry's tolerance). Entries that differ by less are rounding of the matrix's own computation (a
product of filter matrices rounds each diagonal differently), below the FFT product's own rounding error. A bank of
such matrices whose kernels are delays of the first one (lagged copies of a filter, as a regressor's columns) shares
one convolution, read at each delay, where the kernels differ by less than ROUNDING times each diagonal's scale.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from numpy.lib.stride_tricks import sliding_window_view
from scipy.fft import irfft, next_fast_len, rfft

MIN_ENTRIES, MIN_SIDE = 65_536, 64
"""Matrices with fewer entries, or fewer rows or columns, stay dense (a BLAS product of a 256 x 256 matrix costs about
what two FFTs do; a thin one is cheaper than a transform of its length)."""
ROUNDING = 2.0 ** -46
"""Differences from the Toeplitz part up to this fraction of an entry's scale (entry_scales) are rounding, not
corrections."""
CORRECTION_PER_EDGE = 8
"""The correction may hold at most this many entries per row plus column of the matrix (a few boundary columns)."""
DYNAMIC_RANGE = 2.0 ** 16
"""The FFT product rounds every entry by about 2^-52 log2(L) max|A| max|x|, whatever the entry's own scale: a matrix
whose largest entry exceeds this many times its smallest nonzero row or column scale stays dense, so that rounding
stays near 2^-32 of every nonzero row's and column's own size (a huge corner of an otherwise moderate filter would
swamp the other entries' products)."""
MAX_DELAY = 16
"""Kernels that are the first one delayed by at most this many samples (up to a few entries) share its transform."""


class Split(NamedTuple):
    """A = T(t) + R (T(t)[i, j] = t[i - j + n - 1], R sparse with few entries); scale[p]: the smallest entry scale
    (entry_scales) on diagonal p of A, the tolerance unit of a change to that whole diagonal."""

    t: np.ndarray
    R: sp.csr_matrix
    scale: np.ndarray


def entry_scales(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r, c): the largest magnitude of each row and of each column of A; entry (i, j)'s scale is min(r_i, c_j)."""
    magnitude = np.abs(A)
    return magnitude.max(axis=1), magnitude.max(axis=0)


def _diagonal_scales(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The smallest min(r_i, c_j) over the entries (i, j) of each diagonal p = i - j + n - 1 of an m x n matrix: the
    rows of diagonal p are the window [p - n + 1, p + 1) of r and its columns the window [n - 1 - p, n - 1 - p + m)
    of c, read from inf-padded copies."""
    m, n = r.size, c.size
    rows = sliding_window_view(np.concatenate([np.full(n - 1, np.inf), r, np.full(n - 1, np.inf)]), n).min(axis=1)
    cols = sliding_window_view(np.concatenate([np.full(m - 1, np.inf), c, np.full(m - 1, np.inf)]), m).min(axis=1)
    return np.minimum(rows, cols[::-1])


def toeplitz_split(A: np.ndarray) -> Split | None:
    """A = T(t) + R with R sparse with few entries, every other entry reproduced to ROUNDING times its scale
    (entry_scales), or None when A is no such matrix or too small to gain."""
    m, n = A.shape
    if m * n < MIN_ENTRIES or min(m, n) < MIN_SIDE:
        return None
    r, c = entry_scales(A)
    smallest = min(r[r > 0].min(initial=np.inf), c[c > 0].min(initial=np.inf))
    if not r.max() <= DYNAMIC_RANGE * smallest:
        return None
    mid = m // 2  # one row against the next first: most matrices that are not Toeplitz are rejected in O(n)
    pair = ROUNDING * (np.minimum(r[mid], c[1:]) + np.minimum(r[mid - 1], c[:-1]))  # both entries' tolerances
    if np.count_nonzero(np.abs(A[mid, 1:] - A[mid - 1, :-1]) > pair) > 2 * CORRECTION_PER_EDGE:
        return None
    tol = ROUNDING * np.minimum(r[:, None], c[None, :])
    best = None
    for t in (np.concatenate([A[:m - 1, n - 1], A[m - 1, ::-1]]), np.concatenate([A[0, ::-1], A[1:, 0]])):
        R = A - sliding_window_view(t, n)[:, ::-1]  # T(t) as a view: row i is t[i + n - 1], ..., t[i]
        R[np.abs(R) <= tol] = 0.0
        count = np.count_nonzero(R)
        if count <= CORRECTION_PER_EDGE * (m + n) and (best is None or count < best[1].nnz):
            best = (t, sp.csr_matrix(R))
    return None if best is None else Split(best[0], best[1], _diagonal_scales(r, c))


def _toeplitz_entries(delta: np.ndarray, m: int, n: int) -> sp.csr_matrix:
    """T(delta) (m x n, T[i, j] = delta[i - j + n - 1]) as a sparse matrix, for a delta with few nonzeros."""
    rows, cols, values = [], [], []
    for p in np.flatnonzero(delta):
        d = int(p) - (n - 1)  # the diagonal i - j = d
        i = np.arange(max(0, d), min(m, n + d))
        rows.append(i)
        cols.append(i - d)
        values.append(np.full(i.size, delta[p]))
    if not rows:
        return sp.csr_matrix((m, n))
    return sp.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(m, n))


def delays(parts: list[Split], n: int) -> tuple[list[int], list[sp.csr_matrix]] | None:
    """(shifts, corrections) with A_k = T(t_0 delayed by shifts[k]) + corrections[k] for the parts (t_k, R_k) of equal
    shape, where each kernel is the first one delayed by at most MAX_DELAY samples up to CORRECTION_PER_EDGE entries
    (lagged copies of one filter, as the columns of a regressor; a diagonal that differs by ROUNDING times its scale or
    less counts as equal) and the corrections stay few; else None."""
    t0 = parts[0].t
    K, m = t0.size, t0.size - n + 1
    shifts, corrections = [], []
    for t, R, scale in parts:
        tol = ROUNDING * scale
        if t.size != K:
            return None
        best = None
        for shift in range(-MAX_DELAY, MAX_DELAY + 1):
            delayed = np.zeros(K)
            if shift >= 0:
                delayed[shift:] = t0[:K - shift]
            else:
                delayed[:shift] = t0[-shift:]
            delta = t - delayed
            delta[np.abs(delta) <= tol] = 0.0
            count = np.count_nonzero(delta)
            if count <= CORRECTION_PER_EDGE and (best is None or count < best[2]):
                best = (shift, delta, count)
        if best is None:
            return None
        correction = (R + _toeplitz_entries(best[1], m, n)).tocsr()
        correction.eliminate_zeros()
        if correction.nnz > CORRECTION_PER_EDGE * (m + n):
            return None
        shifts.append(best[0])
        corrections.append(correction)
    return shifts, corrections


class ToeplitzBank:
    """Matrices A_k = T(t_k) + R_k with n columns each, applied together: apply(X) = [A_1 X; A_2 X; ...] and
    adjoint([Y_1; Y_2; ...]) = sum_k A_k' Y_k (X and Y vectors or columns), one forward FFT per column of X and one
    inverse FFT per column of the adjoint; where the kernels are delays of the first (`delays`), one inverse FFT per
    column of X and one forward FFT per column of the adjoint too."""

    def __init__(self, parts: list[Split], n: int) -> None:
        self.parts, self.n = parts, n
        self.rows = [part.t.size - n + 1 for part in parts]
        self.cuts = np.cumsum([0] + self.rows)
        self._equal = len(set(self.rows)) == 1
        shared = delays(parts, n) if len(parts) > 1 and self._equal else None
        self._delays: np.ndarray | None = None
        """Where the kernels are delays of the first (`delays`): each row's entry of the one circular convolution."""
        if shared is None:
            kernels = [part.t for part in parts]
            corrections = [part.R for part in parts]
            self.length = next_fast_len(max(t.size for t in kernels), real=True)
        else:
            shifts, corrections = shared
            kernels = [parts[0].t]
            self.length = next_fast_len(parts[0].t.size + max(abs(s) for s in shifts), real=True)
            self._delays = np.concatenate([(np.arange(self.rows[0]) - s) % self.length for s in shifts])
        padded = np.zeros((len(kernels), self.length))
        for k, t in enumerate(kernels):
            padded[k, :t.size] = t
        self.spectra = rfft(np.roll(padded, 1 - n, axis=1), axis=1)
        """The kernels' spectra, rotated by n - 1 entries: row i of A_k X is entry i of the circular convolution (of
        entry i - shift_k of the first kernel's where they are delays)."""
        self._conj = self.spectra.conj()
        self.correction = sp.vstack(corrections, format="csr")
        self._correction_t = self.correction.T.tocsr()
        cols = np.unique(self.correction.indices)
        self._columns: tuple[np.ndarray | slice, np.ndarray] | None = None
        """(columns, their entries) when the corrections sit in a few columns (a filter's boundary): dense products."""
        if cols.size <= CORRECTION_PER_EDGE:
            block = self.correction[:, cols].toarray()
            if cols.size and cols[-1] - cols[0] + 1 == cols.size:  # adjacent columns: X read by a view
                cols = slice(int(cols[0]), int(cols[-1]) + 1)
            self._columns = (cols, block)
        self.shape = (int(self.cuts[-1]), n)

    @classmethod
    def stack(cls, banks: list["ToeplitzBank"]) -> "ToeplitzBank":
        """One bank of all the banks' matrices in order (equal column counts)."""
        return cls([part for bank in banks for part in bank.parts], banks[0].n)

    def apply(self, X: np.ndarray) -> np.ndarray:
        """[A_1 X; A_2 X; ...]."""
        if self._delays is not None:  # one convolution, read at each kernel's delay
            spectrum = self.spectra[0].reshape((-1,) + (1,) * (X.ndim - 1))
            out = irfft(spectrum * rfft(X, self.length, axis=0), self.length, axis=0)[self._delays]
        else:
            spectra = self.spectra.reshape(self.spectra.shape + (1,) * (X.ndim - 1))
            full = irfft(spectra * rfft(X, self.length, axis=0)[None], self.length, axis=1)
            if self._equal:
                out = full[:, :self.rows[0]].reshape((-1,) + X.shape[1:])
            else:
                out = np.concatenate([full[k, :r] for k, r in enumerate(self.rows)])
        out += self.correction @ X if self._columns is None else self._columns[1] @ X[self._columns[0]]
        return out

    def adjoint(self, Y: np.ndarray) -> np.ndarray:
        """sum_k A_k' Y_k for Y = [Y_1; Y_2; ...]: a correlation with each kernel (with the first one, of the Y_k
        placed at their delays, where the kernels are delays of it)."""
        if self._delays is not None:
            if Y.ndim == 1:
                placed = np.bincount(self._delays, Y, minlength=self.length)
            else:
                placed, m = np.zeros((self.length,) + Y.shape[1:]), self.rows[0]
                for k in range(len(self.rows)):
                    placed[self._delays[k * m:(k + 1) * m]] += Y[k * m:(k + 1) * m]
            total = rfft(placed, axis=0) * self._conj[0].reshape((-1,) + (1,) * (Y.ndim - 1))
        else:
            if self._equal:
                parts = rfft(Y.reshape((len(self.rows), self.rows[0]) + Y.shape[1:]), self.length, axis=1)
            else:
                padded = np.zeros((len(self.rows), self.length) + Y.shape[1:])
                for k, r in enumerate(self.rows):
                    padded[k, :r] = Y[self.cuts[k]:self.cuts[k + 1]]
                parts = rfft(padded, axis=1)
            total = (parts * self._conj.reshape(self._conj.shape + (1,) * (Y.ndim - 1))).sum(axis=0)
        out = irfft(total, self.length, axis=0)[:self.n]
        if self._columns is None:
            return out + self._correction_t @ Y
        out[self._columns[0]] += self._columns[1].T @ Y
        return out
