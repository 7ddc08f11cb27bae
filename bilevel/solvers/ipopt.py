"""IPOPT (through CasADi) on the KKT reformulation: multistart from lower-level-optimal points, then polish.

Each start x0 (the declared start, then seeded random points inside the bounds) is completed with the
lower-level solution at x0 and its multipliers, so IPOPT starts on the MPCC's feasible set. The MPCC
is transcribed with a complementarity mode (default Scholtes with a tiny t). The best start (the feasible one with
the lowest F) is then polished on the branch its complementarity pattern selects (G_i = 0 or H_i = 0), a regular NLP
whose solution satisfies complementarity exactly; another start is polished only if it still beats the polished one.

IPOPT finds a local solution near its start. Option warm="hypergradient" (also for `relaxation`) first runs method
`hypergradient` over the same starts and hands its answer to one IPOPT solve: a Newton-accurate KKT point at the
first-order method's (usually better) local solution. The default warm="auto" does so where hypergradient has an
exact block (a block of upper variables it optimizes globally: vrft-maxmin's input poisoning), and starts from the
start points elsewhere. Each NLP solve stops after defaults["ipopt.max_wall_time"] seconds by default.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..defaults import param
from ..errors import BilevelError, ModelError
from ..lower.base import LowerSolution
from ..lower.nlp import ipopt_options
from ..mpcc import Branch, ComplementarityMode, NLPForm, Scholtes
from ..reduction import KKTPoint
from ..result import Status
from .engine.prepared import MethodRun, Prepared, best_of, check_options, unbounded_lower
from .hypergradient import chosen_exact_block, solve_hypergradient
from .engine.implicit import shared_oracle
from .engine.limits import Deadline, progress, stopped
from .engine.starts import start_points

IPOPT_STATUS: dict[str, Status] = {
    "Solve_Succeeded": Status.SOLVED,
    "Solved_To_Acceptable_Level": Status.INACCURATE,
    "Feasible_Point_Found": Status.INACCURATE,
    "Infeasible_Problem_Detected": Status.INFEASIBLE,
    "Maximum_Iterations_Exceeded": Status.MAX_ITERATIONS,
    "Maximum_CpuTime_Exceeded": Status.MAX_ITERATIONS,
    "Maximum_WallTime_Exceeded": Status.MAX_ITERATIONS,
}
"""IPOPT return_status -> Status; anything not listed (restoration failure, errors) is Status.ERROR."""

WARM = ("auto", None, "hypergradient")
"""Values of option `warm` of the KKT methods: start from method hypergradient's answer ("hypergradient"), from the
start points (None), or "auto" (default): from hypergradient's answer where it has an exact block (a ball of upper
variables optimized globally in closed form, bilevel.solvers.engine.block_exact), else from the start points."""


@dataclass
class NLPRun:
    """One IPOPT solve: the point, its objective, mapped status, raw status and iteration count."""

    w: np.ndarray
    objective: float
    status: Status
    raw_status: str
    iterations: int
    trace: dict[str, Any]


def checked_ipopt(extra: Any) -> dict[str, Any]:
    """A method's option ipopt={...} (None: none), refused unless it is a dict of IPOPT options."""
    if extra is not None and not (isinstance(extra, dict) and all(isinstance(k, str) for k in extra)):
        raise ModelError(f"option ipopt={extra!r} is invalid: it must be a dict of IPOPT options, e.g. "
                         "{'max_cpu_time': 60}")
    return extra or {}


def kkt_nlp_options(nlp_tol: float | None, max_iter: int | None, extra: dict[str, Any] | None,
                    warm: dict[str, Any]) -> dict[str, Any]:
    """IPOPT options of a KKT method from its options nlp_tol, max_iter and ipopt (None: the registry's ipopt.NAME),
    with the warm limits (ipopt.warm_max_iter, ipopt.warm_max_wall_time) where its NLPs start from the warm phase's
    answer (stats `warm` from kkt_starts) and the options do not set those limits: from that near-KKT point IPOPT
    converges in a few iterations or wanders (a stopped NLP keeps the warm point, kept_warm_point)."""
    opts = ipopt_options(float(param("ipopt.nlp_tol", nlp_tol)), int(param("ipopt.max_iter", max_iter)),
                         {"acceptable_tol": param("ipopt.acceptable_tol"), "mu_strategy": "adaptive",
                          "max_wall_time": param("ipopt.max_wall_time"), **checked_ipopt(extra)})
    if warm.get("warm", {}).get("used"):
        given = set(extra or {}) | ({"max_iter"} if max_iter is not None else set())
        limits = {"max_iter": param("ipopt.warm_max_iter"), "max_wall_time": param("ipopt.warm_max_wall_time")}
        opts["ipopt"].update({k: v for k, v in limits.items() if k not in given})
    return opts


def within(options: dict[str, Any], limit: Deadline) -> dict[str, Any]:
    """nlpsol options with IPOPT's max_wall_time cut to time_limit / 2^k, the largest such level within the time left
    before `limit` (at least 1 ms: IPOPT then stops after its first iteration, Maximum_WallTime_Exceeded). The levels
    keep the options, hence the compiled solver (cached per options), the same over most of a run."""
    if limit.seconds is None:
        return options
    left = max(limit.remaining(), 1e-3)
    level = limit.seconds * 2.0 ** -math.ceil(max(math.log2(limit.seconds / left), 0.0)) if left < limit.seconds \
        else limit.seconds
    wall = min(float(options["ipopt"].get("max_wall_time", param("ipopt.max_wall_time"))), max(level, 1e-3))
    return {**options, "ipopt": {**options["ipopt"], "max_wall_time": wall}}


def run_nlp(nlp: NLPForm, w0: np.ndarray, options: dict[str, Any], tau: float | None = None,
            lam_g0: np.ndarray | None = None, limit: Deadline | None = None) -> NLPRun:
    """Solve the transcribed NLP from w0 (tau overrides the mode's relaxation parameter), within the deadline `limit`
    if given (a solve it stops marks it hit)."""
    if limit is not None:
        options = within(options, limit)
    # METIS nested dissection (mumps_pivot_order 5) for large KKT systems: matrix data bound to upper variables make
    # rows dense in x and y, and MUMPS's automatic order factored the DeePC learner's (T = 200, 920 rows) 5x slower
    # (2.1 s against 0.4 s CPU over the same 46 iterations); smaller systems keep MUMPS's choice, since another order
    # changes the rounding and so which local solution a start reaches (willems-eigen, 343 rows: 4x the time)
    large = nlp.x.numel() + nlp.g.numel() >= param("ipopt.metis_from")
    if large and "mumps_pivot_order" not in options.get("ipopt", {}):
        options = {**options, "ipopt": {**options.get("ipopt", {}), "mumps_pivot_order": 5}}
    try:
        solver = nlp.solver("ipopt", options)
    except RuntimeError as exc:  # CasADi refuses an option before any solve
        reason = str(exc).strip().splitlines()[-1].split(": ", 1)[-1]
        raise ModelError(f"IPOPT did not accept its options ({reason}); check the names and types in option "
                         "ipopt={...} against the IPOPT options reference") from None
    args = dict(x0=nlp.start(w0[: nlp.n_w]), lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg,
                p=np.concatenate([nlp.p_value if tau is None else [tau], nlp.params.value]))
    if lam_g0 is not None:
        args["lam_g0"] = lam_g0
    sol = solver(**args)
    stats = solver.stats()
    raw = str(stats.get("return_status", "unknown"))
    trace = {k: list(stats.get("iterations", {}).get(k, [])) for k in ("obj", "inf_pr", "inf_du")}
    if limit is not None and raw == "Maximum_WallTime_Exceeded":
        limit.expired()
    return NLPRun(np.asarray(sol["x"]).ravel()[: nlp.n_w], float(sol["f"]), IPOPT_STATUS.get(raw, Status.ERROR),
                  raw, int(stats.get("iter_count", 0)), trace)


def branch_polish(prep: Prepared, w: np.ndarray, options: dict[str, Any],
                  limit: Deadline | None = None) -> NLPRun | None:
    """Re-solve on the MPCC branch selected by w (G_i = 0 where G_i <= H_i), within the deadline `limit`; None if it
    fails or the deadline has passed."""
    if limit is not None and limit.expired():
        return None
    mpcc = prep.mpcc
    sides = {name: G <= H for name, (G, H) in mpcc.pair_values(w).items()}
    exact = {**options, "ipopt": {**options["ipopt"], "bound_relax_factor": 0.0}}
    try:
        run = run_nlp(mpcc.transcribe(Branch(sides=sides)), w, exact, limit=limit)
    except (RuntimeError, BilevelError):
        return None
    return run if run.status is Status.SOLVED else None


def branch_polish_best(prep: Prepared, candidates: list[tuple[np.ndarray, float, float]], runs: list[NLPRun],
                records: list[dict[str, Any]], options: dict[str, Any],
                limit: Deadline | None = None) -> tuple[int, int]:
    """Branch-polish the best candidate (re-solve it on its MPCC branch), and again whichever candidate is best after
    that, until the best is polished or its polish failed (a relaxed solve's objective is within its tau of its
    branch's, so this is usually one polish, not one per start); candidates, runs and records are updated in place.
    The best's index and the polishes' iterations."""
    tried: set[int] = set()
    iterations, polished = 0, None
    while (i := best_of(candidates)) not in tried:
        if polished is not None and candidates[i][1] >= candidates[polished][1] - param("ipopt.polish_tie") * (
                1.0 + abs(candidates[polished][1])):
            return polished, iterations  # no better than the polished one beyond the relaxation's own accuracy
        tried.add(i)
        pol = branch_polish(prep, candidates[i][0], options, limit)
        if pol is None:
            continue
        iterations, polished = iterations + pol.iterations, i
        res, old = residual(prep, pol.w), runs[i]
        candidates[i] = (pol.w, pol.objective, res)
        runs[i] = NLPRun(pol.w, pol.objective, pol.status, f"{old.raw_status}, polished",
                         old.iterations + pol.iterations, old.trace)
        records[i] |= {"status": runs[i].raw_status, "objective": pol.objective, "residual": res, "polished": True,
                       "iterations": runs[i].iterations}
    return i, iterations


def warm_start(prep: Prepared, x0: np.ndarray) -> np.ndarray:
    """MPCC start from x0 with the lower level solved there; zeros for y and multipliers if it cannot be."""
    try:
        return prep.pack(prep.lower_point(x0))
    except BilevelError:
        size = {name: s.stop - s.start for name, s in prep.layout.slices.items()}
        y = prep.canon.y_start if prep.canon.y_start is not None else np.zeros(size["y"])
        return prep.pack(KKTPoint(x0, y, np.zeros(size["lam"]), np.zeros(size["mu"]),
                                  [np.zeros((n, n)) for n in prep.layout.psd_sizes]))


def kkt_starts(prep: Prepared, method: str, starts: int | None, seed: Any, scale: float | None, warm: str | None,
               verbose: bool, limit: Deadline | None = None) -> tuple[list[np.ndarray], str, dict[str, Any]]:
    """The MPCC start vectors of a KKT method (its options starts, seed, scale, warm, verbose; None: the registry's
    ipopt.NAME), a label for its message, and its stats on the warm phase (if hypergradient returns no point: the
    start points, stats["warm"]["used"] False); the warm phase stops at the deadline `limit`."""
    starts, scale = int(param("ipopt.starts", starts)), float(param("ipopt.scale", scale))
    if warm not in WARM:
        raise ModelError(f"option warm={warm!r} of method {method!r} is invalid: it must be 'auto', None or "
                         "'hypergradient'")
    if warm == "auto":
        warm = "hypergradient" if chosen_exact_block(prep, "auto", {})[0] is not None else None
    plain = f"best of {starts} starts"
    if warm is None:
        points = start_points(prep, starts, np.random.default_rng(seed), scale)
        return [warm_start(prep, x0) for x0 in points], plain, {}
    t0 = time.perf_counter()
    budget = {} if limit is None or limit.seconds is None else {"time_limit": max(limit.remaining(), 1e-3)}
    run = solve_hypergradient(prep, starts=starts, seed=seed, scale=scale, verbose=bool(verbose), **budget)
    info = {"warm": {"method": "hypergradient", "status": run.status.value, "message": run.message,
                     "objective": None if run.w is None else prep.declared(prep.mpcc.objective_value(run.w)),
                     "iterations": run.nit,
                     "time": time.perf_counter() - t0, "used": run.w is not None}}
    if run.w is None:
        return kkt_starts(prep, method, starts, seed, scale, None, verbose, limit)[0], plain, info
    return [run.w], "from hypergradient's answer", info


def residual(prep: Prepared, w: np.ndarray) -> float:
    """Largest MPCC violation at w (equalities, inequalities, pair signs, complementarity)."""
    return max(prep.mpcc.residuals(w).values())


def kept_warm_point(prep: Prepared, points: list[np.ndarray], best: tuple[np.ndarray, float, float], outcome: str,
                    nit: int, records: list[dict[str, Any]], stats: dict[str, Any]) -> MethodRun | None:
    """The method's run with the warm phase's own point as its answer when that point beats the NLP's best
    (w, objective, residual) by best_of (an NLP that fails from it, e.g. a limited-memory IPOPT that leaves the
    feasible set), else None; stats must hold the warm phase's record ("warm", from kkt_starts)."""
    warm = stats.get("warm", {})
    if not warm.get("used"):
        return None
    own = (points[0], prep.mpcc.objective_value(points[0]), residual(prep, points[0]))
    if best_of([best, own]) == 0:
        return None
    stats["warm"] = {**warm, "kept": True}
    return MethodRun(points[0], Status(warm["status"]), f"hypergradient's answer kept: the NLP from it ended "
                     f"{outcome} (objective {best[1]:.8g}, residual {best[2]:.1e})", nit, [], records, stats)


def settled(prep: Prepared, run: MethodRun) -> MethodRun:
    """The run with x projected onto the declared box and recognized balls (IPOPT ends up to its tolerance outside
    them), and, where it ended infeasible because the lower level is unbounded below there, a status saying so."""
    if run.w is None or not np.all(np.isfinite(run.w)):
        return run
    point = prep.point(run.w)
    x = prep.projection(point.x)
    if not np.array_equal(x, point.x):
        run.w = prep.pack(_lower_moved_to(prep, point, x))
    if run.status is Status.INFEASIBLE and (why := unbounded_lower(prep, prep.point(run.w).x)) is not None:
        run.status, run.message = Status.ERROR, f"{why} ({run.message})"
    return run


def _lower_moved_to(prep: Prepared, point: KKTPoint, x: np.ndarray) -> KKTPoint:
    """The method's KKT point with x moved to `x` (a projection by rounding-sized steps) and its lower part corrected
    there: Newton on the lower KKT system from the method's y and multipliers (same active set, so the method's
    choice among non-unique lower solutions is kept), or the closed form of a least-squares lower level. Without
    the correction y is stationary only at the old x (2e-6 off after a 1e-8 move of a 200-sample budget)."""
    low = prep.canon.lower
    sol = LowerSolution(point.y, np.nan, point.lam, point.mu, list(point.Z), "optimal", "the method's point")
    try:
        if low.closed_form:
            sol = low.solve(x)
        elif low.psd:
            sol = low.kkt_newton(x, sol)[0]
        else:
            oracle = shared_oracle(prep)
            for _ in range(2):  # exact in one step for LP/QP on the same face; NLP converges quadratically
                sol = oracle.active_set_newton(x, sol)[0]
    except (BilevelError, np.linalg.LinAlgError):  # keep the method's lower part; the certificate judges it
        pass
    return KKTPoint(x, sol.y, sol.lam, sol.mu, list(sol.Z))


def solve_ipopt(prep: Prepared, *, starts: int | None = None, seed: Any = 0, scale: float | None = None,
                warm: str | None = "auto", mode: ComplementarityMode | None = None, branch_polish: bool = True,
                nlp_tol: float | None = None, max_iter: int | None = None, ipopt: dict[str, Any] | None = None,
                time_limit: float | None = None, verbose: bool = False, **unknown: Any) -> MethodRun:
    """Multistart IPOPT on the KKT reformulation. An option left None takes the registry's value,
    defaults["ipopt.NAME"] (bilevel.defaults).

    starts: multistart starts; seed: random starts' seed; scale: half-width of the random starts' box where a bound
    is infinite; warm: "auto" | None | "hypergradient" (module docstring); mode: the complementarity mode (None:
    Scholtes(ipopt.complementarity_t)); branch_polish: re-solve the best start on its MPCC branch; nlp_tol and
    max_iter: IPOPT's tol and max_iter on each NLP; ipopt: further IPOPT options (a dict); time_limit (seconds): each
    NLP is stopped by IPOPT's max_wall_time, the starts not begun are skipped, and the status is MAX_ITERATIONS;
    verbose: progress lines on stderr."""
    check_options("ipopt", unknown, solve_ipopt)
    mode = Scholtes(param("ipopt.complementarity_t")) if mode is None else mode
    if not isinstance(mode, ComplementarityMode):
        raise ModelError(f"option mode={mode!r} is invalid: it must be a complementarity mode such as "
                         "bilevel.Scholtes(1e-9), bilevel.Product() or bilevel.Branch(...)")
    limit = Deadline(time_limit)
    points, source, warm = kkt_starts(prep, "ipopt", starts, seed, scale, warm, verbose, limit)
    nlp_opts = kkt_nlp_options(nlp_tol, max_iter, ipopt, warm)
    nlp = prep.mpcc.transcribe(mode)
    records, candidates, traces = [], [], []
    for k, w0 in enumerate(points):
        if k and limit.expired():
            break
        t0 = time.perf_counter()
        run = run_nlp(nlp, w0, nlp_opts, limit=limit)
        res = residual(prep, run.w)
        candidates.append((run.w, run.objective, res))
        traces.append(run)
        records.append({"start": k, "x0": prep.point(w0).x.tolist(), "status": run.raw_status,
                        "objective": run.objective, "residual": res, "polished": False,
                        "iterations": run.iterations, "time": time.perf_counter() - t0})
        progress(verbose, "ipopt", f"start {k + 1}/{len(points)}: {run.raw_status}, F = "
                 f"{prep.declared(run.objective):.6g}, residual {res:.1e}, {run.iterations} iterations")
    i, _ = (branch_polish_best(prep, candidates, traces, records, nlp_opts, limit)
            if branch_polish and prep.mpcc.pairs else (best_of(candidates), 0))
    total_iter = sum(r["iterations"] for r in records)
    best = traces[i]
    kept = kept_warm_point(prep, points, candidates[i], best.raw_status, total_iter, records,
                           {"mode": repr(mode), **warm})
    if kept is not None:
        return settled(prep, stopped(kept, limit, len(records), len(points)))
    history = [{"iter": j, "objective": o, "inf_pr": p, "inf_du": d}
               for j, (o, p, d) in enumerate(zip(best.trace["obj"], best.trace["inf_pr"], best.trace["inf_du"]))]
    run = MethodRun(best.w, best.status, f"{source}, start {i} ({best.raw_status})", total_iter, history, records,
                    {"mode": repr(mode), "best_start": i, **warm})
    return settled(prep, stopped(run, limit, len(records), len(points)))
