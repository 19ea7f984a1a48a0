"""The MuJoCo plant: rigid bodies, force actuators with drag and lag, MuJoCo's own contact list."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import yaml

from conftest import load_folder, recount_collisions, run_cli
from swarmpc.config import ScenarioError, scenario_from_dict
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.mujoco_plant import MuJoCoPlant
from swarmpc.simulation.results import write_run

PHYSICS = {"type": "mujoco", "drag": 0.5, "lag_s": 0.05}


class AgentContacts:
    """Reads MuJoCo's contact list after every physics step: pairs of agent bodies in contact."""

    def __init__(self) -> None:
        self.calls = 0
        self.touching: list[tuple[int, str, str]] = []

    def __call__(self, model, data) -> None:
        self.calls += 1
        for k in range(data.ncon):
            first, second = model.geom(data.contact[k].geom1).name, model.geom(data.contact[k].geom2).name
            if first.startswith("agent") and second.startswith("agent"):
                self.touching.append((self.calls, first, second))


def test_paper_2d_in_mujoco_reaches_every_goal_without_a_contact(tmp_path):
    scn = builtin_scenario("paper-2d").with_updates(**{"solver.method": "centralized", "plant": PHYSICS})
    contacts = AgentContacts()
    plant = MuJoCoPlant(scn, on_physics_step=contacts)
    result = simulate(scn, plant=plant)
    summary, arrays = load_folder(write_run(result, tmp_path / "run"))
    steps = summary["steps"]
    assert summary["all_reached"]
    assert contacts.calls == steps * 50  # every physics step of the run was read
    assert contacts.touching == [], f"agent bodies touched: {contacts.touching[:3]}"
    collisions, ratio = recount_collisions(arrays["states"], arrays["delta"])
    assert collisions == 0 and ratio >= 1.0
    assert summary["plant"]["type"] == "mujoco" and summary["plant"]["agent_contacts"] == 0
    # the contract: states[k+1] = f(states[k], inputs[k]) + disturbances[k], f the nominal model
    model = DoubleIntegrator(scn.dim, scn.dt, scn.discretization)
    nominal = model.step(arrays["states"][:-1], arrays["inputs"])
    assert np.allclose(arrays["states"][1:], nominal + arrays["disturbances"], rtol=0, atol=1e-12)
    assert np.abs(arrays["disturbances"]).max() > 1e-3  # drag and lag: the plant is not the model


def test_contacts_between_agent_bodies_are_detected():
    """The instrument of the test above: bodies driven into each other show up in data.contact."""
    scn = builtin_scenario("paper-2d").with_updates(plant={"type": "mujoco"})
    contacts = AgentContacts()
    plant = MuJoCoPlant(scn, on_physics_step=contacts)
    push = np.zeros((4, 2))
    push[0], push[1] = [5.0, 0.0], [-5.0, 0.0]  # agents 0 and 1 start 3 m apart on y = -1.5
    for _ in range(20):
        plant.step(push)
    assert {(a, b) for _, a, b in contacts.touching} == {("agent0", "agent1")}
    assert plant.contacts.agent_contacts > 0 and plant.contacts.first_agent_contact[1:] == (0, 1)
    gap = np.abs(plant.true_states()[0, 0] - plant.true_states()[1, 0])
    assert gap == pytest.approx(scn.delta_vector[0], abs=0.01)  # boxes of half-size delta/2 stopped each other


def test_bodies_follow_the_inputs_with_drag_and_lag():
    scn = builtin_scenario("paper-3d").with_updates(plant={"type": "mujoco", "drag": 1.0, "lag_s": 0.2})
    plant = MuJoCoPlant(scn)
    start = plant.reset()
    assert np.array_equal(plant.step(np.zeros((4, 3))), start)  # no gravity, nothing moves by itself
    for _ in range(50):
        states = plant.step(np.tile([1.0, 0.0, 0.0], (4, 1)))
    # steady state of v' = a - drag v: 1 m/s along x
    assert np.allclose(states[:, 3], 1.0, atol=0.02) and np.allclose(states[:, 4:], 0.0)


def test_a_polytope_obstacle_is_a_mesh_with_its_vertices():
    triangle = {"polytope": {"G": [[1, 0], [0, 1], [-1, -1]], "g": [1, 1, 0]}}  # corners (1,-1), (-1,1), (1,1)
    scn = scenario_from_dict({
        "obstacles": [triangle], "plant": {"type": "mujoco"},
        "agents": [{"start": [-2, -2], "goal": [2, -2]}],
    })
    plant = MuJoCoPlant(scn)
    obstacle = plant.model.geom("obstacle0")
    assert obstacle.type == mujoco.mjtGeom.mjGEOM_MESH

    def touches(x: float, y: float) -> bool:
        plant.data.qpos[:] = [x, y]
        mujoco.mj_forward(plant.model, plant.data)
        return plant.data.ncon > 0

    assert touches(0.5, 0.5) and touches(-0.1, -0.1)  # inside, and body overlapping the hypotenuse
    assert not touches(-0.5, -0.5) and not touches(1.2, 1.2)


@pytest.mark.parametrize(
    ("plant", "message"),
    [
        ({"type": "double_integrator", "drag": 0.5}, "plant.drag: only with plant.type: mujoco"),
        ({"lag_s": 0.1}, "plant.lag_s: only with plant.type: mujoco"),
        ({"type": "mujoco", "mass": 0}, "plant.mass"),
        ({"type": "mujoco", "physics_dt": True}, "plant.physics_dt: expected a number"),
        ({"type": "bullet"}, "plant.type"),
    ],
)
def test_a_bad_plant_block_is_one_line_naming_the_field(plant, message):
    with pytest.raises(ScenarioError) as err:
        builtin_scenario("paper-2d").with_updates(plant=plant)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_a_mujoco_block_takes_defaults_and_round_trips():
    scn = builtin_scenario("paper-2d").with_updates(**{"plant.type": "mujoco"})
    assert scn.plant.model_dump() == {"type": "mujoco", "physics_dt": 0.002, "drag": 0.0, "lag_s": 0.0, "mass": 1.0}
    assert scenario_from_dict(yaml.safe_load(yaml.safe_dump(scn.model_dump()))) == scn


@pytest.mark.loop
def test_the_command_line_runs_a_mujoco_plant(tmp_path):
    scenario = tmp_path / "swap.yaml"
    scenario.write_text(yaml.safe_dump({
        "name": "swap", "workspace": {"lower": [-3, -3], "upper": [3, 3]},
        "agents": [{"start": [-1.5, 0.05], "goal": [1.5, 0.05]}, {"start": [1.5, -0.05], "goal": [-1.5, -0.05]}],
        "solver": {"method": "centralized"}, "plant": {"type": "double_integrator"},
    }))
    done = run_cli("run", str(scenario), "--plant", "mujoco", "--out", str(tmp_path / "run"), "--quiet",
                   "--max-steps", "60")
    assert done.returncode == 0, done.stderr
    summary, arrays = load_folder(tmp_path / "run")
    assert summary["plant"]["type"] == "mujoco" and summary["plant"]["substeps"] == 50
    assert yaml.safe_load((tmp_path / "run" / "scenario.yaml").read_text())["plant"]["type"] == "mujoco"
    assert arrays["disturbances"].shape == (summary["steps"], 2, 4)
    assert recount_collisions(arrays["states"], arrays["delta"])[0] == 0
