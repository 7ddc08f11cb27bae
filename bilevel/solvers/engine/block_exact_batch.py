"""ascend_with_exact_block (bilevel.solvers.engine.block_exact) on many instances of one declaration at once, over a
batched oracle (affine_ls_batch.BatchOracle: the exact block a = x[:n_a] at its optimum for every b = x[n_a:]): each
instance's start sequence (start_points; conditioning starts not yet kept are found together), one lockstep ascent
(batch_ascent) over every (instance, start), each instance's MethodRun as the one-instance ascent reports it
(multistart_run), and the parts of the verdict's batched probe. Covered: b's set an l2 ball about 0, no box.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable

import numpy as np

from ...defaults import param
from ...reduction import KKTPoint
from .affine_ls_batch import AffineLSBatch, BatchOracle, conditioning_descent
from .batch_ascent import BatchAscent, batched_projected_ascent
from .batch_linalg import project_l2_balls
from .block_exact import SINGULAR_LEARNER, multistart_run
from .prepared import MethodRun, Prepared, best_of
from .projections import Blocks, NormBall
from .starts import ConditioningParts, conditioning_key, keep_conditioning_start, kept_conditioning_start, start_points


@dataclass
class BatchInstance:
    """One loaded instance of the batched ascent: its prepared problem, the b part of its starts (start_points'
    sequence), the radius of b's ball, b's length scale, the ascent's limits and further MethodRun fields (e.g.
    lower_solve)."""

    prep: Prepared
    starts: list[np.ndarray]
    radius: float
    weight: float
    max_iter: int
    gain_tol: float
    fields: dict[str, Any] = field(default_factory=dict)
    pending: tuple[Hashable, int] | None = None
    """(key, index in starts) of a conditioning start still to be found (conditioning_starts), else None."""


def batch_instance(prep: Prepared, n_a: int, starts: int, seed: Any, parts: ConditioningParts, weight: float,
                   max_iter: int, gain_tol: float, **fields: Any) -> BatchInstance | None:
    """The batched ascent's view of the loaded instance (x = (a, b), the exact block a = x[:n_a]; parts its
    learner's keyed ConditioningParts), or None where b's set is not a plain l2 ball about 0 (it then runs alone)."""
    canon, n_x = prep.canon, int(prep.canon.x.numel())
    own = prep.projection.on(slice(n_a, n_x)) if isinstance(prep.projection, Blocks) else None
    if not (isinstance(own, NormBall) and own.norm == 2 and own.box is None
            and (own.center is None or not np.any(own.center))):
        return None
    placeholder, pending = None, None
    if parts.key is not None and starts > len(canon.x_suggested) and not np.any(canon.x_start):
        key = conditioning_key(prep, parts)  # not kept in this process: found with the batch's (from zero)
        if kept_conditioning_start(key) is None:
            placeholder, pending = np.zeros(n_x), (key, len(canon.x_suggested))
    points = start_points(prep, starts, np.random.default_rng(seed), float(param("hypergradient.scale")), parts,
                          placeholder)
    return BatchInstance(prep, [p[n_a:].copy() for p in points], float(own.radius), float(weight), int(max_iter),
                         float(gain_tol), fields, pending)


def conditioning_starts(instances: list[BatchInstance], design: Callable[[int], Hashable],
                        learner: Callable[[list[int]], AffineLSBatch]) -> None:
    """Fill the instances' pending conditioning starts: found together (conditioning_descent), once per key and in
    one batch per design (design(i) equal: instances whose learners share their maps; learner(idx) the batched learner
    of instances idx), and kept in the process as conditioning_start keeps its own."""
    first: dict[Hashable, int] = {}
    for i, inst in enumerate(instances):
        if inst.pending is not None:
            first.setdefault(inst.pending[0], i)
    by_design: dict[Hashable, list[int]] = {}
    for i in first.values():
        by_design.setdefault(design(i), []).append(i)
    found: dict[Hashable, np.ndarray] = {}
    for idx in by_design.values():
        batch = learner(idx)
        B = conditioning_descent(batch, np.arange(len(idx)), np.array([instances[i].radius for i in idx]))
        for i, b in zip(idx, B):
            key = instances[i].pending[0]  # type: ignore[index]
            found[key] = np.concatenate([np.zeros(batch.n_a), b])
            keep_conditioning_start(key, found[key])
    for inst in instances:
        if inst.pending is not None:
            key, k = inst.pending
            inst.starts[k] = found[key][-inst.starts[k].size:].copy()
            inst.pending = None


def ascend_with_exact_block_batch(oracle: BatchOracle, instances: list[BatchInstance]) -> list[MethodRun]:
    """ascend_with_exact_block from every start of every instance in one lockstep ascent (oracle's instance i is
    instances[i]; the limits are the first instance's), one MethodRun per instance."""
    t0 = time.perf_counter()
    n_a = oracle.learner.n_a
    pairs = [(j, k) for j, inst in enumerate(instances) for k in range(len(inst.starts))]
    of = np.array([j for j, _ in pairs], dtype=int)  # the instance of each row of the ascent
    weight = np.array([instances[j].weight for j in of])
    radius = np.array([instances[j].radius for j in of])

    def direction(rows: np.ndarray, p: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        g = p["g"]
        w = weight[rows, None]
        unit = np.sqrt(np.sum((g * w) ** 2, axis=1))
        d = np.where(unit[:, None] > 0, g * (w * w) / np.where(unit > 0, unit, 1.0)[:, None], 0.0)
        return g, d

    X0 = np.array([instances[j].starts[k] for j, k in pairs])
    res = batched_projected_ascent(lambda rows, X: oracle.evaluate(of[rows], X), direction,
                                   lambda rows, X: project_l2_balls(X, radius[rows]), X0, weight,
                                   instances[0].max_iter, instances[0].gain_tol)
    share = (time.perf_counter() - t0) / max(len(pairs), 1)
    first = np.cumsum([0] + [len(inst.starts) for inst in instances])  # instance j's starts: rows first[j]..first[j+1]
    return [_method_run(inst, res, list(range(first[j], first[j + 1])), radius, share, n_a)
            for j, inst in enumerate(instances)]


def _method_run(inst: BatchInstance, res: BatchAscent, rows: list[int], radius: np.ndarray, share: float,
                n_a: int) -> MethodRun:
    """One instance's MethodRun from its starts' rows of the batched ascent, as ascend_with_exact_block reports it."""
    starts = len(rows)
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
        return multistart_run(None, starts, nit, records, **inst.fields)
    fx, r, converged, k = ends[best_of([(None, -end[0], 0.0) for end in ends])]
    b, a, theta = res.x[r], res.points["a"][r], res.points["theta"][r]
    w = inst.prep.pack(KKTPoint(np.concatenate([a, b]), theta, np.zeros(0), np.zeros(0), []))
    pg = float(np.linalg.norm(project_l2_balls((b + res.gradient[r])[None], radius[r:r + 1])[0] - b))
    return multistart_run((w, converged, k, list(res.history[r]), pg), starts, nit, records, slice(0, n_a),
                          **inst.fields)


def batch_probe_parts(oracle: BatchOracle, instances: list[BatchInstance], runs: list[MethodRun]) -> tuple[
        Callable, Callable, Callable]:
    """The fields of the verdict's ProbeParts (bilevel.solvers.verdict.batch_probe, a layer above): the learners' fits
    at the probe's points, the criterion there (canonical F = -J) and the canonical hypergradient at each run's point,
    oracle's instance i = instances[i]."""
    gradients: dict[int, np.ndarray | None] = {}

    def gradient(i: int) -> np.ndarray | None:
        if not gradients:  # every run's point at once
            have = [j for j, r in enumerate(runs) if r.w is not None]
            x = np.array([instances[j].prep.point(runs[j].w).x for j in have])
            size = int(param("batch.chunk"))
            for s in range(0, len(have), size):
                rows = np.array(have[s: s + size])
                g, ok = oracle.hypergradients(rows, x[s: s + size])
                for j, o, gj in zip(rows, ok, g):
                    gradients[int(j)] = gj if o else None
        return gradients.get(i)

    return oracle.fits, lambda inst, X, Y: -oracle.upper.value(inst, Y), gradient
