"""Car agents from a scenario file to a run folder: the schema, the refusals, the run folder's
arrays, and the built-in car scenarios driven to their goal poses without a collision."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from conftest import cli_in_process, load_folder
from swarmpc.config import ScenarioError, load_scenario, scenario_from_dict, scenario_to_yaml
from swarmpc.model.car import KinematicCar
from swarmpc.model.footprint import footprint_vertices, polygon_distance, polygon_vertices, rectangle_distance
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.contract import conditions_of
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.metrics import heading_error
from swarmpc.simulation.results import write_run

PREFIX = "swarmpc: error: "

BASE: dict[str, Any] = {
    "name": "cars",
    "dim": 2,
    "weights": {"Q": 1.0, "R": 1.0, "Qf": 20.0},
    "solver": {"method": "centralized"},
    "limits": {"accel": 1.0, "speed": 1.0},
    "workspace": {"lower": [-4.0, -4.0], "upper": [4.0, 4.0]},
    "stop": {"goal_tolerance": 0.1, "heading_tolerance_deg": 10.0, "max_steps": 60},
    "agents": [
        {"model": "car", "start": [-2.0, -0.4, 0.0], "goal": [2.0, -0.4, 0.0]},
        {"model": {"type": "car", "length": 0.8, "width": 0.4}, "start": [2.0, 0.4, 180.0], "goal": [-2.0, 0.4, 180]},
        {"start": [0.0, -2.0], "goal": [0.0, 2.0]},
    ],
}


def _scenario(**changes: Any) -> dict[str, Any]:
    data = copy.deepcopy(BASE)
    for key, value in changes.items():
        target = data
        *parents, last = key.split(".")
        for part in parents:
            target = target[int(part)] if part.isdigit() else target[part]
        target[int(last) if last.isdigit() else last] = value
    return data


# ------------------------------------------------------------------ schema
def test_a_car_scenario_loads_with_poses_in_degrees_and_round_trips():
    scn = scenario_from_dict(_scenario())
    assert scn.has_cars and [a.model.is_car for a in scn.agents] == [True, True, False]
    starts, goals = scn.start_states(), scn.goal_states()
    assert starts.shape == goals.shape == (3, 4)
    assert goals[1, 2] == pytest.approx(math.pi) and goals[2].tolist() == [0.0, 2.0, 0.0, 0.0]
    models = scn.agent_models()
    assert isinstance(models[0], KinematicCar) and models[1].footprint == (0.8, 0.4)
    assert models[0].max_steer == pytest.approx(math.radians(35.0))
    assert scn.bodies[1].tolist() == [0.4, 0.2]  # half the footprint
    again = scenario_from_dict(yaml.safe_load(scenario_to_yaml(scn)))
    assert again == scn and again.agents[1].model.length == 0.8


def test_later_pair_copies_are_refused_for_a_swarm_of_point_agents(tmp_path: Path):
    scn = builtin_scenario("swap-2d").with_updates(**{"solver.method": "admm"})
    data = yaml.safe_load(scenario_to_yaml(scn))
    data["solver"].setdefault("admm", {})["pair_copies"] = "later"
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code, stderr = cli_in_process("run", str(path), "--out", str(out), "--quiet")
    assert code == 2 and len(stderr.splitlines()) == 1 and stderr.startswith(PREFIX + "solver.admm.pair_copies: ")
    assert not out.exists()


def test_the_probe_of_own_optima_is_refused_for_a_swarm_with_cars(tmp_path: Path):
    data = yaml.safe_load(scenario_to_yaml(builtin_scenario("intersection")))
    data["solver"].setdefault("admm", {})["independent_first"] = True
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code, stderr = cli_in_process("run", str(path), "--out", str(out), "--quiet")
    assert code == 2 and len(stderr.splitlines()) == 1
    assert stderr.startswith(PREFIX + "solver.admm.independent_first: ")
    assert not out.exists()


def test_parking_by_admm_holds_each_pairs_copy_in_the_later_car_only():
    assert builtin_scenario("parking").solver.admm.pair_copies == "later"
    assert builtin_scenario("intersection").solver.admm.pair_copies == "both"


def test_point_only_scenarios_are_written_without_a_model_key():
    scn = builtin_scenario("swap-2d")
    assert not scn.has_cars and "model" not in scenario_to_yaml(scn)
    assert "cars" not in conditions_of(scn)


BAD = [
    ({"dim": 3, "workspace": None}, "agents[0].model"),
    ({"weights.Qf": "lqr"}, "weights.Qf"),
    ({"solver.method": "admm", "solver.deadline": 0.1}, "solver.deadline"),
    ({"agents.2.start": [0.0, -2.0, 90.0]}, "agents[2].start"),
    ({"agents.0.start": [-2.0, -0.4]}, "agents[0].start"),
    ({"agents.1.start": [-1.7, -0.3, 30.0]}, "agents[1].start"),  # footprints overlap at the starts
    ({"agents.2.goal": [1.8, -0.3]}, "agents[2].goal"),  # a point body inside a car's footprint
    ({"obstacles": [{"box": {"center": [2.3, -0.4], "half_size": [0.2, 0.2]}}]}, "agents[0].goal"),
    ({"agents.0.model": {"type": "car", "rear_overhang": 2.0}}, "agents[0].model.rear_overhang"),
    ({"agents.2.model": {"type": "double_integrator", "length": 1.0}}, "agents[2].model.length"),
    ({"agents.0.body": 0.2}, "agents[0].body"),
    ({"plant": {"type": "mujoco"}}, "plant.type"),
]


@pytest.mark.parametrize("changes,field", BAD, ids=[field for _, field in BAD])
def test_bad_car_scenarios_fail_in_one_line_naming_the_field(tmp_path: Path, changes: dict, field: str):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_scenario(**changes)))
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    assert str(caught.value).startswith(f"{field}: ") or str(caught.value).startswith(f"{field}."), caught.value
    out = tmp_path / "out"
    code, stderr = cli_in_process("run", str(path), "--out", str(out), "--quiet")
    lines = stderr.splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(PREFIX + field), stderr
    assert not out.exists()


def test_admm_with_cars_takes_either_local_step():
    assert scenario_from_dict(_scenario(**{"solver.method": "admm"})).solver.method == "admm"
    assert scenario_from_dict(_scenario(**{"solver.method": "admm", "solver.local": "qp"})).solver.local == "qp"


# ------------------------------------------------------------------ a short run's folder
def _recount(states: np.ndarray, scn: Any) -> tuple[np.ndarray, np.ndarray, int, float]:
    """(poses, sizes, collisions, min distance) recomputed from states by each agent's own model."""
    poses = np.zeros((*states.shape[:2], 3))
    for i, model in enumerate(scn.agent_models()):
        poses[:, i] = model.pose(states[:, i]) if hasattr(model, "pose") else np.column_stack(
            [states[:, i, :2], np.zeros(len(states))])
    sizes = 2.0 * scn.bodies
    count, least = 0, np.inf
    for i in range(scn.num_agents):
        for j in range(i + 1, scn.num_agents):
            distance = rectangle_distance(poses[:, i], sizes[i], poses[:, j], sizes[j], signed=True)
            count += int(np.sum(distance < -1e-9))
            least = min(least, float(distance.min()))
    return poses, sizes, count, least


def test_a_short_car_run_writes_states_poses_and_footprints_that_agree(tmp_path: Path):
    scn = scenario_from_dict(_scenario(**{"stop.max_steps": 12}))
    result = simulate(scn)
    folder = write_run(result, tmp_path / "run")
    summary, arrays = load_folder(folder)
    states, inputs = arrays["states"], arrays["inputs"]
    assert states.shape == (13, 3, 4) and inputs.shape == (12, 3, 2)
    models = scn.agent_models()
    for k in range(12):  # every agent follows its own model exactly
        for i, model in enumerate(models):
            assert np.allclose(model.step(states[k, i], inputs[k, i]), states[k + 1, i], atol=1e-12)
    poses, sizes, collisions, least = _recount(states, scn)
    assert np.allclose(arrays["poses"], poses) and np.allclose(arrays["footprints"], sizes)
    assert arrays["footprints"][:2].tolist() == [[0.7, 0.45], [0.8, 0.4]]
    assert summary["collisions"] == collisions == 0
    assert summary["min_footprint_distance"] == pytest.approx(least)
    assert np.allclose(arrays["goals"][:, 2], [0.0, math.pi, 0.0])
    assert load_scenario(folder / "scenario.yaml") == scn


# ------------------------------------------------------------------ whole runs
def _assert_at_goal_poses_without_collision(folder: Path) -> None:
    summary, arrays = load_folder(folder)
    scn = load_scenario(folder / "scenario.yaml")
    states, goals = arrays["states"], arrays["goals"]
    _, _, collisions, least = _recount(states, scn)
    assert collisions == 0 and least > 0 and summary["collisions"] == 0
    position = np.linalg.norm(states[-1, :, :2] - goals[:, :2], axis=1)
    assert np.all(position <= scn.stop.goal_tolerance + 1e-9), position
    for i, agent in enumerate(scn.agents):
        if agent.model.is_car:
            assert np.degrees(heading_error(states[-1, i, 2], goals[i, 2])) <= scn.stop.heading_tolerance_deg + 1e-9
    assert summary["all_reached"]
    for G, g in scn.obstacle_halfspaces():
        polygon = polygon_vertices(G, g)
        for i, agent in enumerate(scn.agents):
            if agent.model.is_car:
                assert polygon_distance(footprint_vertices(arrays["poses"][:, i], arrays["footprints"][i]),
                                        polygon).min() > 0


@pytest.mark.loop
@pytest.mark.parametrize("name", ["intersection", "mixed"])
def test_car_builtins_reach_every_goal_pose_without_a_collision(tmp_path: Path, name: str):
    out = tmp_path / name
    code, stderr = cli_in_process("run", name, "--out", str(out), "--quiet")
    assert code == 0, stderr
    _assert_at_goal_poses_without_collision(out)


def test_the_run_paragraph_reports_the_footprint_distance_for_cars(tmp_path: Path):
    from swarmpc.cli import result_paragraph

    summary = simulate(scenario_from_dict(_scenario(**{"stop.max_steps": 3}))).summary
    text = result_paragraph(summary, tmp_path)
    assert f"min footprint distance {summary['min_footprint_distance']:.3f} m" in text
    assert "(b_i + b_j)" not in text
