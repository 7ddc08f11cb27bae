"""Check a Willems reproduction against the committed one: every cell's unstable rate inside the committed 95% interval.

For each of table_paper.csv, table_remark.csv and table_designs.csv present in both directories (default committed:
docs/results/willems), per cell: the committed rate with its Wilson interval and ours, whether ours lies inside it,
whether the unstable counts are equal, and whether our mean spectral radius lies inside the committed mean's 95%
interval, and whether the two rates' 95% intervals overlap (the weaker test: a cell whose committed count is 1 of
256 has the interval [0.1, 2.2] %, which 0 of 256 misses). Prints one line per table and every cell outside; exits
1 if any rate lies outside its committed interval.
Run: python benchmarks/willems_table_check.py OUT_DIR [COMMITTED_DIR]
"""

from __future__ import annotations

import csv
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
COMMITTED = os.path.join(os.path.dirname(HERE), "docs", "results", "willems")
KEYS = {"table_paper.csv": ("horizon", "method", "delta_u"), "table_remark.csv": ("horizon", "method", "criterion"),
        "table_designs.csv": ("design", "poison", "criterion", "delta_u")}
SLACK = 1e-9


def cells(path: str, key: tuple[str, ...]) -> dict[tuple[str, ...], dict[str, str]]:
    """Rows of a table CSV by their key columns."""
    with open(path, newline="", encoding="utf-8") as fh:
        return {tuple(r[k] for k in key): r for r in csv.DictReader(fh)}


def inside(value: str, lo: str, hi: str) -> bool:
    """lo <= value <= hi (with SLACK); NaN never inside."""
    return float(lo) - SLACK <= float(value) <= float(hi) + SLACK


def main(out: str, committed: str = COMMITTED) -> int:
    """Print the comparison of every common table; 1 if a rate lies outside its committed interval."""
    outside = 0
    for name, key in KEYS.items():
        ref_path, new_path = os.path.join(committed, name), os.path.join(out, name)
        if not (os.path.exists(ref_path) and os.path.exists(new_path)):
            continue
        ref, new = cells(ref_path, key), cells(new_path, key)
        common = sorted(set(ref) & set(new))
        bad = [k for k in common if not inside(new[k]["rate"], ref[k]["rate_lo"], ref[k]["rate_hi"])]
        same = sum(ref[k]["unstable"] == new[k]["unstable"] and ref[k]["n"] == new[k]["n"] for k in common)
        rho = sum(inside(new[k]["spectral_radius"], ref[k]["spectral_radius_lo"], ref[k]["spectral_radius_hi"])
                  for k in common)
        overlap = sum(float(new[k]["rate_lo"]) <= float(ref[k]["rate_hi"]) + SLACK and
                      float(ref[k]["rate_lo"]) <= float(new[k]["rate_hi"]) + SLACK for k in common)
        print(f"{name}: {len(common)} cells ({len(set(ref) - set(new))} committed cells not in ours); rate inside the "
              f"committed 95% interval {len(common) - len(bad)}/{len(common)}; the two 95% intervals overlap "
              f"{overlap}/{len(common)}; equal unstable counts {same}/{len(common)}; mean spectral radius inside its "
              f"committed 95% interval {rho}/{len(common)}")
        for k in bad:
            print(f"  OUTSIDE {k}: ours {100 * float(new[k]['rate']):.1f}% ({new[k]['unstable']}/{new[k]['n']}) "
                  f"[{100 * float(new[k]['rate_lo']):.1f}, {100 * float(new[k]['rate_hi']):.1f}], committed "
                  f"{100 * float(ref[k]['rate']):.1f}% ({ref[k]['unstable']}/{ref[k]['n']}) "
                  f"[{100 * float(ref[k]['rate_lo']):.1f}, {100 * float(ref[k]['rate_hi']):.1f}]")
        outside += len(bad)
    return 1 if outside else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
