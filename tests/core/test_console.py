"""What a solve prints on the console: nothing from its backends unless asked (verbose=True), and results that
summarize long arrays."""

import re

import casadi as ca
import numpy as np

import bilevel as bl
from bilevel.problems import registry


def test_global_method_prints_nothing_on_stdout(capfd) -> None:
    """HiGHS's banner is written by its C++ code on file descriptor 1: the node LPs are silenced before it can be."""
    res = registry.get("bard1998-ex5.1.1").solve(method="global")
    out, _ = capfd.readouterr()
    assert res.status is bl.Status.SOLVED and abs(res.upper_objective - -12.0) < 1e-6
    assert out == "", out


def test_a_result_summarizes_long_arrays_in_one_line() -> None:
    """An array of more than SHOWN entries prints as its size, norm and first and last entries; short ones in full."""
    res = bl.BilevelResult(bl.Status.SOLVED, "", "ipopt", "p", {"a": np.arange(1024.0), "b": np.array([4.0])},
                           {"y": np.ones((40, 40))}, {}, 1.0, 0.0, None, 0.0, 1)
    lines = {line.split(":", 1)[0].strip(): line.split(":", 1)[1] for line in repr(res).splitlines()}
    norm = np.sqrt(sum(k * k for k in range(1024)))
    head, entries, tail = re.fullmatch(r" \{(a: 1024 entries, norm [^,]+), \[(.*)\], (b: \[4\.\])\}", lines["x"]).groups()
    assert head == f"a: 1024 entries, norm {norm:.6g}" and tail == "b: [4.]"
    assert [float(e) for e in entries.replace("...", "").split()] == [0, 1, 2, 1021, 1022, 1023]
    assert lines["y"] == " {y: 40x40 entries, norm 40, [1. 1. 1. ... 1. 1. 1.]}"


def test_cli_solve_prints_a_summary_and_says_where_the_full_values_go(capsys) -> None:
    from bilevel.cli import main

    assert main(["solve", "vrft-maxmin", "--method", "ipopt", "--starts", "1"]) == 0
    out = capsys.readouterr().out
    assert "a_u: 64 entries, norm" in out and len(out.splitlines()) < 20, out
    assert "--json PATH writes every value" in out


def test_a_function_outside_its_domain_prints_nothing_and_never_wins(capfd) -> None:
    """log(x) on a box reaching x < 0: starts there make IPOPT stop with Invalid_Number_Detected (their status in
    res.start_records), silently; such a start's point is infinitely infeasible (NaN), so a converged start is the answer:
    min (y - 1)^2 with y = x, optimum 0 at x = 1."""
    p = bl.BilevelProblem("log-domain")
    x = p.upper_variable("x", lb=-1, ub=4)
    y = p.lower_variable("y")
    p.minimize_lower((y - x) ** 2)
    p.upper_constraint(ca.log(x) >= -3)
    p.minimize_upper((y - 1) ** 2)
    res = p.solve("ipopt", starts=8, seed=0)
    assert "Invalid_Number_Detected" in [s["status"] for s in res.start_records]
    assert res.status is bl.Status.SOLVED and abs(res.x["x"][0] - 1.0) < 1e-6, res.message
    out, err = capfd.readouterr()
    assert out == "" and err == "", err


def test_an_inaccurate_conic_solve_is_a_status_not_a_warning() -> None:
    """SCS stopped after 50 iterations: the learner's status says optimal_inaccurate; cvxpy's warning is not shown."""
    import warnings

    from bilevel.ddc.data import batch_reactor_data
    from bilevel.ddc.depersis_tesi import lqr_controller

    x, u = batch_reactor_data(20, np.random.default_rng(0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        controller = lqr_controller(x, u, solver="scs", solver_options={"max_iters": 50})
    assert controller.status == "optimal_inaccurate"
    assert not [w for w in caught if "inaccurate" in str(w.message)], [str(w.message) for w in caught]
