"""Deadlock rules for cars: a car's detour is a pose it drives to forwards (it cannot side-step), and
two cars meeting head-on on one line, which stall for good without the rules, pass each other
with them, collision-free by the exact rectangle distance recomputed from the flown states."""

from __future__ import annotations

import numpy as np
import pytest

from swarmpc.config import scenario_from_dict
from swarmpc.model.agent_model import make_model
from swarmpc.model.footprint import rectangle_distance
from swarmpc.scenarios import CARS
from swarmpc.simulation.deadlock import DeadlockPolicy, DeadlockResolver, rest_state
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import agent_footprints, agent_poses


def test_a_car_rests_facing_the_way_it_is_sent_and_a_point_agent_just_rests() -> None:
    car = make_model("car", 2, 0.1, "rk4")
    point = make_model("double_integrator", 2, 0.1)
    direction = np.array([0.0, -2.0])
    state = rest_state(car, np.array([1.0, 2.0]), direction)
    assert np.allclose(state, [1.0, 2.0, -np.pi / 2, 0.0])
    assert np.allclose(rest_state(point, np.array([1.0, 2.0]), direction), point.state_at(np.array([1.0, 2.0])))


def test_a_stalled_car_is_sent_forwards_right_not_sideways() -> None:
    car = make_model("car", 2, 0.1, "rk4")
    policy = DeadlockPolicy(patience=2, keep_right_deg=0.0)
    resolver = DeadlockResolver(2, 2, policy, clearance=0.75, models=(car, car))
    states = np.array([[-0.45, 0.0, 0.0, 0.0], [0.45, 0.0, np.pi, 0.0]])  # nose to nose, at rest
    goals = np.array([[3.0, 0.0, 0.0, 0.0], [-3.0, 0.0, np.pi, 0.0]])
    for step in range(4):
        out = resolver.goals(step, states, goals)
    assert resolver.active.all()
    for i, sign in ((0, -1.0), (1, 1.0)):  # right of +x is -y, right of -x is +y
        offset = out[i, :2] - states[i, :2]
        assert np.sign(offset[1]) == sign and out[i, 3] == 0.0
        assert np.isclose(out[i, 2], np.arctan2(offset[1], offset[0]))  # faces the way it is sent


def _head_on(enabled: bool) -> tuple[dict, np.ndarray, np.ndarray]:
    agents = [{"model": "car", "start": [-3.0, 0.0, 0.0], "goal": [3.0, 0.0, 0.0]},
              {"model": "car", "start": [3.0, 0.0, 180.0], "goal": [-3.0, 0.0, 180.0]}]
    data = {"name": "head-on-cars", "dim": 2, **CARS, "delta": 0.3, "seed": 0, "agents": agents,
            "workspace": {"lower": [-4.0, -2.0], "upper": [4.0, 2.0]}, "deadlock": {"enabled": enabled},
            "stop": {**CARS["stop"], "max_steps": 160}}
    scn = scenario_from_dict(data)
    result = simulate(scn)
    models = scn.agent_models()
    return result.summary, agent_poses(models, result.states), agent_footprints(models, scn.bodies)


@pytest.mark.parametrize("enabled", [True, False])
def test_head_on_cars_pass_only_with_the_rules(enabled: bool) -> None:
    summary, poses, sizes = _head_on(enabled)
    least = float(rectangle_distance(poses[:, 0], sizes[0], poses[:, 1], sizes[1], signed=True).min())
    assert least >= 0.05 - 1e-6  # d_min of the car built-ins, kept with or without the rules
    assert summary["all_reached"] is enabled
