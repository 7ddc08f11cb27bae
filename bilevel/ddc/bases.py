"""Controller bases linear in theta, K_theta(z) = sum_i theta_i beta_i(z), and their assembly."""

from __future__ import annotations

from collections.abc import Sequence

import control
import numpy as np
from numpy.typing import ArrayLike

from bilevel.errors import InvalidData
from bilevel.ddc.systems import SystemLike, num_den

Basis = Sequence[SystemLike]


def pi_basis(dt: float | bool = True) -> tuple[control.TransferFunction, ...]:
    """PI basis [1, 1/(z-1)]: K = theta_1 + theta_2 / (z - 1)."""
    return control.tf([1.0], [1.0], dt), control.tf([1.0], [1.0, -1.0], dt)


def pid_basis(dt: float | bool = True) -> tuple[control.TransferFunction, ...]:
    """PID basis [1, 1/(z-1), (z-1)/z]: proportional, integral, backward-difference derivative."""
    return pi_basis(dt) + (control.tf([1.0, -1.0], [1.0, 0.0], dt),)


def flexible_transmission_basis(dt: float | bool = 0.05) -> tuple[control.TransferFunction, ...]:
    """Campi et al. (2002) basis beta_i = z^(2-i)/(z-1), i = 1..6, for the flexible transmission."""
    first = control.tf([1.0, 0.0], [1.0, -1.0], dt)
    rest = tuple(control.tf([1.0], np.concatenate([[1.0, -1.0], np.zeros(k)]), dt) for k in range(5))
    return (first,) + rest


def _divides(divisor: np.ndarray, poly: np.ndarray) -> bool:
    if divisor.size > poly.size:
        return False
    _, remainder = np.polydiv(poly, divisor)
    return bool(np.max(np.abs(remainder)) <= 1e-12 * np.max(np.abs(poly)))


def basis_polynomials(basis: Basis) -> tuple[np.ndarray, np.ndarray]:
    """(N, D): row i of N is the numerator of beta_i over the common denominator D, so K = (theta' N) / D."""
    parts = [num_den(beta) for beta in basis]
    common = parts[0][1]
    for _, den in parts[1:]:
        if _divides(den, common):
            continue
        common = den if _divides(common, den) else np.polymul(common, den)
    nums = [np.polymul(n, np.polydiv(common, d)[0]) for n, d in parts]
    width = max(x.size for x in nums)
    return np.array([np.concatenate([np.zeros(width - x.size), x]) for x in nums]), common


def controller_tf(
    basis: Basis, theta: ArrayLike, dt: float | bool = True
) -> control.TransferFunction:
    """K_theta = sum_i theta_i beta_i over a common denominator (exact when denominators divide each other)."""
    theta = np.asarray(theta, dtype=float).ravel()
    if theta.size != len(basis):
        raise InvalidData(f"theta has {theta.size} entries but the basis has {len(basis)} functions")
    nums, common = basis_polynomials(basis)
    num = theta @ nums
    return control.tf(np.trim_zeros(num, "f") if np.any(num) else num, common, dt)
