"""Big-M values derived, never guessed: each slack G_i and multiplier H_i maximized by an LP over the relaxed KKT
polyhedron R (all linear MPCC constraints and bounds, G >= 0, H >= 0, complementarity dropped).

Every MPCC point lies in R, so max_R G_i and max_R H_i bound G_i and H_i at every feasible point (in particular at
the optimum): a big-M at least that large cannot cut it. Before that, sides are fixed where R forces them: if
min_R G_i > 0 the slack is positive at every feasible point, so complementarity forces H_i = 0 (and vice versa);
R shrinks by these equalities and the LPs are repeated until nothing more is fixed. An unbounded LP means no
big-M exists for that pair; the method then branches on the pairs instead (Fortuny-Amat & McCarl 1981 for the
big-M form; Kleinert, Labbé, Plein & Schmidt (2020), "There's no free lunch: on the hardness of choosing a
correct big-M in bilevel optimization", Oper. Res. 68:1716-1721, show that guessed values can cut the optimum).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...defaults import param
from .nodes import G_SIDE, H_SIDE, Relaxation


@dataclass(frozen=True)
class BigM:
    """Bounds on each pair's slack G_i and multiplier H_i over R (inf where the LP is unbounded), and the sides
    R forces (pair index -> G_SIDE or H_SIDE)."""

    slack: np.ndarray
    multiplier: np.ndarray
    labels: tuple[str, ...]
    fixed: dict[int, int] = field(default_factory=dict)
    slater: frozenset[int] = frozenset()
    """Pairs whose multiplier bound comes from a Slater point (slater.py), not from an LP over R."""

    @property
    def finite(self) -> bool:
        """True when every pair has finite bounds (the MILP path applies)."""
        return bool(np.all(np.isfinite(self.slack)) and np.all(np.isfinite(self.multiplier)))

    def justification(self) -> tuple[str, ...]:
        """One line per pair: its two bounds, or its forced side, and where they come from."""
        def say(v: float, slater: bool = False) -> str:
            if slater:
                return f"{v:.6g} (Slater bound)"
            return f"{v:.6g} (LP max over R + margin)" if np.isfinite(v) else "unbounded over R (no big-M; branched)"

        lines = []
        for i, (name, s, m) in enumerate(zip(self.labels, self.slack, self.multiplier)):
            side = self.fixed.get(i)
            if side == H_SIDE:
                lines.append(f"{name}: multiplier = 0 (its slack has a positive minimum over R), slack <= {say(s)}")
            elif side == G_SIDE:
                lines.append(f"{name}: slack = 0 (its multiplier has a positive minimum over R), "
                             f"multiplier <= {say(m, i in self.slater)}")
            else:
                lines.append(f"{name}: slack <= {say(s)}, multiplier <= {say(m, i in self.slater)}")
        return tuple(lines)


def _extreme(relax: Relaxation, row: np.ndarray, const: float, fixed: dict[int, int], sign: float) -> float:
    """max (sign = 1) or min (sign = -1) of row'w + const over R with `fixed`; a failed LP gives the safe answer
    (inf for a max, -inf for a min: no bound, no fixing); nan if R is empty."""
    sol = relax.minimize_linear(-sign * row, fixed)
    if sol.status == "optimal":
        return -sign * sol.value + const
    if sol.status == "infeasible":
        return np.nan
    return sign * np.inf


def _widen(value: float) -> float:
    safety = param("global.bigm_safety")
    return max(value, 0.0) * (1.0 + safety) + safety if np.isfinite(value) else np.inf


def derive_big_m(relax: Relaxation) -> BigM | None:
    """Fix the sides R forces, then bound every slack and multiplier over R (LPs on relax's HiGHS model).

    None when fixing empties R, i.e. some pair can be complementary at no point: the MPCC is infeasible.
    """
    f = relax.form
    nonlinear = f.nonlinear_pairs  # slack nonlinear in x: no LP bound, never fixed by its slack's minimum
    fixed: dict[int, int] = {}
    while True:
        slack = np.array([np.inf if i in nonlinear else _extreme(relax, f.G[i], f.g[i], fixed, 1.0)
                          for i in range(f.n_pairs)])
        mult = np.array([_extreme(relax, f.H[i], f.h[i], fixed, 1.0) for i in range(f.n_pairs)])
        if np.any(np.isnan(slack)) or np.any(np.isnan(mult)):
            return None
        new = {}
        for i in range(f.n_pairs):
            if i in fixed:
                continue
            fix_tol = param("global.fix_tol")
            if i not in nonlinear and _extreme(relax, f.G[i], f.g[i], fixed, -1.0) > fix_tol * max(1.0, slack[i]):
                new[i] = H_SIDE
            elif _extreme(relax, f.H[i], f.h[i], fixed, -1.0) > fix_tol * max(1.0, mult[i]):
                new[i] = G_SIDE
        if not new:
            break
        fixed.update(new)
    slack, mult = np.array([_widen(v) for v in slack]), np.array([_widen(v) for v in mult])
    for i, side in fixed.items():  # a fixed side is zero at every feasible point: its bound is exact
        (mult if side == H_SIDE else slack)[i] = 0.0
    return BigM(slack, mult, f.labels, fixed)


def derive_bounds(relax: Relaxation, fixed: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) bounds of every MPCC variable over R with `fixed` (LP minima and maxima widened by the margin;
    -inf / inf where unbounded): the box SCIP's spatial branch-and-bound branches in."""
    eye = np.eye(relax.form.n)
    hi = np.array([_extreme(relax, e, 0.0, fixed, 1.0) for e in eye])
    lo = np.array([_extreme(relax, e, 0.0, fixed, -1.0) for e in eye])
    margin = param("global.bigm_safety") * (1.0 + np.maximum(np.abs(lo), np.abs(hi)))
    return np.maximum(lo - margin, relax.form.lb), np.minimum(hi + margin, relax.form.ub)
