"""The quick reproduction runs end to end, writes every artifact, and resumes without recomputing."""

from __future__ import annotations

import json
import os

from bilevel.lower.sdp import SemidefiniteLower
from bilevel.experiments.willems import attack_task, make_plan, paper_tasks, run_reproduction, sim_seeds


def test_quick_reproduction_writes_report_tables_and_figures(tmp_path) -> None:
    out = str(tmp_path / "willems")
    lines: list[str] = []
    report = run_reproduction(sims=2, out_dir=out, quick=True, seed=0, progress=lines.append)
    assert report == os.path.join(out, "report.md")
    text = open(report, encoding="utf-8").read()
    for needle in ("Fraction of unstable closed loops", "fig7_eigenvalues.png", "fig8_objective.png",
                   "fig9_signals.png", "The paper's claims next to ours", "Output poisoning", "Other designs",
                   "Timing", "How much input poisoning destabilizes the loop", "fig_budget_cdf.png", "ours max rho"):
        assert needle in text
    assert os.path.getsize(os.path.join(out, "fig_budget_cdf.png")) > 1000
    budget = open(os.path.join(out, "budget.csv"), encoding="utf-8").read().splitlines()
    assert len(budget) == 1 + 2 * 2  # header + (N = 15, 50) x 2 sims
    for name in ("paper", "remark", "designs"):
        assert os.path.getsize(os.path.join(out, f"table_{name}.csv")) > 0
        assert os.path.getsize(os.path.join(out, f"table_{name}.md")) > 0
        rows = [json.loads(line) for line in open(os.path.join(out, f"{name}.jsonl"), encoding="utf-8")]
        assert rows and all("error" in r or r["budget_violation"] == 0.0 for r in rows)
    for fig in ("fig7_eigenvalues", "fig8_objective", "fig9_signals"):
        for ext in ("png", "pdf"):
            assert os.path.getsize(os.path.join(out, f"{fig}.{ext}")) > 1000
    assert any("done" in line and "ETA" in line for line in lines)
    paper_rows = len(paper_tasks(make_plan(2, True), 0))
    assert sum(1 for _ in open(os.path.join(out, "paper.jsonl"), encoding="utf-8")) == paper_rows
    # resumable: a rerun finds every task done and only rewrites the summaries
    lines.clear()
    run_reproduction(sims=2, out_dir=out, quick=True, seed=0, progress=lines.append)
    assert not any("running" in line for line in lines)
    assert sum(1 for _ in open(os.path.join(out, "paper.jsonl"), encoding="utf-8")) == paper_rows
    # the first run's sweep times survive the resume, so the report still states them
    timings = json.load(open(os.path.join(out, "timings.json"), encoding="utf-8"))
    assert set(timings) == {"paper", "remark", "designs"} and timings["paper"][0] == paper_rows
    assert timings["paper"][1] > 0 and f"paper {paper_rows} attacks in" in open(report, encoding="utf-8").read()


def test_selection_is_part_of_every_task_and_reaches_the_learner(monkeypatch) -> None:
    """Rows of the two selections never share a key (a resumed run cannot mix them), and attack_task builds the
    learner with the task's selection: the engine's minimum-norm selection runs for min-norm tasks only."""
    plan = make_plan(1, True)
    tasks = {sel: paper_tasks(plan, 0, sel) for sel in ("min-norm", "tikhonov")}
    assert not {t["key"] for t in tasks["min-norm"]} & {t["key"] for t in tasks["tikhonov"]}
    calls = []
    original = SemidefiniteLower.select_min_norm
    monkeypatch.setattr(SemidefiniteLower, "select_min_norm",
                        lambda self, x, sol: calls.append(len(x)) or original(self, x, sol))
    for sel in ("tikhonov", "min-norm"):
        task = next(t for t in tasks[sel] if t["horizon"] == 15 and t["method"] == "hypergradient")
        row = attack_task({**task, "starts": 1})
        assert row["selection"] == sel and "error" not in row and row["kkt_residual"] <= 1e-9
        assert bool(calls) == (sel == "min-norm")


def test_simulation_seeds_are_reproducible() -> None:
    """SeedSequence(seed).spawn: the same seed gives the same (data, attack) seeds; prefixes are stable."""
    assert sim_seeds(0, 3) == sim_seeds(0, 3)
    assert sim_seeds(0, 5)[:3] == sim_seeds(0, 3)
    assert sim_seeds(0, 3) != sim_seeds(1, 3)


def test_solver_selection_runs_the_input_poisoning_sweeps_and_says_what_it_left_out(tmp_path) -> None:
    """With the SDP solver's own Q (clarabel) only input poisoning without an input cost is defined: the paper
    sweep and those designs run against that learner, the state-poisoning remark and lqr-r do not, and the report
    names the learner and what was not run."""
    out = str(tmp_path / "willems-clarabel")
    report = open(run_reproduction(sims=1, out_dir=out, quick=True, seed=0, progress=None, selection="clarabel"),
                  encoding="utf-8").read()
    paper = [json.loads(line) for line in open(os.path.join(out, "paper.jsonl"), encoding="utf-8")]
    assert len(paper) == len(paper_tasks(make_plan(1, True), 0))
    assert all(r["selection"] == "clarabel" and "error" not in r for r in paper)
    designs = [json.loads(line) for line in open(os.path.join(out, "designs.jsonl"), encoding="utf-8")]
    assert designs and {(r["design"], r["poison"]) for r in designs} == {("lqr", "u"), ("stabilizing", "u")}
    assert not os.path.exists(os.path.join(out, "remark.jsonl"))
    assert report.count("Not run for the `clarabel` selection") == 2
    assert "Clarabel's own optimal Q" in report and "computed against the `clarabel` selection" in report
    budget = open(os.path.join(out, "budget.csv"), encoding="utf-8").read().splitlines()[1:]
    assert len(budget) == 2 and all(",clarabel," in line for line in budget)


def test_cli_offers_every_learner_selection() -> None:
    from bilevel.cli import WILLEMS_SELECTIONS
    from bilevel.problems.willems_instance import SELECTIONS

    assert WILLEMS_SELECTIONS == SELECTIONS


def test_budget_sweep_is_resumable_and_matches_the_search_per_data_set(tmp_path) -> None:
    """`reproduce willems-budget`'s sweep: one row per data set, equal to smallest_destabilizing_budget on that data
    set's seeds; a rerun recomputes nothing."""
    from bilevel.experiments.willems_budget import smallest_destabilizing_budget
    from bilevel.experiments.willems_budget import budget_distribution
    from bilevel.problems.willems_instance import WillemsSetting

    path, lines = str(tmp_path / "budget.jsonl"), []
    rows = budget_distribution((15,), ("min-norm",), 1, path, starts=1, workers=1, progress=lines.append)
    data_seed, attack_seed = sim_seeds(0, 1)[0]
    found = smallest_destabilizing_budget(WillemsSetting(objective="destabilize", horizon=15, seed=data_seed),
                                          starts=1, seed=attack_seed)
    assert rows == [{"horizon": 15, "selection": "min-norm", "data_seed": data_seed, "delta_star": found.delta,
                     "attacks": len(found.runs)}]
    lines.clear()
    assert budget_distribution((15,), ("min-norm",), 1, path, starts=1, workers=1, progress=lines.append) == rows
    assert not any("running" in line for line in lines)


def test_reproduce_rejects_the_flags_of_another_target(capsys) -> None:
    """--quick and --selection belong to `reproduce willems`: elsewhere they are a one-line error, not ignored."""
    from bilevel.cli import main

    assert main(["reproduce", "vrft", "--quick"]) == 2
    err = capsys.readouterr().err
    assert "--quick: only `reproduce willems`, `reproduce identification`, `reproduce defenses`" in err
    assert "not `reproduce vrft`" in err
    assert main(["reproduce", "willems-budget", "--selection", "scs"]) == 2
    assert "runs the selections min-norm, clarabel and scs" in capsys.readouterr().err


def test_budget_quantiles_keep_data_sets_never_destabilized() -> None:
    """A data set that stays stable has delta_u* = inf: the quartiles that reach it are inf, not nan, and the others
    are np.quantile's (one stable set of four: median 0.25, upper quartile inf)."""
    import numpy as np

    from bilevel.experiments.willems_budget import quantiles, summary_markdown

    d = np.array([0.1, 0.2, 0.3, np.inf])
    np.testing.assert_allclose(quantiles(d, (0.25, 0.5, 0.75)), [0.175, 0.25, np.inf], rtol=1e-12)
    np.testing.assert_array_equal(quantiles(d[:3], (0.5,)), np.quantile(d[:3], [0.5]))
    rows = [{"horizon": 15, "selection": "min-norm", "delta_star": v} for v in d]
    assert "| 15 | min-norm | 4 | 0.25 | 0.175 - inf | 1 |" in summary_markdown(rows)
