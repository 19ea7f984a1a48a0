"""Distributed MPC by consensus ADMM (paper section III-E, Algorithms 1-2; Boyd et al. 2011 sec. 7).

Agent i holds its own trajectory and local copies of the positions of the agents it couples with.
Consensus is on positions at the constrained horizon steps, the only quantities the coupling
constraints read. One ADMM iteration:

1. local step (every agent, through the executor): minimise own cost
   + gamma_i'(v_i - z) + rho/2 ||v_i - z||^2 subject to own dynamics, bounds and OBCA against
   its copies;
2. averaging (the coordinator): z_j = mean of every copy of agent j's positions, its own included;
3. multiplier step (inside each agent, at its next call): gamma_i += rho (v_i - z).

Every pair (i, j) keeps the offset of its centres out of the box of half-size Delta_ij = b_i + b_j
(the two bodies): the coordinator hands each agent the Delta_ij of each of its neighbours, and
uses the same Delta_ij wherever it reasons about a pair (coupling reach, separating planes,
conflict and safety checks, repair). Each agent's OCP holds the obstacles grown by its own body.

It stops when the RMS primal residual ||v - z|| and the RMS dual residual rho ||z - z_prev|| are
both below ``tol`` (metres), or at ``max_iter``. Each agent then applies its OWN plan's first
input, which is always dynamically feasible. Multipliers and the agent's last solution are private
to the agent; the coordinator sees only what an agent transmits (its positions and its copies).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

import numpy as np

from swarmpc.formulation.nlp import CompiledNLP, NLPSolution, shift_blocks
from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.model.dynamics import discrete_matrices
from swarmpc.model.geometry import as_bodies, box_exterior_distance, box_signed_distance, largest_pair_delta
from swarmpc.solvers.base import PlanStep, fallback_plan
from swarmpc.solvers.executors import Executor, SerialExecutor
from swarmpc.solvers.guesses import agent_guess_blocks, inputs_from_states, pair_guess_blocks
from swarmpc.solvers.qp_local import QPLocalLadder


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
    closing_time: float = 0.0
    """Seconds of closing speed added to the coupling margin per pair: pairs whose guesses approach
    each other at relative speed v (inf-norm, largest over the horizon) couple within
    max(Delta_ij) + d_min + coupling_margin + closing_time * v."""
    stall_window: int | None = 5
    stall_rho_factor: float | None = 2.0
    rho_bounds: tuple[float, float] = (1e-2, 1e3)
    seed_duals: bool = True
    carry_multipliers: Literal["stable", "always", "never"] = "stable"
    """Which consensus multipliers a new MPC step starts from (shifted by one step) rather than
    from zero. "always": every one (the paper). "never": none. "stable" (default): those of the
    blocks whose agent has the same neighbours as at the end of the previous step, for every
    holder of the block alike. A block's multipliers sum to zero (the plain average is then
    ADMM's z-update) only while nobody drops a copy of it; a multiplier kept after its
    counterpart was dropped acts as a constant force, which held agents at rest 0.15 m from
    free goals for hundreds of steps in dense swarms (docs/admm.md)."""
    warm_start: bool = True
    """Start each ADMM iteration's local solve after the first of an MPC step from the previous
    iterate's multipliers too, not only its primal point (IPOPT warm start). Halves the
    local-solver time on random swarms at equal ADMM iterations (docs/admm.md)."""
    local: Literal["qp", "ipopt"] = "ipopt"
    """The agents' local step. "ipopt": the OBCA NLP by IPOPT (the reference). "qp": the convex
    local step of :mod:`swarmpc.solvers.qp_local` (OBCA certificates held fixed per QP, OSQP, a
    short certificate loop), whose answers are safe as they stand; any call it fails is solved by
    IPOPT instead (:class:`QPLocalSolverLadder`, counted in ``LocalResult.local_fallbacks``).
    Needs free copies (``dynamic_copies`` False)."""
    relaxation: float = 1.0
    """Over-relaxation alpha of the consensus (Boyd et al. sec. 3.4.3): the average and the
    multipliers use alpha * v + (1 - alpha) * z_previous in place of each block's answer v.
    1: plain ADMM (the paper); 1.5-1.8 often needs fewer iterations; the fixed points are the same."""
    reuse_tol: float = 1e-4
    """Within an MPC step, an agent whose consensus targets (z - gamma / rho_b, per block) all moved
    less than this [m] since its last solve, at the same penalty and neighbours, sends its last
    answer again instead of solving: that answer solves a problem whose targets differ by at most
    this much (0: always solve). An inexact local step, far below the consensus tolerance;
    measured in docs/admm.md."""
    component_stop: bool = False
    """Also stop each connected component of the coupling graph on its own residuals: agents whose
    component has met the tolerance are not solved again in the step (their answers and
    multipliers stand) while other components iterate on, until the residuals over all blocks meet
    the tolerance (the paper's stop, which alone decides with False). Either way the conflict check
    runs on everyone's plans before any is applied (docs/admm.md)."""
    plane_margin: float | None = None
    """None: every coupled pair holds copies of each other (OBCA and consensus). A margin [m]: a
    coupled pair whose guesses stay at least d_min + plane_margin beyond its Delta_ij box on one axis
    at every constrained step is kept apart by a fixed separating plane per step instead, each
    agent keeping to its side with half the spare room (:func:`separating_planes`): no copies, no
    consensus, no iterations for that pair. A plane pair whose plans break the separation is
    coupled with copies (docs/admm.md)."""
    engage_margin: float | None = None
    """None: the paper's stop (primal and dual residual over every block). A margin [m]: the
    engaged stop, primal residual over engaged pairs' blocks plus mutually clear own plans
    (measured faster per step but slower to the goals in closed loop; docs/admm.md)."""
    deadline: float | None = None
    """Critical-path budget of one MPC step [s] (None: none): an iteration that would overrun it is
    not started and the step ends through the repair pass (:class:`StepClock`,
    :meth:`ADMMSolver.plan`)."""


@dataclass(frozen=True)
class LocalRequest:
    """What the coordinator hands agent ``agent`` for one local step."""

    agent: int
    state: np.ndarray
    goal: np.ndarray
    delta: np.ndarray
    """(n, d) Delta_ij of the pair with each neighbour, rows in the order of ``neighbours`` (a (d,)
    value is taken for every neighbour); see :attr:`pair_deltas`."""
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
    reuse_tol: float = 0.0
    """See ``ADMMConfig.reuse_tol``."""
    relaxation: float = 1.0
    """See ``ADMMConfig.relaxation``."""
    carry: tuple[bool, ...] = ()
    """At a new step: per block (own, then each neighbour's), whether its multiplier is carried
    over (shifted) instead of restarting from zero; missing entries restart."""
    rescue: bool = False
    """A repair's last attempt: if the hard solves fail and the fallback plan breaks the separation
    from the pinned plans, fly the least-violating plan instead (see ``LocalAgent._rescue``)."""
    plane_normals: np.ndarray | None = None
    """(P, d, K) unit normals of the separating planes the agent's positions keep to (None: none);
    see :func:`separating_planes`."""
    plane_offsets: np.ndarray | None = None
    """(P, K) offsets of those planes: normal' p_k >= offset_k at each constrained step k."""

    @property
    def num_planes(self) -> int:
        return 0 if self.plane_normals is None else len(self.plane_normals)

    @property
    def pair_deltas(self) -> np.ndarray:
        """(n, d) Delta_ij of the pair with each neighbour (``delta`` broadcast when it is one value)."""
        d = np.asarray(self.z_own).shape[0]
        return np.broadcast_to(np.asarray(self.delta, float), (len(self.neighbours), d))


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
    local_fallbacks: int = 0
    """Local-step calls of this request whose QP path failed and which IPOPT solved instead
    (``ADMMConfig.local`` "qp"; always 0 with "ipopt")."""


class LocalSolverLadder:
    """An agent's local NLPs, one per neighbour count 0, 1, 2, ... up to ``max_slots``.

    An agent with n neighbours solves the problem with exactly n copy slots, so its work follows
    its neighbourhood, not the swarm size, and no solve pays for idle slots (a build takes
    0.04 s at 3 slots, 0.4 s at 31). Each size is built on first use and kept (once per shape,
    never rebuilt); agents in one process share the built solvers, which are stateless between
    calls (a lock guards the solver statistics under threads). Pickling drops the built
    solvers, so a worker process builds its own.
    """

    def __init__(
        self, settings: OCPSettings, max_slots: int, dynamic_copies: bool,
        plugin: str = "ipopt", options: dict[str, Any] | None = None, warm_start: bool = False,
        pair_collision: str | None = None,
    ) -> None:
        self.settings = settings
        self.max_slots = max_slots
        self.dynamic_copies = dynamic_copies
        self.plugin = plugin
        self.options = options
        self.warm_start = warm_start
        self.pair_collision = pair_collision
        self._built: dict[tuple[int, int], CompiledNLP] = {}
        self._lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        return {"settings": self.settings, "max_slots": self.max_slots, "dynamic_copies": self.dynamic_copies,
                "plugin": self.plugin, "options": self.options, "warm_start": self.warm_start,
                "pair_collision": self.pair_collision}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(**state)  # type: ignore[misc]

    def slots_for(self, copies: int) -> int:
        """Slot count of the problem that holds ``copies`` neighbours."""
        if copies > self.max_slots:
            raise ValueError(f"{copies} neighbours exceed the {self.max_slots} copy slots")
        return copies

    def solver(self, slots: int, planes: int = 0) -> CompiledNLP:
        """The built problem with ``slots`` copy slots and ``planes`` separating-plane slots (built
        now if this is its first use)."""
        key = (slots, planes)
        if key not in self._built:
            self._built[key] = build_local(self.settings, slots, self.dynamic_copies, self.options, self.plugin,
                                           self.warm_start, self.pair_collision, num_planes=planes)
        return self._built[key]

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, fixed: dict[str, Any] | None = None,
        *, copies: int, planes: int = 0, duals: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> NLPSolution:
        """Solve the problem sized for ``copies`` neighbours and ``planes`` separating planes (see
        :meth:`CompiledNLP.solve`); ``duals``: multipliers of the bounds and constraints (from a
        previous solve of the same problem) that start this one when the ladder warm-starts."""
        with self._lock:
            nlp = self.solver(self.slots_for(copies), planes)
            if duals is None or not self.warm_start:
                return nlp.solve(params, guess, fixed=fixed)
            warm = nlp.solve(params, guess, *duals, fixed=fixed)
            if warm.success:
                return warm
            # a warm start that fails is retried cold: the multipliers were the bad part
            cold = nlp.solve(params, guess, fixed=fixed)
            return replace(cold, solve_time=warm.solve_time + cold.solve_time)

    def verified(
        self, params: dict[str, Any], point: dict[str, np.ndarray], fixed: dict[str, Any], *, copies: int,
        planes: int = 0,
    ) -> NLPSolution | None:
        """``point`` with ``fixed`` pinned as a solution (status :data:`KEPT_PLAN`, no cost, no
        time) when it meets every bound and constraint of the problem sized for ``copies`` and
        ``planes`` to 1e-7; None otherwise. A repair keeps a verified current plan this way."""
        nlp = self.solver(self.slots_for(copies), planes)
        x_vec = nlp.x_layout.pack({**point, **fixed})
        if nlp.constraint_violation(x_vec, params) > 1e-7:
            return None
        return NLPSolution(
            x=nlp.x_layout.unpack(x_vec), x_vec=x_vec, lam_x=np.zeros_like(x_vec),
            lam_g=np.zeros_like(nlp.lbg), cost=np.nan, success=True, status=KEPT_PLAN,
            iterations=0, solve_time=0.0,
        )


@dataclass(frozen=True)
class FallbackSolution(NLPSolution):
    """IPOPT's answer to a local step whose QP path failed (:class:`QPLocalSolverLadder`)."""

    qp_status: str = ""
    """The QP path's status of the failed call."""


class QPLocalSolverLadder:
    """An agent's local steps on the QP path, with IPOPT behind every call the QP path fails.

    The interface of :class:`LocalSolverLadder`. Each call goes to ``qp``
    (:class:`swarmpc.solvers.qp_local.QPLocalLadder`), whose answer is safe as it stands: its
    collision rows hold fixed dual-feasible certificates (weak duality), tightened by its margin
    against OSQP's tolerance, and the plan it returns is rebuilt exactly and checked. When it
    fails (the certificates of its start ask for a separation the plan cannot reach, OSQP gives
    up, or the check rejects the plan), the same call is solved by ``ipopt``, the reference, from
    the same start (a solution vector unpacked into named blocks, its certificates included),
    cold: multipliers do not carry across solvers. That answer is returned as
    :class:`FallbackSolution`, its solution vector laid out for the QP path so that the agent's
    next call starts the QP from it.
    """

    def __init__(self, qp: QPLocalLadder, ipopt: LocalSolverLadder) -> None:
        self.qp = qp
        self.ipopt = ipopt

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, fixed: dict[str, Any] | None = None,
        *, copies: int, planes: int = 0, duals: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> NLPSolution:
        """The QP path's answer if it succeeds, else IPOPT's (:class:`FallbackSolution`)."""
        answer = self.qp.solve(params, guess, fixed, copies=copies, planes=planes, duals=duals)
        if answer.success:
            return answer
        pinned = _pins_copies(fixed)
        start = self.qp.guess_blocks(params, guess, copies=copies, planes=planes, pinned=pinned)
        reference = self.ipopt.solve(params, start, fixed, copies=copies, planes=planes)
        values = {f.name: getattr(reference, f.name) for f in fields(NLPSolution)}
        values.update(lam_x=np.zeros(0), lam_g=np.zeros(0), solve_time=answer.solve_time + reference.solve_time)
        if reference.success:
            values["x_vec"] = self.qp.solution_vector(reference.x, params, copies=copies, planes=planes, pinned=pinned)
        return FallbackSolution(**values, qp_status=answer.status)

    def verified(
        self, params: dict[str, Any], point: dict[str, np.ndarray], fixed: dict[str, Any], *, copies: int,
        planes: int = 0,
    ) -> NLPSolution | None:
        """:meth:`LocalSolverLadder.verified` by the reference problem, its solution vector laid
        out for the QP path."""
        kept = self.ipopt.verified(params, point, fixed, copies=copies, planes=planes)
        if kept is None:
            return None
        vector = self.qp.solution_vector(kept.x, params, copies=copies, planes=planes, pinned=_pins_copies(fixed))
        return replace(kept, x_vec=vector, lam_x=np.zeros(0), lam_g=np.zeros(0))


def _pins_copies(fixed: dict[str, Any] | None) -> bool:
    """Whether ``fixed`` pins the copies (``C{c}``: a repair pass)."""
    return any(key.startswith("C") and key[1:].isdigit() for key in fixed or {})


AgentLadder = LocalSolverLadder | QPLocalSolverLadder
"""What an agent solves its local steps with (``ADMMConfig.local``)."""


class LocalAgentFactory:
    """Picklable recipe for agents' local solvers (built where the agents live; agents made by
    one factory object share its :class:`LocalSolverLadder` and, under hard constraints, its
    rescue ladder: the same problems with soft pair constraints, built only when first needed).

    With ``bodies`` (M, d), agent i's problems hold the obstacles grown by its body
    (:meth:`OCPSettings.for_body`); agents whose grown obstacles are the same (every agent without
    obstacles, every agent of one body size) share one pair of ladders. None: the obstacles of
    ``settings`` as they are, for every agent.

    ``local`` "qp": each ladder is a :class:`QPLocalSolverLadder` (the QP path, with these IPOPT
    ladders as its fallback), the rescue ladder too (the QP path's soft pair form).
    """

    def __init__(
        self, settings: OCPSettings, slots: int, dynamic_copies: bool = True, seed_duals: bool = True,
        warm_start: bool = False, bodies: np.ndarray | None = None, local: Literal["qp", "ipopt"] = "ipopt",
    ) -> None:
        if local == "qp" and dynamic_copies:
            raise ValueError("local: qp needs free copies (dynamic_copies False)")
        self.settings = settings
        self.slots = slots
        self.dynamic_copies = dynamic_copies
        self.seed_duals = seed_duals
        self.warm_start = warm_start
        self.bodies = None if bodies is None else np.asarray(bodies, float)
        self.local = local
        self._ladders: dict[tuple[bytes, ...], tuple[AgentLadder, AgentLadder | None]] = {}
        self.ladder, self.rescue = self._ladders_for(settings)

    def _ladders_for(self, settings: OCPSettings) -> tuple[AgentLadder, AgentLadder | None]:
        """The (ladder, rescue ladder) of problems with ``settings``' obstacles, made on first use."""
        key = tuple(np.asarray(g, float).tobytes() for _, g in settings.obstacles)
        if key not in self._ladders:
            ladder = LocalSolverLadder(settings, self.slots, self.dynamic_copies, warm_start=self.warm_start)
            rescue = (LocalSolverLadder(settings, self.slots, self.dynamic_copies, pair_collision="soft")
                      if settings.collision == "hard" else None)
            self._ladders[key] = (ladder, rescue) if self.local == "ipopt" else (
                QPLocalSolverLadder(QPLocalLadder(settings), ladder),
                None if rescue is None else QPLocalSolverLadder(QPLocalLadder(settings, pair_collision="soft"), rescue),
            )
        return self._ladders[key]

    def __call__(self, agent: int) -> LocalAgent:
        settings = self.settings if self.bodies is None else self.settings.for_body(self.bodies[agent])
        ladder, rescue = self._ladders_for(settings)
        return LocalAgent(agent, settings, ladder, self.dynamic_copies, self.seed_duals, rescue)


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


KEPT_PLAN = "kept_verified_current_plan"
"""Status of a repair whose solves failed but whose current plan satisfies every constraint."""


class LocalAgent:
    """One agent's private side of ADMM: its solver, multipliers and last solution."""

    def __init__(
        self, agent: int, settings: OCPSettings, nlp: AgentLadder, dynamic_copies: bool,
        seed_duals: bool = True, rescue: AgentLadder | None = None,
    ) -> None:
        self.agent = agent
        self.rescue = rescue
        self.seed_duals = seed_duals
        self.dynamic_copies = dynamic_copies
        self.settings = settings
        self.nlp = nlp
        self._fallbacks = 0
        """Calls of the current request that IPOPT answered for the QP path."""
        self._gamma_own: np.ndarray | None = None
        self._gamma: dict[int, np.ndarray] = {}
        self._last: NLPSolution | None = None
        self._last_neighbours: tuple[int, ...] = ()
        self._last_planes: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        self._last_sent: LocalResult | None = None
        self._last_state: np.ndarray | None = None
        self._plan: tuple[np.ndarray, np.ndarray] | None = None
        self._solved_targets: tuple[float, float, np.ndarray] | None = None
        self._previous_z: tuple[np.ndarray, dict[int, np.ndarray]] | None = None

    def _relaxed(self, answer: np.ndarray, alpha: float, previous: np.ndarray | None) -> np.ndarray:
        return answer if alpha == 1.0 or previous is None else alpha * answer + (1.0 - alpha) * previous

    def _ladder_solve(
        self, ladder: AgentLadder, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray,
        fixed: dict[str, Any] | None = None, **sizes: Any,
    ) -> NLPSolution:
        """``ladder.solve``, counting the calls IPOPT answered for a failed QP path."""
        solution = ladder.solve(params, guess, fixed, **sizes)
        self._fallbacks += isinstance(solution, FallbackSolution)
        return solution

    def _multipliers_step(self, request: LocalRequest) -> None:
        last = self._last_sent
        previous_z, self._previous_z = self._previous_z, (
            request.z_own, dict(zip(request.neighbours, request.z_neighbours)))
        if request.new_step or last is None:
            carry = request.carry + (False,) * (1 + len(request.neighbours) - len(request.carry))
            if self._gamma_own is not None:
                self._gamma_own = shift_blocks({"own": self._gamma_own})["own"] if carry[0] else None
            self._gamma = shift_blocks({
                j: self._gamma[j] for slot, j in enumerate(request.neighbours) if carry[1 + slot] and j in self._gamma
            })
            return
        rho, alpha = request.rho_previous, request.relaxation
        own_before, copies_before = previous_z if previous_z is not None else (None, {})
        self._gamma_own = (self._gamma_own if self._gamma_own is not None else 0.0) + (
            rho * request.owner_weight * (self._relaxed(last.own, alpha, own_before) - request.z_own)
        )
        for slot, j in enumerate(request.neighbours):
            if j in self._last_neighbours:
                previous = self._relaxed(last.copies[self._last_neighbours.index(j)], alpha, copies_before.get(j))
                self._gamma[j] = self._gamma.get(j, 0.0) + rho * (previous - request.z_neighbours[slot])

    def _initial_point(
        self, request: LocalRequest, seed: bool = True, always_seed: bool = False
    ) -> dict[str, np.ndarray]:
        """Primal start from the guess; certificates seeded when ``seed`` and ``seed_duals``
        (or ``always_seed``)."""
        s, first = self.settings, self.settings.first_constrained_step
        seed = seed and (self.seed_duals or always_seed)
        point = agent_guess_blocks("", request.guess, s, seed)
        own = request.guess[first:, : s.dim]
        for slot, z in enumerate(request.z_neighbours):
            if self.dynamic_copies:
                trajectory = trajectory_through(request.neighbour_states[slot], z, s)
                point[f"Xc{slot}"] = trajectory.T
                point[f"Uc{slot}"] = inputs_from_states(trajectory, s).T
            else:
                point[f"C{slot}"] = z
            point.update(pair_guess_blocks(str(slot), own - z.T, request.pair_deltas[slot], s, seed))
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

    def _repair_from_own_plan(
        self, request: LocalRequest, params: dict[str, Any], pinned: dict[str, np.ndarray],
        failed: NLPSolution,
    ) -> NLPSolution:
        """A failed repair solve, retried from the agent's current plan with its certificates
        seeded against the pinned plans (IPOPT's restoration phase can report a nearly feasible
        start as infeasible). If that fails too, the current plan itself is kept when it
        verifiably satisfies every constraint against the pinned plans; otherwise ``failed``."""
        assert self._plan is not None
        n = len(request.neighbours)
        candidate = self._initial_point(replace(request, guess=self._plan[0]), always_seed=True)
        retry = self._ladder_solve(self.nlp, params, candidate, pinned, copies=n, planes=request.num_planes)
        if retry.success:
            return retry
        kept = self.nlp.verified(params, candidate, pinned, copies=n, planes=request.num_planes)
        if kept is None:
            return failed
        return replace(kept, cost=retry.cost, solve_time=failed.solve_time + retry.solve_time)

    def _violation(self, states: np.ndarray, request: LocalRequest) -> float:
        """How far a plan falls short of the separation d_min from the pinned neighbours' plans:
        the shortfall of the signed distance (negative inside the pair's Delta_ij box, so depth
        counts), summed over neighbours and constrained steps; 0 for a plan clear of them all."""
        assert request.neighbour_plans is not None
        d, first = self.settings.dim, self.settings.first_constrained_step
        others = request.neighbour_plans[0][:, first:, :d]
        signed = box_signed_distance(states[None, first:, :d] - others, request.pair_deltas[:, None, :])
        return float(np.maximum(self.settings.d_min - signed, 0.0).sum())

    def _rescue(
        self, request: LocalRequest, params: dict[str, Any], pinned: dict[str, np.ndarray], fallback: np.ndarray,
    ) -> tuple[tuple[np.ndarray, np.ndarray] | None, float]:
        """A plan for a repair whose hard solves failed and whose fallback plan (states
        ``fallback``) violates the separation from a pinned neighbour's plan: the same problem
        with soft pair constraints, always feasible, whose optimum violates the separation least.
        It is flown instead of the fallback only when it violates less. Two agents failing
        together (each blind to the other's fallback) and a pair whose bodies already
        overlap (every hard problem infeasible, both on fallbacks for good) have no other way
        out. Returns (states, inputs) or None, and the time spent."""
        if self.rescue is None:
            return None, 0.0
        s, first = self.settings, self.settings.first_constrained_step
        before = self._violation(fallback, request)
        if before == 0.0:
            return None, 0.0
        soft = replace(s, collision="soft")
        point = agent_guess_blocks("", fallback, s)
        assert request.neighbour_plans is not None
        for slot, other in enumerate(request.neighbour_plans[0]):
            offsets = fallback[first:, : s.dim] - other[first:, : s.dim]
            point.update(pair_guess_blocks(str(slot), offsets, request.pair_deltas[slot], soft))
        solution = self._ladder_solve(self.rescue, params, point, pinned, copies=len(request.neighbours),
                                     planes=request.num_planes)
        if not solution.success:
            return None, solution.solve_time
        states, inputs = solution.x["X"].T, solution.x["U"].T
        if self._violation(states, request) >= before:
            return None, solution.solve_time
        return (states, inputs), solution.solve_time

    def _warm_duals(self, request: LocalRequest, same_shape: bool) -> tuple[np.ndarray, np.ndarray] | None:
        """The last iterate's multipliers, for a later ADMM iteration of the same MPC step on the
        same problem. A new step starts cold: shifted multipliers let a lone agent's plan slide
        out of local minima it used to keep (u-trap), a change of behaviour, not only of speed."""
        if self._last is None or not same_shape or request.new_step:
            return None
        return self._last.lam_x, self._last.lam_g

    def _unchanged_lone_problem(self, request: LocalRequest) -> bool:
        """True when this request is the same lone problem the last one was: nobody couples with
        the agent, in the same MPC step, from the same state. Without consensus blocks its problem
        does not depend on z or rho, so the last (successful) answer is the answer again."""
        return (
            not request.neighbours and not request.new_step and request.neighbour_plans is None
            and self._last_neighbours == () and self._last_sent is not None and self._last_sent.success
            and self._last_state is not None and np.array_equal(request.state, self._last_state)
            and self._same_planes(request)
        )

    def _same_planes(self, request: LocalRequest) -> bool:
        """True when ``request`` poses the separating planes of the last request."""
        normals, offsets = self._last_planes
        if request.plane_normals is None or normals is None:
            return request.plane_normals is None and normals is None
        return (np.array_equal(request.plane_normals, normals)
                and np.array_equal(request.plane_offsets, offsets))

    def _consensus_targets(self, request: LocalRequest, params: dict[str, Any]) -> tuple[float, float, np.ndarray]:
        """(rho, owner weight, every block's target z - gamma / rho_b): the local problem depends
        on the consensus only through these, the cost being rho_b / 2 ||v - target||^2 + const."""
        rho, weight = float(request.rho), float(request.owner_weight)
        blocks = [np.asarray(params["Z"]) - np.asarray(params["Y"]) / (rho * weight)]
        blocks += [np.asarray(params[f"Z{slot}"]) - np.asarray(params[f"Y{slot}"]) / rho
                   for slot in range(len(request.neighbours))]
        return rho, weight, np.concatenate([b.ravel() for b in blocks])

    def _reusable(self, request: LocalRequest, targets: tuple[float, float, np.ndarray], same_shape: bool) -> bool:
        """True when the last answer of this MPC step solves the problem posed now to within
        ``request.reuse_tol`` of its targets (see ``ADMMConfig.reuse_tol``)."""
        solved, last = self._solved_targets, self._last_sent
        return (
            request.reuse_tol > 0 and not request.new_step and request.neighbour_plans is None and same_shape
            and solved is not None and last is not None and last.success and not last.fallback
            and solved[:2] == targets[:2] and solved[2].shape == targets[2].shape
            and float(np.max(np.abs(solved[2] - targets[2]))) <= request.reuse_tol
        )

    def solve(self, request: LocalRequest) -> LocalResult:
        """Multiplier update for the new consensus, then the local NLP."""
        if self._unchanged_lone_problem(request) and self._last_sent is not None:
            return replace(self._last_sent, solve_time=0.0, local_fallbacks=0)
        self._last_state = request.state
        self._fallbacks = 0
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
            "delta": request.pair_deltas.T,
            "rho": request.rho,
            "owner_weight": request.owner_weight,
            "Z": request.z_own,
            "Y": self._gamma_own if self._gamma_own is not None and not repair else zeros,
        }
        n = len(request.neighbours)
        for slot, j in enumerate(request.neighbours):
            if self.dynamic_copies:
                params[f"x0c{slot}"] = request.neighbour_states[slot]
            params[f"Z{slot}"] = request.z_neighbours[slot]
            params[f"Y{slot}"] = zeros if repair else self._gamma.get(j, zeros)
        planes = request.num_planes
        if planes:
            assert request.plane_normals is not None and request.plane_offsets is not None
            for p in range(planes):
                params[f"Hn{p}"] = request.plane_normals[p]
                params[f"Hb{p}"] = request.plane_offsets[p][None, :]
        # the same problem as the last solve: same copies, same planes
        same_shape = request.neighbours == self._last_neighbours and self._same_planes(request)
        targets = self._consensus_targets(request, params) if n else None
        if targets is not None and self._reusable(request, targets, same_shape) and self._last_sent is not None:
            self._last_sent = replace(self._last_sent, solve_time=0.0, local_fallbacks=0)
            return self._last_sent
        point: dict[str, np.ndarray] | np.ndarray
        if self._last is not None and same_shape and not request.new_step:
            point = self._last.x_vec  # the same problem's last solution, already laid out
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
            solution = self._ladder_solve(self.nlp, params, point, strict, copies=n, planes=planes)
            if not solution.success:
                solution = self._ladder_solve(self.nlp, params, point, pinned, copies=n, planes=planes)
        else:
            solution = self._ladder_solve(self.nlp, params, point, pinned, copies=n, planes=planes,
                                      duals=self._warm_duals(request, same_shape) if pinned is None else None)
        if pinned is not None and not solution.success and self._plan is not None:
            solution = self._repair_from_own_plan(request, params, pinned, solution)
        first = s.first_constrained_step
        kept = solution.status == KEPT_PLAN  # no solve succeeded; the current plan is verified
        fallback = kept and self._last_sent is not None and self._last_sent.fallback
        slack: list[float] = []
        self._solved_targets = targets if solution.success and not repair else None
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
            if pinned is not None and request.rescue:
                rescued, rescue_time = self._rescue(request, params, pinned, states)
                solution = replace(solution, solve_time=solution.solve_time + rescue_time)
                if rescued is not None:
                    states, inputs = rescued
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
            success=solution.success and not kept,
            fallback=fallback,
            solve_time=solution.solve_time,
            max_slack=float(max(slack)) if slack else 0.0,
            cost=solution.cost,
            local_fallbacks=self._fallbacks,
        )
        self._last_sent = result
        self._last_neighbours = request.neighbours
        self._last_planes = (request.plane_normals, request.plane_offsets)
        return result


DEFAULT_COUPLING = {"hard": (0.2, 0.1), "soft": (0.5, 0.0)}
"""(coupling margin [m], closing time [s]) by collision form when the scenario leaves the margin
open. Hard constraints afford a small margin: a pair coupled too late is caught by the conflict
check after convergence, before any plan is applied, and costs an iteration. The closing-time
term lets pairs that approach fast (the paper's head-on swaps) couple a little earlier. Soft
constraints do not afford a small margin: a late pair's slack is paid for in the cost and no
check undoes it (paper-3d soft at 0.2 m: cost 17 752 against 345 at 0.5 m; docs/admm.md)."""


def default_coupling(collision: str) -> tuple[float, float]:
    """(coupling_margin, closing_time) for hard or soft collision constraints (:data:`DEFAULT_COUPLING`)."""
    return DEFAULT_COUPLING[collision]


REPAIR_ROUNDS = 3
"""Most repair passes in one MPC step (the first, plus re-runs after coupling pairs whose repaired
plans conflict)."""


def reach_radius(states: np.ndarray, settings: OCPSettings) -> np.ndarray:
    """Largest inf-norm displacement each agent's plan can make from ``states`` within the horizon.

    Parameters
    ----------
    states : ndarray, shape (M, 2d)
        Current (measured) states [p, v], the states the plans start from.
    settings : OCPSettings
        Horizon, time step and the limits the plans obey.

    Returns
    -------
    ndarray, shape (M,)
        Per agent, an upper bound on max_k ||p_k - p_0||_inf over the horizon T = horizon * dt
        (``inf`` when the plans are not limited).

    Notes
    -----
    Per axis, with an acceleration limit a: ``|v_axis| T + a T^2 / 2``, the continuous-time bound,
    which both discretisations stay within (Euler moves dt^2 a k(k-1)/2 in k steps, the zero-order
    hold exactly a (k dt)^2 / 2); every plan the solver emits obeys it: local solutions, the
    braking plan and the replayed previous plan of a fallback. With a speed limit s (a bound on the
    norm, so on every axis, for every planned velocity after the measured one):
    ``T max(s, |v_axis|)``, which is ``s T`` whenever the measured velocity is within the limit
    and also covers a measured velocity above it (the first step moves with it) and the braking
    plan (whose speed never grows). With both limits, the smaller bound; with neither, ``inf``.
    Not covered by the speed bound: a fallback that replays the previous plan from a state off
    that plan (its velocities shift by the offset); :meth:`ADMMSolver.plan` therefore also checks
    every pair of an agent whose plan moved farther than this bound.
    """
    states = np.asarray(states, float)
    d = settings.dim
    horizon_time = settings.horizon * settings.dt
    velocity = np.abs(states[:, d : 2 * d])
    reach = np.full(velocity.shape, np.inf)
    if settings.accel is not None:
        reach = velocity * horizon_time + 0.5 * np.asarray(settings.accel, float) * horizon_time**2
    if settings.speed is not None:
        reach = np.minimum(reach, horizon_time * np.maximum(velocity, settings.speed))
    return reach.max(axis=1)


def reach_candidates(states: np.ndarray, settings: OCPSettings, delta: np.ndarray) -> np.ndarray:
    """Pairs of agents whose plans can come within Delta_ij + d_min of each other during the horizon.

    Parameters
    ----------
    states : ndarray, shape (M, 2d)
        Current (measured) states [p, v].
    settings : OCPSettings
        Horizon, time step, ``d_min`` and the limits (see :func:`reach_radius`).
    delta : array_like
        One Delta (d,) for every pair, or the agents' body half-sizes (M, d) with
        Delta_ij = b_i + b_j (:func:`swarmpc.model.geometry.as_bodies`).

    Returns
    -------
    ndarray of bool, shape (M, M)
        Symmetric; ``[i, j]`` is True when the current inf-norm gap between agents i and j is
        below ``max(Delta_ij) + d_min + reach_i + reach_j``; the diagonal is False. Without limits
        every pair (i != j) is a candidate.

    Notes
    -----
    Why: by the triangle inequality the gap at any step of the horizon is at least the current gap
    minus both agents' displacements, so a pair that is not a candidate stays at least
    ``max(Delta_ij) + d_min`` apart (inf-norm) in any plans the two can have. On that axis the
    offset is at least Delta_ij,axis + d_min, so the OBCA pair constraint holds without being
    imposed: such a pair needs no copies, no certificate and no conflict check. Recomputed every
    MPC step.
    """
    states = np.asarray(states, float)
    d = settings.dim
    reach = reach_radius(states, settings)
    positions = states[:, :d]
    gaps = np.max(np.abs(positions[:, None, :] - positions[None, :, :]), axis=2)
    limit = largest_pair_delta(as_bodies(delta, len(states))) + settings.d_min
    candidates = gaps < limit + reach[:, None] + reach[None, :]
    np.fill_diagonal(candidates, False)
    return candidates


PLANE_EXTRA = 1e-3
"""Separation [m] a plane pair keeps beyond d_min, so that a plan meeting its plane to the solver's
constraint tolerance (1e-4 here) still clears d_min."""


PLANE_GOAL_RADIUS = 0.5
"""[m] An agent this close to its goal gets no separating planes (its near pairs keep copies): a
plane lets a parked agent yield only half the spare room, and agents threading between parked
ones took 6-10 s longer, or did not arrive, with planes to them (docs/admm.md)."""


def separating_planes(
    first: np.ndarray, second: np.ndarray, delta: np.ndarray, clearance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-step separating planes between two agents' guessed positions, split between the two.

    Parameters
    ----------
    first, second : ndarray, shape (d, K)
        The two agents' guessed positions at the constrained steps.
    delta : ndarray, shape (d,)
        The pair's Delta_ij per axis (b_i + b_j): the box the offset of the two keeps out of.
    clearance : float
        Distance to keep beyond the box (d_min, plus :data:`PLANE_EXTRA` in the solver).

    Returns
    -------
    normals : ndarray, shape (d, K)
        Per step, the unit axis vector n_k (pointing from ``second`` to ``first``) of the axis on
        which the guesses clear the box farthest.
    first_offsets, second_offsets : ndarray, shape (K,)
        Per step, ``first`` keeps n_k' p_k >= first_offsets[k] and ``second`` keeps
        -n_k' p_k >= second_offsets[k].

    Notes
    -----
    The guesses leave a spare room s_k = |o_a| - delta_a - clearance on that axis a (o = first -
    second); each agent may move s_k / 2 towards the other. Any two positions that keep to their
    sides then have n_k'(p - q) >= delta_a + clearance: they are at least ``clearance`` apart on
    axis a beyond the box, so the Euclidean distance of the offset to the box is at least
    ``clearance`` (OBCA's condition) whatever either agent does within its side. With s_k < 0
    the guesses themselves are too close and the sides overlap: only pairs with s_k >= 0 at every
    step are given planes.
    """
    offset = np.asarray(first, float) - np.asarray(second, float)
    half = np.asarray(delta, float).reshape(-1)
    steps = np.arange(offset.shape[1])
    axis = np.argmax(np.abs(offset) - half[:, None], axis=0)
    sign = np.where(offset[axis, steps] >= 0.0, 1.0, -1.0)
    normals = np.zeros_like(offset)
    normals[axis, steps] = sign
    spare = np.abs(offset[axis, steps]) - half[axis] - clearance
    first_offsets = sign * np.asarray(first, float)[axis, steps] - 0.5 * spare
    second_offsets = -sign * np.asarray(second, float)[axis, steps] - 0.5 * spare
    return normals, first_offsets, second_offsets


def couple(neighbours: list[tuple[int, ...]], pairs: list[tuple[int, int]]) -> list[tuple[int, ...]]:
    """``neighbours`` with every pair in ``pairs`` coupled (both ways)."""
    coupled = [set(n) for n in neighbours]
    for i, j in pairs:
        coupled[i].add(j)
        coupled[j].add(i)
    return [tuple(sorted(n)) for n in coupled]


def components(neighbours: list[tuple[int, ...]]) -> np.ndarray:
    """Label per agent of its connected component in the coupling graph (labels 0, 1, ...)."""
    labels = np.full(len(neighbours), -1)
    count = 0
    for start in range(len(neighbours)):
        if labels[start] >= 0:
            continue
        stack = [start]
        labels[start] = count
        while stack:
            for j in neighbours[stack.pop()]:
                if labels[j] < 0:
                    labels[j] = count
                    stack.append(j)
        count += 1
    return labels


@dataclass(frozen=True)
class EngagedBlocks:
    """Which consensus blocks count in the residuals: own blocks per agent, copy slots per agent."""

    own: np.ndarray
    copies: list[tuple[bool, ...]]


@dataclass(frozen=True)
class TimedResult(LocalResult):
    """A :class:`LocalResult` that also carries the wall time of the local step that produced it."""

    call_time: float = 0.0
    """Seconds the agent spent on the request where it runs: its solver calls (``solve_time``)
    plus its own bookkeeping around them (multipliers, parameters, the reuse test)."""


class TimedAgent:
    """An agent whose answers carry the wall time of its whole local step (:class:`TimedResult`).

    The critical path (:class:`StepClock`) needs each agent's compute per request, measured where
    the agent runs (a worker process under the process executor); executors pass answers through
    unopened, so the answer carries it. Every other attribute is the wrapped agent's, read and
    written through: code that reaches into an executor's agents meets the agent itself.
    """

    def __init__(self, agent: Any) -> None:
        object.__setattr__(self, "_inner", agent)

    def __getattr__(self, name: str) -> Any:
        if name == "_inner":  # not set yet (a copy or unpickling in progress): no recursion
            raise AttributeError(name)
        return getattr(self._inner, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._inner, name, value)

    def solve(self, request: LocalRequest) -> TimedResult:
        started = time.perf_counter()
        result = self._inner.solve(request)
        elapsed = time.perf_counter() - started
        return TimedResult(**{f.name: getattr(result, f.name) for f in fields(LocalResult)}, call_time=elapsed)


class TimedAgentFactory:
    """Picklable: the agents ``factory`` makes, each wrapped in a :class:`TimedAgent`."""

    def __init__(self, factory: Callable[[int], Any]) -> None:
        self.factory = factory

    def __call__(self, agent: int) -> TimedAgent:
        return TimedAgent(self.factory(agent))


class StepClock:
    """The compute on one MPC step's critical path, and the anytime stop at the step's deadline.

    The critical path is what the step would take with one core per agent and no transport
    latency: the coordinator's own work (everything in :meth:`ADMMSolver.plan` outside the agents'
    local steps) plus, for every batch of local steps it waits for, the slowest agent's local step
    (:attr:`TimedResult.call_time`; ``solve_time`` for answers of executors that do not ask the
    agents themselves). It is measured as the step's wall time less, per batch, the batch's wall
    time beyond its slowest agent: under the serial executor the other agents' steps, under a
    process executor the queueing and transport. The repair pass hands its agents over one at a
    time, so its sequential re-plans add up in full.

    Parameters
    ----------
    deadline : float or None
        Critical-path budget of the step [s]; None: no deadline.
    """

    def __init__(self, deadline: float | None = None) -> None:
        self.deadline = deadline
        self.started = time.perf_counter()
        self.stopped = False
        """True once :meth:`next_iteration` refused an iteration for the deadline."""
        self._overlap = 0.0
        self._iteration_began: float | None = None

    def elapsed(self) -> tuple[float, float]:
        """(wall time, critical path) of the step so far [s], read at one instant."""
        wall = time.perf_counter() - self.started
        return wall, wall - self._overlap

    def solve(self, executor: Executor, requests: Sequence[LocalRequest]) -> list[LocalResult]:
        """``executor``'s answers to ``requests``; the batch counts as its slowest agent's step."""
        began = time.perf_counter()
        results = executor.solve(requests)
        batch = time.perf_counter() - began
        slowest = max((getattr(r, "call_time", r.solve_time) for r in results), default=0.0)
        self._overlap += max(batch - slowest, 0.0)
        return results

    def next_iteration(self) -> bool:
        """Whether to start another ADMM iteration. No (and :attr:`stopped`) when the critical path
        so far plus the last iteration's share of it would exceed the deadline: the last iteration
        is the estimate of the next. The first iteration always runs: without it there is no plan
        to make safe."""
        now = self.elapsed()[1]
        last, self._iteration_began = self._iteration_began, now
        if last is None or self.deadline is None or now + (now - last) <= self.deadline:
            return True
        self.stopped = True
        return False


class ADMMSolver:
    """Consensus-ADMM distributed MPC over an executor (serial by default).

    ``delta`` is one Delta (d,) for every pair, or the agents' body half-sizes (M, d): pair (i, j)
    keeps Delta_ij = b_i + b_j and agent i's obstacles are grown by b_i
    (:func:`swarmpc.model.geometry.as_bodies`).
    """

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
        self.bodies = as_bodies(delta, num_agents)
        self._largest_delta = largest_pair_delta(self.bodies)
        """(M, M) largest axis of each pair's Delta_ij."""
        self.config = config
        self.executor = executor or SerialExecutor()
        factory = LocalAgentFactory(settings, max(num_agents - 1, 1), config.dynamic_copies, config.seed_duals,
                                    config.warm_start, bodies=self.bodies, local=config.local)
        self.executor.start(TimedAgentFactory(factory), range(num_agents))
        self._z: np.ndarray | None = None
        self._rho = config.rho
        self._final_neighbours: list[tuple[int, ...]] | None = None
        self._planes: list[dict[int, tuple[np.ndarray, np.ndarray]]] = [{} for _ in range(num_agents)]
        """This step's separating planes: per agent, partner -> (normals (d, K), offsets (K,))."""
        self._clock = StepClock()
        """The current step's clock: every local step is asked through it (:meth:`_solve`)."""

    def close(self) -> None:
        self.executor.close()

    def pair_delta(self, first: Any, second: Any) -> np.ndarray:
        """Delta_ij = b_i + b_j of agents ``first`` and ``second`` (indices or index arrays):
        (d,) for one pair, (n, d) for n pairs."""
        return self.bodies[first] + self.bodies[second]

    def neighbours(self, guess: np.ndarray, candidates: np.ndarray | None = None) -> list[tuple[int, ...]]:
        """Agents each agent couples with this step (symmetric).

        With ``coupling_margin`` None, every other agent (the paper's all-to-all copies). Otherwise
        only reach ``candidates`` (:func:`reach_candidates`; None: every pair) whose guessed
        trajectories come within max(Delta_ij) + d_min + margin (inf-norm) of each other at some
        constrained step; candidate pairs left out are checked after convergence and coupled on
        demand if their plans conflict (see :meth:`plan`). A pair that is not a candidate cannot
        come within Delta_ij + d_min during the horizon, so it needs no coupling.
        """
        M = self.num_agents
        if self.config.coupling_margin is None:
            return [tuple(j for j in range(M) if j != i) for i in range(M)]
        first, d = self.settings.first_constrained_step, self.settings.dim
        reach = self._largest_delta + self.settings.d_min + self.config.coupling_margin
        positions = guess[:, first:, :d]
        gaps = np.max(np.abs(positions[:, None] - positions[None, :]), axis=3).min(axis=2)
        velocities = guess[:, :, d: 2 * d]
        closing = np.max(np.abs(velocities[:, None] - velocities[None, :]), axis=(2, 3))
        coupled = gaps < reach + self.config.closing_time * closing
        if candidates is not None:
            coupled &= candidates
        np.fill_diagonal(coupled, False)
        return [tuple(np.flatnonzero(row).tolist()) for row in coupled]

    def reachable_guesses(self, states: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which guesses a plan can follow, and their positions at the constrained steps (M, K, d).

        A guess is followable when it starts at the measured state and obeys the dynamics and the
        acceleration limit up to its second-to-last state (a shifted previous plan does; a straight
        line from rest does not). Its last state repeats the one before; the positions returned
        coast there instead (zero input), so that a plan can be at every one of them. Planes are
        placed only between followable guesses: a plane drawn from a guess the agent cannot follow
        can cut its reachable positions off altogether."""
        s = self.settings
        d, first = s.dim, s.first_constrained_step
        A, B = discrete_matrices(d, s.dt, s.discretization)  # type: ignore[arg-type]
        head = guess[:, :-1]
        inputs = np.diff(head[:, :, d:], axis=1) / s.dt  # (M, N-1, d)
        predicted = head[:, :-1] @ A.T + inputs @ B.T
        scale = 1.0 + np.abs(guess).max(axis=(1, 2))
        ok = np.abs(predicted - head[:, 1:]).max(axis=(1, 2)) <= 1e-6 * scale
        ok &= np.abs(guess[:, 0] - states).max(axis=1) <= 1e-6 * scale
        if s.accel is not None:
            ok &= (np.abs(inputs) <= np.asarray(s.accel, float) * (1 + 1e-6) + 1e-9).all(axis=(1, 2))
        coasting = guess.copy()
        coasting[:, -1] = guess[:, -2] @ A.T
        return ok, coasting[:, first:, :d]

    def plane_pairs(
        self, states: np.ndarray, guess: np.ndarray, neighbours: list[tuple[int, ...]],
        goals: np.ndarray | None = None,
    ) -> tuple[list[tuple[int, int]], np.ndarray]:
        """Coupled pairs (i < j) that a separating plane keeps apart instead of copies, and the
        positions (M, K, d) the planes are drawn from. A pair qualifies when both guesses can be
        followed (:meth:`reachable_guesses`) and clear the pair's Delta_ij box by d_min +
        ``plane_margin`` on some axis at every constrained step (see ``ADMMConfig.plane_margin``), and, with
        ``goals``, neither agent is within ``PLANE_GOAL_RADIUS`` of its goal: an agent parked at
        its goal keeps copies of those near it, so that it can move aside for them."""
        margin = self.config.plane_margin
        if margin is None or not any(neighbours):
            return [], np.empty((0,))
        followable, positions = self.reachable_guesses(states, guess)
        if goals is not None:
            d = self.settings.dim
            followable &= np.linalg.norm(states[:, :d] - goals[:, :d], axis=1) > PLANE_GOAL_RADIUS
        pairs = []
        for i, n in enumerate(neighbours):
            if not followable[i]:
                continue
            for j in n:
                if j > i and followable[j]:
                    excess = (np.abs(positions[i] - positions[j]) - self.pair_delta(i, j)).max(axis=1).min()
                    if excess >= self.settings.d_min + margin:
                        pairs.append((i, j))
        return pairs, positions

    def _set_planes(self, positions: np.ndarray, pairs: list[tuple[int, int]]) -> None:
        """Split each plane pair's separating planes (:func:`separating_planes`) between the two;
        ``positions`` (M, K, d) at the constrained steps."""
        self._planes = [{} for _ in range(self.num_agents)]
        clearance = self.settings.d_min + PLANE_EXTRA
        for i, j in pairs:
            normals, offsets_i, offsets_j = separating_planes(
                positions[i].T, positions[j].T, self.pair_delta(i, j), clearance)
            self._planes[i][j] = (normals, offsets_i)
            self._planes[j][i] = (-normals, offsets_j)

    def _couple(self, neighbours: list[tuple[int, ...]], pairs: list[tuple[int, int]]) -> list[tuple[int, ...]]:
        """:func:`couple`, and any of ``pairs`` that had a separating plane loses it (the copies
        and OBCA take over)."""
        for i, j in pairs:
            self._planes[i].pop(j, None)
            self._planes[j].pop(i, None)
        return couple(neighbours, pairs)

    def _with_planes(self, neighbours: list[tuple[int, ...]]) -> list[tuple[int, ...]]:
        """``neighbours`` plus every plane partner (pairs the plain conflict check must skip)."""
        return couple(neighbours, [(i, j) for i, planes in enumerate(self._planes) for j in planes])

    def broken_planes(self, results: list[LocalResult]) -> list[tuple[int, int]]:
        """Plane pairs (i < j) whose own plans do not keep half the OBCA separation (a fallback
        plan, or a solve that missed its plane): they are coupled with copies."""
        pairs = np.array([(i, j) for i, planes in enumerate(self._planes) for j in planes if i < j],
                         int).reshape(-1, 2)
        broken = ~self._pairs_apart(results, pairs[:, 0], pairs[:, 1])
        return [(int(i), int(j)) for i, j in pairs[broken]]

    def _missing(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]], checked: np.ndarray,
    ) -> list[tuple[int, int]]:
        """Pairs to couple before any plan is applied: candidate pairs with neither copies nor a
        plane whose plans conflict, and plane pairs whose plans break the separation."""
        return self.conflicts(results, self._with_planes(neighbours), checked) + self.broken_planes(results)

    def conflicts(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]], candidates: np.ndarray | None = None
    ) -> list[tuple[int, int]]:
        """Uncoupled candidate pairs (i < j) whose own plans come closer than the coupling would allow
        (inf-norm below max(Delta_ij) + d_min at some constrained step); ``candidates`` None: every pair."""
        M = self.num_agents
        examine = np.triu(np.ones((M, M), bool) if candidates is None else candidates, k=1)
        for i, n in enumerate(neighbours):
            examine[i, list(n)] = False
        first, second = np.nonzero(examine)
        if first.size == 0:
            return []
        own = np.array([r.own for r in results])  # (M, d, K)
        gaps = np.max(np.abs(own[first] - own[second]), axis=1).min(axis=1)
        hit = gaps < self._largest_delta[first, second] + self.settings.d_min
        return list(zip(first[hit].tolist(), second[hit].tolist()))

    def plans_feasible(self, results: list[LocalResult], pairs: np.ndarray) -> bool:
        """Every agent's solve succeeded and, for every pair in ``pairs`` (M x M, bool), the own
        plans keep at least half the OBCA separation (see :meth:`_own_plans_apart`)."""
        if not all(r.success and not r.fallback for r in results):
            return False
        first, second = np.nonzero(np.triu(pairs, k=1))
        return self._own_plans_apart(results, first, second)

    def coupled_plans_clear(self, results: list[LocalResult], neighbours: list[tuple[int, ...]]) -> bool:
        """Every coupled pair's own plans keep half the OBCA separation (see
        :meth:`_own_plans_apart`). Each agent keeps d_min from its copies, and consensus within
        ``tol`` (an RMS) bounds how far the copies sit from the plans flown, not every single step:
        under a loose ``tol`` this check, not the tolerance, is what keeps the flown plans apart,
        and ADMM iterates on until it holds."""
        pairs = np.array([(i, j) for i, n in enumerate(neighbours) for j in n if i < j], int).reshape(-1, 2)
        return self._own_plans_apart(results, pairs[:, 0], pairs[:, 1])

    def _own_plans_apart(self, results: list[LocalResult], first: np.ndarray, second: np.ndarray) -> bool:
        """The own plans of agents ``first[k]`` and ``second[k]`` keep a Euclidean distance of the
        offset to the pair's Delta_ij box of at least d_min / 2 at every constrained step. An RMS consensus
        within tol still lets single steps of two own plans differ from the copies by more: half
        of d_min is kept as the margin, contact is at 0."""
        return bool(np.all(self._pairs_apart(results, first, second)))

    def _pairs_apart(self, results: list[LocalResult], first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """Per pair k: whether agents ``first[k]`` and ``second[k]`` keep their own plans apart as
        :meth:`_own_plans_apart` asks."""
        if first.size == 0:
            return np.ones(0, bool)
        own = np.array([r.own for r in results])  # (M, d, K)
        half = self.pair_delta(first, second)[:, :, None]  # (n, d, 1)
        outside = box_exterior_distance(own[first] - own[second], half, axis=1)
        return np.all(outside >= 0.5 * self.settings.d_min, axis=1)

    def _checked_pairs(self, candidates: np.ndarray, states: np.ndarray, results: list[LocalResult]) -> np.ndarray:
        """``candidates`` plus every pair of an agent whose plan moved farther than its reach bound
        (a replayed fallback under a speed limit, or solver tolerance), so the conflict check never
        relies on a bound a plan broke."""
        d = self.settings.dim
        own = np.array([r.own for r in results])  # (M, d, K)
        moved = np.max(np.abs(own - np.asarray(states)[:, :d, None]), axis=(1, 2))
        escaped = moved > reach_radius(states, self.settings)
        if not escaped.any():
            return candidates
        checked = candidates | escaped[:, None] | escaped[None, :]
        np.fill_diagonal(checked, False)
        return checked

    def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> PlanStep:
        """One MPC step: ADMM iterations until consensus, then every agent's own plan.

        With ``config.deadline``, ADMM is anytime: before each iteration after the first, the
        step's critical path so far plus the last iteration's share of it is compared with the
        deadline (:class:`StepClock`); when it would overrun, no further iteration starts and the
        step ends as one that ran out of iterations does, through :meth:`_make_safe` (the repair
        pass, re-run on conflicting candidate pairs, then re-plans around stranded fallbacks;
        always run after a deadline stop, even with ``repair`` off).

        What is guaranteed: the deadline only ever removes ADMM iterations; it never shortens or
        skips a safety pass. A plan applied after a deadline stop has passed exactly the passes of
        a step that reached ``max_iter`` without consensus: every coupled agent re-planned, one
        after another, against its neighbours' current plans held fixed (each coupled pair is
        then feasible under the OBCA constraints whenever its solves succeed); an agent whose
        solves failed keeps its current plan if it verifiably meets every constraint, else flies
        a fallback that the agents after it respect and that its close neighbours re-plan around
        (rescued by the least-violating soft plan as a last resort); and every candidate pair that
        can meet within the horizon was checked for conflicts and, if it had one, coupled and
        repaired (up to :data:`REPAIR_ROUNDS` passes). The time of these passes counts on the
        critical path; when the total exceeds the deadline the step is a deadline miss (recorded
        by the run), never an unchecked plan. Not guaranteed: that the critical path stays within
        the deadline (the first iteration and the safety passes always run), nor the plan's
        quality (fewer iterations: further from the consensus optimum). Stopping depends on
        measured time, so a deadline that binds makes a run depend on the machine and its load.
        """
        clock = self._clock = StepClock(self.config.deadline)
        s, cfg, M = self.settings, self.config, self.num_agents
        first = s.first_constrained_step
        if self._z is None:
            z = np.transpose(guess[:, first:, : s.dim], (0, 2, 1)).copy()
        else:
            z = np.concatenate([self._z[:, :, 1:], self._z[:, :, -1:]], axis=2)
        candidates = reach_candidates(states, s, self.bodies)
        neighbours = self.neighbours(guess, candidates)
        planed, plane_positions = self.plane_pairs(states, guess, neighbours, goals)
        self._set_planes(plane_positions, planed)
        if planed:
            dropped = set(planed)
            neighbours = [tuple(j for j in n if (min(i, j), max(i, j)) not in dropped) for i, n in enumerate(neighbours)]
        rho = rho_previous = self._rho
        primal: list[float] = []
        dual: list[float] = []
        rhos: list[float] = []
        agent_times = np.zeros(M)
        failures = 0
        results: list[LocalResult] = []
        converged = False
        window_start = 0
        carry = self._carried_blocks(neighbours)
        by_component = cfg.component_stop and cfg.engage_margin is None
        iterating = np.ones(M, bool)  # agents whose component has not met the tolerance yet
        for iteration in range(cfg.max_iter):
            if not clock.next_iteration():
                break
            requests = [
                self._request(i, states, goals, guess, neighbours[i], z, rho, rho_previous, iteration == 0,
                              carry=carry[i] if iteration == 0 else ())
                for i in map(int, np.flatnonzero(iterating))
            ]
            fresh = self._solve(requests)
            if len(fresh) == M:
                results = list(fresh)
            else:  # the stopped components' answers stand
                for r in fresh:
                    results[r.agent] = r
            for r in fresh:
                agent_times[r.agent] += r.solve_time
            failures += sum(not r.success for r in fresh)
            z_new, r_norm, weights = self._average(results, neighbours, z)
            z_new_change = z_new - z
            s_norm = self._dual_residual(z_new_change, weights, neighbours, rho)
            if by_component:
                iterating = ~self._components_converged(results, neighbours, z_new, z_new_change, weights, rho)
            z = z_new
            if cfg.engage_margin is not None:
                # only blocks where a pair's separation binds carry information the others need
                blocks = self.engaged_blocks(results, neighbours, cfg.engage_margin)
                r_norm = self._primal_residual(results, neighbours, z, blocks)
                s_norm = self._dual_residual(z_new_change, weights, neighbours, rho, blocks)
            # a raised rho scales the dual residual, not the motion of z it measures: compare
            # it at the step's starting penalty, or raising rho would itself block convergence
            converged = r_norm <= cfg.tol and (
                s_norm <= cfg.tol * rho / cfg.rho or cfg.engage_margin is not None
            )
            if by_component:
                converged = converged or not iterating.any()
            primal.append(r_norm)
            dual.append(float(s_norm))
            rhos.append(rho)
            if converged:
                checked = self._checked_pairs(candidates, states, results)
                missing = self._missing(results, neighbours, checked)
                if not missing and (cfg.engage_margin is None or self.plans_feasible(results, checked)) and (
                    self.coupled_plans_clear(results, neighbours)
                ):
                    break
                converged = False
                neighbours = self._couple(neighbours, missing)
                if by_component:  # the components the new pairs join iterate again
                    labels = components(neighbours)
                    iterating |= np.isin(labels, labels[[i for pair in missing for i in pair]])
            rho_previous = rho
            rho, window_start, stalled = self._next_penalty(primal, window_start, rho, r_norm, s_norm)
            if stalled:
                break
        repair = cfg.repair or clock.stopped  # a deadline stop is never left unrepaired
        results, neighbours, times, failed = self._make_safe(
            states, goals, guess, neighbours, z, rho, results, candidates, not converged and repair, repair)
        agent_times += times
        failures += failed
        # next step's consensus starts from the plans actually applied: after a repair pass the
        # average z of a non-converged iterate is not what any agent flies
        self._z = np.array([r.own for r in results])
        self._final_neighbours = neighbours
        self._rho = rho if cfg.adaptive_rho else cfg.rho
        plans_x = np.array([r.states for r in results])
        plans_u = np.array([r.inputs for r in results])
        fallback = np.array([r.fallback for r in results])
        wall, critical = clock.elapsed()
        return PlanStep(
            states=plans_x,
            inputs=plans_u,
            predicted_cost=float(sum(r.cost for r in results)),
            max_slack=float(max(r.max_slack for r in results)),
            wall_time=wall,
            agent_times=agent_times,
            failures=failures,
            fallback=fallback,
            admm_iterations=len(primal),
            repaired=not converged and repair,
            critical_path=critical,
            deadline_stop=clock.stopped,
            primal_residuals=primal,
            dual_residuals=dual,
            rho_history=rhos,
            copies=np.array([len(n) for n in neighbours], int),
            planes=np.array([len(p) for p in self._planes], int),
        )

    def _solve(self, requests: list[LocalRequest]) -> list[LocalResult]:
        """The agents' answers to ``requests``, timed on the current step's critical path."""
        return self._clock.solve(self.executor, requests)

    def _next_penalty(
        self, primal: list[float], window_start: int, rho: float, r_norm: float, s_norm: float,
    ) -> tuple[float, int, bool]:
        """(rho, start of the stall window, stop) for the next iteration: a stalled primal
        residual (:meth:`_stalled`) stiffens rho and restarts the window, or stops the iterations
        when rho cannot grow; ``adaptive_rho`` then balances the residuals."""
        cfg = self.config
        if self._stalled(primal[window_start:]):
            if cfg.stall_rho_factor is None or rho >= cfg.rho_bounds[1]:
                return rho, window_start, True
            # a stalled nonconvex ADMM often settles once the penalty is stiffer
            rho = min(rho * cfg.stall_rho_factor, cfg.rho_bounds[1])
            window_start = len(primal)
        if cfg.adaptive_rho:
            if r_norm > 10 * s_norm:
                rho = min(rho * 2, cfg.rho_bounds[1])
            elif s_norm > 10 * r_norm:
                rho = max(rho / 2, cfg.rho_bounds[0])
        return rho, window_start, False

    def _make_safe(
        self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray, neighbours: list[tuple[int, ...]],
        z: np.ndarray, rho: float, results: list[LocalResult], candidates: np.ndarray, repair_all: bool,
        stranded_check: bool,
    ) -> tuple[list[LocalResult], list[tuple[int, ...]], np.ndarray, int]:
        """The safety passes after the iterations; returns the plans, the coupling, the solve time
        per agent and the failed solves the passes added.

        ``repair_all`` (ADMM stopped without consensus): the repair pass (:meth:`_repair`), and
        again after coupling any candidate pair whose repaired plans conflict, up to
        :data:`REPAIR_ROUNDS` passes. ``stranded_check``: fallbacks that break the separation from
        another plan re-plan against every plan (rescued if their hard solves fail), then their
        neighbours against them."""
        times, failures = np.zeros(self.num_agents), 0
        for round_ in range(REPAIR_ROUNDS if repair_all else 0):
            previous = results
            results = self._repair(states, goals, guess, neighbours, z, rho, results)
            # later passes count only the agents they re-solved
            new, failed = self._new_solves(results, previous, every=round_ == 0)
            times, failures = times + new, failures + failed
            # the repair only re-plans against neighbours: couple any candidate pair whose
            # repaired plans now conflict and repair again
            missing = self._missing(results, neighbours, self._checked_pairs(candidates, states, results))
            if not missing or round_ == REPAIR_ROUNDS - 1:
                break
            neighbours = self._couple(neighbours, missing)
        stranded = self._stranded_fallbacks(results) if stranded_check else []
        if stranded:
            neighbours = self._couple(neighbours, stranded)
            previous = results
            results = self._repair(states, goals, guess, neighbours, z, rho, results,
                                   agents=sorted({i for i, _ in stranded}))
            new, failed = self._new_solves(results, previous)
            times, failures = times + new, failures + failed
        return results, neighbours, times, failures

    @staticmethod
    def _new_solves(
        results: list[LocalResult], previous: list[LocalResult], every: bool = False,
    ) -> tuple[np.ndarray, int]:
        """Solve time per agent and failed solves of the answers a repair pass produced (those not
        carried over from ``previous``; ``every``: all of them)."""
        new = [every or r is not old for r, old in zip(results, previous)]
        times = np.array([r.solve_time if fresh else 0.0 for r, fresh in zip(results, new)])
        return times, sum(fresh and not r.success for r, fresh in zip(results, new))

    def _stranded_fallbacks(self, results: list[LocalResult]) -> list[tuple[int, int]]:
        """(fallback agent, other agent) pairs whose plans come closer than d_min / 2 (signed
        distance to the pair's Delta_ij box) at a constrained step: a fallback nobody re-planned around,
        or two agents failing together, each blind to the other's fallback."""
        fell = [r.agent for r in results if r.fallback]
        if not fell:
            return []
        own = np.array([r.own for r in results])  # (M, d, K)
        pairs = []
        for i in fell:
            half = self.pair_delta(i, slice(None))[:, :, None]  # (M, d, 1)
            signed = box_signed_distance(own[i][None] - own, half, axis=1).min(axis=1)
            signed[i] = np.inf
            pairs += [(i, int(j)) for j in np.flatnonzero(signed < 0.5 * self.settings.d_min)]
        return pairs

    def _carried_blocks(self, neighbours: list[tuple[int, ...]]) -> list[tuple[bool, ...]]:
        """Per agent, which of its multipliers (own block, then each neighbour's) the new step
        carries over (see ``ADMMConfig.carry_multipliers``); every holder of a block decides
        alike, so each block's multipliers keep summing to zero."""
        mode, previous = self.config.carry_multipliers, self._final_neighbours
        if mode == "always":
            return [(True,) * (1 + len(n)) for n in neighbours]
        if mode == "never" or previous is None:
            return [(False,) * (1 + len(n)) for n in neighbours]
        stable = [n == p for n, p in zip(neighbours, previous)]
        return [(stable[i], *(stable[j] for j in n)) for i, n in enumerate(neighbours)]

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
        plans: tuple[np.ndarray, np.ndarray] | None = None, carry: tuple[bool, ...] = (), rescue: bool = False,
    ) -> LocalRequest:
        first = self.settings.first_constrained_step
        partners = sorted(self._planes[i])
        normals = offsets = None
        if partners:
            normals = np.array([self._planes[i][j][0] for j in partners])
            offsets = np.array([self._planes[i][j][1] for j in partners])
        if plans is None:
            z_neighbours = z[list(neighbours)]
        else:
            z_neighbours = np.transpose(plans[0][:, first:, : self.settings.dim], (0, 2, 1))
        return LocalRequest(
            agent=i,
            state=states[i],
            goal=goals[i],
            delta=self.pair_delta(i, list(neighbours)),
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
            reuse_tol=self.config.reuse_tol,
            relaxation=self.config.relaxation,
            carry=carry,
            rescue=rescue,
            plane_normals=normals,
            plane_offsets=offsets,
        )

    def _repair(
        self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray, neighbours: list[tuple[int, ...]],
        z: np.ndarray, rho: float, results: list[LocalResult], agents: list[int] | None = None,
    ) -> list[LocalResult]:
        """Consensus repair when ADMM stops at the cap: agents re-plan one after another against
        the others' current own plans (held fixed). Each agent respects the final plans of those
        before it and the plans those after it will respect, so every pair ends up feasible
        whenever the solves succeed. An agent whose solve fails flies its fallback plan, which
        the agents after it respect; it re-plans once more at the end, against everyone's final
        plans, since a plan that respects all of them keeps every pair it is in feasible. If it
        still fails, its fallback is final, and the agents repaired before it never saw it: each
        neighbour whose plan comes within max(Delta_ij) + d_min of that fallback re-plans once more
        against every final plan (spread M = 128 had a collision without this; docs/admm.md).
        ``agents``: re-plan only these (in this order) and then their neighbours as above; None:
        every coupled agent, highest index first."""
        first = self.settings.first_constrained_step
        repaired = list(results)

        def replan(i: int, rescue: bool = True) -> None:
            others = list(neighbours[i])
            plans = (
                np.array([repaired[j].states for j in others]),
                np.array([repaired[j].inputs for j in others]),
            )
            own_z = z.copy()
            own_z[i] = repaired[i].states[first:, : self.settings.dim].T
            request = self._request(i, states, goals, guess, neighbours[i], own_z, rho, rho, False, plans,
                                    rescue=rescue)
            repaired[i] = self._solve([request])[0]

        order = list(range(self.num_agents))[::-1] if agents is None else list(agents)  # tie-break: docs/admm.md
        retried: set[int] = set()
        for i in order:
            if not neighbours[i]:
                continue
            # a first failure re-plans at the end (its fallback is provisional); the retry and the
            # re-plan of a stranded fallback are final and may rescue
            replan(i, rescue=agents is not None or i in retried)
            if not repaired[i].success and i not in retried:
                retried.add(i)
                order.append(i)
        for failed in [k for k in range(self.num_agents) if not repaired[k].success]:
            for i in neighbours[failed]:
                gap = np.max(np.abs(repaired[i].own - repaired[failed].own), axis=0).min()
                if repaired[i].success and gap < self._largest_delta[i, failed] + self.settings.d_min:
                    replan(i)
        return repaired

    def _average(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]], z_previous: np.ndarray | None = None,
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """Consensus positions z (M, d, K), the RMS primal residual, and the own-block weights.

        z_j is the rho_b-weighted mean of every copy of agent j: its own plan (weight
        owner_weight, or 0 for an agent nobody couples with, whose z is then its plan) and the
        copies its neighbours hold (weight 1), each over-relaxed towards ``z_previous`` when
        ``relaxation`` is not 1 (an agent nobody couples with keeps its plan as z).
        """
        alpha = self.config.relaxation
        relax = alpha != 1.0 and z_previous is not None
        own = np.array([r.own for r in results])
        weights = np.array([self.config.owner_weight if n else 1.0 for n in neighbours])
        coupled = np.array([bool(n) for n in neighbours])
        relaxed_own = own
        if relax:
            relaxed_own = np.where(coupled[:, None, None], alpha * own + (1.0 - alpha) * z_previous, own)
        total = weights[:, None, None] * relaxed_own
        count = weights.copy()
        for r in results:
            for slot, j in enumerate(neighbours[r.agent]):
                copy = r.copies[slot]
                total[j] += alpha * copy + (1.0 - alpha) * z_previous[j] if relax else copy
                count[j] += 1
        z = total / count[:, None, None]
        return z, self._primal_residual(results, neighbours, z), weights

    def _components_converged(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]], z: np.ndarray,
        change: np.ndarray, weights: np.ndarray, rho: float,
    ) -> np.ndarray:
        """Per agent: its component of the coupling graph meets the tolerance on its own blocks
        (the primal and dual residuals of :meth:`_primal_residual` and :meth:`_dual_residual`,
        restricted to the component). Components are independent consensus problems: z of a
        block depends only on the answers of its component's agents."""
        cfg = self.config
        labels = components(neighbours)
        primal_sq = np.zeros(labels.max() + 1)
        primal_n = np.zeros_like(primal_sq)
        dual_sq = np.zeros_like(primal_sq)
        dual_n = np.zeros_like(primal_sq)
        held = np.zeros(self.num_agents, int)
        for n in neighbours:
            for j in n:
                held[j] += 1
        for r in results:
            c = labels[r.agent]
            primal_sq[c] += float(np.sum((r.own - z[r.agent]) ** 2))
            primal_n[c] += r.own.size
            for slot, j in enumerate(neighbours[r.agent]):
                primal_sq[c] += float(np.sum((r.copies[slot] - z[j]) ** 2))
                primal_n[c] += r.copies[slot].size
            own = bool(neighbours[r.agent])
            dual_sq[c] += (weights[r.agent] ** 2 * own + held[r.agent]) * float(np.sum(change[r.agent] ** 2))
            dual_n[c] += (own + held[r.agent]) * change[r.agent].size
        primal = np.sqrt(primal_sq / np.maximum(primal_n, 1))
        dual = rho * np.sqrt(dual_sq / np.maximum(dual_n, 1))
        met = (primal <= cfg.tol) & (dual <= cfg.tol * rho / cfg.rho)
        return met[labels]

    def _dual_residual(
        self, change: np.ndarray, weights: np.ndarray, neighbours: list[tuple[int, ...]], rho: float,
        blocks: EngagedBlocks | None = None,
    ) -> float:
        """RMS of rho_b (z - z_prev) over every consensus block (Boyd et al. sec. 3.3 with block
        penalties rho_b: rho * owner_weight for own blocks, rho for copies), or over ``blocks``
        only. Agents nobody couples with hold no consensus block and do not count."""
        if blocks is None:
            own = np.array([bool(n) for n in neighbours])
            copies = np.array([sum(j in n for n in neighbours) for j in range(self.num_agents)])
        else:
            own = blocks.own
            copies = np.zeros(self.num_agents, int)
            for i, n in enumerate(neighbours):
                for slot, j in enumerate(n):
                    copies[j] += blocks.copies[i][slot]
        per_agent = (weights**2 * own + copies) * np.sum(change**2, axis=(1, 2))
        entries = (own + copies).sum() * change[0].size
        return float(rho * np.sqrt(per_agent.sum() / max(entries, 1)))

    def engaged_blocks(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]], margin: float
    ) -> EngagedBlocks:
        """The consensus blocks of engaged pairs: a coupled pair is engaged when, in either
        agent's problem, its own plan comes within d_min + ``margin`` of its copy of the other
        (Euclidean distance to the pair's Delta_ij box) at some constrained step, or the two own
        plans do. A pair that is not
        engaged has slack certificates on both sides: its copies shape nobody's plan, so their
        disagreement need not be iterated away (the own plans are still checked for mutual
        feasibility before they are applied)."""
        pairs: set[tuple[int, int]] = set()
        limit = self.settings.d_min + margin

        def near(a: np.ndarray, b: np.ndarray, half: np.ndarray) -> bool:
            return bool(box_exterior_distance(a - b, half[:, None], axis=0).min() < limit)

        for r in results:
            for slot, j in enumerate(neighbours[r.agent]):
                half = self.pair_delta(r.agent, j)
                # close to its copy in i's problem, or close in the plans the two would fly
                if near(r.own, r.copies[slot], half) or near(r.own, results[j].own, half):
                    pairs.add((min(r.agent, j), max(r.agent, j)))
        own = np.zeros(self.num_agents, bool)
        for i, j in pairs:
            own[i] = own[j] = True
        copies = [tuple((min(i, j), max(i, j)) in pairs for j in n) for i, n in enumerate(neighbours)]
        return EngagedBlocks(own=own, copies=copies)

    def _primal_residual(
        self, results: list[LocalResult], neighbours: list[tuple[int, ...]], z: np.ndarray,
        blocks: EngagedBlocks | None = None,
    ) -> float:
        """RMS of v - z over every block, or over ``blocks`` only (0 when none counts)."""
        squared = 0.0
        entries = 0
        for r in results:
            if blocks is None or blocks.own[r.agent]:
                squared += float(np.sum((r.own - z[r.agent]) ** 2))
                entries += r.own.size
            for slot, j in enumerate(neighbours[r.agent]):
                if blocks is None or blocks.copies[r.agent][slot]:
                    squared += float(np.sum((r.copies[slot] - z[j]) ** 2))
                    entries += r.copies[slot].size
        return float(np.sqrt(squared / max(entries, 1)))
