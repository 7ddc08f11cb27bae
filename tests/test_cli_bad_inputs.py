"""The CLI on bad input (issue "Honest answers II"): every bad invocation exits non-zero with one line on stderr
(or argparse's usage block), never a traceback, before any work and without touching the disk; only functions
marked @bilevel.problem_builder are ever called; a file in the working directory never shadows a package."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

import bilevel
from bilevel.cli import main

ROOT = str(Path(bilevel.__file__).resolve().parents[1])

OWN = '''
from typing import Literal

import bilevel
from bilevel.problems import registry

LIMIT = 3


@bilevel.problem_builder
def bard(scale: float = 1.0, n: int = 2, flag: bool = False, mode: Literal["a", "b"] = "a"):
    """Bard's example (optimum -12 at x = y = 4), upper objective times `scale`."""
    p = registry.get("bard1998-ex5.1.1")
    p.minimize_upper(scale * p.upper_objective.expr)
    return p


def plain():
    return registry.get("bard1998-ex5.1.1")


@bilevel.problem_builder
def needs(n: int, scale: float = 1.0):
    """Bard's example with a required parameter."""
    return bard(scale, n)


@bilevel.problem_builder
def raises():
    raise ZeroDivisionError("boom")


@bilevel.problem_builder
def not_a_problem():
    return 42
'''

OWN_REF = "own_cli_probe"
ONE_LINE, USAGE = "one line", "usage block"

# (argv, expected text on stderr); "{tmp}" is the test's working directory
CASES: dict[str, tuple[list[str], str]] = {
    # user code: only declared builders are called, and only after they are found
    "os:mkdir is not called": (["solve", "os:mkdir", "--param", "path={tmp}/made"],
                               "decorate mkdir with @bilevel.problem_builder"),
    "os:mkdir in compare": (["compare", "--problems", "os:mkdir", "--methods", "ipopt"], "decorate mkdir with"),
    "undecorated function": (["solve", f"{OWN_REF}:plain"], "decorate plain with @bilevel.problem_builder"),
    "undecorated function by path": (["solve", "{tmp}/" + OWN_REF + ".py:plain"], "decorate plain with"),
    "builder raising": (["solve", f"{OWN_REF}:raises"], "its builder raised ZeroDivisionError: boom"),
    "builder returning a non-problem": (["solve", f"{OWN_REF}:not_a_problem"], "returned int, not a BilevelProblem"),
    "function not found": (["solve", f"{OWN_REF}:missing"], "has no function 'missing'"),
    "attribute not callable": (["solve", f"{OWN_REF}:LIMIT"], "has no function 'LIMIT'"),
    "missing module": (["solve", "no_such_module_cli:f"], "cannot import module 'no_such_module_cli'"),
    "module failing at import": (["solve", "broken_cli_probe:f"], "raised RuntimeError: top-level failure"),
    "missing file": (["solve", "{tmp}/nofile.py:f"], "no file"),
    "no module before the colon": (["solve", ":f"], "give MODULE:FUNCTION"),
    "no function after the colon": (["solve", f"{OWN_REF}:"], "give MODULE:FUNCTION"),
    # --param values typed as the builder declares them
    "param of wrong type (willems)": (["solve", "willems-destabilize", "--param", "delta_u=abc"],
                                      "--param delta_u='abc': expected a finite number"),
    "param NaN (willems)": (["solve", "willems-destabilize", "--param", "delta_u=nan"], "expected a finite number"),
    "param int as text (willems)": (["solve", "willems-destabilize", "--param", "horizon=ten"],
                                    "expected an integer"),
    "param float for an int": (["solve", f"{OWN_REF}:bard", "--param", "n=1.5"],
                               "--param n='1.5': expected an integer"),
    "param text for a float": (["solve", f"{OWN_REF}:bard", "--param", "scale=abc"], "expected a finite number"),
    "param infinite": (["solve", f"{OWN_REF}:bard", "--param", "scale=inf"], "expected a finite number"),
    "param not a bool": (["solve", f"{OWN_REF}:bard", "--param", "flag=maybe"], "expected true or false"),
    "param outside a Literal": (["solve", f"{OWN_REF}:bard", "--param", "mode=c"], "expected one of a, b"),
    "param unknown to the builder": (["solve", f"{OWN_REF}:bard", "--param", "zz=1"], "rejected its parameters"),
    "param given twice": (["solve", f"{OWN_REF}:bard", "--param", "n=1", "--param", "n=2"], "given more than once"),
    "param without a name": (["solve", "macmpec-bard1", "--param", "=3"], "is not NAME=VALUE"),
    "param of wrong type (vrft, generic)": (["solve", "vrft-maxmin", "--method", "ipopt", "--param", "N=abc"],
                                            "--param N='abc': expected an integer"),
    "param for a problem without any": (["solve", "macmpec-bard1", "--param", "N=3"], "rejected its parameters"),
    # --option
    "option naming --method": (["solve", "macmpec-bard1", "--option", "method=global"], "a reserved argument"),
    "option naming the problem": (["solve", "macmpec-bard1", "--option", "problem=x"], "a reserved argument"),
    "option NaN": (["solve", "macmpec-bard1", "--option", "tol=NaN"], "NaN is not a value"),
    "option without =": (["solve", "macmpec-bard1", "--option", "tol"], "is not NAME=VALUE"),
    "option unknown to the method": (["solve", "macmpec-bard1", "--option", "stepsize=1"], "does not take option"),
    # numbers
    "absurd --sims": (["reproduce", "vrft", "--sims", "100000000000"], "sims=100000000000 is invalid"),
    "--sims above a million": (["reproduce", "willems", "--sims", "1000001"], "give an integer in [1, 1000000]"),
    "negative --sims": (["reproduce", "willems-budget", "--sims", "-5"], "sims=-5 is invalid"),
    "--sims not an integer": (["reproduce", "vrft", "--sims", "1e3"], "invalid int value"),
    "--param N=0": (["solve", "vrft-maxmin", "--param", "N=0"], "N=0 samples"),
    "--param N negative (generic method)": (["solve", "vrft-maxmin", "--method", "ipopt", "--param", "N=-4"],
                                            "N=-4 samples"),
    "--param eps_u NaN": (["solve", "vrft-maxmin", "--param", "eps_u=NaN"], "expected a finite number"),
    "--param eps_u inf": (["solve", "vrft-targeted", "--param", "eps_u=inf"], "expected a finite number"),
    "--param eps_y negative": (["solve", "vrft-maxmin", "--param", "eps_y=-0.1"], "eps"),
    "negative seed": (["solve", "macmpec-bard1", "--seed", "-1"], "seed=-1 is invalid"),
    "seed beyond 64 bits": (["compare", "--seed", str(2**64)], "is invalid"),
    "negative --starts": (["solve", "macmpec-bard1", "--starts", "-3"], "starts=-3 is invalid"),
    "--starts 0 on willems-destabilize": (["solve", "willems-destabilize", "--starts", "0"], "starts=0 is invalid"),
    "--workers 0": (["compare", "--workers", "0"], "workers=0 is invalid"),
    "too many --workers": (["reproduce", "willems", "--workers", "5000"], "workers=5000 is invalid"),
    # compare's lists
    "duplicated method": (["compare", "--methods", "ipopt,ipopt"], "ipopt given more than once"),
    "duplicated problem": (["compare", "--problems", "macmpec-bard1,macmpec-bard1"], "given more than once"),
    "empty problem name": (["compare", "--problems", "macmpec-bard1,,bard1998-ex5.1.1"], "has an empty name"),
    "unknown compare method": (["compare", "--methods", "newton"], "--methods newton: unknown"),
    "unknown compare problem": (["compare", "--problems", "nosuch"], "no registered problem 'nosuch'"),
    "compare param nobody has": (["compare", "--param", "zz=1"], "no selected problem has such a parameter"),
    "compare param of wrong type": (["compare", "--problems", "vrft-maxmin", "--param", "N=abc"],
                                    "expected an integer"),
    # paths
    "attack's save in a missing directory": (["solve", "vrft-maxmin", "--option", "save={tmp}/nodir/a.npz"],
                                             "does not exist"),
    "--json unwritable": (["solve", "macmpec-bard1", "--json", "/sys/r.json"], "cannot write in '/sys'"),
    "--json in a missing directory": (["solve", "macmpec-bard1", "--json", "{tmp}/nodir/r.json"], "does not exist"),
    "--json is a directory": (["solve", "macmpec-bard1", "--json", "{tmp}"], "is a directory"),
    "--out unwritable": (["compare", "--problems", "macmpec-bard1", "--out", "/proc/cmp"], "cannot write"),
    "--out is a file": (["reproduce", "willems", "--out", "{tmp}/file.txt"], "is a file, not a directory"),
    "--out under a file": (["reproduce", "vrft", "--out", "{tmp}/file.txt/sub"], "is a file, not a directory"),
    "--out holds another target's run": (["reproduce", "vrft", "--out", "{tmp}/willems_run"],
                                         "holds a `reproduce willems` run"),
    # names and flags
    "unknown problem": (["solve", "nosuch"], "no registered problem 'nosuch'"),
    "misspelt problem": (["solve", "bard1998-ex5.1"], "did you mean 'bard1998-ex5.1.1'"),
    "misspelt problem in list --params": (["list", "--params", "vrft-maxmni"], "did you mean 'vrft-maxmin'?"),
    "unknown tag": (["list", "--tag", "nosuch"], "--tag 'nosuch': no problem carries it; known tags: attack, "),
    "misspelt tag": (["list", "--tag", "textbok"], "did you mean 'textbook'?"),
    "list --params with --tag": (["list", "--params", "vrft-maxmin", "--tag", "vrft"], "give one"),
    "unknown method": (["solve", "macmpec-bard1", "--method", "newton"], "unknown method 'newton'"),
    "vrft parameter on a textbook problem": (["solve", "macmpec-bard1", "--param", "eps_u=0.1"],
                                             "rejected its parameters"),
    "structured on a textbook problem": (["solve", "macmpec-bard1", "--method", "structured"],
                                         "has no structured attack"),
    "unknown structured attack option": (["solve", "vrft-maxmin", "--option", "tol=1"],
                                         "takes max_iter, gain_tol, time_limit, verbose, attack, path, save"),
    "data seed twice": (["solve", "vrft-maxmin", "--seed", "2", "--param", "seed=3"], "give one"),
    "--quick on vrft": (["reproduce", "vrft", "--quick"], "only `reproduce willems`, `reproduce identification`, "
                        "`reproduce defenses`, `reproduce certify` and `reproduce robust-willems` take it"),
    "--learners on vrft": (["reproduce", "vrft", "--learners", "vrft"],
                           "only `reproduce defenses` and `reproduce certify` take it"),
    "unknown defenses learner": (["reproduce", "defenses", "--learners", "vrft,dpt"],
                                 "unknown learner(s) 'dpt'; give a comma-separated subset of vrft,willems,ident,deepc"),
    "unknown certify family": (["reproduce", "certify", "--learners", "vrft,foo"],
                               "certify families: unknown family(s) 'foo'; give a comma-separated subset of vrft,"),
    "bad dask address": (["reproduce", "vrft", "--dask", "nowhere"], "--dask"),
    "unknown command": (["frobnicate"], "invalid choice"),
    "unknown flag": (["solve", "macmpec-bard1", "--frob"], "unrecognized arguments"),
    "missing problem": (["solve"], "the following arguments are required"),
    "bad scenario": (["solve", "vrft-maxmin", "--param", "scenario=C"], "expected one of A, B"),
    "unknown reproduce target": (["reproduce", "nosuch"], "invalid choice"),
    "no command": ([], "the following arguments are required"),
}


@pytest.fixture
def workdir(tmp_path, monkeypatch) -> Path:
    """A working directory with the user modules, a stray file and another target's run; sys.path restored."""
    (tmp_path / f"{OWN_REF}.py").write_text(OWN)
    (tmp_path / "broken_cli_probe.py").write_text('raise RuntimeError("top-level failure")\n')
    (tmp_path / "file.txt").write_text("x")
    (tmp_path / "willems_run").mkdir()
    (tmp_path / "willems_run" / "paper.jsonl").write_text("")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.path", list(sys.path))
    return tmp_path


def _disk(root: Path) -> dict[str, tuple[int, int]]:
    """Every file (size, modification time) and directory under root, bytecode caches aside."""
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) if p.is_file() else "dir" for p in root.rglob("*")
            if "__pycache__" not in p.parts}


def _kind(err: str) -> str:
    """ONE_LINE for `bilevel COMMAND: error: ...` alone, USAGE for argparse's usage block ending in its error."""
    lines = err.splitlines()
    if len(lines) == 1 and lines[0].startswith("bilevel") and ": error: " in lines[0]:
        return ONE_LINE
    assert lines[0].startswith("usage: bilevel") and ": error: " in lines[-1], err
    return USAGE


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_invocation_is_refused_in_one_line_before_any_work(case: str, workdir: Path, capsys) -> None:
    """Exit 2, one line (or argparse's usage block) naming the problem, no traceback, nothing written."""
    argv, message = CASES[case]
    argv = [a.replace("{tmp}", str(workdir)) for a in argv]
    before = _disk(workdir)
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and message in err, err
    assert _kind(err) in (ONE_LINE, USAGE)
    assert _disk(workdir) == before
    assert not (workdir / "made").exists()


def test_the_probe_counts() -> None:
    """At least 40 distinct bad invocations, each a distinct argv."""
    argvs = {tuple(argv) for argv, _ in CASES.values()}
    assert len(CASES) >= 40 and len(argvs) == len(CASES)


@pytest.mark.parametrize("error, code, text", [(MemoryError(), 1, "out of memory; give smaller sizes"),
                                               (OSError(28, "No space left on device", "/x/r.json"), 1,
                                                "No space left on device: '/x/r.json'; check the path"),
                                               (bilevel.SolverFailed("backend crashed"), 1, "backend crashed"),
                                               (bilevel.InvalidData("NaN in u"), 2, "NaN in u")])
def test_errors_during_a_run_are_one_line(error: BaseException, code: int, text: str, monkeypatch, capsys) -> None:
    """A failure during the run (not the caller's input) exits 1, bad data 2; one line either way."""
    def fail(*_, **__):
        raise error

    monkeypatch.setattr("bilevel.cli.solve", fail)
    assert main(["solve", "macmpec-bard1", "--starts", "1"]) == code
    err = capsys.readouterr().err
    assert err.startswith(f"bilevel solve: error: {text}") and err.count("\n") == 1, err


def test_a_declared_builder_runs_with_typed_parameters(workdir: Path, capsys) -> None:
    """By dotted name and by file path, the builder's --param values arrive typed (scale=2: optimum -24)."""
    for ref in (f"{OWN_REF}:bard", f"{workdir}/{OWN_REF}.py:bard"):
        assert main(["solve", ref, "--param", "scale=2", "--param", "n=3", "--param", "flag=true",
                     "--param", "mode=b", "--starts", "4"]) == 0
        out = capsys.readouterr().out
        assert "-24" in out and "solved" in out.lower()


def test_an_unknown_name_is_answered_by_the_closest_names_not_by_every_name(capsys) -> None:
    assert main(["solve", "bard1998-ex5.1"]) == 2
    err = capsys.readouterr().err
    assert "macmpec" not in err and "vrft" not in err and err.count("\n") == 1, err
    assert main(["solve", "zzzz"]) == 2
    assert capsys.readouterr().err == ("bilevel solve: error: no registered problem 'zzzz'; `bilevel list` shows the "
                                       "known ones\n")


def test_list_params_reads_the_registry_and_the_builders_signature(workdir: Path, capsys) -> None:
    """A registered problem's defaults with their types; a builder's annotations (Literal: its values); none."""
    from bilevel.problems import registry

    assert main(["list", "--params", "vrft-maxmin"]) == 0
    out = capsys.readouterr().out.splitlines()
    end = out.index("structured attack (--method structured, the default; --starts and --seed set its starts and seed), "
                    "options given as --option NAME=VALUE:")
    rows = {line.split()[0]: re.split(r"\s{2,}", line.strip())[1:] for line in out[1:end - 1]}
    defaults = registry.spec("vrft-maxmin").defaults
    assert set(rows) == set(defaults) >= {"norm", "N", "seed", "eps_u", "eps_y", "scenario", "convention"}
    assert rows["N"] == ["int", str(defaults["N"])] and rows["eps_y"] == ["float", str(defaults["eps_y"])]
    assert rows["scenario"] == ["one of A, B", "B"] and rows["norm"] == ["one of l2, linf, l1", "l2"]
    attack = {line.split()[0]: re.split(r"\s{2,}", line.strip())[1:] for line in out[end + 1:end + 8]}
    assert attack == {"max_iter": ["int or none", "registry (below)"], "gain_tol": ["float or none", "registry (below)"],
                      "time_limit": ["float or none", "null"], "verbose": ["bool", "false"],
                      "attack": ["one of alternating, joint, white-noise or none", "null"], "path": ["bool", "false"],
                      "save": ["str or none", "null"]}, out
    assert out[end + 8:] == ["registry defaults (bilevel.defaults, bilevel.set_defaults):",
                             *("  " + line for line in bilevel.defaults.describe("vrft.").splitlines())]
    assert main(["list", "--params", "willems-eigen"]) == 0  # the run's stop_when_unstable default, not the method's
    out = capsys.readouterr().out.splitlines()
    assert [re.split(r"\s{2,}", line.strip()) for line in out[-7:-4]] == [
        ["max_iter", "int or none", "registry (below)"], ["ftol", "float or none", "registry (below)"],
        ["stop_when_unstable", "bool", "false"]], out
    assert out[-3:] == ["  " + line for line in bilevel.defaults.describe("willems.hypergradient.").splitlines()]
    assert main(["list", "--params", f"{OWN_REF}:bard"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [re.split(r"\s{2,}", line.strip()) for line in out[1:5]] == [
        ["scale", "float", "1.0"], ["n", "int", "2"], ["flag", "bool", "false"], ["mode", "one of a, b", "a"]], out
    assert main(["list", "--params", f"{OWN_REF}:needs"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [re.split(r"\s{2,}", line.strip()) for line in out[1:3]] == [["n", "int", "(required)"],
                                                                        ["scale", "float", "1.0"]], out
    assert out[3].startswith(f"give them as --param NAME=VALUE, e.g. bilevel solve {OWN_REF}:needs --param n=VALUE")
    assert main(["list", "--params", "bard1998-ex5.1.1"]) == 0
    assert capsys.readouterr().out.splitlines()[1] == "no parameters"


def test_force_writes_into_another_targets_run(workdir: Path) -> None:
    """--force lifts the refusal (checked without running the reproduction)."""
    from bilevel.cli import _check_out

    _check_out(str(workdir / "willems_run"), "vrft", force=True)
    _check_out(str(workdir / "willems_run"), "willems", force=False)


def test_version_comes_from_package_metadata(capsys) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out == f"bilevel {metadata.version('bilevel')}\n"


def _cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """`python -P -m bilevel.cli ARGS` in cwd (-P: Python itself puts no working directory on sys.path)."""
    env = {**os.environ, "PYTHONPATH": ROOT}
    return subprocess.run([sys.executable, "-P", "-m", "bilevel.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.parametrize("case", ["os:mkdir is not called", "param of wrong type (willems)", "absurd --sims"])
def test_console_prints_one_line_and_no_traceback(case: str, workdir: Path) -> None:
    argv = [a.replace("{tmp}", str(workdir)) for a in CASES[case][0]]
    run = _cli(argv, workdir)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.count("\n") == 1 and CASES[case][1] in run.stderr, run.stderr
    assert not (workdir / "made").exists()


def test_a_reader_that_leaves_early_gets_no_error(workdir: Path) -> None:
    """`bilevel list | head -1`: the pipe is closed before the list is written; no error line, no traceback."""
    env = {**os.environ, "PYTHONPATH": ROOT}
    run = subprocess.Popen([sys.executable, "-P", "-m", "bilevel.cli", "list"], cwd=workdir, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    run.stdout.close()
    err = run.stderr.read()
    run.wait(timeout=300)
    assert err == "", err


def test_a_stray_package_name_in_the_working_directory_is_not_imported(workdir: Path) -> None:
    """A matplotlib.py beside the user's module: solve and compare import the real matplotlib (the user's module
    imports it, and compare uses it), the working directory only finding the user's module."""
    (workdir / "matplotlib.py").write_text('raise RuntimeError("stray matplotlib imported")\n')
    (workdir / "uses_matplotlib_cli.py").write_text(
        "import matplotlib\nimport bilevel\nfrom own_cli_probe import bard\n\n"
        "assert 'site-packages' in matplotlib.__file__ or 'dist-packages' in matplotlib.__file__\n"
        "build = bilevel.problem_builder(lambda: bard(2.0))\n")
    solved = _cli(["solve", "uses_matplotlib_cli:build", "--starts", "4"], workdir)
    assert solved.returncode == 0 and "stray" not in solved.stderr, solved.stderr
    compared = _cli(["compare", "--problems", "uses_matplotlib_cli:build", "--methods", "ipopt", "--starts", "4",
                     "--workers", "1", "--out", "cmp"], workdir)
    assert compared.returncode == 0 and "stray" not in compared.stderr, compared.stderr
    assert "-24" in (workdir / "cmp" / "compare.csv").read_text()


def test_solve_verbose_shows_progress_and_attacks_show_their_clean_scale(capsys) -> None:
    """`bilevel solve --verbose` prints the method's progress on stderr; an attack's output names its clean-data
    values next to the attacked ones (issue 50); a structured attack without progress reports says so in one line."""
    assert main(["solve", "bard1998-ex5.1.1", "--method", "ipopt", "--starts", "2", "--verbose"]) == 0
    out, err = capsys.readouterr()
    assert "[ipopt] start 1/2:" in err and "[ipopt] start 2/2:" in err
    assert main(["solve", "vrft-maxmin", "--param", "N=64", "--starts", "1"]) == 0
    out, _ = capsys.readouterr()
    assert "clean data (the scale of the attack's numbers): value_clean " in out
    assert main(["solve", "willems-eigen", "--verbose"]) == 2
    _, err = capsys.readouterr()
    assert "--verbose: the structured attack of willems-eigen reports no progress" in err
