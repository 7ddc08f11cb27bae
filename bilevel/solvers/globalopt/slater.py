"""Bounds on the lower level's multipliers from a Slater point: method "global" on a convex NLP lower level or on
lower constraint matrices depending on x, where multipliers enter products in the KKT stationarity.

Let the lower level be convex in y on a convex set Y holding its feasible set (proven before, form.py) and
let one point y^ of Y satisfy every lower row that depends on y strictly at every x of the upper box X:
g_i(x, y^) <= -s_i < 0. Then (i) Slater's condition holds at every x, so the KKT conditions are necessary and the
reformulation is exact; (ii) at a KKT point (y*, lam) at x, y* minimizes the convex Lagrangian L(., lam) = f + lam'g
over Y, so f(x, y*) = L(x, y*, lam) <= L(x, y^, lam) = f(x, y^) + lam'g(x, y^), and with lam >= 0 (rows free of y
are <= 0 wherever the lower level is feasible)

    lam_i <= (max_X f(., y^) - min f(x, y*)) / s_i    for every row i that depends on y

(Boyd & Vandenberghe (2004), Convex Optimization, sec. 5.2.3 and exercise 5.3's bound on dual variables from a
Slater point). The minimum of f runs over the box of (x, y) derived over the relaxed KKT polyhedron, which holds
every feasible point. y^ is found by IPOPT (the largest common margin at the box's vertices); s_i, max f and min f
are interval enclosures (lower/interval.py), so nothing rests on IPOPT's accuracy.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ...defaults import param
from ...errors import ModelError
from ...lower.interval import enclose
from ...lower.nlp import ipopt_options
from ..engine.prepared import Prepared
from .bigm import BigM
from .form import LOCAL_METHODS, LinearMPCC

CLASS = "class: lower multipliers without a derivable bound"


@dataclass(frozen=True)
class SlaterBounds:
    """A Slater point y^, the margins s_i of the lower rows at y^ over the upper box (nan for rows free of y), the
    range [f_low, f_high] the bound uses, and the bound on each row's multiplier (inf for rows free of y)."""

    point: np.ndarray
    margins: np.ndarray
    f_low: float
    f_high: float
    bounds: np.ndarray
    names: tuple[str, ...]

    def justification(self) -> tuple[str, ...]:
        """One line for the point and the range, one per bounded multiplier."""
        head = (f"multiplier bounds from the Slater point y^ = {np.array2string(self.point, precision=4)}: "
                f"lam_i <= (max f(x, y^) = {self.f_high:.6g} - min f = {self.f_low:.6g}) / s_i, s_i = -max_x g_i(x, y^)"
                " over the upper box (exact for rows affine in x, interval enclosures otherwise)",)
        return head + tuple(f"{n}: lam <= {b:.6g} (s = {s:.4g})" for n, s, b in zip(self.names, self.margins,
                                                                                   self.bounds) if np.isfinite(b))


def _refuse(what: str) -> ModelError:
    return ModelError("method 'global' needs a Slater point of the lower level (for its KKT conditions to be "
                      "necessary at rows nonlinear in y, and for bounds on the multipliers that enter products in the "
                      f"KKT stationarity); {what} ({CLASS}); {LOCAL_METHODS}")


def _corners(x_lb: np.ndarray, x_ub: np.ndarray, dims: np.ndarray) -> list[np.ndarray]:
    """The box's vertices over `dims` (the others at their midpoint, or 0 where unbounded), at most
    defaults["global.max_box_vertices"], and its centre."""
    mid = np.where(np.isfinite(x_lb) & np.isfinite(x_ub), 0.5 * (x_lb + x_ub), np.clip(0.0, x_lb, x_ub))
    points = [mid]
    for corner in itertools.islice(itertools.product(*[(x_lb[i], x_ub[i]) for i in dims]),
                                   int(param("global.max_box_vertices"))):
        x = mid.copy()
        x[dims] = corner
        points.append(x)
    return points


def _box_max(exprs: ca.SX, x: ca.SX, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
    """An upper bound on each entry of exprs (in x only) over the box: exact for an entry affine in x (its value at
    the centre plus |gradient| times the half-widths), an interval enclosure otherwise; None where none exists."""
    lo, hi = box
    finite = np.isfinite(lo) & np.isfinite(hi)
    centre, half = np.where(finite, 0.5 * (lo + hi), 0.0), np.where(finite, 0.5 * (hi - lo), np.inf)
    enclosed = enclose(ca.Function("box_max", [x], [ca.densify(exprs)]), [box])
    bounds = np.full(int(exprs.numel()), np.inf) if enclosed is None else enclosed[0][1].copy()
    for i in range(int(exprs.numel())):
        grad = ca.gradient(exprs[i], x)
        if not ca.depends_on(grad, x):
            at = ca.Function("affine_at", [x], [exprs[i], grad])
            value, slope = (np.asarray(v, dtype=float).ravel() for v in at(centre))
            moving = slope != 0.0
            bounds[i] = min(bounds[i], float(value[0] + np.abs(slope[moving]) @ half[moving]))
    return bounds if np.all(np.isfinite(bounds)) else None


def _slater_point(x: ca.SX, y: ca.SX, g: ca.SX, corners: list[np.ndarray], y_start: np.ndarray
                  ) -> tuple[np.ndarray, float]:
    """(y, s): the largest common margin s <= 1 of the rows g at the given upper points (IPOPT)."""
    s = ca.SX.sym("s")
    rows = ca.vertcat(*[ca.substitute(g, x, ca.DM(c)) + s for c in corners])
    solver = ca.nlpsol("slater", "ipopt", {"x": ca.vertcat(y, s), "f": -s, "g": rows},
                       ipopt_options(param("global.slater_tol"), param("global.slater_max_iter")))
    n = int(y.numel())
    sol = solver(x0=np.append(y_start, 0.0), lbx=np.append(np.full(n, -np.inf), -np.inf),
                 ubx=np.append(np.full(n, np.inf), 1.0), ubg=0.0)
    z = np.asarray(sol["x"], dtype=float).ravel()
    return z[:n], float(z[n])


def slater_bounds(x: ca.SX, y: ca.SX, f: ca.SX, g: ca.SX, h: ca.SX, names: list[str],
                  x_box: tuple[np.ndarray, np.ndarray], xy_box: tuple[np.ndarray, np.ndarray],
                  y_start: np.ndarray) -> SlaterBounds:
    """Bounds on every multiplier of a row of g (parameters substituted) that depends on y, by the module's
    argument: x_box the declared upper box, xy_box the derived box of (x, y); a ModelError naming what is missing
    where none can be derived."""
    if h.numel():
        raise _refuse("the lower level has equality constraints, whose multipliers' term mu'h(x, y^) the bound cannot "
                      "drop")
    rows = np.array([i for i in range(int(g.numel())) if ca.depends_on(g[i], y)], dtype=int)
    g_rows = g[rows.tolist()] if rows.size else ca.SX(0, 1)
    x_lb, x_ub = x_box
    dims = np.array([j for j in range(int(x.numel())) if ca.depends_on(ca.vertcat(g_rows, f), x[j])], dtype=int)
    if not np.all(np.isfinite(x_lb[dims]) & np.isfinite(x_ub[dims])):
        raise _refuse("the lower rows or objective depend on upper variables without finite bounds; declare bounds "
                      "on them")
    point, margin = _slater_point(x, y, g_rows, _corners(x_lb, x_ub, dims), y_start)
    rows_at = _box_max(ca.substitute(g_rows, y, ca.DM(point)), x, x_box) if np.all(np.isfinite(point)) else None
    if rows_at is None:
        raise _refuse("no Slater point was found")
    margins = -rows_at
    if not np.all(margins > 0.0):
        tight = [names[i] for i, s in zip(rows, margins) if not s > 0.0]
        raise _refuse(f"no point satisfies the lower rows {', '.join(tight)} strictly at every x of the upper box "
                      f"(the best common margin found is {margin:.3g}): Slater's condition is not shown")
    high = _box_max(ca.substitute(f, y, ca.DM(point)), x, x_box)
    n_x = int(x.numel())
    low = enclose(ca.Function("f_box", [x, y], [f]), [(xy_box[0][:n_x], xy_box[1][:n_x]),
                                                      (xy_box[0][n_x:], xy_box[1][n_x:])])
    if high is None or low is None or not (np.isfinite(high[0]) and np.isfinite(low[0][0][0])):
        raise _refuse("the lower objective has no finite range on the derived box of (x, y); declare bounds on the "
                      "lower variables")
    f_high, f_low = float(high[0]), float(low[0][0][0])
    safety = param("global.bigm_safety")
    bounds = np.full(int(g.numel()), np.inf)
    bounds[rows] = max(f_high - f_low, 0.0) / margins * (1.0 + safety) + safety
    all_margins = np.full(int(g.numel()), np.nan)
    all_margins[rows] = margins
    return SlaterBounds(point, all_margins, f_low, f_high, bounds, tuple(names))


def curved_rows(prep: Prepared) -> bool:
    """True when some lower row is nonlinear in y: Slater's condition is then what makes the KKT conditions
    necessary (affine rows need no constraint qualification)."""
    low = prep.canon.lower.symbolic()
    return any(ca.depends_on(ca.jacobian(low.g[i], low.y), low.y) for i in range(int(low.g.numel())))


def bound_multipliers(prep: Prepared, form: LinearMPCC, box: tuple[np.ndarray, np.ndarray], big_m: BigM,
                      multipliers: list[str]) -> tuple[tuple[np.ndarray, np.ndarray], BigM, SlaterBounds]:
    """The derived box and big-M with the Slater bounds on the lower multipliers (a convex NLP lower level, or
    `multipliers`, the names of those in products, non-empty); a ModelError where none can be derived."""
    if any(not v.startswith("lam[") for v in multipliers):
        raise _refuse(f"the equality multipliers {', '.join(v for v in multipliers if not v.startswith('lam['))} "
                      "enter products with x (an x-dependent lower equality matrix), and equality multipliers have "
                      "no sign and no Slater bound")
    low, canon = prep.canon.lower.symbolic(), prep.canon
    sub = low.params.substitute
    lam = prep.mpcc.blocks["lam"]
    x_cols = prep.mpcc.blocks["x"]
    y_cols = prep.mpcc.blocks["y"]
    xy = (np.concatenate([box[0][x_cols], box[0][y_cols]]), np.concatenate([box[1][x_cols], box[1][y_cols]]))
    y_lo, y_hi = xy[0][low.n_x:], xy[1][low.n_x:]
    y_start = np.clip(0.0, y_lo, y_hi)
    both = np.isfinite(y_lo) & np.isfinite(y_hi)
    y_start[both] = 0.5 * (y_lo[both] + y_hi[both])
    slater = slater_bounds(low.x, low.y, sub(low.f), sub(low.g), sub(low.h), list(low.g_names),
                           (canon.x_lb, canon.x_ub), xy, y_start)
    lo, hi = box[0].copy(), box[1].copy()
    hi[lam] = np.minimum(hi[lam], slater.bounds)
    multiplier, tightened = big_m.multiplier.copy(), set()
    for i in range(form.n_pairs):
        cols = np.flatnonzero(form.H[i])
        if cols.size == 1 and lam.start <= cols[0] < lam.stop and form.H[i, cols[0]] == 1.0 and form.h[i] == 0.0:
            bound = slater.bounds[cols[0] - lam.start]
            if bound < multiplier[i]:
                multiplier[i] = bound
                tightened.add(i)
    return (lo, hi), dataclasses.replace(big_m, multiplier=multiplier, slater=frozenset(tightened)), slater
