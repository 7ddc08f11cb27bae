"""An LP lower level declared by CasADi expressions against the same LP through lower_qp, in one process.

bench_scale's right-hand-side attack (the follower minimizes c'y s.t. A y <= b + x, -1 <= y <= 1; the leader
maximizes c'y over x in [-0.2, 0.2]^m) at m rows x n variables, declared three ways: `lower_qp` (matrices, the
baseline), one vector `lower_constraint(A @ y <= b + x)`, and one `lower_constraint` per row. Each is timed for its
declaration, `prepare` (canonical form and lower-level classification, where the expressions are recognized as
lower_qp's matrix form) and one solve (method and starts below, the certificate and verdict included), and the
expression/lower_qp ratio of the totals is printed with the answers.

    python benchmarks/bench_expression_lp.py [method] [sizes, e.g. 300x30,1000x100]
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone


from bilevel import BilevelProblem
from bilevel.problems.rhs_lp import rhs_lp
from bilevel.solvers.engine.prepared import prepare

DELTA = 0.2


def declare(form: str, m: int, n: int) -> BilevelProblem:
    """The attack at m x n, its lower level declared by `form`: lower_qp, vector or rows."""
    return rhs_lp(m, n, form, DELTA)


def timed(form: str, m: int, n: int, method: str) -> tuple[list[float], object, str]:
    """(declare, prepare, solve times), the result and the lower level's class."""
    t0 = time.perf_counter()
    p = declare(form, m, n)
    t1 = time.perf_counter()
    low = prepare(p).canon.lower
    t2 = time.perf_counter()
    res = p.solve(method, starts=1)
    return [t1 - t0, t2 - t1, time.perf_counter() - t2], res, f"{type(low).__name__} ({low.kind})"


def main(method: str = "hypergradient", sizes: str = "300x30,1000x100") -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    print(f"# bench_expression_lp  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  load {os.getloadavg()[0]:.1f}  "
          f"python {platform.python_version()}  commit {commit}  method {method}, one start", flush=True)
    for size in sizes.split(","):
        m, n = (int(v) for v in size.split("x"))
        print(f"\n## {m} constraints x {n} variables (plus {2 * n} bounds)")
        base = None
        for form in ("lower_qp", "vector", "rows"):
            (t_decl, t_prep, t_solve), res, kind = timed(form, m, n, method)
            total = t_decl + t_prep + t_solve
            base = total if base is None else base
            print(f"{form:8s} {kind:20s} declare {t_decl:6.2f} s  prepare {t_prep:6.2f} s  solve {t_solve:7.2f} s  "
                  f"total {total:7.2f} s = {total / base:.2f}x lower_qp's  | {res.status.value}, F = "
                  f"{res.upper_objective:.10f}, {res.nit} steps  (load {os.getloadavg()[0]:.1f})", flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
