"""Numeric shortcuts that must give what the long way gives: reverse-sweep Jacobians, eigenvalue-only spectral
radii, diagonal Hessians read without factoring, the constants check over several expressions, the cvxpy re-solve
stated once with Parameters, and the batched box ascent stopping where the projection holds a start still."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from bilevel.errors import InvalidData, NonConvexLowerLevel
from bilevel.lower.convexity import min_eigenvalue, require_psd
from bilevel.lower.quadratic import QPData, clarabel_direct, clarabel_solution
from bilevel.model import check_constants
from bilevel.parameters import ParameterSet, ValueAndJacobian
from bilevel.solvers.engine.ascent import batched_box_ascent
from bilevel.spectral_radius import radius, spectral_radius


def test_reverse_sweep_jacobian_matches_the_symbolic_one() -> None:
    """e(x, y; p) nonlinear in both, with a parameter: value and Jacobian in x and in y as CasADi's jacobian gives."""
    x, y, p = ca.SX.sym("x", 3), ca.SX.sym("y", 2), ca.SX.sym("p", 2)
    params = ParameterSet()
    params.add("p", p, np.array([0.7, -1.3]))
    e = ca.vertcat(ca.sin(x[0]) * y[0] + p[0] * x[1] ** 2, ca.exp(x[2] * y[1]) - p[1] * y[0] * x[0],
                   x[0] * x[1] * x[2] + y[1] ** 3)
    xv, yv = np.array([0.3, -0.8, 1.1]), np.array([0.5, -0.2])
    for wrt, var in ((0, x), (1, y)):
        value, jac = ValueAndJacobian(params, "e", [x, y], e, wrt)(xv, yv)
        ref = ca.Function("ref", [x, y, p], [e, ca.jacobian(e, var)])(xv, yv, params.value)
        np.testing.assert_allclose(value, np.asarray(ref[0]), rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(jac, np.asarray(ref[1]), rtol=1e-13, atol=1e-14)


def test_radius_from_eigenvalues_equals_spectral_radius() -> None:
    m = np.random.default_rng(1).standard_normal((200, 4, 4))
    np.testing.assert_allclose(radius(m), spectral_radius(m).value, rtol=1e-14, atol=0)
    np.testing.assert_allclose(radius(m), np.abs(np.linalg.eigvals(m)).max(axis=-1), rtol=1e-14, atol=0)


def test_diagonal_hessians_are_read_not_factored() -> None:
    d = np.array([3.0, 1e-8, 2.0, 0.0])
    assert min_eigenvalue(np.diag(d)) == 0.0
    np.testing.assert_array_equal(require_psd(np.diag(d), "f", "here"), np.diag(d))
    with pytest.raises(NonConvexLowerLevel, match="eigenvalue -0.5"):
        require_psd(np.diag([1.0, -0.5]), "f", "here")
    full = np.array([[2.0, 1.0], [1.0, 2.0]])  # not diagonal: factored, eigenvalues 1 and 3
    assert min_eigenvalue(full) == pytest.approx(1.0, rel=1e-14)
    np.testing.assert_allclose(require_psd(full, "f", "here"), full, rtol=1e-14)


def test_constants_checked_together_name_the_expression_with_the_nan() -> None:
    x = ca.SX.sym("x", 2)
    clean, dirty = x[0] * 2.5 + x[1], x[1] * ca.DM(np.nan) + x[0]
    check_constants([(clean, "the upper objective"), (clean * 3, "lower constraint 'c'")])
    with pytest.raises(InvalidData, match="lower constraint 'bad' contains the constant nan"):
        check_constants([(clean, "the upper objective"), (dirty, "lower constraint 'bad'")])


def _lmi_qp(seed: int) -> tuple[QPData, tuple]:
    """min q'y + 1/2 eps |y|^2 s.t. [[1 + y0, y1], [y1, 1 - y0]] >= 0 (a disc of radius 1), q random."""
    q = np.random.default_rng(seed).standard_normal(2)
    m0 = np.eye(2)
    jac = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [-1.0, 0.0]])  # vec(M) = vec(M0) + jac y, column-major
    empty = np.zeros((0, 2))
    return QPData(1e-3 * np.eye(2), q, 0.0, empty, np.zeros(0), empty, np.zeros(0)), ((m0, jac),)


def test_recurring_lmi_problems_solved_through_parameters_match_the_direct_solve() -> None:
    """The first solve of a shape is stated with numbers, later ones through the Parameters of one statement: every
    one agrees with Clarabel's direct interface on the optimum (the disc's boundary point against q)."""
    for seed in range(4):
        d, lmis = _lmi_qp(seed)
        via_cvxpy, direct = clarabel_solution(d, "", lmis), clarabel_direct(d, "", False, lmis)
        assert via_cvxpy.objective == pytest.approx(direct.objective, rel=1e-7, abs=1e-9)
        np.testing.assert_allclose(via_cvxpy.y, direct.y, atol=1e-5)
        assert np.linalg.norm(via_cvxpy.y) == pytest.approx(1.0, abs=1e-4)


def test_batched_box_ascent_reaches_the_vertex_and_stops_there() -> None:
    """A linear objective: every start ends at the vertex sign(c) * b, and a start stops once the projection holds it
    still instead of halving its step down to min_step."""
    rng = np.random.default_rng(2)
    b, c = rng.uniform(0.5, 1.5, 6), rng.standard_normal(6)
    values = lambda xs: (xs @ c, np.tile(c, (xs.shape[0], 1)))  # noqa: E731
    x, f, _, evaluations = batched_box_ascent(values, b, rng.uniform(-1.0, 1.0, (5, 6)) * b, 100)
    np.testing.assert_array_equal(x, np.tile(np.sign(c) * b, (5, 1)))
    np.testing.assert_allclose(f, np.abs(c) @ b, rtol=1e-14)
    assert evaluations < 5 * 10  # halving to min_step 1e-6 would take 20 more evaluations per start


def test_batched_box_ascent_rows_climb_as_alone() -> None:
    """Two problems' starts climbing together (indexed values, a bound per row) reach each problem's points, values,
    iterations and evaluations of its own run (group_counts)."""
    from bilevel.solvers.engine.ascent import group_counts
    rng = np.random.default_rng(3)
    centres, bounds = rng.standard_normal((2, 4)), np.array([[0.5] * 4, [2.0] * 4])

    def one(k: int):
        return lambda x: (-np.sum((x - centres[k]) ** 2, axis=1), -2.0 * (x - centres[k]))
    starts = [rng.uniform(-1.0, 1.0, (3, 4)) * bounds[k] for k in range(2)]
    owner = np.repeat([0, 1], 3)

    def values(x, rows):
        f, g = zip(*(one(owner[r])(x[i: i + 1]) for i, r in enumerate(rows)))
        return np.concatenate(f), np.vstack(g)
    counts: dict = {}
    x, f, _, _ = batched_box_ascent(values, np.repeat(bounds, 3, axis=0), np.vstack(starts), 40, indexed=True,
                                    counts=counts)
    for k in range(2):
        xk, fk, it, ev = batched_box_ascent(one(k), bounds[k], starts[k], 40)
        rows = np.flatnonzero(owner == k)
        assert np.array_equal(x[rows], xk) and np.array_equal(f[rows], fk)
        assert group_counts(counts, rows, 40) == (it, ev)
