"""swarmpc: distributed model predictive control for robot swarms.

Consensus ADMM over per-agent optimal-control problems, with collisions excluded exactly by the
dual (OBCA) reformulation of the signed distance.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from swarmpc.config import Scenario, ScenarioError, load_scenario, scenario_from_dict

__all__ = ["Scenario", "ScenarioError", "load_scenario", "scenario_from_dict"]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    """The configuration names, imported on first use: ``import swarmpc`` stays instant, so the
    command line can take Ctrl-C from its very first moment (:mod:`swarmpc._launch`)."""
    if name in __all__:
        from swarmpc import config

        return getattr(config, name)
    raise AttributeError(f"module 'swarmpc' has no attribute {name!r}")
