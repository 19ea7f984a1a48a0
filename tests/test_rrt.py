"""Tests of the OMPL-based initial-guess planner (swarmpc.solvers.rrt).

Clearance is checked with an independent oracle: the Euclidean point-to-polytope distance from a
small projection QP (SLSQP), on densely sampled path segments. A bounding-sphere lower bound
(from the obstacle's vertices) skips the QP for points that are obviously far away.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize

ou = pytest.importorskip("ompl.util")

from swarmpc.solvers.rrt import (  # noqa: E402
    RRTGuess,
    _Validity,
    plan_path,
    straight_line_guess,
    time_parametrize,
)

# ----------------------------------------------------------------------------- helpers / oracle


@dataclass(frozen=True)
class Poly:
    """A convex obstacle {x : G x <= g} together with its vertices (for the oracle only)."""

    G: np.ndarray
    g: np.ndarray
    vertices: np.ndarray

    @property
    def pair(self) -> tuple[np.ndarray, np.ndarray]:
        return self.G, self.g


def box(lo, hi) -> Poly:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    d = lo.size
    verts = np.array(list(itertools.product(*zip(lo, hi, strict=True))), float)
    return Poly(np.vstack([np.eye(d), -np.eye(d)]), np.concatenate([hi, -lo]), verts)


def regular_polygon(center, radius, n) -> Poly:
    """Regular n-gon with the given circumradius (faces with obtuse interior angles)."""
    angles = 2 * np.pi * np.arange(n) / n
    verts = np.asarray(center) + radius * np.column_stack([np.cos(angles), np.sin(angles)])
    G, g = [], []
    for a, b in zip(verts, np.roll(verts, -1, axis=0), strict=True):
        normal = np.array([b[1] - a[1], a[0] - b[0]])  # outward for counter-clockwise vertices
        G.append(normal)
        g.append(normal @ a)
    return Poly(np.array(G), np.array(g), verts)


def qp_distance(q: np.ndarray, poly: Poly) -> float:
    """Euclidean distance from q to the polytope: min ||x - q|| s.t. G x <= g (SLSQP)."""
    res = minimize(
        lambda x: 0.5 * np.sum((x - q) ** 2),
        poly.vertices.mean(axis=0),
        jac=lambda x: x - q,
        method="SLSQP",
        constraints=[
            {"type": "ineq", "fun": lambda x: poly.g - poly.G @ x, "jac": lambda x: -poly.G}
        ],
        options={"ftol": 1e-12, "maxiter": 500},
    )
    assert res.success, res.message
    return float(np.linalg.norm(res.x - q))


def densify(path: np.ndarray, per_segment: int = 6) -> np.ndarray:
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)
    pts = path[:-1, None, :] + t[None, :, None] * np.diff(path, axis=0)[:, None, :]
    return np.vstack([pts.reshape(-1, path.shape[1]), path[-1:]])


def min_clearance(path: np.ndarray, obstacles: list[Poly], inflate: float) -> float:
    """Smallest oracle distance of the densely sampled path to any obstacle.

    Points whose bounding-sphere lower bound already exceeds inflate + 0.05 are not sent to the
    QP (their true distance is larger than that bound anyway).
    """
    pts = densify(path)
    worst = np.inf
    for poly in obstacles:
        c = poly.vertices.mean(axis=0)
        radius = np.max(np.linalg.norm(poly.vertices - c, axis=1))
        lower_bound = np.linalg.norm(pts - c, axis=1) - radius
        near = lower_bound < inflate + 0.05
        if not np.all(near):
            worst = min(worst, float(np.min(lower_bound[~near])))
        for q in pts[near]:
            worst = min(worst, qp_distance(q, poly))
    return worst


# ----------------------------------------------------------------------------- scenes

LO2, HI2 = np.zeros(2), np.full(2, 10.0)
DOOR_WALLS = [box([4.5, 0.0], [5.5, 4.0]), box([4.5, 6.0], [5.5, 10.0])]  # door y in (4, 6)
START2, GOAL2 = np.array([1.0, 1.0]), np.array([9.0, 1.0])  # straight line blocked
INFLATE2 = 0.3

LO3, HI3 = np.zeros(3), np.full(3, 4.0)
PILLARS = [box([1.5, 1.5, 0.0], [2.5, 2.5, 4.0]), box([0.8, 2.8, 0.0], [1.6, 3.6, 4.0])]
START3, GOAL3 = np.array([0.5, 0.5, 2.0]), np.array([3.5, 3.5, 2.0])  # through a pillar
INFLATE3 = 0.2


def plan2(seed: int, **kw) -> np.ndarray | None:
    obstacles = kw.pop("obstacles", DOOR_WALLS)
    return plan_path(START2, GOAL2, LO2, HI2, [o.pair for o in obstacles], INFLATE2, seed, **kw)


def plan3(seed: int, **kw) -> np.ndarray | None:
    return plan_path(START3, GOAL3, LO3, HI3, [o.pair for o in PILLARS], INFLATE3, seed, **kw)


# ----------------------------------------------------------------------------- oracle sanity


def test_qp_oracle_matches_box_distance():
    rng = np.random.default_rng(0)
    for poly, lo, hi in [(DOOR_WALLS[0], LO2, HI2), (PILLARS[0], LO3, HI3)]:
        blo, bhi = poly.vertices.min(axis=0), poly.vertices.max(axis=0)
        for q in rng.uniform(lo, hi, size=(20, lo.size)):
            q = np.where(np.all((q >= blo) & (q <= bhi)), bhi + 0.1, q)  # keep q outside
            exact = np.linalg.norm(q - np.clip(q, blo, bhi))
            assert qp_distance(q, poly) == pytest.approx(exact, abs=1e-6)


# ----------------------------------------------------------------------------- clearance


def _check_path(path, start, goal, lo, hi, obstacles, inflate, bound):
    assert path is not None
    assert path.ndim == 2 and path.shape[1] == start.size and path.shape[0] >= 2
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    assert np.all(path >= lo) and np.all(path <= hi)
    assert min_clearance(path, obstacles, inflate) >= bound - 1e-6


def test_doorway_paths_keep_clearance_2d():
    for seed in range(30):
        path = plan2(seed)
        _check_path(path, START2, GOAL2, LO2, HI2, DOOR_WALLS, INFLATE2, INFLATE2)
        # it has to use the door: where it crosses the wall's mid-plane, y is inside the door
        crossing = np.argmax(path[:, 0] >= 5.0)
        assert 4.0 + INFLATE2 - 1e-6 <= path[crossing, 1] <= 6.0 - INFLATE2 + 1e-6


def test_pillar_paths_keep_clearance_3d():
    for seed in range(30):
        _check_path(plan3(seed), START3, GOAL3, LO3, HI3, PILLARS, INFLATE3, INFLATE3)


def test_rrt_planner_obtuse_polygon_documented_bound():
    """Non-right-angle corners: clearance >= inflate - step / 2 (the documented bound)."""
    octagon = regular_polygon([5.0, 5.0], 2.0, 8)
    start, goal, inflate = np.array([1.5, 5.2]), np.array([8.5, 4.8]), 0.4
    step = min(inflate / 2, 0.01 * np.linalg.norm(HI2 - LO2))
    for seed in range(15):
        path = plan_path(start, goal, LO2, HI2, [octagon.pair], inflate, seed, planner="rrt")
        _check_path(path, start, goal, LO2, HI2, [octagon], inflate, inflate - step / 2)


def test_waypoint_spacing_is_at_most_the_motion_check_step():
    path = plan2(3)
    step = min(INFLATE2 / 2, 0.01 * np.linalg.norm(HI2 - LO2))
    assert np.max(np.linalg.norm(np.diff(path, axis=0), axis=1)) <= step + 1e-9


# ----------------------------------------------------------------------------- reproducibility


def test_same_seed_same_path_different_seeds_differ():
    for plan in (plan2, plan3):
        a, b = plan(7), plan(7)
        np.testing.assert_array_equal(a, b)
        others = [plan(s) for s in range(8, 14)]
        n_different = sum(p.shape != a.shape or not np.array_equal(p, a) for p in others)
        assert n_different >= 5


def test_rrt_planner_same_seed_same_path():
    np.testing.assert_array_equal(plan2(11, planner="rrt"), plan2(11, planner="rrt"))


# ----------------------------------------------------------------------------- failures


def test_closed_wall_returns_none_within_budget():
    wall = [box([4.5, 0.0], [5.5, 10.0])]
    for planner in ("rrtconnect", "rrt"):
        t0 = time.perf_counter()
        assert plan2(0, obstacles=wall, time_budget=0.05, planner=planner) is None
        assert time.perf_counter() - t0 < 1.0


def test_invalid_endpoints_return_none():
    pairs = [o.pair for o in DOOR_WALLS]
    # goal within the inflation margin of a wall (but outside the wall itself)
    assert plan_path(START2, [4.3, 2.0], LO2, HI2, pairs, INFLATE2, 0) is None
    # start inside a wall, start outside the workspace
    assert plan_path([5.0, 2.0], GOAL2, LO2, HI2, pairs, INFLATE2, 0) is None
    assert plan_path([-1.0, 2.0], GOAL2, LO2, HI2, pairs, INFLATE2, 0) is None


def test_bad_arguments_raise():
    with pytest.raises(ValueError):
        plan2(0, planner="prm")
    with pytest.raises(ValueError):
        plan_path(START2, GOAL2, LO2, HI2, [], -0.1, 0)
    with pytest.raises(ValueError):
        plan_path(START3, GOAL3, LO2, HI2, [], 0.1, 0)


def test_no_ompl_log_output_and_log_level_restored(capfd):
    before = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_DEBUG)  # OMPL would print Debug/Info lines and the reseed error
    try:
        capfd.readouterr()
        assert plan2(1) is not None
        assert plan2(1) is not None  # reseeding after generators exist makes OMPL log an error
        assert plan2(0, obstacles=[box([4.5, 0.0], [5.5, 10.0])], time_budget=0.02) is None
        out, err = capfd.readouterr()
        assert out == "" and err == ""
        assert ou.getLogLevel() == ou.LOG_DEBUG
    finally:
        ou.setLogLevel(before)


# ----------------------------------------------------------------------------- time_parametrize


def test_time_parametrize_basic():
    path = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])
    state = np.array([0.0, 0.0, -0.5, 0.25])
    dt, speed = 0.1, 2.0
    out = time_parametrize(path, state, dt, 50, speed)
    assert out.shape == (51, 4)
    np.testing.assert_array_equal(out[0], state)
    step = np.linalg.norm(np.diff(out[:, :2], axis=0), axis=1)
    assert np.all(step <= speed * dt + 1e-9)
    # path length 7 at 0.2 per step: the goal is reached at k = 35 and then held with v = 0
    np.testing.assert_allclose(out[35:, :2], np.tile([3.0, 4.0], (16, 1)), atol=1e-12)
    np.testing.assert_array_equal(out[36:, 2:], 0.0)
    np.testing.assert_allclose(out[10], [2.0, 0.0, 2.0, 0.0], atol=1e-12)  # along segment 1
    np.testing.assert_allclose(out[20], [3.0, 1.0, 0.0, 2.0], atol=1e-12)  # along segment 2


def test_time_parametrize_prepends_current_position_and_short_horizon():
    path = np.array([[1.0, 0.0, 0.0], [1.0, 10.0, 0.0]])
    state = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    out = time_parametrize(path, state, 0.5, 4, 1.0)
    assert out.shape == (5, 6)
    np.testing.assert_array_equal(out[0], state)
    np.testing.assert_allclose(out[2, :3], [1.0, 0.0, 0.0], atol=1e-12)  # reached path[0] first
    np.testing.assert_allclose(out[4, :3], [1.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out[4, 3:], [0.0, 1.0, 0.0], atol=1e-12)  # not at the end yet


def test_straight_line_guess():
    state = np.array([1.0, 1.0, 0.3, 0.0])
    out = straight_line_guess(state, [4.0, 5.0], 0.2, 30, 2.5)
    assert out.shape == (31, 4)
    np.testing.assert_array_equal(out[0], state)
    np.testing.assert_allclose(out[1], [1.3, 1.4, 1.5, 2.0], atol=1e-12)
    np.testing.assert_allclose(out[-1], [4.0, 5.0, 0.0, 0.0], atol=1e-12)


def _point_polyline_distance(q: np.ndarray, pts: np.ndarray) -> float:
    if pts.shape[0] == 1:
        return float(np.linalg.norm(q - pts[0]))
    a, b = pts[:-1], pts[1:]
    ab = b - a
    denom = np.maximum(np.sum(ab * ab, axis=1), 1e-300)
    t = np.clip(np.sum((q - a) * ab, axis=1) / denom, 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - q, axis=1)))


coord = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)


@st.composite
def polyline_cases(draw):
    d = draw(st.sampled_from([2, 3]))
    n = draw(st.integers(1, 6))
    point = st.lists(coord, min_size=d, max_size=d)
    path = np.array(draw(st.lists(point, min_size=n, max_size=n)))
    vel = np.array(draw(point))
    start = path[0] if draw(st.booleans()) else np.array(draw(point))
    dt = draw(st.floats(0.01, 1.0))
    horizon = draw(st.integers(0, 40))
    speed = draw(st.floats(0.0, 3.0))
    return path, np.concatenate([start, vel]), dt, horizon, speed


@settings(max_examples=60, deadline=None)
@given(polyline_cases())
def test_time_parametrize_property(case):
    path, state, dt, horizon, speed = case
    d = path.shape[1]
    out = time_parametrize(path, state, dt, horizon, speed)
    assert out.shape == (horizon + 1, 2 * d)
    np.testing.assert_array_equal(out[0], state)
    pos, vel = out[:, :d], out[1:, d:]
    assert np.all(np.linalg.norm(np.diff(pos, axis=0), axis=1) <= speed * dt + 1e-9)
    full = np.vstack([state[:d], path])
    for q in pos:
        assert _point_polyline_distance(q, full) <= 1e-9
    speeds = np.linalg.norm(vel, axis=1)
    assert np.all(np.isclose(speeds, speed, atol=1e-9) | (speeds == 0.0))
    length = np.sum(np.linalg.norm(np.diff(full, axis=0), axis=1))
    if speed * dt * horizon >= length + 1e-9:
        np.testing.assert_allclose(pos[-1], path[-1], atol=1e-9)
        np.testing.assert_array_equal(vel[-1], 0.0)


# ----------------------------------------------------------------------------- RRTGuess


def make_guess(seed: int = 3) -> RRTGuess:
    return RRTGuess(LO2, HI2, [o.pair for o in DOOR_WALLS], INFLATE2, seed=seed, time_budget=0.05)


def test_rrtguess_reuse_and_replan_on_goal_change():
    guess = make_guess()
    first = guess.path_for(0, START2, GOAL2)
    assert first is not None
    assert guess.stats == {"fresh": 1, "reused": 0, "failed": 0}
    second = guess.path_for(0, START2, GOAL2)
    assert guess.stats == {"fresh": 1, "reused": 1, "failed": 0}
    np.testing.assert_array_equal(second, first)

    # moving along the path keeps reusing; the result starts here and is a suffix of the path
    here = first[len(first) // 2] + np.array([0.0, 0.01])
    third = guess.path_for(0, here, GOAL2)
    assert guess.stats["reused"] == 2 and guess.stats["fresh"] == 1
    np.testing.assert_array_equal(third[0], here)
    np.testing.assert_array_equal(third[-1], GOAL2)
    np.testing.assert_array_equal(third[1:], first[-(len(third) - 1) :])
    assert len(third) < len(first)

    new_goal = np.array([9.0, 9.0])
    fourth = guess.path_for(0, here, new_goal)
    assert guess.stats == {"fresh": 2, "reused": 2, "failed": 0}
    np.testing.assert_array_equal(fourth[-1], new_goal)

    # another agent has its own path and counters
    guess.path_for(1, START2, GOAL2)
    assert guess.stats["fresh"] == 3


def test_rrtguess_no_reuse_from_invalid_position():
    guess = make_guess()
    assert guess.path_for(0, START2, GOAL2) is not None
    too_close = np.array([4.3, 2.0])  # 0.2 from the wall, inflate is 0.3
    assert guess.path_for(0, too_close, GOAL2) is None
    assert guess.stats == {"fresh": 2, "reused": 0, "failed": 1}
    assert guess.path_for(0, START2, GOAL2) is not None  # stored path was dropped: plans again
    assert guess.stats["fresh"] == 3


def test_reuse_check_rejects_segments_through_obstacles():
    validity = _Validity(LO2, HI2, [o.pair for o in DOOR_WALLS], INFLATE2)
    assert validity.path_valid(np.array([[4.0, 5.0], [6.0, 5.0]]))  # through the door
    assert not validity.path_valid(np.array([[4.0, 2.0], [6.0, 2.0]]))  # through a wall
    assert not validity.path_valid(np.array([[4.0, 4.0], [4.75, 4.0], [4.75, 4.0]]))  # margin
    assert validity.path_valid(np.array([[4.0, 4.5], [6.0, 4.5]]))


def test_rrtguess_is_reproducible_and_guess_shape():
    runs = []
    for _ in range(2):
        guess = make_guess(seed=5)
        state = np.array([*START2, 0.1, -0.2])
        out = [guess.guess(0, state, GOAL2, 0.1, 20, 1.5)]
        out.append(guess.path_for(0, [1.0, 8.0], GOAL2))  # off the path: likely a fresh plan
        out.append(guess.path_for(1, START2, GOAL2))
        runs.append((out, guess.stats))
    (a, sa), (b, sb) = runs
    assert sa == sb
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    g = a[0]
    assert g.shape == (21, 4)
    np.testing.assert_array_equal(g[0], [*START2, 0.1, -0.2])
    assert np.all(np.linalg.norm(np.diff(g[:, :2], axis=0), axis=1) <= 1.5 * 0.1 + 1e-9)
