"""One identification + CE LQR certificate (T = 100) at delta 0.0035 on the reproduction's first three data sets, by
mechanism affine (twice: cold, then warm with the fit's second-order forms and their bounds cached per data set) and
by directional (each alone, with its re-check): CPU (process_time) and wall seconds, load."""
import os
import time

import bilevel as bl
from bilevel.experiments.certify import certify_tasks
from bilevel.problems.identification_instance import attack_instance

for task in certify_tasks(32, False, 0, 10000, ("ident",))[:3]:
    atk = attack_instance("ss", 100, 0.0, "ce-lqr", seed=task["seed"])
    for mechanism, label in (("affine", "affine-cold"), ("affine", "affine-warm"), ("directional", "directional")):
        load, cpu, wall = os.getloadavg()[0], time.process_time(), time.perf_counter()
        cert = bl.certify(atk, 0.0035, mechanisms=(mechanism,))
        print(task["seed"], label, cert.proof.value, "cpu %.2f wall %.2f load %.1f"
              % (time.process_time() - cpu, time.perf_counter() - wall, load), flush=True)
