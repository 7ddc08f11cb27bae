"""Scratch harness of bench_ident_gain_set_limits (benchmarks/results/bench_ident_gain_set_limits.txt): affine's gain set at a
budget without re-checks, and a bisection of zero exclusion over it with the set's support replaced by a variant."""
import sys, time, os
import numpy as np
import bilevel.robust.identification as I
from bilevel.experiments.certify import certify_tasks
from bilevel.problems.identification_instance import attack_instance
from bilevel.problems.identification_instance import least_squares_fit
from bilevel.robust.zero_exclusion import sweep

def parts(atk, delta):
    A, B = atk.setting.state_space
    Y0, Z0 = atk.regression(atk.signals)
    c = I.clean(atk, least_squares_fit(Y0, Z0))
    maps = I.model_maps(atk)
    E1, Wmap = I.riccati_maps(c)
    in_model, in_gain = I.second_parts(atk, c, Wmap, delta)
    shape = I.model_shape(atk, delta, maps, ball=True, second=in_model)
    found = I.affine_sandwich(atk, c, shape, E1, Wmap)
    if found is None:
        return None
    gains = I.affine_gain_set(atk, c, delta, shape, found, maps, E1, Wmap, in_gain)
    return c, gains

def proves(atk, delta, variant=None):
    A, B = atk.setting.state_space
    p = parts(atk, delta)
    if p is None: return False, None
    c, gains = p
    if variant: gains = variant(atk, c, gains)
    if not gains.m_lo > 0: return False, gains
    swept = sweep(*I.loop_polynomial(A, B, c.K0), gains.support, I.GRID, I.ANGLES)
    return swept.proven, gains

def bisect(atk, lo, hi, variant=None, tol=0.02):
    while hi / lo > 1 + tol:
        mid = np.sqrt(lo * hi)
        ok, _ = proves(atk, mid, variant)
        if ok: lo = mid
        else: hi = mid
    return lo

def data(i):
    task = certify_tasks(32, False, 0, 10000, ("ident",))[i]
    return task, attack_instance("ss", 100, 0.0, "ce-lqr", seed=task["seed"])
