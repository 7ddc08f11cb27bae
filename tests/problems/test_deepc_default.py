"""Issue 44 item 7: deepc-tracking's default answer under different OpenBLAS kernels. IPOPT's path from one start (the
sixth of eight, 128 iterations through ill-conditioned steps) ends at 165.442 under one kernel and at 157.819, another
genuine local solution, under Haswell and Sandybridge: no choice among the starts can undo that. What the kernel must
not decide is the choice among starts that reach the same local solution (their objectives differ in the last bits):
the first of those wins (bilevel.solvers.engine.prepared.best_of). Run this file under OPENBLAS_CORETYPE=Haswell and
=Sandybridge too."""

from __future__ import annotations

import numpy as np
import pytest

from bilevel.problems import registry
from bilevel.problems.deepc_instance import attack_instance
from bilevel.solvers.engine.prepared import best_of
from tests.problems.test_deepc import own_deepc, true_cost

LOCAL_SOLUTIONS = (165.44179608822, 157.81893177315)
"""deepc-tracking's default answers (seed 0) under the kernels measured (docs/deepc.md, "Measured")."""


def test_last_bits_do_not_choose_among_tied_starts() -> None:
    w = np.zeros(1)
    tied = [(w, -157.81893567731862, 0.0), (w, -157.81893567731998, 0.0), (w, -154.48, 0.0)]
    assert best_of(tied) == 0
    assert best_of([(w, -157.8, 0.0), (w, -165.4, 0.0), (w, -165.4 - 1e-12, 0.0)]) == 1
    assert best_of([(w, np.nan, 0.0), (w, -1.0, 0.0), (w, -1.0, 1.0)]) == 1
    assert best_of([(w, 0.0, 0.0), (w, -np.inf, 0.0)]) == 1
    assert best_of([(w, -5.0, 1.0), (w, -1.0, 0.5)]) == 1  # none feasible: the least infeasible


def test_default_answer_is_a_documented_local_solution_from_the_first_start_reaching_it() -> None:
    result = registry.get("deepc-tracking").solve()
    assert result.status.value == "solved" and result.certificate.passed, result.message
    assert any(result.upper_objective == pytest.approx(v, rel=1e-8) for v in LOCAL_SOLUTIONS), result.upper_objective
    first = min(r["start"] for r in result.start_records
                if r["objective"] == pytest.approx(result.upper_objective, rel=1e-6))
    assert result.stats["best_start"] == first
    atk = attack_instance(objective="tracking")  # the value is the true plant's cost of the plan DeePC makes on the poisoned data
    u, y = atk.u + np.ravel(result.x["du"]), atk.y + np.ravel(result.x["dy"])
    assert true_cost(atk, own_deepc(atk, u, y)[2]) == pytest.approx(result.upper_objective, rel=1e-6)
