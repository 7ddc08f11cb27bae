"""CPU of a subset of the Willems reproduction and of the defenses frontier on this tree against a base tree (e.g. a
git worktree of the commit before a change), both run at once in two single-threaded processes (so they share the
load), each task list in task order in one process as `--workers 1` runs it; prints CPU s (time.process_time), wall s,
the load, the ratio and whether the rows agree (wall times excluded).

Run: python benchmarks/bench_willems_defenses_reuse.py BASE_TREE [--paper-sims 2] [--design-sims 1] [--frontier-sims 1]
(from any directory: each process imports `bilevel` from its own tree).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHILD = r"""
import json, sys, time
part, sims, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
import bilevel
if part == "frontier":
    from bilevel.experiments.defenses import frontier_task as fn, frontier_tasks, make_plan
    tasks = [t for t in frontier_tasks(make_plan(64, False), 0, ["vrft", "willems"])
             if int(t["key"].split("sim=")[1]) < sims]
else:
    from bilevel.experiments.willems import attack_task as fn, design_tasks, make_plan, paper_tasks, remark_tasks
    make = {"paper": paper_tasks, "designs": design_tasks, "remark": remark_tasks}[part]
    tasks = [t for t in make(make_plan(256, False), 0) if t["sim"] < sims]
from bilevel.experiments.executor import run_task
c0, w0 = time.process_time(), time.perf_counter()
rows = [run_task(fn, t) for t in tasks]
cpu, wall = time.process_time() - c0, time.perf_counter() - w0
strip = lambda r: {k: v for k, v in r.items() if k != "wall_time"}
json.dump({"file": bilevel.__file__, "tasks": len(tasks), "cpu": cpu, "wall": wall, "rows": [strip(r) for r in rows]},
          open(out, "w"))
"""


def run_pair(base: str, part: str, sims: int, scratch: str) -> dict[str, dict]:
    """The part's tasks on base and on this tree at once; their outputs by label."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    procs = {}
    for label, tree in (("base", base), ("this", HERE)):
        out = os.path.join(scratch, f"{part}-{label}.json")
        procs[label] = (subprocess.Popen([sys.executable, "-c", CHILD, part, str(sims), out], cwd=scratch,
                                         env={**env, "PYTHONPATH": tree}), out)
    result = {}
    for label, (proc, out) in procs.items():
        if proc.wait() != 0:
            raise SystemExit(f"{part} on {label} failed (exit {proc.returncode})")
        with open(out, encoding="utf-8") as fh:
            result[label] = json.load(fh)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", help="the base tree (a checkout of the commit to compare against)")
    parser.add_argument("--paper-sims", type=int, default=2)
    parser.add_argument("--design-sims", type=int, default=1)
    parser.add_argument("--frontier-sims", type=int, default=1)
    args = parser.parse_args()
    print(f"# {platform.node()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}, "
          f"load at start {open('/proc/loadavg').read().split()[:3]}")
    print(f"# base: {os.path.abspath(args.base)}; this: {HERE}; each side one process, one BLAS thread")
    print("| part | sims | tasks | base CPU s | this CPU s | CPU ratio | base wall s | this wall s | rows equal | "
          "load at end |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as scratch:
        for part, sims in (("paper", args.paper_sims), ("designs", args.design_sims), ("remark", args.design_sims),
                           ("frontier", args.frontier_sims)):
            r = run_pair(args.base, part, sims, scratch)
            b, t = r["base"], r["this"]
            same = sum(x == y for x, y in zip(b["rows"], t["rows"]))
            print(f"| {part} | {sims} | {t['tasks']} | {b['cpu']:.1f} | {t['cpu']:.1f} | {b['cpu'] / t['cpu']:.2f} | "
                  f"{b['wall']:.0f} | {t['wall']:.0f} | {same}/{len(t['rows'])} | "
                  f"{' '.join(open('/proc/loadavg').read().split()[:3])} |", flush=True)


if __name__ == "__main__":
    main()
