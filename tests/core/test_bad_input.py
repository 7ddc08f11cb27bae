"""Bad input through the API and the CLI: a named exception (or an honest status), never a raw traceback,
never `solved` with a wrong answer (issue 16)."""

from __future__ import annotations

import subprocess
import sys

import casadi as ca
import numpy as np
import pytest

import bilevel as bl
from bilevel.cli import main
from bilevel.errors import (BilevelError, InvalidData, ModelError, NonConvexLowerLevel, UnknownName,
                            UnknownOption)
from bilevel.problems import registry
from tests.conftest import bard_511


def _problem(lower=None, upper=None, lower_constraint=None, **var) -> bl.BilevelProblem:
    """x in [0, 2], y >= 0 (or var overrides); F = (x - 1)^2 + y^2 and f = (y - x)^2 unless replaced."""
    p = bl.BilevelProblem("bad")
    x = p.upper_variable("x", lb=0, ub=2)
    y = p.lower_variable("y", **(var or {"lb": 0}))
    p.minimize_upper(upper(x, y) if upper else (x - 1) ** 2 + y ** 2)
    p.minimize_lower(lower(x, y) if lower else (y - x) ** 2)
    if lower_constraint:
        p.lower_constraint(lower_constraint(x, y))
    return p


def _decl(fn):
    """Run a declaration on a fresh problem with x (upper, 2) and y (lower, 2) declared."""
    def run():
        p = bl.BilevelProblem()
        x = p.upper_variable("x", 2)
        y = p.lower_variable("y", 2)
        fn(p, x, y)
        return p
    return run


API_CASES = {
    "lower ub -inf": (lambda: _problem(ub=-np.inf), ModelError, "no feasible value"),
    "lower lb +inf": (lambda: _problem(lb=np.inf), ModelError, "no feasible value"),
    "upper lb +inf": (_decl(lambda p, x, y: p.upper_variable("z", lb=np.inf)), ModelError, "no feasible value"),
    "crossed bounds": (lambda: _problem(lb=2, ub=1), ModelError, "exceeds its upper bound"),
    "NaN bound": (lambda: _problem(lb=np.nan), ModelError, "contains NaN"),
    "bound length": (_decl(lambda p, x, y: p.lower_variable("z", 3, lb=[0, 1])), ModelError, "has 2 entries"),
    "string bound": (_decl(lambda p, x, y: p.lower_variable("z", lb="zero")), ModelError, "must be a number"),
    "inf start": (_decl(lambda p, x, y: p.lower_variable("z", start=np.inf)), ModelError, "finite start"),
    "zero shape": (_decl(lambda p, x, y: p.lower_variable("z", (0, 1))), ModelError, "must be positive"),
    "bad shape": (_decl(lambda p, x, y: p.lower_variable("z", "3x3")), ModelError, "must be an int or a pair"),
    "bad name": (_decl(lambda p, x, y: p.lower_variable("1z")), ModelError, "Python identifier"),
    "duplicate name": (_decl(lambda p, x, y: p.lower_variable("y")), ModelError, "already declared"),
    "symmetric not square": (_decl(lambda p, x, y: p.lower_variable("S", (2, 3), symmetric=True)), ModelError,
                             "must be square"),
    "symmetric bound not symmetric": (_decl(lambda p, x, y: p.lower_variable("S", (2, 2), symmetric=True,
                                                                            lb=[[0, 1], [2, 0]])),
                                      ModelError, "not symmetric"),
    "y <= inf": (_decl(lambda p, x, y: p.lower_constraint(y <= np.inf)), ModelError, "bound at infinity"),
    "y >= -inf": (_decl(lambda p, x, y: p.lower_constraint(y >= -np.inf)), ModelError, "bound at infinity"),
    "x <= inf upper": (_decl(lambda p, x, y: p.upper_constraint(x <= np.inf)), ModelError, "bound at infinity"),
    "not a comparison": (_decl(lambda p, x, y: p.lower_constraint(y + 1)), ModelError, "not a comparison"),
    "python bool": (_decl(lambda p, x, y: p.lower_constraint(True)), ModelError, "expects a CasADi comparison"),
    "vector objective": (_decl(lambda p, x, y: p.minimize_lower(y)), ModelError, "must be scalar"),
    "string objective": (_decl(lambda p, x, y: p.minimize_upper("x")), ModelError, "CasADi expression"),
    "non-symmetric LMI": (_decl(lambda p, x, y: p.lower_psd_constraint(ca.vertcat(ca.horzcat(y[0], 1),
                                                                                 ca.horzcat(0, y[1])))),
                          ModelError, "not symmetric"),
}

SOLVE_CASES = {
    "NaN in lower objective data": (lambda: _problem(lower=lambda x, y: (y - np.nan * x) ** 2), InvalidData,
                                    "NaN/inf in the data"),
    "inf in lower constraint data": (lambda: _problem(lower_constraint=lambda x, y: np.inf * x + y <= 1), InvalidData,
                                     "NaN/inf in the data"),
    "NaN in upper objective data": (lambda: _problem(upper=lambda x, y: x + np.nan * y), InvalidData,
                                    "NaN/inf in the data"),
    "lower objective without y": (lambda: _problem(lower=lambda x, y: x ** 2), ModelError, "does not depend"),
    "concave lower minimization": (lambda: _problem(lower=lambda x, y: -(y - x) ** 2), NonConvexLowerLevel,
                                   "not convex"),
    "non-convex inside bounds": (lambda: _problem(lower=lambda x, y: (y - x) ** 2 - 100 * ca.exp(-(y - 8) ** 2),
                                                  lb=-10, ub=10), NonConvexLowerLevel, "inside the declared bounds"),
    "non-affine equality": (lambda: _problem(lower_constraint=lambda x, y: y ** 2 == x), NonConvexLowerLevel,
                            "not affine"),
    "foreign symbol": (lambda: _problem(lower=lambda x, y: (y - ca.SX.sym("q")) ** 2), ModelError, "not variables"),
    "no lower objective": (lambda: _no_lower_objective(), ModelError, "no lower objective"),
}

OPTION_CASES = {
    "unknown method": ({"method": "newton"}, ModelError, "unknown method"),
    "unknown option": ({"method": "ipopt", "stepsize": 1.0}, UnknownOption, "does not take option"),
    "starts 0": ({"starts": 0}, ModelError, "starts=0 is invalid"),
    "starts float": ({"starts": 2.5}, ModelError, "starts=2.5 is invalid"),
    "starts bool": ({"starts": True}, ModelError, "starts=True is invalid"),
    "gtol negative": ({"gtol": -1e-8}, ModelError, "gtol=-1e-08 is invalid"),
    "nlp_tol NaN": ({"nlp_tol": float("nan")}, ModelError, "nlp_tol=nan is invalid"),
    "max_iter negative": ({"max_iter": -5}, ModelError, "max_iter=-5 is invalid"),
    "certificate_tol zero": ({"certificate_tol": 0.0}, ModelError, "certificate_tol=0.0 is invalid"),
    "certificate_tol string": ({"certificate_tol": "1e-6"}, ModelError, "certificate_tol='1e-6' is invalid"),
    "seed negative": ({"seed": -1}, ModelError, "seed=-1 is invalid"),
    "relaxation factor": ({"method": "relaxation", "factor": 2.0}, ModelError,
                          "factor=2.0 is invalid: it must be a finite number in \\(0, 1\\)"),
}


def _no_lower_objective() -> bl.BilevelProblem:
    p = bl.BilevelProblem()
    x = p.upper_variable("x")
    p.lower_variable("y")
    p.minimize_upper(x ** 2)
    return p


@pytest.mark.parametrize("case", sorted(API_CASES))
def test_declaration_errors_are_named(case: str) -> None:
    build, exc, match = API_CASES[case]
    with pytest.raises(exc, match=match):
        build()


@pytest.mark.parametrize("case", sorted(SOLVE_CASES))
def test_problem_errors_are_named_before_any_solve(case: str) -> None:
    build, exc, match = SOLVE_CASES[case]
    with pytest.raises(exc, match=match):
        build().solve("ipopt", starts=1)


@pytest.mark.parametrize("case", sorted(OPTION_CASES))
def test_option_errors_are_named(case: str) -> None:
    options, exc, match = OPTION_CASES[case]
    with pytest.raises(exc, match=match):
        bl.solve(bard_511(), **options)


def test_unknown_problem_is_a_named_key_error() -> None:
    with pytest.raises(UnknownName, match="no registered problem 'nope'") as info:
        registry.get("nope")
    assert isinstance(info.value, KeyError) and str(info.value).startswith("no registered")


def test_infeasible_lower_level_is_not_solved() -> None:
    p = _problem(lower_constraint=lambda x, y: y <= -1 - x ** 2)  # y >= 0 and y <= -1 - x^2: empty
    res = p.solve("ipopt", starts=2)
    assert not res.success and res.status is not bl.Status.SOLVED


# -- CLI: one line on stderr, exit 2, no traceback ---------------------------------------------------------
CLI_CASES = {
    "unknown problem": (["solve", "nosuch"], "no registered problem 'nosuch'"),
    "unknown method": (["solve", "macmpec-bard1", "--method", "newton"], "unknown method 'newton'"),
    "unknown vrft method": (["solve", "vrft-maxmin", "--method", "newton"], "unknown method 'newton'; choose auto, "
                            "structured"),
    "param without =": (["solve", "macmpec-bard1", "--param", "foo"], "is not NAME=VALUE"),
    "unknown param": (["solve", "macmpec-bard1", "--param", "foo=1"], "rejected its parameters"),
    "bad option value": (["solve", "macmpec-bard1", "--option", "starts=0"], "starts=0 is invalid"),
    "unknown option": (["solve", "macmpec-bard1", "--option", "stepsize=1"], "does not take option"),
    "starts 0": (["solve", "macmpec-bard1", "--starts", "0"], "starts=0 is invalid"),
    "json to missing dir": (["solve", "macmpec-bard1", "--json", "/nonexistent-dir/r.json"], "does not exist"),
    "save to missing dir": (["solve", "vrft-maxmin", "--option", "save=/nonexistent-dir/a.npz"], "does not exist"),
    "save for a textbook problem": (["solve", "macmpec-bard1", "--option", "save=attack"], "does not take option"),
}


@pytest.mark.parametrize("case", sorted(CLI_CASES))
def test_cli_named_errors_print_one_line_and_exit_2(case: str, capsys) -> None:
    argv, message = CLI_CASES[case]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("bilevel solve: error: ") and message in err, err
    assert "Traceback" not in err


def test_cli_json_to_a_directory(tmp_path, capsys) -> None:
    assert main(["solve", "macmpec-bard1", "--json", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err


def test_cli_out_pointing_at_a_file(tmp_path, capsys) -> None:
    f = tmp_path / "file.txt"
    f.write_text("x")
    assert main(["compare", "--out", str(f), "--problems", "macmpec-bard1"]) == 2
    assert "is a file, not a directory" in capsys.readouterr().err


def test_cli_console_script_prints_no_traceback() -> None:
    out = subprocess.run([sys.executable, "-m", "bilevel.cli", "solve", "nosuch"], capture_output=True, text=True)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines() == [out.stderr.strip()]


def test_cli_json_is_strict(tmp_path) -> None:
    path = tmp_path / "r.json"
    assert main(["solve", "macmpec-bard1", "--starts", "1", "--json", str(path)]) == 0
    back = bl.BilevelResult.from_json(str(path))
    assert back.success and back.upper_objective == pytest.approx(17.0, abs=1e-6)


def test_all_named_errors_share_one_base() -> None:
    for exc in (InvalidData, ModelError, NonConvexLowerLevel, UnknownName, UnknownOption):
        assert issubclass(exc, BilevelError)
