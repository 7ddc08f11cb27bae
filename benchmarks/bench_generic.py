"""The generic route against the structured attacks on the paper's instances (issue "One engine").

For scenario B, N = 512, eps = (0.1, 0.057), each seed: the structured alternating attack
(bilevel.attacks.vrft_methods), then the vrft-maxmin problem, declared once for seed 0 with the data as
parameters and moved to each seed's data set by `load_instance` (set_value), solved by the generic methods
`hypergradient` (default options: its exact-block mode where the structure allows it) and its descent alone
(exact_block=False) with one start (the problem's suggested conditioning start). Times: the
declaration, the first solve of each method (canonicalization, classification, reduction, compiling; seed 0),
and each seed's `solve` after set_value (method, certificate and local probe; the medians are over these).
Objectives are ratios to the structured attack's.
`--kkt S` also runs `ipopt` and `relaxation` with their defaults (one start; warm="auto", which here starts the NLP
from hypergradient's answer, as the problem has an exact block) on the first S seeds.
Willems (appendix B, N = 15, input poisoning, lqr design): the Willems hypergradient attack (8 starts, no stop at
instability) against `bilevel.solve(..., method="hypergradient", starts=8)` on the same problem, for the eigenvalue
criterion at delta_u = 0.6 and the max-min criterion at delta_u = 0.1 (where the loops stay stable: the attack's
+inf convention for an unstable identified loop has no counterpart in the declared H2 cost).
linf budgets (`--linf S`, S seeds): declared as the poisoning's bounds, a fresh declaration per seed; the structured
attack against hypergradient (the descent: no exact block without an l2 ball) and ipopt, one start each.
Run: python benchmarks/bench_generic.py [seeds] [--kkt S] [--willems W] [--linf S]
"""

from __future__ import annotations

import os
import platform
import sys
import time
from datetime import datetime, timezone

import numpy as np

import bilevel as bl
from bilevel.problems.vrft_instance import attack_instance
from bilevel.attacks.vrft_methods import attack_alternating
from bilevel.attacks.willems import hypergradient_attack
from bilevel.problems.vrft import attack_problem, load_instance
from bilevel.problems.willems import build_attack

GENERIC = {"hypergradient": ("hypergradient", {}), "hg gain_tol=1e-4": ("hypergradient", {"gain_tol": 1e-4}),
           "descent": ("hypergradient", {"exact_block": False})}
"""Row label -> (method, options): hypergradient as a user calls it (its default exact_block="auto" takes the exact
input block it finds in the declared structure; gain_tol 1e-5), the same with the structured attack's stopping tolerance
(relative gain 1e-4 over 5 steps), and its first-order descent alone (exact_block=False)."""
KKT = {m: (m, {}) for m in ("ipopt", "relaxation")}


def willems(seeds: int) -> None:
    """Generic hypergradient vs the Willems attack: time ratio and criterion difference, per criterion/selection."""
    for objective, delta in (("eigen", 0.6), ("maxmin", 0.1)):
        for selection in ("tikhonov", "min-norm"):
            ratios, diffs, solved = [], [], 0
            for seed in range(seeds):
                attack = build_attack(objective=objective, horizon=15, seed=seed, delta_u=delta, selection=selection)
                ours = hypergradient_attack(attack, seed=seed, starts=8, stop_when_unstable=False)
                t = time.perf_counter()
                res = bl.solve(attack.problem, method="hypergradient", starts=8, seed=seed)
                ratios.append((time.perf_counter() - t) / ours.wall_time)
                diffs.append(abs(res.upper_objective - ours.upper_objective) / max(1.0, abs(ours.upper_objective)))
                solved += res.status.value == "solved"
            print(f"willems-{objective} N = 15, delta_u = {delta}, {selection:8s} learner, {seeds} seeds: generic / "
                  f"attack time median {np.median(ratios):.2f}x (max {np.max(ratios):.2f}x); criterion difference "
                  f"median {np.median(diffs):.1e}, max {np.max(diffs):.1e} (relative); solved {solved}/{seeds}",
                  flush=True)


def linf(seeds: int) -> None:
    """linf budgets (declared as bounds; no exact block, so hypergradient is the descent): the structured attack
    (alternating, conditional-gradient input step for max-min) against hypergradient and ipopt, one start each,
    a fresh declaration per seed (bounds are fixed at declaration), N = 512, scenario B, eps = (0.1, 0.057)."""
    for objective in ("maxmin", "targeted"):
        better = 1.0 if objective == "maxmin" else -1.0
        rows: dict[str, list[tuple[float, float, str]]] = {"hypergradient": [], "ipopt": []}
        t_ref, declare = [], []
        for seed in range(seeds):
            atk = attack_instance(objective, "B", 0.1, 0.057, seed=seed, N=512, norm="linf")
            ref = attack_alternating(atk, seed=seed)
            t_ref.append(ref.wall_time)
            t = time.perf_counter()
            problem = attack_problem(atk)
            declare.append(time.perf_counter() - t)
            line = f"linf {objective} seed {seed:2d}: structured {ref.wall_time:6.3f} s J = {ref.upper_objective:.6f}"
            for m in rows:
                res = problem.solve(method=m, starts=1)
                ratio = res.upper_objective / ref.upper_objective
                rows[m].append((res.wall_time, ratio, res.status.value))
                line += f" | {m} {res.wall_time:6.2f} s J/J_s = {ratio:.4f} {res.status.value}"
            print(line, flush=True)
        print(f"linf {objective}, {seeds} seeds: structured median {np.median(t_ref):.3f} s; declaration median "
              f"{np.median(declare):.2f} s (not in the solve times)")
        for m, r in rows.items():
            t, ratio = np.array([v[0] for v in r]), np.array([v[1] for v in r])
            stronger = np.mean(better * (ratio - 1.0) >= -1e-6)
            print(f"  {m:13s}: median solve {np.median(t):.2f} s = {np.median(t) / np.median(t_ref):.1f}x the "
                  f"structured attack; J/J_s median {np.median(ratio):.3f} (min {ratio.min():.3f}, max "
                  f"{ratio.max():.3f}); at least as strong on {100 * stronger:.0f}%; solved "
                  f"{sum(v[2] == 'solved' for v in r)}/{len(r)}", flush=True)


def main(seeds: int = 40, kkt: int = 0, willems_seeds: int = 0, linf_seeds: int = 0) -> None:
    print(f"# bench_generic  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}")
    rows = {m: [] for m in ("structured", *GENERIC, *KKT)}
    t = time.perf_counter()
    problem = attack_problem(attack_instance("maxmin", "B", 0.1, 0.057, seed=0, N=512))
    declare = time.perf_counter() - t
    first = {}
    for label, (m, opts) in {**GENERIC, **(KKT if kkt else {})}.items():
        first[label] = problem.solve(method=m, starts=1, **opts).wall_time
    print(f"declaration {declare:.2f} s; first solve (preparation + compile + solve, seed 0): "
          + ", ".join(f"{m} {v:.2f} s" for m, v in first.items()), flush=True)
    for seed in range(seeds):
        atk = attack_instance("maxmin", "B", 0.1, 0.057, seed=seed, N=512)
        ref = attack_alternating(atk, seed=seed)
        rows["structured"].append((ref.wall_time, 1.0, ref.status.value))
        load_instance(problem, atk)
        line = f"seed {seed:3d}: structured {1000 * ref.wall_time:6.1f} ms J = {ref.upper_objective:.6f}"
        for label, (m, opts) in {**GENERIC, **(KKT if seed < kkt else {})}.items():
            res = problem.solve(method=m, starts=1, **opts)
            ratio = res.upper_objective / ref.upper_objective if res.upper_objective is not None else np.nan
            rows[label].append((res.wall_time, ratio, res.status.value))
            line += f" | {label} {res.wall_time:6.2f} s J/J_s = {ratio:.6f} {res.status.value}"
        print(line, flush=True)
    t_ref = np.median([r[0] for r in rows["structured"]])
    print(f"\nN = 512, {seeds} seeds, scenario B, eps = (0.1, 0.057); generic methods one start:")
    print(f"  structured attack: median {1000 * t_ref:.1f} ms; declaration once {declare:.2f} s")
    for m in (*GENERIC, *KKT):
        if not rows[m]:
            continue
        t = np.array([r[0] for r in rows[m]])
        ratio = np.array([r[1] for r in rows[m]])
        solved = sum(r[2] == "solved" for r in rows[m])
        print(f"  {m:13s}: median solve {1000 * np.median(t):.1f} ms = {np.median(t) / t_ref:.2f}x the structured "
              f"attack (first solve with preparation {first[m]:.2f} s; amortized over {seeds} seeds with it and the "
              f"declaration: {(t.sum() + first[m] + declare) / seeds / t_ref:.1f}x); "
              f"J >= 0.98 J_s on {100 * np.mean(ratio >= 0.98):.0f}%, >= 0.95 J_s on "
              f"{100 * np.mean(ratio >= 0.95):.0f}%, >= J_s (1e-6) on {100 * np.mean(ratio >= 1 - 1e-6):.0f}% of "
              f"{t.size}; min ratio {np.nanmin(ratio):.4f};"
              f" status solved {solved}/{t.size}")
    if willems_seeds:
        print()
        willems(willems_seeds)
    if linf_seeds:
        print()
        linf(linf_seeds)


if __name__ == "__main__":
    args = sys.argv[1:]
    flags = {f: int(args[args.index(f) + 1]) if f in args else 0 for f in ("--kkt", "--willems", "--linf")}
    pos = [a for i, a in enumerate(args) if not a.startswith("--") and (i == 0 or not args[i - 1].startswith("--"))]
    main(int(pos[0]) if pos else 40, flags["--kkt"], flags["--willems"], flags["--linf"])
