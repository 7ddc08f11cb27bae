"""Big-M values derived, never guessed: each slack G_i and multiplier H_i maximized by an LP over the relaxed KKT
polyhedron R (all linear MPCC constraints and bounds, G >= 0, H >= 0, complementarity dropped).

Every MPCC point lies in R, so max_R G_i and max_R H_i bound G_i and H_i at every feasible point (in particular at
the optimum): a big-M at least that large cannot cut it. An unbounded LP means no big-M exists for that pair;
the method then branches on the pairs instead (Fortuny-Amat & McCarl 1981 for the big-M form; the bounding LPs
follow Kleinert, Labbé, Plein & Schmidt (2020), "There's no free lunch: on the hardness of choosing a correct
big-M in bilevel optimization", Oper. Res. 68:1716-1721, which shows guessed values can cut the optimum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog

from ..errors import SolverFailed
from .global_form import LinearMPCC

SAFETY = 1e-6
"""Relative and absolute margin added to each LP maximum so that LP tolerances cannot make M too small."""


@dataclass(frozen=True)
class BigM:
    """Bounds on each pair's slack G_i and multiplier H_i over R (inf where the LP is unbounded)."""

    slack: np.ndarray
    multiplier: np.ndarray
    labels: tuple[str, ...]

    @property
    def finite(self) -> bool:
        """True when every pair has finite bounds (the MILP path applies)."""
        return bool(np.all(np.isfinite(self.slack)) and np.all(np.isfinite(self.multiplier)))

    def justification(self) -> tuple[str, ...]:
        """One line per pair: its two bounds and where they come from."""
        def say(v: float) -> str:
            return f"{v:.6g} (LP max over R + margin)" if np.isfinite(v) else "unbounded over R (no big-M; branched)"

        return tuple(f"{name}: slack <= {say(s)}, multiplier <= {say(m)}"
                     for name, s, m in zip(self.labels, self.slack, self.multiplier))


def _lp_max(form: LinearMPCC, row: np.ndarray, const: float, A_ub: np.ndarray, b_ub: np.ndarray,
            bounds: np.ndarray) -> float:
    """max row'w + const over R (inf if unbounded); raises SolverFailed if HiGHS fails (R must be nonempty)."""
    res = linprog(-row, A_ub=A_ub, b_ub=b_ub, A_eq=form.A_eq if form.b_eq.size else None,
                  b_eq=form.b_eq if form.b_eq.size else None, bounds=bounds, method="highs")
    if res.status == 3:
        return np.inf
    if res.status != 0:
        raise SolverFailed(f"HiGHS failed on a big-M bounding LP: {res.message}")
    value = max(-float(res.fun) + const, 0.0)
    return value * (1.0 + SAFETY) + SAFETY


def derive_big_m(form: LinearMPCC) -> BigM:
    """Bound every slack and multiplier over R by one LP each (2 LPs per pair)."""
    A_ub = np.vstack([form.A_in, -form.G, -form.H])
    b_ub = np.concatenate([form.b_in, form.g, form.h])
    bounds = np.column_stack([form.lb, form.ub])
    slack = np.array([_lp_max(form, form.G[i], form.g[i], A_ub, b_ub, bounds) for i in range(form.n_pairs)])
    mult = np.array([_lp_max(form, form.H[i], form.h[i], A_ub, b_ub, bounds) for i in range(form.n_pairs)])
    return BigM(slack, mult, form.labels)
