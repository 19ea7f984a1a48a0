"""Seeding the OBCA certificates from a guess (swarmpc.solvers.dual_seed) and RRT path reuse.

Independent references: the Euclidean point-box distance in closed form, and for convex polygons
the exact distance to their edges as segments (no projection solver).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import box_halfspaces, obstacle_penetration, point_box_distance
from swarmpc.scenarios import builtin_scenario
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.dual_seed import certificate_value, obstacle_seed, pair_seed, polytope_certificate

coords = st.floats(-4.0, 4.0, allow_nan=False)
sizes = st.floats(0.05, 1.5, allow_nan=False)


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * (b - a))))


def polygon(center, radius, n, phase):
    """A regular convex n-gon as (G, g, vertices), counter-clockwise, outward normals."""
    angles = phase + 2 * np.pi * np.arange(n) / n
    verts = np.asarray(center) + radius * np.column_stack([np.cos(angles), np.sin(angles)])
    G, g = [], []
    for a, b in zip(verts, np.roll(verts, -1, axis=0), strict=True):
        normal = np.array([b[1] - a[1], a[0] - b[0]])
        G.append(normal)
        g.append(normal @ a)
    return np.array(G), np.array(g), verts


@settings(max_examples=150, deadline=None)
@given(st.lists(coords, min_size=3, max_size=3), st.lists(coords, min_size=3, max_size=3),
       st.lists(sizes, min_size=3, max_size=3), st.sampled_from([2, 3]))
def test_box_seed_is_feasible_and_exact(point, center, half, dim):
    point, center, half = (np.array(v[:dim]) for v in (point, center, half))
    G, g = box_halfspaces(center, half)
    lam = polytope_certificate(point, G, g)
    assert np.all(lam >= 0)
    assert np.linalg.norm(G.T @ lam) == pytest.approx(1.0, abs=1e-9)  # dual feasible (and tight)
    value = certificate_value(point, G, g, lam)
    distance = point_box_distance(point - center, half)
    if distance > 0:
        assert value == pytest.approx(distance, abs=1e-9)  # equal to the distance outside
    else:
        assert value == pytest.approx(distance, abs=1e-9)  # minus the depth inside
        assert value <= 1e-12


@settings(max_examples=150, deadline=None)
@given(st.lists(coords, min_size=2, max_size=2), st.floats(0.2, 2.0), st.integers(3, 8),
       st.floats(0.0, 2 * np.pi))
def test_polygon_seed_is_a_lower_bound_equal_to_the_distance_outside(point, radius, n, phase):
    point = np.array(point)
    G, g, verts = polygon([0.3, -0.2], radius, n, phase)
    lam = polytope_certificate(point, G, g)
    assert np.all(lam >= 0) and np.linalg.norm(G.T @ lam) <= 1 + 1e-9
    value = certificate_value(point, G, g, lam)
    inside = np.all(G @ point <= g)
    if inside:
        assert value <= 1e-9
    else:
        true = min(segment_distance(point, a, b) for a, b in zip(verts, np.roll(verts, -1, axis=0), strict=True))
        assert value <= true + 1e-9  # weak duality
        assert value == pytest.approx(true, abs=1e-7)  # and the seed is the optimal certificate


def test_most_violated_face_is_not_enough_near_a_vertex():
    """Near a box corner the single-face certificate under-reports; the seed is exact."""
    G, g = box_halfspaces(np.zeros(2), np.ones(2))
    point = np.array([2.0, 1.9])  # 1.0 and 0.9 beyond two faces: distance sqrt(1.81)
    lam = polytope_certificate(point, G, g)
    assert certificate_value(point, G, g, lam) == pytest.approx(np.sqrt(1.81))
    assert np.count_nonzero(lam) == 2


@pytest.mark.parametrize("collision", ["hard", "soft"])
def test_seeded_blocks_make_every_separation_row_feasible(collision):
    scn = builtin_scenario("wall-door").with_updates(collision=collision)
    s = OCPSettings.from_scenario(scn)
    rng = np.random.default_rng(0)
    # inside each wall, within d_min of the door's edge, and random points around
    positions = np.vstack([[0.0, 1.8], [0.0, -1.8], [0.0, 0.62], rng.uniform(-3, 3, size=(6, 2))])
    blocks = obstacle_seed("0", positions, s)
    for n, (G, g) in enumerate(s.obstacles):
        lam = blocks[f"L0_o{n}"]
        assert lam.shape == (G.shape[0], 9) and np.all(lam >= 0)
        margin = np.einsum("mk,mk->k", G @ positions.T - g[:, None], lam)
        slack = blocks[f"A0_o{n}"][0] if collision == "soft" else 0.0
        if collision == "soft":
            assert np.all(margin + slack >= s.d_min - 1e-12)
            close = obstacle_penetration(positions, G, g) > -s.d_min  # inside or nearer than d_min
            assert close.sum() >= 1 and np.all(slack[close] > 0) and np.all(slack[~close] == 0)
        else:
            assert f"A0_o{n}" not in blocks
    offsets = rng.uniform(-1, 1, size=(9, 2))
    pair = pair_seed("0_1", offsets, np.full(2, 0.2), s)
    assert pair["L0_1"].shape == (4, 9)
    if collision == "soft":
        direction = pair["L0_1"][:2] - pair["L0_1"][2:]
        value = np.einsum("kd,dk->k", offsets, direction) - 0.2 * pair["L0_1"].sum(axis=0)
        assert np.all(value + pair["A0_1"][0] >= s.d_min - 1e-12)


def test_centralized_initial_point_seeds_or_zeroes_the_certificates():
    scn = builtin_scenario("wall-door")
    s = OCPSettings.from_scenario(scn)
    # a guess that keeps clear of both walls and of each other: certificates make every row hold
    guess = np.zeros((2, s.horizon + 1, 4))
    guess[0, :, :2] = np.column_stack([np.linspace(-2.0, -1.0, s.horizon + 1), np.full(s.horizon + 1, 0.0)])
    guess[1, :, :2] = np.column_stack([np.linspace(2.0, 1.0, s.horizon + 1), np.full(s.horizon + 1, 0.0)])
    params = {"delta": scn.delta_vector, "x00": guess[0, 0], "x01": guess[1, 0],
              "goal0": np.zeros(4), "goal1": np.zeros(4)}
    rows = {}
    for seed in (True, False):
        solver = CentralizedSolver(s, 2, scn.delta_vector, seed_duals=seed)
        point = solver.initial_point(guess)
        assert ("L0_1" in point) is seed and ("L0_o0" in point) is seed
        g = np.asarray(solver.nlp.constraint_function(solver.nlp.x_layout.pack(point),
                                                      solver.nlp.p_layout.pack(params))).ravel()
        rows[seed] = {k: v for k, v in solver.nlp.g_layout.unpack(g).items() if k.startswith("sep")}
    assert all(np.all(v >= s.d_min - 1e-12) for v in rows[True].values())
    assert all(np.all(v == 0.0) for v in rows[False].values())  # lambda = 0 violates every row


def test_rrt_guesses_reuse_the_path_along_the_way():
    """In closed loop the RRT strategy plans once per agent and then reuses while nothing changed."""
    from swarmpc.simulation.guessing import GuessProvider

    scn = builtin_scenario("wall-door").with_updates(**{"solver.initial_guess": "rrt"})
    s = OCPSettings.from_scenario(scn)
    provider = GuessProvider(scn, s)
    states, goals = scn.start_states(), scn.goal_states()
    steered = 0
    for _ in range(15):
        step_goals = provider.goals(states, goals)  # walls block both lines: RRT waypoints
        steered += int(np.any(step_goals != goals))
        guess = provider.guesses(states, step_goals, None)
        states = guess[:, 1]  # follow the guess exactly: every stored path stays valid
    assert steered == 15
    stats = provider.rrt_stats
    # one plan per agent; the guess follows the path to the route goal, not the moving waypoint
    assert stats["fresh"] == 2 and stats["failed"] == 0 and stats["reused"] >= 2 * 15
    # a changed goal invalidates the stored path: exactly one fresh plan for that agent
    moved = goals.copy()
    moved[0, :2] = [2.0, -2.0]
    provider.guesses(states, provider.goals(states, moved), None)
    assert provider.rrt_stats["fresh"] == 3


@pytest.mark.parametrize("method", ["admm", "centralized"])
def test_seed_duals_is_a_scenario_switch(method):
    from swarmpc.simulation.loop import make_solver

    for flag in (False, True):
        scn = builtin_scenario("u-trap").with_updates(**{"solver.seed_duals": flag, "solver.method": method})
        solver = make_solver(scn, OCPSettings.from_scenario(scn))
        if method == "admm":
            assert solver.config.seed_duals is flag  # type: ignore[attr-defined]
            solver.close()  # type: ignore[attr-defined]
        else:
            assert solver.seed_duals is flag  # type: ignore[attr-defined]


def test_rrt_guess_retries_a_timed_out_plan_once_and_counts_one_failure():
    """A closed wall makes every plan time out: one retry, one plan, one failure, bounded time."""
    import time

    from swarmpc.solvers.rrt import RRTGuess

    G, g = box_halfspaces(np.array([5.0, 5.0]), np.array([0.5, 5.0]))
    guess = RRTGuess(np.zeros(2), np.full(2, 10.0), [(G, g)], inflate=0.1, seed=1, time_budget=0.02)
    started = time.perf_counter()
    assert guess.path_for(0, np.array([1.0, 5.0]), np.array([9.0, 5.0])) is None
    elapsed = time.perf_counter() - started
    assert guess.stats == {"fresh": 1, "reused": 0, "failed": 1}
    assert 0.02 * 5 * 0.9 <= elapsed < 2.0  # the budget, then four times the budget
    # an invalid start is not retried (nothing to plan): returns at once
    started = time.perf_counter()
    assert guess.path_for(0, np.array([5.0, 5.0]), np.array([9.0, 5.0])) is None
    assert time.perf_counter() - started < 0.02
