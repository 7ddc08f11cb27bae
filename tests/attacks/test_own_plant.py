"""docs/own_plant.md runs as shown: its python blocks are executed here, and its printed numbers are checked."""

from __future__ import annotations

import control
import numpy as np

from tests.docs_pages import run_page


def test_own_plant_page_runs_and_prints_what_it_says(tmp_path, monkeypatch) -> None:
    """VRFT: fit, max-min attack with float budgets, step figure, destabilize with ARX orders from the data.
    Willems: the aircraft pitch instance; the generic solve's point re-evaluated here (K = (U0 + Du) Q S^-1 from
    its Du and Q) has the stable loop the page states, the destabilizing attack's an unstable one with nearly the
    same log-det criterion."""
    monkeypatch.chdir(tmp_path)
    namespace = run_page("own_plant.md")
    result, fit = namespace["result"], namespace["fit"]
    theta0 = result.stats["theta_clean"]
    np.testing.assert_allclose(theta0, fit.theta, rtol=1e-9)
    assert result.upper_objective > 2 * result.stats["value_clean"] and result.certificate.passed
    assert np.linalg.norm(result.y["theta"] - theta0) > 0.5 * np.linalg.norm(theta0)
    assert namespace["unstable"].stats["spectral_radius"] > namespace["unstable"].stats["spectral_radius_clean"]
    figure = tmp_path / "own_plant_steps.png"
    assert figure.stat().st_size > 10_000 and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    instance, generic, aircraft = namespace["instance"], namespace["generic"], namespace["aircraft"]
    q, du = generic.y["Q"], generic.x["Du"]
    s = instance.x[:, :-1] @ q
    gain = np.linalg.solve((s + s.T) / 2, ((instance.u + du) @ q).T).T
    assert generic.certificate.passed and np.max(np.abs(du)) <= 0.3 + 1e-9
    assert abs(max(abs(np.linalg.eigvals(aircraft.A + aircraft.B @ gain))) - 0.9845) < 1e-3
    radius = namespace["radius"]
    assert max(abs(np.linalg.eigvals(aircraft.A + aircraft.B @ radius.stats["gain"]))) > 1.2
    # the page's proxy remark: the destabilizing point's log det(Acl Acl') is within 1e-5 below the generic maximum
    log_det = 2 * np.log(abs(np.linalg.det(instance.a_id + instance.b_id @ radius.stats["gain"])))
    assert generic.upper_objective - 1e-5 < log_det < generic.upper_objective


def test_own_plant_identification_and_deepc_sections_check_independently(monkeypatch, tmp_path) -> None:
    """The identification section's attack: [A B] re-fitted by numpy's least squares on the poisoned data, the LQR
    gain from scipy's Riccati solver, the true loop's radius equal to the reported one; the DeePC section's attack:
    DeePC re-solved on the poisoned data by a cvxpy model written here, its plan's true tracking cost equal to the
    reported objective, the poisoning inside the l_inf box."""
    import cvxpy as cp
    import scipy.linalg

    monkeypatch.chdir(tmp_path)
    ns = run_page("own_plant.md")
    ident, ce, motor = ns["ident"], ns["ce"], ns["motor"]
    X, U = ident.signals["X"], ident.signals["U"]
    dX, dU = ce.x["dX"], ce.x["dU"]
    assert np.linalg.norm(dX) <= 0.05 * np.linalg.norm(X) * (1 + 1e-9)
    assert np.linalg.norm(dU) <= 0.05 * np.linalg.norm(U) * (1 + 1e-9)
    Xp, Up = X + dX, U + dU
    theta = np.linalg.lstsq(np.vstack([Xp[:, :-1], Up]).T, Xp[:, 1:].T, rcond=None)[0].T
    np.testing.assert_allclose(theta, ce.y["theta"], atol=1e-8)
    a_hat, b_hat = theta[:, :2], theta[:, 2:]
    P = scipy.linalg.solve_discrete_are(a_hat, b_hat, np.eye(2), np.eye(1))
    K = -np.linalg.solve(np.eye(1) + b_hat.T @ P @ b_hat, b_hat.T @ P @ a_hat)
    A, B = motor.state_space
    assert abs(max(abs(np.linalg.eigvals(A + B @ K))) - ce.upper_objective) < 1e-8

    deepc, attack = ns["deepc"], ns["plan_attack"]
    du, dy = attack.x["du"], attack.x["dy"]
    assert np.max(np.abs(du)) <= 0.05 * np.max(np.abs(deepc.u)) * (1 + 1e-9)
    assert np.max(np.abs(dy)) <= 0.05 * np.max(np.abs(deepc.y)) * (1 + 1e-9)
    depth, k, N = deepc.t_ini + deepc.horizon, deepc.t_ini, deepc.horizon
    cols = deepc.u.size - depth + 1
    Hu = np.array([deepc.u[j:j + cols] + du[j:j + cols] for j in range(depth)])
    Hy = np.array([deepc.y[j:j + cols] + dy[j:j + cols] for j in range(depth)])
    g, u, y, s = cp.Variable(cols), cp.Variable(N), cp.Variable(N), cp.Variable(k)
    cost = (deepc.q * cp.sum_squares(y - deepc.reference) + deepc.r_weight * cp.sum_squares(u)
            + deepc.lambda_g * cp.sum_squares(g) + deepc.lambda_y * cp.norm1(s))
    cp.Problem(cp.Minimize(cost), [Hu[:k] @ g == deepc.past_u[-k:], Hy[:k] @ g == deepc.past_y[-k:] + s,
                                   Hu[k:] @ g == u, Hy[k:] @ g == y]).solve(solver=cp.CLARABEL)
    impulse = np.array(control.impulse_response(deepc.plant, T=np.arange(N)).outputs).ravel()
    step = scipy.linalg.toeplitz(impulse, np.zeros(N))  # the plant starts at rest (its past is zero here)
    error = step @ u.value - deepc.reference
    tracking = deepc.q * error @ error + deepc.r_weight * u.value @ u.value
    assert abs(tracking - attack.upper_objective) <= 1e-5 * attack.upper_objective
