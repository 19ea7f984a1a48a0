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

import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from swarmpc.formulation.nlp import CompiledNLP, NLPSolution, shift_blocks
from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.solvers.base import PlanStep, fallback_plan
from swarmpc.solvers.executors import Executor, SerialExecutor
from swarmpc.solvers.guesses import agent_guess_blocks, inputs_from_states, pair_guess_blocks


@dataclass(frozen=True)
class ADMMConfig:
    """ADMM parameters (see the scenario's ``solver`` block)."""

    rho: float = 10.0
    max_iter: int = 100
    tol: float = 1e-3
    adaptive_rho: bool = False
    dynamic_copies: bool = False
    owner_weight: float = 5.0
    repair: bool = True
    coupling_margin: float | None = 0.5
    stall_window: int | None = 20
    rho_bounds: tuple[float, float] = (1e-2, 1e3)
    seed_duals: bool = True


@dataclass(frozen=True)
class LocalRequest:
    """What the coordinator hands agent ``agent`` for one local step."""

    agent: int
    state: np.ndarray
    goal: np.ndarray
    delta: np.ndarray
    rho: float
    rho_previous: float
    owner_weight: float
    new_step: bool
    z_own: np.ndarray
    neighbours: tuple[int, ...]
    z_neighbours: np.ndarray
    neighbour_states: np.ndarray
    guess: np.ndarray
    neighbour_plans: tuple[np.ndarray, np.ndarray] | None = None


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


class LocalSolverLadder:
    """An agent's local NLPs for copy-slot counts 0, 1, 2, 4, 8, ... up to ``max_slots``.

    An agent with n neighbours this step solves the smallest problem with at least n slots, so
    its work follows its neighbourhood, not the swarm size. Each size is built on first use and
    kept (once per shape, never rebuilt); agents in one process share the built solvers, which
    are stateless between calls (a lock guards the solver statistics under threads). Pickling
    drops the built solvers, so a worker process builds its own.
    """

    def __init__(
        self, settings: OCPSettings, max_slots: int, dynamic_copies: bool,
        plugin: str = "ipopt", options: dict[str, Any] | None = None,
    ) -> None:
        self.settings = settings
        self.max_slots = max_slots
        self.dynamic_copies = dynamic_copies
        self.plugin = plugin
        self.options = options
        self._built: dict[int, CompiledNLP] = {}
        self._lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        return {"settings": self.settings, "max_slots": self.max_slots, "dynamic_copies": self.dynamic_copies,
                "plugin": self.plugin, "options": self.options}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(**state)  # type: ignore[misc]

    def slots_for(self, copies: int) -> int:
        """Slot count of the problem that holds ``copies`` neighbours."""
        if copies > self.max_slots:
            raise ValueError(f"{copies} neighbours exceed the {self.max_slots} copy slots")
        size = 0 if copies == 0 else 1
        while size < copies:
            size *= 2
        return min(size, self.max_slots)

    def solver(self, slots: int) -> CompiledNLP:
        """The built problem with ``slots`` copy slots (built now if this is its first use)."""
        if slots not in self._built:
            self._built[slots] = build_local(self.settings, slots, self.dynamic_copies, self.options, self.plugin)
        return self._built[slots]

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray], fixed: dict[str, Any] | None = None,
        *, copies: int,
    ) -> NLPSolution:
        """Solve the problem sized for ``copies`` neighbours (see :meth:`CompiledNLP.solve`)."""
        with self._lock:
            return self.solver(self.slots_for(copies)).solve(params, guess, fixed=fixed)


class LocalAgentFactory:
    """Picklable recipe for agents' local solvers (built where the agents live; agents made by
    one factory object share its :class:`LocalSolverLadder`)."""

    def __init__(
        self, settings: OCPSettings, slots: int, dynamic_copies: bool = True, seed_duals: bool = True
    ) -> None:
        self.settings = settings
        self.slots = slots
        self.dynamic_copies = dynamic_copies
        self.seed_duals = seed_duals
        self.ladder = LocalSolverLadder(settings, slots, dynamic_copies)

    def __call__(self, agent: int) -> LocalAgent:
        return LocalAgent(agent, self.settings, self.ladder, self.dynamic_copies, self.seed_duals)


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
        self, agent: int, settings: OCPSettings, nlp: LocalSolverLadder, dynamic_copies: bool,
        seed_duals: bool = True,
    ) -> None:
        self.agent = agent
        self.seed_duals = seed_duals
        self.dynamic_copies = dynamic_copies
        self.settings = settings
        self.nlp = nlp
        self._gamma_own: np.ndarray | None = None
        self._gamma: dict[int, np.ndarray] = {}
        self._last: NLPSolution | None = None
        self._last_neighbours: tuple[int, ...] = ()
        self._last_sent: LocalResult | None = None
        self._plan: tuple[np.ndarray, np.ndarray] | None = None

    def _multipliers_step(self, request: LocalRequest) -> None:
        last = self._last_sent
        if request.new_step or last is None:
            if self._gamma_own is not None:
                self._gamma_own = shift_blocks({"own": self._gamma_own})["own"]
            self._gamma = shift_blocks({j: y for j, y in self._gamma.items() if j in request.neighbours})
            return
        rho = request.rho_previous
        self._gamma_own = (self._gamma_own if self._gamma_own is not None else 0.0) + (
            rho * request.owner_weight * (last.own - request.z_own)
        )
        for slot, j in enumerate(request.neighbours):
            if j in self._last_neighbours:
                previous = last.copies[self._last_neighbours.index(j)]
                self._gamma[j] = self._gamma.get(j, 0.0) + rho * (previous - request.z_neighbours[slot])

    def _initial_point(self, request: LocalRequest, seed: bool = True) -> dict[str, np.ndarray]:
        """Primal start from the guess; certificates seeded when ``seed`` and ``seed_duals``."""
        s, first = self.settings, self.settings.first_constrained_step
        seed = seed and self.seed_duals
        point = agent_guess_blocks("", request.guess, s, seed)
        own = request.guess[first:, : s.dim]
        for slot, z in enumerate(request.z_neighbours):
            if self.dynamic_copies:
                trajectory = trajectory_through(request.neighbour_states[slot], z, s)
                point[f"Xc{slot}"] = trajectory.T
                point[f"Uc{slot}"] = inputs_from_states(trajectory, s).T
            else:
                point[f"C{slot}"] = z
            point.update(pair_guess_blocks(str(slot), own - z.T, request.delta, s, seed))
        return point

    def _copy_positions(self, solution: NLPSolution, slot: int) -> np.ndarray:
        if self.dynamic_copies:
            return solution.x[f"Xc{slot}"][: self.settings.dim, self.settings.first_constrained_step :]
        return solution.x[f"C{slot}"]

    def _pinned_copies(self, request: LocalRequest) -> dict[str, np.ndarray] | None:
        """In a repair pass the copies are the neighbours' actual plans, held fixed."""
        if request.neighbour_plans is None:
            return None
        states, inputs = request.neighbour_plans
        if self.dynamic_copies:
            pinned = {f"Xc{slot}": states[slot].T for slot in range(len(states))}
            pinned.update({f"Uc{slot}": inputs[slot].T for slot in range(len(inputs))})
            return pinned
        return {f"C{slot}": z for slot, z in enumerate(request.z_neighbours)}

    def solve(self, request: LocalRequest) -> LocalResult:
        """Multiplier update for the new consensus, then the local NLP."""
        s = self.settings
        repair = request.neighbour_plans is not None
        if not request.neighbours:
            # nobody holds a copy of this agent: no consensus block, no multipliers
            self._gamma_own, self._gamma = None, {}
        elif not repair:
            self._multipliers_step(request)
        zeros = np.zeros_like(request.z_own)
        params: dict[str, np.ndarray | float] = {
            "x0": request.state,
            "goal": request.goal,
            "delta": request.delta,
            "rho": request.rho,
            "owner_weight": request.owner_weight,
            "Z": request.z_own,
            "Y": self._gamma_own if self._gamma_own is not None and not repair else zeros,
        }
        n = len(request.neighbours)
        for slot in range(self.nlp.slots_for(n)):
            active = slot < len(request.neighbours)
            params[f"active{slot}"] = 1.0 if active else 0.0
            if self.dynamic_copies:
                params[f"x0c{slot}"] = request.neighbour_states[slot] if active else request.state
            if active:
                j = request.neighbours[slot]
                params[f"Z{slot}"] = request.z_neighbours[slot]
                params[f"Y{slot}"] = zeros if repair else self._gamma.get(j, zeros)
        same_shape = request.neighbours == self._last_neighbours
        if self._last is not None and same_shape and not request.new_step:
            point: dict[str, np.ndarray] = dict(self._last.x)
        else:
            warm = self._last is not None and request.new_step and same_shape
            point = self._initial_point(request, seed=not warm)  # warm: shifted L, A below
            if warm:
                shifted = shift_blocks(self._last.x)
                point.update({k: v for k, v in shifted.items() if k.startswith(("L", "A"))})
        pinned = self._pinned_copies(request)
        if pinned is not None and s.collision == "soft":
            # repair: first try to keep clear of the fixed plans without slack
            strict = {**pinned, **{f"A{slot}": 0.0 for slot in range(len(request.neighbours))}}
            solution = self.nlp.solve(params, point, fixed=strict, copies=n)
            if not solution.success:
                solution = self.nlp.solve(params, point, fixed=pinned, copies=n)
        else:
            solution = self.nlp.solve(params, point, fixed=pinned, copies=n)
        first = s.first_constrained_step
        fallback = False
        slack: list[float] = []
        if solution.success:
            self._last = solution
            states, inputs = solution.x["X"].T, solution.x["U"].T
            copies = np.array([self._copy_positions(solution, slot) for slot in range(n)])
            copies = copies.reshape(n, s.dim, s.num_constrained)
            slack = [float(solution.x[f"A{slot}"].max()) for slot in range(n) if f"A{slot}" in solution.x]
        elif (
            not request.new_step and not repair and self._plan is not None
            and self._last_sent is not None and same_shape
        ):
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
        factory = LocalAgentFactory(settings, max(num_agents - 1, 1), config.dynamic_copies, config.seed_duals)
        self.executor.start(factory, range(num_agents))
        self._z: np.ndarray | None = None
        self._rho = config.rho

    def close(self) -> None:
        self.executor.close()

    def neighbours(self, guess: np.ndarray) -> list[tuple[int, ...]]:
        """Agents each agent couples with this step (symmetric).

        With ``coupling_margin`` None, every other agent (the paper's all-to-all copies). Otherwise
        only agents whose guessed trajectories come within delta + d_min + margin (inf-norm) of
        each other at some constrained step; pairs left out are checked after convergence and
        coupled on demand if their plans conflict (see :meth:`plan`).
        """
        M = self.num_agents
        if self.config.coupling_margin is None:
            return [tuple(j for j in range(M) if j != i) for i in range(M)]
        first, d = self.settings.first_constrained_step, self.settings.dim
        reach = float(np.max(self.delta)) + self.settings.d_min + self.config.coupling_margin
        positions = guess[:, first:, :d]
        gaps = np.max(np.abs(positions[:, None] - positions[None, :]), axis=3).min(axis=2)
        return [tuple(j for j in range(M) if j != i and gaps[i, j] < reach) for i in range(M)]

    def conflicts(self, results: list[LocalResult], neighbours: list[tuple[int, ...]]) -> list[tuple[int, int]]:
        """Uncoupled pairs whose own plans come closer than the coupling would allow."""
        d = self.settings.dim
        limit = float(np.max(self.delta)) + self.settings.d_min
        pairs = []
        for i in range(self.num_agents):
            for j in range(i + 1, self.num_agents):
                if j in neighbours[i]:
                    continue
                gap = np.max(np.abs(results[i].own - results[j].own), axis=0).min()
                if gap < limit:
                    pairs.append((i, j))
        return pairs

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> PlanStep:
        """One MPC step: ADMM iterations until consensus, then every agent's own plan."""
        started = time.perf_counter()
        s, cfg, M = self.settings, self.config, self.num_agents
        first = s.first_constrained_step
        if self._z is None:
            z = np.transpose(guess[:, first:, : s.dim], (0, 2, 1)).copy()
        else:
            z = np.concatenate([self._z[:, :, 1:], self._z[:, :, -1:]], axis=2)
        neighbours = self.neighbours(guess)
        rho = rho_previous = self._rho
        primal: list[float] = []
        dual: list[float] = []
        rhos: list[float] = []
        agent_times = np.zeros(M)
        failures = 0
        results: list[LocalResult] = []
        converged = False
        for iteration in range(cfg.max_iter):
            requests = [
                self._request(i, states, goals, guess, neighbours[i], z, rho, rho_previous, iteration == 0)
                for i in range(M)
            ]
            results = self.executor.solve(requests)
            agent_times += [r.solve_time for r in results]
            failures += sum(not r.success for r in results)
            z_new, r_norm, weights = self._average(results, neighbours)
            s_norm = self._dual_residual(z_new - z, weights, neighbours, rho)
            primal.append(r_norm)
            dual.append(float(s_norm))
            rhos.append(rho)
            z = z_new
            converged = r_norm <= cfg.tol and s_norm <= cfg.tol
            if converged:
                missing = self.conflicts(results, neighbours)
                if not missing:
                    break
                converged = False
                coupled = [set(n) for n in neighbours]
                for i, j in missing:
                    coupled[i].add(j)
                    coupled[j].add(i)
                neighbours = [tuple(sorted(n)) for n in coupled]
            if self._stalled(primal):
                break
            rho_previous = rho
            if cfg.adaptive_rho:
                if r_norm > 10 * s_norm:
                    rho = min(rho * 2, cfg.rho_bounds[1])
                elif s_norm > 10 * r_norm:
                    rho = max(rho / 2, cfg.rho_bounds[0])
        if not converged and cfg.repair:
            results = self._repair(states, goals, guess, neighbours, z, rho, results)
            agent_times += [r.solve_time for r in results]
            failures += sum(not r.success for r in results)
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
            repaired=not converged and cfg.repair,
            primal_residuals=primal,
            dual_residuals=dual,
            rho_history=rhos,
        )

    def _stalled(self, primal: list[float]) -> bool:
        """No 10% progress of the primal residual over the last ``stall_window`` iterations: more
        iterations will not reach consensus, so stop and let the repair pass finish the step."""
        window = self.config.stall_window
        if window is None or len(primal) <= window:
            return False
        return min(primal[-window:]) > 0.9 * min(primal[:-window])

    def _request(
        self, i: int, states: np.ndarray, goals: np.ndarray, guess: np.ndarray, neighbours: tuple[int, ...],
        z: np.ndarray, rho: float, rho_previous: float, new_step: bool,
        plans: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> LocalRequest:
        first = self.settings.first_constrained_step
        if plans is None:
            z_neighbours = z[list(neighbours)]
        else:
            z_neighbours = np.transpose(plans[0][:, first:, : self.settings.dim], (0, 2, 1))
        return LocalRequest(
            agent=i,
            state=states[i],
            goal=goals[i],
            delta=self.delta,
            rho=rho,
            rho_previous=rho_previous,
            owner_weight=self.config.owner_weight if neighbours else 0.0,
            new_step=new_step,
            z_own=z[i],
            neighbours=neighbours,
            z_neighbours=z_neighbours.reshape(len(neighbours), self.settings.dim, z.shape[2]),
            neighbour_states=states[list(neighbours)],
            guess=guess[i],
            neighbour_plans=plans,
        )

    def _repair(
        self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray, neighbours: list[tuple[int, ...]],
        z: np.ndarray, rho: float, results: list[LocalResult],
    ) -> list[LocalResult]:
        """Consensus repair when ADMM stops at the cap: agents re-plan one after another against
        the others' current own plans (held fixed). Each agent respects the final plans of those
        before it and the plans those after it will respect, so every pair ends up feasible
        whenever the solves succeed."""
        first = self.settings.first_constrained_step
        repaired = list(results)
        for i in range(self.num_agents):
            others = list(neighbours[i])
            if not others:
                continue
            plans = (
                np.array([repaired[j].states for j in others]),
                np.array([repaired[j].inputs for j in others]),
            )
            own_z = z.copy()
            own_z[i] = repaired[i].states[first:, : self.settings.dim].T
            request = self._request(i, states, goals, guess, neighbours[i], own_z, rho, rho, False, plans)
            repaired[i] = self.executor.solve([request])[0]
        return repaired

    def _average(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]]
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """Consensus positions z (M, d, K), the RMS primal residual, and the own-block weights.

        z_j is the rho_b-weighted mean of every copy of agent j: its own plan (weight
        owner_weight, or 0 for an agent nobody couples with, whose z is then its plan) and the
        copies its neighbours hold (weight 1).
        """
        own = np.array([r.own for r in results])
        weights = np.array([self.config.owner_weight if n else 1.0 for n in neighbours])
        total = weights[:, None, None] * own
        count = weights.copy()
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
        return z, float(np.sqrt(squared / max(entries, 1))), weights

    def _dual_residual(
        self, change: np.ndarray, weights: np.ndarray, neighbours: list[tuple[int, ...]], rho: float
    ) -> float:
        """RMS of rho_b (z - z_prev) over every consensus block (Boyd et al. sec. 3.3 with block
        penalties rho_b: rho * owner_weight for own blocks, rho for copies). Agents nobody
        couples with hold no consensus block and do not count."""
        coupled = np.array([bool(n) for n in neighbours])
        copies = np.array([sum(j in n for n in neighbours) for j in range(self.num_agents)])
        per_agent = (weights**2 * coupled + copies) * np.sum(change**2, axis=(1, 2))
        entries = (coupled + copies).sum() * change[0].size
        return float(rho * np.sqrt(per_agent.sum() / max(entries, 1)))
