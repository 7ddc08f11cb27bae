"""Many VRFT attacks at once (bilevel.attacks.vrft_batch.attack_many) against one at a time (vrft_methods.attack), in
one process with one BLAS thread: CPU time per attack and peak memory for batches of 1, 16, 256 and 4,096 instances.

The instances are Table 1's scenario-B cells (paper convention, N = 512, max-min, alternating): data sets of seeds
SeedSequence(0).spawn(...), each at eps_u in (0, 0.1, 0.2) x the paper's five eps_y, the first SIZE of them. Each
measurement starts with the process's conditioning starts forgotten (both paths find their own) and the instances'
data made beforehand (not timed). For each size: CPU ms per attack batched and one at a time (one at a time on at most
--single instances, the first of the batch), their ratio, statuses equal (on those instances), peak traced memory of
the batched call (tracemalloc, a separate run: numpy's arrays are traced). Batch size 1 runs the one-instance path
(below defaults["batch.min_size"]), measured as 16 batches of one; "forced" runs the batched path on batches of one
(min_size set to 1). Prints the load average before and after.

Run: python benchmarks/bench_vrft_batch.py [--sizes 1,16,256,4096] [--single 256]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import time
import tracemalloc

from bilevel.attacks.vrft_batch import attack_many
from bilevel.attacks.vrft_methods import attack
from bilevel.defaults import defaults
from bilevel.experiments.sweep import sim_seeds
from bilevel.problems.vrft_instance import PAPER_EPS_Y, attack_instance
from bilevel.solvers.engine import starts
from bilevel.threads import single_threaded


def instances(count: int) -> list:
    """The first `count` scenario-B Table 1 attack instances (data sets in seed order, 15 cells each)."""
    seeds = sim_seeds(0, -(-count // 15))
    return [attack_instance("maxmin", "B", eu, ey, s, 512, "paper") for s in seeds for eu in (0.0, 0.1, 0.2)
            for ey in PAPER_EPS_Y][:count]


def cpu(f) -> tuple[float, object]:
    """(CPU seconds of f(), its value), the process's conditioning starts forgotten first."""
    starts._KEPT.clear()
    t0 = time.process_time()
    out = f()
    return time.process_time() - t0, out


def peak(f) -> float:
    """Peak traced memory of f() in MiB."""
    tracemalloc.start()
    f()
    top = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return top / 2 ** 20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1,16,256,4096")
    parser.add_argument("--single", type=int, default=256, help="one-at-a-time attacks per size at most")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    print(f"# bench_vrft_batch.py at {commit}, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; {platform.platform()}; nproc "
          f"{os.cpu_count()}; python {platform.python_version()}; load average before: "
          f"{open('/proc/loadavg').read().split()[:3]} (a shared machine: other jobs ran alongside)")
    print("# CPU ms per attack (time.process_time, one BLAS thread, one process); ratio = one-at-a-time / batched, "
          "both measured in this run")
    every = instances(max(max(sizes), 16))
    with single_threaded():
        attack_many(every[:8]), attack(every[0], "alternating")  # imports, declarations, compiled functions
        for size in sizes:
            atks = every[:size]
            n_single = min(size, args.single)
            if size == 1:  # one attack is a few ms: the mean of 16 batches of one (different instances)
                t_batch, many = cpu(lambda: [attack_many([a])[0] for a in every[:16]])
                t_batch, n_single, atks = t_batch / 16, 16, every[:16]
            else:
                t_batch, many = cpu(lambda: attack_many(atks))
            t_single, single = cpu(lambda: [attack(a, "alternating") for a in atks[:n_single]])
            same = sum(a.status == b.status for a, b in zip(single, many))
            rel = max(abs(a.stats["value"] - b.stats["value"]) / abs(a.stats["value"]) for a, b in zip(single, many))
            starts._KEPT.clear()  # the conditioning starts are computed inside the traced run, as in cpu()
            memory = peak(lambda: attack_many(atks[:size]))
            line = (f"batch {size:5d}: batched {1e3 * t_batch / size:6.2f} ms/attack, one at a time "
                    f"{1e3 * t_single / n_single:6.2f} ms/attack (on {n_single}); ratio "
                    f"{(t_single / n_single) / (t_batch / size):.2f}x; statuses equal {same}/{n_single}, value max "
                    f"rel diff {rel:.1e}; peak traced memory of the batched call {memory:.1f} MiB")
            if size == 1:
                old = defaults["batch.min_size"]
                defaults["batch.min_size"] = 1
                try:
                    t_forced, _ = cpu(lambda: [attack_many([a]) for a in atks])
                finally:
                    defaults["batch.min_size"] = old
                line += f"; the batched path forced on batches of one {1e3 * t_forced / len(atks):.2f} ms/attack"
            print(line, flush=True)
    print(f"# load average after: {open('/proc/loadavg').read().split()[:3]}")


if __name__ == "__main__":
    main()
