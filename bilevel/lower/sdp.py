"""SDP lower level: convex quadratic (or linear) objective, affine constraints and LMIs affine in y."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from .base import LowerSolution
from .quadratic import QuadraticLower, solve_qp_clarabel


@dataclass
class SemidefiniteLower(QuadraticLower):
    """min 1/2 y'Py + q'y s.t. Ay + b <= 0, Ey + e = 0, M_k(x, y) = M_k0(x) + sum_j y_j M_kj(x) >= 0."""

    kind = "sdp"

    def __post_init__(self) -> None:
        super().__post_init__()
        zero = ca.DM.zeros(self.n_y)
        outs = []
        for m in self.psd:
            outs += [ca.substitute(m, self.y, zero), ca.substitute(ca.jacobian(ca.vec(m), self.y), self.y, zero)]
        self._lmi = ca.Function("lmi_coeffs", [self.x], outs)

    def lmi_data(self, x: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """(M_k0, d vec(M_k)/dy) for every LMI at upper point x."""
        out = self._lmi(self.check_point(x))
        return tuple((np.asarray(out[2 * k]), np.asarray(out[2 * k + 1]).reshape(-1, self.n_y))
                     for k in range(len(self.psd)))

    def solve(self, x: np.ndarray) -> LowerSolution:
        """Solve the SDP at x with cvxpy + Clarabel; Z_k are the LMI multipliers (L = f - sum <Z_k, M_k>)."""
        return solve_qp_clarabel(self.data(x), f"at x = {np.array2string(np.asarray(x), precision=4)}",
                                 self.lmi_data(x))
