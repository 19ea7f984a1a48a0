"""What every MPC solver returns, and the safe fallback plans used when a solve fails."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.dynamics import DoubleIntegrator


@dataclass(frozen=True)
class PlanStep:
    """The outcome of one MPC step for the whole swarm.

    ``states`` (M, N+1, 2d) and ``inputs`` (M, N, d) are each agent's own, dynamically feasible
    plan; ``fallback`` marks agents whose solve failed and whose plan is a safe fallback.
    """

    states: np.ndarray
    inputs: np.ndarray
    predicted_cost: float
    max_slack: float
    wall_time: float
    agent_times: np.ndarray
    failures: int
    fallback: np.ndarray
    admm_iterations: int | None = None
    repaired: bool = False
    primal_residuals: list[float] = field(default_factory=list)
    dual_residuals: list[float] = field(default_factory=list)
    rho_history: list[float] = field(default_factory=list)


def input_bounds(settings: OCPSettings) -> np.ndarray:
    """Per-axis acceleration bound (inf when unbounded)."""
    return settings.accel if settings.accel is not None else np.full(settings.dim, np.inf)


def braking_plan(state: np.ndarray, settings: OCPSettings) -> tuple[np.ndarray, np.ndarray]:
    """Decelerate to rest as hard as the limits allow, then hold: (states (N+1, 2d), inputs (N, d)).

    Without acceleration limits it stops within one step, the safest thing a double integrator
    can do when no plan can be trusted.
    """
    model = DoubleIntegrator(settings.dim, settings.dt, settings.discretization)  # type: ignore[arg-type]
    d, amax = settings.dim, input_bounds(settings)
    states = [np.asarray(state, float)]
    inputs = []
    for _ in range(settings.horizon):
        velocity = states[-1][d:]
        control = np.clip(-velocity / settings.dt, -amax, amax)
        inputs.append(control)
        states.append(model.step(states[-1], control))
    return np.array(states), np.array(inputs)


def fallback_plan(
    state: np.ndarray, previous_states: np.ndarray | None, previous_inputs: np.ndarray | None,
    settings: OCPSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """The previous plan shifted by one step when it starts at ``state``, else a braking plan."""
    if previous_states is not None and previous_inputs is not None:
        if np.allclose(previous_states[1], state, atol=1e-9):
            braking_tail_states, braking_tail_inputs = braking_plan(previous_states[-1], settings)
            states = np.vstack([previous_states[1:], braking_tail_states[1:2]])
            inputs = np.vstack([previous_inputs[1:], braking_tail_inputs[:1]])
            return states, inputs
    return braking_plan(state, settings)
