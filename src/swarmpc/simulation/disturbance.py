"""Seeded uncertainty for the closed loop: process noise on the true state, measurement noise on
what the planner sees, and the planner's tightened bodies.

The draws come from generators seeded by the scenario's ``seed`` (one stream for process noise,
another for measurement noise, so switching one on does not change the other's draws); a run
with the same scenario is reproducible. With the default (all zero) block nothing is drawn and
the loop is the nominal one.
"""

from __future__ import annotations

import numpy as np

from swarmpc.config import Disturbance, Scenario
from swarmpc.model.agent_model import AgentModel, make_model

_PROCESS_STREAM = 1
_MEASUREMENT_STREAM = 2


def planner_bodies(scn: Scenario) -> np.ndarray:
    """(M, d) half-sizes of the bodies the planner keeps apart: each true body grown by half the
    tightening, so that every pair keeps its Delta_ij plus the tightening (and every obstacle half
    the tightening more). Collisions are still counted between the true bodies."""
    return scn.bodies + 0.5 * scn.disturbance.tightening


def planner_delta(scn: Scenario) -> np.ndarray:
    """(d,) largest Delta_ij the planner keeps between two agents, per axis: the sum of the two
    largest planner bodies on each axis (twice the body of a lone agent). With default bodies it
    is the true delta plus the tightening, bit for bit."""
    bodies = planner_bodies(scn)
    if len(bodies) < 2:
        return 2.0 * bodies[0]
    top = np.sort(bodies, axis=0)[-2:]
    return top[0] + top[1]


class DisturbanceModel:
    """Draws the per-step process noise (M, n) and the measurement noise (M, n) of a run.

    The noise is on the states of the agents' ``model`` (None: the double integrator of ``dim``,
    whose state layout alone is used): each state gets the position and velocity standard
    deviations of the ``disturbance`` block where the model holds a position and a velocity
    (:meth:`~swarmpc.model.agent_model.AgentModel.state_at` of the two).
    """

    def __init__(self, config: Disturbance, num_agents: int, dim: int, seed: int,
                 model: AgentModel | None = None) -> None:
        self.config = config
        self.model = model if model is not None else make_model("double_integrator", dim, 1.0)
        self.shape = (num_agents, self.model.state_dim)
        self.dim = dim
        self._process = np.random.default_rng([seed, _PROCESS_STREAM])
        self._measurement = np.random.default_rng([seed, _MEASUREMENT_STREAM])

    @classmethod
    def from_scenario(cls, scn: Scenario) -> DisturbanceModel:
        return cls(scn.disturbance, scn.num_agents, scn.dim, scn.seed, scn.agent_model())

    def _std(self, position: float, velocity: float) -> np.ndarray:
        return self.model.state_at(np.full(self.dim, position), np.full(self.dim, velocity))

    def process(self) -> np.ndarray:
        """Additive noise on the true state after one step (zeros when process noise is off)."""
        c = self.config
        if not c.has_process_noise:
            return np.zeros(self.shape)
        std = self._std(c.process_position_std, c.process_velocity_std)
        return self._process.standard_normal(self.shape) * std

    def measurement(self) -> np.ndarray:
        """Noise on the state the planner sees this step (zeros when measurement noise is off)."""
        c = self.config
        if not c.has_measurement_noise:
            return np.zeros(self.shape)
        std = self._std(c.measurement_position_std, c.measurement_velocity_std)
        return self._measurement.standard_normal(self.shape) * std
