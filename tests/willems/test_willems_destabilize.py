"""The destabilizing attack on the De Persis–Tesi learners (issue 12): its gradient, its answer (the largest
spectral radius reached), the learner's selections and the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bilevel.attacks.outcome import unstable
from bilevel.attacks.willems import (SDPHypergradient, destabilize_attack, hypergradient_attack, log_radius_gradient,
                                     smallest_destabilizing_budget)
from bilevel.cli import main
from bilevel.ddc.data import batch_reactor_data
from bilevel.ddc.depersis_tesi import lqr_controller
from bilevel.errors import ModelError
from bilevel.problems import registry
from bilevel.problems.willems import WillemsSetting, build_attack


def test_log_radius_gradient_matches_central_differences() -> None:
    """d log rho / dK at a random gain (a complex top pair here) agrees with central differences to 1e-6."""
    attack = build_attack(objective="destabilize", horizon=15, seed=1)
    k = np.random.default_rng(0).standard_normal((2, 4))
    value, grad = log_radius_gradient(attack.a_id + attack.b_id @ k, attack.b_id)
    assert value == pytest.approx(np.log(np.max(np.abs(np.linalg.eigvals(attack.a_id + attack.b_id @ k)))))
    fd = np.zeros_like(k)
    for i in np.ndindex(k.shape):
        e = np.zeros_like(k)
        e[i] = 1e-6
        fd[i] = (log_radius_gradient(attack.a_id + attack.b_id @ (k + e), attack.b_id)[0]
                 - log_radius_gradient(attack.a_id + attack.b_id @ (k - e), attack.b_id)[0]) / 2e-6
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9)


def test_gain_gradient_through_the_sdp_matches_central_differences() -> None:
    """State poisoning (the SDP depends on x): d log rho(A_id + B_id K(x)) / dx by the KKT adjoint agrees with
    central differences along two random directions to 1e-4 relative."""
    attack = build_attack(objective="destabilize", horizon=15, seed=11, poison="x", delta_u=0.0, delta_x=1e-3)
    oracle = SDPHypergradient(attack)
    rng = np.random.default_rng(2)
    x = 0.5 * rng.uniform(-1, 1, oracle.n_x) * attack.budget()
    ev = oracle.evaluate(x)
    grad = oracle.gain_gradient(ev, log_radius_gradient(ev.closed_loop, attack.b_id)[1])
    for _ in range(2):
        v = rng.standard_normal(oracle.n_x) * attack.budget()
        v /= np.linalg.norm(v)
        fd = (np.log(oracle.evaluate(x + 1e-6 * v).identified_radius)
              - np.log(oracle.evaluate(x - 1e-6 * v).identified_radius)) / 2e-6
        assert fd == pytest.approx(grad @ v, rel=1e-4)


def test_attack_reports_the_largest_radius_and_beats_the_eigenvalue_attack() -> None:
    """N = 15, seed 1, delta_u = 0.3: the result's point is the one with the largest identified radius over all
    starts and paths, inside the box, and deterministic. Measured: rho 1.0214 (unstable) where the log-det attack
    (8 starts, with or without stopping at instability) ends at 0.8212."""
    attack = build_attack(objective="destabilize", horizon=15, seed=1, delta_u=0.3)
    res = destabilize_attack(attack, starts=4, seed=0)
    radii = [r[key] for r in res.stats["details"]["starts"] for key in ("smooth_radius", "direct_radius")]
    assert res.stats["details"]["identified_radius"] == max(radii)
    assert res.stats["spectral_radius"] == pytest.approx(res.stats["details"]["identified_radius"], rel=1e-9)
    assert res.stats["budget_violation"] == 0.0 and np.max(np.abs(res.stats["x"])) == pytest.approx(0.3)
    assert unstable(res) and res.stats["spectral_radius"] == pytest.approx(1.0214, abs=1e-3)
    eigen = hypergradient_attack(build_attack(objective="eigen", horizon=15, seed=1, delta_u=0.3), seed=0)
    assert eigen.stats["spectral_radius"] == pytest.approx(0.8212, abs=1e-3)
    again = destabilize_attack(attack, starts=4, seed=0)
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
    oracle = SDPHypergradient(attack)
    point = 0.3 * np.random.default_rng(1).choice([-1.0, 1.0], oracle.n_x)
    ev = oracle.evaluate(point)
    du, _ = attack.split(point)
    s = x[:, :-1] @ own.q
    np.testing.assert_allclose(ev.gain, (u + du) @ own.q @ np.linalg.inv((s + s.T) / 2), rtol=1e-9, atol=1e-9)
    assert np.isnan(ev.kkt_residual)
    min_norm = SDPHypergradient(build_attack(objective="destabilize", horizon=15, seed=7, delta_u=0.3))
    assert np.abs(min_norm.evaluate(point).gain - ev.gain).max() > 1e-2
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
    assert data["setting"]["delta_u"] == 0.3 and data["method"] == "destabilize"
    assert data["unstable"] is True and data["spectral_radius"] == pytest.approx(1.0214, abs=1e-3)
    assert "spectral_radius" in capsys.readouterr().out
    assert main(["solve", "willems-destabilize", "--param", "budget=1"]) == 2
    assert "willems-destabilize takes delta_u" in capsys.readouterr().err


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
