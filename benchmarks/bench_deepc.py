"""A DeePC learner declared as a user would, through lower_cvxpy, attacked by poisoning its output data.

The learner (Coulson, Lygeros & Doerfler 2019): min_{g, u, y, s} sum (y_k - r)^2 + R sum u_k^2 + lambda_g ||g||^2
+ lambda_y ||s||_1 s.t. Up g = u_ini, Yp g = y_ini + s, Uf g = u, Yf g = y, with Up, Uf, Yp, Yf the depth-L Hankel
matrices of the recorded input/output data as cvxpy Parameters; the output ones are bound to the poisoned data
y_d + dy, the attacker changing ATTACKED samples within an l_inf budget |dy_t| <= eps. The attacker maximizes the
true plant's tracking cost of the planned inputs (the plant's response from the same past, an affine map of u).

Every applicable method runs on it (time, objective, status) and the default; the best objective is the reference.
The registered DeePC attacks (deepc-tracking, deepc-first-action) get the same table at their defaults with either
budget norm (method ipopt is what auto runs there), then the default against the best method.
Usage: python benchmarks/bench_deepc.py > benchmarks/results/bench_deepc.txt
       python benchmarks/bench_deepc.py family   (the registered attacks' tables only)
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone

import casadi as ca
import control
import cvxpy as cp
import numpy as np

import bilevel as bl
from bilevel.ddc import simulate

T, ATTACKED, T_INI, HORIZON = 200, 80, 4, 10
LAMBDA_G, LAMBDA_Y, R_WEIGHT, REFERENCE = 1e-1, 1e3, 1e-2, 1.0
PLANT = control.tf([0.1, 0.05], [1.0, -1.5, 0.7], True)


def hankel(signal: ca.SX, depth: int) -> ca.SX:
    """The depth x (n - depth + 1) Hankel matrix of a column signal."""
    n = int(signal.numel())
    return ca.horzcat(*[signal[j:j + depth] for j in range(n - depth + 1)])


def deepc_problem(eps_fraction: float = 0.1, seed: int = 0) -> bl.BilevelProblem:
    """The attacked DeePC learner: T recorded samples, the first ATTACKED outputs poisoned, |dy| <= eps."""
    rng = np.random.default_rng(seed)
    u_d = rng.standard_normal(T)
    y_d = simulate(PLANT, u_d)
    past_u = rng.standard_normal(30)
    past_y = simulate(PLANT, past_u)
    u_ini, y_ini = past_u[-T_INI:], past_y[-T_INI:]
    depth, cols = T_INI + HORIZON, T - T_INI - HORIZON + 1
    free = simulate(PLANT, np.concatenate([past_u, np.zeros(HORIZON)]))[-HORIZON:]  # the plant's own future
    step = np.column_stack([simulate(PLANT, np.concatenate([np.zeros(30), np.eye(HORIZON)[k]]))[-HORIZON:]
                            for k in range(HORIZON)])
    eps = eps_fraction * float(np.std(y_d))

    Hu = cp.Parameter((depth, cols), name="Hu", value=np.array(hankel(ca.DM(u_d), depth)))
    Hy = cp.Parameter((depth, cols), name="Hy")
    g, u, y, s = cp.Variable(cols), cp.Variable(HORIZON), cp.Variable(HORIZON), cp.Variable(T_INI)
    learner = cp.Problem(cp.Minimize(cp.sum_squares(y - REFERENCE) + R_WEIGHT * cp.sum_squares(u)
                                     + LAMBDA_G * cp.sum_squares(g) + LAMBDA_Y * cp.norm1(s)),
                         [Hu[:T_INI] @ g == u_ini, Hy[:T_INI] @ g == y_ini + s,
                          Hu[T_INI:] @ g == u, Hy[T_INI:] @ g == y])
    p = bl.BilevelProblem("deepc")
    dy = p.upper_variable("dy", ATTACKED, lb=-eps, ub=eps)
    poisoned = ca.DM(y_d) + ca.vertcat(dy, ca.DM.zeros(T - ATTACKED))
    ll = p.lower_cvxpy(learner, parameters={Hy: hankel(poisoned, depth)})
    plan = ll[u]
    p.maximize_upper(ca.sumsqr(ca.DM(free) + ca.mtimes(ca.DM(step), plan) - REFERENCE))
    return p


def dense_least_squares(n: int, rows: int = 60, k: int = 20, seed: int = 0) -> bl.BilevelProblem:
    """Maximize the deviation of a least-squares fit (k coefficients, `rows` samples) whose targets the attacker
    shifts by B x, |x| <= 0.1 (n upper entries)."""
    rng = np.random.default_rng(seed)
    A, B, b = rng.standard_normal((rows, k)), rng.standard_normal((rows, n)), rng.standard_normal(rows)
    clean = np.linalg.lstsq(A, b, rcond=None)[0]
    p = bl.BilevelProblem(f"dense-ls-{n}")
    x = p.upper_variable("x", n, lb=-0.1, ub=0.1)
    y = p.lower_variable("y", k)
    p.minimize_lower(ca.sumsqr(ca.mtimes(ca.DM(A), y) - ca.DM(b) - ca.mtimes(ca.DM(B), x)))
    p.maximize_upper(ca.sumsqr(y - ca.DM(clean)))
    return p


def run(problem: bl.BilevelProblem, method: str, **options: object) -> tuple[str, str, float | None, float, str]:
    """(method that ran, status, objective, seconds, message) of one solve; a refusal is a status 'refused'."""
    t0 = time.perf_counter()
    try:
        r = problem.solve(method=method, time_limit=LIMIT, **options)
    except bl.BilevelError as exc:
        return method, "refused", None, time.perf_counter() - t0, str(exc)
    return r.method, r.status.value, r.upper_objective, time.perf_counter() - t0, r.message


LIMIT = 60.0
"""time_limit of every solve here (seconds)."""
TIE = 1e-6
"""Objectives within this relative distance of the best are ties (the family section's best method: the fastest)."""


def table(rows: list[tuple[str, str, str, float | None, float, str]], sense: str) -> None:
    """Rows (asked, ran, status, objective, seconds, message) with the gap to the best objective and the time ratio to
    the default's."""
    values = [r[3] for r in rows if r[3] is not None and r[2] in ("solved", "inaccurate")]
    best = (max if sense == "max" else min)(values) if values else None
    default = next(r[4] for r in rows if r[0] == "auto")
    print(f"  {'method':24s} {'ran':24s} {'status':20s} {'objective':>12s} {'gap':>8s} {'time s':>8s} {'/auto':>7s}")
    for asked, ran, status, value, seconds, message in rows:
        gap = "" if value is None or best is None else f"{abs(best - value) / max(abs(best), 1e-12):8.2%}"
        shown = "" if value is None else f"{value:12.6g}"
        print(f"  {asked:24s} {ran:24s} {status:20s} {shown:>12s} {gap:>8s} {seconds:8.2f} {seconds / default:7.1f}")
        if status == "refused":
            print(f"      ({message[:110]})")


def deepc_section() -> None:
    print(f"DeePC learner via lower_cvxpy: T = {T}, {ATTACKED} attacked output samples (l_inf box), T_ini = {T_INI}, "
          f"horizon {HORIZON}, lambda_g = {LAMBDA_G}, lambda_y = {LAMBDA_Y}; the attacker maximizes the true plant's "
          f"tracking cost of the plan. time_limit {LIMIT:g} s each.")
    rows = []
    for method in ("auto", "ipopt", "relaxation", "hypergradient", "differential-evolution", "block-exact", "global"):
        problem = deepc_problem()  # a fresh declaration: every method pays its own preparation
        rows.append((method, *run(problem, method)))
    table(rows, "max")
    print("  auto's reason:", next(r[5] for r in rows if r[0] == "auto").split(";")[0])


def load() -> str:
    """The machine's load averages (1, 5, 15 min) from `uptime`."""
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip().split("load average:")[-1].strip()


def family_section() -> None:
    """The registered DeePC attacks (bilevel/problems/deepc.py: the flexible transmission, T = 200, both signals
    poisoned within 5% budgets) with both norms, every applicable method; then the default against the best method:
    objective ratio, wall and CPU seconds (this process's), and the machine's load
    before each problem."""
    from bilevel.problems import registry

    summary = []
    for name in ("deepc-tracking", "deepc-first-action"):
        for norm in ("l2", "linf"):
            before = load()
            print(f"\n{name}, norm={norm} (other parameters at the registered defaults); time_limit {LIMIT:g} s each; "
                  f"load before: {before}")
            rows, cpu = [], {}
            for label, method, options in (("auto", "auto", {}), ("relaxation", "relaxation", {}),
                                           ("hypergradient", "hypergradient", {}),
                                           ("auto starts=1", "auto", {"starts": 1})):
                c0 = time.process_time()
                rows.append((label, *run(registry.get(name, norm=norm), method, **options)))
                cpu[label] = time.process_time() - c0
            table(rows, "max")
            done = [r for r in rows if r[3] is not None and r[2] in ("solved", "inaccurate")]
            top = max(r[3] for r in done)
            best = min((r for r in done if r[3] >= top - TIE * abs(top)), key=lambda r: r[4])  # ties: the fastest
            auto = rows[0]
            ratio = auto[3] / best[3] if auto[3] is not None else float("nan")
            summary.append((f"{name} {norm}", auto, cpu["auto"], best, cpu[best[0]], ratio, before))
            time_of_default(registry.get(name, norm=norm))
    print("\nthe default (auto) against the best method of each table (objective ratio: auto's over the best's):")
    print(f"  {'problem':26s} {'auto s':>7s} {'CPU s':>6s} {'best method':>14s} {'best s':>7s} {'CPU s':>6s} "
          f"{'objective ratio':>16s}  load before (1, 5, 15 min)")
    for label, auto, auto_cpu, best, best_cpu, ratio, before in summary:
        print(f"  {label:26s} {auto[4]:7.2f} {auto_cpu:6.2f} {best[0]:>14s} {best[4]:7.2f} {best_cpu:6.2f} "
              f"{ratio:16.4f}  {before}")


def time_of_default(problem: bl.BilevelProblem) -> None:
    """Where a default solve's wall time goes: its IPOPT starts (iterations and seconds each, the best one's index),
    the branch polish, and the rest (preparation, the NLPs' construction, the lower solves of the starts, the
    certificate and the local probe), from one more solve's start records."""
    t0 = time.perf_counter()
    r = problem.solve(time_limit=LIMIT)
    total = time.perf_counter() - t0
    records = r.start_records
    nlp = sum(rec["time"] for rec in records)
    print(f"  where auto's {total:.2f} s go: {len(records)} IPOPT starts {nlp:.2f} s (iterations "
          f"{', '.join(str(rec['iterations']) for rec in records)}; best start {r.stats.get('best_start')}), the "
          f"rest {total - nlp:.2f} s; {r.status.value} {r.upper_objective:.6g}")


def evaluation_cost() -> None:
    """Where hypergradient's time goes on the DeePC learner: one evaluation of phi (lower solve + upper sweep) and its
    gradient, against the lower solve alone, at 20 points of the box."""
    from bilevel.solvers.engine.prepared import prepare
    from bilevel.solvers.engine.implicit import shared_oracle

    prep = prepare(deepc_problem())
    oracle = shared_oracle(prep)
    rng = np.random.default_rng(1)
    points = [rng.uniform(prep.canon.x_lb, prep.canon.x_ub) for _ in range(20)]
    oracle.gradient(oracle.evaluate(points[0]))  # compiled functions built before timing
    t0 = time.perf_counter()
    for x in points:
        prep.canon.lower.solve(x)
    solve = (time.perf_counter() - t0) / len(points)
    t0 = time.perf_counter()
    for x in points:
        oracle.gradient(oracle.evaluate(x))
    total = (time.perf_counter() - t0) / len(points)
    print(f"  hypergradient on DeePC, per point: evaluation + gradient {1e3 * total:.1f} ms, of which the lower QP "
          f"solve (Clarabel + face polish, {prep.canon.lower.n_y} variables) {1e3 * solve:.1f} ms "
          f"({solve / total:.0%})")


def auto_section() -> None:
    from bilevel.problems import registry
    from bilevel.solvers.engine.prepared import prepare
    from bilevel.solvers.registry import choose_method

    print("\nauto's choice on the registered problems (bilevel list):")
    picks: dict[str, list[str]] = {}
    for name in registry.names():
        method, why = choose_method(prepare(registry.get(name)), {})
        picks.setdefault(f"{method}: {why}", []).append(name)
    for reason, names in sorted(picks.items()):
        print(f"  {reason}: {', '.join(names)}")
    print("\nwhere auto differs from ipopt (the former default), and a dense least squares (60 x 20, n upper):")
    cases = [(n, lambda n=n: registry.get(n)) for n in registry.names()
             if choose_method(prepare(registry.get(n)), {})[0] != "ipopt"]
    cases += [(f"dense-ls n={n}", lambda n=n: dense_least_squares(n)) for n in (5, 20, 80, 300)]
    for label, build in cases:
        problem = build()
        sense = problem.upper_objective.sense
        print(f" {label} ({sense}):")
        table([(m, *run(build(), m)) for m in ("auto", "ipopt", "hypergradient")], sense)


def main() -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False,
                            cwd=os.path.dirname(bl.__file__)).stdout.strip() or "unknown"
    print(f"bench_deepc: {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.node()}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, python {platform.python_version()}, "
          f"bilevel at {os.path.dirname(bl.__file__)} (commit {commit}), load {load()}")
    print("Times are wall clock in one process: compare ratios (/auto: seconds over the default's "
          "seconds in the same table), not absolute seconds; gap: relative to the best objective in the table.\n")
    if sys.argv[1:] == ["family"]:
        family_section()
        return
    deepc_section()
    family_section()
    evaluation_cost()
    auto_section()


if __name__ == "__main__":
    main()
