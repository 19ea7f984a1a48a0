"""The agent-model seam: what the planner needs of an agent's dynamics, and the registry of models.

Every layer above this one (the OCP, the solvers, the closed loop) reaches an agent's state only
through an :class:`AgentModel`: where the position is in the state, how the state steps, how the
dynamics and the speed read in CasADi, how the agent brakes and how far it can get. A new kind of
agent is then one class implementing the protocol plus a :func:`register_model` call; nothing
else assumes a state layout.

The double integrator (:class:`swarmpc.model.dynamics.DoubleIntegrator`, state [p, v], input a)
is registered as ``double_integrator``, the kinematic bicycle (:class:`swarmpc.model.car.KinematicCar`,
state [x, y, theta, v], input [a, delta], planar only) as ``car``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, Protocol, runtime_checkable

import numpy as np

from swarmpc.model.car import KinematicCar
from swarmpc.model.dynamics import DoubleIntegrator

__all__ = [
    "AgentModel",
    "ModelFactory",
    "make_model",
    "model_names",
    "register_model",
    "registered_model",
    "unregister_model",
]


@runtime_checkable
class AgentModel(Protocol):
    """An agent's discrete-time dynamics as the planner sees them.

    States are vectors of ``state_dim`` entries, inputs of ``input_dim``; numpy methods take any
    leading shape (one state (n,), a stack (..., n)). The position (``dim`` entries, the point
    OBCA keeps out of obstacles and other agents) is a contiguous block of state entries,
    ``position_rows``: the formulation bounds those entries to the workspace and hands them to
    the collision constraints.
    """

    @property
    def name(self) -> str:
        """The name the model is registered under."""
        ...

    @property
    def dim(self) -> int:
        """Workspace dimension d (2 or 3)."""
        ...

    @property
    def dt(self) -> float:
        """Sampling time [s]."""
        ...

    @property
    def state_dim(self) -> int:
        """Entries of a state."""
        ...

    @property
    def input_dim(self) -> int:
        """Entries of an input."""
        ...

    @property
    def position_rows(self) -> slice:
        """The state entries that hold the position."""
        ...

    @property
    def first_constrained_step(self) -> int:
        """First horizon step whose position depends on the inputs (the OCP constrains positions
        from there on; earlier ones are fixed by the measured state)."""
        ...

    def position(self, states: np.ndarray) -> np.ndarray:
        """Positions (..., d) of states (..., n)."""
        ...

    def velocity(self, states: np.ndarray) -> np.ndarray:
        """Velocities (..., d) of states (..., n) (zeros when the state holds no velocity)."""
        ...

    def state_at(self, position: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
        """States (..., n) at positions (..., d), moving with ``velocity`` (None: at rest)."""
        ...

    def step(self, state: np.ndarray, control: np.ndarray) -> np.ndarray:
        """The next state(s) from state(s) (..., n) under input(s) (..., m)."""
        ...

    def rollout(self, state: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """States (N+1, n) from ``state`` under inputs (N, m), row 0 the state itself."""
        ...

    def guess_inputs(self, states: np.ndarray) -> np.ndarray:
        """Inputs (N, m) that take each state of a guessed trajectory (N+1, n) to the next: exact
        where the guess obeys the dynamics, a consistent start for the solver elsewhere."""
        ...

    def input_bounds(self, accel: np.ndarray | None, speed: float | None) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) box (m,) of the input under the scenario's acceleration limit (d,) and
        speed limit (None: unlimited)."""
        ...

    def casadi_dynamics(self, X: Any, U: Any) -> Any:
        """The CasADi states X_{k+1}, k = 0..N-1, (n, N) of states X (n, N+1) and inputs U (m, N)."""
        ...

    def casadi_speed_sq(self, X: Any, U: Any) -> Any:
        """The CasADi squared speed (1, N) over the horizon's steps, held below the speed limit."""
        ...

    def braking_inputs(self, state: np.ndarray, horizon: int, accel_limit: np.ndarray | None) -> np.ndarray:
        """Inputs (horizon, m) that bring the agent to rest as fast as ``accel_limit`` allows and
        hold it there: the plan of last resort when no solved plan can be trusted."""
        ...

    def reach_bound(
        self, states: np.ndarray, steps: int, accel: np.ndarray | None, speed: float | None
    ) -> np.ndarray:
        """Per state (..., n), an upper bound on the inf-norm displacement of the position within
        ``steps`` steps of any admissible plan (inf when the plans are not limited)."""
        ...

    def linear_matrices(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(A, B) with s_{k+1} = A s_k + B u_k when the model is linear, else None."""
        ...


ModelFactory = Callable[..., AgentModel]
"""Builds a model as ``factory(dim, dt, discretization, **params)``."""

_REGISTRY: dict[str, ModelFactory] = {"double_integrator": DoubleIntegrator, "car": KinematicCar}
"""The registered models by name. Module-level on purpose: registration is the plug-in point a
new kind of agent uses, at import time (and a test, inside :func:`registered_model`)."""


def register_model(name: str, factory: ModelFactory) -> None:
    """Make ``factory`` the model called ``name``; ValueError if the name is taken."""
    if name in _REGISTRY:
        raise ValueError(f"model {name!r} is already registered")
    _REGISTRY[name] = factory


def unregister_model(name: str) -> None:
    """Forget the model called ``name``; KeyError if it is not registered."""
    if name not in _REGISTRY:
        raise KeyError(f"model {name!r} is not registered")
    del _REGISTRY[name]


@contextmanager
def registered_model(name: str, factory: ModelFactory) -> Iterator[None]:
    """Register ``factory`` as ``name`` for the duration of a ``with`` block."""
    register_model(name, factory)
    try:
        yield
    finally:
        unregister_model(name)


def model_names() -> tuple[str, ...]:
    """The names of the registered models, sorted."""
    return tuple(sorted(_REGISTRY))


def make_model(name: str, dim: int, dt: float, discretization: str = "euler", **params: Any) -> AgentModel:
    """The registered model ``name`` for workspace dimension ``dim``, sampling time ``dt`` and
    ``discretization`` (``euler`` or ``zoh``); ``params`` go to the model's factory."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown agent model {name!r} (registered: {', '.join(model_names())})") from None
    return factory(dim, dt, discretization, **params)
