"""Sweeps survive faults: a worker killed (new pool, lost tasks rerun), the main process killed (its workers die
with it), any written file truncated anywhere, rows corrupted (set aside by schema and recomputed); every resumed
table equals an uninterrupted run's, time columns aside, and no process is left behind."""

from __future__ import annotations

import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator

import matplotlib.image
import numpy as np
import psutil
import pytest

from bilevel.cli import main
from bilevel.errors import WorkerLost
from bilevel.experiments import vrft, willems
from bilevel.experiments.executor import MARKS_PREFIX, LocalExecutor
from bilevel.experiments.sweep import run_sweep
from bilevel.files import atomic_open

from . import faulty
from .tables import table_difference, tables, wait_for_rows

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TOY_TASKS = 16


def _outputs(out: str) -> dict:
    """The tables (time columns dropped), the result JSON, the npz and the figure's size of a toy reproduction, and
    whether timings.json holds a toy timing."""
    with open(os.path.join(out, "best.json"), encoding="utf-8") as fh:
        best = json.load(fh)
    return {**tables(out), "best": best, "theta": np.load(os.path.join(out, "theta.npz"))["theta"].tolist(),
            "figure": matplotlib.image.imread(os.path.join(out, "fig_toy.png")).shape,
            "timed": list(faulty.load_timings(os.path.join(out, "timings.json")))}


def _alive(procs: list[psutil.Process], timeout: float) -> list[int]:
    """Pids among `procs` still running (not a zombie) after up to `timeout` seconds."""
    t0 = time.monotonic()
    while True:
        alive = []
        for p in procs:
            try:
                if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                    alive.append(p.pid)
            except psutil.NoSuchProcess:
                pass
        if not alive or time.monotonic() - t0 > timeout:
            return alive
        time.sleep(0.05)


def _no_temporaries(out: str) -> None:
    """No temporary file of an atomic write is left in `out`."""
    assert not [f for f in os.listdir(out) if f.startswith(".")]


@pytest.fixture(autouse=True)
def no_process_left_behind() -> Iterator[None]:
    """Every process a test starts (workers, pools' helpers) is gone within 5 s of its end."""
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    yield
    assert _alive([p for p in psutil.Process().children(recursive=True) if p.pid not in before], 5.0) == []


@pytest.fixture(scope="module")
def toy_reference(tmp_path_factory) -> dict:
    """The toy reproduction run uninterrupted: its outputs and its output directory."""
    out = str(tmp_path_factory.mktemp("toy") / "ref")
    faulty.reproduce(out, TOY_TASKS)
    return {"out": out, "outputs": _outputs(out)}


@pytest.fixture
def marks(tmp_path, monkeypatch) -> str:
    path = tmp_path / "marks"
    path.mkdir()
    monkeypatch.setenv(faulty.DIE_MARKS, str(path))
    return str(path)


def test_batches_run_in_one_worker_in_task_order(tmp_path) -> None:
    """Tasks that `together` groups run one after another in one worker, in task order, on the pool and alone."""
    tasks = [{"key": f"x={x}", "x": x} for x in range(12)]
    for workers in (2, 1):
        rows = run_sweep(faulty.ordered_task, tasks, str(tmp_path / f"{workers}.jsonl"), LocalExecutor(workers), None,
                         "t", together=lambda t: t["x"] // 4)
        for b in range(3):
            batch = rows[4 * b:4 * b + 4]
            assert len({r["pid"] for r in batch}) == 1
            assert batch[-1]["ran"][-4:] == [4 * b, 4 * b + 1, 4 * b + 2, 4 * b + 3]
            assert [r["ran"][:-1] for r in batch[1:]] == [r["ran"] for r in batch[:-1]]  # nothing ran in between


@pytest.mark.parametrize("together", [None, lambda t: t["x"] // 4])
def test_worker_killed_mid_run_is_replaced_and_its_task_rerun(tmp_path, marks, toy_reference, together) -> None:
    """Task x=5 SIGKILLs its worker the first time it runs: the sweep says so in one line, starts a new pool,
    reruns the unfinished tasks (their whole batch where tasks run in batches) and ends with every row once, equal
    to the uninterrupted run's."""
    lines: list[str] = []
    out = str(tmp_path / "run")
    rows = faulty.reproduce(out, TOY_TASKS, sleep=0.02, progress=lines.append, die={5: 1}, together=together)
    assert len(os.listdir(marks)) == 1  # it did kill its worker once
    died = [ln for ln in lines if "worker process died" in ln]
    assert len(died) == 1 and "x=5 (SIGKILL)" in died[0] and "new pool, rerunning" in died[0]
    assert [r["key"] for r in rows] == [f"x={x}" for x in range(TOY_TASKS)]
    with open(os.path.join(out, "rows.jsonl"), encoding="utf-8") as fh:
        assert sorted(json.loads(line)["key"] for line in fh) == sorted(r["key"] for r in rows)
    assert _outputs(out) == toy_reference["outputs"]
    _no_temporaries(out)


def test_task_killing_its_worker_twice_stops_with_one_line_and_keeps_rows(tmp_path, marks, toy_reference) -> None:
    """A task that kills its worker on every try stops the sweep after WORKER_DEATHS tries with a WorkerLost naming
    it (the CLI prints such a BilevelError as one line); the rows finished before are kept, and once the task
    runs normally the resumed outputs equal the uninterrupted run's."""
    out = str(tmp_path / "run")
    with pytest.raises(WorkerLost, match=r"^task x=3 lost its worker process 2 times \(SIGKILL\); finished rows"):
        faulty.reproduce(out, TOY_TASKS, sleep=0.02, die={3: 1000})
    _no_temporaries(out)
    with open(os.path.join(out, "rows.jsonl"), encoding="utf-8") as fh:
        kept = [json.loads(line)["key"] for line in fh]
    assert "x=3" not in kept and len(kept) == len(set(kept)) >= 1
    lines: list[str] = []
    faulty.reproduce(out, TOY_TASKS, sleep=0.02, progress=lines.append, die={3: 2})
    assert any(f"{len(kept)} of {TOY_TASKS} already done" in ln for ln in lines)
    assert _outputs(out) == toy_reference["outputs"]


def test_real_vrft_sweep_survives_a_worker_killed_from_outside(tmp_path) -> None:
    """VRFT max-min attacks (24 tasks) on two workers, one worker SIGKILLed from outside (as the OOM killer does)
    after the third row: the sweep reports it, reruns what was lost, and its rows and Table-1 cells equal a
    one-process run's."""
    tasks = vrft.cell_tasks(2, 0, "paper", "maxmin", "alternating", eps_u=(0.1, 0.2), eps_y=(0.01, 0.037, 0.057))
    ref = run_sweep(vrft.attack_task, tasks, str(tmp_path / "ref.jsonl"), LocalExecutor(1), None, "ref",
                    valid=vrft.valid_row)
    lines, killed, before = [], [], {p.pid for p in psutil.Process().children()}

    def progress(text: str) -> None:
        lines.append(text)
        if text.startswith("\r") and len([ln for ln in lines if ln.startswith("\r")]) == 3:
            killed.append(next(p.pid for p in psutil.Process().children() if p.pid not in before))
            os.kill(killed[0], signal.SIGKILL)

    with LocalExecutor(2) as executor:
        rows = run_sweep(vrft.attack_task, tasks, str(tmp_path / "run.jsonl"), executor, progress, "t",
                         valid=vrft.valid_row)
    assert len(killed) == 1 and len([ln for ln in lines if "a worker process died" in ln]) == 1
    strip = lambda rs: [{k: v for k, v in r.items() if k != "wall_time"} for r in rs]  # noqa: E731
    assert strip(rows) == strip(ref)
    summary, ref_summary = vrft.summarize(rows), vrft.summarize(ref)
    assert vrft.table_markdown(summary, "t") == vrft.table_markdown(ref_summary, "t")
    assert [{k: v for k, v in c.items() if k != "time_ms"} for c in summary.values()] == [
        {k: v for k, v in c.items() if k != "time_ms"} for c in ref_summary.values()]


def test_main_process_killed_takes_its_workers_and_resume_matches(tmp_path, toy_reference, monkeypatch) -> None:
    """SIGKILL of the main process (nothing can run in it): its two workers are gone within 3 s (they die with
    their parent), the resumed run's outputs equal the uninterrupted run's, and it removes the killed run's
    temporary directory. Both runs use a private temporary directory: any sweep starting elsewhere (another test
    process) removes the stale marks of dead processes in the shared one, which would race the check below."""
    out = str(tmp_path / "run")
    private = tmp_path / "tmp"
    private.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    proc = subprocess.Popen([sys.executable, "-m", "tests.experiments.faulty", out, str(TOY_TASKS), "0.3"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                            env={**os.environ, "PYTHONPATH": ROOT, "TMPDIR": str(private)})
    try:
        wait_for_rows(proc, os.path.join(out, "rows.jsonl"), 3)
        workers = psutil.Process(proc.pid).children(recursive=True)
        assert len(workers) >= 2
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
        assert _alive(workers, 3.0) == [], "workers outlived their parent"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    stale = os.path.join(tempfile.gettempdir(), f"{MARKS_PREFIX}{proc.pid}-*")
    assert len(glob.glob(stale)) == 1  # the killed run's marks of running tasks
    lines: list[str] = []
    faulty.reproduce(out, TOY_TASKS, sleep=0.3, progress=lines.append)
    assert any("already done" in ln for ln in lines) and not glob.glob(stale)
    assert _outputs(out) == toy_reference["outputs"]
    _no_temporaries(out)


@pytest.mark.parametrize("name", ["rows.jsonl", "timings.json", "table_toy.csv", "report.md", "best.json",
                                  "theta.npz", "fig_toy.png"])
def test_every_written_file_truncated_anywhere_resumes_to_the_same_outputs(tmp_path, toy_reference, name) -> None:
    """Each file the toy reproduction writes, cut at 0, 1, a third, half and all-but-one bytes: the resume
    rewrites it whole (a torn row is set aside and recomputed; timings.json, reported unreadable, is rewritten and
    holds the timing of the rerun rows if any) and every output equals the uninterrupted run's."""
    size = os.path.getsize(os.path.join(toy_reference["out"], name))
    for cut in sorted({0, 1, size // 3, size // 2, size - 1}):
        out = str(tmp_path / f"cut{cut}")
        shutil.copytree(toy_reference["out"], out)
        with open(os.path.join(out, name), "r+b") as fh:
            fh.truncate(cut)
            fh.seek(max(cut - 1, 0))
            torn = cut > 0 and fh.read(1) != b"\n"
        lines: list[str] = []
        faulty.reproduce(out, TOY_TASKS, progress=lines.append)
        untimed = name == "timings.json"  # rewritten empty, and no row was rerun to time
        assert _outputs(out) == {**toy_reference["outputs"], **({"timed": []} if untimed else {})}, (name, cut)
        assert any("timings.json: unreadable" in ln for ln in lines) == untimed
        if name == "rows.jsonl":
            assert any("set aside 1 malformed row(s)" in ln and "truncated line" in ln for ln in lines) == torn
        with open(os.path.join(out, "rows.jsonl"), encoding="utf-8") as fh:
            assert len(fh.readlines()) == TOY_TASKS
        _no_temporaries(out)


def test_corrupt_rows_are_set_aside_by_schema_and_recomputed(tmp_path, toy_reference) -> None:
    """Bad UTF-8, the string "false" for a bool, a missing field, NaN for a finite field, a number as a string and a
    torn last line: one line reports six rows set aside and why, they land in rows.jsonl.rejected (bytes as they
    were) and are recomputed; "false" never counts as unstable."""
    out = str(tmp_path / "run")
    shutil.copytree(toy_reference["out"], out)
    path = os.path.join(out, "rows.jsonl")
    with open(path, "rb") as fh:
        lines = fh.readlines()
    rows = [json.loads(line) for line in lines]  # in completion order
    false = next(i for i in range(1, len(rows) - 1) if rows[i]["unstable"] is False)
    missing, nan, text = [i for i in range(1, len(rows) - 1) if i != false][:3]
    rows[false]["unstable"] = "false"
    del rows[missing]["theta"]
    rows[nan]["wall_time"] = float("nan")
    rows[text]["value"] = str(rows[text]["value"])
    corrupt = {0: lines[0].replace(b'"x=', b'"\xff\xfe='), len(lines) - 1: lines[-1][:25],
               **{i: json.dumps(rows[i]).encode() + b"\n" for i in (false, missing, nan, text)}}
    with open(path, "wb") as fh:
        fh.writelines(corrupt.get(i, line) for i, line in enumerate(lines))
    report: list[str] = []
    faulty.reproduce(out, TOY_TASKS, progress=report.append)
    aside = [ln for ln in report if "set aside" in ln]
    assert len(aside) == 1 and "set aside 6 malformed row(s)" in aside[0]
    for why in ("line 1: not UTF-8", f"line {false + 1}: unstable: 'false' is not bool",
                f"line {missing + 1}: lacks result fields (theta)", f"line {nan + 1}: wall_time: nan is not finite",
                f"line {text + 1}: value: '"):
        assert why in aside[0], why
    assert aside[0].endswith(" ...")  # five reasons shown, the torn line counted
    with open(path + ".rejected", "rb") as fh:
        assert fh.read() == b"".join(corrupt[i] for i in sorted(corrupt)) + b"\n"
    assert any(f"{TOY_TASKS - 6} of {TOY_TASKS} already done" in ln for ln in report)
    assert _outputs(out) == toy_reference["outputs"]
    report.clear()
    faulty.reproduce(out, TOY_TASKS, progress=report.append)
    assert not report  # nothing left to set aside or to run


def test_atomic_write_interrupted_keeps_the_old_file(tmp_path) -> None:
    """An exception inside atomic_open (a run killed mid-write) leaves the previous content and no temporary."""
    path = str(tmp_path / "timings.json")
    with atomic_open(path) as fh:
        fh.write('{"a": [1, 2.0]}')
    with pytest.raises(RuntimeError):
        with atomic_open(path) as fh:
            fh.write('{"a": [3')
            raise RuntimeError("killed")
    with open(path, encoding="utf-8") as fh:
        assert json.load(fh) == {"a": [1, 2.0]}
    assert os.listdir(tmp_path) == ["timings.json"]


WILLEMS = ["reproduce", "willems", "--quick", "--sims", "1", "--workers", "2"]


def test_real_reproduction_resumes_from_truncated_files_and_corrupt_rows(tmp_path, willems_seed0, capsys) -> None:
    """The quick Willems reproduction with every file it wrote truncated (each at its own offset) and corrupt rows
    (a stable loop's "unstable": "false", bad UTF-8, a missing field): `bilevel reproduce willems` reports what it
    set aside and resumes to the uninterrupted run's tables. Accepted, "false" would count as unstable."""
    out = str(tmp_path / "w")
    shutil.copytree(willems_seed0, out)
    paper = os.path.join(out, "paper.jsonl")
    with open(paper, "rb") as fh:
        lines = fh.readlines()
    rows = [json.loads(line) for line in lines]
    stable = next(i for i, r in enumerate(rows) if r["unstable"] is False and r["method"] == "hypergradient")
    rows[stable]["unstable"] = "false"
    assert next(iter(willems.summarize([rows[stable]], ("horizon",)).values()))["unstable"] == 1
    lines[stable] = json.dumps(rows[stable]).encode() + b"\n"
    other = next(i for i, r in enumerate(rows) if i != stable and r["method"] == "hypergradient")
    lines[other] = lines[other].replace(b'"status": "', b'"status": "\xc3(')
    with open(paper, "wb") as fh:
        fh.writelines(lines)
    remark = os.path.join(out, "remark.jsonl")
    with open(remark, encoding="utf-8") as fh:
        rrows = [json.loads(line) for line in fh]
    del rrows[0]["spectral_radius"]
    with open(remark, "w", encoding="utf-8") as fh:
        fh.writelines(json.dumps(r) + "\n" for r in rrows)
    names = sorted(set(os.listdir(out)) - {"paper.jsonl", "remark.jsonl"})
    for k, name in enumerate(names):  # cut each other file at its own fraction of its length
        with open(os.path.join(out, name), "r+b") as fh:
            fh.truncate(os.path.getsize(os.path.join(out, name)) * (k % 4 + 1) // 5)
            fh.seek(-1, os.SEEK_END)
            torn = fh.read(1) != b"\n"
        if name == "designs.jsonl":
            designs_torn = torn
    capsys.readouterr()
    assert main(WILLEMS + ["--out", out]) == 0
    err = capsys.readouterr().err
    assert "paper.jsonl: set aside 2 malformed row(s)" in err and "unstable: 'false' is not bool" in err
    assert "not UTF-8" in err and "remark.jsonl: set aside 1 malformed" in err and "spectral_radius" in err
    assert ("designs.jsonl: set aside 1 malformed row(s)" in err) == designs_torn
    assert "timings.json: unreadable" in err
    assert not (diff := table_difference(out, willems_seed0)), diff
    rejected = ["paper.jsonl.rejected", "remark.jsonl.rejected"] + (["designs.jsonl.rejected"] if designs_torn else [])
    assert sorted(os.listdir(out)) == sorted(os.listdir(willems_seed0) + rejected)
    for name in os.listdir(willems_seed0):  # every file whole again
        assert os.path.getsize(os.path.join(out, name)) > 0.9 * os.path.getsize(os.path.join(willems_seed0, name))
