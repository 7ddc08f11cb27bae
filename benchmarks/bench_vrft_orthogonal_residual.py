"""VRFT delta_lb with the refinement's ||r(a) - r0|| bounded as sqrt(||P_a r0||^2 + ||(I - P_a) v||^2) (two orthogonal
parts) instead of their sum, the critical directions picked over both sets (vrft.critical; at commit 845de10 over the
smaller set alone, results/bench_vrft_orthogonal_residual.txt's first run):
certified_margin (with re-checks) below the reproduction's delta_ub (docs/results/certify/certify.csv) on its first
data sets at N = 512, then 10,000 budget-sphere poisonings at the new delta_lb and the target's attacks there
(sample_soundness: the joint attack with 8 starts, white noise; the 64-start attack is left to the reproduction).
CPU seconds of one certificate at the new delta_lb (warm), load."""
import csv, os, sys, time

import bilevel as bl
from bilevel.experiments.certify import certify_tasks
from bilevel.problems.vrft_instance import attack_instance
from bilevel.robust import as_target, sample_soundness

rows = {int(r["data_seed"]): r for r in csv.DictReader(open("docs/results/certify/certify.csv"))
        if r["family"] == "vrft" and r["size"] == "512"}
count = int(sys.argv[1]) if len(sys.argv) > 1 else 3
samples = int(sys.argv[2]) if len(sys.argv) > 2 else 10000
print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()}")
for task in [t for t in certify_tasks(32, False, 0, 10000, ("vrft",)) if t["size"] == 512][:count]:
    atk = attack_instance("destabilize", "B", 0.0, 0.0, seed=task["seed"], N=512)
    target = as_target(atk, starts=8)
    before = float(rows[task["seed"]]["delta_lb"])
    top = float(rows[task["seed"]]["delta_ub"])
    c = time.process_time()
    margin = bl.certified_margin(target, seed=task["attack_seed"], delta_ub=top)
    spent = time.process_time() - c
    c = time.process_time()
    cert = bl.certify(target, margin.delta_lb)
    one = time.process_time() - c
    check = sample_soundness(as_target(atk, starts=8), margin.delta_lb, samples, seed=task["attack_seed"])
    print(f"data seed {task['seed']}: delta_lb {margin.delta_lb:.5g} (committed {before:.5g}, "
          f"x{margin.delta_lb / before:.3f}), delta_ub {top:.5g}, ratio {top / margin.delta_lb:.3g} "
          f"(committed {top / before:.3g}); certificate at delta_lb "
          f"{cert.proof.value}, re-check {cert.evidence[0].check.passed}, {one:.2f} CPU s warm; "
          f"bisection {spent:.0f} CPU s;"
          f" {check.samples} sphere poisonings and the attacks: unstable {check.unstable}, largest radius "
          f"{check.worst_radius:.4f}, attacks' {max(check.attack_radius.values()):.4f}; load {os.getloadavg()[0]:.1f}",
          flush=True)
