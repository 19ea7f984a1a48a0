"""The last safety pass, which asks no agent: fallback agents still in conflict choose among the
plans they have."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from itertools import product

import numpy as np

from swarmpc.solvers.admm.graph import components
from swarmpc.solvers.admm.messages import LocalResult, StepRequests
from swarmpc.solvers.admm.safety import SafetyChecks
from swarmpc.solvers.base import braking_plan, fallback_plan

SETTLE_COMBINATIONS = 243
"""Most combinations of plans :class:`Settle` tries for one group of fallback agents (3^5);
a larger group chooses agent by agent."""


class Settle:
    """The settling pass of one MPC step (:meth:`__call__`)."""

    def __init__(self, requests: StepRequests, safety: SafetyChecks) -> None:
        self.requests = requests
        self.safety = safety

    def __call__(self, results: list[LocalResult]) -> list[LocalResult]:
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


def _choices(
    options: list[list[LocalResult]], settled: list[LocalResult], group: list[int],
) -> Iterator[tuple[LocalResult, ...]]:
    """The combinations :class:`Settle` tries for ``group`` (``options`` per agent, the
    current plan first): all of them up to :data:`SETTLE_COMBINATIONS`, else each agent's options
    with the others on their current plans."""
    if np.prod([len(o) for o in options]) <= SETTLE_COMBINATIONS:
        yield from product(*options)
        return
    current = tuple(settled[a] for a in group)
    for k, row in enumerate(options):
        for plan in row:
            yield current[:k] + (plan,) + current[k + 1:]
