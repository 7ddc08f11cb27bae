"""What makes the Willems sweeps fast, each against an independent computation: the SDP's numeric KKT system, the
oracle shared across budgets, the affine gain, the reused reference learner, differential evolution and task order."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel.attacks.willems as willems
from bilevel.ddc.plants import batch_reactor
from bilevel.experiments.willems import _reference_learner, _reference_radius, make_plan, paper_tasks
from bilevel.problems.willems import build_attack
from bilevel.solvers.evolution import _others, evolve
from bilevel.vech import vech_sx


def symbolic_kkt(low: object) -> ca.Function:
    """(x, w) -> r, dr/dw, dr/dx of the conic KKT system, by CasADi's symbolic derivatives (written here), at the
    lower level's parameter values (the shared problem's data)."""
    kkt = low.kkt()
    products = [vech_sx(0.5 * (ca.mtimes(m, z) + ca.mtimes(z, m))) for m, z in zip(low.psd, kkt.Z)]
    r = ca.vertcat(kkt.stationarity, kkt.lam * low.g, low.h, *products)
    w = ca.vertcat(low.y, kkt.lam, kkt.mu, *kkt.Z_vech)
    return low.params.function("kkt", [low.x, w], [r, ca.jacobian(r, w), ca.jacobian(r, low.x)])


@pytest.mark.parametrize("params", [dict(design="lqr", poison="u"),
                                    dict(design="lqr-r", poison="xu", delta_x=0.1),
                                    dict(design="stabilizing", poison="xu", delta_x=0.1)])
def test_numeric_conic_kkt_equals_symbolic(params: dict) -> None:
    """SemidefiniteLower's numeric r(w; x) and dr/dw (and its dr/dx) equal CasADi's symbolic ones at random (x, w),
    on one LMI (lqr, stabilizing) and two (lqr-r), to 1e-13 relative."""
    low = build_attack(objective="eigen", horizon=8, seed=3, delta_u=0.1, **params).oracle().low
    reference = symbolic_kkt(low)
    rng = np.random.default_rng(0)
    for _ in range(3):
        x, w = 0.1 * rng.standard_normal(low.n_x), rng.standard_normal(sum(low.conic_kkt.sizes))
        r0, j0, jx0 = (np.asarray(v) for v in reference(x, w))
        r1, j1 = low.conic_kkt.residual(x, w)
        assert np.abs(r1 - r0.ravel()).max() <= 1e-13 * np.abs(r0).max()
        assert np.abs(j1 - j0).max() <= 1e-13 * np.abs(j0).max()
        np.testing.assert_allclose(np.asarray(low.conic_kkt.residual_x(x, w)), jx0, rtol=0, atol=1e-13)


def test_numeric_conic_kkt_with_inequalities() -> None:
    """The lam * g rows too: an SDP with two inequalities and an LMI, numeric against symbolic."""
    from bilevel import BilevelProblem
    from bilevel.solvers.engine.prepared import prepare

    p = BilevelProblem("lmi-and-inequalities")
    x = p.upper_variable("x", 2, lb=-1, ub=1)
    y = p.lower_variable("y", 3)
    p.minimize_upper(ca.sumsqr(y))
    p.minimize_lower(0.5 * ca.sumsqr(y) - ca.dot(ca.vertcat(x, x[0] * x[1]), y))
    p.lower_constraint(y[0] + y[1] <= 1.0 + x[0])
    p.lower_constraint(y[2] >= -0.5)
    p.lower_psd_constraint(ca.SX.eye(2) + y[0] * ca.DM([[0, 1], [1, 0]]) + x[1] * y[2] * ca.DM([[1, 0], [0, -1]]))
    low = prepare(p).canon.lower
    reference = symbolic_kkt(low)
    rng = np.random.default_rng(1)
    x0, w = rng.uniform(-1, 1, 2), rng.standard_normal(sum(low.conic_kkt.sizes))
    r0, j0, _ = (np.asarray(v) for v in reference(x0, w))
    r1, j1 = low.conic_kkt.residual(x0, w)
    assert low.n_g == 2
    np.testing.assert_allclose(r1, r0.ravel(), rtol=0, atol=1e-13)
    np.testing.assert_allclose(j1, j0, rtol=0, atol=1e-13)


def test_a_learner_that_ignores_the_poisoning_is_solved_once_per_role(monkeypatch) -> None:
    """Two destabilizing attacks on one attack: the learner's SDP is solved twice in all (the method's solve and the
    certificate's independent re-solve), and the second attack's answer equals the first's."""
    import bilevel.lower.sdp as sdp

    counts = {"method": 0, "reference": 0}
    raw, faced = sdp.clarabel_direct, sdp.solve_qp_clarabel
    monkeypatch.setattr(sdp, "clarabel_direct",
                        lambda *a, **k: counts.__setitem__("method", counts["method"] + 1) or raw(*a, **k))
    monkeypatch.setattr(sdp, "solve_qp_clarabel",
                        lambda *a: counts.__setitem__("reference", counts["reference"] + 1) or faced(*a))
    attack = build_attack(objective="destabilize", horizon=15, seed=4, delta_u=0.2)
    a = willems.destabilize_attack(attack, starts=8, pool=32)
    b = willems.destabilize_attack(attack, starts=8, pool=32)
    assert counts == {"method": 1, "reference": 1}
    np.testing.assert_array_equal(a.stats["x"], b.stats["x"])
    assert np.abs(a.stats["x"]).max() <= 0.2 + 1e-12 and a.certificate.lower_gap == pytest.approx(0.0, abs=1e-8)


@pytest.mark.parametrize("design", ["lqr", "stabilizing"])
def test_reused_reference_learner_equals_a_fresh_solve(design: str) -> None:
    """The reference radius from the clean data's Q (kept per data set) equals bilevel.ddc's learner solved anew on
    the poisoned data, at random input poisonings."""
    attack = build_attack(objective="eigen", horizon=15, seed=6, delta_u=0.5, design=design)
    plant, rng = batch_reactor(), np.random.default_rng(4)
    for _ in range(3):
        u = attack.u + rng.uniform(-0.5, 0.5, attack.u.shape)
        k = _reference_learner(design, attack.x, u).k
        expected = np.max(np.abs(np.linalg.eigvals(plant.A + plant.B @ k)))
        assert _reference_radius(attack.setting, attack.x, u, attack.u) == pytest.approx(expected, rel=1e-9)


def test_evolution_pairs_and_minimum() -> None:
    """_others draws two distinct indices, both unlike the member; evolve, batched and point by point, reaches the
    minimum 0 of a shifted sphere inside the box and reports its evaluations."""
    rng = np.random.default_rng(0)
    members = np.arange(7).repeat(200)
    r0, r1 = _others(rng, members, 7)
    assert np.all((r0 != members) & (r1 != members) & (r0 != r1)) and set(r0) == set(r1) == set(range(7))
    target = np.array([0.3, -0.2, 0.1])
    for vectorized in (True, False):
        f = (lambda xs: np.sum((xs - target[:, None]) ** 2, axis=0)) if vectorized else \
            (lambda x: float(np.sum((x - target) ** 2)))
        out = evolve(f, -np.ones(3), np.ones(3), np.random.default_rng(1), 200, 10, 1e-12, vectorized=vectorized)
        assert out.fun <= 1e-8 and np.abs(out.x - target).max() <= 1e-4
        assert out.nfev == 30 * (out.nit + 1)


def test_paper_tasks_keep_a_data_set_together() -> None:
    """Every data set's tasks (10 budgets x 3 methods) are consecutive, so a worker's shared oracle serves them."""
    tasks = paper_tasks(make_plan(3, False), 0)
    sets = [(t["horizon"], t["seed"]) for t in tasks]
    runs = [s for i, s in enumerate(sets) if i == 0 or s != sets[i - 1]]
    assert len(runs) == len(set(sets)) == 6 and len(tasks) == 6 * 30


def test_newton_continuation_reaches_the_conic_solution() -> None:
    """State poisoning: continue_from at a point 1e-3 away from a solved one equals Clarabel + Newton polish there
    (Q to 1e-6 relative, far closer than x0's, residual <= 1e-9); from the same solution at a point 0.5 away it gives up
    (None) or returns a point inside the cones at the same residual bound."""
    attack = build_attack(objective="eigen", horizon=15, seed=8, poison="xu", delta_u=0.01, delta_x=0.01)
    low = attack.oracle().low
    rng = np.random.default_rng(5)
    x0 = rng.uniform(-0.01, 0.01, low.n_x)
    x1 = x0 + rng.uniform(-1e-3, 1e-3, low.n_x)
    at0 = low.kkt_newton(x0, low.reference_solve(x0))[0]
    fresh, fresh_residual = low.kkt_newton(x1, low.reference_solve(x1))
    near = low.continue_from(x1, at0)
    assert near is not None and near[1] <= 1e-9 and fresh_residual <= 1e-9
    # both are KKT points at residual <= 1e-9 of an ill-conditioned SDP: they agree to ~1e-8 relative, and how closely
    # depends on the BLAS kernel (1.1e-8 under OpenBLAS Haswell); x0's solution is ~1e-3 away, so 1e-6 tells them apart
    assert np.abs(near[0].y - fresh.y).max() <= 1e-6 * np.abs(fresh.y).max()
    assert np.abs(at0.y - fresh.y).max() > 1e-4 * np.abs(fresh.y).max()
    far = low.continue_from(x1 + 0.5, at0)
    assert far is None or (far[1] <= 1e-9 and low.in_cones(x1 + 0.5, far[0]))


def test_budget_cdf_shows_every_finite_budget() -> None:
    """The delta_u* CDF's x-axis reaches past the largest finite delta_u* (1.25 here), each curve ends at its final
    fraction on the right edge, and a data set never destabilized (inf) keeps its curve below 1."""
    from bilevel.experiments.willems_budget import budget_figure

    rows = [{"horizon": n, "selection": "min-norm", "data_seed": i, "delta_star": v, "attacks": 10}
            for n, values in ((15, [0.3, 0.5, 1.25]), (50, [0.7, 1.0, float("inf")])) for i, v in enumerate(values)]
    ax = budget_figure(rows).axes[0]
    right = ax.get_xlim()[1]
    assert right == pytest.approx(1.05 * 1.25)
    ends = sorted((line.get_xdata()[-1], line.get_ydata()[-1]) for line in ax.get_lines())
    assert ends == [(pytest.approx(right), pytest.approx(2 / 3)), (pytest.approx(right), pytest.approx(1.0))]


def test_reference_re_solve_does_not_depend_on_the_solves_before_it() -> None:
    """The certificate's cvxpy re-solve of the learner's SDP on three data sets, then again in reverse order: the same
    numbers each time (before, cvxpy updated the previous solve's Clarabel solver, whose answer moved by 1e-8 with
    that history), and the optimum Clarabel's direct interface finds."""
    from bilevel.lower.quadratic import clarabel_direct, clarabel_solution

    lows = [build_attack(objective="destabilize", horizon=15, seed=s, delta_u=0.1).oracle(radius=True).low
            for s in (21, 22, 23)]
    data = [(low.data(np.zeros(low.n_x)), low.lmi_data(np.zeros(low.n_x))) for low in lows]
    forward = [clarabel_solution(d, "", lmis) for d, lmis in data]
    backward = [clarabel_solution(d, "", lmis) for d, lmis in data[::-1]][::-1]
    for one, two, (d, lmis) in zip(forward, backward, data):
        np.testing.assert_array_equal(one.y, two.y)
        assert one.objective == pytest.approx(clarabel_direct(d, "", False, lmis).objective, rel=1e-7)


def test_lqr_r_design_tasks_pass_their_certificates() -> None:
    """The first three lqr-r/u design tasks of the plan (the regularized learner's two-LMI SDP, re-solved through
    cvxpy's Parameter statement from the second one on): every certificate passes (at e4da3ae the third failed on
    lower_gap: Clarabel's answer with the zeros cvxpy stores was suboptimal)."""
    from bilevel.experiments import willems as experiment
    from bilevel.threads import single_threaded

    tasks = [t for t in experiment.design_tasks(make_plan(256, False), 0)
             if t["design"] == "lqr-r" and t["poison"] == "u"][:3]
    kept, experiment._REFERENCES = experiment._REFERENCES, {}
    try:
        with single_threaded():
            rows = [experiment.attack_task(t) for t in tasks]
    finally:
        experiment._REFERENCES = kept
    statuses = [r["status"] for r in rows]
    assert all(s in ("solved", "not_locally_optimal", "inaccurate") for s in statuses), statuses


def test_kept_attack_at_a_new_budget_is_a_fresh_attack():
    """kept_attack re-budgets the attack of its declaration (nothing rebuilt): same box, criterion values and result
    as build_attack at that budget; the compiled maps are shared, the declared box follows the budget."""
    from bilevel.attacks.willems import destabilize_attack
    from bilevel.problems.willems import build_attack, kept_attack
    from bilevel.problems.willems_instance import WillemsSetting

    first = kept_attack(WillemsSetting(objective="destabilize", horizon=15, seed=11, delta_u=0.2))
    setting = WillemsSetting(objective="destabilize", horizon=15, seed=11, delta_u=0.5)
    again, fresh = kept_attack(setting), build_attack(setting)
    assert again is not first and again.compiled is first.compiled and again.setting == setting
    np.testing.assert_array_equal(again.budget(), fresh.budget())
    du = next(v for v in again.problem.upper_variables if v.name == "Du")
    assert np.all(du.ub == 0.5) and np.all(du.lb == -0.5)
    ours, theirs = destabilize_attack(again, seed=2, starts=4), destabilize_attack(fresh, seed=2, starts=4)
    np.testing.assert_array_equal(ours.stats["x"], theirs.stats["x"])
    assert ours.stats["spectral_radius"] == theirs.stats["spectral_radius"]
