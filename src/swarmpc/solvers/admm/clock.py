"""The compute on an MPC step's critical path, measured per agent where the agent runs.

:class:`TimedAgent` makes each answer carry the wall time of the local step that produced it
(:class:`~swarmpc.solvers.admm.messages.TimedResult`); :class:`StepClock` adds up the step's
critical path from those and decides whether another ADMM iteration fits the deadline.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import fields
from typing import Any

from swarmpc.solvers.admm.messages import LocalRequest, LocalResult, TimedResult, compute_time
from swarmpc.solvers.executors import Executor

BATCH_WINDOW = 20
"""Batches of re-plans on a budget whose longest share of the critical path estimates the next
one's (:class:`BatchBudget`)."""

ESTIMATE_WINDOW = 3
"""Iterations whose largest share of the critical path estimates the next one's
(:meth:`StepClock.next_iteration`)."""


class TimedAgent:
    """An agent whose answers carry the wall time of its whole local step (:class:`TimedResult`).

    The critical path (:class:`StepClock`) needs each agent's compute per request, measured where
    the agent runs (a worker process under the process executor); executors pass answers through
    unopened, so the answer carries it. Every other attribute is the wrapped agent's, read and
    written through: code that reaches into an executor's agents meets the agent itself.
    """

    def __init__(self, agent: Any) -> None:
        object.__setattr__(self, "_inner", agent)

    def __getattr__(self, name: str) -> Any:
        if name == "_inner":  # not set yet (a copy or unpickling in progress): no recursion
            raise AttributeError(name)
        return getattr(self._inner, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._inner, name, value)

    _FIELDS = tuple(f.name for f in fields(LocalResult))
    """The fields an answer carries over (read once: ``fields`` walks the class on every call)."""

    def solve(self, request: LocalRequest) -> TimedResult:
        started = time.perf_counter()
        result = self._inner.solve(request)
        elapsed = time.perf_counter() - started
        return TimedResult(**{name: getattr(result, name) for name in self._FIELDS}, call_time=elapsed)


class TimedAgentFactory:
    """Picklable: the agents ``factory`` makes, each wrapped in a :class:`TimedAgent`."""

    def __init__(self, factory: Callable[[int], Any]) -> None:
        self.factory = factory

    def __call__(self, agent: int) -> TimedAgent:
        return TimedAgent(self.factory(agent))


class StepClock:
    """The compute on one MPC step's critical path, and the anytime stop at the step's deadline.

    The critical path is what the step would take with one core per agent and no transport
    latency: the coordinator's own work (everything in :meth:`ADMMSolver.plan` outside the agents'
    local steps) plus, for every batch of local steps it waits for, the slowest agent's local step
    (:attr:`TimedResult.call_time`; ``solve_time`` for answers of executors that do not ask the
    agents themselves). It is measured as the step's wall time less, per batch, the batch's wall
    time beyond its slowest agent: under the serial executor the other agents' steps, under a
    process executor the queueing and transport. The repair pass hands its agents over one at a
    time, so its sequential re-plans add up in full.

    Parameters
    ----------
    deadline : float or None
        Critical-path budget of the step [s]; None: no deadline.
    clock : callable
        The time in seconds (monotonic); the step starts when the clock object is made.
    reserve : float
        Critical-path seconds kept free of ADMM iterations for the safety passes that end a step
        stopped by the deadline (the solver passes what the last such passes took).
    """

    def __init__(self, deadline: float | None = None, clock: Callable[[], float] = time.perf_counter,
                 reserve: float = 0.0) -> None:
        self.deadline = deadline
        self.clock = clock
        self.reserve = reserve
        self.started = clock()
        self.stopped = False
        """True once :meth:`next_iteration` refused an iteration for the deadline."""
        self._overlap = 0.0
        self._iteration_began: float | None = None
        self._shares: deque[float] = deque(maxlen=ESTIMATE_WINDOW)

    def elapsed(self) -> tuple[float, float]:
        """(wall time, critical path) of the step so far [s], read at one instant."""
        wall = self.clock() - self.started
        return wall, wall - self._overlap

    def solve(self, executor: Executor, requests: Sequence[LocalRequest]) -> list[LocalResult]:
        """``executor``'s answers to ``requests``; the batch counts as its slowest agent's step."""
        began = self.clock()
        results = executor.solve(requests)
        batch = self.clock() - began
        slowest = max((compute_time(r) for r in results), default=0.0)
        self._overlap += max(batch - slowest, 0.0)
        return results

    def next_iteration(self) -> bool:
        """Whether to start another ADMM iteration. No (and :attr:`stopped`) when the critical path
        so far plus the estimate of the next iteration's share of it plus the :attr:`reserve` would
        exceed the deadline: the estimate is the largest share of the last
        :data:`ESTIMATE_WINDOW` iterations (an iteration's slowest agent varies from one iteration
        to the next). The first iteration always runs: without it there is no plan to make safe."""
        now = self.elapsed()[1]
        last, self._iteration_began = self._iteration_began, now
        if last is not None:
            self._shares.append(now - last)
        if last is None or self.deadline is None or now + max(self._shares) + self.reserve <= self.deadline:
            return True
        self.stopped = True
        return False

    def iteration_estimate(self) -> float:
        """The largest share of the critical path of the last :data:`ESTIMATE_WINDOW` iterations
        (0 before the second iteration began)."""
        return max(self._shares, default=0.0)


class BatchBudget:
    """Whether one more batch of re-plans fits the step's deadline (:meth:`allows`).

    A batch is estimated at the longest share of the critical path of the last
    :data:`BATCH_WINDOW` batches asked on a budget (``history``, kept by the solver across steps;
    a repair batch's calls run more certificate rounds than an iteration's and may fail and
    retry), and no shorter than the clock's estimate of an ADMM iteration (one local step per
    agent, as a batch is). ``margin`` is kept free after the last batch for the coordinator's work
    that follows it. Without a deadline every batch fits.
    """

    def __init__(self, clock: StepClock, history: deque[float] | None = None, margin: float = 0.0) -> None:
        self.clock = clock
        self.history: deque[float] = deque(maxlen=BATCH_WINDOW) if history is None else history
        self.margin = margin
        self.longest = max(clock.iteration_estimate(), max(self.history, default=0.0))
        self.refused = False
        """True once :meth:`allows` refused a batch."""
        self.closed_at: float | None = None
        """The critical path [s] when the last batch ended or was refused (None: none asked)."""
        self._began: float | None = None

    def close(self) -> float:
        """End the batch in progress, if any (its share joins the history); the critical path now."""
        now = self.clock.elapsed()[1]
        if self._began is not None:
            share = now - self._began
            self.history.append(share)
            self.longest = max(self.longest, share)
        self._began = None
        self.closed_at = now
        return now

    def allows(self) -> bool:
        """Whether to ask the next batch (which begins now): the critical path so far plus the
        estimate of a batch plus the margin stays within the deadline. Call it before each
        batch, and :meth:`close` after the last."""
        now = self.close()
        deadline = self.clock.deadline
        if deadline is not None and now + self.longest + self.margin > deadline:
            self.refused = True
            return False
        self._began = now
        return True
