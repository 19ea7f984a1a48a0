"""The solvers a scenario can name (``solver.method``), each built from the scenario's options.

The simulation layer never builds a concrete solver: it asks :func:`build_solver` for the
scenario's method and talks to what it gets through the :class:`~swarmpc.solvers.base.MPCSolver`
protocol. A :class:`SolverRegistry` maps each method to a builder that takes

* the scenario's ``solver`` section (:class:`swarmpc.config.SolverConfig`, validated),
* the agents' :class:`~swarmpc.formulation.ocp.OCPSettings`,
* the agents' body half-sizes (M, d) (pair (i, j) keeps b_i + b_j apart), and
* an executor for the local solves, or None.

The registry is immutable: :meth:`SolverRegistry.register` returns a new registry, so a program
that adds a method passes its own registry to :func:`build_solver` and nothing global changes.
:data:`SOLVERS` holds the methods of this package.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from swarmpc.config import SolverConfig
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver
from swarmpc.solvers.base import MPCSolver
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.executors import Executor

SolverBuilder = Callable[[SolverConfig, OCPSettings, np.ndarray, "Executor | None"], MPCSolver]
"""``builder(options, settings, bodies, executor)`` -> a solver (see the module docstring)."""


@dataclass(frozen=True)
class SolverRegistry:
    """Solver builders by method name (immutable; :meth:`register` returns a new registry)."""

    builders: Mapping[str, SolverBuilder] = field(default_factory=lambda: types.MappingProxyType({}))

    def register(self, method: str, builder: SolverBuilder) -> SolverRegistry:
        """A registry with ``method`` built by ``builder`` (replacing any builder of that name)."""
        return SolverRegistry(types.MappingProxyType({**self.builders, method: builder}))

    @property
    def methods(self) -> tuple[str, ...]:
        """The registered method names, in registration order."""
        return tuple(self.builders)

    def build(
        self, method: str, options: SolverConfig, settings: OCPSettings, bodies: np.ndarray,
        executor: Executor | None = None,
    ) -> MPCSolver:
        """The solver of ``method`` for the agents of ``bodies`` (M, d); ValueError (one line) for
        a method nobody registered."""
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


SOLVERS = SolverRegistry().register("admm", admm_solver).register("centralized", centralized_solver)
"""The methods of ``solver.method``."""


def build_solver(
    method: str, options: SolverConfig, settings: OCPSettings, bodies: np.ndarray,
    executor: Executor | None = None, registry: SolverRegistry = SOLVERS,
) -> MPCSolver:
    """The solver of ``method`` from ``registry`` (default: :data:`SOLVERS`); see
    :meth:`SolverRegistry.build`."""
    return registry.build(method, options, settings, bodies, executor)
