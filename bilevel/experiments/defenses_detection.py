"""Detection as a defense (issue 29): the share of attacks a defender's test flags at a 5% false-alarm rate,
calibrated on clean data sets, for attacks that ignore and that respect the test's stealth constraint.

Tests and attacks:
  vrft      input integrity (bilevel.ddc.input_integrity: the Whittle deviance of the recorded input against the known
            spectrum of the prefiltered white excitation). "ignores": the engine's destabilizing attack on (u, y) at
            eps_u = eps_y = VRFT_EPS; "respects": the same attack on y alone (eps_u = 0: the input passes unchanged).
  willems   input integrity against the white excitation (std 1). "ignores": destabilize_attack at delta_u =
            WILLEMS_DELTA (linf box on U); "respects": the hypergradient attack (stopping once the identified loop is
            unstable) on the states alone, |Dx| <= WILLEMS_DELTA_X, x_0 clean (the paper's output-poisoning remark).
  ident     the residual tests whose null hypothesis is a well-fitted model (bilevel.ddc.residual_tests: variance and
            whiteness; the input F-test rejects on clean data by design); flagged when the smaller p-value is below its
            clean 5% quantile. "ignores": the ident-ss attack without stealth; "respects": with stealth =
            IDENT_STEALTH (each statistic within 5% of its clean value), both at eps = IDENT_EPS, T = 100.
The thresholds are the 95% quantile of the statistic (5% quantile of the smallest p-value) over CALIBRATION clean data
sets drawn with seeds independent of the attacked ones.
"""

from __future__ import annotations

import os
from typing import Any, Callable

import numpy as np

from ..attacks.willems import destabilize_attack, hypergradient_attack
from ..ddc.input_integrity import filtered_white_spectrum, whittle_deviance
from ..ddc.plants import flexible_transmission_prefilter
from ..files import atomic_open, write_rows_csv
from ..problems.defended_vrft import declare, defended_instance
from ..problems.identification import problem_for
from ..problems.identification_instance import attack_instance, least_squares_fit
from ..problems.willems import build_attack
from ..problems.willems_instance import WillemsSetting
from ..solvers.registry import solve
from .identification import METHOD
from .stats import wilson_interval
from .sweep import FINITE, check_fields, run_sweep, sim_seeds, stderr_progress

VRFT_EPS = 0.2
WILLEMS_DELTA, WILLEMS_DELTA_X = 0.5, 0.1
IDENT_EPS, IDENT_STEALTH, IDENT_T = 0.05, 0.05, 100
CALIBRATION = 500
FALSE_ALARM = 0.05
ROW_SCHEMA = {"case": str, "data_seed": int, "statistic": FINITE, "succeeded": bool}
"""statistic: the Whittle deviance (vrft, willems) or the smallest residual-test p-value (ident); succeeded: the true
loop unstable (vrft, willems) or ||d[A B]||_2 > IDENT_DAMAGE (ident)."""
IDENT_DAMAGE = 0.1
CASES = ("vrft-ignores", "vrft-respects", "willems-ignores", "willems-respects", "ident-ignores", "ident-respects")
FAMILIES = ("vrft", "willems", "ident")
"""The learners a case attacks (its name's first part)."""


def _vrft_spectrum(N: int) -> np.ndarray:
    return filtered_white_spectrum(flexible_transmission_prefilter(), N)


def clean_statistic(family: str, N: int, seed: int) -> float:
    """The test's statistic on one clean data set of `family` (vrft: N samples; willems: horizon N; ident: T = N)."""
    rng = np.random.default_rng(seed)
    if family == "vrft":
        d = defended_instance("none", "maxmin", 0.0, "B", 0.0, 0.0, seed, N)
        return whittle_deviance(d.atk.u, _vrft_spectrum(N))
    if family == "willems":
        return whittle_deviance(rng.standard_normal((2, N)), filtered_white_spectrum(None, N))
    atk = attack_instance("ss", N, IDENT_EPS, seed=seed)
    return _smallest_p(atk.tests())


def _smallest_p(tests: dict[str, Any]) -> float:
    """The smaller p-value of the variance and whiteness tests."""
    return min(tests[name].p_value for name in ("variance", "whiteness"))


def thresholds(N: int, T: int, seed: int, count: int = CALIBRATION,
               families: tuple[str, ...] = FAMILIES) -> dict[str, float]:
    """Per family of `families`, the statistic's 5% false-alarm threshold over `count` clean data sets (seeds from
    seed + 7)."""
    seeds = sim_seeds(seed + 7, count)
    out = {}
    for family, n in (("vrft", N), ("willems", T), ("ident", IDENT_T)):
        if family not in families:
            continue
        values = np.array([clean_statistic(family, n, s) for s in seeds])
        out[family] = float(np.quantile(values, FALSE_ALARM if family == "ident" else 1 - FALSE_ALARM))
    return out


def detection_task(task: dict[str, Any]) -> dict[str, Any]:
    """One attack of `case` on one data set and the test's statistic on its poisoned data."""
    case, seed = task["case"], task["seed"]
    if case.startswith("vrft"):
        eps_u = VRFT_EPS if case == "vrft-ignores" else 0.0
        d = defended_instance("none", "destabilize", 0.0, "B", eps_u, VRFT_EPS, seed, task["N"])
        result = solve(declare(d), starts=2, seed=task["attack_seed"])
        a_u, a_y = (np.asarray(result.x[k], dtype=float).ravel() for k in ("a_u", "a_y"))
        return {"case": case, "data_seed": seed, "statistic": whittle_deviance(d.atk.u + a_u, _vrft_spectrum(d.atk.N)),
                "succeeded": bool(d.atk.setting.loop.spectral_radius(d.poisoned(a_u, a_y)) >= 1.0)}
    if case == "willems-ignores":
        attack = build_attack(WillemsSetting(objective="destabilize", horizon=task["T"], seed=seed,
                                             delta_u=WILLEMS_DELTA))
        result = destabilize_attack(attack, seed=task["attack_seed"])
        du, _ = attack.split(result.stats["x"])
        return {"case": case, "data_seed": seed,
                "statistic": whittle_deviance(attack.u + du, filtered_white_spectrum(None, task["T"])),
                "succeeded": bool(result.stats["spectral_radius"] >= 1.0)}
    if case == "willems-respects":
        attack = build_attack(WillemsSetting(objective="destabilize", horizon=task["T"], seed=seed, poison="x",
                                             delta_u=0.0, delta_x=WILLEMS_DELTA_X))
        result = hypergradient_attack(attack, starts=4, seed=task["attack_seed"])
        return {"case": case, "data_seed": seed,
                "statistic": whittle_deviance(attack.u, filtered_white_spectrum(None, task["T"])),
                "succeeded": bool(result.stats["spectral_radius"] >= 1.0)}
    atk = attack_instance("ss", IDENT_T, IDENT_EPS, stealth=IDENT_STEALTH if case == "ident-respects" else None,
                          seed=seed)
    result = problem_for(atk).solve(**METHOD, seed=0)
    signals = {k: atk.signals[k] + np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in atk.signals}
    damage = float(np.linalg.norm(least_squares_fit(*atk.regression(signals)) - atk.theta0, 2))
    return {"case": case, "data_seed": seed, "statistic": _smallest_p(atk.tests(signals)),
            "succeeded": damage > IDENT_DAMAGE}


def detection_markdown(rows: list[dict[str, Any]], limits: dict[str, float]) -> str:
    """Per case: attacks, share detected at the calibrated 5% threshold (Wilson 95% interval), share that succeeded."""
    lines = ["| case | test | threshold (5% false alarms) | attacks | detected (95% CI) | attack succeeded |",
             "|---|---|---|---|---|---|"]
    for case in CASES:
        rs = [r for r in rows if r["case"] == case]
        if not rs:
            continue
        family = case.split("-")[0]
        flagged = [(r["statistic"] < limits[family]) if family == "ident" else (r["statistic"] > limits[family])
                   for r in rs]
        low, high = wilson_interval(sum(flagged), len(rs))
        test = "variance/whiteness tests (min p)" if family == "ident" else "input integrity (Whittle deviance)"
        lines.append(f"| {case} | {test} | {limits[family]:.4g} | {len(rs)} | {sum(flagged)}/{len(rs)} "
                     f"({low:.2f} - {high:.2f}) | {sum(r['succeeded'] for r in rs)}/{len(rs)} |")
    return "\n".join(lines) + "\n"


def run_detection(sims: int, N: int, T: int, out_dir: str, seed: int = 0, executor: Any = None,
                  progress: Callable[[str], None] | None = stderr_progress, calibration: int = CALIBRATION,
                  families: tuple[str, ...] = FAMILIES, reference: str | None = None) -> str:
    """The detection sweep of the cases attacking `families` (resumable, detection.jsonl), detection.csv (one row per
    attack) and detection.md; returns the table. reference: a committed timings.json to estimate from."""
    seeds = list(enumerate(zip(sim_seeds(seed, sims), sim_seeds(seed + 1, sims))))
    tasks = [{"key": f"{case}|N={N}|T={T}|sim={i}", "case": case, "N": N, "T": T, "seed": data_seed,
              "attack_seed": attack_seed, "root_seed": seed}
             for case in CASES if case.split("-")[0] in families for i, (data_seed, attack_seed) in seeds]
    rows = run_sweep(detection_task, tasks, os.path.join(out_dir, "detection.jsonl"), executor, progress,
                     "defenses-detection", valid=lambda r: check_fields(r, ROW_SCHEMA), reference=reference)
    write_rows_csv(os.path.join(out_dir, "detection.csv"), rows, ROW_SCHEMA)
    table = detection_markdown(rows, thresholds(N, T, seed, calibration, families))
    with atomic_open(os.path.join(out_dir, "detection.md")) as fh:
        fh.write(table)
    return table
