"""De Persis–Tesi certificates (issue 46): the gain is affine in the input poisoning, the exact triangle mechanism at
n = 2 proves below and refutes above its radius, the small-gain proof at the batch reactor survives sampling and the
attacks, and evidence that fails its numpy re-check never makes a certificate proven."""

import dataclasses

import numpy as np
import pytest

from bilevel.ddc.depersis_tesi import lqr_controller
from bilevel.errors import ModelError
from bilevel.experiments.certify import N2_PLANT
from bilevel.problems.willems import build_attack
from bilevel.problems.willems_instance import WillemsSetting
from bilevel.robust import Proof, as_target, certified_margin, certify, sample_soundness
from bilevel.robust.depersis_tesi import recheck_small_gain
from tests.docs_pages import run_page


def _target(selection="min-norm", plant=None, horizon=15, seed=1):
    return as_target(build_attack(WillemsSetting(objective="destabilize", horizon=horizon, seed=seed,
                                                 selection=selection, plant=plant)))


def test_refit_is_the_learner_and_affine():
    target = _target("clarabel")
    atk = target.declaration.attack
    du = 0.1 * np.random.default_rng(0).standard_normal(atk.u.shape)
    learned = lqr_controller(atk.x, atk.u + du, atk.qx, input_cost=False, solver="clarabel").k
    np.testing.assert_allclose(target.refit({"u": atk.u + du}), learned, rtol=1e-6, atol=1e-8)
    loop = target.declaration
    np.testing.assert_allclose(loop.acl + loop.b @ du @ loop.g,
                               atk.true_closed_loop(target.refit({"u": atk.u + du})), atol=1e-10)


@pytest.mark.parametrize("selection", ["min-norm", "clarabel"])
def test_triangle_is_exact_at_n2(selection):
    target = _target(selection, N2_PLANT)
    exact = certify(target, 0.1).evidence[0].numbers["exact_radius"] / target.scale["u"]
    below, above = certify(target, 0.999 * exact), certify(target, 1.001 * exact)
    assert below.proof is Proof.PROVEN and below.evidence[0].check.passed
    assert above.proof is Proof.REFUTED and above.evidence[0].check.numbers["spectral_radius"] >= 1.0
    margin = certified_margin(target, rel_tol=0.01)
    assert 0 < margin.delta_lb <= exact <= margin.delta_ub and margin.ratio <= 1.1
    assert sample_soundness(target, margin.delta_lb, samples=500).sound


def test_small_gain_at_the_reactor_is_sound():
    target = _target("min-norm")
    cert = certify(target, 0.05)
    assert cert.proven and cert.evidence[-1].mechanism == "small-gain"
    numbers = cert.evidence[-1].check.numbers
    assert numbers["largest_lmi_eigenvalue"] < -numbers["margin"] < 0 < numbers["margin"] < 1e-5
    margin = certified_margin(target, rel_tol=0.02)
    assert 0 < margin.delta_lb <= margin.delta_ub and margin.ratio < 1.5
    assert sample_soundness(target, margin.delta_lb, samples=500).sound


def test_failed_recheck_is_unknown():
    target = _target("min-norm")
    loop = target.declaration
    p, mu = loop.cache.get("small-gain") or (certify(target, 0.01), loop.cache["small-gain"])[1]
    assert recheck_small_gain(loop.acl, loop.b, loop.g, p, 0.5 * np.sqrt(mu)).passed
    loop.cache["small-gain"] = (p * np.diag([1.0, 1.0, 1.0, -1.0]), mu)  # a tampered Lyapunov matrix
    cert = certify(target, 0.01, mechanisms=["small-gain"])
    assert cert.proof is Proof.UNKNOWN and not cert.evidence[0].check.passed


def test_other_settings_are_refused():
    atk = build_attack(WillemsSetting(objective="destabilize", horizon=15, seed=1))
    with pytest.raises(ModelError, match="poison='u'"):
        as_target(dataclasses.replace(atk, setting=dataclasses.replace(atk.setting, selection="tikhonov")))


def test_page_runs():
    run_page("certify_dpt.md")
