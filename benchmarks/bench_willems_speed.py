"""CPU of a subset of the Willems reproduction's tasks on two trees, in the same run: for each round and each part
(sweep, methods, sims), benchmarks/bench_willems_tasks.py runs once under each tree in a subprocess (the order
alternating by round), then the two trees' rows are compared byte for byte. Prints CPU seconds (time.process_time of
the subprocess's tasks), the ratio base / head per part and in all, and the load average before and after.

Run: python benchmarks/bench_willems_speed.py BASE_TREE HEAD_TREE OUT_DIR [ROUNDS]
"""

from __future__ import annotations

import filecmp
import json
import os
import platform
import subprocess
import sys
import time

PARTS = (("paper", "differential-evolution", "0,1"), ("paper", "destabilize", "0,1"),
         ("paper", "hypergradient", "0,1"), ("remark", "all", "0"), ("designs", "all", "0"))
"""(sweep, methods, sims) of the subset: every method and horizon of the paper sweep on two data sets, one of the
remark's and one of the designs'."""


def load() -> str:
    with open("/proc/loadavg", encoding="utf-8") as fh:
        return " ".join(fh.read().split()[:3])


def run(tree: str, out: str, sweep: str, methods: str, sims: str) -> float:
    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bench_willems_tasks.py")
    line = subprocess.run([sys.executable, script, out, methods, sims, sweep], env={**os.environ, "PYTHONPATH": tree},
                          check=True, capture_output=True, text=True, cwd=os.path.dirname(out)).stdout
    return float(json.loads(line.strip().splitlines()[-1])["cpu"])


def main() -> None:
    base, head, out_dir = (os.path.abspath(a) for a in sys.argv[1:4])
    rounds = int(sys.argv[4]) if len(sys.argv) > 4 else 1
    os.makedirs(out_dir, exist_ok=True)
    print(f"# {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, {platform.node()} {platform.machine()}, "
          f"nproc {os.cpu_count()}, Python {platform.python_version()}; load average {load()} at start")
    print(f"# base {base}, head {head}; {rounds} round(s), trees alternating; CPU s = time.process_time of the tasks "
          "(after one warm-up task) in a subprocess per tree and part")
    cpu = {"base": {}, "head": {}}
    same = {}
    for r in range(rounds):
        for sweep, methods, sims in PARTS:
            part = f"{sweep} {methods} sims {sims}"
            order = (("base", base), ("head", head)) if r % 2 == 0 else (("head", head), ("base", base))
            for name, tree in order:
                out = os.path.join(out_dir, f"{name}_{sweep}_{methods}.jsonl")
                cpu[name].setdefault(part, []).append(run(tree, out, sweep, methods, sims))
            same[part] = filecmp.cmp(os.path.join(out_dir, f"base_{sweep}_{methods}.jsonl"),
                                     os.path.join(out_dir, f"head_{sweep}_{methods}.jsonl"), shallow=False)
            print(f"round {r + 1}: {part}: base {cpu['base'][part][-1]:.2f} s, head {cpu['head'][part][-1]:.2f} s, "
                  f"rows identical: {same[part]}; load {load()}", flush=True)
    print(f"{'part':>42} {'base CPU s':>10} {'head CPU s':>10} {'ratio':>6}  rows identical")
    for part in cpu["base"]:
        b, h = min(cpu["base"][part]), min(cpu["head"][part])
        print(f"{part:>42} {b:>10.2f} {h:>10.2f} {b / h:>6.2f}  {same[part]}")
    b, h = (sum(min(v) for v in cpu[k].values()) for k in ("base", "head"))
    print(f"{'all (min over rounds per part)':>42} {b:>10.2f} {h:>10.2f} {b / h:>6.2f}  {all(same.values())}")
    print(f"# load average {load()} at end")


if __name__ == "__main__":
    main()
