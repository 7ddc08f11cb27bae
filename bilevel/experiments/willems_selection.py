"""How the learner's choice among non-unique SDP solutions sets its sensitivity to input poisoning.

The appendix SDP sees Q only through X0 Q and X1 Q, so every Q + N with [X0; X1] N = 0 is optimal, and
the SDP data do not contain U0. Input poisoning therefore leaves the learner's Q unchanged and moves the
gain affinely: K' = (U0 + A_u) Q S^-1 = K + A_u G with G = Q S^-1, S = X0 Q. Under |A_u| <= delta
entrywise, entry K_ij moves by at most delta * sum_t |G_tj|: the column-sum norm of G is the learner's
worst-case gain, and it depends on which optimal Q the learner picks. "min-norm" is the selection our
attacks model (reg -> 0); "clarabel" is what Clarabel's interior point returns without regularization.
"""

from __future__ import annotations

import os

import numpy as np

from ..ddc.data import batch_reactor_data
from ..ddc.depersis_tesi import lqr_controller, min_norm_q
from ..files import write_rows_csv

SELECTIONS = ("min-norm", "clarabel")


def input_gains(x: np.ndarray, u: np.ndarray) -> dict[str, float]:
    """Worst-case linf gain max_j sum_t |G_tj| of K to input poisoning per selection, and Clarabel's null share."""
    x0, x1 = x[:, :-1], x[:, 1:]
    q_solver = lqr_controller(x, u, input_cost=False, balance=False).q  # Clarabel's raw Q (the committed study)
    data = np.vstack([x0, x1])
    q_min = min_norm_q(data, q_solver)  # the part of Q the SDP sees: the minimum-norm optimum
    out = {}
    for name, q in zip(SELECTIONS, (q_min, q_solver)):
        s = x0 @ q
        g = q @ np.linalg.inv(0.5 * (s + s.T))
        out[name] = float(np.abs(g).sum(axis=0).max())
    out["null_share"] = float(np.linalg.norm(q_solver - q_min) / np.linalg.norm(q_min))
    return out


def selection_table(horizons: tuple[int, ...], seeds: list[int], out_dir: str) -> str:
    """Median gains per horizon over data seeds; writes table_selection.csv and returns a Markdown table."""
    rows = []
    for n in horizons:
        gains = [input_gains(*batch_reactor_data(n, np.random.default_rng(s))) for s in seeds]
        rows.append({"horizon": n, "sims": len(seeds), **{k: float(np.median([g[k] for g in gains]))
                                                          for k in (*SELECTIONS, "null_share")}})
    write_rows_csv(os.path.join(out_dir, "table_selection.csv"), rows, rows[0])
    lines = ["| N | sims | gain, min-norm Q | gain, Clarabel's Q | Clarabel's Q: null-space part / min-norm part |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['horizon']} | {r['sims']} | {r['min-norm']:.2f} | {r['clarabel']:.2f} | {r['null_share']:.2f} |"
              for r in rows]
    trend = {k: "falls" if rows[-1][k] < rows[0][k] else "does not fall" for k in SELECTIONS}
    lines += ["", f"From N = {rows[0]['horizon']} to N = {rows[-1]['horizon']} the median gain "
              f"{trend['min-norm']} under the minimum-norm selection and {trend['clarabel']} under Clarabel's."]
    return "\n".join(lines) + "\n"
