"""The robustness frontier of the defended learners (issue 29): per learner x defense setting, the clean-data
performance cost against the poisoning margin delta*, the smallest budget at which the adaptive attack (the generic
engine on the defended lower level) makes the true closed loop unstable (VRFT, De Persis–Tesi) or, for learners a
bounded attack cannot destabilize, degrades the learner's performance by FACTOR (identification, DeePC), with
confidence intervals over data sets.

VRFT (scenario B, measurement noise 2% of std(y), the destabilizing criterion: the ARX-modelled loop's spectral
radius): budgets eps_u = eps_y = eps (relative l2), the attack `solve(defended problem, starts=2)`, judged by the true
loop of the defended learner re-solved in closed form at the attack's poisoning; clean cost: the model-reference cost.
De Persis–Tesi (batch reactor, design lqr, input poisoning): delta_u* by bilevel.attacks.willems.
smallest_destabilizing_budget on the regularized learner; clean cost: the true loop's H2 cost trace(Qx W).
Identification (flexible transmission, "ss" data, T samples; least squares, Huber, LAD): budgets eps on both signals
(relative Frobenius), the attack `solve(defended problem, starts=1)`, judged by the learner re-solved by cvxpy; the
performance is the error ||[A B] - [A B]_true||_F. DeePC (flexible transmission, T samples, horizon DEEPC_HORIZON;
lambda_g swept): budgets eps on both signals (relative l2), the attack `solve(deepc-tracking, starts=1)`, judged by
the learner re-solved by cvxpy; the performance is the true plant's tracking cost of the plan.
delta* per data set comes from the package's budget search (bilevel.attacks.budget_search: an increasing path, then
bisection); a setting's margin is the median of delta* over data sets (half of the data sets destabilized), with its
order-statistic interval; the clean cost's mean has a t interval. One resumable sweep task per data set and setting.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ..result import Status  # noqa: E402
from ..files import atomic_open, atomic_path, write_rows_csv  # noqa: E402
from ..problems import defended_deepc, defended_identification  # noqa: E402
from ..problems.deepc import declare as declare_deepc  # noqa: E402
from ..problems.deepc_instance import attack_instance as deepc_instance  # noqa: E402
from ..kept import kept  # noqa: E402
from ..problems.defended_vrft import budget_values, declare, defended_instance, model_reference_cost  # noqa: E402
from ..problems.willems import kept_attack  # noqa: E402
from ..problems.willems_instance import WillemsAttack, WillemsSetting, criterion_values  # noqa: E402
from ..attacks.budget_search import smallest_budget  # noqa: E402
from ..solvers.engine.block_exact import SINGULAR_LEARNER  # noqa: E402
from ..solvers.registry import solve  # noqa: E402
from .defenses_detection import FAMILIES, run_detection  # noqa: E402
from .executor import open_executor  # noqa: E402
from .stats import mean_interval, median_interval  # noqa: E402
from .willems_budget import smallest_destabilizing_budget  # noqa: E402
from .sweep import (NUMBER, check_fields, check_subset, committed_timings, run_sweep, sim_seeds,  # noqa: E402
                    stderr_progress)

LEARNERS = ("vrft", "willems", "ident", "deepc")
"""The learners of the sweep, in run order (`learners` of run_defenses picks a subset)."""
ROW_SCHEMA = {"learner": str, "defense": str, "param": NUMBER, "N": int, "data_seed": int, "clean_cost": NUMBER,
              "delta_star": NUMBER, "attacks": int}
"""A row's fields (delta_star inf: goal not reached on the budget path)."""
VRFT_SETTINGS = (("none", 0.0), ("ridge", 1e-4), ("ridge", 1e-3), ("ridge", 1e-2), ("iv", 0.0), ("iv-trusted", 0.0))
WILLEMS_REGS = (1e-8, 1e-2, 1e-1, 1.0)
IDENT_SETTINGS = (("ls", 0.0), ("huber", defended_identification.HUBER_K), ("lad", 0.0))
DEEPC_LAMBDA_G = (0.1, 1.0, 10.0, 100.0)
DEEPC_HORIZON = 6
VRFT_PATH = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
"""Relative l2 budgets eps (= eps_u = eps_y) tried in order before bisection."""
IDENT_PATH = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1)
DEEPC_PATH = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
FACTOR = 2.0
"""Identification and DeePC: the goal is an attacked performance (error, tracking cost) >= FACTOR x the clean one."""
COST_LABEL = {"vrft": "model-reference cost", "willems": "H2 cost", "ident": "identification error",
              "deepc": "tracking cost"}
BASELINE = {"vrft": "none", "ident": "ls"}
"""The undefended setting of a learner (the others: its smallest parameter)."""
REL_TOL = 0.1
"""The budget search's final bracket, relative to its top."""


def clean_gain(attack: WillemsAttack) -> np.ndarray:
    """The learner's gain on the clean data (the engine's SDP lower level solved at zero poisoning, on the radius
    problem that destabilize_attack then searches: one learner solve per data set serves both)."""
    zero = np.zeros(int(attack.upper.numel()))
    return attack.loop(zero, attack.oracle(radius=True).evaluate(zero).lower.y)[0]


def h2_cost(attack: WillemsAttack, gain: np.ndarray) -> float:
    """The true closed loop's H2 cost trace((Qx + K' R K) W), W = Acl W Acl' + I, with the learner's Qx and R (R = 0
    for the designs without an input cost: the cost the SDP minimizes); inf where A + B K is unstable."""
    return float(criterion_values(attack.true_closed_loop(gain), gain, "maxmin", attack.qx, attack.cost_weight))


def clean_performance(attack: WillemsAttack) -> float:
    """h2_cost of the gain learned from the clean data."""
    return h2_cost(attack, clean_gain(attack))


@dataclass(frozen=True)
class Plan:
    """The run's size: data sets per setting, the VRFT record length, the De Persis–Tesi horizons, the samples of the
    identification and DeePC data."""

    sims: int
    vrft_n: int
    horizons: tuple[int, ...]
    ident_t: int
    deepc_t: int


def make_plan(sims: int, quick: bool) -> Plan:
    """The issue's plan (N = 512; horizons 15 and 50; identification T = 100, DeePC T = 200; `sims` data sets), or
    the small plan (<= 8 sims: the fewest with a finite 95% interval of the median; N = 128, T = 15, identification
    T = 25, DeePC T = 60)."""
    if quick:
        return Plan(min(sims, 8), 128, (15,), 25, 60)
    return Plan(sims, 512, (15, 50), 100, 200)


KEPT_DECLARED = 2
"""Defended VRFT problems (one per data set and setting) a process keeps for the budget search's next radius."""
_DECLARED: dict[tuple, Any] = {}


def vrft_radius(defense: str, lam: float, N: int, seed: int, eps: float, attack_seed: int) -> float:
    """The true closed loop's spectral radius after the adaptive attack at budget eps; inf where a start of the attack
    made the learner's system singular (the IV matrix Z' Phi: the start record's SINGULAR_LEARNER field; the learner
    returns no controller) or no start could be solved."""
    d = defended_instance(defense, "destabilize", lam, "B", eps, eps, seed, N)
    problem = kept(_DECLARED, (defense, lam, N, seed), lambda: declare(d), KEPT_DECLARED)[0]
    for name, value in budget_values(d).items():  # the budget search's next radius, on the problem prepared once
        problem.set_value(name, value)
    result = solve(problem, starts=2, seed=attack_seed)
    if result.status is Status.ERROR or any(r.get(SINGULAR_LEARNER) for r in result.start_records):
        return float("inf")
    x = {k: np.asarray(v, dtype=float).ravel() for k, v in result.x.items()}
    return d.atk.setting.loop.spectral_radius(d.poisoned(**x))


def ident_error(loss: str, T: int, seed: int, eps: float, attack_seed: int) -> float:
    """The identification error ||[A B] - [A B]_true||_F of the learner `loss` after the adaptive attack at budget eps
    (the learner re-solved at the attack's poisoning)."""
    d = defended_identification.defended_instance(loss, T, eps, seed)
    result = solve(defended_identification.declare(d), starts=1, seed=attack_seed)
    A, B = d.atk.setting.state_space
    return float(np.linalg.norm(d.poisoned(result.x["dX"], result.x["dU"]) - np.hstack([A, B])))


def deepc_cost(lambda_g: float, T: int, seed: int, eps: float, attack_seed: int) -> float:
    """The true tracking cost of DeePC's plan (weight lambda_g) after the adaptive attack at budget eps (the learner
    re-solved at the attack's poisoning)."""
    atk = deepc_instance(T=T, eps=eps, seed=seed, horizon=DEEPC_HORIZON, lambda_g=lambda_g)
    result = solve(declare_deepc(atk), starts=1, seed=attack_seed)
    return defended_deepc.attacked_performance(atk, result.x["du"], result.x["dy"])


def degraded(clean: float) -> Callable[[float], bool]:
    """The degradation goal: an attacked performance >= FACTOR x the clean one."""
    return lambda value: value >= FACTOR * clean


def frontier_task(task: dict[str, Any]) -> dict[str, Any]:
    """Clean cost and delta* of one data set under one setting (task: learner, defense, param, N, seed,
    attack_seed)."""
    if task["learner"] == "ident":
        cost = defended_identification.defended_instance(task["defense"], task["N"], 0.0,
                                                         task["seed"]).clean_performance()
        found = smallest_budget(lambda eps: ident_error(task["defense"], task["N"], task["seed"], eps,
                                                        task["attack_seed"]), degraded(cost), IDENT_PATH, REL_TOL)
    elif task["learner"] == "deepc":
        cost = defended_deepc.clean_performance(deepc_instance(T=task["N"], seed=task["seed"], horizon=DEEPC_HORIZON,
                                                               lambda_g=task["param"]))
        found = smallest_budget(lambda eps: deepc_cost(task["param"], task["N"], task["seed"], eps,
                                                       task["attack_seed"]), degraded(cost), DEEPC_PATH, REL_TOL)
    elif task["learner"] == "vrft":
        d = defended_instance(task["defense"], "destabilize", task["param"], "B", 0.1, 0.1, task["seed"], task["N"])
        cost = model_reference_cost(d.atk.setting, d.theta_clean)
        found = smallest_budget(lambda eps: vrft_radius(task["defense"], task["param"], task["N"], task["seed"], eps,
                                                        task["attack_seed"]), lambda rho: rho >= 1.0, VRFT_PATH,
                                REL_TOL)
    else:
        setting = WillemsSetting(objective="destabilize", horizon=task["N"], seed=task["seed"], reg=task["param"])
        cost = clean_performance(kept_attack(setting))
        found = smallest_destabilizing_budget(setting, rel_tol=REL_TOL, starts=8, seed=task["attack_seed"])
    return {"learner": task["learner"], "defense": task["defense"], "param": task["param"], "N": task["N"],
            "data_seed": task["seed"], "clean_cost": cost, "delta_star": found.delta, "attacks": len(found.runs)}


def check_learners(learners: Sequence[str] | None) -> tuple[str, ...]:
    """The learners to run, in LEARNERS' order (None: all); an unknown or repeated name, or none, is refused."""
    return check_subset(learners, LEARNERS, "learner", "defenses learners")


def frontier_tasks(plan: Plan, seed: int, learners: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """One task per (setting, data set) of the chosen learners (check_learners; None: all); data set i has the same
    seeds in every setting, whichever learners run."""
    chosen = check_learners(learners)
    seeds = list(enumerate(zip(sim_seeds(seed, plan.sims), sim_seeds(seed + 1, plan.sims))))
    settings = [("vrft", defense, lam, plan.vrft_n) for defense, lam in VRFT_SETTINGS]
    settings += [("willems", "ridge", reg, n) for n in plan.horizons for reg in WILLEMS_REGS]
    settings += [("ident", loss, k, plan.ident_t) for loss, k in IDENT_SETTINGS]
    settings += [("deepc", "ridge", lam, plan.deepc_t) for lam in DEEPC_LAMBDA_G]
    return [{"key": f"{learner}|{defense}|{param:g}|N={n}|sim={i}", "learner": learner, "defense": defense,
             "param": param, "N": n, "seed": data_seed, "attack_seed": attack_seed, "root_seed": seed}
            for learner, defense, param, n in settings if learner in chosen
            for i, (data_seed, attack_seed) in seeds]


def _baseline(learner: str, N: int, rows: list[dict[str, Any]]) -> dict[int, dict[str, Any]]:
    """The undefended setting's rows by data seed: BASELINE's defense (VRFT, identification), else the smallest
    parameter (De Persis–Tesi's reg, DeePC's lambda_g)."""
    own = [r for r in rows if (r["learner"], r["N"]) == (learner, N)]
    if learner in BASELINE:
        own = [r for r in own if r["defense"] == BASELINE[learner]]
    else:
        own = [r for r in own if r["param"] == min(q["param"] for q in own)]
    return {r["data_seed"]: r for r in own}


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per setting: data sets, mean clean cost with its 95% t interval, median delta* with its 95% interval, how
    many data sets did not reach the goal on the path, and paired with the undefended learner on the same data sets
    (_baseline): the median ratios of clean cost and of delta*, and on how many data sets delta* is larger."""
    out = []
    for key in sorted({(r["learner"], r["defense"], r["param"], r["N"]) for r in rows}):
        rs = [r for r in rows if (r["learner"], r["defense"], r["param"], r["N"]) == key]
        cost = mean_interval(np.array([r["clean_cost"] for r in rs]))
        delta = np.array([r["delta_star"] for r in rs])
        base = _baseline(key[0], key[3], rows)
        pairs = [(r, base[r["data_seed"]]) for r in rs if r["data_seed"] in base]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratios = np.array([[r["clean_cost"] / b["clean_cost"], r["delta_star"] / b["delta_star"]]
                               for r, b in pairs])
        out.append({"learner": key[0], "defense": key[1], "param": key[2], "N": key[3], "data_sets": len(rs),
                    "clean_cost": cost[0], "clean_cost_low": cost[1], "clean_cost_high": cost[2],
                    "unstable_clean": int(sum(not np.isfinite(r["clean_cost"]) for r in rs)),
                    **dict(zip(("delta_star", "delta_star_low", "delta_star_high"), median_interval(delta))),
                    "not_destabilized": int(np.isinf(delta).sum()),
                    "paired": len(pairs), "cost_ratio": float(np.median(ratios[:, 0])) if pairs else float("nan"),
                    "delta_ratio": float(np.median(ratios[:, 1])) if pairs else float("nan"),
                    "delta_larger": int(sum(r["delta_star"] > b["delta_star"] for r, b in pairs)),
                    "delta_smaller": int(sum(r["delta_star"] < b["delta_star"] for r, b in pairs))})
    return out


def summary_markdown(summary: list[dict[str, Any]]) -> str:
    """The frontier table: one line per setting."""
    lines = ["| learner | defense | parameter | N | data sets | clean cost (mean, 95% CI) | median delta* (95% CI) | "
             "goal not reached | paired with undefended: cost ratio, delta* ratio (medians) | "
             "delta* larger / smaller |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['learner']} | {s['defense']} | {s['param']:g} | {s['N']} | {s['data_sets']} | "
                     f"{s['clean_cost']:.4g} ({s['clean_cost_low']:.4g} - {s['clean_cost_high']:.4g}) | "
                     f"{s['delta_star']:.3g} ({s['delta_star_low']:.3g} - {s['delta_star_high']:.3g}) | "
                     f"{s['not_destabilized']} | {s['cost_ratio']:.3g}, {s['delta_ratio']:.3g} | "
                     f"{s['delta_larger']} / {s['delta_smaller']} of {s['paired']} |")
    return "\n".join(lines) + "\n"


def learners_line(learners: Sequence[str] | None = None) -> str:
    """The sentence naming the learners run (check_learners) and those left out."""
    run = check_learners(learners)
    left = [name for name in LEARNERS if name not in run]
    return f"Learners run: {', '.join(run)}" + (f" (not run: {', '.join(left)})." if left else " (all).")


def _annotate_apart(ax: Any, labels: list[tuple[float, float, str, Any]], near: float = 0.04) -> None:
    """Each point's parameter label in its series' colour; points of one series closer than `near` of the panel's
    width and height share one label ("a, b"), and a label that would overlap one already placed moves up a line."""
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    merged: list[list[Any]] = []
    for x, y, text, color in labels:
        for spot in merged:
            if abs(x - spot[0]) <= near * (x1 - x0) and abs(y - spot[1]) <= near * (y1 - y0) and spot[3] == color:
                spot[2].append(text)
                break
        else:
            merged.append([x, y, [text], color])
    to_points = 72.0 / ax.figure.dpi
    boxes: list[tuple[float, float, float, float]] = []  # placed labels (left, bottom, right, top) in points
    for x, y, texts, color in merged:
        text = ", ".join(texts)
        px, py = (v * to_points for v in ax.transData.transform((x, y)))
        width, height = 4.6 * len(text) + 3.0, 9.0  # fontsize 7, with a little space
        lift = 0
        while any(px + 4 < r and l < px + 4 + width and py + 4 + 9 * lift < t and b < py + 4 + 9 * lift + height
                  for l, b, r, t in boxes):
            lift += 1
        boxes.append((px + 4, py + 4 + 9 * lift, px + 4 + width, py + 4 + 9 * lift + height))
        ax.annotate(text, (x, y), fontsize=7, color=color, textcoords="offset points", xytext=(4, 4 + 9 * lift))


def frontier_figure(summary: list[dict[str, Any]], learners: Sequence[str] | None = None) -> Figure:
    """Median delta* against mean clean cost, one panel per learner in the rows, with both 95% intervals (an infinite
    end is drawn to the panel's edge); the title is learners_line."""
    learners_run = learners_line(learners)
    learners = sorted({s["learner"] for s in summary})
    fig = Figure(figsize=(5.0 * len(learners), 4.1))
    fig.suptitle(learners_run, fontsize=9)
    panels = []
    for i, learner in enumerate(learners):
        ax = fig.add_subplot(1, len(learners), i + 1)
        groups = sorted({(s["defense"], s["N"]) for s in summary if s["learner"] == learner})
        labels: list[tuple[float, float, str, Any]] = []
        for defense, n in groups:
            ss = [s for s in summary if (s["learner"], s["defense"], s["N"]) == (learner, defense, n)]
            x = np.array([s["clean_cost"] for s in ss])
            y = np.array([s["delta_star"] for s in ss])
            top = 1.5 * max([v for s in ss for v in (s["delta_star"], s["delta_star_high"]) if np.isfinite(v)],
                            default=1.0)
            ylo = y - np.array([s["delta_star_low"] if np.isfinite(s["delta_star_low"]) else 0.0 for s in ss])
            yhi = np.array([min(s["delta_star_high"], top) for s in ss]) - y
            xerr = [x - [s["clean_cost_low"] for s in ss], [s["clean_cost_high"] for s in ss] - x]
            bars = ax.errorbar(x, np.minimum(y, top), yerr=[np.maximum(ylo, 0), np.maximum(yhi, 0)], xerr=xerr,
                               fmt="o-", capsize=3, label=f"{defense}, N = {n}")
            labels += [(xi, min(yi, top), f"{s['param']:g}", bars.lines[0].get_color()) for s, xi, yi in zip(ss, x, y)]
        panels.append((ax, labels))
        ax.set_title(learner)
        ax.set_xlabel(f"clean {COST_LABEL.get(learner, 'cost')}")
        ax.set_ylabel("median delta*" + (f" ({FACTOR:g}x degradation)" if learner in ("ident", "deepc")
                                         else " (destabilizing budget)"))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    for ax, labels in panels:  # after the layout: labels are kept apart in the panel's final size
        _annotate_apart(ax, labels)
    return fig


def write_outputs(rows: list[dict[str, Any]], out_dir: str, learners: Sequence[str] | None = None) -> str:
    """frontier.csv (per data set), frontier.md (learners_line, then summary_markdown) and fig_frontier.png; returns
    frontier.md's text."""
    os.makedirs(out_dir, exist_ok=True)
    write_rows_csv(os.path.join(out_dir, "frontier.csv"), rows, ROW_SCHEMA)
    summary = summarize(rows)
    fig = frontier_figure(summary, learners)
    with atomic_path(os.path.join(out_dir, "fig_frontier.png")) as tmp:
        fig.savefig(tmp, dpi=150)
    table = learners_line(learners) + "\n\n" + summary_markdown(summary)
    with atomic_open(os.path.join(out_dir, "frontier.md")) as fh:
        fh.write(table)
    return table


def run_defenses(sims: int = 64, out_dir: str = "out/defenses", quick: bool = False, seed: int = 0,
                 workers: int | None = None, dask: str | None = None,
                 progress: Callable[[str], None] | None = stderr_progress,
                 learners: Sequence[str] | None = None) -> str:
    """`bilevel reproduce defenses`: the frontier sweep of the chosen learners (check_learners; None: all; resumable,
    defenses.jsonl), its table and figure, then the detection sweep of those among vrft, willems and ident
    (bilevel.experiments.defenses_detection: detection.jsonl, detection.md); returns the path of frontier.md."""
    plan = make_plan(sims, quick)
    chosen = check_learners(learners)
    committed = committed_timings("defenses-quick" if quick else "defenses")
    with open_executor(workers, dask) as executor:
        rows = run_sweep(frontier_task, frontier_tasks(plan, seed, chosen), os.path.join(out_dir, "defenses.jsonl"),
                         executor, progress, "defenses", valid=lambda r: check_fields(r, ROW_SCHEMA),
                         reference=committed)
        write_outputs(rows, out_dir, chosen)
        families = tuple(name for name in chosen if name in FAMILIES)
        if families:
            run_detection(plan.sims, plan.vrft_n, plan.horizons[0], out_dir, seed, executor, progress,
                          families=families, reference=committed)
    path = os.path.join(out_dir, "frontier.md")
    if progress:
        progress(f"wrote {path}")
    return path
