"""VRFT poisoning attacks as registered bilevel problems (paper Sec. 3-4, appendix A).

Upper variables a_u, a_y (N each) with budgets ||a|| <= eps ||signal|| (l2: a ball constraint; linf: the
variables' bounds; l1, for the structured attacks: a constraint on sum |a_i|); lower variable theta (nk)
solving the VRFT least squares on the poisoned data. The regressor Phi(y + a_y) is written as
filter recursions (O(N) expression nodes per column, no N x N blocks), each a definition: the KKT
reformulation keeps the filtered signals as variables bound by their difference equations, so IPOPT's
exact Hessian is sparse; or, on request (FILTERS), as LinearOperators. The instance (setting, data, budgets, objective) is bilevel.problems.vrft_instance's
VRFTAttack; the structured attacks on the declared problem are in bilevel.attacks.vrft_methods.
"""

from __future__ import annotations

from typing import Any, Callable, Literal

import casadi as ca
import numpy as np
from scipy.sparse.linalg import LinearOperator

from ..ddc.operators import LTIOperator
from ..ddc.vrft import VRFTRegressor
from ..errors import ModelError
from ..kept import kept
from ..model import BilevelProblem
from .registry import register
from .vrft_instance import VRFTAttack, VRFTSetting, attack_instance

SOURCE = "Russo & Proutiere, Poisoning Attacks against Data-Driven Control Methods (extended), "
DEFAULTS = {"scenario": "B", "eps_u": 0.1, "eps_y": 0.057, "seed": 0, "N": 64, "convention": "paper", "norm": "l2"}
"""The registered problems' parameters (their builders' keyword defaults); the structured attacks take the same."""


def _recursion(op: LTIOperator, x: ca.SX) -> tuple[ca.SX, np.ndarray, np.ndarray]:
    """x padded with the operator's advance (zero final conditions), and its normalized (b, a)."""
    d = op.advance
    return (ca.vertcat(x, ca.SX.zeros(d)) if d else x), op._b / op.den[0], op.den / op.den[0]


def _delayed(v: ca.SX, j: int) -> ca.SX:
    """v delayed by j samples (zeros first), of the same length."""
    n = int(v.numel())
    return v if j == 0 else ca.vertcat(ca.SX.zeros(min(j, n)), v[: max(n - j, 0)])


def _fir(coefficients: np.ndarray, v: ca.SX) -> ca.SX:
    """sum_j c_j v(t - j) over the record (zero before it), as whole-vector operations."""
    out = ca.SX.zeros(int(v.numel()))
    for j, c in enumerate(coefficients):
        if c != 0 and j < v.numel():
            out = out + c * _delayed(v, j)
    return out


def sx_filter(op: LTIOperator, x: ca.SX) -> ca.SX:
    """The operator's response to an SX signal over the record and its advance, by its difference equation
    (O(N order) nodes; the first `advance` samples precede the record): the input taps as vector operations, the
    output recursion as one CasADi step function accumulated over the record."""
    src, b, a = _recursion(op, x)
    u = _fir(b, src)
    na = a.size - 1
    if na == 0:
        return u
    s, ut = ca.SX.sym("s", na), ca.SX.sym("u")
    y = ut - sum(a[j] * s[j - 1] for j in range(1, a.size) if a[j] != 0)
    step = ca.Function("step", [s, ut], [ca.vertcat(y, s[0:na - 1]) if na > 1 else y, y])
    return step.mapaccum("filter", int(src.numel()))(ca.SX.zeros(na), u.T)[1].T


def difference_equation(op: LTIOperator, x: ca.SX, z: ca.SX) -> ca.SX:
    """a(q) z - b(q) x, zero exactly where z = sx_filter(op, x): banded in (x, z)."""
    src, b, a = _recursion(op, x)
    return _fir(a, z) - _fir(b, src)


def filtered(problem: BilevelProblem, name: str, op: LTIOperator, x: ca.SX) -> ca.SX:
    """op applied to x, declared as a definition: the KKT reformulation keeps the filter's output as variables bound
    by the difference equation (sparse), the other methods substitute the recursion."""
    z = problem.define(name, sx_filter(op, x), lambda z: difference_equation(op, x, z))
    return z[op.advance:]


def filter_bank(reg: VRFTRegressor, N: int) -> LinearOperator:
    """a_y -> vec(Phi(a_y)) (column-major, rows x nk) as a LinearOperator: the regressor's filters, O(N nk) per
    product."""
    rows, k = reg.rows(N), reg.n_params
    return LinearOperator((rows * k, N), dtype=float,
                          matvec=lambda v: reg(np.asarray(v).ravel()).reshape(-1, order="F"),
                          rmatvec=lambda g: reg.adjoint(np.asarray(g).reshape(rows, k, order="F")))


def target_map(reg: VRFTRegressor, N: int) -> LinearOperator:
    """a_u -> targets(a_u) (the learner's prefilter L on the regression rows) as a LinearOperator."""
    return LinearOperator((reg.rows(N), N), dtype=float, matvec=lambda v: reg.targets(np.asarray(v).ravel()),
                          rmatvec=lambda g: reg.targets_adjoint(np.asarray(g).ravel(), N))


FILTERS = ("recursions", "operators")
"""How a declaration writes the learner's filters: "recursions", difference-equation definitions (the KKT
reformulation keeps the filtered signals as variables: a sparse Hessian); "operators", scipy LinearOperators
(bilevel.linear_maps: a first declaration and preparation several times faster at large N, each later evaluation a
little slower; the KKT reformulation forms them as dense matrices). benchmarks/bench_vrft_declarations.py measures
both."""


def attack_problem(atk: VRFTAttack, filters: str = "recursions") -> VRFTProblem:
    """The bilevel program of an attack instance (l2 budgets as balls, linf budgets as bounds), declared with the
    generic API.

    The clean data enter as parameters (clean regressor and targets, l2 budget radii, the objective's data), so
    `load_instance` re-targets the declared problem to another data set of the same scenario and N without
    rebuilding it (with linf budgets only to one with the same radii: bounds are fixed at declaration).
    """
    _check_budgets(atk)
    return declare(atk, filters)


def declare(atk: VRFTAttack, filters: str = "recursions") -> VRFTProblem:
    """attack_problem without its check of the budgets: an l1 budget becomes the constraint ||a||_1 <= delta, and a
    sparsity fraction rho is left out (the declared set is the norm ball; a method that keeps the sparsity searches
    the narrower set and says so: MethodRun.feasible_set). filters: one of FILTERS."""
    if filters not in FILTERS:
        raise ModelError(f"filters={filters!r} is not one of {', '.join(FILTERS)}")
    reg = atk.setting.regressor
    N, k = atk.N, reg.n_params
    rows = reg.rows(N)
    p = VRFTProblem(atk)
    signals = {}
    for name, budget, delta in (("a_u", atk.budget_u, atk.delta_u), ("a_y", atk.budget_y, atk.delta_y)):
        box = {"lb": -delta, "ub": delta} if budget.norm == "linf" else {}  # bounds: every method projects on them
        signals[name] = p.upper_variable(name, N, **box)
    a_u, a_y = signals["a_u"], signals["a_y"]
    theta = p.lower_variable("theta", k, start=atk.theta0)
    t0, phi0 = p.parameter("t0", rows), p.parameter("phi0", (rows, k))
    if filters == "operators":
        phi_a = ca.reshape(p.linear_map(filter_bank(reg, N), "Phi") @ a_y, rows, k)
        t_a = a_u[:rows] if reg.prefilter is None else p.linear_map(target_map(reg, N), "L") @ a_u
    else:
        err = filtered(p, "e_y", reg.error, a_y)
        if reg.prefilter is not None:
            err = filtered(p, "le_y", reg.prefilter, err)
        phi_a = ca.horzcat(*[filtered(p, f"phi_{j}", beta, err)[:rows] for j, beta in enumerate(reg.basis)])
        t_a = (a_u if reg.prefilter is None else filtered(p, "lu", reg.prefilter, a_u))[:rows]
    residual = t0 + t_a - ca.mtimes(phi0 + phi_a, theta)
    p.minimize_lower(ca.sumsqr(residual) / rows)
    for name, budget in (("u", atk.budget_u), ("y", atk.budget_y)):
        if budget.norm == "l2":
            p.upper_constraint(ca.sumsqr(signals[f"a_{name}"]) <= p.parameter(f"delta_{name}") ** 2,
                               name=f"budget_{name}")
        elif budget.norm == "l1":
            p.upper_constraint(ca.sum1(ca.fabs(signals[f"a_{name}"])) <= p.parameter(f"delta_{name}"),
                               name=f"budget_{name}")
    if atk.objective == "maxmin":  # ||t0 - Phi0 theta||^2 by Phi0's Gram matrix: O(k^2) nodes, not O(N k)
        gram, cross, energy = p.parameter("gram0", (k, k)), p.parameter("cross0", k), p.parameter("energy0")
        p.maximize_upper((energy - 2 * ca.dot(cross, theta) + ca.bilin(gram, theta, theta)) / rows)
    elif atk.objective == "targeted":
        p.minimize_upper(ca.sumsqr(p.parameter("theta_target", k) - theta) / k)
    else:
        loop = atk.model_loop
        p.maximize_spectral_radius(companion(p.parameter("loop_base", loop.base.size),
                                             p.parameter("loop_slopes", loop.slopes.shape), theta))
    _load(p, atk)
    return p


class VRFTProblem(BilevelProblem):
    """A BilevelProblem declared from a VRFT attack instance (declare): it carries the instance it is loaded with, so
    the structured attacks (bilevel.attacks.vrft_methods) read their data from the problem they are handed."""

    def __init__(self, atk: VRFTAttack) -> None:
        super().__init__(f"vrft-{atk.objective}")
        self.instance: VRFTAttack = atk
        """The instance whose data the parameters hold (load_instance replaces it); its budget norms are the declared
        ones."""


def instance_of(problem: BilevelProblem) -> VRFTAttack:
    """The instance a problem from attack_problem (or a vrft-* builder) currently holds (load_instance sets it)."""
    if not isinstance(problem, VRFTProblem):
        raise ModelError(f"problem {problem.name!r} was not declared from a VRFT instance; declare it with "
                         "bilevel.problems.vrft.attack_problem(atk) or build a registered vrft-* problem")
    return problem.instance


DECLARED_CACHE = 4
"""problem_for keeps this many declared problems per process (declaring and preparing one at N = 512 takes about
0.4 s, re-loading it a few ms)."""
_DECLARED: dict[tuple[Any, ...], tuple[VRFTSetting, VRFTProblem]] = {}


def problem_for(atk: VRFTAttack, load: bool = True) -> VRFTProblem:
    """The declared problem of `atk` (any budget `declare` takes), loaded with its data: declared once per setting,
    objective, N, budget norms (linf: radii) and ARX orders in this process, re-targeted with set_value after (not
    with load=False: a caller that loads instances itself, e.g. bilevel.attacks.vrft_batch)."""
    budgets = tuple(b.radius(s) if b.norm == "linf" else b.norm
                    for b, s in ((atk.budget_u, atk.u), (atk.budget_y, atk.y)))  # linf radii are declared bounds
    key = (id(atk.setting), atk.objective, atk.N, budgets,
           tuple(atk.arx_orders) if atk.objective == "destabilize" else ())
    # the setting is kept alive with its problem: its id is not reused while kept
    (_, problem), made = kept(_DECLARED, key, lambda: (atk.setting, declare(atk)), DECLARED_CACHE,
                              usable=lambda hit: hit[0] is atk.setting)
    if not made and load:
        _load(problem, atk)
    return problem


def _check_budgets(atk: VRFTAttack) -> None:
    for budget in (atk.budget_u, atk.budget_y):
        if budget.norm not in ("l2", "linf") or budget.rho:
            raise ModelError("the declared VRFT problem supports l2 budgets (balls) and linf budgets (bounds) with no "
                             f"sparsity; got {atk.budget_u} and {atk.budget_y}: use the structured attacks in "
                             "bilevel.attacks.vrft_methods for l1 or sparse budgets")


def load_instance(problem: BilevelProblem, atk: VRFTAttack) -> None:
    """Set the parameters and the suggested start of a problem from `attack_problem` to instance `atk` (same
    scenario, N, objective and budget norms); the next solve reuses the declared problem's preparation."""
    _check_budgets(atk)
    _load(problem, atk)


def _load(problem: BilevelProblem, atk: VRFTAttack) -> None:
    """load_instance for any budget `declare` takes."""
    declared = {q.name: q for q in problem.parameters.items}
    rows = declared["t0"].size if "t0" in declared else 0
    if not isinstance(problem, VRFTProblem) or problem.name != f"vrft-{atk.objective}" or rows != atk.t0.size:
        raise ModelError(f"instance ({atk.objective}, N = {atk.N}) does not fit problem {problem.name!r} declared for "
                         f"{rows} regression rows; declare it with attack_problem(atk)")
    bounds = {v.name: float(v.ub[0]) for v in problem.variables if v.name in ("a_u", "a_y")}
    values = {"t0": atk.t0, "phi0": atk.phi0}
    held = problem.instance  # the declaring instance or one loaded since: its budget norms are the declared ones
    for name, budget, delta in (("u", atk.budget_u, atk.delta_u), ("y", atk.budget_y, atk.delta_y)):
        declared_norm = getattr(held, f"budget_{name}").norm
        if budget.norm != declared_norm:
            raise ModelError(f"this problem was declared with an {declared_norm} budget on a_{name}, the instance has "
                             f"{budget.norm}; declare the instance with attack_problem(atk)")
        if budget.norm == "linf" and not np.isclose(bounds[f"a_{name}"], delta, rtol=1e-12, atol=0):
            raise ModelError(f"instance budgets (delta_u = {atk.delta_u:.6g}, delta_y = {atk.delta_y:.6g}, linf) "
                             f"differ from the declared linf bounds ({bounds['a_u']:.6g}, {bounds['a_y']:.6g}); "
                             "declare the instance with attack_problem(atk)")
        if budget.norm != "linf":
            values[f"delta_{name}"] = delta
    if "gram0" in declared:
        values |= {"gram0": atk.gram0, "cross0": atk.cross0, "energy0": float(atk.t0 @ atk.t0)}
    if "theta_target" in declared:
        values["theta_target"] = atk.theta_target
    if "loop_base" in declared:
        values |= {"loop_base": atk.model_loop.base, "loop_slopes": atk.model_loop.slopes}
    for name, value in values.items():
        problem.set_value(name, value)
    problem.suggested_starts.clear()  # a_y = 0 is stationary: the engine's first start is its conditioning start
    problem.instance = atk


def companion(base: np.ndarray | ca.SX, slopes: np.ndarray | ca.SX, theta: ca.SX) -> ca.SX:
    """The companion matrix of the closed-loop polynomial base + theta' slopes (highest power first): its
    eigenvalues are the polynomial's roots, the modelled closed-loop poles."""
    coeffs = ca.SX(base) + ca.mtimes(ca.SX(slopes).T, theta)
    n = int(coeffs.numel()) - 1
    monic = coeffs[1:] / coeffs[0]
    return ca.vertcat(-monic.T, ca.horzcat(ca.SX.eye(n - 1), ca.SX.zeros(n - 1, 1)))


def _builder(objective: str, doc: str) -> Callable[..., BilevelProblem]:
    """The registered builder of vrft-<objective>: the paper's instance (attack_instance) declared by attack_problem."""
    def build(scenario: Literal["A", "B"] = "B", eps_u: float = 0.1, eps_y: float = 0.057, seed: int = 0, N: int = 64,
              convention: Literal["paper", "prefiltered-drop", "raw", "raw-drop"] = "paper",
              norm: Literal["l2", "linf", "l1"] = "l2") -> BilevelProblem:
        return attack_problem(attack_instance(objective, scenario, eps_u, eps_y, seed, N, convention, norm))
    build.__name__, build.__doc__ = f"vrft_{objective}", doc
    return build


vrft_maxmin = register(
    "vrft-maxmin", source=SOURCE + "Sec. 4.4, eq. (op_maxmin)", tags=("attack", "vrft"), defaults=DEFAULTS,
    description="max-min poisoning of VRFT on the flexible transmission (maximize the learner's loss)")(_builder(
        "maxmin", "Max-min attack on VRFT: maximize the learner's clean-data loss at the poisoned theta."))
vrft_targeted = register(
    "vrft-targeted", source=SOURCE + "appendix A, eq. (op_vrft_targeted), theta_a = 3 theta_0", tags=("attack", "vrft"),
    defaults=DEFAULTS, description="targeted poisoning of VRFT: drive theta towards theta_a = 3 theta_0")(_builder(
        "targeted", "Targeted attack on VRFT: minimize ||theta_a - theta'||^2 / nk."))
vrft_destabilize = register(
    "vrft-destabilize", source=SOURCE + "beyond the paper: the attacker fits an ARX model to the clean data and "
    "maximizes the spectral radius of the modelled closed loop", tags=("attack", "vrft"), defaults=DEFAULTS,
    description="destabilizing poisoning of VRFT (maximize the modelled closed-loop spectral radius)")(_builder(
        "destabilize", "Destabilizing attack: maximize the spectral radius of the ARX-modelled closed loop's companion "
        "matrix."))
