"""The swarm's model predictive controller, one call per control period.

:class:`Controller` is what runs on (or next to) the robots: give it the states the sensors
measured, it returns every agent's acceleration for the next period. Between calls it keeps what
receding-horizon control carries over: the previous plan (the warm start and the fallback of a
failed solve), the initial-guess provider (with its stored RRT paths), the deadlock resolver
(stall counters, detours in progress) and the solver with its executor (built once). The closed
loop of :func:`swarmpc.simulation.loop.simulate` is this controller plus a plant.

The solver comes from the registry of :mod:`swarmpc.solvers.registry` (the scenario's
``solver.method``) and is used only through the :class:`~swarmpc.solvers.base.MPCSolver`
protocol; the executor of its local solves is the scenario's ``executor`` section unless the
caller hands one in. What the controller creates, it closes.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from swarmpc.config import ExecutorConfig, Scenario, load_scenario
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.simulation.deadlock import DeadlockPolicy, DeadlockResolver
from swarmpc.simulation.disturbance import planner_bodies, planner_delta
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.simulation.results import StepRecord
from swarmpc.solvers.base import MPCSolver, PlanStep
from swarmpc.solvers.executors import Executor, make_executor
from swarmpc.solvers.registry import SOLVERS, SolverRegistry, agent_settings

__all__ = ["Controller", "DeadlockFactory", "GuessFactory", "MPCSolver", "close_solver", "deadlock_resolver",
           "make_solver", "section_executor"]

GuessFactory = Callable[[Scenario, OCPSettings], GuessProvider]
"""``factory(scenario, settings)`` -> the initial-guess provider of a controller (default:
:class:`~swarmpc.simulation.guessing.GuessProvider`; a subclass changes how guesses are made)."""

DeadlockFactory = Callable[..., DeadlockResolver]
"""Called as :class:`~swarmpc.simulation.deadlock.DeadlockResolver` is by
:func:`deadlock_resolver` (default: that class; a subclass changes the rules' implementation)."""


def make_solver(
    scn: Scenario, settings: OCPSettings, executor: Executor | None = None, registry: SolverRegistry = SOLVERS,
) -> MPCSolver:
    """The scenario's solver (``solver.method`` in ``registry``), built once for the run.

    The solver keeps each pair apart by the sum of the planner's bodies (the true ones grown by
    any tightening), and each agent's body out of the obstacles. A solver given ``executor``
    leaves it open when closed (its creator closes it); without one an ADMM solver makes and
    closes its own serial one. A scenario with cars hands the registry each agent's own settings
    (:func:`~swarmpc.solvers.registry.agent_settings`): the method's footprint builder makes its
    solver, and a method without one refuses the swarm.
    """
    agents = agent_settings(scn) if scn.has_cars else None
    return registry.build(scn.solver.method, scn.solver, settings, planner_bodies(scn), executor, agents=agents)


def section_executor(section: ExecutorConfig) -> Executor | None:
    """A new executor as an ``executor`` section describes it; None for ``serial`` (the solver's
    own). The caller owns it and closes it. ValueError (one line) when it cannot be made (Ray
    not installed)."""
    if section.type == "serial":
        return None
    if section.type == "ray":
        return make_executor("ray", address=section.address, actors=section.workers)
    return make_executor(section.type, workers=section.workers)


def deadlock_resolver(scn: Scenario, factory: DeadlockFactory = DeadlockResolver) -> DeadlockResolver:
    """The scenario's deadlock resolver: the rules of its ``deadlock`` section, agents kept the
    planner's clearance apart, detours kept inside the workspace, jitter seeded by the scenario.

    In a swarm with cars each agent is read through its own model (a car's detours are poses it
    drives to forwards, :func:`~swarmpc.simulation.deadlock.rest_state`) and the clearance covers
    the longest footprint."""
    policy = DeadlockPolicy.from_config(scn.deadlock)
    if not scn.has_cars:
        return factory(scn.num_agents, scn.dim, policy=policy, seed=scn.seed,
                       clearance=planner_delta(scn) + scn.d_min, bounds=scn.bounds())
    models = tuple(scn.agent_models())
    longest = max(max(getattr(m, "footprint", (0.0,))) for m in models)
    return factory(scn.num_agents, scn.dim, policy=policy, seed=scn.seed,
                   clearance=np.maximum(planner_delta(scn), longest) + scn.d_min, bounds=scn.bounds(), models=models)


def close_solver(solver: Any) -> None:
    """Close ``solver`` if it can be closed (an ADMM solver closes the executor it made for
    itself, never one it was given)."""
    close = getattr(solver, "close", None)
    if callable(close):
        close()


def _array(value: Any, name: str) -> np.ndarray:
    """``value`` as a new finite float array; ValueError (one line) otherwise."""
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected an array of numbers") from None
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: must be finite (found NaN or inf)")
    return array


class Controller:
    """Distributed MPC of a scenario's swarm, stepped by the caller (do-mpc's ``make_step``).

    Parameters
    ----------
    scenario
        The swarm, its limits, costs, obstacles, default goals and solver settings.
    executor
        Where ADMM's local solves run: None (the scenario's ``executor`` section, serial by
        default), an executor's name (``"serial"``, ``"thread"``, ``"process"``, ``"ray"``) or an
        executor object. One made from the section or a name is the controller's, released by
        :meth:`close`; an object given stays the caller's, who closes it.
    solver
        A solver built elsewhere (owned by the caller; ``executor`` is then not used).
    deadlocks
        A deadlock resolver built elsewhere (default: :func:`deadlock_resolver` with
        ``deadlock_factory``).
    guess_provider
        Makes the initial-guess provider from the scenario and the settings (default:
        :class:`~swarmpc.simulation.guessing.GuessProvider`).
    deadlock_factory
        The resolver class (or factory) :func:`deadlock_resolver` builds when ``deadlocks`` is None.
    solvers
        Where the scenario's ``solver.method`` is looked up (default:
        :data:`swarmpc.solvers.registry.SOLVERS`).

    After each :meth:`step`, :attr:`plan` holds the predicted plans and :attr:`last_record` the
    solver's record of the step. Use it in a ``with`` block, or call :meth:`close`.
    """

    def __init__(
        self,
        scenario: Scenario,
        executor: Executor | str | None = None,
        *,
        solver: MPCSolver | None = None,
        deadlocks: DeadlockResolver | None = None,
        guess_provider: GuessFactory = GuessProvider,
        deadlock_factory: DeadlockFactory = DeadlockResolver,
        solvers: SolverRegistry = SOLVERS,
    ) -> None:
        scn = scenario.revalidated()  # the lists of a frozen scenario can still be changed in place
        self.scenario = scn
        self.settings = OCPSettings.from_scenario(scn)
        self._owns_solver = solver is None
        self._made_executor: Executor | None = None
        """The executor made here, from the scenario's section or a name (closed by :meth:`close`)."""
        if solver is None:
            made = self._executor(executor)
            self._made_executor = made if executor is None or isinstance(executor, str) else None
            try:
                solver = make_solver(scn, self.settings, made, solvers)
            except BaseException:
                if self._made_executor is not None:
                    self._made_executor.close()
                raise
        self.solver = solver
        self.guesser = guess_provider(scn, self.settings)
        self.deadlocks = deadlocks or deadlock_resolver(scn, deadlock_factory)
        self.goals = scn.goal_states()
        """(M, 2d) the goals a :meth:`step` without ``goals`` steers to (the scenario's)."""
        self.steps = 0
        self._plan: PlanStep | None = None
        self._record: StepRecord | None = None
        self._closed = False

    def _executor(self, executor: Executor | str | None) -> Executor | None:
        """The executor object for ``executor``: created here from the scenario's ``executor``
        section (None) or a name."""
        if executor is None:
            return section_executor(self.scenario.executor)
        if not isinstance(executor, str):
            return executor
        if self.scenario.solver.method != "admm" and executor != "serial":
            raise ValueError(f"executor: {executor} only applies to solver.method admm")
        return make_executor(executor)

    @classmethod
    def from_file(cls, path: str | Path, executor: Executor | str | None = None) -> Controller:
        """A controller for the scenario file at ``path`` (validated; ScenarioError otherwise)."""
        return cls(load_scenario(path), executor)

    # ----------------------------------------------------------------- what the last step left
    @property
    def plan(self) -> PlanStep | None:
        """The last step's plans: ``states`` (M, N+1, 2d), ``inputs`` (M, N, d); None before a step."""
        return self._plan

    @property
    def last_record(self) -> StepRecord | None:
        """The last step's solver record (times, iterations, residuals, fallbacks); None before a step."""
        return self._record

    @property
    def deadlock_events(self) -> list[tuple[int, int]]:
        """(step, agent) of every detour the deadlock resolver started."""
        return self.deadlocks.events

    @property
    def rrt_stats(self) -> dict[str, int] | None:
        return self.guesser.rrt_stats

    # ----------------------------------------------------------------- control
    def step(self, measured_states: Any, goals: Any = None) -> np.ndarray:
        """Every agent's input (M, d) for the next period, from the measured states (M, 2d).

        ``goals`` replaces the default goals for this step: (M, 2d) states or (M, d) positions
        (at rest). The controller guesses, lets the deadlock resolver swap in detours, solves, and
        keeps the plan as the next step's warm start.
        """
        if self._closed:
            raise RuntimeError("controller: closed; build a new one")
        measured = self._measured(measured_states)
        targets = self.goals if goals is None else self._goals(goals)
        step_goals = self.guesser.goals(measured, self.deadlocks.goals(self.steps, measured, targets))
        guess = self.guesser.guesses(measured, step_goals, self._plan)
        plan = self.solver.plan(measured, step_goals, guess)
        self._plan, self._record = plan, StepRecord.from_plan(plan)
        self.steps += 1
        return plan.inputs[:, 0].copy()

    make_step = step

    def _measured(self, value: Any) -> np.ndarray:
        m, n = self.scenario.num_agents, self.scenario.state_dim
        array = _array(value, "measured_states")
        if array.shape != (m, n):
            raise ValueError(
                f"measured_states: expected shape ({m}, {n}) (agents, [position, velocity]), got {array.shape}"
            )
        return array

    def _goals(self, value: Any) -> np.ndarray:
        m, d = self.scenario.num_agents, self.scenario.dim
        array = _array(value, "goals")
        if array.shape == (m, d):
            return np.hstack([array, np.zeros((m, d))])
        if array.shape != (m, 2 * d):
            raise ValueError(f"goals: expected shape ({m}, {2 * d}) or ({m}, {d}) positions, got {array.shape}")
        return array

    # ----------------------------------------------------------------- lifetime
    def close(self) -> None:
        """Release what the controller created (its solver, an executor made from a name); idempotent."""
        if not self._closed:
            if self._owns_solver:
                close_solver(self.solver)
            if self._made_executor is not None:
                self._made_executor.close()
        self._closed = True

    def __enter__(self) -> Controller:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()
