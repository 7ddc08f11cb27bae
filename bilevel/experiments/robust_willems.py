"""The robust De Persis–Tesi learner under adaptive attack (issue 46): per design budget delta_d and attack budget
delta <= delta_d, on the batch reactor's drawn data (T samples), how often the attacker forces the learner to abstain,
the largest true closed-loop spectral radius among its answers (a radius >= 1 would contradict its theorem: a bug), and
its clean-data cost, next to the undefended (min-norm, reg 1e-8) and ridge-defended (reg 1) De Persis–Tesi learners
attacked at the same budgets.

The attacks on the robust learner (bilevel.ddc.robust_depersis_tesi) know the plant, the data, the learner and delta_d:
the generic engine (method hypergradient) on defense-willems-robust with each criterion (objective "radius": rho(A + B
K); "abstain": the learner's H2 bound tr(Qx P), unbounded as it nears abstention), and RANDOM_VERTICES random sign
poisonings at the budget. Each answer is judged by the cvxpy learner re-solved at the attack's poisoning (its own numpy
re-check included) and numpy eigenvalues of the true loop. The other learners are attacked by destabilize_attack (the
exact input-poisoning attack of bilevel.attacks.willems). Clean cost: the true loop's H2 cost trace(Qx W) (R = 0, the
lqr design's). One resumable sweep task per (learner, delta_d, delta, data set).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..attacks.willems import destabilize_attack
from ..ddc.robust_depersis_tesi import RobustController, robust_lqr_controller
from ..errors import BilevelError
from ..files import atomic_open, write_rows_csv
from ..problems.defended_willems import ROBUST_OBJECTIVES, declare_robust
from ..problems.willems import build_attack
from ..problems.willems_instance import WillemsSetting, criterion_values
from ..solvers.registry import solve
from .defenses import clean_gain, clean_performance
from .executor import open_executor
from .sweep import NUMBER, check_fields, committed_timings, run_sweep, sim_seeds, stderr_progress

ROW_SCHEMA = {"learner": str, "design": NUMBER, "budget": NUMBER, "horizon": int, "data_seed": int,
              "answers": int, "abstained": int, "engine_abstained": int, "unstable": int, "radius": NUMBER,
              "clean_cost": NUMBER, "seconds": NUMBER}
"""A row: the learner (robust, none, ridge), its design budget (0 for the others), the attack budget (0: clean data),
how many poisonings were judged, how many made the learner abstain (of them the engine's answers) or gave an unstable
true loop, the largest true radius among answers (nan if none), the learner's clean cost on this data set (inf if it
abstains on clean data)."""
FRACTIONS = (0.25, 0.5, 0.75, 1.0)
"""Attack budgets as fractions of the design budget."""
RIDGE_REG = 1.0
RANDOM_VERTICES = 8


@dataclass(frozen=True)
class Plan:
    """Data sets, horizon, the design budgets attacked at these fractions of them, those measured on clean data only,
    and the engine's starts."""

    sims: int
    horizon: int
    designs: tuple[float, ...]
    fractions: tuple[float, ...]
    clean_designs: tuple[float, ...]
    starts: int


def make_plan(sims: int, quick: bool) -> Plan:
    """The full plan (T = 15; design 0.1 attacked at FRACTIONS of it, 0.01-0.15 on clean data; 1 engine start per
    criterion: the clean data) or the CI plan (at most 2 data sets, design 0.1 attacked at its full budget only)."""
    if quick:
        return Plan(min(sims, 2), 15, (0.1,), (1.0,), (0.05, 0.1), 1)
    return Plan(sims, 15, (0.1,), FRACTIONS, (0.01, 0.025, 0.05, 0.1, 0.15), 1)


def true_h2_cost(setting: WillemsSetting, gain: np.ndarray) -> float:
    """trace(Qx W), W = Acl W Acl' + I, of the true loop A + B K (inf where unstable)."""
    a, b = setting.plant_matrices()
    n, m = b.shape
    return float(criterion_values(a + b @ gain, gain, "maxmin", np.eye(n), np.zeros((m, m))))


def _judge(setting: WillemsSetting, answer: RobustController) -> float:
    """The true loop's spectral radius under a certified answer (nan for an abstention)."""
    if not answer.certified:
        return float("nan")
    a, b = setting.plant_matrices()
    return float(np.max(np.abs(np.linalg.eigvals(a + b @ answer.k))))


def robust_poisonings(setting: WillemsSetting, design: float, attack_seed: int, starts: int) -> list[np.ndarray]:
    """The attacker's candidate input poisonings at budget setting.delta_u: the engine's answer per criterion
    (ROBUST_OBJECTIVES; none where the engine returned no point), then RANDOM_VERTICES random sign patterns."""
    out = []
    for objective in ROBUST_OBJECTIVES:
        result = solve(declare_robust(setting, design, objective), method="hypergradient", starts=starts,
                       seed=attack_seed)
        if result.x is not None and "Du" in result.x:
            out.append(np.clip(np.asarray(result.x["Du"], dtype=float), -setting.delta_u, setting.delta_u))
    m, t = np.shape(setting.experiment()[1])
    signs = np.random.default_rng(attack_seed).choice([-1.0, 1.0], size=(RANDOM_VERTICES, m, t))
    return out + list(setting.delta_u * signs)


def robust_task(task: dict[str, Any]) -> dict[str, Any]:
    """One (design, budget, data set) of the robust learner: the learner at every candidate poisoning (the clean data
    at budget 0), judged by the true loop."""
    t0 = time.perf_counter()
    setting = WillemsSetting(objective="destabilize", horizon=task["N"], seed=task["seed"], delta_u=task["budget"])
    x, u = setting.experiment()
    clean = robust_lqr_controller(x, u, task["design"])
    clean_cost = true_h2_cost(setting, clean.k) if clean.certified else float("inf")
    poisonings = ([np.zeros_like(u)] if task["budget"] == 0 else
                  robust_poisonings(setting, task["design"], task["attack_seed"], task["starts"]))
    answers = [robust_lqr_controller(x, u + du, task["design"]) for du in poisonings]
    engine = len(answers) - (RANDOM_VERTICES if task["budget"] > 0 else 0)
    radii = np.array([_judge(setting, a) for a in answers])
    answered = radii[np.isfinite(radii)]
    return {"learner": "robust", "design": task["design"], "budget": task["budget"], "horizon": task["N"],
            "data_seed": task["seed"], "answers": len(answers), "abstained": int(sum(not a.certified for a in answers)),
            "engine_abstained": int(sum(not a.certified for a in answers[:engine])),
            "unstable": int(np.sum(answered >= 1.0)),
            "radius": float(answered.max()) if answered.size else float("nan"),
            "clean_cost": clean_cost, "seconds": time.perf_counter() - t0}


def nominal_task(task: dict[str, Any]) -> dict[str, Any]:
    """One budget and data set of the undefended (reg 1e-8) or ridge (reg RIDGE_REG) learner under destabilize_attack;
    budget 0: the clean data."""
    t0 = time.perf_counter()
    reg = RIDGE_REG if task["learner"] == "ridge" else 1e-8
    setting = WillemsSetting(objective="destabilize", horizon=task["N"], seed=task["seed"], delta_u=task["budget"],
                             reg=reg)
    attack = build_attack(setting)
    if task["budget"] == 0:
        a, b = setting.plant_matrices()
        radius = float(np.max(np.abs(np.linalg.eigvals(a + b @ clean_gain(attack)))))
    else:
        radius = destabilize_attack(attack, seed=task["attack_seed"]).stats["spectral_radius"]
    return {"learner": task["learner"], "design": 0.0, "budget": task["budget"], "horizon": task["N"],
            "data_seed": task["seed"], "answers": 1, "abstained": 0, "engine_abstained": 0,
            "unstable": int(radius >= 1.0), "radius": radius,
            "clean_cost": clean_performance(attack), "seconds": time.perf_counter() - t0}


def task_row(task: dict[str, Any]) -> dict[str, Any]:
    """A task's row (robust_task or nominal_task by its learner); a named error of the learner is re-raised."""
    try:
        return robust_task(task) if task["learner"] == "robust" else nominal_task(task)
    except BilevelError as err:
        raise type(err)(f"{task['key']}: {err}") from err


def tasks(plan: Plan, seed: int) -> list[dict[str, Any]]:
    """Every (learner, design, budget, data set) of the plan; data set i has the same seeds for every learner."""
    seeds = list(enumerate(zip(sim_seeds(seed, plan.sims), sim_seeds(seed + 1, plan.sims))))
    cells = [("robust", d, 0.0) for d in plan.clean_designs]
    cells += [("robust", d, f * d) for d in plan.designs for f in plan.fractions]
    budgets = sorted({0.0, *(b for _, _, b in cells)})
    cells += [(learner, 0.0, b) for learner in ("none", "ridge") for b in budgets]
    return [{"key": f"{learner}|design={design:g}|delta={budget:g}|N={plan.horizon}|sim={i}", "learner": learner,
             "design": design, "budget": budget, "N": plan.horizon, "seed": data_seed, "attack_seed": attack_seed,
             "starts": plan.starts, "root_seed": seed}
            for learner, design, budget in cells for i, (data_seed, attack_seed) in seeds]


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (learner, design, budget): data sets, abstention rate (data sets where some poisoning made the learner
    abstain), unstable loops (answers), the median and largest true radius among answers, the mean clean cost and its
    median ratio to the undefended learner's on the same data sets."""
    base = {r["data_seed"]: r["clean_cost"] for r in rows if r["learner"] == "none" and r["budget"] == 0}
    out = []
    for key in sorted({(r["learner"], r["design"], r["budget"]) for r in rows}):
        rs = [r for r in rows if (r["learner"], r["design"], r["budget"]) == key]
        radii = np.array([r["radius"] for r in rs if np.isfinite(r["radius"])])
        costs = np.array([r["clean_cost"] for r in rs])
        ratios = [r["clean_cost"] / base[r["data_seed"]] for r in rs if r["data_seed"] in base]
        out.append({"learner": key[0], "design": key[1], "budget": key[2], "data_sets": len(rs),
                    "abstention_rate": float(np.mean([r["abstained"] > 0 for r in rs])),
                    "engine_abstention_rate": float(np.mean([r["engine_abstained"] > 0 for r in rs])),
                    "unstable": int(sum(r["unstable"] for r in rs)), "answers": int(sum(r["answers"] for r in rs)),
                    "median_radius": float(np.median(radii)) if radii.size else float("nan"),
                    "max_radius": float(radii.max()) if radii.size else float("nan"),
                    "clean_cost": float(np.mean(costs[np.isfinite(costs)])) if np.isfinite(costs).any() else np.inf,
                    "cost_ratio": float(np.median(ratios)) if ratios else float("nan"),
                    "seconds": float(np.mean([r["seconds"] for r in rs]))})
    return out


def summary_markdown(summary: list[dict[str, Any]]) -> str:
    """The table: one line per (learner, design, budget)."""
    lines = ["| learner | design budget | attack budget | data sets | abstention rate (by the engine's attacks) | "
             "unstable loops / answers | median true radius | largest true radius | clean H2 cost (mean over "
             "certified) | clean cost ratio to undefended (median) | seconds per data set |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['learner']} | {s['design']:g} | {s['budget']:g} | {s['data_sets']} | "
                     f"{s['abstention_rate']:.3g} ({s['engine_abstention_rate']:.3g}) | "
                     f"{s['unstable']} / {s['answers']} | {s['median_radius']:.4g} | {s['max_radius']:.4g} | "
                     f"{s['clean_cost']:.4g} | {s['cost_ratio']:.4g} | {s['seconds']:.3g} |")
    return "\n".join(lines) + "\n"


def write_outputs(rows: list[dict[str, Any]], out_dir: str) -> str:
    """robust.csv (per data set) and robust.md (summary_markdown); returns the table."""
    os.makedirs(out_dir, exist_ok=True)
    write_rows_csv(os.path.join(out_dir, "robust.csv"), rows, ROW_SCHEMA)
    table = summary_markdown(summarize(rows))
    with atomic_open(os.path.join(out_dir, "robust.md")) as fh:
        fh.write(table)
    return table


def run_robust_willems(sims: int = 64, out_dir: str = "out/robust-willems", quick: bool = False, seed: int = 0,
                       workers: int | None = None, dask: str | None = None,
                       progress: Callable[[str], None] | None = stderr_progress) -> str:
    """`bilevel reproduce robust-willems`: the sweep (resumable, robust.jsonl), robust.csv and robust.md; returns the
    path of robust.md."""
    plan = make_plan(sims, quick)
    with open_executor(workers, dask) as executor:
        rows = run_sweep(task_row, tasks(plan, seed), os.path.join(out_dir, "robust.jsonl"), executor, progress,
                         "robust-willems", valid=lambda r: check_fields(r, ROW_SCHEMA),
                         reference=committed_timings("robust-willems"))
    write_outputs(rows, out_dir)
    path = os.path.join(out_dir, "robust.md")
    if progress:
        progress(f"wrote {path}")
    return path
