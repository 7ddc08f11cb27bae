"""The alternating VRFT attack on many instances at once: its batched form for bilevel.solvers.batch.solve_many (the
instances, objectives, budgets and limits, handed to the engine's batched exact-input-step ascent,
bilevel.solvers.engine.block_exact_batch, over the learners' stacked affine least squares), and attack_many /
attack_budget_paths, the batched counterparts of vrft_methods.attack and attack_budget_path. Instances that the batched
form does not cover (no exact input step, l1 or sparse budgets, a time limit, verbose) run one at a time.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from ..defaults import param
from ..errors import ModelError, SolverFailed
from ..model import BilevelProblem
from ..problems.vrft import _load, instance_of, problem_for
from ..problems.vrft_instance import VRFTAttack
from ..result import BilevelResult
from ..solvers.batch import BatchMethod, in_groups, register_batch, solve_many
from ..solvers.engine.affine_ls import Oracle
from ..solvers.engine.affine_ls_batch import AffineLSBatch, BatchMaps, BatchOracle, TargetBlockBatch, UpperBatch
from ..solvers.engine.block_exact_batch import (BatchInstance, ascend_with_exact_block_batch, batch_instance,
                                                batch_probe_parts, conditioning_starts)
from ..solvers.engine.prepared import MethodRun, Prepared, check_options
from ..solvers.verdict.batch_probe import ProbeParts
from .vrft_methods import METHODS, alternating


class Gathered(NamedTuple):
    """One loaded instance of the alternating attack: the instance and its view for the engine's batched ascent."""

    atk: VRFTAttack
    inst: BatchInstance


def gather(prep: Prepared, options: dict[str, Any]) -> Gathered | None:
    """The batched alternating attack's view of the loaded instance, or None where it runs alone (no exact input
    step, a budget the declaration relaxes, a_y's set not a plain l2 ball, time_limit or verbose)."""
    check_options("alternating", options, alternating)
    if options.get("time_limit") is not None or options.get("verbose"):
        return None
    atk = instance_of(prep.problem)
    if atk.no_exact_input or atk.searched is not None:
        return None
    inst = batch_instance(prep, atk.N, int(param("vrft.starts", options.get("starts"))), options.get("seed", 0),
                          Oracle(atk.learner, atk.upper, atk.conditioning_key).hessian_parts, atk.delta_y,
                          int(param(f"vrft.max_iter.{atk.objective}", options.get("max_iter"))),
                          float(param("vrft.gain_tol", options.get("gain_tol"))), lower_solve=atk.learner.thetas)
    return None if inst is None else Gathered(atk, inst)


def run(gathered: list[Gathered], options: dict[str, Any]) -> list[MethodRun]:
    """The alternating attack's runs of the gathered instances, those sharing a learner design and limits in one
    batched ascent (of at most defaults["batch.max_rows"] instances at a time); instances without an input budget
    (delta_u 0) apart from the others, so that their evaluations skip the input block's step (TargetBlockBatch.solve)."""
    atks = [g.atk for g in gathered]
    conditioning_starts([g.inst for g in gathered], lambda i: (id(atks[i].setting.regressor), atks[i].N),
                        lambda idx: _learner([atks[i] for i in idx]))
    return in_groups(gathered, lambda g: (id(g.atk.setting.regressor), g.atk.N, g.atk.objective, g.inst.max_iter,
                                          g.inst.gain_tol, g.atk.delta_u == 0),
                     lambda part: ascend_with_exact_block_batch(_oracle([g.atk for g in part]), [g.inst for g in part]))


def _maps(atk: VRFTAttack) -> BatchMaps:
    """The VRFT regressor's filters and prefilter on stacked signals."""
    reg, N = atk.setting.regressor, atk.N
    lagged = (reg.stack_signals, reg.stack_lags) if reg.lags_are_regressors else (None, None)
    if reg.prefilter is None:
        return BatchMaps(reg.stack, reg.stack_adjoint, None, None, reg.stack_adjoint_outer, *lagged)

    def target_adjoints(G: np.ndarray) -> np.ndarray:  # (m, rows, p) -> (m, N, p): every column in one call
        m, rows, p = G.shape
        cols = reg.targets_adjoint(np.transpose(G, (1, 0, 2)).reshape(rows, m * p), N)
        return np.transpose(cols.reshape(N, m, p), (1, 0, 2))

    return BatchMaps(reg.stack, reg.stack_adjoint, reg.stack_targets, target_adjoints, reg.stack_adjoint_outer, *lagged)


def _stacked(atks: Sequence[VRFTAttack]) -> tuple[np.ndarray, np.ndarray]:
    """The instances' clean regressors and targets, stacked (m x rows x k, m x rows)."""
    return np.stack([a.phi0 for a in atks]), np.stack([a.t0 for a in atks])


def upper_batch(atks: Sequence[VRFTAttack], phi0: np.ndarray, t0: np.ndarray) -> UpperBatch:
    """J of the quadratic objectives (VRFTAttack.value, grad_theta, upper.hessian) of the instances (rows: their
    indices), phi0 and t0 their _stacked data."""
    objective, k = atks[0].objective, atks[0].theta0.size
    if objective == "maxmin":
        gram, cross = np.stack([a.gram0 for a in atks]), np.stack([a.cross0 for a in atks])
        n = float(atks[0].n)

        def value(rows: np.ndarray, theta: np.ndarray) -> np.ndarray:
            r = t0[rows] - (phi0[rows] @ theta[:, :, None])[:, :, 0]
            return np.sum(r * r, axis=1) / n

        def gradient(rows: np.ndarray, theta: np.ndarray) -> np.ndarray:
            return -2.0 / n * (cross[rows] - np.einsum("mij,mj->mi", gram[rows], theta))

        return UpperBatch(value, gradient, 2.0 * gram / n)
    if objective == "targeted":
        target = np.stack([a.theta_target for a in atks])
        return UpperBatch(lambda rows, theta: -np.sum((target[rows] - theta) ** 2, axis=1) / k,
                          lambda rows, theta: 2.0 / k * (target[rows] - theta),
                          np.broadcast_to(-2.0 * np.eye(k) / k, (len(atks), k, k)))
    raise ModelError(f"the batched alternating attack needs a quadratic objective, not {objective!r}")


def _learner(atks: Sequence[VRFTAttack]) -> AffineLSBatch:
    """The instances' learners, stacked (one design), with the clean data's signals where the regressors are their lags
    and the instances' phi0 are those lags (checked once here)."""
    maps, (phi0, t0) = _maps(atks[0]), _stacked(atks)
    S0 = None if maps.signals is None else maps.signals(np.stack([a.y for a in atks]))
    if S0 is not None and not np.array_equal(maps.lags(S0), phi0):
        S0 = None
    return AffineLSBatch(phi0, t0, maps, atks[0].N, atks[0].N, S0)


def _oracle(atks: Sequence[VRFTAttack]) -> BatchOracle:
    """The instances' attack as the engine's batched oracle: the input poisoning a at its optimum for each a_y."""
    learner = _learner(atks)
    return BatchOracle(TargetBlockBatch(learner, upper_batch(atks, learner.C0, learner.d0),
                                        np.array([a.delta_u for a in atks])))


def probe_parts(gathered: list[Gathered], runs: list[MethodRun]) -> ProbeParts:
    """What the verdict's batched probe needs of the gathered instances (the engine's batch_probe_parts)."""
    return ProbeParts(*batch_probe_parts(_oracle([g.atk for g in gathered]), [g.inst for g in gathered], runs))


BATCHED = BatchMethod(gather, run, probe_parts)
register_batch(alternating, BATCHED)


def _loader(atk: VRFTAttack, warm: np.ndarray | None) -> Callable[[BilevelProblem], None]:
    def load(problem: BilevelProblem) -> None:
        _load(problem, atk)
        if warm is not None:
            problem.suggest_start(a_y=atk.budget_y.projection(atk.y)(np.asarray(warm, dtype=float)))
    return load


def attack_many(atks: Sequence[VRFTAttack], method: str = "alternating", seeds: Sequence[Any] | None = None,
                warm_starts: Sequence[np.ndarray] | None = None, **options: Any) -> list[BilevelResult]:
    """vrft_methods.attack(atks[i], method, warm_starts[i], seed=seeds[i], **options) for every i, the instances of
    one declared problem solved together (bilevel.solvers.batch.solve_many); results in order, each with its
    instance's stats. A batched attack's wall time is its share of the batch plus its own verdict."""
    if method not in METHODS:
        raise ModelError(f"attack {method!r} is not one of {', '.join(METHODS)}")
    seeds = [options.pop("seed", 0)] * len(atks) if seeds is None else list(seeds)
    warm = [None] * len(atks) if warm_starts is None else list(warm_starts)
    if len(seeds) != len(atks) or len(warm) != len(atks):
        raise ModelError(f"attack_many: {len(atks)} instances, {len(seeds)} seeds, {len(warm)} warm starts")
    for w, atk in zip(warm, atks):
        if w is not None and np.shape(w) != (atk.N,):
            raise ModelError(f"warm_start must have shape ({atk.N},), got {np.shape(w)}")
    groups: dict[int, tuple[BilevelProblem, list[int]]] = {}
    for i, atk in enumerate(atks):
        problem = problem_for(atk, load=False)  # solve_many loads each instance
        groups.setdefault(id(problem), (problem, []))[1].append(i)
    out: list[BilevelResult | None] = [None] * len(atks)
    for problem, idx in groups.values():
        for flag in (False, True):  # with and without a warm start: one more start for those with one
            part = [i for i in idx if (warm[i] is not None) == flag]
            if not part:
                continue
            opts = dict(options)
            if flag:
                opts["starts"] = param("vrft.starts", options.get("starts")) + 1
            results = solve_many(problem, [_loader(atks[i], warm[i]) for i in part], METHODS[method],
                                 each=[{"seed": seeds[i]} for i in part], **opts)
            for i, res in zip(part, results):
                out[i] = _attack_result(atks[i], res, method)
    return out  # type: ignore[return-value]


def _attack_result(atk: VRFTAttack, result: BilevelResult, name: str) -> BilevelResult:
    """attack_result's additions (bilevel.attacks.outcome) to a solve_many result."""
    if result.certificate is None:
        raise SolverFailed(f"{name} attack: {result.status.value}: {result.message}", result=result)
    stats = {**atk.stats(result.y["theta"]),
             "evaluations": sum(s.get("evaluations", 0) for s in result.start_records) or 1}
    return dataclasses.replace(result, method=name, stats={**result.stats, **stats})


def attack_budget_paths(atks: Sequence[VRFTAttack], eps_y: Sequence[float], seeds: Sequence[Any] | None = None,
                        **options: Any) -> list[list[BilevelResult]]:
    """vrft_methods.attack_budget_path for every instance, each budget's attacks solved together (attack_many)."""
    if any(atk.objective == "destabilize" for atk in atks):
        raise ModelError("the budget path runs the alternating attack; 'destabilize' needs attack_joint")
    if len(eps_y) == 0:
        raise ModelError("attack_budget_paths needs at least one output budget eps_y, e.g. [0.02, 0.05, 0.1]")
    paths: list[list[BilevelResult]] = [[] for _ in atks]
    for eps in sorted(eps_y):
        stage = [dataclasses.replace(atk, budget_y=dataclasses.replace(atk.budget_y, eps=eps)) for atk in atks]
        warm = [p[-1].x["a_y"] for p in paths] if paths and paths[0] else None
        for path, res in zip(paths, attack_many(stage, "alternating", seeds, warm, **options)):
            path.append(res)
    return paths
