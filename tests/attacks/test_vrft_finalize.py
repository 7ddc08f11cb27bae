"""Every VRFT attack result comes out of the engine's finalize: a certificate with an independent re-solve of the
learner (checks computed, not filled in) and the local probe, which may call the attack's point not locally optimal."""

from __future__ import annotations

import numpy as np
import pytest

import bilevel as bl
from bilevel.attacks import attack_alternating, attack_joint, attack_white_noise
from bilevel.ddc.vrft import fit_vrft
from bilevel.problems.budget import Budget
from bilevel.problems.vrft import problem_for
from bilevel.problems.vrft_instance import VRFTAttack, attack_instance
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.verdict.probe import improving_neighbour

KINDS = [("alternating", "maxmin"), ("alternating", "targeted"), ("joint", "maxmin"), ("joint", "targeted"),
         ("joint", "destabilize"), ("white-noise", "maxmin"), ("white-noise", "targeted"),
         ("white-noise", "destabilize")]
RUN = {"alternating": lambda atk, **o: attack_alternating(atk, **o), "joint": lambda atk, **o: attack_joint(atk, **o),
       "white-noise": lambda atk, **o: attack_white_noise(atk, seed=3)}


def _refit(atk: VRFTAttack, a_u: np.ndarray, a_y: np.ndarray) -> np.ndarray:
    """The learner on the poisoned data, by bilevel.ddc.vrft.fit_vrft (not the attack's QR path)."""
    s = atk.setting
    return fit_vrft(atk.u + a_u, atk.y + a_y, s.reference, s.basis,
                    prefilter=None if s.data == "prefiltered" else s.prefilter, boundary=s.boundary).theta


def _F(atk: VRFTAttack, theta: np.ndarray) -> float:
    """The registered problem's upper objective in its own sense, written out: the clean-data loss (max-min), the
    squared distance to the target (targeted, minimized); None for destabilize (a Gelfand radius)."""
    if atk.objective == "maxmin":
        r = atk.t0 - atk.phi0 @ theta
        return float(r @ r) / atk.t0.size
    d = atk.theta_target - theta
    return float(d @ d) / d.size


@pytest.mark.parametrize("method,objective", KINDS)
def test_attack_result_has_the_engines_certificate_and_probe(method: str, objective: str) -> None:
    """The certificate's reference theta and lower optimum are an independent refit's, every check names its worst
    row (the budgets among the upper rows), and stats hold the probe's record."""
    atk = attack_instance(objective, "B", 0.1, 0.057, seed=2, N=128)
    res = RUN[method](atk)
    cert = res.certificate
    theta = _refit(atk, res.x["a_u"], res.x["a_y"])
    np.testing.assert_allclose(cert.lower_reference_y, theta, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.y["theta"], theta, rtol=1e-8, atol=1e-10)
    assert cert.passed and cert.lower_unique is True
    assert {"stationarity", "upper_feasibility", "lower_solution"} <= set(cert.worst)
    assert cert.worst["upper_feasibility"] in ("budget_u[0]", "budget_y[0]")
    reg = atk.setting.regressor
    residual = reg.targets(atk.u + res.x["a_u"]) - reg(atk.y + res.x["a_y"]) @ theta
    assert cert.lower_reference == pytest.approx(float(residual @ residual) / atk.t0.size, rel=1e-9)
    if objective != "destabilize":
        assert cert.upper_at_reference == pytest.approx((1 if objective == "targeted" else -1) * _F(atk, theta),
                                                        rel=1e-9)
    assert "probe" in res.stats and res.stats["evaluations"] >= 1 and res.method == method


@pytest.mark.parametrize("method,objective", [("alternating", "maxmin"), ("joint", "targeted"),
                                              ("white-noise", "maxmin")])
def test_probe_finds_a_better_point_next_to_an_unfinished_attack(method: str, objective: str) -> None:
    """One iteration (or a white-noise sample) is not a local maximum: the status is not_locally_optimal and the
    probe's point, refitted independently, is inside the budgets and gives the attacker more."""
    atk = attack_instance(objective, "B", 0.1, 0.057, seed=2, N=128)
    res = RUN[method](atk, max_iter=1)
    assert res.status is bl.Status.NOT_LOCALLY_OPTIMAL and res.certificate.passed
    probe = res.stats["probe"]
    a_u, a_y = probe["x"][: atk.N], probe["x"][atk.N:]
    assert np.linalg.norm(a_u) <= atk.delta_u * (1 + 1e-9) and np.linalg.norm(a_y) <= atk.delta_y * (1 + 1e-9)
    better, here = _F(atk, _refit(atk, a_u, a_y)), _F(atk, res.y["theta"])
    assert (better > here) if objective == "maxmin" else (better < here)
    assert better == pytest.approx(probe["objective"], rel=1e-9)  # the probe reports F in the problem's own sense


def test_probe_searches_the_sparse_budget_the_attack_keeps() -> None:
    """With a sparsity fraction the declared problem has the norm balls only; the attack hands its sparse sets to the
    probe, whose point changes at most floor(rho N) samples of each signal."""
    base = attack_instance("maxmin", "B", 0.1, 0.057, seed=2, N=128)
    atk = VRFTAttack(base.setting, base.u, base.y, Budget(0.1, "l2", 0.25), Budget(0.057, "l2", 0.25))
    res = attack_white_noise(atk, seed=1)
    assert res.status is bl.Status.NOT_LOCALLY_OPTIMAL
    x = res.stats["probe"]["x"]
    assert np.count_nonzero(x[: atk.N]) <= 32 and np.count_nonzero(x[atk.N:]) <= 32


def test_probe_by_the_learners_solve_agrees_with_the_lower_levels() -> None:
    """The probe solving the learner by its thin QR at all points in one call (MethodRun.lower_solve, as the attacks
    pass it) finds the point and objective that it finds with the declared lower level's own solver."""
    atk = attack_instance("maxmin", "B", 0.1, 0.057, seed=2, N=128)
    res = attack_alternating(atk, max_iter=1)
    prep = prepare(problem_for(atk))
    x = np.concatenate([res.x["a_u"], res.x["a_y"]])
    F = -_F(atk, res.y["theta"])  # canonical: the max-min loss minimized as its negative
    own = improving_neighbour(prep, x, F, prep.projection)
    learner = improving_neighbour(prep, x, F, prep.projection, lower_solve=atk.learner.thetas)
    assert own is not None and learner is not None
    np.testing.assert_array_equal(learner.x, own.x)
    assert learner.radius == own.radius and learner.objective == pytest.approx(own.objective, rel=1e-9)
    assert learner.objective == pytest.approx(-_F(atk, _refit(atk, learner.x[: atk.N], learner.x[atk.N:])), rel=1e-9)


def test_probe_points_in_one_mapped_call_equal_one_call_each() -> None:
    """The probe's F, G, H at all its points in one call of the problem's mapped functions: each point's upper
    objective is the one a call at that point alone gives, bit for bit, and a point outside the budget is None."""
    from bilevel.solvers.verdict.probe import _feasible_objective, _structured_objectives

    atk = attack_instance("maxmin", "B", 0.1, 0.057, seed=2, N=128)
    prep = prepare(problem_for(atk))
    rng = np.random.default_rng(0)
    X = np.array([prep.projection(rng.standard_normal(2 * atk.N)) for _ in range(5)])
    X = np.vstack([X, 3 * X[0] / np.linalg.norm(X[0]) * max(atk.delta_u, atk.delta_y)])  # outside both balls
    one_each = [_feasible_objective(prep, x, y)[0] for x, y in zip(X, atk.learner.thetas(X))]
    assert _structured_objectives(prep, X, atk.learner.thetas) == one_each
    assert one_each[-1] is None and all(v is not None for v in one_each[:-1])
