"""Injected solver failures: the failing agent falls back safely, the run goes on, and the
failures are counted in summary.json and in the per-step record (steps.npz)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from conftest import load_folder, recount_collisions
from swarmpc.config import scenario_from_dict
from swarmpc.formulation.nlp import NLPSolution
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.simulation.disturbance import planner_bodies
from swarmpc.simulation.loop import make_solver, simulate
from swarmpc.simulation.results import write_run
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalAgent, LocalAgentFactory

# three agents whose straight paths cross near the origin within a few steps of each other
CROSSING = {
    "name": "crossing-3",
    "dim": 2,
    "delta": 0.25,
    "workspace": {"lower": [-2.5, -2.5], "upper": [2.5, 2.5]},
    "limits": {"accel": 2.0},
    "weights": {"Q": 1.0, "R": 0.5, "Qf": 5.0},  # brisker than the paper's weights: a short test
    "agents": [
        {"start": [-1.6, 0.1], "goal": [1.6, 0.1]},
        {"start": [0.1, -1.6], "goal": [0.1, 1.6]},
        {"start": [1.4, 1.4], "goal": [-1.4, -1.4]},
    ],
    "solver": {"initial_guess": "straight"},
    "stop": {"max_steps": 150, "goal_tolerance": 0.1},
}
# (MPC step, agent) pairs whose every local solve fails, including during the encounter
FAILING = {(3, 0), (4, 0), (12, 0), (13, 0), (14, 0), (12, 1), (15, 2), (16, 2), (20, 1), (21, 0)}


class _FlakyLadder:
    """An agent's ladder that, while ``failing``, solves for real, then reports failure: the agent
    must not use the answer."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.failing = False

    def solve(self, *args: Any, **kwargs: Any) -> NLPSolution:
        solution = self.inner.solve(*args, **kwargs)
        if not self.failing:
            return solution
        return dataclasses.replace(solution, success=False, status="Infeasible_Problem_Detected")

    def verified(self, *args: Any, **kwargs: Any) -> NLPSolution | None:
        return self.inner.verified(*args, **kwargs)


class _FlakyAgent:
    """A real LocalAgent whose solver fails on the chosen MPC steps."""

    def __init__(self, agent: LocalAgent, failing: set[tuple[int, int]]) -> None:
        self.ladder = _FlakyLadder(agent.nlp)
        self.inner = LocalAgent(agent.agent, agent.settings, self.ladder, agent.dynamic_copies, agent.seed_duals,
                                agent.rescue)
        self.failing = failing
        self.step = -1
        self.state: np.ndarray | None = None

    def solve(self, request: Any) -> Any:
        # a step's first request (its probe of the agent's own optimum, else its first iteration)
        # starts from a new measured state; the probe and the iterations of one step share it
        if request.new_step and (self.state is None or not np.array_equal(request.state, self.state)):
            self.step += 1
            self.state = request.state
        self.ladder.failing = (self.step, request.agent) in self.failing
        return self.inner.solve(request)


class FlakyAgents:
    """The agents ``factory`` makes, with fault injection on chosen (step, agent) pairs."""

    def __init__(self, factory: LocalAgentFactory, failing: set[tuple[int, int]]) -> None:
        self.factory = factory
        self.failing = failing

    def __call__(self, agent: int) -> _FlakyAgent:
        return _FlakyAgent(self.factory(agent), self.failing)


def flaky_solver(scn: Any, failing: set[tuple[int, int]]) -> ADMMSolver:
    """The scenario's ADMM solver (as ``make_solver`` builds it) with fault injection."""
    s, bodies = OCPSettings.from_scenario(scn), planner_bodies(scn)
    config = ADMMConfig.from_options(scn.solver, scn.collision)
    agents = FlakyAgents(LocalAgentFactory.for_config(s, bodies, config), failing)
    return ADMMSolver(s, scn.num_agents, bodies, config, agents=agents)


def _check_folder(folder, expect_failures: bool) -> tuple[dict, dict]:
    summary, arrays = load_folder(folder)
    collisions, ratio = recount_collisions(arrays["states"], arrays["delta"])
    assert collisions == 0 and ratio >= 1.0
    assert summary["collisions"] == 0
    with np.load(folder / "steps.npz") as steps:
        failures, fallback = steps["failures"], steps["fallback"]
    assert failures.shape[0] == summary["steps"] and fallback.shape == (summary["steps"], 3)
    assert summary["solver_failures"] == int(failures.sum())
    assert summary["fallback_agent_steps"] == int(fallback.sum())
    if expect_failures:
        assert summary["solver_failures"] > 0
    return summary, {"failures": failures, "fallback": fallback, **arrays}


@pytest.mark.loop
def test_admm_local_failures_fall_back_and_the_run_goes_on(tmp_path):
    scn = scenario_from_dict(CROSSING)
    solver = flaky_solver(scn, set(FAILING))
    try:
        result = simulate(scn, solver=solver)
    finally:
        solver.close()
    folder = write_run(result, tmp_path / "admm")
    summary, arrays = _check_folder(folder, expect_failures=True)
    assert summary["all_reached"]
    # every injected (step, agent) is in the per-step record, as a failure and as a fallback
    for step, agent in FAILING:
        assert arrays["failures"][step] >= 1
        assert arrays["fallback"][step, agent]
    # the fallback's first input still respects the acceleration limit
    assert np.abs(arrays["inputs"]).max() <= 2.0 + 1e-6


class _FailingCalls:
    """A compiled NLP that reports failure on chosen call numbers (0-based)."""

    def __init__(self, inner: Any, failing: set[int]) -> None:
        self._inner = inner
        self.failing = failing
        self.calls = 0

    def solve(self, *args: Any, **kwargs: Any) -> NLPSolution:
        solution = self._inner.solve(*args, **kwargs)
        self.calls += 1
        if self.calls - 1 in self.failing:
            return dataclasses.replace(solution, success=False, status="Maximum_Iterations_Exceeded")
        return solution

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def test_centralized_failures_fall_back_the_same_way(tmp_path):
    scn = scenario_from_dict({**CROSSING, "solver": {"method": "centralized", "initial_guess": "straight"}})
    solver = make_solver(scn, OCPSettings.from_scenario(scn))
    failing = {3, 4, 12, 13, 14, 15, 20}
    solver.nlp = _FailingCalls(solver.nlp, failing)
    result = simulate(scn, solver=solver)
    folder = write_run(result, tmp_path / "central")
    summary, arrays = _check_folder(folder, expect_failures=True)
    assert summary["all_reached"]
    assert summary["solver_failures"] == len(failing)
    assert sorted(np.flatnonzero(arrays["failures"])) == sorted(failing)
    assert arrays["fallback"][sorted(failing)].all()
    assert np.abs(arrays["inputs"]).max() <= 2.0 + 1e-6


@pytest.mark.parametrize("shifted", [True, False])
def test_fallback_plan_obeys_dynamics_and_limits(shifted):
    from swarmpc.model.dynamics import DoubleIntegrator
    from swarmpc.solvers.base import braking_plan, fallback_plan

    scn = scenario_from_dict(CROSSING)
    settings = OCPSettings.from_scenario(scn)
    model = DoubleIntegrator(2, scn.dt, "euler")
    state = np.array([0.0, 0.0, 1.0, -0.5])
    inputs = np.tile([[0.5, 0.2]], (scn.horizon, 1))
    previous = model.rollout(state, inputs)
    now = previous[1] + (np.array([0.01, -0.01, 0.02, 0.0]) if shifted else np.array([0.3, 0, 0, 0]))
    states, plan_inputs = fallback_plan(now, previous, inputs, settings)
    assert np.allclose(states[0], now)
    assert np.allclose(model.rollout(now, plan_inputs), states)
    assert np.abs(plan_inputs).max() <= 2.0 + 1e-12
    if shifted:
        assert np.allclose(plan_inputs[:-1], inputs[1:])
    else:
        assert np.allclose(states, braking_plan(now, settings)[0])
        assert np.linalg.norm(states[-1, 2:]) < 1e-12


def test_admm_capped_before_consensus_is_repaired_and_stays_safe(tmp_path):
    """ADMM capped at 2 iterations stops before consensus on every coupled step; the repair pass
    (agents re-plan in turn against the others' fixed plans) must still keep the crossing safe.
    The same run without the repair pass collides, so the repair is what keeps it safe."""
    from swarmpc.simulation.disturbance import planner_delta
    from swarmpc.solvers.admm import ADMMConfig, ADMMSolver

    scn = scenario_from_dict({**CROSSING, "solver": {**CROSSING["solver"], "max_iter": 2}})
    result = simulate(scn)
    repaired = np.array([r.repaired for r in result.records])
    assert all(r.admm_iterations <= 2 for r in result.records)
    assert repaired.any() and result.summary["admm_repairs"] == int(repaired.sum()) > 0
    collisions, ratio = recount_collisions(result.states, scn.delta_vector)
    assert collisions == 0 and ratio >= 1.0 and result.summary["collisions"] == 0
    assert result.summary["all_reached"]
    # the closest approach of any pair happens on a repaired step
    d = scn.dim
    positions = result.states[:, :, :d]
    closest = min(range(1, len(positions)), key=lambda k: min(
        np.max(np.abs(positions[k, i] - positions[k, j])) for i in range(3) for j in range(i + 1, 3)))
    assert repaired[closest - 1]
    # the per-step record in the run folder says the same
    folder = write_run(result, tmp_path / "capped")
    with np.load(folder / "steps.npz") as steps:
        assert np.array_equal(steps["repaired"], repaired)

    unrepaired = ADMMSolver(OCPSettings.from_scenario(scn), scn.num_agents, planner_delta(scn),
                            ADMMConfig(rho=scn.solver.rho, max_iter=2, tol=scn.solver.tol, repair=False))
    try:
        without = simulate(scn, solver=unrepaired)
    finally:
        unrepaired.close()
    assert without.summary["admm_repairs"] == 0
    assert recount_collisions(without.states, scn.delta_vector)[0] > 0
