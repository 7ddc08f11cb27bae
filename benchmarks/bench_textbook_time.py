"""CPU time per textbook problem of this tree against a baseline tree, measured in the same run.

For each tree, alternating ROUNDS times, a fresh process (PYTHONPATH=tree, single-threaded BLAS) solves every
registered textbook problem with METHODS (starts 8, seed 0): the first solve (declaration, preparation, compiling,
method, certificate, probe) and then REPEATS re-solves; per tree the CPU time (time.process_time) of each, summed over
the problems (median over rounds), their ratio this / baseline, and on how many (problem, method) pairs the upper
objective and status agree exactly.

Run: python benchmarks/bench_textbook_time.py BASELINE_TREE [ROUNDS [METHOD,...]]   (defaults 2, auto)
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

REPEATS = 2


def child(methods: list[str]) -> None:
    """Time every textbook problem and method in this process; print one JSON line."""
    import bilevel as bl  # noqa: F401
    from bilevel.problems import registry

    out = {}
    for name in registry.names("textbook"):
        for method in methods:
            t0 = time.process_time()
            p = registry.get(name)
            try:
                first = p.solve(method, starts=8, seed=0)
            except Exception as exc:  # a method a problem does not take: recorded, not timed
                out[f"{name} {method}"] = {"error": type(exc).__name__}
                continue
            t_first = time.process_time() - t0
            again = []
            for _ in range(REPEATS):
                t0 = time.process_time()
                res = p.solve(method, starts=8, seed=0)
                again.append(time.process_time() - t0)
            out[f"{name} {method}"] = {"first": t_first, "again": statistics.median(again),
                                       "objective": repr(first.upper_objective), "status": first.status.value,
                                       "repeat_same": repr(res.upper_objective) == repr(first.upper_objective)}
    print(json.dumps(out))


def run(tree: str, methods: list[str]) -> dict:
    env = {**os.environ, "PYTHONPATH": tree, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    text = subprocess.run([sys.executable, __file__, "--child", ",".join(methods)], env=env, capture_output=True,
                          text=True, check=True).stdout
    return json.loads(text.strip().splitlines()[-1])


def main() -> None:
    baseline = sys.argv[1]
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    methods = sys.argv[3].split(",") if len(sys.argv) > 3 else ["auto"]
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with open("/proc/loadavg", encoding="utf-8") as fh:
        load = fh.read().split()[:3]
    print(f"# bench_textbook_time: {platform.node()}, {platform.processor() or platform.machine()}, {os.cpu_count()} "
          f"CPUs, {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, load {' '.join(load)}; {rounds} rounds alternating "
          f"trees (this: {here}, baseline: {baseline}); methods {','.join(methods)}, starts 8, seed 0; CPU seconds")
    ours, base = [], []
    for _ in range(rounds):
        base.append(run(baseline, methods))
        ours.append(run(here, methods))
    cases = [c for c in ours[0] if "error" not in ours[0][c]]
    same = sum(all(o[c]["objective"] == b[c]["objective"] and o[c]["status"] == b[c]["status"]
                   for o, b in zip(ours, base)) for c in cases)
    for key, label in (("first", "first solve (declare, prepare, solve)"), ("again", "re-solve")):
        t_ours = statistics.median(sum(r[c][key] for c in cases) for r in ours)
        t_base = statistics.median(sum(r[c][key] for c in cases) for r in base)
        print(f"{label:40s} this {t_ours:8.2f} s  baseline {t_base:8.2f} s  ratio {t_ours / t_base:5.3f}  "
              f"({len(cases)} problem/method pairs)")
    print(f"same objective and status (every round): {same}/{len(cases)}; errors (both trees): "
          f"{sorted(c for c in ours[0] if 'error' in ours[0][c])}")


if __name__ == "__main__":
    child(sys.argv[2].split(",")) if sys.argv[1:2] == ["--child"] else main()
