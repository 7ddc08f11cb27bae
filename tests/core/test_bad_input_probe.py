"""A probe of the public API with bad input (issue "Honest answers II", item 6): every case ends in exactly one
outcome, a named `bilevel.errors.BilevelError` subclass whose message names the problem, or a result whose status is
not SOLVED with a message saying why; never a raw AttributeError, ValueError, numpy or CasADi error.

Cases already in test_bad_input.py and test_honest_answers.py are not repeated here."""

from __future__ import annotations

import re
from collections import Counter
from typing import Any, Callable

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl
from bilevel import attacks as atk
from bilevel.attacks import willems
from bilevel.errors import (BilevelError, InvalidData, ModelError, NotPersistentlyExciting,
                            RankDeficientRegressor, UnknownName, UnknownOption)
from bilevel.experiments.vrft import attack_summary
from bilevel.experiments.willems import willems_row
from bilevel.problems import registry
from bilevel.problems.willems import build_attack
from bilevel.problems.willems_instance import WillemsSetting
from bilevel.solvers.engine.prepared import MethodRun
from bilevel.solvers.registry import METHODS
from tests.conftest import bard_511, projection_qp

STATUS = "status"
"""Expected outcome of a case that returns a result: its status is not SOLVED and its message matches."""


def _p(**lower: Any) -> tuple[bl.BilevelProblem, ca.SX, ca.SX]:
    """x in [0, 2]^2 (upper), y (lower, 2) with `lower` as its bounds; no objectives yet."""
    p = bl.BilevelProblem("probe")
    x = p.upper_variable("x", 2, lb=0, ub=2)
    y = p.lower_variable("y", 2, **lower)
    return p, x, y


def _full(**lower: Any) -> tuple[bl.BilevelProblem, ca.SX, ca.SX]:
    """_p with F = |y - (1, 2)|^2 and f = |y - x|^2."""
    p, x, y = _p(**lower)
    p.minimize_upper(ca.sumsqr(y - ca.DM([1, 2])))
    p.minimize_lower(ca.sumsqr(y - x))
    return p, x, y


def _decl(fn: Callable[[bl.BilevelProblem, ca.SX, ca.SX], Any]) -> Callable[[], Any]:
    def run() -> Any:
        p, x, y = _full()
        return fn(p, x, y)
    return run


def _with_param(fn: Callable[[bl.BilevelProblem], Any]) -> Callable[[], Any]:
    def run() -> Any:
        p, x, y = _full()
        p.parameter("w", 2, value=[1.0, 2.0])
        return fn(p)
    return run


def _solve(options: dict[str, Any], problem: Callable[[], bl.BilevelProblem] = bard_511) -> Callable[[], Any]:
    return lambda: bl.solve(problem(), **options)


def _unbounded_lp() -> bl.BilevelProblem:
    """min_y y - x over y free: unbounded below at every x."""
    p = bl.BilevelProblem("unbounded-lp")
    x = p.upper_variable("x", lb=0, ub=1)
    y = p.lower_variable("y")
    p.minimize_upper((x - 1) ** 2 + y ** 2)
    p.minimize_lower(-y)
    p.lower_constraint(y >= x)
    return p


def _unbounded_nlp() -> bl.BilevelProblem:
    """min_y exp(-y) - (1 + x) y: convex, unbounded below (IPOPT's iterates diverge)."""
    p = bl.BilevelProblem("unbounded-nlp")
    x = p.upper_variable("x", lb=0, ub=1)
    y = p.lower_variable("y")
    p.minimize_upper((x - 1) ** 2 + y ** 2)
    p.minimize_lower(ca.exp(-y) - y * (1 + x))
    return p


def _norm_ball(tilt: float = 0.1, center: float = 0.0) -> bl.BilevelProblem:
    """d in R^2 under norm_2(d - center) + tilt d_0 <= 1, F = |y - (3, 1)|^2, y*(d) = d; with tilt != 0 not a
    recognized ball, and not differentiable at d = center (the declared start for center 0)."""
    p = bl.BilevelProblem("norm2")
    d = p.upper_variable("d", 2, lb=-2, ub=2)
    y = p.lower_variable("y", 2)
    p.minimize_upper(ca.sumsqr(y - ca.DM([3, 1])))
    p.minimize_lower(ca.sumsqr(y - d))
    p.upper_constraint(ca.norm_2(d - center) + tilt * d[0] <= 1)
    return p


def _custom(returns: Any) -> Callable[[], Any]:
    def method(prep: Any, **options: Any) -> Any:
        return returns
    return lambda: bl.solve(bard_511(), method=method)


def _register(name: Any, fn: Any, **kw: Any) -> Callable[[], Any]:
    return lambda: bl.register_method(name, fn, **kw)


def _twice() -> None:
    fn = lambda prep, **o: MethodRun(None, bl.Status.ERROR, "nothing")  # noqa: E731
    bl.register_method("probe-twice", fn)
    try:
        bl.register_method("probe-twice", fn)
    finally:
        METHODS.pop("probe-twice", None)


_VRFT = atk.flexible_transmission_setting()


def _vrft_data(n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    return _VRFT.recorded(np.random.default_rng(0).standard_normal(n))


def _vrft(objective: str = "maxmin", target: Any = None, n: int = 64) -> atk.VRFTAttack:
    u, y = _vrft_data(n)
    return atk.VRFTAttack(_VRFT, u, y, 0.1, 0.05, objective, target)


def _saved_to_missing_dir() -> None:
    a = _vrft()
    a.save(atk.attack_white_noise(a), "/nonexistent-probe-dir/attack.npz")


def _lower_cvxpy(build: Callable[[bl.BilevelProblem, ca.SX], Any]) -> Callable[[], Any]:
    def run() -> Any:
        p = bl.BilevelProblem("cvx")
        x = p.upper_variable("x", lb=0, ub=1)
        return build(p, x)
    return run


def _cvx_integer(p: bl.BilevelProblem, x: ca.SX) -> Any:
    z = cp.Variable(integer=True)
    return p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(z))))


def _cvx_not_dcp(p: bl.BilevelProblem, x: ca.SX) -> Any:
    z = cp.Variable()
    return p.lower_cvxpy(cp.Problem(cp.Maximize(cp.square(z))))


def _cvx_after_lower(p: bl.BilevelProblem, x: ca.SX) -> Any:
    p.lower_variable("y")
    z = cp.Variable()
    return p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(z))))


def _cvx_foreign_variable(p: bl.BilevelProblem, x: ca.SX) -> Any:
    z, w = cp.Variable(), cp.Variable()
    ll = p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(z))))
    return ll[w]


def _cvx_foreign_parameter(p: bl.BilevelProblem, x: ca.SX) -> Any:
    z, a, other = cp.Variable(), cp.Parameter(), cp.Parameter()
    return p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(z - a))), {other: x})


CASES: dict[str, tuple[Callable[[], Any], Any, str]] = {
    # -- constraint names: unique, and not the bounds' multiplier names ----------------------------------------------
    "duplicate lower constraint name": (_decl(lambda p, x, y: (p.lower_constraint(y[0] <= 1, name="cap"),
                                                              p.lower_constraint(y[1] <= 1, name="cap"))),
                                        ModelError, "'cap' is already used by the lower constraint 'cap'"),
    "upper and lower constraint alike": (_decl(lambda p, x, y: (p.upper_constraint(x[0] <= 1, name="c"),
                                                               p.lower_constraint(y[1] <= 1, name="c"))),
                                         ModelError, "'c' is already used by the upper constraint"),
    "LMI named like a constraint": (_decl(lambda p, x, y: (p.lower_constraint(y[0] <= 1, name="m"),
                                                          p.lower_psd_constraint(ca.diag(y), name="m"))),
                                    ModelError, "'m' is already used by the lower constraint"),
    "constraint named like a lower bound": (_decl(lambda p, x, y: p.lower_constraint(y[0] <= 1, name="y.lb")),
                                            ModelError, "'y.lb' ends in '.lb'.*bounds"),
    "constraint named like an upper bound": (_decl(lambda p, x, y: p.upper_constraint(x[0] <= 1, name="z.ub")),
                                             ModelError, "'z.ub' ends in '.ub'"),
    "constraint named by a number": (_decl(lambda p, x, y: p.lower_constraint(y[0] <= 1, name=3)), ModelError,
                                     "name 3 must be a non-empty string"),
    "constraint named by an empty string": (_decl(lambda p, x, y: p.upper_constraint(x[0] <= 1, name="")),
                                            ModelError, "must be a non-empty string"),
    # -- LMIs ------------------------------------------------------------------------------------------------------
    "empty LMI": (_decl(lambda p, x, y: p.lower_psd_constraint(ca.SX(0, 0))), ModelError, "matrix is empty"),
    "LMI of a string": (_decl(lambda p, x, y: p.lower_psd_constraint("M")), ModelError, "expected a square CasADi"),
    "non-square LMI": (_decl(lambda p, x, y: p.lower_psd_constraint(ca.vertcat(y, y))), ModelError, "must be square"),
    # -- parameters --------------------------------------------------------------------------------------------------
    "complex parameter value": (_with_param(lambda p: p.set_value("w", [1 + 2j, 3.0])), InvalidData, "is complex"),
    "complex scalar with zero imaginary part": (_with_param(lambda p: p.set_value("w", np.array([1, 2], complex))),
                                                InvalidData, "is complex"),
    "string parameter value": (_with_param(lambda p: p.set_value("w", ["a", "b"])), InvalidData,
                               "must be real numbers"),
    "None parameter value": (_with_param(lambda p: p.set_value("w", None)), InvalidData, "must be real numbers"),
    "dict parameter value": (_with_param(lambda p: p.set_value("w", {"a": 1})), InvalidData, "must be real numbers"),
    "inf parameter value": (_with_param(lambda p: p.set_value("w", [np.inf, 1.0])), InvalidData, "NaN or inf"),
    "wrong-shape parameter value": (_with_param(lambda p: p.set_value("w", np.ones((2, 2)))), ModelError,
                                    "has shape \\(2, 2\\)"),
    "complex first value": (_decl(lambda p, x, y: p.parameter("c", 1, value=1j)), InvalidData, "is complex"),
    "zero-size parameter": (_decl(lambda p, x, y: p.parameter("c", 0)), ModelError, "must be positive"),
    "parameter named like a variable": (_decl(lambda p, x, y: p.parameter("y")), ModelError, "already declared"),
    "unset parameter at solve": (lambda: _unset_parameter().solve("ipopt", starts=1), ModelError, "have no value"),
    # -- declarations ----------------------------------------------------------------------------------------------
    "upper bounds crossed in one entry": (lambda: _p(lb=[0, 3], ub=[1, 2]), ModelError, "exceeds its upper bound"),
    "upper bound of wrong length": (_decl(lambda p, x, y: p.upper_variable("z", 3, ub=[1, 2])), ModelError,
                                    "has 2 entries but the variable has 3"),
    "complex bound": (_decl(lambda p, x, y: p.upper_variable("z", lb=1j)), ModelError, "must be a number"),
    "start of wrong length": (_decl(lambda p, x, y: p.upper_variable("z", 2, start=[1, 2, 3])), ModelError,
                              "has 3 entries"),
    "list objective": (_decl(lambda p, x, y: p.minimize_upper([x[0], y[0]])), ModelError,
                       "expected a CasADi expression.*got list"),
    "vector lower maximization": (_decl(lambda p, x, y: p.maximize_lower(y)), ModelError, "must be scalar"),
    "string constraint": (_decl(lambda p, x, y: p.upper_constraint("x <= 1")), ModelError,
                          "expects a CasADi comparison"),
    "mixed comparison": (_decl(lambda p, x, y: p.lower_constraint(ca.vertcat(y[0] <= 1, y[1] == 0))), ModelError,
                         "mixes equalities and inequalities"),
    "constant comparison": (_decl(lambda p, x, y: p.upper_constraint(ca.SX(1) <= 2)), ModelError,
                            "contains no variables"),
    "definition of a lower variable": (_decl(lambda p, x, y: p.define("z", 2 * y)), ModelError,
                                       "definition depends on the leader's choices only"),
    "suggest_start of a lower variable": (_decl(lambda p, x, y: p.suggest_start(y=[0, 0])), ModelError,
                                          "'y' is not an upper variable"),
    "suggest_start of wrong length": (_decl(lambda p, x, y: p.suggest_start(x=[0, 0, 0])), ModelError,
                                      "has 3 entries"),
    "suggest_start of nothing": (_decl(lambda p, x, y: p.suggest_start()), ModelError, "needs values"),
    "lower_qp of a non-variable": (_decl(lambda p, x, y: p.lower_qp(x, C=np.eye(2))), ModelError,
                                   "y must be a vector lower variable"),
    "lower_qp after a lower objective": (_decl(lambda p, x, y: p.lower_qp(y, C=np.eye(2))), ModelError,
                                         "declare nothing else on the lower level"),
    "lower_qp with indefinite P": (lambda: _lower_qp(P=np.diag([1.0, -1.0])), ModelError,
                                   "not positive semidefinite"),
    "lower_qp with d of wrong length": (lambda: _lower_qp(C=np.eye(2), d=[1.0, 2.0, 3.0]), ModelError,
                                        "d has 3 entries; it needs 2"),
    "lower_qp without objective": (lambda: _lower_qp(), ModelError, "no objective"),
    "constraint after lower_qp": (lambda: _lower_qp(C=np.eye(2), then=True), ModelError, "declared by lower_qp"),
    # -- problems that cannot be solved as declared ----------------------------------------------------------------
    "empty problem": (lambda: bl.BilevelProblem().solve(), ModelError, "no upper objective"),
    "no lower variables": (lambda: _no_lower().solve(), ModelError, "no lower variables"),
    "lower constraint of upper variables only": (lambda: _upper_only_lower_constraint().solve(starts=1), ModelError,
                                                 "does not involve lower variables"),
    "unknown registered problem": (lambda: registry.get("no-such-problem"), UnknownName, "no registered problem"),
    # -- options ---------------------------------------------------------------------------------------------------
    "scale 0 (ipopt)": (_solve({"method": "ipopt", "scale": 0.0}), ModelError, "scale=0.0 is invalid"),
    "scale negative (hypergradient)": (_solve({"method": "hypergradient", "scale": -1.0}), ModelError,
                                       "scale=-1.0 is invalid"),
    "scale NaN (relaxation)": (_solve({"method": "relaxation", "scale": float("nan")}), ModelError,
                               "scale=nan is invalid"),
    "scale string (block-exact)": (_solve({"method": "block-exact", "scale": "10"}), ModelError,
                                   "scale='10' is invalid"),
    "pop_tol zero": (_solve({"pop_tol": 0.0}), ModelError, "pop_tol=0.0 is invalid"),
    "max_iter float": (_solve({"max_iter": 2.5}), ModelError, "max_iter=2.5 is invalid"),
    "seed float": (_solve({"seed": 1.5}), ModelError, "seed=1.5 is invalid"),
    "seed string": (_solve({"seed": "abc"}), ModelError, "seed='abc' is invalid"),
    "certificate_tol inf": (_solve({"certificate_tol": float("inf")}), ModelError, "certificate_tol=inf is invalid"),
    "method None": (_solve({"method": None}), ModelError, "unknown method None"),
    "unknown hypergradient option": (_solve({"method": "hypergradient", "step": 1.0}), UnknownOption,
                                     "does not take option\\(s\\) step"),
    "unknown relaxation scheme": (_solve({"method": "relaxation", "scheme": "fast"}), ModelError,
                                  "unknown relaxation scheme 'fast'"),
    "invalid warm": (_solve({"method": "ipopt", "warm": "cold"}), ModelError, "option warm='cold'"),
    "invalid exact_block": (_solve({"method": "hypergradient", "exact_block": "yes"}), ModelError,
                            "exact_block='yes' is invalid"),
    "projection of a wrong type": (_solve({"method": "hypergradient", "projection": "ball"}), ModelError,
                                   "must be a Projection"),
    "relaxation t0 negative": (_solve({"method": "relaxation", "t0": -1.0}), ModelError, "t0=-1.0 is invalid"),
    "relaxation comp_tol string": (_solve({"method": "relaxation", "comp_tol": "tight"}), ModelError,
                                   "comp_tol='tight' is invalid"),
    "relaxation t_min zero": (_solve({"method": "relaxation", "t_min": 0.0}), ModelError, "t_min=0.0 is invalid"),
    "branch_polish given as a string": (_solve({"method": "ipopt", "branch_polish": "no"}), ModelError,
                                        "branch_polish='no' is invalid"),
    "Scholtes with a negative tau": (lambda: bl.mpcc.Scholtes(-1.0), ModelError, "tau must be a finite number >= 0"),
    "differential-evolution popsize 1.5": (_solve({"method": "differential-evolution", "popsize": 1.5},
                                                  lambda: projection_qp()), ModelError, "popsize=1.5 is invalid"),
    "hypergradient penalty string": (_solve({"method": "hypergradient", "penalty": "big"}), ModelError,
                                     "penalty='big' is invalid"),
    "hypergradient ftol negative": (_solve({"method": "hypergradient", "ftol": -1.0}), ModelError,
                                    "ftol=-1.0 is invalid"),
    "hypergradient active_tol zero": (_solve({"method": "hypergradient", "active_tol": 0.0}), ModelError,
                                      "active_tol=0.0 is invalid"),
    "ipopt mode by name": (_solve({"method": "ipopt", "mode": "scholtes"}), ModelError,
                           "mode='scholtes' is invalid: it must be a complementarity mode"),
    "ipopt options not a dict": (_solve({"method": "ipopt", "ipopt": "quiet"}), ModelError,
                                 "ipopt='quiet' is invalid: it must be a dict"),
    "unknown IPOPT option": (_solve({"method": "ipopt", "starts": 1, "ipopt": {"nonsense": 1}}), ModelError,
                             "No such IPOPT option: nonsense"),
    "IPOPT option of a wrong type": (_solve({"method": "ipopt", "starts": 1, "ipopt": {"max_iter": "many"}}),
                                     ModelError, "IPOPT did not accept its options \\(type mismatch\\)"),
    # -- entry points given the wrong type -------------------------------------------------------------------------
    "solve of a string": (lambda: bl.solve("bard1998-ex5.1.1"), ModelError, "expected a BilevelProblem, got str"),
    "solve of None": (lambda: bl.solve(None), ModelError, "expected a BilevelProblem, got NoneType"),
    "problem named by a number": (lambda: bl.BilevelProblem(3), ModelError, "name 3 must be a string"),
    "registered problem by a number": (lambda: registry.get(123), UnknownName, "a problem name is a string"),
    "definition equation of a string": (_decl(lambda p, x, y: p.define("z", x, equation=lambda z: "z = 0")),
                                        ModelError, "the equation: expected a CasADi expression or numbers"),
    "definition of a string": (_decl(lambda p, x, y: p.define("z", "2 x")), ModelError,
                               "expected a CasADi expression, got str"),
    "lower_qp q of a string": (lambda: _lower_qp(C=np.eye(2), q="zero"), ModelError,
                               "lower_qp: q: expected a CasADi expression or numbers"),
    "Willems unknown setting": (lambda: build_attack(horizn=10), ModelError,
                                "the parameters horizn include an unknown one.*horizon"),
    "Willems attack starts 0": (lambda: willems.hypergradient_attack(build_attack(), starts=0), ModelError,
                                "starts=0 is invalid"),
    "Willems destabilize max_iter negative": (lambda: willems.destabilize_attack(
        build_attack(objective="destabilize"), max_iter=-1), ModelError, "max_iter=-1 is invalid"),
    "Willems random seed string": (lambda: willems.random_attack(build_attack(), seed="x"), ModelError,
                                   "seed='x' is invalid"),
    "registered VRFT problem with a negative seed": (lambda: registry.get("vrft-maxmin", seed=-1), ModelError,
                                                     "seed=-1 is invalid"),
    "registered Willems problem with a negative seed": (lambda: registry.get("willems-eigen", seed=-2), ModelError,
                                                        "seed=-2 is invalid"),
    "Willems row of None": (lambda: willems_row(None), ModelError, "stats\\['eigenvalues'\\]"),
    # -- methods ---------------------------------------------------------------------------------------------------
    "replace a built-in method": (_register("ipopt", lambda prep, **o: None), ModelError,
                                  "built-in method 'ipopt' is already registered.*replace=True"),
    "replace a built-in method, other case": (_register("Hypergradient", lambda prep, **o: None), ModelError,
                                              "built-in method 'hypergradient'"),
    "register a non-callable": (_register("probe-x", "ipopt"), ModelError, "is a str, not callable"),
    "register an empty name": (_register(" ", lambda prep, **o: None), ModelError, "must be a non-empty string"),
    "register a name twice": (_twice, ModelError, "'probe-twice' is already registered"),
    "method returning None": (_custom(None), ModelError, "returned NoneType, not a MethodRun"),
    "method returning a dict": (_custom({"w": None}), ModelError, "returned dict, not a MethodRun"),
    # -- honest statuses ----------------------------------------------------------------------------------------------
    "unbounded lower LP (ipopt)": (lambda: _unbounded_lp().solve("ipopt", starts=1), STATUS,
                                   "lower level unbounded, not an infeasible problem"),
    "unbounded lower LP (relaxation)": (lambda: _unbounded_lp().solve("relaxation", starts=1), STATUS,
                                        "lower level unbounded"),
    "from_json of broken JSON": (lambda: bl.BilevelResult.from_json("{bad"), InvalidData,
                                 "not a result written by BilevelResult.to_json \\(JSONDecodeError"),
    "from_json of another JSON object": (lambda: bl.BilevelResult.from_json('{"a": 1}'), InvalidData,
                                         "not a result written by BilevelResult.to_json \\(KeyError"),
    "unbounded lower LP (global)": (lambda: _unbounded_lp().solve("global"), STATUS,
                                    "lower level unbounded, not an infeasible problem"),
    "unbounded lower LP (hypergradient)": (lambda: _unbounded_lp().solve("hypergradient", starts=1), STATUS,
                                           "LowerLevelUnbounded"),
    "unbounded lower NLP (ipopt)": (lambda: _unbounded_nlp().solve("ipopt", starts=1), STATUS,
                                    "lower level unbounded.*Diverging_Iterates"),
    "tilted norm_2 ball at its kink (hypergradient)": (lambda: _norm_ball().solve("hypergradient", starts=1), STATUS,
                                                "hypergradient is NaN or inf"),
    "tilted norm_2 ball at its kink (ipopt)": (lambda: _norm_ball().solve("ipopt", starts=1), STATUS,
                                        "Invalid_Number_Detected"),
    "max_iter 0 (ipopt)": (_solve({"method": "ipopt", "starts": 1, "max_iter": 0}, projection_qp), STATUS,
                           "Maximum_Iterations_Exceeded"),
    # -- attacks ---------------------------------------------------------------------------------------------------
    "alternating starts 0": (lambda: atk.attack_alternating(_vrft(), starts=0), ModelError, "starts=0 is invalid"),
    "alternating max_iter negative": (lambda: atk.attack_alternating(_vrft(), max_iter=-1), ModelError,
                                      "max_iter=-1 is invalid"),
    "alternating gain_tol zero": (lambda: atk.attack_alternating(_vrft(), gain_tol=0.0), ModelError,
                                  "gain_tol=0.0 is invalid"),
    "joint starts float": (lambda: atk.attack_joint(_vrft(), starts=1.5), ModelError, "starts=1.5 is invalid"),
    "joint max_iter negative": (lambda: atk.attack_joint(_vrft(), max_iter=-3), ModelError, "max_iter=-3"),
    "white noise seed negative": (lambda: atk.attack_white_noise(_vrft(), seed=-1), ModelError, "seed=-1"),
    "targeted target of wrong length": (lambda: _vrft("targeted", np.ones(3)), InvalidData,
                                        "theta_target must be 6 finite numbers.*shape \\(3,\\)"),
    "targeted target with NaN": (lambda: _vrft("targeted", np.full(6, np.nan)), InvalidData,
                                 "theta_target must be 6 finite"),
    "targeted without target": (lambda: _vrft("targeted"), ModelError, "needs theta_target"),
    "VRFT fewer samples than parameters": (lambda: _vrft(n=5), InvalidData,
                                           "5 samples give 5 regression rows for 6 controller parameters"),
    "VRFT data of strings": (lambda: atk.VRFTAttack(_VRFT, ["a"] * 8, ["b"] * 8, 0.1, 0.1), InvalidData,
                             "arrays of real numbers"),
    "attack_instance N 0": (lambda: atk.attack_instance("maxmin", N=0), InvalidData, "N=0 samples"),
    "budget path of no budgets": (lambda: atk.attack_budget_path(_vrft(), []), ModelError,
                                  "needs at least one output budget"),
    "attack_value of None": (lambda: atk.attack_value(None), ModelError, "expected the BilevelResult of a VRFT"),
    "unstable of a dict": (lambda: atk.unstable({"spectral_radius": 2.0}), ModelError, "got dict"),
    "attack_summary of a solve": (lambda: attack_summary(bard_511().solve("ipopt", starts=1)), ModelError,
                                  "stats\\['learner_loss'\\]"),
    "VRFTAttack.save to a missing directory": (_saved_to_missing_dir, ModelError, "does not exist; create it"),
    "fit_arx on too few samples": (lambda: atk.fit_arx(*_vrft_data(3), 4, 2, 3), RankDeficientRegressor,
                                   "3 samples are too few"),
    "fit_arx negative order": (lambda: atk.fit_arx(*_vrft_data(64), -1, 2, 0), InvalidData,
                               "ARX orders must be integers"),
    "Willems horizon too short": (lambda: build_attack(WillemsSetting(horizon=3)), NotPersistentlyExciting,
                                  "T >= n \\+ m = 6 samples at least.*Fix: a longer horizon"),
    # -- the cvxpy front end -----------------------------------------------------------------------------------------
    "cvxpy integer lower level": (_lower_cvxpy(_cvx_integer), ModelError, "integer or boolean variables"),
    "cvxpy non-DCP lower level": (_lower_cvxpy(_cvx_not_dcp), ModelError, "not DCP"),
    "cvxpy after lower variables": (_lower_cvxpy(_cvx_after_lower), ModelError, "use one or the other"),
    "cvxpy foreign variable": (_lower_cvxpy(_cvx_foreign_variable), ModelError, "is not a Variable of this cvxpy"),
    "cvxpy binding of a foreign Parameter": (_lower_cvxpy(_cvx_foreign_parameter), ModelError,
                                             "is not a cvxpy Parameter of this problem"),
}


def _unset_parameter() -> bl.BilevelProblem:
    p, x, y = _p()
    w = p.parameter("w", 2)
    p.minimize_upper(ca.sumsqr(y - w))
    p.minimize_lower(ca.sumsqr(y - x))
    return p


def _no_lower() -> bl.BilevelProblem:
    p = bl.BilevelProblem()
    x = p.upper_variable("x")
    p.minimize_upper(x ** 2)
    p.minimize_lower(x ** 2)
    return p


def _upper_only_lower_constraint() -> bl.BilevelProblem:
    p, x, y = _full()
    p.lower_constraint(x[0] <= 1)
    return p


def _lower_qp(then: bool = False, **mats: Any) -> bl.BilevelProblem:
    p, x, y = _p()
    p.minimize_upper(ca.sumsqr(y - x))
    p.lower_qp(y, **mats)
    if then:
        p.lower_constraint(y[0] <= 1)
    return p


def _outcome(case: str) -> str:
    return "honest status" if CASES[case][1] == STATUS else "named error"


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_has_one_named_outcome(case: str) -> None:
    run, expected, match = CASES[case]
    if expected == STATUS:
        res = run()
        assert isinstance(res, bl.BilevelResult) and res.status is not bl.Status.SOLVED and not res.success
        assert re.search(match, res.message), res.message
        return
    with pytest.raises(BilevelError, match=match) as info:
        run()
    assert type(info.value) is expected, f"{type(info.value).__name__}: {info.value}"


def test_the_probe_covers_sixty_inputs_in_both_outcomes() -> None:
    counts = Counter(_outcome(case) for case in CASES)
    assert sum(counts.values()) >= 60 and counts["honest status"] >= 5 and counts["named error"] >= 55, counts


# -- regressions of the mechanisms the probe found silent --------------------------------------------------------------
def test_default_constraint_names_step_around_given_ones_and_keep_every_multiplier() -> None:
    """y*(x) = argmin |y - x|^2 s.t. y0 <= 1 (named 'g1'), y1 <= 0.5 (unnamed: g1 is taken, so 'g1_'); the upper
    optimum x = (1.5, 1.5) has lam = 2 (x - y) = (1, 2), one multiplier per constraint (before: one lost)."""
    p, x, y = _p()
    p.minimize_upper(ca.sumsqr(y - ca.DM([3, 3])) + 0.1 * ca.sumsqr(x - 1.5))
    p.minimize_lower(ca.sumsqr(y - x))
    p.lower_constraint(y[0] <= 1, name="g1")
    p.lower_constraint(y[1] <= 0.5)
    assert [c.name for c in p.lower_constraints] == ["g1", "g1_"]
    res = p.solve("ipopt", starts=1)
    assert res.status is bl.Status.SOLVED, res.message
    np.testing.assert_allclose(res.x["x"], [1.5, 1.5], atol=1e-6)
    np.testing.assert_allclose(res.multipliers["g1"], [1.0], atol=1e-6)
    np.testing.assert_allclose(res.multipliers["g1_"], [2.0], atol=1e-6)


def _ball_and_box() -> bl.BilevelProblem:
    """d in the unit ball (sumsqr), e <= 0.5; y*(d, e) = (d, e); F = |y - (3, 1, 2)|^2: optimum at d = (3, 1) /
    sqrt(10) on the sphere and e = 0.5 on its bound."""
    p = bl.BilevelProblem("ball-and-box")
    d = p.upper_variable("d", 2, lb=-2, ub=2)
    e = p.upper_variable("e", lb=-1, ub=0.5)
    y = p.lower_variable("y", 3)
    p.minimize_upper(ca.sumsqr(y - ca.DM([3, 1, 2])))
    p.minimize_lower(ca.sumsqr(y - ca.vertcat(d, e)))
    p.upper_constraint(ca.sumsqr(d) <= 1)
    return p


@pytest.mark.parametrize("method", ["ipopt", "relaxation"])
@pytest.mark.parametrize("polish", [True, False])
def test_kkt_answers_lie_inside_the_declared_box_and_ball_exactly(method: str, polish: bool) -> None:
    res = _ball_and_box().solve(method, starts=2, branch_polish=polish)
    assert res.status is bl.Status.SOLVED, res.message
    np.testing.assert_allclose(res.x["d"], np.array([3.0, 1.0]) / np.sqrt(10.0), atol=1e-6)
    assert np.linalg.norm(res.x["d"]) <= 1.0 * (1 + 1e-12)
    assert -1.0 <= res.x["e"][0] <= 0.5 and np.all(np.abs(res.x["d"]) <= 2.0)
    assert res.x["e"][0] == pytest.approx(0.5, abs=1e-8)


@pytest.mark.parametrize("center", [0.0, 0.3])
def test_a_norm_2_ball_is_projected_on_exactly(center: float) -> None:
    """norm_2(d - c) <= 1 is read as the ball it is (before: penalized, and NaN at its center): hypergradient ends at
    the projection of (3, 1) onto it, c + (3 - c, 1 - c) / |(3 - c, 1 - c)|, on the sphere."""
    res = _norm_ball(tilt=0.0, center=center).solve("hypergradient", starts=2)
    assert res.status is bl.Status.SOLVED, res.message
    direction = np.array([3.0, 1.0]) - center
    np.testing.assert_allclose(res.x["d"], center + direction / np.linalg.norm(direction), atol=1e-7)
    assert np.linalg.norm(res.x["d"] - center) <= 1.0 * (1 + 1e-12)


def test_register_method_replaces_only_when_asked() -> None:
    def nothing(prep: Any, **options: Any) -> MethodRun:
        return MethodRun(None, bl.Status.ERROR, "no point by design")

    builtin = METHODS["relaxation"]
    try:
        bl.register_method("relaxation", nothing, replace=True)
        res = bl.solve(bard_511(), method="relaxation")
        assert res.status is bl.Status.ERROR and res.message == "no point by design"
    finally:
        METHODS["relaxation"] = builtin
    with pytest.raises(ModelError, match="already registered"):
        bl.register_method("relaxation", nothing)
    assert METHODS["relaxation"] is builtin


def test_a_refused_value_leaves_the_parameter_unchanged() -> None:
    p, x, y = _full()
    p.parameter("w", 2, value=[1.0, 2.0])
    revision = p.parameters.revision
    for bad in ([1 + 1j, 2.0], ["1", "2"], [np.nan, 0.0]):
        with pytest.raises(InvalidData):
            p.set_value("w", bad)
    np.testing.assert_array_equal(p.parameters.value, [1.0, 2.0])
    assert p.parameters.revision == revision
