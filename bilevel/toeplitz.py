"""Dense matrices that are Toeplitz up to a few entries (filter matrices: a convolution whose boundary rows or columns
differ), applied by FFT convolution plus a sparse correction: O(L log L + corrections) per product instead of m n.

A matrix is recognized once (O(m n)): its diagonals are read off one corner (last row and column, or first row and
column) and the entries that differ from that Toeplitz matrix by more than ROUNDING * max|A| form the correction;
it is used when the correction has at most CORRECTION_PER_EDGE * (m + n) entries. Entries that differ by less are
rounding of the matrix's own computation (a product of filter matrices rounds each diagonal differently), below the
FFT product's own rounding error.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.lib.stride_tricks import sliding_window_view
from scipy.fft import irfft, next_fast_len, rfft

MIN_ENTRIES, MIN_SIDE = 65_536, 64
"""Matrices with fewer entries, or fewer rows or columns, stay dense (a BLAS product of a 256 x 256 matrix costs about
what two FFTs do; a thin one is cheaper than a transform of its length)."""
ROUNDING = 2.0 ** -46
"""Differences from the Toeplitz part up to this fraction of max|A| are rounding, not corrections."""
CORRECTION_PER_EDGE = 8
"""The correction may hold at most this many entries per row plus column of the matrix (a few boundary columns)."""


def toeplitz_split(A: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix] | None:
    """(t, R) with A = T(t) + R, T(t)[i, j] = t[i - j + n - 1] and R sparse with few entries, or None when A is no
    such matrix or too small to gain."""
    m, n = A.shape
    if m * n < MIN_ENTRIES or min(m, n) < MIN_SIDE:
        return None
    tol = ROUNDING * float(np.abs(A).max(initial=0.0))
    mid = m // 2  # one row against the next first: most matrices that are not Toeplitz are rejected in O(n)
    if np.count_nonzero(np.abs(A[mid, 1:] - A[mid - 1, :-1]) > tol) > 2 * CORRECTION_PER_EDGE:
        return None
    best = None
    for t in (np.concatenate([A[:m - 1, n - 1], A[m - 1, ::-1]]), np.concatenate([A[0, ::-1], A[1:, 0]])):
        R = A - sliding_window_view(t, n)[:, ::-1]  # T(t) as a view: row i is t[i + n - 1], ..., t[i]
        R[np.abs(R) <= tol] = 0.0
        count = np.count_nonzero(R)
        if count <= CORRECTION_PER_EDGE * (m + n) and (best is None or count < best[1].nnz):
            best = (t, sp.csr_matrix(R))
    return best


class ToeplitzBank:
    """Matrices A_k = T(t_k) + R_k with n columns each, applied together: apply(X) = [A_1 X; A_2 X; ...] and
    adjoint([Y_1; Y_2; ...]) = sum_k A_k' Y_k (X and Y vectors or columns), one forward FFT per column of X and one
    inverse FFT per column of the adjoint."""

    def __init__(self, parts: list[tuple[np.ndarray, sp.csr_matrix]], n: int) -> None:
        self.parts, self.n = parts, n
        self.rows = [t.size - n + 1 for t, _ in parts]
        self.cuts = np.cumsum([0] + self.rows)
        self.length = next_fast_len(max(t.size for t, _ in parts), real=True)
        kernels = np.zeros((len(parts), self.length))
        for k, (t, _) in enumerate(parts):
            kernels[k, :t.size] = t
        self.spectra = rfft(np.roll(kernels, 1 - n, axis=1), axis=1)
        """The kernels' spectra, rotated by n - 1 entries: row i of A_k X is entry i of the circular convolution."""
        self._conj = self.spectra.conj()
        self.correction = sp.vstack([R for _, R in parts], format="csr")
        self._correction_t = self.correction.T.tocsr()
        cols = np.unique(self.correction.indices)
        self._columns: tuple[np.ndarray | slice, np.ndarray] | None = None
        """(columns, their entries) when the corrections sit in a few columns (a filter's boundary): dense products."""
        if cols.size <= CORRECTION_PER_EDGE:
            block = self.correction[:, cols].toarray()
            if cols.size and cols[-1] - cols[0] + 1 == cols.size:  # adjacent columns: X read by a view
                cols = slice(int(cols[0]), int(cols[-1]) + 1)
            self._columns = (cols, block)
        self._equal = len(set(self.rows)) == 1
        self.shape = (int(self.cuts[-1]), n)

    @classmethod
    def stack(cls, banks: list["ToeplitzBank"]) -> "ToeplitzBank":
        """One bank of all the banks' matrices in order (equal column counts)."""
        return cls([part for bank in banks for part in bank.parts], banks[0].n)

    def apply(self, X: np.ndarray) -> np.ndarray:
        """[A_1 X; A_2 X; ...]."""
        spectra = self.spectra.reshape(self.spectra.shape + (1,) * (X.ndim - 1))
        full = irfft(spectra * rfft(X, self.length, axis=0)[None], self.length, axis=1)
        if self._equal:
            out = full[:, :self.rows[0]].reshape((-1,) + X.shape[1:])
        else:
            out = np.concatenate([full[k, :r] for k, r in enumerate(self.rows)])
        out += self.correction @ X if self._columns is None else self._columns[1] @ X[self._columns[0]]
        return out

    def adjoint(self, Y: np.ndarray) -> np.ndarray:
        """sum_k A_k' Y_k for Y = [Y_1; Y_2; ...]: a correlation with each kernel."""
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
