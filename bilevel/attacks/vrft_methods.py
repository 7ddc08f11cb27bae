"""Structured attacks on a VRFT instance, methods of `bilevel.solve` (its finalize: independent re-solve, probe) on
its declared problem vrft-<objective>, the learner an affine least squares (bilevel.solvers.engine.affine_ls):
alternating (the paper's Algorithm 1, strengthened) ascends V(a_y) = max_{a_u} J(theta(u + a_u, y + a_y)), the inner
max solved globally at every evaluation (the exact input step; quadratic objectives, plain l2 input budget); joint
ascends (a_u, a_y) together, each block in its budget radius; white-noise: a random point on the budget boundary."""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Sequence

import numpy as np

from ..defaults import param
from ..errors import ModelError
from ..problems.vrft import instance_of, problem_for
from ..problems.vrft_instance import VRFTAttack
from ..reduction import KKTPoint
from ..result import BilevelResult, Status
from ..solvers.engine.affine_ls import Oracle, TargetBlock
from ..solvers.engine.prepared import MethodRun, Prepared, check_options
from ..solvers.engine.block_exact import ascend_with_exact_block
from .outcome import attack_result, attack_stat


def _ascend(prep: Prepared, joint: bool, starts: int | None, seed: Any, max_iter: int | None, gain_tol: float | None,
            time_limit: float | None, verbose: bool) -> MethodRun:
    """The engine's multistart ascent on the problem's VRFT instance, with the exact input step unless `joint`; None
    takes the registry's value."""
    atk = instance_of(prep.problem)
    step = None
    if not joint:
        if why := atk.no_exact_input:
            raise ModelError(f"the alternating attack needs the exact input step: {why}; use the joint attack")
        step = TargetBlock(atk.learner, atk.upper, next(b for b in prep.balls if b.block.start == 0), atk.delta_u)
    weights = np.concatenate([np.full(atk.N, atk.delta_u), np.full(atk.N, atk.delta_y)])
    run = ascend_with_exact_block(prep, step, [], starts=param("vrft.starts", starts), seed=seed,
                                  max_iter=param(f"vrft.max_iter.{atk.objective}", max_iter),
                                  gain_tol=param("vrft.gain_tol", gain_tol), time_limit=time_limit, verbose=verbose,
                                  oracle=Oracle(atk.learner, atk.upper, atk.conditioning_key),
                                  projection=atk.searched, weights=weights)
    return dataclasses.replace(run, lower_solve=atk.learner.thetas)  # the local probe's lower solve


def alternating(prep: Prepared, *, starts: int | None = None, seed: Any = 0, max_iter: int | None = None,
                gain_tol: float | None = None, time_limit: float | None = None, verbose: bool = False,
                **unknown: Any) -> MethodRun:
    """The alternating attack (module docstring). None takes the registry's value, defaults["vrft.NAME"] (max_iter:
    "vrft.max_iter.<objective>"). starts: multistart starts; seed: random starts' seed; max_iter: ascent steps per
    start; gain_tol: the ascent stops when its relative gain over its window of steps is below it; time_limit
    (seconds): the starts not begun are skipped; verbose: progress lines on stderr."""
    check_options("alternating", unknown, alternating)
    return _ascend(prep, False, starts, seed, max_iter, gain_tol, time_limit, verbose)


def joint(prep: Prepared, *, starts: int | None = None, seed: Any = 0, max_iter: int | None = None,
          gain_tol: float | None = None, time_limit: float | None = None, verbose: bool = False,
          **unknown: Any) -> MethodRun:
    """The joint attack (module docstring); starts, seed, max_iter, gain_tol, time_limit, verbose: as `alternating`."""
    check_options("joint", unknown, joint)
    return _ascend(prep, True, starts, seed, max_iter, gain_tol, time_limit, verbose)


def white_noise(prep: Prepared, *, seed: Any = 0, **unknown: Any) -> MethodRun:
    """White-noise poisoning drawn from `seed` on the budget boundary of the problem's VRFT instance (the paper's
    random baseline)."""
    check_options("white-noise", unknown, white_noise)
    atk = instance_of(prep.problem)
    rng = np.random.default_rng(seed)
    signals = []
    for budget, signal, radius in ((atk.budget_u, atk.u, atk.delta_u), (atk.budget_y, atk.y, atk.delta_y)):
        z = rng.standard_normal(atk.N)
        signals.append(budget.projection(signal)(z * radius / max(np.linalg.norm(z, budget.order), 1e-300)))
    theta = atk.learner.fit(*signals).theta
    return MethodRun(prep.pack(KKTPoint(np.concatenate(signals), theta, np.zeros(0), np.zeros(0), [])),
                     Status.INACCURATE, "a sample at the budget (a baseline, not an optimizer)",
                     feasible_set=atk.searched, lower_solve=atk.learner.thetas)


METHODS: dict[str, Callable[..., MethodRun]] = {"alternating": alternating, "joint": joint, "white-noise": white_noise}
"""The structured methods by name: function(prepared, **options) -> MethodRun on a problem from problem_for."""


def attack(atk: VRFTAttack, method: str | Callable[..., MethodRun], warm_start: np.ndarray | None = None,
           **options: Any) -> BilevelResult:
    """A structured method (a name in METHODS, or a function(prepared, **options) -> MethodRun) on instance `atk`
    through the engine's solve, warm_start (an a_y) one more start; the instance's stats (VRFTAttack.stats)."""
    t0 = time.perf_counter()
    if not callable(method) and method not in METHODS:
        raise ModelError(f"attack {method!r} is not one of {', '.join(METHODS)}")
    problem = problem_for(atk)
    if warm_start is not None:
        if np.shape(warm_start) != (atk.N,):
            raise ModelError(f"warm_start must have shape ({atk.N},), got {np.shape(warm_start)}")
        problem.suggest_start(a_y=atk.budget_y.projection(atk.y)(np.asarray(warm_start, dtype=float)))
        options["starts"] = param("vrft.starts", options.get("starts")) + 1
    return attack_result(problem, method if callable(method) else METHODS[method],
                         method if isinstance(method, str) else None,
                         lambda r: {**atk.stats(r.y["theta"]),  # evaluations: a white-noise sample is one
                                    "evaluations": sum(s.get("evaluations", 0) for s in r.start_records) or 1},
                         t0, **options)


def attack_alternating(atk: VRFTAttack, warm_start: np.ndarray | None = None, **options: Any) -> BilevelResult:
    """The alternating attack (module docstring) on `atk`, with the options of method `alternating` (show_options).
    V(a_y) is multimodal: the engine's first start makes the poisoned regressor ill-conditioned, further starts are
    seeded random points, and warm_start (an a_y, e.g. the best one at a smaller budget) is one more."""
    return attack(atk, "alternating", warm_start, **options)


def attack_joint(atk: VRFTAttack, **options: Any) -> BilevelResult:
    """The joint attack (module docstring) on `atk`, with the options of method `joint` (show_options)."""
    return attack(atk, "joint", **options)


def attack_white_noise(atk: VRFTAttack, seed: int = 0) -> BilevelResult:
    """White-noise poisoning of `atk` on the budget boundary (the paper's random baseline)."""
    return attack(atk, "white-noise", seed=seed)


def attack_budget_path(atk: VRFTAttack, eps_y: Sequence[float], **options: Any) -> list[BilevelResult]:
    """attack_alternating at each output budget eps_y in increasing order (same data and a_u budget), from the second
    on with the previous best a_y as one more start: V grows with the budget along the path, as it must."""
    if atk.objective == "destabilize":
        raise ModelError("the budget path runs the alternating attack; 'destabilize' needs attack_joint")
    if len(eps_y) == 0:
        raise ModelError("attack_budget_path needs at least one output budget eps_y, e.g. [0.02, 0.05, 0.1]")
    results: list[BilevelResult] = []
    for eps in sorted(eps_y):
        stage = dataclasses.replace(atk, budget_y=dataclasses.replace(atk.budget_y, eps=eps))
        results.append(attack_alternating(stage, warm_start=results[-1].x["a_y"] if results else None, **options))
    return results


def attack_value(result: BilevelResult) -> float:
    """The attack's own criterion at the poisoned theta (maximized): -distance for 'targeted', the log-sum-exp
    of the modelled poles for 'destabilize'; upper_objective is the registered problem's F."""
    return attack_stat(result, "value")
