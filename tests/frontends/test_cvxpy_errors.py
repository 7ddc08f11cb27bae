"""Bad cvxpy lower levels fail at declaration with a ModelError naming the problem and the fix."""

from __future__ import annotations

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl


def declare(learner: cp.Problem, parameters: dict | None = None) -> bl.BilevelProblem:
    p = bl.BilevelProblem("bad")
    p.upper_variable("x", 2)
    p.lower_cvxpy(learner, parameters=parameters)
    return p


def test_non_dpp_problem_is_named() -> None:
    a, b, y = cp.Parameter(), cp.Parameter(), cp.Variable()
    with pytest.raises(bl.ModelError, match="not DPP.*introduce one Parameter"):
        declare(cp.Problem(cp.Minimize(a * b * y), [y >= 0]), {a: 1.0, b: 2.0})


def test_non_dcp_problem_is_named() -> None:
    y = cp.Variable()
    with pytest.raises(bl.ModelError, match="not DCP"):
        declare(cp.Problem(cp.Minimize(cp.sqrt(y))))


def test_unbound_parameter_without_value() -> None:
    a, y = cp.Parameter(name="a"), cp.Variable()
    with pytest.raises(bl.ModelError, match="Parameter 'a'.*has no value.*set param.value"):
        declare(cp.Problem(cp.Minimize(cp.square(y - a))))


def test_exponential_cone_is_rejected_with_a_hint() -> None:
    y = cp.Variable()
    with pytest.raises(bl.ModelError, match="exponential cone.*zero, nonnegative, second-order and PSD"):
        declare(cp.Problem(cp.Minimize(-cp.log(y) + y)))


def test_power_cone_is_rejected_with_a_hint() -> None:
    y = cp.Variable(2)
    with pytest.raises(bl.ModelError, match="power cone"):
        declare(cp.Problem(cp.Minimize(cp.sum(cp.power(y, 1.5, approx=False))), [y >= 1]))


def test_wrong_shaped_binding() -> None:
    a, y = cp.Parameter(3, name="a"), cp.Variable(3)
    p = bl.BilevelProblem("bad")
    x = p.upper_variable("x", 2)
    with pytest.raises(bl.ModelError, match=r"Parameter 'a' \(shape \(3,\)\) is bound to an expression of shape "
                                            r"\(2, 1\).*3 x 1"):
        p.lower_cvxpy(cp.Problem(cp.Minimize(cp.sum_squares(y - a))), parameters={a: x})


def test_binding_to_a_foreign_symbol_and_a_foreign_key() -> None:
    a, y = cp.Parameter(), cp.Variable()
    learner = cp.Problem(cp.Minimize(cp.square(y - a)))
    with pytest.raises(bl.ModelError, match="not an upper variable"):
        declare(learner, {a: ca.SX.sym("stranger")})
    with pytest.raises(bl.ModelError, match="not a cvxpy Parameter of this problem"):
        declare(learner, {cp.Parameter(): 1.0, a: 1.0})


def test_integer_variables_and_a_second_lower_declaration() -> None:
    with pytest.raises(bl.ModelError, match="integer or boolean"):
        declare(cp.Problem(cp.Minimize(cp.Variable(integer=True))))
    p = bl.BilevelProblem("twice")
    p.lower_variable("y")
    with pytest.raises(bl.ModelError, match="declares the whole lower level"):
        p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(cp.Variable()))))


def test_unbound_parameter_takes_its_value_and_unknown_variable_is_refused() -> None:
    a, y = cp.Parameter(value=3.0), cp.Variable()
    p = bl.BilevelProblem("fixed")
    x = p.upper_variable("x", lb=-1, ub=1)
    ll = p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(y - a))))
    p.minimize_upper((x - ll[y]) ** 2)
    res = p.solve()
    assert res.x["x"] == pytest.approx(1.0) and res.value(ll[y]) == pytest.approx(3.0)
    with pytest.raises(bl.ModelError, match="not a Variable of this cvxpy lower level"):
        ll[cp.Variable()]
    assert np.isfinite(res.upper_objective)


def test_lower_level_is_closed_after_lower_cvxpy() -> None:
    p = bl.BilevelProblem("closed")
    x = p.upper_variable("x")
    a, y = cp.Parameter(), cp.Variable()
    ll = p.lower_cvxpy(cp.Problem(cp.Minimize(cp.square(y - a))), parameters={a: x})
    with pytest.raises(bl.ModelError, match="lower_constraint: the lower level of 'closed' is a cvxpy problem"):
        p.lower_constraint(ll[y] <= 1)
    with pytest.raises(bl.ModelError, match="add the variable, objective or constraint to the cvxpy problem"):
        p.lower_variable("z")


def test_parameter_with_a_structural_attribute_is_named() -> None:
    a, y = cp.Parameter((2, 2), symmetric=True, value=np.eye(2)), cp.Variable(2)
    with pytest.raises(bl.ModelError, match="structural attribute.*declare it without the attribute"):
        declare(cp.Problem(cp.Minimize(cp.sum_squares(a @ y - 1))))
