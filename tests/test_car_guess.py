"""Tests of the cars' initial guesses (swarmpc.solvers.car_guess): an OMPL path in SE(2) within the
turning limit around the obstacles, and a speed profile along it whose inputs reproduce its states.

Clearance is recomputed with the exact rectangle-polygon distance of swarmpc.model.footprint
(signed), independently of the planner's validity checker (which pads the obstacles and skips far
ones by a bound).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

pytest.importorskip("ompl")

from swarmpc.model.car import KinematicCar  # noqa: E402
from swarmpc.model.footprint import rectangle_polytope_distance, rectangle_vertices  # noqa: E402
from swarmpc.solvers.car_guess import car_guess, car_path, car_straight_guess  # noqa: E402

CAR = KinematicCar(dim=2, dt=0.1)
BOUNDS = (np.array([0.0, 0.0]), np.array([8.0, 6.0]))
D_MIN = 0.1
GUARD = 30.0
"""[s] the time limit of searches expected to find a path: the planner's iterations end them (in
well under a second on an idle core), the limit only guards, so a loaded machine cannot end them first."""
START = np.array([1.0, 1.0, 0.0])
GOAL = np.array([7.0, 1.0, 0.0])  # behind the wall
BESIDE = np.array([1.0, 2.2, 0.0])  # one lane up, same heading, close to the left edge: a parking move


def box(lo: list[float], hi: list[float]) -> tuple[np.ndarray, np.ndarray]:
    return np.vstack([np.eye(2), -np.eye(2)]), np.concatenate([hi, -np.asarray(lo)])


WALL_WITH_GAP = [box([4.0, 0.0], [4.4, 2.6]), box([4.0, 4.0], [4.4, 6.0])]  # gap y in (2.6, 4.0)
CLOSED_WALL = [box([4.0, 0.0], [4.4, 6.0])]


def clearance(model: KinematicCar, poses: np.ndarray, obstacles: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Least exact (signed) distance (n,) of the footprint at each reference pose to the obstacles."""
    centres = model.pose(np.column_stack([poses, np.zeros(len(poses))]))
    size = np.array(model.footprint)
    return np.min([rectangle_polytope_distance(centres, size, G, g, signed=True) for G, g in obstacles], axis=0)


def inside_bounds(model: KinematicCar, poses: np.ndarray) -> bool:
    centres = model.pose(np.column_stack([poses, np.zeros(len(poses))]))
    corners = rectangle_vertices(centres[:, :2], centres[:, 2], model.length, model.width)
    return bool(np.all(corners >= BOUNDS[0]) and np.all(corners <= BOUNDS[1]))


def same_angle(a: float, b: float) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) < 1e-9


def directions(path: np.ndarray) -> np.ndarray:
    """+1 / -1 for each step of a path driven forwards / in reverse."""
    chord = np.diff(path[:, :2], axis=0)
    return np.sign(chord[:, 0] * np.cos(path[:-1, 2]) + chord[:, 1] * np.sin(path[:-1, 2]))


def assert_turning_limit(model: KinematicCar, path: np.ndarray) -> None:
    """Consecutive headings turn by at most max_curvature times the distance between the poses.

    On an arc a chord is shorter than the arc by a relative (angle / 2)^2 / 6, far below 1e-3 for
    these few-centimetre steps; a cusp missing between two poses would break the bound there (the
    heading turns along both the forward and the reverse piece while the chord is their difference).
    """
    chord = np.linalg.norm(np.diff(path[:, :2], axis=0), axis=1)
    assert np.all(chord > 0)
    assert np.all(np.abs(np.diff(path[:, 2])) <= model.max_curvature * chord * (1 + 1e-3))


@pytest.fixture(scope="module")
def gap_path() -> np.ndarray:
    path = car_path(CAR, START, GOAL, WALL_WITH_GAP, BOUNDS, D_MIN, seed=3, time_limit=GUARD)
    assert path is not None
    return path


@pytest.mark.parametrize("prefer_forward", [True, False])
def test_path_through_the_gap_is_clear_and_within_the_turning_limit(prefer_forward: bool) -> None:
    path = car_path(CAR, START, GOAL, WALL_WITH_GAP, BOUNDS, D_MIN, 3, GUARD, prefer_forward)
    assert path is not None
    if prefer_forward:  # found forwards only
        assert np.all(directions(path) > 0)
    np.testing.assert_array_equal(path[0], START)
    np.testing.assert_array_equal(path[-1, :2], GOAL[:2])
    assert same_angle(path[-1, 2], GOAL[2])
    assert np.all(np.abs(np.diff(path[:, 2])) < 0.5)  # continuous headings
    crossing = (path[:, 0] > 4.0) & (path[:, 0] < 4.4)
    assert np.all((path[crossing, 1] > 2.6) & (path[crossing, 1] < 4.0))  # through the gap

    assert np.min(clearance(CAR, path, WALL_WITH_GAP)) >= D_MIN
    assert inside_bounds(CAR, path)
    # Between rows (chords of arcs of at most a few centimetres) the clearance loses at most d_min / 4.
    fractions = np.linspace(0.0, 1.0, 6)[1:-1, None, None]
    between = (path[:-1] + fractions * np.diff(path, axis=0)).reshape(-1, 3)
    assert np.min(clearance(CAR, between, WALL_WITH_GAP)) >= 0.75 * D_MIN

    assert_turning_limit(CAR, path)


def test_same_seed_same_path(gap_path: np.ndarray) -> None:
    again = car_path(CAR, START, GOAL, WALL_WITH_GAP, BOUNDS, D_MIN, seed=3, time_limit=GUARD)
    assert again is not None
    np.testing.assert_array_equal(again, gap_path)


def test_closed_wall_gives_none_within_the_time_limit() -> None:
    t0 = time.perf_counter()
    assert car_path(CAR, START, GOAL, CLOSED_WALL, BOUNDS, D_MIN, seed=0, time_limit=1.0) is None
    assert time.perf_counter() - t0 < 5.0


def test_a_search_ends_by_its_iterations_not_the_clock() -> None:
    # Two attempts of 50 iterations round a closed wall take a fraction of a second, not the minute.
    t0 = time.perf_counter()
    assert car_path(CAR, START, GOAL, CLOSED_WALL, BOUNDS, D_MIN, seed=0, time_limit=60.0, iterations=50) is None
    assert time.perf_counter() - t0 < 10.0


def test_the_iterations_decide_which_attempt_finds_the_path(gap_path: np.ndarray) -> None:
    # The forwards-only search through the gap needs about 100 iterations: with 40 it gives up,
    # and the path is the Reeds-Shepp attempt's, whatever the time limit.
    short = [car_path(CAR, START, GOAL, WALL_WITH_GAP, BOUNDS, D_MIN, seed=3, time_limit=t, iterations=40)
             for t in (GUARD, 2 * GUARD)]
    reeds_shepp = car_path(CAR, START, GOAL, WALL_WITH_GAP, BOUNDS, D_MIN, seed=3, time_limit=GUARD,
                           prefer_forward=False, iterations=40)
    assert short[0] is not None and reeds_shepp is not None
    np.testing.assert_array_equal(short[0], short[1])
    np.testing.assert_array_equal(short[0], reeds_shepp)
    assert short[0].shape != gap_path.shape or not np.array_equal(short[0], gap_path)


def test_invalid_endpoints_give_none_without_planning() -> None:
    near_wall = np.array([3.35, 1.0, 0.0])  # the front bumper (0.6 ahead of the axle) within d_min
    assert clearance(CAR, near_wall[None], WALL_WITH_GAP)[0] < D_MIN
    assert car_path(CAR, near_wall, GOAL, WALL_WITH_GAP, BOUNDS, D_MIN, seed=0) is None
    outside = np.array([0.05, 1.0, 0.0])  # the rear overhang sticks out of the workspace
    assert car_path(CAR, START, outside, WALL_WITH_GAP, BOUNDS, D_MIN, seed=0) is None


@pytest.mark.parametrize("prefer_forward", [True, False])
def test_parking_move_reverses(prefer_forward: bool) -> None:
    # Forwards only, the car would have to loop round with its body beyond the left edge.
    path = car_path(CAR, START, BESIDE, [], BOUNDS, D_MIN, 1, GUARD, prefer_forward)
    assert path is not None
    assert np.any(directions(path) < 0) and np.any(directions(path) > 0)
    assert np.min(clearance(CAR, path, [box([-1.0, -1.0], [0.0, 7.0])])) >= 0.0  # a wall as the left edge
    assert inside_bounds(CAR, path)
    assert_turning_limit(CAR, path)


def test_car_without_reverse_drives_forwards_only() -> None:
    forward_only = KinematicCar(dim=2, dt=0.1, max_reverse_speed=0.0)
    u_turn = np.array([1.5, 3.5, math.pi])
    path = car_path(forward_only, START, u_turn, [], BOUNDS, D_MIN, 1, GUARD, prefer_forward=False)
    assert path is not None
    assert np.all(directions(path) > 0)
    assert_turning_limit(forward_only, path)


def assert_plausible(model: KinematicCar, states: np.ndarray, inputs: np.ndarray, accel: float, cap: float) -> None:
    """The inputs reproduce the states (open loop over the horizon) and respect the limits."""
    rollout = model.rollout(states[0], inputs)
    np.testing.assert_allclose(rollout[:, :2], states[:, :2], atol=0.02)
    np.testing.assert_allclose(rollout[:, 2:], states[:, 2:], atol=1e-3)
    assert np.all(np.abs(inputs[:, 0]) <= accel + 1e-12)
    assert np.all(np.abs(inputs[:, 1]) <= model.max_steer + 1e-12)
    assert np.all(np.abs(np.diff(states[:, 3])) <= accel * model.dt + 1e-9)
    assert np.all(states[1:, 3] <= min(cap, model.max_speed) + 1e-12)
    assert np.all(states[1:, 3] >= -min(cap, model.max_reverse_speed) - 1e-12)


@pytest.mark.parametrize("v0", [0.0, 0.8, -0.3])
def test_guess_along_the_gap_path_is_dynamically_plausible(gap_path: np.ndarray, v0: float) -> None:
    state = np.array([*START, v0])
    states, inputs = car_guess(CAR, state, GOAL, gap_path, horizon=80, dt=CAR.dt, speed=1.2, accel=0.8)
    assert states.shape == (81, 4) and inputs.shape == (80, 2)
    np.testing.assert_array_equal(states[0], state)
    assert_plausible(CAR, states, inputs, 0.8, 1.2)
    assert np.min(clearance(CAR, states[:, :3], WALL_WITH_GAP)) >= 0.75 * D_MIN
    if v0 < 0:  # moving against the path: brakes to rest first
        first_stop = int(np.argmax(states[:, 3] >= 0))
        assert np.all(np.diff(states[: first_stop + 1, 3]) > 0)
    assert states[-1, 0] > 4.4  # through the gap within 8 s


def test_guess_with_cusps_reverses_and_stops_at_the_goal() -> None:
    path = car_path(CAR, START, BESIDE, [], BOUNDS, D_MIN, 1, GUARD, prefer_forward=False)
    assert path is not None
    states, inputs = car_guess(CAR, np.array([*START, 0.0]), BESIDE, path, horizon=120, dt=CAR.dt)
    assert_plausible(CAR, states, inputs, CAR.default_accel, math.inf)
    assert np.min(states[:, 3]) < 0 < np.max(states[:, 3])
    # v changes sign only through rest (at a cusp), and the car ends at rest at the goal.
    assert not np.any(states[1:, 3] * states[:-1, 3] < 0)
    np.testing.assert_allclose(states[-1], [*BESIDE, 0.0], atol=1e-2)


def test_straight_guess_heads_along_the_line_and_holds_at_the_goal() -> None:
    state = np.array([1.0, 1.0, 2 * math.pi + 0.3, 0.0])  # heading wound once
    goal = np.array([4.0, 4.0])
    states, inputs = car_straight_guess(CAR, state, goal, horizon=80, dt=CAR.dt)
    np.testing.assert_allclose(states[1:, 2], 2 * math.pi + math.pi / 4)  # the line, nearest turn
    assert_plausible(CAR, states[1:], inputs[1:], CAR.default_accel, math.inf)
    np.testing.assert_allclose(states[-1], [4.0, 4.0, 2 * math.pi + math.pi / 4, 0.0], atol=1e-2)

    at_goal = np.array([4.0, 4.0, 1.0, 0.0])
    states, inputs = car_straight_guess(CAR, at_goal, goal, horizon=10, dt=CAR.dt)
    np.testing.assert_array_equal(states, np.tile(at_goal, (11, 1)))
    np.testing.assert_array_equal(inputs, np.zeros((10, 2)))

    rolling = np.array([4.0, 4.0, 1.0, 0.5])  # at the goal but moving: brakes and comes back
    states, inputs = car_straight_guess(CAR, rolling, goal, horizon=30, dt=CAR.dt)
    assert_plausible(CAR, states, inputs, CAR.default_accel, math.inf)
    np.testing.assert_allclose(states[-1], at_goal, atol=1e-2)


def test_failed_plan_falls_back_to_the_straight_line() -> None:
    state = np.array([*START, 0.0])
    expected = car_straight_guess(CAR, state, GOAL, horizon=20, dt=CAR.dt)
    got = car_guess(CAR, state, GOAL, None, horizon=20, dt=CAR.dt)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)


def test_guess_arguments_are_checked(gap_path: np.ndarray) -> None:
    state = np.array([*START, 0.0])
    with pytest.raises(ValueError, match="start at the car's pose"):
        car_guess(CAR, state + [0.1, 0, 0, 0], GOAL, gap_path, horizon=5, dt=CAR.dt)
    with pytest.raises(ValueError, match="sampling time"):
        car_guess(CAR, state, GOAL, gap_path, horizon=5, dt=0.2)
    with pytest.raises(ValueError, match="d_min"):
        car_path(CAR, START, GOAL, WALL_WITH_GAP, BOUNDS, -0.1, seed=0)
    # A path given with wrapped headings is accepted from a car whose heading is wound.
    wound = np.array([*START[:2], START[2] + 2 * math.pi, 0.0])
    states, _ = car_guess(CAR, wound, GOAL, gap_path, horizon=5, dt=CAR.dt)
    assert np.all(np.abs(states[:, 2] - 2 * math.pi) < 1.0)
