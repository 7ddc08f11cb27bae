"""Methods through the dispatcher: options are checked, statuses are honest, results serialize."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bilevel as bl
from bilevel.cli import main
from tests.conftest import bard_511, projection_qp


@pytest.mark.parametrize("method, options", [
    ("ipopt", {}),
    ("relaxation", {"scheme": "scholtes"}),
    ("relaxation", {"scheme": "kanzow-schwartz"}),
])
def test_methods_reach_bard_optimum(method: str, options: dict) -> None:
    """Bard (1998) Example 5.1.1: F* = -12 at (x, y) = (4, 4)."""
    res = bard_511().solve(method=method, starts=4, seed=0, **options)
    assert res.status is bl.Status.SOLVED
    assert res.upper_objective == pytest.approx(-12.0, rel=1e-6)
    assert res.x["x"] == pytest.approx(4.0, abs=1e-6) and res.y["y"] == pytest.approx(4.0, abs=1e-6)
    assert res.lower_objective == pytest.approx(4.0, abs=1e-6)
    assert res.nit > 0 and len(res.start_records) == 4 and res.wall_time > 0
    # several starts end at (4, 4), within the relaxation's accuracy of each other: only the answer is polished
    assert [k for k, rec in enumerate(res.start_records) if rec["polished"]] == [res.stats["best_start"]]


@pytest.mark.parametrize("method", ["ipopt", "relaxation"])
def test_warm_start_from_hypergradient_reaches_bard_optimum(method: str) -> None:
    """Bard (1998) Example 5.1.1, F* = -12: warm="hypergradient" runs one NLP from hypergradient's best point, and
    the NLP makes it exact (the penalized hypergradient point is infeasible by about 1e-9)."""
    res = bard_511().solve(method=method, starts=4, seed=0, warm="hypergradient")
    warm = res.stats["warm"]
    assert warm["used"] and warm["method"] == "hypergradient" and warm["objective"] == pytest.approx(-12.0, rel=1e-6)
    assert res.status is bl.Status.SOLVED and len(res.start_records) == 1
    assert res.upper_objective == pytest.approx(-12.0, rel=1e-9)
    assert res.certificate.complementarity <= 1e-9


def test_warm_start_on_vrft_maxmin_keeps_the_hypergradient_attack() -> None:
    """On vrft-maxmin (N = 64) one IPOPT solve from hypergradient's answer ends at a point at least as strong, in a
    few iterations: the warm start is the framework's route to a Newton-accurate KKT point of the attack."""
    from bilevel.problems import registry

    p = registry.get("vrft-maxmin", N=64)
    hg = p.solve(method="hypergradient", starts=1)
    res = p.solve(method="ipopt", starts=1, warm="hypergradient")
    assert res.stats["warm"]["objective"] == pytest.approx(hg.upper_objective, rel=1e-12)
    assert res.status is bl.Status.SOLVED and res.certificate.passed
    assert res.upper_objective >= hg.upper_objective * (1 - 1e-9)
    assert res.start_records[0]["iterations"] <= 30


def test_warm_auto_starts_from_hypergradient_only_where_it_has_an_exact_block() -> None:
    """The default warm="auto": vrft-maxmin (least-squares learner, l2 input budget: an exact block) gets the warm
    phase, the same answer as warm="hypergradient"; Bard 5.1.1 (a QP learner: no exact block) gets its 4 starts."""
    from bilevel.problems import registry

    p = registry.get("vrft-maxmin", N=64)
    auto, forced = p.solve(method="ipopt", starts=1), p.solve(method="ipopt", starts=1, warm="hypergradient")
    assert auto.stats["warm"]["used"] and auto.upper_objective == pytest.approx(forced.upper_objective, rel=1e-12)
    res = bard_511().solve(method="relaxation", starts=4, seed=0)
    assert "warm" not in res.stats and len(res.start_records) == 4


def test_warm_phase_without_a_point_falls_back_to_the_start_points(monkeypatch: pytest.MonkeyPatch) -> None:
    """If hypergradient returns no point, the KKT method runs from its ordinary starts and says so in stats."""
    from bilevel.solvers import ipopt

    monkeypatch.setattr(ipopt, "solve_hypergradient",
                        lambda prep, **o: ipopt.MethodRun(None, bl.Status.ERROR, "no start could be solved"))
    res = bard_511().solve(method="ipopt", starts=3, seed=0, warm="hypergradient")
    assert res.stats["warm"]["used"] is False and res.stats["warm"]["status"] == "error"
    assert len(res.start_records) == 3 and res.upper_objective == pytest.approx(-12.0, rel=1e-6)


def test_warm_option_and_wall_time_are_honest() -> None:
    with pytest.raises(bl.ModelError, match="warm='hg'.*'auto', None or 'hypergradient'"):
        bard_511().solve(method="ipopt", warm="hg")
    # IPOPT stopped by its wall-time limit: a status, never `solved`
    res = bard_511().solve(method="ipopt", starts=1, ipopt={"max_wall_time": 1e-9})
    assert res.status is bl.Status.MAX_ITERATIONS and "WallTime" in res.message


def test_relaxation_path_is_recorded_and_decreasing() -> None:
    res = bard_511().solve(method="relaxation", starts=1, t0=1.0, factor=0.1)
    ts = [h["t"] for h in res.history]
    assert ts == sorted(ts, reverse=True) and len(ts) >= 2
    assert res.history[-1]["complementarity"] <= 1e-7  # default comp_tol
    assert res.certificate.complementarity <= 1e-9  # exact after polishing


def test_unknown_option_and_method_raise() -> None:
    with pytest.raises(bl.UnknownOption, match="strats"):
        bard_511().solve(strats=3)
    with pytest.raises(bl.ModelError, match="unknown method"):
        bard_511().solve(method="newton")
    with pytest.raises(bl.ModelError, match="scheme"):
        bard_511().solve(method="relaxation", scheme="nope")


def test_custom_callable_method_plugs_in() -> None:
    best = bl.solve(projection_qp(), method="ipopt", starts=4)
    assert best.success

    def fixed_point(x):
        def method(prep, **_):
            from bilevel.solvers.engine.prepared import MethodRun
            return MethodRun(prep.pack(prep.lower_point(np.asarray(x, dtype=float))), bl.Status.SOLVED, "fixed point")
        return method

    res = bl.solve(projection_qp(), method=fixed_point(best.x["x"]))
    assert res.method == "method" and res.certificate.passed and res.success
    # a plug-in that calls an arbitrary lower-optimal point solved is contradicted by the local probe
    res = bl.solve(projection_qp(), method=fixed_point([1.0, 0.0]))
    assert res.certificate.passed and res.status is bl.Status.NOT_LOCALLY_OPTIMAL
    assert res.stats["probe"]["objective"] < res.upper_objective - 1e-3


def test_infeasible_upper_level_is_a_status_not_an_answer() -> None:
    p = bard_511()
    x = p.variables[0].sym
    p.upper_constraint(x >= 7)  # lower level infeasible for x > 6 (2x + y <= 12, y >= 2x - ...)
    res = p.solve(starts=3)
    assert not res.success
    assert res.status in (bl.Status.INFEASIBLE, bl.Status.CERTIFICATE_FAILED, bl.Status.ERROR,
                          bl.Status.MAX_ITERATIONS)


def test_result_json_round_trip(tmp_path) -> None:
    res = bard_511().solve(starts=4)
    path = tmp_path / "r.json"
    text = res.to_json(str(path))
    data = json.loads(path.read_text())
    assert data == json.loads(text)
    assert data["status"] == "solved" and data["success"] is True
    assert data["x"]["x"] == pytest.approx([4.0]) and data["certificate"]["passed"] is True


def test_value_evaluates_expressions_at_solution() -> None:
    p = bard_511()
    x, y = p.variables[0].sym, p.variables[1].sym
    res = p.solve(starts=4)
    assert res.value(x + 2 * y) == pytest.approx(12.0, abs=1e-6)


def test_cli_list_and_solve(capsys, tmp_path) -> None:
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "problems; methods:" in out
    for name in ("bard1998-ex5.1.1", "vrft-maxmin", "vrft-destabilize", "willems-eigen", "willems-maxmin",
                 "willems-destabilize"):
        assert name in out
    assert main(["solve", "bard1998-ex5.1.1", "--starts", "4", "--json", str(tmp_path / "r.json")]) == 0
    assert "relative gap 0.00e+00" in capsys.readouterr().out
    save = tmp_path / "a.npz"
    main(["solve", "vrft-maxmin", "--param", "N=256", "--seed", "1", "--starts", "1", "--option", f"save={save}"])
    data = np.load(save)
    assert data["a_u"].shape == (256,) and data["theta_poisoned"].shape == (6,)


def test_nlp_from_the_warm_point_has_short_limits_unless_the_user_sets_them() -> None:
    """An NLP started at hypergradient's answer is a polish: the warm limits (50 iterations, 10 s) replace the
    defaults (3000, 300 s); a user's max_iter or ipopt options win, and plain starts keep the defaults."""
    from bilevel.solvers.ipopt import kkt_nlp_options

    used = {"warm": {"used": True}}
    warm = kkt_nlp_options(None, None, None, used)["ipopt"]
    assert (warm["max_iter"], warm["max_wall_time"]) == (50, 10.0)
    mine = kkt_nlp_options(None, 7, {"max_wall_time": 2.0}, used)["ipopt"]
    assert mine["max_iter"] == 7 and mine["max_wall_time"] == 2.0
    plain = kkt_nlp_options(None, None, None, {})["ipopt"]
    assert plain["max_iter"] == 3000 and plain["max_wall_time"] == 300.0
