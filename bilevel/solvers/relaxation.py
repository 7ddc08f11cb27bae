"""Warm-started relaxation sequence on the MPCC: solve with Scholtes (or Kanzow–Schwartz) for t_k -> 0.

One NLP is transcribed once with the relaxation parameter as an NLP parameter; each step re-solves it
from the previous step's primal and dual point. The sequence stops when the complementarity residual
is below `comp_tol` (or t reaches `t_min`); the best start's point is then polished on its MPCC branch.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..errors import ModelError
from ..mpcc import ComplementarityMode, KanzowSchwartz, Scholtes
from .base import MethodRun, Prepared, best_of, check_options
from .options import check_numbers
from .ipopt import NLPRun, kept_warm_point, kkt_nlp_options, kkt_starts, polish_best, residual, run_nlp, settled
from .limits import Deadline, deadline, progress, stopped

SCHEMES: dict[str, type[ComplementarityMode]] = {
    "scholtes": Scholtes,
    "kanzow-schwartz": KanzowSchwartz,
}


def relaxation_path(prep: Prepared, nlp: Any, w0: np.ndarray, opts: dict[str, Any], t0: float, factor: float,
                    t_min: float, comp_tol: float, limit: Deadline | None = None,
                    verbose: bool = False) -> tuple[NLPRun, list[dict[str, Any]]]:
    """Follow t_k = t0 * factor^k, warm starting each solve, until the deadline `limit` at the latest; return the
    last run and the path (one progress line per step when verbose)."""
    path, t, lam_g, run = [], t0, None, None
    w = w0
    while True:
        run = run_nlp(nlp, w, opts, tau=t, lam_g0=lam_g, limit=limit)
        comp = prep.mpcc.residuals(run.w)["complementarity"]
        path.append({"t": t, "objective": run.objective, "complementarity": comp, "status": run.raw_status,
                     "iterations": run.iterations})
        w = run.w
        progress(verbose, "relaxation", f"t = {t:.1e}: {run.raw_status}, F = {prep.declared(run.objective):.6g}, "
                 f"complementarity {comp:.1e}")
        if comp <= comp_tol or t * factor < t_min or (limit is not None and limit.expired()):
            return run, path
        t *= factor


def solve_relaxation(prep: Prepared, **options: Any) -> MethodRun:
    """Multistart relaxation sequence (options: scheme, t0, factor, t_min, comp_tol, starts, seed, polish,
    tol, max_iter, ipopt, scale, time_limit, verbose, warm: "auto", None or "hypergradient", as for ipopt). At
    time_limit the sequence and the starts stop, status MAX_ITERATIONS."""
    check_options("relaxation", options, {"scheme", "t0", "factor", "t_min", "comp_tol", "starts", "seed", "polish",
                                          "tol", "max_iter", "ipopt", "scale", "time_limit", "verbose", "warm"})
    check_numbers(options, positive=("t0", "factor", "t_min", "comp_tol"))
    scheme = options.get("scheme", "scholtes")
    if scheme not in SCHEMES:
        raise ModelError(f"unknown relaxation scheme {scheme!r}; choose one of {', '.join(SCHEMES)}")
    factor = float(options.get("factor", 0.1))
    if not 0.0 < factor < 1.0:
        raise ModelError(f"relaxation factor must be in (0, 1), got {factor}")
    mode = SCHEMES[scheme]()
    limit, verbose = deadline(options), bool(options.get("verbose"))
    points, source, warm = kkt_starts(prep, "relaxation", options, limit)
    opts = kkt_nlp_options(options, warm)
    nlp = prep.mpcc.transcribe(mode)
    candidates, finals, paths, records = [], [], [], []
    for k, w0 in enumerate(points):
        if k and limit.expired():
            break
        t_start = time.perf_counter()
        run, path = relaxation_path(prep, nlp, w0, opts, float(options.get("t0", 1.0)), factor,
                                    float(options.get("t_min", 1e-12)), float(options.get("comp_tol", 1e-7)), limit,
                                    verbose)
        res = residual(prep, run.w)
        candidates.append((run.w, run.objective, res))
        finals.append(run)
        paths.append(path)
        records.append({"start": k, "x0": prep.point(w0).x.tolist(), "status": path[-1]["status"],
                        "objective": run.objective, "residual": res, "polished": False,
                        "steps": len(path), "time": time.perf_counter() - t_start})
        progress(verbose, "relaxation", f"start {k + 1}/{len(points)}: {len(path)} steps, "
                 f"F = {prep.declared(run.objective):.6g}, residual {res:.1e}")
    i, polishing = (polish_best(prep, candidates, finals, records, opts, limit)
                    if options.get("polish", True) and prep.mpcc.pairs else (best_of(candidates), 0))
    total = sum(p["iterations"] for path in paths for p in path) + polishing
    kept = kept_warm_point(prep, points, candidates[i], f"{finals[i].status.value} after {len(paths[i])} relaxation "
                           "steps", total, records, {"scheme": scheme, **warm})
    run = kept if kept is not None else MethodRun(
        finals[i].w, finals[i].status, f"{source}, start {i} ({len(paths[i])} relaxation steps, last t = "
        f"{paths[i][-1]['t']:.1e})", total, paths[i], records, {"scheme": scheme, "best_start": i, **warm})
    return settled(prep, stopped(run, limit, len(records), len(points)))
