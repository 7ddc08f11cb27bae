"""Model-based attack objectives of ident-ss: the identified model's H2 norm ("h2") and the true closed loop's spectral
radius under the certainty-equivalence LQR gain ("ce-lqr"). Values against scipy computations written here, the
engine's hypergradient against central differences of the whole attack objective over the poisoning, and attacks
against random poisoning of the same budget."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from bilevel.ddc.model_based import CertaintyEquivalenceRadius, H2Norm
from bilevel.errors import ModelError
from bilevel.problems import registry
from bilevel.problems.identification import declare
from bilevel.problems.identification_instance import attack_instance
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.implicit import hypergradient

Q_WEIGHT, R_WEIGHT = 1.0, 0.5


def refit(X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """[A B] by np.linalg.lstsq on [X_t; U_t] -> X_{t+1}."""
    T = U.shape[1]
    return np.linalg.lstsq(np.vstack([X[:, :T], U]).T, X[:, 1:T + 1].T, rcond=None)[0].T


def h2(theta: np.ndarray) -> float:
    """sqrt(trace P), P = A P A' + B B' (scipy's dlyap)."""
    n = theta.shape[0]
    A, B = theta[:, :n], theta[:, n:]
    return float(np.sqrt(np.trace(scipy.linalg.solve_discrete_lyapunov(A, B @ B.T))))


def ce_radius(theta: np.ndarray, plant: tuple[np.ndarray, np.ndarray]) -> float:
    """rho(A_true + B_true K), K the LQR gain of the model theta = [A B] from scipy's DARE (Q = q I, R = r I)."""
    n = theta.shape[0]
    A, B = theta[:, :n], theta[:, n:]
    R = R_WEIGHT * np.eye(B.shape[1])
    P = scipy.linalg.solve_discrete_are(A, B, Q_WEIGHT * np.eye(n), R)
    K = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    return float(np.abs(np.linalg.eigvals(plant[0] + plant[1] @ K)).max())


def objective(atk, x: np.ndarray) -> float:
    """The attack objective at the flat poisoning x = [vec dX; vec dU] (column-major), computed independently."""
    X, U = atk.signals["X"], atk.signals["U"]
    dX = x[:X.size].reshape(X.shape, order="F")
    dU = x[X.size:].reshape(U.shape, order="F")
    theta = refit(X + dX, U + dU)
    return h2(theta) if atk.objective == "h2" else ce_radius(theta, atk.setting.state_space)


def instance(objective_name: str, eps: float, seed: int = 0):
    return attack_instance("ss", T=100, eps=eps, objective=objective_name, seed=seed, lqr_weights=(Q_WEIGHT, R_WEIGHT))


def random_poisoning(atk, rng: np.random.Generator) -> np.ndarray:
    """A poisoning on the budget's boundary in a random direction, per signal."""
    parts = []
    for name in ("X", "U"):
        d = rng.standard_normal(atk.signals[name].size)
        parts.append(d * atk.radius(name) / np.linalg.norm(d))
    return np.concatenate(parts)


@pytest.mark.parametrize("objective_name", ["h2", "ce-lqr"])
def test_value_and_hypergradient_match_scipy_and_central_differences(objective_name: str) -> None:
    atk = instance(objective_name, eps=0.01)
    prep = prepare(declare(atk))
    rng = np.random.default_rng(3)
    x = 0.5 * random_poisoning(atk, rng)
    phi, grad, _ = hypergradient(prep, x)
    assert -phi == pytest.approx(objective(atk, x), rel=1e-9)  # maximized: phi is its negative
    for _ in range(3):
        d = rng.standard_normal(x.size)
        d /= np.linalg.norm(d)
        h = 1e-5
        fd = (objective(atk, x + h * d) - objective(atk, x - h * d)) / (2 * h)
        assert -grad @ d == pytest.approx(fd, rel=1e-4, abs=1e-6 * np.linalg.norm(grad))


def test_matrix_functions_agree_with_scipy_on_the_clean_model() -> None:
    atk = instance("ce-lqr", eps=0.01)
    A, B = atk.setting.state_space
    value, _ = H2Norm()(atk.theta0)
    assert value == pytest.approx(h2(atk.theta0), rel=1e-10)
    ce = CertaintyEquivalenceRadius(Q_WEIGHT * np.eye(4), R_WEIGHT * np.eye(1))
    value, _ = ce(np.hstack([atk.theta0, A, B]))
    assert value == pytest.approx(ce_radius(atk.theta0, (A, B)), rel=1e-10)
    assert value < 0.7  # the clean certainty-equivalence loop is well damped
    unstable = np.hstack([1.01 * np.eye(4), np.ones((4, 1))])
    assert H2Norm()(unstable)[0] == np.inf


@pytest.mark.parametrize("objective_name,eps", [("h2", 0.01), ("ce-lqr", 0.05)])
def test_attack_beats_random_poisoning_and_ce_lqr_destabilizes_the_true_loop(objective_name: str, eps: float) -> None:
    atk = instance(objective_name, eps=eps)
    result = declare(atk).solve(starts=1, seed=0)
    assert result.method == "hypergradient" and result.status.value == "solved", result.message
    x = np.concatenate([np.ravel(result.x["dX"], order="F"), np.ravel(result.x["dU"], order="F")])
    for name, part in (("X", x[:atk.signals["X"].size]), ("U", x[atk.signals["X"].size:])):
        assert np.linalg.norm(part) <= atk.radius(name) * (1 + 1e-9)
    value = objective(atk, x)
    assert result.upper_objective == pytest.approx(value, rel=1e-8)
    rng = np.random.default_rng(0)
    best_random = max(objective(atk, random_poisoning(atk, rng)) for _ in range(20))
    clean = objective(atk, np.zeros_like(x))
    assert value - clean > 5 * (best_random - clean) > 0
    if objective_name == "ce-lqr":
        assert clean < 0.7 and value > 1.1  # the identified model's LQR gain destabilizes the true plant


def test_registered_and_refused_where_it_cannot_apply() -> None:
    problem = registry.get("ident-ss", T=100, eps=0.01, objective="ce-lqr", q=Q_WEIGHT, r=R_WEIGHT)
    with pytest.raises(ModelError, match="numeric objective of a matrix.*hypergradient"):
        problem.solve("ipopt")
    with pytest.raises(ModelError, match="state-space model"):
        attack_instance("arx", objective="h2")
    with pytest.raises(ModelError, match="lqr_weights"):
        attack_instance("ss", objective="ce-lqr", lqr_weights=(1.0, 0.0))


def test_matrix_function_objective_on_a_small_box_problem() -> None:
    """maximize_matrix_function on y = x + c over the box [-1, 1]^2 with f(M) = ||M||_F^2 given numerically: the
    maximizer is the corner sign(c), value 1.3^2 + 1.2^2, for hypergradient and differential-evolution alike."""
    import casadi as ca

    from bilevel.model import BilevelProblem

    p = BilevelProblem("box")
    x = p.upper_variable("x", 2, lb=-1, ub=1)
    y = p.lower_variable("y", 2)
    p.minimize_lower(ca.sumsqr(y - x - ca.DM([0.3, -0.2])))
    p.maximize_matrix_function(y, lambda m: (float(np.sum(m ** 2)), 2 * m))
    for method in ("hypergradient", "differential-evolution"):
        result = p.solve(method, seed=0)
        assert result.upper_objective == pytest.approx(1.3 ** 2 + 1.2 ** 2, rel=1e-8), method
        np.testing.assert_allclose(result.x["x"], [1, -1], atol=1e-8)
    with pytest.raises(ModelError, match="callable"):
        p.maximize_matrix_function(y, "not a function")


def test_h2_attack_that_destabilizes_the_model_says_the_supremum_is_unbounded() -> None:
    """Once the poisoning can make the identified A unstable, the H2 norm has no finite maximum: the ascent reaches an
    unstable model (the true refit there has spectral radius >= 1) and its message says so, not that the objective
    is not differentiable."""
    atk = attack_instance("ss", T=30, eps=0.05, objective="h2", seed=0)
    result = declare(atk).solve(starts=1, seed=0)
    assert result.status.value == "error" and result.upper_objective == np.inf
    assert "identified model became unstable" in result.message and "supremum is unbounded" in result.message
    assert "not differentiable" not in result.message
    X, U = atk.signals["X"], atk.signals["U"]
    theta = refit(X + result.x["dX"].reshape(X.shape), U + result.x["dU"].reshape(U.shape))
    assert max(abs(np.linalg.eigvals(theta[:, :X.shape[0]]))) >= 1.0
