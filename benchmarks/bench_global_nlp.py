"""method="global" on the textbook problems with a convex-NLP lower level or a lower constraint matrix depending on x
(SCIP, multiplier bounds from a Slater point), next to ipopt (8 starts, the baseline, run in the same process).

One line per problem: the published F* (registry), the proven bounds in the declared sense, the relative gap, SCIP's
nodes, the median wall time of REPEATS solves, ipopt's value and median time, and the ratio; then the median time
and the worst |F - F*| over the gap. Asserts nothing.
Usage: cd benchmarks && python bench_global_nlp.py > results/bench_global_nlp.txt
"""

from __future__ import annotations

import os
import statistics
import time

import bilevel as bl
from bilevel.problems import registry
from bench_global import REPEATS, timed  # the same timing of a registered problem (run from benchmarks/)
from bench_global_scip import header

NAMES = sorted({*registry.names("convex-nlp"), *registry.names("x-matrix"), "bolib-floudaszlobec1998"})


def main() -> None:
    header("bench_global_nlp.py")
    print(f"\n## Convex-NLP and x-dependent-matrix lower levels, method='global' (median of {REPEATS} runs) vs ipopt "
          "(8 starts)")
    print(f"| {'problem':<26} | {'F*':>12} | {'lower bound':>14} | {'upper bound':>14} | {'gap':>8} | {'nodes':>5} | "
          f"{'status':<8} | {'global [s]':>10} | {'ipopt F':>12} | {'ipopt [s]':>9} | {'g/i':>5} |")
    print("|" + "|".join("-" * w for w in (28, 14, 16, 16, 10, 7, 10, 12, 14, 11, 7)) + "|")
    times, ratios, errors = [], [], []
    for name in NAMES:
        known = registry.spec(name).optimum
        tg, res = timed(name, "global")
        ti, ri = timed(name, "ipopt", starts=8, seed=0)
        gb = res.certificate.global_bound
        proven = res.status is bl.Status.SOLVED and gb.proven
        times.append(tg)
        ratios.append(tg / ti)
        errors.append(abs(res.upper_objective - known) / max(1.0, abs(known)) / max(gb.gap, gb.tolerance))
        print(f"| {name:<26} | {known:>12.8g} | {gb.lower_bound:>14.10g} | {gb.upper_bound:>14.10g} | "
              f"{gb.gap:>8.1e} | {gb.nodes:>5} | {'proven' if proven else res.status.value:<8} | {tg:>10.3f} | "
              f"{ri.upper_objective:>12.8g} | {ti:>9.3f} | {tg / ti:>5.2f} |", flush=True)
    print(f"\n{len(NAMES)} problems; median time {statistics.median(times):.3f} s, worst {max(times):.3f} s; "
          f"median ratio global / ipopt {statistics.median(ratios):.2f}; largest |F - F*| / max(1, |F*|) over the "
          f"stated gap (or its tolerance) {max(errors):.2f}")
    auto_table()
    print(f"# load average at end: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")


def auto_run(name: str) -> tuple[float, bl.BilevelResult]:
    """Wall time and result of the default method on a registered problem."""
    t0 = time.perf_counter()
    res = bl.solve(registry.get(name))
    return time.perf_counter() - t0, res


def auto_table() -> None:
    """The default method on every textbook problem: global first (auto.global_time, auto.global_size), against the
    local rule alone (auto.global_size = 0: global never tried), one run each, one after another."""
    names = registry.names("textbook")
    rows = []
    for name in names:
        t_auto, res = auto_run(name)
        size = bl.defaults["auto.global_size"]
        bl.defaults["auto.global_size"] = 0
        try:
            t_local, local = auto_run(name)
        finally:
            bl.defaults["auto.global_size"] = size
        rows.append((name, t_auto, res, t_local, local))
    known = {name: registry.spec(name).optimum for name in names}

    def reached(name: str, res: bl.BilevelResult) -> bool:
        return res.status is bl.Status.SOLVED and abs(res.upper_objective - known[name]) <= 1e-4 * max(
            1.0, abs(known[name]))

    proven = [r for r in rows if r[2].method == "global" and reached(r[0], r[2])]
    print(f"\n## The default method (auto) on the {len(names)} textbook problems, one run each")
    print(f"global first: {len(proven)} proven at F* by global, {sum(reached(n, r) for n, _, r, *_ in rows)} solved "
          f"at F* in all, {sum(t for _, t, *_ in rows):.1f} s in all; the local rule alone: "
          f"{sum(reached(n, r) for n, *_, r in rows)} solved at F*, {sum(r[3] for r in rows):.1f} s in all")
    for name, t_auto, res, t_local, local in rows:
        if not reached(name, res) or res.method != "global":
            print(f"  {name}: auto took {res.method} ({res.status.value}, F = {res.upper_objective:.8g}, "
                  f"{t_auto:.2f} s)")
        if not reached(name, local):
            print(f"  {name}: the local rule ends {local.status.value} at F = {local.upper_objective:.8g} "
                  f"(F* = {known[name]:.8g})")


if __name__ == "__main__":
    main()
