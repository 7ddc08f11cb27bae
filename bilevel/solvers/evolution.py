"""Method `differential-evolution`: a derivative-free search of the upper box on the implicit map, then the descent.

phi(x) = F(x, y*(x)) + penalty * (upper violation), from the implicit-differentiation engine (exact lower solves,
the minimum-norm selection of a non-unique SDP solution), is minimized over the declared upper box by scipy's
differential evolution (best1bin, Storn & Price 1997), the seeded population holding the multistart points
(bilevel.solvers.engine.starts) and uniform points of the box; a point where the lower level cannot be solved scores
UNSOLVED; where the lower level ignores x (solved once) the population is scored by one mapped sweep per
generation. Only a box is searched, so every upper variable needs finite bounds. With polish (default) the engine's
projected descent (bilevel.solvers.hypergradient.descend) runs from the best member and its verdict is the run's;
without it the best member is a heuristic's answer, never `solved`.

Default budget, for n upper entries: min(15 n, MEMBERS) members (scipy's popsize 15, capped so a generation costs a
bounded number of lower solves on 80-1,000 upper variables) and min(100, max(20, EVALUATIONS // members))
generations (100 up to 30 members, as scipy's default), so a default run costs at most about EVALUATIONS + 2 MEMBERS
lower solves whatever n is (then the descent); MEMBERS and EVALUATIONS are defaults["evolution.members"] and
defaults["evolution.evaluations"]. Option popsize sets popsize * n members (scipy's meaning), max_iter
the generations. Option time_limit stops the search between evaluations once one point has been scored (the members left in that
generation score UNSOLVED) and bounds the descent; verbose reports each generation.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import scipy.optimize

from ..defaults import param
from ..errors import BilevelError, ModelError
from ..reduction import KKTPoint
from ..result import Status
from .engine.prepared import MethodRun, Prepared, check_options
from .hypergradient import Arc, Descent, descend, intermediate
from .engine.implicit import shared_oracle
from .engine.limits import GOAL_STOP, Deadline, progress
from .engine.options import check_counts
from .engine.starts import start_points

UNSOLVED = 1e20
"""phi's stand-in where the lower level cannot be solved (differential evolution ranks finite values only)."""


def default_budget(n: int) -> tuple[int, int]:
    """(members, generations) of a default run on n upper entries (module docstring)."""
    members = max(5, min(15 * n, param("evolution.members")))
    return members, min(100, max(20, param("evolution.evaluations") // members))


MUTATION, RECOMBINATION = (0.5, 1.0), 0.7
"""scipy's defaults: the differential weight drawn uniformly from MUTATION each generation (dither), and the crossover
probability."""


def _others(rng: np.random.Generator, members: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Two distinct population indices per entry of `members`, both different from it, uniformly at random."""
    r0 = rng.integers(size - 1, size=members.size)
    r0 = r0 + (r0 >= members)
    lo, hi = np.minimum(members, r0), np.maximum(members, r0)
    r1 = rng.integers(size - 2, size=members.size)
    r1 = r1 + (r1 >= lo)
    return r0, r1 + (r1 >= hi)


def _generation(rng: np.random.Generator, unit: np.ndarray, best: int, weight: float, lb: np.ndarray,
                width: np.ndarray, values: Callable[[np.ndarray], Any]) -> tuple[np.ndarray, np.ndarray]:
    """One deferred generation of evolve on the population `unit` (members x n, in the unit box): the best1bin
    trials and their values, scored by values at their points (n x members). The draws, in order, and each entry's
    arithmetic are evolve's member loop's; the arrays are updated in place, masks applied as index lists."""
    size, n = unit.shape
    r0, r1 = _others(rng, np.arange(size), size)
    trial = unit[r0]
    np.subtract(trial, unit[r1], out=trial)
    np.multiply(trial, weight, out=trial)
    np.add(trial, unit[best], out=trial)  # the mutant unit[best] + weight * (unit[r0] - unit[r1])
    keep = rng.random((size, n), dtype=np.float32) >= RECOMBINATION  # not crossed over
    keep[np.arange(size), rng.integers(n, size=size)] = False
    flat = trial.reshape(-1)  # masks as index lists: a random mask's branches cost more than the gather
    kept = np.flatnonzero(keep)
    flat[kept] = unit.reshape(-1)[kept]
    outside = np.flatnonzero((trial < 0.0) | (trial > 1.0))  # redrawn in C order, as trial[mask] = draws
    flat[outside] = rng.uniform(size=outside.size)
    points = np.multiply(trial, width)
    np.add(points, lb, out=points)
    return trial, np.asarray(values(points.T), dtype=float).ravel()


def evolve(values: Callable[[np.ndarray], Any], lb: np.ndarray, ub: np.ndarray, rng: np.random.Generator,
           max_iter: int, popsize: int, tol: float, stop: Callable[[Any], bool] | None = None,
           vectorized: bool = False, init: str | np.ndarray = "latinhypercube") -> scipy.optimize.OptimizeResult:
    """Differential evolution minimizing `values` over the box [lb, ub] (Storn & Price 1997, the algorithm of scipy's
    differential_evolution with its defaults and no gradient polish: best1bin, MUTATION dithered per generation,
    RECOMBINATION, max(5, popsize * n) members from a Latin hypercube or the rows of `init`, an entry leaving the box
    redrawn uniformly; stops after max_iter generations, when std(energies) <= tol * |mean(energies)|, or when
    stop(intermediate_result) is true).
    vectorized: `values` maps an (n, S) array of S points to S values; a generation is then drawn from the population
    as it was and scored in one call (scipy's updating='deferred'); otherwise point by point, each accepted trial
    joining the population at once ('immediate'). Sample selection and crossover are drawn for the whole generation
    at once (scipy draws them member by member: its permutation per member dominates the time of a large
    population on a cheap objective), so the random stream, not the algorithm, differs from scipy's."""
    lb, ub = np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)
    n, width = lb.size, ub - lb
    if isinstance(init, str):
        size = max(5, int(popsize) * n)
        strata = (rng.uniform(size=(size, n)) + np.arange(size)[:, None]) / size
        unit = np.column_stack([strata[rng.permutation(size), j] for j in range(n)])
    else:
        unit = np.clip((np.asarray(init, dtype=float) - lb) / np.where(width > 0, width, 1.0), 0.0, 1.0)
        size = unit.shape[0]

    def score(u: np.ndarray) -> np.ndarray:
        points = lb + u * width
        if vectorized:
            return np.asarray(values(points.T), dtype=float).ravel()
        return np.array([float(values(point)) for point in points])

    energies = score(unit)
    best, nfev, message, success = int(np.argmin(energies)), size, "Maximum number of iterations has been exceeded.", False
    nit = 0
    for nit in range(1, int(max_iter) + 1):
        weight = rng.uniform(*MUTATION)
        if vectorized:  # the whole generation in place: the same arithmetic and draws as the member loop below
            trial, trial_energies = _generation(rng, unit, best, weight, lb, width, values)
            nfev += size
            better = np.flatnonzero(trial_energies <= energies)
            unit[better], energies[better] = trial[better], trial_energies[better]
            best = int(np.argmin(energies))
        else:  # immediate: member by member, each trial scored on its own
            for members in np.arange(size)[:, None]:
                r0, r1 = _others(rng, members, size)
                mutant = unit[best] + weight * (unit[r0] - unit[r1])
                cross = rng.random((members.size, n), dtype=np.float32) < RECOMBINATION
                cross[np.arange(members.size), rng.integers(n, size=members.size)] = True
                trial = np.where(cross, mutant, unit[members])
                outside = (trial < 0.0) | (trial > 1.0)
                trial[outside] = rng.uniform(size=int(outside.sum()))
                trial_energies = score(trial)
                nfev += members.size
                better = trial_energies <= energies[members]
                unit[members[better]], energies[members[better]] = trial[better], trial_energies[better]
                best = int(np.argmin(energies)) if energies[members[0]] <= energies[best] else best
        state = scipy.optimize.OptimizeResult(x=lb + unit[best] * width, fun=float(energies[best]), nit=nit, nfev=nfev)
        if stop is not None and stop(state):
            message = "callback function requested stop early"
            break
        if np.all(np.isfinite(energies)) and np.std(energies) <= tol * np.abs(np.mean(energies)):
            message, success = "Optimization terminated successfully.", True
            break
    return scipy.optimize.OptimizeResult(x=lb + unit[best] * width, fun=float(energies[best]), nit=nit, nfev=nfev,
                                         message=message, success=success)


def solve_evolution(prep: Prepared, *, starts: int | None = None, seed: Any = 0, popsize: int | None = None,
                    max_iter: int | None = None, pop_tol: float | None = None, penalty: float | None = None,
                    polish: bool = True, callback: Callable[[scipy.optimize.OptimizeResult], Any] | None = None,
                    batch_objective: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                    time_limit: float | None = None, verbose: bool = False, **unknown: Any) -> MethodRun:
    """Differential evolution over the upper box, then the engine's descent from its best point unless polish=False.
    An option left None takes the registry's value (bilevel.defaults: evolution.NAME, implicit.penalty) or the
    default budget of the module docstring.

    starts: multistart points seeded into the population; seed: the random stream's seed; popsize: popsize * n
    members; max_iter: generations; pop_tol: the search stops when the population's values spread by at most pop_tol
    relative to their mean; penalty: weight of the penalized upper violation; polish: run the descent
    (hypergradient's defaults) from the best member; time_limit (seconds); verbose: one line per generation.
    callback(intermediate) sees each generation's best point (x, y, fun declared) and, with polish, every point of the
    descent; raising StopIteration ends the method there (the caller's goal). batch_objective(xs, y) -> the declared
    upper objective at each column of xs (n_x x S) with lower solution y: where the lower level ignores x and only the
    box constrains x, it scores a generation in one numeric call instead of the engine's mapped sweep (the caller's
    vectorized twin of its objective)."""
    check_options("differential-evolution", unknown, solve_evolution)
    canon = prep.canon
    lb, ub = canon.x_lb, canon.x_ub
    if not (np.all(np.isfinite(lb)) and np.all(np.isfinite(ub))):
        free = int(np.count_nonzero(~(np.isfinite(lb) & np.isfinite(ub))))
        raise ModelError(f"differential-evolution searches the upper box, but {free} of the {lb.size} upper entries "
                         "have no finite bound on some side: declare lb and ub on every upper variable, or use "
                         "method 'hypergradient'")
    check_counts({} if popsize is None else {"popsize": popsize}, ("popsize",))
    members, generations = default_budget(lb.size)
    if popsize is not None:
        members = max(5, popsize * lb.size)
    generations = int(generations if max_iter is None else max_iter)
    penalty = float(param("implicit.penalty", penalty))
    oracle = shared_oracle(prep, penalty)
    rng = np.random.default_rng(seed)
    limit = Deadline(time_limit)
    seeded = [np.clip(x, lb, ub) for x in start_points(prep, int(param("evolution.starts", starts)), rng, 1.0)][:members]
    population = np.array(seeded + [rng.uniform(lb, ub) for _ in range(members - len(seeded))])
    best: dict[str, Any] = {}

    def ranked(phi: Any) -> Any:
        """phi as differential evolution ranks it: NaN and +inf (and anything beyond) as UNSOLVED."""
        if isinstance(phi, np.ndarray) and phi.dtype == float and np.all(np.abs(phi) < UNSOLVED):
            return phi  # all finite and inside: as it is (the common case, without nan_to_num's copies)
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
            if twin is not None and "y" not in best:
                best["y"] = oracle.evaluate(xs[:, 0]).lower  # the lower solution, the same at every x
            phi = ranked(oracle.batch_phi(xs) if twin is None else
                         prep.declared(twin(xs, best["y"].y)))  # declared -> minimized
        except BilevelError:  # the (one) lower solve failed: nowhere to go
            return np.full(xs.shape[1], UNSOLVED)
        i = int(np.argmin(phi))
        if phi[i] < UNSOLVED and ("ev" not in best or phi[i] < best["ev"].phi):
            best["ev"] = oracle.evaluate(xs[:, i])
        return phi

    goal = []

    def generation(intermediate_result: scipy.optimize.OptimizeResult) -> bool:  # scipy passes it by this name
        """One progress line per generation; True (stop) at the deadline or where the callback raises StopIteration."""
        if verbose:  # the line is formatted only when it is shown (a generation can cost under a millisecond)
            progress(verbose, "differential-evolution", f"generation {intermediate_result.nit}/{generations}: best "
                     f"phi = {prep.declared(intermediate_result.fun):.6g} ({intermediate_result.nfev} evaluations)")
        if callback is not None and "ev" in best:
            try:
                callback(intermediate(prep, best["ev"]))
            except StopIteration:
                goal.append(best["ev"])
                return True
        return limit.expired()

    fixed, twin = oracle.low.fixed, batch_objective
    if twin is not None and (not callable(twin) or not fixed or canon.G.numel() + canon.H.numel()):
        raise ModelError("option batch_objective must be a callable(xs, y), for a lower level that ignores the upper "
                         "variables and a problem without upper constraints besides the box; drop it otherwise")
    progress(verbose, "differential-evolution", f"{members} members, up to {generations} generations")
    out = evolve(batch if fixed else value, lb, ub, rng, generations, 15, float(param("evolution.pop_tol", pop_tol)),
                 stop=generation, vectorized=fixed, init=population)
    if "ev" not in best:
        return MethodRun(None, Status.ERROR, f"the lower level could not be solved at any of the {out.nfev} points "
                         "differential evolution tried", int(out.nit))
    found = best["ev"]
    searched = (limit.reached() if limit.hit else GOAL_STOP if goal
                else str(out.message))
    stats = {"generations": int(out.nit), "evaluations": int(out.nfev), "evolution_objective": found.F,
             "evolution_message": searched, "members": members, "penalty": penalty}
    record = {"start": 0, "objective": found.F, "residual": found.violation, "generations": int(out.nit)}
    start = None
    if polish and not goal:  # the descent's oracle: recognized balls projected on, not penalized
        descent = shared_oracle(prep, penalty, param("implicit.active_tol"), tuple(b.row for b in prep.balls))
        arc = Arc(prep, descent, prep.projection, callback)
        try:
            start = arc(found.x)
        except StopIteration:
            found = arc.last
            goal.append(found)
    if start is None:
        w = prep.pack(KKTPoint(found.x, found.lower.y, found.lower.lam, found.lower.mu, found.lower.Z))
        message = (f"best of {out.nfev} points of differential evolution ({searched}); a heuristic: no optimality "
                   "claim")
        status = Status.MAX_ITERATIONS if limit.hit else Status.INACCURATE
        return MethodRun(w, status, message, int(out.nit), [], [record | {"status": status.value}], stats,
                         at_goal=bool(goal))

    def report(rec: dict[str, Any]) -> None:
        progress(verbose, "differential-evolution", f"descent iteration {rec['iter']}: phi = "
                 f"{prep.declared(rec['objective']):.8g}, projected step {rec['projected_step_norm']:.2e}")

    try:
        run = descend(arc, start, param("hypergradient.gtol"), param("hypergradient.ftol"),
                      param("hypergradient.max_iter"), limit, report if verbose else None)
    except StopIteration:
        run = Descent(arc.last, Status.INACCURATE, GOAL_STOP, 0, [])
        goal.append(run.point)
    p = run.point
    w = prep.pack(KKTPoint(p.x, p.lower.y, p.lower.lam, p.lower.mu, p.lower.Z))
    message = f"descent from the best of {out.nfev} points of differential evolution ({searched}): {run.message}"
    status = Status.MAX_ITERATIONS if limit.hit else run.status
    return MethodRun(w, status, message, int(out.nit) + run.nit, run.history,
                     [record | {"status": status.value, "iterations": run.nit, "objective": p.F,
                                "residual": p.violation}], stats, at_goal=bool(goal))
