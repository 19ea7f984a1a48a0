"""Consensus ADMM for swarms with cars: the local problem keeps a car d_min from a copy by the full
OBCA, far pairs are not coupled, violations are found by the exact distance and repaired, and one
MPC step of ADMM reaches the centralised optimum within 2 %; whole runs fly collision-free.

Every distance is recomputed with the exact rectangle distance of :mod:`swarmpc.model.footprint`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_footprint_ocp import D_MIN, car, point

from conftest import load_folder, run_cli
from swarmpc.formulation.footprint_local import NeighbourKind, build_footprint_local, consensus_block, slot_size
from swarmpc.formulation.footprint_ocp import FootprintAgent, FootprintSwarm
from swarmpc.model.footprint import rectangle_distance
from swarmpc.solvers.footprint_admm import (
    FootprintADMMOptions,
    FootprintADMMSolver,
    coupled_pairs,
    footprint_local_guess,
    plan_violations,
)
from swarmpc.solvers.footprint_central import FootprintCentralSolver, straight_guess

HEAD_ON = ([[-2.0, -0.1, 0.0, 0.0], [2.0, 0.1, np.pi, 0.0]], [[2.0, -0.1, 0.0, 0.0], [-2.0, 0.1, np.pi, 0.0]])
"""Two cars swap ends of a road, 0.2 m apart sideways: each must swerve round the other."""


def swarm_of(*agents: FootprintAgent) -> FootprintSwarm:
    return FootprintSwarm(tuple(agents))


def test_local_problem_keeps_a_car_clear_of_a_pinned_copy() -> None:
    own, other = car(horizon=15), car(horizon=15)
    problem = build_footprint_local(own, (NeighbourKind.of(other),))
    start, goal = np.array([-2.0, 0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0, 0.0])
    parked = np.tile(np.array([[0.0], [0.05], [0.3]]), (1, 15))  # a car parked across the way
    guess = straight_guess(own, start, goal)
    point0 = footprint_local_guess(own, guess, [other], [parked])
    params = {"x0": start, "goal": goal, "rho": np.array([[1.0]]), "Z": consensus_block(own, guess),
              "Y": np.zeros((3, 15)), "Z0": parked, "Y0": np.zeros((3, 15)), "S0": slot_size(own, other)}
    solution = problem.solve(params, point0, fixed={"C0": parked})
    assert solution.success
    poses = own.poses(solution.x["X"].T[1:])
    gaps = rectangle_distance(poses, own.size, parked.T, other.size)
    assert gaps.min() >= D_MIN - 1e-6
    assert np.allclose(solution.x["C0"], parked)


def test_far_agents_are_not_coupled_and_near_ones_are() -> None:
    swarm = swarm_of(car(horizon=5), car(horizon=5), point(0.15, horizon=5))
    states = np.array([[-2.5, 0.0, 0.0, 0.0], [-1.5, 0.0, 0.0, 0.0], [2.8, 1.8, 0.0, 0.0]])
    assert coupled_pairs(swarm, states, 0.1) == [(0, 1)]
    assert coupled_pairs(swarm, states, 100.0) == [(0, 1), (0, 2), (1, 2)]


def test_far_pairs_cannot_touch_within_the_horizon() -> None:
    """An uncoupled pair stays apart whatever its agents do: full throttle, any steering."""
    swarm = swarm_of(car(horizon=6), car(horizon=6))
    states = np.array([[-2.9, -1.8, 0.6, 1.0], [2.9, 1.8, 0.6 - np.pi, 1.0]])
    assert coupled_pairs(swarm, states, 0.0) == []
    rng = np.random.default_rng(0)
    for _ in range(20):
        flown = []
        for i, agent in enumerate(swarm.agents):
            model, s = agent.settings.model, agent.settings
            lower, upper = model.input_bounds(s.accel, s.speed)
            inputs = rng.uniform(lower, upper, size=(s.horizon, 2))
            flown.append(agent.poses(model.rollout(states[i], inputs)))
        assert rectangle_distance(flown[0], swarm.agents[0].size, flown[1], swarm.agents[1].size).min() > D_MIN


def test_plan_violations_finds_an_overlapping_pair_only() -> None:
    swarm = swarm_of(car(horizon=4), car(horizon=4), point(0.15, horizon=4))
    apart = [np.tile([x, 0.0, 0.0, 0.0], (5, 1)) for x in (-2.0, 0.0, 2.0)]
    assert plan_violations(swarm, apart) == []
    close = [apart[0], np.tile([-1.9, 0.3, 0.0, 0.0], (5, 1)), apart[2]]
    assert plan_violations(swarm, close) == [(0, 1)]


def _first_step(solver: FootprintADMMSolver | FootprintCentralSolver, swarm: FootprintSwarm) -> list[np.ndarray]:
    starts, goals = (np.array(x, float) for x in HEAD_ON)
    guesses = [straight_guess(a, starts[i], goals[i]) for i, a in enumerate(swarm.agents)]
    if isinstance(solver, FootprintADMMSolver):
        step = solver.plan(list(starts), list(goals), guesses)
        return [step.states, step.inputs, np.array(step.predicted_cost)]
    outcome = solver.plan(list(starts), list(goals), guesses)
    return [np.array([p.states for p in outcome.plans]), np.array([p.inputs for p in outcome.plans]),
            np.array(outcome.stats.cost)]


def _plan_cost(swarm: FootprintSwarm, states: np.ndarray, inputs: np.ndarray) -> float:
    goals = np.array(HEAD_ON[1], float)
    total = 0.0
    for i, agent in enumerate(swarm.agents):
        s, err = agent.settings, states[i] - goals[i]
        total += float(np.einsum("ki,ij,kj->", err[:-1], s.Q, err[:-1]) + np.einsum("ki,ij,kj->", inputs[i], s.R,
                                                                                         inputs[i]))
        total += float(err[-1] @ s.Qf @ err[-1])
    return total


@pytest.mark.parametrize("local,pair_copies", [("ipopt", "both"), ("qp", "both"), ("ipopt", "later")])
def test_one_admm_step_matches_the_centralised_plan(local: str, pair_copies: str) -> None:
    swarm = swarm_of(car(horizon=15), car(horizon=15))
    options = FootprintADMMOptions(max_iter=200, local=local, pair_copies=pair_copies)
    admm_states, admm_inputs, _ = _first_step(FootprintADMMSolver(swarm, options), swarm)
    central_states, central_inputs, _ = _first_step(FootprintCentralSolver(swarm), swarm)
    assert plan_violations(swarm, list(admm_states)) == []
    for i, agent in enumerate(swarm.agents):  # each plan flies the car's own dynamics
        assert np.allclose(agent.settings.model.rollout(admm_states[i][0], admm_inputs[i]), admm_states[i], atol=1e-6)
    admm_cost = _plan_cost(swarm, admm_states, admm_inputs)
    central_cost = _plan_cost(swarm, central_states, central_inputs)
    assert admm_cost <= 1.02 * central_cost


@pytest.mark.parametrize("local,pair_copies", [("ipopt", "both"), ("qp", "both"), ("ipopt", "later"),
                                               ("qp", "later")])
def test_a_step_cut_short_is_repaired_to_a_safe_plan(local: str, pair_copies: str) -> None:
    """Two iterations do not agree; the repair still leaves no pair closer than d_min (with
    ``pair_copies`` "later" the earlier car holds no copy, and its repair is asked against both)."""
    swarm = swarm_of(car(horizon=15), car(horizon=15))
    step = FootprintADMMSolver(swarm, FootprintADMMOptions(max_iter=2, local=local, pair_copies=pair_copies))
    starts, goals = (np.array(x, float) for x in HEAD_ON)
    result = step.plan(list(starts), list(goals), [straight_guess(a, starts[i], goals[i])
                                                   for i, a in enumerate(swarm.agents)])
    assert result.admm_iterations == 2 and result.repaired
    assert plan_violations(swarm, list(result.states)) == []
    gaps = rectangle_distance(swarm.agents[0].poses(result.states[0][1:]), swarm.agents[0].size,
                              swarm.agents[1].poses(result.states[1][1:]), swarm.agents[1].size)
    assert gaps.min() >= D_MIN - 1e-6


@pytest.mark.loop
@pytest.mark.parametrize("local", ["ipopt", "qp"])
def test_mixed_swarm_by_admm_reaches_every_goal_without_collision(tmp_path: Path, local: str) -> None:
    out = tmp_path / "run"
    done = run_cli("run", "mixed", "--method", "admm", "--local", local, "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    summary, arrays = load_folder(out)
    assert summary["method"] == "admm" and summary["all_reached"] and summary["collisions"] == 0
    poses, sizes = arrays["poses"], arrays["footprints"]
    least = min(float(rectangle_distance(poses[:, i], sizes[i], poses[:, j], sizes[j], signed=True).min())
                for i in range(poses.shape[1]) for j in range(i + 1, poses.shape[1]))
    assert least > 0.0


def _block_sums(solver: FootprintADMMSolver) -> list[float]:
    """Per block, the largest entry of the sum of its holders' multipliers (own and copies)."""
    sums = []
    for j, state in enumerate(solver._agents):
        assert state is not None
        total = np.zeros_like(solver._z[j]) if state.own_y is None else state.own_y.copy()  # type: ignore[index]
        for other in solver._agents:
            assert other is not None
            if j in other.copy_y:
                total += other.copy_y[j]
        sums.append(float(np.max(np.abs(total))))
    return sums


def test_multipliers_carried_to_a_new_step_keep_summing_to_zero_per_block() -> None:
    """Three cars in a row, 0-1 and 1-2 coupled; then 1-2 no longer is. Car 0 keeps its
    neighbours, car 1 does not: car 0 must not keep its multiplier of car 1's block alone
    (a lone multiplier is a constant force on car 1)."""
    swarm = swarm_of(car(horizon=6), car(horizon=6), car(horizon=6))
    states = np.array([[-2.2, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [2.2, 0.0, 0.0, 0.0]])
    goals = states + np.array([0.5, 0.0, 0.0, 0.0])
    solver = FootprintADMMSolver(swarm, FootprintADMMOptions(max_iter=5))
    assert coupled_pairs(swarm, states, 0.5) == [(0, 1), (1, 2)]
    solver.plan(list(states), list(goals), [straight_guess(a, states[i], goals[i]) for i, a in enumerate(swarm.agents)])
    assert max(_block_sums(solver)) < 1e-9
    assert any(state is not None and state.copy_y for state in solver._agents)  # something to carry
    solver._start_agents([(0, 1)])
    assert max(_block_sums(solver)) < 1e-9
    carried = solver._agents[0]
    assert carried is not None and carried.neighbours == (1,) and 1 not in carried.copy_y


def test_with_later_pair_copies_only_the_later_car_of_a_pair_holds_a_copy() -> None:
    """Three cars in a row, 0-1 and 1-2 coupled: with ``pair_copies`` "later" car 0 holds no copy,
    car 1 a copy of car 0 and car 2 one of car 1; each block's multipliers still sum to zero (the
    consensus of a block is the weighted mean of its holders, the copy included)."""
    swarm = swarm_of(car(horizon=6), car(horizon=6), car(horizon=6))
    states = np.array([[-2.2, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [2.2, 0.0, 0.0, 0.0]])
    goals = states + np.array([0.5, 0.0, 0.0, 0.0])
    solver = FootprintADMMSolver(swarm, FootprintADMMOptions(max_iter=5, pair_copies="later"))
    solver.plan(list(states), list(goals), [straight_guess(a, states[i], goals[i]) for i, a in enumerate(swarm.agents)])
    assert [state.neighbours for state in solver._agents if state is not None] == [(), (0,), (1,)]
    assert max(_block_sums(solver)) < 1e-9


def test_owner_weighted_consensus_leans_to_the_owner_and_keeps_multipliers_summing_to_zero() -> None:
    """With owner weight w the consensus of a block is the penalty-weighted mean of its holders:
    after one iteration z lies w times closer to the owner's block than to the copy, and the
    block's multipliers (w rho (v - z) and rho (c - z)) still sum to zero."""
    swarm = swarm_of(car(horizon=15), car(horizon=15))
    weight, rho = 4.0, 10.0
    solver = FootprintADMMSolver(swarm, FootprintADMMOptions(rho=rho, max_iter=1, owner_weight=weight))
    _first_step(solver, swarm)
    assert max(_block_sums(solver)) < 1e-9
    for j, state in enumerate(solver._agents):
        assert state is not None and state.own_y is not None and solver._z is not None
        owner_offset = state.own_y / (rho * weight)  # v - z
        other = solver._agents[1 - j]
        assert other is not None
        copy_offset = other.copy_y[j] / rho  # c - z
        assert np.allclose(weight * np.abs(owner_offset), np.abs(copy_offset))
        assert np.max(np.abs(copy_offset)) > 1e-6  # the holders disagreed: a real test



def test_an_agent_standing_still_restarts_from_the_guess_when_its_goal_moves() -> None:
    """The rule of :meth:`FootprintADMMSolver._restarts`: only an agent whose last plan stands
    still and whose goal moved since the last step starts afresh."""
    from types import SimpleNamespace

    solver = FootprintADMMSolver(swarm_of(car(horizon=5), car(horizon=5)))
    still = np.tile([0.5, 0.2, 0.3, 0.0], (6, 1))
    moving = still.copy()
    moving[:, 0] += np.linspace(0.0, 0.3, 6)
    goals = [np.array([2.0, 0.0, 0.0, 0.0]), np.array([-2.0, 0.0, 0.0, 0.0])]
    assert solver._restarts(goals) == frozenset()  # no last step yet
    solver._goals = [g.copy() for g in goals]
    solver._agents = [SimpleNamespace(answer=SimpleNamespace(states=plan)) for plan in (still, moving)]
    assert solver._restarts(goals) == frozenset()  # same goals
    detour = [g + np.array([0.0, 1.0, 0.0, 0.0]) for g in goals]
    assert solver._restarts(detour) == frozenset({0})  # the moving agent keeps its warm start
    turned = [g + np.array([0.0, 0.0, 1.0, 0.0]) for g in goals]
    assert solver._restarts(turned) == frozenset()  # a new heading alone is not a new goal position
