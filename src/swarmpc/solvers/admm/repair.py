"""The safety passes after the ADMM iterations: the sequential repair pass and stranded fallbacks.

ADMM on nonconvex problems may not reach consensus within any fixed number of iterations, and a
step cannot wait. A step that stops without consensus ends with a sequential pass: each agent
re-plans against its neighbours' current own plans, held fixed, so every coupled pair is feasible
whenever the solves succeed. Pairs the repaired plans bring into conflict are coupled and repaired
again, and a fallback that breaks the separation from another plan is planned around.

:class:`Repair` runs the passes of one step in order; the selection pass of a deadline stop
(:mod:`~swarmpc.solvers.admm.selection`), the settling pass (:mod:`~swarmpc.solvers.admm.settle`),
the re-plan calls (:mod:`~swarmpc.solvers.admm.replan`) and the batching of re-plans
(:mod:`~swarmpc.solvers.admm.schedule`) live in their own modules.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.admm.clock import BatchBudget
from swarmpc.solvers.admm.graph import CouplingGraph
from swarmpc.solvers.admm.messages import LocalResult, StepRequests
from swarmpc.solvers.admm.replan import Replanner, Solve
from swarmpc.solvers.admm.safety import SafetyChecks
from swarmpc.solvers.admm.schedule import LevelSchedule, colour_order
from swarmpc.solvers.admm.selection import Selection
from swarmpc.solvers.admm.settle import Settle
from swarmpc.solvers.base import fallback_plan


@dataclass(frozen=True, eq=False)
class SafePlans:
    """What the safety passes leave: the plans, the coupling, and the solves they added."""

    results: list[LocalResult]
    graph: CouplingGraph
    agent_times: np.ndarray
    """(M,) each agent's compute on the passes' re-plans."""
    failures: int
    """Failed re-plans of the passes."""


def committed_plans(
    states: np.ndarray, applied: tuple[np.ndarray, np.ndarray] | None, settings: OCPSettings,
    results: Sequence[LocalResult],
) -> list[LocalResult]:
    """Every agent's committed plan at measured ``states``: the plan the last step applied
    (``applied``: states (M, N+1, n), inputs (M, N, m); None: none yet) shifted by one step
    (:func:`~swarmpc.solvers.base.fallback_plan`), as a fallback answer in place of ``results``."""
    committed = []
    for i, r in enumerate(results):
        previous = (None, None) if applied is None else (applied[0][i], applied[1][i])
        x, u = fallback_plan(states[i], previous[0], previous[1], settings)
        own = settings.model.position(x[settings.first_constrained_step:]).T.copy()
        committed.append(LocalResult(agent=i, own=own, copies=r.copies, states=x, inputs=u, success=False,
                                     fallback=True, solve_time=0.0, max_slack=0.0, cost=r.cost))
    return committed


class Repair:
    """The safety passes of one MPC step, asking the agents through ``solve``."""

    def __init__(
        self, requests: StepRequests, safety: SafetyChecks, solve: Solve, budget: BatchBudget | None = None,
    ) -> None:
        self.requests = requests
        self.safety = safety
        self.replan = Replanner(requests, solve)
        self.budget = budget
        """With ``config.deadline_repair`` "budget": how many batches the first repair pass and the
        selection pass's refreshing re-plans may ask (None: all)."""
        self.selection = Selection(requests, safety, self.replan, budget)
        self.settle = Settle(requests, safety)

    def make_safe(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, results: list[LocalResult], repair_all: bool,
        stranded_check: bool, committed: list[LocalResult] | None = None, waiting: np.ndarray | None = None,
    ) -> SafePlans:
        """The safety passes after the iterations.

        ``repair_all`` (ADMM stopped without consensus): the repair pass (:meth:`sequential`), and
        after coupling any candidate pair whose repaired plans conflict, a pass over the agents of
        those pairs (each re-plans against all its neighbours' plans, so every pair it was
        coupled in stays feasible), up to ``config.repair_rounds`` passes. ``stranded_check``:
        fallbacks that break the separation from another plan re-plan against every plan (rescued
        if their hard solves fail), then their neighbours against them. ``committed`` (with
        ``repair_all``): the selection pass (:class:`~swarmpc.solvers.admm.selection.Selection`)
        instead, which asks no agent; pairs of committed plans it leaves in conflict are cleared by
        :meth:`~swarmpc.solvers.admm.selection.Selection.clear`, and only what that
        leaves (with candidate pairs its new plans bring into conflict) goes through the repair
        passes above, for those agents. Agents that fly their committed plans after
        :data:`~swarmpc.solvers.admm.selection.STALE_STEPS` steps of it (``waiting``, (M,)) re-plan
        first (:meth:`~swarmpc.solvers.admm.selection.Selection.refresh`). With ``committed`` and a
        :attr:`budget`: the repair pass first, for as many batches as the budget allows (a pass
        cut short leaves the agents it did not reach on their last iterates, which the repaired
        agents planned against), and the selection pass over its plans; the refreshing re-plans
        are asked on the same budget. Last, with
        ``stranded_check``, the settling pass (:class:`~swarmpc.solvers.admm.settle.Settle`)."""
        states = self.requests.states
        agents: list[int] | None = None  # None: the full pass
        rounds = self.requests.config.repair_rounds
        if repair_all and committed is not None and self.budget is not None:
            results = self.sequential(graph, z, rho, results, budget=self.budget)
        if repair_all and committed is not None:
            results, graph, left = self.selection(graph, z, rho, results, committed, waiting)
            repair_all, graph, agents = bool(left), graph.coupled(left), _agents_of(left)
        for round_ in range(rounds if repair_all else 0):
            results = self.sequential(graph, z, rho, results, agents)
            # the repair only re-plans against neighbours: couple any candidate pair whose
            # repaired plans now conflict and repair again
            missing = self.safety.missing(results, graph, self.safety.checked_pairs(graph.candidates, states, results))
            if not missing or round_ == rounds - 1:
                break
            graph = graph.coupled(missing)
            agents = _agents_of(missing)  # the others' pairs are as the last pass left them
        stranded = self.safety.stranded_fallbacks(results) if stranded_check else []
        if stranded:
            graph = graph.coupled(stranded)
            results = self.sequential(graph, z, rho, results, agents=sorted({i for i, _ in stranded}))
        if stranded_check:
            results = self.settle(results)
        return SafePlans(results, graph, self.replan.spent.copy(), self.replan.failed)

    def sequential(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, results: list[LocalResult],
        agents: list[int] | None = None, budget: BatchBudget | None = None,
    ) -> list[LocalResult]:
        """Consensus repair: agents re-plan one after another against the others' current own
        plans (held fixed). Each agent respects the final plans of those before it and the plans
        those after it will respect, so every pair ends up feasible whenever the solves succeed.
        An agent whose solve fails flies its fallback plan (rescued by the least-violating soft plan
        when the fallback breaks the separation from a pinned plan), which the agents after it
        respect; it re-plans once more at the end, against everyone's final plans, since a plan
        that respects all of them keeps every pair it is in feasible. Rescuing already on the first
        failure gives the agents after it a plan that moves on rather than one that brakes into a
        neighbour: rescued only on the retry, swarms under a deadline took longer to their goals
        (evidence: docs/lab/admm.md#repair-rounds). If the retry fails, its fallback is final,
        and the agents repaired before it never saw it: each neighbour whose plan comes within
        max(Delta_ij) + d_min of that fallback re-plans once more against every final plan
        (evidence: docs/lab/admm.md#spread-scaling-first); those re-plans ask consecutive
        uncoupled agents in one batch (:meth:`_replan_around`). ``agents``: re-plan only these
        (in this order) and then their neighbours as above; None: every coupled agent in the order
        of ``config.repair_order``: highest index first (a tie-break;
        docs/lab/admm.md#closing-the-gap) or colour by colour (:func:`colour_order`).

        The re-plans are asked level by level (:class:`LevelSchedule`): a re-plan reads only its
        neighbours' plans, so it waits only for the earlier re-plans of its neighbours and itself,
        and each level, asked in one batch, gives the answers of asking the order one agent after
        another; a batch costs the step's critical path only its slowest re-plan. ``budget``: a
        level is asked only if it allows (:meth:`BatchBudget.allows`); the pass returns at the first
        it refuses, and the re-plans around failures are asked while it allows (the selection pass
        that follows covers what is left)."""
        repaired = list(results)
        neighbours = graph.neighbours
        if agents is None:
            agents = colour_order(neighbours) if self.requests.config.repair_order == "colour" else \
                list(range(len(results)))[::-1]
        schedule = LevelSchedule(neighbours)
        for i in agents:
            if neighbours[i]:
                schedule.append(i)
        retried: set[int] = set()
        while batch := schedule.pop():
            if budget is not None and not budget.allows():
                return repaired  # the selection pass makes what is left safe
            rescue = [True] * len(batch)  # every failed call may fly a rescue plan
            for i, answer in zip(batch, self.replan(batch, graph, z, rho, repaired, rescue), strict=True):
                repaired[i] = answer
            for i in batch:  # a retry goes after every re-plan queued so far, as in the one-by-one order
                if not repaired[i].success and i not in retried:
                    retried.add(i)
                    schedule.append(i)
        failures = [k for k in range(len(results)) if not repaired[k].success]
        self._replan_around(failures, graph, z, rho, repaired, budget)
        if budget is not None:
            budget.close()
        return repaired

    def _replan_around(
        self, failures: list[int], graph: CouplingGraph, z: np.ndarray, rho: float, repaired: list[LocalResult],
        budget: BatchBudget | None = None,
    ) -> None:
        """Each neighbour of a ``failures`` agent whose plan comes within max(Delta_ij) + d_min of
        that agent's fallback re-plans against every current plan (``repaired``, updated in
        place), failure by failure, neighbour by neighbour. Consecutive re-plans of agents that
        hold no copy of each other are asked in one batch: a re-plan sees only its neighbours'
        plans, so the answers are those of asking them one after another. ``budget``: a batch is
        asked only if it allows, and none after the first it refuses."""
        d_min, largest = self.safety.settings.d_min, self.safety.largest_delta
        neighbours = graph.neighbours
        batch: list[int] = []

        refused = False

        def flush() -> None:
            nonlocal refused
            refused = refused or (budget is not None and not budget.allows())
            if not refused:
                for i, answer in zip(batch, self.replan(batch, graph, z, rho, repaired, [True] * len(batch)),
                                     strict=True):
                    repaired[i] = answer
            batch.clear()

        for failed in failures:
            for i in neighbours[failed]:
                if i in batch or any(i in neighbours[b] or b in neighbours[i] for b in batch):
                    flush()
                gap = np.max(np.abs(repaired[i].own - repaired[failed].own), axis=0).min()
                if repaired[i].success and gap < largest[i, failed] + d_min:
                    batch.append(i)
        if batch:
            flush()



def _agents_of(pairs: Sequence[tuple[int, int]]) -> list[int]:
    """The agents of ``pairs``, highest index first (the repair pass's order)."""
    return sorted({k for pair in pairs for k in pair}, reverse=True)


