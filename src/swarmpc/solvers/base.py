"""What every MPC solver is (:class:`MPCSolver`) and returns (:class:`PlanStep`), and the safe
fallback plans used when a solve fails."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from swarmpc.formulation.ocp import OCPSettings


@dataclass(frozen=True)
class PlanStep:
    """The outcome of one MPC step for the whole swarm.

    ``states`` (M, N+1, n) and ``inputs`` (M, N, m) (the agent model's states and inputs: [p, v]
    and a for the double integrator) are each agent's own, dynamically feasible plan;
    ``fallback`` marks agents whose solve failed and whose plan is a safe fallback.
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
    copies: np.ndarray | None = None
    """(M,) how many neighbours' copies each agent held at the end of the step (ADMM; None for a
    centralised solve, where every pair is in one problem)."""
    planes: np.ndarray | None = None
    """(M,) how many separating planes each agent kept to at the end of the step (ADMM with
    ``plane_margin``; None for a centralised solve)."""
    critical_path: float | None = None
    """Seconds of compute on the step's critical path: what the step would take with one core per
    agent (ADMM: per batch of local steps the slowest agent's, plus the coordinator's own work;
    centralised: the whole solve). None: not measured, read as ``wall_time``."""
    deadline_stop: bool = False
    """ADMM stopped iterating because another iteration would have overrun ``solver.deadline``."""
    local_fallbacks: int = 0
    """Local solves of the step that the QP local step failed and IPOPT answered instead (ADMM
    with ``solver.local: qp``: the sum of the step's ``LocalResult.local_fallbacks``); 0 on the
    IPOPT local step and for a centralised solve."""


class MPCSolver(Protocol):
    """What the closed loop asks of a solver: one MPC step of the whole swarm.

    ``states`` (M, n) are the measured states, ``goals`` (M, n) this step's goals and ``guess``
    (M, N+1, n) the initial-guess trajectories. A solver that holds resources (an executor's
    workers) may also have a ``close()``, which whoever built the solver calls.
    """

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> PlanStep: ...


def braking_plan(state: np.ndarray, settings: OCPSettings) -> tuple[np.ndarray, np.ndarray]:
    """Come to rest as fast as the limits allow, then hold: (states (N+1, n), inputs (N, m)).

    The model's :meth:`~swarmpc.model.agent_model.AgentModel.braking_inputs`, the safest thing an
    agent can do when no plan can be trusted (a double integrator without acceleration limits
    stops within one step).
    """
    model = settings.model
    inputs = model.braking_inputs(np.asarray(state, float), settings.horizon, settings.accel)
    return model.rollout(state, inputs), inputs


# How far (inf-norm over the state: m and m/s for the double integrator) the measured state may
# sit from where the previous plan expected it for that plan to still be reused (as a warm start
# or a fallback). Zero would never reuse a plan under measurement or process noise; 0.05 is a
# sixth of the default delta.
SHIFT_TOLERANCE = 0.05


def fallback_plan(
    state: np.ndarray, previous_states: np.ndarray | None, previous_inputs: np.ndarray | None,
    settings: OCPSettings, tolerance: float = SHIFT_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """A safe plan for an agent whose solve failed.

    When the previous plan's next state is within ``tolerance`` of ``state``: the previous plan
    shifted by one step (its remaining inputs replayed from ``state``, so the result obeys the
    dynamics exactly even under noise, then one braking input). Otherwise, or without a previous
    plan, :func:`braking_plan`. Either way the first input respects the acceleration limit.
    """
    state = np.asarray(state, float)
    if previous_states is not None and previous_inputs is not None:
        gap = np.max(np.abs(previous_states[1] - state))
        # a plan that already starts at ``state`` (this step's own) is not a previous plan
        if gap <= tolerance and gap <= np.max(np.abs(previous_states[0] - state)):
            model = settings.model
            replayed = model.rollout(state, previous_inputs[1:])
            tail = model.braking_inputs(replayed[-1], 1, settings.accel)[0]
            inputs = np.vstack([previous_inputs[1:], tail[None]])
            return np.vstack([replayed, model.step(replayed[-1], tail)[None]]), inputs
    return braking_plan(state, settings)
