"""swarmpc: distributed model predictive control for robot swarms.

Consensus ADMM over per-agent optimal-control problems, with collisions excluded exactly by the
dual (OBCA) reformulation of the signed distance.
"""

from swarmpc.config import Scenario, ScenarioError, load_scenario, scenario_from_dict

__all__ = ["Scenario", "ScenarioError", "load_scenario", "scenario_from_dict"]
__version__ = "0.1.0"
