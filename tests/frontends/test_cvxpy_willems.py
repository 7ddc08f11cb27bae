"""The De Persis-Tesi LQR learner written in cvxpy: the attack on it equals willems-eigen's (5 seeds, 1e-6)."""

from __future__ import annotations

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

import bilevel as bl
from bilevel.ddc.depersis_tesi import state_data
from bilevel.problems.willems import build_attack
from bilevel.problems.willems_instance import DEFAULT_REG, WillemsAttack


def cvxpy_attack(attack: WillemsAttack) -> bl.BilevelProblem:
    """willems-eigen (poison u, design lqr) with the learner as a cvxpy problem, the data as its Parameters."""
    data = state_data(attack.x, attack.u)
    n, horizon = data.x0.shape
    x0, x1 = cp.Parameter((n, horizon), value=data.x0), cp.Parameter((n, horizon), value=data.x1)
    q = cp.Variable((horizon, n))
    s = x0 @ q
    s_sym, m = (s + s.T) / 2, x1 @ q
    learner = cp.Problem(cp.Minimize(cp.trace(attack.qx @ s_sym) + DEFAULT_REG / 2 * cp.sum_squares(q)),
                         [cp.upper_tri(s - s.T) == 0, cp.bmat([[s_sym - np.eye(n), m], [m.T, s_sym]]) >> 0])
    p = bl.BilevelProblem("willems-eigen-cvxpy")
    delta = attack.setting.delta_u
    du = p.upper_variable("Du", data.u0.shape, lb=-delta, ub=delta, start=0.0)
    ll = p.lower_cvxpy(learner)
    gram = ca.mtimes(ca.DM(data.x0), ll[q])
    gain = ca.mtimes(ca.mtimes(ca.DM(data.u0) + du, ll[q]), ca.inv(0.5 * (gram + gram.T)))
    closed_loop = ca.DM(attack.a_id) + ca.mtimes(ca.DM(attack.b_id), gain)
    p.maximize_upper(2 * ca.log(ca.fabs(ca.det(closed_loop))))
    return p


@pytest.mark.parametrize("seed", range(5))
def test_cvxpy_learner_attack_equals_willems_eigen(seed: int) -> None:
    attack = build_attack(horizon=15, seed=seed, delta_u=0.1)
    ours = cvxpy_attack(attack).solve(method="hypergradient", seed=0)
    reference = attack.problem.solve(method="hypergradient", seed=0)
    assert ours.status is bl.Status.SOLVED and ours.certificate.passed, ours.message
    assert "user's problem" in ours.certificate.lower_solver
    assert ours.upper_objective == pytest.approx(reference.upper_objective, abs=1e-6)
    assert np.max(np.abs(ours.x["Du"] - reference.x["Du"])) <= 1e-6
