"""The order of a pass's re-plans: the fewest batches that give the answers of asking the agents
one after another.

An agent's re-plan reads only its neighbours' plans, so re-plans of agents no two of which are
coupled may be asked together; each batch costs a step's critical path only its slowest re-plan.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import networkx as nx


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
