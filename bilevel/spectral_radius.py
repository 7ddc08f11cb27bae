"""The spectral radius rho(M) = max |lambda_i(M)| of real square matrices and its exact derivative.

For a simple top eigenvalue lambda with right eigenvector v and left eigenvector w (w^H M = lambda w^H),
d lambda = w^H dM v / (w^H v), so d|lambda| / dM = Re(conj(lambda) / |lambda| * conj(w) v^T / (w^H v)).
The left eigenvectors are the rows of V^-1 (then w^H v = 1). A complex pair gives the same gradient from either
member. Where several eigenvalues of different branches share the top modulus exactly (a tie), rho is not
differentiable: the mean of their gradients is returned, an element of Clarke's generalized gradient, and `ties`
counts the branches; a defective top eigenvalue (V singular) has no derivative and gives NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .defaults import param
from .errors import ModelError


@dataclass
class SpectralRadius:
    """rho(M) and d rho / dM for a stack of matrices (..., n, n); ties: top branches per matrix (1: smooth)."""

    value: np.ndarray
    gradient: np.ndarray
    ties: np.ndarray


def spectral_radius(m: np.ndarray) -> SpectralRadius:
    """rho and its gradient in M for a real matrix or a stack of them, from one eigendecomposition each."""
    m = np.asarray(m, dtype=float)
    if m.ndim < 2 or m.shape[-1] != m.shape[-2] or m.shape[-1] == 0:
        raise ModelError(f"spectral_radius needs square matrices (..., n, n), got shape {m.shape}")
    lam, v = np.linalg.eig(m)
    modulus = np.abs(lam)
    rho = modulus.max(axis=-1)
    top = modulus == rho[..., None]
    try:
        w = np.linalg.inv(v)
        cond = np.linalg.norm(v, axis=(-2, -1)) * np.linalg.norm(w, axis=(-2, -1))  # Frobenius: >= the 2-norm's
    except np.linalg.LinAlgError:  # some V exactly singular: invert the others one by one
        cond = np.linalg.cond(v)
        defective = param("spectral_radius.defective_cond")
        w = np.linalg.inv(np.where((cond <= defective)[..., None, None], v, np.eye(m.shape[-1])))
    # branch i: d|lambda_i|/dM_jk = Re(conj(lambda_i)/|lambda_i| * w_ij v_ki), w = V^-1 (rows: left vectors)
    phase = np.where(top, np.conj(lam) / np.where(modulus > 0, modulus, 1.0), 0.0)
    grad = np.real(np.einsum("...i,...ij,...ki->...jk", phase, w, v))
    branches = top & (np.imag(lam) >= 0)  # a complex pair is one branch (the member with Im > 0)
    ties = branches.sum(axis=-1)
    shared = top.sum(axis=-1)
    if np.any(shared > 1):
        grad = grad / shared[..., None, None]
    bad = (cond > param("spectral_radius.defective_cond")) | (rho == 0)
    if np.any(bad):
        grad = np.where(bad[..., None, None], np.nan, grad)
    return SpectralRadius(rho, grad, ties)


def rho_and_gradient(m: np.ndarray) -> tuple[float, np.ndarray]:
    """(rho(M), d rho / dM) of one real square matrix: the matrix function of maximize_spectral_radius."""
    r = spectral_radius(m)
    return float(r.value), r.gradient


def radius(m: np.ndarray) -> np.ndarray:
    """rho of a real matrix or of each of a stack of them, from the eigenvalues alone (about half the cost of
    spectral_radius; the same eigenvalues, so the same rho)."""
    m = np.asarray(m, dtype=float)
    if m.ndim < 2 or m.shape[-1] != m.shape[-2] or m.shape[-1] == 0:
        raise ModelError(f"radius needs square matrices (..., n, n), got shape {m.shape}")
    return np.abs(np.linalg.eigvals(m)).max(axis=-1)
