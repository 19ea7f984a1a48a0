"""Double-integrator dynamics in d = 2 or 3 dimensions.

State s = [p, v] (2d entries), input u = a (d entries). The paper discretises with a first-order
Euler step (the default here); the exact zero-order hold is offered as well.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.linalg

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


def lqr_terminal_weight(model: DoubleIntegrator, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Infinite-horizon cost-to-go P of ``model`` with stage cost sᵀQs + uᵀRu.

    P is the stabilising solution of the discrete algebraic Riccati equation
    P = AᵀPA − AᵀPB (R + BᵀPB)⁻¹ BᵀPA + Q of the discretised dynamics (A, B). Used as the
    terminal weight of a finite-horizon MPC, it makes the MPC equal to the infinite-horizon LQR
    wherever no constraint binds, whatever the horizon, which is why it is offered as
    ``weights.Qf: lqr``.

    Parameters
    ----------
    model
        The agent's discretised double integrator (its ``dt`` and ``method`` matter).
    Q
        (2d, 2d) symmetric positive semidefinite state weight; every mode of the double
        integrator must show in it (a weight on each position suffices), see
        :func:`riccati_weights_problem`.
    R
        (d, d) symmetric positive definite input weight.

    Returns
    -------
    numpy.ndarray
        (2d, 2d) symmetric positive definite P.

    Raises
    ------
    ValueError
        When the Riccati equation has no stabilising solution for these weights.
    """
    Q, R = np.asarray(Q, float), np.asarray(R, float)
    problem = riccati_weights_problem(Q, R)
    if problem is not None:
        raise ValueError(problem)
    try:
        P = scipy.linalg.solve_discrete_are(model.A, model.B, Q, R)
    except (np.linalg.LinAlgError, ValueError) as err:
        raise ValueError(f"no stabilising Riccati solution for these Q, R ({err})") from None
    return 0.5 * (P + P.T)


def lqr_gain(model: DoubleIntegrator, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Infinite-horizon LQR gain K = (R + BᵀPB)⁻¹BᵀPA, the input being u = −K (s − s_goal).

    The reference the ``Qf: lqr`` MPC must reproduce where no constraint binds.
    """
    P = lqr_terminal_weight(model, Q, R)
    A, B = model.A, model.B
    return np.linalg.solve(np.asarray(R, float) + B.T @ P @ B, B.T @ P @ A)


def riccati_weights_problem(Q: np.ndarray, R: np.ndarray) -> str | None:
    """Why the double integrator's Riccati equation has no stabilising solution for Q, R, or None.

    Every eigenvalue of the double integrator's A (Euler or zero-order hold, any dt) is 1, on the
    unit circle, so a stabilising solution exists iff R is positive definite and every mode is
    observable through Q: the pair (A_c, Q) with A_c the continuous A has full observability rank.
    A Q that weighs only velocities, for example, leaves positions free and has no solution.
    """
    Q, R = np.asarray(Q, float), np.asarray(R, float)
    size = Q.shape[0] if Q.ndim == 2 else 0
    if size == 0 or Q.shape != (size, size) or size % 2 or R.shape != (size // 2, size // 2):
        return f"Q must be 2d x 2d and R d x d, got {Q.shape} and {R.shape}"
    if np.min(np.linalg.eigvalsh(0.5 * (R + R.T))) <= 0:
        return "R must be positive definite"
    A, _ = continuous_matrices(size // 2)
    observability = np.vstack([Q, Q @ A])
    if np.linalg.matrix_rank(observability) < size:
        return "Q leaves a mode of the double integrator unweighted (give every position a weight)"
    return None
