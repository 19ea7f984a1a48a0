"""Double-integrator dynamics in d = 2 or 3 dimensions, the first :class:`AgentModel`.

State s = [p, v] (2d entries), input u = a (d entries). The paper discretises with a first-order
Euler step (the default here); the exact zero-order hold is offered as well.
:class:`DoubleIntegrator` implements :class:`swarmpc.model.agent_model.AgentModel` and is
registered there as ``double_integrator``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import casadi as ca
import numpy as np

if TYPE_CHECKING:
    from swarmpc.model.agent_model import AgentModel

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
    """Discrete double integrator s = [p, v], u = a: a setup-once object for stepping and rolling
    out, and the :class:`~swarmpc.model.agent_model.AgentModel` of the paper's agents."""

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
    def name(self) -> str:
        return "double_integrator"

    @property
    def state_dim(self) -> int:
        return 2 * self.dim

    @property
    def input_dim(self) -> int:
        return self.dim

    @property
    def position_rows(self) -> slice:
        return slice(0, self.dim)

    @property
    def first_constrained_step(self) -> int:
        """2 for Euler, where p(1) = p(0) + dt v(0) is fixed by the measured state; 1 for the
        zero-order hold, where p(1) depends on u(0)."""
        return 2 if self.method == "euler" else 1

    def position(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)[..., : self.dim]

    def velocity(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)[..., self.dim :]

    def state_at(self, position: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
        position = np.asarray(position, float)
        velocity = np.zeros_like(position) if velocity is None else np.asarray(velocity, float)
        return np.concatenate([position, velocity], axis=-1)

    def step(self, state: np.ndarray, control: np.ndarray) -> np.ndarray:
        """Next state(s); works on one state (2d,) or a stack (..., 2d)."""
        return state @ self.A.T + control @ self.B.T

    def rollout(self, state: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """States s_0..s_N for inputs u_0..u_{N-1} (N, d) from s_0 = ``state``."""
        states = [np.asarray(state, float)]
        for control in controls:
            states.append(self.step(states[-1], control))
        return np.array(states)

    def guess_inputs(self, states: np.ndarray) -> np.ndarray:
        """The accelerations that reproduce the guessed velocities: (v_{k+1} - v_k) / dt."""
        return np.diff(self.velocity(states), axis=0) / self.dt

    def input_bounds(self, accel: np.ndarray | None, speed: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The acceleration box (inf where unlimited); the speed limit is a state constraint."""
        amax = accel if accel is not None else np.full(self.dim, np.inf)
        return -amax, amax

    def casadi_dynamics(self, X: Any, U: Any) -> Any:
        return ca.mtimes(self.A, X[:, :-1]) + ca.mtimes(self.B, U)

    def casadi_speed_sq(self, X: Any, U: Any) -> Any:
        """||v_k||^2 of the planned states k = 1..N (v_0 is measured)."""
        return ca.sum1(X[self.dim :, 1:] ** 2)

    def braking_inputs(self, state: np.ndarray, horizon: int, accel_limit: np.ndarray | None) -> np.ndarray:
        """Decelerate as hard as the limits allow, then hold: u_k = clip(-v_k / dt). Without an
        acceleration limit the agent stops within one step."""
        amax = accel_limit if accel_limit is not None else np.full(self.dim, np.inf)
        current = np.asarray(state, float)
        inputs = []
        for _ in range(horizon):
            control = np.clip(-self.velocity(current) / self.dt, -amax, amax)
            inputs.append(control)
            current = self.step(current, control)
        return np.array(inputs).reshape(horizon, self.dim)

    def reach_bound(
        self, states: np.ndarray, steps: int, accel: np.ndarray | None, speed: float | None
    ) -> np.ndarray:
        """Per axis, with an acceleration limit a: ``|v_axis| T + a T^2 / 2`` (T = steps dt), the
        continuous-time bound, which both discretisations stay within (Euler moves
        dt^2 a k(k-1)/2 in k steps, the zero-order hold exactly a (k dt)^2 / 2). With a speed
        limit s (a bound on the norm, so on every axis, for every planned velocity after the
        measured one): ``T max(s, |v_axis|)``, which also covers a measured velocity above the
        limit (the first step moves with it) and braking (whose speed never grows). With both
        limits the smaller bound, with neither inf; the largest axis is returned."""
        horizon_time = steps * self.dt
        velocity = np.abs(self.velocity(np.asarray(states, float)))
        reach = np.full(velocity.shape, np.inf)
        if accel is not None:
            reach = velocity * horizon_time + 0.5 * np.asarray(accel, float) * horizon_time**2
        if speed is not None:
            reach = np.minimum(reach, horizon_time * np.maximum(velocity, speed))
        return reach.max(axis=-1)

    def linear_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        return self.A, self.B


def _linear(model: AgentModel) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of a linear model; ValueError for a nonlinear one."""
    matrices = model.linear_matrices()
    if matrices is None:
        raise ValueError(f"the {model.name} model is not linear: no Riccati terminal weight")
    return matrices


def lqr_terminal_weight(model: AgentModel, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Infinite-horizon cost-to-go P of ``model`` with stage cost sᵀQs + uᵀRu.

    P is the stabilising solution of the discrete algebraic Riccati equation
    P = AᵀPA − AᵀPB (R + BᵀPB)⁻¹ BᵀPA + Q of the discretised dynamics (A, B). Used as the
    terminal weight of a finite-horizon MPC, it makes the MPC equal to the infinite-horizon LQR
    wherever no constraint binds, whatever the horizon, which is why it is offered as
    ``weights.Qf: lqr``.

    Parameters
    ----------
    model
        The agent's linear model (an :class:`~swarmpc.model.agent_model.AgentModel` whose
        ``linear_matrices`` are not None), e.g. the discretised double integrator (its ``dt``
        and ``method`` matter).
    Q
        (n, n) symmetric positive semidefinite state weight ((2d, 2d) for the double
        integrator, where every mode must show in it: a weight on each position suffices, see
        :func:`riccati_weights_problem`).
    R
        (m, m) symmetric positive definite input weight ((d, d) for the double integrator).

    Returns
    -------
    numpy.ndarray
        (n, n) symmetric positive definite P.

    Raises
    ------
    ValueError
        When the Riccati equation has no stabilising solution for these weights.
    """
    Q, R = np.asarray(Q, float), np.asarray(R, float)
    A, B = _linear(model)
    problem = riccati_weights_problem(Q, R) if isinstance(model, DoubleIntegrator) else None
    if problem is not None:
        raise ValueError(problem)
    import scipy.linalg  # here, not at the top: the command line starts without scipy (about 0.4 s)

    try:
        P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    except (np.linalg.LinAlgError, ValueError) as err:
        raise ValueError(f"no stabilising Riccati solution for these Q, R ({err})") from None
    return 0.5 * (P + P.T)


def lqr_gain(model: AgentModel, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Infinite-horizon LQR gain K = (R + BᵀPB)⁻¹BᵀPA, the input being u = −K (s − s_goal).

    The reference the ``Qf: lqr`` MPC must reproduce where no constraint binds.
    """
    P = lqr_terminal_weight(model, Q, R)
    A, B = _linear(model)
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
