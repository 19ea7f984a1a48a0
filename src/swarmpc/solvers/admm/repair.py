"""The safety passes after the ADMM iterations: the sequential repair pass and stranded fallbacks.

ADMM on nonconvex problems may not reach consensus within any fixed number of iterations, and a
step cannot wait. A step that stops without consensus ends with a sequential pass: each agent
re-plans against its neighbours' current own plans, held fixed, so every coupled pair is feasible
whenever the solves succeed. Pairs the repaired plans bring into conflict are coupled and repaired
again, and a fallback that breaks the separation from another plan is planned around.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from itertools import product

import networkx as nx
import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.admm.graph import CouplingGraph, components
from swarmpc.solvers.admm.messages import LocalRequest, LocalResult, StepRequests
from swarmpc.solvers.admm.safety import SafetyChecks
from swarmpc.solvers.base import braking_plan, fallback_plan

"""Most repair passes in one MPC step (the first, plus re-runs after coupling pairs whose repaired
plans conflict)."""

SETTLE_COMBINATIONS = 243
"""Most combinations of plans :meth:`Repair.settle` tries for one group of fallback agents (3^5);
a larger group chooses agent by agent."""

STALE_STEPS = 2
"""Steps an agent has flown its committed plan after which the selection pass has it re-plan
rather than fly that plan again (:meth:`Repair.refresh`)."""

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

    def __init__(self, requests: StepRequests, safety: SafetyChecks, solve: Solve) -> None:
        self.requests = requests
        self.safety = safety
        self.solve = solve

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
        ``repair_all``): the selection pass (:meth:`select`) instead, which asks no agent; pairs of
        committed plans it leaves in conflict are cleared by :meth:`clear`, and only what that
        leaves (with candidate pairs its new plans bring into conflict) goes through the repair
        passes above, for those agents. Agents that fly their committed plans after
        :data:`STALE_STEPS` steps of it (``waiting``, (M,)) re-plan first (:meth:`refresh`)."""
        times, failures = np.zeros(len(results)), 0
        states = self.requests.states
        agents: list[int] | None = None  # None: the full pass
        if repair_all and committed is not None:
            previous = results
            results, graph, left = self._select(graph, z, rho, results, committed, waiting)
            new, failed = new_solves(results, previous)
            times, failures = times + new, failures + failed
            repair_all, graph, agents = bool(left), graph.coupled(left), _agents_of(left)
        rounds = self.requests.config.repair_rounds
        for round_ in range(rounds if repair_all else 0):
            previous = results
            results = self.sequential(graph, z, rho, results, agents)
            # later passes count only the agents they re-solved
            new, failed = new_solves(results, previous, every=round_ == 0 and agents is None)
            times, failures = times + new, failures + failed
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
            previous = results
            results = self.sequential(graph, z, rho, results, agents=sorted({i for i, _ in stranded}))
            new, failed = new_solves(results, previous)
            times, failures = times + new, failures + failed
        if stranded_check:
            results = self.settle(results)
        return SafePlans(results, graph, times, failures)

    def settle(self, results: list[LocalResult]) -> list[LocalResult]:
        """The last safety pass, which asks no agent: fallback agents whose plans still come closer
        than d_min / 2 to another plan (:meth:`SafetyChecks.stranded_fallbacks`) choose among the
        plans they have without a solve: the plan they fly now, their committed plan (the plan
        applied at the last step, shifted: :func:`~swarmpc.solvers.base.fallback_plan`) and
        braking to rest from the measured state.

        Two agents whose solves keep failing in each other's way each re-plan against the other's
        fallback, and each rescue plan violates least against a plan the other then replaces: their
        plans' first conflict creeps towards the present by about a step per MPC step, and ends in
        a collision (evidence: docs/lab/admm.md#settle-fallbacks). Each group of such agents in
        conflict with each other takes the combination whose first conflict with any plan comes
        latest in the horizon (:meth:`SafetyChecks.first_close_steps`), then the one with the
        smallest shortfall, then the one that changes fewest plans (every combination up to
        :data:`SETTLE_COMBINATIONS`, else each agent's options with the others' current plans)."""
        stranded = self.safety.stranded_fallbacks(results)
        fell = sorted({k for pair in stranded for k in pair if results[k].fallback})
        index = {a: k for k, a in enumerate(fell)}
        links: list[list[int]] = [[] for _ in fell]
        for i, j in stranded:
            if i in index and j in index:
                links[index[i]].append(index[j])
                links[index[j]].append(index[i])
        settled = list(results)
        labels = components([tuple(row) for row in links])
        for label in range(len(set(labels.tolist()))):
            group = [fell[k] for k in np.flatnonzero(labels == label)]
            options = [self._plans_without_solve(results[a]) for a in group]
            best: tuple[tuple[int, float, int], list[LocalResult]] | None = None
            for choice in _choices(options, settled, group):
                trial = list(settled)
                for a, plan in zip(group, choice, strict=True):
                    trial[a] = plan
                first, short = self.safety.first_close_steps(trial, group)
                key = (-first, short, sum(plan is not settled[a] for a, plan in zip(group, choice, strict=True)))
                if best is None or key < best[0]:
                    best = (key, trial)
            assert best is not None
            settled = best[1]
        return settled

    def _plans_without_solve(self, current: LocalResult) -> list[LocalResult]:
        """Agent ``current.agent``'s plans that need no solve: ``current``, its committed plan and
        braking to rest (each once)."""
        s, i = self.requests.settings, current.agent
        state, applied = self.requests.states[i], self.requests.applied
        made = [braking_plan(state, s)]
        if applied is not None:
            made.insert(0, fallback_plan(state, applied[0][i], applied[1][i], s))
        plans = [current]
        for x, u in made:
            if not any(np.array_equal(x, p.states) for p in plans):
                own = s.model.position(x[s.first_constrained_step:]).T.copy()
                plans.append(replace(current, own=own, states=x, inputs=u, success=False, fallback=True,
                                     solve_time=0.0))
        return plans

    def _select(
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
        while pending:
            batch = independent_run(pending, graph.neighbours)
            answers = self._replan_all(batch, graph, z, rho, repaired, [False] * len(batch), quick=True)
            for answer in answers:
                if answer.success and self._clear_of(repaired, answer, first, second):
                    repaired[answer.agent] = answer
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
            answers = self._replan_all(batch, graph, z, rho, repaired, [False] * len(batch), quick=True)
            for i, answer in zip(batch, answers, strict=True):
                if answer.success:
                    repaired[i] = answer
                    continue
                repaired[i] = replace(results[i], solve_time=answer.solve_time)
                pending.extend(j for pair in clashing if i in pair for j in pair
                               if j not in asked and j not in pending)
        return repaired

    def sequential(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, results: list[LocalResult],
        agents: list[int] | None = None,
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
        another; a batch costs the step's critical path only its slowest re-plan."""
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
            rescue = [True] * len(batch)  # every failed call may fly a rescue plan
            for i, answer in zip(batch, self._replan_all(batch, graph, z, rho, repaired, rescue), strict=True):
                repaired[i] = answer
            for i in batch:  # a retry goes after every re-plan queued so far, as in the one-by-one order
                if not repaired[i].success and i not in retried:
                    retried.add(i)
                    schedule.append(i)
        failures = [k for k in range(len(results)) if not repaired[k].success]
        self._replan_around(failures, graph, z, rho, repaired)
        return repaired

    def _replan_around(
        self, failures: list[int], graph: CouplingGraph, z: np.ndarray, rho: float, repaired: list[LocalResult],
    ) -> None:
        """Each neighbour of a ``failures`` agent whose plan comes within max(Delta_ij) + d_min of
        that agent's fallback re-plans against every current plan (``repaired``, updated in
        place), failure by failure, neighbour by neighbour. Consecutive re-plans of agents that
        hold no copy of each other are asked in one batch: a re-plan sees only its neighbours'
        plans, so the answers are those of asking them one after another."""
        d_min, largest = self.safety.settings.d_min, self.safety.largest_delta
        neighbours = graph.neighbours
        batch: list[int] = []

        def flush() -> None:
            for i, answer in zip(batch, self._replan_all(batch, graph, z, rho, repaired, [True] * len(batch)),
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

    def _replan_all(
        self, agents: list[int], graph: CouplingGraph, z: np.ndarray, rho: float, plans: list[LocalResult],
        rescue: list[bool], quick: bool = False,
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
            requests.append(self.requests.request(i, graph, own_z, rho, rho, False, pinned, rescue=last_attempt,
                                                  quick=quick))
        return self.solve(requests)


def _choices(
    options: list[list[LocalResult]], settled: list[LocalResult], group: list[int],
) -> Iterator[tuple[LocalResult, ...]]:
    """The combinations :meth:`Repair.settle` tries for ``group`` (``options`` per agent, the
    current plan first): all of them up to :data:`SETTLE_COMBINATIONS`, else each agent's options
    with the others on their current plans."""
    if np.prod([len(o) for o in options]) <= SETTLE_COMBINATIONS:
        yield from product(*options)
        return
    current = tuple(settled[a] for a in group)
    for k, row in enumerate(options):
        for plan in row:
            yield current[:k] + (plan,) + current[k + 1:]


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


def _agents_of(pairs: Sequence[tuple[int, int]]) -> list[int]:
    """The agents of ``pairs``, highest index first (the repair pass's order)."""
    return sorted({k for pair in pairs for k in pair}, reverse=True)


def colour_order(neighbours: Sequence[Sequence[int]]) -> list[int]:
    """Every agent, the classes of a greedy colouring of the coupling graph (``neighbours``) one
    after another (largest-degree-first colouring, :func:`networkx.greedy_color`), highest index first
    within a class: no two agents of a class are coupled, so :func:`independent_run` asks each class
    in one batch."""
    graph: nx.Graph[int] = nx.Graph()
    graph.add_nodes_from(range(len(neighbours)))
    graph.add_edges_from((i, j) for i, row in enumerate(neighbours) for j in row)
    colours = nx.greedy_color(graph, strategy="largest_first")
    return sorted(range(len(neighbours)), key=lambda i: (colours[i], -i))


class LevelSchedule:
    """A sequence of re-plans (agents, an agent again for a retry) asked in the fewest batches
    that give the answers of asking them one after another.

    An agent's re-plan reads only its neighbours' current plans. So it must follow the earlier
    re-plans of its neighbours and of itself, and nothing else: its level is one more than the
    highest level among those (0 without any). The levels are asked in turn, each in one batch in
    the sequence's order. Its batches are never more than the runs of mutually uncoupled agents
    (:func:`independent_run`) of the same sequence, which wait for every earlier re-plan. An
    agent appended after some levels were asked (a retry) goes after the re-plans appended before
    it, at a level not yet asked.
    """

    def __init__(self, neighbours: Sequence[Sequence[int]]) -> None:
        self._adjacent = [set(row) for row in neighbours]
        for i, row in enumerate(neighbours):
            for j in row:
                self._adjacent[j].add(i)
        self._latest: dict[int, int] = {}  # agent -> level of its latest re-plan in the sequence
        self._levels: list[list[int]] = []
        self._next = 0

    def append(self, agent: int) -> None:
        """Queue a re-plan of ``agent`` after every re-plan queued so far."""
        waits_for = [self._latest[j] for j in (agent, *self._adjacent[agent]) if j in self._latest]
        level = max(1 + max(waits_for, default=-1), self._next)
        self._latest[agent] = level
        if level == len(self._levels):
            self._levels.append([])
        self._levels[level].append(agent)

    def pop(self) -> list[int]:
        """The next level's agents, in the sequence's order ([] when every level was asked)."""
        if self._next == len(self._levels):
            return []
        self._next += 1
        return self._levels[self._next - 1]


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
