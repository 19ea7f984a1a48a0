"""The solvers a scenario can name (``solver.method``), each built from the scenario's options.

The simulation layer never builds a concrete solver: it asks :func:`build_solver` for the
scenario's method and talks to what it gets through the :class:`~swarmpc.solvers.base.MPCSolver`
protocol. A :class:`SolverRegistry` maps each method to a builder that takes

* the scenario's ``solver`` section (:class:`swarmpc.config.SolverConfig`, validated),
* the agents' :class:`~swarmpc.formulation.ocp.OCPSettings`,
* the agents' body half-sizes (M, d) (pair (i, j) keeps b_i + b_j apart), and
* an executor for the local solves, or None.

A swarm whose agents have their own models (cars among them) is built by a second kind of
builder, registered with :meth:`SolverRegistry.register_footprint`: it takes the per-agent
settings instead of the shared ones (:class:`FootprintBuilder`). A method without one refuses
such a swarm in one line.

The registry is immutable: :meth:`SolverRegistry.register` returns a new registry, so a program
that adds a method passes its own registry to :func:`build_solver` and nothing global changes.
:data:`SOLVERS` holds the methods of this package.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from swarmpc.config import Scenario, SolverConfig
from swarmpc.formulation.footprint_ocp import FootprintAgent, FootprintSwarm, OrientedBody
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver
from swarmpc.solvers.base import MPCSolver
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.executors import Executor
from swarmpc.solvers.footprint_admm import FootprintADMMMPCSolver, FootprintADMMOptions, FootprintADMMSolver
from swarmpc.solvers.footprint_central import FootprintCentralSolver, FootprintMPCSolver

SolverBuilder = Callable[[SolverConfig, OCPSettings, np.ndarray, "Executor | None"], MPCSolver]
"""``builder(options, settings, bodies, executor)`` -> a solver (see the module docstring)."""

FootprintBuilder = Callable[[SolverConfig, "tuple[OCPSettings, ...]", np.ndarray, "Executor | None"], MPCSolver]
"""``builder(options, agents, bodies, executor)`` -> a solver for a swarm whose agents have their
own models: ``agents`` holds each agent's settings (its model among them), ``bodies`` (M, 2) the
point agents' half-sizes (a car's row is half its footprint and not used: its model has it)."""


@dataclass(frozen=True)
class SolverRegistry:
    """Solver builders by method name (immutable; :meth:`register` returns a new registry)."""

    builders: Mapping[str, SolverBuilder] = field(default_factory=lambda: types.MappingProxyType({}))
    footprint_builders: Mapping[str, FootprintBuilder] = field(default_factory=lambda: types.MappingProxyType({}))

    def register(self, method: str, builder: SolverBuilder) -> SolverRegistry:
        """A registry with ``method`` built by ``builder`` (replacing any builder of that name)."""
        return SolverRegistry(types.MappingProxyType({**self.builders, method: builder}), self.footprint_builders)

    def register_footprint(self, method: str, builder: FootprintBuilder) -> SolverRegistry:
        """A registry whose ``method`` builds swarms with per-agent models by ``builder``."""
        return SolverRegistry(self.builders, types.MappingProxyType({**self.footprint_builders, method: builder}))

    @property
    def methods(self) -> tuple[str, ...]:
        """The registered method names, in registration order."""
        return tuple(self.builders)

    def build(
        self, method: str, options: SolverConfig, settings: OCPSettings, bodies: np.ndarray,
        executor: Executor | None = None, agents: Sequence[OCPSettings] | None = None,
    ) -> MPCSolver:
        """The solver of ``method`` for the agents of ``bodies`` (M, d); ValueError (one line) for
        a method nobody registered. ``agents``: each agent's own settings, for a swarm whose agents
        have their own models (built by the method's :class:`FootprintBuilder`)."""
        if agents is not None:
            footprint = self.footprint_builders.get(method)
            if footprint is None:
                usable = ", ".join(self.footprint_builders) or "none"
                raise ValueError(f"solver.method: {method} does not take car agents yet; use {usable}")
            return footprint(options, tuple(agents), np.asarray(bodies, float), executor)
        builder = self.builders.get(method)
        if builder is None:
            raise ValueError(f"solver.method: unknown method {method!r} (registered: {', '.join(self.methods)})")
        bodies = np.asarray(bodies, float)
        if bodies.ndim != 2 or bodies.shape[1] != settings.dim:
            raise ValueError(f"bodies: expected (agents, {settings.dim}) half-sizes, got shape {bodies.shape}")
        return builder(options, settings, bodies, executor)


def admm_solver(
    options: SolverConfig, settings: OCPSettings, bodies: np.ndarray, executor: Executor | None = None
) -> ADMMSolver:
    """Consensus ADMM with the section's parameters (:meth:`ADMMConfig.from_options`). An
    executor given stays its creator's; without one the solver makes and closes its own."""
    config = ADMMConfig.from_options(options, settings.collision)
    return ADMMSolver(settings, len(bodies), bodies, config, executor)


def centralized_solver(
    options: SolverConfig, settings: OCPSettings, bodies: np.ndarray, executor: Executor | None = None
) -> CentralizedSolver:
    """One NLP over the whole swarm. It has no local solves, so ``executor`` is not used
    (the scenario's validation refuses a non-serial ``executor`` section with this method)."""
    return CentralizedSolver(settings, len(bodies), bodies, options.seed_duals)


def footprint_central_solver(
    options: SolverConfig, agents: tuple[OCPSettings, ...], bodies: np.ndarray, executor: Executor | None = None
) -> FootprintMPCSolver:
    """One NLP over a swarm of cars and point agents, the full OBCA between footprints
    (:class:`~swarmpc.solvers.footprint_central.FootprintCentralSolver`); a point agent's
    footprint is its body box (its row of ``bodies``). No local solves: ``executor`` is not used."""
    return FootprintMPCSolver(FootprintCentralSolver(_footprint_swarm(agents, bodies)))


def _footprint_swarm(agents: tuple[OCPSettings, ...], bodies: np.ndarray) -> FootprintSwarm:
    """The footprint swarm of per-agent settings; a point agent's footprint is its body box."""
    return FootprintSwarm(tuple(
        FootprintAgent(s) if isinstance(s.model, OrientedBody) else FootprintAgent(s, (bodies[i, 0], bodies[i, 1]))
        for i, s in enumerate(agents)
    ))


def footprint_admm_solver(
    options: SolverConfig, agents: tuple[OCPSettings, ...], bodies: np.ndarray, executor: Executor | None = None
) -> FootprintADMMMPCSolver:
    """Consensus ADMM over a swarm of cars and point agents, agreeing on footprint poses
    (:class:`~swarmpc.solvers.footprint_admm.FootprintADMMSolver`). Its local solves run on
    ``executor``; an executor given stays its creator's, without one the solver makes and closes its
    own serial one."""
    return FootprintADMMMPCSolver(FootprintADMMSolver(_footprint_swarm(agents, bodies),
                                                      FootprintADMMOptions.from_options(options), executor))


SOLVERS = (SolverRegistry().register("admm", admm_solver).register("centralized", centralized_solver)
           .register_footprint("centralized", footprint_central_solver)
           .register_footprint("admm", footprint_admm_solver))
"""The methods of ``solver.method``."""


def agent_settings(scn: Scenario) -> tuple[OCPSettings, ...]:
    """Each agent's OCP settings: the scenario's (:meth:`OCPSettings.from_scenario`) with the
    agent's own model, a car's parameters from its ``model`` section (one settings object per
    distinct model, shared by the agents that have it)."""
    point = OCPSettings.from_scenario(scn)
    cars: dict[object, OCPSettings] = {}
    out = []
    for agent in scn.agents:
        if not agent.model.is_car:
            out.append(point)
            continue
        if agent.model not in cars:
            cars[agent.model] = OCPSettings.from_scenario(scn, "car", **agent.model.car_params())
        out.append(cars[agent.model])
    return tuple(out)


def build_solver(
    method: str, options: SolverConfig, settings: OCPSettings, bodies: np.ndarray,
    executor: Executor | None = None, registry: SolverRegistry = SOLVERS,
) -> MPCSolver:
    """The solver of ``method`` from ``registry`` (default: :data:`SOLVERS`); see
    :meth:`SolverRegistry.build`."""
    return registry.build(method, options, settings, bodies, executor)
