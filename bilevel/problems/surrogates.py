"""Smooth surrogates of non-smooth closed-loop quantities, as CasADi expressions for registered problems."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..errors import ModelError


def gelfand_log_radius(matrix: ca.SX, power: int) -> ca.SX:
    """Smooth spectral-radius surrogate log(||M^p||_F) / p (Gelfand: -> log rho(M) as p -> inf); p a power of two."""
    if power < 1 or power & (power - 1):
        raise ModelError(f"gelfand_log_radius: power must be a power of two, got {power}")
    for _ in range(int(np.log2(power))):
        matrix = ca.mtimes(matrix, matrix)
    return 0.5 * ca.log(ca.sumsqr(matrix)) / power
