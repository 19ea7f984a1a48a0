"""What the coordinator and the agents exchange, and how the coordinator poses a request.

An agent sees only its :class:`LocalRequest` and answers with a :class:`LocalResult` (its own
positions, its copies of its neighbours' positions, and its plan); multipliers and earlier
solutions stay inside the agent.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from swarmpc.formulation.nlp import NLPSolution
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.admm.config import ADMMConfig

if TYPE_CHECKING:
    from swarmpc.solvers.admm.graph import CouplingGraph

KEPT_PLAN = "kept_verified_current_plan"
"""Status of a repair whose solves failed but whose current plan satisfies every constraint."""


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
    independent: bool = False
    """A probe (``ADMMConfig.independent_first``): the agent's own optimum with no neighbour in it,
    answered without touching its consensus multipliers, its cached answer or its warm start."""
    carry: tuple[bool, ...] = ()
    """At a new step: per block (own, then each neighbour's), whether its multiplier is carried
    over (shifted) instead of restarting from zero; missing entries restart."""
    rescue: bool = False
    """A repair's last attempt: if the hard solves fail and the fallback plan breaks the separation
    from the pinned plans, fly the least-violating plan instead (see ``LocalAgent._rescue``)."""
    plane_normals: np.ndarray | None = None
    """(P, d, K) unit normals of the separating planes the agent's positions keep to (None: none);
    see :func:`~swarmpc.solvers.admm.graph.separating_planes`."""
    plane_offsets: np.ndarray | None = None
    """(P, K) offsets of those planes: normal' p_k >= offset_k at each constrained step k."""
    quick: bool = False
    """A call whose failure the caller has a cheaper answer to (the selection pass's clearing
    re-plan, whose agent keeps its committed plan and whose partner is asked instead): on the QP
    path one certificate loop without restarts, and no retry from the agent's own plan."""
    handover: bool = True
    """Whether a call the QP local step fails may be handed to IPOPT (``ADMMConfig.local`` "qp").
    False under a deadline: an IPOPT call takes tens to hundreds of ms, more than a step's budget,
    so a failed QP call is a failed local step, answered by the agent's rules for one (last plan
    within a step, a verified current plan or the fallback in a repair)."""

    @property
    def num_planes(self) -> int:
        return 0 if self.plane_normals is None else len(self.plane_normals)

    @property
    def pair_deltas(self) -> np.ndarray:
        """(n, d) Delta_ij of the pair with each neighbour (``delta`` broadcast when it is one value)."""
        d = np.asarray(self.z_own).shape[0]
        delta = np.asarray(self.delta, float)
        if delta.shape != (len(self.neighbours), d):
            return np.broadcast_to(delta, (len(self.neighbours), d))
        view = delta.view()  # one per neighbour already: the values as they are, read-only as broadcast
        view.flags.writeable = False
        return view

    @property
    def repair(self) -> bool:
        """Whether this is a repair's request: the neighbours' plans are pinned, no consensus."""
        return self.neighbour_plans is not None

    def with_changes(self, **changes: Any) -> LocalRequest:
        """This request with ``changes`` (field name -> value): what :func:`dataclasses.replace`
        makes, the fields set as they are, without its per-field work (the class checks nothing
        on construction), as the coordinator re-poses M requests every ADMM iteration."""
        unknown = changes.keys() - self.__dict__.keys()
        if unknown:
            raise TypeError(f"LocalRequest has no fields {sorted(unknown)}")
        request = object.__new__(LocalRequest)
        request.__dict__.update(self.__dict__, **changes)
        return request


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


@dataclass(frozen=True)
class TimedResult(LocalResult):
    """A :class:`LocalResult` that also carries the wall time of the local step that produced it."""

    call_time: float = 0.0
    """Seconds the agent spent on the request where it runs: its solver calls (``solve_time``)
    plus its own bookkeeping around them (multipliers, parameters, the reuse test)."""


def compute_time(result: LocalResult) -> float:
    """Seconds of the agent's compute behind ``result``: its whole local step where the agent
    measured it (:attr:`TimedResult.call_time`), else its solver calls (``solve_time``)."""
    return float(getattr(result, "call_time", result.solve_time))


@dataclass(frozen=True)
class FallbackSolution(NLPSolution):
    """IPOPT's answer to a local step whose QP path failed
    (:class:`~swarmpc.solvers.admm.ladders.QPLocalSolverLadder`)."""

    qp_status: str = ""
    """The QP path's status of the failed call."""


@dataclass(frozen=True, eq=False)
class StepRequests:
    """What every request of one MPC step shares, and the requests made from it.

    ``bodies`` (M, d): pair (i, j) keeps Delta_ij = b_i + b_j. ``states`` (M, n), ``goals``
    (M, n) and ``guess`` (M, N+1, n) are the step's measured states, goals and initial guesses
    (states of the settings' agent model).
    """

    settings: OCPSettings
    config: ADMMConfig
    bodies: np.ndarray
    states: np.ndarray
    goals: np.ndarray
    guess: np.ndarray
    applied: tuple[np.ndarray, np.ndarray] | None = None
    """States (M, N+1, n) and inputs (M, N, m) of the plans the last step applied (None: none
    yet): the committed plans of :class:`~swarmpc.solvers.admm.settle.Settle`."""
    _shared: dict[tuple[int, tuple[int, ...]], tuple[np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=dict, init=False, repr=False)
    """Agent and neighbours -> (the neighbours as an index array, the pairs' Delta, the neighbours'
    states): what every request of the agent with those neighbours in this step shares, made
    once (the coordinator asks M requests per ADMM iteration)."""
    _posed: dict[CouplingGraph, tuple[list[LocalRequest], np.ndarray, list[int]]] = field(
        default_factory=dict, init=False, repr=False)
    """Graph -> the first requests of an ADMM iteration on it, every agent's neighbours in one
    index array, and where each agent's part of it ends (:meth:`iteration`)."""

    def _neighbourhood(self, i: int, neighbours: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = (i, neighbours)
        if key not in self._shared:
            index = np.array(neighbours, int)
            delta, states = self.bodies[i] + self.bodies[index], self.states[index]
            delta.flags.writeable = states.flags.writeable = False  # shared by the agent's requests
            self._shared[key] = (index, delta, states)
        return self._shared[key]

    def independent(self, i: int, z: np.ndarray, rho: float) -> LocalRequest:
        """Agent ``i``'s probe for its own optimum (:attr:`LocalRequest.independent`): no neighbours,
        no planes, no consensus penalty (``z`` (M, d, K) only sizes its blocks)."""
        s = self.settings
        return LocalRequest(
            agent=i, state=self.states[i], goal=self.goals[i], delta=np.zeros((0, s.dim)), rho=rho, rho_previous=rho,
            owner_weight=0.0, new_step=True, z_own=z[i], neighbours=(), z_neighbours=np.zeros((0, *z.shape[1:])),
            neighbour_states=np.zeros((0, self.states.shape[1])), guess=self.guess[i], reuse_tol=0.0,
            relaxation=self.config.relaxation, independent=True, handover=self.config.deadline is None,
        )

    def request(
        self, i: int, graph: CouplingGraph, z: np.ndarray, rho: float, rho_previous: float, new_step: bool,
        plans: tuple[np.ndarray, np.ndarray] | None = None, carry: tuple[bool, ...] = (), rescue: bool = False,
        quick: bool = False,
    ) -> LocalRequest:
        """Agent ``i``'s request: its neighbours and planes in ``graph``, the consensus ``z``
        (M, d, K); with ``plans`` (states, inputs of each neighbour) a repair's request, whose
        copies are those plans' positions."""
        s = self.settings
        neighbours = graph.neighbours[i]
        normals, offsets = graph.planes_of(i)
        index, delta, neighbour_states = self._neighbourhood(i, neighbours)
        if plans is None:
            z_neighbours = z.take(index, axis=0)
        else:
            z_neighbours = np.transpose(s.model.position(plans[0][:, s.first_constrained_step:]), (0, 2, 1))
        return LocalRequest(
            agent=i,
            state=self.states[i],
            goal=self.goals[i],
            delta=delta,
            rho=rho,
            rho_previous=rho_previous,
            owner_weight=self.config.owner_weight if neighbours else 0.0,
            new_step=new_step,
            z_own=z[i],
            neighbours=neighbours,
            z_neighbours=z_neighbours.reshape(len(neighbours), s.dim, z.shape[2]),
            neighbour_states=neighbour_states,
            guess=self.guess[i],
            neighbour_plans=plans,
            reuse_tol=self.config.reuse_tol,
            relaxation=self.config.relaxation,
            carry=carry,
            rescue=rescue,
            quick=quick,
            plane_normals=normals,
            plane_offsets=offsets,
            handover=self.config.deadline is None,
        )

    def iteration(
        self, graph: CouplingGraph, z: np.ndarray, rho: float, rho_previous: float, new_step: bool,
        carry: Sequence[tuple[bool, ...]] | None = None,
    ) -> list[LocalRequest]:
        """Every agent's request of one ADMM iteration on ``graph``: :meth:`request` of agents 0 to
        M - 1 (``carry``: each one's, at a new step). The first iteration on a graph poses them in
        full; later ones change only what an iteration changes (the consensus and the penalty),
        every neighbour's z gathered at once."""
        posed = self._posed.get(graph)
        if posed is None:
            requests = [self.request(i, graph, z, rho, rho_previous, new_step, carry=carry[i] if carry else ())
                        for i in range(len(z))]
            index = np.array([j for n in graph.neighbours for j in n], int)
            self._posed[graph] = (requests, index, np.cumsum([len(n) for n in graph.neighbours]).tolist())
            return requests
        first, index, ends = posed
        gathered = z.take(index, axis=0)
        return [request.with_changes(z_own=z[i], z_neighbours=gathered[start:end], rho=rho, rho_previous=rho_previous,
                                     new_step=new_step, carry=carry[i] if carry else ())
                for i, (request, start, end) in enumerate(zip(first, [0, *ends], ends, strict=False))]
