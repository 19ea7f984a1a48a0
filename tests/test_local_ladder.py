"""Local problems sized to the neighbourhood: the slot ladder and what it must not change."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalAgentFactory, LocalRequest, LocalSolverLadder
from swarmpc.solvers.executors import SerialExecutor


@pytest.fixture(scope="module")
def settings():
    return OCPSettings.from_scenario(builtin_scenario("paper-2d"))


@pytest.mark.parametrize(("copies", "slots"), [(0, 0), (1, 1), (2, 2), (3, 3), (5, 5), (9, 9)])
def test_slots_match_the_neighbour_count(settings, copies, slots):
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
    assert set(ladder._built) == {(0, 0)}
    assert plan.admm_iterations == 1 and not plan.fallback.any()
    solver.close()


def test_warm_started_multipliers_reach_the_same_solution_in_fewer_iterations():
    """The next ADMM iterate's problem differs only in its consensus targets; started from the
    last solution's multipliers IPOPT lands on the cold solve's solution, sooner."""
    scn = builtin_scenario("paper-2d")
    s = OCPSettings.from_scenario(scn)
    nlp = build_local(s, 1, warm_start=True)
    states, goals = scn.start_states(), scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    first, d, K = s.first_constrained_step, s.dim, s.num_constrained
    own, other = guess[0][first:, :d].T, guess[2][first:, :d].T  # diagonal neighbours meet mid-way
    params = {"x0": states[0], "goal": goals[0], "delta": scn.delta_vector, "rho": 10.0, "owner_weight": 5.0,
              "Z": own, "Y": np.zeros((d, K)), "Z0": other, "Y0": np.zeros((d, K))}
    start = {"X": guess[0].T, "C0": other}
    previous = nlp.solve(params, start)
    assert previous.success
    moved = {**params, "Z0": other + 0.2, "Y0": np.full((d, K), 0.5)}
    cold = nlp.solve(moved, previous.x_vec)
    warm = nlp.solve(moved, previous.x_vec, previous.lam_x, previous.lam_g)
    assert cold.success and warm.success
    assert np.max(np.abs(warm.x["X"] - cold.x["X"])) <= 1e-4
    assert warm.iterations < cold.iterations


def test_a_failed_warm_start_is_retried_cold(settings):
    """Multipliers carried from the last iterate can mislead IPOPT; the ladder then solves again
    without them and reports the time of both attempts."""
    ladder = LocalSolverLadder(settings, 2, False, warm_start=True)
    real = ladder.solver(1)
    calls = []

    class WarmFails:
        def solve(self, params, guess, lam_x=None, lam_g=None, fixed=None):
            calls.append(lam_g is not None)
            solution = real.solve(params, guess, fixed=fixed)
            return replace(solution, success=False, status="Infeasible_Problem_Detected") if lam_g is not None else solution

    ladder._built[(1, 0)] = WarmFails()
    scn = builtin_scenario("paper-2d")
    states, goals = scn.start_states(), scn.goal_states()
    d, K = settings.dim, settings.num_constrained
    params = {"x0": states[0], "goal": goals[0], "delta": scn.delta_vector, "rho": 10.0, "owner_weight": 5.0,
              "Z": np.zeros((d, K)), "Y": np.zeros((d, K)), "Z0": np.ones((d, K)), "Y0": np.zeros((d, K))}
    first = ladder.solve(params, {}, copies=1)
    retried = ladder.solve(params, first.x, copies=1, duals=(first.lam_x, first.lam_g))
    assert calls == [False, True, False]
    assert retried.success and np.allclose(retried.x["X"], first.x["X"], atol=1e-6)


def _lone_request(scn, s, state, new_step: bool) -> LocalRequest:
    d, K = s.dim, s.num_constrained
    goal = scn.goal_states()[0]
    guess = GuessProvider(scn, s, "straight").guesses(scn.start_states(), scn.goal_states(), None)[0]
    return LocalRequest(
        agent=0, state=state, goal=goal, delta=scn.delta_vector, rho=10.0, rho_previous=10.0, owner_weight=0.0,
        new_step=new_step, z_own=guess[s.first_constrained_step:, :d].T, neighbours=(),
        z_neighbours=np.zeros((0, d, K)), neighbour_states=np.zeros((0, 2 * d)), guess=guess,
    )


def test_unchanged_lone_problem_is_answered_without_a_solve():
    """Nobody couples with the agent: a later iteration of the same step poses the same problem
    (no consensus block, so no z or rho in it) and gets the last answer at no cost; a new state
    or a new step is solved again."""
    scn = builtin_scenario("paper-2d")
    s = OCPSettings.from_scenario(scn)
    agent = LocalAgentFactory(s, 3)(0)
    solves = []
    original = agent.nlp.solve
    agent.nlp.solve = lambda *a, **k: solves.append(1) or original(*a, **k)  # type: ignore[method-assign]
    state = scn.start_states()[0]
    first = agent.solve(_lone_request(scn, s, state, new_step=True))
    again = agent.solve(_lone_request(scn, s, state, new_step=False))
    assert first.success and len(solves) == 1
    assert again.solve_time == 0.0 and np.array_equal(again.states, first.states)
    agent.solve(_lone_request(scn, s, state + 0.01, new_step=False))
    agent.solve(_lone_request(scn, s, state + 0.01, new_step=True))
    assert len(solves) == 3


def test_skipping_unchanged_lone_problems_keeps_the_plans():
    """A step of a swarm where some agents are lone and others negotiate: the same plans whether
    lone agents re-solve every iteration or not, with fewer solves."""
    scn = builtin_scenario("random", agents=8, dim=3, seed=0)
    s = OCPSettings.from_scenario(scn)
    states, goals = scn.start_states(), scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    outcomes = []
    for skip in (True, False):
        executor = SerialExecutor()
        # a small coupling margin leaves some of the eight agents lone at the start
        solver = ADMMSolver(s, scn.num_agents, scn.delta_vector, ADMMConfig(coupling_margin=0.1), executor)
        solves = []
        ladder = executor._agents[0].nlp
        original = ladder.solve
        ladder.solve = lambda *a, **k: solves.append(1) or original(*a, **k)  # type: ignore[method-assign]
        if not skip:
            for agent in executor._agents.values():
                agent._unchanged_lone_problem = lambda request: False
        plan = solver.plan(states, goals, guess)
        outcomes.append((plan, len(solves)))
        solver.close()
    (skipped, fewer), (full, more) = outcomes
    assert full.admm_iterations > 1 and fewer < more
    assert skipped.admm_iterations == full.admm_iterations
    assert np.allclose(skipped.states, full.states, atol=1e-5)


def _coupled_request(scn, s, guess, z_shift: float, new_step: bool) -> LocalRequest:
    """Agent 0 coupled with agent 2 (they meet mid-way), consensus targets shifted by ``z_shift``."""
    d, first = s.dim, s.first_constrained_step
    states = scn.start_states()
    return LocalRequest(
        agent=0, state=states[0], goal=scn.goal_states()[0], delta=scn.delta_vector, rho=10.0, rho_previous=10.0,
        owner_weight=5.0, new_step=new_step, z_own=guess[0][first:, :d].T + z_shift, neighbours=(2,),
        z_neighbours=guess[2][first:, :d].T[None] + z_shift, neighbour_states=states[[2]], guess=guess[0],
        reuse_tol=1e-4,
    )


def test_agent_reuses_its_answer_only_while_its_targets_stay_within_reuse_tol():
    """Within a step, targets that moved less than reuse_tol since the last solve get the last
    answer back without a solve, and that answer is close to the exact one; a larger move, a new
    step or a changed penalty is solved."""
    scn = builtin_scenario("paper-2d")
    s = OCPSettings.from_scenario(scn)
    guess = GuessProvider(scn, s, "straight").guesses(scn.start_states(), scn.goal_states(), None)
    agent = LocalAgentFactory(s, 3, dynamic_copies=False, warm_start=True)(0)
    agent._multipliers_step = lambda request: None  # keep gamma at zero: the targets are the z given
    solves = []
    original = agent.nlp.solve
    agent.nlp.solve = lambda *a, **k: solves.append(1) or original(*a, **k)  # type: ignore[method-assign]
    first = agent.solve(_coupled_request(scn, s, guess, 0.0, new_step=True))
    assert first.success and len(solves) == 1
    near = agent.solve(_coupled_request(scn, s, guess, 5e-5, new_step=False))
    assert len(solves) == 1 and near.solve_time == 0.0 and np.array_equal(near.states, first.states)
    exact = LocalAgentFactory(s, 3, dynamic_copies=False)(0).solve(_coupled_request(scn, s, guess, 5e-5, True))
    assert np.max(np.abs(exact.own - near.own)) <= 1e-3
    agent.solve(replace(_coupled_request(scn, s, guess, 5e-5, new_step=False), rho=20.0))
    assert len(solves) == 2
    agent.solve(_coupled_request(scn, s, guess, 5e-4, new_step=False))
    assert len(solves) == 3
    agent.solve(_coupled_request(scn, s, guess, 5e-4, new_step=True))
    assert len(solves) == 4


def test_reused_answers_keep_the_step_plans_with_fewer_solves():
    """One ADMM step of a random swarm: answers reused within reuse_tol leave the plans within
    the consensus tolerance of solving every local problem, with fewer solves."""
    scn = builtin_scenario("random", agents=8, dim=3, seed=0)
    s = OCPSettings.from_scenario(scn)
    states, goals = scn.start_states(), scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    outcomes = []
    for reuse_tol in (1e-4, 0.0):
        executor = SerialExecutor()
        solver = ADMMSolver(s, scn.num_agents, scn.delta_vector, ADMMConfig(reuse_tol=reuse_tol), executor)
        solves = []
        ladder = executor._agents[0].nlp
        original = ladder.solve
        ladder.solve = lambda *a, **k: solves.append(1) or original(*a, **k)  # type: ignore[method-assign]
        outcomes.append((solver.plan(states, goals, guess), len(solves)))
        solver.close()
    (reused, fewer), (full, more) = outcomes
    assert full.admm_iterations > 1 and fewer < more
    assert np.max(np.abs(reused.states[:, :, :3] - full.states[:, :, :3])) <= ADMMConfig().tol
