"""Cars steered along their SE(2) paths (swarmpc.simulation.guessing.CarRoutes.blocked / waypoint and
GuessProvider.goals): while a static obstacle blocks a car's straight way, its MPC goal is a pose
along its path ``lookahead`` ahead, at rest; with the way clear, its true goal."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip("ompl")

from conftest import one_car_scenario  # noqa: E402
from swarmpc.config import Scenario  # noqa: E402
from swarmpc.formulation.ocp import OCPSettings  # noqa: E402
from swarmpc.model.car import KinematicCar  # noqa: E402
from swarmpc.simulation.guessing import CAR_OFF_PATH, CarRoutes, GuessProvider  # noqa: E402

WALL = {"box": {"center": [0.0, 0.0], "half_size": [0.2, 1.0]}}
"""A wall across the straight line from the car's start [-2, 0] to its goal [2, 0], y in [-1, 1]."""
ASIDE = {"box": {"center": [0.0, 2.0], "half_size": [0.2, 0.2]}}
"""A block well off the straight line from [-2, 0] to [2, 0]."""
BAY = [{"box": {"center": [x, 0.0], "half_size": [0.05, 0.5]}} for x in (-0.4, 0.4)]
"""Two dividers 0.8 m apart, y in [-0.5, 0.5]: a bay 0.7 m wide between them."""


def _one_car(obstacles: list[dict[str, Any]], start: list[float] | None = None,
             goal: list[float] | None = None) -> Scenario:
    """One car, by default from [-2, 0] heading +x to [2, 0] heading +x, RRT guesses, a 2 s horizon
    at 1 m/s (a lookahead of 1.5 * 0.8 * 2 = 2.4 m)."""
    return one_car_scenario(obstacles, horizon=20, start=start, goal=goal, name="car-waypoints")


def _car(scn: Scenario) -> KinematicCar:
    model = scn.agent_models()[0]
    assert isinstance(model, KinematicCar)
    return model


def _pose(x: float, y: float, heading_deg: float) -> np.ndarray:
    return np.array([x, y, np.radians(heading_deg), 0.0])


def _at_arc_length(path: np.ndarray, length: float) -> np.ndarray:
    """The pose (3,) ``length`` metres along the polyline of ``path``'s positions, interpolated."""
    chords = np.linalg.norm(np.diff(path[:, :2], axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(chords)])
    return np.array([np.interp(length, arc, path[:, i]) for i in range(3)])


# ------------------------------------------------------------------ the blocked test
def test_a_car_facing_a_wall_is_blocked_and_a_clear_line_is_not():
    scn = _one_car([WALL])
    routes, model = CarRoutes(scn), _car(scn)
    assert routes.blocked(model, _pose(-2.0, 0.0, 0.0), _pose(2.0, 0.0, 0.0))
    assert not routes.blocked(model, _pose(-2.0, 0.0, 0.0), _pose(-1.2, 0.0, 0.0))  # short of the wall
    clear = _one_car([ASIDE])
    assert not CarRoutes(clear).blocked(model, _pose(-2.0, 0.0, 0.0), _pose(2.0, 0.0, 0.0))


def test_the_footprint_not_only_the_reference_point_must_clear_the_wall():
    """Past the wall's end (y = 1): the centre line 0.2 m above it misses the wall, the footprint
    (half diagonal 0.42 m) does not; 0.5 m above it (0.5 > 0.42 + 0.9 d_min) the way is clear."""
    scn = _one_car([WALL])
    routes, model = CarRoutes(scn), _car(scn)
    half_diagonal = 0.5 * np.hypot(*model.footprint)
    assert 0.2 < half_diagonal + routes.clearance < 0.5
    offset = model.centre_offset  # the reference point sits behind the centre, heading +x
    assert routes.blocked(model, _pose(-2.0 - offset, 1.2, 0.0), _pose(2.0 - offset, 1.2, 0.0))
    assert not routes.blocked(model, _pose(-2.0 - offset, 1.5, 0.0), _pose(2.0 - offset, 1.5, 0.0))


def test_a_car_in_a_bay_is_blocked_by_the_dividers_at_any_heading():
    """A goal less than a half diagonal from the dividers (a 0.7 m bay) is always blocked."""
    scn = _one_car(BAY, start=[0.0, 1.5, -90.0], goal=[0.0, 0.2, -90.0])
    routes, model = CarRoutes(scn), _car(scn)
    assert routes.blocked(model, _pose(0.0, 1.5, -90.0), _pose(0.0, 0.2, -90.0))
    assert routes.blocked(model, _pose(0.0, 0.2, -90.0), _pose(0.0, 0.2, -90.0))


# ------------------------------------------------------------------ the waypoint
def _expected(routes: CarRoutes, model: KinematicCar, state: np.ndarray, rest: np.ndarray,
              lookahead: float) -> np.ndarray:
    """The waypoint by its definition, pose by pose: the last pose of ``rest`` in plain sight
    when it lies beyond ``lookahead``, else the pose at ``lookahead``; at rest."""
    chords = np.linalg.norm(np.diff(rest[:, :2], axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(chords)])
    seen = [k for k, pose in enumerate(rest) if not routes.blocked(model, state, np.append(pose, 0.0))]
    if seen and arc[seen[-1]] > lookahead:
        return np.append(rest[seen[-1]], 0.0)
    return np.append(_at_arc_length(rest, lookahead), 0.0)


def test_the_waypoint_is_on_the_path_lookahead_ahead_with_its_heading_at_rest():
    """A car leaving a bay sees no pose of its path from inside: the pose ``lookahead`` ahead."""
    scn = _one_car(BAY, start=[0.0, 0.1, 90.0], goal=[2.0, 1.8, 0.0])
    routes, model = CarRoutes(scn), _car(scn)
    start, goal = scn.start_states()[0], scn.goal_states()[0]
    path = routes.path(0, model, start, goal)
    assert path is not None
    assert all(routes.blocked(model, start, np.append(pose, 0.0)) for pose in path)
    for lookahead in (0.3, 0.9, 1.5):
        waypoint = routes.waypoint(0, model, start, goal, lookahead)
        assert waypoint is not None and waypoint.shape == (4,) and waypoint[3] == 0.0
        np.testing.assert_allclose(waypoint[:3], _at_arc_length(path, lookahead), atol=1e-12)
    assert routes.stats == {"fresh": 1, "reused": 3, "failed": 0}  # one plan, reused


def test_a_later_pose_of_the_path_in_plain_sight_is_the_waypoint():
    """Round the wall's end the path's poses past the corner are in sight from the start, farther
    than a short lookahead; from a place further along, the rule holds from there on."""
    scn = _one_car([WALL])
    routes, model = CarRoutes(scn), _car(scn)
    start, goal = scn.start_states()[0], scn.goal_states()[0]
    path = routes.path(0, model, start, goal)
    assert path is not None
    waypoint = routes.waypoint(0, model, start, goal, 0.5)
    assert waypoint is not None
    np.testing.assert_allclose(waypoint, _expected(routes, model, start, path, 0.5), atol=1e-12)
    assert any(np.array_equal(waypoint[:3], pose) for pose in path)  # a pose of the path, beyond 0.5 m
    assert not np.allclose(waypoint[:3], _at_arc_length(path, 0.5))
    m = len(path) // 3
    moved = np.append(path[m], 0.3)
    for lookahead in (0.5, 2.4):
        waypoint = routes.waypoint(0, model, moved, goal, lookahead)
        assert waypoint is not None
        np.testing.assert_allclose(waypoint, _expected(routes, model, moved, path[m:], lookahead), atol=1e-12)


def test_the_waypoint_is_the_goal_when_less_than_the_lookahead_is_left():
    scn = _one_car([WALL])
    routes, model = CarRoutes(scn), _car(scn)
    start, goal = scn.start_states()[0], scn.goal_states()[0]
    path = routes.path(0, model, start, goal)
    assert path is not None
    near_end = np.append(path[-3], 0.0)
    waypoint = routes.waypoint(0, model, near_end, goal, 2.4)
    assert waypoint is not None and np.array_equal(waypoint, np.append(goal[:3], 0.0))


def test_the_heading_tells_apart_two_passes_of_the_same_spot():
    """A stored path runs east through (0, 0) and comes back north through (0.05, 0): a car at
    (0.04, 0) facing east is placed on the first pass (the second is nearer by position alone)."""
    scn = _one_car([WALL])
    routes, model = CarRoutes(scn), _car(scn)
    east = [(x, 0.0, 0.0) for x in np.linspace(0.0, 1.0, 11)]
    back = [(1.0 - 0.95 * t, -0.5, np.pi) for t in np.linspace(0.0, 1.0, 11)]
    north = [(0.05, y, 0.5 * np.pi) for y in np.linspace(-0.5, 0.5, 11)]
    path = np.array(east + back + north)
    goal = np.append(path[-1], 0.0)
    routes._routes[0], routes._progress[0] = (goal[:3], path), 0
    waypoint = routes.waypoint(0, model, np.array([0.04, 0.0, 0.0, 0.5]), goal, 0.5)
    assert waypoint is not None
    np.testing.assert_allclose(waypoint, [0.6, 0.0, 0.0, 0.0], atol=1e-12)


def test_a_car_far_off_its_path_gets_a_fresh_one_from_where_it_is():
    scn = _one_car([WALL])
    routes, model = CarRoutes(scn), _car(scn)
    start, goal = scn.start_states()[0], scn.goal_states()[0]
    assert routes.path(0, model, start, goal) is not None
    near = start + np.array([0.0, 0.5 * CAR_OFF_PATH * model.length, 0.0, 0.0])
    assert routes.path(0, model, near, goal) is not None
    assert routes.stats == {"fresh": 1, "reused": 1, "failed": 0}
    far = start - np.array([1.2 * CAR_OFF_PATH * model.length, 0.0, 0.0, 0.0])  # behind the path's start
    path = routes.path(0, model, far, goal)
    assert path is not None and np.array_equal(path[0], far[:3])
    assert routes.stats == {"fresh": 2, "reused": 1, "failed": 0}


# ------------------------------------------------------------------ the closed loop's goals
def test_a_blocked_car_is_steered_to_its_path_and_a_clear_one_keeps_its_goal():
    blocked = _one_car([WALL])
    provider = GuessProvider(blocked, OCPSettings.from_scenario(blocked))
    states, goals = blocked.start_states(), blocked.goal_states()
    step_goals = provider.goals(states, goals)
    assert not np.array_equal(step_goals, goals) and step_goals[0, 3] == 0.0
    assert provider._car_routes is not None
    waypoint = provider._car_routes.waypoint(0, _car(blocked), states[0], goals[0], 2.4)
    assert waypoint is not None
    np.testing.assert_allclose(step_goals[0], waypoint, atol=1e-9)
    guess = provider.guesses(states, step_goals, None)  # along the path to the route goal: no new plan
    assert provider.rrt_stats == {"fresh": 1, "reused": 2, "failed": 0}
    assert np.array_equal(guess[0, 0], states[0])

    clear = _one_car([ASIDE])
    provider = GuessProvider(clear, OCPSettings.from_scenario(clear))
    assert np.array_equal(provider.goals(clear.start_states(), clear.goal_states()), clear.goal_states())
    assert provider.rrt_stats == {"fresh": 0, "reused": 0, "failed": 0}  # no path needed
