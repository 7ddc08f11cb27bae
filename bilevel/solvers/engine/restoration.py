"""Restoration of an upper point onto the upper feasible set along y*(x), by Gauss-Newton steps on its constraints.

Each step moves x by the minimum-norm dx that zeroes the linearization of the violated and active inequality rows
(G_i >= -tol, kept once seen) and of the equality rows, with the exact Jacobian along y*(x) (Hypergradient.jacobian),
then projects onto the upper bounds and balls. A step that does not at least halve the violation ends the
restoration: from far outside, the linearization of a nonlinear constraint (a statistic of the learner's residuals)
overshoots, and the caller then tries a point closer to its fallback.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ...defaults import param
from ...errors import BilevelError
from .implicit import Evaluation, Hypergradient

RESTORATION_STEPS = 6
"""Gauss-Newton steps of restore (Newton's rate reaches the tolerance in 2-5 from a point that converges)."""
CONTRACTION = 0.5
"""A step is kept when the violation falls at least to this fraction of the last one."""


def restore(oracle: Hypergradient, x: np.ndarray, projection: Callable[[np.ndarray], np.ndarray],
            steps: int = RESTORATION_STEPS) -> Evaluation | None:
    """The evaluated point reached from x with upper violation <= defaults["solvers.feasibility_tol"] (module
    docstring), or None if the steps stop contracting or the lower level or its derivative fails on the way."""
    tol = param("solvers.feasibility_tol")
    rows = np.zeros(0, dtype=int)
    try:
        ev = oracle.evaluate(x)
        for _ in range(steps):
            if ev.violation <= tol:
                return ev
            G, H = ev.upper[1].ravel(), ev.upper[2].ravel()
            rows = np.union1d(rows, np.flatnonzero(G >= -tol))
            J = oracle.jacobian(ev)[0]  # columns: d/dx of F, G_i, H_j
            A = np.hstack([J[:, 1 + rows], J[:, 1 + G.size:]]).T
            dx = A.T @ np.linalg.lstsq(A @ A.T, -np.concatenate([G[rows], H]), rcond=None)[0]
            new = oracle.evaluate(projection(ev.x + dx))
            if not new.violation <= CONTRACTION * ev.violation:
                return None
            ev = new
    except (BilevelError, np.linalg.LinAlgError):  # a singular learner, or no finite Jacobian, on the way
        return None
    return ev if ev.violation <= tol else None
