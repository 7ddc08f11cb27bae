"""`bilevel reproduce certify --quick` (the CI path): brackets per family, resumable rows, outputs."""

from __future__ import annotations

import json
import os

from bilevel.cli import main
from bilevel.experiments.certify import ROW_SCHEMA, certify_tasks, run_certify


def test_quick_certify_writes_consistent_brackets_and_resumes(tmp_path) -> None:
    notes: list[str] = []
    path = run_certify(sims=1, out_dir=str(tmp_path), quick=True, workers=1, progress=notes.append)
    rows = [json.loads(line) for line in open(tmp_path / "certify.jsonl")]
    assert {r["family"] for r in rows} == {"vrft", "ident"} and set(ROW_SCHEMA) <= set(rows[0])
    vrft = next(r for r in rows if r["family"] == "vrft")
    assert 0 < vrft["delta_lb"] <= vrft["delta_ub"] and vrft["unstable"] == 0 and vrft["samples"] == 200
    assert vrft["worst_radius"] < 1 and vrft["attack_radius"] < 1
    ident = next(r for r in rows if r["family"] == "ident")
    assert 0 < ident["delta_lb"] <= ident["delta_ub"] and ident["unstable"] == 0 and ident["samples"] == 200
    assert ident["worst_radius"] < 1 and ident["attack_radius"] < 1
    assert os.path.exists(tmp_path / "fig_brackets.png") and "| vrft | 64 |" in open(path).read()
    notes.clear()
    run_certify(sims=1, out_dir=str(tmp_path), quick=True, workers=1, progress=notes.append)
    assert not any("running" in n for n in notes)  # resumed: nothing recomputed


def test_cli_refuses_a_flag_certify_does_not_take(capsys) -> None:
    assert main(["reproduce", "certify", "--selection", "clarabel"]) != 0
    assert "--selection" in capsys.readouterr().err


def test_the_full_run_certifies_vrft_at_its_small_size_too() -> None:
    """VRFT's full run: N = 512 and N = 64 on the same data and attack seeds; the quick run only N = 64."""
    full = certify_tasks(3, False, 0, 10, ("vrft",))
    assert [t["size"] for t in full] == [512] * 3 + [64] * 3 and len({t["key"] for t in full}) == 6
    assert [t["seed"] for t in full[:3]] == [t["seed"] for t in full[3:]]
    assert [t["size"] for t in certify_tasks(3, True, 0, 10, ("vrft",))] == [64] * 3
