"""Double-integrator dynamics in d = 2 or 3 dimensions.

State s = [p, v] (2d entries), input u = a (d entries). The paper discretises with a first-order
Euler step (the default here); the exact zero-order hold is offered as well.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Discretization = Literal["euler", "zoh"]


def continuous_matrices(dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of ds/dt = A s + B u for the double integrator."""
    A = np.zeros((2 * dim, 2 * dim))
    A[:dim, dim:] = np.eye(dim)
    B = np.zeros((2 * dim, dim))
    B[dim:, :] = np.eye(dim)
    return A, B


def discrete_matrices(dim: int, dt: float, method: Discretization = "euler") -> tuple[np.ndarray, np.ndarray]:
    """(A_k, B_k) with s_{k+1} = A_k s_k + B_k u_k.

    Euler: A_k = I + A dt, B_k = B dt (the paper). ZOH: the exact solution for a constant input
    over the step, which adds dt^2/2 to the position's response to the input.
    """
    if dt <= 0:
        raise ValueError("dt must be > 0")
    A, B = continuous_matrices(dim)
    Ak = np.eye(2 * dim) + A * dt
    Bk = B * dt
    if method == "zoh":
        Bk = Bk.copy()
        Bk[:dim, :] = 0.5 * dt * dt * np.eye(dim)
    elif method != "euler":
        raise ValueError(f"unknown discretisation {method!r}")
    return Ak, Bk


@dataclass(frozen=True)
class DoubleIntegrator:
    """Discrete double integrator: a setup-once object for stepping and rolling out."""

    dim: int
    dt: float
    method: Discretization = "euler"
    A: np.ndarray = field(init=False, repr=False)
    B: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        Ak, Bk = discrete_matrices(self.dim, self.dt, self.method)
        object.__setattr__(self, "A", Ak)
        object.__setattr__(self, "B", Bk)

    @property
    def state_dim(self) -> int:
        return 2 * self.dim

    def step(self, state: np.ndarray, control: np.ndarray) -> np.ndarray:
        """Next state(s); works on one state (2d,) or a stack (..., 2d)."""
        return state @ self.A.T + control @ self.B.T

    def rollout(self, state: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """States s_0..s_N for inputs u_0..u_{N-1} (N, d) from s_0 = ``state``."""
        states = [np.asarray(state, float)]
        for control in controls:
            states.append(self.step(states[-1], control))
        return np.array(states)
