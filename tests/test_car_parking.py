"""The cars' SE(2) guesses in the closed loop (swarmpc.simulation.guessing.CarRoutes) and the
``parking`` built-in: cars leaving and entering bays between dividers.

Clearances are recomputed with the exact rectangle-polygon distance of swarmpc.model.footprint,
independently of the planner's validity check.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

pytest.importorskip("ompl")

from conftest import cli_in_process, load_folder, one_car_scenario  # noqa: E402
from swarmpc.config import Scenario, load_scenario  # noqa: E402
from swarmpc.formulation.footprint_ocp import FootprintAgent  # noqa: E402
from swarmpc.formulation.ocp import OCPSettings  # noqa: E402
from swarmpc.model.footprint import (  # noqa: E402
    footprint_vertices,
    polygon_distance,
    polygon_vertices,
    rectangle_distance,
)
from swarmpc.scenarios import builtin_scenario  # noqa: E402
from swarmpc.simulation.guessing import GuessProvider  # noqa: E402
from swarmpc.simulation.metrics import heading_error  # noqa: E402
from swarmpc.solvers import car_guess as car_guess_module  # noqa: E402
from swarmpc.solvers.base import PlanStep  # noqa: E402
from swarmpc.solvers.footprint_central import straight_guess  # noqa: E402
from swarmpc.solvers.registry import agent_settings  # noqa: E402

WALL = {"box": {"center": [0.0, 0.0], "half_size": [0.2, 1.0]}}
"""A wall across the straight line from the car's start to its goal."""
PEN = [  # three walls and the workspace's right edge close the goal [2, 0, 0] in
    {"box": {"center": [2.3, 0.75], "half_size": [0.7, 0.1]}},
    {"box": {"center": [2.3, -0.75], "half_size": [0.7, 0.1]}},
    {"box": {"center": [1.5, 0.0], "half_size": [0.1, 0.85]}},
]


def _one_car(obstacles: list[dict[str, Any]], **changes: Any) -> Scenario:
    """One car from [-2, 0] heading +x to [2, 0] heading +x, RRT guesses, a horizon long enough for
    the guess to pass the wall."""
    return one_car_scenario(obstacles, horizon=100, name="car-guess", **changes)


def _guess(scn: Scenario, strategy: str | None = None) -> tuple[GuessProvider, np.ndarray]:
    """A provider of the scenario and its first guess (1, N+1, 4)."""
    provider = GuessProvider(scn, OCPSettings.from_scenario(scn), strategy)
    return provider, provider.guesses(scn.start_states(), scn.goal_states(), None)


def _clearance(scn: Scenario, states: np.ndarray) -> np.ndarray:
    """Least exact signed distance (K,) of the car's footprint at each state to the obstacles."""
    model = scn.agent_models()[0]
    corners = footprint_vertices(model.pose(states), np.array(model.footprint))
    return np.min([polygon_distance(corners, polygon_vertices(G, g), signed=True)
                   for G, g in scn.obstacle_halfspaces()], axis=0)


# ------------------------------------------------------------------ the wired guess
def test_a_cars_rrt_guess_drives_round_the_wall_the_straight_guess_runs_into():
    scn = _one_car([WALL])
    provider, guess = _guess(scn)
    states = guess[0]
    assert np.array_equal(states[0], scn.start_states()[0])
    assert states[-1, 0] > 0.5  # past the wall
    assert _clearance(scn, states).min() >= 0.5 * scn.d_min
    assert provider.rrt_stats is not None and provider.rrt_stats["fresh"] >= 1
    _, straight = _guess(scn, "straight")
    assert _clearance(scn, straight[0]).min() < 0  # the straight line goes through the wall


def test_the_car_guess_is_the_same_for_the_same_seed():
    scn = _one_car([WALL])
    assert np.array_equal(_guess(scn)[1], _guess(scn)[1])


def test_the_car_guesses_do_not_depend_on_the_machines_speed(monkeypatch: pytest.MonkeyPatch):
    """On a machine where every planner iteration takes 4 ms (1.6 s for the 400 of one attempt)
    the iterations, not the clock, still end the parking built-in's searches: same guesses."""
    scn = builtin_scenario("parking")
    idle = _guess(scn)[1]
    ticks = [0]

    def slow_clock() -> float:
        ticks[0] += 1
        return 0.004 * ticks[0]

    monkeypatch.setattr(car_guess_module, "time", SimpleNamespace(perf_counter=slow_clock))
    provider, slow = _guess(scn)
    assert ticks[0] > 250 * len(scn.agents)  # the searches ran on the slow clock, past the old 1 s limit
    assert provider.rrt_stats is not None and provider.rrt_stats["failed"] == 0
    assert np.array_equal(slow, idle)


def test_auto_plans_a_car_in_se2_when_the_scenario_has_obstacles():
    scn = _one_car([WALL], solver={"method": "centralized", "initial_guess": "auto"})
    assert np.array_equal(_guess(scn)[1], _guess(_one_car([WALL]))[1])
    assert _clearance(scn, _guess(scn)[1][0]).min() >= 0.5 * scn.d_min


def test_the_path_is_planned_once_and_followed_from_where_the_car_is():
    scn = _one_car([WALL])
    provider, first = _guess(scn)
    moved = first[:, 30]  # the car drove 3 s along its guess
    again = provider.guesses(moved, scn.goal_states(), None)
    assert provider.rrt_stats == {"fresh": 1, "reused": 1, "failed": 0}
    assert np.array_equal(again[0, 0], moved[0])
    assert again[0, -1, 0] > 0.5 and _clearance(scn, again[0]).min() >= 0.5 * scn.d_min
    other = scn.goal_states().copy()
    other[0, 1] = 1.5  # a new goal: planned afresh
    provider.guesses(moved, other, None)
    assert provider.rrt_stats == {"fresh": 2, "reused": 1, "failed": 0}


def test_a_walled_in_goal_falls_back_to_the_straight_guess_without_planning_again():
    scn = _one_car(PEN, solver={"method": "centralized", "initial_guess": "rrt", "rrt_time_budget": 0.005})
    provider, guess = _guess(scn)
    car = FootprintAgent(agent_settings(scn)[0])
    assert np.array_equal(guess[0], straight_guess(car, scn.start_states()[0], scn.goal_states()[0]))
    assert provider.rrt_stats == {"fresh": 1, "reused": 0, "failed": 1}
    provider.guesses(scn.start_states(), scn.goal_states(), None)
    assert provider.rrt_stats == {"fresh": 1, "reused": 1, "failed": 1}


def test_a_car_follows_its_own_shifted_plan_while_the_solves_succeed():
    scn = _one_car([WALL])
    provider, guess = _guess(scn)
    plan = PlanStep(states=guess, inputs=np.zeros((1, scn.horizon, 2)), predicted_cost=0.0, max_slack=0.0,
                    wall_time=0.0, agent_times=np.zeros(1), failures=0, fallback=np.array([False]))
    shifted = provider.guesses(guess[:, 1], scn.goal_states(), plan)
    assert np.array_equal(shifted[0], np.vstack([guess[0, 1:], guess[0, -1:]]))
    assert provider.rrt_stats == {"fresh": 1, "reused": 0, "failed": 0}  # no guess made
    failed = replace(plan, failures=1, fallback=np.array([True]))
    fresh = provider.guesses(guess[:, 1], scn.goal_states(), failed)
    assert np.array_equal(fresh[0, 0], guess[0, 1]) and provider.rrt_stats["reused"] == 1


def test_straight_strategy_keeps_the_straight_car_guess():
    scn = _one_car([WALL], solver={"method": "centralized", "initial_guess": "straight"})
    provider, guess = _guess(scn)
    car = FootprintAgent(agent_settings(scn)[0])
    assert np.array_equal(guess[0], straight_guess(car, scn.start_states()[0], scn.goal_states()[0]))
    assert provider.rrt_stats is None


# ------------------------------------------------------------------ the parking built-in
def _bays(scn: Scenario) -> tuple[np.ndarray, float]:
    """x of the dividers (sorted) and the height of their tops."""
    boxes = [(o.box.center, o.box.half_size) for o in scn.obstacles if o.box is not None]
    return np.sort([c[0] for c, _ in boxes]), max(c[1] + h[1] for c, h in boxes)


def _in_a_bay(scn: Scenario, pose: np.ndarray, model: Any) -> bool:
    """Whether the car's footprint centre lies between two neighbouring dividers, below their tops."""
    dividers, top = _bays(scn)
    x, y, _ = model.pose(np.append(pose, 0.0))
    return bool(y < top and np.any((dividers[:-1] < x) & (x < dividers[1:])))


def test_parking_has_two_cars_leaving_bays_and_two_entering_them_with_rrt_guesses():
    scn = builtin_scenario("parking")
    models = scn.agent_models()
    assert scn.num_agents == 4 and all(a.model.is_car for a in scn.agents)
    assert scn.solver.initial_guess == "rrt"
    starts, goals = scn.start_states(), scn.goal_states()
    leaving = [_in_a_bay(scn, starts[i, :3], m) and not _in_a_bay(scn, goals[i, :3], m) for i, m in enumerate(models)]
    entering = [_in_a_bay(scn, goals[i, :3], m) and not _in_a_bay(scn, starts[i, :3], m) for i, m in enumerate(models)]
    assert sum(leaving) == 2 and sum(entering) == 2
    dividers, _ = _bays(scn)
    bay = np.diff(dividers).min()
    assert models[0].width < bay - 0.1 < 2 * models[0].width  # room for one car, not for two side by side


@pytest.mark.loop
def test_parking_reaches_every_goal_pose_without_a_collision(tmp_path: Path):
    out = tmp_path / "parking"
    code, stderr = cli_in_process("run", "parking", "--out", str(out), "--quiet")
    assert code == 0, stderr
    summary, arrays = load_folder(out)
    scn = load_scenario(out / "scenario.yaml")
    states, goals = arrays["states"], arrays["goals"]
    models = scn.agent_models()
    poses = np.stack([m.pose(states[:, i]) for i, m in enumerate(models)], axis=1)
    sizes = np.array([m.footprint for m in models])
    assert np.allclose(arrays["poses"], poses) and np.allclose(arrays["footprints"], sizes)
    least = min(float(rectangle_distance(poses[:, i], sizes[i], poses[:, j], sizes[j], signed=True).min())
                for i in range(4) for j in range(i + 1, 4))
    assert least >= scn.d_min - 1e-6 and summary["collisions"] == 0
    assert summary["min_footprint_distance"] == pytest.approx(least)
    for G, g in scn.obstacle_halfspaces():
        polygon = polygon_vertices(G, g)
        for i in range(4):
            assert polygon_distance(footprint_vertices(poses[:, i], sizes[i]), polygon, signed=True).min() \
                >= scn.d_min - 1e-6
    assert summary["all_reached"]
    position = np.linalg.norm(states[-1, :, :2] - goals[:, :2], axis=1)
    assert np.all(position <= scn.stop.goal_tolerance + 1e-9), position
    heading = np.degrees(heading_error(states[-1, :, 2], goals[:, 2]))
    assert np.all(heading <= scn.stop.heading_tolerance_deg + 1e-9), heading
