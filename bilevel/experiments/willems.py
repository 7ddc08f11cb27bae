"""Reproduction of the paper's attacks on the De Persis–Tesi learners (appendix B): sweeps, tables, figures 7-9.

Paper setting: batch reactor, u ~ N(0, 1), x_0 = 0, N in {15, 50}, the appendix SDP (design "lqr",
Qx = I), input poisoning in an linf ball of radius delta_u, eigenvalue criterion; our hypergradient
attack and the differential-evolution baseline run on the same instances (sim i has the same data
for every delta and method). Side experiments: the paper's output-poisoning remark (delta_y = 1e-3
on the states, x_0 clean) and the other designs (lqr-r, stabilizing; u and xu poisoning; max-min
criterion). Every attack is one sweep task (bilevel.experiments.sweep: one JSON line per finished
attack, resumable, on the local pool or a Dask cluster); seeds come from SeedSequence(seed).spawn(sims).
"""

from __future__ import annotations

import csv
import json
import os
import platform
import time
import warnings
from dataclasses import asdict, dataclass
from typing import Any, Callable

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..attacks.outcome import attack_stat, unstable  # noqa: E402
from ..attacks.willems import de_attack, destabilize_attack, hypergradient_attack, random_attack  # noqa: E402
from ..ddc.data import batch_reactor_data  # noqa: E402
from ..ddc.depersis_tesi import (check_persistency, lqr_controller, stabilizing_controller,  # noqa: E402
                                 state_data)
from ..ddc.plants import batch_reactor  # noqa: E402
from ..errors import BilevelError  # noqa: E402
from ..files import atomic_open, save_figure  # noqa: E402
from ..problems.willems import kept_attack  # noqa: E402
from ..problems.willems_instance import (DEFAULT_REG, SOLVER_SELECTIONS, WillemsSetting,  # noqa: E402
                                         selection_applies)
from ..result import BilevelResult  # noqa: E402
from .stats import mean_interval, wilson_interval  # noqa: E402
from .executor import open_executor  # noqa: E402
from .sweep import (FINITE, NUMBER, check_fields, committed_timings, load_timings, run_sweep,  # noqa: E402
                    settings_of, stderr_progress)
from .willems_selection import selection_table  # noqa: E402

DELTA_Y = 1e-3
METHODS = {"hypergradient": "hypergradient (ours)", "destabilize": "destabilizing (ours, max rho)",
           "differential-evolution": "differential evolution", "random": "random signs"}
PAPER_CLAIMS = (
    ("small budgets suffice", "\"For very small values of delta_u we can get the system unstable.\""),
    ("more data is more fragile", "\"increasing the number of points N makes the closed-loop system unstable "
                                  "for smaller values of delta_u\" (Fig. 7)"),
    ("output poisoning", "\"an attacker can make the closed-loop system unstable even for perturbations computed "
                         "using the constraint delta_y = 1e-3 (even without poisoning the initial condition x0)\""),
)


@dataclass(frozen=True)
class Plan:
    """Sizes of every sweep of one reproduction run."""

    sims: int
    deltas: tuple[float, ...]
    horizons: tuple[int, ...]
    de_popsize: int
    de_max_iter: int
    starts: int
    remark_sims: int
    remark_horizons: tuple[int, ...]
    design_sims: int
    design_deltas: tuple[float, ...]
    rho_iter: int = 100
    """max_iter of the destabilizing attack's batched ascent."""
    rho_starts: int = 64
    """Starts of the destabilizing attack (ascending together, screened from a pool of 512 points)."""


def make_plan(sims: int, quick: bool) -> Plan:
    """The paper-sized plan (`sims` per cell), or the CI plan (<= 4 sims, 3 budgets, short DE) when quick."""
    if sims < 1:
        raise ValueError(f"sims must be >= 1, got {sims}")
    if quick:
        return Plan(min(sims, 4), (0.2, 0.6, 1.25), (15, 50), 5, 40, 4, 1, (15,), 1, (1e-3, 1e-1), rho_iter=20,
                    rho_starts=16)
    return Plan(sims, (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0, 1.25), (15, 50), 5, 300, 8,
                max(2, min(sims, 32)), (15, 50), max(2, min(sims, 16)),
                (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0))


def sim_seeds(seed: int, sims: int) -> list[tuple[int, int]]:
    """(data seed, attack seed) per simulation, from SeedSequence(seed).spawn(sims)."""
    return [tuple(int(v) for v in s.generate_state(2)) for s in np.random.SeedSequence(seed).spawn(sims)]


LEARNER_TEXT = {
    "min-norm": " (Q projected onto the row space of [X0; X1] after solving: the minimum-norm Q, reproducible to "
                "solver accuracy)",
    "tikhonov": " (the solver's Q under reg alone)",
    "clarabel": " (Clarabel's own optimal Q of the unregularized SDP, as a user calling the solver gets it)",
    "scs": " (SCS's own optimal Q of the unregularized SDP, as a user calling the solver gets it)",
}
NOT_DEFINED = ("Not run for the `{learner}` selection: the solver's own Q is defined (and differentiable) only where "
               "the SDP ignores the poisoning, i.e. input poisoning without an input cost; rerun with "
               "`--selection min-norm` or `tikhonov` for state poisoning and the lqr-r design.")
SETTING_SCHEMA = {"experiment": str, "horizon": int, "method": str, "delta_u": FINITE, "criterion": str, "design": str,
                  "poison": str, "seed": int, "selection": str}
ROW_SCHEMA = {**SETTING_SCHEMA, "unstable": bool, "wall_time": FINITE, "reference_radius": NUMBER,
              "spectral_radius": NUMBER, "eig_abs_sum": NUMBER, "objective": (NUMBER, None)}
"""The fields of a row that the summaries and figures read (an error row: its settings and the error)."""


def valid_row(row: dict[str, Any]) -> str:
    """"" if a row has every field the summaries and figures read, of its kind; else why not."""
    if "error" in row:
        return check_fields(row, {**SETTING_SCHEMA, "error": str})
    return check_fields(row, {**ROW_SCHEMA, **({"du": list} if row.get("experiment") == "paper" else {})})


def _task(plan: Plan, root_seed: int, experiment: str, i: int, seeds: tuple[int, int], method: str,
          **setting: Any) -> dict[str, Any]:
    fields = "|".join(f"{k}={setting[k]}" for k in sorted(setting))
    return {"key": f"{experiment}|{method}|{fields}|sim={i}", "experiment": experiment, "method": method,
            "sim": i, "seed": seeds[0], "attack_seed": seeds[1], **setting, "root_seed": root_seed,
            "reg": DEFAULT_REG, "starts": plan.starts, "de_popsize": plan.de_popsize, "de_max_iter": plan.de_max_iter,
            "rho_iter": plan.rho_iter, "rho_starts": plan.rho_starts}


def paper_tasks(plan: Plan, seed: int, selection: str = "min-norm") -> list[dict[str, Any]]:
    """Input poisoning of the appendix SDP: every (N, sim, delta_u) for the eigenvalue criterion (ours and DE)
    and for the destabilizing attack (its own criterion). A data set's tasks are consecutive, so a worker reuses
    its reference learner across budgets and methods (_reference_radius)."""
    return [_task(plan, seed, "paper", i, s, method, horizon=n, delta_u=d, delta_x=0.0, poison="u", design="lqr",
                  criterion="destabilize" if method == "destabilize" else "eigen", selection=selection)
            for n in plan.horizons for i, s in enumerate(sim_seeds(seed, plan.sims)) for d in plan.deltas
            for method in ("hypergradient", "differential-evolution", "destabilize")]


def remark_tasks(plan: Plan, seed: int, selection: str = "min-norm") -> list[dict[str, Any]]:
    """The output-poisoning remark: states poisoned with delta_y = 1e-3 (x_0 clean), inputs clean."""
    return [_task(plan, seed, "remark", i, s, method, horizon=n, delta_u=0.0, delta_x=DELTA_Y, poison="x", design="lqr",
                  criterion=criterion, selection=selection)
            for n in plan.remark_horizons for i, s in enumerate(sim_seeds(seed, plan.remark_sims))
            for method, criterion in (("hypergradient", "eigen"), ("hypergradient", "maxmin"), ("random", "eigen"))]


def design_tasks(plan: Plan, seed: int, selection: str = "min-norm") -> list[dict[str, Any]]:
    """Both criteria on the three designs, inputs only or states and inputs (delta_x = delta_u), N = 15."""
    return [_task(plan, seed, "designs", i, s, "hypergradient", horizon=15, delta_u=d,
                  delta_x=d if poison == "xu" else 0.0, poison=poison, design=design, criterion=criterion,
                  selection=selection)
            for design in ("lqr", "lqr-r", "stabilizing") for poison in ("u", "xu") for criterion in ("maxmin", "eigen")
            for i, s in enumerate(sim_seeds(seed, plan.design_sims)) for d in plan.design_deltas]


REFERENCES_KEPT = 4
"""Data sets whose reference learner (bilevel.ddc, clean data) a process keeps."""
_REFERENCES: dict[tuple, Any] = {}


def _reference_learner(design: str, x: np.ndarray, u: np.ndarray) -> Any:
    """The unregularized learner of bilevel.ddc on (x, u), no column balancing (the committed sweep's)."""
    if design == "stabilizing":
        return stabilizing_controller(x, u, balance=False)
    return lqr_controller(x, u, input_cost=design == "lqr-r", balance=False)


def _reference_radius(setting: WillemsSetting, x: np.ndarray, u: np.ndarray, clean_u: np.ndarray) -> float:
    """Spectral radius of the true loop under the unregularized learner of bilevel.ddc on the poisoned data (x, u).
    Where that SDP ignores the inputs (designs lqr and stabilizing) its Q is the clean data's, solved once per data
    set and kept: K = U Q (X0 Q)^-1 on the poisoned inputs, after the learner's persistency check on them."""
    plant = batch_reactor()
    try:
        if setting.design == "lqr-r":
            k = _reference_learner(setting.design, x, u).k
        else:
            key = (setting.design, x.tobytes(), clean_u.tobytes())
            learner = _REFERENCES.pop(key, None) or _reference_learner(setting.design, x, clean_u)
            _REFERENCES[key] = learner
            while len(_REFERENCES) > REFERENCES_KEPT:
                del _REFERENCES[next(iter(_REFERENCES))]
            data = state_data(x, u)
            check_persistency(data)
            s = data.x0 @ learner.q
            k = scipy.linalg.solve(0.5 * (s + s.T), (data.u0 @ learner.q).T, assume_a="sym").T
    except BilevelError:
        return float("nan")
    return float(np.max(np.abs(np.linalg.eigvals(plant.A + plant.B @ k))))


def attack_task(task: dict[str, Any]) -> dict[str, Any]:
    """Run one attack described by a task; a JSON row with the task's fields and its outcome (or its error)."""
    fields = {k: v for k, v in task.items() if k != "key"}
    setting = WillemsSetting(objective=task["criterion"], horizon=task["horizon"], seed=task["seed"],
                             delta_u=task["delta_u"], delta_x=task["delta_x"], poison=task["poison"],
                             design=task["design"], selection=task["selection"], reg=task["reg"])
    try:
        attack = kept_attack(setting)
        if task["method"] == "hypergradient":
            res = hypergradient_attack(attack, starts=task["starts"], seed=task["attack_seed"])
        elif task["method"] == "destabilize":
            res = destabilize_attack(attack, starts=task["rho_starts"], seed=task["attack_seed"],
                                     max_iter=task["rho_iter"])
        elif task["method"] == "differential-evolution":
            res = de_attack(attack, seed=task["attack_seed"], max_iter=task["de_max_iter"], popsize=task["de_popsize"])
        else:
            res = random_attack(attack, seed=task["attack_seed"])
    except BilevelError as exc:
        return {**fields, "error": f"{type(exc).__name__}: {exc}"}
    du, dx = attack.split(res.stats["x"])
    row = {**fields, **{k: v for k, v in willems_row(res).items()
                        if k not in ("method", "x", "details", "gain", "eigenvalues")}}
    with warnings.catch_warnings():  # cvxpy's "solution may be inaccurate" on the badly scaled N = 50 data
        warnings.simplefilter("ignore", UserWarning)
        row["reference_radius"] = _reference_radius(setting, attack.x + dx, attack.u + du, attack.u)
    if task["experiment"] == "paper":
        row["du"] = du.tolist()
    return row


def willems_row(result: BilevelResult) -> dict[str, Any]:
    """JSON-ready summary, one row of the reproduction (objective: the criterion, inf for an unstable max-min loop;
    eigenvalues as [re, im])."""
    attack_stat(result, "eigenvalues")
    st = result.stats
    eig = st["eigenvalues"]
    return {"method": result.method, "status": result.status.value, "objective": st["criterion"],
            "spectral_radius": st["spectral_radius"], "eig_abs_sum": float(np.sum(np.abs(eig))),
            "unstable": unstable(result), "gain": st["gain"].tolist(),
            "eigenvalues": [[float(v.real), float(v.imag)] for v in eig], "wall_time": result.wall_time,
            "evaluations": st["evaluations"], "iterations": result.nit, "message": result.message,
            "budget_violation": st["budget_violation"], "kkt_residual": st["kkt_residual"], "x": st["x"].tolist(),
            "details": st["details"]}


# -- summaries and tables -------------------------------------------------------------------------------------
def summarize(rows: list[dict[str, Any]], fields: tuple[str, ...]) -> dict[tuple, dict[str, float]]:
    """Per group of `fields`: unstable rate with Wilson 95% CI, means with t CIs, median time, error count."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[f] for f in fields), []).append(r)
    out = {}
    for key, rs in sorted(groups.items()):
        ok = [r for r in rs if "error" not in r]
        n, k = len(ok), sum(bool(r["unstable"]) for r in ok)
        lo, hi = wilson_interval(k, n)
        ref = [r["reference_radius"] for r in ok if np.isfinite(r["reference_radius"])]
        ref_k = sum(v >= 1 for v in ref)
        cell = {"n": n, "errors": len(rs) - n, "unstable": k, "rate": k / n if n else float("nan"), "rate_lo": lo,
                "rate_hi": hi, "reference_n": len(ref), "reference_rate": ref_k / len(ref) if ref else float("nan"),
                "time_median": float(np.median([r["wall_time"] for r in ok])) if ok else float("nan"),
                "time_total": float(sum(r["wall_time"] for r in ok))}
        for name in ("spectral_radius", "eig_abs_sum", "objective"):
            values = np.array([r[name] for r in ok], dtype=float)
            m, mlo, mhi = mean_interval(values)
            cell.update({name: m, f"{name}_lo": mlo, f"{name}_hi": mhi,
                         f"{name}_infinite": int(np.sum(np.isinf(values)))})
        out[key] = cell
    return out


def _rate(c: dict[str, float] | None) -> str:
    if c is None or not c["n"]:
        return "-"
    return f"{100 * c['rate']:.1f}% [{100 * c['rate_lo']:.1f}, {100 * c['rate_hi']:.1f}]"


def write_csv(summary: dict[tuple, dict[str, float]], fields: tuple[str, ...], path: str) -> str:
    """One CSV row per summary cell."""
    cols = list(next(iter(summary.values())).keys()) if summary else []
    with atomic_open(path, newline="") as fh:
        w = csv.writer(fh)
        w.writerow(list(fields) + cols)
        for key, cell in summary.items():
            w.writerow(list(key) + [cell[c] for c in cols])
    return path


def paper_table(summary: dict[tuple, dict[str, float]], plan: Plan) -> str:
    """Markdown: % unstable [Wilson 95% CI] per delta_u: log-det attack, destabilizing attack and DE for each N."""
    head = " | ".join(f"N={n} {m}" for n in plan.horizons for m in ("ours log det", "ours max rho", "DE"))
    lines = [f"| delta_u | {head} |", "|---" * (1 + 3 * len(plan.horizons)) + "|"]
    for d in plan.deltas:
        cells = [_rate(summary.get((n, m, d))) for n in plan.horizons
                 for m in ("hypergradient", "destabilize", "differential-evolution")]
        lines.append(f"| {d:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def transfer_table(summary: dict[tuple, dict[str, float]], plan: Plan) -> str:
    """Markdown: % unstable when bilevel.ddc.lqr_controller (reg = 0, Clarabel's Q) learns from our poisoned data."""
    head = " | ".join(f"N={n}: regularized learner | N={n}: bilevel.ddc learner" for n in plan.horizons)
    lines = [f"| delta_u | {head} |", "|---" * (1 + 2 * len(plan.horizons)) + "|"]
    for d in plan.deltas:
        cells = []
        for n in plan.horizons:
            c = summary.get((n, "hypergradient", d))
            cells += ["-", "-"] if c is None or not c["n"] else [
                f"{100 * c['rate']:.1f}%", f"{100 * c['reference_rate']:.1f}% of {c['reference_n']}"]
        lines.append(f"| {d:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def remark_table(summary: dict[tuple, dict[str, float]], plan: Plan) -> str:
    """Markdown: % unstable at delta_y = 1e-3 per N and attack, with the unregularized learner's rate."""
    lines = ["| N | attack | criterion | unstable (regularized learner) | unstable (bilevel.ddc learner, reg = 0) "
             "| mean max abs eig | median time (s) |", "|---|---|---|---|---|---|---|"]
    for (n, method, criterion), c in summary.items():
        lines.append(f"| {n} | {METHODS[method]} | {criterion} | {_rate(c)} | "
                     f"{100 * c['reference_rate']:.1f}% of {c['reference_n']} | {c['spectral_radius']:.3f} | "
                     f"{c['time_median']:.2f} |")
    return "\n".join(lines) + "\n"


def design_table(summary: dict[tuple, dict[str, float]], plan: Plan) -> str:
    """Markdown: % unstable per design / poisoning / criterion (rows) and budget (columns), our attack, N = 15."""
    lines = ["| design | poisoned | criterion | " + " | ".join(f"delta = {d:g}" for d in plan.design_deltas) + " |",
             "|---" * (3 + len(plan.design_deltas)) + "|"]
    for design in ("lqr", "lqr-r", "stabilizing"):
        for poison in ("u", "xu"):
            for criterion in ("maxmin", "eigen"):
                cells = []
                for d in plan.design_deltas:
                    c = summary.get((design, poison, criterion, d))
                    cells.append("-" if c is None else _rate(c) + (f" ({c['errors']} failed)" if c["errors"] else ""))
                lines.append(f"| {design} | {poison} | {criterion} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def path_thresholds(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """delta_u* along the sweep's budget grid: per (N, sim) the smallest delta_u at which the destabilizing attack
    made the true loop unstable (inf if none did); rows in bilevel.experiments.willems_budget's format."""
    runs: dict[tuple, list[tuple[float, float]]] = {}
    for r in rows:
        if r.get("method") == "destabilize" and "error" not in r:
            runs.setdefault((r["horizon"], r["selection"], r["seed"]), []).append((r["delta_u"], r["spectral_radius"]))
    return [{"horizon": n, "selection": sel, "data_seed": seed,
             "delta_star": min((d for d, rho in found if rho >= 1.0), default=float("inf")), "attacks": len(found)}
            for (n, sel, seed), found in sorted(runs.items())]


# -- figures --------------------------------------------------------------------------------------------------
def _series(summary: dict[tuple, dict[str, float]], n: int, method: str, deltas: tuple[float, ...],
            name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    cells = [(d, summary.get((n, method, d))) for d in deltas]
    cells = [(d, c) for d, c in cells if c is not None and c["n"]]
    return tuple(np.array(v, dtype=float) for v in zip(*[(d, c[name], c[f"{name}_lo"], c[f"{name}_hi"])
                                                          for d, c in cells])) if cells else (np.zeros(0),) * 4


BUDGET_LABEL = "delta_u: linf budget, |Du| <= delta_u (input units)"
"""The x label of the figures over the input budget."""


def figure_eigenvalues(summary: dict[tuple, dict[str, float]], plan: Plan, out_dir: str) -> str:
    """Fig. 7: mean max |eig(A+BK)| (black, left) and mean sum |eig| (red, right) vs delta_u (N=15 solid, 50 dashed)."""
    fig = Figure(figsize=(12, 4), layout="constrained")
    for ax, method in zip(fig.subplots(1, 2, sharey=True), ("hypergradient", "differential-evolution")):
        twin = ax.twinx()
        for n, style in zip(plan.horizons, ("-", "--")):
            for axis, name, color in ((ax, "spectral_radius", "k"), (twin, "eig_abs_sum", "tab:red")):
                d, m, lo, hi = _series(summary, n, method, plan.deltas, name)
                axis.plot(d, m, style, color=color, marker="o", ms=3, label=f"N={n}")
                axis.fill_between(d, lo, hi, color=color, alpha=0.12)
        ax.axhline(1.0, color="0.6", lw=0.8, ls=":")
        ax.set_xlabel(BUDGET_LABEL)
        ax.set_ylabel("max |eig(A+BK)|")
        twin.set_ylabel("sum |eig(A+BK)|", color="tab:red")
        ax.set_title(METHODS[method])
        ax.legend(loc="upper left", fontsize=8, title="black: max (left axis)\nred: sum (right axis)",
                  title_fontsize=7)
    return save_figure(fig, out_dir, "fig7_eigenvalues")


def figure_objective(summary: dict[tuple, dict[str, float]], plan: Plan, out_dir: str) -> str:
    """Fig. 8: the attacker's criterion log det((A+BK)(A+BK)') vs delta_u, mean and 95% CI."""
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for method, color in (("hypergradient", "tab:blue"), ("differential-evolution", "tab:orange")):
        for n, style in zip(plan.horizons, ("-", "--")):
            d, m, lo, hi = _series(summary, n, method, plan.deltas, "objective")
            ax.plot(d, m, style, color=color, marker="o", ms=3, label=f"{METHODS[method]}, N={n}")
            ax.fill_between(d, lo, hi, color=color, alpha=0.15)
    ax.set_xlabel(BUDGET_LABEL)
    ax.set_ylabel("attacker objective log det(Acl Acl') (dimensionless)")
    ax.legend(fontsize=8)
    return save_figure(fig, out_dir, "fig8_objective")


def signal_delta(summary: dict[tuple, dict[str, float]], plan: Plan, n: int) -> float:
    """The smallest budget at which our attack destabilizes at least half the loops (else the largest budget)."""
    for d in plan.deltas:
        c = summary.get((n, "hypergradient", d))
        if c is not None and c["n"] and c["rate"] >= 0.5:
            return d
    return plan.deltas[-1]


def figure_signals(rows: list[dict[str, Any]], summary: dict[tuple, dict[str, float]], plan: Plan,
                   out_dir: str) -> tuple[str, dict[int, tuple[float, int]]]:
    """Fig. 9: clean and poisoned inputs of the loops our attack destabilized (mean over sims, 95% CI band)."""
    fig = Figure(figsize=(11, 5.4), layout="constrained")
    axes = fig.subplots(2, len(plan.horizons), squeeze=False)
    used = {}
    for col, n in enumerate(plan.horizons):
        d = signal_delta(summary, plan, n)
        sel = [r for r in rows if r["horizon"] == n and r["delta_u"] == d and r["method"] == "hypergradient"
               and "error" not in r and r["unstable"]]
        used[n] = (d, len(sel))
        if not sel:
            axes[0, col].set_title(f"N={n}: no unstable loop at delta_u={d:g}")
            continue
        clean = np.stack([batch_reactor_data(n, np.random.default_rng(r["seed"]))[1] for r in sel])
        poisoned = clean + np.stack([np.asarray(r["du"]) for r in sel])
        t = np.arange(n)
        for ch in range(2):
            ax = axes[ch, col]
            for sig, color, label in ((clean, "tab:blue", "clean u (mean)"),
                                      (poisoned, "tab:orange", "poisoned u' (mean, 95% CI band)")):
                stats = np.array([mean_interval(sig[:, ch, j]) for j in range(n)])
                ax.step(t, stats[:, 0], where="post", color=color, label=label)
                if color == "tab:orange":
                    ax.fill_between(t, stats[:, 1], stats[:, 2], step="post", color=color, alpha=0.25)
            ax.set_ylabel(f"u_{ch + 1} (input units)")
            ax.set_title(f"N={n}, delta_u={d:g}: mean of {len(sel)} destabilized loops" if ch == 0 else "")
        axes[1, col].set_xlabel("t (samples)")
    handles, labels = next(((h, lab) for ax in axes.flat for h, lab in [ax.get_legend_handles_labels()] if h), ([], []))
    if handles:
        fig.legend(handles, labels, loc="outside upper center", ncols=2, fontsize=8)
    return save_figure(fig, out_dir, "fig9_signals"), used


# -- the report -----------------------------------------------------------------------------------------------
def _first(summary: dict[tuple, dict[str, float]], n: int, method: str, deltas: tuple[float, ...],
           level: float) -> str:
    for d in deltas:
        c = summary.get((n, method, d))
        if c is not None and c["n"] and c["rate"] >= level:
            return f"{d:g}"
    return f"> {deltas[-1]:g}"


def _timing(summary: dict[tuple, dict[str, float]], plan: Plan) -> str:
    lines = ["| N | ours: median s / attack | DE: median s / attack | DE / ours | ours: CPU s (all) "
             "| DE: CPU s (all) |",
             "|---|---|---|---|---|---|"]
    for n in plan.horizons:
        hg = [c for (m_n, m, _), c in summary.items() if m_n == n and m == "hypergradient"]
        de = [c for (m_n, m, _), c in summary.items() if m_n == n and m == "differential-evolution"]
        if not hg or not de:
            continue
        t_hg = float(np.median([c["time_median"] for c in hg]))
        t_de = float(np.median([c["time_median"] for c in de]))
        lines.append(f"| {n} | {t_hg:.3f} | {t_de:.3f} | {t_de / t_hg:.1f} | {sum(c['time_total'] for c in hg):.0f} "
                     f"| {sum(c['time_total'] for c in de):.0f} |")
    return "\n".join(lines) + "\n"


def write_report(out_dir: str, plan: Plan, settings: dict[str, list], summaries: dict[str, dict],
                 figures: dict[str, str], signals: dict[int, tuple[float, int]], wall: dict[str, tuple[int, float]],
                 selection_md: str, executor: str, budget_md: str = "") -> str:
    """report.md: settings (field -> values read from the rows), tables, figures, timing and the paper's claims
    next to ours."""
    seed, learner, reg = (", ".join(map(str, settings[k])) for k in ("root_seed", "selection", "reg"))
    paper = summaries["paper"]
    hz = plan.horizons
    first = {(n, m, lv): _first(paper, n, m, plan.deltas, lv) for n in hz
             for m in ("hypergradient", "differential-evolution") for lv in (1e-9, 0.5)}
    de = {(n, lv): first[(n, "differential-evolution", lv)] for n in hz for lv in (1e-9, 0.5)}
    remark = summaries["remark"]
    remark_rates = "; ".join(f"N={n}: {_rate(c)} unstable" for (n, method, crit), c in remark.items()
                             if method == "hypergradient" and crit == "maxmin") or f"not run for `{learner}`"
    more_data = []
    for d in plan.deltas:
        a, b = paper.get((hz[0], "hypergradient", d)), paper.get((hz[-1], "hypergradient", d))
        if a and b and a["n"] and b["n"]:
            more_data.append(f"{d:g}: {100 * a['rate']:.0f}% vs {100 * b['rate']:.0f}%")
    lr = summaries["designs"]
    lqr_r = ", ".join(f"delta={d:g}: {_rate(lr.get(('lqr-r', 'u', 'eigen', d)))}" for d in plan.design_deltas)
    claims = [
        f"ours: N={hz[0]}: first unstable loop at delta_u = {first[(hz[0], 'hypergradient', 1e-9)]}, >= 50% at "
        f"{first[(hz[0], 'hypergradient', 0.5)]} (DE: {de[(hz[0], 1e-9)]}, {de[(hz[0], 0.5)]}); "
        f"N={hz[-1]}: {first[(hz[-1], 'hypergradient', 1e-9)]}, {first[(hz[-1], 'hypergradient', 0.5)]} "
        f"(DE: {de[(hz[-1], 1e-9)]}, {de[(hz[-1], 0.5)]}); for scale, u ~ N(0, 1). The R-term "
        f"design (Thm 4, eigenvalue attack, N=15): {lqr_r}.",
        f"ours (% unstable, N={hz[0]} vs N={hz[-1]}, our attack): " + "; ".join(more_data) + ".",
        f"ours (max-min attack on the states, delta_y = 1e-3, x_0 clean): {remark_rates}; see the table below.",
    ]
    lines = [
        "# Poisoning the De Persis–Tesi learners (paper appendix B): reproduction", "",
        f"Generated by `bilevel.experiments.willems.run_reproduction` on {time.strftime('%Y-%m-%d %H:%M:%S %Z')} "
        f"({platform.node()}, {os.cpu_count()} CPUs, {executor}). Settings read from the result rows: seed {seed}, "
        f"selection {learner}, reg {reg}, algorithm version {', '.join(settings['version'])}.", "",
        "## How much input poisoning destabilizes the loop", "",
        "delta_u*: per data set, the smallest budget of the grid at which the destabilizing attack (max rho) made "
        "the true loop unstable (grid resolution; `smallest_destabilizing_budget` bisects further):", "",
        budget_md, "![delta_u* CDF](fig_budget_cdf.png)", "",
        "Figure: the empirical CDF of delta_u* over the data sets (fraction of data sets destabilized at or below each "
        "input budget), per horizon.", "",
        "## Settings", "",
        "- Plant: batch reactor (Walsh & Ye 2001), Ts = 0.1, n = 4, m = 2; data: u ~ N(0, 1) white, x_0 = 0, "
        "noise free. The attacker uses [B A] = X1 [U0; X0]^+ from the clean data (equal to the plant here).",
        "- Learner (paper setting): the appendix SDP min tr(Qx X0 Q) s.t. [[X0 Q - I, X1 Q], [Q' X1', X0 Q]] >= 0, "
        + ("Qx = I (no regularization)" if learner in SOLVER_SELECTIONS else
           f"Qx = I, plus reg/2 ||Q||_F^2 with reg = {reg}") + f"; selection `{learner}` of the non-unique Q"
        + LEARNER_TEXT.get(learner, "")
        + "; see docs/willems.md. K = U0 Q (X0 Q)^-1.",
        f"- Attack: input poisoning |Du| <= delta_u entrywise (linf), criterion log det((A+BK)(A+BK)'), "
        f"delta_u in {list(plan.deltas)}, N in {list(plan.horizons)}, {plan.sims} simulations per cell "
        "(the same data for every delta and method). The destabilizing attack (`destabilize_attack`, "
        f"{plan.rho_starts} starts) maximizes rho(A_id + B_id K) = max |eig| instead, exactly (eigenvector "
        "derivatives, the learner solved once) and reports the largest radius it reached.",
        f"- Ours: projected hypergradient ascent, {plan.starts} starts (clean data + uniform in the box). "
        "DE: differential evolution (bilevel.solvers.evolution.evolve: scipy's algorithm and defaults), best1bin, "
        f"popsize {plan.de_popsize} x dim, {plan.de_max_iter} "
        "generations, no gradient polish, same box and seeds (the paper used MATLAB's particle swarm).",
        "- Stability is judged on the true plant: unstable iff max |eig(A + B K)| >= 1.", "",
        "## Fraction of unstable closed loops (paper setting)", "",
        paper_table(paper, plan),
        f"Brackets: 95% Wilson intervals over {plan.sims} simulations. CSV: `table_paper.csv`.", "",
        f"![Fig. 7]({figures['fig7']})", "",
        "Figure 7: mean max |eig(A+BK)| (black, left axis) and mean sum |eig| (red, right axis) with 95% CIs; "
        f"N={hz[0]} solid, N={hz[-1]} dashed.", "",
        f"![Fig. 8]({figures['fig8']})", "", "Figure 8: the attacker's criterion (mean, 95% CI).", "",
        f"![Fig. 9]({figures['fig9']})", "",
        "Figure 9: inputs of the loops our attack destabilized, averaged over simulations (orange band: 95% CI of "
        "the poisoned signal's mean); " + ", ".join(f"N={n}: delta_u={d:g}, {k} loops" for n, (d, k) in
                                                    signals.items()) + ".", "",
        "## Transfer to the unregularized learner", "",
        f"Our poisoning (computed against the `{learner}` selection) handed to `bilevel.ddc.lqr_controller("
        "input_cost=False)`, whose Q is whatever Clarabel returns on the optimal face:", "",
        transfer_table(paper, plan), "",
        "## Why more data does not make this learner more fragile here", "",
        "Input poisoning does not change the SDP (it has no U0), so K' = K + A_u G with G = Q (X0 Q)^-1, and "
        "|A_u| <= delta_u moves an entry of K by at most delta_u max_j sum_t |G_tj| (the gain below). Q is "
        "non-unique (any Q + N with [X0; X1] N = 0 is optimal), so the gain depends on the learner's selection; "
        "see `bilevel.experiments.willems_selection`.", "",
        selection_md,
        "A learner whose gain falls with N cannot show the paper's 'larger N destabilizes at smaller delta_u'; "
        "that needs a selection that puts a growing null-space component into Q. The paper does not name its "
        "SDP solver.", "",
        "## Timing", "", _timing(paper, plan),
        f"Wall-clock ({executor}; timings.json keeps each sweep's time across resumed runs): "
        + ", ".join(f"{k} {n} attacks in {v:.0f} s" for k, (n, v) in wall.items()) + ".", "",
        "## The paper's claims next to ours", "",
        "| claim | paper | ours |", "|---|---|---|",
        *[f"| {name} | {text} | {ours} |" for (name, text), ours in zip(PAPER_CLAIMS, claims)], "",
        f"## Output poisoning (delta_y = {DELTA_Y:g} on the states, x_0 and inputs clean)", "",
        remark_table(remark, plan) if remark else NOT_DEFINED.format(learner=learner),
        f"{plan.remark_sims} simulations per row. The last learner column re-learns K with `bilevel.ddc.lqr_controller`"
        " (no regularization, Clarabel's choice of Q) on the poisoned data our attack produced. CSV: "
        "`table_remark.csv`.", "",
        "## Other designs (our attack, N = 15)", "",
        design_table(lr, plan),
        *([NOT_DEFINED.format(learner=learner) + " Those cells show '-'."] if learner in SOLVER_SELECTIONS else []),
        f"{plan.design_sims} simulations per cell; xu poisons states and inputs with delta_x = delta_u; lqr-r is "
        "De Persis–Tesi Thm 4 (Qx = I, R = I), stabilizing is Thm 3. CSV: `table_designs.csv`.", "",
    ]
    path = os.path.join(out_dir, "report.md")
    with atomic_open(path) as fh:
        fh.write("\n".join(lines))
    return path


def run_reproduction(sims: int = 256, out_dir: str = "out/willems", quick: bool = False, seed: int = 0,
                     progress: Callable[[str], None] | None = stderr_progress, selection: str = "min-norm",
                     workers: int | None = None, dask: str | None = None) -> str:
    """Run (or resume) every sweep on `workers` local processes or the Dask cluster `dask`, then write tables
    (CSV + Markdown), figures 7-9 and report.md; returns its path.

    `selection` is the learner's choice among its optimal Q (bilevel.problems.willems): "min-norm" (default),
    "tikhonov" (the solver's Q under reg alone, as in the sweep committed in session 1), or the SDP solver's own Q
    ("clarabel", "scs"; defined only for input poisoning without an input cost, so the state-poisoning remark and
    those designs are not run, and the report says so)."""
    plan = make_plan(sims, quick)
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    os.makedirs(out_dir, exist_ok=True)
    sweeps = {"paper": (paper_tasks(plan, seed, selection), ("horizon", "method", "delta_u")),
              "remark": (remark_tasks(plan, seed, selection), ("horizon", "method", "criterion")),
              "designs": (design_tasks(plan, seed, selection), ("design", "poison", "criterion", "delta_u"))}
    sweeps = {name: ([t for t in tasks if selection_applies(selection, t["poison"], t["design"])], fields)
              for name, (tasks, fields) in sweeps.items()}
    rows, summaries = {}, {}
    with open_executor(workers, dask) as executor:
        for name, (tasks, fields) in sweeps.items():
            rows[name] = run_sweep(attack_task, tasks, os.path.join(out_dir, f"{name}.jsonl"), executor, progress,
                                   f"willems-{name}", valid_row, timing=name, reference=committed_timings("willems"))
            summaries[name] = summarize(rows[name], fields)
            write_csv(summaries[name], fields, os.path.join(out_dir, f"table_{name}.csv"))
    wall = load_timings(os.path.join(out_dir, "timings.json"), progress)
    tables = {"paper": paper_table, "remark": remark_table, "designs": design_table}
    for name, fn in tables.items():
        with atomic_open(os.path.join(out_dir, f"table_{name}.md")) as fh:
            fh.write(fn(summaries[name], plan))
    fig9, signals = figure_signals(rows["paper"], summaries["paper"], plan, out_dir)
    figures = {"fig7": figure_eigenvalues(summaries["paper"], plan, out_dir),
               "fig8": figure_objective(summaries["paper"], plan, out_dir), "fig9": fig9}
    with atomic_open(os.path.join(out_dir, "plan.json")) as fh:
        json.dump({**asdict(plan), "seed": seed, "reg": DEFAULT_REG, "selection": selection}, fh, indent=2)
    selection_md = selection_table(plan.horizons, [s for s, _ in sim_seeds(seed, min(plan.sims, 64))], out_dir)
    with atomic_open(os.path.join(out_dir, "table_selection.md")) as fh:
        fh.write(selection_md)
    every = [r for rs in rows.values() for r in rs]
    settings = settings_of(every, "root_seed", "selection", "reg") | {"version": sorted({r["version"] for r in every})}
    from .willems_budget import write_outputs  # willems_budget reads this module's sim_seeds

    budget_md = write_outputs(path_thresholds(rows["paper"]), out_dir)
    path = write_report(out_dir, plan, settings, summaries, figures, signals, wall, selection_md,
                        executor.description, budget_md)
    if progress:
        progress(f"wrote {path}")
    return path
