"""The defenses frontier's summaries: the median interval, the per-setting table and figure, and one sweep task."""

import math

import numpy as np
import pytest
from scipy import stats

from bilevel.experiments.defenses import frontier_task, summarize, summary_markdown, write_outputs
from bilevel.experiments.stats import median_interval


def test_median_interval_order_statistics():
    values = np.arange(1.0, 65.0)
    median, low, high = median_interval(values)
    assert median == 32.5
    k = int(low)  # the k-th smallest value: coverage 1 - 2 P(Binomial(64, 1/2) <= k - 1)
    assert 1 - 2 * stats.binom.cdf(k - 1, 64, 0.5) >= 0.95 > 1 - 2 * stats.binom.cdf(k, 64, 0.5)
    assert high == 64 - k + 1
    assert median_interval([1.0, 2.0, 3.0]) == (2.0, -math.inf, math.inf)  # no 95% interval from 3 values
    assert median_interval(np.r_[np.arange(10.0), np.full(10, np.inf)])[0] == math.inf


def _rows():
    rng = np.random.default_rng(0)
    return [{"learner": "vrft", "defense": d, "param": p, "N": 128, "data_seed": i,
             "clean_cost": c + 0.01 * rng.random(),
             "delta_star": (math.inf if i == 0 and d == "iv" else delta * (1 + 0.1 * i)), "attacks": 5}
            for d, p, c, delta in (("none", 0.0, 0.02, 0.1), ("ridge", 1e-3, 0.03, 0.2), ("iv", 0.0, 0.025, 0.05))
            for i in range(12)]


def test_summary_per_setting(tmp_path):
    rows = _rows()
    summary = summarize(rows)
    assert [(s["defense"], s["data_sets"]) for s in summary] == [("iv", 12), ("none", 12), ("ridge", 12)]
    ridge = summary[2]
    assert ridge["delta_star"] == pytest.approx(np.median([0.2 * (1 + 0.1 * i) for i in range(12)]))
    assert ridge["clean_cost_low"] < ridge["clean_cost"] < ridge["clean_cost_high"]
    assert summary[0]["not_destabilized"] == 1
    assert ridge["delta_ratio"] == pytest.approx(2.0) and (ridge["delta_larger"], ridge["paired"]) == (12, 12)
    assert summary[1]["cost_ratio"] == 1.0 and summary[1]["delta_smaller"] == 0  # the baseline against itself
    assert summary[0]["delta_ratio"] == pytest.approx(0.5)  # iv: 0.05 against 0.1 (its inf on set 0 counts high)
    table = write_outputs(rows, str(tmp_path), ["vrft"])
    assert table == "Learners run: vrft (not run: willems, ident, deepc).\n\n" + summary_markdown(summary)
    assert "| vrft | ridge | 0.001 | 128 | 12 |" in table and (tmp_path / "frontier.md").read_text() == table
    assert (tmp_path / "fig_frontier.png").stat().st_size > 0
    assert (tmp_path / "frontier.csv").read_text().count("\n") == len(rows) + 1


def test_willems_task_matches_its_parts():
    from bilevel.experiments.willems_budget import smallest_destabilizing_budget
    from bilevel.problems.willems_instance import WillemsSetting

    task = {"learner": "willems", "defense": "ridge", "param": 1e-2, "N": 15, "seed": 3, "attack_seed": 1}
    row = frontier_task(task)
    found = smallest_destabilizing_budget(WillemsSetting(objective="destabilize", horizon=15, seed=3, reg=1e-2),
                                          rel_tol=0.1, starts=8, seed=1)
    assert row["delta_star"] == found.delta and 0 < row["delta_star"] <= 1.0
    assert 7.0 < row["clean_cost"] < 20.0  # the batch reactor's trace(Qx W) near the SDP optimum (7.70 at reg 1e-8)


def test_clean_gain_of_the_radius_problem_is_the_learners_to_rounding():
    """clean_gain solves the learner on the radius problem (shared with destabilize_attack): the gain of the declared
    problem's learner, to rounding (the clean costs of the committed frontier agree to 1e-15 relative)."""
    from bilevel.experiments.defenses import clean_gain
    from bilevel.problems.willems import build_attack
    from bilevel.problems.willems_instance import WillemsSetting

    for reg in (1e-8, 1e-2):
        attack = build_attack(WillemsSetting(objective="destabilize", horizon=15, seed=3, reg=reg))
        zero = np.zeros(int(attack.upper.numel()))
        declared = attack.loop(zero, attack.oracle().evaluate(zero).lower.y)[0]
        np.testing.assert_allclose(clean_gain(attack), declared, rtol=1e-12, atol=1e-12)


def test_input_integrity_deviance():
    from bilevel.ddc.input_integrity import filtered_white_spectrum, whittle_deviance

    rng = np.random.default_rng(0)
    n = 256
    flat = filtered_white_spectrum(None, n)
    clean = [whittle_deviance(rng.standard_normal(n), flat) for _ in range(200)]
    # r_k ~ Exp(1) on the 127 inner frequencies: E[r - 1 - log r] = Euler's gamma each
    assert np.mean(clean) == pytest.approx(127 * np.euler_gamma, rel=0.05)
    assert whittle_deviance(2 * rng.standard_normal(n), flat) > max(clean)  # four times the power
    u = rng.standard_normal(n)
    spectrum = np.abs(np.fft.rfft(u)) ** 2 / n  # the periodogram itself: zero deviance
    assert whittle_deviance(u, spectrum) == pytest.approx(0.0, abs=1e-9)


def test_detection_table():
    from bilevel.experiments.defenses_detection import detection_markdown

    rows = [{"case": "vrft-ignores", "data_seed": i, "statistic": float(i), "succeeded": i > 1} for i in range(4)]
    rows += [{"case": "ident-respects", "data_seed": i, "statistic": 0.01 * i, "succeeded": True} for i in range(4)]
    table = detection_markdown(rows, {"vrft": 1.5, "ident": 0.015})
    assert "| vrft-ignores | input integrity (Whittle deviance) | 1.5 | 4 | 2/4 " in table  # statistics 2, 3 > 1.5
    assert "| ident-respects | variance/whiteness tests (min p) | 0.015 | 4 | 2/4 " in table  # p 0, 0.01 < 0.015
    assert "| 2/4 |" in table and "| 4/4 |" in table


def test_attack_respecting_the_input_check_leaves_the_input_clean():
    from bilevel.ddc.input_integrity import filtered_white_spectrum, whittle_deviance
    from bilevel.experiments.defenses_detection import detection_task
    from bilevel.problems.willems_instance import WillemsSetting

    row = detection_task({"case": "willems-respects", "N": 128, "T": 15, "seed": 5, "attack_seed": 2})
    _, u = WillemsSetting(horizon=15, seed=5).experiment()
    assert row["statistic"] == pytest.approx(whittle_deviance(u, filtered_white_spectrum(None, 15)), rel=1e-12)
    assert row["succeeded"]  # 0.1 per state entry destabilizes this data set's true loop


@pytest.mark.slow  # a budget search (5 DeePC attacks) and two more attacks: about 10 s
def test_deepc_task_reaches_the_degradation_goal():
    """delta* of a DeePC data set: at it the adaptive attack at least doubles the clean plan's true tracking cost
    (checked against a DeePC written in test_deepc), at half of it the attack does not."""
    from bilevel.experiments.defenses import FACTOR, deepc_cost
    from bilevel.problems.deepc_instance import attack_instance
    from tests.problems.test_deepc import own_deepc, true_cost

    task = {"learner": "deepc", "defense": "ridge", "param": 0.1, "N": 60, "seed": 3, "attack_seed": 1}
    row = frontier_task(task)
    atk = attack_instance(T=60, horizon=6, seed=3, lambda_g=0.1)
    assert row["clean_cost"] == pytest.approx(true_cost(atk, own_deepc(atk, atk.u, atk.y)[2]), rel=1e-5)
    assert 0 < row["delta_star"] < 0.5
    assert deepc_cost(0.1, 60, 3, row["delta_star"], 1) >= FACTOR * row["clean_cost"]
    assert deepc_cost(0.1, 60, 3, row["delta_star"] / 2, 1) < FACTOR * row["clean_cost"]


def test_identification_rows_pair_with_least_squares():
    rows = [{"learner": "ident", "defense": d, "param": p, "N": 25, "data_seed": i, "clean_cost": c,
             "delta_star": delta * (1 + i), "attacks": 5}
            for d, p, c, delta in (("ls", 0.0, 0.1, 0.01), ("huber", 1.345, 0.09, 0.02), ("lad", 0.0, 0.2, 0.005))
            for i in range(8)]
    summary = {s["defense"]: s for s in summarize(rows)}
    assert summary["huber"]["delta_ratio"] == pytest.approx(2.0) and summary["huber"]["delta_larger"] == 8
    assert summary["lad"]["cost_ratio"] == pytest.approx(2.0) and summary["lad"]["delta_smaller"] == 8
    assert summary["ls"]["delta_ratio"] == 1.0


def test_vrft_radius_reads_a_singular_learner_from_the_result(monkeypatch):
    """vrft_radius is inf where a start of the attack ended on a singular learner (its record's SINGULAR_LEARNER) and
    otherwise the true loop's radius at the attack's poisoning (zero poisoning here: the clean IV learner's)."""
    import dataclasses

    from bilevel.experiments import defenses
    from bilevel.problems.defended_vrft import defended_instance
    from bilevel.solvers.engine.block_exact import SINGULAR_LEARNER

    d = defended_instance("iv", "destabilize", 0.0, "B", 0.02, 0.02, 0, 128)
    clean = d.atk.setting.loop.spectral_radius(d.theta_clean)
    zero = {"a_u": np.zeros(128), "a_y": np.zeros(128), "a_y2": np.zeros(128)}
    base = defenses.solve(defenses.declare(d), method="hypergradient", starts=1, max_iter=0)
    fake = dataclasses.replace(base, x=zero, start_records=({"status": "solved", "message": "tol",
                                                             SINGULAR_LEARNER: False},))
    monkeypatch.setattr(defenses, "solve", lambda *args, **kwargs: fake)
    assert defenses.vrft_radius("iv", 0.0, 128, 0, 0.02, 0) == pytest.approx(clean, rel=1e-12)
    singular = dataclasses.replace(fake, start_records=({"status": "error", "message": "...", SINGULAR_LEARNER: True},))
    monkeypatch.setattr(defenses, "solve", lambda *args, **kwargs: singular)
    assert defenses.vrft_radius("iv", 0.0, 128, 0, 0.02, 0) == math.inf


def test_vrft_radius_on_the_kept_problem_is_a_fresh_declarations():
    """vrft_radius re-sets the budget parameters of the problem declared for the data set's first budget (budget_values):
    at each budget of a search the answer is that of the problem declared afresh at that budget."""
    from bilevel.experiments import defenses
    from bilevel.problems.defended_vrft import defended_instance

    for eps in (0.05, 0.02):
        d = defended_instance("iv", "destabilize", 0.0, "B", eps, eps, 4, 128)
        fresh = defenses.solve(defenses.declare(d), starts=2, seed=1)
        x = {k: np.asarray(v, dtype=float).ravel() for k, v in fresh.x.items()}
        assert defenses.vrft_radius("iv", 0.0, 128, 4, eps, 1) == d.atk.setting.loop.spectral_radius(d.poisoned(**x))


def test_learner_subset_keeps_the_full_runs_tasks():
    """A subset runs exactly the full sweep's tasks of those learners (same keys and seeds: a full run's rows are
    reused, and a subset's rows by a later full run); a bad subset names the valid learners."""
    from bilevel.errors import ModelError
    from bilevel.experiments.defenses import check_learners, frontier_tasks, learners_line, make_plan

    plan = make_plan(3, quick=True)
    full = frontier_tasks(plan, 0)
    subset = frontier_tasks(plan, 0, ["willems", "vrft"])
    assert subset == [t for t in full if t["learner"] in ("vrft", "willems")]
    assert {t["learner"] for t in full} == {"vrft", "willems", "ident", "deepc"} and len(subset) == 3 * (6 + 4)
    assert check_learners(["deepc", " vrft"]) == ("vrft", "deepc")
    assert learners_line(["willems", "vrft"]) == "Learners run: vrft, willems (not run: ident, deepc)."
    assert learners_line(None) == "Learners run: vrft, willems, ident, deepc (all)."
    for bad, why in ((["vrft", "dpt"], "unknown learner(s) 'dpt'"), ([], "no learner given"),
                     (["vrft", "vrft"], "repeated")):
        with pytest.raises(ModelError, match=r"subset of vrft,willems,ident,deepc") as info:
            check_learners(bad)
        assert why in str(info.value)


def test_run_defenses_on_one_learner_resumes(tmp_path):
    """run_defenses on De Persis–Tesi alone: its frontier rows and detection cases only, the learners named in
    frontier.md; a rerun computes nothing."""
    import json

    from bilevel.experiments.defenses import run_defenses

    notes = []
    path = run_defenses(sims=1, out_dir=str(tmp_path), quick=True, workers=1, progress=notes.append,
                        learners=["willems"])
    rows = [json.loads(line) for line in (tmp_path / "defenses.jsonl").read_text().splitlines()]
    assert {r["learner"] for r in rows} == {"willems"} and sorted(r["param"] for r in rows) == [1e-8, 1e-2, 1e-1, 1.0]
    text = (tmp_path / "frontier.md").read_text()
    assert path == str(tmp_path / "frontier.md")
    assert text.startswith("Learners run: willems (not run: vrft, ident, deepc).")
    assert text.count("| willems | ridge |") == 4 and "| vrft |" not in text
    detection = [json.loads(line)["case"] for line in (tmp_path / "detection.jsonl").read_text().splitlines()]
    assert sorted(detection) == ["willems-ignores", "willems-respects"]
    assert "| willems-ignores |" in (tmp_path / "detection.md").read_text()
    notes.clear()
    run_defenses(sims=1, out_dir=str(tmp_path), quick=True, workers=1, progress=notes.append, learners=["willems"])
    assert (tmp_path / "defenses.jsonl").read_text().count("\n") == 4 and not any("running" in n for n in notes)


def test_frontier_labels_of_close_points_do_not_overlap() -> None:
    """Parameter labels: coinciding points of one series share a label; close labels of different series are
    lifted apart (the committed frontier figure printed '0' and '0.0001' over each other)."""
    from matplotlib.figure import Figure

    from bilevel.experiments.defenses import _annotate_apart

    ax = Figure(figsize=(5, 4)).add_subplot()
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    _annotate_apart(ax, [(0.5, 0.5, "1e-08", "C0"), (0.501, 0.5, "0.01", "C0"), (0.505, 0.5, "0", "C1"),
                         (0.9, 0.1, "1", "C0")])
    texts = {t.get_text(): t.xyann for t in ax.texts}
    assert set(texts) == {"1e-08, 0.01", "0", "1"}
    assert texts["0"][1] > texts["1e-08, 0.01"][1] and texts["1"] == (4, 4)
