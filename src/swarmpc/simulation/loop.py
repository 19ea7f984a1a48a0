"""The receding-horizon closed loop: guess, solve, apply the first inputs, record, repeat."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from swarmpc.config import Scenario
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.simulation.deadlock import DeadlockResolver
from swarmpc.simulation.disturbance import DisturbanceModel, planner_delta
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.simulation.results import RunResult, StepRecord
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, default_coupling
from swarmpc.solvers.base import PlanStep
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.executors import Executor

ProgressCallback = Callable[[int, int, np.ndarray], None]


class MPCSolver(Protocol):
    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> PlanStep: ...


def make_solver(scn: Scenario, settings: OCPSettings, executor: Executor | None = None) -> MPCSolver:
    """The scenario's solver (``solver.method``), built once for the run.

    The solver keeps agents apart by the planner's delta (the true one plus any tightening).
    """
    delta = planner_delta(scn)
    if scn.solver.method == "centralized":
        return CentralizedSolver(settings, scn.num_agents, delta, scn.solver.seed_duals)
    margin, closing_time = default_coupling(scn.collision)
    if scn.solver.coupling_margin is not None:  # the scenario's margin, as given
        margin, closing_time = scn.solver.coupling_margin, 0.0
    config = ADMMConfig(
        rho=scn.solver.rho, max_iter=scn.solver.max_iter, tol=scn.solver.tol,
        adaptive_rho=scn.solver.adaptive_rho, seed_duals=scn.solver.seed_duals,
        coupling_margin=margin, closing_time=closing_time, reuse_tol=scn.solver.reuse_tol,
        relaxation=scn.solver.relaxation, component_stop=scn.solver.component_stop,
        plane_margin=scn.solver.plane_margin,
    )
    return ADMMSolver(settings, scn.num_agents, delta, config, executor)


def goal_reached(states: np.ndarray, goals: np.ndarray, scn: Scenario) -> np.ndarray:
    """Per agent: within the goal tolerance in position and nearly at rest."""
    d = scn.dim
    near = np.linalg.norm(states[:, :d] - goals[:, :d], axis=1) <= scn.stop.goal_tolerance
    slow = np.linalg.norm(states[:, d:] - goals[:, d:], axis=1) <= scn.stop.speed_tolerance
    return near & slow


@dataclass
class StopFlag:
    """Set ``requested`` (e.g. from a signal handler) to end the loop after the current step."""

    requested: bool = False


def simulate(
    scn: Scenario,
    solver: MPCSolver | None = None,
    progress: ProgressCallback | None = None,
    stop_flag: StopFlag | None = None,
    executor: Executor | None = None,
) -> RunResult:
    """Run the scenario in closed loop until every agent is at its goal or ``max_steps``.

    With a ``disturbance`` block the planner sees the measured state (true + measurement noise)
    and the true state receives process noise after each step; the stop test and every metric use
    the true state.
    """
    scn = scn.revalidated()  # the lists of a frozen scenario can still be changed in place
    started = time.perf_counter()
    settings = OCPSettings.from_scenario(scn)
    solver = solver or make_solver(scn, settings, executor)
    model = DoubleIntegrator(scn.dim, scn.dt, scn.discretization)
    guesser = GuessProvider(scn, settings)
    deadlocks = DeadlockResolver(
        scn.num_agents, scn.dim, seed=scn.seed, clearance=planner_delta(scn) + scn.d_min, bounds=scn.bounds()
    )
    noise = DisturbanceModel.from_scenario(scn)
    disturbances: list[np.ndarray] = []
    goals = scn.goal_states()
    states = scn.start_states()
    trajectory = [states]
    inputs: list[np.ndarray] = []
    records: list[StepRecord] = []
    previous: PlanStep | None = None
    interrupted = False
    for step in range(scn.stop.max_steps):
        if goal_reached(states, goals, scn).all():
            break
        if stop_flag is not None and stop_flag.requested:
            interrupted = True
            break
        measured = states + noise.measurement()
        step_goals = guesser.goals(measured, deadlocks.goals(step, measured, goals))
        guess = guesser.guesses(measured, step_goals, previous)
        plan = solver.plan(measured, step_goals, guess)
        control = plan.inputs[:, 0]
        disturbance = noise.process()
        states = model.step(states, control) + disturbance
        disturbances.append(disturbance)
        trajectory.append(states)
        inputs.append(control)
        records.append(StepRecord.from_plan(plan))
        previous = plan
        if progress is not None:
            progress(step + 1, scn.stop.max_steps, states)
    close = getattr(solver, "close", None)
    if callable(close):
        close()
    result_states = np.array(trajectory)
    result_inputs = np.array(inputs).reshape(len(inputs), scn.num_agents, scn.dim)
    return RunResult.create(
        scenario=scn,
        states=result_states,
        inputs=result_inputs,
        records=records,
        deadlock_events=deadlocks.events,
        interrupted=interrupted,
        wall_time=time.perf_counter() - started,
        rrt_stats=guesser.rrt_stats,
        disturbances=np.array(disturbances).reshape(len(inputs), scn.num_agents, scn.state_dim)
        if scn.disturbance.has_process_noise
        else None,
    )
