"""``solver.admm.independent_first``: the agents' own optima end a step whose pairs they keep apart.

Where those plans keep every pair that can meet d_min apart, the joint problem's pair constraints
are slack, so the plans are its optimum: checked against the centralised solver. Where they do
not, the step iterates exactly as it would have without the probe."""

from __future__ import annotations

import numpy as np
import pytest
from test_admm import approach_state

from conftest import recount_collisions
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import point_box_distance
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver
from swarmpc.solvers.admm.consensus import Carryover, carried_blocks
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.executors import SerialExecutor


class CountingExecutor(SerialExecutor):
    """The serial executor, counting the probes it hands on."""

    def __init__(self) -> None:
        super().__init__()
        self.probes = 0

    def solve(self, requests):
        self.probes += sum(bool(getattr(r, "independent", False)) for r in requests)
        return super().solve(requests)


def parting_pair():
    """Two agents just past each other on a swap, close enough to be coupled, heading apart."""
    scn = builtin_scenario("circle", agents=2, radius=2.0).with_updates(**{"limits.accel": 1.0})
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    direction = np.sign(goals[0, 0])
    states = np.array([[0.2 * direction, 0.2, 0.8 * direction, 0.0], [-0.2 * direction, -0.2, -0.8 * direction, 0.0]])
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    return scn, s, states, goals, guess


@pytest.mark.parametrize("local", ["qp", "ipopt"])
def test_own_optima_that_keep_apart_are_the_joint_optimum_in_one_round(local):
    scn, s, states, goals, guess = parting_pair()
    solver = ADMMSolver(s, 2, scn.delta_vector, ADMMConfig(local=local, independent_first=True))
    step = solver.plan(states, goals, guess)
    assert any(solver.neighbours(guess))  # the pair is coupled: without the probe, ADMM iterates
    assert step.admm_iterations == 1 and not step.repaired and step.failures == 0
    central = CentralizedSolver(s, 2, scn.delta_vector).plan(states, goals, guess)
    np.testing.assert_allclose(step.states, central.states, atol=1e-4)
    iterated = ADMMSolver(s, 2, scn.delta_vector, ADMMConfig(local=local)).plan(states, goals, guess)
    assert iterated.admm_iterations > 1
    np.testing.assert_allclose(iterated.states, central.states, atol=2e-3)  # consensus within tol = 1 mm


@pytest.mark.parametrize("name", ["paper-2d", "paper-3d"])
def test_a_probe_that_is_not_taken_leaves_the_step_as_it_was(name):
    """About to cross, the own optima run into each other: the step iterates, bit for bit as
    without the probe, whose round the agents' compute counts."""
    scn, states = approach_state(name, 26)
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    executor = CountingExecutor()
    probed = ADMMSolver(s, 4, scn.delta_vector, ADMMConfig(local="qp", independent_first=True), executor)
    step = probed.plan(states, goals, guess)
    plain = ADMMSolver(s, 4, scn.delta_vector, ADMMConfig(local="qp")).plan(states, goals, guess)
    assert executor.probes == 4 and step.admm_iterations > 1
    assert np.array_equal(step.states, plain.states) and np.array_equal(step.inputs, plain.inputs)
    assert step.primal_residuals == plain.primal_residuals and step.dual_residuals == plain.dual_residuals
    assert np.all(step.agent_times > 0) and step.critical_path > 0


@pytest.mark.parametrize("steps", [26, 28])
def test_the_next_step_probes_only_after_plans_that_kept_every_pair_clear_of_d_min(steps):
    """A pair at d_min in the plans flown is engaged, and the next step's own optima would run into
    each other again: no probe then. Recomputed from the plans: the closest pair's distance."""
    scn, states = approach_state("paper-2d", steps)
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    config = ADMMConfig(local="qp", independent_first=True)
    executor = CountingExecutor()
    solver = ADMMSolver(s, 4, scn.delta_vector, config, executor)
    step = solver.plan(states, goals, guess)
    positions = step.states[:, s.first_constrained_step:, : s.dim]
    closest = min(point_box_distance(p - q, scn.delta_vector)
                  for i in range(4) for j in range(i + 1, 4) for p, q in zip(positions[i], positions[j], strict=True))
    solver.plan(states, goals, guess)
    assert executor.probes == (8 if closest >= s.d_min + config.tol else 4)


def test_an_agent_remembers_the_probe_it_flew_as_its_last_plan():
    """Its fallback is its last flown plan shifted: a probe followed by a request from another state
    was flown (also when that request is the next step's probe), one followed by a request from
    the same state was not."""
    from swarmpc.solvers.admm.agent import LocalAgentFactory
    from swarmpc.solvers.admm.messages import StepRequests

    scn, s, states, goals, guess = parting_pair()
    config = ADMMConfig(local="qp", independent_first=True)
    agent = LocalAgentFactory.for_config(s, np.broadcast_to(scn.delta_vector / 2, (2, 2)), config)(0)
    z = np.zeros((2, s.dim, s.num_constrained))
    first = agent.solve(StepRequests(s, config, np.zeros((2, 2)), states, goals, guess).independent(0, z, 10.0))
    assert first.success and agent._plan is None  # not flown yet
    moved = first.states[1][None].repeat(2, axis=0)
    again = StepRequests(s, config, np.zeros((2, 2)), moved, goals, guess)
    agent.solve(again.independent(0, z, 10.0))
    assert agent._plan is not None and np.array_equal(agent._plan[0], first.states)  # flown: the new step moved on
    agent.solve(again.independent(0, z, 10.0))  # from the same state: the last probe was not flown
    assert np.array_equal(agent._plan[0], first.states)


def test_after_a_step_answered_by_own_optima_no_multiplier_is_carried():
    neighbours = [(1,), (0,)]
    kept = Carryover(np.zeros((2, 2, 3)), ((1,), (0,)), 10.0)
    flown = Carryover(np.zeros((2, 2, 3)), ((1,), (0,)), 10.0, multipliers=False)
    assert carried_blocks("stable", neighbours, kept) == [(True, True), (True, True)]
    for mode in ("stable", "always"):
        assert carried_blocks(mode, neighbours, flown) == [(False, False), (False, False)]


def test_a_scenario_that_leaves_the_key_out_probes_and_false_turns_it_off():
    scn = builtin_scenario("paper-2d")
    assert scn.solver.admm.independent_first is None
    assert ADMMConfig.from_options(scn.solver, scn.collision).independent_first
    off = scn.with_updates(**{"solver.admm.independent_first": False})
    assert not ADMMConfig.from_options(off.solver, off.collision).independent_first
    assert not ADMMConfig().independent_first  # the paper's algorithm


def test_the_paper_reproduction_runs_the_papers_iterations():
    from swarmpc.experiments.plan import RunSpec

    spec = RunSpec("paper-2d", 0.3, "hard", "admm", "auto")
    assert spec.build().solver.admm.independent_first is False


@pytest.mark.loop
def test_paper_2d_flies_the_same_closed_loop_in_fewer_iterations():
    plain = simulate(builtin_scenario("paper-2d").with_updates(**{"solver.admm.independent_first": False}))
    probed = simulate(builtin_scenario("paper-2d"))
    scn = probed.scenario
    assert recount_collisions(probed.states, scn.delta_vector)[0] == 0
    assert probed.summary["all_reached"]
    assert probed.summary["cost"] == pytest.approx(plain.summary["cost"], rel=1e-3)
    iterations = [sum(r.admm_iterations for r in run.records) for run in (probed, plain)]
    assert iterations[0] < 0.9 * iterations[1]
