"""stealth_kind "authors": Russo & Proutiere's stealth constraints (L4DC 2023, arXiv 2211.08804, section 5; their
example_stealthy_attack/algorithm.py), their statistics' exact Jacobians, the independent check, the loader of their
data-set format (files written here in that format) and `bilevel reproduce identification --paper`."""

from __future__ import annotations

import json
import os
import pickle
import sys
import types
from collections import namedtuple

import casadi as ca
import numpy as np
import pytest

from bilevel.cli import main
from bilevel.ddc.stealth_check import check_stealth, correlations, statistics
from bilevel.ddc.stealth_statistics import StealthStatistics, authors_lags
from bilevel.errors import InvalidData, ModelError
from bilevel.experiments.identification_paper import DELTAS, PLANT, attack_tasks, dataset_path, load_dataset, \
    paper_attack, paper_instance
from bilevel.numeric_node import numeric_node
from bilevel.problems.identification import problem_for
from bilevel.problems.identification_instance import attack_instance


def fit_parts(X: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, ...]:
    Y, Z = X[:, 1:], np.vstack([X[:, :-1], U])
    theta = np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T
    theta_r = np.linalg.lstsq(X[:, :-1].T, Y.T, rcond=None)[0].T
    return Y, Z, theta, theta_r


def test_lags_follow_the_authors_rule() -> None:
    """s = 2 floor(0.025 T): 4 lags at T = 100, 24 at T = 500 (algorithm.py: num_lags = int(0.025 T), s = 2
    num_lags)."""
    assert (authors_lags(100), authors_lags(500), authors_lags(79), authors_lags(80)) == (4, 24, 2, 4)


def test_correlations_are_the_authors_order() -> None:
    """C_1 = (1/T) sum_t e_t e_{t+1}': for e_t = (t, 1) the (0, 1) entry sums t and the (1, 0) entry sums t + 1."""
    E = np.vstack([np.arange(4.0), np.ones(4)])
    C1 = correlations(E, 1)[1]
    assert np.allclose(C1, np.array([[0 * 1 + 1 * 2 + 2 * 3, 0 + 1 + 2], [1 + 2 + 3, 3]]) / 4)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_statistics_match_the_independent_check(seed: int) -> None:
    """The attack's statistics (one vectorized evaluation) equal the check's sample-by-sample sums, on clean and on
    randomly changed data."""
    rng = np.random.default_rng(seed)
    X, U = rng.standard_normal((4, 101)), rng.standard_normal((1, 100))
    for dX, dU in ((0 * X, 0 * U), (0.1 * rng.standard_normal(X.shape), 0.1 * rng.standard_normal(U.shape))):
        Y, Z, theta, theta_r = fit_parts(X + dX, U + dU)
        values, _ = StealthStatistics(4, 5, 100, (0, 1, 2, 3), 4).evaluate(Y, Z, theta, theta_r)
        check = statistics(X + dX, U + dU, 4)
        assert np.allclose(values, [check["r"], check["zd"], *check["correlation"]], rtol=1e-10, atol=0)


def test_jacobian_matches_central_differences() -> None:
    """Every block of the exact Jacobian (at a point off the least-squares fit, so every term counts) against central
    differences of step 1e-6."""
    rng = np.random.default_rng(3)
    X, U = rng.standard_normal((4, 61)), rng.standard_normal((1, 60))
    Y, Z, theta, theta_r = fit_parts(X, U)
    args = [Y, Z, theta + 0.1 * rng.standard_normal(theta.shape), theta_r - 0.1]
    stats = StealthStatistics(4, 5, 60, (0, 1, 2, 3), authors_lags(60))
    _, blocks = stats.evaluate(*args, jacobian=True)
    for j, block in enumerate(blocks):
        for _ in range(4):
            idx = tuple(int(rng.integers(d)) for d in args[j].shape)
            up, down = [a.copy() for a in args], [a.copy() for a in args]
            up[j][idx] += 1e-6
            down[j][idx] -= 1e-6
            fd = (stats.evaluate(*up)[0] - stats.evaluate(*down)[0]) / 2e-6
            assert np.allclose(block[(slice(None), *idx)], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())


def test_numeric_node_derivative_in_casadi() -> None:
    """CasADi's jacobian of an expression calling the node (SX, through a linear map of its input) is the node's
    Jacobian times that map."""
    rng = np.random.default_rng(4)
    X, U = rng.standard_normal((4, 61)), rng.standard_normal((1, 60))
    Y, Z, theta, theta_r = fit_parts(X, U)
    stats = StealthStatistics(4, 5, 60, (0, 1, 2, 3), 2)
    node = numeric_node("t", stats.evaluate, [Y.shape, Z.shape, theta.shape, theta_r.shape], stats.size)
    x = ca.SX.sym("x", Y.size)
    out = node(3 * ca.reshape(x, *Y.shape), Z, theta, theta_r)
    value, jac = ca.Function("f", [x], [out, ca.jacobian(out, x)])(Y.ravel(order="F") / 3)
    want_value, blocks = stats.evaluate(Y, Z, theta, theta_r, jacobian=True)
    assert np.allclose(np.array(value).ravel(), want_value, rtol=1e-12)
    assert np.allclose(np.array(jac), 3 * blocks[0].transpose(0, 2, 1).reshape(stats.size, -1), rtol=1e-12)


def test_authors_attack_is_stealthy_by_the_independent_check() -> None:
    """T = 100, delta = 0.05 on the flexible transmission: the engine's answer satisfies every authors' constraint
    within 1e-6 by the numpy check (each lag's ratio, Z_d, the residual energy, both norm ratios, the box), and its
    ||d[A B]||_2 is the numpy refit's."""
    atk = attack_instance("ss", T=100, eps=0.05, objective="spectral", stealth=0.05, seed=0, stealth_kind="authors")
    assert atk.lags == 4 and atk.box == 0.5
    result = problem_for(atk).solve(method="reduced", starts=1, nlp_tol=1e-6, seed=0)
    X, U = atk.signals["X"], atk.signals["U"]
    check = check_stealth(X, U, result.x["dX"].reshape(X.shape), result.x["dU"].reshape(U.shape), 0.05)
    assert result.status.value == "solved" and check["stealthy"], (result.status, check["worst"], check["violation"])
    assert set(check["ratios"]) == {"c_r", "c_z", "c_x", "c_u", "c_c1", "c_c2", "c_c3", "c_c4"}
    assert np.isclose(check["norm2"], np.linalg.norm(result.y["theta"] - atk.theta0, 2), rtol=1e-8)
    assert np.isclose(result.upper_objective, check["norm2"] ** 2, rtol=1e-8)


def test_authors_kind_refuses_what_it_cannot_take() -> None:
    with pytest.raises(ModelError, match="state-space"):
        attack_instance("arx", T=100, stealth=0.05, stealth_kind="authors")
    with pytest.raises(ModelError, match="lags=None"):
        attack_instance("ss", T=100, stealth=0.05, stealth_kind="authors", lags=10)
    with pytest.raises(ModelError, match="stealth_kind"):
        attack_instance("ss", T=100, stealth=0.05, stealth_kind="paper")


def write_authors_format(folder: str, T: int, sims: int, seed: int = 0) -> None:
    """Data sets as the authors' extract_data.py writes them: a pickled utils.CollectedData (a NamedTuple of their
    utils module; a stand-in module of that name here) of the flexible transmission in scipy's realization, x_0
    standard normal, std_u = 1, std_w = 0.1."""
    from scipy.signal import tf2ss

    A, B, _, _ = tf2ss(*PLANT)
    utils = types.ModuleType("utils")
    record = namedtuple("CollectedData", "X U W std_u std_w")
    record.__module__ = "utils"
    utils.CollectedData = record
    rng = np.random.default_rng(seed)
    sys.modules["utils"] = utils
    try:
        for i in range(sims):
            X, U, W = np.zeros((4, T + 1)), rng.standard_normal((1, T)), 0.1 * rng.standard_normal((4, T))
            X[:, 0] = rng.standard_normal(4)
            for t in range(T):
                X[:, t + 1] = A @ X[:, t] + B[:, 0] * U[0, t] + W[:, t]
            with open(dataset_path(folder, T, i), "wb") as fh:
                pickle.dump(record(X, U, W, 1.0, 0.1), fh, protocol=pickle.HIGHEST_PROTOCOL)
    finally:
        del sys.modules["utils"]


def test_loader_reads_their_format_and_nothing_else(tmp_path) -> None:
    write_authors_format(str(tmp_path), 100, 1)
    data = load_dataset(dataset_path(str(tmp_path), 100, 0))
    assert data.X.shape == (4, 101) and data.U.shape == (1, 100) and data.std_w == 0.1
    atk = paper_instance(data, 0.05)
    assert atk.stealth_kind == "authors" and atk.lags == 4 and atk.objective == "spectral"
    bad = tmp_path / "data_100timesteps_1.pkl"
    bad.write_bytes(pickle.dumps(os.path.join))  # a callable, not their record
    with pytest.raises(InvalidData, match="not one of theirs"):
        load_dataset(str(bad))
    with pytest.raises(InvalidData, match="datasets.7z"):
        load_dataset(dataset_path(str(tmp_path), 500, 0))


def test_continuation_over_the_delta_grid(tmp_path) -> None:
    """paper_attack on one data set in their format, each delta from the smaller delta's answer: every answer
    stealthy by the independent check, ||d[A B]||_2 never falls as delta grows, the first start cold and the later
    ones warm where the warm run is kept; an answer that breaks the constraints at delta (here the answer at a larger
    delta) is no start: the run is cold."""
    write_authors_format(str(tmp_path), 100, 1, seed=3)
    data = load_dataset(dataset_path(str(tmp_path), 100, 0))
    runs, smaller = [], None
    for delta in DELTAS[:3]:
        smaller = paper_attack(data, delta, smaller)
        runs.append(smaller)
    for delta, run in zip(DELTAS, runs):
        again = check_stealth(data.X, data.U, run.dX, run.dU, delta)
        assert again["stealthy"] and run.check["stealthy"], (delta, again["worst"], again["violation"])
    norms = [run.check["norm2"] for run in runs]
    assert all(b >= a for a, b in zip(norms, norms[1:])), norms
    assert runs[0].start == "cold" and {run.start for run in runs[1:]} <= {"warm", "cold", "kept"}
    assert "warm" in {run.start for run in runs[1:]}, [run.start for run in runs]
    back = paper_attack(data, DELTAS[0], runs[-1])
    assert not check_stealth(data.X, data.U, runs[-1].dX, runs[-1].dU, DELTAS[0])["stealthy"]
    assert back.start == "cold" and back.check["stealthy"] and np.isclose(back.check["norm2"], norms[0], rtol=1e-6)


def test_attack_tasks_continue_within_their_batch(tmp_path) -> None:
    """attack_tasks (run_paper's batch of one data set's tasks) returns rows in the tasks' order, each delta continued
    from the smaller delta's answer of the same batch, whatever the tasks' order: the same rows in reversed order."""
    write_authors_format(str(tmp_path), 100, 1, seed=3)
    path = dataset_path(str(tmp_path), 100, 0)
    tasks = [{"path": path, "delta": delta} for delta in DELTAS[:3]]
    forward, backward = attack_tasks(tasks), attack_tasks(tasks[::-1])
    assert forward[0]["start"] == "cold" and set(r["start"] for r in forward[1:]) != {"cold"}
    assert [r["start"] for r in backward[::-1]] == [r["start"] for r in forward]
    assert [r["norm2"] for r in backward[::-1]] == pytest.approx([r["norm2"] for r in forward], rel=1e-6)


def test_problem_for_without_start_suggests_none() -> None:
    """start=False leaves the problem without suggested starts (the caller suggests its own); the default suggests the
    stealth start."""
    atk = attack_instance("ss", T=100, eps=0.05, objective="spectral", stealth=0.05, seed=0, stealth_kind="authors")
    assert len(problem_for(atk).suggested_starts) == 1
    assert problem_for(atk, start=False).suggested_starts == []
    assert len(problem_for(atk).suggested_starts) == 1


def test_reproduce_paper_on_data_in_their_format(tmp_path) -> None:
    """`reproduce identification --paper DIR` on one T = 100 data set written in their format: five rows (one per
    delta), every answer stealthy by the independent check and at least the answer at a smaller delta (whose feasible
    set lies inside), the table in report.md."""
    data, out = tmp_path / "datasets", str(tmp_path / "out")
    data.mkdir()
    write_authors_format(str(data), 100, 1, seed=5)
    assert main(["reproduce", "identification", "--paper", str(data), "--out", out, "--workers", "1"]) == 0
    rows = [json.loads(line) for line in open(os.path.join(out, "authors_terms.jsonl"))]
    assert sorted(r["task"]["delta"] for r in rows) == [0.01, 0.025, 0.05, 0.075, 0.1]
    assert all(r["stealthy"] and r["violation"] <= 1e-6 for r in rows), [(r["worst"], r["violation"]) for r in rows]
    norms = [r["norm2"] for r in sorted(rows, key=lambda r: r["task"]["delta"])]
    assert all(b >= a for a, b in zip(norms, norms[1:])), norms  # nested budgets: each from the smaller's answer
    starts = [r["start"] for r in sorted(rows, key=lambda r: r["task"]["delta"])]
    assert starts[0] == "cold" and set(starts[1:]) != {"cold"}, starts  # the batch hands each answer to the next delta
    report = open(os.path.join(out, "report.md")).read()
    assert "| 100 | 0.05 | 1 | 1 |" in report
    assert main(["reproduce", "identification", "--paper", str(data), "--quick", "--out", out]) == 2


def test_numeric_node_reverse_in_several_directions() -> None:
    """The node's reverse derivative with two adjoint directions at once gives each seed times the Jacobian."""
    rng = np.random.default_rng(6)
    X, U = rng.standard_normal((4, 61)), rng.standard_normal((1, 60))
    Y, Z, theta, theta_r = fit_parts(X, U)
    stats = StealthStatistics(4, 5, 60, (0, 1, 2, 3), 2)
    node = numeric_node("t2", stats.evaluate, [Y.shape, Z.shape, theta.shape, theta_r.shape], stats.size)
    seeds = rng.standard_normal((stats.size, 2))
    outs = node.reverse(2)(Y, Z, theta, theta_r, node(Y, Z, theta, theta_r), seeds)
    _, blocks = stats.evaluate(Y, Z, theta, theta_r, jacobian=True)
    for out, block in zip(outs, blocks):
        got, cols = np.array(out), block.shape[2]  # direction j: columns j cols .. (j + 1) cols - 1
        for j in range(2):
            want = np.tensordot(seeds[:, j], block, axes=1)
            assert np.allclose(got[:, j * cols:(j + 1) * cols], want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", [ca.SX, ca.MX])
def test_expressions_equal_the_numeric_statistics(kind: type) -> None:
    """StealthStatistics.expression (CasADi, for the compiled NLP) and evaluate (numpy) share one definition (_parts):
    their values agree to 1e-12 relative on changed data, and CasADi's derivative of the expressions equals
    evaluate's exact Jacobian to 1e-9."""
    rng = np.random.default_rng(4)
    X, U = rng.standard_normal((4, 101)), rng.standard_normal((1, 100))
    Y, Z, theta, theta_r = fit_parts(X + 0.1 * rng.standard_normal(X.shape), U)
    stats = StealthStatistics(4, 5, 100, (0, 1, 2, 3), 4)
    syms = [kind.sym(name, *a.shape) for name, a in zip(("Y", "Z", "t", "tr"), (Y, Z, theta, theta_r))]
    expr = stats.expression(*syms)
    values, blocks = stats.evaluate(Y, Z, theta, theta_r, jacobian=True)
    got = np.asarray(ca.Function("s", syms, [expr])(Y, Z, theta, theta_r)).ravel()
    assert np.max(np.abs(got - values) / np.abs(values)) < 1e-12
    jac = ca.Function("j", syms, [ca.jacobian(expr, syms[1])])(Y, Z, theta, theta_r)
    assert np.allclose(np.asarray(jac), blocks[1].transpose(0, 2, 1).reshape(stats.size, -1), rtol=1e-9, atol=1e-9)


def test_compiled_reduced_reaches_the_callback_answer(tmp_path) -> None:
    """Method reduced with compiled=True (one CasADi graph, the spectral objective as max u'M u on the unit ball) on
    the problem declared with the statistics as expressions ends at the same stealthy answer as the callback path
    (||d[A B]||_2 to 1e-4 relative), each judged by the independent check."""
    write_authors_format(str(tmp_path), 100, 1, seed=3)
    data = load_dataset(dataset_path(str(tmp_path), 100, 0))
    runs = [paper_attack(data, DELTAS[1], compiled=compiled) for compiled in (False, True)]
    for run in runs:
        assert run.check["stealthy"], (run.check["worst"], run.check["violation"])
    assert np.isclose(runs[1].check["norm2"], runs[0].check["norm2"], rtol=1e-4), [r.check["norm2"] for r in runs]


def test_compiled_states_rho_of_a_psd_matrix_and_refuses_others() -> None:
    """compiled=True states max rho(M) as max u'M u over the unit ball: for M = y y' (PSD) it reaches the optimum
    rho = ||y||^2 = 2 at a corner of the box (y* = x); an indefinite M (rho from its negative eigenvalue) is refused,
    naming the option to drop."""
    from bilevel.model import BilevelProblem

    def problem(indefinite: bool) -> BilevelProblem:
        p = BilevelProblem("rho")
        x = p.upper_variable("x", 2, lb=-1, ub=1, start=[0.3, 0.2])
        y = p.lower_variable("y", 2)
        p.minimize_lower(ca.sumsqr(y - x))
        p.maximize_spectral_radius(ca.diag(ca.vertcat(y[0], -2)) if indefinite else ca.mtimes(y, y.T))
        return p

    result = problem(False).solve(method="reduced", compiled=True)
    assert np.isclose(result.upper_objective, 2.0, rtol=1e-6), result.upper_objective
    with pytest.raises(ModelError, match="drop compiled=True"):
        problem(True).solve(method="reduced", compiled=True)
