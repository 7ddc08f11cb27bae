"""Issue 16, one test per item: answers that were reported `solved` while wrong, and the crashes.

Colson's test set: B. Colson, P. Marcotte, G. Savard (2005), "A trust-region method for nonlinear
bilevel programming: algorithm and computational experience", Comput. Optim. Appl. 30:211-227,
problems BIPA1 and BIPA4 (as coded in BOLIB, Zhou, Zemkoho & Tin 2020, Colson2002BIPA1/BIPA4).
"""

from __future__ import annotations

import dataclasses
import json

import casadi as ca
import numpy as np
import pytest
import scipy.linalg as sla

import bilevel as bl
from bilevel.certificate import certify_point
from bilevel.errors import InvalidData, ModelError, NonConvexLowerLevel
from bilevel.mpcc import psd_factor
from bilevel.result import BilevelResult
from bilevel.solvers.engine.prepared import prepare
from bilevel.vech import lower_triangular
from tests.conftest import bard_511

BIPA1_OPTIMUM = 230.26769199924937
"""min over x in [0, 10] of (10 - x)^3 + (2.5 + x/2)^3 (y = (15 - x)/2 substituted), at x = 6.0819419."""


def bipa1() -> bl.BilevelProblem:
    """Colson's BIPA1 without its bound x <= 5 (with it the optimum is the corner x = y = 5, F = 250),
    x in [0, 10] instead, as in the issue's probe: the lower objective (x + 2y - 15)^4 is flat at y*."""
    p = bl.BilevelProblem("bipa1")
    x = p.upper_variable("x", lb=0, ub=10)
    y = p.lower_variable("y")
    p.minimize_upper((10 - x) ** 3 + (10 - y) ** 3)
    p.upper_constraint(y <= x)
    p.minimize_lower((x + 2 * y - 15) ** 4)
    p.lower_constraint(x + y <= 20)
    p.lower_constraint(y <= 20)
    p.lower_constraint(y >= 0)
    return p


def bipa4() -> bl.BilevelProblem:
    """Colson's BIPA4: the lower objective x^3 + 2y^3 + x - 2y - x^2 is convex only for y >= 0 (its bound)."""
    p = bl.BilevelProblem("bipa4")
    x = p.upper_variable("x", lb=0)
    y = p.lower_variable("y", lb=0)
    p.minimize_upper(x ** 2 + (y - 10) ** 2)
    p.upper_constraint(x + 2 * y <= 6)
    p.minimize_lower(x ** 3 + 2 * y ** 3 + x - 2 * y - x ** 2)
    p.lower_constraint(-x + 2 * y <= 3)
    return p


def bump(assume_convex: bool = False) -> bl.BilevelProblem:
    """The issue's exp-bump: f = (y - x)^2 - 100 exp(-(y - 8)^2) on y in [-10, 10] is not convex; at x = 0.25
    the follower's optimum is y = 7.92 (F = 62.8), not y = x (F = 0.125)."""
    p = bl.BilevelProblem("bump")
    x = p.upper_variable("x", lb=-10, ub=10)
    y = p.lower_variable("y", lb=-10, ub=10)
    p.minimize_upper((x - 0.5) ** 2 + y ** 2)
    p.minimize_lower((y - x) ** 2 - 100 * ca.exp(-(y - 8) ** 2), assume_convex=assume_convex)
    return p


# -- item 1: impossible bounds ---------------------------------------------------------------------------------
@pytest.mark.parametrize("bounds", [{"ub": -np.inf}, {"lb": np.inf}])
def test_impossible_lower_bound_is_an_error_not_a_free_variable(bounds) -> None:
    p = bl.BilevelProblem()
    with pytest.raises(ModelError, match="no\nfeasible value|no feasible value"):
        p.lower_variable("y", **bounds)


# -- item 2: hidden non-convexity ------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["ipopt", "relaxation", "hypergradient"])
def test_bump_nonconvexity_inside_the_bounds_is_detected(method: str) -> None:
    with pytest.raises(NonConvexLowerLevel, match="inside the declared bounds"):
        bump().solve(method)


def test_bump_with_assume_convex_fails_the_multistart_certificate() -> None:
    """The user's claim is checked: the multistart re-solve finds y = 7.92 with f far below f(0.25)."""
    res = bump(assume_convex=True).solve("ipopt", starts=2)
    assert res.status is bl.Status.CERTIFICATE_FAILED and not res.success
    cert = res.certificate
    assert "lower_gap" in cert.failed and "local evidence, not a proof" in cert.note
    # scipy's bounded minimize_scalar on [7, 9]: y* = 7.9228133, f* = -40.5339286, F(0.25, y*) = 62.8335
    assert cert.lower_reference_y[0] == pytest.approx(7.9228133, abs=1e-5)
    assert cert.lower_reference == pytest.approx(-40.5339286, abs=1e-6)


# -- item 3: convex on the declared domain ----------------------------------------------------------------------
@pytest.mark.parametrize("method", ["ipopt", "hypergradient"])
def test_bipa4_convex_on_its_bound_is_accepted_and_solved(method: str) -> None:
    """Optimum y = 1/sqrt(3) at x = 0: F = (10 - 1/sqrt 3)^2 = 88.78632..., f = -4/(3 sqrt 3) = -0.7698."""
    res = bipa4().solve(method, starts=2)
    assert res.status is bl.Status.SOLVED, res.message
    assert res.upper_objective == pytest.approx((10 - 1 / np.sqrt(3)) ** 2, abs=1e-6)
    assert res.y["y"][0] == pytest.approx(1 / np.sqrt(3), abs=1e-6)
    assert res.x["x"][0] == pytest.approx(0.0, abs=1e-5)  # ipopt stops at x = 6e-6 (F is flat there: dF/dx = 2x)
    assert res.lower_objective == pytest.approx(-4 / (3 * np.sqrt(3)), abs=1e-5)


# -- item 4: flat lower optimum --------------------------------------------------------------------------------
def test_bipa1_inexact_lower_point_is_not_solved_and_reports_the_bilevel_feasible_value() -> None:
    """IPOPT stops with y 7e-4 from y*(x) (f = 4e-12 passes the gap check), so F = 230.20 < 230.2677;
    the certificate compares y with the unique re-solved y and reports F there."""
    res = bipa1().solve("ipopt")
    assert res.status is bl.Status.CERTIFICATE_FAILED
    assert "lower_solution" in res.certificate.failed and res.certificate.lower_unique
    assert res.stats["method_upper_objective"] == pytest.approx(230.2027, abs=1e-3)
    assert res.upper_objective == pytest.approx(BIPA1_OPTIMUM, abs=3e-3)
    assert res.y["y"][0] == pytest.approx((15 - res.x["x"][0]) / 2, abs=1e-4)


# -- item 5: NaN objective, option validation, NaN data, y <= inf -------------------------------------------
def test_nan_upper_objective_is_never_a_usable_status() -> None:
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=0, ub=1)
    y = p.lower_variable("y", lb=0)
    p.minimize_upper(ca.sqrt(-1 - x ** 2) + y)
    p.minimize_lower((y - x) ** 2)
    res = p.solve("ipopt", starts=1)
    assert res.status not in (bl.Status.SOLVED, bl.Status.INACCURATE)
    assert res.certificate is None or "upper_objective" in res.certificate.failed


@pytest.mark.parametrize("options", [{"starts": 0}, {"starts": -2}, {"gtol": -1.0}, {"max_iter": -1},
                                     {"certificate_tol": float("nan")}])
@pytest.mark.parametrize("method", ["ipopt", "hypergradient"])
def test_common_options_are_validated_before_dispatch(method: str, options: dict) -> None:
    with pytest.raises(ModelError, match="is invalid"):
        bard_511().solve(method, **options)


def test_nan_in_lower_data_is_invalid_data() -> None:
    p = bl.BilevelProblem()
    x = p.upper_variable("x", 2)
    y = p.lower_variable("y", 2)
    p.minimize_upper(ca.sumsqr(x - y))
    p.minimize_lower(ca.sumsqr(y - np.array([1.0, np.nan]) * x))
    with pytest.raises(InvalidData, match="NaN/inf in the data"):
        p.solve()


def test_comparison_with_inf_is_a_model_error() -> None:
    p = bl.BilevelProblem()
    y = p.lower_variable("y")
    with pytest.raises(ModelError, match="bound at infinity"):
        p.lower_constraint(y <= np.inf)


# -- item 6: scaled residuals with the failing row named ---------------------------------------------------
def _big_row_problem(scale: float) -> bl.BilevelProblem:
    p = bl.BilevelProblem()
    x = p.upper_variable("x", lb=0, ub=2)
    y = p.lower_variable("y")
    p.minimize_upper((x - 2) ** 2 + y ** 2)
    p.minimize_lower((y - x) ** 2)
    p.lower_constraint(scale * y <= scale * 1.0, name="cap")
    return p


def test_feasibility_is_scaled_by_the_size_of_the_row() -> None:
    """A row 1e6 (y - 1) <= 0 violated by 1e-4 (y off by 1e-10) passes; the same y error on the unscaled
    row would too, while a violation of 1e-10 relative to the row's size is what is reported."""
    prep = prepare(_big_row_problem(1e6))
    point = prep.lower_point(np.array([2.0]))
    bad = dataclasses.replace(point, y=point.y + 1e-10)
    cert = certify_point(prep.canon, bad)
    assert "lower_feasibility" not in cert.failed
    assert cert.lower_feasibility == pytest.approx(1e-4 / (1 + 1e6), rel=1e-3)


def test_failing_row_is_named() -> None:
    prep = prepare(_big_row_problem(1.0))
    point = prep.lower_point(np.array([2.0]))
    cert = certify_point(prep.canon, dataclasses.replace(point, y=point.y + 0.1))
    assert "lower_feasibility" in cert.failed and cert.worst["lower_feasibility"] == "cap[0]"
    assert "lower_feasibility (cap[0])" in cert.describe_failures()


# -- crashes: psd_factor, the Lyapunov lower level, symmetric variables, JSON ------------------------------
def test_psd_factor_survives_an_ill_conditioned_matrix() -> None:
    """Eigenvalues 1e9, 1, -3 in a random basis (seed 1): Cholesky of the clipped rebuild raised LinAlgError."""
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    m = q @ np.diag([1e9, 1.0, -3.0]) @ q.T
    low, v = lower_triangular("P", 3)
    p = np.asarray(ca.evalf(ca.substitute(low, v, ca.DM(psd_factor(m)))))
    expected = q @ np.diag([1e9, 1.0, 1e-8]) @ q.T
    np.testing.assert_allclose(p @ p.T, expected, atol=1e-6)


A3 = np.array([[1.0, 0.2, 0.0], [0.0, 0.9, 0.3], [0.1, 0.0, 0.8]])
B3 = np.array([[0.0], [0.0], [1.0]])
LYAP_OPTIMUM = 20.401067817758
"""min_K trace(dlyap(A + BK)) + |K|^2, from scipy's solve_discrete_lyapunov and Nelder-Mead (see the test)."""


def lyapunov3(start=None) -> bl.BilevelProblem:
    """Upper gain K (|K| <= 3); lower: the minimum-trace Lyapunov certificate P of A + BK (an SDP)."""
    p = bl.BilevelProblem("lyapunov3")
    K = p.upper_variable("K", (1, 3), lb=-3, ub=3, start=start)
    P = p.lower_variable("P", (3, 3), symmetric=True)
    acl = A3 + B3 @ K
    p.minimize_upper(ca.trace(P) + ca.sumsqr(K))
    p.minimize_lower(ca.trace(P))
    p.lower_psd_constraint(P - acl.T @ P @ acl - np.eye(3))
    return p


@pytest.mark.parametrize("method", ["ipopt", "relaxation"])
def test_lyapunov_lower_level_with_a_stabilizing_start_solves(method: str) -> None:
    res = lyapunov3(start=[[-0.5, -0.5, -0.5]]).solve(method, starts=1)
    assert res.status is bl.Status.SOLVED, res.message
    assert res.upper_objective == pytest.approx(LYAP_OPTIMUM, abs=1e-6)
    K = res.x["K"]
    P_ref = sla.solve_discrete_lyapunov((A3 + B3 @ K).T, np.eye(3))
    np.testing.assert_allclose(res.y["P"], P_ref, atol=1e-6)
    assert res.y["P"].shape == (3, 3)
    cost = lambda k: np.trace(sla.solve_discrete_lyapunov((A3 + B3 @ k).T, np.eye(3))) + np.sum(k ** 2)  # noqa: E731
    assert cost(K) == pytest.approx(LYAP_OPTIMUM, abs=1e-6)
    for e in np.eye(3):  # a local minimum of the reduced cost
        assert cost(K + 1e-3 * e[None, :]) > cost(K) and cost(K - 1e-3 * e[None, :]) > cost(K)


def test_symmetric_lower_variable() -> None:
    p = bl.BilevelProblem()
    P = p.lower_variable("P", (2, 2), symmetric=True, lb=[[0, -1], [-1, 0]])
    assert P.shape == (2, 2) and ca.is_equal(P[0, 1], P[1, 0])
    v = p.lower_variables[0]
    assert v.size == 3 and v.lb.tolist() == [0.0, -1.0, 0.0]
    np.testing.assert_array_equal(v.unflatten([1.0, 2.0, 3.0]), [[1.0, 2.0], [2.0, 3.0]])
    with pytest.raises(ModelError, match="square"):
        p.lower_variable("Q", (2, 3), symmetric=True)


def test_json_is_strict_and_round_trips() -> None:
    res = bipa1().solve("ipopt", starts=1)
    text = res.to_json()
    assert "NaN" not in text and "Infinity" not in text
    json.loads(text)  # strict JSON
    back = BilevelResult.from_json(text)
    assert back.status is res.status and back.upper_objective == res.upper_objective
    np.testing.assert_array_equal(back.y["y"], res.y["y"])
    assert back.certificate.failed == res.certificate.failed
    assert back.certificate.worst == res.certificate.worst
    nan_inside = dataclasses.replace(res, upper_objective=float("nan"), stats={"trace": np.array([1.0, np.inf])})
    d = json.loads(nan_inside.to_json())
    assert d["upper_objective"] is None and d["stats"]["trace"] == [1.0, None]


def test_lyapunov_from_an_unstable_start_is_an_honest_status() -> None:
    """K = 0 leaves A + BK unstable (spectral radius 1.1) and only 6% of K in [-3, 3]^3 stabilize; at an unstable
    gain an indefinite P satisfies the LMI and trace(P) is unbounded below, so the KKT system has no solution: a
    status naming the unbounded lower level (not `infeasible`), with the point kept, never an exception."""
    assert max(abs(np.linalg.eigvals(A3))) == pytest.approx(1.1, abs=1e-9)
    res = lyapunov3().solve("ipopt", starts=2)
    assert res.status is bl.Status.ERROR and not res.success
    assert res.message.startswith("lower level unbounded, not an infeasible problem")
    assert max(abs(np.linalg.eigvals(A3 + B3 @ res.x["K"]))) > 1.0
    assert "lower_gap" in res.certificate.failed and res.x["K"].shape == (1, 3)
