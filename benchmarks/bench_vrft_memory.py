"""Traced peak memory (tracemalloc) of the max-min VRFT attack (scenario B, eps = (0.1, 0.057), seed 0, 10 iterations)
at several record lengths N, for this tree and a baseline tree (default /work/main), each in a fresh process
(PYTHONPATH=tree): the peak in bytes and in length-N vectors of doubles, its growth from the smallest N, the ratio
this / baseline, and whether the two trees' answers are bit-identical (SHA-1 of x and y).

tracemalloc sees Python's allocations (numpy arrays, Python objects), not CasADi's C++ graph.

Run: python benchmarks/bench_vrft_memory.py [N,N,... [BASELINE]]   (defaults 4096,16384,65536 and /work/main)
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import platform
import subprocess
import sys

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def worker(n: int) -> None:
    """Print one JSON object: the traced peak of the attack at N = n, its upper objective and the answer's hash."""
    import tracemalloc

    import numpy as np

    from bilevel.attacks.vrft_methods import attack_alternating
    from bilevel.problems.vrft_instance import attack_instance

    atk = attack_instance("maxmin", "B", 0.1, 0.057, seed=0, N=n)
    tracemalloc.start()
    res = attack_alternating(atk, max_iter=10)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    parts = [np.ascontiguousarray(v).tobytes() for v in [*res.x.values(), *res.y.values()]]
    print(json.dumps({"peak": peak, "value": res.upper_objective, "hash": hashlib.sha1(b"".join(parts)).hexdigest()}))


def measure(tree: str, n: int) -> dict:
    """worker(n) in a fresh process importing `tree`."""
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", str(n)], capture_output=True,
                         text=True, check=True, env={**os.environ, "PYTHONPATH": tree})
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    sizes = [int(s) for s in (sys.argv[1] if len(sys.argv) > 1 else "4096,16384,65536").split(",")]
    baseline = sys.argv[2] if len(sys.argv) > 2 else "/work/main"
    print(f"machine: {platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores, Python "
          f"{platform.python_version()}; date {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC")
    print(f"this tree {HERE}, baseline {baseline}; traced peak in MB and in length-N vectors of doubles")
    print(f"{'N':>7} {'this MB':>9} {'this /8N':>9} {'base MB':>9} {'base /8N':>9} {'this/base':>9} {'same':>5}")
    peaks = []
    for n in sizes:
        own, base = measure(HERE, n), measure(baseline, n)
        peaks.append(own["peak"])
        print(f"{n:>7} {own['peak'] / 1e6:>9.1f} {own['peak'] / (8 * n):>9.0f} {base['peak'] / 1e6:>9.1f} "
              f"{base['peak'] / (8 * n):>9.0f} {own['peak'] / base['peak']:>9.2f} "
              f"{own['hash'] == base['hash']!s:>5}", flush=True)
    for n, peak in zip(sizes[1:], peaks[1:]):
        print(f"this tree, N {sizes[0]} -> {n} (x{n / sizes[0]:g}): peak x{peak / peaks[0]:.2f}")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--worker":
        worker(int(sys.argv[2]))
    else:
        main()
