"""Method `hypergradient`: projected ascent on the reduced objective phi(x) = F(x, y*(x)), y*(x) solved exactly.

phi and its gradient come from the implicit-differentiation engine (bilevel.solvers.engine.implicit). Where the declared
structure has an exact block (a ball of upper variables on which phi is a quadratic of the ball's vector,
bilevel.solvers.engine.block_exact), option exact_block="auto" (default) optimizes that block globally at every
evaluation and the rest by the engine's spectral projected gradient loop (bilevel.solvers.engine.ascent);
exact_block=True requires such a block (method `block-exact`), exact_block=False never uses one.

Otherwise, projected hypergradient descent: recognized balls (bilevel.solvers.engine.structure) are projected on, other
upper constraints penalized (bilevel.solvers.engine.implicit); a point is reported feasible when max(G, 0) and |H|
are <= 1e-6. The iteration is x+ = P(x - t grad phi), P the projection
onto the option `projection` (see projections.py) intersected with the declared box, by the engine's loop
(bilevel.solvers.engine.ascent, on -phi): long Barzilai-Borwein trial steps and Armijo backtracking along the projection
arc. A trial point at which the lower level is infeasible is moved to
the nearest upper point (in the box) where it is feasible, found by IPOPT on
min ||x - v||^2 s.t. g(x, y) <= 0, h(x, y) = 0, then projected again: with the default box projection
and jointly convex lower constraints this makes P the projection onto the lower level's domain.
Stops when ||x - P(x - grad phi)|| <= gtol (P without the lower solve of the restoration; with it, asked only
when the line search fails) or the relative decrease of phi in one step is <= ftol (SOLVED), at
max_iter (MAX_ITERATIONS), or when backtracking finds no decrease (INACCURATE: x is then typically at a
kink of y*(x), where the generalized gradient is not a descent direction).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import casadi as ca
import numpy as np
import scipy.optimize

from ..defaults import param
from ..errors import BilevelError, LowerLevelInfeasible, ModelError, RankDeficientRegressor
from ..lower.nlp import ipopt_options
from ..reduction import KKTPoint
from ..result import Status
from .engine.prepared import MethodRun, Prepared, best_of, check_options
from .engine.implicit import Evaluation, Hypergradient, shared_oracle
from .engine.ascent import projected_ascent
from .engine.block_exact import SINGULAR_LEARNER, ExactBlock, ascend_with_exact_block, exact_block_of
from .engine.options import check_numbers
from .engine.limits import GOAL_STOP, Deadline, progress, stopped
from .engine.starts import start_points
from .engine.projections import Projection


SINGULAR_CAUSE = ("the learner's regressor is rank-deficient at the poisoning reached: the attack made the learner "
                  "singular")
SINGULAR = (f"{SINGULAR_CAUSE} (the lower level has no unique solution at the trial points beyond x, so the run ends "
            "at the last point where it has one)")
"""The message of a run that ends where every step leads to a lower level without a unique solution."""


class _Restoration:
    """The nearest upper point in the box at which the lower level is feasible (IPOPT over (x, y))."""

    def __init__(self, prep: Prepared) -> None:
        canon, low = prep.canon, prep.canon.lower.symbolic()
        v = ca.SX.sym("v", canon.x.numel())
        nlp = {"x": ca.vertcat(canon.x, canon.y), "p": ca.vertcat(v, canon.params.sym),
               "f": 0.5 * ca.sumsqr(canon.x - v),
               "g": ca.vertcat(low.g, low.h)}
        options = ipopt_options(param("hypergradient.restoration_tol"), param("hypergradient.restoration_max_iter"),
                                {"bound_relax_factor": 0.0})
        self._solver = ca.nlpsol("restoration", "ipopt", nlp, options)
        ng, nh = low.n_g, low.n_h
        ny = int(canon.y.numel())
        self._bounds = dict(lbx=np.concatenate([canon.x_lb, np.full(ny, -np.inf)]),
                            ubx=np.concatenate([canon.x_ub, np.full(ny, np.inf)]),
                            lbg=np.concatenate([np.full(ng, -np.inf), np.zeros(nh)]), ubg=np.zeros(ng + nh))
        self._y0 = np.zeros(ny) if canon.y_start is None else canon.y_start
        self._nx = int(canon.x.numel())
        self._params = canon.params

    def __call__(self, v: np.ndarray) -> np.ndarray | None:
        """The restored point, or None if IPOPT finds none."""
        sol = self._solver(x0=np.concatenate([v, self._y0]), p=np.concatenate([v, self._params.value]),
                           **self._bounds)
        if self._solver.stats()["return_status"] not in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
            return None
        return np.asarray(sol["x"]).ravel()[: self._nx]


def intermediate(prep: Prepared, ev: Evaluation) -> scipy.optimize.OptimizeResult:
    """What option `callback` receives: an evaluated point's x, lower solution y (flat, canonical order) and upper
    objective `fun` in the declared sense."""
    return scipy.optimize.OptimizeResult(x=ev.x, y=ev.lower.y, fun=prep.declared(ev.F))


class Arc:
    """Points P(v) of the projection arc, evaluated; restored into the lower level's domain when needed. Every
    evaluated point goes to `callback` (option callback), which may raise StopIteration: `last` is then that point."""

    def __init__(self, prep: Prepared, oracle: Hypergradient, projection: Projection,
                 callback: Callable[[scipy.optimize.OptimizeResult], Any] | None = None) -> None:
        self.prep, self.oracle, self.project, self.callback = prep, oracle, projection, callback
        self._restoration: _Restoration | None = None
        self.last: Evaluation | None = None
        self.error: BilevelError | None = None
        """Why the last point that could not be evaluated could not be (for the message when no start can be)."""

    def __call__(self, v: np.ndarray) -> Evaluation | None:
        """The evaluated point P(v), or None if no lower-feasible point was found near it; raises StopIteration where
        the callback does."""
        ev = self._point(v)
        if ev is not None and self.callback is not None:
            self.last = ev
            self.callback(intermediate(self.prep, ev))
        return ev

    def _point(self, v: np.ndarray) -> Evaluation | None:
        x = self.project(v)
        try:
            return self.oracle.evaluate(x)
        except LowerLevelInfeasible as exc:
            self.error = exc
        except BilevelError as exc:
            self.error = exc
            return None
        if self._restoration is None:
            self._restoration = _Restoration(self.prep)
        restored = self._restoration(x)
        if restored is None:
            return None
        try:
            return self.oracle.evaluate(self.project(restored))
        except BilevelError as exc:
            self.error = exc
            return None


@dataclass
class Descent:
    """The outcome of one start: final point, status, message, accepted steps and per-iterate records."""

    point: Evaluation
    status: Status
    message: str
    nit: int
    history: list[dict[str, Any]]
    singular: bool = False
    """Whether the run ended where every step leads to a learner without a unique solution (message SINGULAR)."""


def _domain_stationary(arc: Arc, cur: Evaluation, grad: np.ndarray, tol: float) -> bool:
    """Whether the projected gradient step is <= tol once the projection is restored into the lower level's
    domain (the arc's P(x - grad)): asked only when the line search fails, as it costs a lower solve."""
    unit = arc(cur.x - grad)
    return unit is not None and float(np.linalg.norm(unit.x - cur.x)) <= tol


def descend(arc: Arc, start: Evaluation, tol: float, ftol: float, max_iter: int, limit: Deadline | None = None,
            report: Callable[[dict[str, Any]], None] | None = None) -> Descent:
    """The engine's spectral projected gradient loop (bilevel.solvers.engine.ascent) on -phi along the arc, in x units:
    long Barzilai-Borwein steps, each trial point restored into the lower level's domain; stops when
    ||P(x - grad phi) - x|| <= tol or phi's relative decrease in one step is <= ftol, or at the deadline `limit`
    (MAX_ITERATIONS); report, if given, receives each iterate's record."""
    history: list[dict[str, Any]] = []
    last: dict[str, Any] = {}
    singular: list[str] = []  # trial points since the last accepted one whose lower level had no unique solution

    def gradient(ev: Evaluation) -> tuple[np.ndarray, float]:
        """grad phi and the projected step at ev, once per evaluated point (recorded in history)."""
        if last.get("ev") is not ev:
            grad, degenerate, n_active = arc.oracle.gradient(ev)
            singular.clear()
            # NaN at a kink of an upper function (e.g. a norm at 0); no lower solve for the step: _domain_stationary
            pstep = float(np.linalg.norm(arc.project(ev.x - grad) - ev.x)) if np.all(np.isfinite(grad)) else np.nan
            history.append({"iter": len(history), "objective": ev.phi, "step": 0.0,
                            "grad_norm": float(np.linalg.norm(grad)), "projected_step_norm": pstep,
                            "active": n_active, "degenerate": degenerate})
            last.update(ev=ev, grad=grad, pstep=pstep)
            if report is not None:
                report(history[-1])
        return last["grad"], last["pstep"]

    def value(x: np.ndarray) -> tuple[float, Evaluation | None]:
        ev = start if np.array_equal(x, start.x) else arc(x)  # the loop's first call: the start, already evaluated
        if ev is None and isinstance(arc.error, RankDeficientRegressor):
            singular.append(str(arc.error))
        return (-np.inf, None) if ev is None else (-ev.phi, ev)

    def direction(ev: Evaluation) -> tuple[np.ndarray, np.ndarray]:
        g = -gradient(ev)[0]
        return g, g / max(1.0, float(np.abs(g).max(initial=0.0)))  # first step: at most 1 in any entry

    def stop(ev: Evaluation) -> bool:
        """The gradient is not finite, the projected step is <= tol, or phi fell by <= ftol (relative) in the last
        step."""
        if not np.isfinite(gradient(ev)[1]):
            last["reason"] = "non-finite gradient"
            return True
        if gradient(ev)[1] <= tol:
            last["reason"] = "tol"
            return True
        if len(history) > 1 and history[-2]["objective"] - ev.phi <= ftol * max(1.0, abs(ev.phi)):
            last["reason"] = "ftol"
            return True
        if limit is not None and limit.expired():
            last["reason"] = "time_limit"
            return True
        return False

    why: dict[str, str] = {}
    steps: list[dict[str, float]] = []
    _, _, cur, nit, _, _ = projected_ascent(value, direction, arc.project, start.x, 1.0, max_iter, 0.0, steps,
                                            stop=stop, bb="long", at=lambda ev: ev.x, why=why,
                                            min_step=param("hypergradient.min_step"))
    for record, step in zip(history[1:], steps):
        record["step"] = step["step"]
    grad, pstep = gradient(cur)
    reason = last["reason"] if why["stop"] == "stop" else why["stop"]  # the stop hook names its own reason
    if reason == "line search" and (singular or "singular" in why):
        return Descent(cur, Status.ERROR, SINGULAR, nit, history, singular=True)
    if reason == "max_iter":
        return Descent(cur, Status.MAX_ITERATIONS, f"max_iter = {max_iter} reached", nit, history)
    if reason == "time_limit":
        return Descent(cur, Status.MAX_ITERATIONS, limit.reached(), nit, history)
    if reason == "non-finite gradient" and cur.F == -np.inf:  # minimized F: the declared objective's supremum
        return Descent(cur, Status.ERROR, unbounded_message(arc.prep), nit, history)
    if reason == "non-finite gradient":
        return Descent(cur, Status.ERROR, f"the hypergradient is NaN or inf at x = {cur.x} (an upper objective or "
                       "constraint is not differentiable there, e.g. a norm at 0: declare a ball as "
                       "norm_2(v - c) <= r or sumsqr(v - c) <= r**2, or give a start away from the kink)", nit, history)
    # a trial step that rounds to x ("stationary") after many halvings is no proof either: both ask the domain
    if reason in ("line search", "stationary") and not _domain_stationary(arc, cur, grad, tol):
        return Descent(cur, Status.INACCURATE, "line search found no decrease (x is likely at a kink of "
                       "y*(x), where the generalized gradient is not a descent direction)", nit, history)
    message = {"tol": f"projected gradient step {pstep:.2e} <= gtol",
               "ftol": "relative decrease in one step <= ftol",
               "zero step": "zero gradient"}.get(reason, "projected gradient step <= gtol on the lower level's domain")
    return Descent(cur, Status.SOLVED, message, nit, history)


def unbounded_message(prep: Prepared) -> str:
    """Why a run ends where the upper objective is infinite in the improving direction: the matrix function's own
    reason (its attribute `infinite`) where it has one."""
    reason = getattr(prep.canon.matrix_function, "infinite", None)
    return f"{reason or 'the upper objective is infinite at the point reached'}: the supremum is unbounded"


def _projection(prep: Prepared, projection: Any) -> Projection:
    """The option `projection` intersected with the declared box (by default the box and the recognized balls)."""
    canon = prep.canon
    if projection is None:
        return prep.projection
    if not isinstance(projection, Projection):
        raise ModelError(f"option projection must be a Projection from bilevel.solvers.engine.projections (Box, "
                         f"NormBall, SparseNormBall, Blocks), got {type(projection).__name__}")
    proj = projection.with_box(canon.x_lb, canon.x_ub)
    if proj(canon.x_start).shape != canon.x_start.shape:
        raise ModelError(f"the projection maps the {canon.x_start.size} upper entries to a vector of another size")
    return proj


DESCENT_ONLY = ("projection", "gtol", "ftol", "active_tol", "callback", "prefer")
"""Options of the descent that the exact-block mode does not take."""


def solve_block_exact(prep: Prepared, *, starts: int | None = None, seed: Any = 0, scale: float | None = None,
                      penalty: float | None = None, gain_tol: float | None = None, max_iter: int | None = None,
                      time_limit: float | None = None, verbose: bool = False, **unknown: Any) -> MethodRun:
    """Method `block-exact`: `hypergradient` with exact_block=True (an error where the structure has no exact block).
    Its options are hypergradient's exact-block ones: starts, seed, scale, penalty, gain_tol, max_iter, time_limit,
    verbose (None: the registry's value, bilevel.defaults)."""
    if "exact_block" in unknown:
        raise ModelError("method 'block-exact' is hypergradient with exact_block=True; it takes no exact_block option")
    check_options("block-exact", unknown, solve_block_exact)
    return solve_hypergradient(prep, exact_block=True, starts=starts, seed=seed, scale=scale, penalty=penalty,
                               gain_tol=gain_tol, max_iter=max_iter, time_limit=time_limit, verbose=verbose)


def chosen_exact_block(prep: Prepared, mode: Any, options: dict[str, Any]) -> tuple[ExactBlock | None, list[str]]:
    """The exact block hypergradient uses with option exact_block=mode and these options (None: the descent), and
    why the candidates were not used."""
    if mode not in ("auto", True, False):
        raise ModelError(f"option exact_block={mode!r} is invalid: it must be 'auto', True or False")
    descent_only = sorted(set(options) & set(DESCENT_ONLY))
    if mode is False or (mode == "auto" and descent_only):
        return None, []
    if descent_only:
        raise ModelError(f"option(s) {', '.join(descent_only)} belong to the descent, not to the exact-block mode; "
                         "drop them or pass exact_block=False")
    exact, why = exact_block_of(prep)
    if exact is None and mode is True:
        raise ModelError("exact_block=True (method 'block-exact') needs a block of upper variables on which the "
                         f"reduced objective is a ball-constrained quadratic: {'; '.join(why)}; use "
                         "method='hypergradient'")
    if exact is None or mode is True:
        return exact, why
    S = exact.ball.block
    dimension = min(int(prep.canon.y.numel()), S.stop - S.start)
    if dimension > (limit := param("hypergradient.auto_exact_dimension")):
        return None, why + [f"x[{S.start}:{S.stop}] is exact, but its subproblem has dimension {dimension} > "
                            f"{limit}: the descent is cheaper (exact_block=True forces it)"]
    return exact, why


def _preferred(prep: Prepared, i: int, candidates: list[tuple[np.ndarray, float, float]], points: list[Evaluation],
               prefer: Callable[[scipy.optimize.OptimizeResult], float] | None) -> int:
    """Among the feasible candidates tied with candidate i (within defaults["hypergradient.tie_rtol"]), the one
    `prefer` rates highest."""
    top, feasible, rtol = candidates[i][1], param("solvers.feasibility_tol"), param("hypergradient.tie_rtol")
    ties = [j for j, (_, F, r) in enumerate(candidates) if r <= feasible and F - top <= rtol * max(1.0, abs(top))]
    if prefer is None or i not in ties:
        return i
    return max(ties, key=lambda j: (prefer(intermediate(prep, points[j])), -j))


def solve_hypergradient(prep: Prepared, *, starts: int | None = None, seed: Any = 0, scale: float | None = None,
                        exact_block: bool | str = "auto", penalty: float | None = None, max_iter: int | None = None,
                        gtol: float | None = None, ftol: float | None = None, gain_tol: float | None = None,
                        projection: Projection | None = None, active_tol: float | None = None,
                        callback: Callable[[scipy.optimize.OptimizeResult], Any] | None = None,
                        prefer: Callable[[scipy.optimize.OptimizeResult], float] | None = None,
                        time_limit: float | None = None, verbose: bool = False, **unknown: Any) -> MethodRun:
    """Multistart projected hypergradient ascent: with the exact block where the declared structure has one, else
    descent with recognized balls projected on, other upper constraints penalized. An option left None takes the
    registry's value, defaults["hypergradient.NAME"] (bilevel.defaults; penalty and active_tol: "implicit.NAME",
    gain_tol: "block_exact.gain_tol").

    starts: multistart starts; seed: random starts' seed; scale: half-width of the random starts' box where a bound
    is infinite; exact_block: "auto" | True | False (module docstring); penalty: weight of the penalized upper
    violation; max_iter: steps per start; time_limit (seconds): the starts not begun are skipped, status
    MAX_ITERATIONS; verbose: progress lines on stderr.
    Exact-block mode only: gain_tol, the relative gain over the ascent's window of steps below which it stops.
    Descent only: gtol (projected step norm) and ftol (relative decrease in one step) stop it; projection (a set
    narrower than the declared one); active_tol (lower constraints taken as active); callback(intermediate) sees every
    evaluated point (x, y, fun declared), raising StopIteration ends the method there with that point as its answer
    (the caller's goal, never `solved`); prefer(intermediate) -> float breaks near-ties (hypergradient.tie_rtol)
    between the starts' end points, the highest value winning."""
    check_options("hypergradient", unknown, solve_hypergradient)
    given = {name: value for name, value in dict(projection=projection, gtol=gtol, ftol=ftol, active_tol=active_tol,
                                                 callback=callback, prefer=prefer).items() if value is not None}
    check_numbers(given, positive=("active_tol",), nonnegative=("ftol",))
    check_numbers({} if penalty is None else {"penalty": penalty}, nonnegative=("penalty",))
    exact, why = chosen_exact_block(prep, exact_block, given)
    if exact is not None:
        return ascend_with_exact_block(prep, exact, why, starts=starts, seed=seed, scale=scale, penalty=penalty,
                                       gain_tol=gain_tol, max_iter=max_iter, time_limit=time_limit, verbose=verbose)
    if gain_tol is not None:
        raise ModelError("option gain_tol belongs to hypergradient's exact-block mode, which does not run here "
                         f"({'; '.join(why) or 'exact_block=False'}); the descent stops by gtol and ftol")
    starts, penalty = int(param("hypergradient.starts", starts)), float(param("implicit.penalty", penalty))
    projected = tuple(b.row for b in prep.balls) if projection is None else ()
    active_tol = float(param("implicit.active_tol", active_tol))
    oracle = shared_oracle(prep, penalty, active_tol, projected)
    arc = Arc(prep, oracle, _projection(prep, projection), callback)
    tol, ftol = float(param("hypergradient.gtol", gtol)), float(param("hypergradient.ftol", ftol))
    max_iter = int(param("hypergradient.max_iter", max_iter))
    rng = np.random.default_rng(seed)
    limit = Deadline(time_limit)
    records, runs, candidates, goal = [], [], [], None
    for k, x0 in enumerate(start_points(prep, starts, rng, float(param("hypergradient.scale", scale)))):
        if k and limit.expired():
            break
        t0 = time.perf_counter()

        seen: list[dict[str, Any]] = []  # this start's iterate records, kept where the callback ends the run

        def report(record: dict[str, Any], k: int = k) -> None:
            seen.append(record)
            if verbose:  # the text is built only when it is shown (this runs at every iteration)
                progress(verbose, "hypergradient", f"start {k + 1}/{starts}, iteration {record['iter']}: phi = "
                         f"{prep.declared(record['objective']):.8g}, projected step "
                         f"{record['projected_step_norm']:.2e}")

        failed, singular = None, False  # why no descent could begin at this start; whether on a singular learner
        try:
            start = arc(x0)
            if start is None:
                singular = isinstance(arc.error, RankDeficientRegressor)
                failed = (f"{SINGULAR_CAUSE} (at the start: {arc.error})" if singular
                          else "no upper point near the start where the lower level can be solved")
            else:
                run = descend(arc, start, tol, ftol, max_iter, limit, report)
        except RankDeficientRegressor as exc:  # the start's lower level has no derivative: no step can begin
            failed, singular = f"{SINGULAR_CAUSE} (at the start: {exc})", True
        except StopIteration:
            run = Descent(arc.last, Status.INACCURATE, GOAL_STOP,
                          max(len(seen) - 1, 0), seen)
            goal = k
        if failed is not None:
            records.append({"start": k, "x0": x0.tolist(), "status": Status.ERROR.value, "iterations": 0,
                            "message": failed, SINGULAR_LEARNER: singular, "time": time.perf_counter() - t0})
            continue
        p = run.point
        w = prep.pack(KKTPoint(p.x, p.lower.y, p.lower.lam, p.lower.mu, p.lower.Z))
        runs.append((k, run))
        candidates.append((w, p.F, p.violation))
        records.append({"start": k, "x0": x0.tolist(), "status": run.status.value, "message": run.message,
                        SINGULAR_LEARNER: run.singular, "objective": p.F, "residual": p.violation,
                        "iterations": run.nit, "time": time.perf_counter() - t0})
        progress(verbose, "hypergradient", f"start {k + 1}/{starts}: {run.status.value}, F = "
                 f"{prep.declared(p.F):.6g}, upper violation {p.violation:.1e} ({run.message})")
        if goal is not None:
            break
    nit = sum(r["iterations"] for r in records)
    if not runs:
        cause = records[-1]["message"] if arc.error is None else f"{type(arc.error).__name__}: {arc.error}"
        return MethodRun(None, Status.ERROR, f"all {starts} starts failed: the lower level could not be solved "
                         f"near any start ({cause})", nit, [], records)
    i = len(runs) - 1 if goal is not None else _preferred(prep, best_of(candidates), candidates,
                                                            [r.point for _, r in runs], prefer)
    k, best = runs[i]
    run = MethodRun(candidates[i][0], best.status, f"best of {starts} starts: start {k} ({best.message})", nit,
                    best.history, records, {"best_start": k, "penalty": penalty, "exact_block": None,
                                            "not_exact": why,
                                            "projected_gradient_norm": best.history[-1]["projected_step_norm"]
                                            if best.history else None},
                    feasible_set=None if projection is None else arc.project, at_goal=goal is not None)
    return stopped(run, limit, len(records), starts)
