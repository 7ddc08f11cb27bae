"""Attacks on the De Persis–Tesi learners (WillemsAttack, bilevel.problems.willems) as `bilevel.solve` runs on the
attack's declared problem (`radius_problem` for destabilize_attack), with the learner's selection given to its SDP
lower level: the engine's oracle, methods and finalize (independent re-solve, local probe). Each result carries
willems_stats (gain, true and identified radius)."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import casadi as ca
import numpy as np

from ..ddc.depersis_tesi import lqr_controller, stabilizing_controller
from ..defaults import param
from ..errors import ModelError
from ..model import BilevelProblem
from ..problems.willems import SOLVER_SELECTIONS, WillemsAttack, criterion_values
from ..result import BilevelResult
from ..solvers.base import check_options, prepare
from ..solvers.box_methods import destabilize, random_signs
from ..solvers.implicit import Hypergradient, shared_oracle
from ..threads import single_threaded_call
from .outcome import attack_result


def loop(attack: WillemsAttack, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gain K and the attacker's identified loop A_id + B_id K at poisoning x (flat) and learner solution y (the
    CasADi function of the declared gain and loop kept on attack)."""
    if "_loop" not in attack.__dict__:
        y_sym = ca.vertcat(*[ca.vec(v.sym) for v in attack.problem.lower_variables])
        attack.__dict__["_loop"] = ca.Function("loop", [attack.upper, y_sym], [attack.gain, attack.closed_loop])
    gain, acl = attack.__dict__["_loop"](x, y)
    return np.asarray(gain, dtype=float), np.asarray(acl, dtype=float)


def identified_radius(attack: WillemsAttack, x: np.ndarray, y: np.ndarray) -> float:
    """Spectral radius of the attacker's identified closed loop A_id + B_id K at poisoning x, learner solution y."""
    return float(np.max(np.abs(np.linalg.eigvals(loop(attack, x, y)[1]))))


def engine(attack: WillemsAttack, radius: bool = False) -> Hypergradient:
    """The engine's implicit oracle on the attack's problem (radius: its spectral-radius form), the learner with the
    attack's selection; `engine(attack).low` is the learner's SDP lower level."""
    return shared_oracle(prepare(_problem(attack, radius)))


_SHARED: dict[tuple, BilevelProblem] = {}


def _problem(attack: WillemsAttack, radius: bool) -> BilevelProblem:
    """The problem of the attack's declaration (or its spectral-radius form), prepared once per process for the last
    defaults["willems.shared_kept"] declarations and given this attack's box (Prepared.rebox): attacks on one data set
    at several budgets or by several methods share the engine's preparation and the learner's solves. The learner's
    selection is given to its SDP lower level."""
    key = (attack.declaration, radius)
    problem = _SHARED.pop(key, None) or (attack.radius_problem() if radius else attack.problem)
    _SHARED[key] = problem
    while len(_SHARED) > param("willems.shared_kept"):
        del _SHARED[next(iter(_SHARED))]
    prep = prepare(problem)
    bound = attack.budget()
    if not (np.array_equal(prep.canon.x_ub, bound) and np.array_equal(prep.canon.x_lb, -bound)):
        prep.rebox(-bound, bound)
    low = prep.canon.lower
    low.min_norm = attack.setting.selection == "min-norm"
    if attack.setting.selection in SOLVER_SELECTIONS and low.chosen() is None:
        zero = np.zeros(low.n_x)
        ridge = low.select_min_norm(zero, low.newton_polish(zero, low.reference_solve(zero))[0])
        learner = stabilizing_controller if attack.setting.design == "stabilizing" else lqr_controller
        kwargs = {} if attack.setting.design == "stabilizing" else {"qx": attack.qx, "input_cost": False}
        q = learner(attack.x, attack.u, solver=attack.setting.selection, **kwargs).q.ravel(order="F")
        low.choose(dataclasses.replace(ridge, y=q, objective=float(low.evaluate(zero, q)[0]),
                                       solver=f"cvxpy+{attack.setting.selection}"))
    return problem


def _goal(attack: WillemsAttack, stop_when_unstable: bool, counter: dict[str, int]) -> Any:
    """The attacker's callback: count evaluations, stop (StopIteration) once the identified loop is unstable, with
    stop_when_unstable or for the max-min criterion (+inf there)."""
    stops = stop_when_unstable or attack.setting.objective == "maxmin"

    def callback(point: Any) -> None:
        counter["evaluations"] += 1
        if stops and identified_radius(attack, point.x, point.y) >= 1.0:
            raise StopIteration
    return callback


def willems_stats(attack: WillemsAttack, result: BilevelResult, evaluations: int,
                  relearn: bool = False) -> dict[str, Any]:
    """The Willems quantities of an attack's result: x, gain, eigenvalues and spectral radius of the true loop, the
    identified radius, the criterion (numerically; +inf for an unstable max-min loop), the budget violation and the
    learner's largest scaled KKT residual (certificate); relearn: the gain of the engine's learner solved at x, not
    of the result's y (a KKT method's y need not be the learner's response)."""
    p, cert = attack.problem, result.certificate
    x = np.concatenate([np.asarray(result.x[v.name], dtype=float).reshape(-1, order="F") for v in p.upper_variables])
    y = engine(attack).evaluate(x).lower.y if relearn else \
        np.concatenate([np.asarray(result.y[v.name], dtype=float).reshape(-1, order="F") for v in p.lower_variables])
    gain, acl = loop(attack, x, y)
    eig = np.linalg.eigvals(attack.true_closed_loop(gain))
    criterion = float(criterion_values(acl, gain, attack.setting.objective, attack.qx, attack.cost_weight))
    return {"objective": attack.setting.objective, "x": x, "gain": gain, "eigenvalues": eig,
            "spectral_radius": float(np.max(np.abs(eig))), "identified_radius": identified_radius(attack, x, y),
            "criterion": criterion, "evaluations": evaluations, "budget_violation": cert.upper_feasibility,
            "kkt_residual": max(cert.stationarity, cert.lower_feasibility, cert.dual_feasibility, cert.complementarity),
            "details": {"starts": len(result.start_records), "best_start": result.stats.get("best_start"),
                        "certificate_failed": list(cert.failed)}}


def _run(attack: WillemsAttack, name: str, method: Any, radius: bool = False, relearn: bool = False,
         **options: Any) -> BilevelResult:
    """solve(the attack's problem, method, options) as attack `name`, with willems_stats; the whole call's time."""
    t0, counter = time.perf_counter(), {"evaluations": 0}
    if "stop_when_unstable" in options:
        options["callback"] = _goal(attack, options.pop("stop_when_unstable"), counter)
    return attack_result(_problem(attack, radius), method, name, lambda r: willems_stats(
        attack, r, int(r.stats.get("evaluations", counter["evaluations"] or 1)), relearn), t0, **options)


@single_threaded_call
def hypergradient_attack(attack: WillemsAttack, *, starts: int | None = None, seed: Any = 0,
                         max_iter: int | None = None, ftol: float | None = None, stop_when_unstable: bool = True,
                         **unknown: Any) -> BilevelResult:
    """Method hypergradient on the attack's criterion from `starts` starts (start 0: clean data; others uniform in the
    box, drawn from `seed`), max_iter steps each, ftol its stop, near-ties between starts to the larger identified
    radius; with stop_when_unstable it stops at the first point whose identified loop is unstable. None takes the
    registry's value, defaults["willems.hypergradient.NAME"]."""
    check_options("hypergradient_attack", unknown, hypergradient_attack)
    prefer = lambda point: identified_radius(attack, point.x, point.y)  # noqa: E731
    return _run(attack, "hypergradient", "hypergradient", starts=param("willems.hypergradient.starts", starts),
                seed=seed, max_iter=param("willems.hypergradient.max_iter", max_iter),
                ftol=param("willems.hypergradient.ftol", ftol), stop_when_unstable=stop_when_unstable, prefer=prefer)


@single_threaded_call
def de_attack(attack: WillemsAttack, *, seed: Any = 0, max_iter: int | None = None, popsize: int | None = None,
              pop_tol: float | None = None, stop_when_unstable: bool = True, **unknown: Any) -> BilevelResult:
    """Method differential-evolution (seed, max_iter generations of popsize members per entry, pop_tol its stop) on
    the input poisoning, without its descent (a heuristic), a generation scored at once where the learner ignores the
    poisoning (_criteria); with stop_when_unstable it stops once the incumbent's identified loop is unstable. None
    takes the registry's value, defaults["willems.evolution.NAME"] (pop_tol: "evolution.pop_tol")."""
    check_options("de_attack", unknown, de_attack)
    if attack.setting.poison != "u" or attack.setting.delta_u <= 0:
        raise ModelError(f"de_attack poisons the inputs only (the paper's corollary) with delta_u > 0; got poison="
                         f"{attack.setting.poison!r}, delta_u={attack.setting.delta_u}")
    twin = {} if attack.setting.design == "lqr-r" else {"batch_objective": lambda xs, y: _criteria(attack, xs, y)}
    return _run(attack, "differential-evolution", "differential-evolution", seed=seed,
                max_iter=param("willems.evolution.max_iter", max_iter),
                popsize=param("willems.evolution.popsize", popsize), pop_tol=pop_tol, polish=False,
                stop_when_unstable=stop_when_unstable, **twin)


def _criteria(attack: WillemsAttack, xs: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The criterion at each column of xs for a learner that ignores the poisoning: K = K0 + dK/dx x is affine in x
    (K0 and dK/dx from the declared gain, once per attack), the criterion numerically (criterion_values)."""
    if "_affine" not in attack.__dict__:
        y_sym = ca.vertcat(*[ca.vec(v.sym) for v in attack.problem.lower_variables])
        affine = ca.Function("affine", [attack.upper, y_sym], [attack.gain, ca.jacobian(ca.vec(attack.gain),
                                                                                         attack.upper)])
        attack.__dict__["_affine"] = tuple(np.asarray(v, dtype=float) for v in affine(np.zeros(xs.shape[0]), y))
    k0, jac = attack.__dict__["_affine"]
    gains = k0[None] + (xs.T @ jac.T).reshape(xs.shape[1], attack.n_states, attack.n_inputs).transpose(0, 2, 1)
    return criterion_values(attack.a_id + attack.b_id @ gains, gains, attack.setting.objective, attack.qx,
                            attack.cost_weight)


@single_threaded_call
def random_attack(attack: WillemsAttack, *, seed: Any = 0) -> BilevelResult:
    """A budget-matched, non-adaptive baseline: every poisoned entry +-budget with a fair random sign."""
    return _run(attack, "random", random_signs, seed=seed)


@single_threaded_call
def destabilize_attack(attack: WillemsAttack, *, starts: int | None = None, seed: Any = 0, max_iter: int | None = None,
                       pool: int | None = None, **unknown: Any) -> BilevelResult:
    """Maximize the spectral radius of the attacker's loop A_id + B_id K over the input poisoning, exactly (method
    destabilize on attack.radius_problem: the learner solved once, K affine in the poisoning) with its options starts,
    seed, max_iter and pool, None taking defaults["destabilize.NAME"]."""
    check_options("destabilize_attack", unknown, destabilize_attack)
    if attack.setting.objective != "destabilize":
        raise ModelError(f"destabilize_attack maximizes the spectral radius; got objective="
                         f"{attack.setting.objective!r}: build the attack with objective='destabilize'")
    return _run(attack, "destabilize", destabilize, radius=True, starts=starts, seed=seed, max_iter=max_iter,
                pool=pool)


@single_threaded_call
def kkt_attack(attack: WillemsAttack, method: str = "ipopt", **options: Any) -> BilevelResult:
    """The generic route: bilevel.solve on the declared problem with a KKT method (reformulation, PSD pairs
    factored); its answer is certified and probed like every attack's; the gain in stats is the learner's, re-solved
    at the answer's poisoning."""
    return _run(attack, f"kkt-{method}", method, relearn=True, **options)
