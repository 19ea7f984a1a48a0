"""The repair pass asks runs of mutually uncoupled agents in one batch
(:func:`swarmpc.solvers.admm.repair.independent_run`): the answers are those of the sequential
order, and the batch costs the critical path only its slowest re-plan."""

from __future__ import annotations

from collections import deque

from hypothesis import given
from hypothesis import strategies as st

from swarmpc.solvers.admm.repair import colour_order, independent_run


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
