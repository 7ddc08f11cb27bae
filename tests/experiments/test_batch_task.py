"""A BatchTask gets each batch of `together` whole, from every executor, and a sweep of the VRFT reproduction's tasks
through it (attack_tasks: the batched attacks) gives the rows attack_task gives one at a time."""

from __future__ import annotations

import os

import numpy as np

from bilevel.experiments import vrft
from bilevel.experiments.executor import BatchTask, LocalExecutor, run_batch
from bilevel.experiments.sweep import run_sweep

CALLS: list[list[int]] = []


def _numbers(tasks: list[dict]) -> list[dict]:
    """Rows of a batch, the batch recorded."""
    CALLS.append([t["i"] for t in tasks])
    return [{"square": t["i"] ** 2, "batch": len(tasks)} for t in tasks]


NUMBERS = BatchTask(_numbers)


def test_batch_task_receives_whole_batches() -> None:
    tasks = [{"key": str(i), "i": i} for i in range(7)]
    CALLS.clear()
    with LocalExecutor(1) as executor:
        got = dict((t["i"], row) for t, row in executor.imap_unordered(NUMBERS, tasks, together=lambda t: t["i"] % 3))
    assert sorted(CALLS) == [[0, 3, 6], [1, 4], [2, 5]]
    assert all(got[i] == {"square": i * i, "batch": len(range(i % 3, 7, 3))} for i in range(7))
    assert run_batch(NUMBERS, tasks[:2]) == [{"square": 0, "batch": 2}, {"square": 1, "batch": 2}]
    assert NUMBERS(tasks[3]) == {"square": 9, "batch": 1}


def test_batched_sweep_rows_equal_one_at_a_time(tmp_path) -> None:
    """Two worker processes, batches of data sets (same_data), alternating attacks and budget paths: the rows' statuses
    and unstable verdicts equal attack_task's, values to rounding."""
    tasks = [t for m in ("alternating", "path") for t in vrft.cell_tasks(5, 0, "paper", "maxmin", m,
                                                                          eps_u=(0.1,), eps_y=(0.023, 0.057))]
    tasks = [{**t, "N": 128} for t in tasks]
    with LocalExecutor(2) as executor:
        rows = run_sweep(vrft.BATCHED_TASKS, tasks, os.path.join(tmp_path, "rows.jsonl"), executor, None, "t",
                         vrft.valid_row, vrft.same_attack, vrft.same_data)
    for task, row in zip(tasks, rows):
        one = vrft.attack_task(task)
        for a, b in zip(one.get("cells", [one]), row.get("cells", [row])):
            assert (a["status"], a["unstable"]) == (b["status"], b["unstable"])
            assert abs(a["value"] - b["value"]) <= 1e-7 * abs(a["value"])
            np.testing.assert_allclose(a["theta_poisoned"], b["theta_poisoned"], rtol=0, atol=1e-6)
