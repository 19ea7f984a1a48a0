"""The scenario's disturbance block: validation, seeded noise stored so that the saved states
follow the dynamics plus the saved disturbances, and a tightened planner delta."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import load_folder, recount_collisions
from swarmpc.config import ScenarioError, scenario_from_dict
from swarmpc.simulation.disturbance import DisturbanceModel, planner_delta
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import write_run

TWO = {
    "name": "pass-2",
    "delta": 0.2,
    "seed": 3,
    "workspace": {"lower": [-2.0, -2.0], "upper": [2.0, 2.0]},
    "weights": {"Q": 1.0, "R": 0.5, "Qf": 5.0},
    "agents": [{"start": [-1.2, 0.15], "goal": [1.2, 0.15]}, {"start": [1.2, -0.15], "goal": [-1.2, -0.15]}],
    "solver": {"method": "centralized", "initial_guess": "straight"},
    "stop": {"max_steps": 60, "goal_tolerance": 0.1, "speed_tolerance": 0.2},
}
NOISE = {"process_position_std": 0.003, "process_velocity_std": 0.01,
         "measurement_position_std": 0.003, "measurement_velocity_std": 0.01}


def test_default_is_off_and_bad_values_name_the_field():
    scn = scenario_from_dict(TWO)
    assert not scn.disturbance.has_process_noise and not scn.disturbance.has_measurement_noise
    assert np.all(DisturbanceModel.from_scenario(scn).process() == 0)
    with pytest.raises(ScenarioError, match=r"^disturbance\.process_position_std: "):
        scenario_from_dict({**TWO, "disturbance": {"process_position_std": -0.1}})
    with pytest.raises(ScenarioError, match=r"^disturbance\.bogus: unknown key"):
        scenario_from_dict({**TWO, "disturbance": {"bogus": 1}})
    with pytest.raises(ScenarioError, match=r"^disturbance\.tightening: "):
        scenario_from_dict({**TWO, "disturbance": {"tightening": float("nan")}})


def test_noise_is_seeded_and_streams_are_independent():
    scn = scenario_from_dict({**TWO, "disturbance": NOISE})
    a, b = DisturbanceModel.from_scenario(scn), DisturbanceModel.from_scenario(scn)
    assert np.array_equal(a.process(), b.process())
    only_process = scenario_from_dict({**TWO, "disturbance": {"process_position_std": 0.003,
                                                              "process_velocity_std": 0.01}})
    c = DisturbanceModel.from_scenario(only_process)
    assert np.array_equal(c.process(), DisturbanceModel.from_scenario(scn).process())
    other_seed = scenario_from_dict({**TWO, "seed": 4, "disturbance": NOISE})
    assert not np.array_equal(DisturbanceModel.from_scenario(other_seed).process(), a.process())


def test_disturbed_run_saves_disturbances_consistent_with_the_dynamics(tmp_path):
    scn = scenario_from_dict({**TWO, "disturbance": {**NOISE, "tightening": 0.05}})
    assert np.allclose(planner_delta(scn), 0.25)
    folder = write_run(simulate(scn), tmp_path / "noisy")
    summary, arrays = load_folder(folder)
    states, inputs, w = arrays["states"], arrays["inputs"], arrays["disturbances"]
    T = inputs.shape[0]
    assert w.shape == (T, 2, 4) and T >= 1
    dt = float(arrays["dt"])
    nominal = np.concatenate([states[:-1, :, :2] + dt * states[:-1, :, 2:],
                              states[:-1, :, 2:] + dt * inputs], axis=2)
    assert np.allclose(states[1:], nominal + w, atol=1e-12)
    assert not np.allclose(states[1:], nominal, atol=1e-4)  # the noise is really there
    assert np.std(w[:, :, :2]) == pytest.approx(0.003, rel=0.35)
    assert summary["disturbance"]["tightening"] == 0.05
    collisions, _ = recount_collisions(states, arrays["delta"])
    assert summary["collisions"] == collisions  # counted against the true delta
    assert summary["all_reached"]


def test_nominal_run_has_no_disturbances_array(tmp_path):
    folder = write_run(simulate(scenario_from_dict(TWO)), tmp_path / "nominal")
    summary, arrays = load_folder(folder)
    assert "disturbances" not in arrays and summary["disturbance"] is None


def _min_separation(states: np.ndarray) -> float:
    """Smallest inf-norm distance between the two agents over the run, from the saved states."""
    return float(np.min(np.max(np.abs(states[:, 0, :2] - states[:, 1, :2]), axis=1)))


def test_tightening_keeps_the_noisy_agents_further_apart():
    # head-on: 0.1 m apart across the line of travel, so they must swerve to pass at >= delta
    crossing = {**TWO, "agents": [{"start": [-1.2, 0.05], "goal": [1.2, 0.05]},
                                  {"start": [1.2, -0.05], "goal": [-1.2, -0.05]}]}
    runs = {}
    for tightening in (0.0, 0.1):
        scn = scenario_from_dict({**crossing, "disturbance": {**NOISE, "tightening": tightening}})
        result = simulate(scn)
        assert result.summary["all_reached"]  # they really passed each other
        assert result.disturbances is not None and np.abs(result.disturbances).max() > 0
        runs[tightening] = result
    # the same seed: the same noise draws, only the planner's delta differs
    assert np.array_equal(runs[0.0].disturbances[:5], runs[0.1].disturbances[:5])
    loose, tight = _min_separation(runs[0.0].states), _min_separation(runs[0.1].states)
    assert tight > loose + 0.05, (loose, tight)
    assert tight > 0.2 + 0.1 - 0.02  # about the tightened delta, up to the noise
