"""Column balancing of the De Persis-Tesi learners at N = 50 (issue 12, item 4): solver status, value and time.

bilevel.ddc.lqr_controller on the reproduction's data seeds 0..SEEDS-1 at T = 50 (states up to ~2e4), appendix SDP
(input_cost=False) and Theorem 4 (input_cost=True), Clarabel and SCS (eps 1e-7), unbalanced (balance=False) and
balanced (default). Value error relative to the clean-data optimum (7.701763 appendix, trace(P_DARE) = 29.1262
Thm 4); baseline: the unbalanced learner, run in the same process. Asserts nothing.
"""

from __future__ import annotations

import os
import time
import warnings

import numpy as np

from bilevel.ddc.data import batch_reactor_data
from bilevel.ddc.depersis_tesi import lqr_controller
from bilevel.errors import BilevelError

SEEDS = 4
OPTIMUM = {False: 7.701763394, True: 29.1262}


def main() -> None:
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, nproc {os.cpu_count()}, load "
          f"{os.getloadavg()[0]:.2f}; T = 50, data seeds 0..{SEEDS - 1}")
    print(f"{'formulation':>11} {'solver':>8} {'balanced':>8} {'optimal':>7} {'statuses':>30} {'max rel err':>11} "
          f"{'max time [s]':>12}")
    for input_cost in (False, True):
        for solver in ("clarabel", "scs"):
            for balance in (False, True):
                statuses, errors, times = [], [], []
                for seed in range(SEEDS):
                    x, u = batch_reactor_data(50, np.random.default_rng(seed))
                    t0 = time.perf_counter()
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", UserWarning)
                        try:
                            c = lqr_controller(x, u, input_cost=input_cost, solver=solver, balance=balance)
                            statuses.append(c.status)
                            errors.append(abs(c.value - OPTIMUM[input_cost]) / OPTIMUM[input_cost])
                        except BilevelError as exc:
                            statuses.append(type(exc).__name__)
                    times.append(time.perf_counter() - t0)
                name = "Thm 4" if input_cost else "appendix"
                print(f"{name:>11} {solver:>8} {str(balance):>8} {statuses.count('optimal'):>4} / {SEEDS} "
                      f"{','.join(sorted(set(statuses))):>30} {max(errors, default=np.nan):>11.1e} {max(times):>12.2f}",
                      flush=True)


if __name__ == "__main__":
    main()
