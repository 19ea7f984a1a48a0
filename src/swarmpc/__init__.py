"""swarmpc: distributed model predictive control for robot swarms.

Consensus ADMM over per-agent optimal-control problems, with collisions excluded exactly by the
dual (OBCA) reformulation of the signed distance.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from swarmpc.config import Scenario, ScenarioError, load_scenario, scenario_from_dict
    from swarmpc.simulation.controller import Controller

    __version__: str

__all__ = ["Controller", "Scenario", "ScenarioError", "load_scenario", "scenario_from_dict"]


def __getattr__(name: str) -> Any:
    """The public names (configuration, :class:`Controller`), imported on first use: ``import
    swarmpc`` stays instant, so the command line can take Ctrl-C from its very first moment
    (:mod:`swarmpc._launch`).
    ``__version__`` is read from the installed package's metadata, so the version is defined once,
    in ``pyproject.toml``."""
    if name == "__version__":
        return _installed_version()
    if name == "Controller":
        from swarmpc.simulation.controller import Controller

        return Controller
    if name in __all__:
        from swarmpc import config

        return getattr(config, name)
    raise AttributeError(f"module 'swarmpc' has no attribute {name!r}")


def _installed_version() -> str:
    """The version of the installed ``swarmpc`` distribution (``0+unknown`` when the sources run
    without being installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("swarmpc")
    except PackageNotFoundError:
        return "0+unknown"
