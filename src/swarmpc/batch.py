"""Many independent tasks on a pool of worker processes: results as they finish, one line per
failed task, and a clean stop on Ctrl-C or SIGTERM.

``swarmpc bench``, ``swarmpc reproduce`` and the scripts under ``benchmarks/`` run their closed
loops through :func:`run_batch`; a task is typically "simulate this scenario and write (or score)
its run".

Why a pool of its own rather than ``concurrent.futures`` or ``multiprocessing.Pool``:

* Ctrl-C in a terminal reaches the whole foreground process group, so the workers of those pools
  die with a ``KeyboardInterrupt`` traceback each. Here a worker is born with SIGINT and SIGTERM
  blocked, ignores them from its first line on and runs in its own process group: the parent alone
  decides, kills its workers (and whatever they started) and only then raises
  ``KeyboardInterrupt``, so the caller keeps every result it was given and no process outlives
  the batch.
* A worker that dies (killed, out of memory, a crash in compiled code) breaks a
  ``ProcessPoolExecutor`` for every pending task and hangs a ``multiprocessing.Pool``; here only
  the task it was running fails, and a new worker takes its place.

Workers are started with the spawn method: CasADi (and the threads a process may hold) does not
survive ``fork``.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
from collections import deque
from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from types import FrameType
from typing import Any, Self

SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals a batch answers to in the parent and that its workers ignore."""

POLL_S = 0.1
"""Longest wait between two looks at a pending stop request [s]."""

STOP_GRACE_S = 5.0
"""How long a worker told to stop (at the end of a batch) may take before it is killed [s]."""


@dataclass(frozen=True)
class Task:
    """One unit of work: ``fn(*args)``. With more than one worker both are pickled, so ``fn`` must
    be a module-level function and ``args`` picklable."""

    fn: Callable[..., Any]
    args: tuple[Any, ...] = ()


@dataclass(frozen=True)
class Finished:
    """A task that ended: its return value, or the one-line error it ended with."""

    index: int
    """Position of the task in the list given to :func:`run_batch`."""
    task: Task
    value: Any = None
    error: str | None = None
    """``"TypeName: first line of the message"`` when the task raised (or its worker died)."""

    @property
    def ok(self) -> bool:
        return self.error is None


def error_line(error: BaseException) -> str:
    """``"TypeName: message"`` with the message's first non-empty line (a traceback is for the
    author of the task, a progress line or a report needs one line)."""
    message = next((line.strip() for line in str(error).splitlines() if line.strip()), "")
    return f"{type(error).__name__}: {message}" if message else type(error).__name__


def run_batch(
    tasks: Sequence[Task], jobs: int, *, max_tasks_per_worker: int | None = None
) -> Generator[Finished, None, None]:
    """Run every task, ``jobs`` at a time; yield each :class:`Finished` as soon as it is known.

    With ``jobs`` = 1 (or a single task) the tasks run one after another in this process, in list
    order, without a pool. Otherwise ``min(jobs, len(tasks))`` spawned worker processes take the
    tasks in list order; a worker is replaced by a fresh one after ``max_tasks_per_worker`` tasks
    (None: never), for tasks that should not share a process's leftovers.

    A task that raises an ``Exception`` yields its :func:`error_line` and the others go on. While
    the batch runs (from the first ``next`` to the last), SIGINT and SIGTERM in this process stop
    it: pending tasks are dropped, the workers are killed and waited for, and
    ``KeyboardInterrupt`` is raised from the iterator (in this process: from the running task). A
    stop that arrives while the caller handles a result (writes a report, say) takes effect at the
    next ``next``, so that handling is never cut in half. A signal the caller ignores stays
    ignored.

    Close the iterator when leaving it early (``contextlib.closing``): that kills the workers too.
    """
    if jobs < 1:
        raise ValueError(f"jobs: expected at least 1, got {jobs}")
    if max_tasks_per_worker is not None and max_tasks_per_worker < 1:
        raise ValueError(f"max_tasks_per_worker: expected at least 1 or None, got {max_tasks_per_worker}")
    tasks = list(tasks)
    workers = min(jobs, len(tasks))
    if workers <= 1:
        return _run_here(tasks)
    return _run_pool(tasks, workers, max_tasks_per_worker)


# ----------------------------------------------------------------------------- signals


@contextmanager
def quiet_children() -> Iterator[None]:
    """Processes started inside the block are born with SIGINT and SIGTERM blocked.

    Ctrl-C in a terminal reaches every process of the foreground group; a child that is still
    starting (importing, before it can ignore the signal) would die with a traceback. A blocked
    mask is inherited across fork and exec, so the child holds the signal until it decides what to
    do with it. In this thread the signals are held for the duration and delivered at its end.
    """
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - not POSIX
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class QuietStart:
    """An executor (``start``/``solve``/``close``) whose worker processes are started inside
    :func:`quiet_children`, for a caller that builds an executor without a command line's
    Ctrl-C handling around it. Ray keeps signals away from its own processes; wrap only an executor
    that starts plain processes."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def start(self, factory: Any, agent_ids: Any) -> None:
        with quiet_children():
            self.inner.start(factory, agent_ids)

    def solve(self, requests: Any) -> list[Any]:
        return self.inner.solve(requests)

    def close(self) -> None:
        self.inner.close()


class _StopRequests:
    """SIGINT and SIGTERM handlers for the duration of a batch (main thread only: elsewhere Python
    delivers no signals). The handler records the request, for :meth:`check` to act on, and while
    ``raising`` (a task runs in this process) also raises ``KeyboardInterrupt`` at once."""

    def __init__(self, raising: bool) -> None:
        self.raising = raising
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> Self:
        if threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                if signal.getsignal(sig) not in (signal.SIG_IGN, None):
                    self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        self.received = signum
        if self.raising:
            raise KeyboardInterrupt

    def check(self) -> None:
        if self.received is not None:
            raise KeyboardInterrupt


# ----------------------------------------------------------------------------- in this process


def _run_here(tasks: list[Task]) -> Generator[Finished, None, None]:
    """The tasks in list order in this process: a stop interrupts a running task at once, and one
    that arrives while the caller handles a result at the next ``next``."""
    with _StopRequests(raising=False) as stop:
        for index, task in enumerate(tasks):
            stop.raising = True
            stop.check()  # a stop recorded while the caller held the previous result
            try:
                finished = Finished(index, task, task.fn(*task.args))
            except Exception as err:  # noqa: BLE001 - one failed task must not lose the others
                finished = Finished(index, task, error=error_line(err))
            finally:
                stop.raising = False
            yield finished
        stop.check()


# ----------------------------------------------------------------------------- worker side


def _serve(connection: Connection) -> None:
    """A worker's main loop: run ``(fn, args)`` messages until ``None`` or until the parent is
    gone. Signals: ignored (the parent decides), then unblocked (:func:`quiet_children`), so what
    the worker starts inherits "ignored". Its own process group keeps a terminal's Ctrl-C away and
    lets the parent kill it together with everything it started."""
    for sig in SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, SIGNALS)
    try:
        os.setpgid(0, 0)
    except (AttributeError, OSError):  # pragma: no cover - not POSIX
        pass
    while True:
        try:
            message = connection.recv()
        except (EOFError, OSError):
            return
        except Exception as err:  # noqa: BLE001 - the task could not be unpickled here
            connection.send((False, error_line(err)))
            continue
        if message is None:
            return
        fn, args = message
        try:
            reply = (True, fn(*args))
        except Exception as err:  # noqa: BLE001 - reported to the parent as one line
            reply = (False, error_line(err))
        try:
            connection.send(reply)
        except (EOFError, OSError):
            return
        except Exception as err:  # noqa: BLE001 - the result could not be pickled
            connection.send((False, f"result not picklable: {error_line(err)}"))


# ----------------------------------------------------------------------------- parent side


class _Worker:
    """One worker process and the parent's end of its pipe."""

    def __init__(self, context: Any) -> None:
        parent_end, child_end = context.Pipe()
        # not daemonic: a task may start processes of its own (a process executor)
        self.process: BaseProcess = context.Process(target=_serve, args=(child_end,), name="swarmpc-batch")
        with quiet_children():
            self.process.start()
        child_end.close()
        self.connection: Connection = parent_end
        self.running: int | None = None
        self.done = 0
        self._reaped = False

    def hand(self, index: int, task: Task) -> str | None:
        """Send a task to this idle worker; None when sent, else the task's one-line error."""
        try:
            self.connection.send((task.fn, task.args))
        except (OSError, EOFError):
            return self.death()
        except Exception as err:  # noqa: BLE001 - fn or args cannot be pickled
            return f"task not picklable: {error_line(err)}"
        self.running = index
        return None

    def receive(self) -> Any:
        """The reply of the running task, None when the worker died before sending it."""
        try:
            return self.connection.recv() if self.connection.poll() else None
        except (EOFError, OSError):
            return None

    def death(self) -> str:
        """Why the worker is gone (one line); what it started goes with it."""
        self.kill()
        self.process.join()
        self._reaped = True
        code = self.process.exitcode
        how = (f"killed by {signal.Signals(-code).name}" if code is not None and code < 0
               else f"exit status {code}")
        return f"WorkerDied: the worker process ended ({how})"

    def stop(self) -> None:
        """Ask the worker to end once idle (the normal end of a batch, or its share done)."""
        try:
            self.connection.send(None)
        except (OSError, EOFError):
            pass

    def kill(self) -> None:
        """SIGKILL to the worker's process group (it ignores SIGTERM), so what it started goes too."""
        pid = self.process.pid
        if pid is None or self._reaped:
            return
        try:
            os.killpg(pid, signal.SIGKILL)  # unreaped, the worker's pid cannot name another group
        except (ProcessLookupError, PermissionError, AttributeError):
            pass  # not (yet) in a group of its own
        self.process.kill()

    def ended(self) -> bool:
        """Whether the process has ended (and is reaped)."""
        if not self._reaped and self.process.exitcode is not None:
            self._reaped = True
            self.connection.close()
        return self._reaped

    def reap(self, timeout: float) -> None:
        """Wait up to ``timeout`` for the worker to end, then kill it and wait."""
        self.process.join(timeout=timeout)
        if self.process.exitcode is None:
            self.kill()
            self.process.join()
        self._reaped = True
        self.connection.close()


class _Pool:
    """The parent's view of a batch: waiting tasks, busy and idle workers, retired ones."""

    def __init__(self, tasks: list[Task], size: int, max_tasks_per_worker: int | None) -> None:
        self.context = multiprocessing.get_context("spawn")
        self.tasks = tasks
        self.size = size
        self.max_tasks_per_worker = max_tasks_per_worker
        self.waiting = deque(range(len(tasks)))
        self.workers: list[_Worker] = []
        self.retired: list[_Worker] = []

    def hand_out(self) -> Iterator[Finished]:
        """Give every idle worker the next waiting task (starting workers up to ``size``); a task
        that cannot be handed over is finished at once with its error."""
        while self.waiting:
            idle = next((w for w in self.workers if w.running is None), None)
            if idle is None and len(self.workers) < self.size:
                idle = _Worker(self.context)
                self.workers.append(idle)
            if idle is None:
                return
            index = self.waiting.popleft()
            problem = idle.hand(index, self.tasks[index])
            if problem is not None:
                if not idle.process.is_alive():
                    self.workers.remove(idle)
                yield Finished(index, self.tasks[index], error=problem)

    def busy(self) -> list[_Worker]:
        return [w for w in self.workers if w.running is not None]

    def ready(self, busy: list[_Worker], timeout: float) -> list[_Worker]:
        """The busy workers with a reply (or an end) to collect, after waiting up to ``timeout``."""
        ready = set(wait([w.connection for w in busy] + [w.process.sentinel for w in busy], timeout=timeout))
        self.retired = [w for w in self.retired if not w.ended()]
        return [w for w in busy if w.connection in ready or w.process.sentinel in ready]

    def collect(self, worker: _Worker) -> Finished:
        """The task a ready worker ended; the worker retires when it died or did its share."""
        index, worker.running = worker.running, None
        assert index is not None
        worker.done += 1
        reply = worker.receive()
        if reply is None:
            self.workers.remove(worker)
            return Finished(index, self.tasks[index], error=worker.death())
        if self.max_tasks_per_worker is not None and worker.done >= self.max_tasks_per_worker:
            self.workers.remove(worker)
            worker.stop()
            self.retired.append(worker)
        ok, payload = reply
        return Finished(index, self.tasks[index], payload) if ok else Finished(index, self.tasks[index], error=payload)

    def shut_down(self, graceful: bool) -> None:
        """End every worker, waited for: told to stop after a complete batch, killed otherwise
        (a stop request, an error in the caller, an iterator closed early)."""
        everyone = self.workers + self.retired
        for worker in everyone:
            if graceful:
                worker.stop()
            else:
                worker.kill()
        for worker in everyone:
            worker.reap(timeout=STOP_GRACE_S if graceful else 0.0)
        self.workers, self.retired = [], []


def _run_pool(
    tasks: list[Task], size: int, max_tasks_per_worker: int | None
) -> Generator[Finished, None, None]:
    pool = _Pool(tasks, size, max_tasks_per_worker)
    complete = False
    with _StopRequests(raising=False) as stop:
        try:
            while True:
                stop.check()
                for finished in pool.hand_out():
                    yield finished
                    stop.check()
                busy = pool.busy()
                if not busy:
                    break
                for worker in pool.ready(busy, POLL_S):
                    yield pool.collect(worker)
                    stop.check()
            complete = True
        finally:
            pool.shut_down(graceful=complete)
