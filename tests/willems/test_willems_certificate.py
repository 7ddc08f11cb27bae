"""The certificate on the Willems learner's SDP where its independent re-solve stops short: the output-poisoning remark
at N = 50 (states poisoned by 1e-3, the random-sign baseline of sim 0 of the 256-simulation reproduction)."""

from __future__ import annotations

import dataclasses

import numpy as np

from bilevel.attacks.willems import random_attack
from bilevel.certificate import certify_point
from bilevel.experiments.willems import DELTA_Y, sim_seeds
from bilevel.problems.willems import build_attack
from bilevel.solvers.engine.prepared import prepare


def test_remark_point_is_certified_by_weak_duality_and_the_re_solves_point_is_not() -> None:
    """Clarabel's re-solve (AlmostSolved) lands on the unregularized SDP's optimal set but not at the reg = 1e-8
    ridge's minimum norm: its value is ~1.7e-5 (relative) above the learner's, whose multipliers bound f* from below
    to rounding. The learner's point passes for that reason; the re-solve's point, given with the learner's
    multipliers, fails on lower_gap (comparing values with the re-solve alone passed it and failed the learner)."""
    data_seed, attack_seed = sim_seeds(0, 1)[0]
    attack = build_attack(objective="eigen", horizon=50, seed=data_seed, delta_u=0.0, delta_x=DELTA_Y, poison="x",
                          design="lqr")
    res = random_attack(attack, seed=attack_seed)
    cert = res.certificate
    assert cert.passed, cert
    prep = prepare(attack.shared_problem())
    point = prep.lower_point(np.asarray(res.stats["x"], dtype=float))
    f = float(prep.canon.lower.evaluate(point.x, point.y)[0])
    assert (cert.lower_reference - f) / (1 + f) > 10 * cert.tolerance  # the case: the re-solve stops short
    assert cert.lower_bound is not None and abs(f - cert.lower_bound) <= 1e-9 * (1 + f)
    wrong = certify_point(prep.canon, dataclasses.replace(point, y=np.asarray(cert.lower_reference_y)))
    assert "lower_gap" in wrong.failed and wrong.lower_gap > 10 * wrong.tolerance
