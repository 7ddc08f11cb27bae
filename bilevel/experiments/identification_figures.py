"""Figures and report.md of `bilevel reproduce identification` (matplotlib, Agg; PNG and PDF)."""

from __future__ import annotations

import json
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from ..files import save_figure  # noqa: E402
from ..problems.identification import STATISTICS  # noqa: E402
from .identification import Plan, cells, compare  # noqa: E402
from .identification_baseline import SLSQP_ITERATIONS, START_SCALE  # noqa: E402

Rows = list[dict[str, Any]]
ENGINE, BASELINE, BEFORE = "tab:blue", "tab:orange", "0.6"
TEST_NAMES = {"variance": "residual variance (chi-square)", "whiteness": "whiteness, 10 lags (portmanteau)",
              "input": "input contribution (F-test)"}
BUDGET_TEXT = "budget ||dX||_F/||X||_F = ||dU||_F/||U||_F = delta, stealth |1 - stat'/stat| <= delta"


def _boxes(ax: plt.Axes, groups: list[tuple[list[float], str]], deltas: list[float]) -> None:
    """Box plots at each delta, one box per (values per delta, colour) group side by side."""
    width = 0.8 / len(groups)
    for j, (values, colour) in enumerate(groups):
        pos = np.arange(len(deltas)) + (j - (len(groups) - 1) / 2) * width
        data = [v if len(v) else [np.nan] for v in values]
        ax.boxplot(data, positions=pos, widths=0.9 * width, patch_artist=True, manage_ticks=False,
                   boxprops={"facecolor": colour, "alpha": 0.6}, medianprops={"color": "k"},
                   flierprops={"markersize": 3})
    ax.set_xticks(np.arange(len(deltas)), [f"{d:g}" for d in deltas])
    ax.set_xlabel("delta (relative data change = stealth tolerance)")
    ax.grid(axis="y", alpha=0.3)


def _by_cell(rows: Rows, T: int, deltas: list[float], get: Any) -> list[list[float]]:
    by = cells(rows)
    return [[get(r) for r in by.get((T, d), [])] for d in deltas]


def _grid(rows: Rows) -> tuple[list[int], list[float]]:
    return sorted({r["task"]["T"] for r in rows}), sorted({r["task"]["delta"] for r in rows})


def _method(rows: Rows) -> str:
    """The engine's method name(s) in the rows' tasks (each task's method is its JSON options)."""
    return ", ".join(sorted({json.loads(r["task"]["method"]).get("method", "auto") for r in rows})) or "none"


def figure_error(rows: Rows, baseline: Rows, out_dir: str) -> str:
    """||d[A B]||_2 of the stealthy results per delta, engine (every data set) and SLSQP (its subset), one panel per
    T."""
    horizons, deltas = _grid(rows)
    fig, axes = plt.subplots(1, len(horizons), figsize=(5.5 * len(horizons), 4), squeeze=False, layout="constrained")
    for ax, T in zip(axes[0], horizons):
        stealthy = lambda rs: [r for r in rs if r["stealthy"]]  # noqa: E731
        groups = [(_by_cell(stealthy(rows), T, deltas, lambda r: r["norm2"]), ENGINE)]
        if baseline:
            groups.append((_by_cell(stealthy(baseline), T, deltas, lambda r: r["norm2"]), BASELINE))
        _boxes(ax, groups, deltas)
        ax.set_yscale("log")
        ax.set_ylabel("||[A B]' - [A B]_clean||_2 (dimensionless)")
        n, nb = len(cells(rows).get((T, deltas[0]), [])), len(cells(baseline).get((T, deltas[0]), []))
        ax.set_title(f"T = {T}: identified model's error\n{BUDGET_TEXT}", fontsize=8)
        ax.legend([Patch(color=ENGINE, alpha=0.6), Patch(color=BASELINE, alpha=0.6)],
                  [f"engine ({_method(rows)}), {n} data sets", f"SLSQP baseline, first {nb} data sets",
                   ][:len(groups)], fontsize=7, title="stealthy results only (counts in report.md)", title_fontsize=7,
                  loc="upper left")
    return save_figure(fig, out_dir, "error_norm")


def figure_statistics(rows: Rows, out_dir: str) -> str:
    """Residual norm ||E||_F and whiteness statistic Q before and after the attack, per delta and T."""
    horizons, deltas = _grid(rows)
    fig, axes = plt.subplots(2, len(horizons), figsize=(5.5 * len(horizons), 7), squeeze=False, layout="constrained")
    quantities = (("residual norm ||E||_F (state units)", lambda r, w: r["residual_norm"][w]),
                  ("whiteness statistic Q (dimensionless)", lambda r, w: r[w]["whiteness"]["statistic"]))
    for i, (label, get) in enumerate(quantities):
        for ax, T in zip(axes[i], horizons):
            _boxes(ax, [(_by_cell(rows, T, deltas, lambda r: get(r, "before")), BEFORE),
                        (_by_cell(rows, T, deltas, lambda r: get(r, "after")), ENGINE)], deltas)
            ax.set_ylabel(label)
            ax.set_title(f"T = {T}; {BUDGET_TEXT}", fontsize=8)
    fig.legend([Patch(color=BEFORE, alpha=0.6), Patch(color=ENGINE, alpha=0.6)],
               ["clean data (before)", "poisoned by the stealthy attack (after)"], loc="outside upper center", ncols=2,
               fontsize=8)
    return save_figure(fig, out_dir, "statistics")


def figure_p_values(rows: Rows, out_dir: str) -> str:
    """Each test's p-value before and after the attack, per delta and T, with the 5% level."""
    horizons, deltas = _grid(rows)
    fig, axes = plt.subplots(len(STATISTICS), len(horizons), figsize=(5.5 * len(horizons), 9.5), squeeze=False,
                             layout="constrained")
    for i, name in enumerate(STATISTICS):
        for ax, T in zip(axes[i], horizons):
            # the input test's p-values are tiny (the input drives the plant): on a log10 scale, floored at 1e-300
            scale = (lambda p: np.log10(max(p, 1e-300))) if name == "input" else (lambda p: p)
            _boxes(ax, [(_by_cell(rows, T, deltas, lambda r: scale(r["before"][name]["p_value"])), BEFORE),
                        (_by_cell(rows, T, deltas, lambda r: scale(r["after"][name]["p_value"])), ENGINE)], deltas)
            line = ax.axhline(scale(0.05), color="r", ls="--", lw=0.8)
            ax.set_ylabel("log10 p-value" if name == "input" else "p-value")
            if name != "input":
                ax.set_ylim(0, 1)
            ax.set_title(f"{TEST_NAMES[name]}, T = {T}\n{BUDGET_TEXT}", fontsize=8)
    fig.legend([Patch(color=BEFORE, alpha=0.6), Patch(color=ENGINE, alpha=0.6), line],
               ["clean data (before)", "poisoned (after)", "5% level: below it the test rejects"],
               loc="outside upper center", ncols=3, fontsize=8)
    return save_figure(fig, out_dir, "p_values")


def make_all(rows: Rows, baseline: Rows, out_dir: str) -> dict[str, str]:
    """Every figure (file names by key)."""
    return {"error": figure_error(rows, baseline, out_dir), "statistics": figure_statistics(rows, out_dir),
            "p_values": figure_p_values(rows, out_dir)}


def _q(values: list[float]) -> str:
    if not values:
        return "-"
    lo, mid, hi = np.quantile(values, [0.25, 0.5, 0.75])
    return f"{mid:.3g} [{lo:.3g}, {hi:.3g}]"


def _rate(values: list[bool]) -> str:
    return f"{sum(values)}/{len(values)}"


def report(rows: Rows, baseline: Rows, figures: dict[str, str], plan: Plan, timings: dict[str, tuple[int, float]],
           executor: str, settings: dict[str, list]) -> str:
    """report.md: the setting, the engine's attack per cell (error, stealth, statistics, p-values), the SLSQP
    baseline side by side, and the figures."""
    by, by_base, vs = cells(rows), cells(baseline), compare(rows, baseline)
    all_pairs = sum(c["n"] for c in vs.values())
    all_wins = sum(c["at_least_baseline"] for c in vs.values())
    parts = [
        "# Stealthy poisoning of state-space identification (`bilevel reproduce identification`; the project's own "
        "stealth definition, stealth_kind \"tests\")", "",
        "Plant: the flexible transmission (Landau 1995, Ts = 0.05 s) in controllable canonical state-space form "
        "(4 states, 1 input), x+ = A x + B u + w, u ~ N(0, 1), w ~ N(0, 0.1^2 I), x_0 = 0. Learner: least squares "
        "[A B] = argmin ||X+ - [A B][X; U]||_F^2. Attacker: changes X and U with ||dX||_F <= delta ||X||_F and "
        "||dU||_F <= delta ||U||_F, maximizes ||[A B]' - [A B]_clean||_F^2, and keeps each of the defender's three "
        "statistics (residual variance against the known noise variance, portmanteau whiteness over 10 lags, F-test "
        "of the input's contribution) within |1 - stat'/stat| <= delta of its clean value.", "",
        f"Grid: T in {list(plan.horizons)}, delta in {list(plan.deltas)}, {plan.sims} data sets per cell (the same "
        "data in every delta cell of a T). Engine: `bilevel.solve` with the method and options under \"Settings "
        "read from the rows\" below, from the conditioning start scaled into the stealth constraints. Baseline: "
        "scipy SLSQP with "
        f"exact gradients on the same program with the learner in closed form, {SLSQP_ITERATIONS} iterations, from a "
        f"random point at {START_SCALE} x the budget radii, on the first {plan.baseline_sims} data sets of each "
        "cell. Every number below is the defender's: a numpy refit of the returned data, judged by "
        "bilevel.ddc.residual_tests (not the solver's own values).", "",
        "Settings read from the rows: " + "; ".join(f"{k.removeprefix('root_')} {', '.join(map(str, v))}"
                                                    for k, v in settings.items()) + ".", "",
        f"Run on {executor}. Wall time of the sweeps (`timings.json`; a resumed sweep records only the rows it "
        "added): " + ("; ".join(f"{k}: {n} attacks in {t:.0f} s" for k, (n, t) in timings.items()) or "none") + ".",
        "",
        "## Summary", "",
        f"- Stealthy (every statistic within delta of its clean value, checked on the refit): "
        f"{_rate([r['stealthy'] for r in rows])} engine attacks; solved and certified: "
        f"{_rate([r['status'] == 'solved' and r['certified'] for r in rows])}.",
        f"- Engine stealthy and ||d[A B]||_2 at least SLSQP's (or SLSQP not stealthy): {all_wins}/{all_pairs} data "
        "sets the baseline ran.",
        f"- CPU time per attack (one BLAS thread per worker; CPU time is little affected by other load), median: "
        f"engine {np.median([r['cpu_time'] for r in rows]):.2f} s, SLSQP "
        + (f"{np.median([r['cpu_time'] for r in baseline]):.2f} s" if baseline else "-")
        + f"; total: engine {sum(r['cpu_time'] for r in rows):.0f} s for {len(rows)} attacks, SLSQP "
        f"{sum(r['cpu_time'] for r in baseline):.0f} s for {len(baseline)}. Before its first attack of a T, each "
        "worker process declares and compiles the engine's problem by a warm-up attack on data no task uses: "
        f"{sum(r['warm_up_cpu_time'] for r in rows):.1f} s in all, in the sweep's wall time and in no "
        "attack's.", "",
        "## The engine's attack, per cell", "",
        "‖d[A B]‖₂: median [25%, 75%] over the stealthy runs; ‖E‖_F, Q and CPU time: medians over all runs (a failed, "
        "non-stealthy one included).", "",
        "| T | delta | stealthy | solved+certified | ‖d[A B]‖₂ (stealthy runs) | max rel. change (all runs) | ‖E‖_F before -> after | "
        "Q before -> after | CPU time (s) |", "|---|---|---|---|---|---|---|---|---|",
    ]
    for (T, d), rs in sorted(by.items()):
        parts.append(
            f"| {T} | {d:g} | {_rate([r['stealthy'] for r in rs])} | "
            f"{_rate([r['status'] == 'solved' and r['certified'] for r in rs])} | "
            f"{_q([r['norm2'] for r in rs if r['stealthy']])} | "
            f"{max(r['max_relative_change'] for r in rs):.4f} | "
            f"{np.median([r['residual_norm']['before'] for r in rs]):.3f} -> "
            f"{np.median([r['residual_norm']['after'] for r in rs]):.3f} | "
            f"{np.median([r['before']['whiteness']['statistic'] for r in rs]):.1f} -> "
            f"{np.median([r['after']['whiteness']['statistic'] for r in rs]):.1f} | "
            f"{np.median([r['cpu_time'] for r in rs]):.2f} |")
    parts += ["", "## The defender's tests: median p-value before -> after, and rejections at 5% before -> after", "",
              "| T | delta | " + " | ".join(TEST_NAMES[k] for k in STATISTICS) + " |",
              "|---|---|" + "---|" * len(STATISTICS)]
    for (T, d), rs in sorted(by.items()):
        parts.append(f"| {T} | {d:g} | " + " | ".join(
            f"{np.median([r['before'][k]['p_value'] for r in rs]):.3g} -> "
            f"{np.median([r['after'][k]['p_value'] for r in rs]):.3g} "
            f"(rejects {sum(r['before'][k]['p_value'] < 0.05 for r in rs)} -> "
            f"{_rate([r['after'][k]['p_value'] < 0.05 for r in rs])})" for k in STATISTICS) + " |")
    parts += ["", "The input test rejects on clean data too (the input does drive the plant): a stealthy attack keeps "
              "it rejecting.", "",
              "## Side by side: SLSQP baseline on the same data sets", "",
              "| T | delta | data sets | SLSQP stealthy | SLSQP ‖d[A B]‖₂ (stealthy runs) | engine ‖d[A B]‖₂ (its stealthy runs "
              "on the same sets) | "
              "engine >= SLSQP | SLSQP CPU time (s) | median CPU-time ratio SLSQP/engine |",
              "|---|---|---|---|---|---|---|---|---|"]
    for (T, d), bs in sorted(by_base.items()):
        engine = {r["key"]: r for r in by.get((T, d), [])}
        c = vs.get((T, d), {"n": 0, "at_least_baseline": 0, "time_ratio": float("nan")})
        parts.append(f"| {T} | {d:g} | {len(bs)} | {_rate([b['stealthy'] for b in bs])} | "
                     f"{_q([b['norm2'] for b in bs if b['stealthy']])} | "
                     f"{_q([engine[b['key']]['norm2'] for b in bs if b['key'] in engine and engine[b['key']]['stealthy']])}"
                     f" | {c['at_least_baseline']}/{c['n']} | {np.median([b['cpu_time'] for b in bs]):.2f} | "
                     f"{c['time_ratio']:.1f}x |")
    parts += ["", "## Figures", "",
              f"![||d[A B]||_2 per budget]({figures['error']})", "",
              "Figure 1: the identified model's error ||[A B]' - [A B]_clean||_2 of the stealthy answers per budget "
              "delta (box: quartiles, whiskers 1.5 IQR, circles beyond), the engine on every data set and the SLSQP "
              "baseline on its subset; one panel per T.", "",
              f"![residual norm and whiteness statistic before and after]({figures['statistics']})", "",
              "Figure 2: the residual norm ||E||_F (state units) and the whiteness statistic Q of the fit on the clean "
              "(grey) and the poisoned (blue) data, per budget; one column per T.", "",
              f"![p-values of the three tests before and after]({figures['p_values']})", "",
              "Figure 3: each residual test's p-value on the clean and the poisoned data, per budget (red: the 5 % "
              "level, below which the test rejects); the input test's on a log10 scale.", ""]
    return "\n".join(parts)
