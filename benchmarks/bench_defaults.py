"""Cost of reading tolerances from the defaults registry at call time instead of module constants.

Runs the same solves with this tree's `bilevel` and with a baseline tree (a checkout of the commit before the
registry, e.g. `git archive 726cb8c bilevel | tar -x -C /tmp/base`), each in its own process, alternating, and
prints the median time of each solve (after a first solve that prepares and compiles) and the ratio
this / baseline. Only options both trees accept are passed (starts, seed).
Run: python benchmarks/bench_defaults.py BASELINE_DIR [rounds]
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone

CASES = [("bard", "ipopt", 8), ("bard", "relaxation", 4), ("bard", "hypergradient", 4),
         ("bard", "differential-evolution", 1), ("vrft-maxmin", "hypergradient", 1)]
"""(problem, method, starts): the textbook problem (Bard 5.1.1, boxed) and the registry's vrft-maxmin (N = 64)."""
REPEATS = 5


def child() -> None:
    """Time each case in this process: one preparing solve, then REPEATS timed solves; print JSON medians."""
    import bilevel as bl
    from bilevel.problems import registry

    def bard() -> bl.BilevelProblem:
        p = bl.BilevelProblem("bard")
        x = p.upper_variable("x", lb=0, ub=10)
        y = p.lower_variable("y", lb=0)
        p.minimize_upper(x - 4 * y)
        p.minimize_lower(y)
        for c in (-x - y <= -3, -2 * x + y <= 0, 2 * x + y <= 12, 3 * x - 2 * y <= 4):
            p.lower_constraint(c)
        return p

    out = {}
    for name, method, starts in CASES:
        p = bard() if name == "bard" else registry.get(name)
        first = p.solve(method, starts=starts, seed=0)
        times = []
        for _ in range(REPEATS):
            t0 = time.perf_counter()
            res = p.solve(method, starts=starts, seed=0)
            times.append(time.perf_counter() - t0)
        assert res.upper_objective == first.upper_objective
        out[f"{name} {method}"] = {"time": statistics.median(times), "objective": res.upper_objective}
    print(json.dumps(out))


def run(tree: str) -> dict:
    env = {**os.environ, "PYTHONPATH": tree}
    text = subprocess.run([sys.executable, __file__, "--child"], env=env, capture_output=True, text=True,
                          check=True).stdout
    return json.loads(text.strip().splitlines()[-1])


def main() -> None:
    baseline, rounds = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 3
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    print(f"# bench_defaults: {platform.node()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC; {rounds} rounds alternating, median of {REPEATS} solves "
          "per round after a preparing solve")
    ours, base = [], []
    for _ in range(rounds):
        base.append(run(baseline))
        ours.append(run(here))
    for case in ours[0]:
        t_ours = statistics.median(r[case]["time"] for r in ours)
        t_base = statistics.median(r[case]["time"] for r in base)
        same = all(r[case]["objective"] == b[case]["objective"] for r, b in zip(ours, base))
        print(f"{case:32s} registry {1e3 * t_ours:8.2f} ms  constants {1e3 * t_base:8.2f} ms  ratio "
              f"{t_ours / t_base:5.2f}  same objective: {same}")


if __name__ == "__main__":
    child() if sys.argv[1:] == ["--child"] else main()
