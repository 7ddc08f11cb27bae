"""Every code block of the README and docs/*.md is run or checked: Python blocks are executed by their page's test
(run_page), `bilevel list` and `bilevel solve` commands are run, the long `compare` and `reproduce` commands are
parsed and pass the checks the CLI makes before any work, and any other shell command sits in a block marked
`<!-- shell: REASON -->`; text blocks are displays (a formula, a signature, a printed output)."""

from __future__ import annotations

import sys
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest

import bilevel as bl
from bilevel.cli import _check_numbers, _check_paths, _names, build_parser, main
from bilevel.problems import registry
from tests.docs_pages import PAGES, ROOT, SHELL_REASON, Block, code_blocks, page_path, run_page

BLOCKS = [b for page in PAGES for b in code_blocks(page)]
RUN = ("list", "solve")
"""Commands the tests run; compare and reproduce sweep for minutes to hours and are checked only."""


def _bilevel(command: list[str]) -> bool:
    return Path(command[0]).name == "bilevel"


def _commands() -> dict[tuple[str, ...], Block]:
    """Each distinct bilevel command of the pages (argv after `bilevel`) and the first block showing it."""
    out: dict[tuple[str, ...], Block] = {}
    for b in BLOCKS:
        for command in b.commands() if b.kind == "shell" else []:
            if _bilevel(command):
                out.setdefault(tuple(command[1:]), b)
    return out


COMMANDS = _commands()


def test_every_page_with_python_is_executed_by_a_test() -> None:
    tests = "\n".join(p.read_text() for p in (ROOT / "tests").rglob("test_*.py"))
    for page in PAGES:
        if any(b.kind == "python" for b in code_blocks(page)):
            assert f'run_page("{page}"' in tests, f"{page} has Python blocks that no test runs: add run_page({page!r})"


def test_shell_blocks_hold_bilevel_commands_or_say_why_not() -> None:
    assert len(COMMANDS) >= 15
    for page in PAGES:  # a marker must be the last non-blank line before its block
        markers = len(SHELL_REASON.findall(page_path(page).read_text()))
        assert markers == sum(b.reason is not None for b in code_blocks(page)), f"{page}: a shell marker marks no block"
    for b in BLOCKS:
        if b.kind == "shell":
            others = [" ".join(c) for c in b.commands() if not _bilevel(c)]
            assert b.commands(), f"{b.page} line {b.line}: an empty shell block"
            assert not others or b.reason, (f"{b.page} line {b.line}: {others[0]!r} is not run by any test; mark the "
                                             "block `<!-- shell: REASON -->` or make it a bilevel command")


@pytest.mark.parametrize("argv", sorted(COMMANDS), ids=lambda argv: " ".join(argv))
def test_bilevel_commands_of_the_docs_run_or_pass_the_clis_checks(argv: tuple[str, ...], tmp_path, monkeypatch,
                                                                   capsys) -> None:
    """list and solve (of a registered problem) run and succeed; compare, reproduce and solve MODULE:FUNCTION (run
    by the page's own test) are parsed, and their numbers, paths and problem and method names checked."""
    monkeypatch.chdir(tmp_path)
    where = f"{COMMANDS[argv].page} line {COMMANDS[argv].line}: bilevel {' '.join(argv)}"
    args = build_parser().parse_args(list(argv))
    if args.command in RUN and ":" not in getattr(args, "problem", ""):
        assert main(list(argv)) == 0, f"{where} failed: {capsys.readouterr().err}"
        return
    _check_numbers(args)
    _check_paths(args)
    if args.command == "compare":
        for name in _names(args.problems, "--problems") if args.problems else []:
            assert ":" in name or registry.spec(name), where
        methods = _names(args.methods, "--methods") if args.methods else []
        assert set(methods) <= set(bl.METHODS) | {"structured"}, where


def test_solvers_page_builder_runs_from_the_command_line(tmp_path, monkeypatch, capsys) -> None:
    """docs/solvers.md's builder, saved as mymodule.py, solved as the page's command line says: -24 at x = y = 4."""
    run_page("solvers.md")
    python = next(b for b in code_blocks("solvers.md") if b.kind == "python")
    (tmp_path / "mymodule.py").write_text("\n".join(python.lines) + "\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.path", list(sys.path))
    argv = next(a for a in COMMANDS if a[:2] == ("solve", "mymodule.py:build"))
    assert main(list(argv)) == 0
    out = capsys.readouterr().out
    assert "upper_objective: -24.0" in out and "x: {x: [4.]}" in out and "y: {y: [4.]}" in out, out


class _Served(Exception):
    """Raised by the stand-in time.sleep: the page's script reached its serving loop."""


def test_clusters_page_script_serves_a_sweep(tmp_path, monkeypatch) -> None:
    """docs/clusters.md's cluster.py with SLURMCluster replaced by a LocalCluster of one worker process: it prints the
    scheduler's address and serves, and `bilevel compare --dask ADDRESS` runs on it (Bard's optimum -12)."""
    distributed = pytest.importorskip("distributed")

    class SLURMCluster:
        """The keywords of dask_jobqueue.SLURMCluster, kept; a local scheduler and worker processes instead of jobs."""

        def __init__(self, **kwargs: object) -> None:
            self.kwargs = kwargs
            self.local = distributed.LocalCluster(n_workers=0, threads_per_worker=1, processes=True,
                                                  dashboard_address=None, host="127.0.0.1")

        def scale(self, jobs: int) -> None:
            self.local.scale(min(jobs, 1))

        @property
        def scheduler_address(self) -> str:
            return self.local.scheduler_address

    real_sleep = time.sleep

    def sleep(seconds: float) -> None:
        if threading.current_thread() is threading.main_thread():
            raise _Served
        real_sleep(seconds)

    monkeypatch.setitem(sys.modules, "dask_jobqueue", types.SimpleNamespace(SLURMCluster=SLURMCluster))
    monkeypatch.setattr(time, "sleep", sleep)
    namespace: dict = {}
    with pytest.raises(_Served):
        run_page("clusters.md", namespace)
    monkeypatch.setattr(time, "sleep", real_sleep)
    cluster = namespace["cluster"]
    try:
        assert cluster.kwargs["cores"] == 1 and cluster.kwargs["processes"] == 1
        out = tmp_path / "cmp"
        assert main(["compare", "--problems", "bard1998-ex5.1.1", "--methods", "ipopt", "--starts", "2",
                     "--dask", cluster.scheduler_address, "--out", str(out)]) == 0
        assert "-12" in (out / "compare.csv").read_text()
    finally:
        cluster.local.close()


def test_willems_page_builds_and_attacks_up_to_the_generic_route() -> None:
    """docs/willems.md up to the KKT route (which takes a minute; the slow test runs it): results of willems-eigen,
    the spectral radius that of the true batch reactor under the learned gain, the ascent at least DE's criterion."""
    from bilevel.ddc.plants import batch_reactor

    namespace = run_page("willems.md", until="kkt = ")
    res, de = namespace["res"], namespace["de"]
    assert res.problem == de.problem == "willems-eigen" and res.upper_objective >= de.upper_objective
    plant = batch_reactor()
    rho = max(abs(np.linalg.eigvals(plant.A + plant.B @ res.stats["gain"])))
    assert abs(res.stats["spectral_radius"] - rho) <= 1e-9 * rho


@pytest.mark.slow
def test_willems_page_runs_whole() -> None:
    """The generic KKT route too: a certified answer of willems-eigen."""
    kkt = run_page("willems.md")["kkt"]
    assert kkt.problem == "willems-eigen" and kkt.certificate.passed


def test_solve_docstring_names_every_method() -> None:
    doc = bl.BilevelProblem.solve.__doc__
    assert all(f'- "{name}": ' in doc for name in bl.METHODS), doc
