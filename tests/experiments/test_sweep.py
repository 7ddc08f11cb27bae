"""Sweeps never mix settings, never lose rows, repair malformed rows, stop on SIGINT/SIGTERM, and the CLI
rejects bad numbers before any work."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import time

import psutil
import pytest

from bilevel.cli import main
from bilevel.experiments import vrft, willems
from bilevel.experiments.executor import BatchTask, LocalExecutor
from bilevel.experiments.sweep import pace, run_sweep

from .tables import BILEVEL, row_count, table_difference, tables, wait_for_rows

WILLEMS = ["reproduce", "willems", "--quick", "--sims", "1", "--workers", "2"]


def _strip_times(rows: list[dict]) -> list[dict]:
    """Rows without their wall times (a budget-path row's cells too)."""
    return [{k: _strip_times(v) if k == "cells" else v for k, v in r.items() if k != "wall_time"} for r in rows]


@pytest.mark.parametrize("signum,executor", [(signal.SIGINT, []), (signal.SIGTERM, []),
                                             (signal.SIGINT, ["--dask", "local"])])
def test_signal_to_main_process_only_stops_within_5s_and_resume_matches(tmp_path, willems_seed0, signum,
                                                                        executor) -> None:
    """The signal goes to the main process alone (as `timeout -s INT` sends it): workers (local pool or Dask
    LocalCluster) are stopped, the process exits within 5 s with 128 + signum, finished rows are kept, and the
    resumed run's tables equal an uninterrupted run's (to rounding: table_difference)."""
    out = str(tmp_path / "run")
    paper = os.path.join(out, "paper.jsonl")
    proc = subprocess.Popen(BILEVEL + WILLEMS + executor + ["--out", out], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_for_rows(proc, paper, 2)
        children = psutil.Process(proc.pid).children(recursive=True)
        t0 = time.monotonic()
        os.kill(proc.pid, signum)
        proc.wait(timeout=5)
        assert time.monotonic() - t0 < 5
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    stderr = proc.stderr.read()
    assert proc.returncode == 128 + signum, stderr
    assert "workers stopped" in stderr and "Traceback" not in stderr
    psutil.wait_procs(children, timeout=2)
    assert not [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
    kept = row_count(paper)
    assert 2 <= kept < len(willems.paper_tasks(willems.make_plan(1, True), 0))
    if signum == signal.SIGTERM or executor:
        return  # the resume below is the same code path whichever signal or executor stopped the run
    assert main(WILLEMS + ["--out", out]) == 0
    with open(paper, encoding="utf-8") as fh:
        keys = [json.loads(line)["key"] for line in fh]
    assert len(keys) == len(set(keys)) == len(willems.paper_tasks(willems.make_plan(1, True), 0))
    assert not (diff := table_difference(out, willems_seed0)), diff


def test_willems_other_seed_recomputes_and_report_states_the_rows_seed(tmp_path, willems_seed0) -> None:
    """`reproduce willems --seed 5` on a seed-0 directory computes every row anew; the report's seed comes
    from the rows, and the tables differ from seed 0's."""
    out = str(tmp_path / "w")
    shutil.copytree(willems_seed0, out)
    before = row_count(os.path.join(out, "paper.jsonl"))
    assert main(WILLEMS + ["--out", out, "--seed", "5"]) == 0
    assert row_count(os.path.join(out, "paper.jsonl")) == 2 * before  # seed-0 rows kept, none reused
    report = open(os.path.join(out, "report.md"), encoding="utf-8").read()
    assert "Settings read from the result rows: seed 5," in report
    assert "seed 0" not in report
    assert tables(out)["table_paper.csv"] != tables(willems_seed0)["table_paper.csv"]


def test_vrft_other_seed_or_budget_never_reuses_rows(tmp_path) -> None:
    """A VRFT sweep resumed with another seed (or another budget norm / N) recomputes every task; going back
    to the first settings reuses its rows, which are the same numbers as before."""
    path = str(tmp_path / "white-noise.jsonl")
    lines: list[str] = []
    tasks = {s: vrft.cell_tasks(1, s, "paper", "maxmin", "white-noise", eps_u=(0.1,), eps_y=(0.05,))
             for s in (0, 1)}
    first = run_sweep(vrft.attack_task, tasks[0], path, LocalExecutor(1), lines.append, "t")
    lines.clear()
    second = run_sweep(vrft.attack_task, tasks[1], path, LocalExecutor(1), lines.append, "t")
    assert any("0 of 2 already done (2 row(s) of other settings not reused); running 2" in ln for ln in lines)
    assert [r["task"]["seed"] for r in second] == [t["seed"] for t in tasks[1]] != [t["seed"] for t in tasks[0]]
    assert [r["value"] for r in second] != [r["value"] for r in first]
    lines.clear()
    other_n = [{**t, "N": 256} for t in tasks[0]]
    assert [r["task"]["N"] for r in run_sweep(vrft.attack_task, other_n, path, LocalExecutor(1), lines.append,
                                              "t")] == [256, 256]
    assert any("running 2" in ln for ln in lines)
    lines.clear()
    assert run_sweep(vrft.attack_task, tasks[0], path, LocalExecutor(1), lines.append, "t") == first
    assert not lines and row_count(path) == 6


def test_compare_more_starts_never_reuses_a_one_start_row(tmp_path) -> None:
    """`compare --starts 8` after `--starts 1` recomputes; the CSV and the Markdown state 8 starts."""
    out = str(tmp_path / "cmp")
    args = ["compare", "--problems", "bard1998-ex5.1.1", "--methods", "ipopt", "--workers", "1", "--out", out]
    assert main(args + ["--starts", "1"]) == 0
    assert main(args + ["--starts", "8"]) == 0
    assert row_count(os.path.join(out, "compare.jsonl")) == 2
    with open(os.path.join(out, "compare.csv"), encoding="utf-8") as fh:
        header, row = [line.strip().split(",") for line in fh]
    assert row[header.index("starts")] == "8"
    assert float(row[header.index("objective")]) == pytest.approx(-12.0, abs=1e-6)  # one start stops at -7
    assert "Settings read from the rows: starts 8; seed 0." in open(os.path.join(out, "compare.md")).read()


def test_compare_never_reuses_a_row_of_an_older_method(tmp_path, monkeypatch) -> None:
    """A row computed before a registered method changed its answers (METHODS_VERSION bumped) is not reused."""
    import bilevel.experiments.compare as cmp

    path, lines = str(tmp_path / "cmp" / "compare.csv"), []
    cmp.compare(["bard1998-ex5.1.1"], ["ipopt"], path, starts=1, workers=1, progress=None)
    monkeypatch.setattr(cmp, "METHODS_VERSION", "methods-test")
    cmp.compare(["bard1998-ex5.1.1"], ["ipopt"], path, starts=1, workers=1, progress=lines.append)
    assert any("1 row(s) of other settings not reused" in line for line in lines)
    assert row_count(str(tmp_path / "cmp" / "compare.jsonl")) == 2


def test_malformed_rows_are_reported_set_aside_and_recomputed(tmp_path) -> None:
    """A line that does not parse, a row lacking a result field, one lacking its digest and a truncated last
    line: each is reported, moved to <path>.rejected and recomputed to the same numbers."""
    path = str(tmp_path / "s.jsonl")
    tasks = vrft.cell_tasks(1, 0, "paper", "maxmin", "white-noise", eps_u=(0.1,), eps_y=(0.01, 0.05))
    first = run_sweep(vrft.attack_task, tasks, path, LocalExecutor(1), None, "t", valid=vrft.valid_row)
    with open(path, encoding="utf-8") as fh:
        lines = fh.readlines()
    rows = [json.loads(line) for line in lines]
    del rows[1]["value"], rows[2]["digest"]
    with open(path, "w", encoding="utf-8") as fh:
        fh.write('{"key": "paper/maxmin/white-noise/A/0.1/0.01/0", "val\n')
        fh.writelines(json.dumps(r) + "\n" for r in rows[1:3])
        fh.write(lines[3][:40])
    report: list[str] = []
    again = run_sweep(vrft.attack_task, tasks, path, LocalExecutor(1), report.append, "t", valid=vrft.valid_row)
    assert _strip_times(again) == _strip_times(first)
    assert any("set aside 4 malformed row(s)" in ln and "line 1: not JSON" in ln and "line 2: lacks result fields"
               in ln and "line 3: lacks digest" in ln and "line 4: truncated line" in ln for ln in report)
    assert row_count(path + ".rejected") == 4 and row_count(path) == 4
    report.clear()
    run_sweep(vrft.attack_task, tasks, path, LocalExecutor(1), report.append, "t", valid=vrft.valid_row)
    assert not report


OWN_PROBLEMS = '''
import bilevel
from bilevel.problems import registry


@bilevel.problem_builder
def bard(scale=1.0):
    """Bard's example (optimum -12 at x = y = 4), upper objective times `scale`."""
    p = registry.get("bard1998-ex5.1.1")
    p.minimize_upper(scale * p.upper_objective.expr)
    return p


@bilevel.problem_builder
def not_a_problem():
    return 42
'''


def test_compare_runs_a_users_own_problem_by_module_path(tmp_path, monkeypatch, capsys) -> None:
    """Issue 16: `compare --problems mod:function` imports a builder from the working directory; its keyword
    defaults are --param parameters; a bad module, function or return type is a one-line error (exit 2)."""
    (tmp_path / "own_problems_issue16.py").write_text(OWN_PROBLEMS)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.path", list(__import__("sys").path))
    args = ["compare", "--methods", "ipopt", "--workers", "1", "--starts", "4", "--out", str(tmp_path / "cmp")]
    assert main(args + ["--problems", "own_problems_issue16:bard", "--param", "scale=2"]) == 0
    with open(tmp_path / "cmp" / "compare.csv", encoding="utf-8") as fh:
        header, row = [line.strip().split(",") for line in fh]
    assert row[header.index("problem")] == "own_problems_issue16:bard"
    assert float(row[header.index("objective")]) == pytest.approx(-24.0, abs=1e-6)
    capsys.readouterr()
    for ref, message in (("no_such_module_issue16:f", "cannot import module"),
                         ("own_problems_issue16:missing", "has no function 'missing'"),
                         ("own_problems_issue16:not_a_problem", "returned int, not a BilevelProblem")):
        assert main(args + ["--problems", ref, "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err and not (tmp_path / "bad").exists()


@pytest.mark.parametrize("argv", [["reproduce", "vrft", "--sims", "0"], ["reproduce", "vrft", "--sims", "-3"],
                                  ["reproduce", "willems", "--workers", "0"], ["reproduce", "vrft", "--seed", "-1"],
                                  ["compare", "--starts", "0"], ["reproduce", "vrft", "--dask", "nowhere"],
                                  ["reproduce", "vrft", "--dask", "tcp://127.0.0.1:1", "--workers", "2"]])
def test_bad_numbers_are_one_line_errors_before_any_work(tmp_path, capsys, argv) -> None:
    """Exit 2 with one line on stderr, nothing written."""
    out = tmp_path / "out"
    assert main(argv + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"bilevel {argv[0]}: error: ")
    assert not out.exists()


def test_compare_runs_the_structured_attack_beside_the_generic_methods(tmp_path) -> None:
    """Method 'structured' is an attack problem's own attack, a BilevelResult like any method's: on vrft-maxmin it
    is certified and as strong as the generic hypergradient from one start on the same instance (to the attack's
    stopping tolerance: measured 0.1550020 against 0.1550058); a textbook problem has none
    (not applicable); an unknown method name is a one-line error before any work."""
    out = str(tmp_path / "cmp")
    args = ["compare", "--problems", "vrft-maxmin,bard1998-ex5.1.1", "--methods", "structured,hypergradient",
            "--starts", "1", "--workers", "1", "--out", out]
    assert main(args) == 0
    rows = {(r["problem"], r["method"]): r for r in csv.DictReader(open(os.path.join(out, "compare.csv")))}
    mine, generic = rows[("vrft-maxmin", "structured")], rows[("vrft-maxmin", "hypergradient")]
    assert mine["status"] == "solved" and mine["certified"] == "True"
    assert float(mine["objective"]) >= float(generic["objective"]) * (1 - 1e-4)  # the attack stops at TOL = 1e-4
    assert rows[("bard1998-ex5.1.1", "structured")]["status"] == "not_applicable"
    assert main(["compare", "--methods", "structured,foo", "--out", str(tmp_path / "bad")]) == 2
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("objective,method", [("maxmin", "alternating"), ("maxmin", "path"),
                                              ("destabilize", "joint"), ("targeted", "alternating")])
def test_scenario_a_simulations_are_one_attack_run_once(tmp_path, objective, method) -> None:
    """same_attack groups a scenario-A cell's simulations only where they compute the same row: run separately, two
    of its seeds give equal rows; in a sweep, the cell's attack runs once and every simulation gets its row, while
    scenario B's simulations (and white noise's) run one by one."""
    tasks = vrft.cell_tasks(2, 0, "paper", objective, method, eps_u=(0.1,), eps_y=(0.05,))
    a = [t for t in tasks if t["scenario"] == "A"]
    assert a[0]["seed"] != a[1]["seed"] and vrft.same_attack(a[0]) == vrft.same_attack(a[1])
    separately = [_strip_times([vrft.attack_task(t)]) for t in a]
    assert separately[0] == separately[1]
    ran: list[str] = []
    rows = run_sweep(lambda t: ran.append(t["key"]) or vrft.attack_task(t), tasks, str(tmp_path / "s.jsonl"),
                     LocalExecutor(1), None, "t", valid=vrft.valid_row, shared=vrft.same_attack)
    assert [r["key"] for r in rows] == [t["key"] for t in tasks]
    assert ran == [a[0]["key"]] + [t["key"] for t in tasks if t["scenario"] == "B"]
    assert [r["task"]["seed"] for r in rows] == [t["seed"] for t in tasks]
    assert _strip_times([{k: v for k, v in r.items() if k in separately[0][0]} for r in rows[:2]]) == separately[0] * 2
    noise = vrft.cell_tasks(2, 0, "paper", "maxmin", "white-noise", eps_u=(0.1,), eps_y=(0.05,))
    assert len({vrft.same_attack(t) for t in noise}) == len(noise)


def test_a_sweep_gives_its_rate_and_eta_from_the_first_finished_task(tmp_path) -> None:
    """Long tasks (a defenses bisection takes minutes) must not leave the user without an estimate until 5 % of the
    tasks are done: the first finished task already prints the rate and the ETA (issue 50)."""
    lines: list[str] = []
    tasks = vrft.cell_tasks(3, 0, "paper", "maxmin", "white-noise")  # 45 tasks: an update every 2 after the first
    assert len(tasks) >= 40
    run_sweep(vrft.attack_task, tasks, str(tmp_path / "t.jsonl"), LocalExecutor(1), lines.append, "t")
    updates = [ln for ln in lines if "tasks/s, ETA" in ln]
    assert updates and updates[0].startswith("\r[t] 1/")


def test_a_batched_sweep_rate_counts_from_the_start(tmp_path) -> None:
    """Batches (`together`) deliver their rows in one burst: the printed pace must not count a burst's rows as made
    in no time (it printed 48,304 tasks/s on the Willems sweep). Each task here sleeps 20 ms, so no honest pace
    exceeds 50 tasks/s."""
    def many(tasks: list[dict]) -> list[dict]:
        time.sleep(0.02 * len(tasks))
        return [{"value": t["i"]} for t in tasks]

    tasks = [{"key": f"k{i}", "i": i} for i in range(40)]
    lines: list[str] = []
    run_sweep(BatchTask(many), tasks, str(tmp_path / "b.jsonl"), LocalExecutor(1), lines.append, "b",
              together=lambda t: t["i"] // 8)
    rates = [float(ln.split(" done, ")[1].split(" tasks/s")[0]) for ln in lines if "tasks/s, ETA" in ln]
    assert len(rates) >= 3 and max(rates) <= 50.0


def test_a_sweep_estimates_its_time_before_it_starts_from_an_earlier_run(tmp_path) -> None:
    """Issue 50: reproductions print an estimate before they start. A first sweep records (tasks, wall seconds,
    workers) in timings.json beside its rows; a later sweep of the same name in that folder estimates from that pace
    (before any task finishes), and one in an empty folder says that it has nothing to estimate from."""
    tasks = vrft.cell_tasks(1, 0, "paper", "maxmin", "white-noise")
    first: list[str] = []
    run_sweep(vrft.attack_task, tasks[:6], str(tmp_path / "a.jsonl"), LocalExecutor(1), first.append, "t")
    assert any("no earlier run recorded" in ln for ln in first)
    stored = json.load(open(tmp_path / "timings.json", encoding="utf-8"))["t"]
    assert stored[0] == 6 and stored[1] > 0 and stored[2] == 1
    later: list[str] = []
    run_sweep(vrft.attack_task, tasks[6:12], str(tmp_path / "b.jsonl"), LocalExecutor(1), later.append, "t")
    estimate_line = next(i for i, ln in enumerate(later) if "estimate ~" in ln)
    assert "an earlier run in this folder" in later[estimate_line]
    assert estimate_line < next(i for i, ln in enumerate(later) if "done, " in ln)
    again = json.load(open(tmp_path / "timings.json", encoding="utf-8"))["t"]
    assert pace("t", [str(tmp_path / "timings.json")]) == (again[1] * again[2] / again[0], str(tmp_path / "timings.json"))
