"""The centralised OCP of cars and point agents with footprints: a car turns to pass a gate that
its bounding square cannot, cars and mixed pairs cross keeping the exact rectangle distance, a
swarm of point agents builds the problem of build_centralized, guesses are certified in closed form and a failed
solve brakes.

Every distance is recomputed from the flown states with the exact rectangle distances of
:mod:`swarmpc.model.footprint`, never read from the solver.
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np
import pytest

from swarmpc.formulation.footprint_ocp import (
    FootprintAgent,
    FootprintSwarm,
    footprint_guess_blocks,
)
from swarmpc.formulation.nlp import CompiledNLP
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.footprint import rectangle_distance, rectangle_polytope_distance
from swarmpc.model.geometry import box_halfspaces
from swarmpc.solvers.base import braking_plan
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.footprint_central import FootprintCentralSolver, straight_guess

D_MIN = 0.05
WALL = 0.1
"""Half-thickness of the gate's wall (along x) [m]."""
GAP = 0.6
"""The gate's opening [m]: wider than the car (0.45 + 2 d_min = 0.55), narrower than its length (0.7)."""


def box(lower: list[float], upper: list[float]) -> tuple[np.ndarray, np.ndarray]:
    lower_, upper_ = np.array(lower, float), np.array(upper, float)
    return box_halfspaces((lower_ + upper_) / 2, (upper_ - lower_) / 2)


Obstacles = tuple[tuple[np.ndarray, np.ndarray], ...]

GATE = (box([-WALL, GAP / 2], [WALL, 3.0]), box([-WALL, -3.0], [WALL, -GAP / 2]))
"""A wall along x = 0 with an opening |y| < GAP / 2; it runs past the workspace (|y| <= 2), so
the only way to the other side is through the opening."""


def settings(model: str, horizon: int = 25, dt: float = 0.2, obstacles: Obstacles = (), collision: str = "hard",
             ) -> OCPSettings:
    """Planar settings of a car (state [x, y, theta, v]) or a double integrator ([p, v])."""
    Q = np.diag([1.0, 1.0, 0.5, 0.1]) if model == "car" else np.diag([1.0, 1.0, 0.1, 0.1])
    return OCPSettings(
        dim=2, horizon=horizon, dt=dt, discretization="rk4" if model == "car" else "euler",
        Q=Q, R=0.1 * np.eye(2), Qf=20.0 * Q, collision=collision, d_min=D_MIN, kappa=100.0,
        lower=np.array([-3.0, -2.0]), upper=np.array([3.0, 2.0]), accel=np.array([1.0, 1.0]), speed=1.0,
        obstacles=obstacles, model_name=model,
    )


def car(**kwargs: Any) -> FootprintAgent:
    return FootprintAgent(settings("car", **kwargs))


def point(half: float, **kwargs: Any) -> FootprintAgent:
    return FootprintAgent(settings("double_integrator", **kwargs), half_size=(half, half))


def fly(swarm: FootprintSwarm, starts: list[list[float]], goals: list[list[float]], steps: int
        ) -> tuple[list[np.ndarray], list[bool]]:
    """A closed loop on the agents' own models: the flown states (T+1, n_i) per agent and
    whether each step's solve succeeded."""
    solver = FootprintCentralSolver(swarm)
    states = [np.array(s, float) for s in starts]
    flown, solved = [[s] for s in states], []
    for _ in range(steps):
        result = solver.plan(states, [np.array(g, float) for g in goals])
        solved.append(result.stats.success)
        states = [agent.settings.model.step(s, u) for agent, s, u in zip(swarm.agents, states, result.inputs,
                                                                         strict=True)]
        for own, state in zip(flown, states, strict=True):
            own.append(state)
    return [np.array(own) for own in flown], solved


def obstacle_distance(agent: FootprintAgent, states: np.ndarray, obstacles: Obstacles) -> float:
    """Least exact distance of the agent's footprint to any obstacle over the flown states."""
    poses = agent.poses(states)
    return min(float(rectangle_polytope_distance(poses, agent.size, G, g).min()) for G, g in obstacles)


def pair_distance(first: FootprintAgent, a: np.ndarray, second: FootprintAgent, b: np.ndarray) -> float:
    return float(rectangle_distance(first.poses(a), first.size, second.poses(b), second.size).min())


def assert_at_goal_pose(states: np.ndarray, goal: list[float]) -> None:
    assert np.linalg.norm(states[-1, :2] - np.array(goal[:2])) <= 0.1
    assert abs(states[-1, 2] - goal[2]) <= 0.1


# ----------------------------------------------------------------------------- the narrow gate
def test_a_car_turns_to_pass_a_gate_narrower_than_its_length() -> None:
    agent = car(obstacles=GATE)
    start, goal = [-2.0, -0.7, math.pi / 2, 0.0], [1.5, 0.0, 0.0, 0.0]  # facing across the gate's axis
    (states,), solved = fly(FootprintSwarm((agent,)), [start], [goal], 40)
    assert all(solved)
    assert_at_goal_pose(states, goal)
    assert obstacle_distance(agent, states, GATE) >= D_MIN - 1e-6
    in_gate = np.abs(agent.poses(states)[:, 0]) <= WALL
    assert in_gate.any()  # its centre was in the opening, where only an aligned footprint keeps d_min
    length, width = agent.size
    assert length > GAP > width + 2 * D_MIN  # what makes the test: only an aligned car fits


def test_the_cars_bounding_square_cannot_pass_the_gate_that_a_box_as_wide_as_the_car_passes() -> None:
    start, goal = [-2.0, -0.7, 0.0, 0.0], [1.5, 0.0, 0.0, 0.0]
    length, width = car().size
    square = point(length / 2, obstacles=GATE)
    (states,), _ = fly(FootprintSwarm((square,)), [start], [goal], 30)
    assert states[:, 0].max() + length / 2 <= -WALL  # its body never enters the wall's slab
    narrow = point(width / 2, obstacles=GATE)
    (states,), solved = fly(FootprintSwarm((narrow,)), [start], [goal], 30)
    assert all(solved) and states[-1, 0] > WALL + width / 2  # through and clear on the far side
    assert obstacle_distance(narrow, states, GATE) >= D_MIN - 1e-6


# ----------------------------------------------------------------------------- crossings
def test_two_cars_swap_head_on_keeping_their_footprints_apart() -> None:
    first, second = car(), car()
    starts = [[-2.0, 0.0, 0.0, 0.0], [2.0, 0.0, math.pi, 0.0]]
    goals = [[2.0, 0.0, 0.0, 0.0], [-2.0, 0.0, math.pi, 0.0]]
    (a, b), solved = fly(FootprintSwarm((first, second)), starts, goals, 40)
    assert all(solved)
    assert_at_goal_pose(a, goals[0])
    assert_at_goal_pose(b, goals[1])
    assert pair_distance(first, a, second, b) >= D_MIN - 1e-6


def test_a_car_and_a_point_agent_cross_keeping_the_exact_distance() -> None:
    vehicle, walker = car(), point(0.15)
    starts = [[-2.0, 0.0, 0.0, 0.0], [0.0, -2.0, 0.0, 0.0]]
    goals = [[2.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0]]
    (a, b), solved = fly(FootprintSwarm((vehicle, walker)), starts, goals, 40)
    assert all(solved)
    assert_at_goal_pose(a, goals[0])
    assert np.linalg.norm(b[-1, :2] - np.array(goals[1][:2])) <= 0.1
    assert pair_distance(vehicle, a, walker, b) >= D_MIN - 1e-6
    # a real encounter: their straight paths meet at the origin, and they do come close
    assert np.min(np.linalg.norm(a[:, :2] - b[:, :2], axis=1)) < 1.0


def test_a_plan_is_warm_started_from_the_shifted_previous_one() -> None:
    solver = FootprintCentralSolver(FootprintSwarm((car(), point(0.15))))
    states = [np.array([-2.0, 0.0, 0.0, 0.0]), np.array([0.0, -2.0, 0.0, 0.0])]
    goals = [np.array([2.0, 0.0, 0.0, 0.0]), np.array([0.0, 2.0, 0.0, 0.0])]
    cold = solver.plan(states, goals)
    states = [agent.settings.model.step(s, u) for agent, s, u in zip(solver.swarm.agents, states, cold.inputs,
                                                                     strict=True)]
    warm = solver.plan(states, goals)
    assert cold.stats.success and not cold.stats.warm
    assert warm.stats.success and warm.stats.warm
    assert warm.stats.iterations < cold.stats.iterations


# ----------------------------------------------------------------------------- the point form
@pytest.mark.parametrize("collision", ["hard", "soft"])
def test_a_swarm_of_point_agents_builds_the_point_form_problem(collision: str) -> None:
    obstacles = (box([-0.3, -0.3], [0.3, 0.3]),)
    s = settings("double_integrator", horizon=12, obstacles=obstacles, collision=collision)
    bodies = np.array([[0.15, 0.15], [0.2, 0.1], [0.1, 0.2]])
    swarm = FootprintSwarm(tuple(FootprintAgent(s, half_size=tuple(b)) for b in bodies))
    reference_solver = CentralizedSolver(s, 3, bodies)
    solver = FootprintCentralSolver(swarm)
    ours = solver.nlp
    assert list(ours.x_layout.blocks) == list(reference_solver.nlp.x_layout.blocks)
    assert list(ours.g_layout.blocks) == list(reference_solver.nlp.g_layout.blocks)
    starts = np.array([[-1.5, 0.1, 0, 0], [1.5, -0.1, 0, 0], [0.1, 1.5, 0, 0]], float)
    goals = np.array([[1.5, 0.1, 0, 0], [-1.5, -0.1, 0, 0], [0.0, -1.5, 0, 0]], float)
    guesses = [straight_guess(agent, starts[i], goals[i]) for i, agent in enumerate(swarm.agents)]
    point_ = reference_solver.initial_point(np.array(guesses))
    ours_point = solver.initial_point(guesses)  # the same seeds as CentralizedSolver's
    assert sorted(ours_point) == sorted(point_)
    for name, value in point_.items():
        np.testing.assert_array_equal(ours_point[name], value)
    params = {"delta": swarm.point_deltas, **{f"x0{i}": starts[i] for i in range(3)},
              **{f"goal{i}": goals[i] for i in range(3)}}
    reference = reference_solver.nlp.solve(params, point_)
    solution = ours.solve(params, point_)
    assert reference.success and solution.success
    assert solution.cost == pytest.approx(reference.cost, abs=1e-6)


# ----------------------------------------------------------------------------- guesses and fallback
def row_values(nlp: CompiledNLP, x_vec: np.ndarray, params: dict[str, np.ndarray], name: str) -> np.ndarray:
    """The values of the constraint block ``name`` at the primal point x_vec."""
    g = np.asarray(nlp.constraint_function(x_vec, nlp.p_layout.pack(params))).ravel()
    block = nlp.g_layout.blocks[name]
    return g[block.start : block.stop].reshape(block.shape, order="F")


@pytest.mark.parametrize("collision", ["hard", "soft"])
def test_guess_certificates_certify_the_exact_signed_distance_of_the_guess(collision: str) -> None:
    obstacle = (box([-0.4, 1.0], [0.4, 1.4]),)
    swarm = FootprintSwarm((car(horizon=8, obstacles=obstacle, collision=collision),
                            car(horizon=8, obstacles=obstacle, collision=collision),
                            point(0.2, horizon=8, obstacles=obstacle, collision=collision)))
    starts = [[-1.5, 0.0, 0.3, 0.0], [1.0, 0.2, math.pi, 0.0], [0.0, -1.5, 0.0, 0.0]]
    goals = [[1.5, 0.0, 0.0, 0.0], [-1.5, 0.2, math.pi, 0.0], [0.0, 1.8, 0.0, 0.0]]
    solver = FootprintCentralSolver(swarm)
    guesses = [straight_guess(a, np.array(s, float), np.array(g, float))
               for a, s, g in zip(swarm.agents, starts, goals, strict=True)]
    blocks = footprint_guess_blocks(swarm, guesses)
    assert all(np.all(value >= 0) for name, value in blocks.items() if name.startswith("L"))
    params = {"delta": swarm.point_deltas, **{f"x0{i}": np.array(s) for i, s in enumerate(starts)},
              **{f"goal{i}": np.array(g) for i, g in enumerate(goals)}}
    x_vec = solver.nlp.x_layout.pack(solver.initial_point(guesses))
    agents = swarm.agents
    signed = {f"{i}_o0": rectangle_polytope_distance(agents[i].poses(guesses[i][1:]), agents[i].size,
                                                     *obstacle[0], signed=True) for i in (0, 1)}
    signed.update({f"{i}_{j}": rectangle_distance(agents[i].poses(guesses[i][1:]), agents[i].size,
                                                  agents[j].poses(guesses[j][1:]), agents[j].size, signed=True)
                   for i, j in ((0, 1), (0, 2), (1, 2))})
    assert min(float(v.min()) for v in signed.values()) < D_MIN  # the straight lines do collide somewhere
    for tag, distance in signed.items():
        np.testing.assert_allclose(row_values(solver.nlp, x_vec, params, f"couple{tag}"), 0.0, atol=1e-9)
        np.testing.assert_allclose(row_values(solver.nlp, x_vec, params, f"norm{tag}"), 1.0, atol=1e-9)
        separation = row_values(solver.nlp, x_vec, params, f"sep{tag}").ravel()
        # hard: the certified value is the signed distance; soft: the slack lifts it to d_min
        expected = distance if collision == "hard" else np.maximum(distance, D_MIN)
        np.testing.assert_allclose(separation, expected, atol=1e-9)


def test_a_failed_solve_brakes_every_agent_and_says_so() -> None:
    obstacle = (box([-0.5, -0.5], [0.5, 0.5]),)
    swarm = FootprintSwarm((car(horizon=10, obstacles=obstacle), point(0.15, horizon=10)))
    states = [np.array([0.0, 0.0, 0.5, 0.8]), np.array([2.0, 1.0, -0.5, 0.3])]  # the car starts in the block
    goals = [np.array([2.0, 0.0, 0.0, 0.0]), np.array([-2.0, 1.0, 0.0, 0.0])]
    result = FootprintCentralSolver(swarm, {"ipopt.max_iter": 50}).plan(states, goals)
    assert not result.stats.success and result.stats.fallback
    for agent, state, plan, first in zip(swarm.agents, states, result.plans, result.inputs, strict=True):
        expected_states, expected_inputs = braking_plan(state, agent.settings)
        np.testing.assert_array_equal(plan.states, expected_states)
        np.testing.assert_array_equal(plan.inputs, expected_inputs)
        np.testing.assert_array_equal(first, expected_inputs[0])
    assert result.inputs[0][1] == 0.0 and result.inputs[0][0] < 0  # wheels straight, slowing down


def test_symbolic_poses_are_the_numeric_ones() -> None:
    rng = np.random.default_rng(3)
    states = rng.uniform(-3, 3, (7, 4))
    for agent in (car(), point(0.2)):
        X = ca.SX.sym("X", 4, 7)
        symbolic = ca.Function("pose", [X], [agent.casadi_poses(X)])(states.T)
        np.testing.assert_allclose(np.array(symbolic).T, agent.poses(states), rtol=0, atol=1e-12)
    assert car().poses(states)[:, 2].tolist() == states[:, 2].tolist()  # a car turns with its heading
    assert np.all(point(0.2).poses(states)[:, 2] == 0.0)  # a point agent's box never does


def test_agents_must_share_the_time_grid_and_name_their_bodies_rightly() -> None:
    with pytest.raises(ValueError, match="horizon"):
        FootprintSwarm((car(horizon=10), car(horizon=12)))
    with pytest.raises(ValueError, match="half_size"):
        FootprintAgent(settings("car"), half_size=(0.2, 0.2))
    with pytest.raises(ValueError, match="half_size"):
        FootprintAgent(settings("double_integrator"))
    with pytest.raises(ValueError, match="half_size"):
        FootprintAgent(settings("double_integrator"), half_size=(0.2, -0.1))
