"""Poisoning attacks on least-squares system identification as registered bilevel problems.

Upper variables: one change dS per signal (dX, dU for the state-space learner; du, dy for ARX), each in the ball
||dS||_F <= eps ||S||_F. Lower variable Theta ([A B] or the ARX theta as a 1 x (na + nb) row) solving the learner's
least squares min ||Y - Theta Z||_F^2 on the poisoned signals (bilevel.problems.identification_instance). The
attacker maximizes ||Theta - Theta_clean||_F^2 ("frobenius") or ||Theta - Theta_clean||_2^2 ("spectral", the
spectral radius of dTheta dTheta'), or, on [A B], a numeric function of the identified model with its exact gradient
(maximize_matrix_function, bilevel.ddc.model_based): its H2 norm ("h2") or the spectral radius of the true plant
(parameter "plant" = [A_true B_true]) under the model's certainty-equivalence LQR gain ("ce-lqr"). With stealth = delta, upper constraints 1 - delta <= stat'/stat <= 1 + delta keep
each residual statistic of bilevel.ddc.residual_tests (variance, whiteness, input F) within delta of its clean value;
the F statistic's restricted model (Y regressed on Z without its input rows) is a second least-squares block of the
lower level. Each statistic enters its constraints as a call of its MX Function of (Y, Z, theta, theta_r)
(statistics_functions). With stealth_kind "authors" the constraints are instead Russo & Proutiere's (the state-space
learner): 1 - delta <= stat'/stat <= 1 + delta for the residual energy, Z_d and the correlation ratio of each lag
tau = 1..s, all from one numeric call node with exact first derivatives (authors_node: bilevel.ddc.stealth_statistics
through bilevel.numeric_node), their c_x, c_u being the budgets (eps = delta), and |entries| <= box on dX and dU.
The clean data and statistics are parameters: load_instance re-targets a declared problem, and with stealth suggests a
start inside the stealth constraints (stealth_start).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import casadi as ca
import numpy as np

from ..ddc.model_based import CertaintyEquivalenceRadius, H2Norm
from ..ddc.stealth_statistics import StealthStatistics, statistic_names
from ..errors import ModelError
from ..kept import kept
from ..model import BilevelProblem
from ..numeric_node import numeric_node
from ..solvers.engine.prepared import prepare
from ..solvers.engine.implicit import shared_oracle
from ..solvers.engine.restoration import restore
from ..solvers.engine.starts import conditioning_start
from .identification_instance import IdentificationAttack, Objective, StealthKind, arx_regression, attack_instance, \
    least_squares_fit, ss_regression
from .registry import register

SOURCE = ("beyond the paper: least-squares identification of the flexible transmission (Russo & Proutiere, Analysis "
          "and Detectability of Offline Data Poisoning Attacks on Linear Systems, 2023)")
DEFAULTS = {"T": 100, "eps": 0.05, "objective": "frobenius", "stealth": None, "seed": 0, "lags": None}
STATISTICS = ("variance", "whiteness", "input")


def statistics(E: ca.SX | ca.MX, E_restricted: ca.SX | ca.MX, n_regressors: int, n_inputs: int, noise_std: float,
               lags: int) -> dict[str, ca.SX | ca.MX]:
    """The residual tests' statistics as expressions (SX or MX) of the residuals E (n x N) of the model and
    E_restricted of the model without its input rows (the formulas of bilevel.ddc.residual_tests)."""
    n, N = E.shape
    rss, rss0 = ca.sumsqr(E), ca.sumsqr(E_restricted)
    R = [ca.mtimes(E[:, j:], E[:, :N - j].T) / N for j in range(lags + 1)]
    inv0 = ca.inv(R[0])
    whiteness = N ** 2 * sum(ca.trace(ca.mtimes([R[j].T, inv0, R[j], inv0])) / (N - j) for j in range(1, lags + 1))
    d1, d2 = n * n_inputs, n * (N - n_regressors)
    return {"variance": rss / noise_std ** 2, "whiteness": whiteness, "input": ((rss0 - rss) / d1) / (rss / d2)}


@lru_cache(maxsize=8)
def statistics_functions(n: int, k: int, N: int, keep: tuple[int, ...], noise_std: float, lags: int
                         ) -> tuple[ca.Function, ...]:
    """`statistics` of the model Y ~ theta Z (Y: n x N, Z: k x N) and of its restriction Y ~ theta_r Z[keep] as one
    CasADi Function of (Y, Z, theta, theta_r) per statistic (in the order of STATISTICS), each kept a call node in the
    expressions that call it (never inlined): the compiled constraints and their derivatives evaluate the residuals
    and statistics as matrix operations of one MX graph, not as their expansion into scalar operations, and a
    constraint's derivative runs the adjoint of its own statistic only
    (bilevel.solvers.engine.implicit.row_jacobian)."""
    Y, Z = ca.MX.sym("Y", n, N), ca.MX.sym("Z", k, N)
    theta, theta_r = ca.MX.sym("theta", n, k), ca.MX.sym("theta_restricted", n, len(keep))
    E, E_r = Y - ca.mtimes(theta, Z), Y - ca.mtimes(theta_r, Z[list(keep), :])
    stats = statistics(E, E_r, k, k - len(keep), noise_std, lags)
    return tuple(ca.Function(name, [Y, Z, theta, theta_r], [stats[name]], {"never_inline": True})
                 for name in STATISTICS)


@lru_cache(maxsize=8)
def authors_node(stats: StealthStatistics) -> ca.Function:
    """The authors' statistics [r, Z_d, f_1..f_s] of (Y, Z, theta, theta_r) as one numeric call node with exact first
    derivatives (kept per size: CasADi holds no Python reference to it)."""
    shapes = [(stats.n, stats.N), (stats.k, stats.N), (stats.n, stats.k), (stats.n, len(stats.keep))]
    return numeric_node("authors_statistics", stats.evaluate, shapes, stats.size)


@lru_cache(maxsize=8)
def authors_function(stats: StealthStatistics) -> ca.Function:
    """The authors' statistics [r, Z_d, f_1..f_s] of (Y, Z, theta, theta_r) as one CasADi Function of MX expressions
    (StealthStatistics.expression, the same formulas as authors_node), kept a call node: for method reduced with
    compiled=True, whose NLP CasADi then evaluates and differentiates without Python."""
    Y, Z = ca.MX.sym("Y", stats.n, stats.N), ca.MX.sym("Z", stats.k, stats.N)
    theta, theta_r = ca.MX.sym("theta", stats.n, stats.k), ca.MX.sym("theta_restricted", stats.n, len(stats.keep))
    return ca.Function("authors_statistics", [Y, Z, theta, theta_r], [stats.expression(Y, Z, theta, theta_r)],
                       {"never_inline": True})


def declare(atk: IdentificationAttack, compiled: bool = False) -> BilevelProblem:
    """The bilevel program of an attack instance, declared with the generic API (budgets as balls); compiled: the
    authors' statistics as CasADi expressions (authors_function) instead of the numeric node (authors_node), for method
    reduced's option compiled."""
    p = BilevelProblem(f"ident-{atk.learner}")
    poisoned = {}
    bound = np.inf if atk.box is None else atk.box
    for name, clean in atk.signals.items():
        d = p.upper_variable(f"d{name}", clean.shape, lb=-bound, ub=bound)
        p.upper_constraint(ca.sumsqr(d) <= p.parameter(f"delta_{name}") ** 2, name=f"budget_{name}")
        poisoned[name] = p.parameter(name, clean.shape) + d
    if atk.learner == "ss":
        Y, Z = ss_regression(poisoned["X"], poisoned["U"])
    else:
        Y, Z = arx_regression(poisoned["u"], poisoned["y"], *atk.orders)
    theta = p.lower_variable("theta", atk.theta0.shape, start=atk.theta0)
    E = Y - ca.mtimes(theta, Z)
    lower = ca.sumsqr(E)
    if atk.stealth is not None:
        keep = [i for i in range(Z.shape[0]) if i not in atk.input_rows]
        theta_r = p.lower_variable("theta_restricted", (atk.theta0.shape[0], len(keep)))
        E_r = Y - ca.mtimes(theta_r, Z[keep, :])
        lower += ca.sumsqr(E_r)
        delta = p.parameter("stealth")
        if atk.stealth_kind == "authors":
            node = authors_function if compiled else authors_node
            values = node(atk.authors_statistics)(Y, Z, theta, theta_r)
            stats = [(values[i], name) for i, name in enumerate(statistic_names(atk.lags))]
        else:
            nodes = statistics_functions(Y.shape[0], *Z.shape, tuple(keep), atk.setting.noise_std, atk.lags)
            stats = [(node(Y, Z, theta, theta_r), name) for node, name in zip(nodes, STATISTICS)]
        for value, name in stats:
            ratio = value / p.parameter(f"{name}_clean")
            p.upper_constraint(ratio <= 1 + delta, name=f"stealth_{name}_high")
            p.upper_constraint(ratio >= 1 - delta, name=f"stealth_{name}_low")
    p.minimize_lower(lower)
    error = theta - p.parameter("theta_clean", atk.theta0.shape)
    if atk.objective == "frobenius":
        p.maximize_upper(ca.sumsqr(error))
    elif atk.objective == "spectral":
        p.maximize_spectral_radius(ca.mtimes(error, error.T))
    elif atk.objective == "h2":
        p.maximize_matrix_function(theta, H2Norm())
    else:
        n, m = atk.signals["X"].shape[0], atk.signals["U"].shape[0]
        q, r = atk.lqr_weights
        p.maximize_matrix_function(ca.horzcat(theta, p.parameter("plant", atk.theta0.shape)),
                                   CertaintyEquivalenceRadius(q * np.eye(n), r * np.eye(m)))
    load_instance(p, atk)
    return p


DECLARED_CACHE = 4
"""problem_for keeps this many declared problems per process (a declared problem keeps its preparation: IPOPT's
compiled NLP takes seconds to build, re-loading data a few milliseconds)."""
_DECLARED: dict[tuple[Any, ...], BilevelProblem] = {}


def problem_for(atk: IdentificationAttack, start: bool = True, compiled: bool = False) -> BilevelProblem:
    """The declared problem of `atk`, loaded with its data: declared once per learner, signal shapes, orders,
    objective, stealth declaration and `compiled` (declare's) in this process, re-targeted with load_instance after
    (start: as there)."""
    key = (atk.learner, tuple(v.shape for v in atk.signals.values()), atk.orders, atk.objective, atk.lags,
           atk.stealth is None, atk.lqr_weights, atk.stealth_kind, atk.box, compiled)
    problem, made = kept(_DECLARED, key, lambda: declare(atk, compiled), DECLARED_CACHE)
    if not made:
        load_instance(problem, atk, start)
    elif not start:
        problem.suggested_starts.clear()
    return problem


def load_instance(problem: BilevelProblem, atk: IdentificationAttack, start: bool = True) -> None:
    """Set the parameters of a problem from `declare` to instance `atk` (same learner, shapes, objective and stealth
    declaration); the next solve reuses the declared problem's preparation. start: suggest a stealthy instance's
    stealth_start; False leaves no suggested start (for a caller that suggests its own, e.g. a warm start)."""
    declared = {q.name: q for q in problem.parameters.items}
    if problem.name != f"ident-{atk.learner}" or ("stealth" in declared) != (atk.stealth is not None) \
            or any(declared[k].sym.shape != v.shape for k, v in atk.signals.items()):
        raise ModelError(f"instance ({atk.learner}, signals {[v.shape for v in atk.signals.values()]}, stealth "
                         f"{atk.stealth}) does not fit problem {problem.name!r}; declare it with declare(atk)")
    values: dict[str, Any] = {**atk.signals, "theta_clean": atk.theta0}
    values |= {f"delta_{name}": atk.radius(name) for name in atk.signals}
    if "plant" in declared:
        values["plant"] = np.hstack(atk.setting.state_space)
    if atk.stealth is not None:
        values |= {"stealth": atk.stealth} | {f"{name}_clean": value for name, value in clean_statistics(atk).items()}
    for name, value in values.items():
        problem.set_value(name, value)
    problem.suggested_starts.clear()  # a start suggested for the previous instance
    if atk.stealth is not None and start:
        x0 = stealth_start(problem)
        layout = problem.upper_layout()
        problem.suggest_start(**{f"d{k}": x0[layout[f"d{k}"]] for k in atk.signals})


def clean_statistics(atk: IdentificationAttack) -> dict[str, float]:
    """The clean data's value of each statistic the stealth constraints of `atk` bound, by name."""
    if atk.stealth_kind == "authors":
        theta_r = least_squares_fit(atk.Y0, np.delete(atk.Z0, atk.input_rows, axis=0))
        values = atk.authors_statistics.evaluate(atk.Y0, atk.Z0, atk.theta0, theta_r)[0]
        return dict(zip(statistic_names(atk.lags), map(float, values)))
    clean = atk.tests()
    return {name: clean[name].statistic for name in STATISTICS}


STEALTH_HALVINGS = 40
"""stealth_start tries the conditioning start times 1, 1/2, .., 2^-STEALTH_HALVINGS: the statistics' ratios are 1 at
the clean data, so a small enough scale is inside the stealth constraints. On an unstable plant's data (pole 1.2,
T = 40) the states grow to 1e3 while the residuals stay at the noise's 0.1, and the feasible set reaches only about
4e-4 of the budget: from 8 halvings (2^-8 = 4e-3) the start fell back to zero, the clean data, a stationary point of
every attack, where IPOPT stopped at once."""


def stealth_start(problem: BilevelProblem) -> np.ndarray:
    """The engine's conditioning start (bilevel.solvers.engine.starts) of the loaded problem, scaled by the largest 2^-k
    from which it is restored onto the upper feasible set (bilevel.solvers.engine.restoration: the budgets, and each
    statistic within delta of its clean value, up to defaults["solvers.feasibility_tol"]; zero if from none), judged by
    the engine's own evaluation of the declared statistics. At its full budget the conditioning start breaks the stealth
    constraints, and scaled into them alone it is far from the attack, which spends the budget: restored from the
    largest scale, IPOPT starts near the attack and needs fewer iterations. Never the clean data (a stationary point,
    the attack's worst) unless no scale down to 2^-STEALTH_HALVINGS is restored."""
    prep = prepare(problem)
    x = conditioning_start(prep)
    if x is None:
        raise ModelError(f"problem {problem.name!r} has no conditioning start (its lower level does not move with x)")
    oracle = shared_oracle(prep)
    for k in range(STEALTH_HALVINGS + 1):
        ev = restore(oracle, 2.0 ** -k * x, prep.projection)
        if ev is not None:
            return ev.x
    return np.zeros_like(x)


@register("ident-ss", source=SOURCE, tags=("attack", "identification"), defaults={**DEFAULTS, "q": 1.0, "r": 1.0,
                                                                                  "stealth_kind": "tests"},
          description="poisoning of state-space least squares [A B] (maximize the parameter error, the model's H2 "
                      "norm, or the true loop's spectral radius under certainty-equivalence LQR)")
def ident_ss(T: int = 100, eps: float = 0.05, objective: Objective = "frobenius", stealth: float | None = None,
             seed: int = 0, lags: int | None = None, q: float = 1.0, r: float = 1.0, stealth_kind: StealthKind = "tests"
             ) -> BilevelProblem:
    """[A B] from T poisoned states and inputs of the flexible transmission (controllable canonical form); q, r: the
    LQR weights Q = q I, R = r I of objective "ce-lqr"; stealth_kind "tests" (the project's residual tests) or
    "authors" (Russo & Proutiere's statistics and box)."""
    return declare(attack_instance("ss", T, eps, objective, stealth, seed, lags, lqr_weights=(q, r),
                                   stealth_kind=stealth_kind))


@register("ident-arx", source=SOURCE, tags=("attack", "identification"), defaults={**DEFAULTS, "na": 4, "nb": 4},
          description="poisoning of ARX(na, nb) least squares (maximize the parameter error)")
def ident_arx(T: int = 100, eps: float = 0.05, objective: Objective = "frobenius", stealth: float | None = None,
              seed: int = 0, lags: int | None = None, na: int = 4, nb: int = 4) -> BilevelProblem:
    """ARX(na, nb) from T poisoned input/output samples of the flexible transmission."""
    return declare(attack_instance("arx", T, eps, objective, stealth, seed, lags, na, nb))
