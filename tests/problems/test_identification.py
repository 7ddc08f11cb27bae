"""Identification attacks (ident-ss, ident-arx): certified, the poisoned learner's answer is a numpy refit of the
poisoned data, budgets hold, stealthy attacks keep the residual tests' statistics within delta of the clean ones."""

from __future__ import annotations

import numpy as np
import pytest

from bilevel.ddc.plants import flexible_transmission
from bilevel.ddc.residual_tests import regression_tests
from bilevel.errors import InvalidData, ModelError
from bilevel.problems import registry
from bilevel.problems.identification import STATISTICS, declare, load_instance, statistics_functions
from bilevel.problems.identification_instance import attack_instance, controllable_canonical


def ss_refit(X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """[A B] by np.linalg.lstsq on [X_t; U_t] -> X_{t+1}, written out here."""
    T = U.shape[1]
    return np.linalg.lstsq(np.vstack([X[:, :T], U]).T, X[:, 1:T + 1].T, rcond=None)[0].T


def arx_rows(u: np.ndarray, y: np.ndarray, na: int, nb: int) -> tuple[np.ndarray, np.ndarray]:
    """The ARX regression written sample by sample: y_t against [-y_{t-1..t-na}, u_{t-1..t-nb}], t >= max(na, nb)."""
    n0 = max(na, nb)
    rows = [[-y[t - i] for i in range(1, na + 1)] + [u[t - j] for j in range(1, nb + 1)] for t in range(n0, u.size)]
    return np.array(rows), y[n0:]


def arx_refit(u: np.ndarray, y: np.ndarray, na: int, nb: int) -> np.ndarray:
    phi, target = arx_rows(u, y, na, nb)
    return np.linalg.lstsq(phi, target, rcond=None)[0]


def poisoned(atk, result) -> dict[str, np.ndarray]:
    return {k: atk.signals[k] + np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in atk.signals}


def refit(atk, signals: dict[str, np.ndarray]) -> np.ndarray:
    if atk.learner == "ss":
        return ss_refit(signals["X"], signals["U"])
    return arx_refit(signals["u"].ravel(), signals["y"].ravel(), *atk.orders)[None, :]


def test_controllable_canonical_realizes_the_flexible_transmission() -> None:
    """C (zI - A)^-1 B equals G(z) = B(z)/A(z) at points off the unit circle."""
    g = flexible_transmission()
    A, B, C = controllable_canonical(g.num[0][0], g.den[0][0])
    for z in (1.3, -0.7 + 0.4j, 2.0j):
        model = (C @ np.linalg.solve(z * np.eye(4) - A, B)).item()
        assert model == pytest.approx(complex(g(z)), rel=1e-12)


def test_arx_data_follow_the_equation_error_model() -> None:
    """The true ARX(4, 4) parameters leave residuals that are the drawn noise: ~N(0, 0.1^2), variance test passes."""
    atk = attack_instance("arx", T=2000, seed=5)
    theta = atk.setting.arx_parameters(4, 4)
    assert theta[:4] == pytest.approx([-1.41833, 1.58939, -1.31608, 0.88642])
    assert theta[4:] == pytest.approx([0.0, 0.0, 0.28261, 0.50666])
    phi, target = arx_rows(atk.signals["u"].ravel(), atk.signals["y"].ravel(), 4, 4)
    e = target - phi @ theta
    assert np.std(e) == pytest.approx(0.1, rel=0.05)
    np.testing.assert_allclose(atk.theta0.ravel(), theta, atol=0.05)


@pytest.mark.parametrize("name,objective", [("ident-ss", "frobenius"), ("ident-ss", "spectral"),
                                            ("ident-arx", "frobenius")])
def test_attack_is_certified_and_equals_numpy_refit(name: str, objective: str) -> None:
    atk = attack_instance("ss" if name == "ident-ss" else "arx", T=100, eps=0.05, objective=objective, seed=1)
    problem = registry.get(name, T=100, eps=0.05, objective=objective, seed=1)
    result = problem.solve(starts=2, seed=0)
    assert result.status.value == "solved" and result.certificate.passed, result.message
    signals = poisoned(atk, result)
    theta = refit(atk, signals)
    assert np.linalg.norm(result.y["theta"] - theta) <= 1e-8 * np.linalg.norm(theta)
    for k in atk.signals:
        assert np.linalg.norm(signals[k] - atk.signals[k]) <= atk.radius(k) * (1 + 1e-9)
    d = theta - atk.theta0
    value = np.sum(d ** 2) if objective == "frobenius" else np.linalg.norm(d, 2) ** 2
    assert result.upper_objective == pytest.approx(value, rel=1e-8)


@pytest.mark.parametrize("learner,method,options", [
    ("ss", "ipopt", {"ipopt": {"hessian_approximation": "limited-memory"}}), ("arx", "ipopt", {}),
    ("ss", "reduced", {}), ("arx", "reduced", {})])
def test_stealthy_attack_keeps_statistics_within_delta(learner: str, method: str, options: dict) -> None:
    """Every statistic of the defender's tests on the returned poisoned data, refitted independently, is within delta
    of its clean value; the result is certified and its theta is the numpy refit (the KKT form, and the reduced
    form over the poisoning alone)."""
    delta = 0.05
    atk = attack_instance(learner, T=100, eps=0.05, stealth=delta, seed=0)
    result = declare(atk).solve(method, starts=1, seed=0, **options)
    assert result.status.value == "solved" and result.certificate.passed, result.message
    signals = poisoned(atk, result)
    theta = refit(atk, signals)
    assert np.linalg.norm(result.y["theta"] - theta) <= 1e-8 * np.linalg.norm(theta)
    if learner == "ss":
        Y, Z = signals["X"][:, 1:], np.vstack([signals["X"][:, :-1], signals["U"]])
    else:
        phi, target = arx_rows(signals["u"].ravel(), signals["y"].ravel(), 4, 4)
        Y, Z = target[None, :], phi.T
    after = regression_tests(Y, Z, theta, atk.input_rows, 0.1, atk.lags)
    before = atk.tests()
    for name in before:
        assert abs(1 - after[name].statistic / before[name].statistic) <= delta + 1e-6, name
    free = declare(attack_instance(learner, T=100, eps=0.05, seed=0)).solve(starts=2, seed=0)
    assert result.upper_objective <= free.upper_objective * (1 + 1e-6)  # stealth costs the attacker


def test_statistics_functions_are_the_defenders_tests() -> None:
    """The statistics' Functions (the call nodes of the stealth constraints) at the least-squares fits of random data
    give the statistics of bilevel.ddc.residual_tests."""
    rng = np.random.default_rng(3)
    Y, Z = rng.standard_normal((2, 40)), rng.standard_normal((3, 40))
    theta = np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T
    theta_r = np.linalg.lstsq(Z[[0, 2]].T, Y.T, rcond=None)[0].T
    value = [float(f(Y, Z, theta, theta_r)) for f in statistics_functions(2, 3, 40, (0, 2), 0.3, 4)]
    tests = regression_tests(Y, Z, theta, [1], 0.3, 4)
    np.testing.assert_allclose(value, [tests[name].statistic for name in STATISTICS], rtol=1e-10)


def test_load_instance_retargets_a_declared_problem() -> None:
    problem = declare(attack_instance("ss", T=60, seed=0))
    fresh = declare(attack_instance("ss", T=60, seed=3)).solve(starts=1, seed=0)
    load_instance(problem, attack_instance("ss", T=60, seed=3))
    again = problem.solve(starts=1, seed=0)
    assert again.upper_objective == pytest.approx(fresh.upper_objective, rel=1e-9)
    with pytest.raises(ModelError, match="declare it with declare"):
        load_instance(problem, attack_instance("ss", T=80, seed=3))


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ModelError, match="objective"):
        attack_instance("ss", objective="h3")
    with pytest.raises(ModelError, match="stealth"):
        attack_instance("arx", stealth=1.5)
    with pytest.raises(InvalidData, match="longer experiment"):
        attack_instance("arx", T=15)
    with pytest.raises(ModelError, match="learner"):
        attack_instance("bj")


def test_identification_page_runs() -> None:
    """docs/identification.md's code prints what the page says."""
    from tests.docs_pages import run_page

    run_page("identification.md")
