"""The stealthy identification attack on the authors' terms at T = 500, delta 0.075: the direct continuation from the
delta 0.05 answer (paper_attack, as reproduce and bench_identification_authors.py run it) against finer ladders of
deltas in between (each step paper_attack continued from the previous one), on chosen data sets.

Each data set runs deltas 0.01, 0.025 and 0.05 as the benchmark does; then each ladder starts from that 0.05 answer.
Per ladder: the final ||d[A B]||_2 at 0.075, its verdict (bilevel.ddc.stealth_check, tolerance 1e-6) and the CPU
seconds of all its steps, each step's value / IPOPT iterations / start / status / CPU.

Run: python benchmarks/bench_identification_ladder.py DIR SIMS [LADDERS]; DIR: the authors' extracted data sets, SIMS:
comma-separated data sets, LADDERS: JSON {name: [deltas]} (default LADDERS). Output:
benchmarks/results/bench_identification_ladder.txt.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from datetime import datetime, timezone

from bilevel.experiments.identification_paper import dataset_path, load_dataset, paper_attack
from bilevel.threads import single_threaded

T = 500
LADDERS = {"direct": [0.075], "fine": [0.0625, 0.075], "fine3": [0.0583, 0.0667, 0.075]}


def main() -> None:
    folder, sims = sys.argv[1], [int(s) for s in sys.argv[2].split(",")]
    ladders = json.loads(sys.argv[3]) if len(sys.argv) > 3 else LADDERS
    print(f"# bench_identification_ladder  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  {platform.node()}  "
          f"{platform.processor() or platform.machine()}  cores={os.cpu_count()}  python {platform.python_version()}  "
          f"load {os.getloadavg()[0]:.1f}", flush=True)
    with single_threaded():
        for sim in sims:
            data, base = load_dataset(dataset_path(folder, T, sim)), None
            for delta in (0.01, 0.025, 0.05):
                base = paper_attack(data, delta, base)
            print(sim, "0.05", f"{base.check['norm2']:.3f}", flush=True)
            for name, ladder in ladders.items():
                run, cpu, trace = base, 0.0, []
                for delta in ladder:
                    run = paper_attack(data, delta, run)
                    cpu += run.cpu_time
                    trace.append(f"{delta}:{run.check['norm2']:.3f}/{run.result.nit}/{run.start}/"
                                 f"{run.result.status.value}/{run.cpu_time:.1f}s")
                print(sim, name, f"final {run.check['norm2']:.3f} stealthy {run.check['stealthy']} cpu {cpu:.1f}",
                      " ".join(trace), flush=True)
    print(f"# load at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    sys.exit(main())
