"""The selection pass of a deadline stop: every agent flies its new plan or its committed plan,
chosen so that every pair that can meet keeps half the OBCA separation, with as few solves as
possible (``solver.admm.deadline_repair: select``)."""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Sequence

import numpy as np

from swarmpc.solvers.admm.clock import BatchBudget
from swarmpc.solvers.admm.graph import CouplingGraph
from swarmpc.solvers.admm.messages import LocalResult, StepRequests
from swarmpc.solvers.admm.replan import Replanner
from swarmpc.solvers.admm.safety import SafetyChecks
from swarmpc.solvers.admm.schedule import independent_run

STALE_STEPS = 2
"""Steps an agent has flown its committed plan after which the selection pass has it re-plan
rather than fly that plan again (:meth:`Selection.refresh`)."""


class Selection:
    """The selection pass of one MPC step (:meth:`__call__`), its clearing and refreshing re-plans
    asked through ``replan``."""

    def __init__(
        self, requests: StepRequests, safety: SafetyChecks, replan: Replanner, budget: BatchBudget | None = None,
    ) -> None:
        self.requests = requests
        self.safety = safety
        self.replan = replan
        self.budget = budget
        """How many batches :meth:`refresh` may ask (None: all): its re-plans help a waiting agent
        on, and the plans are safe without them."""

    def __call__(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, iterates: list[LocalResult],
        committed: list[LocalResult], waiting: np.ndarray | None,
    ) -> tuple[list[LocalResult], CouplingGraph, list[tuple[int, int]]]:
        """The selection pass (:meth:`select`), then :meth:`clear` and :meth:`refresh`: the plans,
        the graph with the pairs they coupled, and the checked pairs whose plans still do not keep
        d_min / 2 (for the repair pass)."""
        chosen, clashing = self.select(graph, iterates, committed, waiting)
        graph = graph.coupled(clashing)
        results = self.clear(graph, z, rho, chosen, clashing)
        stale = [] if waiting is None else [i for i, r in enumerate(results)
                                            if r is committed[i] and waiting[i] >= STALE_STEPS]
        first, second = self.pairs_to_check(graph, results, committed)
        if stale:
            results, graph = self.refresh(graph, z, rho, results, iterates, stale, (first, second))
            first, second = self.pairs_to_check(graph, results, committed)  # a new plan may leave its reach
        apart = self.safety.pairs_apart(results, first, second)
        return results, graph, list(zip(first[~apart].tolist(), second[~apart].tolist(), strict=True))

    def select(
        self, graph: CouplingGraph, results: list[LocalResult], committed: list[LocalResult],
        waiting: np.ndarray | None = None,
    ) -> tuple[list[LocalResult], list[tuple[int, int]]]:
        """The selection pass: every agent flies its new plan or its ``committed`` plan, chosen so
        that every pair that can meet keeps half the OBCA separation, with no solve.

        All agents start on their new plans (an answer that is already a fallback starts on its
        committed plan). While some checked pair (:meth:`pairs_to_check`) is closer than d_min / 2
        (:meth:`SafetyChecks.pairs_apart`, the margin of the converged step's check), one agent of
        each such pair that is on its new plan goes back to its committed plan: the one that has
        flown its committed plan for fewer steps before this one (``waiting``, (M,); None: none),
        then the lower index (the sequential pass gives the higher index precedence), so that no
        agent waits for good behind the same neighbour. The set of committed agents only grows, so
        this ends within M rounds; agents sent back are then readmitted where they can be
        (:meth:`_readmit`). The committed plans are last step's checked plans shifted, so they
        rarely clash with each other; pairs that do are returned (with the plans chosen so far)."""
        rank = _ranks(len(results), waiting)
        on_new = np.array([not r.fallback for r in results])
        first, second = self.pairs_to_check(graph, results, committed)
        while True:
            chosen = [r if new else c for r, c, new in zip(results, committed, on_new, strict=True)]
            clash = ~self.safety.pairs_apart(chosen, first, second)
            back: set[int] = set()
            for i, j in zip(first[clash].tolist(), second[clash].tolist(), strict=True):
                movable = sorted((k for k in (i, j) if on_new[k]), key=lambda k: rank[k])
                if movable and back.isdisjoint((i, j)):
                    back.add(movable[0])
            if not back:
                break
            on_new[sorted(back)] = False
        self._readmit(chosen, results, on_new, first, second, rank)
        clash = ~self.safety.pairs_apart(chosen, first, second)
        return chosen, list(zip(first[clash].tolist(), second[clash].tolist(), strict=True))

    def pairs_to_check(
        self, graph: CouplingGraph, results: list[LocalResult], committed: list[LocalResult],
    ) -> tuple[np.ndarray, np.ndarray]:
        """(first, second) agents of every pair (i < j) that can meet: a reach candidate, a coupled
        or plane pair, or a pair of an agent whose new or committed plan left its reach bound."""
        states = self.requests.states
        checked = self.safety.checked_pairs(graph.candidates, states, results)
        checked = checked | self.safety.checked_pairs(graph.candidates, states, committed)
        for i, n in enumerate(graph.with_plane_partners()):
            checked[i, list(n)] = True
        first, second = np.nonzero(np.triu(checked | checked.T, k=1))
        return first, second

    def _readmit(
        self, chosen: list[LocalResult], results: list[LocalResult], on_new: np.ndarray, first: np.ndarray,
        second: np.ndarray, rank: np.ndarray,
    ) -> None:
        """Put agents sent back to their committed plans on their new plans again, highest rank
        first, where the new plan keeps clear of every plan chosen now (an agent sent back for a
        clash with a plan that was itself sent back later). ``chosen`` and ``on_new`` change in place."""
        for i in sorted(np.flatnonzero(~on_new), key=lambda k: -rank[k]):
            if results[i].fallback:
                continue
            if self._clear_of(chosen, results[i], first, second):
                chosen[i], on_new[i] = results[i], True

    def _clashes_of(
        self, chosen: list[LocalResult], plan: LocalResult, first: np.ndarray, second: np.ndarray,
    ) -> np.ndarray:
        """Indices into (``first``, ``second``) of the checked pairs that agent ``plan.agent``,
        flying ``plan``, does not keep apart from the other ``chosen`` plans."""
        i = plan.agent
        mine = np.flatnonzero((first == i) | (second == i))
        trial = chosen[:i] + [plan] + chosen[i + 1:]
        return mine[~self.safety.pairs_apart(trial, first[mine], second[mine])]

    def _clear_of(self, chosen: list[LocalResult], plan: LocalResult, first: np.ndarray, second: np.ndarray) -> bool:
        """Whether agent ``plan.agent`` flying ``plan`` keeps every checked pair it is in apart
        from the other ``chosen`` plans."""
        return self._clashes_of(chosen, plan, first, second).size == 0

    def refresh(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, chosen: list[LocalResult],
        iterates: list[LocalResult], agents: list[int], pairs: tuple[np.ndarray, np.ndarray],
    ) -> tuple[list[LocalResult], CouplingGraph]:
        """Agents ``agents``, on their committed plans, re-plan against their neighbours' chosen
        plans, held fixed (quick calls, uncoupled agents in one batch), each first coupled with
        every agent whose chosen plan its iterate (``iterates``) conflicts with; a new plan replaces
        the committed one where it keeps every checked pair (``pairs``) apart. An agent sent back
        step after step flies a plan that brakes to rest, and its iterates, made for an unfinished
        consensus, keep conflicting with its neighbours' plans: a re-plan against the plans they
        fly gets it moving (evidence: docs/lab/admm.md#deadline-selection). Returns the plans and
        the graph with those couplings."""
        first, second = pairs
        hits = [k for i in agents for k in self._clashes_of(chosen, iterates[i], first, second)]
        graph = graph.coupled((int(first[k]), int(second[k])) for k in hits)
        repaired = list(chosen)
        pending = deque(i for i in sorted(agents, reverse=True) if graph.neighbours[i])
        while pending and (self.budget is None or self.budget.allows()):
            batch = independent_run(pending, graph.neighbours)
            answers = self.replan(batch, graph, z, rho, repaired, [False] * len(batch), quick=True)
            for answer in answers:
                if answer.success and self._clear_of(repaired, answer, first, second):
                    repaired[answer.agent] = answer
        if self.budget is not None:
            self.budget.close()
        return repaired, graph

    def clear(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, results: list[LocalResult],
        clashing: list[tuple[int, int]],
    ) -> list[LocalResult]:
        """Clear the ``clashing`` pairs (coupled in ``graph``) of the selection pass: one agent of
        each pair (:func:`_cover`) re-plans against its neighbours' chosen plans, held fixed, which
        clears the pair if it succeeds. An agent whose re-plan fails keeps its chosen plan and its
        clash partners not yet asked re-plan in its place: each failed call costs a step tens of
        milliseconds, and the partner's problem is a different one."""
        repaired = list(results)
        pending = deque(_cover(clashing))
        asked: set[int] = set()
        while pending:
            batch = independent_run(pending, graph.neighbours)
            asked.update(batch)
            answers = self.replan(batch, graph, z, rho, repaired, [False] * len(batch), quick=True)
            for i, answer in zip(batch, answers, strict=True):
                if answer.success:
                    repaired[i] = answer
                    continue
                pending.extend(j for pair in clashing if i in pair for j in pair
                               if j not in asked and j not in pending)
        return repaired


def _ranks(count: int, waiting: np.ndarray | None) -> np.ndarray:
    """(count,) each agent's rank in the selection pass: by steps waited (``waiting``), then index."""
    waited = np.zeros(count, int) if waiting is None else np.asarray(waiting, int)
    order = np.lexsort((np.arange(count), waited))
    rank = np.empty(count, int)
    rank[order] = np.arange(count)
    return rank


def _cover(pairs: Sequence[tuple[int, int]]) -> list[int]:
    """Agents of ``pairs`` such that every pair holds one (greedily, the agent in most pairs first,
    then the higher index), highest index first: re-planning one agent of a pair against the other's
    plan, held fixed, clears the pair."""
    left, cover = list(pairs), []
    while left:
        counts = Counter(k for pair in left for k in pair)
        pick = max(counts, key=lambda k: (counts[k], k))
        cover.append(pick)
        left = [pair for pair in left if pick not in pair]
    return sorted(cover, reverse=True)
