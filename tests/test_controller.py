"""swarmpc.Controller: the closed loop's controller, stepped by hand, is the one simulate() runs."""

from __future__ import annotations

import multiprocessing

import numpy as np
import pytest

import swarmpc
from swarmpc.config import scenario_from_dict
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.controller import Controller
from swarmpc.simulation.loop import goal_reached, simulate
from swarmpc.simulation.plant import DoubleIntegratorPlant
from swarmpc.solvers.executors import ProcessExecutor

SWAP = {
    "name": "swap",
    "dim": 2,
    "workspace": {"lower": [-3, -3], "upper": [3, 3]},
    "agents": [{"start": [-1.0, 0.0], "goal": [1.0, 0.1]}, {"start": [1.0, 0.0], "goal": [-1.0, -0.1]}],
    "solver": {"method": "centralized"},
    "stop": {"max_steps": 150},
}


def test_a_controller_stepped_by_hand_reproduces_simulate():
    scn = builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 20})
    result = simulate(scn)
    model = DoubleIntegrator(scn.dim, scn.dt, scn.discretization)
    states = scn.start_states()
    with swarmpc.Controller(scn) as mpc:
        assert mpc.plan is None and mpc.last_record is None
        for k in range(20):
            inputs = mpc.step(states)
            assert np.array_equal(inputs, result.inputs[k]), f"step {k}: other inputs than simulate()"
            assert mpc.plan.states.shape == (4, scn.horizon + 1, 4) and mpc.plan.inputs.shape == (4, scn.horizon, 2)
            assert np.allclose(mpc.plan.states[:, 0], states, atol=1e-9)  # the plan starts at the measurement
            assert mpc.last_record.admm_iterations == result.records[k].admm_iterations
            states = model.step(states, inputs)
            assert np.array_equal(states, result.states[k + 1])
    assert mpc.steps == 20


def test_simulate_with_the_default_plant_given_explicitly_is_unchanged():
    scn = builtin_scenario("paper-2d").with_updates(**{
        "stop.max_steps": 15, "solver.method": "centralized",
        "disturbance": {"process_position_std": 0.002, "measurement_position_std": 0.003},
    })
    default, explicit = simulate(scn), simulate(scn, plant=DoubleIntegratorPlant(scn))
    assert np.array_equal(default.states, explicit.states)
    assert np.array_equal(default.disturbances, explicit.disturbances)
    assert default.summary["plant"] == {"type": "double_integrator", "physics_dt": None, "drag": None,
                                        "lag_s": None, "mass": None}


def test_goals_given_to_step_retarget_the_agents():
    scn = scenario_from_dict(SWAP)
    new_goals = np.array([[-1.0, -1.5], [1.0, 1.5]])  # positions: at rest there
    targets = np.hstack([new_goals, np.zeros((2, 2))])
    plant = DoubleIntegratorPlant(scn)
    states = plant.reset()
    with Controller(scn) as mpc:
        for _ in range(400):
            if goal_reached(states, targets, scn).all():
                break
            states = plant.step(mpc.step(plant.measure(), goals=new_goals))
    assert goal_reached(states, targets, scn).all()
    assert np.linalg.norm(states[:, :2] - scn.goal_states()[:, :2], axis=1).min() > 1.0


def test_with_closes_the_executor_it_created_and_not_one_it_was_given():
    scn = scenario_from_dict({**SWAP, "solver": {"method": "admm"}})
    with Controller(scn, executor="process") as mpc:
        workers = list(mpc.solver.executor._processes)
        assert workers and all(w.is_alive() for w in workers)
        assert mpc.step(scn.start_states()).shape == (2, 2)
    assert not any(w.is_alive() for w in workers)
    assert not set(workers) & set(multiprocessing.active_children())

    given = ProcessExecutor(workers=1)
    try:
        with Controller(scn, executor=given) as mpc:
            mpc.step(scn.start_states())
        assert all(w.is_alive() for w in given._processes), "the caller's executor was closed"
    finally:
        given.close()


@pytest.mark.parametrize(
    ("measured", "message"),
    [
        (np.zeros((3, 4)), "measured_states: expected shape (2, 4)"),
        (np.zeros((2, 2)), "measured_states: expected shape (2, 4)"),
        (np.zeros(8), "measured_states: expected shape (2, 4)"),
        (np.full((2, 4), np.nan), "measured_states: must be finite"),
        ([["a", "b", "c", "d"]] * 2, "measured_states: expected an array of numbers"),
    ],
    ids=["too many agents", "positions only", "flat", "NaN", "text"],
)
def test_wrong_measured_states_are_refused_in_one_line(measured, message):
    with Controller(scenario_from_dict(SWAP)) as mpc:
        with pytest.raises(ValueError) as err:
            mpc.step(measured)
        assert str(err.value).startswith(message) and "\n" not in str(err.value)
        with pytest.raises(ValueError, match=r"^goals: expected shape \(2, 4\) or \(2, 2\)"):
            mpc.step(np.zeros((2, 4)), goals=np.zeros((2, 3)))
        assert mpc.steps == 0


def test_a_closed_controller_refuses_to_step_and_closing_twice_is_harmless():
    mpc = Controller(scenario_from_dict(SWAP))
    mpc.close()
    mpc.close()
    with pytest.raises(RuntimeError, match="closed"):
        mpc.step(np.zeros((2, 4)))


def test_from_file_and_make_step(tmp_path):
    import yaml

    path = tmp_path / "swap.yaml"
    path.write_text(yaml.safe_dump(SWAP))
    with Controller.from_file(path) as mpc:
        first = mpc.make_step(mpc.scenario.start_states())
    assert first.shape == (2, 2) and np.all(np.isfinite(first))
    assert first[0, 0] > 0 > first[1, 0]  # each heads for its goal
