"""The executor contract: every executor gives the same plans as the serial one, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver
from swarmpc.solvers.executors import (
    ProcessExecutor,
    RayExecutor,
    SerialExecutor,
    ThreadExecutor,
    make_executor,
)


@pytest.fixture(scope="module")
def meeting_point():
    """paper-2d agents close to the centre, where the coupling constraints are active."""
    scn = builtin_scenario("paper-2d").with_updates(**{"solver.method": "centralized", "stop.max_steps": 30})
    states = simulate(scn).states[-1]
    settings = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, settings, "straight").guesses(states, goals, None)
    return scn, settings, states, goals, guess


def two_steps(executor, meeting_point):
    scn, settings, states, goals, guess = meeting_point
    solver = ADMMSolver(settings, scn.num_agents, scn.delta_vector, ADMMConfig(), executor)
    try:
        first = solver.plan(states, goals, guess)
        second = solver.plan(first.states[:, 1], goals, guess)  # warm-started step
    finally:
        solver.close()
    return first, second


@pytest.fixture(scope="module")
def serial_plans(meeting_point):
    return two_steps(SerialExecutor(), meeting_point)


def assert_same_plans(reference, plans) -> None:
    for a, b in zip(reference, plans, strict=True):
        assert a.admm_iterations == b.admm_iterations
        assert np.array_equal(a.states, b.states) and np.array_equal(a.inputs, b.inputs)
        assert a.primal_residuals == b.primal_residuals and a.dual_residuals == b.dual_residuals


def test_meeting_point_needs_several_iterations(serial_plans):
    assert serial_plans[0].admm_iterations > 1  # otherwise the comparison below proves little


@pytest.mark.parametrize("make", [lambda: ThreadExecutor(workers=2), lambda: ProcessExecutor(workers=2)],
                         ids=["thread", "process"])
def test_executor_matches_serial(make, serial_plans, meeting_point, monkeypatch):
    """The same plans as the serial executor; agents on a thread pool build their CasADi problems
    one at a time (CasADi's symbolic layer is not thread-safe)."""
    import threading

    from swarmpc.formulation import nlp

    built, nlpsol = [], nlp.ca.nlpsol

    def recording(*args, **kwargs):
        built.append((threading.current_thread() is threading.main_thread(), nlp.CASADI_CONSTRUCTION._is_owned()))
        return nlpsol(*args, **kwargs)

    monkeypatch.setattr(nlp.ca, "nlpsol", recording)
    executor = make()
    assert_same_plans(serial_plans, two_steps(executor, meeting_point))
    if isinstance(executor, ThreadExecutor):  # built in this process, some on the pool's threads
        assert any(not main for main, _ in built)
        assert all(owned for _, owned in built)


def test_ray_executor_matches_serial(serial_plans, meeting_point):
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'swarmpc[ray]')")
    assert_same_plans(serial_plans, two_steps(RayExecutor(actors=2), meeting_point))


def test_process_executor_reports_worker_errors():
    executor = ProcessExecutor(workers=1)
    executor.start(FailingAgent, [0])
    try:
        with pytest.raises(RuntimeError, match="worker process: ValueError: agent 0 refuses"):
            executor.solve([Request(agent=0)])
    finally:
        executor.close()


def test_unknown_executor_is_named():
    with pytest.raises(ValueError, match="unknown executor 'gpu'"):
        make_executor("gpu")


class Request:
    def __init__(self, agent: int) -> None:
        self.agent = agent


class FailingAgent:
    def __init__(self, agent: int) -> None:
        self.agent = agent

    def solve(self, request: Request) -> None:
        raise ValueError(f"agent {request.agent} refuses")


def test_step_fields_travel_once_and_arrive_intact():
    """What a remote host rebuilds equals what the coordinator sent, for any sequence of requests;
    a step field that did not change since the agent last received it is not sent again."""
    from dataclasses import dataclass

    from hypothesis import given
    from hypothesis import strategies as st

    from swarmpc.solvers.executors import STEP_FIELDS, RequestCache, RequestDeduplicator

    @dataclass(frozen=True)
    class Request:
        agent: int
        rho: float
        state: np.ndarray
        goal: np.ndarray
        delta: np.ndarray
        guess: np.ndarray
        neighbour_states: np.ndarray
        neighbour_plans: tuple[np.ndarray, np.ndarray] | None

    values = st.sampled_from([np.zeros(2), np.ones(2), np.arange(3.0)])

    @given(st.lists(st.tuples(st.integers(0, 2), values, values,
                              st.one_of(st.none(), st.tuples(values, values))), min_size=1, max_size=12))
    def check(sequence):
        outbox, inbox = RequestDeduplicator(), RequestCache()
        for agent, state, guess, plans in sequence:
            request = Request(agent, 1.0, state, np.ones(2), np.ones(2), guess, np.zeros((0, 2)), plans)
            packed, kept = outbox.pack(request)
            assert all(getattr(packed, f) is None for f in kept) and set(kept) <= set(STEP_FIELDS)
            rebuilt = inbox.unpack((packed, kept))
            for field in ("agent", "rho", *STEP_FIELDS):
                a, b = getattr(rebuilt, field), getattr(request, field)
                assert (a is None and b is None) or all(np.array_equal(x, y) for x, y in zip(
                    a if isinstance(a, tuple) else (a,), b if isinstance(b, tuple) else (b,), strict=True))
        again = outbox.pack(request)[1]
        assert set(again) == set(STEP_FIELDS)  # an identical repeat sends no step field

    check()


def test_problems_are_built_one_at_a_time():
    """Every CasADi builder an executor's thread may run holds the one construction lock, and the
    lock lets one build run at a time (the thread executor's own check is in the test above)."""
    import threading
    import time
    from itertools import pairwise

    from swarmpc.formulation import footprint_local, footprint_ocp, nlp, ocp
    from swarmpc.solvers import footprint_qp

    for builder in (ocp.build_local, ocp.build_centralized, footprint_local.build_footprint_local,
                    footprint_ocp.build_footprint_centralized, footprint_qp._Dynamics.__init__):
        assert hasattr(builder, "__wrapped__"), builder.__name__

    spans = []

    @nlp.builds_casadi
    def slow_build():
        began = time.perf_counter()
        time.sleep(0.05)
        spans.append((began, time.perf_counter()))

    threads = [threading.Thread(target=slow_build) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    spans.sort()
    assert all(later[0] >= earlier[1] for earlier, later in pairwise(spans))  # never two at once
