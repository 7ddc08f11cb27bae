"""The alternating VRFT attack on many instances at once: its batched form for bilevel.solvers.batch.solve_many (the
engine's exact-input-step ascent on the learners' affine least squares, vectorized over instances and starts:
bilevel.solvers.engine.affine_ls_batch, batch_ascent), and attack_many / attack_budget_paths, the batched
counterparts of vrft_methods.attack and attack_budget_path. Instances that the batched form does not cover (no exact
input step, l1 or sparse budgets, a time limit, verbose) run one at a time.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..defaults import param
from ..errors import ModelError, SolverFailed
from ..model import BilevelProblem
from ..problems.vrft import _load, instance_of, problem_for
from ..problems.vrft_instance import VRFTAttack
from ..reduction import KKTPoint
from ..result import BilevelResult
from ..solvers.batch import BatchMethod, register_batch, solve_many
from ..solvers.engine.affine_ls import Oracle
from ..solvers.engine.affine_ls_batch import (AffineLSBatch, BatchMaps, TargetBlockBatch, UpperBatch,
                                              conditioning_descent)
from ..solvers.engine.batch_ascent import Points, batched_projected_ascent
from ..solvers.engine.batch_linalg import project_l2_balls
from ..solvers.engine.block_exact import SINGULAR_LEARNER, multistart_run
from ..solvers.engine.prepared import MethodRun, Prepared, best_of, check_options
from ..solvers.engine.projections import Blocks, NormBall
from ..solvers.engine.starts import (conditioning_key, keep_conditioning_start, kept_conditioning_start,
                                     random_starts, start_points)
from ..solvers.verdict.batch_probe import ProbeParts
from .vrft_methods import METHODS, alternating


@dataclass
class Gathered:
    """One loaded instance of the alternating attack: its prepared problem, instance, a_y starts (the engine's start
    sequence), ball radius of a_y and the ascent's limits."""

    prep: Prepared
    atk: VRFTAttack
    starts: list[np.ndarray]
    radius_y: float
    max_iter: int
    gain_tol: float
    pending: tuple[Any, int] | None = None
    """(key, index in starts) of a conditioning start the batch finds (conditioning_descent), None where none is."""


def gather(prep: Prepared, options: dict[str, Any]) -> Gathered | None:
    """The batched alternating attack's view of the loaded instance, or None where it runs alone (no exact input
    step, a budget the declaration relaxes, a_y's set not a plain l2 ball, time_limit or verbose)."""
    check_options("alternating", options, alternating)
    if options.get("time_limit") is not None or options.get("verbose"):
        return None
    atk = instance_of(prep.problem)
    if atk.no_exact_input or atk.searched is not None:
        return None
    N = atk.N
    own = prep.projection.on(slice(N, 2 * N)) if isinstance(prep.projection, Blocks) else None
    if not (isinstance(own, NormBall) and own.norm == 2 and own.box is None
            and (own.center is None or not np.any(own.center))):
        return None
    rng = np.random.default_rng(options.get("seed", 0))
    parts = Oracle(atk.learner, atk.upper, atk.conditioning_key).hessian_parts
    starts, canon = int(param("vrft.starts", options.get("starts"))), prep.canon
    pending = None
    if starts > len(canon.x_suggested) and not np.any(canon.x_start):  # start_points' sequence, its conditioning
        pending = conditioning_key(prep, parts)  # start found with the batch's where this process keeps none
        known = kept_conditioning_start(pending)
        points = [*canon.x_suggested, known if known is not None else np.zeros(2 * N), canon.x_start][:starts]
        points += random_starts(prep, starts - len(points), rng, float(param("hypergradient.scale")))
        pending = None if known is not None else (pending, len(canon.x_suggested))
    else:
        points = start_points(prep, starts, rng, float(param("hypergradient.scale")), parts)
    return Gathered(prep, atk, [p[N:].copy() for p in points], float(own.radius),
                    int(param(f"vrft.max_iter.{atk.objective}", options.get("max_iter"))),
                    float(param("vrft.gain_tol", options.get("gain_tol"))), pending)


def _conditioning(gathered: list[Gathered]) -> None:
    """The pending conditioning starts of the gathered instances, found together (once per key) and kept in the
    process as the engine keeps its own."""
    first: dict[Any, int] = {}
    for i, g in enumerate(gathered):
        if g.pending is not None:
            first.setdefault(g.pending[0], i)
    by_design: dict[tuple, list[int]] = {}
    for i in first.values():
        by_design.setdefault((id(gathered[i].atk.setting.regressor), gathered[i].atk.N), []).append(i)
    found: dict[Any, np.ndarray] = {}
    for idx in by_design.values():
        atks = [gathered[i].atk for i in idx]
        N = atks[0].N
        learner = AffineLSBatch(*_stacked(atks), _maps(atks[0]), N, N)
        B = conditioning_descent(learner, np.arange(len(idx)), np.array([gathered[i].radius_y for i in idx]))
        for i, b in zip(idx, B):
            found[gathered[i].pending[0]] = np.concatenate([np.zeros(N), b])
            keep_conditioning_start(gathered[i].pending[0], found[gathered[i].pending[0]])
    for g in gathered:
        if g.pending is not None:
            key, k = g.pending
            g.starts[k] = found[key][g.atk.N:].copy()
            g.pending = None


def run(gathered: list[Gathered], options: dict[str, Any]) -> list[MethodRun]:
    """The alternating attack's runs of the gathered instances, those sharing a learner design and limits in one
    batched ascent (of at most defaults["batch.max_rows"] instances at a time)."""
    _conditioning(gathered)
    groups: dict[tuple, list[int]] = {}
    for i, g in enumerate(gathered):
        key = (id(g.atk.setting.regressor), g.atk.N, g.atk.objective, g.max_iter, g.gain_tol)
        groups.setdefault(key, []).append(i)
    out: list[MethodRun | None] = [None] * len(gathered)
    size = int(param("batch.max_rows"))
    for idx in groups.values():
        for s in range(0, len(idx), size):  # consecutive ascents of at most batch.max_rows instances
            part = idx[s: s + size]
            for i, r in zip(part, _run_group([gathered[i] for i in part])):
                out[i] = r
    return out  # type: ignore[return-value]


def _maps(atk: VRFTAttack) -> BatchMaps:
    """The VRFT regressor's filters and prefilter on stacked signals."""
    reg, N = atk.setting.regressor, atk.N
    if reg.prefilter is None:
        return BatchMaps(reg.stack, reg.stack_adjoint, regressor_adjoints_outer=reg.stack_adjoint_outer)

    def target_adjoints(G: np.ndarray) -> np.ndarray:  # (m, rows, p) -> (m, N, p): every column in one call
        m, rows, p = G.shape
        cols = reg.targets_adjoint(np.transpose(G, (1, 0, 2)).reshape(rows, m * p), N)
        return np.transpose(cols.reshape(N, m, p), (1, 0, 2))

    return BatchMaps(reg.stack, reg.stack_adjoint, reg.stack_targets, target_adjoints, reg.stack_adjoint_outer)


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
            r = t0[rows] - np.einsum("mrk,mk->mr", phi0[rows], theta)
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


def _run_group(items: list[Gathered]) -> list[MethodRun]:
    """One batched ascent over every (instance, start) of items that share a learner design and limits."""
    t0 = time.perf_counter()
    atks = [g.atk for g in items]
    N = atks[0].N
    pairs = [(j, k) for j, g in enumerate(items) for k in range(len(g.starts))]
    inst = np.array([j for j, _ in pairs], dtype=int)  # the instance of each row of the ascent
    phi0, t0 = _stacked(atks)
    learner = AffineLSBatch(phi0, t0, _maps(atks[0]), N, N)
    upper = upper_batch(atks, phi0, t0)
    block = TargetBlockBatch(learner, upper, np.array([a.delta_u for a in atks]))
    weight = np.array([atks[j].delta_y for j in inst])
    radius = np.array([items[j].radius_y for j in inst])

    def value(rows: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, Points]:
        """J at each trial point, with its gradient in b (most trial points are accepted: computed while the fit's
        arrays are at hand, the points keep only theta, a and the gradient)."""
        of = inst[rows]
        with np.errstate(all="ignore"):
            fit = block.solve(of, X)
            f = upper.value(of, fit.theta)
            g = learner.gradient(fit, upper.gradient(of, fit.theta), target=False)[1]
        f = np.where(fit.ok & np.isfinite(f), f, -np.inf)
        return f, {"theta": fit.theta, "a": fit.a, "g": g}

    def direction(rows: np.ndarray, p: Points) -> tuple[np.ndarray, np.ndarray]:
        g = p["g"]
        w = weight[rows, None]
        unit = np.sqrt(np.sum((g * w) ** 2, axis=1))
        d = np.where(unit[:, None] > 0, g * (w * w) / np.where(unit > 0, unit, 1.0)[:, None], 0.0)
        return g, d

    X0 = np.array([items[j].starts[k] for j, k in pairs])
    res = batched_projected_ascent(value, direction, lambda rows, X: project_l2_balls(X, radius[rows]), X0, weight,
                                   items[0].max_iter, items[0].gain_tol)
    share = (time.perf_counter() - t0) / max(len(pairs), 1)
    runs = []
    for j, g in enumerate(items):
        mine = [r for r, (jj, _) in enumerate(pairs) if jj == j]
        runs.append(_method_run(g, res, mine, radius, share))
    return runs


def _method_run(g: Gathered, res: Any, rows: list[int], radius: np.ndarray, share: float) -> MethodRun:
    """One instance's MethodRun from its starts' rows of the batched ascent, as ascend_with_exact_block reports it
    (the VRFT attack's lower_solve set, as vrft_methods._ascend sets it)."""
    atk, N, starts = g.atk, g.atk.N, len(rows)
    records, ends, nit = [], [], 0
    for k, r in enumerate(rows):
        failed = res.why[r] == "start"
        nit += int(res.iterations[r])
        records.append({"start": k, "objective": None if failed else -float(res.f[r]),
                        "iterations": int(res.iterations[r]), "evaluations": int(res.evaluations[r]),
                        "converged": bool(res.converged[r]), SINGULAR_LEARNER: failed, "time": share})
        if not failed:
            ends.append((float(res.f[r]), r, bool(res.converged[r]), k))
    if not ends:
        return multistart_run(None, starts, nit, records, lower_solve=atk.learner.thetas)
    fx, r, converged, k = ends[best_of([(None, -end[0], 0.0) for end in ends])]
    b, a, theta = res.x[r], res.points["a"][r], res.points["theta"][r]
    w = g.prep.pack(KKTPoint(np.concatenate([a, b]), theta, np.zeros(0), np.zeros(0), []))
    pg = float(np.linalg.norm(project_l2_balls((b + res.gradient[r])[None], radius[r:r + 1])[0] - b))
    return multistart_run((w, converged, k, list(res.history[r]), pg), starts, nit, records, slice(0, N),
                          lower_solve=atk.learner.thetas)


def probe_parts(gathered: list[Gathered], runs: list[MethodRun]) -> ProbeParts:
    """The learners' fits at the probe's points, the attack's criterion there (canonical F = -J) and the canonical
    hypergradient at each run's point (bilevel.solvers.verdict.batch_probe)."""
    atks = [g.atk for g in gathered]
    N = atks[0].N
    phi0, t0 = _stacked(atks)
    learner = AffineLSBatch(phi0, t0, _maps(atks[0]), N, N)
    upper = upper_batch(atks, phi0, t0)

    def solve(inst: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(all="ignore"):
            fit = learner.fit(inst, X[:, :N], X[:, N:])
        return fit.theta, fit.ok

    gradients: dict[int, np.ndarray | None] = {}

    def gradient(i: int) -> np.ndarray | None:
        if not gradients:  # every run's point at once
            have = [j for j, r in enumerate(runs) if r.w is not None]
            x = np.array([gathered[j].prep.point(runs[j].w).x for j in have])
            size = int(param("batch.chunk"))
            for s in range(0, len(have), size):
                rows = np.array(have[s: s + size])
                with np.errstate(all="ignore"):
                    fit = learner.fit(rows, x[s: s + size, :N], x[s: s + size, N:])
                    g_a, g_b = learner.gradient(fit, upper.gradient(rows, fit.theta))
                for j, ok, ga, gb in zip(rows, fit.ok, g_a, g_b):
                    gradients[int(j)] = -np.concatenate([ga, gb]) if ok else None
        return gradients.get(i)

    return ProbeParts(solve, lambda inst, X, Y: -upper.value(inst, Y), gradient)


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
