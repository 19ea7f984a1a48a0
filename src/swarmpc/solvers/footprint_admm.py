"""Consensus ADMM for a swarm with cars: every agent plans its own trajectory against copies of its
neighbours' footprint poses (:mod:`swarmpc.formulation.footprint_local`), and the agents agree on
those poses.

One MPC step (:meth:`FootprintADMMSolver.plan`):

1. **Coupling.** Agents i and j are neighbours when the exact distance between their footprints
   now is at most the sum of what either can move within the horizon
   (:meth:`~swarmpc.model.agent_model.AgentModel.reach_bound`, a point agent's inf-norm bound
   times sqrt 2) plus d_min and ``coupling_margin``. Two agents that are not cannot touch within
   the horizon, whatever they plan, so they need no copies of each other.
2. **ADMM** (scaled form). Each agent's consensus block is its footprint pose at steps 1..N
   (:func:`~swarmpc.formulation.footprint_local.consensus_block`); its holders are the agent
   itself and every neighbour (its copy); with ``pair_copies`` "later" only the neighbours later in
   index order hold a copy, so of each pair only the later agent keeps the pair's OBCA rows, and
   the earlier one yields only through the consensus of its block. Per iteration every agent solves its local problem
   with IPOPT (warm-started from its previous iterate), the consensus of a block is the mean of
   its holders' ``v + Y / rho_b`` weighted by their penalties rho_b (``rho * owner_weight`` for the
   agent's own block, ``rho`` for a copy), and each holder's Y moves by ``rho_b (v - z)``. It stops when the
   largest primal residual ``|v - z|`` and dual residual ``rho |z - z_previous|`` are both
   below ``tol``, or after ``max_iter`` iterations.
3. **Safety.** In the hard form the agents' own plans are checked pairwise by the exact distance
   between their footprints (:func:`~swarmpc.model.footprint.rectangle_distance`) at every
   constrained step. The agents of a pair closer than d_min are repaired one after the other in
   index order: each solves its local problem again with copies of every neighbour (whatever
   ``pair_copies``) pinned to their current plans, so its answer keeps d_min from all of them by
   the OBCA rows; every pair with a repaired agent is then certified by the later of its two
   repairs. An agent whose repair fails brakes (:func:`~swarmpc.solvers.base.braking_plan`: a car
   cannot side-step), which is counted as a fallback, and the agents whose plans that braking plan
   violates are repaired against it in a further pass (:data:`REPAIR_PASSES` passes at most).

A local solve that fails warm (from the agent's previous answer) is tried once more cold: from
the agent's last plan with every certificate seeded afresh from the geometry.

The local solves of an iteration are independent: each agent is a
:class:`~swarmpc.solvers.footprint_agent.FootprintLocalAgent` (its problems, its last answer, its
solves), hosted by any executor of :mod:`swarmpc.solvers.executors` (serial, thread, process, ray),
and the solver (the coordinator: coupling, consensus, multipliers, safety checks, the order of the
repairs) talks to it only by messages. An iteration's solves are one batch: every agent solves
before the consensus update, and the plans are the same, bit for bit, whatever the executor. The
step's critical path is reported as if each agent had its own core (per iteration the slowest
local solve, plus the coordinator's consensus update; every repair solve in full).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from swarmpc.config import SolverConfig
from swarmpc.formulation.footprint_local import consensus_block, slot_size
from swarmpc.formulation.footprint_ocp import FootprintAgent, FootprintSwarm
from swarmpc.model.footprint import rectangle_distance
from swarmpc.solvers.base import PlanStep, braking_plan
from swarmpc.solvers.executors import Executor, SerialExecutor
from swarmpc.solvers.footprint_agent import (
    FootprintAgentFactory,
    FootprintAnswer,
    FootprintResult,
    FootprintSolve,
    FootprintStart,
    footprint_local_guess,
)
from swarmpc.solvers.footprint_central import nearest_heading, straight_guess
from swarmpc.solvers.qp_local import QPLocalOptions

__all__ = ["FootprintADMMOptions", "FootprintADMMSolver", "coupled_pairs", "footprint_local_guess", "plan_violations"]

SAFETY_TOLERANCE = 1e-6
"""[m] a planned pair closer than d_min by more than this is repaired (IPOPT meets its rows to
within its own tolerance, far below)."""


STILL = 1e-3
"""[m] a plan whose positions all lie within this of its first stands still (:meth:`FootprintADMMSolver._restarts`)."""


REPAIR_PASSES = 3
"""Repair passes per step: the first repairs the violating pairs, the next ones the pairs that a
braking fallback of the pass before violates."""


@dataclass(frozen=True)
class FootprintADMMOptions:
    """The parameters of :class:`FootprintADMMSolver` (a scenario's ``solver`` section)."""

    rho: float = 10.0
    max_iter: int = 100
    tol: float = 1e-3
    coupling_margin: float = 0.5
    local: str = "ipopt"
    """The local step: ``ipopt`` (the NLP) or ``qp`` (:class:`~swarmpc.solvers.footprint_qp.FootprintLocalQP`,
    whose failed calls are handed to IPOPT)."""
    qp: QPLocalOptions = field(default_factory=QPLocalOptions)
    """The QP local step's tolerances (``solver.qp``)."""
    carry_multipliers: bool = True
    """Start a step's multipliers from the previous step's, shifted (as the plans are), for every
    block whose holders are those of the previous step (:meth:`FootprintADMMSolver._start_agents`)."""
    owner_weight: float = 1.0
    """Weight w of an agent's own block against each copy of it: its penalty is rho * w and the
    consensus is the penalty-weighted mean of the holders' values."""
    pair_copies: str = "both"
    """Which agents of a coupled pair hold a copy of the other (and the pair's OBCA rows): ``both``
    or ``later`` (the one later in index order; module docstring, step 2)."""

    @classmethod
    def from_options(cls, options: SolverConfig) -> FootprintADMMOptions:
        margin = options.coupling_margin
        return cls(options.rho, options.max_iter, options.tol, 0.5 if margin is None else margin,
                   owner_weight=options.admm.owner_weight, local=options.local,
                   qp=QPLocalOptions.from_config(options.qp), pair_copies=options.admm.pair_copies)


def _euclidean_reach(agent: FootprintAgent, state: np.ndarray) -> float:
    """A bound on how far any point of the agent's footprint moves within the horizon."""
    s = agent.settings
    reach = float(s.model.reach_bound(np.asarray(state, float), s.horizon, s.accel, s.speed))
    return reach if agent.oriented else reach * np.sqrt(2.0)


def coupled_pairs(swarm: FootprintSwarm, states: np.ndarray, margin: float) -> list[tuple[int, int]]:
    """The pairs (i, j), i < j, whose footprints may come within d_min + ``margin`` of each other
    within the horizon (module docstring, step 1)."""
    agents = swarm.agents
    poses = [agent.poses(np.asarray(states[i], float)) for i, agent in enumerate(agents)]
    reach = [_euclidean_reach(agent, states[i]) for i, agent in enumerate(agents)]
    out = []
    for i, j in swarm.pairs:
        gap = float(rectangle_distance(poses[i], agents[i].size, poses[j], agents[j].size))
        if gap <= reach[i] + reach[j] + swarm.settings.d_min + margin:
            out.append((i, j))
    return out


def plan_violations(swarm: FootprintSwarm, plans: Sequence[np.ndarray]) -> list[tuple[int, int]]:
    """The pairs whose planned footprints (states (N+1, n) per agent) come closer than d_min
    (less :data:`SAFETY_TOLERANCE`) at a constrained step, by the exact rectangle distance."""
    agents, d_min = swarm.agents, swarm.settings.d_min
    out = []
    for i, j in swarm.pairs:
        first = swarm.pair_first_step(i, j)
        gap = rectangle_distance(agents[i].poses(plans[i][first:]), agents[i].size,
                                 agents[j].poses(plans[j][first:]), agents[j].size)
        if float(np.min(gap)) < d_min - SAFETY_TOLERANCE:
            out.append((i, j))
    return out


@dataclass
class _AgentState:
    """The coordinator's side of one agent for a step: its neighbours, its last answer (the
    agent's own copy of it lives in the agent, :class:`~swarmpc.solvers.footprint_agent.FootprintLocalAgent`),
    its multipliers and what its solves cost."""

    neighbours: tuple[int, ...]
    answer: FootprintAnswer | None = None
    own_y: np.ndarray | None = None
    copy_y: dict[int, np.ndarray] = field(default_factory=dict)
    seconds: float = 0.0
    failures: int = 0
    handovers: int = 0
    """QP calls that failed and were handed to IPOPT (``local: qp``)."""

    def block(self) -> np.ndarray:
        assert self.answer is not None
        return self.answer.block

    def copy(self, j: int) -> np.ndarray:
        assert self.answer is not None
        return self.answer.copies[self.neighbours.index(j)]

    def count(self, result: FootprintResult) -> None:
        """Adds what a reply of the agent cost; keeps its answer when it is of the step's problem."""
        self.seconds += result.solve_time
        self.failures += result.failures
        self.handovers += result.handovers
        if result.own:
            self.answer = result.answer


@dataclass
class _Step:
    """What one MPC step's iterations share: the measured states, goals and the consensus."""

    states: list[np.ndarray]
    goals: list[np.ndarray]
    z: list[np.ndarray]
    rho: float
    critical: float = 0.0
    primal: list[float] = field(default_factory=list)
    dual: list[float] = field(default_factory=list)


class FootprintADMMSolver:
    """Consensus ADMM over the local problems of a swarm with cars (module docstring).

    Each agent's local solves run in a :class:`~swarmpc.solvers.footprint_agent.FootprintLocalAgent`
    hosted by ``executor``; an agent's solve starts from its previous answer (shifted by one step at
    a new MPC step) while its neighbours are the same, and from the guess otherwise.

    Parameters
    ----------
    swarm : FootprintSwarm
        The agents, each with its own settings and footprint.
    options : FootprintADMMOptions
        ADMM's parameters.
    executor : Executor or None
        Where the agents' local solves run. An executor given is the caller's: :meth:`close`
        leaves it open. None: the solver's own serial executor, which :meth:`close` closes.
    """

    def __init__(
        self, swarm: FootprintSwarm, options: FootprintADMMOptions = FootprintADMMOptions(),
        executor: Executor | None = None,
    ) -> None:
        self.swarm = swarm
        self.options = options
        self._owns_executor = executor is None
        self.executor: Executor = SerialExecutor() if executor is None else executor
        self.executor.start(FootprintAgentFactory(swarm, options.local, options.qp, options.owner_weight),
                            range(swarm.num_agents))
        self._agents: list[_AgentState | None] = [None] * swarm.num_agents
        self._z: list[np.ndarray] | None = None
        """The last step's consensus, to start the next step's from (shifted)."""
        self._goals: list[np.ndarray] | None = None
        """The last step's goals (:meth:`_restarts`)."""
        self._pairs: list[tuple[int, int]] = []
        """The current step's coupled pairs."""

    def close(self) -> None:
        """Close the executor the solver made for itself (never one it was given)."""
        if self._owns_executor:
            self.executor.close()

    def _order(self, i: int, pairs: list[tuple[int, int]], every: bool = False) -> tuple[int, ...]:
        """Agent i's neighbours whose copies it holds (``every``: all of them, as in a repair), cars
        first, each kind in index order (the slot order)."""
        agents = self.swarm.agents
        mine = [b if a == i else a for a, b in pairs if i in (a, b)]
        if self.options.pair_copies == "later" and not every:
            mine = [j for j in mine if j < i]
        return tuple(sorted(mine, key=lambda j: (not agents[j].oriented, j)))

    def _start_agents(self, pairs: list[tuple[int, int]], restart: frozenset[int] = frozenset()) -> None:
        """Every agent's state for a new step: the previous answer shifted when the neighbours
        are unchanged (the agents shift their own, :class:`FootprintStart`), and with
        ``carry_multipliers`` the multipliers of every stable block shifted (the others reset).
        Agents in ``restart`` start afresh, from the guess, as if their neighbours had changed
        (:meth:`_restarts`).

        A block is stable when its agent has the neighbours it had: its holders are then the
        same, and all of them carry their multipliers of it, so these keep summing to zero and
        the consensus stays the plain mean of the holders' values. A multiplier kept by one
        holder after another holder dropped or reset its own would act as a constant force
        on the block's agent, which can hold a car short of a free goal."""
        order = [self._order(i, pairs) for i in range(self.swarm.num_agents)]
        stable = [previous is not None and previous.neighbours == order[i] and i not in restart
                  for i, previous in enumerate(self._agents)]
        results = self.executor.solve([
            FootprintStart(i, neighbours, stable[i] and previous is not None and previous.answer is not None)
            for i, (neighbours, previous) in enumerate(zip(order, self._agents, strict=True))])
        for i, neighbours in enumerate(order):
            previous, state = self._agents[i], _AgentState(neighbours, results[i].answer)
            if previous is not None and self.options.carry_multipliers:
                if stable[i] and previous.own_y is not None:
                    state.own_y = _shift(previous.own_y)
                state.copy_y = {j: _shift(y) for j, y in previous.copy_y.items() if stable[j] and j in neighbours}
            self._agents[i] = state

    def _params(self, i: int, step: _Step, state: _AgentState) -> dict[str, np.ndarray]:
        agents, rho = self.swarm.agents, step.rho
        zeros = np.zeros_like(step.z[i])
        params = {"x0": step.states[i], "goal": step.goals[i], "rho": np.array([[rho]]),
                  "Z": step.z[i], "Y": zeros if state.own_y is None else state.own_y}
        for slot, j in enumerate(state.neighbours):
            params[f"Z{slot}"] = step.z[j]
            params[f"Y{slot}"] = state.copy_y.get(j, np.zeros_like(step.z[j]))
            params[f"S{slot}"] = slot_size(agents[i], agents[j])
        return params

    def _consensus(self, step: _Step) -> tuple[float, float]:
        """The z and multiplier updates from every agent's last answer; (primal, dual) residuals."""
        agents, rho = self._agents, step.rho
        holders: list[list[tuple[np.ndarray, np.ndarray | None, int, int]]] = [[] for _ in agents]
        for i, state in enumerate(agents):
            assert state is not None and state.answer is not None
            holders[i].append((state.block(), state.own_y, i, -1))
            for j in state.neighbours:
                holders[j].append((state.copy(j), state.copy_y.get(j), i, j))
        primal = dual = 0.0
        weight = self.options.owner_weight
        for j, values in enumerate(holders):
            penalties = [rho * (weight if owner < 0 else 1.0) for _, _, _, owner in values]
            z = np.sum([r * v + (0.0 if y is None else y) for r, (v, y, _, _) in zip(penalties, values, strict=True)],
                       axis=0) / sum(penalties)
            dual = max(dual, rho * float(np.max(np.abs(z - step.z[j]))))
            step.z[j] = z
            for r, (v, y, holder, owner) in zip(penalties, values, strict=True):
                primal = max(primal, float(np.max(np.abs(v - z))))
                updated = (0.0 if y is None else y) + r * (v - z)
                if owner < 0:
                    agents[holder].own_y = updated  # type: ignore[union-attr]
                else:
                    agents[holder].copy_y[owner] = updated  # type: ignore[union-attr]
        return primal, dual

    def _iterate(self, step: _Step, guesses: Sequence[np.ndarray]) -> int:
        """ADMM iterations until the residuals are below ``tol``; the iteration count. Every agent
        solves its local problem of an iteration (one batch of the executor) before the consensus
        update; an agent left without any answer ends the iterations (:class:`_NoAnswer`)."""
        options, agents = self.options, self._agents
        for iteration in range(1, options.max_iter + 1):
            requests = []
            for i, state in enumerate(agents):
                assert state is not None
                requests.append(FootprintSolve(i, state.neighbours, self._params(i, step, state),
                                               np.asarray(guesses[i], float)))
            results = self.executor.solve(requests)
            for state, result in zip(agents, results, strict=True):
                state.count(result)  # type: ignore[union-attr]
            for result in results:
                if result.answer is None:
                    raise _NoAnswer(result.agent)
            slowest = max(result.solve_time for result in results)
            started = time.perf_counter()
            primal, dual = self._consensus(step)
            step.primal.append(primal)
            step.dual.append(dual)
            step.critical += slowest + time.perf_counter() - started
            if primal < options.tol and dual < options.tol:
                return iteration
        return options.max_iter

    def _repair(self, step: _Step, plans: list[np.ndarray], inputs: list[np.ndarray], fallback: np.ndarray) -> bool:
        """Repairs the agents of every violating pair in index order (module docstring, step 3);
        True when a repair was needed. An agent whose repair fails brakes; the pairs that braking
        plan violates are repaired in a further pass by their agents that still plan (at most
        :data:`REPAIR_PASSES` passes)."""
        if self.swarm.settings.collision != "hard":
            return False
        repaired = False
        for _ in range(REPAIR_PASSES):
            violating = plan_violations(self.swarm, plans)
            agents = sorted({a for pair in violating for a in pair if not fallback[a]})
            if not agents:
                break
            repaired = True
            for i in agents:
                self._repair_agent(i, step, plans, inputs, fallback)
        return repaired

    def _repair_agent(
        self, i: int, step: _Step, plans: list[np.ndarray], inputs: list[np.ndarray], fallback: np.ndarray,
    ) -> None:
        """Agent i's plan solved again against every neighbour's plan (copies pinned), or braking.
        With ``pair_copies`` "later" the agent may hold no copy of some neighbours: the repair
        is solved in a problem with all of them, of which the agent keeps no answer (and whose
        multipliers start at zero). The repairs of a pass run one after the other: each pins the
        plans the ones before it left."""
        own = self._agents[i]
        assert own is not None
        agents = self.swarm.agents
        every = self._order(i, self._pairs, every=True)
        view = own if every == own.neighbours else _AgentState(every)
        params = self._params(i, step, view)
        own_block = consensus_block(agents[i], plans[i])  # the own block is drawn to the agent's own plan
        params.update({"Z": own_block, "Y": np.zeros_like(own_block)})
        fixed = {f"C{slot}": consensus_block(agents[j], plans[j]) for slot, j in enumerate(every)}
        [result] = self.executor.solve([FootprintSolve(i, every, params, np.asarray(plans[i], float), fixed)])
        own.count(result)
        if result.success:
            assert result.answer is not None
            plans[i], inputs[i] = result.answer.states, result.answer.inputs
        else:
            plans[i], inputs[i] = braking_plan(step.states[i], agents[i].settings)
            fallback[i] = True
        step.critical += result.solve_time

    def plan(
        self, states: Sequence[np.ndarray], goals: Sequence[np.ndarray], guesses: Sequence[np.ndarray],
    ) -> PlanStep:
        """One MPC step from measured ``states`` (one (n_i,) per agent) towards goal states
        ``goals``, starting agents without a previous answer from ``guesses`` (N+1, n_i)."""
        started = time.perf_counter()
        swarm, m = self.swarm, self.swarm.num_agents
        states = [np.asarray(x, float) for x in states]
        restart = self._restarts(goals)
        self._goals = [np.asarray(g, float).copy() for g in goals]
        self._pairs = coupled_pairs(swarm, np.array(states), self.options.coupling_margin)
        self._start_agents(self._pairs, restart)
        step = _Step(states, [np.asarray(g, float) for g in goals], self._first_consensus(guesses), self.options.rho)
        fallback = np.zeros(m, bool)
        try:
            iterations = self._iterate(step, guesses)
        except _NoAnswer:
            iterations = len(step.primal)
        plans, inputs = [], []
        for i, state in enumerate(self._agents):
            assert state is not None
            if state.answer is None:
                plan, controls = braking_plan(states[i], swarm.agents[i].settings)
                fallback[i] = True
            else:
                plan, controls = state.answer.states, state.answer.inputs
            plans.append(np.asarray(plan))
            inputs.append(np.asarray(controls))
        self._z = step.z
        repaired = self._repair(step, plans, inputs, fallback)
        return self._outcome(step, plans, inputs, fallback, iterations, repaired, started)

    def _restarts(self, goals: Sequence[np.ndarray]) -> frozenset[int]:
        """Agents whose last plan stands still (its positions within :data:`STILL` of the first)
        and whose goal moved since the last step (a deadlock detour, or its end): they start from
        the guess. Warm-started from a plan at rest, a car's local solves kept it at rest after
        its goal moved, detour after detour, where a start from the guess (the route to the new
        goal) set it moving (evidence: docs/lab/cars.md#parking-admm-probe)."""
        if self._goals is None:
            return frozenset()
        out = set()
        for i, (state, agent) in enumerate(zip(self._agents, self.swarm.agents, strict=True)):
            if state is None or state.answer is None:
                continue
            positions = agent.settings.model.position(np.asarray(state.answer.states))
            moved = np.max(np.abs(np.asarray(goals[i], float)[:2] - self._goals[i][:2]))
            if np.max(np.abs(positions - positions[0])) < STILL and moved > 0:
                out.add(i)
        return frozenset(out)

    def _first_consensus(self, guesses: Sequence[np.ndarray]) -> list[np.ndarray]:
        """A step's first consensus: the last step's shifted for agents that carry their
        multipliers, else the block of the agent's shifted answer or guess."""
        out = []
        for i, agent in enumerate(self.swarm.agents):
            state = self._agents[i]
            if self._z is not None and state is not None and state.own_y is not None:
                out.append(_shift(self._z[i]))
            elif state is not None and state.answer is not None:
                out.append(state.answer.block)
            else:
                out.append(consensus_block(agent, np.asarray(guesses[i], float)))
        return out

    def _outcome(
        self, step: _Step, plans: list[np.ndarray], inputs: list[np.ndarray], fallback: np.ndarray,
        iterations: int, repaired: bool, started: float,
    ) -> PlanStep:
        agents = self.swarm.agents
        cost = sum(_stage_cost(plans[i], inputs[i], step.goals[i], agent) for i, agent in enumerate(agents))
        slacks = [state.answer.max_slack for state in self._agents
                  if state is not None and state.answer is not None and state.answer.max_slack is not None]
        failures = sum(state.failures for state in self._agents if state is not None)
        handovers = sum(state.handovers for state in self._agents if state is not None)
        return PlanStep(
            states=np.array(plans), inputs=np.array(inputs), predicted_cost=cost,
            max_slack=max([0.0, *slacks]), wall_time=time.perf_counter() - started,
            agent_times=np.array([state.seconds for state in self._agents if state is not None]),
            failures=failures, fallback=fallback, admm_iterations=iterations, repaired=repaired,
            primal_residuals=step.primal, dual_residuals=step.dual,
            rho_history=[step.rho] * len(step.primal), critical_path=step.critical, local_fallbacks=handovers,
        )


class _NoAnswer(Exception):
    """An agent's first local solve of a step failed: it has nothing to agree with."""

    def __init__(self, agent: int) -> None:
        super().__init__(f"agent {agent}: the local problem has no answer")
        self.agent = agent


def _shift(block: np.ndarray) -> np.ndarray:
    """A (rows, N) block one step on: moved back in time, the last column repeated."""
    return np.concatenate([block[:, 1:], block[:, -1:]], axis=1)


def _stage_cost(states: np.ndarray, inputs: np.ndarray, goal: np.ndarray, agent: FootprintAgent) -> float:
    """The quadratic cost of one agent's plan (:func:`~swarmpc.formulation.ocp.quadratic_cost`)."""
    s = agent.settings
    err = np.asarray(states, float) - np.asarray(goal, float)
    stage = np.einsum("ki,ij,kj->", err[:-1], s.Q, err[:-1]) + np.einsum("ki,ij,kj->", inputs, s.R, inputs)
    return float(stage + err[-1] @ s.Qf @ err[-1])


class FootprintADMMMPCSolver:
    """:class:`FootprintADMMSolver` behind the closed loop's
    :class:`~swarmpc.solvers.base.MPCSolver` protocol (stacked (M, ...) arrays; a car's goal
    heading taken within pi of its heading, :func:`~swarmpc.solvers.footprint_central.nearest_heading`)."""

    def __init__(self, solver: FootprintADMMSolver) -> None:
        self.solver = solver

    def close(self) -> None:
        """Close the executor the solver made for itself (:meth:`FootprintADMMSolver.close`)."""
        self.solver.close()

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray | None) -> PlanStep:
        agents = self.solver.swarm.agents
        targets = [nearest_heading(goals[i], states[i]) if agent.oriented else np.asarray(goals[i], float)
                   for i, agent in enumerate(agents)]
        if guess is None:
            guess = np.array([straight_guess(agent, states[i], targets[i]) for i, agent in enumerate(agents)])
        return self.solver.plan(list(states), targets, list(guess))
