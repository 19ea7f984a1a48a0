"""The receding-horizon closed loop: a controller, a plant, and the record of what happened.

Each step the loop asks the plant what its sensors measure, lets the
:class:`~swarmpc.simulation.controller.Controller` turn that into inputs (guess, deadlock goals,
solve, first input), applies them to the plant and records the true states, the inputs, the
solver's record and how far the plant strayed from the nominal model. The loop itself only
decides when to stop (every agent at its goal, ``max_steps``, or a stop request).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from swarmpc.config import Scenario
from swarmpc.simulation.controller import Controller, DeadlockFactory, GuessFactory, make_solver
from swarmpc.simulation.deadlock import DeadlockResolver
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.simulation.metrics import heading_error
from swarmpc.simulation.plant import Plant, make_plant
from swarmpc.simulation.results import RunResult, StepRecord
from swarmpc.solvers.base import MPCSolver
from swarmpc.solvers.executors import Executor

__all__ = ["MPCSolver", "ProgressCallback", "StopFlag", "goal_reached", "heading_error", "make_solver", "simulate"]

ProgressCallback = Callable[[int, int, np.ndarray], None]


def goal_reached(states: np.ndarray, goals: np.ndarray, scn: Scenario) -> np.ndarray:
    """Per agent: within the goal tolerance in position and nearly at rest (the scenario's agent
    model reads both from the states); a car also within ``stop.heading_tolerance_deg`` of its
    goal heading, modulo a full turn (:func:`heading_error`)."""
    if not scn.has_cars:
        model = scn.agent_model()
        near = np.linalg.norm(model.position(states) - model.position(goals), axis=1) <= scn.stop.goal_tolerance
        slow = np.linalg.norm(model.velocity(states) - model.velocity(goals), axis=1) <= scn.stop.speed_tolerance
        return near & slow
    reached = np.empty(scn.num_agents, bool)
    for i, (model, agent) in enumerate(zip(scn.agent_models(), scn.agents, strict=True)):
        near = np.linalg.norm(model.position(states[i]) - model.position(goals[i])) <= scn.stop.goal_tolerance
        slow = np.linalg.norm(model.velocity(states[i]) - model.velocity(goals[i])) <= scn.stop.speed_tolerance
        aligned = not agent.model.is_car or bool(
            np.degrees(heading_error(states[i, 2], goals[i, 2])) <= scn.stop.heading_tolerance_deg)
        reached[i] = near and slow and aligned
    return reached


@dataclass
class StopFlag:
    """Set ``requested`` (e.g. from a signal handler) to end the loop after the current step."""

    requested: bool = False


@dataclass
class _Recording:
    """What a run keeps of each step: true states, inputs, solver records, plant mismatch."""

    states: list[np.ndarray]
    inputs: list[np.ndarray] = field(default_factory=list)
    records: list[StepRecord] = field(default_factory=list)
    disturbances: list[np.ndarray] = field(default_factory=list)

    def add(self, states: np.ndarray, inputs: np.ndarray, record: StepRecord, disturbance: np.ndarray) -> None:
        self.states.append(states)
        self.inputs.append(inputs)
        self.records.append(record)
        self.disturbances.append(disturbance)

    def arrays(self, scn: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(states (T+1, M, n), inputs (T, M, m), disturbances (T, M, n)) of the agent model."""
        steps = len(self.inputs)
        return (
            np.array(self.states),
            np.array(self.inputs).reshape(steps, scn.num_agents, scn.agent_model().input_dim),
            np.array(self.disturbances).reshape(steps, scn.num_agents, scn.state_dim),
        )


def simulate(
    scn: Scenario,
    solver: MPCSolver | None = None,
    progress: ProgressCallback | None = None,
    stop_flag: StopFlag | None = None,
    executor: Executor | None = None,
    plant: Plant | None = None,
    *,
    guess_provider: GuessFactory = GuessProvider,
    deadlock_factory: DeadlockFactory = DeadlockResolver,
) -> RunResult:
    """Run the scenario in closed loop until every agent is at its goal or ``max_steps``.

    The plant is the scenario's (``plant.type``) unless one is given. With a ``disturbance`` block
    the controller sees the measured state (true + measurement noise) and the true state receives
    process noise after each step; the stop test and every metric use the true state. A solver or
    executor handed in stays open: whoever created it closes it. Without either, the
    :class:`~swarmpc.simulation.controller.Controller` builds the scenario's solver and the
    executor of its ``executor`` section, and closes them when the run ends.
    ``guess_provider`` and ``deadlock_factory`` make the controller's initial-guess provider and
    deadlock resolver (see :class:`~swarmpc.simulation.controller.Controller`).
    """
    scn = scn.revalidated()  # the lists of a frozen scenario can still be changed in place
    started = time.perf_counter()
    plant = plant if plant is not None else make_plant(scn)
    goals = scn.goal_states()
    with Controller(scn, executor, solver=solver, guess_provider=guess_provider,
                    deadlock_factory=deadlock_factory) as controller:
        recording = _Recording(states=[plant.reset()])
        interrupted = False
        for step in range(scn.stop.max_steps):
            if goal_reached(recording.states[-1], goals, scn).all():
                break
            if stop_flag is not None and stop_flag.requested:
                interrupted = True
                break
            control = controller.step(plant.measure())
            states = plant.step(control)
            recording.add(states, control, controller.last_record, plant.last_disturbance)  # type: ignore[arg-type]
            if progress is not None:
                progress(step + 1, scn.stop.max_steps, states)
    states, inputs, disturbances = recording.arrays(scn)
    result = RunResult.create(
        scenario=scn,
        states=states,
        inputs=inputs,
        records=recording.records,
        deadlock_events=controller.deadlock_events,
        interrupted=interrupted,
        wall_time=time.perf_counter() - started,
        rrt_stats=controller.rrt_stats,
        disturbances=None if plant.nominal else disturbances,
    )
    return replace(result, summary={**result.summary, "plant": plant.describe()})
