"""What the controller's inputs drive: the plant of the closed loop.

A :class:`Plant` holds the true states of all agents. The loop asks it what the sensors report
(:meth:`Plant.measure`), hands the measurement to the controller and applies the controller's
inputs for one sampling period (:meth:`Plant.step`). Two plants come with swarmpc:

* :class:`DoubleIntegratorPlant`: the planner's own agent models (each agent's,
  :meth:`~swarmpc.config.Scenario.agent_models`: the double integrator, or a car's kinematic
  bicycle), exactly, plus the scenario's seeded ``disturbance`` noise (the default plant);
* :class:`~swarmpc.simulation.mujoco_plant.MuJoCoPlant`: rigid bodies in the MuJoCo physics
  engine (``plant: {type: mujoco}``), imported only when a scenario asks for it.

Whatever the plant, a run folder keeps ``states[k+1] = f(states[k], inputs[k]) + disturbances[k]``
with ``f`` the nominal model: a plant reports in :attr:`Plant.last_disturbance` how far its last
step landed from the nominal one, and :attr:`Plant.nominal` says whether there is anything to
report at all.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from swarmpc.config import PlantConfig, Scenario
from swarmpc.model.agent_model import AgentModel
from swarmpc.simulation.disturbance import DisturbanceModel


class Plant(Protocol):
    """The true system of the closed loop: M agents with the states of the scenario's agent model
    (n entries each: [p, v], 2d, for the double integrator)."""

    nominal: bool
    """True when the states follow the nominal model exactly (no disturbances to record)."""
    last_disturbance: np.ndarray
    """(M, n) true state after the last :meth:`step` minus the nominal model's step from the state
    before it (zeros before the first step)."""

    def reset(self) -> np.ndarray:
        """Put every agent at its start; return the true states (M, n)."""
        ...

    def step(self, inputs: np.ndarray) -> np.ndarray:
        """Apply ``inputs`` (M, m) for one sampling period; return the true states (M, n)."""
        ...

    def measure(self) -> np.ndarray:
        """The states (M, n) the sensors report now (the true ones plus any measurement noise)."""
        ...

    def describe(self) -> dict[str, Any]:
        """What ``summary.json`` records of the plant (its settings and anything it counted)."""
        ...


def checked_inputs(inputs: Any, num_agents: int, dim: int) -> np.ndarray:
    """``inputs`` as a finite float array of shape (M, ``dim``), ``dim`` the model's input size;
    ValueError (one line) otherwise."""
    try:
        array = np.asarray(inputs, float)
    except (TypeError, ValueError):
        raise ValueError(f"inputs: expected an array of numbers of shape ({num_agents}, {dim})") from None
    if array.shape != (num_agents, dim):
        raise ValueError(f"inputs: expected shape ({num_agents}, {dim}) (agents, dim), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError("inputs: must be finite (found NaN or inf)")
    return array


def model_groups(models: tuple[AgentModel, ...]) -> list[tuple[AgentModel, np.ndarray]]:
    """The agents grouped by equal model: (model, agent indices) in order of first appearance."""
    groups: list[tuple[AgentModel, list[int]]] = []
    for i, model in enumerate(models):
        for known, members in groups:
            if known == model:
                members.append(i)
                break
        else:
            groups.append((model, [i]))
    return [(model, np.array(members)) for model, members in groups]


class DoubleIntegratorPlant:
    """The planner's agent models (the discrete double integrator; a car's kinematic bicycle), with
    the scenario's process and measurement noise.

    Each agent steps with its own model; agents of one model step in one call (a swarm of point
    agents is one call, as it always was).

    The noise comes from :class:`~swarmpc.simulation.disturbance.DisturbanceModel`, seeded by the
    scenario: measurement noise is drawn in :meth:`measure`, process noise in :meth:`step`, so a
    loop that measures, plans and steps draws them in the same order every run (and nothing at
    all while the ``disturbance`` block is off). :meth:`reset` restarts both streams.
    """

    def __init__(self, scn: Scenario) -> None:
        self.scenario = scn
        self.model = scn.agent_model()
        self.groups = model_groups(scn.agent_models())
        self.nominal = not scn.disturbance.has_process_noise
        self.noise = DisturbanceModel.from_scenario(scn)
        self.states = scn.start_states()
        self.last_disturbance = np.zeros_like(self.states)

    def reset(self) -> np.ndarray:
        self.noise = DisturbanceModel.from_scenario(self.scenario)
        self.states = self.scenario.start_states()
        self.last_disturbance = np.zeros_like(self.states)
        return self.states

    def measure(self) -> np.ndarray:
        return self.states + self.noise.measurement()

    def step(self, inputs: np.ndarray) -> np.ndarray:
        control = checked_inputs(inputs, self.scenario.num_agents, self.model.input_dim)
        disturbance = self.noise.process()
        if len(self.groups) == 1:
            following = self.groups[0][0].step(self.states, control)
        else:
            following = np.empty_like(self.states)
            for model, members in self.groups:
                following[members] = model.step(self.states[members], control[members])
        self.states = following + disturbance
        self.last_disturbance = disturbance
        return self.states

    def describe(self) -> dict[str, Any]:
        block = self.scenario.plant
        return (block if block.type == "double_integrator" else PlantConfig()).model_dump()


def make_plant(scn: Scenario) -> Plant:
    """The scenario's plant (``plant.type``); MuJoCo is imported only when it is asked for."""
    if scn.plant.type == "mujoco":
        from swarmpc.simulation.mujoco_plant import MuJoCoPlant

        return MuJoCoPlant(scn)
    return DoubleIntegratorPlant(scn)
