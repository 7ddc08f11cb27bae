"""Compare two Willems reproduction runs row by row (same sweep task keys): criteria, verdicts, task times.

For each sweep (paper, remark, designs) present in both output directories: how many tasks both finished, on how many
the criterion agrees to 1e-6 relative, the unstable counts, the tasks whose verdict flipped (by method), and the sum
of task times. Run: python benchmarks/compare_runs.py OUT_BEFORE OUT_AFTER
"""

from __future__ import annotations

import collections
import json
import math
import os
import sys


def load(path: str) -> dict[str, dict]:
    """Rows of a sweep's .jsonl by task key (empty if the sweep did not run)."""
    if not os.path.exists(path):
        return {}
    with open(path, encoding="utf-8") as fh:
        return {row["key"]: row for row in map(json.loads, fh)}


def difference(x: float | None, y: float | None) -> float:
    """Relative criterion difference (0 for equal infinities, inf for one infinite)."""
    if x is None or y is None:
        return math.nan
    if math.isinf(x) or math.isinf(y):
        return 0.0 if x == y else math.inf
    return abs(x - y) / max(1.0, abs(x))


def main(before: str, after: str) -> None:
    for sweep in ("paper", "remark", "designs"):
        a, b = load(os.path.join(before, f"{sweep}.jsonl")), load(os.path.join(after, f"{sweep}.jsonl"))
        common = sorted(set(a) & set(b))
        if not common:
            continue
        diffs = sorted(d for d in (difference(a[k].get("objective"), b[k].get("objective")) for k in common)
                       if not math.isnan(d))
        flips = collections.Counter((a[k].get("method"), a[k].get("unstable"), b[k].get("unstable"))
                                    for k in common if a[k].get("unstable") != b[k].get("unstable"))
        unstable = [sum(bool(r[k].get("unstable")) for k in common) for r in (a, b)]
        times = [sum(r[k].get("wall_time", 0.0) for k in common) for r in (a, b)]
        print(f"{sweep}: {len(common)} common tasks; criterion equal (1e-6 rel) on {sum(d <= 1e-6 for d in diffs)}/"
              f"{len(diffs)}; median diff {diffs[len(diffs) // 2]:.1e}, max {diffs[-1]:.1e}; unstable before "
              f"{unstable[0]} after {unstable[1]}; verdict flips {sum(flips.values())} (method, before, after): "
              f"{dict(flips)}; task time sum before {times[0]:.0f} s after {times[1]:.0f} s")


if __name__ == "__main__":
    main(*sys.argv[1:3])
