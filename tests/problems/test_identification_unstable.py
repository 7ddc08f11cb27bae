"""Issue 44 item 1: a stealthy identification attack on an unstable plant (pole 1.2, T = 40, stealth 0.05), whose
stealth constraints leave a feasible set of about 4e-4 of the budget around the clean data. The clean data (zero
poisoning, a stationary point and the attack's worst) were returned `solved` with objective 1e-19: the stealth start
fell back to zero and the local probe, whose radii all lay outside the feasible set, saw no feasible neighbour."""

from __future__ import annotations

import numpy as np
import pytest

from bilevel.problems.identification import declare
from bilevel.problems.identification_instance import IdentificationAttack, IdentificationSetting
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.verdict.probe import improving_neighbour
from tests.problems.test_identification_experiment import own_statistics

DELTA = 0.05


def unstable_attack() -> IdentificationAttack:
    """x+ = 1.2 x + u + w, T = 40 (the states grow to about 1e3; the noise std is 0.1)."""
    setting = IdentificationSetting(np.array([1.0]), np.array([1.0, -1.2]))
    X, U = setting.state_data(40, np.random.default_rng(0))
    return IdentificationAttack(setting, "ss", {"X": X, "U": U}, {"X": 0.05, "U": 0.05}, stealth=DELTA)


def error(atk: IdentificationAttack, dX: np.ndarray, dU: np.ndarray) -> float | None:
    """||[A B] - [A B]_clean||_F^2 of the numpy refit on the poisoned data, None where a statistic moves by more
    than DELTA or the budget is exceeded (up to the engine's feasibility tolerance 1e-6; independent statistics)."""
    X, U = atk.signals["X"] + dX, atk.signals["U"] + dU
    if any(np.linalg.norm(d) > 0.05 * (1 + 1e-6) * np.linalg.norm(atk.signals[k]) for k, d in (("X", dX), ("U", dU))):
        return None
    clean, after = (own_statistics(x, u, 0.1, atk.lags) for x, u in ((atk.signals["X"], atk.signals["U"]), (X, U)))
    if any(abs(1 - after[k] / clean[k]) > DELTA + 1e-6 for k in clean):
        return None
    Z, Y = np.vstack([X[:, :-1], U]), X[:, 1:]
    theta = np.linalg.lstsq(Z.T, Y.T, rcond=None)[0].T
    return float(np.sum((theta - atk.theta0) ** 2))


def random_stealthy_best(atk: IdentificationAttack, directions: int = 20) -> float:
    """The best error of random poisonings, each direction scaled down by 2 from the full budget until stealthy."""
    rng, best = np.random.default_rng(1), 0.0
    for _ in range(directions):
        d = {k: rng.standard_normal(v.shape) for k, v in atk.signals.items()}
        d = {k: v * 0.05 * np.linalg.norm(atk.signals[k]) / np.linalg.norm(v) for k, v in d.items()}
        for j in range(40):
            value = error(atk, 2.0 ** -j * d["X"], 2.0 ** -j * d["U"])
            if value is not None:
                best = max(best, value)
                break
    return best


def test_unstable_plant_attack_is_not_the_clean_data() -> None:
    atk = unstable_attack()
    result = declare(atk).solve("auto", seed=0)
    floor = random_stealthy_best(atk)
    assert floor > 1e-6  # the clean data (error 0) are beaten by a random stealthy poisoning
    assert result.status.value in ("solved", "inaccurate"), result.message
    dX, dU = (np.reshape(result.x[f"d{k}"], atk.signals[k].shape) for k in ("X", "U"))
    value = error(atk, dX, dU)
    assert value is not None and value == pytest.approx(result.upper_objective, rel=1e-6)
    assert value >= floor


def test_probe_sees_the_narrow_feasible_set_around_the_clean_data() -> None:
    """At zero poisoning every probe at the radii 0.1, 0.01, 0.001 of the budget breaks a stealth constraint; the
    probe goes on to smaller radii and finds a better stealthy neighbour."""
    prep = prepare(declare(unstable_attack()))
    x = np.zeros(prep.canon.x_lb.size)
    better = improving_neighbour(prep, x, 0.0, prep.projection)
    assert better is not None and better.radius < 1e-3 and better.objective < -1e-8
    dX, dU = better.x[:41].reshape(1, 41), better.x[41:].reshape(1, 40)
    assert error(unstable_attack(), dX, dU) == pytest.approx(-better.objective, rel=1e-6)
