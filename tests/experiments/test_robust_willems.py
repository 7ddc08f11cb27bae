"""The robust De Persis–Tesi learner under adaptive attack (issue 46): no answer of the learner leaves the true loop
unstable at any budget up to its design budget (its theorem: a violation is a bug), and its clean cost is at least the
undefended learner's (the nominal design is H2-optimal)."""

import json

import numpy as np
import pytest

from bilevel.experiments.robust_willems import ROW_SCHEMA, make_plan, run_robust_willems, summarize, tasks
from bilevel.experiments.sweep import check_fields


def _rows(path):
    with open(path) as fh:
        return [json.loads(line) for line in fh]


def _check(rows, plan):
    assert all(check_fields(r, ROW_SCHEMA) == "" for r in rows)
    robust = [r for r in rows if r["learner"] == "robust"]
    assert sum(r["unstable"] for r in robust) == 0
    assert all(np.isnan(r["radius"]) or r["radius"] < 1.0 for r in robust)
    base = {r["data_seed"]: r["clean_cost"] for r in rows if r["learner"] == "none" and r["budget"] == 0}
    for r in robust:
        assert r["clean_cost"] >= base[r["data_seed"]] * (1 - 1e-6)
    attacked = [r for r in robust if r["budget"] > 0]
    assert attacked and all(r["answers"] >= 8 for r in attacked)  # the engine's answers and the random vertices
    summary = summarize(rows)
    assert {s["learner"] for s in summary} == {"robust", "none", "ridge"}
    assert all(0.0 <= s["abstention_rate"] <= 1.0 for s in summary)
    assert len(rows) == len(tasks(plan, 0))


def test_quick_run(tmp_path):
    run_robust_willems(sims=1, out_dir=str(tmp_path), quick=True, workers=1, progress=None)
    _check(_rows(tmp_path / "robust.jsonl"), make_plan(1, True))
    assert (tmp_path / "robust.md").read_text().startswith("| learner |")


@pytest.mark.slow
def test_full_plan_eight_data_sets(tmp_path):
    run_robust_willems(sims=8, out_dir=str(tmp_path), workers=1, progress=None)
    _check(_rows(tmp_path / "robust.jsonl"), make_plan(8, False))
