"""Centralised MPC of a planar swarm of cars and point agents with footprints: one NLP over all
agents (:func:`swarmpc.formulation.footprint_ocp.build_footprint_centralized`), built once per
swarm and solved at every step.

Initial point of a solve, in this order of preference:

* a guess the caller gives (states per agent): trajectories from it, certificates from its poses;
* the previous solution shifted one step forward (every primal block and the multipliers), while
  the previous solve succeeded;
* the straight line to the goal (:func:`straight_guess`), its certificates in closed form.

The certificates of a guess are the best ones of its poses (footprint rows:
:func:`~swarmpc.formulation.footprint_ocp.footprint_guess_blocks`; the point form's rows: the
seeds of :mod:`swarmpc.solvers.dual_seed`), so the primal point is consistent in every block.
When IPOPT fails, every agent brakes (its model's
:meth:`~swarmpc.model.agent_model.AgentModel.braking_inputs`: a car in a straight line along its
heading, a point agent along its velocity) and the stats report the failure.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from swarmpc.formulation.footprint_ocp import (
    FootprintAgent,
    FootprintSwarm,
    build_footprint_centralized,
    footprint_guess_blocks,
)
from swarmpc.formulation.nlp import NLPSolution, shift_blocks
from swarmpc.formulation.ocp import pair_tag
from swarmpc.solvers.base import PlanStep, braking_plan
from swarmpc.solvers.guesses import agent_guess_blocks, nominal_speed, pair_guess_blocks

__all__ = [
    "AgentPlan",
    "FootprintCentralSolver",
    "FootprintMPCSolver",
    "FootprintPlan",
    "FootprintPlanStats",
    "straight_guess",
]


class AgentPlan(NamedTuple):
    """One agent's plan: states (N+1, n) and inputs (N, m) of its own model."""

    states: np.ndarray
    inputs: np.ndarray


@dataclass(frozen=True)
class FootprintPlanStats:
    """How one solve went.

    ``success``: IPOPT converged and the plans are its solution; otherwise every plan is a
    braking plan (``fallback``). ``warm``: the solve started from the shifted previous solution.
    ``cost`` is the NLP's objective at IPOPT's last iterate (meaningless after a failure);
    ``max_slack`` the largest soft-form slack of a successful solve (0 in the hard form).
    """

    success: bool
    status: str
    iterations: int
    cost: float
    max_slack: float
    solve_time: float
    wall_time: float
    warm: bool

    @property
    def fallback(self) -> bool:
        """True when the plans are braking plans (the solve failed)."""
        return not self.success


class FootprintPlan(NamedTuple):
    """The outcome of one MPC step: ``inputs`` (the first input (m_i,) of each agent, the one to
    apply), ``plans`` (each agent's full plan) and ``stats``."""

    inputs: tuple[np.ndarray, ...]
    plans: tuple[AgentPlan, ...]
    stats: FootprintPlanStats


def straight_guess(agent: FootprintAgent, state: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """A state guess (N+1, n) along the straight line from the agent's position to its goal's.

    The position travels at the nominal speed (:func:`~swarmpc.solvers.guesses.nominal_speed`)
    until it reaches the goal, then rests there; row 0 is the measured state. A point agent's
    states are its model's :meth:`~swarmpc.model.agent_model.AgentModel.state_at` the guessed
    positions and velocities. A car heads along the path (the direction's angle taken within pi
    of its current heading, so the heading does not spin by whole turns) at the speed it
    travels, or keeps its heading when it already stands at the goal.
    """
    s = agent.settings
    model, N = s.model, s.horizon
    state, goal = np.asarray(state, float), np.asarray(goal, float)
    start, end = model.position(state), model.position(goal)
    distance = float(np.linalg.norm(end - start))
    direction = (end - start) / distance if distance > 0 else np.zeros(2)
    travelled = np.minimum(distance, nominal_speed(s) * s.dt * np.arange(N + 1))
    positions = start + travelled[:, None] * direction
    velocities = np.vstack([np.diff(positions, axis=0) / s.dt, np.zeros((1, 2))])
    if agent.oriented:
        theta = float(state[2])
        if distance > 0:
            angle = float(np.arctan2(direction[1], direction[0]))
            theta = angle + 2 * np.pi * round((theta - angle) / (2 * np.pi))
        speeds = np.linalg.norm(velocities, axis=1)
        guess = np.column_stack([positions, np.full(N + 1, theta), speeds])
    else:
        guess = model.state_at(positions, velocities)
    guess[0] = state
    return guess


class FootprintCentralSolver:
    """Solves the footprint OCP of one swarm with IPOPT at every MPC step.

    The NLP is built once (its shape is fixed by the swarm: models, horizon, obstacles); every
    call only changes the measured states, the goals and the initial point.

    Parameters
    ----------
    swarm
        The agents, their settings and footprints.
    options
        CasADi/IPOPT options on top of agent 0's ``ipopt`` section.
    """

    def __init__(self, swarm: FootprintSwarm, options: dict[str, Any] | None = None) -> None:
        self.swarm = swarm
        self.nlp = build_footprint_centralized(swarm, options)
        self._previous: NLPSolution | None = None

    def reset(self) -> None:
        """Forget the previous solution: the next solve starts from a guess."""
        self._previous = None

    @property
    def warm(self) -> bool:
        """True when the next solve without a guess starts from the shifted previous solution."""
        return self._previous is not None

    def initial_point(self, guesses: Sequence[np.ndarray]) -> dict[str, np.ndarray]:
        """The primal point of state guesses (one (N+1, n_i) per agent): trajectories, inputs,
        and every certificate and soft slack from the guessed poses."""
        swarm = self.swarm
        point: dict[str, np.ndarray] = {}
        for i, agent in enumerate(swarm.agents):
            point.update(agent_guess_blocks(str(i), np.asarray(guesses[i], float), agent.obstacle_settings,
                                            seed_duals=not agent.oriented))
        for (i, j), delta in zip(swarm.point_pairs, swarm.point_deltas.T, strict=True):
            first = swarm.pair_first_step(i, j)
            model_i, model_j = swarm.agents[i].settings.model, swarm.agents[j].settings.model
            offsets = model_i.position(guesses[i][first:]) - model_j.position(guesses[j][first:])
            point.update(pair_guess_blocks(pair_tag(i, j), offsets, delta, swarm.settings))
        point.update(footprint_guess_blocks(swarm, guesses))
        return point

    def _start(
        self, states: Sequence[np.ndarray], goals: Sequence[np.ndarray], guess: Sequence[np.ndarray] | None
    ) -> tuple[dict[str, np.ndarray] | np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(primal point, lam_x, lam_g) of a solve: the given guess, else the shifted previous
        solution, else the straight line."""
        if guess is None and self._previous is not None:
            layout_x, layout_g = self.nlp.x_layout, self.nlp.g_layout
            previous = self._previous
            return (layout_x.pack(shift_blocks(previous.x)),
                    layout_x.pack(shift_blocks(layout_x.unpack(previous.lam_x))),
                    layout_g.pack(shift_blocks(layout_g.unpack(previous.lam_g))))
        if guess is None:
            guess = [straight_guess(agent, states[i], goals[i]) for i, agent in enumerate(self.swarm.agents)]
        return self.initial_point(guess), None, None

    def plan(
        self, states: Sequence[np.ndarray], goals: Sequence[np.ndarray], guess: Sequence[np.ndarray] | None = None
    ) -> FootprintPlan:
        """One MPC step from the measured ``states`` (one (n_i,) per agent) towards ``goals`` (goal
        states (n_i,)); ``guess``: state guesses (N+1, n_i) per agent (None: the shifted previous
        solution, or the straight line)."""
        started = time.perf_counter()
        swarm = self.swarm
        params: dict[str, np.ndarray] = {"delta": swarm.point_deltas}
        for i in range(swarm.num_agents):
            params[f"x0{i}"] = np.asarray(states[i], float)
            params[f"goal{i}"] = np.asarray(goals[i], float)
        warm = guess is None and self._previous is not None
        point, lam_x, lam_g = self._start(states, goals, guess)
        solution = self.nlp.solve(params, point, lam_x, lam_g)
        if solution.success:
            self._previous = solution
            plans = tuple(AgentPlan(solution.x[f"X{i}"].T, solution.x[f"U{i}"].T) for i in range(swarm.num_agents))
        else:
            self._previous = None
            plans = tuple(AgentPlan(*braking_plan(np.asarray(states[i], float), agent.settings))
                          for i, agent in enumerate(swarm.agents))
        slacks = [float(value.max()) for name, value in solution.x.items() if name.startswith("A") and value.size]
        stats = FootprintPlanStats(
            success=solution.success,
            status=solution.status,
            iterations=solution.iterations,
            cost=solution.cost,
            max_slack=max(0.0, *slacks) if slacks and solution.success else 0.0,
            solve_time=solution.solve_time,
            wall_time=time.perf_counter() - started,
            warm=warm,
        )
        return FootprintPlan(tuple(plan.inputs[0].copy() for plan in plans), plans, stats)


def nearest_heading(goal: np.ndarray, state: np.ndarray) -> np.ndarray:
    """A car's goal state (4,) with its heading moved by whole turns to within pi of the state's,
    so that the cost on the heading error turns the car the short way round."""
    goal = np.array(goal, float)
    goal[2] += 2 * np.pi * np.round((float(state[2]) - goal[2]) / (2 * np.pi))
    return goal


class FootprintMPCSolver:
    """:class:`FootprintCentralSolver` behind the closed loop's
    :class:`~swarmpc.solvers.base.MPCSolver` protocol: stacked (M, ...) arrays in and a
    :class:`~swarmpc.solvers.base.PlanStep` out.

    Every agent's state and input have its own model's layout; the closed loop stacks them, so
    the models must agree on the sizes (in the plane a car and a point agent both have 4 state
    and 2 input entries). A car's goal heading is taken within pi of its current heading
    (:func:`nearest_heading`). The solve starts from the solver's own shifted previous solution
    (primal and multipliers) while it has one, and from the caller's guess otherwise.
    """

    def __init__(self, solver: FootprintCentralSolver) -> None:
        self.solver = solver
        shapes = {(a.settings.model.state_dim, a.settings.model.input_dim) for a in solver.swarm.agents}
        if len(shapes) != 1:
            raise ValueError(f"the agents' models differ in state or input size {sorted(shapes)}: "
                             "they cannot be stacked")

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray | None) -> PlanStep:
        """One MPC step of the swarm from measured ``states`` (M, n) to ``goals`` (M, n)."""
        agents = self.solver.swarm.agents
        targets = [nearest_heading(goals[i], states[i]) if agent.oriented else np.asarray(goals[i], float)
                   for i, agent in enumerate(agents)]
        start = None if self.solver.warm or guess is None else [np.asarray(g, float) for g in guess]
        outcome = self.solver.plan(list(states), targets, start)
        stats, m = outcome.stats, len(agents)
        return PlanStep(
            states=np.array([plan.states for plan in outcome.plans]),
            inputs=np.array([plan.inputs for plan in outcome.plans]),
            predicted_cost=stats.cost,
            max_slack=stats.max_slack,
            wall_time=stats.wall_time,
            agent_times=np.full(m, stats.solve_time / m),
            failures=0 if stats.success else 1,
            fallback=np.full(m, stats.fallback),
            critical_path=stats.wall_time,  # one process solves the whole step
        )
