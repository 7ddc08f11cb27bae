"""Many instances at once (bilevel.solvers.batch.solve_many, the batched alternating VRFT attack): every instance's
result equals the one-at-a-time result, bit for bit where the arithmetic is the same (batch size below
defaults["batch.min_size"], instances the batched form leaves alone, the stacked filters) and otherwise to rounding:
statuses and iteration counts equal, attacker values within 1e-7 relative, theta within 1e-6 (the batched QR, triangular
solves and trust-region Newton sum in another order; measured: 3e-9 and 1e-8)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import bilevel as bl
from bilevel.attacks.vrft_batch import attack_budget_paths, attack_many
from bilevel.attacks.vrft_methods import attack, attack_budget_path
from bilevel.errors import UnknownOption
from bilevel.lower.least_squares import thin_qr
from bilevel.model import BilevelProblem
from bilevel.problems.budget import Budget
from bilevel.problems.vrft_instance import attack_instance
from bilevel.solvers.batch import solve_many
from bilevel.solvers.engine.ascent import projected_ascent
from bilevel.solvers.engine.batch_ascent import batched_projected_ascent
from bilevel.solvers.engine.batch_linalg import (inverse_upper, maximize_quadratics_on_balls, project_l2_balls,
                                                 r_factor_batch, solve_upper)
from bilevel.solvers.engine.projections import NormBall
from bilevel.solvers.engine.trust_region import maximize_quadratic_on_ball

VALUE_RTOL, THETA_ATOL = 1e-7, 1e-6


def _same(single, many, exact: bool = False) -> None:
    """The per-instance results agree: statuses, iterations, values and theta (bit for bit where `exact`)."""
    assert [r.status for r in single] == [r.status for r in many]
    assert [r.nit for r in single] == [r.nit for r in many]
    for a, b in zip(single, many):
        if exact:
            assert a.stats["value"] == b.stats["value"] and np.array_equal(a.y["theta"], b.y["theta"])
        else:
            assert abs(a.stats["value"] - b.stats["value"]) <= VALUE_RTOL * abs(a.stats["value"])
            np.testing.assert_allclose(a.y["theta"], b.y["theta"], rtol=0, atol=THETA_ATOL)
        assert a.certificate.passed == b.certificate.passed


def _instances(objective: str = "maxmin", convention: str = "paper", n: int = 128) -> list:
    return [attack_instance(objective, "B", eu, ey, seed, n, convention)
            for seed in (1, 2, 3) for eu in (0.0, 0.2) for ey in (0.01, 0.057)]


def test_trust_region_batch_equals_one_at_a_time() -> None:
    """Convex (on the sphere), concave with the maximizer inside or on the sphere, zero radius, the hard case."""
    rng = np.random.default_rng(0)
    A, b, delta = [], [], []
    for i in range(40):
        M = rng.standard_normal((6, 6))
        A.append((M @ M.T) * (1 if i % 2 else -1))
        b.append(rng.standard_normal(6) * (0.01 if i % 5 == 0 else 1.0))
        delta.append(0.0 if i == 7 else rng.uniform(0.1, 3.0))
    A.append(np.diag([3.0, 1.0, 0, 0, 0, 0]))  # hard case: b orthogonal to the top eigenvector
    b.append(np.array([0.0, 1.0, 0, 0, 0, 0]))
    delta.append(2.0)
    A, b, delta = np.array(A), np.array(b), np.array(delta)
    out = maximize_quadratics_on_balls(A, b, delta)
    for i in range(len(A)):
        np.testing.assert_allclose(out[i], maximize_quadratic_on_ball(A[i], b[i], delta[i]), rtol=0, atol=1e-10)


def test_triangular_solves_and_ball_projection() -> None:
    rng = np.random.default_rng(1)
    R = np.triu(rng.standard_normal((5, 6, 6))) + 4 * np.eye(6)
    rhs = rng.standard_normal((5, 6))
    for i in range(5):
        np.testing.assert_allclose(solve_upper(R, rhs)[i], np.linalg.solve(R[i], rhs[i]), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(inverse_upper(R)[i], np.linalg.inv(R[i]), rtol=1e-12, atol=1e-12)
    D, radius = rng.standard_normal((5, 9)), np.array([0.5, 10.0, 1.0, 0.0, 2.0])
    for i, row in enumerate(project_l2_balls(D, radius)):
        np.testing.assert_allclose(row, NormBall(radius[i])(D[i]), rtol=1e-15, atol=1e-15)


def test_r_factor_is_householders() -> None:
    """R, R^{-1} and Q'd of each C (well and ill conditioned, rank deficient, NaN) as the one-instance thin_qr gives
    them, to rounding (geqrf on [C d] rather than on C, Q'd from its last column)."""
    rng = np.random.default_rng(2)
    C = rng.standard_normal((6, 200, 6)) * np.array([1.0, 1e-1, 1e-2, 1.0, 3.0, 1.0])
    C[3, :, 5] = C[3, :, 4] + 1e-7 * rng.standard_normal(200)  # cond ~1e8
    C[4, :, 5] = C[4, :, 4]  # rank deficient
    C[5, 7, 2] = np.nan
    d = rng.standard_normal((6, 200))
    R, R_inv, Qd = r_factor_batch(C, d)
    for i in range(5):
        Q, Rh = thin_qr(C[i])
        np.testing.assert_allclose(R[i], Rh, rtol=0, atol=1e-13 * np.abs(Rh).max())
        if i < 4:  # Q'd's last entry to rounding times cond(C) (1e8 for C[3]; rank deficient C[4]: noise)
            np.testing.assert_allclose(Qd[i], Q.T @ d[i], rtol=0, atol=1e-13 if i < 3 else 1e-7)
            np.testing.assert_allclose(R_inv[i] @ R[i], np.eye(6), rtol=0, atol=1e-12 if i < 3 else 1e-6)
    assert np.array_equal(R_inv[5], np.eye(6)) and not np.all(np.isfinite(R[5]))


@pytest.mark.parametrize("convention", ["paper", "raw-drop"])
def test_stacked_filters_are_bit_identical(convention: str) -> None:
    """The regressor's adjoint and targets on stacked signals equal the one-signal maps exactly."""
    reg = attack_instance("maxmin", "B", 0.1, 0.05, 1, 128, convention).setting.regressor
    rng = np.random.default_rng(2)
    G, U = rng.standard_normal((4, reg.rows(128), 6)), rng.standard_normal((4, 128))
    for i in range(4):
        assert np.array_equal(reg.stack_adjoint(G)[i], reg.adjoint(G[i]))
        assert np.array_equal(reg.stack_targets(U)[i], reg.targets(U[i]))


def test_batched_ascent_follows_the_one_instance_loop() -> None:
    """A concave quadratic on a ball per row: the lockstep loop takes the single loop's steps (same iterations and
    stop reason; the evaluations too, but for the last line searches, where the gains sit at the rounding of f)."""
    rng = np.random.default_rng(3)
    m, n = 6, 8
    H = np.array([-(M @ M.T) - np.eye(n) for M in rng.standard_normal((m, n, n))])
    c, radius = 5 * rng.standard_normal((m, n)), rng.uniform(0.5, 2.0, m)

    def value(rows, X):
        f = np.einsum("mi,mi->m", c[rows], X) + 0.5 * np.einsum("mi,mij,mj->m", X, H[rows], X)
        return f, {"x": X}

    def direction(rows, p):
        g = c[rows] + np.einsum("mij,mj->mi", H[rows], p["x"])
        return g, g * (radius[rows, None] / np.linalg.norm(g, axis=1, keepdims=True))

    X0 = rng.standard_normal((m, n))
    res = batched_projected_ascent(value, direction, lambda rows, X: project_l2_balls(X, radius[rows]), X0, radius,
                                   200, 1e-10)
    for i in range(m):
        f1 = lambda x, i=i: value(np.array([i]), x[None])[0][0]  # noqa: E731
        why: dict = {}
        x, fx, _, it, evals, conv = projected_ascent(
            lambda x: (f1(x), x), lambda x: tuple(a[0] for a in direction(np.array([i]), {"x": x[None]})),
            NormBall(radius[i]), X0[i], radius[i], 200, 1e-10, [], why=why)
        assert (it, conv, why["stop"]) == (res.iterations[i], res.converged[i], res.why[i])
        assert abs(evals - res.evaluations[i]) <= 3
        np.testing.assert_allclose(res.x[i], x, rtol=0, atol=1e-7)
        assert abs(res.f[i] - fx) <= 1e-12 * abs(fx)


def test_attack_many_equals_one_at_a_time() -> None:
    atks = _instances()
    _same([attack(a, "alternating") for a in atks], attack_many(atks))


def test_attack_many_with_random_starts() -> None:
    """starts=3: the conditioning start, zero poisoning and a seeded sphere point per instance (its own seed). Zero
    poisoning is a stationary point of the attacker's objective, so the ascent from it follows the gradient's rounding
    and may end elsewhere (measured: 0.0320 one at a time, 0.0311 batched; the best values 1.8e-7 apart under one
    OpenBLAS kernel and 1.05e-6 under another, where zero poisoning's start won): the other starts agree as always, and
    each best value is its own starts' best and at least the agreeing starts' best."""
    atks = _instances()[:6]
    seeds = [11, 12, 13, 14, 15, 16]
    single = [attack(a, "alternating", starts=3, seed=s) for a, s in zip(atks, seeds)]
    many = attack_many(atks, seeds=seeds, starts=3)
    assert [r.status for r in single] == [r.status for r in many]
    for a, b in zip(single, many):
        for k in (0, 2):  # the conditioning start and the random one
            ra, rb = a.start_records[k], b.start_records[k]
            assert ra["iterations"] == rb["iterations"]
            assert abs(ra["objective"] - rb["objective"]) <= VALUE_RTOL * abs(ra["objective"])
        for r in (a, b):
            objectives = [rec["objective"] for rec in r.start_records]
            assert len(objectives) == 3 and np.isfinite(objectives[1])
            assert r.stats["value"] >= max(objectives[0], objectives[2]) * (1 - VALUE_RTOL)
            assert abs(r.stats["value"] - max(objectives)) <= VALUE_RTOL * abs(r.stats["value"])


def test_attack_many_with_target_maps() -> None:
    """The raw convention (the learner's prefilter: the target block's isometric coordinates) and dropped rows."""
    atks = _instances(convention="raw-drop")
    _same([attack(a, "alternating") for a in atks], attack_many(atks))


def test_attack_many_targeted() -> None:
    """A concave objective: the trust-region step's interior maximizer."""
    atks = _instances("targeted")[:6]
    _same([attack(a, "alternating", max_iter=40) for a in atks], attack_many(atks, max_iter=40))


def test_batch_below_min_size_is_the_single_path() -> None:
    """Batch size 1 (and anything below defaults["batch.min_size"]) runs `solve` itself: bit-identical."""
    atks = _instances()[:3]
    _same([attack(a, "alternating") for a in atks], attack_many(atks), exact=True)
    _same([attack(atks[0], "alternating")], attack_many(atks[:1]), exact=True)


def test_instances_the_batch_leaves_alone_run_alone() -> None:
    """A sparse output budget (a set the declaration relaxes) has no batched form: that instance is the single path's,
    bit for bit, the others batched."""
    atks = _instances()[:5]
    atks[2] = dataclasses.replace(atks[2], budget_y=Budget(0.05, "l2", 0.5))
    many, single = attack_many(atks), [attack(a, "alternating") for a in atks]
    _same(single, many)
    _same(single[2:3], many[2:3], exact=True)


def test_budget_paths_equal_one_at_a_time() -> None:
    atks = [attack_instance("maxmin", "B", 0.1, 0.01, seed, 128) for seed in (1, 2, 3, 4)]
    eps = [0.01, 0.037, 0.057]
    paths = attack_budget_paths(atks, eps, seeds=[5, 6, 7, 8])
    for atk, seed, path in zip(atks, (5, 6, 7, 8), paths):
        _same(attack_budget_path(atk, eps, seed=seed), path)


def test_solve_many_without_a_batched_form_is_solve() -> None:
    """Parameter values as mappings on a generic problem: solve at each, bit for bit."""
    p = BilevelProblem("param-qp")
    x, y, c = p.upper_variable("x", 1, lb=-2, ub=2), p.lower_variable("y", 1), p.parameter("c")
    p.minimize_upper((x - 1) ** 2 + (y - c) ** 2)
    p.minimize_lower((y - x) ** 2)
    values = [{"c": v} for v in (0.0, 0.5, 1.5, -1.0, 2.0)]
    many = solve_many(p, values, "hypergradient", starts=1)
    for v, r in zip(values, many):
        p.set_value("c", v["c"])
        one = bl.solve(p, "hypergradient", starts=1)
        assert one.status == r.status and one.upper_objective == r.upper_objective


def test_per_instance_options_and_bad_counts() -> None:
    atks = _instances()[:4]
    with pytest.raises(bl.ModelError, match="seeds"):
        attack_many(atks, seeds=[1, 2])
    with pytest.raises(UnknownOption, match="bogus"):
        attack_many(atks, bogus=1)
    with pytest.raises(bl.ModelError, match="per-instance"):
        solve_many(BilevelProblem("p"), [{}, {}], "hypergradient", each=[{}])


@pytest.mark.parametrize("convention", ["paper", "raw"])
def test_fits_from_summed_signals_equal_gathered_regressors(convention: str) -> None:
    """Where the regressors are lags of one signal, a fit's C0 + R(b) formed as the lags of the summed signals (S0) is
    the gathered C0 plus R(b) bit for bit, and so is its theta."""
    from bilevel.attacks.vrft_batch import _learner
    atks = _instances(convention=convention)
    learner = _learner(atks)
    assert learner.S0 is not None
    plain = dataclasses.replace(learner, S0=None)
    rows, B = np.array([5, 0, 3]), 0.01 * np.random.default_rng(4).standard_normal((3, learner.n_b))
    a, b = learner.fit(rows, None, B), plain.fit(rows, None, B)
    assert np.array_equal(a.C, b.C) and np.array_equal(a.theta, b.theta)
