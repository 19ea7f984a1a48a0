"""Centralised MPC: one NLP over all agents, the optimality reference and a baseline."""

from __future__ import annotations

import time

import numpy as np

from swarmpc.formulation.nlp import NLPSolution, shift_blocks
from swarmpc.formulation.ocp import OCPSettings, agent_pairs, build_centralized, pair_tag
from swarmpc.model.geometry import as_bodies
from swarmpc.solvers.base import PlanStep, fallback_plan
from swarmpc.solvers.guesses import agent_guess_blocks, pair_guess_blocks


class CentralizedSolver:
    """Solves the global OCP with IPOPT; built once, warm-started from its shifted solution.

    ``delta`` is one Delta (d,) for every pair, or the agents' body half-sizes (M, d): pair (i, j)
    keeps Delta_ij = b_i + b_j and agent i's obstacles are grown by b_i
    (:func:`swarmpc.model.geometry.as_bodies`).
    """

    def __init__(
        self, settings: OCPSettings, num_agents: int, delta: np.ndarray, seed_duals: bool = True
    ) -> None:
        self.settings = settings
        self.seed_duals = seed_duals
        self.num_agents = num_agents
        self.bodies = as_bodies(delta, num_agents)
        self.pairs = agent_pairs(num_agents)
        self.pair_deltas = np.array([self.bodies[i] + self.bodies[j] for i, j in self.pairs]).reshape(-1, settings.dim)
        self.agent_settings = [settings.for_body(b) for b in self.bodies]
        self.nlp = build_centralized(settings, num_agents, bodies=self.bodies)
        self._previous: NLPSolution | None = None
        self._previous_plan: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        self._previous = None
        self._previous_plan = None

    def initial_point(self, guess: np.ndarray, seed: bool = True) -> dict[str, np.ndarray]:
        """Primal guess from state guesses (M, N+1, n): trajectories and certificates."""
        s, first = self.settings, self.settings.first_constrained_step
        point: dict[str, np.ndarray] = {}
        for i in range(self.num_agents):
            point.update(agent_guess_blocks(str(i), guess[i], self.agent_settings[i], seed and self.seed_duals))
        for (i, j), delta in zip(self.pairs, self.pair_deltas, strict=True):
            offsets = s.model.position(guess[i, first:]) - s.model.position(guess[j, first:])
            point.update(pair_guess_blocks(pair_tag(i, j), offsets, delta, s, seed and self.seed_duals))
        return point

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> PlanStep:
        """One MPC step from measured ``states`` (M, n) towards ``goals`` (M, n)."""
        started = time.perf_counter()
        params: dict[str, np.ndarray] = {"delta": self.pair_deltas.T}
        for i in range(self.num_agents):
            params[f"x0{i}"] = states[i]
            params[f"goal{i}"] = goals[i]
        point = self.initial_point(guess, seed=self._previous is None)  # else shifted L, A below
        lam_x = lam_g = None
        if self._previous is not None:
            shifted = shift_blocks(self._previous.x)
            for name, value in shifted.items():
                if name.startswith(("L", "A")):
                    point[name] = value
            lam_g = self.nlp.g_layout.pack(shift_blocks(self.nlp.g_layout.unpack(self._previous.lam_g)))
            lam_x = self.nlp.x_layout.pack(shift_blocks(self.nlp.x_layout.unpack(self._previous.lam_x)))
        solution = self.nlp.solve(params, point, lam_x, lam_g)
        model, M = self.settings.model, self.num_agents
        plans_x = np.empty((M, self.settings.horizon + 1, model.state_dim))
        plans_u = np.empty((M, self.settings.horizon, model.input_dim))
        fallback = np.zeros(M, bool)
        if solution.success:
            self._previous = solution
            for i in range(M):
                plans_x[i] = solution.x[f"X{i}"].T
                plans_u[i] = solution.x[f"U{i}"].T
        else:
            self._previous = None
            fallback[:] = True
            for i in range(M):
                previous = self._previous_plan
                plans_x[i], plans_u[i] = fallback_plan(
                    states[i],
                    previous[0][i] if previous else None,
                    previous[1][i] if previous else None,
                    self.settings,
                )
        self._previous_plan = (plans_x, plans_u)
        slack = [v.max() for k, v in solution.x.items() if k.startswith("A") and v.size]
        elapsed = time.perf_counter() - started
        return PlanStep(
            states=plans_x,
            inputs=plans_u,
            predicted_cost=solution.cost,
            max_slack=max(0.0, float(max(slack))) if slack and solution.success else 0.0,
            wall_time=elapsed,
            agent_times=np.full(M, solution.solve_time / M),
            failures=0 if solution.success else 1,
            fallback=fallback,
            critical_path=elapsed,  # one process solves the whole step: all of it is on the path
        )
