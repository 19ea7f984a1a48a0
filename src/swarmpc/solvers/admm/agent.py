"""One agent's private side of ADMM: its local step, its consensus multipliers and its answer cache.

:class:`LocalAgent` answers a :class:`~swarmpc.solvers.admm.messages.LocalRequest`: it updates its
multipliers (:class:`ConsensusMultipliers`) for the consensus it was sent, sends its last answer
again when the problem posed has not changed enough to matter (:class:`AnswerCache`), and otherwise
solves its local problem. A repair's request pins the neighbours' plans; a failed repair solve is
retried from the agent's own plan, kept if that plan is verifiably safe, and as a last resort
rescued by the least-violating plan of the soft-constrained problem.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any, Literal

import numpy as np

from swarmpc.formulation.nlp import NLPSolution, shift_blocks
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import box_signed_distance
from swarmpc.solvers.admm.config import ADMMConfig
from swarmpc.solvers.admm.ladders import AgentLadder, LocalSolverLadder, QPLocalSolverLadder
from swarmpc.solvers.admm.messages import KEPT_PLAN, FallbackSolution, LocalRequest, LocalResult
from swarmpc.solvers.base import fallback_plan
from swarmpc.solvers.guesses import agent_guess_blocks, inputs_from_states, pair_guess_blocks
from swarmpc.solvers.qp_local import QPBackend, QPLocalLadder, QPLocalOptions

Targets = tuple[float, float, np.ndarray]
"""(rho, owner weight, every block's consensus target z - gamma / rho_b, flattened)."""


def trajectory_through(state: np.ndarray, z: np.ndarray, s: OCPSettings) -> np.ndarray:
    """A state trajectory (N+1, n) of the settings' model from ``state`` whose constrained
    positions are ``z`` (d, K): the guess for a dynamically constrained copy.

    The positions before the first constrained step follow from ``state`` alone (the model coasts
    there: they do not depend on the inputs); the velocities are the measured one, then the
    differences of the positions, the last repeated (the model's state carries them where it has
    a velocity)."""
    model, first = s.model, s.first_constrained_step
    state = np.asarray(state, float)
    positions = np.empty((s.horizon + 1, s.dim))
    positions[0] = model.position(state)
    coasting = state
    for k in range(1, first):
        coasting = model.step(coasting, np.zeros(model.input_dim))
        positions[k] = model.position(coasting)
    positions[first:] = z.T
    velocities = np.empty_like(positions)
    velocities[0] = model.velocity(state)
    velocities[1:-1] = np.diff(positions, axis=0)[1:] / s.dt
    velocities[-1] = velocities[-2]
    return model.state_at(positions, velocities)


def initial_point(
    request: LocalRequest, s: OCPSettings, dynamic_copies: bool, seed: bool,
) -> dict[str, np.ndarray]:
    """Primal start of a local problem from the request's guess (and its copies from z), with the
    OBCA certificates seeded from the geometry when ``seed``."""
    point = agent_guess_blocks("", request.guess, s, seed)
    own = s.model.position(request.guess[s.first_constrained_step:])
    for slot, z in enumerate(request.z_neighbours):
        if dynamic_copies:
            trajectory = trajectory_through(request.neighbour_states[slot], z, s)
            point[f"Xc{slot}"] = trajectory.T
            point[f"Uc{slot}"] = inputs_from_states(trajectory, s).T
        else:
            point[f"C{slot}"] = z
        point.update(pair_guess_blocks(str(slot), own - z.T, request.pair_deltas[slot], s, seed))
    return point


def consensus_targets(request: LocalRequest, params: dict[str, Any]) -> Targets:
    """(rho, owner weight, every block's target z - gamma / rho_b): the local problem depends
    on the consensus only through these, the cost being rho_b / 2 ||v - target||^2 + const."""
    rho, weight = float(request.rho), float(request.owner_weight)
    own = np.asarray(params["Z"]) - np.asarray(params["Y"]) / (rho * weight)
    slots = range(len(request.neighbours))
    if not slots:
        return rho, weight, own.ravel().copy()
    copies = np.array([params[f"Z{slot}"] for slot in slots]) - np.array([params[f"Y{slot}"] for slot in slots]) / rho
    return rho, weight, np.concatenate([own.ravel(), copies.ravel()])  # the copies' blocks stacked, slot by slot


def _shifted(multiplier: np.ndarray) -> np.ndarray:
    """A multiplier (d, K) one step on: moved back in time, the last column repeated."""
    return shift_blocks({"gamma": multiplier})["gamma"]


def matching_slots(wanted: Sequence[int], offered: Sequence[int]) -> tuple[list[int], list[int]]:
    """The slots of ``wanted`` whose agent ``offered`` holds too, and the (first) slot of that agent
    in ``offered``; ``wanted`` holds each agent once."""
    first: dict[int, int] = {}
    for slot, j in enumerate(offered):
        first.setdefault(j, slot)
    slots = [slot for slot, j in enumerate(wanted) if j in first]
    return slots, [first[wanted[slot]] for slot in slots]


def _answered_copies(
    request: LocalRequest, last: LocalResult, last_neighbours: tuple[int, ...],
) -> tuple[Sequence[int], np.ndarray, np.ndarray]:
    """The neighbours of ``request`` that the ``last`` answer (to ``last_neighbours``) holds copies
    of too, those copies (n, d, K) and the z of them ``request`` sends (n, d, K)."""
    if request.neighbours == last_neighbours:  # the usual case: the neighbours of the last answer
        return request.neighbours, last.copies[: len(last_neighbours)], request.z_neighbours
    slots, sent = matching_slots(request.neighbours, last_neighbours)
    return [request.neighbours[slot] for slot in slots], last.copies[sent], request.z_neighbours[slots]


def _relaxed(answer: np.ndarray, alpha: float, previous: np.ndarray | None) -> np.ndarray:
    return answer if alpha == 1.0 or previous is None else alpha * answer + (1.0 - alpha) * previous


class ConsensusMultipliers:
    """An agent's consensus multipliers gamma: one for its own block, one per neighbour's copy.

    Updated at the agent's next call, from the answer it last sent and the consensus z it is sent
    now (gamma += rho_b (v - z), v over-relaxed towards the previous z when alpha is not 1). A new
    MPC step keeps (shifted by one step) only the blocks the coordinator says to carry.
    """

    def __init__(self) -> None:
        self.own: np.ndarray | None = None
        """The own block's multiplier; None while nobody couples with the agent."""
        self.copies: dict[int, np.ndarray] = {}
        """Neighbour j -> the multiplier of the agent's copy of j."""
        self._previous_z: tuple[np.ndarray, tuple[int, ...], np.ndarray] | None = None
        """The own z, the neighbours and their z (n, d, K) of the last request."""

    def clear(self) -> None:
        """Nobody holds a copy of the agent: no consensus block, no multipliers."""
        self.own, self.copies = None, {}

    def update(self, request: LocalRequest, last: LocalResult | None, last_neighbours: tuple[int, ...]) -> None:
        """The multiplier step for the consensus of ``request``, given the agent's ``last`` answer
        (to ``last_neighbours``); at a new step, the carry-over instead."""
        previous_z, self._previous_z = self._previous_z, (request.z_own, request.neighbours, request.z_neighbours)
        if request.new_step or last is None:
            carry = request.carry + (False,) * (1 + len(request.neighbours) - len(request.carry))
            if self.own is not None:
                self.own = _shifted(self.own) if carry[0] else None
            self.copies = {
                j: _shifted(self.copies[j]) for slot, j in enumerate(request.neighbours)
                if carry[1 + slot] and j in self.copies
            }
            return
        rho, alpha = request.rho_previous, request.relaxation
        own_before, neighbours_before, copies_before = previous_z if previous_z is not None else (None, (), None)
        self.own = (self.own if self.own is not None else 0.0) + (
            rho * request.owner_weight * (_relaxed(last.own, alpha, own_before) - request.z_own)
        )
        held, answers, z_now = _answered_copies(request, last, last_neighbours)
        if not held:
            return
        if alpha != 1.0 and copies_before is not None:
            known, before = matching_slots(held, neighbours_before)  # relaxed towards the z last sent, if any
            answers = answers.copy()
            answers[known] = alpha * answers[known] + (1.0 - alpha) * copies_before[before]
        zero = np.zeros_like(request.z_own)
        gamma = np.array([self.copies.get(j, zero) for j in held])  # 0.0 + step where none yet, as a sum with 0.0
        self.copies.update(zip(held, gamma + rho * (answers - z_now), strict=True))

    def parameters(self, request: LocalRequest) -> dict[str, np.ndarray]:
        """The multiplier parameters of the local problem (``Y``, ``Y0``, ...); zero in a repair and a probe."""
        zeros = np.zeros_like(request.z_own)
        repair = request.repair or request.independent
        params = {"Y": self.own if self.own is not None and not repair else zeros}
        for slot, j in enumerate(request.neighbours):
            params[f"Y{slot}"] = zeros if repair else self.copies.get(j, zeros)
        return params


class AnswerCache:
    """The answer an agent sent last and the problem it answered: when the problem posed now is the
    same, or within ``reuse_tol`` of it, the answer is sent again without a solve."""

    def __init__(self) -> None:
        self.sent: LocalResult | None = None
        self.neighbours: tuple[int, ...] = ()
        self.planes: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        self.state: np.ndarray | None = None
        """The state of the last request that was not answered from the cache as a lone problem."""
        self.targets: Targets | None = None
        """The consensus targets the last answer solved (None: not a reusable answer)."""

    def lone_answer(self, request: LocalRequest) -> LocalResult | None:
        """The last answer again when ``request`` is the same lone problem the last one was: nobody
        couples with the agent, in the same MPC step, from the same state. Without consensus blocks
        its problem does not depend on z or rho, so the last (successful) answer is the answer."""
        last = self.sent
        if (
            request.neighbours or request.new_step or request.repair or self.neighbours != ()
            or last is None or not last.success or self.state is None
            or not np.array_equal(request.state, self.state) or not self.same_planes(request)
        ):
            return None
        return replace(last, solve_time=0.0, local_fallbacks=0)

    def same_planes(self, request: LocalRequest) -> bool:
        """True when ``request`` poses the separating planes of the last request."""
        normals, offsets = self.planes
        if request.plane_normals is None or normals is None:
            return request.plane_normals is None and normals is None
        assert request.plane_offsets is not None and offsets is not None  # set with the normals
        return np.array_equal(request.plane_normals, normals) and np.array_equal(request.plane_offsets, offsets)

    def same_shape(self, request: LocalRequest) -> bool:
        """True when ``request`` poses the problem of the last answer: same copies, same planes."""
        return request.neighbours == self.neighbours and self.same_planes(request)

    def reused(self, request: LocalRequest, targets: Targets) -> LocalResult | None:
        """The last answer of this MPC step again (at no solve time) when it solves the problem
        posed now to within ``request.reuse_tol`` of its targets (see ``ADMMConfig.reuse_tol``)."""
        solved, last = self.targets, self.sent
        if not (
            request.reuse_tol > 0 and not request.new_step and not request.repair and self.same_shape(request)
            and solved is not None and last is not None and last.success and not last.fallback
            and solved[:2] == targets[:2] and solved[2].shape == targets[2].shape
            and float(np.max(np.abs(solved[2] - targets[2]))) <= request.reuse_tol
        ):
            return None
        self.sent = replace(last, solve_time=0.0, local_fallbacks=0)
        return self.sent

    def remember(self, request: LocalRequest, result: LocalResult, targets: Targets | None) -> None:
        """``result`` was sent for ``request``; ``targets``: what it solved, when it may be reused."""
        self.sent = result
        self.neighbours = request.neighbours
        self.planes = (request.plane_normals, request.plane_offsets)
        self.targets = targets


class LocalAgent:
    """One agent's private side of ADMM: its solver, multipliers, answer cache and last plan.

    ``nlp`` solves its local steps; ``rescue`` (under hard constraints) the same problems with soft
    pair constraints, for a repair whose fallback plan would break the separation. ``cache``: None
    for a new :class:`AnswerCache`.
    """

    def __init__(
        self, agent: int, settings: OCPSettings, nlp: AgentLadder, dynamic_copies: bool,
        seed_duals: bool = True, rescue: AgentLadder | None = None, cache: AnswerCache | None = None,
    ) -> None:
        self.agent = agent
        self.settings = settings
        self.nlp = nlp
        self.rescue = rescue
        self.dynamic_copies = dynamic_copies
        self.seed_duals = seed_duals
        self.multipliers = ConsensusMultipliers()
        self.cache = cache if cache is not None else AnswerCache()
        self._fallbacks = 0
        """Calls of the current request that IPOPT answered for the QP path."""
        self._handover = True
        """The current request's :attr:`LocalRequest.handover`."""
        self._quick = False
        """The current request's :attr:`LocalRequest.quick`."""
        self._solution: NLPSolution | None = None
        """The last successful solve: the primal (and dual) start of the next one of the same shape."""
        self._plan: tuple[np.ndarray, np.ndarray] | None = None
        self._probe: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        """The state and plan (states, inputs) of the last probe answered, until the next request."""

    def solve(self, request: LocalRequest) -> LocalResult:
        """Multiplier update for the new consensus, then the local NLP (or the cached answer); a
        probe (:attr:`LocalRequest.independent`) by :meth:`_independent`."""
        if request.independent:
            return self._independent(request)
        self._flown_probe(request)
        lone = self.cache.lone_answer(request)
        if lone is not None:
            return lone
        self.cache.state = request.state
        self._fallbacks = 0
        self._handover = request.handover
        self._quick = request.quick
        if not request.neighbours:
            self.multipliers.clear()
        elif not request.repair:
            self.multipliers.update(request, self.cache.sent, self.cache.neighbours)
        params = self._parameters(request)
        targets = consensus_targets(request, params) if request.neighbours else None
        if targets is not None:
            reused = self.cache.reused(request, targets)
            if reused is not None:
                return reused
        same_shape = self.cache.same_shape(request)
        solution = self._local_solve(request, params, same_shape)
        result = self._answer(request, params, solution, same_shape)
        self.cache.remember(request, result, targets if solution.success and not request.repair else None)
        return result

    def _independent(self, request: LocalRequest) -> LocalResult:
        """The agent's own optimum with no neighbour in it, from the step's guess: a probe, solved
        without touching its multipliers, its cached answer or its warm start, so that a step whose
        probe is not taken iterates exactly as it would have without one. A failed probe answers
        the fallback plan (marked so); the coordinator then iterates."""
        s = self.settings
        self._flown_probe(request)  # the last step may have flown the last probe
        self._fallbacks, self._handover, self._quick = 0, request.handover, False
        params = self._parameters(request)
        solution = self._ladder_solve(self.nlp, params, self._start(request, False), None, copies=0, planes=0)
        if solution.success:
            states, inputs = solution.x["X"].T, solution.x["U"].T
        else:
            previous = self._plan if self._plan is not None else (None, None)
            states, inputs = fallback_plan(request.state, previous[0], previous[1], s)
        self._probe = (request.state, states, inputs) if solution.success else None
        return LocalResult(
            agent=self.agent, own=s.model.position(states[s.first_constrained_step:]).T.copy(),
            copies=np.zeros((0, s.dim, s.num_constrained)), states=states, inputs=inputs, success=solution.success,
            fallback=not solution.success, solve_time=solution.solve_time, max_slack=0.0, cost=solution.cost,
            local_fallbacks=self._fallbacks,
        )

    def _flown_probe(self, request: LocalRequest) -> None:
        """After a probe, the plan of the last step flown: the probe's when ``request`` starts from
        another state (the coordinator took the probes as the step's answer), else the agent's own
        (the iterations of the probe's step follow, from its state). An agent at rest, whose state
        does not change, keeps its older plan, from which its fallback brakes in place."""
        if self._probe is None:
            return
        state, states, inputs = self._probe
        self._probe = None
        if not np.array_equal(request.state, state):
            self._plan = (states, inputs)

    def _parameters(self, request: LocalRequest) -> dict[str, Any]:
        """The local problem's parameter values for ``request``."""
        params: dict[str, Any] = {
            "x0": request.state,
            "goal": request.goal,
            "delta": request.pair_deltas.T,
            "rho": request.rho,
            "owner_weight": request.owner_weight,
            "Z": request.z_own,
        }
        for slot in range(len(request.neighbours)):
            if self.dynamic_copies:
                params[f"x0c{slot}"] = request.neighbour_states[slot]
            params[f"Z{slot}"] = request.z_neighbours[slot]
        params.update(self.multipliers.parameters(request))
        if request.num_planes:
            assert request.plane_normals is not None and request.plane_offsets is not None
            for p in range(request.num_planes):
                params[f"Hn{p}"] = request.plane_normals[p]
                params[f"Hb{p}"] = request.plane_offsets[p][None, :]
        return params

    def _ladder_solve(
        self, ladder: AgentLadder, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray,
        fixed: dict[str, Any] | None = None, **sizes: Any,
    ) -> NLPSolution:
        """``ladder.solve`` (IPOPT behind a failed QP call only if the request allows it), counting
        the calls IPOPT answered for a failed QP path."""
        if isinstance(ladder, QPLocalSolverLadder) and not self._handover:
            sizes = {**sizes, "handover": False}
        if isinstance(ladder, QPLocalSolverLadder) and self._quick:
            sizes = {**sizes, "restarts": False}
        solution = ladder.solve(params, guess, fixed, **sizes)
        self._fallbacks += isinstance(solution, FallbackSolution)
        return solution

    def _start(self, request: LocalRequest, same_shape: bool) -> dict[str, np.ndarray] | np.ndarray:
        """The primal start: the same problem's last solution within a step; at a new step of the
        same shape, the guess with the last certificates shifted; otherwise the seeded guess."""
        last = self._solution
        if last is not None and same_shape and not request.new_step:
            return last.x_vec  # the same problem's last solution, already laid out
        warm = last is not None and request.new_step and same_shape
        # the QP path starts from the plan and copies and certifies them itself: the seeded
        # certificates would be read only by IPOPT, after a failed QP call it may take over
        read = not isinstance(self.nlp, QPLocalSolverLadder) or self._handover
        point = initial_point(request, self.settings, self.dynamic_copies, seed=not warm and self.seed_duals and read)
        if warm:
            assert last is not None
            shifted = shift_blocks(last.x)
            point.update({k: v for k, v in shifted.items() if k.startswith(("L", "A"))})
        return point

    def _warm_duals(self, request: LocalRequest, same_shape: bool) -> tuple[np.ndarray, np.ndarray] | None:
        """The last iterate's multipliers, for a later ADMM iteration of the same MPC step on the
        same problem. A new step starts cold: shifted multipliers let a lone agent's plan slide
        out of local minima it used to keep (u-trap), a change of behaviour, not only of speed."""
        if self._solution is None or not same_shape or request.new_step:
            return None
        return self._solution.lam_x, self._solution.lam_g

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

    def _local_solve(self, request: LocalRequest, params: dict[str, Any], same_shape: bool) -> NLPSolution:
        """The local problem solved; in a repair, against the pinned plans (soft: first without
        slack) and retried from the agent's own plan if that fails."""
        sizes = {"copies": len(request.neighbours), "planes": request.num_planes}
        point = self._start(request, same_shape)
        pinned = self._pinned_copies(request)
        if pinned is not None and self.settings.collision == "soft":
            # repair: first try to keep clear of the fixed plans without slack
            strict = {**pinned, **{f"A{slot}": 0.0 for slot in range(len(request.neighbours))}}
            solution = self._ladder_solve(self.nlp, params, point, strict, **sizes)
            if not solution.success:
                solution = self._ladder_solve(self.nlp, params, point, pinned, **sizes)
        else:
            duals = self._warm_duals(request, same_shape) if pinned is None else None
            solution = self._ladder_solve(self.nlp, params, point, pinned, **sizes, duals=duals)
        if pinned is not None and not solution.success and self._plan is not None and not request.quick:
            solution = self._repair_from_own_plan(request, params, pinned, solution)
        return solution

    def _answer(
        self, request: LocalRequest, params: dict[str, Any], solution: NLPSolution, same_shape: bool,
    ) -> LocalResult:
        """The result to transmit for ``solution``: its plan and copies; a failed solve keeps this
        step's last plan and copies (a failed iterate must not pull the consensus anywhere) or, in
        a new step or a repair, flies the fallback plan."""
        s, n, last = self.settings, len(request.neighbours), self.cache.sent
        kept = solution.status == KEPT_PLAN  # no solve succeeded; the current plan is verified
        fallback = kept and last is not None and last.fallback
        slack: list[float] = []
        if solution.success:
            self._solution = solution
            states, inputs = solution.x["X"].T, solution.x["U"].T
            copies = np.array([self._copy_positions(solution, slot) for slot in range(n)])
            copies = copies.reshape(n, s.dim, s.num_constrained)
            slack = [float(solution.x[f"A{slot}"].max()) for slot in range(n) if f"A{slot}" in solution.x]
        elif not request.new_step and not request.repair and self._plan is not None and last is not None and same_shape:
            states, inputs = self._plan
            copies, fallback = last.copies, last.fallback
        else:
            states, inputs, solution = self._fallback(request, params, solution)
            copies, fallback = request.z_neighbours.copy(), True
            self._solution = None
        self._plan = (states, inputs)
        return LocalResult(
            agent=self.agent, own=s.model.position(states[s.first_constrained_step:]).T.copy(), copies=copies,
            states=states, inputs=inputs, success=solution.success and not kept, fallback=fallback,
            solve_time=solution.solve_time, max_slack=float(max(slack)) if slack else 0.0, cost=solution.cost,
            local_fallbacks=self._fallbacks,
        )

    def _copy_positions(self, solution: NLPSolution, slot: int) -> np.ndarray:
        if self.dynamic_copies:
            s = self.settings
            return solution.x[f"Xc{slot}"][s.model.position_rows, s.first_constrained_step :]
        return solution.x[f"C{slot}"]

    def _fallback(
        self, request: LocalRequest, params: dict[str, Any], failed: NLPSolution,
    ) -> tuple[np.ndarray, np.ndarray, NLPSolution]:
        """(states, inputs) of the fallback plan after ``failed``, rescued in a repair's last
        attempt when it breaks the separation (``failed`` then also counts the rescue's time)."""
        previous = self._plan if self._plan is not None else (None, None)
        states, inputs = fallback_plan(request.state, previous[0], previous[1], self.settings)
        pinned = self._pinned_copies(request)
        if pinned is not None and request.rescue:
            rescued, rescue_time = self._rescue(request, params, pinned, states)
            failed = replace(failed, solve_time=failed.solve_time + rescue_time)
            if rescued is not None:
                states, inputs = rescued
        return states, inputs, failed

    def _repair_from_own_plan(
        self, request: LocalRequest, params: dict[str, Any], pinned: dict[str, np.ndarray],
        failed: NLPSolution,
    ) -> NLPSolution:
        """A failed repair solve, retried from the agent's current plan with its certificates
        seeded against the pinned plans (IPOPT's restoration phase can report a nearly feasible
        start as infeasible). If that fails too, the current plan itself is kept when it
        verifiably satisfies every constraint against the pinned plans; otherwise ``failed``."""
        assert self._plan is not None
        sizes = {"copies": len(request.neighbours), "planes": request.num_planes}
        candidate = initial_point(replace(request, guess=self._plan[0]), self.settings, self.dynamic_copies, True)
        retry = self._ladder_solve(self.nlp, params, candidate, pinned, **sizes)
        if retry.success:
            return retry
        kept = self.nlp.verified(params, candidate, pinned, **sizes)
        if kept is None:
            return failed
        return replace(kept, cost=retry.cost, solve_time=failed.solve_time + retry.solve_time)

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
        before = separation_shortfall(fallback, request, s)
        if before == 0.0:
            return None, 0.0
        soft = replace(s, collision="soft")
        point = agent_guess_blocks("", fallback, s)
        assert request.neighbour_plans is not None
        for slot, other in enumerate(request.neighbour_plans[0]):
            offsets = s.model.position(fallback[first:]) - s.model.position(other[first:])
            point.update(pair_guess_blocks(str(slot), offsets, request.pair_deltas[slot], soft))
        solution = self._ladder_solve(self.rescue, params, point, pinned, copies=len(request.neighbours),
                                      planes=request.num_planes)
        if not solution.success:
            return None, solution.solve_time
        states, inputs = solution.x["X"].T, solution.x["U"].T
        if separation_shortfall(states, request, s) >= before:
            return None, solution.solve_time
        return (states, inputs), solution.solve_time


def separation_shortfall(states: np.ndarray, request: LocalRequest, s: OCPSettings) -> float:
    """How far a plan falls short of the separation d_min from the pinned neighbours' plans of a
    repair's ``request``: the shortfall of the signed distance (negative inside the pair's
    Delta_ij box, so depth counts), summed over neighbours and constrained steps; 0 for a plan
    clear of them all."""
    assert request.neighbour_plans is not None
    model, first = s.model, s.first_constrained_step
    others = model.position(request.neighbour_plans[0][:, first:])
    signed = box_signed_distance(model.position(states[first:])[None] - others, request.pair_deltas[:, None, :])
    return float(np.maximum(s.d_min - signed, 0.0).sum())


class LocalAgentFactory:
    """Picklable recipe for agents' local solvers (built where the agents live; agents made by
    one factory object share its :class:`LocalSolverLadder` and, under hard constraints, its
    rescue ladder: the same problems with soft pair constraints, built only when first needed).

    With ``bodies`` (M, d), agent i's problems hold the obstacles grown by its body
    (:meth:`OCPSettings.for_body`); agents whose grown obstacles are the same (every agent without
    obstacles, every agent of one body size) share one pair of ladders. None: the obstacles of
    ``settings`` as they are, for every agent.

    ``local`` "qp": each ladder is a :class:`QPLocalSolverLadder` (the QP path, with these IPOPT
    ladders as its fallback), the rescue ladder too (the QP path's soft pair form); ``qp_backend``
    makes the QP path's solver (None: OSQP, :class:`swarmpc.solvers.qp_local.QPLocalLadder`'s own).
    ``ladder_type`` builds the IPOPT ladders (a subclass can record or alter the local problems).
    """

    def __init__(
        self, settings: OCPSettings, slots: int, dynamic_copies: bool = True, seed_duals: bool = True,
        warm_start: bool = False, bodies: np.ndarray | None = None, local: Literal["qp", "ipopt"] = "ipopt",
        qp_backend: Callable[[QPLocalOptions], QPBackend] | None = None,
        ladder_type: type[LocalSolverLadder] = LocalSolverLadder,
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
        self.qp_backend = qp_backend
        self.ladder_type = ladder_type
        self._ladders: dict[tuple[bytes, ...], tuple[AgentLadder, AgentLadder | None]] = {}
        self.ladder, self.rescue = self._ladders_for(settings)

    @classmethod
    def for_config(
        cls, settings: OCPSettings, bodies: np.ndarray, config: ADMMConfig,
        qp_backend: Callable[[QPLocalOptions], QPBackend] | None = None,
        ladder_type: type[LocalSolverLadder] = LocalSolverLadder,
    ) -> LocalAgentFactory:
        """The agents of an :class:`~swarmpc.solvers.admm.solver.ADMMSolver` with ``config`` for
        agents of ``bodies`` (M, d): as many copy slots as other agents."""
        return cls(settings, max(len(bodies) - 1, 1), config.dynamic_copies, config.seed_duals, config.warm_start,
                   bodies=bodies, local=config.local, qp_backend=qp_backend, ladder_type=ladder_type)

    def _ladders_for(self, settings: OCPSettings) -> tuple[AgentLadder, AgentLadder | None]:
        """The (ladder, rescue ladder) of problems with ``settings``' obstacles, made on first use."""
        key = tuple(np.asarray(g, float).tobytes() for _, g in settings.obstacles)
        if key not in self._ladders:
            ladder = self.ladder_type(settings, self.slots, self.dynamic_copies, warm_start=self.warm_start)
            rescue = (self.ladder_type(settings, self.slots, self.dynamic_copies, pair_collision="soft")
                      if settings.collision == "hard" else None)
            self._ladders[key] = (ladder, rescue) if self.local == "ipopt" else (
                QPLocalSolverLadder(self._qp(settings), ladder),
                None if rescue is None else QPLocalSolverLadder(self._qp(settings, "soft"), rescue),
            )
        return self._ladders[key]

    def _qp(self, settings: OCPSettings, pair_collision: str | None = None) -> QPLocalLadder:
        if self.qp_backend is None:
            return QPLocalLadder(settings, pair_collision=pair_collision)
        return QPLocalLadder(settings, pair_collision=pair_collision, backend=self.qp_backend)

    def __call__(self, agent: int) -> LocalAgent:
        settings = self.settings if self.bodies is None else self.settings.for_body(self.bodies[agent])
        ladder, rescue = self._ladders_for(settings)
        return LocalAgent(agent, settings, ladder, self.dynamic_copies, self.seed_duals, rescue)
