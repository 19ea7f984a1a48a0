"""The car ADMM on every executor: its agents answer plain-data messages, the plans are the same bit
for bit whichever executor runs the local solves, a scenario with cars takes any executor, and a
worker process that dies is reported as for point agents."""

from __future__ import annotations

import pickle
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from test_car_scenarios import _scenario
from test_footprint_admm import HEAD_ON, swarm_of
from test_footprint_ocp import car, point

from conftest import load_folder, run_cli
from swarmpc.config import scenario_from_dict
from swarmpc.formulation.footprint_local import consensus_block, slot_size
from swarmpc.formulation.footprint_ocp import FootprintSwarm
from swarmpc.solvers.base import PlanStep
from swarmpc.solvers.executors import (
    Executor,
    ExecutorError,
    ProcessExecutor,
    RayExecutor,
    RequestCache,
    RequestDeduplicator,
    SerialExecutor,
    ThreadExecutor,
)
from swarmpc.solvers.footprint_admm import FootprintADMMOptions, FootprintADMMSolver, plan_violations
from swarmpc.solvers.footprint_agent import FootprintAgentFactory, FootprintResult, FootprintSolve, FootprintStart
from swarmpc.solvers.footprint_central import straight_guess

SETUPS = {
    "ipopt-both": FootprintADMMOptions(local="ipopt", max_iter=10),
    "qp-later": FootprintADMMOptions(local="qp", pair_copies="later", max_iter=2),
}
"""Steps of several iterations then a repair, by IPOPT and by the QP local step (whose failed
calls go to IPOPT; with ``later`` copies the earlier car's repairs are solved in a problem it does
not hold)."""


def three_agents() -> FootprintSwarm:
    """Two cars swapping ends of a road (:data:`HEAD_ON`) and a point agent crossing it."""
    return swarm_of(car(horizon=12), car(horizon=12), point(0.15, horizon=12))


STARTS = np.array([*HEAD_ON[0], [0.0, -1.2, 0.0, 0.0]])
GOALS = np.array([*HEAD_ON[1], [0.0, 1.2, 0.0, 0.0]])


def two_steps(options: FootprintADMMOptions, executor: Executor) -> list[PlanStep]:
    """Two MPC steps of the three agents (the second warm-started from the first) on ``executor``."""
    swarm = three_agents()
    solver = FootprintADMMSolver(swarm, options, executor)
    try:
        guesses = [straight_guess(a, STARTS[i], GOALS[i]) for i, a in enumerate(swarm.agents)]
        first = solver.plan(list(STARTS), list(GOALS), guesses)
        second = solver.plan(list(first.states[:, 1]), list(GOALS), guesses)
    finally:
        executor.close()
    return [first, second]


def assert_same_steps(reference: list[PlanStep], steps: list[PlanStep]) -> None:
    for a, b in zip(reference, steps, strict=True):
        assert np.array_equal(a.states, b.states) and np.array_equal(a.inputs, b.inputs)
        assert a.admm_iterations == b.admm_iterations and a.repaired == b.repaired
        assert a.primal_residuals == b.primal_residuals and a.dual_residuals == b.dual_residuals
        assert np.array_equal(a.fallback, b.fallback) and a.failures == b.failures
        assert a.local_fallbacks == b.local_fallbacks and a.max_slack == b.max_slack
        assert a.predicted_cost == b.predicted_cost


@pytest.fixture(scope="module", params=list(SETUPS))
def serial_steps(request: pytest.FixtureRequest) -> tuple[str, list[PlanStep]]:
    return request.param, two_steps(SETUPS[request.param], SerialExecutor())


def test_the_serial_steps_are_worth_comparing(serial_steps: tuple[str, list[PlanStep]]) -> None:
    name, steps = serial_steps
    assert all(plan_violations(three_agents(), list(step.states)) == [] for step in steps)
    assert all((step.admm_iterations or 0) > 1 and step.repaired for step in steps)
    if name == "qp-later":
        assert sum(step.local_fallbacks for step in steps) > 0


@pytest.mark.parametrize("make", [lambda: ThreadExecutor(workers=2), lambda: ProcessExecutor(workers=2)],
                         ids=["thread", "process"])
def test_executor_matches_serial(make: Callable[[], Executor], serial_steps: tuple[str, list[PlanStep]]) -> None:
    name, reference = serial_steps
    assert_same_steps(reference, two_steps(SETUPS[name], make()))


@pytest.fixture(scope="module")
def ray_session() -> Iterator[None]:
    """One local Ray for the module's Ray tests (starting and stopping one costs about 6 s); an
    executor that finds Ray running uses it and leaves it running. Starting Ray on demand is
    tested in tests/test_executors.py."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'swarmpc[ray]')")
    ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield
    ray.shutdown()


@pytest.mark.usefixtures("ray_session")
def test_ray_executor_matches_serial(serial_steps: tuple[str, list[PlanStep]]) -> None:
    name, reference = serial_steps
    assert_same_steps(reference, two_steps(SETUPS[name], RayExecutor(actors=2)))


def local_params(swarm: FootprintSwarm, neighbours: tuple[int, ...], guesses: list[np.ndarray]) -> dict:
    """Agent 0's parameters with copies of ``neighbours``: every block drawn to its guess, no multipliers."""
    agents = swarm.agents
    own = consensus_block(agents[0], guesses[0])
    params = {"x0": STARTS[0], "goal": GOALS[0], "rho": np.array([[10.0]]), "Z": own, "Y": np.zeros_like(own)}
    for slot, j in enumerate(neighbours):
        params[f"Z{slot}"] = consensus_block(agents[j], guesses[j])
        params[f"Y{slot}"] = np.zeros_like(params[f"Z{slot}"])
        params[f"S{slot}"] = slot_size(agents[0], agents[j])
    return params


def test_an_agent_answers_in_plain_data_and_keeps_its_step_answer() -> None:
    """The factory pickles, and so does a reply (numpy arrays, no CasADi objects); a repair with
    other neighbours than the step's is solved in a problem of its own and leaves the step's answer."""
    swarm = three_agents()
    guesses = [straight_guess(a, STARTS[i], GOALS[i]) for i, a in enumerate(swarm.agents)]
    agent = pickle.loads(pickle.dumps(FootprintAgentFactory(swarm)))(0)
    assert agent.solve(FootprintStart(0, (1,), keep=False)).answer is None
    reply = agent.solve(FootprintSolve(0, (1,), local_params(swarm, (1,), guesses), guesses[0]))
    assert reply.success and reply.own and reply.answer is not None and len(reply.answer.copies) == 1
    assert isinstance(pickle.loads(pickle.dumps(reply)), FootprintResult)
    pinned = {f"C{slot}": consensus_block(swarm.agents[j], guesses[j]) for slot, j in enumerate((1, 2))}
    repair = agent.solve(FootprintSolve(0, (1, 2), local_params(swarm, (1, 2), guesses), guesses[0], pinned))
    assert not repair.own and repair.answer is not None and len(repair.answer.copies) == 2
    kept = agent.solve(FootprintStart(0, (1,), keep=True)).answer
    assert kept is not None
    assert np.array_equal(kept.states[:-1], reply.answer.states[1:])  # the step's answer, shifted


def test_a_scenario_with_cars_takes_any_executor() -> None:
    for kind in ("thread", "process", "ray"):
        scn = scenario_from_dict(_scenario(**{"solver.method": "admm", "executor": {"type": kind, "workers": 2}}))
        assert scn.has_cars and scn.executor.type == kind


def test_a_dead_worker_is_reported_in_one_line() -> None:
    executor = ProcessExecutor(workers=2)
    solver = FootprintADMMSolver(three_agents(), FootprintADMMOptions(), executor)
    try:
        executor._processes[1].kill()
        executor._processes[1].join(timeout=10)
        guesses = [straight_guess(a, STARTS[i], GOALS[i]) for i, a in enumerate(three_agents().agents)]
        with pytest.raises(ExecutorError, match="a worker process ended unexpectedly"):
            solver.plan(list(STARTS), list(GOALS), guesses)
    finally:
        executor.close()


def test_requests_without_step_fields_travel_whole() -> None:
    """The Ray executor's deduplication leaves a car agent's requests (no step fields) as they are."""
    outbox, inbox = RequestDeduplicator(), RequestCache()
    for request in (FootprintStart(0, (1,), True), FootprintSolve(0, (1,), {"x0": np.zeros(4)}, np.zeros((3, 4)))):
        packed = outbox.pack(request)
        unpacked = inbox.unpack(packed)
        assert packed[1] == () and type(unpacked) is type(request)
        assert all(getattr(unpacked, f) is getattr(request, f) for f in request.__dataclass_fields__)


@pytest.mark.loop
def test_a_car_run_on_worker_processes_flies_the_serial_run(tmp_path: Path) -> None:
    """``swarmpc run mixed --executor process`` writes the trajectory of the serial run, bit for bit."""
    arrays = []
    for executor in ("serial", "process"):
        out = tmp_path / executor
        extra = ["--workers", "2"] if executor == "process" else []
        done = run_cli("run", "mixed", "--method", "admm", "--max-steps", "4", "--executor", executor, *extra,
                       "--out", str(out), "--quiet")
        assert done.returncode == 0, done.stderr
        arrays.append(load_folder(out)[1])
    assert np.array_equal(arrays[0]["states"], arrays[1]["states"])
    assert np.array_equal(arrays[0]["inputs"], arrays[1]["inputs"])
