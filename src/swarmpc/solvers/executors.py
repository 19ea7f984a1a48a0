"""Where the agents' local solves run: one interface, several executors.

An executor hosts one local agent per agent (a :class:`~swarmpc.solvers.admm.LocalAgent` of the
point ADMM, a :class:`~swarmpc.solvers.footprint_agent.FootprintLocalAgent` of the car ADMM; built
by a picklable factory, so a worker process can build its own) and runs a batch of requests,
returning results in request order. The ADMM algorithm never changes with the executor; only where
the work happens does.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import signal
import socket
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Protocol

import numpy as np

RAY_CONNECT_TIMEOUT_S = 10.0
"""How long joining a Ray cluster may take before the run is refused."""


class ExecutorError(RuntimeError):
    """An executor cannot start or lost its workers; the message is one line."""


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


def _serve_agents(connection: Connection, factory: AgentFactory, agent_ids: Sequence[int]) -> None:
    """Worker-process main loop: build this worker's agents once, then answer batches until told
    to stop (``None``). Exceptions travel back to the coordinator instead of killing the worker.

    Workers ignore SIGINT and SIGTERM: the coordinator receives them, finishes its step and stops
    the workers itself. A worker whose coordinator vanished (its pipe closed) exits quietly."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    agents = {i: factory(i) for i in agent_ids}
    connection.send(("ready", None))
    while True:
        try:
            batch = connection.recv()
        except (EOFError, OSError):
            return
        if batch is None:
            break
        try:
            connection.send(("ok", [agents[r.agent].solve(r) for r in batch]))
        except Exception as err:  # noqa: BLE001 - reported to the coordinator, which re-raises
            connection.send(("error", f"{type(err).__name__}: {err}"))
    connection.close()


def available_cores() -> int:
    """Cores this process may use (the affinity mask, not the machine's total)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class ProcessExecutor:
    """Agents spread over long-lived worker processes (agent ``i`` on worker ``i mod W``).

    Each worker builds its agents' CasADi solvers once at :meth:`start` and keeps them, so a
    batch costs only the pickling of requests and results; the workers' solves overlap.
    """

    def __init__(self, workers: int | None = None) -> None:
        self._workers = workers or available_cores()
        self._connections: list[Connection] = []
        self._processes: list[multiprocessing.process.BaseProcess] = []
        self._home: dict[int, int] = {}

    def start(self, factory: AgentFactory, agent_ids: Sequence[int]) -> None:
        self.close()
        ids = list(agent_ids)
        count = max(1, min(self._workers, len(ids)))
        context = multiprocessing.get_context("spawn")
        for worker in range(count):
            mine = ids[worker::count]
            parent, child = context.Pipe()
            process = context.Process(target=_serve_agents, args=(child, factory, mine), daemon=True)
            process.start()
            child.close()
            self._connections.append(parent)
            self._processes.append(process)
            self._home.update({i: worker for i in mine})
        for connection in self._connections:
            self._receive(connection)

    @staticmethod
    def _receive(connection: Connection) -> Any:
        try:
            kind, payload = connection.recv()
        except (EOFError, OSError):
            raise ExecutorError("--executor: a worker process ended unexpectedly") from None
        if kind == "error":
            raise RuntimeError(f"local solve failed in a worker process: {payload}")
        return payload

    def solve(self, requests: Sequence[Any]) -> list[Any]:
        batches: dict[int, list[Any]] = {}
        for request in requests:
            batches.setdefault(self._home[request.agent], []).append(request)
        for worker, batch in batches.items():
            try:
                self._connections[worker].send(batch)
            except OSError:  # the worker's end of the pipe closed: it died
                raise ExecutorError("--executor: a worker process ended unexpectedly") from None
        answers: dict[int, Any] = {}
        for worker, batch in batches.items():
            for request, result in zip(batch, self._receive(self._connections[worker]), strict=True):
                answers[request.agent] = result
        return [answers[r.agent] for r in requests]

    def close(self) -> None:
        for connection in self._connections:
            try:
                connection.send(None)
            except (BrokenPipeError, OSError):
                pass
        for process in self._processes:
            process.join(timeout=5)
            if process.is_alive():
                process.kill()  # workers ignore SIGTERM
                process.join(timeout=5)
        self._connections, self._processes, self._home = [], [], {}


STEP_FIELDS = ("state", "goal", "delta", "guess", "neighbour_states", "neighbour_plans")
"""Request fields that do not change between the ADMM iterations of one MPC step: a remote
executor sends each of them again only when it changed since it last went to that agent."""


def _step_fields(request: Any) -> tuple[str, ...]:
    """The :data:`STEP_FIELDS` a request has (a request type without them travels whole)."""
    return tuple(f for f in STEP_FIELDS if hasattr(request, f))


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if a is None or b is None:
        return a is b
    return np.array_equal(a, b)


class RequestDeduplicator:
    """The sending side: strips the step fields an agent's host already holds."""

    def __init__(self) -> None:
        self._sent: dict[int, dict[str, Any]] = {}

    def pack(self, request: Any) -> tuple[Any, tuple[str, ...]]:
        sent, names = self._sent.setdefault(request.agent, {}), _step_fields(request)
        kept = tuple(f for f in names if f in sent and _same(sent[f], getattr(request, f)))
        sent.update({f: getattr(request, f) for f in names})
        return dataclasses.replace(request, **{f: None for f in kept}), kept


class RequestCache:
    """The receiving side: restores the stripped step fields from what the agent last received."""

    def __init__(self) -> None:
        self._held: dict[int, dict[str, Any]] = {}

    def unpack(self, packed: tuple[Any, tuple[str, ...]]) -> Any:
        request, kept = packed
        held = self._held.setdefault(request.agent, {})
        request = dataclasses.replace(request, **{f: held[f] for f in kept})
        held.update({f: getattr(request, f) for f in _step_fields(request)})
        return request


class _RayAgentHost:
    """A Ray actor hosting one or more agents (the remote counterpart of a worker process)."""

    def __init__(self, factory: AgentFactory, agent_ids: Sequence[int]) -> None:
        self._agents = {i: factory(i) for i in agent_ids}
        self._cache = RequestCache()

    def solve(self, batch: Sequence[Any]) -> list[Any]:
        requests = [self._cache.unpack(packed) for packed in batch]
        return [self._agents[r.agent].solve(r) for r in requests]


class RayExecutor:
    """Agents as Ray actors: a local Ray started on demand, or an existing cluster by address.

    ``actors`` bounds how many actors host the agents (agent ``i`` on actor ``i mod A``);
    by default one actor per available CPU of the cluster. Actors are spread over the cluster's
    nodes; a request's step fields (:data:`STEP_FIELDS`) travel once per change, not once per
    ADMM iteration.
    """

    def __init__(self, address: str | None = None, actors: int | None = None) -> None:
        try:
            import ray
        except ImportError as err:
            raise ValueError("executor ray needs Ray: pip install 'swarmpc[ray]'") from err
        self._ray = ray
        self._address = address
        self._actors_wanted = actors
        self._actors: list[Any] = []
        self._home: dict[int, int] = {}
        self._started_ray = False
        self._outbox = RequestDeduplicator()

    def start(self, factory: AgentFactory, agent_ids: Sequence[int]) -> None:
        ray = self._ray
        if not ray.is_initialized():
            self._connect()
        ids = list(agent_ids)
        cpus = int(ray.cluster_resources().get("CPU", 1))
        count = max(1, min(self._actors_wanted or cpus, len(ids)))
        self._outbox = RequestDeduplicator()
        host = ray.remote(num_cpus=0, scheduling_strategy="SPREAD")(_RayAgentHost)
        self._actors = [host.remote(factory, ids[a::count]) for a in range(count)]
        self._home = {i: a for a in range(count) for i in ids[a::count]}

    def _connect(self) -> None:
        """Start a local Ray or join the cluster at the address, within a bounded time; every
        way this can fail is an :class:`ExecutorError` of one line."""
        if self._address not in (None, "auto", "local"):
            check_reachable(self._address, RAY_CONNECT_TIMEOUT_S)
            use_token_if_present()
        try:
            with _quiet_stderr(), _keep_sigterm_handler():
                self._ray.init(address=self._address, include_dashboard=False, log_to_driver=False,
                               configure_logging=False)
        except Exception as err:  # noqa: BLE001 - Ray raises many types for a failed connection
            where = f"--address: cannot join the Ray cluster at {self._address}" if self._address \
                else "--executor: cannot start a local Ray"
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ExecutorError(f"{where}: {first}") from None
        self._started_ray = True

    def solve(self, requests: Sequence[Any]) -> list[Any]:
        batches: dict[int, list[Any]] = {}
        for request in requests:
            batches.setdefault(self._home[request.agent], []).append(request)
        futures = {a: self._actors[a].solve.remote([self._outbox.pack(r) for r in batch])
                   for a, batch in batches.items()}
        answers: dict[int, Any] = {}
        for a, batch in batches.items():
            for request, result in zip(batch, self._ray.get(futures[a]), strict=True):
                answers[request.agent] = result
        return [answers[r.agent] for r in requests]

    def close(self) -> None:
        for actor in self._actors:
            self._ray.kill(actor)
        self._actors, self._home = [], {}
        if self._started_ray:
            self._ray.shutdown()
            self._started_ray = False


def use_token_if_present() -> None:
    """Authenticate like Ray's own command line: a stock ``ray start --head`` turns token
    authentication on when a token exists (``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH`` or
    ``~/.ray/auth_token``), but ``ray.init`` with an explicit address does not. With
    ``RAY_AUTH_MODE`` unset and a token present, this process uses it (a cluster without
    authentication ignores it)."""
    if os.environ.get("RAY_AUTH_MODE") is not None:
        return
    token_file = Path(os.environ.get("RAY_AUTH_TOKEN_PATH") or Path.home() / ".ray" / "auth_token")
    if os.environ.get("RAY_AUTH_TOKEN") or token_file.is_file():
        os.environ["RAY_AUTH_MODE"] = "token"
        try:  # Ray reads its configuration once; refresh it as Ray's own switch to token mode does
            # Config exists at run time but ray's stub of _raylet leaves it out
            from ray._raylet import Config  # type: ignore[attr-defined]

            Config.initialize("")
        except (ImportError, AttributeError):  # pragma: no cover - another Ray version
            pass


@contextmanager
def _keep_sigterm_handler() -> Iterator[None]:
    """Ray's core installs its own SIGTERM handler (a stack dump, then death); the caller's
    handler (the command line's: finish the step, write the run) is put back afterwards."""
    previous = signal.getsignal(signal.SIGTERM)
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


@contextmanager
def _quiet_stderr() -> Iterator[None]:
    """File descriptor 2 sent to /dev/null for the duration (C++ logging bypasses sys.stderr)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def check_reachable(address: str, timeout_s: float) -> None:
    """Raise :class:`ExecutorError` unless a TCP connection to ``host:port`` (optionally behind
    ``ray://``) opens within ``timeout_s``: Ray itself retries an unreachable address for minutes."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ExecutorError(f"--address: expected host:port, ray://host:port or auto, got {address!r}")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as err:
        reason = "timed out" if isinstance(err, TimeoutError) else (err.strerror or type(err).__name__)
        raise ExecutorError(f"--address: cannot reach the Ray cluster at {address} ({reason})") from None


EXECUTORS = ("serial", "thread", "process", "ray")


def make_executor(name: str, **options: Any) -> Executor:
    """An executor by name: one of :data:`EXECUTORS`."""
    if name == "serial":
        return SerialExecutor()
    if name == "thread":
        return ThreadExecutor(**options)
    if name == "process":
        return ProcessExecutor(**options)
    if name == "ray":
        return RayExecutor(**options)
    raise ValueError(f"unknown executor {name!r} (choose one of {', '.join(EXECUTORS)})")
