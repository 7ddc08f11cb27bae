"""Where the CPU time of batched VRFT attacks goes: attack_many on the first 240 Table 1 scenario-B instances
(bench_vrft_batch.instances), one process, one BLAS thread, the phases of bilevel.solvers.batch.solve_many timed by
wrapping them (time.process_time): the batched ascent, the batched probe (of which the learners' fits at the probe's
points and the hypergradients), finalize (of which certify_point and its independent lower re-solve); then the CPU
per row of the probe's stacked fit (BatchOracle.fits) at chunk sizes 8-512. Prints the load average before and after.

Run: python benchmarks/bench_vrft_batch_phases.py [--count 240] [--repeats 3]
"""

from __future__ import annotations

import argparse
import time
from typing import Any, Callable

import numpy as np

import bilevel.certificate as certificate
import bilevel.solvers.batch as batch
import bilevel.solvers.verdict.finalize as finalize
from bilevel.attacks import vrft_batch
from bilevel.solvers.engine import starts
from bilevel.solvers.engine.affine_ls_batch import BatchOracle
from bilevel.threads import single_threaded
from bench_vrft_batch import instances

ACC: dict[str, float] = {}


def timed(owner: Any, name: str, key: str) -> None:
    """Replace owner.name by a wrapper that adds its CPU seconds to ACC[key]."""
    f: Callable = getattr(owner, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t = time.process_time()
        try:
            return f(*args, **kwargs)
        finally:
            ACC[key] = ACC.get(key, 0.0) + time.process_time() - t

    setattr(owner, name, wrapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=240)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"# bench_vrft_batch_phases.py, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; load average before: "
          f"{open('/proc/loadavg').read().split()[:3]} (shared machine)")
    for owner, name, key in ((vrft_batch, "ascend_with_exact_block_batch", "ascent"), (batch, "_probe", "probe"),
                             (BatchOracle, "fits", "probe fits"), (BatchOracle, "hypergradients", "probe gradients"),
                             (batch, "finalize", "finalize"), (finalize, "certify_point", "certify_point"),
                             (certificate, "_re_solve", "lower re-solve")):
        timed(owner, name, key)
    atks = instances(args.count)
    with single_threaded():
        vrft_batch.attack_many(atks[:16])  # imports, declarations, compiled functions
        for _ in range(args.repeats):
            ACC.clear()
            starts._KEPT.clear()
            t = time.process_time()
            vrft_batch.attack_many(atks)
            total = time.process_time() - t
            print(f"{args.count} attacks: CPU {total:.3f} s; " + ", ".join(
                f"{k} {v:.3f} s ({100 * v / total:.0f}%)" for k, v in ACC.items()), flush=True)
        oracle = vrft_batch._oracle(atks[:64])
        X = 0.01 * np.random.default_rng(0).standard_normal((512, oracle.learner.n_a + oracle.learner.n_b))
        for rows in (8, 16, 32, 64, 128, 256, 512):
            inst, calls, best = np.arange(rows) % 64, max(1, 1024 // rows), np.inf
            for _ in range(5):
                t = time.process_time()
                for _ in range(calls):
                    oracle.fits(inst, X[:rows])
                best = min(best, (time.process_time() - t) / (calls * rows))
            print(f"probe fit, {rows:3d} rows a call: {1e6 * best:.1f} us CPU per row (min of 5)", flush=True)
    print(f"# load average after: {open('/proc/loadavg').read().split()[:3]}")


if __name__ == "__main__":
    main()
