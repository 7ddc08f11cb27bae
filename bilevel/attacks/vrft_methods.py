"""Attack algorithms on a VRFTAttack: alternating (the paper's Algorithm 1, strengthened), joint
hypergradient ascent, and white-noise poisoning at the same budget.

alternating: ascend the value function V(a_y) = max_{a_u} J(theta(u + a_u, y + a_y)) by spectral
  projected gradient (Barzilai-Borwein steps, Armijo backtracking); the inner max over a_u is solved at
  every evaluation (globally for l2 budgets by a trust-region subproblem, by monotone conditional gradient
  for the max-min objective under linf/l1/sparse budgets, by projected gradient otherwise).
  Danskin: grad V = dJ/da_y at a_u*.
joint: spectral projected gradient ascent on (a_u, a_y) together, each block measured in its budget radius.
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np

from ..certificate import DEFAULT_TOL, Certificate
from ..errors import ModelError
from ..files import atomic_path
from ..result import BilevelResult, Status
from ..solvers.ascent import budget_direction, projected_ascent
from ..solvers.options import check_common_options
from ..threads import single_threaded
from .outcome import attack_stat, unstable
from .vrft import State, VRFTAttack

DEFAULT_STEPS = (1.0,)
MAX_ITER = {"maxmin": 60, "targeted": 500}
"""attack_alternating's iteration limit by objective: 60 for max-min (the setting of the committed Table 1); 500 for
targeted, which at 60 ended at the limit on 40 of 40 data sets (scenario B, N = 512) and converges in 118-195
iterations (benchmarks/results/bench_vrft_iterations.txt)."""


def _certificate(atk: VRFTAttack, s: State, tol: float = DEFAULT_TOL) -> Certificate:
    """The learner's KKT at the poisoned data (stationarity max |Phi'(t - Phi theta)| over 1 + |Phi|_F |t|), an
    independent SVD least-squares refit theta_ref (relative distance and loss gap) and the budgets."""
    stationarity = float(np.abs(s.phi.T @ (s.target - s.phi @ s.theta)).max()
                         / (1.0 + np.linalg.norm(s.phi) * np.linalg.norm(s.target)))
    refit = np.linalg.lstsq(s.phi, s.target, rcond=None)[0]  # SVD: independent of the attack's QR path
    distance = float(np.linalg.norm(s.theta - refit) / max(1.0, float(np.linalg.norm(s.theta))))
    loss = lambda theta: float(np.sum((s.target - s.phi @ theta) ** 2) / atk.n)  # noqa: E731
    best = loss(refit)
    gap = (loss(s.theta) - best) / (1.0 + abs(best))
    over = [max(0.0, float(np.linalg.norm(a, b.order)) - r) / (1.0 + r)
            for a, b, r in ((s.a_u, atk.budget_u, atk.delta_u), (s.a_y, atk.budget_y, atk.delta_y))]
    checks = {"stationarity": stationarity, "lower_solution": distance, "lower_gap": gap,
              "upper_feasibility": max(over)}
    failed = tuple(k for k, v in checks.items() if not v <= tol)
    return Certificate(stationarity, 0.0, 0.0, 0.0, max(over), gap, best, refit.tolist(),
                       "numpy.linalg.lstsq (SVD)", tol, not failed, failed,
                       "least-squares learner: stationarity of its normal equations at the poisoned data and an "
                       "independent SVD refit (y_distance: relative distance to it)", lower_unique=True,
                       y_distance=distance)


def _result(atk: VRFTAttack, method: str, converged: bool | None, s: State, t0: float, iterations: int,
            evaluations: int, history: list[dict[str, float]]) -> BilevelResult:
    """The attack's outcome as a BilevelResult of its registered problem (vrft-<objective>): x = {a_u, a_y},
    y = {theta}, objectives in the problem's sense (lower_objective: the learner's loss on the poisoned data), the
    certificate, and the VRFT quantities in stats (learner_loss: its loss on the clean data at the poisoned theta).
    converged None: a sample, not an optimization (its status is at best INACCURATE)."""
    wall_time = time.perf_counter() - t0
    cert = _certificate(atk, s)
    status = Status.of_run(converged, cert.passed)
    message = ("a sample at the budget (a baseline, not an optimizer)" if converged is None else
               "converged" if converged else "max_iter reached")
    message += "; certificate passed" if cert.passed else f"; certificate failed on {cert.describe_failures()}"
    loop, value = atk.setting.loop, atk.value(s.theta)
    r, poisoned = atk.t0 - atk.phi0 @ s.theta, s.target - s.phi @ s.theta
    stats = {"objective": atk.objective, "value": value, "learner_loss": float(r @ r / atk.n),
             "theta_clean": atk.theta0, "value_clean": atk.value(atk.theta0),
             "spectral_radius": loop.spectral_radius(s.theta),
             "spectral_radius_clean": loop.spectral_radius(atk.theta0),
             "delta_u": atk.delta_u, "delta_y": atk.delta_y, "evaluations": evaluations}
    return BilevelResult(status, message, method, f"vrft-{atk.objective}", {"a_u": s.a_u, "a_y": s.a_y},
                         {"theta": s.theta}, {}, _registered_objective(atk, s.theta, value),
                         float(poisoned @ poisoned / atk.n),
                         cert, wall_time, iterations, tuple(history), (), stats)


def _registered_objective(atk: VRFTAttack, theta: np.ndarray, value: float) -> float:
    """F of the registered problem vrft-<objective> at theta (the attack's own criterion is `value`): the same for
    max-min, its negative for 'targeted' (a minimization there), the Gelfand radius for 'destabilize' (the attack
    ascends a log-sum-exp of the pole moduli instead)."""
    if atk.objective == "destabilize":
        from ..problems.vrft import gelfand_radius  # problems.vrft imports this module

        loop = atk.model_loop
        return float(gelfand_radius(loop.base, loop.slopes, ca.DM(theta)))
    return -value if atk.objective == "targeted" else value


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


def input_step(atk: VRFTAttack, a_y: np.ndarray, a_u0: np.ndarray | None = None, iters: int = 30) -> tuple[np.ndarray, State]:
    """The best a_u for fixed a_y: exact (l2), monotone conditional gradient (max-min), or projected gradient."""
    b = atk.budget_u
    if atk.objective != "destabilize" and b.norm == "l2" and b.rho is None:
        return atk.best_input_attack(a_y)
    a = np.zeros(atk.N) if a_u0 is None else a_u0
    s = atk.state(a, a_y)
    if atk.objective == "maxmin":  # J convex in a_u: the linear maximizer never decreases J (Mangasarian 1996)
        value = atk.value(s.theta)
        for _ in range(iters):
            g_u, _ = atk.hypergradient(s)
            a_new = b.linear_maximizer(g_u, atk.delta_u)
            s_new = atk.state(a_new, a_y)
            v_new = atk.value(s_new.theta)
            if v_new <= value * (1 + 1e-12):
                break
            a, s, value = a_new, s_new, v_new
        return a, s
    proj = b.projection(atk.u)
    order = b.order
    def value(x: np.ndarray) -> tuple[float, State]:
        st = atk.state(x, a_y)
        return atk.value(st.theta), st

    def direction(st: State) -> tuple[np.ndarray, np.ndarray]:
        g = atk.hypergradient(st)[0]
        return g, budget_direction(g, atk.delta_u, order)

    a, _, s, _, _, _ = projected_ascent(value, direction, proj, a, atk.delta_u, iters, 1e-9, [])
    return a, s


def conditioning_start(atk: VRFTAttack, iters: int = 10) -> np.ndarray:
    """a_y that makes the poisoned regressor ill-conditioned: projected descent on sigma_min(Phi(y + a_y)).

    The learner's loss at theta' grows when Phi'^T Phi' nearly loses rank (theta' then moves far for a
    small a_u), so the max-min ascent starts from the a_y that shrinks Phi's smallest singular value
    (gradient sum_i w_i T_i^T l for its singular pair (l, w)), one budget radius per step.
    """
    reg = atk.setting.regressor
    proj = atk.budget_y.projection(atk.y)
    a = np.zeros(atk.N)
    for _ in range(iters):
        U, _, Vt = np.linalg.svd(atk.phi0 + reg(a), full_matrices=False)
        g = reg.adjoint(np.outer(U[:, -1], Vt[-1]))
        a = proj(a - budget_direction(g, atk.delta_y, atk.budget_y.order))
    return a


def _start_points(atk: VRFTAttack, starts: int, rng: np.random.Generator, first: str,
                  warm_start: np.ndarray | None = None) -> list[np.ndarray]:
    """a_y starts: `first` ("conditioning", "zero" or "random"), seeded random points on the budget boundary,
    then warm_start (projected onto the budget) if given."""
    if first not in ("conditioning", "zero", "random"):
        raise ModelError(f"first start {first!r} is not 'conditioning', 'zero' or 'random'")
    proj = atk.budget_y.projection(atk.y)
    points = {"conditioning": [conditioning_start(atk)], "zero": [np.zeros(atk.N)], "random": []}[first]
    while len(points) < starts:
        z = rng.standard_normal(atk.N)
        points.append(proj(z * (atk.delta_y / max(np.linalg.norm(z, atk.budget_y.order), 1e-300))))
    if warm_start is not None:
        if np.shape(warm_start) != (atk.N,):
            raise ModelError(f"warm_start must have shape ({atk.N},), got {np.shape(warm_start)}")
        points.append(proj(np.asarray(warm_start, dtype=float)))
    return points


def attack_alternating(atk: VRFTAttack, starts: int = 1, seed: int = 0, max_iter: int | None = None,
                       tol: float = 1e-4, first: str = "conditioning",
                       steps: tuple[float, ...] = DEFAULT_STEPS, warm_start: np.ndarray | None = None) -> BilevelResult:
    """The paper's Algorithm 1 with an exact a_u step and line-searched projected ascent on a_y.

    V(a_y) is multimodal: the first start makes the poisoned regressor ill-conditioned (see
    conditioning_start), further starts are seeded random points, and warm_start (an a_y, e.g. the
    best one at a smaller budget) is one more; every start is followed from each initial step in
    `steps` (fractions of the budget radius) and the best end point is kept. max_iter: MAX_ITER by objective.
    """
    if atk.objective == "destabilize":
        raise ModelError("the alternating attack needs a quadratic objective; use attack_joint for 'destabilize'")
    max_iter = MAX_ITER[atk.objective] if max_iter is None else max_iter
    check_common_options({"starts": starts, "seed": seed, "max_iter": max_iter, "tol": tol})
    if not steps or not all(isinstance(v, (int, float)) and 0 < v < np.inf for v in steps):
        raise ModelError(f"steps={steps!r} is invalid: it must be a non-empty tuple of initial steps > 0 (fractions "
                         "of the budget radius), e.g. (1.0,)")
    t0 = time.perf_counter()
    proj_y = atk.budget_y.projection(atk.y)
    order = atk.budget_y.order
    best, total_it, total_ev = None, 0, 0
    with single_threaded():
        runs = [(ay0, step0) for ay0 in _start_points(atk, starts, np.random.default_rng(seed), first, warm_start)
                for step0 in steps]
        for k, (ay0, step0) in enumerate(runs):
            history: list[dict[str, float]] = []
            memo: dict[str, np.ndarray] = {}

            def value(a_y: np.ndarray) -> tuple[float, State]:
                a_u, s = input_step(atk, a_y, memo.get("a_u"))
                memo["a_u"] = a_u
                return atk.value(s.theta), s

            def direction(s: State) -> tuple[np.ndarray, np.ndarray]:
                g_y = atk.hypergradient(s)[1]
                return g_y, budget_direction(g_y, atk.delta_y, order)

            _, fx, s, it, ev, conv = projected_ascent(value, direction, proj_y, ay0, atk.delta_y, max_iter, tol,
                                                      history, step0)
            total_it, total_ev = total_it + it, total_ev + ev
            if best is None or fx > best[0]:
                best = (fx, s, history, conv, k)
    fx, s, history, conv, k = best
    return _result(atk, "alternating", conv, s, t0, total_it, total_ev, history)


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


def attack_joint(atk: VRFTAttack, starts: int = 1, seed: int = 0, max_iter: int = 200,
                 tol: float = 1e-4, first: str = "zero") -> BilevelResult:
    """Joint projected hypergradient ascent on (a_u, a_y), each block scaled to its budget (multistart)."""
    check_common_options({"starts": starts, "seed": seed, "max_iter": max_iter, "tol": tol})
    t0 = time.perf_counter()
    N = atk.N
    pu, py = atk.budget_u.projection(atk.u), atk.budget_y.projection(atk.y)
    ou, oy = atk.budget_u.order, atk.budget_y.order
    project = lambda x: np.concatenate([pu(x[:N]), py(x[N:])])  # noqa: E731
    scale = np.concatenate([np.full(N, atk.delta_u), np.full(N, atk.delta_y)])

    def value(x: np.ndarray) -> tuple[float, State]:
        s = atk.state(x[:N], x[N:])
        return atk.value(s.theta), s

    def direction(s: State) -> tuple[np.ndarray, np.ndarray]:
        g_u, g_y = atk.hypergradient(s)
        return np.concatenate([g_u, g_y]), np.concatenate([budget_direction(g_u, atk.delta_u, ou),
                                                           budget_direction(g_y, atk.delta_y, oy)])

    best, total_it, total_ev = None, 0, 0
    with single_threaded():
        for ay0 in _start_points(atk, starts, np.random.default_rng(seed), first):
            history: list[dict[str, float]] = []
            _, fx, s, it, ev, conv = projected_ascent(value, direction, project, np.concatenate([np.zeros(N), ay0]),
                                                      scale, max_iter, tol, history)
            total_it, total_ev = total_it + it, total_ev + ev
            if best is None or fx > best[0]:
                best = (fx, s, history, conv)
    fx, s, history, conv = best
    return _result(atk, "joint", conv, s, t0, total_it, total_ev, history)


def attack_white_noise(atk: VRFTAttack, seed: int = 0) -> BilevelResult:
    """White-noise poisoning on the budget boundary (the paper's random baseline)."""
    check_common_options({"seed": seed})
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    signals = []
    for budget, signal, radius in ((atk.budget_u, atk.u, atk.delta_u), (atk.budget_y, atk.y, atk.delta_y)):
        z = rng.standard_normal(atk.N)
        signals.append(budget.projection(signal)(z * radius / max(np.linalg.norm(z, budget.order), 1e-300)))
    s = atk.state(*signals)
    return _result(atk, "white-noise", None, s, t0, 0, 1, [])


ATTACKS: dict[str, Callable[..., BilevelResult]] = {
    "alternating": attack_alternating,
    "joint": attack_joint,
    "white-noise": attack_white_noise,
}
"""Attack methods by name."""
