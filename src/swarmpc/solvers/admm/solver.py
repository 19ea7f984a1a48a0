"""The coordinator: one MPC step of consensus ADMM over an executor (:class:`ADMMSolver`)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import as_bodies
from swarmpc.solvers.admm.agent import LocalAgentFactory
from swarmpc.solvers.admm.clock import BATCH_WINDOW, BatchBudget, StepClock, TimedAgentFactory
from swarmpc.solvers.admm.config import ADMMConfig
from swarmpc.solvers.admm.consensus import (
    Blocks,
    Carryover,
    PenaltySchedule,
    Residuals,
    average,
    carried_blocks,
    consensus_met,
    dual_residual,
    primal_residual,
    starting_consensus,
)
from swarmpc.solvers.admm.graph import CouplingGraph, guess_neighbours, reachable_guesses
from swarmpc.solvers.admm.messages import LocalRequest, LocalResult, StepRequests, compute_time
from swarmpc.solvers.admm.repair import Repair, SafePlans, committed_plans
from swarmpc.solvers.admm.safety import SafetyChecks, own_positions
from swarmpc.solvers.base import PlanStep
from swarmpc.solvers.executors import AgentFactory, Executor, SerialExecutor

RESERVE_WINDOW = 5
"""Repairing steps whose longest safety passes set the next step's reserve (:meth:`ADMMSolver._reserve`)."""


@dataclass(frozen=True, eq=False)
class Iterations:
    """Where the ADMM iterations of a step ended."""

    results: list[LocalResult]
    graph: CouplingGraph
    z: np.ndarray
    rho: float
    """The penalty after the last iteration (the repair pass and ``adaptive_rho`` carry it on)."""
    converged: bool
    residuals: Residuals
    agent_times: np.ndarray
    failures: int


class ADMMSolver:
    """Consensus-ADMM distributed MPC over an executor.

    Parameters
    ----------
    settings : OCPSettings
        The agents' problem: horizon, dynamics, limits, costs, obstacles.
    num_agents : int
        M.
    delta : ndarray
        One Delta (d,) for every pair, or the agents' body half-sizes (M, d): pair (i, j) keeps
        Delta_ij = b_i + b_j and agent i's obstacles are grown by b_i
        (:func:`swarmpc.model.geometry.as_bodies`).
    config : ADMMConfig or None
        ADMM's parameters (None: the defaults).
    executor : Executor or None
        Where the agents' local steps run. An executor given is the caller's: :meth:`close`
        leaves it open. None: the solver's own serial executor, which :meth:`close` closes.
    agents : callable or None
        The agents' recipe, ``agents(i)`` -> agent i (picklable for a process executor); None:
        :meth:`LocalAgentFactory.for_config`.
    """

    def __init__(
        self,
        settings: OCPSettings,
        num_agents: int,
        delta: np.ndarray,
        config: ADMMConfig | None = None,
        executor: Executor | None = None,
        agents: AgentFactory | None = None,
    ) -> None:
        self.settings = settings
        self.num_agents = num_agents
        self.bodies = as_bodies(delta, num_agents)
        self.config = config if config is not None else ADMMConfig()
        self.safety = SafetyChecks(settings, self.bodies)
        self._owns_executor = executor is None
        self.executor: Executor = SerialExecutor() if executor is None else executor
        factory = agents if agents is not None else LocalAgentFactory.for_config(settings, self.bodies, self.config)
        self.executor.start(TimedAgentFactory(factory), range(num_agents))
        self.carryover: Carryover | None = None
        """What the next step starts from (None before the first step)."""
        self._clock = StepClock()
        """The current step's clock: every local step is asked through it (:meth:`_solve`)."""
        self._local_fallbacks = 0
        """The current step's local solves the QP path failed and IPOPT answered (:meth:`_solve`)."""
        self._safety_times: deque[float] = deque(maxlen=RESERVE_WINDOW)
        """Critical-path seconds the safety passes of the last steps that repaired took (see
        :meth:`_reserve`)."""
        self._batch_shares: deque[float] = deque(maxlen=BATCH_WINDOW)
        """Critical-path seconds of the last batches of re-plans asked on a budget
        (``config.deadline_repair`` "budget"; :class:`~swarmpc.solvers.admm.clock.BatchBudget`)."""
        self._after_batches: deque[float] = deque(maxlen=RESERVE_WINDOW)
        """Critical-path seconds the last budget steps spent after their last batch: the margin kept
        free after a batch."""
        self._waiting = np.zeros(num_agents, int)
        """Per agent, the steps in a row it has flown a fallback or committed plan (the selection
        pass's priority)."""
        self._slack = True
        """Whether the last step's plans kept every pair that could meet at least d_min + ``tol``
        apart: no pair constraint near binding, the state in which the next step's probe
        (``config.independent_first``) tends to be taken; after a step with a pair at d_min the
        probe would mostly add a round for nothing."""
        self._applied: tuple[np.ndarray, np.ndarray] | None = None
        """States and inputs of the plans the last step applied (the committed plans of
        ``config.deadline_repair`` "select")."""

    def close(self) -> None:
        """Close the executor the solver made for itself (never one it was given)."""
        if self._owns_executor:
            self.executor.close()

    def pair_delta(self, first: Any, second: Any) -> np.ndarray:
        """Delta_ij = b_i + b_j of agents ``first`` and ``second`` (indices or index arrays):
        (d,) for one pair, (n, d) for n pairs."""
        return self.safety.pair_delta(first, second)

    def neighbours(self, guess: np.ndarray, candidates: np.ndarray | None = None) -> list[tuple[int, ...]]:
        """Agents each agent couples with up front, from the guesses (M, N+1, n), among reach
        ``candidates`` (None: every pair); see :func:`~swarmpc.solvers.admm.graph.guess_neighbours`.
        Candidate pairs left out are checked after convergence and coupled on demand if their
        plans conflict (see :meth:`plan`)."""
        return guess_neighbours(guess, self.settings, self.safety.largest_delta, self.config, candidates)

    def reachable_guesses(self, states: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """See :func:`~swarmpc.solvers.admm.graph.reachable_guesses`."""
        return reachable_guesses(states, guess, self.settings)

    def conflicts(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]], candidates: np.ndarray | None = None,
    ) -> list[tuple[int, int]]:
        """See :meth:`~swarmpc.solvers.admm.safety.SafetyChecks.conflicts`."""
        return self.safety.conflicts(results, neighbours, candidates)

    def coupled_plans_clear(self, results: list[LocalResult], neighbours: tuple[tuple[int, ...], ...]) -> bool:
        """The stop's check on the flown plans: every coupled pair's own plans keep half the OBCA
        separation (:meth:`~swarmpc.solvers.admm.safety.SafetyChecks.coupled_plans_clear`)."""
        return self.safety.coupled_plans_clear(results, neighbours)

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> PlanStep:
        """One MPC step: ADMM iterations until consensus, then the safety passes, then every
        agent's own plan.

        The coupling graph is built once from the measured ``states`` and the ``guess``
        (:meth:`CouplingGraph.build`) and grows only by pairs whose plans conflict. The agents
        iterate through the executor until the residuals meet ``tol`` and every coupled pair's
        plans are clear (:meth:`_iterate`); a step that ends without consensus goes through the
        repair pass (:class:`~swarmpc.solvers.admm.repair.Repair`). With
        ``config.independent_first``, after a step whose plans kept every pair d_min + ``tol``
        apart, every agent's own optimum is asked first (:meth:`_independent`): plans that keep
        every pair that can meet d_min apart are the step's answer, with no iterations.

        With ``config.deadline``, ADMM is anytime: before each iteration after the first, the
        step's critical path so far plus the largest share of the last few iterations plus a reserve for the
        safety passes (:meth:`_reserve`) is compared with the deadline
        (:class:`StepClock`); when it would overrun, no further iteration starts and the
        step ends as one that ran out of iterations does, through the safety passes (the repair
        pass, re-run on conflicting candidate pairs, then re-plans around stranded fallbacks;
        always run after a deadline stop, even with ``repair`` off).

        What is guaranteed with ``config.deadline_repair`` "select": every pair of
        agents that can meet within the horizon flies plans that keep half the OBCA separation at
        every constrained step, checked on the plans themselves; each agent flies its last iterate
        or the plan applied at the last step, shifted (its committed plan), and an agent of a pair
        of committed plans that conflict re-plans against its neighbours' chosen plans
        (:class:`~swarmpc.solvers.admm.selection.Selection`,
        :meth:`~swarmpc.solvers.admm.selection.Selection.clear`); what that leaves goes through the passes
        below for those agents. With "sequential" (the default): the deadline only ever removes ADMM iterations;
        it never shortens or skips a safety pass. A plan applied after a deadline stop has passed
        exactly the passes of a step that reached ``max_iter`` without consensus: every coupled
        agent re-planned, one after another, against its neighbours' current plans held fixed (each
        coupled pair is then feasible under the OBCA constraints whenever its solves succeed); an
        agent whose solves failed keeps its current plan if it verifiably meets every constraint,
        else flies a fallback that the agents after it respect and that its close neighbours re-plan
        around (rescued by the least-violating soft plan as a last resort); and every candidate pair
        that can meet within the horizon was checked for conflicts and, if it had one, coupled and
        repaired (up to ``solver.admm.repair_rounds`` passes). The time of these passes counts on
        the critical path; when the total exceeds the deadline the step is a deadline miss (recorded
        by the run), never an unchecked plan. Not guaranteed: that the critical path stays within
        the deadline (the first iteration and the safety passes always run), nor the plan's quality
        (fewer iterations: further from the consensus optimum).
        Stopping depends on measured time, so a deadline that binds makes a run depend on the
        machine and its load.
        """
        self._clock = StepClock(self.config.deadline, reserve=self._reserve())
        self._local_fallbacks = 0
        cfg, s = self.config, self.settings
        requests = StepRequests(s, cfg, self.bodies, states, goals, guess, self._applied)
        graph = CouplingGraph.build(states, guess, goals, s, self.bodies, cfg)
        z = starting_consensus(s.model.position(guess[:, s.first_constrained_step:]), self.carryover)
        probing = cfg.independent_first and self._slack and any(graph.neighbours)
        probe = self._independent(requests, graph, z) if probing else None
        run = probe if probe is not None and probe.converged else self._iterate(requests, graph, z)
        if probe is not None and run is not probe:  # the probe's round counts towards the step's compute
            run = replace(run, agent_times=run.agent_times + probe.agent_times, failures=run.failures + probe.failures)
        repair = cfg.repair or self._clock.stopped  # a deadline stop is never left unrepaired
        repaired = not run.converged and repair
        before = self._clock.elapsed()[1]
        committed = None
        budget = None
        if self._clock.stopped and cfg.deadline_repair in ("select", "budget"):
            committed = committed_plans(states, self._applied, s, run.results)
            if cfg.deadline_repair == "budget":
                budget = BatchBudget(self._clock, self._batch_shares, max(self._after_batches, default=0.0))
        safe = Repair(requests, self.safety, self._solve, budget).make_safe(
            run.graph, run.z, run.rho, run.results, repaired, repair, committed, self._waiting)
        if budget is not None and budget.closed_at is not None:
            self._after_batches.append(self._clock.elapsed()[1] - budget.closed_at)
        self._waiting = np.where([r.fallback for r in safe.results], self._waiting + 1, 0)
        if cfg.independent_first:
            self._slack = self.safety.plans_keep_d_min(safe.results, safe.graph.candidates, states, cfg.tol)
        self._applied = (np.array([r.states for r in safe.results]), np.array([r.inputs for r in safe.results]))
        if repaired:  # a pass the budget cut short needed more than it took: the largest reserve
            cut = budget is not None and budget.refused
            self._safety_times.append(np.inf if cut else self._clock.elapsed()[1] - before)
        # the next step's consensus starts from the plans actually applied: after a repair pass
        # the average z of a non-converged iterate is not what any agent flies
        self.carryover = Carryover(own_positions(safe.results), safe.graph.neighbours,
                                   run.rho if cfg.adaptive_rho else cfg.rho, multipliers=run is not probe)
        return self._plan_step(run, safe, repaired=repaired)

    def _reserve(self) -> float:
        """Critical-path seconds a step under a deadline keeps free of ADMM iterations for its
        safety passes: the longest the passes of the last :data:`RESERVE_WINDOW` repairing steps
        took, at most half the deadline. An
        uncapped reserve feeds itself: a step left one iteration needs a long repair, which leaves
        the next step one iteration (evidence: docs/lab/admm.md#deadline-repair-batches)."""
        deadline = self.config.deadline
        if deadline is None or not self._safety_times:
            return 0.0
        return min(max(self._safety_times), 0.5 * deadline)

    def _independent(self, requests: StepRequests, graph: CouplingGraph, z: np.ndarray) -> Iterations:
        """The probe of ``config.independent_first``: every agent's own optimum with no neighbour in
        it, in one round of local steps. Converged (one iteration, residuals zero) when every plan
        succeeded and every pair that can meet keeps d_min at every constrained step
        (:meth:`~swarmpc.solvers.admm.safety.SafetyChecks.plans_keep_d_min`): the joint problem's
        pair constraints are slack at these plans, each of which minimises its own agent's cost
        under its own constraints, so together they are the joint optimum, with every consensus
        multiplier zero. The probe leaves the agents' ADMM state as it was, so a step whose probe
        is not taken iterates exactly as it would have without it."""
        rho = self.carryover.rho if self.carryover is not None else self.config.rho
        results = self._solve([requests.independent(i, z, rho) for i in range(self.num_agents)])
        times = np.zeros(self.num_agents)
        for r in results:
            times[r.agent] += compute_time(r)
        failures = sum(not r.success for r in results)
        clear = failures == 0 and self.safety.plans_keep_d_min(results, graph.candidates, requests.states)
        residuals = Residuals()
        if clear:
            residuals.add(0.0, 0.0, rho)
        return Iterations(results, graph, own_positions(results), rho, clear, residuals, times, failures)

    def _iterate(self, requests: StepRequests, graph: CouplingGraph, z: np.ndarray) -> Iterations:
        """ADMM iterations until the stop rule holds on plans that pass the checks, ``max_iter``,
        a stall at the largest rho, or the deadline. A converged iterate whose plans conflict
        couples the pairs concerned (:meth:`CouplingGraph.coupled`) and iterates on."""
        cfg, M = self.config, self.num_agents
        penalty = PenaltySchedule(cfg, self.carryover.rho if self.carryover is not None else cfg.rho)
        residuals = Residuals()
        agent_times, failures = np.zeros(M), 0
        results: list[LocalResult] = []
        converged = False
        carry = carried_blocks(cfg.carry_multipliers, graph.neighbours, self.carryover)
        blocks: Blocks | None = None
        for iteration in range(cfg.max_iter):
            if not self._clock.next_iteration():
                break
            new = iteration == 0
            asked = requests.iteration(graph, z, penalty.rho, penalty.previous, new, carry if new else None)
            results = self._solve(asked)
            # in the answers' order, as a loop adding each agent's time would
            np.add.at(agent_times, [r.agent for r in results], [compute_time(r) for r in results])
            failures += sum(not r.success for r in results)
            blocks = Blocks.of(results, graph.neighbours, blocks.layout if blocks is not None else None)
            z_new, weights = average(results, graph.neighbours, cfg.owner_weight, cfg.relaxation, z, blocks)
            r_norm = primal_residual(results, graph.neighbours, z_new, blocks)
            s_norm = dual_residual(z_new - z, weights, graph.neighbours, penalty.rho, blocks)
            z = z_new
            converged = consensus_met(r_norm, s_norm, penalty.rho, cfg)
            residuals.add(r_norm, s_norm, penalty.rho)
            if converged:
                checked = self.safety.checked_pairs(graph.candidates, requests.states, results)
                missing = self.safety.missing(results, graph, checked)
                if not missing and self.coupled_plans_clear(results, graph.neighbours):
                    break
                converged = False
                graph = graph.coupled(missing)
            if penalty.advance(residuals.primal, s_norm):
                break
        return Iterations(results, graph, z, penalty.rho, converged, residuals, agent_times, failures)

    def _solve(self, requests: list[LocalRequest]) -> list[LocalResult]:
        """The agents' answers to ``requests``, timed on the current step's critical path; the
        answers' QP-to-IPOPT fallbacks count towards the step's (iterations and safety passes alike)."""
        results = list(self._clock.solve(self.executor, requests))
        self._local_fallbacks += sum(r.local_fallbacks for r in results)
        return results

    def _plan_step(self, run: Iterations, safe: SafePlans, repaired: bool) -> PlanStep:
        """The step's record: the plans the safety passes left, and what the step cost."""
        results = safe.results
        wall, critical = self._clock.elapsed()
        return PlanStep(
            states=np.array([r.states for r in results]),
            inputs=np.array([r.inputs for r in results]),
            predicted_cost=float(sum(r.cost for r in results)),
            max_slack=float(max(r.max_slack for r in results)),
            wall_time=wall,
            agent_times=run.agent_times + safe.agent_times,
            failures=run.failures + safe.failures,
            fallback=np.array([r.fallback for r in results]),
            admm_iterations=len(run.residuals),
            repaired=repaired,
            critical_path=critical,
            deadline_stop=self._clock.stopped,
            local_fallbacks=self._local_fallbacks,
            primal_residuals=run.residuals.primal,
            dual_residuals=run.residuals.dual,
            rho_history=run.residuals.rho,
            copies=safe.graph.copies,
            planes=safe.graph.plane_counts,
        )
