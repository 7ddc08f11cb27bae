"""Re-solve the ridge example of docs/cvxpy.md on 100 data sets: declared once (the training data as unbound cvxpy
Parameters, i.e. model parameters, re-set with ll.set_value; the validation data as model parameters) against
rebuilding the cvxpy problem and the BilevelProblem for every data set (the baseline, same process, same data).

Both solve with method="hypergradient" and must agree on every data set (asserted, 1e-8 relative). Prints the
total times and their ratio. Usage: python benchmarks/bench_cvxpy_declare_once.py > benchmarks/results/...
"""

from __future__ import annotations

import os
import time
from datetime import datetime, timezone

import casadi as ca
import cvxpy as cp
import numpy as np

import bilevel as bl

DATA_SETS = 100
N_TRAIN, N_VAL, N_FEATURES = 40, 30, 20


def data_set(seed: int) -> tuple[np.ndarray, ...]:
    """The docs/cvxpy.md data, drawn with another seed."""
    rng = np.random.default_rng(seed)
    xtr, xval = rng.standard_normal((N_TRAIN, N_FEATURES)), rng.standard_normal((N_VAL, N_FEATURES))
    truth = rng.standard_normal(N_FEATURES)
    return (xtr, xtr @ truth + 2 * rng.standard_normal(N_TRAIN), xval,
            xval @ truth + 2 * rng.standard_normal(N_VAL))


def declare(xtr: np.ndarray, ytr: np.ndarray, xval: np.ndarray, yval: np.ndarray):
    """The ridge bilevel problem with every data array re-settable; returns it, the lower level and the Parameters."""
    a, b = cp.Parameter(xtr.shape, value=xtr), cp.Parameter(ytr.size, value=ytr)
    lam, w = cp.Parameter(nonneg=True), cp.Variable(N_FEATURES)
    p = bl.BilevelProblem("ridge")
    l = p.upper_variable("l", lb=0, start=1.0)
    xv, yv = p.parameter("Xval", xval.shape, xval), p.parameter("yval", yval.size, yval)
    ll = p.lower_cvxpy(cp.Problem(cp.Minimize(cp.sum_squares(a @ w - b) + lam * cp.sum_squares(w))),
                       parameters={lam: l})
    p.minimize_upper(ca.sumsqr(ca.mtimes(xv, ll[w]) - yv))
    return p, ll, a, b


def rebuilt(sets: list[tuple[np.ndarray, ...]]) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    values = [declare(*d)[0].solve(method="hypergradient").upper_objective for d in sets]
    return time.perf_counter() - t0, values


def declared_once(sets: list[tuple[np.ndarray, ...]]) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    p, ll, a, b = declare(*sets[0])
    values = []
    for xtr, ytr, xval, yval in sets:
        ll.set_value(a, xtr)
        ll.set_value(b, ytr)
        p.set_value("Xval", xval)
        p.set_value("yval", yval)
        values.append(p.solve(method="hypergradient").upper_objective)
    return time.perf_counter() - t0, values


def main() -> None:
    print(f"# bench_cvxpy_declare_once.py — {datetime.now(timezone.utc):%Y-%m-%d %H:%M:%S} UTC; nproc "
          f"{os.cpu_count()}; load average at start {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
    sets = [data_set(seed) for seed in range(DATA_SETS)]
    base, base_values = rebuilt(sets)
    once, once_values = declared_once(sets)
    np.testing.assert_allclose(once_values, base_values, rtol=1e-8)
    print(f"ridge {N_TRAIN}x{N_FEATURES}, {DATA_SETS} data sets, method=hypergradient, same optima on all")
    print(f"rebuilt each time: {base:.2f} s ({1e3 * base / DATA_SETS:.1f} ms per data set)")
    print(f"declared once:     {once:.2f} s ({1e3 * once / DATA_SETS:.1f} ms per data set)")
    print(f"ratio rebuilt / declared once: {base / once:.2f}")


if __name__ == "__main__":
    main()
