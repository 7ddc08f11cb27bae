"""certify: a family's mechanisms, cheapest first, until one proves or refutes at a budget; certified_margin: the
largest budget proven safe (bisection with certificates) next to the smallest budget the project's attack reaches
(bilevel.attacks.budget_search)."""

from __future__ import annotations

import math
import time
from typing import Any, Sequence

from ..defaults import param
from ..errors import ModelError
from ..attacks.budget_search import smallest_budget
from ..threads import single_threaded
from .target import Target, as_target, mechanisms_of
from .verdict import Evidence, Margin, Proof, RobustnessCertificate, proof_of

DECISIVE = (Proof.PROVEN, Proof.REFUTED)


def _claim(target: Target, delta: float | None, evidence: list[Evidence], proof: Proof) -> str:
    """The certificate's claim in words: the deciding evidence's claim, or why nothing was decided."""
    deciding = [e for e in evidence if e.holds and e.proof is proof]
    if deciding:
        return deciding[0].claim
    failed = [e.mechanism for e in evidence if e.proof is not Proof.UNKNOWN and not e.check.passed]
    at = "" if delta is None else f" at delta = {delta:.6g}"
    if failed:
        return f"unknown{at}: the evidence of {', '.join(failed)} failed its independent re-check"
    tried = ", ".join(e.mechanism for e in evidence) or "none applied"
    return f"unknown{at}: no mechanism proved or refuted ({tried})"


def certify(declaration: Any, delta: float | None = None, *, mechanisms: Sequence[str] | None = None,
            options: dict[str, Any] | None = None) -> RobustnessCertificate:
    """The robustness certificate of `declaration` (a registered attack instance, a BilevelProblem or a Target:
    as_target) at budget delta (None for a generic problem: its own budget set): the family's mechanisms (or those
    named) run cheapest first and the chain stops at the first re-checked proof or refutation."""
    target = as_target(declaration)
    if delta is not None and not (math.isfinite(delta) and delta > 0):
        raise ModelError(f"certify: delta must be a positive budget, got {delta}")
    if delta is None and target.family != "generic":
        raise ModelError(f"certify: target {target.name!r} needs a budget delta (e.g. 0.01)")
    chosen = mechanisms_of(target.family, mechanisms)
    if not chosen:
        raise ModelError(f"no certificate mechanism is registered for family {target.family!r}")
    t0 = time.perf_counter()
    evidence: list[Evidence] = []
    with single_threaded():  # small dense algebra: one BLAS thread is faster, much faster on a loaded machine
        for mechanism in chosen:
            found = mechanism.fn(target, delta, dict(options or {}))
            if found is not None:
                evidence.append(found)
                if found.holds and found.proof in DECISIVE:
                    break
    proof = proof_of(evidence)
    bounds = [e.numbers["bound"] for e in evidence if e.holds and "bound" in e.numbers]
    return RobustnessCertificate(target.name, delta, proof, _claim(target, delta, evidence, proof), tuple(evidence),
                                 time.perf_counter() - t0, min(bounds) if bounds else None)


def attack_bound(target: Target, seed: int = 0, rel_tol: float | None = None) -> tuple[float, tuple, float]:
    """(delta_ub, the runs (budget, true spectral radius), seconds): the project's budget search with the target's
    first attack, each poisoning judged by the numpy re-fit's true loop (spectral radius >= 1: destabilized)."""
    if not target.attacks or not target.path:
        raise ModelError(f"target {target.name!r} has no attack to bound the margin from above")
    t0 = time.perf_counter()
    attack = next(iter(target.attacks.values()))
    found = smallest_budget(lambda d: target.true_radius(attack(d, seed)), lambda rho: rho >= 1.0, target.path,
                            param("robust.attack_rel_tol", rel_tol))
    return found.delta, tuple(found.runs), time.perf_counter() - t0


def certified_margin(declaration: Any, *, seed: int = 0, delta_ub: float | None = None,
                     rel_tol: float | None = None, mechanisms: Sequence[str] | None = None,
                     options: dict[str, Any] | None = None) -> Margin:
    """delta_lb, the largest budget proven safe by `certify` (bisection on [0, delta_ub] to a bracket of rel_tol
    times its top), next to delta_ub, the attack's smallest destabilizing budget (attack_bound; or the delta_ub
    given, e.g. from an earlier run). Bisection assumes a proof at delta also holds below it (true of the balls'
    nesting: a set of poisonings proven safe contains every smaller one, and the mechanisms' bounds grow with delta)."""
    target = as_target(declaration)
    runs: tuple = ()
    seconds_ub = 0.0
    if delta_ub is None:
        delta_ub, runs, seconds_ub = attack_bound(target, seed)
    top = delta_ub if math.isfinite(delta_ub) else max(target.path, default=1.0)
    tol = param("robust.margin_rel_tol", rel_tol)
    t0 = time.perf_counter()
    low, best = 0.0, None
    high = top
    while high - low > tol * high and high > param("robust.smallest_delta") * top:
        mid = 0.5 * (low + high) if low > 0 else high / 2.0
        cert = certify(target, mid, mechanisms=mechanisms, options=options)
        if cert.proven:
            low, best = mid, cert
        else:
            high = mid
    return Margin(target.name, low, float(delta_ub), best, runs, time.perf_counter() - t0, seconds_ub)
