"""`bilevel reproduce certify --quick` (the CI path): brackets per family, resumable rows, outputs."""

from __future__ import annotations

import json
import os

import pytest

from bilevel.cli import main
from bilevel.errors import ModelError
from bilevel.experiments.certify import DEEPC_BUDGETS, FAMILIES, ROW_SCHEMA, certify_tasks, run_certify


def test_quick_certify_writes_consistent_brackets_and_resumes(tmp_path) -> None:
    notes: list[str] = []
    path = run_certify(sims=1, out_dir=str(tmp_path), quick=True, workers=1, progress=notes.append)
    rows = [json.loads(line) for line in open(tmp_path / "certify.jsonl")]
    assert [r["family"] for r in rows] == list(FAMILIES) and all(set(ROW_SCHEMA) <= set(r) for r in rows)
    for r in rows:  # every family: a consistent bracket, and nothing sampled or attacked at delta_lb reached the goal
        assert 0 < r["delta_lb"] <= r["delta_ub"] and r["unstable"] == 0 and r["samples"] == 200, r["family"]
        assert r["worst_radius"] < 1 and r["attack_radius"] < 1 and r["mechanism"], r["family"]
    deepc = rows[-1]
    assert [b[0] for b in deepc["budgets"]] == list(DEEPC_BUDGETS)
    assert all(bound >= attack >= 1.0 for _, bound, attack in deepc["budgets"])  # the proven bound is above the attack
    report = open(path).read()
    assert os.path.exists(tmp_path / "fig_brackets.png") and "| vrft | 64 |" in report and "| deepc | 60 |" in report
    notes.clear()
    run_certify(sims=1, out_dir=str(tmp_path), quick=True, workers=1, progress=notes.append)
    assert not any("running" in n for n in notes)  # resumed: nothing recomputed


def test_unknown_family_is_refused(tmp_path) -> None:
    with pytest.raises(ModelError, match="certify families: unknown family"):
        run_certify(sims=1, out_dir=str(tmp_path), quick=True, families=("vrft", "lqr"))


def test_cli_refuses_a_flag_certify_does_not_take(capsys) -> None:
    assert main(["reproduce", "certify", "--selection", "clarabel"]) != 0
    assert "--selection" in capsys.readouterr().err


def test_the_full_run_certifies_vrft_at_its_small_size_too() -> None:
    """VRFT's full run: N = 512 and N = 64 on the same data and attack seeds; the quick run only N = 64."""
    full = certify_tasks(3, False, 0, 10, ("vrft",))
    assert [t["size"] for t in full] == [512] * 3 + [64] * 3 and len({t["key"] for t in full}) == 6
    assert [t["seed"] for t in full[:3]] == [t["seed"] for t in full[3:]]
    assert [t["size"] for t in certify_tasks(3, True, 0, 10, ("vrft",))] == [64] * 3
