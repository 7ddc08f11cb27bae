"""Where one stealthy identification attack on the authors' terms spends its CPU time (T = 100), and the floor IPOPT
alone sets: the measurements behind the 30x target of issue 45 at T = 100.

Part 1, the engine's attacks (bilevel.experiments.identification_paper.paper_attack, paper_method(T), one BLAS thread,
after one warm-up attack) on the authors' data sets 0..N-1, each data set's deltas continued as in the benchmark beside
it (bench_identification_authors.py). Per attack (time.process_time): the IPOPT call of method `reduced` split into
the Python evaluations it asks for (Hypergradient.evaluate and .jacobian: the learner's solve, the statistics, the
spectral norm, their sweeps and the adjoint) and the rest (IPOPT's own work and CasADi's callback layer); the stealth
start of a cold run (stealth_start); everything else (re-targeting, the independent checks, the certificate).

Part 2, the floor: IPOPT with the same options on a compiled CasADi NLP of the same shape (504 variables in a box,
8 dense rows: 6 ranged, 2 one-sided; a smooth nonconvex objective and rows; at most 300 iterations), once as CasADi
functions and once through method `reduced`'s callbacks (bilevel.solvers.reduced._Values on numpy copies of the same
functions): IPOPT's own CPU per iteration, and what the callback layer adds per iteration beyond the Python work.

Run: python benchmarks/bench_identification_time_split.py --data DIR [--sims 10] [--slsqp FILE]; DIR: the authors'
extracted data sets; FILE: the authors' SLSQP rows (bench_identification_authors.py's --results JSONL) for the time
each attack would need for 30x. Output: benchmarks/results/bench_identification_time_split.txt.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections import Counter
from datetime import datetime, timezone
from typing import Any, Callable

import casadi as ca
import numpy as np

import bilevel.problems.identification as identification
from bilevel.experiments.identification_paper import DELTAS, dataset_path, load_dataset, paper_attack, paper_method
from bilevel.solvers import reduced
from bilevel.solvers.engine.implicit import Hypergradient
from bilevel.threads import single_threaded

T = 100
PARTS = ("ipopt_call", "evaluations", "stealth_start")


class Clock:
    """CPU seconds spent in patched functions, by part; evaluations counted only inside the IPOPT call."""

    def __init__(self) -> None:
        self.parts: Counter[str] = Counter()
        self.inside = False

    def wrap(self, owner: Any, name: str, part: str, only_inside: bool = False,
             when: Callable[[Any], bool] | None = None) -> None:
        fn = getattr(owner, name)
        clock = self

        def timed(*args: Any, **kwargs: Any) -> Any:
            if (only_inside and not clock.inside) or (when is not None and not when(args[0])):
                return fn(*args, **kwargs)
            c0, outer = time.process_time(), clock.inside
            clock.inside = clock.inside or part == "ipopt_call"
            try:
                return fn(*args, **kwargs)
            finally:
                clock.inside = outer
                clock.parts[part] += time.process_time() - c0
        setattr(owner, name, timed)


def engine_split(folder: str, sims: int) -> list[dict[str, Any]]:
    """One row per (data set, delta): CPU seconds by part, IPOPT iterations, value and stealth verdict."""
    clock = Clock()
    clock.wrap(ca.Function, "__call__", "ipopt_call", when=lambda f: f.name() == "reduced")
    clock.wrap(Hypergradient, "evaluate", "evaluations", only_inside=True)
    clock.wrap(Hypergradient, "jacobian", "evaluations", only_inside=True)
    clock.wrap(identification, "stealth_start", "stealth_start")
    rows = []
    with single_threaded():
        paper_attack(load_dataset(dataset_path(folder, T, 0)), DELTAS[0])  # declaration and compilation
        for sim in range(sims):
            data, smaller = load_dataset(dataset_path(folder, T, sim)), None
            for delta in DELTAS:
                clock.parts.clear()
                smaller = paper_attack(data, delta, smaller)
                rows.append({"sim": sim, "delta": delta, "cpu": smaller.cpu_time, "nit": smaller.result.nit,
                             "norm2": smaller.check["norm2"], "stealthy": bool(smaller.check["stealthy"]),
                             **{p: clock.parts[p] for p in PARTS}})
    return rows


def floor_problem(n: int = 504, rows: int = 8, seed: int = 0) -> tuple[ca.SX, ca.SX, ca.SX, dict[str, np.ndarray]]:
    """A compiled NLP of the attack's shape: x in [-0.5, 0.5]^n, 6 ranged and 2 one-sided dense rows."""
    rng = np.random.default_rng(seed)
    x = ca.SX.sym("x", n)
    Q = ca.DM(rng.normal(size=(20, n)) / np.sqrt(n))
    a = [ca.DM(rng.normal(size=n) / np.sqrt(n)) for _ in range(rows)]
    f = -ca.sumsqr(ca.mtimes(Q, x))
    g = ca.vertcat(*[ca.sumsqr(x * ai) + ca.dot(ai, x) for ai in a])
    bounds = {"lbx": np.full(n, -0.5), "ubx": np.full(n, 0.5), "lbg": np.r_[np.full(6, -0.05), np.full(2, -np.inf)],
              "ubg": np.full(rows, 0.05)}
    return x, f, g, bounds


class _Numpy:
    """The floor problem's [f; g] and Jacobian as numpy callbacks, in the shape method `reduced` hands to CasADi."""

    def __init__(self, x: ca.SX, f: ca.SX, g: ca.SX) -> None:
        out = ca.vertcat(f, g)
        self._values = ca.Function("v", [x], [out])
        self._jacobian = ca.Function("j", [x], [ca.jacobian(out, x)])
        self.n_x, self.n_out = int(x.numel()), int(out.numel())
        self.calls = Counter()

    def values(self, x: np.ndarray) -> np.ndarray:
        self.calls["values"] += 1
        return np.asarray(self._values(x)).ravel()

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        self.calls["jacobian"] += 1
        return np.asarray(self._jacobian(x))


def ipopt_floor(repeats: int = 3) -> dict[str, float]:
    """IPOPT's CPU per iteration on the floor problem: as CasADi functions, and through `reduced`'s callbacks (with the
    Python work of the callbacks measured apart)."""
    x, f, g, bounds = floor_problem()
    opts = reduced._ipopt_options(1e-6, 300, paper_method(T).get("ipopt"))
    direct = ca.nlpsol("floor", "ipopt", {"x": x, "f": f, "g": g}, opts)
    numpy_side = _Numpy(x, f, g)
    values = reduced._Values(numpy_side)
    X = ca.MX.sym("x", numpy_side.n_x)
    out = values(X)
    wrapped = ca.nlpsol("floor_cb", "ipopt", {"x": X, "f": out[0], "g": out[1:]}, opts)
    x0 = np.full(numpy_side.n_x, 1e-3)
    result: dict[str, float] = {}
    for name, solver in (("direct", direct), ("callbacks", wrapped)):
        per = []
        for _ in range(repeats):
            numpy_side.calls.clear()
            c0 = time.process_time()
            solver(x0=x0, **bounds)
            per.append((time.process_time() - c0) / max(1, int(solver.stats()["iter_count"])))
        stats = solver.stats()
        result[f"{name}_ms_per_iter"] = 1e3 * float(np.median(per))
        result[f"{name}_iterations"] = int(stats["iter_count"])
        if name == "direct":
            fun = sum(v for k, v in stats.items() if k.startswith("t_proc_nlp"))
            result["direct_functions_ms_per_iter"] = 1e3 * fun / max(1, int(stats["iter_count"]))
        else:
            result["values_calls_per_iter"] = numpy_side.calls["values"] / max(1, int(stats["iter_count"]))
            result["jacobian_calls_per_iter"] = numpy_side.calls["jacobian"] / max(1, int(stats["iter_count"]))
    c0 = time.process_time()
    for _ in range(1000):
        numpy_side.values(x0)
    t_values = (time.process_time() - c0) / 1000
    c0 = time.process_time()
    for _ in range(300):
        numpy_side.jacobian(x0)
    t_jacobian = (time.process_time() - c0) / 300
    result["callback_python_ms_per_iter"] = 1e3 * (result["values_calls_per_iter"] * t_values
                                                  + result["jacobian_calls_per_iter"] * t_jacobian)
    return result


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--data", required=True)
    p.add_argument("--sims", type=int, default=10)
    p.add_argument("--slsqp", default=None, help="the authors' SLSQP rows (JSONL) for the time 30x would need")
    args = p.parse_args()
    print(f"# bench_identification_time_split  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}  "
          f"load {os.getloadavg()[0]:.1f}")
    print(f"engine {paper_method(T)}, T = {T}, data sets 0-{args.sims - 1}, every delta continued; one BLAS thread; "
          "CPU milliseconds per attack (medians over the data sets)\n")
    rows = engine_split(args.data, args.sims)
    slsqp = {}
    if args.slsqp:
        for line in open(args.slsqp):
            r = json.loads(line)
            if r["T"] == T:
                slsqp[(r["sim"], r["delta"])] = r["cpu_time"]
    print("| delta | attack | IPOPT iterations | evaluations | IPOPT + callback layer | per iteration: evaluations "
          "| per iteration: IPOPT + callbacks | stealth start | rest | stealthy | SLSQP/30 (recorded) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for delta in DELTAS:
        rs = [r for r in rows if r["delta"] == delta]
        med = {k: 1e3 * float(np.median([r[k] for r in rs])) for k in ("cpu", *PARTS)}
        own = [1e3 * (r["ipopt_call"] - r["evaluations"]) for r in rs]
        it_eval = [1e3 * r["evaluations"] / max(1, r["nit"]) for r in rs]
        it_own = [o / max(1, r["nit"]) for o, r in zip(own, rs)]
        rest = [1e3 * (r["cpu"] - r["ipopt_call"] - r["stealth_start"]) for r in rs]
        need = [1e3 * slsqp[(r["sim"], delta)] / 30 for r in rs if (r["sim"], delta) in slsqp]
        print(f"| {delta} | {med['cpu']:.1f} | {np.median([r['nit'] for r in rs]):.0f} | {med['evaluations']:.1f} | "
              f"{np.median(own):.1f} | {np.median(it_eval):.2f} | {np.median(it_own):.2f} | "
              f"{med['stealth_start']:.1f} | {np.median(rest):.1f} | {sum(r['stealthy'] for r in rs)}/{len(rs)} | "
              f"{f'{np.median(need):.1f}' if need else '-'} |")
    total = sum(r["cpu"] for r in rows)
    print(f"\nall {len(rows)} attacks: {total:.2f} CPU s; evaluations {sum(r['evaluations'] for r in rows) / total:.0%},"
          f" IPOPT + callback layer {sum(r['ipopt_call'] - r['evaluations'] for r in rows) / total:.0%}, stealth start "
          f"{sum(r['stealth_start'] for r in rows) / total:.0%}, rest "
          f"{sum(r['cpu'] - r['ipopt_call'] - r['stealth_start'] for r in rows) / total:.0%}")
    floor = ipopt_floor()
    print("\nThe floor: IPOPT with the same options on a compiled NLP of the same shape (504 variables, 8 dense rows), "
          "at most 300 iterations")
    for k, v in floor.items():
        print(f"- {k}: {v:.3f}" if isinstance(v, float) else f"- {k}: {v}")
    own = floor["direct_ms_per_iter"] - floor["direct_functions_ms_per_iter"]
    layer = floor["callbacks_ms_per_iter"] - own - floor["callback_python_ms_per_iter"]
    print(f"- IPOPT's own work: {own:.3f} ms an iteration; the callback layer beyond the Python work: {layer:.3f} ms an "
          "iteration")
    print(f"\n# load at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    sys.exit(main())
