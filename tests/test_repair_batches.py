"""The repair pass asks runs of mutually uncoupled agents in one batch
(:func:`swarmpc.solvers.admm.schedule.independent_run`): the answers are those of the sequential
order, and the batch costs the critical path only its slowest re-plan. So do the re-plans around
a failed agent (``Repair._replan_around``), checked against the one-by-one loop with a stand-in
for the agents."""

from __future__ import annotations

from collections import deque
from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.solvers.admm.repair import Repair
from swarmpc.solvers.admm.schedule import LevelSchedule, colour_order, independent_run


@st.composite
def graphs_and_queues(draw):  # type: ignore[no-untyped-def]
    """A symmetric coupling graph on M agents and a queue of agents (repeats allowed: a retried
    agent is queued again)."""
    m = draw(st.integers(1, 12))
    pairs = draw(st.sets(st.tuples(st.integers(0, m - 1), st.integers(0, m - 1)).filter(lambda p: p[0] < p[1])))
    neighbours = [tuple(sorted({j for a, b in pairs for i, j in ((a, b), (b, a)) if i == k})) for k in range(m)]
    queue = draw(st.lists(st.integers(0, m - 1), min_size=1, max_size=20))
    return neighbours, queue


@given(graphs_and_queues())
def test_a_batch_is_the_longest_uncoupled_run_at_the_front_of_the_queue(case):  # type: ignore[no-untyped-def]
    neighbours, queue = case
    pending = deque(queue)
    batches = []
    while pending:
        batches.append(independent_run(pending, neighbours))
    assert [a for batch in batches for a in batch] == queue  # consecutive runs, in order, nothing lost
    for k, batch in enumerate(batches):
        assert batch and len(set(batch)) == len(batch)
        assert not any(j in neighbours[i] for i in batch for j in batch)
        if k + 1 < len(batches):  # the run ends only where the next agent could not join it
            nxt = batches[k + 1][0]
            assert nxt in batch or any(nxt in neighbours[i] for i in batch)


def test_a_path_graph_batches_every_other_agent():
    neighbours = [(1,), (0, 2), (1, 3), (2,)]
    pending = deque([3, 1, 2, 0])
    assert independent_run(pending, neighbours) == [3, 1]
    assert independent_run(pending, neighbours) == [2, 0]
    assert not pending


@given(graphs_and_queues())
def test_the_colour_order_batches_no_more_rounds_than_a_greedy_colouring_needs(case):  # type: ignore[no-untyped-def]
    """``repair_order: colour``: every agent once, and the batches of that order are independent
    sets, at most max degree + 1 of them (a greedy colouring's bound), each a whole colour class
    or more."""
    neighbours, _ = case
    order = colour_order(neighbours)
    assert sorted(order) == list(range(len(neighbours)))
    pending = deque(order)
    batches = []
    while pending:
        batches.append(independent_run(pending, neighbours))
    assert all(not any(j in neighbours[i] for i in batch for j in batch) for batch in batches)
    assert len(batches) <= max(len(n) for n in neighbours) + 1


def test_the_colour_order_asks_a_path_in_two_batches_where_the_index_order_needs_five():
    path = [(1,), (0, 2), (1, 3), (2, 4), (3,)]
    by_index = deque([4, 3, 2, 1, 0])
    assert [independent_run(by_index, path) for _ in range(5)] == [[4], [3], [2], [1], [0]]
    by_colour = deque(colour_order(path))
    assert [independent_run(by_colour, path), independent_run(by_colour, path)] == [[3, 1], [4, 2, 0]]
    assert not by_colour


class Agents:
    """A stand-in for the agents: a re-plan moves the agent towards its neighbours' plans and
    succeeds unless its neighbours' plans sum to a multiple of three (both deterministic)."""

    def __init__(self, neighbours: list[tuple[int, ...]]) -> None:
        self.neighbours = neighbours
        self.batches: list[list[int]] = []

    def answer(self, i: int, plans: list[SimpleNamespace]) -> SimpleNamespace:
        around = np.mean([plans[j].own for j in self.neighbours[i]], axis=0)
        own = 0.5 * plans[i].own + 0.5 * around + 0.01 * i
        success = int(round(1000 * float(around.sum()))) % 3 != 0
        return SimpleNamespace(own=own, success=success)

    def replan_all(self, agents, graph, z, rho, plans, rescue, quick=False):  # type: ignore[no-untyped-def]
        self.batches.append(list(agents))
        return [self.answer(i, plans) for i in agents]


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 100_000), m=st.integers(2, 9))
def test_re_plans_around_failures_in_batches_give_the_one_by_one_answers(seed, m):
    rng = np.random.default_rng(seed)
    coupled = np.triu(rng.random((m, m)) < 0.5, 1)
    neighbours = [tuple(int(j) for j in np.flatnonzero(coupled[i] | coupled[:, i])) for i in range(m)]
    plans = [SimpleNamespace(own=rng.uniform(0, 1.0, (2, 3)), success=bool(rng.random() < 0.7)) for _ in range(m)]
    failures = [k for k in range(m) if not plans[k].success]
    agents = Agents(neighbours)
    repair = Repair.__new__(Repair)
    repair.safety = SimpleNamespace(settings=SimpleNamespace(d_min=0.05), largest_delta=np.full((m, m), 0.3))
    repair.replan = agents.replan_all  # type: ignore[assignment]
    batched = list(plans)
    repair._replan_around(failures, SimpleNamespace(neighbours=neighbours), None, 0.0, batched)
    one_by_one = list(plans)  # the loop the batches stand in for
    for failed in failures:
        for i in neighbours[failed]:
            gap = np.max(np.abs(one_by_one[i].own - one_by_one[failed].own), axis=0).min()
            if one_by_one[i].success and gap < 0.3 + 0.05:
                one_by_one[i] = agents.answer(i, one_by_one)
    for a, b in zip(batched, one_by_one, strict=True):
        np.testing.assert_array_equal(a.own, b.own)
        assert a.success == b.success
    for batch in agents.batches:
        assert not any(j in neighbours[i] for i in batch for j in batch)


class Recording(Agents):
    """:class:`Agents` that also record, per call, whether it was asked as a last attempt (rescue)."""

    def __init__(self, neighbours: list[tuple[int, ...]]) -> None:
        super().__init__(neighbours)
        self.calls: list[tuple[int, bool]] = []

    def replan_all(self, agents, graph, z, rho, plans, rescue, quick=False):  # type: ignore[no-untyped-def]
        self.calls += list(zip(agents, rescue, strict=True))
        return super().replan_all(agents, graph, z, rho, plans, rescue, quick)


def one_by_one(neighbours, plans, order):  # type: ignore[no-untyped-def]
    """The repair pass's first attempts and retries asked one agent after another (the loop the
    batches stand in for): (plans, agents in the order asked)."""
    agents, plans, asked = Agents(neighbours), list(plans), []
    queue, retried = deque(i for i in order if neighbours[i]), set()
    while queue:
        i = queue.popleft()
        asked.append(i)
        plans[i] = agents.answer(i, plans)
        if not plans[i].success and i not in retried:
            retried.add(i)
            queue.append(i)
    return plans, asked


def pass_with_stand_ins(neighbours, plans, order):  # type: ignore[no-untyped-def]
    """The repair pass (``Repair.sequential``) over ``plans`` with the stand-in agents, without the
    re-plans around final failures (checked on their own above): (plans, the batches asked)."""
    m = len(neighbours)
    recording = Recording(neighbours)
    repair = Repair.__new__(Repair)
    repair.requests = SimpleNamespace(config=SimpleNamespace(repair_order="index"))
    repair.safety = SimpleNamespace(settings=SimpleNamespace(d_min=0.05), largest_delta=np.full((m, m), 0.3))
    repair.replan = recording.replan_all  # type: ignore[assignment]
    repair._replan_around = lambda *args: None  # type: ignore[method-assign]
    repaired = repair.sequential(SimpleNamespace(neighbours=neighbours), None, 0.0, list(plans), order)
    assert all(rescue for _, rescue in recording.calls)  # every call may rescue
    return repaired, recording.batches


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 100_000), m=st.integers(2, 12), density=st.sampled_from([0.2, 0.5, 0.8]))
def test_the_pass_asked_level_by_level_gives_the_one_by_one_answers(seed, m, density):
    """Every coupled agent is asked once and each one whose call failed once more after all first
    attempts; the batches are levels of uncoupled agents whose answers are exactly those of asking
    the agents one after another, in no more batches than the runs of uncoupled agents need."""
    rng = np.random.default_rng(seed)
    coupled = np.triu(rng.random((m, m)) < density, 1)
    neighbours = [tuple(int(j) for j in np.flatnonzero(coupled[i] | coupled[:, i])) for i in range(m)]
    plans = [SimpleNamespace(own=rng.uniform(0, 1.0, (2, 3)), success=True) for _ in range(m)]
    order = [int(i) for i in rng.permutation(m)]
    expected, asked = one_by_one(neighbours, plans, order)
    repaired, batches = pass_with_stand_ins(neighbours, plans, order)
    for a, b in zip(repaired, expected, strict=True):
        np.testing.assert_array_equal(a.own, b.own)
        assert a.success == b.success
    assert sorted(a for batch in batches for a in batch) == sorted(asked)
    assert all(not any(j in neighbours[i] for i in batch for j in batch) for batch in batches)
    runs, pending = 0, deque(asked)
    while pending:
        independent_run(pending, neighbours)
        runs += 1
    assert len(batches) <= runs


def test_two_coupled_pairs_take_two_levels_where_the_runs_take_three():
    """Pairs 0-1 and 2-3 in the index order 3, 2, 1, 0: the runs are [3], [2, 1], [0]; each agent
    waits only for its partner, so 3 and 1 go first and 2 and 0 after them."""
    neighbours = [(1,), (0,), (3,), (2,)]
    schedule = LevelSchedule(neighbours)
    for i in (3, 2, 1, 0):
        schedule.append(i)
    assert schedule.pop() == [3, 1]
    schedule.append(3)  # a retry of 3, queued after everything: after its partner 2
    assert schedule.pop() == [2, 0]
    assert schedule.pop() == [3]
    assert schedule.pop() == []
    pending = deque([3, 2, 1, 0])
    assert [independent_run(pending, neighbours) for _ in range(3)] == [[3], [2, 1], [0]]


def test_a_later_round_re_plans_only_the_agents_of_the_pairs_it_coupled():
    """After the full pass, pairs whose repaired plans conflict are coupled and only their agents
    re-plan (each against all its neighbours' plans): the rest keep the first pass's plans."""
    asked: list[list[int] | None] = []
    conflicts = [[(1, 4), (4, 6)], []]
    coupled: list[list[tuple[int, int]]] = []

    class Graph(SimpleNamespace):
        def coupled(self, pairs):  # type: ignore[no-untyped-def]
            coupled.append(list(pairs))
            return self

    repair = Repair.__new__(Repair)
    repair.requests = SimpleNamespace(config=SimpleNamespace(repair_rounds=3), states=np.zeros((8, 6)))
    repair.safety = SimpleNamespace(checked_pairs=lambda *args: None, missing=lambda *args: conflicts.pop(0),
                                    stranded_fallbacks=lambda results: [])
    results = [SimpleNamespace(agent=i, success=True, solve_time=0.001) for i in range(8)]

    def sequential(graph, z, rho, plans, agents=None):  # type: ignore[no-untyped-def]
        asked.append(agents)
        return [SimpleNamespace(**vars(p)) for p in plans]  # new answers

    repair.sequential = sequential  # type: ignore[method-assign]
    repair.replan = SimpleNamespace(spent=np.arange(8.0), failed=2)  # type: ignore[assignment]
    safe = repair.make_safe(Graph(candidates=None), None, 1.0, results, repair_all=True, stranded_check=False)
    assert asked == [None, [6, 4, 1]]  # the full pass, then the coupled pairs' agents, highest first
    assert coupled == [[(1, 4), (4, 6)]]
    # the passes' compute and failures are what the re-plans asked cost (the re-planner's tally)
    assert safe.agent_times.tolist() == list(range(8)) and safe.failures == 2
