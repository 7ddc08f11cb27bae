"""One method's column of the paper sweep, or one side sweep, alone, against the committed table's 95% intervals.

Runs every task of METHOD (de, hypergradient or destabilize) in the 256-simulation paper sweep, or every task of the
remark or designs sweep (METHOD remark / designs), or their first SIMS simulations, through attack_task in task
order, appending rows to OUT/METHOD.jsonl (resumable), then writes its table CSV (OUT/table_paper.csv: that
column's cells; OUT/table_remark.csv, OUT/table_designs.csv) and prints willems_table_check's comparison with
docs/results/willems. Usage: willems_column.py OUT METHOD [SIMS].
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time

from bilevel.experiments.willems import (attack_task, design_tasks, make_plan, paper_tasks, remark_tasks,
                                        summarize, write_csv)
from bilevel.threads import single_threaded

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from willems_table_check import main as check  # noqa: E402

SWEEPS = {"paper": (paper_tasks, ("horizon", "method", "delta_u")),
          "remark": (remark_tasks, ("horizon", "method", "criterion")),
          "designs": (design_tasks, ("design", "poison", "criterion", "delta_u"))}


def main(out: str, method: str, sims: int = 256) -> int:
    """Run (or resume) the method's tasks, write their table and compare it with the committed one."""
    print(f"# willems_column.py {out} {method} {sims} -- {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, "
          f"{platform.node()}, nproc {os.cpu_count()}")
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{method}.jsonl")
    done = {}
    if os.path.exists(path):
        with open(path, encoding="utf-8") as fh:
            done = {r["key"]: r for r in map(json.loads, fh)}
    sweep = method if method in SWEEPS else "paper"
    make_tasks, fields = SWEEPS[sweep]
    tasks = [t for t in make_tasks(make_plan(256, False), 0)
             if (sweep != "paper" or t["method"] == method) and t["sim"] < sims]
    with single_threaded(), open(path, "a", encoding="utf-8") as fh:
        for task in tasks:
            if task["key"] not in done:
                row = {k: v for k, v in attack_task(task).items() if k != "du"} | {"key": task["key"]}
                fh.write(json.dumps(row) + "\n")
                fh.flush()
                done[task["key"]] = row
    write_csv(summarize([done[t["key"]] for t in tasks], fields), fields, os.path.join(out, f"table_{sweep}.csv"))
    return check(out)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], *(int(a) for a in sys.argv[3:4])))
