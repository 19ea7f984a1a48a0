"""Distributed MPC by consensus ADMM (paper section III-E, Algorithms 1-2; Boyd et al. 2011 sec. 7).

Agent i holds its own trajectory and local copies of the positions of the agents it couples with.
Consensus is on positions at the constrained horizon steps, the only quantities the coupling
constraints read. One ADMM iteration:

1. local step (every agent, through the executor): minimise own cost
   + gamma_i'(v_i - z) + rho/2 ||v_i - z||^2 subject to own dynamics, bounds and OBCA against
   its copies;
2. averaging (the coordinator): z_j = mean of every copy of agent j's positions, its own included;
3. multiplier step (inside each agent, at its next call): gamma_i += rho (v_i - z).

It stops when the RMS primal residual ||v - z|| and the RMS dual residual rho ||z - z_prev|| are
both below ``tol`` (metres), or at ``max_iter``. Each agent then applies its OWN plan's first
input, which is always dynamically feasible. Multipliers and the agent's last solution are private
to the agent; the coordinator sees only what an agent transmits (its positions and its copies).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from swarmpc.formulation.nlp import CompiledNLP, NLPSolution, shift_blocks
from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.solvers.base import PlanStep, fallback_plan
from swarmpc.solvers.executors import Executor, SerialExecutor
from swarmpc.solvers.guesses import agent_guess_blocks, inputs_from_states, pair_certificates


@dataclass(frozen=True)
class ADMMConfig:
    """ADMM parameters (see the scenario's ``solver`` block)."""

    rho: float = 1.0
    max_iter: int = 100
    tol: float = 1e-3
    adaptive_rho: bool = False
    dynamic_copies: bool = True
    rho_bounds: tuple[float, float] = (1e-2, 1e3)


@dataclass(frozen=True)
class LocalRequest:
    """What the coordinator hands agent ``agent`` for one local step."""

    agent: int
    state: np.ndarray
    goal: np.ndarray
    delta: np.ndarray
    rho: float
    rho_previous: float
    new_step: bool
    z_own: np.ndarray
    neighbours: tuple[int, ...]
    z_neighbours: np.ndarray
    neighbour_states: np.ndarray
    guess: np.ndarray


@dataclass(frozen=True)
class LocalResult:
    """What agent ``agent`` transmits after its local step (plus its plan and diagnostics)."""

    agent: int
    own: np.ndarray
    copies: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    success: bool
    fallback: bool
    solve_time: float
    max_slack: float
    cost: float


@dataclass(frozen=True)
class LocalAgentFactory:
    """Picklable recipe for an agent's local solver (built where the agent lives)."""

    settings: OCPSettings
    slots: int
    dynamic_copies: bool = True

    def __call__(self, agent: int) -> LocalAgent:
        nlp = build_local(self.settings, self.slots, self.dynamic_copies)
        return LocalAgent(agent, self.settings, nlp, self.slots, self.dynamic_copies)


def trajectory_through(state: np.ndarray, z: np.ndarray, s: OCPSettings) -> np.ndarray:
    """A state trajectory (N+1, 2d) from ``state`` whose constrained positions are ``z`` (d, K):
    the guess for a dynamically constrained copy."""
    d, first = s.dim, s.first_constrained_step
    positions = np.empty((s.horizon + 1, d))
    positions[0] = state[:d]
    if first == 2:
        positions[1] = state[:d] + s.dt * state[d:]
    positions[first:] = z.T
    velocities = np.vstack([state[d:], np.diff(positions, axis=0)[1:] / s.dt, np.zeros((1, d))])[: s.horizon + 1]
    velocities[1:-1] = np.diff(positions, axis=0)[1:] / s.dt
    velocities[-1] = velocities[-2]
    return np.hstack([positions, velocities])


class LocalAgent:
    """One agent's private side of ADMM: its solver, multipliers and last solution."""

    def __init__(
        self, agent: int, settings: OCPSettings, nlp: CompiledNLP, slots: int, dynamic_copies: bool
    ) -> None:
        self.agent = agent
        self.dynamic_copies = dynamic_copies
        self.settings = settings
        self.nlp = nlp
        self.slots = slots
        self._gamma_own: np.ndarray | None = None
        self._gamma: dict[int, np.ndarray] = {}
        self._last: NLPSolution | None = None
        self._last_neighbours: tuple[int, ...] = ()
        self._last_sent: LocalResult | None = None
        self._plan: tuple[np.ndarray, np.ndarray] | None = None

    def _multipliers_step(self, request: LocalRequest) -> None:
        last = self._last_sent
        if request.new_step or last is None:
            shift = lambda y: np.concatenate([y[:, 1:], y[:, -1:]], axis=1)  # noqa: E731
            self._gamma_own = shift(self._gamma_own) if self._gamma_own is not None else None
            self._gamma = {j: shift(y) for j, y in self._gamma.items() if j in request.neighbours}
            return
        rho = request.rho_previous
        self._gamma_own = (self._gamma_own if self._gamma_own is not None else 0.0) + rho * (
            last.own - request.z_own
        )
        for slot, j in enumerate(request.neighbours):
            if j in self._last_neighbours:
                previous = last.copies[self._last_neighbours.index(j)]
                self._gamma[j] = self._gamma.get(j, 0.0) + rho * (previous - request.z_neighbours[slot])

    def _initial_point(self, request: LocalRequest) -> dict[str, np.ndarray]:
        s, first = self.settings, self.settings.first_constrained_step
        point = agent_guess_blocks("", request.guess, s)
        own = request.guess[first:, : s.dim]
        for slot, z in enumerate(request.z_neighbours):
            if self.dynamic_copies:
                trajectory = trajectory_through(request.neighbour_states[slot], z, s)
                point[f"Xc{slot}"] = trajectory.T
                point[f"Uc{slot}"] = inputs_from_states(trajectory, s).T
            else:
                point[f"C{slot}"] = z
            point[f"L{slot}"] = pair_certificates(own - z.T, request.delta)
        return point

    def _copy_positions(self, solution: NLPSolution, slot: int) -> np.ndarray:
        if self.dynamic_copies:
            return solution.x[f"Xc{slot}"][: self.settings.dim, self.settings.first_constrained_step :]
        return solution.x[f"C{slot}"]

    def solve(self, request: LocalRequest) -> LocalResult:
        """Multiplier update for the new consensus, then the local NLP."""
        s = self.settings
        self._multipliers_step(request)
        zeros = np.zeros_like(request.z_own)
        params: dict[str, np.ndarray | float] = {
            "x0": request.state,
            "goal": request.goal,
            "delta": request.delta,
            "rho": request.rho,
            "Z": request.z_own,
            "Y": self._gamma_own if self._gamma_own is not None else zeros,
        }
        for slot in range(self.slots):
            active = slot < len(request.neighbours)
            params[f"active{slot}"] = 1.0 if active else 0.0
            if self.dynamic_copies:
                params[f"x0c{slot}"] = request.neighbour_states[slot] if active else request.state
            if active:
                j = request.neighbours[slot]
                params[f"Z{slot}"] = request.z_neighbours[slot]
                params[f"Y{slot}"] = self._gamma.get(j, zeros)
        same_shape = request.neighbours == self._last_neighbours
        if self._last is not None and same_shape and not request.new_step:
            point: dict[str, np.ndarray] = dict(self._last.x)
        else:
            point = self._initial_point(request)
            if self._last is not None and request.new_step and same_shape:
                shifted = shift_blocks(self._last.x)
                point.update({k: v for k, v in shifted.items() if k.startswith(("L", "A"))})
        solution = self.nlp.solve(params, point)
        first = s.first_constrained_step
        n = len(request.neighbours)
        fallback = False
        slack: list[float] = []
        if solution.success:
            self._last = solution
            states, inputs = solution.x["X"].T, solution.x["U"].T
            copies = np.array([self._copy_positions(solution, slot) for slot in range(n)])
            copies = copies.reshape(n, s.dim, -1)
            slack = [float(solution.x[f"A{slot}"].max()) for slot in range(n) if f"A{slot}" in solution.x]
        elif not request.new_step and self._plan is not None and self._last_sent is not None and same_shape:
            # keep this step's last plan and transmit the same copies: a failed iterate
            # must not pull the consensus anywhere
            states, inputs = self._plan
            copies = self._last_sent.copies
            fallback = self._last_sent.fallback
        else:
            previous = self._plan if self._plan is not None else (None, None)
            states, inputs = fallback_plan(request.state, previous[0], previous[1], s)
            copies = request.z_neighbours.copy()
            fallback = True
            self._last = None
        self._plan = (states, inputs)
        result = LocalResult(
            agent=self.agent,
            own=states[first:, : s.dim].T.copy(),
            copies=copies,
            states=states,
            inputs=inputs,
            success=solution.success,
            fallback=fallback,
            solve_time=solution.solve_time,
            max_slack=float(max(slack)) if slack else 0.0,
            cost=solution.cost,
        )
        self._last_sent = result
        self._last_neighbours = request.neighbours
        return result


class ADMMSolver:
    """Consensus-ADMM distributed MPC over an executor (serial by default)."""

    def __init__(
        self,
        settings: OCPSettings,
        num_agents: int,
        delta: np.ndarray,
        config: ADMMConfig = ADMMConfig(),
        executor: Executor | None = None,
    ) -> None:
        self.settings = settings
        self.num_agents = num_agents
        self.delta = np.asarray(delta, float)
        self.config = config
        self.executor = executor or SerialExecutor()
        factory = LocalAgentFactory(settings, max(num_agents - 1, 1), config.dynamic_copies)
        self.executor.start(factory, range(num_agents))
        self._z: np.ndarray | None = None
        self._rho = config.rho

    def close(self) -> None:
        self.executor.close()

    def neighbours(self, states: np.ndarray) -> list[tuple[int, ...]]:
        """Agents each agent couples with: every other agent (the paper's all-to-all copies)."""
        return [tuple(j for j in range(self.num_agents) if j != i) for i in range(self.num_agents)]

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> PlanStep:
        """One MPC step: ADMM iterations until consensus, then every agent's own plan."""
        started = time.perf_counter()
        s, cfg, M = self.settings, self.config, self.num_agents
        first = s.first_constrained_step
        if self._z is None:
            z = np.transpose(guess[:, first:, : s.dim], (0, 2, 1)).copy()
        else:
            z = np.concatenate([self._z[:, :, 1:], self._z[:, :, -1:]], axis=2)
        neighbours = self.neighbours(states)
        rho = rho_previous = self._rho
        primal: list[float] = []
        dual: list[float] = []
        rhos: list[float] = []
        agent_times = np.zeros(M)
        failures = 0
        results: list[LocalResult] = []
        for iteration in range(cfg.max_iter):
            requests = [
                LocalRequest(
                    agent=i,
                    state=states[i],
                    goal=goals[i],
                    delta=self.delta,
                    rho=rho,
                    rho_previous=rho_previous,
                    new_step=iteration == 0,
                    z_own=z[i],
                    neighbours=neighbours[i],
                    z_neighbours=z[list(neighbours[i])] if neighbours[i] else np.zeros((0, s.dim, z.shape[2])),
                    neighbour_states=states[list(neighbours[i])],
                    guess=guess[i],
                )
                for i in range(M)
            ]
            results = self.executor.solve(requests)
            agent_times += [r.solve_time for r in results]
            failures += sum(not r.success for r in results)
            z_new, r_norm, count = self._average(results, neighbours)
            s_norm = rho * np.sqrt(np.sum(count[:, None, None] * (z_new - z) ** 2) / max(count.sum() * z[0].size, 1))
            primal.append(r_norm)
            dual.append(float(s_norm))
            rhos.append(rho)
            z = z_new
            if r_norm <= cfg.tol and s_norm <= cfg.tol:
                break
            rho_previous = rho
            if cfg.adaptive_rho:
                if r_norm > 10 * s_norm:
                    rho = min(rho * 2, cfg.rho_bounds[1])
                elif s_norm > 10 * r_norm:
                    rho = max(rho / 2, cfg.rho_bounds[0])
        self._z = z
        self._rho = rho if cfg.adaptive_rho else cfg.rho
        plans_x = np.array([r.states for r in results])
        plans_u = np.array([r.inputs for r in results])
        fallback = np.array([r.fallback for r in results])
        return PlanStep(
            states=plans_x,
            inputs=plans_u,
            predicted_cost=float(sum(r.cost for r in results)),
            max_slack=float(max(r.max_slack for r in results)),
            wall_time=time.perf_counter() - started,
            agent_times=agent_times,
            failures=failures,
            fallback=fallback,
            admm_iterations=len(primal),
            primal_residuals=primal,
            dual_residuals=dual,
            rho_history=rhos,
        )

    def _average(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]]
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """Consensus positions z (M, d, K), the RMS primal residual, and copies per agent."""
        total = np.array([r.own for r in results])
        count = np.ones(self.num_agents)
        for r in results:
            for slot, j in enumerate(neighbours[r.agent]):
                total[j] += r.copies[slot]
                count[j] += 1
        z = total / count[:, None, None]
        squared = 0.0
        entries = 0
        for r in results:
            squared += float(np.sum((r.own - z[r.agent]) ** 2))
            entries += r.own.size
            for slot, j in enumerate(neighbours[r.agent]):
                squared += float(np.sum((r.copies[slot] - z[j]) ** 2))
                entries += r.copies[slot].size
        return z, float(np.sqrt(squared / max(entries, 1))), count
