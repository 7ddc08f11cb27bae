"""A faithful paper-style baseline of the VRFT max-min attack (Russo & Proutiere, Algorithm 1).

a_u-step: DCCP (Shen et al. 2016, the `dccp` package on cvxpy) maximizing the convex learner loss over
the l2 ball, from a random start, as the paper describes; a_y-step: fixed-step projected gradient ascent
(PGA) with the paper's hypergradient; stop when |J(i+1) - J(i)| < eta. The step is a fixed fraction
gamma of the budget along the normalized gradient (the paper leaves the step rule to tuning).
"""

from __future__ import annotations

import cvxpy as cp
import dccp  # noqa: F401  (registers the "dccp" solve method on cvxpy problems)
import numpy as np

from bilevel.attacks.vrft_methods import attack
from bilevel.problems.vrft_instance import VRFTAttack
from bilevel.reduction import KKTPoint
from bilevel.result import BilevelResult, Status
from bilevel.solvers.engine.prepared import MethodRun, Prepared


def dccp_input_step(atk: VRFTAttack, a_y: np.ndarray, seed: int) -> np.ndarray:
    """max_a (1/n)||t0 - Phi0 P'(t' + targets(a))||^2 s.t. ||a||_2 <= delta_u, by DCCP (prefiltered data)."""
    s = atk.learner.fit(np.zeros(atk.N), a_y)
    pinv = np.linalg.solve(s.R, s.Q.T)  # theta' = pinv @ target'
    a = cp.Variable(atk.N)
    rows = atk.n
    theta = pinv @ (s.d + a[:rows])
    prob = cp.Problem(cp.Maximize(cp.sum_squares(atk.t0 - atk.phi0 @ theta) / rows), [cp.norm(a, 2) <= atk.delta_u])
    prob.solve(method="dccp", solver=cp.CLARABEL, seed=seed)  # seeded random initial point: reproducible
    return np.zeros(atk.N) if a.value is None else np.asarray(a.value).ravel()


def paper_baseline(atk: VRFTAttack, seed: int = 0, eta: float = 1e-4, pga_steps: int = 10, gamma: float = 0.1,
                   max_outer: int = 20) -> BilevelResult:
    """Algorithm 1 as published: alternate a DCCP a_u-step and `pga_steps` fixed-step PGA steps on a_y."""
    if atk.objective != "maxmin" or atk.setting.data != "prefiltered":
        raise ValueError("the paper-style baseline covers the max-min attack on prefiltered data")

    def paper_baseline_method(prep: Prepared, **options: object) -> MethodRun:
        proj = atk.budget_y.projection(atk.y)
        a_u, a_y = np.zeros(atk.N), np.zeros(atk.N)
        J = atk.value(atk.learner.fit(a_u, a_y).theta)
        history, it, converged = [], 0, False
        for it in range(1, max_outer + 1):
            a_u = dccp_input_step(atk, a_y, seed + it)
            for _ in range(pga_steps):
                s = atk.learner.fit(a_u, a_y)
                g = atk.learner.gradient(s, atk.grad_theta(s.theta))[1]
                norm = np.linalg.norm(g)
                if norm == 0:
                    break
                a_y = proj(a_y + gamma * atk.delta_y * g / norm)
            J_new = atk.value(atk.learner.fit(a_u, a_y).theta)
            history.append({"iter": it, "value": J_new})
            if abs(J_new - J) < eta:
                J, converged = J_new, True
                break
            J = J_new
        theta = atk.learner.fit(a_u, a_y).theta
        return MethodRun(prep.pack(KKTPoint(np.concatenate([a_u, a_y]), theta, np.zeros(0), np.zeros(0), [])),
                         Status.SOLVED if converged else Status.MAX_ITERATIONS,
                         "converged" if converged else "max_outer reached", it, history,
                         [{"start": 0, "iterations": it, "evaluations": it * (pga_steps + 1)}])

    return attack(atk, paper_baseline_method)
