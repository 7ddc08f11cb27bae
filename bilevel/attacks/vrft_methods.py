"""Structured attacks on a VRFT instance, as methods of the engine on its declared problem vrft-<objective>
(bilevel.problems.vrft): each returns a MethodRun, and `bilevel.solvers.solve` certifies it (independent
re-solve of the learner), probes its neighbourhood and maps it to the declared names like any method's.

alternating (the paper's Algorithm 1, strengthened): ascend the value function V(a_y) = max_{a_u} J(theta(u + a_u,
  y + a_y)) by the engine's spectral projected gradient (Barzilai-Borwein steps, Armijo backtracking); the inner
  max over a_u is solved at every evaluation (globally for l2 budgets by a trust-region subproblem, by monotone
  conditional gradient for the max-min objective under linf/l1/sparse budgets, by projected gradient otherwise).
  Danskin: grad V = dJ/da_y at a_u*.
joint: spectral projected gradient ascent on (a_u, a_y) together, each block measured in its budget radius.
white-noise: a random point on the budget boundary (the paper's baseline).
Starts are the engine's (bilevel.solvers.starts: the problem's suggested conditioning start, then random points on
the budget spheres), and so is the choice of the best one (best_of).
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import ModelError
from ..files import atomic_path
from ..problems.vrft import instance_of, problem_for
from ..problems.vrft_instance import VRFTAttack
from ..reduction import KKTPoint
from ..result import BilevelResult, Status
from ..solvers.ascent import budget_direction, projected_ascent
from ..solvers.base import MethodRun, Prepared, best_of, check_options
from ..solvers.options import check_common_options
from ..solvers.projections import Blocks, Projection
from ..solvers.registry import solve
from ..solvers.starts import start_points
from .outcome import attack_stat, unstable
from .vrft import State, best_input_attack, hypergradient, state

DEFAULT_STEPS = (1.0,)
MAX_ITER = {"maxmin": 60, "targeted": 500}
"""attack_alternating's iteration limit by objective: 60 for max-min (the setting of the committed Table 1); 500 for
targeted, which at 60 ended at the limit on 40 of 40 data sets (scenario B, N = 512) and converges in 118-195
iterations (benchmarks/results/bench_vrft_iterations.txt)."""
JOINT_MAX_ITER, TOL = 200, 1e-4
"""attack_joint's iteration limit; both ascents stop when the projected step is below TOL budget radii."""
FIRST = ("conditioning", "zero")
"""The first start: the problem's suggested one (the conditioning start of bilevel.problems.vrft_instance), or zero
poisoning (the declared start); then the engine's further starts."""


def _budgets(atk: VRFTAttack) -> Projection:
    """Projection onto both budgets, a_u the first N entries of the upper vector and a_y the last N."""
    N = atk.N
    return Blocks([(slice(0, N), atk.budget_u.projection(atk.u)), (slice(N, 2 * N), atk.budget_y.projection(atk.y))],
                  2 * N)


def _starts(prep: Prepared, atk: VRFTAttack, starts: int, seed: int, first: str) -> list[np.ndarray]:
    """`starts` distinct points of the engine's start sequence, projected onto the budgets (which it may not know: l1,
    sparsity): for l2 budgets its conditioning start repeats the suggested one. With first="zero" the declared start
    (zero poisoning) comes first."""
    if first not in FIRST:
        raise ModelError(f"first start {first!r} is not one of {', '.join(FIRST)}")
    project = _budgets(atk)
    head = [prep.canon.x_start] if first == "zero" else []
    for n in range(starts - len(head), starts + 3):  # the sequence's prefix is the same for every n (same seed)
        points = list(head)
        for x in map(project, start_points(prep, n, np.random.default_rng(seed), 1.0)):
            if not any(np.allclose(x, p, rtol=1e-8, atol=1e-12) for p in points):
                points.append(x)
        if len(points) >= starts:
            break
    return points[:starts]


def method_run(prep: Prepared, atk: VRFTAttack, s: State, converged: bool | None, message: str,
               records: Sequence[dict[str, Any]] = (), history: Sequence[dict[str, Any]] = (), evaluations: int = 1,
               best_start: int = 0) -> MethodRun:
    """The MethodRun of an attack's end point s: converged -> SOLVED, a sample (None) -> INACCURATE, else
    MAX_ITERATIONS; the budget sets as the searched set where the declared problem relaxes them (l1, sparsity)."""
    empty = np.zeros(0)
    w = prep.pack(KKTPoint(np.concatenate([s.a_u, s.a_y]), s.theta, empty, empty, []))
    status = Status.SOLVED if converged else Status.INACCURATE if converged is None else Status.MAX_ITERATIONS
    exact = all(b.norm in ("l2", "linf") and b.rho is None for b in (atk.budget_u, atk.budget_y))
    return MethodRun(w, status, message, sum(r.get("iterations", 0) for r in records), list(history), list(records),
                     {"best_start": best_start, "evaluations": evaluations},
                     feasible_set=None if exact else _budgets(atk))


def _best(prep: Prepared, atk: VRFTAttack, ends: list[tuple[float, tuple[State, bool | None, int, list]]],
          records: list[dict[str, Any]], evaluations: int) -> MethodRun:
    """The engine's best-start rule over the ends (attack criterion fx, maximized) of every start."""
    i = best_of([(None, -fx, 0.0) for fx, _ in ends])
    s, converged, k, history = ends[i][1]
    message = f"best of {len(ends)} runs: run {i} ({'converged' if converged else 'max_iter reached'})"
    return method_run(prep, atk, s, converged, message, records, history, evaluations, k)


def alternating(prep: Prepared, *, starts: int = 1, seed: int = 0, max_iter: int | None = None, tol: float = TOL,
                first: str = "conditioning", steps: tuple[float, ...] = DEFAULT_STEPS, **unknown: Any) -> MethodRun:
    """The alternating attack on the problem's VRFT instance (module docstring): every start followed from each
    initial step in `steps` (fractions of the budget radius); max_iter: MAX_ITER by objective."""
    check_options("alternating", unknown, {"starts", "seed", "max_iter", "tol", "first", "steps"})
    atk = instance_of(prep.problem)
    if atk.objective == "destabilize":
        raise ModelError("the alternating attack needs a quadratic objective; use attack_joint for 'destabilize'")
    max_iter = MAX_ITER[atk.objective] if max_iter is None else max_iter
    check_common_options({"starts": starts, "seed": seed, "max_iter": max_iter, "tol": tol})
    if not steps or not all(isinstance(v, (int, float)) and 0 < v < np.inf for v in steps):
        raise ModelError(f"steps={steps!r} is invalid: it must be a non-empty tuple of initial steps > 0 (fractions "
                         "of the budget radius), e.g. (1.0,)")
    N, proj_y, order = atk.N, atk.budget_y.projection(atk.y), atk.budget_y.order
    ends, records, evaluations = [], [], 0
    for k, x0 in enumerate(_starts(prep, atk, starts, seed, first)):
        for step0 in steps:
            history: list[dict[str, float]] = []
            memo: dict[str, np.ndarray] = {}

            def value(a_y: np.ndarray) -> tuple[float, State]:
                a_u, s = input_step(atk, a_y, memo.get("a_u"))
                memo["a_u"] = a_u
                return atk.value(s.theta), s

            def direction(s: State) -> tuple[np.ndarray, np.ndarray]:
                g_y = hypergradient(atk, s)[1]
                return g_y, budget_direction(g_y, atk.delta_y, order)

            _, fx, s, it, ev, conv = projected_ascent(value, direction, proj_y, x0[N:], atk.delta_y, max_iter, tol,
                                                      history, step0)
            evaluations += ev
            ends.append((fx, (s, conv, k, history)))
            records.append({"start": k, "step": step0, "objective": fx, "converged": conv, "iterations": it})
    return _best(prep, atk, ends, records, evaluations)


def joint(prep: Prepared, *, starts: int = 1, seed: int = 0, max_iter: int = JOINT_MAX_ITER, tol: float = TOL,
          first: str = "zero", **unknown: Any) -> MethodRun:
    """Joint projected hypergradient ascent on (a_u, a_y) of the problem's VRFT instance, each block scaled to its
    budget."""
    check_options("joint", unknown, {"starts", "seed", "max_iter", "tol", "first"})
    check_common_options({"starts": starts, "seed": seed, "max_iter": max_iter, "tol": tol})
    atk = instance_of(prep.problem)
    N = atk.N
    ou, oy = atk.budget_u.order, atk.budget_y.order
    scale = np.concatenate([np.full(N, atk.delta_u), np.full(N, atk.delta_y)])

    def value(x: np.ndarray) -> tuple[float, State]:
        s = state(atk, x[:N], x[N:])
        return atk.value(s.theta), s

    def direction(s: State) -> tuple[np.ndarray, np.ndarray]:
        g_u, g_y = hypergradient(atk, s)
        return np.concatenate([g_u, g_y]), np.concatenate([budget_direction(g_u, atk.delta_u, ou),
                                                           budget_direction(g_y, atk.delta_y, oy)])

    ends, records, evaluations = [], [], 0
    for k, x0 in enumerate(_starts(prep, atk, starts, seed, first)):
        history: list[dict[str, float]] = []
        _, fx, s, it, ev, conv = projected_ascent(value, direction, _budgets(atk), x0, scale, max_iter, tol, history)
        evaluations += ev
        ends.append((fx, (s, conv, k, history)))
        records.append({"start": k, "objective": fx, "converged": conv, "iterations": it})
    return _best(prep, atk, ends, records, evaluations)


def white_noise(prep: Prepared, *, seed: int = 0, **unknown: Any) -> MethodRun:
    """White-noise poisoning on the budget boundary of the problem's VRFT instance (the paper's random baseline)."""
    check_options("white-noise", unknown, {"seed"})
    check_common_options({"seed": seed})
    atk = instance_of(prep.problem)
    rng = np.random.default_rng(seed)
    signals = []
    for budget, signal, radius in ((atk.budget_u, atk.u, atk.delta_u), (atk.budget_y, atk.y, atk.delta_y)):
        z = rng.standard_normal(atk.N)
        signals.append(budget.projection(signal)(z * radius / max(np.linalg.norm(z, budget.order), 1e-300)))
    return method_run(prep, atk, state(atk, *signals), None, "a sample at the budget (a baseline, not an optimizer)")


METHODS: dict[str, Callable[..., MethodRun]] = {"alternating": alternating, "joint": joint, "white-noise": white_noise}
"""The structured methods by name: function(prepared, **options) -> MethodRun on a problem from problem_for."""


def attack(atk: VRFTAttack, method: str | Callable[..., MethodRun], warm_start: np.ndarray | None = None,
           **options: Any) -> BilevelResult:
    """Run a structured method (a name in METHODS, or a function(prepared, **options) -> MethodRun) on instance `atk`
    through the engine's solve (its certificate, probe and inversion), with warm_start (an a_y) as one more start;
    the result carries the instance's stats (VRFTAttack.stats) and the whole call's wall time (the problem's
    declaration or re-load included)."""
    t0 = time.perf_counter()
    problem = problem_for(atk)
    if warm_start is not None:
        if np.shape(warm_start) != (atk.N,):
            raise ModelError(f"warm_start must have shape ({atk.N},), got {np.shape(warm_start)}")
        problem.suggest_start(a_y=atk.budget_y.projection(atk.y)(np.asarray(warm_start, dtype=float)))
        options["starts"] = options.get("starts", 1) + 1
    fn = method if callable(method) else METHODS[method]
    result = solve(problem, method=fn, **{k: v for k, v in options.items() if v is not None})
    stats = {**result.stats, **atk.stats(result.y["theta"])}
    return dataclasses.replace(result, method=method if isinstance(method, str) else result.method,
                               wall_time=time.perf_counter() - t0, stats=stats)


def attack_alternating(atk: VRFTAttack, starts: int = 1, seed: int = 0, max_iter: int | None = None,
                       tol: float = TOL, first: str = "conditioning", steps: tuple[float, ...] = DEFAULT_STEPS,
                       warm_start: np.ndarray | None = None) -> BilevelResult:
    """The alternating attack (module docstring) on `atk`. V(a_y) is multimodal: the first start makes the poisoned
    regressor ill-conditioned, further starts are seeded random points, and warm_start (an a_y, e.g. the best one at
    a smaller budget) is one more; the best end point is kept. max_iter: MAX_ITER by objective."""
    return attack(atk, "alternating", warm_start, starts=starts, seed=seed, max_iter=max_iter, tol=tol, first=first,
                  steps=steps)


def attack_joint(atk: VRFTAttack, starts: int = 1, seed: int = 0, max_iter: int = JOINT_MAX_ITER,
                 tol: float = TOL, first: str = "zero") -> BilevelResult:
    """Joint projected hypergradient ascent on (a_u, a_y) of `atk`, each block scaled to its budget (multistart)."""
    return attack(atk, "joint", starts=starts, seed=seed, max_iter=max_iter, tol=tol, first=first)


def attack_white_noise(atk: VRFTAttack, seed: int = 0) -> BilevelResult:
    """White-noise poisoning of `atk` on the budget boundary (the paper's random baseline)."""
    return attack(atk, "white-noise", seed=seed)


def attack_budget_path(atk: VRFTAttack, eps_y: Sequence[float], **options: Any) -> list[BilevelResult]:
    """attack_alternating at each output budget eps_y in increasing order (same data and a_u budget).

    From the second budget on, the previous budget's best a_y (feasible in the larger ball) is an extra
    start, so the objective never decreases along the path (V is monotone in the budget; a single
    start can miss that on a multimodal V). Returns one result per budget, in increasing eps_y.
    """
    if atk.objective == "destabilize":
        raise ModelError("the budget path runs the alternating attack; 'destabilize' needs attack_joint")
    if len(eps_y) == 0:
        raise ModelError("attack_budget_path needs at least one output budget eps_y, e.g. [0.02, 0.05, 0.1]")
    results: list[BilevelResult] = []
    for eps in sorted(eps_y):
        stage = dataclasses.replace(atk, budget_y=dataclasses.replace(atk.budget_y, eps=eps))
        results.append(attack_alternating(stage, warm_start=results[-1].x["a_y"] if results else None, **options))
    return results


ATTACKS: dict[str, Callable[..., BilevelResult]] = {
    "alternating": attack_alternating,
    "joint": attack_joint,
    "white-noise": attack_white_noise,
}
"""Attack functions by name: function(instance, **options) -> BilevelResult."""


def attack_value(result: BilevelResult) -> float:
    """The attack's own criterion at the poisoned theta (maximized): -distance for 'targeted', the log-sum-exp
    of the modelled poles for 'destabilize'; upper_objective is the registered problem's F."""
    return attack_stat(result, "value")


def attack_summary(result: BilevelResult) -> dict[str, Any]:
    """Scalars of a VRFT attack result, one row of the reproduction's tables and of the CLI's output."""
    attack_stat(result, "learner_loss")
    st, cert = result.stats, result.certificate
    return {"method": result.method, "objective": st["objective"], "status": result.status.value,
            "value": attack_value(result), "value_clean": st["value_clean"], "learner_loss": st["learner_loss"],
            "spectral_radius": st["spectral_radius"], "spectral_radius_clean": st["spectral_radius_clean"],
            "delta_u": st["delta_u"], "delta_y": st["delta_y"], "wall_time": result.wall_time,
            "iterations": result.nit, "evaluations": st["evaluations"], "learner_stationarity": cert.stationarity,
            "refit_distance": cert.y_distance, "unstable": unstable(result), "certified": cert.passed}


def save_attack(result: BilevelResult, atk: VRFTAttack, path: str) -> None:
    """Write clean data, attack signals, clean/poisoned theta and closed-loop poles to an .npz file."""
    attack_stat(result, "theta_clean")
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder):
        raise ModelError(f"save_attack: directory {folder!r} of {path!r} does not exist; create it first")
    loop, theta, theta0 = atk.setting.loop, result.y["theta"], result.stats["theta_clean"]
    target = os.fspath(path) if os.fspath(path).endswith(".npz") else os.fspath(path) + ".npz"  # as np.savez names it
    with atomic_path(target) as tmp:
        np.savez(tmp, u=atk.u, y=atk.y, a_u=result.x["a_u"], a_y=result.x["a_y"], theta_clean=theta0,
                 theta_poisoned=theta, poles_clean=loop.poles(theta0), poles_poisoned=loop.poles(theta),
                 delta_u=atk.delta_u, delta_y=atk.delta_y, data_convention=atk.setting.data,
                 boundary=atk.setting.boundary, method=result.method, objective=atk.objective,
                 value=attack_value(result))


def input_step(atk: VRFTAttack, a_y: np.ndarray, a_u0: np.ndarray | None = None,
               iters: int = 30) -> tuple[np.ndarray, State]:
    """The best a_u for fixed a_y: exact (l2), monotone conditional gradient (max-min), or projected gradient."""
    b = atk.budget_u
    if atk.objective != "destabilize" and b.norm == "l2" and b.rho is None:
        return best_input_attack(atk, a_y)
    a = np.zeros(atk.N) if a_u0 is None else a_u0
    s = state(atk, a, a_y)
    if atk.objective == "maxmin":  # J convex in a_u: the linear maximizer never decreases J (Mangasarian 1996)
        value = atk.value(s.theta)
        for _ in range(iters):
            g_u, _ = hypergradient(atk, s)
            a_new = b.linear_maximizer(g_u, atk.delta_u)
            s_new = state(atk, a_new, a_y)
            v_new = atk.value(s_new.theta)
            if v_new <= value * (1 + 1e-12):
                break
            a, s, value = a_new, s_new, v_new
        return a, s
    proj = b.projection(atk.u)
    order = b.order
    def value(x: np.ndarray) -> tuple[float, State]:
        st = state(atk, x, a_y)
        return atk.value(st.theta), st

    def direction(st: State) -> tuple[np.ndarray, np.ndarray]:
        g = hypergradient(atk, st)[0]
        return g, budget_direction(g, atk.delta_u, order)

    a, _, s, _, _, _ = projected_ascent(value, direction, proj, a, atk.delta_u, iters, 1e-9, [])
    return a, s
