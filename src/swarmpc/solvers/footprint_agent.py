"""One agent's private side of the car ADMM (:mod:`swarmpc.solvers.footprint_admm`): its local
problems, its last answer and its local solves, behind the executor interface
(:mod:`swarmpc.solvers.executors`).

The coordinator talks to an agent only through plain-data messages: a :class:`FootprintStart` at
each MPC step (the neighbours whose copies the agent holds, and whether it keeps its last answer,
shifted, as the warm start), then a :class:`FootprintSolve` per local solve (the NLP's parameter
values, the state guess and, in a repair, the pinned copies). Each is answered by a
:class:`FootprintResult`: whether the solve succeeded, the agent's answer (plan, consensus block,
copies, largest slack) and what the request cost. The built problems (CasADi solvers, QP local
steps) and the answers with their IPOPT multipliers stay inside the agent, which a
:class:`FootprintAgentFactory` builds where the executor runs it (a worker process builds its own).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from swarmpc.formulation.footprint_certificates import PolytopeFootprintCertifier, rectangle_pair_certificates
from swarmpc.formulation.footprint_local import NeighbourKind, build_footprint_local, consensus_block, pair_first_step
from swarmpc.formulation.footprint_ocp import FootprintAgent, FootprintSwarm
from swarmpc.formulation.nlp import CompiledNLP, NLPSolution, shift_blocks
from swarmpc.solvers.dual_seed import pair_seed
from swarmpc.solvers.footprint_qp import FootprintLocalQP
from swarmpc.solvers.guesses import agent_guess_blocks
from swarmpc.solvers.qp_local import QPLocalOptions

__all__ = ["FootprintAgentFactory", "FootprintAnswer", "FootprintLocalAgent", "FootprintRequest", "FootprintResult",
           "FootprintSolve", "FootprintStart", "footprint_local_guess"]


def _car_obstacle_blocks(own: FootprintAgent, states: np.ndarray) -> dict[str, np.ndarray]:
    """Closed-form best certificates of a car's guessed footprint against each obstacle."""
    s, blocks = own.settings, {}
    poses = own.poses(states[s.first_constrained_step:])
    for n, (G, g) in enumerate(s.obstacles):
        certificate = PolytopeFootprintCertifier(G, g)(poses, own.size)
        blocks[f"L_o{n}"], blocks[f"Lo{n}_"] = certificate.lam_ij.T, certificate.lam_ji.T
        if s.collision == "soft":
            blocks[f"A_o{n}"] = np.maximum(0.0, s.d_min - certificate.value)[None, :]
    return blocks


def footprint_local_guess(
    own: FootprintAgent, states: np.ndarray, neighbours: Sequence[FootprintAgent], copies: Sequence[np.ndarray],
) -> dict[str, np.ndarray]:
    """The primal start of a local problem: the agent's state guess (N+1, n), its copies (rows, N)
    and every certificate from the guessed poses (closed-form best certificates; the point form's
    seeds between point agents)."""
    states = np.asarray(states, float)
    point = agent_guess_blocks("", states, own.obstacle_settings, seed_duals=not own.oriented)
    if own.oriented:
        point.update(_car_obstacle_blocks(own, states))
    s = own.settings
    for slot, (other, copy) in enumerate(zip(neighbours, copies, strict=True)):
        first, copy = pair_first_step(own, other), np.asarray(copy, float)
        point[f"C{slot}"] = copy
        own_pose = own.poses(states[first:])
        other_pose = np.zeros_like(own_pose)
        other_pose[:, : copy.shape[0]] = copy[:, first - 1:].T
        if not (own.oriented or other.oriented):
            point.update(pair_seed(f"p{slot}", own_pose[:, :2] - other_pose[:, :2], own.body + other.body, s))
            continue
        certificate = rectangle_pair_certificates(own_pose, own.size, other_pose, other.size)
        point[f"Li{slot}"], point[f"Lj{slot}"] = certificate.lam_ij.T, certificate.lam_ji.T
        if s.collision == "soft":
            point[f"Ap{slot}"] = np.maximum(0.0, s.d_min - certificate.value)[None, :]
    return point


# ------------------------------------------------------------------------------------ messages
@dataclass(frozen=True)
class FootprintStart:
    """A new MPC step for agent ``agent``: its problem now holds copies of ``neighbours`` (in slot
    order); with ``keep`` its last answer, shifted by one step, is the warm start of the step's
    first solve (the coordinator's rule: the agent's neighbours are unchanged and it is not
    restarted)."""

    agent: int
    neighbours: tuple[int, ...]
    keep: bool


@dataclass(frozen=True)
class FootprintSolve:
    """One local solve of agent ``agent`` in the problem with copies of ``neighbours``.

    ``params`` holds the values of every parameter of
    :func:`~swarmpc.formulation.footprint_local.build_footprint_local` (``x0``, ``goal``, ``rho``,
    ``Z``, ``Y`` and per slot ``Z{s}``, ``Y{s}``, ``S{s}``). ``guess`` (N+1, n) is the plan a cold
    start begins from when the agent has no answer (in a repair: the agent's current plan).
    ``fixed`` pins the copies ``C{s}`` (a repair); a repair whose ``neighbours`` are not those of the
    agent's step is solved in a problem of its own, whose answer the agent does not keep.
    """

    agent: int
    neighbours: tuple[int, ...]
    params: dict[str, np.ndarray]
    guess: np.ndarray
    fixed: dict[str, np.ndarray] | None = None


FootprintRequest = FootprintStart | FootprintSolve
"""What the coordinator sends an agent."""


@dataclass(frozen=True)
class FootprintAnswer:
    """An agent's answer to its local problem, in the coordinator's terms."""

    states: np.ndarray
    """(N+1, n) the planned states."""
    inputs: np.ndarray
    """(N, m) the planned inputs."""
    block: np.ndarray
    """(rows, N) the agent's consensus block (its planned footprint poses)."""
    copies: tuple[np.ndarray, ...]
    """Per slot, the agent's copy (rows, N) of that neighbour's block."""
    max_slack: float | None
    """The largest soft-constraint slack of the answer (None: it has none)."""

    @classmethod
    def of(cls, agent: FootprintAgent, solution: NLPSolution, slots: int) -> FootprintAnswer:
        x = solution.x
        slacks = [float(np.max(value)) for name, value in x.items() if name.startswith("A") and value.size]
        return cls(states=x["X"].T, inputs=x["U"].T, block=consensus_block(agent, x["X"].T),
                   copies=tuple(np.asarray(x[f"C{slot}"]) for slot in range(slots)),
                   max_slack=max(slacks) if slacks else None)


@dataclass(frozen=True)
class FootprintResult:
    """Agent ``agent``'s reply to one request."""

    agent: int
    success: bool
    """The solve succeeded (always True for a :class:`FootprintStart`)."""
    answer: FootprintAnswer | None
    """The answer of the problem the request addressed after it (the last one kept when the solve
    failed; None: that problem has none)."""
    own: bool
    """Whether that problem is the agent's step problem (False: a repair's problem of its own)."""
    solve_time: float = 0.0
    """Seconds in the request's solver calls (measured where the agent runs)."""
    failures: int = 0
    """Solver calls of the request that failed."""
    handovers: int = 0
    """QP local steps of the request that failed and were handed to IPOPT (``local: qp``)."""


# --------------------------------------------------------------------------------------- agent
@dataclass
class _Problem:
    """One local problem of an agent (copies of ``neighbours``, in slot order) and its last answer."""

    neighbours: tuple[int, ...]
    nlp: CompiledNLP
    qp: FootprintLocalQP | None
    solution: NLPSolution | None = None


@dataclass
class _Tally:
    """What one request cost: solver seconds, failed calls, QP calls handed to IPOPT."""

    seconds: float = 0.0
    failures: int = 0
    handovers: int = 0


@dataclass(frozen=True)
class FootprintAgentFactory:
    """Picklable recipe for the agents of a :class:`~swarmpc.solvers.footprint_admm.FootprintADMMSolver`:
    ``factory(i)`` is agent i of ``swarm``. ``local``, ``qp`` and ``owner_weight`` are the
    solver's options of those names (:class:`~swarmpc.solvers.footprint_admm.FootprintADMMOptions`)."""

    swarm: FootprintSwarm
    local: str = "ipopt"
    qp: QPLocalOptions = field(default_factory=QPLocalOptions)
    owner_weight: float = 1.0

    def __call__(self, agent: int) -> FootprintLocalAgent:
        return FootprintLocalAgent(agent, self)


class FootprintLocalAgent:
    """Agent ``index``'s local solves (module docstring).

    Its problems are built once per sequence of neighbour kinds and reused (the NLP, and with
    ``local: qp`` the QP local step). A solve starts warm from the agent's last answer of the
    problem and, when that fails (or there is none), cold from its last plan (or the request's
    guess) with every certificate seeded afresh from the geometry.
    """

    def __init__(self, index: int, recipe: FootprintAgentFactory) -> None:
        self.index, self.recipe = index, recipe
        self.agent = recipe.swarm.agents[index]
        self._nlps: dict[tuple[NeighbourKind, ...], CompiledNLP] = {}
        self._qps: dict[tuple[NeighbourKind, ...], FootprintLocalQP] = {}
        self._step: _Problem | None = None
        """The current step's problem (:class:`FootprintStart`)."""

    def solve(self, request: FootprintRequest) -> FootprintResult:
        """The reply to ``request`` (a step's start or a local solve)."""
        if isinstance(request, FootprintStart):
            return self._start(request)
        return self._local_solve(request)

    def _problem(self, neighbours: tuple[int, ...]) -> _Problem:
        """A fresh problem with copies of ``neighbours``, its solvers built on first use."""
        agents, recipe = self.recipe.swarm.agents, self.recipe
        kinds = tuple(NeighbourKind.of(agents[j]) for j in neighbours)
        if kinds not in self._nlps:
            self._nlps[kinds] = build_footprint_local(self.agent, kinds, owner_weight=recipe.owner_weight)
        if recipe.local == "qp" and kinds not in self._qps:
            self._qps[kinds] = FootprintLocalQP(self.agent, kinds, recipe.qp, recipe.owner_weight)
        return _Problem(neighbours, self._nlps[kinds], self._qps.get(kinds))

    def _start(self, request: FootprintStart) -> FootprintResult:
        """The step's problem; the last answer shifted one step on when ``keep``."""
        previous, self._step = self._step, self._problem(request.neighbours)
        if request.keep and previous is not None and previous.solution is not None:
            self._step.solution = _shifted(previous.nlp, previous.solution)
        return self._result(self._step, True, _Tally())

    def _result(self, problem: _Problem, success: bool, tally: _Tally) -> FootprintResult:
        answer = None if problem.solution is None else FootprintAnswer.of(
            self.agent, problem.solution, len(problem.neighbours))
        return FootprintResult(self.index, success, answer, problem is self._step, tally.seconds, tally.failures,
                               tally.handovers)

    def _local_solve(self, request: FootprintSolve) -> FootprintResult:
        """A solve in the step's problem, or in one of its own for a repair with other neighbours."""
        step = self._step
        problem = step if step is not None and step.neighbours == request.neighbours else \
            self._problem(request.neighbours)
        tally = _Tally()
        success = self._solve(problem, request, tally)
        return self._result(problem, success, tally)

    def _solve(self, problem: _Problem, request: FootprintSolve, tally: _Tally) -> bool:
        """The local solve in ``problem``, warm from its last answer; when that fails (or there is
        none), cold from its last plan (or the guess) with certificates seeded afresh. Keeps the
        answer when one succeeds; True on success."""
        params, fixed = request.params, request.fixed
        previous = problem.solution
        copies = [fixed[f"C{slot}"] if fixed else params[f"Z{slot}"] for slot in range(len(problem.neighbours))]
        if problem.qp is not None:
            if self._solve_qp(problem, request, copies, tally):
                return True
            previous = None  # hand the call to IPOPT, cold: a QP answer has no IPOPT multipliers
        for point, lam_x, lam_g in self._starts(problem, request, previous, copies):
            solution = problem.nlp.solve(params, point, lam_x, lam_g, fixed)
            tally.seconds += solution.solve_time
            if solution.success:
                problem.solution = solution
                return True
            tally.failures += 1
        return False

    def _starts(
        self, problem: _Problem, request: FootprintSolve, previous: NLPSolution | None, copies: list[np.ndarray],
    ) -> Iterator[tuple[dict[str, np.ndarray], np.ndarray | None, np.ndarray | None]]:
        """The starts of :meth:`_solve` in turn: warm (the previous answer with its multipliers)
        when there is one, then cold. The cold start (certificates from the geometry, a sizeable
        share of a warm call's time) is made only when asked for, after the warm start failed."""
        if previous is not None and previous.lam_x.size:
            yield previous.x, previous.lam_x, previous.lam_g
        plan = request.guess if previous is None or request.fixed else np.asarray(previous.x["X"]).T
        neighbours = [self.recipe.swarm.agents[j] for j in problem.neighbours]
        yield footprint_local_guess(self.agent, plan, neighbours, copies), None, None

    def _solve_qp(self, problem: _Problem, request: FootprintSolve, copies: list[np.ndarray], tally: _Tally) -> bool:
        """The QP local step, from the problem's last answer (its plan, inputs and copies) unless
        this is a repair (from the guess, the agent's plan, with the copies pinned); keeps the
        answer on success, and counts a failure as a hand-over to IPOPT."""
        assert problem.qp is not None
        previous, fixed = problem.solution, request.fixed
        if previous is not None and not fixed:
            plan, inputs = np.asarray(previous.x["X"]).T, np.asarray(previous.x["U"]).T
            copies = [np.asarray(previous.x[f"C{slot}"]) for slot in range(len(copies))]
        else:
            plan, inputs = np.asarray(request.guess, float), None
        solution = problem.qp.solve(request.params, plan, inputs, copies, pinned=bool(fixed))
        tally.seconds += solution.solve_time
        if solution.success:
            problem.solution = solution
            return True
        tally.failures += 1
        tally.handovers += 1
        return False


def _shifted(problem: CompiledNLP, solution: NLPSolution) -> NLPSolution:
    """A previous answer moved one step on (primal and multipliers), to warm-start the next step."""
    layout_x, layout_g = problem.x_layout, problem.g_layout
    x = shift_blocks(solution.x)
    if not solution.lam_x.size:  # a QP answer: its blocks only
        return NLPSolution(x=x, x_vec=solution.x_vec, lam_x=solution.lam_x, lam_g=solution.lam_g, cost=solution.cost,
                           success=True, status=solution.status, iterations=0, solve_time=0.0)
    return NLPSolution(
        x=x, x_vec=layout_x.pack(x),
        lam_x=layout_x.pack(shift_blocks(layout_x.unpack(solution.lam_x))),
        lam_g=layout_g.pack(shift_blocks(layout_g.unpack(solution.lam_g))),
        cost=solution.cost, success=True, status=solution.status, iterations=0, solve_time=0.0,
    )
