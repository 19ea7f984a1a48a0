"""Local problems sized to the neighbourhood: the slot ladder and what it must not change."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.model.geometry import as_bodies
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.solvers.admm import (
    ADMMConfig,
    ADMMSolver,
    AnswerCache,
    LocalAgent,
    LocalAgentFactory,
    LocalRequest,
    LocalSolverLadder,
)
from swarmpc.solvers.admm.ladders import solve_warm_or_cold


class CountingLadder:
    """A ladder that counts the solves asked of it (an answer sent again asks none)."""

    def __init__(self, inner: LocalSolverLadder) -> None:
        self.inner = inner
        self.solves = 0

    def solve(self, *args, **kwargs):
        self.solves += 1
        return self.inner.solve(*args, **kwargs)

    def verified(self, *args, **kwargs):
        return self.inner.verified(*args, **kwargs)


class CountedAgents:
    """The agents ``factory`` makes, all solving through one :class:`CountingLadder` around the
    factory's shared ladder, each with a new ``cache``."""

    def __init__(self, factory: LocalAgentFactory, cache: type[AnswerCache] = AnswerCache) -> None:
        self.factory = factory
        self.cache = cache
        self.ladder = CountingLadder(factory.ladder)

    def __call__(self, i: int) -> LocalAgent:
        agent = self.factory(i)
        assert agent.nlp is self.factory.ladder  # one ladder for every agent: the count is the swarm's
        return LocalAgent(i, agent.settings, self.ladder, agent.dynamic_copies, agent.seed_duals, agent.rescue,
                          cache=self.cache())


class SolveLoneAgain(AnswerCache):
    """Never answers a lone problem from the cache: every call is solved."""

    def lone_answer(self, request):
        return None


def counted_solver(scn, s: OCPSettings, config: ADMMConfig, cache: type[AnswerCache] = AnswerCache):
    """An ADMM solver of ``scn`` whose agents count their solves, and the ladder that counts them."""
    bodies = as_bodies(scn.delta_vector, scn.num_agents)
    agents = CountedAgents(LocalAgentFactory.for_config(s, bodies, config), cache)
    return ADMMSolver(s, scn.num_agents, scn.delta_vector, config, agents=agents), agents.ladder


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
    assert ladder.built == {(0, 0)}
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
    real = LocalSolverLadder(settings, 2, False, warm_start=True).solver(1)
    calls, times = [], []

    class WarmFails:
        def solve(self, params, guess, lam_x=None, lam_g=None, fixed=None):
            calls.append(lam_g is not None)
            solution = real.solve(params, guess, fixed=fixed)
            times.append(solution.solve_time)
            if lam_g is None:
                return solution
            return replace(solution, success=False, status="Infeasible_Problem_Detected")

    scn = builtin_scenario("paper-2d")
    states, goals = scn.start_states(), scn.goal_states()
    d, K = settings.dim, settings.num_constrained
    params = {"x0": states[0], "goal": goals[0], "delta": scn.delta_vector, "rho": 10.0, "owner_weight": 5.0,
              "Z": np.zeros((d, K)), "Y": np.zeros((d, K)), "Z0": np.ones((d, K)), "Y0": np.zeros((d, K))}
    first = real.solve(params, {})
    retried = solve_warm_or_cold(WarmFails(), params, first.x, None, (first.lam_x, first.lam_g))
    assert calls == [True, False]
    assert retried.success and np.allclose(retried.x["X"], first.x["X"], atol=1e-6)
    assert retried.solve_time == pytest.approx(sum(times))


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
    ladder = CountingLadder(LocalSolverLadder(s, 3, dynamic_copies=True))
    agent = LocalAgent(0, s, ladder, dynamic_copies=True)
    state = scn.start_states()[0]
    first = agent.solve(_lone_request(scn, s, state, new_step=True))
    again = agent.solve(_lone_request(scn, s, state, new_step=False))
    assert first.success and ladder.solves == 1
    assert again.solve_time == 0.0 and np.array_equal(again.states, first.states)
    agent.solve(_lone_request(scn, s, state + 0.01, new_step=False))
    agent.solve(_lone_request(scn, s, state + 0.01, new_step=True))
    assert ladder.solves == 3


def test_skipping_unchanged_lone_problems_keeps_the_plans():
    """A step of a swarm where some agents are lone and others negotiate: the same plans whether
    lone agents re-solve every iteration or not, with fewer solves."""
    scn = builtin_scenario("random", agents=8, dim=3, seed=0)
    s = OCPSettings.from_scenario(scn)
    states, goals = scn.start_states(), scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    outcomes = []
    for cache in (AnswerCache, SolveLoneAgain):
        # a small coupling margin leaves some of the eight agents lone at the start
        solver, ladder = counted_solver(scn, s, ADMMConfig(coupling_margin=0.1), cache)
        plan = solver.plan(states, goals, guess)
        outcomes.append((plan, ladder.solves))
        solver.close()
    (skipped, fewer), (full, more) = outcomes
    assert full.admm_iterations > 1 and fewer < more
    assert skipped.admm_iterations == full.admm_iterations
    assert np.allclose(skipped.states, full.states, atol=1e-5)


def _coupled_request(scn, s, guess, z_shift: float, new_step: bool) -> LocalRequest:
    """Agent 0 coupled with agent 2 (they meet mid-way), consensus targets shifted by ``z_shift``.
    The last iteration's penalty is 0: no multiplier step, so the targets are the z given."""
    d, first = s.dim, s.first_constrained_step
    states = scn.start_states()
    return LocalRequest(
        agent=0, state=states[0], goal=scn.goal_states()[0], delta=scn.delta_vector, rho=10.0, rho_previous=0.0,
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
    ladder = CountingLadder(LocalSolverLadder(s, 3, dynamic_copies=False, warm_start=True))
    agent = LocalAgent(0, s, ladder, dynamic_copies=False)
    first = agent.solve(_coupled_request(scn, s, guess, 0.0, new_step=True))
    assert first.success and ladder.solves == 1
    near = agent.solve(_coupled_request(scn, s, guess, 5e-5, new_step=False))
    assert ladder.solves == 1 and near.solve_time == 0.0 and np.array_equal(near.states, first.states)
    exact = LocalAgentFactory(s, 3, dynamic_copies=False)(0).solve(_coupled_request(scn, s, guess, 5e-5, True))
    assert np.max(np.abs(exact.own - near.own)) <= 1e-3
    agent.solve(replace(_coupled_request(scn, s, guess, 5e-5, new_step=False), rho=20.0))
    assert ladder.solves == 2
    agent.solve(_coupled_request(scn, s, guess, 5e-4, new_step=False))
    assert ladder.solves == 3
    agent.solve(_coupled_request(scn, s, guess, 5e-4, new_step=True))
    assert ladder.solves == 4


def test_reused_answers_keep_the_step_plans_with_fewer_solves():
    """One ADMM step of a random swarm: answers reused within reuse_tol leave the plans within
    the consensus tolerance of solving every local problem, with fewer solves."""
    scn = builtin_scenario("random", agents=8, dim=3, seed=0)
    s = OCPSettings.from_scenario(scn)
    states, goals = scn.start_states(), scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    outcomes = []
    for reuse_tol in (1e-4, 0.0):
        solver, ladder = counted_solver(scn, s, ADMMConfig(reuse_tol=reuse_tol))
        outcomes.append((solver.plan(states, goals, guess), ladder.solves))
        solver.close()
    (reused, fewer), (full, more) = outcomes
    assert full.admm_iterations > 1 and fewer < more
    assert np.max(np.abs(reused.states[:, :, :3] - full.states[:, :, :3])) <= ADMMConfig().tol
