"""The destabilizing attack on the De Persis–Tesi learners (issue 12): its gradient, its answer (the largest
spectral radius reached), the learner's selections and the command line."""

from __future__ import annotations

import json

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

from bilevel import BilevelProblem, solve
from bilevel.attacks.outcome import unstable
from bilevel.attacks.willems import destabilize_attack, hypergradient_attack
from bilevel.cli import main
from bilevel.experiments.willems_budget import smallest_destabilizing_budget
from bilevel.ddc.plants import batch_reactor
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.implicit import Hypergradient
from bilevel.spectral_radius import spectral_radius
from bilevel.ddc.data import batch_reactor_data
from bilevel.ddc.depersis_tesi import lqr_controller
from bilevel.errors import ModelError
from bilevel.problems import registry
from bilevel.problems.willems import build_attack
from bilevel.problems.willems_instance import WillemsSetting


def test_spectral_radius_gradient_matches_central_differences() -> None:
    """d rho / dM at a random 5 x 5 matrix and at A_id + B_id K (a complex top pair) agrees with central
    differences to 1e-6 relative, entry by entry."""
    attack = build_attack(objective="destabilize", horizon=15, seed=1)
    rng = np.random.default_rng(0)
    for m in (rng.standard_normal((5, 5)), attack.a_id + attack.b_id @ rng.standard_normal((2, 4))):
        r = spectral_radius(m)
        assert r.value == pytest.approx(np.max(np.abs(np.linalg.eigvals(m))), rel=1e-12) and r.ties == 1
        fd = np.zeros_like(m)
        for i in np.ndindex(m.shape):
            e = np.zeros_like(m)
            e[i] = 1e-6
            fd[i] = (spectral_radius(m + e).value - spectral_radius(m - e).value) / 2e-6
        np.testing.assert_allclose(r.gradient, fd, rtol=1e-6, atol=1e-8)


def test_spectral_radius_gradient_has_the_2x2_closed_forms() -> None:
    """2 x 2: a complex pair has rho = sqrt(det M), so d rho / dM = [[d, -c], [-b, a]] / (2 rho); real eigenvalues
    (trace > 0) have rho = t/2 + sqrt(q), q = ((a - d)/2)^2 + b c; a tie lambda = +-1 gives the mean of both
    branches' gradients (Clarke), ties = 2; a stack is evaluated matrix by matrix."""
    a, b, c, d = 0.3, -0.8, 0.5, 0.1
    pair = spectral_radius(np.array([[a, b], [c, d]]))
    rho = np.sqrt(a * d - b * c)
    assert pair.value == pytest.approx(rho, rel=1e-13) and pair.ties == 1
    np.testing.assert_allclose(pair.gradient, np.array([[d, -c], [-b, a]]) / (2 * rho), rtol=1e-12)
    a, b, c, d = 0.9, 0.4, 0.3, 0.2
    real = spectral_radius(np.array([[a, b], [c, d]]))
    root = np.sqrt(((a - d) / 2) ** 2 + b * c)
    assert real.value == pytest.approx((a + d) / 2 + root, rel=1e-13)
    expected = np.array([[0.5 + (a - d) / (4 * root), c / (2 * root)], [b / (2 * root), 0.5 - (a - d) / (4 * root)]])
    np.testing.assert_allclose(real.gradient, expected, rtol=1e-12)
    tie = spectral_radius(np.diag([1.0, -1.0]))
    assert tie.value == 1.0 and tie.ties == 2
    np.testing.assert_allclose(tie.gradient, np.diag([0.5, -0.5]), atol=1e-15)
    stack = spectral_radius(np.stack([np.array([[0.3, -0.8], [0.5, 0.1]]), np.diag([1.0, -1.0])]))
    np.testing.assert_allclose(stack.value, [pair.value, 1.0], rtol=1e-13)
    assert np.isnan(spectral_radius(np.array([[0.5, 1.0], [0.0, 0.5]])).gradient).all()  # defective: no derivative


def test_spectral_objective_on_the_engine_and_refused_by_kkt_methods() -> None:
    """maximize_spectral_radius: the engine's batched F and gradient equal its pointwise evaluation, and solve with
    the hypergradient method reaches rho([[0.5, y0], [y1, 0.2]]) = (0.7 + sqrt(4.09)) / 2 at |x| = 1, y = x; ipopt,
    relaxation and global refuse with a ModelError naming the methods that can."""
    p = BilevelProblem("spectral")
    x = p.upper_variable("x", 2, lb=-1, ub=1)
    y = p.lower_variable("y", 2)
    p.minimize_lower(ca.sumsqr(y - x))
    p.maximize_spectral_radius(ca.vertcat(ca.horzcat(0.5, y[0]), ca.horzcat(y[1], 0.2)))
    res = solve(p, method="hypergradient")
    assert res.upper_objective == pytest.approx((0.7 + np.sqrt(4.09)) / 2, rel=1e-9)
    for method in ("ipopt", "relaxation", "global"):
        with pytest.raises(ModelError, match="'hypergradient' or 'differential-evolution'"):
            solve(p, method=method)
    attack = build_attack(objective="destabilize", horizon=15, seed=1, delta_u=0.3)
    engine = Hypergradient(prepare(attack.radius_problem()))
    xs = 0.3 * np.random.default_rng(3).uniform(-1, 1, (3, 30))
    f, g, ties = engine.spectral_batch(xs.T)
    for i, xi in enumerate(xs):
        ev = engine.evaluate(xi)
        assert f[i] == pytest.approx(ev.F, rel=1e-10)
        np.testing.assert_allclose(g[:, i], engine.gradient(ev)[0], rtol=1e-8, atol=1e-10)


def _fresh_min_norm_radius(attack, du: np.ndarray) -> float:
    """rho(A + B K) of the true plant, K learned from the poisoned data by a fresh cvxpy solve of the appendix SDP
    (reg 1e-8) with Q projected onto the row space of [X0; X1] (the min-norm selection)."""
    x0, x1, u0 = attack.x[:, :-1], attack.x[:, 1:], attack.u + du
    n, t = x0.shape
    q = cp.Variable((t, n))
    s = x0 @ q
    lmi = cp.bmat([[s - np.eye(n), x1 @ q], [(x1 @ q).T, s]])
    cp.Problem(cp.Minimize(cp.trace(s) + 0.5 * attack.setting.reg * cp.sum_squares(q)),
               [s == s.T, 0.5 * (lmi + lmi.T) >> 0]).solve(solver=cp.CLARABEL)
    d = np.vstack([x0, x1])
    qm = np.linalg.pinv(d) @ d @ q.value
    k = u0 @ qm @ np.linalg.inv(0.5 * (x0 @ qm + (x0 @ qm).T))
    plant = batch_reactor()
    return float(np.max(np.abs(np.linalg.eigvals(plant.A + plant.B @ k))))


def test_attack_reports_the_largest_radius_rechecked_by_a_fresh_learner() -> None:
    """N = 15, seed 1, delta_u = 0.3: the point returned has the largest radius over the starts, lies in the box and is
    deterministic; rho recomputed from the returned poisoned inputs by an independent learner solve agrees to 1e-4.
    Measured: rho 1.0214 (unstable) where the log-det attack (8 starts) ends at 0.8212."""
    attack = build_attack(objective="destabilize", horizon=15, seed=1, delta_u=0.3)
    res = destabilize_attack(attack, seed=0)
    assert res.stats["identified_radius"] == pytest.approx(max(res.stats["start_values"]), rel=1e-12)
    assert res.stats["spectral_radius"] == pytest.approx(res.stats["identified_radius"], rel=1e-9)
    assert res.stats["budget_violation"] == 0.0 and np.max(np.abs(res.stats["x"])) == pytest.approx(0.3)
    assert unstable(res) and res.stats["spectral_radius"] == pytest.approx(1.0214, abs=1e-3)
    du, _ = attack.split(res.stats["x"])
    assert _fresh_min_norm_radius(attack, du) == pytest.approx(res.stats["spectral_radius"], rel=1e-4)
    eigen = hypergradient_attack(build_attack(objective="eigen", horizon=15, seed=1, delta_u=0.3), seed=0)
    assert eigen.stats["spectral_radius"] == pytest.approx(0.8212, abs=1e-3)
    again = destabilize_attack(attack, seed=0)
    np.testing.assert_array_equal(again.stats["x"], res.stats["x"])


def test_attack_refuses_another_objective() -> None:
    with pytest.raises(ModelError, match="objective='destabilize'"):
        destabilize_attack(build_attack(objective="eigen", horizon=15))


@pytest.mark.parametrize("selection", ["clarabel", "scs"])
def test_solver_selection_is_the_solvers_own_q(selection: str) -> None:
    """The solver's own Q: the unregularized learner's gain on clean data, with the appendix SDP's value, but a
    different poisoned gain than the min-norm Q (the selection matters under poisoning)."""
    x, u = batch_reactor_data(15, np.random.default_rng(7))
    own = lqr_controller(x, u, input_cost=False, solver=selection)
    attack = build_attack(objective="destabilize", horizon=15, seed=7, delta_u=0.3, selection=selection)
    point = 0.3 * np.random.default_rng(1).choice([-1.0, 1.0], 30)
    gain = attack.loop(point, attack.oracle().evaluate(point).lower.y)[0]
    du, _ = attack.split(point)
    s = x[:, :-1] @ own.q
    np.testing.assert_allclose(gain, (u + du) @ own.q @ np.linalg.inv((s + s.T) / 2), rtol=1e-9, atol=1e-9)
    min_norm = build_attack(objective="destabilize", horizon=15, seed=7, delta_u=0.3)
    assert np.abs(min_norm.loop(point, min_norm.oracle().evaluate(point).lower.y)[0] - gain).max() > 1e-2
    res = destabilize_attack(attack, starts=4, pool=16)  # certified against the regularized re-solve: same SDP value
    assert res.certificate.passed and abs(res.certificate.lower_gap) <= 1e-6
    assert own.value == pytest.approx(lqr_controller(x, u, input_cost=False).value, rel=1e-6)


def test_declared_problem_refuses_the_solvers_own_selection() -> None:
    """The generic route solves the declared regularized SDP: a solver selection there would be silently ignored."""
    with pytest.raises(ModelError, match="exists in the structured attacks only"):
        registry.get("willems-destabilize", selection="scs")


def test_cli_solves_willems_destabilize_with_json(tmp_path, capsys) -> None:
    path = tmp_path / "out.json"
    code = main(["solve", "willems-destabilize", "--param", "delta_u=0.3", "--param", "seed=1", "--starts", "4",
                 "--json", str(path)])
    assert code == 0
    data = json.loads(path.read_text())
    assert data["x"]["Du"] and np.max(np.abs(data["x"]["Du"])) == pytest.approx(0.3, rel=1e-12)
    assert data["method"] == "destabilize" and data["certificate"]["passed"]
    assert data["upper_objective"] == pytest.approx(1.0214, abs=1e-3)  # identified rho = true rho (no noise)
    assert "spectral radius of the true closed loop 1.021" in capsys.readouterr().out
    assert main(["solve", "willems-destabilize", "--param", "budget=1"]) == 2
    assert "--param budget is not one of them (data, delta_u" in capsys.readouterr().err


def test_smallest_destabilizing_budget_brackets_the_first_unstable_budget() -> None:
    """Seed 1, N = 15 (4 starts): the path 0.1, 0.2, 0.3 finds instability at 0.3, bisection narrows it to 5 %;
    the returned budget is an unstable run and a stable run lies within 5 % below it. Measured: 0.2875."""
    found = smallest_destabilizing_budget(WillemsSetting(horizon=15, seed=1), path=(0.1, 0.2, 0.3), starts=4)
    broke = [d for d, rho in found.runs if rho >= 1.0]
    stable = [d for d, rho in found.runs if rho < 1.0]
    assert found.delta == min(broke) == pytest.approx(0.2875)
    assert found.delta - max(d for d in stable if d < found.delta) <= 0.05 * found.delta
    assert smallest_destabilizing_budget(WillemsSetting(horizon=15, seed=1), path=(0.05,), starts=1).delta == np.inf
    with pytest.raises(ModelError, match="increasing and positive"):
        smallest_destabilizing_budget(WillemsSetting(horizon=15), path=(0.3, 0.1))


def test_destabilize_many_equals_one_at_a_time_to_rounding() -> None:
    """Three data sets, two budgets each (a batch above batch.min_size): destabilize_many's results are
    destabilize_attack's: statuses, iterations, evaluations and unstable flags equal, points and radii to rounding
    (stacked complex arithmetic may round differently with a matrix's place in the stack); a non-destabilizing
    attack is refused."""
    from bilevel.attacks.willems import destabilize_many
    atks = [build_attack(objective="destabilize", horizon=15, seed=s, delta_u=d) for s in (1, 2, 3)
            for d in (0.2, 0.6)]
    seeds = [10, 11, 12, 13, 14, 15]
    one = [destabilize_attack(a, seed=s, starts=8, max_iter=15) for a, s in zip(atks, seeds)]
    many = destabilize_many(atks, seeds, starts=8, max_iter=15)
    for a, b in zip(one, many):
        assert (a.status, a.nit, a.stats["evaluations"], unstable(a)) == (b.status, b.nit, b.stats["evaluations"],
                                                                          unstable(b))
        assert np.abs(a.stats["x"] - b.stats["x"]).max() <= 1e-12
        assert b.stats["spectral_radius"] == pytest.approx(a.stats["spectral_radius"], rel=1e-12)
        assert b.stats["identified_radius"] == pytest.approx(a.stats["identified_radius"], rel=1e-12)
    assert len({r.nit for r in one} | {r.stats["evaluations"] for r in one}) > 2  # the counts are per instance
    with pytest.raises(ModelError, match="objective='destabilize'"):
        destabilize_many([build_attack(objective="eigen", horizon=15, seed=1)])
