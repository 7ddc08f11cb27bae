"""Check a VRFT reproduction against the committed one: every cell's unstable rate inside the committed 95% interval.

For every table_*.csv present in both directories (default committed: docs/results/vrft), per cell: the committed
rate with its Wilson interval and ours, whether ours lies inside it, whether the unstable counts are equal, and the
relative difference of the mean attacker objective. Prints one line per table and every cell outside its interval;
exits 1 if any cell is outside. Run: python benchmarks/vrft_table_check.py OUT_DIR [COMMITTED_DIR]
"""

from __future__ import annotations

import csv
import glob
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
COMMITTED = os.path.join(os.path.dirname(HERE), "docs", "results", "vrft")


def cells(path: str) -> dict[tuple[str, str, str], dict[str, str]]:
    """Rows of a table_*.csv by (scenario, eps_u, eps_y)."""
    with open(path, newline="", encoding="utf-8") as fh:
        return {(r["scenario"], r["eps_u"], r["eps_y"]): r for r in csv.DictReader(fh)}


def main(out: str, committed: str = COMMITTED) -> int:
    """Print the comparison of every common table; 1 if a cell lies outside its committed interval."""
    outside = 0
    for path in sorted(glob.glob(os.path.join(committed, "table_*.csv"))):
        name = os.path.basename(path)
        if not os.path.exists(os.path.join(out, name)):
            continue
        ref, new = cells(path), cells(os.path.join(out, name))
        common = sorted(set(ref) & set(new))
        bad = [k for k in common
               if not float(ref[k]["rate_lo"]) - 1e-9 <= float(new[k]["rate"]) <= float(ref[k]["rate_hi"]) + 1e-9]
        same = sum(ref[k]["unstable"] == new[k]["unstable"] and ref[k]["n"] == new[k]["n"] for k in common)
        diffs = sorted(abs(float(new[k]["value"]) - float(ref[k]["value"])) / max(1e-12, abs(float(ref[k]["value"])))
                       for k in common)
        print(f"{name}: {len(common)} cells; inside the committed 95% interval {len(common) - len(bad)}/{len(common)};"
              f" equal unstable counts {same}/{len(common)}; mean objective relative difference median "
              f"{diffs[len(diffs) // 2]:.1e}, max {diffs[-1]:.1e}")
        for k in bad:
            print(f"  OUTSIDE {k}: ours {float(new[k]['rate']):.1f}% ({new[k]['unstable']}/{new[k]['n']}), committed "
                  f"{float(ref[k]['rate']):.1f}% [{float(ref[k]['rate_lo']):.1f}, {float(ref[k]['rate_hi']):.1f}]")
        outside += len(bad)
    return 1 if outside else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
