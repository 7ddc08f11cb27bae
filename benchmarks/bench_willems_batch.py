"""Many Willems destabilizing attacks at once (bilevel.attacks.willems.destabilize_many) against one at a time
(destabilize_attack), in one process with one BLAS thread: CPU time per attack and peak memory for batches of 1, 16,
256 and 4,096 instances.

The instances are the paper sweep's destabilizing attacks (appendix SDP, design lqr, input poisoning, N = 50 by
default, the reproduction's 64 starts and 100 steps): data sets of seeds sim_seeds(0, ...), each at the paper's ten
delta_u, the first SIZE of them, each with its sweep attack seed. Attacks are built beforehand (not timed). For each
size: CPU ms per attack batched and one at a time (one at a time on at most --single instances, the first of the
batch, measured in the same run), their ratio, results equal field by field (every field but the wall time) on those
instances, statuses, iterations and unstable flags equal, the true loop's spectral radius's largest relative difference,
peak traced memory of the batched call (tracemalloc, a separate run; --memory-max caps the sizes traced).
Batch size 1 runs the one-instance path (below defaults["batch.min_size"]), measured as 16 batches of one. Prints the
load average before and after.

Run: python benchmarks/bench_willems_batch.py [--sizes 1,16,256,4096] [--single 256] [--horizon 50]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import time

import numpy as np

from bilevel.attacks.outcome import unstable
from bilevel.attacks.willems import destabilize_attack, destabilize_many
from bilevel.experiments.willems import make_plan, sim_seeds
from bilevel.problems.willems import build_attack
from bilevel.problems.willems_instance import WillemsSetting
from bilevel.threads import single_threaded
from bench_vrft_batch import peak  # benchmarks/ (the script's directory) is on sys.path


def instances(count: int, horizon: int) -> tuple[list, list]:
    """The first `count` destabilizing attacks of the paper sweep at N = horizon and their attack seeds."""
    deltas = make_plan(256, False).deltas
    atks, seeds = [], []
    for data_seed, attack_seed in sim_seeds(0, -(-count // len(deltas))):
        first = build_attack(WillemsSetting(objective="destabilize", horizon=horizon, seed=data_seed,
                                            delta_u=deltas[0], poison="u", design="lqr"))
        for d in deltas:
            atks.append(first if d == deltas[0] else first.at_budget(d, 0.0))
            seeds.append(attack_seed)
    return atks[:count], seeds[:count]


def fields(result) -> tuple:
    """Every field of an attack's result but its wall time."""
    st = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in result.stats.items()}
    return (result.status, result.message, result.nit, result.upper_objective, repr(result.certificate), repr(st),
            repr(result.start_records), {k: v.tolist() for k, v in result.x.items()})


def cpu(f) -> tuple[float, object]:
    """(CPU seconds of f(), its value)."""
    t0 = time.process_time()
    out = f()
    return time.process_time() - t0, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1,16,256,4096")
    parser.add_argument("--single", type=int, default=256, help="one-at-a-time attacks per size at most")
    parser.add_argument("--horizon", type=int, default=50)
    parser.add_argument("--memory-max", type=int, default=4096, help="largest size whose memory is traced")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    plan = make_plan(256, False)
    opts = {"starts": plan.rho_starts, "max_iter": plan.rho_iter}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    print(f"# bench_willems_batch.py at {commit}, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; {platform.platform()}; "
          f"nproc {os.cpu_count()}; python {platform.python_version()}; load average before: "
          f"{open('/proc/loadavg').read().split()[:3]} (a shared machine: other jobs ran alongside)")
    print(f"# N = {args.horizon}, {opts['starts']} starts, {opts['max_iter']} steps; CPU ms per attack "
          "(time.process_time, one BLAS thread, one process); ratio = one-at-a-time / batched, both in this run")
    atks, seeds = instances(max(max(sizes), 16), args.horizon)
    with single_threaded():
        destabilize_many(atks[:8], seeds[:8], **opts), destabilize_attack(atks[0], seed=seeds[0], **opts)  # warm up
        for size in sizes:
            part, ps = atks[:size], seeds[:size]
            n_single = min(size, args.single)
            if size == 1:  # the mean of 16 batches of one (different instances)
                t_batch, many = cpu(lambda: [destabilize_many([a], [s], **opts)[0]
                                             for a, s in zip(atks[:16], seeds[:16])])
                t_batch, n_single, part, ps = t_batch / 16, 16, atks[:16], seeds[:16]
            else:
                t_batch, many = cpu(lambda: destabilize_many(part, ps, **opts))
            t_single, single = cpu(lambda: [destabilize_attack(a, seed=s, **opts)
                                            for a, s in zip(part[:n_single], ps[:n_single])])
            same = sum(fields(a) == fields(b) for a, b in zip(single, many))
            flags = sum((a.status, a.nit, unstable(a)) == (b.status, b.nit, unstable(b)) for a, b in zip(single, many))
            rel = max(abs(a.stats["spectral_radius"] / b.stats["spectral_radius"] - 1) for a, b in zip(single, many))
            line = (f"batch {size:5d}: batched {1e3 * t_batch / size:7.2f} ms/attack, one at a time "
                    f"{1e3 * t_single / n_single:7.2f} ms/attack (on {n_single}); ratio "
                    f"{(t_single / n_single) / (t_batch / size):.2f}x; results equal {same}/{n_single}, status, "
                    f"iterations and unstable flag equal {flags}/{n_single}, spectral radius max rel diff {rel:.1e}")
            print(line, flush=True)  # before the memory run, which takes longer than the timed one
            if size <= args.memory_max:
                memory = peak(lambda: destabilize_many(atks[:size], seeds[:size], **opts))
                print(f"batch {size:5d}: peak traced memory of the batched call {memory:.1f} MiB", flush=True)
    print(f"# load average after: {open('/proc/loadavg').read().split()[:3]}")


if __name__ == "__main__":
    main()
