"""Polishing the reference lower-level solve onto its optimal face: optima known by hand, a rejected face,
random QPs with known (often degenerate) optima, and a duality bound on the distance to y*."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bilevel.lower.base import LowerSolution
from bilevel.lower.polish import Lmi, kkt_residual, polish
from bilevel.lower.quadratic import QPData, clarabel_solution, solve_qp_clarabel

DISC_JACOBIAN = np.array([[0.0, 1.0], [1.0, 0.0], [1.0, 0.0], [0.0, -1.0]])
"""d vec(M)/dy (column-major) of M(y) = [[1 + y1, y0], [y0, 1 - y1]], which is >= 0 exactly on the unit disc."""


def qp(P: np.ndarray, q: np.ndarray, A: np.ndarray | None = None, b: np.ndarray | None = None,
       r: float = 0.0) -> QPData:
    """min 1/2 y'Py + q'y + r s.t. A y + b <= 0 (no equalities)."""
    n = q.size
    A = np.zeros((0, n)) if A is None else A
    return QPData(P, q, r, A, np.zeros(0) if b is None else b, np.zeros((0, n)), np.zeros(0))


def disc(t: tuple[float, float]) -> tuple[QPData, tuple[Lmi, ...], np.ndarray, np.ndarray]:
    """Projection of t onto the unit disc as an SDP, with its optimum derived by hand.

    y* = t/|t| and, from stationarity y - t = (2 Z01, Z00 - Z11), Z* = (|t| - 1)/2 (2I - M(y*)) when |t| > 1;
    y* = t and Z* = 0 otherwise (on the circle: not strictly complementary, M(y*) singular and Z* = 0).
    """
    tv = np.asarray(t, dtype=float)
    norm = float(np.linalg.norm(tv))
    y = tv / max(norm, 1.0)
    m = np.array([[1.0 + y[1], y[0]], [y[0], 1.0 - y[1]]])
    z = 0.5 * (norm - 1.0) * (2.0 * np.eye(2) - m) if norm > 1.0 else np.zeros((2, 2))
    return qp(np.eye(2), -tv, r=0.5 * float(tv @ tv)), ((np.eye(2), DISC_JACOBIAN),), y, z


def dual_bound(d: QPData, lmis: tuple[Lmi, ...], sol: LowerSolution) -> float:
    """sqrt(2 (f(y) - q) / m) >= |y - y*| for a feasible y, m = min eig P > 0 and q the Lagrangian dual function.

    y* minimizes f over the feasible set, so f(y) - f(y*) >= grad f(y*)'(y - y*) + m/2 |y - y*|^2 >= m/2 |y - y*|^2,
    and f(y*) >= q(lam, mu, Z) for lam >= 0, Z >= 0 (sol's multipliers projected there). For quadratic f,
    q = r + lam'b + mu'e - sum <Z_k, M_k0> - c'P^-1 c / 2 with c = q + A'lam + E'mu - [sum <Z_k, M_kj>]_j.
    """
    lam = np.maximum(sol.lam, 0.0)
    c, value = d.q + d.A.T @ lam + d.E.T @ sol.mu, d.r + lam @ d.b + sol.mu @ d.e
    for (m0, jac), z in zip(lmis, sol.Z):
        w, v = np.linalg.eigh(0.5 * (z + z.T))
        z_psd = (v * np.maximum(w, 0.0)) @ v.T
        c = c - jac.T @ z_psd.reshape(-1, order="F")
        value -= float(np.sum(z_psd * m0))
    value -= 0.5 * c @ np.linalg.solve(d.P, c)
    f = 0.5 * sol.y @ d.P @ sol.y + d.q @ sol.y + d.r
    return float(np.sqrt(max(2.0 * (f - value) / np.linalg.eigvalsh(d.P).min(), 0.0)))


def lmi_feasibility(lmis: tuple[Lmi, ...], y: np.ndarray) -> float:
    """The smallest eigenvalue over the LMIs at y."""
    return min(float(np.linalg.eigvalsh(m0 + (jac @ y).reshape(m0.shape, order="F")).min()) for m0, jac in lmis)


@pytest.mark.parametrize("t, raw_error", [
    ((1.0, 0.8), 1e-12),   # outside: strictly complementary, Clarabel already accurate to ~1e-11
    ((3.0, -4.0), 1e-11),
    ((0.0, 1.0), 1e-6),    # on the circle: M(y*) singular and Z* = 0, Clarabel off by ~sqrt(its gap)
    ((0.6, 0.8), 1e-6),
])
def test_polish_reaches_the_hand_derived_disc_projection(t: tuple[float, float], raw_error: float) -> None:
    d, lmis, y_star, z_star = disc(t)
    raw = clarabel_solution(d, "disc", lmis)
    pol = polish(d, lmis, raw)
    assert pol.solver == "cvxpy+clarabel+polish" and pol.status == raw.status
    np.testing.assert_allclose(pol.y, y_star, rtol=0, atol=1e-14)
    np.testing.assert_allclose(pol.Z[0], z_star, rtol=0, atol=1e-14)
    assert np.abs(raw.y - y_star).max() > raw_error  # what the polish improves on (measured 8e-12 .. 8e-6)
    assert kkt_residual(d, lmis, pol) < 1e-14 < kkt_residual(d, lmis, raw)
    assert pol.objective == pytest.approx(0.5 * float(np.sum((y_star - np.asarray(t)) ** 2)), rel=1e-14, abs=1e-15)


@pytest.mark.parametrize("t", [(0.0, 1.0), (0.6, 0.8), (1.0, 0.8)])
def test_duality_bound_certifies_the_polished_distance_to_y_star(t: tuple[float, float]) -> None:
    """The bound, computed from the polished point alone, is ~1e-8 and holds; Clarabel's own bound is ~1e-5."""
    d, lmis, y_star, _ = disc(t)
    raw = clarabel_solution(d, "disc", lmis)
    pol = polish(d, lmis, raw)
    assert lmi_feasibility(lmis, pol.y) >= -1e-15  # the bound needs a feasible y (up to rounding here)
    bound = dual_bound(d, lmis, pol)
    assert np.linalg.norm(pol.y - y_star) <= bound + 1e-15 and bound <= 1e-7
    assert lmi_feasibility(lmis, raw.y) >= 0.0 and np.linalg.norm(raw.y - y_star) <= dual_bound(d, lmis, raw)


def test_qp_with_the_minimizer_on_a_constraint_is_polished() -> None:
    """Projection of t onto y0 + y1 <= 1 with t on the line: y* = t, lam* = 0 (not strictly complementary)."""
    t = np.array([0.25, 0.75])
    d = qp(np.eye(2), -t, np.array([[1.0, 1.0]]), np.array([-1.0]))
    raw = clarabel_solution(d, "line")
    sol = solve_qp_clarabel(d, "line")
    assert np.abs(raw.y - t).max() > 1e-6 and raw.lam[0] > 1e-6  # measured 3.5e-6 in both
    assert sol.solver == "clarabel+polish"
    np.testing.assert_array_equal(sol.y, t)
    np.testing.assert_array_equal(sol.lam, [0.0])


def test_face_with_an_inactive_row_is_repaired() -> None:
    """tol = 10 takes the inactive row y0 <= 5 as active; its multiplier comes out < 0, it leaves the face."""
    t = np.array([0.25, 0.75])
    d = qp(np.eye(2), -t, np.array([[1.0, 1.0], [1.0, 0.0]]), np.array([-1.0, -5.0]))
    pol = polish(d, (), clarabel_solution(d, "two rows"), tol=10.0)
    np.testing.assert_array_equal(pol.y, t)
    np.testing.assert_array_equal(pol.lam, [0.0, 0.0])


def test_wrong_face_is_rejected_and_the_solver_point_kept() -> None:
    """min 1e-3 y s.t. 0 <= y <= 1 from an interior-point-like point (y = 1e-5, slack times lam = 1e-8).

    With tol = 1e-7 no row is active: that face has no stationary point (P = 0, residual 1e-3 > 1e-8), so
    the given point is returned unchanged. With tol = 1e-4 the face y = 0 is found exactly.
    """
    d = qp(np.zeros((1, 1)), np.array([1e-3]), np.array([[-1.0], [1.0]]), np.array([0.0, -1.0]))
    sol = LowerSolution(np.array([1e-5]), 1e-8, np.array([1e-3, 0.0]), np.zeros(0), [], "optimal", "test")
    assert kkt_residual(d, (), sol) == pytest.approx(1e-8)
    assert polish(d, (), sol, tol=1e-7) is sol
    right = polish(d, (), sol, tol=1e-4)
    assert right.solver == "test+polish" and kkt_residual(d, (), right) == 0.0
    np.testing.assert_array_equal(right.y, [0.0])
    np.testing.assert_array_equal(right.lam, [1e-3, 0.0])


@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5),
       kinds=st.lists(st.sampled_from(["active", "degenerate", "inactive"]), max_size=9))
def test_random_qp_with_known_optimum_is_polished_to_rounding(seed: int, n: int, kinds: list[str]) -> None:
    """A strongly convex QP built around y* with rows active (lam in [0.1, 2]), degenerate (g = lam = 0) or
    inactive (slack in [0.1, 2]): the polished point has KKT residual <= 1e-11 relative to the data's scale (the
    rounding of a solve on a degenerate face: measured up to 2e-12 absolute with scale ~5, 77 eps x scale over 1,500
    draws), no worse than Clarabel's, and y within 1e-11 of y* (Clarabel alone: up to ~1e-4 on degenerate rows)."""
    rng = np.random.default_rng(seed)
    kind = np.array(kinds, dtype=str)
    R, y_star, A = rng.standard_normal((n, n)), rng.standard_normal(n), rng.standard_normal((kind.size, n))
    lam = np.where(kind == "active", rng.uniform(0.1, 2.0, kind.size), 0.0)
    b = -A @ y_star - np.where(kind == "inactive", rng.uniform(0.1, 2.0, kind.size), 0.0)
    P = R @ R.T + 0.1 * np.eye(n)
    d = qp(P, -P @ y_star - A.T @ lam, A, b)
    with warnings.catch_warnings():  # cvxpy's "may be inaccurate": the residual decides below
        warnings.simplefilter("ignore", UserWarning)
        raw = clarabel_solution(d, "random qp")
    pol = polish(d, (), raw)
    scale = max(1.0, np.abs(P).sum(1).max() * np.abs(y_star).max(), np.abs(d.q).max(),
                float(np.max(np.abs(A).sum(1), initial=0.0)) * np.abs(y_star).max(), float(np.max(np.abs(b), initial=0.0)))
    assert kkt_residual(d, (), pol) <= min(kkt_residual(d, (), raw), 1e-11 * scale)
    np.testing.assert_allclose(pol.y, y_star, rtol=0, atol=1e-11 * (1.0 + np.abs(y_star).max()))
