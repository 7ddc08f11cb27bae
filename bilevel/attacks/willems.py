"""Attacks on the De Persis–Tesi learners: hypergradient ascent through the SDP, the KKT route, and DE.

Hypergradient. At a poisoning x the learner's SDP (bilevel.problems.willems) is solved by its own
solver (cvxpy + Clarabel) and polished by Newton steps on its KKT system (bilevel.lower.sdp.ConicKKT,
the one implementation the generic hypergradient method uses too)

    r(w; x) = [grad_y L ; h ; vech((M_k Z_k + Z_k M_k) / 2)] = 0,   w = (y, mu, vech Z_k),

with L = f + mu'h - sum_k <Z_k, M_k> (the framework's convention, Z_k >= 0). With the "min-norm"
selection, y is then projected onto the directions the SDP sees (SemidefiniteLower.select_min_norm, the generic
engine's selection; here Q onto the row space of the data D(x), see bilevel.problems.willems): this removes the
solver's error in Q's null-space directions, which only the tiny Tikhonov weight reg pins down, and leaves D Q and
every constraint unchanged. At a strictly
complementary, nondegenerate solution dr/dw is nonsingular (Alizadeh, Haeberly & Overton 1998),
so y*(x) is differentiable with dw/dx = -(dr/dw)^-1 dr/dx. The gradient of phi(x) = F(x, y*(x))
comes from the adjoint system (dr/dw)' z = (dF/dy, 0, 0): grad phi = dF/dx - (dr/dx)' z. When the
lower level does not depend on x (U poisoning of the lqr and stabilizing designs) it is solved once; otherwise each
new point's solution is first sought by Newton continuation from the last one (SemidefiniteLower.continue_from).
Attacks on one declaration (data, learner, criterion; any budget) share one oracle per process (shared_oracle).

Ascent: the engine's spectral projected gradient loop (bilevel.solvers.ascent, in budget units) on the
linf box (exact clipping, bilevel.solvers.projections.Box), from the clean data and from uniform random
points of the box. For the max-min criterion a point whose identified
closed loop is unstable has phi = +inf (the paper's convention): the ascent stops there; with
stop_when_unstable (default) the eigenvalue attack stops there too, since instability is its goal.

Destabilizing attack (destabilize_attack): the exact spectral radius of the identified loop on the generic engine
(WillemsAttack.radius_problem, BilevelProblem.maximize_spectral_radius) for a learner that ignores the poisoning:
the learner is solved once, a pool of points is screened and the best ascend together (batched_box_ascent); the
answer is the evaluated point with the largest identified rho.
smallest_destabilizing_budget finds delta_u* along a budget path, then by bisection.

Baselines: differential evolution (bilevel.solvers.evolution) on the input poisoning with the same box, criterion and
stopping rule; random signs at the budget; and the generic route, bilevel.solve on the registered
problem (KKT reformulation with the LMI's PSD complementarity pair, IPOPT or the relaxation sequence).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Callable, Literal

import casadi as ca
import numpy as np
import scipy.optimize

from ..ddc.depersis_tesi import lqr_controller, stabilizing_controller
from ..certificate import DEFAULT_TOL, Certificate
from ..errors import BilevelError, ModelError, SolverFailed
from ..lower import LowerSolution, build_lower
from ..lower.quadratic import clarabel_solution
from ..lower.sdp import SemidefiniteLower
from ..model import unflatten_all
from ..problems.willems import SOLVER_SELECTIONS, WillemsAttack, WillemsSetting, build_attack, criterion_values
from ..result import BilevelResult, Status
from ..solvers import solve
from ..solvers.ascent import batched_box_ascent, budget_direction, projected_ascent
from ..solvers.budget_search import BudgetSearch, smallest_budget
from ..solvers.base import prepare
from ..solvers.evolution import evolve
from ..solvers.implicit import Hypergradient
from ..solvers.projections import Box
from ..solvers.options import check_common_options, check_counts, check_numbers
from ..threads import single_threaded_call
from .outcome import attack_stat, unstable

KKT_TOL = 1e-6
GOAL = "identified closed loop unstable (the attacker's goal: a stop, not a local maximum)"
CONVERGED = "relative increase <= ftol, or no ascent along the projection arc"
TIE_RTOL = 1e-6
UNSTABLE_PENALTY = 1e12
"""Finite stand-in for phi = +inf handed to differential evolution (which cannot rank infinities)."""


@dataclass
class Evaluation:
    """An upper point with the learner's (polished) response, its gain and the attacker's objective."""

    x: np.ndarray
    phi: float
    gain: np.ndarray
    closed_loop: np.ndarray
    lower: LowerSolution
    kkt_residual: float
    grad_x: np.ndarray
    grad_y: np.ndarray

    @property
    def identified_radius(self) -> float:
        """Spectral radius of the attacker's (identified) closed loop A_id + B_id K."""
        return float(np.max(np.abs(np.linalg.eigvals(self.closed_loop))))


class SDPHypergradient:
    """phi(x) = F(x, y*(x)) of a WillemsAttack and its gradient by implicit differentiation of the SDP's KKT system."""

    def __init__(self, attack: WillemsAttack, polish_steps: int = 4, lower: SemidefiniteLower | None = None) -> None:
        """lower: the learner's lower level if already built from attack.problem (an engine's canonical one)."""
        p = attack.problem
        self.attack, self.polish_steps = attack, int(polish_steps)
        x = attack.upper
        y = ca.vertcat(*[ca.vec(v.sym) for v in p.lower_variables])
        if lower is None:
            h = ca.vertcat(*[c.body for c in p.lower_constraints])
            psd = [c.matrix for c in p.lower_psd_constraints]
            h_names = [f"{c.name}[{i}]" for c in p.lower_constraints for i in range(int(c.body.numel()))]
            lower = build_lower(x, y, p.lower_objective.expr, ca.SX(0, 1), h, psd, [], h_names,
                                [c.name for c in p.lower_psd_constraints], [np.zeros(int(x.numel()))])
        self.lower_level = lower
        F = p.upper_objective.expr
        self._upper = ca.Function("attacker", [x, y], [F, ca.gradient(F, x), ca.gradient(F, y), attack.gain,
                                                       attack.closed_loop])
        self.lower_fixed = self.lower_level.fixed
        self._x, self._y = x, y
        self.n_x = int(x.numel())
        self.lower_solves = 0
        self._cache: tuple[np.ndarray, LowerSolution, float] | None = None
        self._affine: tuple[np.ndarray, np.ndarray] | None = None  # K(0) and dK/dx of a fixed learner

    @cached_property
    def _gain(self) -> ca.Function:
        """(x, y) -> K and dK/dx (built on first use: only the batched paths read it)."""
        x, gain = self._x, self.attack.gain
        return ca.Function("gain", [x, self._y], [gain, ca.jacobian(ca.vec(gain), x)])

    @cached_property
    def _gain_affine(self) -> bool:
        """Whether K is affine in x: the learner ignores x and dK/dx does not depend on x."""
        return self.lower_fixed and not ca.depends_on(ca.jacobian(ca.vec(self.attack.gain), self._x), self._x)

    # -- the learner's response ---------------------------------------------------------------------
    def polish(self, x: np.ndarray, sol: LowerSolution) -> tuple[LowerSolution, float]:
        """The lower level's Newton polish on its KKT system (bilevel.lower.sdp), polish_steps steps."""
        return self.lower_level.newton_polish(x, sol, self.polish_steps)

    def solver_selection(self) -> LowerSolution:
        """The unregularized learner's Q as its SDP solver returns it (selections "clarabel", "scs"), on the clean
        states: these selections exist only where the SDP ignores the poisoning (WillemsSetting checks it)."""
        at = self.attack
        if at.setting.design == "stabilizing":
            q = stabilizing_controller(at.x, at.u, solver=at.setting.selection).q
        else:
            q = lqr_controller(at.x, at.u, at.qx, input_cost=False, solver=at.setting.selection).q
        y = q.ravel(order="F")
        zero = np.zeros(self.n_x)
        return LowerSolution(y, float(self.lower_level.evaluate(zero, y)[0]), np.zeros(0),
                             np.zeros(int(self.lower_level.h.numel())), [], "optimal", f"cvxpy+{at.setting.selection}")

    def lower_solution(self, x: np.ndarray) -> tuple[LowerSolution, float]:
        """The learner's polished SDP solution at x and its KKT residual (solved once if it cannot depend on x).
        For the solver's own selection the residual is nan: its unregularized KKT system has no unique solution."""
        x = self.lower_level.check_point(x)
        if self._cache is not None and (self.lower_fixed or np.array_equal(self._cache[0], x)):
            return self._cache[1], self._cache[2]
        if self.attack.setting.selection in SOLVER_SELECTIONS:
            self.lower_solves += 1
            self._cache = (x.copy(), self.solver_selection(), float("nan"))
            return self._cache[1], self._cache[2]
        near = None if self._cache is None else self.lower_level.continue_from(x, self._cache[1], self.polish_steps + 2)
        if near is not None:  # Newton continuation from the last point's solution: no conic solve
            sol, res = near
        else:
            with warnings.catch_warnings():  # cvxpy's "may be inaccurate": the polished KKT residual decides below
                warnings.simplefilter("ignore", UserWarning)
                # Clarabel's raw point: the Newton polish below works on this SDP's own KKT system, so the
                # generic face polish of the certificate's re-solve would only add ~20 ms per solve
                sol = clarabel_solution(self.lower_level.data(x), "of the learner", self.lower_level.lmi_data(x))
            sol, res = self.polish(x, sol)
        if self.attack.setting.selection == "min-norm":  # the engine's selection: Q onto the row space of D
            sol = self.lower_level.select_min_norm(x, sol)
            res = self.lower_level.kkt_residual(x, sol)
        self.lower_solves += 1
        if res > KKT_TOL and not self.lower_fixed:  # a fixed response needs no implicit differentiation
            raise SolverFailed(f"the learner's SDP at this poisoning has KKT residual {res:.1e} > {KKT_TOL:g} after "
                               "Newton polishing (no strictly complementary solution found); the hypergradient "
                               "is not defined there — lower the budget or raise reg")
        self._cache = (x.copy(), sol, res)
        return sol, res

    # -- the attacker's objective ---------------------------------------------------------------------
    def evaluate(self, x: np.ndarray) -> Evaluation:
        """Solve the learner at x and evaluate the attacker's criterion (+inf for an unstable max-min loop)."""
        x = np.asarray(x, dtype=float).ravel()
        sol, res = self.lower_solution(x)
        F, gx, gy, k, acl = (np.asarray(v, dtype=float) for v in self._upper(x, sol.y))
        ev = Evaluation(x, float(F.ravel()[0]), k, acl, sol, res, gx.ravel(), gy.ravel())
        if self.attack.setting.objective == "maxmin" and ev.identified_radius >= 1.0:
            ev.phi = float("inf")
        return ev

    def gradient(self, ev: Evaluation) -> np.ndarray:
        """d phi / dx at an evaluated point: direct part plus the adjoint of the KKT system."""
        return self._total(ev, ev.grad_x, ev.grad_y)

    def _total(self, ev: Evaluation, grad_x: np.ndarray, grad_y: np.ndarray) -> np.ndarray:
        """grad_x - (dr/dx)' z with (dr/dw)' z = (grad_y, 0): the implicit derivative through the KKT system."""
        if self.lower_fixed:
            return grad_x
        return grad_x - self.lower_level.adjoint(ev.x, ev.lower, grad_y[:, None])[0].ravel()

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """(phi(x), grad phi(x))."""
        ev = self.evaluate(x)
        return ev.phi, self.gradient(ev)

    def loops(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Identified closed loops A_id + B_id K and gains K at the rows of xs, where the learner ignores x and K is
        affine in x (K0 and dK/dx evaluated once)."""
        if not self._gain_affine:
            raise ModelError("loops needs a learner that ignores the poisoning (K affine in it); use evaluate")
        if self._affine is None:
            zero = np.zeros(self.n_x)
            self._affine = tuple(np.asarray(v, dtype=float) for v in self._gain(zero, self.lower_solution(zero)[0].y))
        (k0, jac), at = self._affine, self.attack
        gains = k0[None] + (xs @ jac.T).reshape(xs.shape[0], at.n_states, at.n_inputs).transpose(0, 2, 1)
        return at.a_id + at.b_id @ gains, gains

    def identified_radius(self, x: np.ndarray) -> float:
        """Spectral radius of the identified closed loop at x."""
        acl = self.loops(x[None])[0][0] if self._gain_affine else self.evaluate(x).closed_loop
        return float(np.max(np.abs(np.linalg.eigvals(acl))))

    def objectives(self, xs: np.ndarray) -> np.ndarray:
        """phi at each row of xs; batched in numpy when the learner ignores x and K is then affine in x."""
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        if not self._gain_affine:
            return np.array([self.evaluate(x).phi for x in xs])
        at = self.attack
        return criterion_values(*self.loops(xs), at.setting.objective, at.qx, at.cost_weight)


def _certificate(at: WillemsAttack, x: np.ndarray, ev: Evaluation) -> Certificate:
    """The learner's KKT residual at the poisoned data (its own solve, Newton-polished; not checked for the solver's
    own Q, which is by definition that solver's answer) and the budget; no independent re-solve (lower_gap NaN)."""
    own = at.setting.selection in SOLVER_SELECTIONS
    bound = at.budget()
    violation = float(np.max(np.maximum(np.abs(x) - bound, 0.0), initial=0.0))
    failed = tuple(k for k, bad in (("stationarity", not own and not ev.kkt_residual <= KKT_TOL),
                                    ("upper_feasibility", violation > DEFAULT_TOL)) if bad)
    note = ("the learner is the SDP solver's own answer (selection " + at.setting.selection + "): no KKT check"
            if own else "KKT residual of the learner's SDP at the poisoned data (cvxpy + Clarabel, Newton-polished, "
            f"selection {at.setting.selection}); no independent re-solve")
    return Certificate(np.nan if own else ev.kkt_residual, 0.0, 0.0, 0.0, violation, np.nan, np.nan,
                       ev.lower.y.tolist(), "cvxpy + Clarabel", KKT_TOL, not failed, failed, note, y_distance=np.nan)


def _result(at: WillemsAttack, oracle: SDPHypergradient, method: str, x: np.ndarray, t0: float, evaluations: int,
            iterations: int, message: str, converged: bool | None,
            details: dict[str, Any] | None = None, ev: Evaluation | None = None) -> BilevelResult:
    """The attack's outcome as a BilevelResult of its registered problem willems-<objective>: x = {Du, Dx}, the
    learner's variables in y, upper_objective the criterion (+inf where the identified loop is unstable for the
    max-min criterion, the paper's convention), the certificate, and the gain and true closed loop in stats.
    converged: True at a converged ascent, False at max_iter, None for a heuristic, a sample or a stop at the
    attacker's goal (never SOLVED). ev: the point's evaluation if the attack made it (the learner is not solved
    again: where the SDP moves with x, the ascent's solution may come from Newton continuation)."""
    x = np.asarray(x, dtype=float)
    ev = ev if ev is not None and np.array_equal(ev.x, x) else oracle.evaluate(x)
    eig = np.linalg.eigvals(at.true_closed_loop(ev.gain))
    cert = _certificate(at, x, ev)
    p = at.problem
    stats = {"objective": at.setting.objective, "x": x, "gain": ev.gain, "eigenvalues": eig,
             "spectral_radius": float(np.max(np.abs(eig))), "identified_radius": ev.identified_radius,
             "evaluations": evaluations, "budget_violation": cert.upper_feasibility, "kkt_residual": ev.kkt_residual,
             "details": dict(details or {})}
    status = Status.of_run(converged, cert.passed)
    message += "; certificate passed" if cert.passed else f"; certificate failed on {cert.describe_failures()}"
    return BilevelResult(status, message, method, p.name, unflatten_all(p.upper_variables, x),
                         unflatten_all(p.lower_variables, ev.lower.y), {}, ev.phi, ev.lower.objective, cert,
                         time.perf_counter() - t0, iterations, (), (), stats)


def willems_row(result: BilevelResult) -> dict[str, Any]:
    """JSON-ready summary, one row of the reproduction (objective inf for an unstable max-min loop; eigenvalues as
    [re, im]; kkt_residual None for the solver's own selection)."""
    attack_stat(result, "eigenvalues")
    st = result.stats
    eig = st["eigenvalues"]
    return {"method": result.method, "status": result.status.value, "objective": result.upper_objective,
            "spectral_radius": st["spectral_radius"], "eig_abs_sum": float(np.sum(np.abs(eig))),
            "unstable": unstable(result), "gain": st["gain"].tolist(),
            "eigenvalues": [[float(v.real), float(v.imag)] for v in eig], "wall_time": result.wall_time,
            "evaluations": st["evaluations"], "iterations": result.nit, "message": result.message,
            "budget_violation": st["budget_violation"],
            "kkt_residual": None if np.isnan(st["kkt_residual"]) else st["kkt_residual"], "x": st["x"].tolist(),
            "details": st["details"]}


def _seed(seed: int | np.random.SeedSequence | np.random.Generator | None) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


@single_threaded_call
def _ascent_setup(attack: WillemsAttack, oracle: "SDPHypergradient | None", seed: Any,
                  who: str) -> tuple["SDPHypergradient", np.random.Generator, np.ndarray, Box]:
    """The oracle (built unless given, and checked to be this attack's), the rng, the budget and its box."""
    oracle = oracle or shared_oracle(attack)[0]
    if oracle.attack.declaration != attack.declaration:
        raise ModelError(f"{who}: the oracle was built for another WillemsAttack (other data, learner or criterion)")
    bound = attack.budget()
    return oracle, _seed(seed), bound, Box(-bound, bound)


def hypergradient_attack(attack: WillemsAttack, starts: int = 8, seed: Any = 0, max_iter: int = 300,
                         ftol: float = 1e-10, stop_when_unstable: bool = True,
                         oracle: SDPHypergradient | None = None) -> BilevelResult:
    """Multistart projected hypergradient ascent on the poisoning (start 0: clean data; others uniform in the box).

    With stop_when_unstable the attacker stops once its identified closed loop is unstable (its goal) and
    returns that point; otherwise (and when no start gets there) the best objective over the starts."""
    check_common_options({"starts": starts, "seed": seed, "max_iter": max_iter})
    check_numbers({"ftol": ftol}, nonnegative=("ftol",))
    t0 = time.perf_counter()
    oracle, rng, bound, box = _ascent_setup(attack, oracle, seed, "hypergradient_attack")
    finished, records, evals, iters = [], [], 0, 0

    def goal(ev: Evaluation | None) -> bool:
        return ev is not None and (ev.phi == np.inf or (stop_when_unstable and ev.identified_radius >= 1.0))

    for k in range(starts):
        x0 = np.zeros(bound.size) if k == 0 else rng.uniform(-bound, bound)
        path = _Best()
        _, ev, it, converged = _ascent_path(oracle, box, bound, x0, max_iter, ftol, path, goal, "long")
        evals, iters = evals + path.evaluations, iters + it
        if ev is None:
            records.append({"start": k, "status": "error", "message": path.error})
            continue
        reason = GOAL if goal(ev) else CONVERGED if converged else "max_iter reached"
        records.append({"start": k, "objective": ev.phi, "iterations": it, "message": reason,
                        "identified_radius": ev.identified_radius})
        finished.append((ev, k, reason))
        if goal(ev):
            break
    if not finished:
        raise SolverFailed(f"hypergradient attack: the learner's SDP could not be solved from any of {starts} starts "
                           f"({records[-1]['message']})")
    ev, k, reason = _select(finished, stop_when_unstable)
    return _result(attack, oracle, "hypergradient", ev.x, t0, evals, iters, f"start {k} of {len(records)} run ({reason})",
                   None if reason == GOAL else reason == CONVERGED,
                   {"starts": records, "lower_solves": oracle.lower_solves}, ev)


def _select(finished: list[tuple[Evaluation, int, str]], stop_when_unstable: bool) -> tuple[Evaluation, int, str]:
    """The start that reached an unstable identified loop (when stopping there), else the best criterion;
    near-ties (relative TIE_RTOL) go to the larger identified spectral radius. The criteria have flat optimal
    faces (log|det(A + B K)| is one scalar of the m T poisoned inputs): starts often tie on the criterion but
    not on the eigenvalue that decides stability."""
    if stop_when_unstable and finished[-1][0].identified_radius >= 1.0:
        return finished[-1]
    top = max(ev.phi for ev, _, _ in finished)
    close = [f for f in finished
             if f[0].phi == top or (np.isfinite(top) and top - f[0].phi <= TIE_RTOL * max(1.0, abs(top)))]
    return max(close, key=lambda f: f[0].identified_radius)


@single_threaded_call
def de_attack(attack: WillemsAttack, seed: Any = 0, maxiter: int = 300, popsize: int = 5, tol: float = 1e-8,
              stop_when_unstable: bool = True, oracle: SDPHypergradient | None = None) -> BilevelResult:
    """Differential evolution (the framework's, bilevel.solvers.evolution.evolve) on the input poisoning inside the linf
    box, batched over the population where the learner ignores the poisoning.

    With stop_when_unstable it stops once the incumbent's identified closed loop is unstable (as our attack)."""
    if attack.setting.poison != "u":
        raise ModelError(f"de_attack poisons the inputs only (the paper's corollary); got poison="
                         f"{attack.setting.poison!r}: build the attack with poison='u'")
    if attack.setting.delta_u <= 0:
        raise ModelError("de_attack: delta_u = 0 leaves nothing to search; use delta_u > 0")
    check_common_options({"seed": seed, "tol": tol, "max_iter": maxiter})
    check_counts({"popsize": popsize}, ("popsize",))
    t0 = time.perf_counter()
    oracle, _, bound, _ = _ascent_setup(attack, oracle, seed, "de_attack")
    counter = {"evaluations": 0}

    def loss(xs: np.ndarray) -> np.ndarray:
        xs = np.asarray(xs, dtype=float)
        phi = oracle.objectives(xs.T if xs.ndim == 2 else xs[None, :])
        counter["evaluations"] += phi.size
        return -np.minimum(phi, UNSTABLE_PENALTY) if xs.ndim == 2 else float(-min(phi[0], UNSTABLE_PENALTY))

    def stop(intermediate_result: scipy.optimize.OptimizeResult) -> bool:
        if -intermediate_result.fun >= UNSTABLE_PENALTY:
            return True
        return stop_when_unstable and oracle.identified_radius(intermediate_result.x) >= 1.0

    out = evolve(loss, -bound, bound, _seed(seed), maxiter, popsize, tol, stop=stop, vectorized=oracle.lower_fixed)
    return _result(attack, oracle, "differential-evolution", np.clip(out.x, -bound, bound), t0, counter["evaluations"],
                   int(out.nit), f"{out.message} (a heuristic: no optimality claim)", None,
                   {"lower_solves": oracle.lower_solves})


@single_threaded_call
def random_attack(attack: WillemsAttack, seed: Any = 0) -> BilevelResult:
    """A budget-matched, non-adaptive baseline: every poisoned entry +-budget with a fair random sign."""
    check_common_options({"seed": seed})
    t0 = time.perf_counter()
    bound = attack.budget()
    x = bound * _seed(seed).choice([-1.0, 1.0], size=bound.size)
    return _result(attack, shared_oracle(attack)[0], "random", x, t0, 1, 0, "random signs at the budget (a baseline)", None)


@single_threaded_call
def kkt_attack(attack: WillemsAttack, method: str = "ipopt", **options: Any) -> BilevelResult:
    """The generic route: bilevel.solve on the registered problem (KKT reformulation, PSD pairs factored).

    The returned point is clipped to the budget box and the learner is re-solved there independently,
    so gain and eigenvalues are the learner's true response; the solve's status and certificate are kept.
    """
    t0 = time.perf_counter()
    res = solve(attack.problem, method=method, **options)
    if "Du" not in res.x:
        raise SolverFailed(f"kkt_attack: {method} returned no point (status {res.status.value}: {res.message})",
                           result=res)
    x = np.concatenate([np.asarray(res.x[name], dtype=float).reshape(-1, order="F")
                        for name in ("Du", "Dx") if name in res.x])
    bound = attack.budget()
    clipped = float(np.max(np.abs(x - np.clip(x, -bound, bound)), initial=0.0))
    oracle = shared_oracle(attack)[0]
    cert = res.certificate
    details = {"status": res.status.value, "solver_objective": res.upper_objective, "clipped_by": clipped,
               "certificate_passed": bool(cert is not None and cert.passed),
               "certificate_failed": list(cert.failed) if cert is not None else [], "solve_time": res.wall_time}
    return _result(attack, oracle, f"kkt-{method}", np.clip(x, -bound, bound), t0, 0, res.nit,
                   f"{method} on the KKT reformulation: {res.status.value} ({res.message}); the learner re-solved at "
                   "that point clipped to the budget", res.status is Status.SOLVED and clipped == 0.0, details)


@dataclass
class _Best:
    """The evaluated point with the largest identified spectral radius so far."""

    ev: Evaluation | None = None
    evaluations: int = 0
    error: str = ""
    """The last reason the learner could not be solved at an evaluated point."""

    def see(self, ev: Evaluation | None, evaluations: int = 1) -> None:
        """Count `evaluations` and keep ev if its identified radius is the largest so far."""
        self.evaluations += evaluations
        if ev is not None and (self.ev is None or ev.identified_radius > self.ev.identified_radius):
            self.ev = ev


def _ascent_path(oracle: SDPHypergradient, box: Box, scale: np.ndarray, x0: np.ndarray, max_iter: int, tol: float,
                 best: _Best, stop: Callable[[Evaluation | None], bool] | None = None,
                 bb: Literal["short", "long"] = "short") -> tuple[np.ndarray, Evaluation | None, int, bool]:
    """One projected ascent (the engine's, bilevel.solvers.ascent, Barzilai-Borwein steps `bb`) on the attack's
    criterion phi, until `stop` holds; a point where the learner cannot be solved is a failed trial (backtrack); every
    evaluated point goes to `best`. Returns the final point, its evaluation (None if the start could not be
    evaluated), the iteration count and whether the ascent converged (or stopped)."""

    def value(x: np.ndarray) -> tuple[float, Evaluation | None]:
        try:
            ev = oracle.evaluate(x)
        except BilevelError as exc:
            best.error = str(exc)
            best.see(None)
            return -np.inf, None
        best.see(ev)
        return ev.phi, ev

    def direction(ev: Evaluation | None) -> tuple[np.ndarray, np.ndarray]:
        if ev is None:  # the start itself could not be evaluated: no move, the path ends there
            return np.zeros_like(scale), np.zeros_like(scale)
        g = oracle.gradient(ev)
        return g, scale * budget_direction(scale * g, 1.0, np.inf)

    x, _, ev, it, _, converged = projected_ascent(value, direction, box, x0, scale, max_iter, tol, [], stop=stop,
                                                  bb=bb)
    return x, ev, it, converged


def radius_engine(attack: WillemsAttack, oracle: SDPHypergradient | None = None) -> Hypergradient:
    """The generic engine (bilevel.solvers.implicit) on the attack's spectral-radius problem, its fixed lower level
    given the learner's solution of `oracle` (any selection; by default an oracle on the engine's own lower level):
    it never solves the SDP again."""
    engine = Hypergradient(prepare(attack.radius_problem()))
    if not engine.low.fixed:
        raise ModelError("destabilize_attack needs a learner that ignores the poisoning (poison='u' with design 'lqr' "
                         "or 'stabilizing'); for state or joint poisoning solve attack.radius_problem() with "
                         "method='hypergradient', which re-solves the SDP at every point")
    oracle = oracle or SDPHypergradient(attack, lower=engine.low)
    zero = np.zeros(oracle.n_x)
    engine.evaluate(zero, lower=oracle.lower_solution(zero)[0])
    return engine


ORACLES_KEPT = 4
"""Declarations (WillemsAttack.declaration) whose oracle and radius engine a process keeps, most recent first."""
_ORACLES: dict[tuple, tuple[SDPHypergradient, Hypergradient | None]] = {}


def shared_oracle(attack: WillemsAttack, engine: bool = False) -> tuple[SDPHypergradient, Hypergradient | None]:
    """The oracle of the attack's declaration (data, learner, criterion: any budget) and, if `engine`, its radius
    engine (radius_engine, on the oracle's lower level), kept per process for the last ORACLES_KEPT declarations:
    attacks on one data set at several budgets, or by several methods, build them and solve the learner once.
    Neither reads the budget (each attack passes its own box to the ascent)."""
    key = attack.declaration
    oracle, eng = _ORACLES.pop(key, (None, None))
    if engine and eng is None:
        eng = radius_engine(attack, oracle)
        oracle = oracle or SDPHypergradient(attack, lower=eng.low)
    oracle = oracle or SDPHypergradient(attack)
    _ORACLES[key] = (oracle, eng)
    while len(_ORACLES) > ORACLES_KEPT:
        del _ORACLES[next(iter(_ORACLES))]
    return oracle, eng


@single_threaded_call
def destabilize_attack(attack: WillemsAttack, starts: int = 64, seed: Any = 0, max_iter: int = 100, pool: int = 512,
                       oracle: SDPHypergradient | None = None) -> BilevelResult:
    """Maximize the spectral radius of the attacker's closed loop A_id + B_id K over the input poisoning, exactly
    (eigenvector derivatives of rho) on the generic engine: the learner is solved once, K is affine in the poisoning,
    and `starts` points ascend together (bilevel.solvers.ascent.batched_box_ascent): the clean data and the largest-rho
    points of a pool of `pool` random ones (half uniform in the box, half its vertices). Returns the point with the
    largest identified rho. Without `oracle`, the declaration's shared oracle and engine (shared_oracle)."""
    if attack.setting.objective != "destabilize":
        raise ModelError(f"destabilize_attack maximizes the spectral radius; got objective="
                         f"{attack.setting.objective!r}: build the attack with objective='destabilize'")
    check_common_options({"starts": starts, "seed": seed, "max_iter": max_iter})
    check_counts({"pool": pool}, ("pool",))
    t0 = time.perf_counter()
    oracle, engine = shared_oracle(attack, engine=True) if oracle is None else (oracle, radius_engine(attack, oracle))
    oracle, rng, bound, _ = _ascent_setup(attack, oracle, seed, "destabilize_attack")
    candidates = rng.uniform(-1.0, 1.0, (max(pool, starts - 1), bound.size)) * bound
    candidates[: candidates.shape[0] // 2] = np.sign(candidates[: candidates.shape[0] // 2]) * bound
    screened = np.argsort(engine.spectral_batch(candidates.T)[0], kind="stable")[: starts - 1]  # F = -rho
    x0 = np.vstack([np.zeros(bound.size), candidates[screened]])
    def radius(xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # rows of xs; the engine's F is -rho (minimized)
        f, g, _ = engine.spectral_batch(xs.T)
        return -f, -g.T

    xs, rho, iters, evaluations = batched_box_ascent(radius, bound, x0, max_iter)
    evaluations += candidates.shape[0]
    best = int(np.nanargmax(rho))
    return _result(attack, oracle, "destabilize", xs[best], t0, evaluations, iters,
                   f"largest identified spectral radius {rho[best]:.6g} over {starts} starts (the best point of "
                   "their ascents, not a certified local maximum)", None,
                   {"starts": starts, "identified_radius": float(rho[best]), "start_radii": rho.tolist(),
                    "lower_solves": oracle.lower_solves})


def smallest_destabilizing_budget(setting: WillemsSetting, path: tuple[float, ...] = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0),
                                  rel_tol: float = 0.05, **options: Any) -> BudgetSearch:
    """delta_u* of one data set: the framework's budget search (bilevel.solvers.budget_search) with destabilize_attack
    (options passed on) as the attack and an unstable true loop (spectral radius >= 1) as the goal."""
    if setting.poison != "u":
        raise ModelError(f"smallest_destabilizing_budget searches delta_u with input poisoning; got poison="
                         f"{setting.poison!r}: use poison='u'")

    def radius(delta: float) -> float:
        attack = build_attack(dataclasses.replace(setting, objective="destabilize", delta_u=delta))
        return destabilize_attack(attack, **options).stats["spectral_radius"]

    return smallest_budget(radius, lambda rho: rho >= 1.0, path, rel_tol)
