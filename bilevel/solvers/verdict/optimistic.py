"""The optimistic selection at an upper point: the best upper objective over the lower level's solution set.

Where the lower solution is not unique, the bilevel problem's value at x is min F(x, y) over the lower solutions y (the
optimistic convention; the leader picks among the follower's optimal responses); a method's y is one of them and need
not be that one. IPOPT (CasADi; independent of the methods' lower solves and of the MPCC) solves min_y F(x, y) s.t. g <=
0, h = 0, the upper rows that involve y, and f(x, y) <= f*(x) + defaults["optimistic.slack"] (1 + |f*|) from the given
starts; an answer counts only once verified at its y (rows within defaults["optimistic.row_tol"], lower gap within 10
defaults["optimistic.slack"]). Lower levels with LMIs are not handled (IPOPT does not take them): the caller gets None.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ...defaults import param
from ...lower.nlp import ipopt_options
from ..engine.prepared import Prepared


@dataclass(frozen=True)
class Selection:
    """A verified lower solution y at x, its upper objective (canonical sense), and price: the optimality row's
    multiplier times its slack, what the slack alone could have bought in F."""

    y: np.ndarray
    objective: float
    price: float

    def improves(self, F: float) -> bool:
        """Whether this selection's F is below F by more than defaults["optimistic.improve_rel_tol"] max(1, |F|) +
        price."""
        return self.objective < F - param("optimistic.improve_rel_tol") * max(1.0, abs(F)) - self.price


class _SelectionNLP:
    """min_y F(x, y) over {g <= 0, h = 0, upper rows in y, f <= bound}, x, bound and the data as parameters."""

    def __init__(self, prep: "Prepared") -> None:
        canon, low = prep.canon, prep.canon.lower.symbolic()
        G = [canon.G[i] for i in range(int(canon.G.numel())) if ca.depends_on(canon.G[i], canon.y)]
        H = [canon.H[i] for i in range(int(canon.H.numel())) if ca.depends_on(canon.H[i], canon.y)]
        bound = ca.SX.sym("bound")
        rows = ca.vertcat(low.g, *G, low.h, *H, low.f - bound)
        nlp = {"x": canon.y, "p": ca.vertcat(canon.x, bound, canon.params.sym), "f": canon.F, "g": rows}
        tol = param("optimistic.nlp_tol")
        options = ipopt_options(tol, param("optimistic.max_iter"), {"constr_viol_tol": tol})
        self.solver = ca.nlpsol("optimistic", "ipopt", nlp, options)
        n_ineq, n_eq = int(low.g.numel()) + len(G), int(low.h.numel()) + len(H)
        self.lbg = np.concatenate([np.full(n_ineq, -np.inf), np.zeros(n_eq), [-np.inf]])
        self.ubg = np.zeros(n_ineq + n_eq + 1)
        self.check = canon.params.function("optimistic_rows", [canon.x, canon.y],
                                           [canon.F, ca.vertcat(low.g, *G), ca.vertcat(low.h, *H), low.f])
        self.params = canon.params


def optimistic_selection(prep: "Prepared", x: np.ndarray, f_star: float,
                         starts: list[np.ndarray]) -> Selection | None:
    """The best verified selection from `starts` (lower solutions at x) of min F over the lower solutions at x,
    f* the lower optimal value there; None if IPOPT verifies none or the lower level has LMIs."""
    if prep.canon.lower.psd or not np.isfinite(f_star):
        return None
    nlp: _SelectionNLP = prep.cached(("optimistic-selection",), lambda: _SelectionNLP(prep))
    slack = param("optimistic.slack") * (1.0 + abs(f_star))
    p = np.concatenate([x, [f_star + slack], nlp.params.value])
    best: Selection | None = None
    for y0 in starts:
        sol = nlp.solver(x0=y0, p=p, lbg=nlp.lbg, ubg=nlp.ubg)
        if not nlp.solver.stats()["success"]:
            continue
        y = np.asarray(sol["x"], dtype=float).ravel()
        F, g, h, f = (np.asarray(v, dtype=float).ravel() for v in nlp.check(x, y))
        feas = param("optimistic.row_tol") * (1.0 + float(np.max(np.abs(y), initial=0.0)))
        if (np.any(g > feas) or np.any(np.abs(h) > feas) or f[0] - f_star > 10.0 * slack
                or not np.isfinite(F[0])):
            continue
        price = abs(float(np.asarray(sol["lam_g"]).ravel()[-1])) * slack
        if best is None or F[0] < best.objective:
            best = Selection(y, float(F[0]), price)
    return best
