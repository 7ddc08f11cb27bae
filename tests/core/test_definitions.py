"""Definitions (BilevelProblem.define): substituted by the methods that eliminate the lower level, kept as variables
bound by their equation in the KKT reformulation; both routes give the same answer."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import bilevel as bl
from bilevel.problems.vrft_instance import flexible_transmission_setting
from bilevel.errors import InvalidData, ModelError
from bilevel.mpcc import Scholtes
from bilevel.problems import registry
from bilevel.problems.vrft import difference_equation, sx_filter
from bilevel.solvers.engine.prepared import prepare

A = np.array([[1.0, 1.0], [1.0, -2.0]])
C = np.array([1.0, 3.0])


def _problem(recursive: bool) -> bl.BilevelProblem:
    """min_x ||y - c||^2 + 0.1 ||x||^2, y = argmin ||y - z||^2, z = A x defined (explicitly, or by the recursion
    z_0 = x_0 + x_1, z_1 = z_0 - 3 x_1): optimum x = (A'A + 0.1 I)^-1 A'c, inside the box."""
    p = bl.BilevelProblem("defined")
    x = p.upper_variable("x", 2, lb=-3, ub=3)
    equation = (lambda z: ca.vertcat(z[0] - x[0] - x[1], z[1] - z[0] + 3 * x[1])) if recursive else None
    z = p.define("z", ca.mtimes(ca.DM(A), x), equation)
    y = p.lower_variable("y", 2)
    p.minimize_lower(ca.sumsqr(y - z))
    p.minimize_upper(ca.sumsqr(y - ca.DM(C)) + 0.1 * ca.sumsqr(x))
    return p


X_STAR = np.linalg.solve(A.T @ A + 0.1 * np.eye(2), A.T @ C)


@pytest.mark.parametrize("recursive", [False, True])
@pytest.mark.parametrize("method", ["ipopt", "relaxation", "hypergradient"])
def test_defined_problem_reaches_the_closed_form_optimum(recursive: bool, method: str) -> None:
    problem = _problem(recursive)
    res = problem.solve(method, starts=1)
    assert res.status is bl.Status.SOLVED and res.certificate.passed
    np.testing.assert_allclose(res.x["x"], X_STAR, atol=1e-5)
    np.testing.assert_allclose(res.y["y"], A @ X_STAR, atol=1e-5)
    assert set(res.x) == {"x"}  # a definition is not a decision: results name the declared variables only
    z = next(d.sym for d in problem.definitions)
    np.testing.assert_allclose(res.value(z), A @ res.x["x"], atol=1e-12)  # expressions may use definitions


def test_the_kkt_reformulation_lifts_definitions_and_pack_restores_them() -> None:
    prep = prepare(_problem(recursive=True))
    blocks = {k: v.stop - v.start for k, v in prep.mpcc.blocks.items()}
    assert blocks["x"] == 4 and int(prep.mpcc.equalities.numel()) == 2 + 2  # the 2 equations + stationarity
    assert not ca.depends_on(prep.canon.F, ca.vertcat(*[d.sym for d in prep.problem.definitions]))
    point = prep.lower_point(np.array([0.5, -1.0]))
    w = prep.pack(point)
    np.testing.assert_allclose(w[prep.mpcc.blocks["x"]], [0.5, -1.0, -0.5, 2.5])  # z = A x appended
    assert max(prep.mpcc.residuals(w).values()) < 1e-9
    np.testing.assert_array_equal(prep.point(w).x, point.x)


def test_an_equation_that_does_not_hold_at_the_value_is_refused() -> None:
    p = bl.BilevelProblem("wrong")
    x = p.upper_variable("x", 2, lb=-1, ub=1)
    z = p.define("z", 2 * x, lambda z: z - 3 * x)
    y = p.lower_variable("y", 2)
    p.minimize_lower(ca.sumsqr(y - z))
    p.minimize_upper(ca.sumsqr(y))
    with pytest.raises(ModelError, match=r"define\('z'\): its equation"):
        p.solve("ipopt")


def test_definitions_of_lower_variables_and_reused_names_are_refused() -> None:
    p = bl.BilevelProblem("bad")
    x = p.upper_variable("x")
    y = p.lower_variable("y")
    with pytest.raises(ModelError, match="depends on the leader's choices only"):
        p.define("w", x + y)
    with pytest.raises(ModelError, match="already declared"):
        p.define("x", 2 * x)
    with pytest.raises(ModelError, match="one equation per entry"):
        p.define("v", ca.vertcat(x, x), lambda v: v[0] - x)
    with pytest.raises(InvalidData, match="NaN/inf in the data"):  # the same data check as every declared expression
        p.define("u", x * float("nan"))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.sampled_from(["paper", "raw"]))
def test_vrft_difference_equations_vanish_at_the_filtered_signal(seed: int, convention: str) -> None:
    """Every VRFT filter (error, prefilter, basis) as the registered problem declares it: a(q) z - b(q) x = 0 at
    z = sx_filter(x), and sx_filter equals the numeric filter (including the advance's zero final conditions)."""
    setting = flexible_transmission_setting(*({"paper": ("prefiltered", "zero-final"),
                                               "raw": ("raw", "zero-final")}[convention]))
    reg = setting.regressor
    x = np.random.default_rng(seed).standard_normal(40)
    ops = [reg.error] + list(reg.basis) + ([reg.prefilter] if reg.prefilter is not None else [])
    for op in ops:
        z = np.asarray(ca.evalf(sx_filter(op, ca.DM(x)))).ravel()
        np.testing.assert_allclose(z[op.advance:], op.apply(x), atol=1e-10)
        assert np.abs(np.asarray(ca.evalf(difference_equation(op, ca.DM(x), ca.DM(z))))).max() < 1e-10


def test_lifted_vrft_lagrangian_hessian_is_sparse() -> None:
    """The reason for lifting: with the filtered signals as variables, the NLP's Lagrangian Hessian grows linearly
    in N (122 nonzeros per sample: the k x k blocks of each regressor row with itself and theta), where the
    substituted regressor makes the a_y block dense (N^2 more)."""
    nnz = {}
    for n in (64, 128):
        nlp = prepare(registry.get("vrft-maxmin", N=n)).mpcc.transcribe(Scholtes(1e-9))
        lam = ca.SX.sym("lam", nlp.g.numel())
        nnz[n] = ca.hessian(nlp.f + ca.dot(lam, nlp.g), nlp.x)[0].nnz()
    assert nnz[64] < 130 * 64 and nnz[128] < 2.05 * nnz[64], nnz
