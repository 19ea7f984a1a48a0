"""Agents' physical bodies: pairs keep Δ_ij = b_i + b_j, obstacles keep the whole body out, the
metrics count overlapping bodies, and every picture draws the bodies, so a drawn overlap is a
counted collision and nothing else. Default bodies (Δ/2) leave obstacle-free runs bit for bit as
they were (tests/test_pinned_behaviour.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.optimize import linprog

from conftest import ScriptedExecutor
from swarmpc import plots, viewer
from swarmpc.config import ScenarioError, load_scenario, scenario_from_dict
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import count_body_collisions, inflate_polytope
from swarmpc.simulation.controller import make_solver
from swarmpc.simulation.disturbance import planner_bodies, planner_delta
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import RunResult, StepRecord, write_run
from swarmpc.simulation.rundata import RunDataError, load_run
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalResult

TOUCH = 1e-9
"""Bodies closer than this to touching count as touching, not overlapping (the metrics' tolerance)."""

PAIR = {
    "name": "unequal-pair", "dim": 2, "delta": 0.2,  # Δ_ij = 0.1 + 0.3 = 0.4, twice the scenario's Δ
    "workspace": {"lower": [-3, -3], "upper": [3, 3]}, "limits": {"accel": 2.0},
    "agents": [{"start": [-1.5, 0.05], "goal": [1.5, 0.05], "body": 0.1},
               {"start": [1.5, -0.05], "goal": [-1.5, -0.05], "body": [0.3, 0.3]}],
    "stop": {"max_steps": 400},
}
WALL = [{"box": {"center": [0.0, 1.8], "half_size": [0.15, 1.2]}},
        {"box": {"center": [0.0, -1.8], "half_size": [0.15, 1.2]}}]
DOOR = {
    "name": "body-door", "dim": 2, "delta": 0.2, "workspace": {"lower": [-3, -3], "upper": [3, 3]},
    "obstacles": WALL,
    "agents": [{"start": [-2.0, 1.5], "goal": [2.0, 1.5], "body": 0.25},
               {"start": [2.0, -1.5], "goal": [-2.0, -1.5], "body": 0.08}],
    "stop": {"max_steps": 600},
}


def _with(spec: dict, **changes) -> dict:
    return {**spec, **changes}


def _saved(folder: Path) -> tuple[np.ndarray, dict]:
    """Positions (T+1, M, d) as the run folder saved them, and the scenario file's data."""
    with np.load(folder / "trajectory.npz") as arrays:
        states = arrays["states"]
    scn = load_scenario(folder / "scenario.yaml")
    return states[:, :, : scn.dim], scn


def _overlapping_pairs(centers: np.ndarray, halves: np.ndarray) -> set[tuple[int, int]]:
    """Pairs (i < j) of boxes (centres, half-sizes (n, d)) that overlap by more than TOUCH on every axis."""
    pairs = set()
    for i in range(len(centers)):
        for j in range(i + 1, len(centers)):
            if np.all(np.abs(centers[i] - centers[j]) < halves[i] + halves[j] - TOUCH):
                pairs.add((i, j))
    return pairs


def _collisions_at(positions: np.ndarray, bodies: np.ndarray) -> set[tuple[int, int, int]]:
    """Every (k, i, j) the metrics count, one instant at a time."""
    counted = set()
    for k in range(len(positions)):
        for i in range(positions.shape[1]):
            for j in range(i + 1, positions.shape[1]):
                pair = positions[k : k + 1, [i, j]]
                if count_body_collisions(pair, bodies[[i, j]]):
                    counted.add((k, i, j))
    return counted


def _rectangle(patch) -> tuple[np.ndarray, np.ndarray]:
    """(centre, half-size) of a matplotlib Rectangle, from the geometry the figure draws."""
    half = np.array([patch.get_width(), patch.get_height()]) / 2
    return np.array([patch.get_x(), patch.get_y()]) + half, half


def _box_overlaps_polytope(center: np.ndarray, half: np.ndarray, G: np.ndarray, g: np.ndarray) -> float:
    """Largest radius of a ball inside both the box and the polytope (> 0: they overlap), by a
    linear program on the raw polytope (independent of the inflation the planner uses)."""
    d = len(center)
    norms = np.linalg.norm(G, axis=1)
    A = np.vstack([np.hstack([G, norms[:, None]]), np.hstack([np.eye(d), np.ones((d, 1))]),
                   np.hstack([-np.eye(d), np.ones((d, 1))])])
    b = np.concatenate([g, center + half, half - center])
    result = linprog(np.r_[np.zeros(d), -1.0], A_ub=A, b_ub=b, bounds=[(None, None)] * (d + 1))
    assert result.status == 0
    return float(-result.fun)


# ------------------------------------------------------------------------------ the scenario
def test_default_bodies_are_half_delta_and_pairs_keep_delta_bit_for_bit():
    scn = scenario_from_dict({"dim": 3, "delta": [0.3, 0.1, 0.7], "disturbance": {"tightening": 0.05},
                              "agents": [{"start": [0, 0, 0], "goal": [1, 1, 1]},
                                         {"start": [2, 2, 2], "goal": [3, 3, 3]}]})
    assert np.array_equal(scn.bodies, np.tile(scn.delta_vector / 2, (2, 1)))
    assert np.array_equal(scn.bodies[0] + scn.bodies[1], scn.delta_vector)
    assert np.array_equal(planner_delta(scn), scn.delta_vector + 0.05)  # what the planner kept before
    assert np.array_equal(planner_bodies(scn)[0] + planner_bodies(scn)[1], scn.delta_vector + 0.05)


def test_a_body_is_a_scalar_or_one_value_per_axis():
    scn = scenario_from_dict(PAIR)
    assert np.array_equal(scn.bodies, [[0.1, 0.1], [0.3, 0.3]])
    assert np.array_equal(planner_delta(scn), [0.4, 0.4])  # the largest Δ_ij, for the deadlock clearance


@pytest.mark.parametrize(("change", "message"), [
    ({"agents": [{"start": [0, 0], "goal": [1, 1], "body": 0.1}, {"start": [0.35, 0.1], "goal": [-1, 1], "body": 0.3}]},
     "agents[1].start: within delta of agents[0].start, their bodies overlap"),
    ({"agents": [{"start": [0, 0], "goal": [1, 1], "body": 0.1}, {"start": [2, 2], "goal": [1.2, 1.39], "body": 0.3}]},
     "agents[1].goal: within delta of agents[0].goal, their bodies overlap"),
    ({"obstacles": [{"box": {"center": [1.0, 0.0], "half_size": [0.2, 0.2]}}],
      "agents": [{"start": [-1, 0], "goal": [1.25, 0], "body": 0.1}]},
     "agents[0].goal: the body (half-size [0.1, 0.1]) at [1.25, 0.0] reaches inside obstacles[0]"),
    ({"obstacles": [{"polytope": {"G": [[1, 1]], "g": [0]}}], "agents": [{"start": [0.1, 0.05], "goal": [2, 2]}]},
     "agents[0].start: the body (half-size [0.15, 0.15]) at [0.1, 0.05] reaches inside obstacles[0]"),
    ({"agents": [{"start": [0, 0], "goal": [1, 1], "body": [0.1, 0.1, 0.1]}]},
     "agents[0].body: expected a scalar or 2 values for dim 2, got 3"),
    ({"agents": [{"start": [0, 0], "goal": [1, 1], "body": 0}]}, "agents[0].body: every half-size must be > 0"),
    ({"agents": [{"start": [0, 0], "goal": [1, 1], "body": [0.1, -0.2]}]},
     "agents[0].body: every half-size must be > 0"),
    ({"agents": [{"start": [0, 0], "goal": [1, 1], "body": True}]}, "agents[0].body"),
])
def test_bad_bodies_are_refused_with_one_line(change, message):
    with pytest.raises(ScenarioError) as caught:
        scenario_from_dict({"dim": 2, **change})
    assert str(caught.value).startswith(message) and "\n" not in str(caught.value)


def test_bodies_that_clear_each_other_and_the_obstacles_are_accepted():
    """The same places as the refusals above, with bodies small enough to fit."""
    scenario_from_dict({"dim": 2, "agents": [{"start": [0, 0], "goal": [1, 1], "body": 0.1},
                                             {"start": [0.35, 0.1], "goal": [-1, 1], "body": 0.2}]})
    scenario_from_dict({"dim": 2, "obstacles": [{"box": {"center": [1.0, 0.0], "half_size": [0.2, 0.2]}}],
                        "agents": [{"start": [-1, 0], "goal": [1.25, 0], "body": 0.04}]})


def test_only_delta_keeps_the_old_rule():
    """A scenario with delta alone refuses exactly the starts it refused before: within Δ on every axis."""
    two = [{"start": [0, 0], "goal": [1, 1]}, {"start": [0.29, 0.0], "goal": [-1, 1]}]
    with pytest.raises(ScenarioError, match=r"agents\[1\]\.start: within delta of agents\[0\]\.start"):
        scenario_from_dict({"dim": 2, "delta": 0.3, "agents": two})
    scenario_from_dict({"dim": 2, "delta": 0.29, "agents": two})  # exactly Δ apart: touching, allowed


# ------------------------------------------------------------------------------ the solvers
def test_admm_hands_each_agent_the_delta_of_each_of_its_pairs():
    """Every request carries, per neighbour, Δ_ij = b_i + b_j of that pair (not one Δ for all)."""
    scn = scenario_from_dict({"dim": 2, "agents": [
        {"start": [0.0, 0.0], "goal": [0.0, 0.0], "body": 0.1},
        {"start": [0.6, 0.0], "goal": [0.6, 0.0], "body": 0.2},
        {"start": [0.0, 0.7], "goal": [0.0, 0.7], "body": [0.3, 0.05]}]})
    s = OCPSettings.from_scenario(scn)

    def rest(request):
        states = np.tile(request.state, (s.horizon + 1, 1))
        own = states[s.first_constrained_step:, : s.dim].T.copy()
        return LocalResult(agent=request.agent, own=own, copies=request.z_neighbours.copy(), states=states,
                           inputs=np.zeros((s.horizon, s.dim)), success=True, fallback=False, solve_time=0.0,
                           max_slack=0.0, cost=0.0)

    executor = ScriptedExecutor(rest)
    solver = ADMMSolver(s, 3, scn.bodies, ADMMConfig(coupling_margin=0.5), executor)
    states = scn.start_states()
    solver.plan(states, scn.goal_states(), np.repeat(states[:, None], s.horizon + 1, axis=1))
    checked = 0
    for request in executor.requests:
        for row, j in zip(request.delta, request.neighbours, strict=True):
            assert np.array_equal(row, scn.bodies[request.agent] + scn.bodies[j])
            checked += 1
    assert checked >= 4  # every agent held a copy of another


@pytest.mark.parametrize("method", ["centralized", "admm"])
def test_the_closed_loop_plans_with_each_agents_body(method):
    """The solver the closed loop builds keeps each pair's own Δ_ij and grows each agent's
    obstacles by its own body: it holds the planner's bodies, one row per agent."""
    scn = scenario_from_dict(_with(DOOR, solver={"method": method}, agents=[
        *DOOR["agents"], {"start": [-2.0, -2.5], "goal": [-1.0, -2.5], "body": [0.12, 0.3]}]))
    solver = make_solver(scn, OCPSettings.from_scenario(scn))
    try:
        assert np.array_equal(solver.bodies, planner_bodies(scn))
    finally:
        getattr(solver, "close", lambda: None)()


@pytest.fixture(scope="module", params=["centralized", pytest.param("admm", marks=pytest.mark.loop)])
def pair_run(request, tmp_path_factory) -> Path:
    """The unequal pair (bodies 0.1 and 0.3, Δ = 0.2) swapping head-on, as a run folder."""
    scn = scenario_from_dict(_with(PAIR, solver={"method": request.param}))
    return write_run(simulate(scn), tmp_path_factory.mktemp("bodies") / request.param)


def test_unequal_bodies_never_overlap(pair_run):
    positions, scn = _saved(pair_run)
    reach = scn.bodies[0] + scn.bodies[1]  # 0.4 per axis: the scenario's Δ (0.2) would let them overlap
    excess = (np.abs(positions[:, 0] - positions[:, 1]) - reach).max(axis=1)
    assert excess.min() >= 0.0  # on some axis at least b_i + b_j apart, at every saved state
    assert excess.min() < 0.1  # and they do pass close: the pair's Δ_ij is what binds
    summary = load_run(pair_run).summary
    assert summary["collisions"] == 0 and summary["min_separation_ratio"] >= 1.0 and summary["all_reached"]


def test_the_run_folder_records_the_bodies(pair_run):
    _, scn = _saved(pair_run)
    assert np.array_equal(scn.bodies, [[0.1, 0.1], [0.3, 0.3]])  # scenario.yaml holds each body
    assert [a["body"] for a in yaml.safe_load((pair_run / "scenario.yaml").read_text())["agents"]] == [0.1, [0.3, 0.3]]
    with np.load(pair_run / "trajectory.npz") as arrays:
        assert np.array_equal(arrays["bodies"], scn.bodies)
    assert np.array_equal(load_run(pair_run).bodies, scn.bodies)


@pytest.mark.loop
@pytest.mark.parametrize("method", ["centralized", "admm"])
def test_bodies_stay_out_of_the_wall(method, tmp_path):
    """Two agents of different bodies (0.25 and 0.08) through a door: no body's box ever meets a
    wall, recomputed exactly (a linear program on the raw polytopes) from the saved states."""
    scn = scenario_from_dict(_with(DOOR, solver={"method": method}))
    folder = write_run(simulate(scn), tmp_path / "door")
    positions, scn = _saved(folder)
    assert load_run(folder).summary["all_reached"]
    depth = max(_box_overlaps_polytope(p, scn.bodies[i], G, g)
                for G, g in scn.obstacle_halfspaces() for k, row in enumerate(positions) for i, p in enumerate(row))
    assert depth <= 1e-9
    penetration = load_run(folder).summary["max_obstacle_penetration"]
    assert penetration is not None and penetration <= 0.0


def test_a_body_is_inside_a_grown_box_exactly_when_it_overlaps_the_box():
    """The obstacle growth the planner uses is exact for box obstacles (and conservative elsewhere)."""
    rng = np.random.default_rng(0)
    G = np.vstack([np.eye(2), -np.eye(2)])
    g = np.array([1.0, 0.5, 0.2, 0.3])  # the box [-0.2, 1] x [-0.3, 0.5]
    triangle = (np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0]]), np.array([0.0, 0.0, 1.0]))
    for _ in range(300):
        p, b = rng.uniform(-1.5, 1.5, 2), rng.uniform(0.05, 0.5, 2)
        overlap = _box_overlaps_polytope(p, b, G, g) > 1e-9
        assert np.all(G @ p < inflate_polytope(G, g, b)) == overlap
        if _box_overlaps_polytope(p, b, *triangle) > 1e-9:
            assert np.all(triangle[0] @ p <= inflate_polytope(*triangle, b))


# ------------------------------------------------------------------------------ the pictures
@pytest.fixture(scope="module")
def crossing_run(tmp_path_factory) -> Path:
    """A hand-made run: agent 0 (body 0.1) sweeps along y = 0 past agent 1 (body 0.25, at y = 0.33:
    the bodies overlap while |x_0| < 0.35, where Δ = 0.3 would count nothing) and agent 2 (body
    0.15, at y = -0.26: never overlapping, where Δ would count a collision)."""
    agents = [
        {"start": [-1.0, 0.0], "goal": [1.0, 0.0], "body": 0.1},
        {"start": [0.0, 0.33], "goal": [0.0, 0.33], "body": 0.25},
        {"start": [0.5, -0.26], "goal": [0.5, -0.26], "body": [0.15, 0.15]}]
    scn = scenario_from_dict({"name": "hand-made", "dim": 2, "delta": 0.3, "solver": {"method": "centralized"},
                              "agents": agents})
    steps = 20
    states = np.zeros((steps + 1, 3, 4))
    states[:, 0, 0] = -1.0 + 0.1 * np.arange(steps + 1)
    states[:, 0, 2] = 1.0  # 1 m/s along x: Euler-consistent with zero inputs
    states[:, 1, :2] = [0.0, 0.33]
    states[:, 2, :2] = [0.5, -0.26]
    record = StepRecord(wall_time=0.0, agent_times=np.zeros(3), failures=0, fallback=np.zeros(3, bool),
                        max_slack=0.0, admm_iterations=None, repaired=False, primal_residuals=(),
                        dual_residuals=(), rho=())
    result = RunResult.create(scn, states, np.zeros((steps, 3, 2)), [record] * steps, [], False, 0.0)
    return write_run(result, tmp_path_factory.mktemp("pictures") / "hand-made")


def test_the_hand_made_run_counts_only_overlapping_bodies(crossing_run):
    run = load_run(crossing_run)
    counted = _collisions_at(run.positions, run.bodies)
    assert counted == {(k, 0, 1) for k in range(7, 14)} == {
        (k, i, j) for k in range(run.num_steps + 1) for i, j in [(0, 1), (0, 2), (1, 2)]
        if np.all(np.abs(run.positions[k, i] - run.positions[k, j]) < run.bodies[i] + run.bodies[j] - TOUCH)}
    assert run.summary["collisions"] == len(counted)


def test_snapshot_rectangles_overlap_exactly_at_counted_collisions(crossing_run):
    run = load_run(crossing_run)
    fig = plots.make_trajectory_figure(run, snapshots=run.num_steps + 1)  # every instant drawn
    drawn: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
    for patch in fig.axes[0].patches:
        gid = patch.get_gid() or ""
        if gid.startswith(f"{plots.GID_BODY}:"):
            _, agent, step = gid.split(":")
            drawn.setdefault(int(step), {})[int(agent)] = _rectangle(patch)
    assert sorted(drawn) == list(range(run.num_steps + 1))
    overlaps = set()
    for k, boxes in drawn.items():
        np.testing.assert_allclose([boxes[i][1] for i in range(3)], run.bodies)  # half-size b_i, not Δ
        centers, halves = (np.array([boxes[i][n] for i in range(3)]) for n in (0, 1))
        overlaps |= {(k, i, j) for i, j in _overlapping_pairs(centers, halves)}
    assert overlaps == _collisions_at(run.positions, run.bodies)
    labels = [text.get_text() for text in fig.axes[0].get_legend().get_texts()]
    assert any(plots.BODY_LABEL in label for label in labels)


def _animated_overlaps(run, ax) -> set[tuple[int, int, int]]:
    """Overlapping body rectangles of the animation's artists, frame by frame."""
    update = plots._planar_movers(ax, run, (0, 1), plots.agent_colors(run.num_agents))
    bodies = {int(p.get_gid().split(":")[1]): p for p in ax.patches
              if (p.get_gid() or "").startswith(f"{plots.GID_BODY}:")}
    overlaps = set()
    for k in range(run.num_steps + 1):
        update(k, 0)
        centers, halves = (np.array([_rectangle(bodies[i])[n] for i in range(run.num_agents)]) for n in (0, 1))
        overlaps |= {(k, i, j) for i, j in _overlapping_pairs(centers, halves)}
    return overlaps


def test_animation_rectangles_overlap_exactly_at_counted_collisions(crossing_run):
    run = load_run(crossing_run)
    ax = plots._new_figure(6.0, 5.0).add_subplot()
    assert _animated_overlaps(run, ax) == _collisions_at(run.positions, run.bodies)


def test_the_viewer_draws_bodies_and_marks_exactly_the_counted_collisions(crossing_run):
    run = load_run(crossing_run)
    fig = viewer.figure_dict(crossing_run)
    counted = _collisions_at(run.positions, run.bodies)
    roles = [(tr.get("meta") or {}).get("role") for tr in fig["data"]]
    box_ids = {n: fig["data"][n]["meta"]["agent"] for n, role in enumerate(roles) if role == "box"}
    assert fig["data"][roles.index("bodies-legend")]["name"] == viewer.BODIES_LEGEND
    for frame in fig["frames"]:
        k = int(frame["name"])
        red = set()
        for index, trace in zip(frame["traces"], frame["data"], strict=True):
            if index in box_ids:
                i = box_ids[index]
                xs, ys = [v for v in trace["x"] if v is not None], [v for v in trace["y"] if v is not None]
                half = np.array([max(xs) - min(xs), max(ys) - min(ys)]) / 2
                np.testing.assert_allclose(half, run.bodies[i], atol=1e-3)
                if trace["line"]["color"] == viewer._CLOSEST_COLOR:
                    red.add(i)
        assert red == {a for step, i, j in counted if step == k for a in (i, j)}


def test_a_collision_free_run_draws_no_overlap(pair_run):
    run = load_run(pair_run)
    ax = plots._new_figure(6.0, 5.0).add_subplot()
    assert _animated_overlaps(run, ax) == set()


def test_the_reader_takes_the_bodies_from_the_trajectory_then_the_scenario_then_delta(crossing_run, tmp_path):
    """``bodies`` in trajectory.npz wins (checked: (M, d), finite, > 0); without it the scenario's
    bodies; without a scenario, delta / 2 (a folder from before bodies existed)."""
    with np.load(crossing_run / "trajectory.npz") as data:
        arrays = {name: data[name] for name in data.files if name != "bodies"}
    folder = tmp_path / "bare"
    folder.mkdir()
    np.savez(folder / "trajectory.npz", **arrays)
    assert np.array_equal(viewer.load_run(folder).bodies, np.full((3, 2), 0.15))
    (folder / "scenario.yaml").write_text((crossing_run / "scenario.yaml").read_text())
    assert np.array_equal(load_run(folder).bodies, [[0.1, 0.1], [0.25, 0.25], [0.15, 0.15]])
    np.savez(folder / "trajectory.npz", **arrays, bodies=np.full((3, 2), 0.2))
    assert np.array_equal(load_run(folder).bodies, np.full((3, 2), 0.2))
    for bad in (np.full((2, 2), 0.2), np.zeros((3, 2))):
        np.savez(folder / "trajectory.npz", **arrays, bodies=bad)
        with pytest.raises(RunDataError, match="'bodies' must"):
            load_run(folder)
