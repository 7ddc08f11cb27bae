"""Time per attack of this tree against a baseline tree (default /work/main), measured in the same run: for each
attack, a fresh process per tree (PYTHONPATH=tree) runs one warm-up attack and then the attack on SEEDS data sets
(time: the process's CPU time per attack, single-threaded BLAS, so that other load on the machine counts less),
the two trees alternating ROUNDS times; per attack the median time of each tree and their ratio, and how many results
agree (VRFT: the attack's criterion to 1e-9 relative and the same unstable verdict; Willems: the criterion to 1e-9
relative and the same verdict).

Attacks: VRFT (N = 512, scenario B, eps = (0.1, 0.057)) maxmin, targeted (alternating), destabilize (joint), path
(the alternating attack along the paper's five output budgets); Willems (horizon 15, delta_u = 0.3) eigen
(hypergradient_attack, 8 starts) and destabilize (destabilize_attack, 64 starts).

Run: python benchmarks/bench_attack_time.py [SEEDS [ROUNDS [BASELINE [ATTACK,...]]]]   (defaults 10, 2, /work/main,
all)
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ATTACKS = ("vrft-maxmin", "vrft-targeted", "vrft-destabilize", "vrft-path", "willems-eigen", "willems-destabilize")


def worker(name: str, seeds: int) -> None:
    """Run attack `name` once to warm up, then on data seeds 0..seeds-1; print one JSON list of (time, value,
    unstable)."""
    if name.startswith("vrft"):
        from bilevel.attacks.vrft_methods import attack_alternating, attack_budget_path, attack_joint
        from bilevel.problems.vrft_instance import PAPER_EPS_Y, attack_instance

        objective = name.split("-")[1]
        run = {"destabilize": attack_joint, "path": lambda a: attack_budget_path(a, PAPER_EPS_Y)[-1]}.get(
            objective, attack_alternating)
        make = lambda s: attack_instance("maxmin" if objective == "path" else objective, "B", 0.1, 0.057, s, 512)  # noqa: E731
        read = lambda r: (r.stats["value"], r.stats["spectral_radius"] >= 1.0)  # noqa: E731
    else:
        from bilevel.attacks.willems import destabilize_attack, hypergradient_attack
        from bilevel.problems.willems import build_attack
        from bilevel.problems.willems_instance import WillemsSetting

        objective = name.split("-")[1]
        run = destabilize_attack if objective == "destabilize" else (lambda a: hypergradient_attack(a, starts=8))
        make = lambda s: build_attack(WillemsSetting(objective=objective, horizon=15, seed=s, delta_u=0.3))  # noqa: E731
        read = lambda r: (r.stats["criterion"], r.stats["spectral_radius"] >= 1.0)  # noqa: E731
    run(make(seeds))  # warm-up on a data set not measured
    rows = []
    for seed in range(seeds):
        atk = make(seed)
        t0 = time.process_time()
        res = run(atk)
        rows.append((time.process_time() - t0, *read(res)))
    print(json.dumps(rows))


def measure(tree: str, name: str, seeds: int) -> list[list]:
    env = {**os.environ, "PYTHONPATH": tree, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", name, str(seeds)], env=env,
                         cwd=tree, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def same(a: float, b: float) -> bool:
    return a == b or abs(a - b) <= 1e-9 * max(abs(a), abs(b))


def main(seeds: int = 10, rounds: int = 2, baseline: str = "/work/main", only: str = ",".join(ATTACKS)) -> None:
    print(f"# bench_attack_time.py, {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; {platform.platform()}; nproc "
          f"{os.cpu_count()}; python {platform.python_version()}; load average {os.getloadavg()[0]:.2f}")
    print(f"# this tree {HERE} vs baseline {baseline}; {seeds} data sets, {rounds} rounds alternating, one process per "
          "tree and round, single-threaded BLAS; time: CPU time per attack, median over data sets of the per-round minimum")
    for name in only.split(","):
        times = {"this": [], "base": []}
        results = {}
        for _ in range(rounds):
            for key, tree in (("base", baseline), ("this", HERE)):
                rows = measure(tree, name, seeds)
                times[key].append([r[0] for r in rows])
                results[key] = rows
        best = {k: [min(ts) for ts in zip(*v)] for k, v in times.items()}
        med = {k: statistics.median(v) for k, v in best.items()}
        agree = sum(same(a[1], b[1]) and a[2] == b[2] for a, b in zip(results["this"], results["base"]))
        unstable = {k: sum(r[2] for r in v) for k, v in results.items()}
        print(f"{name:20s} this {1e3 * med['this']:8.1f} ms  baseline {1e3 * med['base']:8.1f} ms  ratio "
              f"{med['this'] / med['base']:.3f}  same result {agree}/{seeds}  unstable {unstable['this']} vs "
              f"{unstable['base']}", flush=True)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--worker"]:
        worker(sys.argv[2], int(sys.argv[3]))
    else:
        main(*(int(a) for a in sys.argv[1:3]), *sys.argv[3:5])
