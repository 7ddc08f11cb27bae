"""The VRFT reproduction's sweeps on 2 local workers: this tree against a baseline tree, wall and CPU seconds.

For each sweep of `bilevel.experiments.vrft.sweep_plan` asked for, and each round, runs it once with the baseline
tree's code and once with this tree's (alternating, so that load from other jobs hits both alike), each in a fresh
child process (PYTHONPATH = the tree) and a fresh output directory, on a 2-process local pool. Prints per run: wall
seconds, CPU seconds of the child and its workers (getrusage), rows, attacks computed, CPU ms per row and per
computed attack; then the ratios baseline / this tree of the medians. With --attacks K, instead: CPU ms per attack
over the first K scenario-B tasks of each sweep, one after another in one process (no pool). Asserts nothing.
The baseline tree is a checkout of an earlier commit, e.g. `git archive COMMIT | tar -x -C /tmp/base`.

With --check, each run's table is compared with the committed one (vrft_table_check.py).

Run: python benchmarks/bench_vrft_reproduction.py --baseline /tmp/base --sims 512 --sweeps maxmin-paper --check
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
TREE = os.path.dirname(HERE)


def child(spec: list, out: str) -> None:
    """Run one sweep (name, sims, convention, objective, method) on 2 local workers, with the tree's sweep function
    (BATCHED_TASKS where the tree has it, else attack_task), write its table_NAME.csv into `out` where the tree can;
    print its measurements."""
    from bilevel.experiments import vrft
    from bilevel.experiments.executor import LocalExecutor
    from bilevel.experiments.sweep import run_sweep

    name, n, convention, objective, method = spec
    tasks = vrft.cell_tasks(n, 0, convention, objective, method)
    shared = {f: getattr(vrft, name) for f, name in (("shared", "same_attack"), ("together", "same_data"))
              if hasattr(vrft, name)}  # absent in older trees
    computed: list[int] = []
    t0 = time.perf_counter()
    with LocalExecutor(2) as executor:  # closed before getrusage: its workers' CPU time counts once reaped
        rows = run_sweep(getattr(vrft, "BATCHED_TASKS", vrft.attack_task), tasks, os.path.join(out, f"{name}.jsonl"),
                         executor, None, name, vrft.valid_row, units=lambda ran: computed.append(len(ran)) or len(ran),
                         **shared)
    wall = time.perf_counter() - t0
    if hasattr(vrft, "write_csv"):
        vrft.write_csv(vrft.summarize(rows), os.path.join(out, f"table_{name}.csv"))
    cpu = sum(getattr(resource.getrusage(who), f) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
              for f in ("ru_utime", "ru_stime"))
    print(json.dumps({"wall": wall, "cpu": cpu, "rows": len(rows), "computed": computed[0]}))


def per_attack(spec: list, count: int) -> None:
    """CPU ms per attack of the first `count` scenario-B tasks of a sweep, one after another in this process (after
    one warm-up task): the attack alone, no pool, no rows written."""
    from bilevel.experiments import vrft
    from bilevel.experiments.executor import run_task

    _, n, convention, objective, method = spec
    tasks = [t for t in vrft.cell_tasks(n, 0, convention, objective, method) if t["scenario"] == "B"][:count]
    run_task(vrft.attack_task, tasks[0])
    c0 = time.process_time()
    for t in tasks:
        run_task(vrft.attack_task, t)
    print(json.dumps({"cpu_ms": 1e3 * (time.process_time() - c0) / len(tasks), "tasks": len(tasks)}))


def run(tree: str, spec: list, out: str, attacks: int = 0) -> dict:
    """child() (or per_attack() for `attacks` > 0) in a fresh interpreter importing bilevel from `tree`."""
    env = {**os.environ, "PYTHONPATH": tree}
    done = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", json.dumps(spec), "--out", out,
                           "--attacks", str(attacks)], env=env, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    """Alternate baseline and this tree over --rounds for each sweep; print every run and the median ratios."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", help="a checkout of the baseline commit")
    parser.add_argument("--sims", type=int, default=512, help="Table 1's simulations per cell (default 512)")
    parser.add_argument("--sweeps", default="maxmin-paper", help="comma-separated sweep names, or 'all'")
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--attacks", type=int, default=0,
                        help="instead of the sweeps: CPU ms per attack over this many scenario-B tasks, one process")
    parser.add_argument("--check", action="store_true",
                        help="check each run's table against the committed intervals (vrft_table_check.py)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        (per_attack(json.loads(args.child), args.attacks) if args.attacks else child(json.loads(args.child), args.out))
        return
    sys.path.insert(0, TREE)
    from bilevel.experiments.vrft import side_default, sweep_plan

    plan = {spec[0]: list(spec) for spec in sweep_plan(args.sims, side_default(args.sims))}
    names = list(plan) if args.sweeps == "all" else args.sweeps.split(",")
    trees = {"baseline": os.path.abspath(args.baseline), "this tree": TREE}
    print(f"# bench_vrft_reproduction.py, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; {platform.platform()}; "
          f"nproc {os.cpu_count()}; python {platform.python_version()}; load average at start "
          f"{os.getloadavg()[0]:.2f}")
    print(f"# sims {args.sims} (side sweeps {side_default(args.sims)}), rounds {args.rounds}, 2 local workers; "
          f"baseline {trees['baseline']}")
    if args.attacks:
        for name in names:
            got = {k: [] for k in trees}
            for r in range(args.rounds):
                for label, tree in trees.items():
                    got[label].append(run(tree, plan[name], "", args.attacks)["cpu_ms"])
            med = {k: statistics.median(v) for k, v in got.items()}
            print(f"{name:>24} per attack, one process, {args.attacks} scenario-B tasks, CPU ms (rounds): baseline "
                  f"{med['baseline']:.2f} ({', '.join(f'{v:.2f}' for v in got['baseline'])}), this tree "
                  f"{med['this tree']:.2f} ({', '.join(f'{v:.2f}' for v in got['this tree'])}); ratio "
                  f"{med['baseline'] / med['this tree']:.2f}x", flush=True)
        return
    totals = {k: [0.0, 0.0] for k in trees}
    for name in names:
        got: dict[str, list[dict]] = {k: [] for k in trees}
        for r in range(args.rounds):
            for label, tree in trees.items():
                with tempfile.TemporaryDirectory() as tmp:
                    m = run(tree, plan[name], tmp)
                    if args.check:
                        check = subprocess.run([sys.executable, os.path.join(HERE, "vrft_table_check.py"), tmp],
                                               capture_output=True, text=True)
                        print(f"{name:>24} {label:>9} round {r + 1}, vrft_table_check.py: {check.stdout.strip()}")
                got[label].append(m)
                print(f"{name:>24} {label:>9} round {r + 1}: wall {m['wall']:7.1f} s, CPU {m['cpu']:7.1f} s, "
                      f"{m['rows']} rows, {m['computed']} computed, CPU {1e3 * m['cpu'] / m['rows']:6.2f} ms/row, "
                      f"{1e3 * m['cpu'] / m['computed']:6.2f} ms/computed task, load {os.getloadavg()[0]:.2f}",
                      flush=True)
        med = {k: (statistics.median(m["wall"] for m in v), statistics.median(m["cpu"] for m in v))
               for k, v in got.items()}
        for k in trees:
            totals[k][0] += med[k][0]
            totals[k][1] += med[k][1]
        print(f"{name:>24} median: baseline wall {med['baseline'][0]:.1f} s / CPU {med['baseline'][1]:.1f} s, "
              f"this tree wall {med['this tree'][0]:.1f} s / CPU {med['this tree'][1]:.1f} s; ratio baseline/this "
              f"tree: wall {med['baseline'][0] / med['this tree'][0]:.2f}x, CPU "
              f"{med['baseline'][1] / med['this tree'][1]:.2f}x", flush=True)
    if len(names) > 1:
        b, t = totals["baseline"], totals["this tree"]
        print(f"{'all ' + str(len(names)) + ' sweeps':>24}: baseline wall {b[0]:.1f} s / CPU {b[1]:.1f} s, this tree "
              f"wall {t[0]:.1f} s / CPU {t[1]:.1f} s; ratio wall {b[0] / t[0]:.2f}x, CPU {b[1] / t[1]:.2f}x")


if __name__ == "__main__":
    main()
