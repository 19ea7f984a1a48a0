"""Re-plans against neighbours' plans held fixed: the one kind of call the safety passes make."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from swarmpc.solvers.admm.graph import CouplingGraph
from swarmpc.solvers.admm.messages import LocalRequest, LocalResult, StepRequests, compute_time

Solve = Callable[[list[LocalRequest]], list[LocalResult]]
"""The agents' answers to a batch of requests (timed on the step's critical path)."""


class Replanner:
    """Asks agents to re-plan against their neighbours' plans, held fixed, through ``solve``."""

    def __init__(self, requests: StepRequests, solve: Solve) -> None:
        self.requests = requests
        self.solve = solve
        self.spent = np.zeros(len(requests.states))
        """(M,) the agents' compute on every re-plan asked so far (retries and answers not taken
        count too: the agent spent it)."""
        self.failed = 0
        """Re-plans asked so far whose solves failed."""

    def __call__(
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
        answers = self.solve(requests)
        for answer in answers:
            self.spent[answer.agent] += compute_time(answer)
            self.failed += not answer.success
        return answers
