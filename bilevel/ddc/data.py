"""Open-loop experiment data: the paper's input signals and exact zero-initial-state simulation."""

from __future__ import annotations

from typing import Literal

import control
import numpy as np
from numpy.typing import ArrayLike

from bilevel.errors import InvalidData
from bilevel.ddc.operators import LTIOperator
from bilevel.ddc.plants import batch_reactor
from bilevel.ddc.systems import SystemLike


def step_pulse(n: int, start: int = 5, stop: int = 15) -> np.ndarray:
    """u_t = 1 for start <= t <= stop, else 0 (the paper's scenario A with the defaults)."""
    u = np.zeros(n)
    u[start:stop + 1] = 1.0
    return u


def white_noise(n: int, rng: np.random.Generator, channels: int | None = None) -> np.ndarray:
    """u_t ~ N(0, 1) i.i.d., shape (n,) or (channels, n) (the paper's scenario B)."""
    return rng.standard_normal(n if channels is None else (channels, n))


def paper_input(
    scenario: Literal["A", "B"], n: int = 512, rng: np.random.Generator | None = None
) -> np.ndarray:
    """Input of the paper's VRFT scenario A (step pulse on [5, 15]) or B (white noise, needs rng)."""
    if scenario == "A":
        return step_pulse(n)
    if scenario == "B":
        if rng is None:
            raise InvalidData("scenario B draws white noise: pass rng=numpy.random.default_rng(seed)")
        return white_noise(n, rng)
    raise InvalidData(f"unknown scenario {scenario!r}; use 'A' (step pulse) or 'B' (white noise)")


def simulate(plant: SystemLike, u: ArrayLike) -> np.ndarray:
    """Output y = T_G u of a SISO plant from zero initial state (exact, O(N))."""
    u = np.asarray(u, dtype=float)
    if u.ndim != 1 or not np.all(np.isfinite(u)):
        raise InvalidData(f"input must be a finite 1-D signal, got shape {u.shape}")
    return LTIOperator(plant).apply(u)


def state_trajectory(
    a: ArrayLike, b: ArrayLike, u: ArrayLike, x0: ArrayLike | None = None
) -> np.ndarray:
    """States X = [x_0 .. x_T] (n x (T+1)) of x_{t+1} = A x_t + B u_t for inputs U (m x T)."""
    a, b, u = np.asarray(a, float), np.asarray(b, float), np.atleast_2d(np.asarray(u, float))
    n, m = b.shape
    if a.shape != (n, n) or u.shape[0] != m:
        raise InvalidData(f"shapes disagree: A {a.shape}, B {b.shape}, U {u.shape} (need n x n, n x m, m x T)")
    x = np.zeros((n, u.shape[1] + 1))
    x[:, 0] = 0.0 if x0 is None else np.asarray(x0, float)
    for t in range(u.shape[1]):
        x[:, t + 1] = a @ x[:, t] + b @ u[:, t]
    return x


def white_noise_trajectory(
    a: ArrayLike, b: ArrayLike, horizon: int, rng: np.random.Generator, input_std: float = 1.0,
    x0: ArrayLike | Literal["random"] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(X, U) of one experiment on x_{t+1} = A x_t + B u_t: U (m x T) i.i.d. N(0, input_std^2), then X (n x (T+1))
    from x0 (0 when None; "random": drawn N(0, I) from rng after U)."""
    b = np.atleast_2d(np.asarray(b, dtype=float))
    u = input_std * white_noise(horizon, rng, channels=b.shape[1])
    if isinstance(x0, str):
        if x0 != "random":
            raise InvalidData(f"x0={x0!r}: give the initial state as n numbers, None (x0 = 0) or 'random'")
        x0 = rng.standard_normal(b.shape[0])
    return state_trajectory(a, b, u, x0), u


def batch_reactor_data(
    horizon: int, rng: np.random.Generator, random_x0: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(X, U): batch reactor states (4 x (T+1)) under white input U (2 x T); x0 = 0 or N(0, I)."""
    plant: control.StateSpace = batch_reactor()
    return white_noise_trajectory(plant.A, plant.B, horizon, rng, x0="random" if random_x0 else None)
