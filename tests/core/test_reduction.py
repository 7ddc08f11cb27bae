"""Single-level reduction: MPCC structure, apply/invert round trip, and max f == min -f for every kind."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.solvers.engine.prepared import prepare
from tests.conftest import bard_511, projection_qp


def test_mpcc_blocks_and_pairs_of_bard() -> None:
    prep = prepare(bard_511())
    mpcc = prep.mpcc
    sizes = {k: v.stop - v.start for k, v in mpcc.blocks.items()}
    assert sizes == {"x": 1, "y": 1, "lam": 5, "mu": 0}  # 4 constraints + the bound y >= 0
    assert int(mpcc.equalities.numel()) == 1  # stationarity only
    assert len(mpcc.pairs) == 1 and int(mpcc.pairs[0].G.numel()) == 5
    assert "5 scalar" in repr(mpcc)


def test_pack_and_invert_are_inverse() -> None:
    prep = prepare(projection_qp())
    point = prep.lower_point(np.array([0.3, 0.9]))
    w = prep.pack(point)
    back = prep.point(w)
    for a, b in ((point.x, back.x), (point.y, back.y), (point.lam, back.lam), (point.mu, back.mu)):
        np.testing.assert_array_equal(a, b)


def test_lower_optimal_start_satisfies_the_mpcc() -> None:
    """A point (x, y*(x), multipliers) from the independent lower solve is MPCC-feasible."""
    prep = prepare(bard_511())
    w = prep.pack(prep.lower_point(np.array([2.5])))
    res = prep.mpcc.residuals(w)
    assert max(res.values()) < 1e-7, res


def _kinds(maximize: bool) -> list[bl.BilevelProblem]:
    out = []
    for kind in ("lp", "qp", "least-squares", "nlp"):
        p = bl.BilevelProblem(kind)
        x = p.upper_variable("x", 2, lb=-1, ub=1)
        y = p.lower_variable("y", 2, lb=-2, ub=2) if kind == "lp" else p.lower_variable("y", 2)
        p.minimize_upper(ca.sumsqr(y - ca.DM([0.5, -0.3])) + 0.01 * ca.sumsqr(x))
        f = {"lp": ca.dot(x + ca.DM([0.5, 0.5]), y), "qp": ca.sumsqr(y - x),
             "least-squares": ca.sumsqr(y - 2 * x), "nlp": ca.sumsqr(y - x) + ca.exp(y[0])}[kind]
        (p.maximize_lower(-f) if maximize else p.minimize_lower(f))
        if kind in ("qp", "nlp"):
            p.lower_constraint(y[0] + y[1] <= 0.5)
        out.append(p)
    return out


@pytest.mark.parametrize("index", range(4))
def test_max_lower_equals_min_negated_lower(index: int) -> None:
    """BilevelJuMP #82/#182: max f and min -f must give the same solution and multipliers, sign-flipped f."""
    rmin = _kinds(False)[index].solve(starts=3, seed=1)
    rmax = _kinds(True)[index].solve(starts=3, seed=1)
    assert rmin.status is bl.Status.SOLVED and rmax.status is bl.Status.SOLVED
    assert rmin.upper_objective == pytest.approx(rmax.upper_objective, abs=1e-7)
    assert rmin.lower_objective == pytest.approx(-rmax.lower_objective, abs=1e-7)
    np.testing.assert_allclose(rmin.y["y"], rmax.y["y"], atol=1e-6)
    for name in rmin.multipliers:
        np.testing.assert_allclose(rmin.multipliers[name], rmax.multipliers[name], atol=1e-6)


def test_max_upper_is_min_of_negated_upper() -> None:
    p = bard_511()
    q = bard_511()
    x, y = q.variables[0].sym, q.variables[1].sym
    q.maximize_upper(-(x - 4 * y))
    rp, rq = p.solve(starts=4), q.solve(starts=4)
    assert rq.upper_objective == pytest.approx(-rp.upper_objective, abs=1e-7) == pytest.approx(12.0, abs=1e-7)


def test_every_branch_of_an_mpcc_is_one_compiled_nlp_with_its_sides_as_bounds() -> None:
    """Bard 5.1.1's branches: each is the same NLP (same rows, one IPOPT build) with the sides in the row bounds, and
    solving it holds the chosen side of every pair at zero."""
    from bilevel.mpcc import Branch
    from bilevel.solvers.ipopt import run_nlp

    prep = prepare(bard_511())
    mpcc = prep.mpcc
    w = prep.pack(prep.lower_point(np.array([4.0])))
    pairs = mpcc.pair_values(w)
    first = {name: G <= H for name, (G, H) in pairs.items()}
    flipped = {name: side.copy() for name, side in first.items()}
    flipped["lower"][2] = False  # a neighbouring branch (the third lower constraint's multiplier held at zero instead)
    options = {"ipopt": {"print_level": 0, "bound_relax_factor": 0.0}, "print_time": False}
    forms = [mpcc.transcribe(Branch(sides=s)) for s in (first, flipped)]
    assert forms[0].g is forms[1].g and not np.array_equal(forms[0].ubg, forms[1].ubg)
    for sides, form in zip((first, flipped), forms):
        run = run_nlp(form, w, options)
        assert run.status is bl.Status.SOLVED
        for name, (G, H) in mpcc.pair_values(run.w).items():
            held = np.where(sides[name], G, H)
            assert np.abs(held).max() <= 1e-8, (name, held)
    assert len(mpcc._nlps) == 1 and len(next(iter(mpcc._nlps.values()))._solvers) == 1
