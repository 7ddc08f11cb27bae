"""Which term of the VRFT certificate's remainder stops the proof? On the reproduction's first data sets (N = 512,
delta_ub from docs/results/certify/certify.csv), delta_lb by bisection (2 %, no re-check; none of the variants but
the first is a proof) with one ingredient set to zero: the bound on ||r(a) - r0|| in the refinement and the joint
bound (resid), its part ||v|| <= ||a_u|| ||t(.)|| + ||a_y|| ||Phi(.) theta0|| alone (norm_t, norm_f), the set's
extents' term sum_k c_k ||H(V_k)'Q g|| (HQ, HVQ), the first outer sets' radii (the expansion's ball and box, the
damped split's balls), and all of them (the linear image alone). CPU seconds, load."""
import dataclasses, os, sys, time

import numpy as np

import bilevel.robust.vrft as V
from bilevel.problems.vrft_instance import attack_instance
from bench_vrft_regressor_floor import bisect, vrft_512  # benchmarks/ (the script's directory) is on sys.path


def proves(atk, P, known, delta, resid=1.0, radii=1.0):
    refined, joint_refined, remainder = V._refined, V._joint_refined, V.remainder
    V._refined = lambda P_, ru, ry, r, before: refined(P_, ru, ry, r * resid, before)
    V._joint_refined = lambda P_, ru, ry, r, before, j: joint_refined(P_, ru, ry, r * resid, before, j)

    def scaled(P_, d, floor=0.0):
        rem = remainder(P_, d, floor)
        if radii == 1.0 or not rem.floor > 0:
            return rem
        return dataclasses.replace(rem, ball=rem.ball * radii, box=rem.box * radii, rem_v=rem.rem_v * radii,
                                   sat_v=rem.sat_v * radii, rem_r=rem.rem_r * radii, sat_r=rem.sat_r * radii,
                                   rest=rem.rest * radii)
    V.remainder = scaled
    try:
        W, keys = V.critical(atk, P, delta)
        _, _, found = V._sweep(atk, P, delta, joint=V.joint_norms(P, W, V._eig_norm, keys, known))
        return found is not None and found.proven
    finally:
        V._refined, V._joint_refined, V.remainder = refined, joint_refined, remainder


tasks, ub = vrft_512(int(sys.argv[1]) if len(sys.argv) > 1 else 2)
for task in tasks:
    atk = attack_instance("destabilize", "B", 0.0, 0.0, seed=task["seed"], N=512)
    _, P, known = V._entry(atk)
    flat = dataclasses.replace(P, HQ=np.zeros_like(P.HQ), HVQ=np.zeros_like(P.HVQ))
    no_v = dataclasses.replace(P, norm_t=0.0, norm_f=0.0)
    top = ub[task["seed"]]
    variants = (("as built (a proof)", P, {}), ("resid 0", P, {"resid": 0.0}), ("resid's ||v|| part 0", no_v, {}),
                          ("extents' term 0", flat, {}), ("first sets' radii 0", P, {"radii": 0.0}),
                          ("resid and extents' term 0", flat, {"resid": 0.0}),
                          ("all 0 (linear image)", flat, {"resid": 0.0, "radii": 0.0}))
    for label, Pv, kw in [v for v in variants if len(sys.argv) < 3 or v[0] in sys.argv[2].split(";")]:
        c = time.process_time()
        lb = bisect(lambda d: proves(atk, Pv, known if Pv is P else {}, d, **kw), top)
        print(f"data seed {task['seed']} (delta_ub {top:.5g}): {label}: delta_lb {lb:.5g}, ratio {top / lb:.3g} "
              f"({time.process_time() - c:.0f} CPU s, load {os.getloadavg()[0]:.1f})", flush=True)
