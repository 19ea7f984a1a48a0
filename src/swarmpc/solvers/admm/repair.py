"""The safety passes after the ADMM iterations: the sequential repair pass and stranded fallbacks.

ADMM on nonconvex problems may not reach consensus within any fixed number of iterations, and a
step cannot wait. A step that stops without consensus ends with a sequential pass: each agent
re-plans against its neighbours' current own plans, held fixed, so every coupled pair is feasible
whenever the solves succeed. Pairs the repaired plans bring into conflict are coupled and repaired
again, and a fallback that breaks the separation from another plan is planned around.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from swarmpc.solvers.admm.graph import CouplingGraph
from swarmpc.solvers.admm.messages import LocalRequest, LocalResult, StepRequests
from swarmpc.solvers.admm.safety import SafetyChecks

"""Most repair passes in one MPC step (the first, plus re-runs after coupling pairs whose repaired
plans conflict)."""

Solve = Callable[[list[LocalRequest]], list[LocalResult]]
"""The agents' answers to a batch of requests (timed on the step's critical path)."""


@dataclass(frozen=True, eq=False)
class SafePlans:
    """What the safety passes leave: the plans, the coupling, and the solves they added."""

    results: list[LocalResult]
    graph: CouplingGraph
    agent_times: np.ndarray
    """(M,) solve time per agent of the passes' new answers."""
    failures: int
    """Failed solves among the passes' new answers."""


def new_solves(
    results: Sequence[LocalResult], previous: Sequence[LocalResult], every: bool = False,
) -> tuple[np.ndarray, int]:
    """Solve time per agent and failed solves of the answers a repair pass produced (those not
    carried over from ``previous``; ``every``: all of them)."""
    new = [every or r is not old for r, old in zip(results, previous, strict=True)]
    times = np.array([r.solve_time if fresh else 0.0 for r, fresh in zip(results, new, strict=True)])
    return times, sum(fresh and not r.success for r, fresh in zip(results, new, strict=True))


class Repair:
    """The safety passes of one MPC step, asking the agents through ``solve``."""

    def __init__(self, requests: StepRequests, safety: SafetyChecks, solve: Solve) -> None:
        self.requests = requests
        self.safety = safety
        self.solve = solve

    def make_safe(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, results: list[LocalResult], repair_all: bool,
        stranded_check: bool,
    ) -> SafePlans:
        """The safety passes after the iterations.

        ``repair_all`` (ADMM stopped without consensus): the repair pass (:meth:`sequential`), and
        again after coupling any candidate pair whose repaired plans conflict, up to
        ``config.repair_rounds`` passes. ``stranded_check``: fallbacks that break the separation from
        another plan re-plan against every plan (rescued if their hard solves fail), then their
        neighbours against them."""
        times, failures = np.zeros(len(results)), 0
        states = self.requests.states
        rounds = self.requests.config.repair_rounds
        for round_ in range(rounds if repair_all else 0):
            previous = results
            results = self.sequential(graph, z, rho, results)
            # later passes count only the agents they re-solved
            new, failed = new_solves(results, previous, every=round_ == 0)
            times, failures = times + new, failures + failed
            # the repair only re-plans against neighbours: couple any candidate pair whose
            # repaired plans now conflict and repair again
            missing = self.safety.missing(results, graph, self.safety.checked_pairs(graph.candidates, states, results))
            if not missing or round_ == rounds - 1:
                break
            graph = graph.coupled(missing)
        stranded = self.safety.stranded_fallbacks(results) if stranded_check else []
        if stranded:
            graph = graph.coupled(stranded)
            previous = results
            results = self.sequential(graph, z, rho, results, agents=sorted({i for i, _ in stranded}))
            new, failed = new_solves(results, previous)
            times, failures = times + new, failures + failed
        return SafePlans(results, graph, times, failures)

    def sequential(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, results: list[LocalResult],
        agents: list[int] | None = None,
    ) -> list[LocalResult]:
        """Consensus repair: agents re-plan one after another against the others' current own
        plans (held fixed). Each agent respects the final plans of those before it and the plans
        those after it will respect, so every pair ends up feasible whenever the solves succeed.
        An agent whose solve fails flies its fallback plan, which the agents after it respect; it
        re-plans once more at the end, against everyone's final plans, since a plan that respects
        all of them keeps every pair it is in feasible. If it still fails, its fallback is final,
        and the agents repaired before it never saw it: each neighbour whose plan comes within
        max(Delta_ij) + d_min of that fallback re-plans once more against every final plan
        (evidence: docs/lab/admm.md#spread-scaling-first). ``agents``: re-plan only these (in this
        order) and then their neighbours as above; None: every coupled agent, highest index first
        (a tie-break; docs/lab/admm.md#closing-the-gap).

        Consecutive agents of that order that hold no copy of each other are asked in one batch
        (:func:`independent_run`): the answers are those of asking them one after another, and
        the batch costs the step's critical path only its slowest re-plan."""
        repaired = list(results)
        neighbours = graph.neighbours
        pending = deque(i for i in (list(range(len(results)))[::-1] if agents is None else agents) if neighbours[i])
        retried: set[int] = set()
        while pending:
            batch = independent_run(pending, neighbours)
            # a first failure re-plans at the end (its fallback is provisional); the retry and the
            # re-plan of a stranded fallback are final and may rescue
            rescue = [agents is not None or i in retried for i in batch]
            for i, answer in zip(batch, self._replan_all(batch, graph, z, rho, repaired, rescue), strict=True):
                repaired[i] = answer
            for i in batch:
                if not repaired[i].success and i not in retried:
                    retried.add(i)
                    pending.append(i)
        d_min, largest = self.safety.settings.d_min, self.safety.largest_delta
        for failed in [k for k in range(len(results)) if not repaired[k].success]:
            for i in neighbours[failed]:
                gap = np.max(np.abs(repaired[i].own - repaired[failed].own), axis=0).min()
                if repaired[i].success and gap < largest[i, failed] + d_min:
                    repaired[i] = self._replan(i, graph, z, rho, repaired)
        return repaired

    def _replan(
        self, i: int, graph: CouplingGraph, z: np.ndarray, rho: float, plans: list[LocalResult],
        rescue: bool = True,
    ) -> LocalResult:
        """Agent ``i``'s answer against its neighbours' current ``plans``, held fixed."""
        return self._replan_all([i], graph, z, rho, plans, [rescue])[0]

    def _replan_all(
        self, agents: list[int], graph: CouplingGraph, z: np.ndarray, rho: float, plans: list[LocalResult],
        rescue: list[bool],
    ) -> list[LocalResult]:
        """The answers of ``agents`` (no two of them coupled) against their neighbours' current
        ``plans``, held fixed, asked in one batch: none of them sees another's plan, so the answers
        are those of asking them one after another, and the batch costs the critical path only
        its slowest re-plan."""
        s = self.requests.settings
        requests = []
        for i, last_attempt in zip(agents, rescue, strict=True):
            others = list(graph.neighbours[i])
            pinned = (np.array([plans[j].states for j in others]), np.array([plans[j].inputs for j in others]))
            own_z = z.copy()
            own_z[i] = s.model.position(plans[i].states[s.first_constrained_step:]).T
            requests.append(self.requests.request(i, graph, own_z, rho, rho, False, pinned, rescue=last_attempt))
        return self.solve(requests)


def independent_run(pending: deque[int], neighbours: Sequence[Sequence[int]]) -> list[int]:
    """Take from the front of ``pending`` the longest run of distinct agents no two of which are
    coupled (at least one agent): re-planning them together changes no answer of the sequential
    order, since each agent's problem holds only its neighbours' plans."""
    batch = [pending.popleft()]
    while pending:
        nxt = pending[0]
        if nxt in batch or any(nxt in neighbours[b] or b in neighbours[nxt] for b in batch):
            break
        batch.append(pending.popleft())
    return batch
