"""Compare two output directories of `bilevel reproduce` or `bilevel compare` (before / after a change) row by row:
every .csv table and every .jsonl sweep, all columns and fields (nested ones too) except times and the source
version, compared exactly (the text of each value). Prints per file how many rows are identical and the first
differing fields. Run: python benchmarks/compare_outputs.py DIR_BEFORE DIR_AFTER
"""

from __future__ import annotations

import csv
import glob
import json
import os
import sys
from typing import Any

SKIPPED = {"wall_time", "version", "digest"}
"""Fields that differ between runs of the same code: times (also every field named time_*), and the source's hash
(which names the tree)."""


def strip(value: Any) -> Any:
    """value without the SKIPPED fields, at every depth."""
    if isinstance(value, dict):
        return {k: strip(v) for k, v in value.items() if k not in SKIPPED and not k.startswith("time_")}
    if isinstance(value, list):
        return [strip(v) for v in value]
    return value


def rows(path: str) -> dict[str, str]:
    """A file's rows as canonical text by key (a sweep's task key, else the row's position)."""
    with open(path, encoding="utf-8") as fh:
        if path.endswith(".csv"):
            return {str(i): json.dumps(strip(r), sort_keys=True) for i, r in enumerate(csv.DictReader(fh))}
        parsed = [json.loads(line) for line in fh if line.strip()]
    return {str(r.get("key", i)): json.dumps(strip(r), sort_keys=True) for i, r in enumerate(parsed)}


def main(before: str, after: str) -> None:
    total = same = 0
    for path in sorted(glob.glob(os.path.join(before, "*.csv")) + glob.glob(os.path.join(before, "*.jsonl"))):
        other = os.path.join(after, os.path.basename(path))
        a, b = rows(path), rows(other) if os.path.exists(other) else {}
        equal = [k for k in a if b.get(k) == a[k]]
        differ = [k for k in a if k not in equal][:3]
        print(f"{os.path.basename(path)}: {len(equal)}/{len(a)} rows identical ({len(b)} after)"
              + (f"; first differing: {differ}" if differ else ""))
        total, same = total + len(a), same + len(equal)
    print(f"total: {same}/{total} rows identical (times and source version excluded)")


if __name__ == "__main__":
    main(*sys.argv[1:3])
