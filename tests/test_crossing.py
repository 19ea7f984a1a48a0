"""The ``crossing`` built-in: cars queued on the four arms of a crossing, all going straight across.
Its layout (valid, footprints apart at the starts and at the goals by the exact distance, straight
lanes) and a whole run driven to every goal pose without a collision."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from conftest import cli_in_process, load_folder
from swarmpc.config import ScenarioError, load_scenario
from swarmpc.model.footprint import rectangle_distance
from swarmpc.scenarios import BUILTINS, builtin_parameters, builtin_scenario
from swarmpc.simulation.metrics import heading_error


def _poses(scn, states: np.ndarray) -> np.ndarray:
    """(..., M, 3) footprint-centre poses of every car, from states (..., M, 4) by its own model."""
    return np.stack([model.pose(states[..., i, :]) for i, model in enumerate(scn.agent_models())], axis=-2)


def _least_gap(poses: np.ndarray, sizes: np.ndarray) -> float:
    """Smallest signed exact distance between two footprints over every pair and pose row."""
    i, j = np.triu_indices(poses.shape[-2], k=1)
    return float(rectangle_distance(poses[..., i, :], sizes[i], poses[..., j, :], sizes[j], signed=True).min())


def test_crossing_is_listed_and_takes_the_number_of_cars():
    assert "crossing" in BUILTINS and builtin_parameters("crossing") == ("agents", "delta", "seed")
    assert builtin_scenario("crossing").num_agents == 8  # the default, as many cars as intersection has
    with pytest.raises(ScenarioError, match="^dim: not an argument"):
        builtin_scenario("crossing", dim=2)
    with pytest.raises(ScenarioError, match="^agents: must be between 1 and"):
        builtin_scenario("crossing", agents=0)


@pytest.mark.parametrize("agents", [1, 2, 3, 4, 5, 8, 12, 16, 64])
def test_starts_and_goals_keep_the_footprints_apart(agents: int):
    scn = builtin_scenario("crossing", agents=agents)
    assert scn.num_agents == agents and all(a.model.is_car for a in scn.agents)
    assert scn.solver.method == "centralized" and scn.name == f"crossing-{agents}"
    lower, upper = scn.bounds()
    sizes = 2.0 * scn.bodies
    for states in (scn.start_states(), scn.goal_states()):
        poses = _poses(scn, states)
        if agents > 1:  # the queued cars: 1.5 m between rear axles, so 0.8 m between a 0.7 m long pair
            assert _least_gap(poses, sizes) >= 0.8 - 1e-9
        reach = np.hypot(*(sizes / 2).T)[:, None]  # no footprint corner outside the workspace
        assert np.all(poses[:, :2] - reach >= lower) and np.all(poses[:, :2] + reach <= upper)


@pytest.mark.parametrize("agents", [4, 8, 16])
def test_every_car_goes_straight_across_in_its_lane(agents: int):
    scn = builtin_scenario("crossing", agents=agents)
    starts, goals = scn.start_states(), scn.goal_states()
    assert np.allclose(starts[:, 2], goals[:, 2])  # no car turns
    heading = np.stack([np.cos(starts[:, 2]), np.sin(starts[:, 2])], axis=1)
    across = goals[:, :2] - starts[:, :2]
    lateral = heading[:, 0] * across[:, 1] - heading[:, 1] * across[:, 0]
    assert np.allclose(lateral, 0.0, atol=1e-6) and np.all(np.sum(across * heading, axis=1) > 6.0 - 1e-6)
    # right-hand traffic: every lane 0.75 m right of the centre line, so a car's lane misses the centre
    offset = heading[:, 0] * starts[:, 1] - heading[:, 1] * starts[:, 0]
    assert np.allclose(offset, -0.75)
    arms = [round(math.degrees(t)) % 360 for t in starts[:, 2]]
    assert sorted(set(arms)) == [0, 90, 180, 270] and all(arms.count(a) == agents // 4 for a in set(arms))
    # the first car of an arm takes the farthest goal: no car has to pass another
    along_start = np.sum(starts[:, :2] * heading, axis=1)
    along_goal = np.sum(goals[:, :2] * heading, axis=1)
    for t in np.unique(np.round(starts[:, 2], 6)):
        arm = np.isclose(starts[:, 2], t)
        order = np.argsort(-along_start[arm])  # front of the queue first
        assert np.all(np.diff(along_goal[arm][order]) < 0)


def _recount(folder: Path) -> tuple[int, float, np.ndarray, np.ndarray]:
    """Collisions, least footprint gap, final position errors and final heading errors [deg],
    recomputed from the saved states with each car's own model."""
    scn = load_scenario(folder / "scenario.yaml")
    _, arrays = load_folder(folder)
    states, goals = arrays["states"], arrays["goals"]
    poses, sizes = _poses(scn, states), 2.0 * scn.bodies
    i, j = np.triu_indices(scn.num_agents, k=1)
    gaps = rectangle_distance(poses[:, i], sizes[i], poses[:, j], sizes[j], signed=True)
    position = np.linalg.norm(states[-1, :, :2] - goals[:, :2], axis=1)
    heading = np.degrees(heading_error(states[-1, :, 2], goals[:, 2]))
    return int(np.sum(gaps < -1e-9)), float(gaps.min()), position, heading


@pytest.mark.loop
def test_four_cars_cross_to_every_goal_without_a_collision(tmp_path: Path):
    out = tmp_path / "crossing"
    code, stderr = cli_in_process("run", "crossing", "--agents", "4", "--out", str(out), "--quiet")
    assert code == 0, stderr
    summary, _ = load_folder(out)
    scn = load_scenario(out / "scenario.yaml")
    collisions, least, position, heading = _recount(out)
    assert collisions == 0 and least > 0 and summary["collisions"] == 0
    assert summary["min_footprint_distance"] == pytest.approx(least)
    assert np.all(position <= scn.stop.goal_tolerance + 1e-9), position
    assert np.all(heading <= scn.stop.heading_tolerance_deg + 1e-9), heading
    assert summary["all_reached"] and summary["steps"] < scn.stop.max_steps
