"""Run the authors' own stealthy-attack code (Russo & Proutiere 2023, rssalessio/data-poisoning-linear-systems,
example_stealthy_attack/algorithm.py: ComputeAttack, SLSQP with torch derivatives) on their published data sets, one
process, and print one JSON line per attack. Nothing of theirs is copied: their module is imported from AUTHORS_DIR.

It needs their environment (torch on CPU, numpy, scipy, momentchi2; see docs/identification.md) and is started by
benchmarks/bench_identification_authors.py with that environment's python. The start is their driver's (_compute in
algorithm.py): numpy.random.seed(seed), then x0 and u0 at 1e-5 times standard normals, drawn once per data set and
used for every delta. Their compute() writes its scipy OptimizeResult to results/SLSQP/T/ under the working
directory, which this runner sets to a scratch folder and reads back. One torch and BLAS thread (threads are set by
the parent through OMP_NUM_THREADS and the like; torch.set_num_threads(1) here), CPU time by time.process_time.

Usage: python authors_slsqp_runner.py AUTHORS_DIR DATA_DIR T SIMS DELTAS [SEED]
(SIMS and DELTAS comma-separated, e.g. 0,1,2 and 0.01,0.05).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import pickle
import sys
import tempfile
import time


def main(authors_dir: str, data_dir: str, T: int, sims: list[int], deltas: list[float], seed: int = 0) -> None:
    sys.path.insert(0, os.path.abspath(authors_dir))
    import numpy as np
    import torch

    import algorithm  # the authors' module (imports their utils)

    torch.set_num_threads(1)
    algorithm.T = T  # their obj_function and _compute_problem read the module-level T their __main__ sets
    data_dir = os.path.abspath(data_dir)
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        os.makedirs(f"results/SLSQP/{T}")
        for sim in sims:
            with open(os.path.join(data_dir, f"data_{T}timesteps_{sim}.pkl"), "rb") as fh:
                data = pickle.load(fh)
            np.random.seed(seed)
            x0 = 1e-5 * np.random.normal(size=(data.X.shape[0] * (data.U.shape[1] + 1)))
            u0 = 1e-5 * np.random.normal(size=(data.U.shape[0] * data.U.shape[1]))
            sigma_w = np.diag([data.std_w ** 2] * data.X.shape[0])
            for delta in deltas:
                cpu, wall = time.process_time(), time.perf_counter()
                with contextlib.redirect_stdout(io.StringIO()):  # they print every evaluation
                    attack = algorithm.ComputeAttack(data.X, data.U, sigma_w)
                    attack.compute(x0, u0, sim, seed, delta)
                cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
                with open(f"results/SLSQP/{T}/results_{sim}_{seed}_{delta}.pickle", "rb") as fh:
                    res = pickle.load(fh)
                print(json.dumps({"T": T, "sim": sim, "delta": delta, "seed": seed, "cpu_time": cpu,
                                  "wall_time": wall, "iterations": int(res.nit), "status": int(res.status),
                                  "message": str(res.message), "x": np.asarray(res.x, float).tolist()}), flush=True)


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], a[1], int(a[2]), [int(s) for s in a[3].split(",")], [float(d) for d in a[4].split(",")],
         int(a[5]) if len(a) > 5 else 0)
