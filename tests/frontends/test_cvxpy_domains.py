"""Issue "Honest answers II", item 2: a cvxpy Parameter bound to upper variables stays in the domain its attributes
declare (the learner is DCP only there), or the binding is refused with a named error."""

from __future__ import annotations

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl
from bilevel.errors import InvalidData, ModelError


def _ridge_like(param: cp.Parameter) -> tuple[cp.Problem, cp.Variable]:
    """min (z - 1)^2 + p z^2 on [-5, 5]: DCP for p >= 0, z* = 1 / (1 + p)."""
    z = cp.Variable()
    return cp.Problem(cp.Minimize(cp.square(z - 1) + param * cp.square(z)), [z >= -5, z <= 5]), z


def _leader(bind) -> tuple[bl.BilevelProblem, object, cp.Parameter]:
    """x in [0, 2], p bound to bind(x), the leader maximizes z^2."""
    param = cp.Parameter(nonneg=True, value=1.0)
    learner, z = _ridge_like(param)
    prob = bl.BilevelProblem("domain")
    x = prob.upper_variable("x", lb=0, ub=2)
    ll = prob.lower_cvxpy(learner, {param: bind(x)})
    prob.maximize_upper(ll[z] ** 2)
    return prob, ll, param


@pytest.mark.parametrize("method", ["ipopt", "hypergradient"])
def test_nonneg_parameter_bound_to_an_expression_that_goes_negative_is_kept_nonneg(method: str) -> None:
    """p = 1 - x is negative for x > 1, where the learner is not DCP (cvxpy refuses the value); unconstrained the
    leader drove p to -1 (z* = 5, F = 25). With p >= 0 enforced: x = 1, p = 0, z* = 1, F = 1."""
    prob, _, param = _leader(lambda x: 1 - x)
    assert [c.name for c in prob.upper_constraints] == [f"cvxpy.{param.name()}.min"]
    res = prob.solve(method)
    assert res.status is bl.Status.SOLVED, res.message
    assert res.x["x"][0] == pytest.approx(1.0, abs=1e-5)
    assert res.upper_objective == pytest.approx(1.0, abs=1e-5)
    assert res.certificate.passed


def test_the_re_solve_does_not_clip_a_value_outside_the_domain() -> None:
    """The certificate's re-solve clipped p = 1 - x to 0 silently; now it refuses (and the certificate fails)."""
    prob, _, _ = _leader(lambda x: 1 - x)
    reference = prob.lower_reference
    x_sym = ca.vertcat(*[v.sym for v in prob.upper_variables])
    with pytest.raises(InvalidData, match="outside its declared domain"):
        reference(x_sym, np.array([1.5]), np.zeros(1))
    sol = reference(x_sym, np.array([1.0 + 1e-9]), np.zeros(1))  # p = -1e-9: rounding, moved onto the domain
    assert sol.objective == pytest.approx(0.0, abs=1e-8)  # p = 0: z* = 1, f = 0


@pytest.mark.parametrize("attributes, bounds", [({"pos": True}, (0.0, np.inf)), ({"nonpos": True}, (-np.inf, 0.0)),
                                                ({"neg": True}, (-np.inf, 0.0)),
                                                ({"bounds": (0.5, 1.5)}, (0.5, 1.5))])
def test_sign_attributes_and_bounds_become_upper_constraints(attributes: dict, bounds: tuple) -> None:
    """Each finite end of the domain is one upper constraint on the bound expression."""
    param = cp.Parameter(**attributes)
    z = cp.Variable()
    learner = cp.Problem(cp.Minimize(cp.square(z - param)))
    prob = bl.BilevelProblem("sign")
    x = prob.upper_variable("x", lb=-3, ub=3)
    ll = prob.lower_cvxpy(learner, {param: x})
    prob.minimize_upper((ll[z] - 2.5) ** 2 + (x + 2.5) ** 2)  # pulls x to 0 from both sides
    res = prob.solve("ipopt")
    assert res.status is bl.Status.SOLVED, res.message
    assert len(prob.upper_constraints) == int(np.isfinite(bounds[0])) + int(np.isfinite(bounds[1]))
    expected = float(np.clip(0.0, *bounds))
    assert res.x["x"][0] == pytest.approx(expected, abs=1e-5)


@pytest.mark.parametrize("attribute", ["PSD", "NSD", "symmetric", "boolean", "integer"])
def test_attribute_without_an_upper_counterpart_is_refused_by_name(attribute: str) -> None:
    shape = (2, 2) if attribute in ("PSD", "NSD", "symmetric") else (2, 1)
    param = cp.Parameter(shape, **{attribute: True})
    z = cp.Variable(2)
    offset = cp.sum(param, axis=1) if len(shape) == 2 else param
    learner = cp.Problem(cp.Minimize(cp.sum_squares(z - offset)))
    prob = bl.BilevelProblem("structural")
    x = prob.upper_variable("x", shape, lb=-1, ub=1)
    with pytest.raises(ModelError, match=f"attribute '{attribute}'"):
        prob.lower_cvxpy(learner, {param: x})


def test_constant_outside_the_domain_is_refused() -> None:
    param = cp.Parameter(nonneg=True)
    z = cp.Variable()
    learner = cp.Problem(cp.Minimize(cp.square(z) + param * cp.square(z - 1)))
    prob = bl.BilevelProblem("constant")
    prob.upper_variable("x", lb=-1, ub=1)
    with pytest.raises(ModelError, match="outside its declared domain"):
        prob.lower_cvxpy(learner, {param: -1.0})
