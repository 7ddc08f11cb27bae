"""`bilevel reproduce identification`: its tasks, the engine's stealthy attack and the SLSQP baseline judged by an
independent computation of the three statistics (written out here), and the quick command's files."""

from __future__ import annotations

import json
import os

import numpy as np

from bilevel.experiments.identification import METHOD, attack_task, cell_tasks, compare, make_plan, warm_up
from bilevel.experiments.identification_baseline import judge, slsqp_attack
from bilevel.problems.identification import load_instance, problem_for
from bilevel.problems.identification_instance import attack_instance


def own_statistics(X: np.ndarray, U: np.ndarray, sigma: float, lags: int) -> dict[str, float]:
    """Variance, whiteness and input-F statistics of the state-space least-squares fit, written sample by sample."""
    T = U.shape[1]
    Z, Y = np.vstack([X[:, :T], U]), X[:, 1:T + 1]
    E = Y - np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T @ Z
    E0 = Y - np.linalg.lstsq(X[:, :T].T, Y.T, rcond=None)[0].T @ X[:, :T]
    n, N = E.shape
    R = [sum(np.outer(E[:, t], E[:, t - j]) for t in range(j, N)) / N for j in range(lags + 1)]
    R0inv = np.linalg.inv(R[0])
    Q = N * N * sum(np.trace(R[j].T @ R0inv @ R[j] @ R0inv) / (N - j) for j in range(1, lags + 1))
    rss, rss0 = float(np.sum(E ** 2)), float(np.sum(E0 ** 2))
    return {"variance": rss / sigma ** 2, "whiteness": float(Q),
            "input": ((rss0 - rss) / (n * U.shape[0])) / (rss / (n * (N - Z.shape[0])))}


def check_stealthy(atk, signals: dict[str, np.ndarray], delta: float) -> None:
    clean = own_statistics(atk.signals["X"], atk.signals["U"], atk.setting.noise_std, atk.lags)
    after = own_statistics(signals["X"], signals["U"], atk.setting.noise_std, atk.lags)
    for name in clean:
        assert abs(1 - after[name] / clean[name]) <= delta + 1e-6, name
    for k in ("X", "U"):
        assert np.linalg.norm(signals[k] - atk.signals[k]) <= delta * np.linalg.norm(atk.signals[k]) * (1 + 1e-6)


def test_plans_and_tasks() -> None:
    assert make_plan(100, False) == make_plan(100, False, 10)
    full, quick = make_plan(100, False), make_plan(100, True)
    assert (full.horizons, full.deltas, full.baseline_sims) == ((100, 500), (0.01, 0.025, 0.05, 0.075, 0.1), 10)
    assert (quick.sims, quick.baseline_sims, quick.horizons) == (2, 1, (100,))
    tasks = cell_tasks(3, seed=0, horizons=(100,), deltas=(0.01, 0.05))
    assert len(tasks) == 6 and len({t["key"] for t in tasks}) == 6
    by_delta = {d: [t["seed"] for t in tasks if t["delta"] == d] for d in (0.01, 0.05)}
    assert by_delta[0.01] == by_delta[0.05] and len(set(by_delta[0.01])) == 3
    base = cell_tasks(3, seed=0, horizons=(100,), deltas=(0.01, 0.05), baseline=True)
    assert [t["key"] for t in base] == [t["key"] for t in tasks] and base[0]["maxiter"] == 100


def test_engine_attack_is_stealthy_by_an_independent_computation() -> None:
    task = {"key": "k", "T": 100, "delta": 0.05, "seed": 1, "lags": 10}
    atk = attack_instance("ss", T=100, eps=0.05, stealth=0.05, seed=1)
    problem = problem_for(atk)
    result = problem.solve(**METHOD, seed=0)
    assert result.status.value == "solved" and result.certificate.passed
    signals = {k: atk.signals[k] + np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in atk.signals}
    check_stealthy(atk, signals, 0.05)
    row = attack_task(task)  # the sweep's row: the same attack, judged by the library's tests
    assert row["stealthy"] and row["certified"] and row["status"] == "solved"
    assert warm_up(task) == 0.0 and row["warm_up_cpu_time"] >= 0.0  # this process has compiled T = 100's problem
    assert np.isclose(row["norm2"], np.linalg.norm(result.y["theta"] - atk.theta0, 2), rtol=1e-6)
    assert row["norm2"] <= row["frobenius"] <= 2 * row["norm2"]  # rank of d[A B] <= 4
    assert row["max_relative_change"] <= 0.05 + 1e-6 and max(row["budget_used"].values()) <= 0.05 * (1 + 1e-6)
    load_instance(problem, attack_instance("ss", T=100, eps=0.05, stealth=0.05, seed=2))  # the start follows the data
    assert not np.allclose(problem.suggested_starts[0]["dX"], result.x["dX"].ravel(order="F"))


def test_slsqp_baseline_and_comparison() -> None:
    atk = attack_instance("ss", T=100, eps=0.01, stealth=0.01, seed=3)
    signals, seconds, iterations = slsqp_attack(atk, seed=3, maxiter=20)
    assert seconds > 0 and 1 <= iterations <= 20
    verdict = judge(atk, signals)
    if verdict["stealthy"]:
        check_stealthy(atk, signals, 0.01)
    row = {"key": "a", "task": {"T": 100, "delta": 0.01}, "stealthy": True, "cpu_time": 1.0}
    rows = [{**row, "norm2": 2.0}, {**row, "key": "b", "norm2": 1.0}]
    base = [{**row, "norm2": 1.5, "cpu_time": 10.0}, {**row, "key": "b", "norm2": 1.5, "cpu_time": 30.0}]
    assert compare(rows, base)[(100, 0.01)] == {"n": 2, "at_least_baseline": 1, "time_ratio": 20.0}


def test_quick_command_writes_the_report(tmp_path) -> None:
    from bilevel.cli import main

    out = str(tmp_path / "ident")
    assert main(["reproduce", "identification", "--quick", "--out", out, "--workers", "1"]) == 0
    for name in ("report.md", "error_norm.png", "statistics.png", "p_values.png", "stealthy.jsonl", "slsqp.jsonl"):
        assert os.path.getsize(os.path.join(out, name)) > 0
    with open(os.path.join(out, "stealthy.jsonl")) as fh:
        rows = [json.loads(line) for line in fh]
    assert len(rows) == 4 and all(r["stealthy"] for r in rows)
    assert sum(r["warm_up_cpu_time"] > 0 for r in rows) <= 1  # one worker: one warm-up for T = 100, in no row's time
    for r in rows:  # the stored statistics are within delta of the clean ones, read back from the file
        for name, before in r["before"].items():
            assert abs(1 - r["after"][name]["statistic"] / before["statistic"]) <= r["task"]["delta"] + 1e-6
    report = open(os.path.join(out, "report.md")).read()
    assert "| 100 | 0.05 | 2/2 |" in report and "Side by side: SLSQP baseline" in report
    assert main(["reproduce", "identification", "--quick", "--out", out, "--workers", "1"]) == 0  # resumes: no rerun
    with open(os.path.join(out, "stealthy.jsonl")) as fh:
        assert len(fh.readlines()) == 4


def test_stealth_start_is_inside_the_stealth_constraints() -> None:
    for delta, seed in ((0.01, 0), (0.1, 1)):
        atk = attack_instance("ss", T=100, eps=delta, stealth=delta, seed=seed)
        problem = problem_for(atk)
        start = problem.suggested_starts[0]
        signals = {k: atk.signals[k] + np.reshape(start[f"d{k}"], atk.signals[k].shape, order="F") for k in ("X", "U")}
        assert np.linalg.norm(start["dX"]) > 0  # not the clean point, where the attacker's gradient vanishes
        check_stealthy(atk, signals, delta)
