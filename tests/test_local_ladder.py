"""Local problems sized to the neighbourhood: the slot ladder and what it must not change."""

from __future__ import annotations

import numpy as np
import pytest

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalSolverLadder


@pytest.fixture(scope="module")
def settings():
    return OCPSettings.from_scenario(builtin_scenario("paper-2d"))


@pytest.mark.parametrize(("copies", "slots"), [(0, 0), (1, 1), (2, 2), (3, 4), (4, 4), (5, 8), (9, 9)])
def test_slots_follow_a_doubling_ladder_capped_at_the_swarm(settings, copies, slots):
    assert LocalSolverLadder(settings, 9, False).slots_for(copies) == slots


def test_more_neighbours_than_slots_is_an_error(settings):
    with pytest.raises(ValueError, match="exceed"):
        LocalSolverLadder(settings, 3, False).slots_for(4)


def test_spread_out_swarm_builds_only_the_smallest_problem():
    scn = builtin_scenario("circle", agents=8, radius=6.0)
    s = OCPSettings.from_scenario(scn)
    solver = ADMMSolver(s, scn.num_agents, scn.delta_vector, ADMMConfig())
    states, goals = scn.start_states(), scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    plan = solver.plan(states, goals, guess)
    ladder = solver.executor._agents[0].nlp  # agents of one executor share one ladder
    assert set(ladder._built) == {0}
    assert plan.admm_iterations == 1 and not plan.fallback.any()
    solver.close()


def test_lone_agent_plan_does_not_depend_on_idle_slots():
    """An agent without neighbours solves the same problem with 0 slots or with inactive ones."""
    scn = builtin_scenario("circle", agents=2, radius=6.0)
    s = OCPSettings.from_scenario(scn)
    plans = []
    for force_slots in (False, True):
        solver = ADMMSolver(s, 2, scn.delta_vector, ADMMConfig())
        ladder = solver.executor._agents[0].nlp
        if force_slots:
            ladder.slots_for = lambda copies: ladder.max_slots  # type: ignore[method-assign]
        states, goals = scn.start_states(), scn.goal_states()
        guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
        plans.append(solver.plan(states, goals, guess))
        assert set(ladder._built) == ({1} if force_slots else {0})
        solver.close()
    assert np.allclose(plans[0].states, plans[1].states, atol=1e-5)
