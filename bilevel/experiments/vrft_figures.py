"""Figures 2-6 and report.md of the VRFT reproduction (matplotlib, Agg; PNG and PDF)."""

from __future__ import annotations

from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from ..attacks.vrft_methods import attack  # noqa: E402
from ..ddc.analysis import closed_loop_bode, closed_loop_step  # noqa: E402
from ..ddc.bases import controller_tf  # noqa: E402
from ..ddc.data import simulate  # noqa: E402
from ..problems.vrft_instance import CONVENTIONS, PAPER_THETA0  # noqa: E402
from ..files import save_figure  # noqa: E402
from .vrft import EPS_U, EPS_Y, PAPER_TABLE1, make_attack, sim_seeds, table_markdown  # noqa: E402


BUDGET = (0.1, 0.057)
"""(eps_u, eps_y) of the single-instance figures 2, 3b, 4 and 5."""


def _budget_text() -> str:
    return f"eps_u = {BUDGET[0]}, eps_y = {BUDGET[1]}"


def _band_legend(ax: plt.Axes, n: int, where: plt.Axes | plt.Figure | None = None, **kwargs: Any) -> None:
    """The legend of ax's lines (drawn on `where`, default ax), with the shaded bands named: each line's 95%
    t-interval of the mean (stats.mean_interval)."""
    handles, labels = ax.get_legend_handles_labels()
    band = Patch(color="grey", alpha=0.2)
    (where or ax).legend([*handles, band], [*labels, f"shaded: 95% confidence interval of the mean over {n} "
                                            "simulations"], fontsize=kwargs.pop("fontsize", 7), **kwargs)


def _instance(scenario: str, objective: str, seed: int, eps_u: float = BUDGET[0], eps_y: float = BUDGET[1]):
    task = {"convention": "paper", "objective": objective, "scenario": scenario, "eps_u": eps_u, "eps_y": eps_y,
            "seed": sim_seeds(seed, 1)[0]}
    atk = make_attack(task)
    method = "joint" if objective == "destabilize" else "alternating"
    return atk, attack(atk, method, seed=task["seed"])


def figure_data(seed: int, out_dir: str) -> str:
    """Fig. 2: recorded u, y of scenario B before and after the max-min attack at BUDGET, and the poisonings a_u, a_y
    themselves (at this budget the poisoned traces lie almost on the clean ones)."""
    atk, res = _instance("B", "maxmin", seed)
    fig, axes = plt.subplots(4, 1, figsize=(8, 8), sharex=True, gridspec_kw={"height_ratios": (3, 1.4, 3, 1.4)})
    t = np.arange(atk.N)
    for k, (clean, a, name) in enumerate(((atk.u, res.x["a_u"], "u"), (atk.y, res.x["a_y"], "y"))):
        ax, ax_a = axes[2 * k], axes[2 * k + 1]
        ax.plot(t, clean, lw=1.6, color="0.55", label=f"{name} (clean)")
        ax.plot(t, clean + a, lw=0.7, color="C3", label=f"{name} + a_{name} (poisoned)")
        ax.set_ylabel(f"{name} (plant {'input' if name == 'u' else 'output'})")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, 1.22), ncol=2, fontsize=8, frameon=False)
        ax_a.plot(t, a, lw=0.7, color="C3")
        ax_a.set_ylabel(f"a_{name}")
        ax_a.axhline(0.0, color="0.7", lw=0.5)
    axes[-1].set_xlabel("t (samples, Ts = 0.05 s)")
    fig.suptitle(f"Scenario B, {_budget_text()} (max-min attack)")
    fig.tight_layout()
    return save_figure(fig, out_dir, "fig2_data")


def figure_loss(summaries: dict, out_dir: str) -> str:
    """Fig. 3a: learner's loss on clean data vs eps_y (mean, shaded 95% CI), dotted along the budget path, and the
    white-noise baseline."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    main, wn = summaries["maxmin-paper"], summaries.get("white-noise-paper", {})
    path = summaries.get("maxmin-paper-path", {})
    for ax, scenario in zip(axes, ("A", "B")):
        for eu in EPS_U:
            c = [main[(scenario, eu, ey)] for ey in EPS_Y]
            line, = ax.plot(EPS_Y, [x["value"] for x in c], marker="o", label=f"attack, eps_u = {eu}")
            ax.fill_between(EPS_Y, [x["value_lo"] for x in c], [x["value_hi"] for x in c], alpha=0.2)
            if path:
                ax.plot(EPS_Y, [path[(scenario, eu, ey)]["value"] for ey in EPS_Y], ls=":", color=line.get_color(),
                        label=f"budget path, eps_u = {eu}")
        if wn:
            c = [wn[(scenario, 0.2, ey)] for ey in EPS_Y]
            ax.plot(EPS_Y, [x["value"] for x in c], ls="--", color="k", label="white noise, eps_u = 0.2")
        ax.set_yscale("log")
        ax.set_title(f"Scenario {scenario}")
        ax.set_xlabel("eps_y")
        ax.set_ylabel("learner's loss L(u, y, theta')")
    # one legend below both panels: inside, it hid scenario B's curves
    _band_legend(axes[0], main[("A", EPS_U[0], EPS_Y[0])]["n"], where=fig, loc="lower center", ncol=3, fontsize=8)
    fig.subplots_adjust(bottom=0.3, wspace=0.3)
    return save_figure(fig, out_dir, "fig3a_loss")


STEP_STYLE = {"clean": dict(color="0.35", lw=2.4, ls="--", zorder=4), "poisoned": dict(color="C3", lw=1.2, zorder=3)}
"""Clean dashed and on top, poisoned solid: where the two coincide both stay visible."""


def _step_axes(ax: plt.Axes, atk, thetas: dict[str, np.ndarray], n: int = 150) -> None:
    setting = atk.setting
    for label, theta in thetas.items():
        resp = closed_loop_step(setting.plant, controller_tf(setting.basis, theta, setting.plant.dt), n)
        rho = setting.loop.spectral_radius(theta)
        style = STEP_STYLE.get(label, dict(color="C2", lw=0.9, alpha=0.7, zorder=2))
        ax.plot(resp.time, np.clip(resp.outputs, -3, 3), label=f"{label} (rho = {rho:.3f})", **style)
    ax.plot(np.arange(n) * setting.plant.dt, simulate(setting.reference, np.ones(n)), "k:", lw=1.2, zorder=5,
            label="M_r")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("closed-loop output y (unit step reference)")
    ax.set_ylim(-1.5, 2.5)
    ax.legend(fontsize=7, loc="lower right")


def figure_steps(seed: int, out_dir: str) -> str:
    """Fig. 3b: closed-loop step responses, clean vs max-min-poisoned controller at BUDGET."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, scenario in zip(axes, ("A", "B")):
        atk, res = _instance(scenario, "maxmin", seed)
        _step_axes(ax, atk, {"clean": atk.theta0, "poisoned": res.y["theta"]})
        ax.set_title(f"Max-min attack, scenario {scenario}\n{_budget_text()}")
    return save_figure(fig, out_dir, "fig3b_step")


def figure_targeted(seed: int, out_dir: str) -> tuple[str, str]:
    """Figs. 4-5: targeted attack (theta_a = 3 theta_0) at BUDGET: step responses and Bode magnitudes."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    fig_b, axes_b = plt.subplots(1, 2, figsize=(10, 4))
    for ax, axb, scenario in zip(axes, axes_b, ("A", "B")):
        atk, res = _instance(scenario, "targeted", seed)
        thetas = {"clean": atk.theta0, "poisoned": res.y["theta"], "target 3 theta_0": 3 * PAPER_THETA0}
        _step_axes(ax, atk, thetas)
        ax.set_title(f"Targeted, scenario {scenario}\n{_budget_text()}")
        setting = atk.setting
        omega = np.logspace(-1, np.log10(np.pi / setting.plant.dt), 300)
        ref = setting.reference(np.exp(1j * omega * setting.plant.dt))
        axb.semilogx(omega, 20 * np.log10(np.abs(ref)), label="reference model M_r")
        for label, theta in thetas.items():
            fr = closed_loop_bode(setting.plant, controller_tf(setting.basis, theta, setting.plant.dt), omega)
            axb.semilogx(fr.omega, 20 * np.log10(np.abs(fr.magnitude.squeeze())), label=label)
        axb.set_xlabel("omega (rad/s)")
        axb.set_ylabel("|T| (dB)")
        axb.set_title(f"Targeted, scenario {scenario}\n{_budget_text()}")
        axb.legend(fontsize=7)
    return save_figure(fig, out_dir, "fig4_targeted_step"), save_figure(fig_b, out_dir, "fig5_targeted_bode")


def figure_targeted_losses(summaries: dict, out_dir: str) -> str:
    """Fig. 6: learner's loss (top) and attacker's loss ||theta_a - theta'||^2 / nk (bottom) vs eps_y (means, shaded
    95% CI)."""
    tg = summaries["targeted-paper"]
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for j, scenario in enumerate(("A", "B")):
        for eu in EPS_U:
            c = [tg[(scenario, eu, ey)] for ey in EPS_Y]
            axes[0, j].plot(EPS_Y, [x["loss"] for x in c], marker="o", label=f"eps_u = {eu}")
            axes[0, j].fill_between(EPS_Y, [x["loss_lo"] for x in c], [x["loss_hi"] for x in c], alpha=0.2)
            axes[1, j].plot(EPS_Y, [-x["value"] for x in c], marker="o", label=f"eps_u = {eu}")
            axes[1, j].fill_between(EPS_Y, [-x["value_hi"] for x in c], [-x["value_lo"] for x in c], alpha=0.2)
        axes[0, j].set_title(f"Scenario {scenario}")
        axes[0, j].set_ylabel("learner's loss L(u, y, theta')")
        axes[1, j].set_ylabel("attacker's loss ||theta_a - theta'||^2 / nk")
        axes[1, j].set_xlabel("eps_y")
    # one legend below the panels: inside, it covered the curves
    _band_legend(axes[0, 0], tg[("A", EPS_U[0], EPS_Y[0])]["n"], where=fig, loc="lower center", ncol=4, fontsize=8)
    fig.subplots_adjust(bottom=0.16, wspace=0.3)
    return save_figure(fig, out_dir, "fig6_targeted_losses")


def make_all(summaries: dict, out_dir: str, seed: int) -> dict[str, str]:
    """Draw every figure; returns {figure id: file name}."""
    t4, t5 = figure_targeted(seed, out_dir)
    return {"2": figure_data(seed, out_dir), "3a": figure_loss(summaries, out_dir), "3b": figure_steps(seed, out_dir),
            "4": t4, "5": t5, "6": figure_targeted_losses(summaries, out_dir)}


def _overall(summary: dict, scenario: str) -> float:
    cells = [c for (sc, _, _), c in summary.items() if sc == scenario]
    return 100 * sum(c["unstable"] for c in cells) / max(1, sum(c["n"] for c in cells))


def path_section(single: dict, path: dict) -> str:
    """Markdown: the budget path's Table 1 and, per cell, the mean attacker objective and % unstable of both."""
    lines = ["## A stronger max-min attacker is not a more destabilizing one", "",
             table_markdown(path, "Max-min attack along the eps_y budget path, % unstable"), "",
             "| cell (scenario, eps_u, eps_y) | mean J, one attack | mean J, budget path | unstable, one attack "
             "| unstable, budget path |", "|---|---|---|---|---|"]
    higher = lower = 0
    for k in sorted(single):
        a, b = single[k], path[k]
        if b["value"] > a["value"] * (1 + 1e-3):
            higher += 1
            lower += b["rate"] < a["rate"]
        lines.append(f"| {k[0]}, {k[1]}, {k[2]} | {a['value']:.4f} | {b['value']:.4f} | {a['rate']:.1f}% | "
                     f"{b['rate']:.1f}% |")
    lines += ["", f"The path raises the mean learner loss J (the paper's attacker objective) by more than 0.1% in "
              f"{higher} of {len(single)} cells; in {lower} of those it destabilizes fewer loops. Instability is a "
              "by-product of which local maximum of J the ascent reaches (the ill-conditioning start favours one "
              "that flips the loop), not of how large J gets; the destabilizing attack targets it directly."]
    return "\n".join(lines)


CAPTIONS = {
    "2": f"Scenario B's recorded input and output, clean (grey) and poisoned by the max-min attack (red) at "
         f"{_budget_text()}, and the poisonings a_u, a_y themselves.",
    "3a": "The learner's loss on clean data at the poisoned controller against eps_y (means over the simulations, "
          "shaded 95% interval), one line per eps_u; dotted: along the budget path; dashed: white-noise poisoning.",
    "3b": f"Closed-loop step responses of the true plant with the clean controller (dashed) and the max-min-poisoned "
          f"one at {_budget_text()}, against the reference model M_r (dotted).",
    "4": f"Step responses under the targeted attack at {_budget_text()}: clean (dashed), poisoned, and the target "
         "controller 3 theta_0 (unstable, rho = 1.018).",
    "5": "Closed-loop magnitude responses |T| of the same controllers and of M_r.",
    "6": "Targeted attack: the learner's loss (top) and the attacker's loss (bottom) against eps_y, one line per "
         "eps_u (means, shaded 95% intervals).",
}
"""One caption per figure id of make_all, written under each figure in report.md."""


def report(summaries: dict, figures: dict[str, str], sims: int, side: int,
           timings: dict[str, tuple[int, float]], executor: str, settings: dict[str, list]) -> str:
    """report.md: settings (`settings`: field -> values read from the rows), Table 1 next to the paper's, the
    other conventions, the other attacks, figures."""
    main = summaries["maxmin-paper"]
    times = [c["time_ms"] for c in main.values()]
    parts = [
        "# VRFT poisoning: reproduction of Russo & Proutiere, Table 1 and figures 2-6", "",
        "Plant: flexible transmission (Landau 1995), Ts = 0.05; M_r = (1-a)^2/(z(z-a)^2), a = e^-0.5; "
        "L = (1-M_r)M_r; basis beta_i = z^(2-i)/(z-1), i = 1..6; N = 512; l2 budgets "
        "delta = eps ||signal||_2. Scenario A: step u = 1 on t in [5, 15]; scenario B: u ~ N(0, 1).", "",
        "**Conventions.** *paper*: the learner receives data already filtered by L and computes the "
        "virtual reference with zero final conditions (the paper's T_{M_r^-1}); *prefiltered-drop*: the "
        "last d = 3 regression rows (whose virtual reference needs unseen samples) are dropped; *raw*: the "
        "learner receives raw data and filters by L itself (zero final conditions); *raw-drop*: both. "
        "The attacker poisons the data set the learner receives, with budgets relative to those signals.", "",
        "**Attack.** Our max-min attack is the paper's Algorithm 1 made exact in a_u: the a_u-step is a "
        "6-dimensional trust-region subproblem solved globally (eigendecomposition + secular equation), and "
        "a_y follows spectral projected hypergradient ascent (Barzilai-Borwein steps, Armijo backtracking) on "
        "V(a_y) = max_a_u A, started "
        "from an a_y that makes the poisoned regressor ill-conditioned (ten projected steps on "
        "sigma_min(Phi(y + a_y))), one attack per cell as in the paper. The sweep *maxmin-paper-path* "
        "instead attacks each (scenario, eps_u, simulation) along the eps_y grid, each cell also started from "
        "the previous cell's best a_y (`attack_budget_path`), so its objective never decreases with eps_y. "
        "The attack is deterministic, and so are scenario A's data: every "
        "scenario-A simulation is the same instance, so its cells are 0% or 100% (the paper does not say "
        "what varies between its 512 scenario-A simulations).",
        "",
        "**Symbols.** theta_0: the controller VRFT fits on clean data; theta': the one it fits on poisoned data; "
        "rho: the spectral radius of the true closed loop (plant + controller), unstable where rho >= 1; the "
        "learner's loss L(u, y, theta'): VRFT's least-squares criterion on the clean data at theta'; the attacker's "
        "loss (targeted attack): ||theta_a - theta'||^2 / nk with theta_a = 3 theta_0 (nk = 6 parameters); "
        "eps_u, eps_y: the relative l2 budgets on u and y; |T| (figure 5): the magnitude of the closed-loop transfer "
        "function from the reference to y.", "",
        f"**Sizes.** Table 1 (maxmin-paper) and the budget path use {sims} simulations per cell; the side sweeps "
        f"(the other conventions, white noise, destabilizing and targeted attacks) use {side} (max(8, sims / 4)).",
        "",
        "Settings read from the result rows: " + "; ".join(f"{k.removeprefix('root_')} {', '.join(map(str, v))}"
                                                          for k, v in settings.items()) + ".", "",
        f"Median time per max-min attack: {np.median(times):.1f} ms (one core per worker, {executor}).", "",
        "Wall time of the attacks (when each sweep's rows were computed; `timings.json`; a resumed sweep "
        "records only the rows it added; the simulations of a scenario-A cell are one attack, run once): "
        + ("; ".join(f"{k}: {n} attacks in {t:.0f} s" for k, (n, t) in timings.items()) or "none recorded")
        + ".", "",
        "## Summary", "",
        "Unstable closed loops over all 30 cells of each sweep (scenario A / scenario B):", "",
        "| sweep | scenario A | scenario B |", "|---|---|---|",
        *[f"| {name} | {_overall(s_, 'A'):.1f}% | {_overall(s_, 'B'):.1f}% |" for name, s_ in summaries.items()],
        "",
        "## Table 1 (paper convention), ours vs the paper", "",
        table_markdown(main, f"Max-min attack, % unstable closed loops ({sims} simulations per cell)", PAPER_TABLE1),
    ]
    if "maxmin-paper-path" in summaries:
        parts += [path_section(main, summaries["maxmin-paper-path"]), ""]
    for c in CONVENTIONS:
        if c != "paper" and f"maxmin-{c}" in summaries:
            parts += [table_markdown(summaries[f"maxmin-{c}"], f"Max-min attack, convention '{c}'"), ""]
    parts += [table_markdown(summaries["destabilize-paper"], "Destabilizing attack (ARX model + smooth spectral "
                             "radius surrogate), paper convention"), "",
              table_markdown(summaries["white-noise-paper"], "White-noise poisoning at the same budgets"), "",
              table_markdown(summaries["targeted-paper"], "Targeted attack (theta_a = 3 theta_0), % unstable"), ""]
    parts += ["## Figures", ""]
    for k, v in figures.items():
        parts += [f"**Figure {k}.** {CAPTIONS.get(k, '')}", "", f"![Figure {k}]({v})", ""]
    return "\n".join(parts) + "\n"
