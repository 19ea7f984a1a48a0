"""The batch runner behind bench, reproduce and the benchmark scripts (:mod:`swarmpc.batch`):
every task comes back once, a failure is one line that costs no other task, one job runs in this
process, and SIGINT/SIGTERM stop a pool promptly, keep what finished and leave no process behind.

The tasks are standard-library functions, so a spawned worker imports nothing but the runner."""

from __future__ import annotations

import math
import multiprocessing
import operator
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from swarmpc.batch import Finished, Task, error_line, run_batch


def test_every_task_comes_back_once_as_it_finishes():
    tasks = [Task(time.sleep, (0.8,)), *[Task(operator.mul, (k, k)) for k in range(1, 6)]]
    finished = list(run_batch(tasks, 2))
    assert sorted(f.index for f in finished) == list(range(6))
    assert all(f.ok and f.task is tasks[f.index] for f in finished)
    assert {f.index: f.value for f in finished if f.index} == {k: k * k for k in range(1, 6)}
    assert finished[-1].index == 0  # the slow one last: results come as they finish, not in order


def test_a_failing_task_is_one_line_and_the_others_complete():
    tasks = [Task(math.sqrt, (-1.0,)), Task(operator.add, (1, 2)), Task(lambda: 1),
             Task(os._exit, (3,)), Task(operator.truediv, (1, 0)), Task(operator.add, (2, 2))]
    by_index = {f.index: f for f in run_batch(tasks, 2)}
    assert len(by_index) == len(tasks)
    assert by_index[0].error == "ValueError: math domain error"
    assert by_index[2].error is not None and by_index[2].error.startswith("task not picklable: ")
    assert by_index[3].error == "WorkerDied: the worker process ended (exit status 3)"
    assert by_index[4].error == "ZeroDivisionError: division by zero"
    assert (by_index[1].value, by_index[5].value) == (3, 4) and by_index[1].ok and by_index[5].ok
    assert all("\n" not in (f.error or "") for f in by_index.values())
    assert not multiprocessing.active_children()


def test_one_job_runs_in_this_process_in_order():
    tasks = [Task(os.getpid), Task(lambda: "no pickling needed"), Task(math.sqrt, (-1.0,))]
    finished = list(run_batch(tasks, 1))
    assert [f.index for f in finished] == [0, 1, 2]
    assert finished[0].value == os.getpid() and finished[1].value == "no pickling needed"
    assert finished[2].error == "ValueError: math domain error"
    assert [f.value for f in run_batch([Task(os.getpid)], 4)] == [os.getpid()]  # one task: no pool
    with pytest.raises(ValueError, match="jobs"):
        run_batch(tasks, 0)


def test_workers_ignore_signals_and_can_be_renewed_after_each_task():
    tasks = [Task(signal.raise_signal, (signal.SIGTERM,)), Task(signal.raise_signal, (signal.SIGINT,)),
             *[Task(os.getpid) for _ in range(3)]]
    finished = list(run_batch(tasks, 2, max_tasks_per_worker=1))
    assert all(f.ok for f in finished)  # the workers survived their own SIGTERM and SIGINT
    pids = [f.value for f in finished if f.value is not None]
    assert len(set(pids)) == 3 and os.getpid() not in pids  # one fresh worker per task


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_stop_while_the_caller_handles_a_result_ends_the_batch_at_the_next_step(jobs):
    before = signal.getsignal(signal.SIGTERM)
    tasks = [Task(operator.add, (1, 1)), Task(time.sleep, (30,)), Task(time.sleep, (30,))]
    seen: list[Finished] = []
    started = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        for finished in run_batch(tasks, jobs):
            signal.raise_signal(signal.SIGTERM)  # recorded, not raised: this handling completes
            seen.append(finished)
    assert [f.value for f in seen] == [2]
    assert time.perf_counter() - started < 10.0
    assert not multiprocessing.active_children()  # killed and waited for
    assert signal.getsignal(signal.SIGTERM) == before


def test_a_stop_in_process_interrupts_the_running_task():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        list(run_batch([Task(signal.raise_signal, (signal.SIGTERM,)), Task(time.sleep, (30,))], 1))
    assert signal.getsignal(signal.SIGTERM) == before


def test_error_lines_name_the_type_and_the_first_line():
    assert error_line(RuntimeError("\nfirst\nsecond")) == "RuntimeError: first"
    assert error_line(KeyError()) == "KeyError"


SCRIPT = """
import os, subprocess, sys, time
from pathlib import Path

from swarmpc.batch import Task, run_batch


def nap(seconds, folder):
    pids = [os.getpid()]
    if seconds > 1:  # a long task starts a process of its own, which must go with its worker
        pids.append(subprocess.Popen(["sleep", str(seconds)]).pid)
    Path(folder, f"{os.getpid()}-{time.monotonic_ns()}.pids").write_text(" ".join(map(str, pids)))
    time.sleep(seconds)
    return seconds


if __name__ == "__main__":
    folder = sys.argv[1]
    kept = []
    try:
        for done in run_batch([Task(nap, (0.01, folder))] * 2 + [Task(nap, (60, folder))] * 3, 2):
            kept.append(done.index)
            print(f"finished {done.index}", flush=True)
    except KeyboardInterrupt:
        print(f"interrupted, kept {sorted(kept)}", flush=True)
        sys.exit(130)
"""


def _like_a_terminal() -> None:
    """Ctrl-C's default disposition in the child, as a shell in the foreground gives it: a suite
    started in the background (``cmd &`` in a script) hands its children SIGINT ignored, and a
    batch keeps ignoring a signal its caller ignores."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _alive(pid: int) -> bool:
    """Whether ``pid`` is a process that still runs (a zombie waiting for its reaper does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False
    return state not in ("Z", "X")


@pytest.mark.skipif(not Path("/proc").is_dir() or sys.platform != "linux", reason="reads /proc")
@pytest.mark.parametrize(("sig", "to_group"), [(signal.SIGINT, True), (signal.SIGTERM, False)],
                         ids=["ctrl-c-to-the-process-group", "sigterm-to-the-parent"])
def test_a_signalled_parent_exits_promptly_keeping_what_finished(tmp_path, sig, to_group):
    script = tmp_path / "batch_script.py"
    script.write_text(textwrap.dedent(SCRIPT))
    parent = subprocess.Popen([sys.executable, str(script), str(tmp_path)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, start_new_session=True,
                              preexec_fn=_like_a_terminal)
    try:
        deadline = time.monotonic() + 60
        while len([p for p in tmp_path.glob("*.pids") if " " in p.read_text()]) < 2:  # both long tasks run
            assert parent.poll() is None and time.monotonic() < deadline, parent.communicate()
            time.sleep(0.05)
        signalled = time.monotonic()
        if to_group:  # what a terminal does on Ctrl-C
            os.killpg(parent.pid, sig)
        else:
            os.kill(parent.pid, sig)
        out, err = parent.communicate(timeout=20)
    finally:
        if parent.poll() is None:
            os.killpg(parent.pid, signal.SIGKILL)
    assert time.monotonic() - signalled < 5.0
    assert parent.returncode == 130, err
    assert sorted(out.splitlines()) == ["finished 0", "finished 1", "interrupted, kept [0, 1]"]
    assert "Traceback" not in err and err.strip() == ""
    pids = [int(p) for f in tmp_path.glob("*.pids") for p in f.read_text().split()]
    assert len(pids) == 6
    assert not [pid for pid in pids if _alive(pid)]
