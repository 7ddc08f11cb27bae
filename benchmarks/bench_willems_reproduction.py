"""Estimate of `bilevel reproduce willems --sims 256` on 2 workers from a subset of its tasks, in CPU seconds.

Runs the first SIMS simulations of each sweep of the 256-simulation plan (paper, remark, designs: every cell, so the
subset has the full plan's mix of methods, horizons and budgets) in task order through attack_task, as two local
workers would take them (tasks dealt alternately to two workers, each with its own per-process cache of reference
learners). Reports CPU seconds (time.process_time: robust to other jobs on the machine, which
wall time is not) per task by sweep and method, and the full plan's estimate: CPU per task x tasks, over 2 workers.
Usage: bench_willems_reproduction.py [PAPER_SIMS] [REMARK_SIMS] [DESIGN_SIMS] (default 4 2 2).
"""

from __future__ import annotations

import os
import platform
import sys
import time
from collections import defaultdict

import bilevel.experiments.willems as experiment
from bilevel.threads import single_threaded

SIMS = {"paper": 4, "remark": 2, "designs": 2}
for i, name in enumerate(SIMS):
    if len(sys.argv) > i + 1:
        SIMS[name] = int(sys.argv[i + 1])


def main() -> None:
    print(f"# {' '.join(sys.argv)} -- {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, "
          f"{platform.node()} {platform.machine()}, nproc {os.cpu_count()}, load average "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())} at start")
    plan = experiment.make_plan(256, False)
    sweeps = {"paper": experiment.paper_tasks(plan, 0), "remark": experiment.remark_tasks(plan, 0),
              "designs": experiment.design_tasks(plan, 0)}
    workers = [{}, {}]  # per worker: reference learners
    total_cpu = 0.0
    print(f"{'sweep':>8} {'group':>24} {'tasks run':>9} {'CPU s/task':>10} {'tasks (256 plan)':>16} {'CPU s (plan)':>12}")
    for name, tasks in sweeps.items():
        subset = [t for t in tasks if t["sim"] < SIMS[name]]
        cpu: dict[str, list[float]] = defaultdict(list)
        with single_threaded():
            for i, task in enumerate(subset):
                experiment._REFERENCES = workers[i % 2]
                t0 = time.process_time()
                row = experiment.attack_task(task)
                cpu[f"N={task['horizon']} {task['method']}" if name == "paper" else
                    f"{task['design']}/{task['poison']} {task['criterion']}"].append(time.process_time() - t0)
                if "error" in row:
                    print(f"  error in {task['key']}: {row['error']}")
        scale = len(tasks) / len(subset)
        for group, values in sorted(cpu.items()):
            plan_cpu = sum(values) * scale
            print(f"{name:>8} {group:>24} {len(values):>9} {sum(values) / len(values):>10.3f} "
                  f"{round(len(values) * scale):>16} {plan_cpu:>12.0f}")
        sweep_cpu = sum(sum(v) for v in cpu.values()) * scale
        total_cpu += sweep_cpu
        print(f"{name:>8} {'all':>24} {len(subset):>9} {sweep_cpu / len(tasks):>10.3f} {len(tasks):>16} "
              f"{sweep_cpu:>12.0f}", flush=True)
    print(f"estimate for the 256-simulation plan: {total_cpu:.0f} CPU s, {total_cpu / 2 / 60:.1f} min on 2 workers "
          "(perfect balance; figures and report add a few seconds)")


if __name__ == "__main__":
    main()
