"""The Theorem 4 learner (input cost) degenerates under tiny input noise on T > n + m data (issue 12, item 5).

bilevel.ddc.lqr_controller(x, u + eps * signs) with fair random signs, 8 data seeds, N = 15 and 50: its gain,
the true loop's spectral radius rho(A + B K) and the SDP value, against the clean ones (value trace(P_DARE) =
29.1262, rho(A) = 1.22). Not a speed claim: a measurement, printed. Asserts nothing.
"""

from __future__ import annotations

import time

import numpy as np

from bilevel.ddc.data import batch_reactor_data
from bilevel.ddc.depersis_tesi import lqr_controller
from bilevel.ddc.plants import batch_reactor

PLANT = batch_reactor()


def main() -> None:
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; learner lqr_controller (Thm 4, R = I, Clarabel, "
          "balanced columns); 8 data seeds, signs from default_rng(100 + seed)")
    print(f"open-loop rho(A) = {np.max(np.abs(np.linalg.eigvals(PLANT.A))):.6f}")
    for n in (15, 50):
        for eps in (0.0, 1e-7, 1e-5, 1e-3):
            k_max, rho, value = [], [], []
            for seed in range(8):
                x, u = batch_reactor_data(n, np.random.default_rng(seed))
                signs = np.random.default_rng(100 + seed).choice([-1.0, 1.0], u.shape)
                c = lqr_controller(x, u + eps * signs)
                k_max.append(np.abs(c.k).max())
                rho.append(np.max(np.abs(np.linalg.eigvals(PLANT.A + PLANT.B @ c.k))))
                value.append(c.value)
            print(f"N = {n:>2}, eps = {eps:<6g}: max|K| median {np.median(k_max):.3g} (max {max(k_max):.3g}), "
                  f"rho median {np.median(rho):.4f} [{min(rho):.4f}, {max(rho):.4f}], value median "
                  f"{np.median(value):.4f}")


if __name__ == "__main__":
    main()
