"""Local evidence that a returned point is a local solution: feasible points around it, none better.

A stationary point of the reduced objective need not be a minimum: zero poisoning is stationary for every attack (the
clean learner minimizes the attacker's loss) and is its *worst* point; a method may stop short of stationarity (IPOPT on
the Willems KKT route, 1.6e-4 below the vertex next to it), or at a kink of y*(x) where two LP vertices tie and F still
decreases along the kink, in a cone that random directions miss. Around x the probe tries seeded random directions, the
negative hypergradient, +/- each coordinate (up to defaults["probe.coordinates"] upper variables) and, at a kink (a
degenerate lower active set), the descent directions of the adjacent pieces; each is scaled per entry (a recognized
ball's radius on its block, else 1). It projects x + h d onto the box and balls for a few radii h (radii(): from
defaults["probe.radius"] down two decades; where none of those points is upper-feasible, three decades smaller at a time
down to defaults["probe.min_radius"]: around an attack's clean data, stealth constraints on an unstable plant's data
leave a feasible set of 4e-4 of the budget, and a probe that saw no feasible point certified the clean data a local
maximum), solves the lower level there independently (and at x itself, the baseline: with a non-unique lower solution F
depends on the solver's choice; with `optimistic`, F is taken at the best lower solution, as in
bilevel.solvers.verdict.optimistic; a method whose lower level has a unique solution may pass its own structured solver,
e.g. the VRFT learner's thin QR, which then solves at x and at all the probes in one call), and reports the best
upper-feasible point whose upper objective is lower than both F at x and the baseline by more than
defaults["probe.rel_tol"] (relative) along random directions, where at a stationary point the change is second order
(the tolerance sits at the lower solves' noise, not above it), and by more than defaults["probe.descent_rel_tol"] along
the first-order ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import nnls

from ...defaults import param
from ...errors import BilevelError, NonConvexLowerLevel
from ...parameters import CompiledFunction
from .optimistic import optimistic_selection
from ..engine.implicit import Hypergradient, shared_oracle
from ..engine.prepared import LowerSolve, Prepared
from ..engine.projections import Projection
from ..engine.structure import budget_scale


def radii() -> tuple[float, float, float]:
    """The probe's radii: defaults["probe.radius"], a tenth and a hundredth of it (budget units)."""
    h = float(param("probe.radius"))
    return h, h / 10, h / 100


@dataclass(frozen=True)
class Probe:
    """A better feasible point found near x: where, its upper objective (canonical sense), and the radius."""

    x: np.ndarray
    objective: float
    radius: float


@dataclass(frozen=True)
class ProbeOutcome:
    """What the probe found around x: a better feasible neighbour (or None) and, where it found none, the nearest
    probed point within the smallest radius radii()[-1] at which the lower level is not convex (point, radius, the
    Hessian's eigenvalue in words; or None): x is then at the edge of where the lower level is convex (a method that
    follows the convex lower level's solution stops there), and beyond it the probe cannot judge F."""

    better: Probe | None
    nonconvex: tuple[np.ndarray, float, str] | None = None


def improving_neighbour(prep: "Prepared", x: np.ndarray, objective: float, projection: Projection,
                        seed: int = 0, optimistic: bool = False, lower_solve: LowerSolve | None = None) -> Probe | None:
    """The better neighbour of probe_neighbours (same arguments), or None."""
    return probe_neighbours(prep, x, objective, projection, seed, optimistic, lower_solve).better


def probe_neighbours(prep: "Prepared", x: np.ndarray, objective: float, projection: Projection,
                     seed: int = 0, optimistic: bool = False, lower_solve: LowerSolve | None = None) -> ProbeOutcome:
    """The best neighbour of x in `projection`'s set, upper-feasible, with upper objective < objective -
    defaults["probe.rel_tol"] max(1, |objective|) (defaults["probe.descent_rel_tol"] along first-order directions), if
    the probe finds one, else the nearest probed point within radii()[-1] where the lower level is not convex, if any
    (ProbeOutcome).
    optimistic: F at each point with the optimistic selection among the lower solutions there; lower_solve: the lower
    level's unique solution at each row of a matrix of points (LowerSolve), used instead of the lower level's own
    solver (not with `optimistic`)."""
    none = ProbeOutcome(None)
    low = prep.canon.lower
    solve = None if optimistic else lower_solve
    try:  # the same lower solver as at the probes: a non-unique lower solution must not pass for a better point
        fixed_y = low.solve(x).y if low.fixed and not optimistic and solve is None else None  # ignores x: once
    except BilevelError:
        return none
    if solve is None:
        baseline, verified, _ = _feasible_objective(prep, x, fixed_y, optimistic)
        if baseline is None:
            return none
        optimistic = optimistic and verified  # where IPOPT verifies no selection at x, it is not asked at the probes
    rng = np.random.default_rng(seed)
    scale = budget_scale(prep.canon, prep.balls)
    directions = [(rng.standard_normal(x.size) * scale, "probe.rel_tol") for _ in range(param("probe.directions"))]
    directions += [(d, "probe.descent_rel_tol") for d in _first_order_directions(prep, x, scale, projection)]
    # one entry per direction, with the tolerances of the kinds it came as (random, first-order: in 1-D every random
    # one is also first-order); it is judged by the stricter bar of them
    kinds: dict[bytes, tuple[np.ndarray, frozenset[str]]] = {}
    for d, tol in directions:
        d = d / max(float(np.linalg.norm(d / scale)), 1e-300)
        key = np.round(d / scale, 12).tobytes()
        kinds[key] = (d, kinds.get(key, (d, frozenset()))[1] | {tol})
    here = x.tobytes()
    values: dict[bytes, float | None] = {} if solve is not None else {here: baseline}
    nonconvex: dict[bytes, str] = {}  # the probed points where the lower level is not convex, and why
    best: Probe | None = None
    probes_seen: list[tuple[np.ndarray, float, frozenset[str]]] = []
    # where no probe at radii() is feasible (a feasible set much narrower than the budget around x: stealth constraints
    # on an unstable plant's data), three decades smaller, down to defaults["probe.min_radius"]
    smallest = radii()[-1]
    for round_radii in _radius_rounds():
        probes = [(projection(x + h * d), h, tols) for d, tols in kinds.values() for h in round_radii]
        probes_seen += probes
        points = {key: xp for key, xp in ({here: x} | {xp.tobytes(): xp for xp, _, _ in probes}).items()
                  if key not in values}  # projections of probes may coincide
        values |= _objectives(prep, points, solve, fixed_y, optimistic, min(1.0, round_radii[-1] / smallest),
                              nonconvex)
        if values[here] is None:
            return none
        reference = min(objective, values[here])
        bars = {tol: reference - param(tol) * max(1.0, abs(reference))
                for tol in ("probe.rel_tol", "probe.descent_rel_tol")}
        for xp, h, tols in probes:
            F, bar = values[xp.tobytes()], min(bars[tol] for tol in tols)
            if F is not None and F < bar and (best is None or F < best.objective):
                best = Probe(xp, F, h)
        if any(values[xp.tobytes()] is not None for xp, _, _ in probes):
            break
    if best is not None:
        return ProbeOutcome(best)
    found = [(h, xp) for xp, h, _ in probes_seen if h <= smallest and xp.tobytes() in nonconvex]
    if not found:
        return none
    h, xp = min(found, key=lambda t: t[0])
    return ProbeOutcome(None, (xp, h, nonconvex[xp.tobytes()]))


def _radius_rounds() -> list[tuple[float, ...]]:
    """radii(), then radii() scaled by 1e-3, 1e-6, .. while their smallest is at least defaults["probe.min_radius"]."""
    rounds, factor, floor, base = [], 1.0, max(param("probe.min_radius"), 1e-300), radii()
    while not rounds or base[-1] * factor >= floor:
        rounds.append(tuple(h * factor for h in base))
        factor *= 1e-3
    return rounds


def _objectives(prep: "Prepared", points: dict[bytes, np.ndarray], solve: LowerSolve | None,
                fixed_y: np.ndarray | None, optimistic: bool, shrink: float,
                nonconvex: dict[bytes, str]) -> dict[bytes, float | None]:
    """F at each point as _feasible_objective finds it (None where unsolved or infeasible by more than
    defaults["probe.feas_tol"] times `shrink`: below radii(), in proportion to the radius, so that no more is gained
    by violating a constraint than at radii()); with `solve`, all in one call (_structured_objectives). The points
    where the lower level is not convex are added to `nonconvex` with why."""
    if not points:
        return {}
    feas_tol = shrink * param("probe.feas_tol")
    if solve is not None:
        return dict(zip(points, _structured_objectives(prep, np.array(list(points.values())), solve, feas_tol)))
    values = {}
    for key, xp in points.items():
        values[key], _, why = _feasible_objective(prep, xp, fixed_y, optimistic, feas_tol)
        if why:
            nonconvex[key] = why
    return values


def _first_order_directions(prep: "Prepared", x: np.ndarray, scale: np.ndarray,
                            projection: Projection) -> list[np.ndarray]:
    """-grad F(x, y*(x)) in budget units (the hypergradient, balls projected on); for at most
    defaults["probe.coordinates"] upper variables also +/- each coordinate and, at a kink of y*(x), the descent
    direction of each adjacent piece. The hypergradient is sampled at x +/- radii()[-1] along each coordinate; x is at a
    kink when its lower active set is degenerate or a sample's active set differs (two LP vertices that tie, an edge
    between them). Then -g for each piece's g, and the steepest descent direction -(least-norm element of their convex
    hull), which follows a kink along which F decreases. A method that stopped at a kink or short of stationarity is
    caught."""
    oracle = shared_oracle(prep, projected_rows=tuple(b.row for b in prep.balls))
    here = _gradient(oracle, x)
    out = [] if here is None or not np.any(here[0]) else [-here[0] * scale ** 2]
    if x.size > param("probe.coordinates"):
        return out
    steps = [sign * scale[i] * np.eye(x.size)[i] for i in range(x.size) for sign in (1.0, -1.0)]
    out += steps
    if here is None:
        return out
    samples = [g for g in (_gradient(oracle, projection(x + radii()[-1] * s)) for s in steps) if g is not None]
    if not here[1] and all(active == here[2] for _, _, active in samples):  # one piece: its direction is there
        return out
    G = np.array([here[0]] + [g for g, _, _ in samples]) * scale  # budget units
    size = max(1.0, float(np.abs(G).max()))
    pieces = np.unique(np.round(G / size, 8), axis=0) * size  # gradients equal up to the solves' noise: one piece
    out += [-g * scale for g in pieces if np.any(g)]
    if len(pieces) > 1:
        steepest = _least_norm_combination(pieces.T)
        if np.any(steepest):
            out.append(-steepest * scale)
    return out


def _gradient(oracle: "Hypergradient", x: np.ndarray) -> tuple[np.ndarray, bool, bytes] | None:
    """(grad phi(x), whether the lower active set is degenerate there, that active set), or None where it cannot
    be had."""
    try:
        ev = oracle.evaluate(x)
        grad, weak, _ = oracle.gradient(ev)
    except (BilevelError, np.linalg.LinAlgError, ValueError):
        return None
    return (grad, weak, (ev.lower.lam > oracle.active_tol).tobytes()) if np.all(np.isfinite(grad)) else None


def _least_norm_combination(G: np.ndarray) -> np.ndarray:
    """The least-norm point of the convex hull of G's columns (nonnegative least squares with the weights' sum
    held at 1 by a heavy row)."""
    weight = 1e3 * max(1.0, float(np.abs(G).max()))
    lam = nnls(np.vstack([G, np.full((1, G.shape[1]), weight)]), np.concatenate([np.zeros(G.shape[0]), [weight]]))[0]
    return G @ (lam / max(float(lam.sum()), 1e-300))


def _structured_objectives(prep: "Prepared", X: np.ndarray, solve: LowerSolve,
                           feas_tol: float | None = None) -> list[float | None]:
    """F at each row of X as _feasible_objective finds it, the lower solutions by `solve` in one call and F, G, H at
    every point in one call of the problem's functions mapped over them (None where `solve` finds no solution)."""
    try:
        ys = solve(X)
    except BilevelError:
        return [None] * len(X)
    known = [i for i, y in enumerate(ys) if y is not None]
    mapped = _mapped_functions(prep, len(known)) if known else None
    if mapped is None:
        return [None if y is None else _feasible_objective(prep, x, y, feas_tol=feas_tol)[0] for x, y in zip(X, ys)]
    F, G, H = mapped(X[known].T, np.array([ys[i] for i in known]).T)
    values: list[float | None] = [None] * len(X)
    for j, i in enumerate(known):
        values[i] = _feasible_value(prep, X[i], ys[i], F[:, j], G[:, j], H[:, j], feas_tol)
    return values


def _mapped_functions(prep: "Prepared", n: int) -> CompiledFunction | None:
    """(X, Y) -> F, G, H at the n columns of X and Y (the problem's functions mapped serially: each column computed as
    one call computes it), kept on prep; None where F is not computed by those functions (NumericSquares)."""
    functions = prep.canon.functions
    if not isinstance(functions, CompiledFunction):
        return None
    shared = [] if functions.params is None else [2]  # the parameters, the same for every column
    return prep.cached(("probe-points", n), lambda: CompiledFunction(
        functions.fun.map("probe_points", "serial", n, shared, []), functions.params))


def _feasible_value(prep: "Prepared", x: np.ndarray, y: np.ndarray, F: np.ndarray, G: np.ndarray,
                    H: np.ndarray, feas_tol: float | None = None) -> float | None:
    """The upper objective at (x, y) from the problem's F, G, H there, or None if (x, y) is upper-infeasible (by more
    than feas_tol, default defaults["probe.feas_tol"]) or it is not finite."""
    value = prep.canon.upper_F(x, y, F[0])
    feas_tol = param("probe.feas_tol", feas_tol)
    if np.any(G > feas_tol) or np.any(np.abs(H) > feas_tol) or not np.isfinite(value):
        return None
    return value


def _feasible_objective(prep: "Prepared", x: np.ndarray, y: np.ndarray | None = None,
                        optimistic: bool = False, feas_tol: float | None = None
                        ) -> tuple[float | None, bool, str]:
    """F(x, y), y from the lower level's own solver unless given (with `optimistic`, also the best verified lower
    solution there found from that one, the better of the two), whether such a selection was verified, and why the
    lower level is not convex at x where its solver refused it for that ('' otherwise); F is None if the solve fails
    or (x, y) is upper-infeasible (by more than feas_tol, as _feasible_value)."""
    try:
        sol = None if y is not None else prep.canon.lower.solve(x)
    except NonConvexLowerLevel as exc:
        return None, False, str(exc)
    except BilevelError:
        return None, False, ""
    ys = [y if sol is None else sol.y]
    if optimistic and sol is not None:
        sel = optimistic_selection(prep, x, float(prep.canon.lower.evaluate(x, sol.y)[0]), [sol.y])
        ys += [] if sel is None else [sel.y]
    values = [_feasible_value(prep, x, yv, *(np.asarray(v, dtype=float).ravel() for v in prep.canon.functions(x, yv)),
                              feas_tol) for yv in ys]
    return min((v for v in values if v is not None), default=None), len(ys) > 1, ""
