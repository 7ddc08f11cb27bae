"""Large lower levels: a dense least squares with 2,000 variables and an LP with 100 variables and 1,000 constraints.

Each (instance, declaration, method) runs in its own process with a wall-clock limit; the time includes the
declaration (not the data generation) and the certificate. Declarations: `lower_qp` (matrices) and the same
problem written as CasADi expressions (minimize_lower / lower_constraint), the baseline. Both instances have a
known optimum, so each answer is also compared with it:
  - ls: label poisoning of ridge regression, max ||w(t + dt) - w(t)||^2 over ||dt|| <= 5 % ||t||;
    w(t + dt) - w(t) = M dt with M = (X'X + reg I)^{-1} X', so the optimum is r^2 ||M||_2^2 (trust-region
    subproblem, More & Sorensen 1983);
  - lp: the follower minimizes c'y s.t. A y <= b + x, -1 <= y <= 1, the leader maximizes the follower's optimal
    cost over x in [-0.2, 0.2]^1000; that cost never increases when a right-hand side grows, so x = -0.2 is optimal.

    python benchmarks/bench_scale.py [--limit 120] [--out benchmarks/results/bench_scale.txt]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import time
from datetime import date

import numpy as np

LS_SHAPE, LP_SHAPE = (2010, 2000), (1000, 100)
REG, LS_BUDGET, LP_DELTA = 1e-3, 0.05, 0.2


def ls_data() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    X = rng.standard_normal(LS_SHAPE)
    return X, X @ rng.standard_normal(LS_SHAPE[1]) + 0.1 * rng.standard_normal(LS_SHAPE[0])


def lp_data() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The LP instance (bilevel.problems.rhs_lp) at LP_SHAPE."""
    from bilevel.problems.rhs_lp import rhs_lp_data

    return rhs_lp_data(*LP_SHAPE)


def declare(instance: str, form: str, data: tuple):
    """The bilevel problem, its lower level declared by matrices (form 'matrix') or expressions ('expression')."""
    import casadi as ca

    from bilevel import BilevelProblem

    p = BilevelProblem(instance)
    if instance == "ls":
        X, t = data
        n = X.shape[1]
        w_clean = np.linalg.solve(X.T @ X + REG * np.eye(n), X.T @ t)
        dt = p.upper_variable("dt", X.shape[0])
        p.upper_constraint(ca.sumsqr(dt) <= (LS_BUDGET * np.linalg.norm(t)) ** 2)
        w = p.lower_variable("w", n)
        p.maximize_upper(ca.sumsqr(w - w_clean))
        p.suggest_start(dt=LS_BUDGET * t)  # on the budget sphere: dt = 0 is a stationary point
        if form == "matrix":
            p.lower_qp(w, C=X, d=t + dt, P=REG * np.eye(n))
        else:
            p.minimize_lower(0.5 * ca.sumsqr(ca.mtimes(ca.DM(X), w) - t - dt) + 0.5 * REG * ca.sumsqr(w))
    else:
        A, b, c = data
        x = p.upper_variable("x", A.shape[0], lb=-LP_DELTA, ub=LP_DELTA)
        y = p.lower_variable("y", A.shape[1], lb=-1, ub=1)
        p.maximize_upper(ca.dot(ca.DM(c), y))
        if form == "matrix":
            p.lower_qp(y, q=c, A=A, b=b + x)
        else:
            p.minimize_lower(ca.dot(ca.DM(c), y))
            p.lower_constraint(ca.mtimes(ca.DM(A), y) <= b + x)
    return p


def optimum(instance: str, data: tuple) -> float:
    """The known optimum (see the module docstring)."""
    if instance == "ls":
        X, t = data
        M = np.linalg.solve(X.T @ X + REG * np.eye(X.shape[1]), X.T)
        return float((LS_BUDGET * np.linalg.norm(t)) ** 2 * np.linalg.norm(M, 2) ** 2)
    from scipy.optimize import linprog

    A, b, c = data
    return float(linprog(c, A_ub=A, b_ub=b - LP_DELTA, bounds=(-1, 1), method="highs").fun)


def _run(instance: str, form: str, method: str, queue: mp.Queue) -> None:
    data = ls_data() if instance == "ls" else lp_data()
    from bilevel.errors import BilevelError

    t0 = time.perf_counter()
    try:
        res = declare(instance, form, data).solve(method=method, starts=1)
    except BilevelError as exc:
        queue.put({"status": f"refused: {type(exc).__name__}", "time": time.perf_counter() - t0, "why": str(exc)})
        return
    queue.put({"status": res.status.value, "objective": res.upper_objective, "time": time.perf_counter() - t0,
               "certificate": None if res.certificate is None else bool(res.certificate.passed), "nit": res.nit})


def run(instance: str, form: str, method: str, limit: float) -> dict:
    """One solve in a child process, killed after `limit` seconds."""
    queue: mp.Queue = mp.get_context("fork").Queue()
    proc = mp.get_context("fork").Process(target=_run, args=(instance, form, method, queue))
    t0 = time.perf_counter()
    proc.start()
    proc.join(limit)
    if proc.is_alive():
        proc.kill()
        proc.join()
        return {"status": f"not finished in {limit:.0f} s", "time": time.perf_counter() - t0}
    return queue.get() if not queue.empty() else {"status": f"crashed (exit {proc.exitcode})",
                                                  "time": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--limit", type=float, default=120.0, help="seconds per solve (default 120)")
    ap.add_argument("--out", default=None, help="also write the table to this file")
    args = ap.parse_args()
    lines = [f"# bench_scale  {date.today()}  {platform.node()}  {mp.cpu_count()} cores  python "
             f"{platform.python_version()}  limit {args.limit:.0f} s per solve, one start",
             "instance  declaration  method          status                time [s]   objective / optimum  cert"]
    print("\n".join(lines), flush=True)
    runs = [(inst, form, meth) for inst in ("ls", "lp") for form, meth in
            [("matrix", "hypergradient"), ("matrix", "ipopt"), ("matrix", "relaxation"), ("matrix", "global"),
             ("expression", "hypergradient")]]
    best = {inst: optimum(inst, ls_data() if inst == "ls" else lp_data()) for inst in ("ls", "lp")}
    base: dict[str, float] = {}
    for inst, form, meth in runs:
        r = run(inst, form, meth, args.limit)
        ratio = "" if r.get("objective") is None else f"{r['objective'] / best[inst]:.6f}"
        line = (f"{inst:8s}  {form:11s}  {meth:14s}  {r['status'][:20]:20s}  {r['time']:9.2f}   {ratio:19s}  "
                f"{r.get('certificate', '')}")
        print(line, flush=True)
        lines.append(line)
        if "why" in r:
            lines.append(f"          ({r['why'][:150]})")
            print(lines[-1], flush=True)
        if form == "matrix" and meth == "hypergradient":
            base[inst] = r["time"]
        elif form == "expression":
            done = "objective" in r
            lines.append(f"          expression / matrix time (hypergradient): {'' if done else '> '}"
                         f"{r['time'] / base[inst]:.1f}x")
            print(lines[-1], flush=True)
    lines.append("optimum: " + json.dumps(best))
    print(lines[-1])
    if args.out:
        with open(args.out, "w") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
