"""CPU of some of the Willems reproduction's tasks on the imported tree (run it under PYTHONPATH=TREE, from outside any
tree, once per tree at the same time to compare): the tasks of the given methods and sims, in sweep order, each through
attack_task after one warm-up task; writes their rows (wall times dropped) to OUT, one JSON line each, for `cmp`, and
prints the CPU seconds (time.process_time) in all and per method.

Run: PYTHONPATH=TREE python benchmarks/bench_willems_tasks.py OUT differential-evolution 0,1,2,3 [SWEEP]
(SWEEP: paper (default), remark or designs; "all" for every method of the sweep).
"""

from __future__ import annotations

import json
import sys
import time

import bilevel
from bilevel.experiments.willems import attack_task, design_tasks, make_plan, paper_tasks, remark_tasks

SWEEPS = {"paper": paper_tasks, "remark": remark_tasks, "designs": design_tasks}


def main() -> None:
    out, methods, sims = sys.argv[1], sys.argv[2].split(","), {int(v) for v in sys.argv[3].split(",")}
    sweep = SWEEPS[sys.argv[4] if len(sys.argv) > 4 else "paper"]
    tasks = [t for t in sweep(make_plan(256, False), 0) if t["sim"] in sims and (methods == ["all"] or t["method"] in methods)]
    attack_task(tasks[0])  # imports, declarations, compiled functions
    cpu: dict[str, float] = {}
    rows = []
    t0 = time.process_time()
    for t in tasks:
        a = time.process_time()
        row = attack_task(t)
        cpu[t["method"]] = cpu.get(t["method"], 0.0) + time.process_time() - a
        row.pop("wall_time", None)
        rows.append(json.dumps(row, sort_keys=True))
    with open(out, "w", encoding="utf-8") as fh:
        fh.write("\n".join(rows) + "\n")
    print(json.dumps({"tree": bilevel.__file__, "tasks": len(tasks), "cpu": round(time.process_time() - t0, 2),
                      "by_method": {k: round(v, 2) for k, v in cpu.items()}}))


if __name__ == "__main__":
    main()
