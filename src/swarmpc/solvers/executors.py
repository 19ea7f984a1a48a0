"""Where the agents' local solves run: one interface, several executors.

An executor hosts one :class:`~swarmpc.solvers.admm.LocalAgent` per agent (built by a picklable
factory, so a worker process can build its own) and runs a batch of requests, returning results in
request order. The ADMM algorithm never changes with the executor; only where the work happens does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol


class LocalAgentLike(Protocol):
    def solve(self, request: Any) -> Any: ...


AgentFactory = Callable[[int], LocalAgentLike]


class Executor(Protocol):
    """Runs each agent's local step; agents keep their private state between calls."""

    def start(self, factory: AgentFactory, agent_ids: Sequence[int]) -> None: ...

    def solve(self, requests: Sequence[Any]) -> list[Any]: ...

    def close(self) -> None: ...


class SerialExecutor:
    """All agents in this process, one after another (the default; the per-step time it
    measures is the sequential sum the paper reports)."""

    def __init__(self) -> None:
        self._agents: dict[int, LocalAgentLike] = {}

    def start(self, factory: AgentFactory, agent_ids: Sequence[int]) -> None:
        self._agents = {i: factory(i) for i in agent_ids}

    def solve(self, requests: Sequence[Any]) -> list[Any]:
        return [self._agents[r.agent].solve(r) for r in requests]

    def close(self) -> None:
        self._agents = {}


class ThreadExecutor(SerialExecutor):
    """Agents in this process, their solves submitted to a thread pool.

    CasADi's IPOPT calls hold the GIL for much of their time, so this is mainly a second,
    independent implementation of the executor contract rather than a speed-up.
    """

    def __init__(self, workers: int = 2) -> None:
        super().__init__()
        self._workers = workers

    def solve(self, requests: Sequence[Any]) -> list[Any]:
        with ThreadPoolExecutor(max_workers=self._workers) as pool:
            return list(pool.map(lambda r: self._agents[r.agent].solve(r), requests))


def make_executor(name: str, **options: Any) -> Executor:
    """An executor by name: ``serial`` or ``thread``."""
    if name == "serial":
        return SerialExecutor()
    if name == "thread":
        return ThreadExecutor(**options)
    raise ValueError(f"unknown executor {name!r} (choose serial or thread)")
