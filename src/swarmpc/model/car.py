"""A kinematic bicycle car: the first nonlinear :class:`~swarmpc.model.agent_model.AgentModel`.

State s = [x, y, theta, v]: the position of the reference point (the centre of the rear axle),
the heading and the signed speed along it (negative when reversing). Input u = [a, delta]: the
longitudinal acceleration [m/s^2] and the steering angle of the front wheels [rad]. In continuous
time::

    x' = v cos(theta),  y' = v sin(theta),  theta' = v tan(delta) / wheelbase,  v' = a.

Discretisation. The input is held over a sampling step (zero-order hold). Unlike the double
integrator, the bicycle has no closed-form step: while the speed changes, the heading is quadratic
in time and the position a Fresnel integral, which has no elementary form (nor a CasADi
function). The step is therefore integrated numerically, with ``substeps`` classical Runge-Kutta
(RK4) substeps per ``dt``. RK4's error is O(h^4) in the substep h (O(h^5) per substep), so a
few substeps keep it far below the planner's tolerances, whereas an Euler step moves along the
tangent and drifts outwards on every turn (it lengthens the radius of a constant-steering circle
step after step). The speed and the heading are integrated exactly by RK4 (v is
linear in time within a step, theta' linear in v), so only x and y carry the integration error.
The numpy (:meth:`KinematicCar.step`) and CasADi (:meth:`KinematicCar.casadi_dynamics`) steps
evaluate the same expression (:func:`rk4_step`), so a plan the solver finds is the trajectory the
simulated agent flies, to rounding.

The model is registered as ``car`` in :mod:`swarmpc.model.agent_model`; it works in the plane
only (dim = 2).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

__all__ = ["KinematicCar", "rk4_step"]

CAR_DISCRETIZATIONS = ("rk4", "euler", "zoh")
"""Discretisation names the car accepts: ``rk4`` is what it does; ``euler`` and ``zoh`` (the
scenario's choice for the double integrator, ``euler`` by default) are accepted so that a scenario
runs unchanged with the car, and select the same RK4 step."""

Trig = Callable[[Any], Any]


def rk4_step(
    state: tuple[Any, Any, Any, Any], accel: Any, curvature: Any, h: float, substeps: int, cos: Trig, sin: Trig
) -> tuple[Any, Any, Any, Any]:
    """One sampling step of the bicycle: ``substeps`` RK4 substeps of length ``h`` under a constant
    input.

    Written once for numpy arrays and CasADi expressions alike (the arithmetic operators are
    elementwise in both), so that both backends evaluate the same expression.

    Parameters
    ----------
    state
        (x, y, theta, v), each an array or a CasADi row of the same shape.
    accel
        Longitudinal acceleration a.
    curvature
        tan(delta) / wheelbase: the path's curvature, constant over the step.
    h
        Substep length dt / substeps [s].
    substeps
        Number of RK4 substeps.
    cos, sin
        The backend's trigonometric functions.

    Returns
    -------
    tuple
        (x, y, theta, v) after the step.
    """
    x, y, theta, v = state
    for _ in range(substeps):
        v_mid, v_end = v + 0.5 * h * accel, v + h * accel  # the stages' speeds: v' = a is constant
        theta_2 = theta + 0.5 * h * v * curvature  # theta at stage 2, from stage 1's slope
        theta_3 = theta + 0.5 * h * v_mid * curvature  # theta at stage 3, from stage 2's slope
        theta_4 = theta + h * v_mid * curvature  # theta at stage 4, from stage 3's slope
        x = x + h / 6 * (v * cos(theta) + 2 * v_mid * cos(theta_2) + 2 * v_mid * cos(theta_3) + v_end * cos(theta_4))
        y = y + h / 6 * (v * sin(theta) + 2 * v_mid * sin(theta_2) + 2 * v_mid * sin(theta_3) + v_end * sin(theta_4))
        theta = theta + h / 6 * (v + 4 * v_mid + v_end) * curvature
        v = v_end
    return x, y, theta, v


def _require(condition: bool, name: str, requirement: str, value: Any) -> None:
    """ValueError naming the parameter ``name`` unless ``condition``."""
    if not condition:
        raise ValueError(f"car parameter {name} must be {requirement}, got {value!r}")


@dataclass(frozen=True)
class KinematicCar:
    """Kinematic bicycle car, state [x, y, theta, v], input [a, delta] (see the module docstring).

    The position the planner keeps clear (``position_rows``) is the reference point, the centre of
    the rear axle; the rectangular body (``footprint``) extends ``rear_overhang`` behind it, so
    its centre lies ``length / 2 - rear_overhang`` ahead of it along the heading (:meth:`pose`).

    The model is nonlinear: :meth:`linear_matrices` is None, so a ``Qf: lqr`` terminal weight is
    refused. The IPOPT local step and the centralised solver take its CasADi dynamics as they
    are; the QP local step of car ADMM (:mod:`swarmpc.solvers.footprint_qp`) expands them about
    each round's plan.

    Parameters
    ----------
    dim
        Workspace dimension; must be 2.
    dt
        Sampling time [s], > 0.
    discretization
        One of :data:`CAR_DISCRETIZATIONS`; every one selects the RK4 step.
    wheelbase
        Distance between the rear and the front axle [m], > 0.
    length, width
        The rectangular footprint [m], > 0.
    rear_overhang
        Distance from the rear bumper to the reference point [m], in [0, length].
    max_steer
        Largest steering angle [rad], in (0, pi/2).
    default_accel
        Longitudinal acceleration limit [m/s^2], > 0, used when the scenario sets none.
    max_speed, max_reverse_speed
        The vehicle's forward and reverse speed limits [m/s] (> 0 and >= 0): :attr:`speed_range`.
        The formulation bounds the speed with the scenario's symmetric limit (through
        :meth:`casadi_speed_sq`); it has no per-state bounds a model could hand it yet, so these
        limits describe the vehicle but do not constrain its plans.
    substeps
        RK4 substeps per sampling step, >= 1.
    """

    dim: int
    dt: float
    discretization: str = "rk4"
    wheelbase: float = 0.5
    length: float = 0.7
    width: float = 0.45
    rear_overhang: float = 0.1
    max_steer: float = 0.6
    default_accel: float = 1.0
    max_speed: float = 1.5
    max_reverse_speed: float = 0.5
    substeps: int = 4

    def __post_init__(self) -> None:
        _require(self.dim == 2, "dim", "2 (the car moves in the plane)", self.dim)
        _require(self.discretization in CAR_DISCRETIZATIONS, "discretization", f"one of {CAR_DISCRETIZATIONS}",
                 self.discretization)
        for name in ("dt", "wheelbase", "length", "width", "default_accel", "max_speed"):
            value = getattr(self, name)
            _require(math.isfinite(value) and value > 0, name, "finite and > 0", value)
        _require(math.isfinite(self.max_reverse_speed) and self.max_reverse_speed >= 0, "max_reverse_speed",
                 "finite and >= 0", self.max_reverse_speed)
        _require(0 <= self.rear_overhang <= self.length, "rear_overhang", f"in [0, length = {self.length}]",
                 self.rear_overhang)
        _require(0 < self.max_steer < math.pi / 2, "max_steer", "in (0, pi/2)", self.max_steer)
        _require(isinstance(self.substeps, int) and self.substeps >= 1, "substeps", "an integer >= 1",
                 self.substeps)

    @property
    def name(self) -> str:
        return "car"

    @property
    def state_dim(self) -> int:
        return 4

    @property
    def input_dim(self) -> int:
        return 2

    @property
    def position_rows(self) -> slice:
        return slice(0, 2)

    @property
    def heading_row(self) -> int:
        """The state entry holding the heading theta [rad]."""
        return 2

    @property
    def speed_row(self) -> int:
        """The state entry holding the signed speed v [m/s]."""
        return 3

    @property
    def first_constrained_step(self) -> int:
        """1: RK4's inner stages use the input, so the first step's position depends on it."""
        return 1

    @property
    def footprint(self) -> tuple[float, float]:
        """(length, width) of the rectangular body [m]."""
        return self.length, self.width

    @property
    def speed_range(self) -> tuple[float, float]:
        """(lowest, highest) signed speed of the vehicle: (-max_reverse_speed, max_speed)."""
        return -self.max_reverse_speed, self.max_speed

    @property
    def centre_offset(self) -> float:
        """Distance from the reference point forward to the footprint's centre [m] (negative when
        the centre lies behind it)."""
        return 0.5 * self.length - self.rear_overhang

    @property
    def body_radius(self) -> float:
        """Largest distance from the reference point to a point of the footprint (a corner) [m]."""
        return math.hypot(max(self.rear_overhang, self.length - self.rear_overhang), 0.5 * self.width)

    @property
    def max_curvature(self) -> float:
        """tan(max_steer) / wheelbase: the sharpest turn [1/m]."""
        return math.tan(self.max_steer) / self.wheelbase

    def position(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)[..., :2]

    def velocity(self, states: np.ndarray) -> np.ndarray:
        """Planar velocities (..., 2) of the reference point: v [cos theta, sin theta]."""
        states = np.asarray(states, float)
        theta, v = states[..., 2], states[..., 3]
        return np.stack([v * np.cos(theta), v * np.sin(theta)], axis=-1)

    def state_at(self, position: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
        """States (..., 4) at positions (..., 2): at rest facing +x, or driving forwards along
        ``velocity`` (heading its direction, speed its norm; a zero velocity is at rest facing +x)."""
        position = np.asarray(position, float)
        velocity = np.zeros_like(position) if velocity is None else np.asarray(velocity, float)
        position, velocity = np.broadcast_arrays(position, velocity)
        theta = np.arctan2(velocity[..., 1], velocity[..., 0])
        speed = np.hypot(velocity[..., 0], velocity[..., 1])
        return np.concatenate([position, theta[..., None], speed[..., None]], axis=-1)

    def pose(self, states: np.ndarray) -> np.ndarray:
        """Poses (..., 3) [x_c, y_c, theta] of the footprint's centre for states (..., 4)."""
        states = np.asarray(states, float)
        theta = states[..., 2]
        x_c = states[..., 0] + self.centre_offset * np.cos(theta)
        y_c = states[..., 1] + self.centre_offset * np.sin(theta)
        return np.stack([x_c, y_c, theta], axis=-1)

    def casadi_pose(self, X: Any) -> Any:
        """The CasADi poses (3, K) [x_c, y_c, theta] of the footprint's centre for the states
        X (4, K): :meth:`pose` as an expression, for the footprint OBCA rows of an OCP."""
        theta = X[2, :]
        return ca.vertcat(X[0, :] + self.centre_offset * ca.cos(theta),
                          X[1, :] + self.centre_offset * ca.sin(theta), theta)

    def step(self, state: np.ndarray, control: np.ndarray) -> np.ndarray:
        """Next state(s) (..., 4) from state(s) (..., 4) under input(s) (..., 2) (broadcast)."""
        state, control = np.asarray(state, float), np.asarray(control, float)
        curvature = np.tan(control[..., 1]) / self.wheelbase
        components = (state[..., 0], state[..., 1], state[..., 2], state[..., 3])
        following = rk4_step(components, control[..., 0], curvature, self.dt / self.substeps, self.substeps,
                             np.cos, np.sin)
        return np.stack(np.broadcast_arrays(*following), axis=-1)

    def rollout(self, state: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """States s_0..s_N for inputs u_0..u_{N-1} (N, 2) from s_0 = ``state``."""
        states = [np.asarray(state, float)]
        for control in controls:
            states.append(self.step(states[-1], control))
        return np.array(states).reshape(len(states), self.state_dim)

    def guess_inputs(self, states: np.ndarray) -> np.ndarray:
        """Inputs (N, 2) between the states (N+1, 4) of a guess: a = (v_{k+1} - v_k) / dt and the
        steering that turns the heading by theta_{k+1} - theta_k at the step's mean speed,
        tan(delta) = wheelbase (theta_{k+1} - theta_k) / (dt (v_k + v_{k+1}) / 2), within
        +-max_steer (at zero mean speed: straight ahead if the heading holds, else full lock).

        Both are exact for a step of the dynamics (RK4 integrates v and theta exactly), so a guess
        that obeys them is reproduced. Headings are read as continuous (not wrapped), as the
        model's own steps produce them. The acceleration is left for the caller to clip to the
        scenario's box (:meth:`input_bounds`), the steering is clipped here."""
        states = np.asarray(states, float)
        accel = np.diff(states[:, 3]) / self.dt
        turn = np.diff(states[:, 2]) * self.wheelbase
        travel = 0.5 * (states[:-1, 3] + states[1:, 3]) * self.dt
        moving = np.abs(travel) > 1e-12
        ratio = np.divide(turn, travel, out=np.zeros_like(turn), where=moving)
        steer = np.where(moving, np.arctan(ratio), np.sign(turn) * self.max_steer)
        return np.stack([accel, np.clip(steer, -self.max_steer, self.max_steer)], axis=-1)

    def accel_limit(self, accel: np.ndarray | None) -> float:
        """The longitudinal acceleration limit under the scenario's limit (d,) (None: unset).

        The scenario's limit is per axis; the car accelerates along its heading, which may point
        along any axis, so it is held to the smallest of them. Without one, ``default_accel``."""
        return self.default_accel if accel is None else float(np.min(accel))

    def input_bounds(self, accel: np.ndarray | None, speed: float | None) -> tuple[np.ndarray, np.ndarray]:
        """[-a_max, -max_steer] .. [a_max, max_steer] (a_max: :meth:`accel_limit`); the speed
        limit is a state constraint (:meth:`casadi_speed_sq`)."""
        upper = np.array([self.accel_limit(accel), self.max_steer])
        return -upper, upper

    def casadi_dynamics(self, X: Any, U: Any) -> Any:
        """The RK4 step (:func:`rk4_step`) of every column of X but the last under U's columns."""
        curvature = ca.tan(U[1, :]) / self.wheelbase
        components = (X[0, :-1], X[1, :-1], X[2, :-1], X[3, :-1])
        following = rk4_step(components, U[0, :], curvature, self.dt / self.substeps, self.substeps, ca.cos, ca.sin)
        return ca.vertcat(*following)

    def casadi_speed_sq(self, X: Any, U: Any) -> Any:
        """v_k^2 of the planned states k = 1..N (v_0 is measured): the planar speed squared."""
        return X[3, 1:] ** 2

    def braking_inputs(self, state: np.ndarray, horizon: int, accel_limit: np.ndarray | None) -> np.ndarray:
        """Wheels straight, decelerate as hard as the limit allows, then hold at rest:
        a_k = clip(-v_k / dt, -a_max, a_max), delta_k = 0. A car cannot side-step, so braking in a
        straight line along its heading is its plan of last resort; its speed never grows."""
        a_max = self.accel_limit(accel_limit)
        current = np.asarray(state, float)
        inputs = []
        for _ in range(horizon):
            control = np.array([np.clip(-current[3] / self.dt, -a_max, a_max), 0.0])
            inputs.append(control)
            current = self.step(current, control)
        return np.array(inputs).reshape(horizon, self.input_dim)

    def reach_bound(
        self, states: np.ndarray, steps: int, accel: np.ndarray | None, speed: float | None
    ) -> np.ndarray:
        """Per state (..., 4), a bound on how far any point of the footprint (the reference point
        included) moves within ``steps`` steps of any admissible plan: ``D + r min(2, kappa D)``.

        D bounds the reference point's path length. Over an RK4 substep of length h the
        reference point moves at most h/6 (|v_0| + 4 |v_mid| + |v_1|) <= h (|v_0| + |v_1|) / 2 (v
        is linear within the step), the trapezoid rule on the speed at the substep ends; with
        |v(t)| <= |v_0| + a_max t this sums to at most ``|v_0| T + a_max T^2 / 2`` (T = steps dt,
        a_max from the input box, always set: :meth:`accel_limit`). With a speed limit s, which
        holds at every planned state after the measured one, the speeds at the substep ends stay
        within max(|v_0|, s), so D <= ``T max(|v_0|, s)`` as well; the smaller bound holds. The
        braking plan (speed never grows) obeys both. The heading turns by at most kappa D
        (kappa = :attr:`max_curvature`; RK4 integrates theta' = v kappa exactly), which moves a
        point at distance r from the reference point by at most r min(2, kappa D); r =
        :attr:`body_radius` covers the whole footprint. The inf-norm displacement the protocol
        asks for is no larger than these Euclidean bounds."""
        horizon_time = steps * self.dt
        speed_now = np.abs(np.asarray(states, float)[..., 3])
        path = speed_now * horizon_time + 0.5 * self.accel_limit(accel) * horizon_time**2
        if speed is not None:
            path = np.minimum(path, horizon_time * np.maximum(speed_now, speed))
        return path + self.body_radius * np.minimum(2.0, self.max_curvature * path)

    def linear_matrices(self) -> None:
        """None: the bicycle is nonlinear (consumers needing one (A, B), such as the point agents'
        QP local step and the Riccati terminal weight, refuse the model with a ValueError)."""
        return None
