"""The identification sweep's tasks, one task's row (judged by the defender's tests) and the summary."""

from __future__ import annotations

import numpy as np

from bilevel.experiments.identification import attack_task, cell_tasks, summarize
from bilevel.problems.identification_instance import attack_instance


def test_tasks_share_data_across_budgets() -> None:
    tasks = cell_tasks(3, seed=0, horizons=(100,), deltas=(0.01, 0.05))
    assert len(tasks) == 6 and len({t["key"] for t in tasks}) == 6
    by_delta = {d: [t["seed"] for t in tasks if t["delta"] == d] for d in (0.01, 0.05)}
    assert by_delta[0.01] == by_delta[0.05] and len(set(by_delta[0.01])) == 3


def test_row_is_the_stealthy_attack_judged_independently() -> None:
    task = {"key": "k", "T": 100, "delta": 0.05, "seed": 1, "lags": 10}
    row = attack_task(task)
    assert row["status"] == "solved" and row["certified"]
    clean = attack_instance("ss", T=100, seed=1).tests()
    for name, test in clean.items():
        assert row["before"][name]["statistic"] == test.statistic
        assert abs(1 - row["after"][name]["statistic"] / test.statistic) <= 0.05 + 1e-6
    assert row["norm2"] <= row["frobenius"] <= np.sqrt(4) * row["norm2"]  # rank of d[A B] <= 4
    summary = summarize([{**row, "task": task}, {**row, "task": task, "certified": False}])
    cell = summary["T=100, delta=0.05"]
    assert cell["runs"] == 2 and cell["solved_certified"] == 1
    assert cell["norm2_quartiles"] == [row["norm2"]] * 3
