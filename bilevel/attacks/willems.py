"""Attacks on the De Persis–Tesi learners (WillemsAttack, bilevel.problems.willems_instance) as `bilevel.solve` runs
on the attack's shared problem (WillemsAttack.shared_problem; its radius form for destabilize_attack), the learner with
the attack's selection: the engine's oracle, methods and finalize (independent re-solve, local probe). Each result
carries WillemsAttack.stats (gain, true and identified radius)."""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Sequence

import numpy as np

from ..defaults import param
from ..errors import ModelError, SolverFailed
from ..problems.willems_instance import WillemsAttack
from ..result import BilevelResult
from ..solvers.batch import solve_many
from ..solvers.engine.prepared import check_options
from .willems_methods import destabilize, random_signs
from ..threads import single_threaded_call
from .outcome import attack_result


def _goal(attack: WillemsAttack, stop_when_unstable: bool, counter: dict[str, int]) -> Any:
    """The attacker's callback: count evaluations, stop (StopIteration) once the identified loop is unstable, with
    stop_when_unstable or for the max-min criterion (+inf there)."""
    stops = stop_when_unstable or attack.setting.objective == "maxmin"
    last: dict[bytes, float] = {}  # the radius at the last point seen (a method may report one point many times)

    def callback(point: Any) -> None:
        counter["evaluations"] += 1
        if not stops:
            return
        key = np.asarray(point.x, dtype=float).tobytes() + np.asarray(point.y, dtype=float).tobytes()
        if key not in last:
            last.clear()
            last[key] = attack.identified_radius(point.x, point.y)
        if last[key] >= 1.0:
            raise StopIteration
    return callback


def _run(attack: WillemsAttack, name: str, method: Any, radius: bool = False, relearn: bool = False,
         **options: Any) -> BilevelResult:
    """solve(the attack's shared problem, method, options) as attack `name`, with its stats; the whole call's time."""
    t0, counter = time.perf_counter(), {"evaluations": 0}
    if "stop_when_unstable" in options:
        options["callback"] = _goal(attack, options.pop("stop_when_unstable"), counter)
    return attack_result(attack.shared_problem(radius), method, name, lambda r: attack.stats(
        r, int(r.stats.get("evaluations", counter["evaluations"] or 1)), relearn), t0, **options)


@single_threaded_call
def hypergradient_attack(attack: WillemsAttack, *, starts: int | None = None, seed: Any = 0,
                         max_iter: int | None = None, ftol: float | None = None, stop_when_unstable: bool = True,
                         **unknown: Any) -> BilevelResult:
    """Method hypergradient on the attack's criterion from `starts` starts (start 0: clean data; others uniform in the
    box, drawn from `seed`), max_iter steps each, ftol its stop, near-ties between starts to the larger identified
    radius; with stop_when_unstable it stops at the first point whose identified loop is unstable. None takes the
    registry's value, defaults["willems.hypergradient.NAME"]."""
    check_options("hypergradient_attack", unknown, hypergradient_attack)
    prefer = lambda point: attack.identified_radius(point.x, point.y)  # noqa: E731
    return _run(attack, "hypergradient", "hypergradient", starts=param("willems.hypergradient.starts", starts),
                seed=seed, max_iter=param("willems.hypergradient.max_iter", max_iter),
                ftol=param("willems.hypergradient.ftol", ftol), stop_when_unstable=stop_when_unstable, prefer=prefer)


@single_threaded_call
def de_attack(attack: WillemsAttack, *, seed: Any = 0, max_iter: int | None = None, popsize: int | None = None,
              pop_tol: float | None = None, stop_when_unstable: bool = True, **unknown: Any) -> BilevelResult:
    """Method differential-evolution (seed, max_iter generations of popsize members per entry, pop_tol its stop) on
    the input poisoning, without its descent (a heuristic), a generation scored at once where the learner ignores the
    poisoning (WillemsAttack.criteria); with stop_when_unstable it stops once the incumbent's identified loop is
    unstable. None takes the registry's value, defaults["willems.evolution.NAME"] (pop_tol: "evolution.pop_tol")."""
    check_options("de_attack", unknown, de_attack)
    if attack.setting.poison != "u" or attack.setting.delta_u <= 0:
        raise ModelError(f"de_attack poisons the inputs only (the paper's corollary) with delta_u > 0; got poison="
                         f"{attack.setting.poison!r}, delta_u={attack.setting.delta_u}")
    twin = {} if attack.setting.design == "lqr-r" else {"batch_objective": attack.criteria}
    return _run(attack, "differential-evolution", "differential-evolution", seed=seed,
                max_iter=param("willems.evolution.max_iter", max_iter),
                popsize=param("willems.evolution.popsize", popsize), pop_tol=pop_tol, polish=False,
                stop_when_unstable=stop_when_unstable, **twin)


@single_threaded_call
def random_attack(attack: WillemsAttack, *, seed: Any = 0) -> BilevelResult:
    """A budget-matched, non-adaptive baseline: every poisoned entry +-budget with a fair random sign."""
    return _run(attack, "random", random_signs, seed=seed)


@single_threaded_call
def destabilize_attack(attack: WillemsAttack, *, starts: int | None = None, seed: Any = 0, max_iter: int | None = None,
                       pool: int | None = None, **unknown: Any) -> BilevelResult:
    """Maximize the spectral radius of the attacker's loop A_id + B_id K over the input poisoning, exactly (method
    destabilize on attack.radius_problem: the learner solved once, K affine in the poisoning) with its options starts,
    seed, max_iter and pool, None taking defaults["destabilize.NAME"]."""
    check_options("destabilize_attack", unknown, destabilize_attack)
    if attack.setting.objective != "destabilize":
        raise ModelError(f"destabilize_attack maximizes the spectral radius; got objective="
                         f"{attack.setting.objective!r}: build the attack with objective='destabilize'")
    return _run(attack, "destabilize", destabilize, radius=True, starts=starts, seed=seed, max_iter=max_iter,
                pool=pool)


@single_threaded_call
def destabilize_many(attacks: Sequence[WillemsAttack], seeds: Sequence[Any] | None = None, *,
                     starts: int | None = None, max_iter: int | None = None,
                     pool: int | None = None) -> list[BilevelResult]:
    """destabilize_attack(attacks[i], seed=seeds[i], starts=..., max_iter=..., pool=...) for every i, the attacks of
    one shape solved together (bilevel.solvers.batch.solve_many: each learner solved on loading, every start of every
    attack in one batched ascent, then each attack's verdict); results in order, as destabilize_attack's (the same
    points, values, iterations and evaluations to rounding, willems_methods._values; the wall time a share of the batch
    plus the attack's verdict)."""
    seeds = [0] * len(attacks) if seeds is None else list(seeds)
    if len(seeds) != len(attacks):
        raise ModelError(f"destabilize_many: {len(attacks)} attacks and {len(seeds)} seeds")
    for a in attacks:
        if a.setting.objective != "destabilize":
            raise ModelError(f"destabilize_many maximizes the spectral radius; got objective={a.setting.objective!r}: "
                             "build the attacks with objective='destabilize'")
    groups: dict[tuple, list[int]] = {}
    for i, a in enumerate(attacks):
        groups.setdefault(a.shape, []).append(i)
    out: list[BilevelResult | None] = [None] * len(attacks)
    for idx in groups.values():
        problem = attacks[idx[0]].shared_problem(radius=True)

        def loader(a: WillemsAttack) -> Any:
            def load(p: Any) -> None:
                if a.shared_problem(radius=True) is not p:
                    raise ModelError("destabilize_many: the shared problem of one shape changed during the batch; "
                                     "raise defaults['willems.shared_kept']")
            return load
        given = {k: v for k, v in (("starts", starts), ("max_iter", max_iter), ("pool", pool)) if v is not None}
        results = solve_many(problem, [loader(attacks[i]) for i in idx], destabilize,
                             each=[{"seed": seeds[i]} for i in idx], **given)
        for i, r in zip(idx, results):
            if r.certificate is None:
                raise SolverFailed(f"destabilize attack: {r.status.value}: {r.message}", result=r)
            out[i] = dataclasses.replace(r, method="destabilize", stats={**r.stats, **attacks[i].stats(
                r, int(r.stats.get("evaluations", 1)))})
    return out  # type: ignore[return-value]


@single_threaded_call
def kkt_attack(attack: WillemsAttack, method: str = "ipopt", **options: Any) -> BilevelResult:
    """The generic route: bilevel.solve on the declared problem with a KKT method (reformulation, PSD pairs
    factored); its answer is certified and probed like every attack's; the gain in stats is the learner's, re-solved
    at the answer's poisoning."""
    return _run(attack, f"kkt-{method}", method, relearn=True, **options)
