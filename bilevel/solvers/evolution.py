"""Method `differential-evolution`: a derivative-free search of the upper box on the implicit map, then the descent.

phi(x) = F(x, y*(x)) + penalty * (upper violation), from the implicit-differentiation engine (exact lower solves,
the minimum-norm selection of a non-unique SDP solution), is minimized over the declared upper box by scipy's
differential evolution (best1bin, Storn & Price 1997), the seeded population holding the multistart points
(bilevel.solvers.starts) and uniform points of the box; a point where the lower level cannot be solved scores
UNSOLVED; where the lower level ignores x (solved once) the population is scored by one mapped sweep per
generation. Only a box is searched, so every upper variable needs finite bounds. With polish (default) the engine's
projected descent (bilevel.solvers.hypergradient.descend) runs from the best member and its verdict is the run's;
without it the best member is a heuristic's answer, never `solved`.

Default budget, for n upper entries: min(15 n, MEMBERS) members (scipy's popsize 15, capped so a generation costs a
bounded number of lower solves on 80-1,000 upper variables) and min(100, max(20, EVALUATIONS // members))
generations (100 up to 30 members, as scipy's default), so a default run costs at most about EVALUATIONS + 2 MEMBERS
lower solves whatever n is (then the descent). Option popsize sets popsize * n members (scipy's meaning), max_iter
the generations. Option time_limit stops the search between evaluations once one point has been scored (the members left in that
generation score UNSOLVED) and bounds the descent; verbose reports each generation.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import scipy.optimize

from ..errors import BilevelError, ModelError
from ..reduction import KKTPoint
from ..result import Status
from .base import MethodRun, Prepared, check_options
from .hypergradient import DESCENT_FTOL, DESCENT_MAX_ITER, DESCENT_TOL, Arc, descend
from .implicit import ACTIVE_TOL, DEFAULT_PENALTY, Evaluation, shared_oracle
from .limits import deadline, progress
from .options import check_counts
from .starts import start_points

UNSOLVED = 1e20
"""phi's stand-in where the lower level cannot be solved (differential evolution ranks finite values only)."""
MEMBERS, EVALUATIONS = 64, 3000
"""The default budget's caps: members of the population, and evaluations the generations are sized to."""


def default_budget(n: int) -> tuple[int, int]:
    """(members, generations) of a default run on n upper entries (module docstring)."""
    members = max(5, min(15 * n, MEMBERS))
    return members, min(100, max(20, EVALUATIONS // members))


def evolve(values: Callable[[np.ndarray], Any], lb: np.ndarray, ub: np.ndarray, rng: np.random.Generator,
           max_iter: int, popsize: int, tol: float, stop: Callable[[Any], bool] | None = None,
           vectorized: bool = False, init: str | np.ndarray = "latinhypercube") -> scipy.optimize.OptimizeResult:
    """scipy's differential evolution (best1bin, no gradient polish) minimizing `values` over the box [lb, ub];
    vectorized: `values` maps an (n, S) array of S points to S values (the population is then updated per generation).
    """
    return scipy.optimize.differential_evolution(
        values, list(zip(lb, ub)), maxiter=int(max_iter), popsize=int(popsize), tol=float(tol), polish=False, rng=rng,
        callback=stop, vectorized=vectorized, updating="deferred" if vectorized else "immediate", init=init)


def solve_evolution(prep: Prepared, **options: Any) -> MethodRun:
    """Differential evolution over the upper box (options: starts, seed, max_iter generations, popsize, tol, penalty,
    polish, time_limit, verbose; default budget in the module docstring), then the engine's descent from its best
    point unless polish=False."""
    check_options("differential-evolution", options, {"starts", "seed", "max_iter", "popsize", "tol", "penalty",
                                                      "polish", "time_limit", "verbose"})
    canon = prep.canon
    lb, ub = canon.x_lb, canon.x_ub
    if not (np.all(np.isfinite(lb)) and np.all(np.isfinite(ub))):
        free = int(np.count_nonzero(~(np.isfinite(lb) & np.isfinite(ub))))
        raise ModelError(f"differential-evolution searches the upper box, but {free} of the {lb.size} upper entries "
                         "have no finite bound on some side: declare lb and ub on every upper variable, or use "
                         "method 'hypergradient'")
    check_counts(options, ("popsize",))
    members, generations = default_budget(lb.size)
    if "popsize" in options:
        members = max(5, options["popsize"] * lb.size)
    generations = int(options.get("max_iter", generations))
    penalty = float(options.get("penalty", DEFAULT_PENALTY))
    oracle = shared_oracle(prep, penalty)
    rng = np.random.default_rng(options.get("seed", 0))
    limit, verbose = deadline(options), options.get("verbose")
    seeded = [np.clip(x, lb, ub) for x in start_points(prep, int(options.get("starts", 1)), rng, 1.0)][:members]
    population = np.array(seeded + [rng.uniform(lb, ub) for _ in range(members - len(seeded))])
    best: dict[str, Evaluation] = {}

    def ranked(phi: Any) -> Any:
        """phi as differential evolution ranks it: NaN and +inf (and anything beyond) as UNSOLVED."""
        return np.clip(np.nan_to_num(phi, nan=UNSOLVED, posinf=UNSOLVED, neginf=-UNSOLVED), -UNSOLVED, UNSOLVED)

    def value(x: np.ndarray) -> float:
        if "ev" in best and limit.expired():  # the rest of this generation is not evaluated; the callback then stops
            return UNSOLVED
        try:
            ev = oracle.evaluate(np.asarray(x, dtype=float))
        except BilevelError:
            return UNSOLVED
        if ranked(ev.phi) < UNSOLVED and ("ev" not in best or ev.phi < best["ev"].phi):
            best["ev"] = ev
        return float(ranked(ev.phi))

    def batch(xs: np.ndarray) -> np.ndarray:  # a lower level that ignores x: the population in one mapped sweep
        xs = np.asarray(xs, dtype=float)
        if "ev" in best and limit.expired():
            return np.full(xs.shape[1], UNSOLVED)
        try:
            phi = ranked(oracle.batch_phi(xs))
        except BilevelError:  # the (one) lower solve failed: nowhere to go
            return np.full(xs.shape[1], UNSOLVED)
        i = int(np.argmin(phi))
        if phi[i] < UNSOLVED and ("ev" not in best or phi[i] < best["ev"].phi):
            best["ev"] = oracle.evaluate(xs[:, i])
        return phi

    def generation(intermediate_result: scipy.optimize.OptimizeResult) -> bool:  # scipy passes it by this name
        """One progress line per generation; True (stop) at the deadline."""
        progress(verbose, "differential-evolution", f"generation {intermediate_result.nit}/{generations}: best phi = "
                 f"{prep.declared(intermediate_result.fun):.6g} ({intermediate_result.nfev} evaluations)")
        return limit.expired()

    fixed = oracle.low.fixed
    progress(verbose, "differential-evolution", f"{members} members, up to {generations} generations")
    out = evolve(batch if fixed else value, lb, ub, rng, generations, 15, float(options.get("tol", 1e-8)),
                 stop=generation, vectorized=fixed, init=population)
    if "ev" not in best:
        return MethodRun(None, Status.ERROR, f"the lower level could not be solved at any of the {out.nfev} points "
                         "differential evolution tried", int(out.nit))
    found = best["ev"]
    searched = limit.reached() if limit.hit else str(out.message)
    stats = {"generations": int(out.nit), "evaluations": int(out.nfev), "evolution_objective": found.F,
             "evolution_message": searched, "members": members, "penalty": penalty}
    record = {"start": 0, "objective": found.F, "residual": found.violation, "generations": int(out.nit)}
    start = None
    if options.get("polish", True):  # the descent's own oracle: recognized balls projected on, not penalized
        polish = shared_oracle(prep, penalty, ACTIVE_TOL, tuple(b.row for b in prep.balls))
        arc = Arc(prep, polish, prep.projection)
        start = arc(found.x)
    if start is None:
        w = prep.pack(KKTPoint(found.x, found.lower.y, found.lower.lam, found.lower.mu, found.lower.Z))
        message = (f"best of {out.nfev} points of differential evolution ({searched}); a heuristic: no optimality "
                   "claim")
        status = Status.MAX_ITERATIONS if limit.hit else Status.INACCURATE
        return MethodRun(w, status, message, int(out.nit), [], [record | {"status": status.value}], stats)

    def report(rec: dict[str, Any]) -> None:
        progress(verbose, "differential-evolution", f"descent iteration {rec['iter']}: phi = "
                 f"{prep.declared(rec['objective']):.8g}, projected step {rec['projected_step_norm']:.2e}")

    run = descend(arc, start, DESCENT_TOL, DESCENT_FTOL, DESCENT_MAX_ITER, limit, report if verbose else None)
    p = run.point
    w = prep.pack(KKTPoint(p.x, p.lower.y, p.lower.lam, p.lower.mu, p.lower.Z))
    message = f"descent from the best of {out.nfev} points of differential evolution ({searched}): {run.message}"
    status = Status.MAX_ITERATIONS if limit.hit else run.status
    return MethodRun(w, status, message, int(out.nit) + run.nit, run.history,
                     [record | {"status": status.value, "iterations": run.nit, "objective": p.F,
                                "residual": p.violation}], stats)
