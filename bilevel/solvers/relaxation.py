"""Warm-started relaxation sequence on the MPCC: solve with Scholtes (or Kanzow–Schwartz) for t_k -> 0.

One NLP is transcribed once with the relaxation parameter as an NLP parameter; each step re-solves it
from the previous step's primal and dual point. The sequence stops when the complementarity residual
is below `comp_tol` (or t reaches `t_min`); the best start's point is then polished on its MPCC branch.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..defaults import param
from ..errors import ModelError
from ..mpcc import ComplementarityMode, KanzowSchwartz, Scholtes
from .engine.prepared import MethodRun, Prepared, best_of, check_options
from .ipopt import NLPRun, kept_warm_point, kkt_nlp_options, kkt_starts, branch_polish_best, residual, run_nlp, settled
from .engine.limits import Deadline, progress, stopped

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


def solve_relaxation(prep: Prepared, *, scheme: str = "scholtes", t0: float | None = None, factor: float | None = None,
                     t_min: float | None = None, comp_tol: float | None = None, starts: int | None = None,
                     seed: Any = 0, scale: float | None = None, warm: str | None = "auto", branch_polish: bool = True,
                     nlp_tol: float | None = None, max_iter: int | None = None, ipopt: dict[str, Any] | None = None,
                     time_limit: float | None = None, verbose: bool = False, **unknown: Any) -> MethodRun:
    """Multistart relaxation sequence. An option left None takes the registry's value, defaults["relaxation.NAME"]
    (t0, factor, t_min, comp_tol) or defaults["ipopt.NAME"] (the others, as for method ipopt; bilevel.defaults).

    scheme: "scholtes" | "kanzow-schwartz"; t0: first relaxation parameter; factor: t's factor per step, in (0, 1);
    t_min and comp_tol: the sequence stops before t falls below t_min or once the complementarity residual is below
    comp_tol; starts, seed, scale, warm, branch_polish, nlp_tol, max_iter, ipopt, verbose: as for method ipopt;
    time_limit (seconds): the sequence and the starts stop, status MAX_ITERATIONS."""
    check_options("relaxation", unknown, solve_relaxation)
    t0, factor = float(param("relaxation.t0", t0)), float(param("relaxation.factor", factor))
    t_min, comp_tol = float(param("relaxation.t_min", t_min)), float(param("relaxation.comp_tol", comp_tol))
    if scheme not in SCHEMES:
        raise ModelError(f"unknown relaxation scheme {scheme!r}; choose one of {', '.join(SCHEMES)}")
    mode = SCHEMES[scheme]()
    limit, verbose = Deadline(time_limit), bool(verbose)
    points, source, warm = kkt_starts(prep, "relaxation", starts, seed, scale, warm, verbose, limit)
    opts = kkt_nlp_options(nlp_tol, max_iter, ipopt, warm)
    nlp = prep.mpcc.transcribe(mode)
    candidates, finals, paths, records = [], [], [], []
    for k, w0 in enumerate(points):
        if k and limit.expired():
            break
        t_start = time.perf_counter()
        run, path = relaxation_path(prep, nlp, w0, opts, t0, factor, t_min, comp_tol, limit, verbose)
        res = residual(prep, run.w)
        candidates.append((run.w, run.objective, res))
        finals.append(run)
        paths.append(path)
        records.append({"start": k, "x0": prep.point(w0).x.tolist(), "status": path[-1]["status"],
                        "objective": run.objective, "residual": res, "polished": False,
                        "steps": len(path), "time": time.perf_counter() - t_start})
        progress(verbose, "relaxation", f"start {k + 1}/{len(points)}: {len(path)} steps, "
                 f"F = {prep.declared(run.objective):.6g}, residual {res:.1e}")
    i, polishing = (branch_polish_best(prep, candidates, finals, records, opts, limit)
                    if branch_polish and prep.mpcc.pairs else (best_of(candidates), 0))
    total = sum(p["iterations"] for path in paths for p in path) + polishing
    kept = kept_warm_point(prep, points, candidates[i], f"{finals[i].status.value} after {len(paths[i])} relaxation "
                           "steps", total, records, {"scheme": scheme, **warm})
    run = kept if kept is not None else MethodRun(
        finals[i].w, finals[i].status, f"{source}, start {i} ({len(paths[i])} relaxation steps, last t = "
        f"{paths[i][-1]['t']:.1e})", total, paths[i], records, {"scheme": scheme, "best_start": i, **warm})
    return settled(prep, stopped(run, limit, len(records), len(points)))
