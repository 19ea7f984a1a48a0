"""The local step of car ADMM as a sequence of convex QPs (``solver.local: qp`` in a swarm with cars).

The local problem of :func:`swarmpc.formulation.footprint_local.build_footprint_local` is an NLP
for two reasons: the bicycle's dynamics are nonlinear, and a footprint's corners turn with its
heading. The point agents' QP step (:mod:`swarmpc.solvers.qp_local`) holds the OBCA certificates
fixed, which leaves rows linear in the positions; a turning footprint is not linear in its heading
even then, so this step is a sequential convex programme (SCP) that linearises about the current
plan and repeats:

1. **Dynamics.** x_{k+1} = f(x_k, u_k) (the model's CasADi step, RK4 for the car) is replaced by its
   first-order expansion about (x̄_k, ū_k). The plan kept after every round is the exact rollout of
   the QP's inputs (inputs clipped to their box), so every answer obeys the true dynamics.
2. **Footprint poses.** The pose (x_c, y_c, theta) of the agent's footprint at steps 1..N is a
   variable linked to its state by the expansion of the model's pose map; a copy's pose is a
   variable as in the NLP (``C{s}``).
3. **Separation** (the OBCA condition with the world-frame normal held). For a pair, the best
   certificate of the current poses gives the unit normal n = A_i^T lambda_ij
   (:func:`~swarmpc.formulation.footprint_certificates.best_direction`). With n held, the value
   of the best multipliers along n is min_{P_j} n^T y - max_{P_i} n^T y (the support functions of
   the module :mod:`~swarmpc.formulation.footprint_certificates`), and "it is >= d_min" reads, with
   one free offset sigma per pair and step:

       n^T corner_c(P_i) + d_min <= sigma <= n^T corner_c'(P_j)   for the 4 corners of each,

   linear in the centres, and in the headings through corner_c = centre + R(theta) h_c, with
   R(theta) h_c expanded about the current heading. A static obstacle is the same with its side
   held (its support along n). Point agents' boxes do not turn: their rows are exact. Every
   corner row has a slack priced at :data:`HARD_PENALTY` per metre (kappa in the soft form): an
   exact penalty, so a QP always has an answer, and a plan that keeps d_min pays nothing.
4. **Rounds.** Solve the QP (set up once per problem shape and kind of call, matrix values and
   vectors updated in place; OSQP, warm-started from the last answer, for the ADMM iterations'
   calls, PIQP for the repairs' calls with pinned copies: ``solver.qp.solver`` and
   ``solver.qp.repair_solver``, as for point agents) inside a trust region (headings within
   tau of the current plan's, inputs within the same share of their range), roll its inputs out,
   and keep the new plan only if it lowers the merit (:meth:`FootprintLocalQP.merit`: the NLP's
   objective plus the price of the separation it lacks, by the exact distances); otherwise shrink
   tau by :data:`SHRINK`. Stop when the plan moves less than ``plan_tol`` (at least
   :data:`PLAN_TOL_FLOOR`), after ``max_rounds``, or when tau falls below :data:`MIN_TRUST`. A
   fixed point (the plan optimal for the normals its own certificates give) is a KKT point of the
   OBCA NLP, as for the point agents' loop; the tests compare the answers with IPOPT's.

A round holds each pair on the side of its separating line that the start gives it, so the rounds
keep the start's way round every neighbour. When the starting plan's footprint OVERLAPS a copy or
an obstacle, the best normal is an axis of least penetration, a guess at the way round that the
rounds would then hold (a head-on pair would stop nose to nose); such a call is answered failed
without a QP, and the ADMM hands it to IPOPT, whose certificates choose the way round.

The kept plan is then checked by the exact distances: its footprint against every static obstacle
and, in a repair (copies pinned to neighbours' plans), against every pinned copy; and its
reference point against the workspace. A hard-form plan that fails the check is a failed call,
which the ADMM hands to IPOPT (:class:`~swarmpc.solvers.footprint_admm.FootprintADMMSolver`).

The speed limit is a box on the car's speed state (the car's speed is signed and scalar); a point
agent's speed limit is the inner polytope of :func:`~swarmpc.solvers.qp_local.speed_polytope`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import scipy.sparse as sp

from swarmpc.formulation.footprint_certificates import best_direction
from swarmpc.formulation.footprint_local import NeighbourKind, block_rows, consensus_block
from swarmpc.formulation.footprint_ocp import FootprintAgent
from swarmpc.formulation.nlp import NLPSolution, builds_casadi
from swarmpc.model.footprint import (
    polygon_vertices,
    rectangle_distance,
    rectangle_polytope_distance,
)
from swarmpc.solvers.guesses import inputs_from_states
from swarmpc.solvers.qp_local import (
    IndexCounter,
    QPAnswer,
    QPBackend,
    QPLocalOptions,
    TripletMatrix,
    qp_backend,
    speed_polytope,
)

__all__ = ["MIN_TRUST", "PLAN_TOL_FLOOR", "TRUST_RADIUS", "FootprintLocalQP", "corner_offsets"]

TRUST_RADIUS = 0.5
"""[rad] The largest heading change per round (the first round's trust radius)."""

MIN_TRUST = 1e-3
"""[rad] The rounds stop when the trust radius falls below this."""

PLAN_TOL_FLOOR = 1e-4
"""[m, rad] The rounds stop once the rolled-out plan moves less than max(plan_tol, this)."""

MERIT_DECREASE = 1e-9
"""A round's plan is kept when it lowers the merit by at least this much (relative)."""

SHRINK = 0.25
"""After a round whose plan did not lower the merit, the trust radius is this share of how far
that round moved (:meth:`FootprintLocalQP._step_size`)."""

HARD_PENALTY = 1e3
"""The price per metre of separation a hard-form plan lacks, in the QPs (an exact penalty on the
corner rows' slacks) and in the merit; the soft form's is kappa."""

NORMAL_HYSTERESIS = 1e-4
"""[m] A round keeps the previous round's normal of a pair and step unless the best one certifies
more than this much more distance."""

CHECK_TOLERANCE = 1e-6
"""[m] How far below d_min (or outside the workspace) the exact check lets a plan be: the ADMM's
own safety tolerance."""


def corner_offsets(size: np.ndarray) -> np.ndarray:
    """The corners (4, 2) of a footprint of size (length, width) about its centre, in its frame,
    counter-clockwise from the rear right."""
    half = 0.5 * np.asarray(size, float)
    return np.array([[-half[0], -half[1]], [half[0], -half[1]], [half[0], half[1]], [-half[0], half[1]]])


def _turned(theta: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R(theta) h and its derivative R'(theta) h, (K, 4, 2), for headings (K,) and offsets (4, 2)."""
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    hx, hy = offsets[None, :, 0], offsets[None, :, 1]
    value = np.stack([c * hx - s * hy, s * hx + c * hy], axis=-1)
    slope = np.stack([-s * hx - c * hy, c * hx - s * hy], axis=-1)
    return value, slope


@dataclass
class _Plan:
    """A plan of the rounds: states (N+1, n) rolled out from inputs (N, m), copies (r_s, N) per
    slot, and its merit (:meth:`FootprintLocalQP.merit`)."""

    X: np.ndarray
    U: np.ndarray
    C: list[np.ndarray]
    merit: float = np.inf

    def distance(self, other: _Plan) -> float:
        """The largest change of a state or copy entry between two plans."""
        changes = [float(np.max(np.abs(self.X - other.X)))]
        changes += [float(np.max(np.abs(a - b))) for a, b in zip(self.C, other.C, strict=True)]
        return max(changes)


@dataclass
class _Loop:
    """The rounds' bookkeeping: count, trust radius, OSQP's last status and iterations summed."""

    rounds: int = 0
    tau: float = TRUST_RADIUS
    status: str = "not run"
    iterations: int = 0
    answered: bool = False


@dataclass(frozen=True)
class _Slot:
    """One neighbour slot: the copy's kind, the pair's first constrained step and row count."""

    oriented: bool
    first: int
    steps: int


class _Layout:
    """The QP's variables: states ``X`` (n, N+1), inputs ``U`` (m, N), own poses ``pose`` (r, N) at
    steps 1..N, per slot the copy ``C`` (r_s, N), the offsets sigma (K_s,) and the soft slacks
    (K_s,); per obstacle the soft slacks (K_o,)."""

    def __init__(self, own: FootprintAgent, slots: Sequence[_Slot]) -> None:
        s = own.settings
        N, n, m = s.horizon, s.model.state_dim, s.model.input_dim
        counter = IndexCounter()
        self.X = counter.take(N + 1, n).T
        self.U = counter.take(N, m).T
        self.pose = counter.take(N, block_rows(own)).T
        self.copies = [counter.take(N, 3 if slot.oriented else 2).T for slot in slots]
        self.sigma = [counter.take(slot.steps) for slot in slots]
        self.pair_slack = [counter.take(slot.steps) for slot in slots]
        self.obstacle_steps = N + 1 - s.first_constrained_step
        self.obstacle_slack = [counter.take(self.obstacle_steps) for _ in s.obstacles]
        self.size = counter.size


class _Rows:
    """Constraint rows by name, with their bounds set per call."""

    def __init__(self) -> None:
        self.count = 0
        self.blocks: dict[str, np.ndarray] = {}

    def take(self, name: str, *shape: int) -> np.ndarray:
        count = int(np.prod(shape))
        self.blocks[name] = np.arange(self.count, self.count + count).reshape(shape)
        self.count += count
        return self.blocks[name]


class _Dynamics:
    """The model's step f(x, u) and its Jacobians as CasADi functions, evaluated N at a time; and
    the pose map of the agent's consensus block with its Jacobian."""

    @builds_casadi
    def __init__(self, own: FootprintAgent) -> None:
        s = own.settings
        n, m, N = s.model.state_dim, s.model.input_dim, s.horizon
        x, u = ca.SX.sym("x", n), ca.SX.sym("u", m)
        step = s.model.casadi_dynamics(ca.horzcat(x, x), u)
        self.step = ca.Function("step", [x, u], [step, ca.jacobian(step, x), ca.jacobian(step, u)]).map(N)
        self._rollout = ca.Function("next", [x, u], [step]).mapaccum(N)
        pose = own.casadi_poses(x)[: block_rows(own), 0]
        self.pose = ca.Function("pose", [x], [pose, ca.jacobian(pose, x)]).map(N)
        self.n, self.m, self.r = n, m, block_rows(own)

    def rollout(self, x0: np.ndarray, U: np.ndarray) -> np.ndarray:
        """States (N+1, n) from x0 under inputs U (N, m): the model's own step, N times."""
        return np.vstack([x0, np.asarray(self._rollout(x0, U.T)).T])

    def expand(self, X: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, ...]:
        """(A (N, n, n), B (N, n, m), c (N, n)) with x_{k+1} ~ A x_k + B u_k + c, and (J (N, r, n),
        p (N, r)) with pose(x_k) ~ J x_k + p at k = 1..N, about states X (N+1, n), inputs U (N, m)."""
        N = U.shape[0]
        nxt, A, B = (np.asarray(v) for v in self.step(X[:-1].T, U.T))
        A = A.reshape(self.n, N, self.n).transpose(1, 0, 2)
        B = B.reshape(self.n, N, self.m).transpose(1, 0, 2)
        c = nxt.T - np.einsum("kij,kj->ki", A, X[:-1]) - np.einsum("kij,kj->ki", B, U)
        pose, J = (np.asarray(v) for v in self.pose(X[1:].T))
        J = J.reshape(self.r, N, self.n).transpose(1, 0, 2)
        p = pose.T - np.einsum("kij,kj->ki", J, X[1:])
        return A, B, c, J, p


@dataclass
class _Geometry:
    """What both the rounds' QP and the merit need of the agent: its footprint, kind and slots,
    the owner weight and the price of missing separation."""

    own: FootprintAgent
    slots: list[_Slot]
    owner_weight: float
    oriented: bool

    def poses(self, X: np.ndarray) -> np.ndarray:
        """Footprint poses (K, 3) of states (K, n) (:meth:`FootprintAgent.poses`, without its
        model check)."""
        model: Any = self.own.settings.model
        if self.oriented:
            return np.asarray(model.pose(X))
        position = model.position(np.asarray(X, float))
        return np.concatenate([position, np.zeros((len(position), 1))], axis=1)

    def copy_size(self, params: dict[str, np.ndarray], slot: int) -> np.ndarray:
        """The footprint size of slot ``slot``'s neighbour from its parameter ``S{slot}``
        (:func:`~swarmpc.formulation.footprint_local.slot_size`: the pair's box half-size between
        point agents)."""
        size = np.asarray(params[f"S{slot}"], float).ravel()
        if self.oriented or self.slots[slot].oriented:
            return size
        return 2.0 * (size - self.own.body)

    @property
    def price(self) -> float:
        """The price per metre of separation a plan lacks: the soft form's kappa, or
        :data:`HARD_PENALTY` (an exact penalty: the rounds start from plans that overlap)."""
        s = self.own.settings
        return s.kappa if s.collision == "soft" else HARD_PENALTY


@dataclass
class _Solver:
    """One kind of call's QP solver: the backend, its last multipliers (a warm start) and the
    penalty its P holds."""

    backend: QPBackend
    rho: float
    y: np.ndarray | None = None


class _RoundQP:
    """The QP of one round (module docstring, items 1-3): its sparsity pattern, built once; per
    round the values of an expansion about a plan, and the QP solver of the kind of call (free or
    pinned copies) set up on its first round and updated in place after. It keeps the normals it
    held (:func:`_steady`)."""

    def __init__(self, geo: _Geometry, options: QPLocalOptions) -> None:
        own, s = geo.own, geo.own.settings
        self.geo, self.own, self.slots, self.oriented, self.options = geo, own, geo.slots, geo.oriented, options
        self.layout = _Layout(own, self.slots)
        self.dynamics = _Dynamics(own)
        self.own_corners = corner_offsets(own.size)
        self.obstacle_vertices = [polygon_vertices(G, g) for G, g in s.obstacles]
        self.normals: list[np.ndarray] | None = None
        self.obstacle_normals: list[np.ndarray] = []
        """The last round's normals (per slot, per obstacle): held on where still nearly best."""
        self.speed = None if own.oriented or s.speed is None else speed_polytope(2)
        model: Any = s.model
        self.heading_row: int = model.heading_row if own.oriented else -1
        self.speed_row: int = model.speed_row if own.oriented else -1
        self.rows = _Rows()
        self.A = TripletMatrix(self.layout.size)
        self.P = TripletMatrix(self.layout.size)
        self._build_pattern()
        self._solvers: dict[bool, _Solver] = {}
        """Per kind of call (copies pinned or free), its QP solver (``solver.qp.repair_solver`` or
        ``solver.qp.solver``), set up on its first call."""

    # ---- pattern -------------------------------------------------------------------------------
    def _build_pattern(self) -> None:
        self._cost_pattern()
        self._trajectory_rows()
        self._limit_rows()
        self._pair_rows()
        self._obstacle_rows()
        self.A_matrix, self.A_base = self.A.freeze(self.rows.count)
        self.P_matrix, self.P_base = self.P.freeze(self.layout.size)

    def _dense_upper(self, index: np.ndarray, weight: np.ndarray) -> None:
        """Add x' W x over the variables ``index`` (n,) to P's upper triangle (OSQP's half)."""
        for a in range(len(index)):
            for b in range(a, len(index)):
                value = weight[a, b] + weight[b, a]  # P = W + W' (x' W x = x' P x / 2)
                if a == b or value != 0.0:
                    self.P.add(min(index[a], index[b]), max(index[a], index[b]), value)

    def _cost_pattern(self) -> None:
        """2 Q on x_0..x_{N-1}, 2 Qf on x_N, 2 R on the inputs; rho * owner_weight on the poses and
        rho on the copies (set per call)."""
        s, lay = self.own.settings, self.layout
        for k in range(s.horizon):
            self._dense_upper(lay.X[:, k], s.Q)
            self._dense_upper(lay.U[:, k], s.R)
        self._dense_upper(lay.X[:, s.horizon], s.Qf)
        own, copies = lay.pose.ravel(), np.concatenate([np.zeros(0, int), *[c.ravel() for c in lay.copies]])
        self.own_rho_slots = self.P.add(own, own, 0.0)
        self.rho_slots = self.P.add(copies, copies, 0.0)

    def _trajectory_rows(self) -> None:
        """x_0 = measured; x_{k+1} - A_k x_k - B_k u_k = c_k; pose_k - J_k x_k = p_k."""
        s, lay, rows = self.own.settings, self.layout, self.rows
        n, N, r = s.model.state_dim, s.horizon, block_rows(self.own)
        self.A.add(rows.take("init", n), lay.X[:, 0], 1.0)
        dyn = rows.take("dyn", N, n)
        self.A.add(dyn, lay.X[:, 1:].T, 1.0)
        self.dyn_A = self.A.add(dyn[:, :, None], lay.X[:, :-1].T[:, None, :])
        self.dyn_B = self.A.add(dyn[:, :, None], lay.U.T[:, None, :])
        link = rows.take("link", N, r)
        self.A.add(link, lay.pose.T, 1.0)
        self.link_J = self.A.add(link[:, :, None], lay.X[:, 1:].T[:, None, :])

    def _limit_rows(self) -> None:
        """Input box, workspace box, speed (box on a car's speed, inner polytope for a point agent),
        the heading trust region of the car and its car copies, and a box on every copy entry
        (free, or pinned in a repair)."""
        s, lay, rows = self.own.settings, self.layout, self.rows
        model, N = s.model, s.horizon
        self.A.add(rows.take("input", *lay.U.shape), lay.U, 1.0)
        if s.lower is not None and s.upper is not None:
            positions = lay.X[model.position_rows, s.first_constrained_step:]
            self.A.add(rows.take("workspace", *positions.shape), positions, 1.0)
        if s.speed is not None and self.oriented:
            self.A.add(rows.take("speed", N), lay.X[self.speed_row, 1:], 1.0)
        elif s.speed is not None and self.speed is not None:
            velocity = model.velocity(np.eye(model.state_dim))
            support = np.flatnonzero(np.any(velocity != 0, axis=1))
            normals = self.speed[0] @ velocity[support].T
            speed = rows.take("speed", N, len(normals))
            self.A.add(speed[:, :, None], lay.X[support, 1:].T[:, None, :], normals[None])
        if self.oriented:
            self.A.add(rows.take("trust", N), lay.X[self.heading_row, 1:], 1.0)
        for slot, copy in enumerate(lay.copies):
            self.A.add(rows.take(f"copy{slot}", *copy.shape), copy, 1.0)

    def _corner_entries(
        self, name: str, steps: int, pose: np.ndarray, oriented: bool,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Rows ``name`` (K, 4) with entries on a pose block's columns (r, K): the normal on x, y
        and, when ``oriented``, the corner's heading slope; returns (rows, xy slots, theta slots)."""
        block = self.rows.take(name, steps, 4)
        xy = self.A.add(block[:, :, None], pose[:2].T[:, None, :])
        theta = self.A.add(block, pose[2][:, None]) if oriented else None
        return block, xy, theta

    def _pair_rows(self) -> None:
        """Per slot and step: sigma - n' corner(own) [+ alpha] >= d_min + ..., n' corner(copy) -
        sigma >= ... (module docstring, item 3)."""
        lay = self.layout
        self.pair_slots = []
        for slot, info in enumerate(self.slots):
            columns = slice(info.first - 1, None)
            own = self._corner_entries(f"own{slot}", info.steps, lay.pose[:, columns], self.oriented)
            copy = self._corner_entries(f"copy_corner{slot}", info.steps, lay.copies[slot][:, columns], info.oriented)
            self.A.add(own[0], lay.sigma[slot][:, None], 1.0)
            self.A.add(copy[0], lay.sigma[slot][:, None], -1.0)
            slack = lay.pair_slack[slot]
            self.A.add(own[0], slack[:, None], 1.0)
            self.A.add(self.rows.take(f"pair_slack{slot}", info.steps), slack, 1.0)
            self.pair_slots.append((own, copy))

    def _obstacle_rows(self) -> None:
        """Per obstacle and step: -n' corner(own) [+ alpha] >= d_min - min_O n' y (item 3)."""
        lay, first = self.layout, self.own.settings.first_constrained_step
        self.obstacle_slots = []
        for o, slack in enumerate(lay.obstacle_slack):
            poses = lay.pose[:, first - 1:]
            entries = self._corner_entries(f"obstacle{o}", lay.obstacle_steps, poses, self.oriented)
            self.A.add(entries[0], slack[:, None], 1.0)
            self.A.add(self.rows.take(f"obstacle_slack{o}", lay.obstacle_steps), slack, 1.0)
            self.obstacle_slots.append(entries)

    def solve(self, params: dict[str, np.ndarray], plan: _Plan, tau: float, pinned: bool) -> QPAnswer:
        """One QP about ``plan`` with trust radius ``tau``."""
        lay, X, U, C = self.layout, plan.X, plan.U, plan.C
        values = self.A_base.copy()
        lower = np.full(self.rows.count, -np.inf)
        upper = np.full(self.rows.count, np.inf)
        self._trajectory_values(values, lower, upper, X, U, params)
        self._limit_values(lower, upper, X, U, C, tau, pinned)
        self._pair_values(values, lower, X, C, params)
        self._obstacle_values(values, lower, X)
        q = self._linear_cost(params)
        rho = float(np.asarray(params["rho"]).ravel()[0])
        P_values = self.P_base.copy()
        P_values[self.rho_slots] = rho
        P_values[self.own_rho_slots] = rho * self.geo.owner_weight
        A_data, P_data = self.A.data(values), self.P.data(P_values)
        solver = self._solvers.get(pinned)
        if solver is None:
            solver = self._solvers[pinned] = _Solver(qp_backend(self.options, pinned), rho)
            solver.backend.setup(_csc(self.P_matrix, P_data), q, _csc(self.A_matrix, A_data), lower, upper)
        else:
            solver.backend.update(q, lower, upper, P_data if rho != solver.rho else None, A_data)
        solver.rho = rho
        start = np.zeros(lay.size)
        start[lay.X] = X.T
        start[lay.U] = U.T
        start[lay.pose] = consensus_block(self.own, X)
        for index, copy in zip(lay.copies, C, strict=True):
            start[index] = copy
        answer = solver.backend.solve(start, solver.y)
        if answer.solved or answer.status.startswith("maximum iterations"):
            solver.y = answer.y
        return answer

    def _trajectory_values(
        self, values: np.ndarray, lower: np.ndarray, upper: np.ndarray, X: np.ndarray, U: np.ndarray,
        params: dict[str, np.ndarray],
    ) -> None:
        A, B, c, J, p = self.dynamics.expand(X, U)
        values[self.dyn_A], values[self.dyn_B], values[self.link_J] = -A, -B, -J
        rows = self.rows.blocks
        lower[rows["init"]] = upper[rows["init"]] = np.asarray(params["x0"], float).ravel()
        lower[rows["dyn"]] = upper[rows["dyn"]] = c
        lower[rows["link"]] = upper[rows["link"]] = p

    def _limit_values(
        self, lower: np.ndarray, upper: np.ndarray, X: np.ndarray, U: np.ndarray, C: Sequence[np.ndarray],
        tau: float, pinned: bool,
    ) -> None:
        s, rows, margin = self.own.settings, self.rows.blocks, self.options.margin
        low, high = s.model.input_bounds(s.accel, s.speed)
        reach = 0.5 * (high - low)[:, None] * (tau / TRUST_RADIUS)
        lower[rows["input"]] = np.maximum(low[:, None], U.T - reach)
        upper[rows["input"]] = np.minimum(high[:, None], U.T + reach)
        if s.lower is not None and s.upper is not None:
            lower[rows["workspace"]] = (s.lower + margin)[:, None]
            upper[rows["workspace"]] = (s.upper - margin)[:, None]
        if s.speed is not None and self.oriented:
            lower[rows["speed"]], upper[rows["speed"]] = -s.speed, s.speed
        elif s.speed is not None and self.speed is not None:
            upper[rows["speed"]] = self.speed[1] * s.speed - margin
        if "trust" in rows:
            heading = X[1:, self.heading_row]
            lower[rows["trust"]], upper[rows["trust"]] = heading - tau, heading + tau
        for slot, copy in enumerate(C):
            block = rows[f"copy{slot}"]
            if pinned:
                lower[block] = upper[block] = copy
            elif self.slots[slot].oriented:
                lower[block[2]], upper[block[2]] = copy[2] - tau, copy[2] + tau

    @staticmethod
    def _corner_terms(
        pose: np.ndarray, offsets: np.ndarray, normal: np.ndarray, oriented: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """For poses (K, 3), corner offsets (4, 2) and normals (K, 2): the heading slope n' R'h
        (K, 4) and the constant n' (R h - R'h theta-bar) (K, 4) of the expansion of n' corner
        (for a box that does not turn: no slope, the constant n' h)."""
        if not oriented:
            return np.zeros((len(pose), 4)), np.einsum("kd,cd->kc", normal, offsets)
        turned, slope = _turned(pose[:, 2], offsets)
        n_slope = np.einsum("kd,kcd->kc", normal, slope)
        return n_slope, np.einsum("kd,kcd->kc", normal, turned) - n_slope * pose[:, 2:3]

    def _pair_values(
        self, values: np.ndarray, lower: np.ndarray, X: np.ndarray, C: Sequence[np.ndarray],
        params: dict[str, np.ndarray],
    ) -> None:
        d_min, margin = self.own.settings.d_min, self.options.margin
        poses = self.geo.poses(X[1:])
        previous, self.normals = self.normals, []
        for slot, (info, (own, copy)) in enumerate(zip(self.slots, self.pair_slots, strict=True)):
            size = self.geo.copy_size(params, slot)
            own_pose = poses[info.first - 1:]
            copy_pose = _as_pose(C[slot][:, info.first - 1:])
            own_vertices, copy_vertices = _vertices(own_pose, self.own.size), _vertices(copy_pose, size)
            normal = best_direction(own_vertices, copy_vertices)
            if previous is not None:
                normal = _steady(previous[slot], normal, own_vertices, copy_vertices)
            self.normals.append(normal)
            slope, constant = self._corner_terms(own_pose, self.own_corners, normal, self.oriented)
            _set(values, own, -normal, -slope)
            lower[own[0]] = d_min + constant + margin
            slope, constant = self._corner_terms(copy_pose, corner_offsets(size), normal, info.oriented)
            _set(values, copy, normal, slope)
            lower[copy[0]] = -constant
            lower[self.rows.blocks[f"pair_slack{slot}"]] = 0.0

    def _obstacle_values(self, values: np.ndarray, lower: np.ndarray, X: np.ndarray) -> None:
        s, margin = self.own.settings, self.options.margin
        pose = self.geo.poses(X[s.first_constrained_step:])
        previous, self.obstacle_normals = self.obstacle_normals, []
        for o, (vertices, entries) in enumerate(zip(self.obstacle_vertices, self.obstacle_slots, strict=True)):
            own_vertices = _vertices(pose, self.own.size)
            normal = best_direction(own_vertices, vertices)
            if o < len(previous):
                normal = _steady(previous[o], normal, own_vertices, vertices)
            self.obstacle_normals.append(normal)
            support = np.min(normal @ vertices.T, axis=1)
            slope, constant = self._corner_terms(pose, self.own_corners, normal, self.oriented)
            _set(values, entries, -normal, -slope)
            lower[entries[0]] = s.d_min - support[:, None] + constant + margin
            lower[self.rows.blocks[f"obstacle_slack{o}"]] = 0.0

    def _linear_cost(self, params: dict[str, np.ndarray]) -> np.ndarray:
        """q: -2 Q goal on x_0..x_{N-1}, -2 Qf goal on x_N, Y - rho Z on the poses and copies,
        kappa on the soft slacks."""
        s, lay = self.own.settings, self.layout
        goal = np.asarray(params["goal"], float).ravel()
        rho = float(np.asarray(params["rho"]).ravel()[0])
        q = np.zeros(lay.size)
        q[lay.X[:, :-1]] = (-2.0 * s.Q @ goal)[:, None]
        q[lay.X[:, -1]] = -2.0 * s.Qf @ goal
        q[lay.pose] = np.asarray(params["Y"], float) - rho * self.geo.owner_weight * np.asarray(params["Z"], float)
        for slot, index in enumerate(lay.copies):
            q[index] = np.asarray(params[f"Y{slot}"], float) - rho * np.asarray(params[f"Z{slot}"], float)
        for slack in [*lay.pair_slack, *lay.obstacle_slack]:
            q[slack] = self.geo.price
        return q


class FootprintLocalQP:
    """One agent's local step against copies of neighbours of given kinds, as a sequence of QPs
    (module docstring): the rounds, and the merit and exact checks that judge their plans;
    ``owner_weight`` as in :func:`~swarmpc.formulation.footprint_local.build_footprint_local`.
    Built once per agent and sequence of neighbour kinds."""

    def __init__(
        self, own: FootprintAgent, kinds: Sequence[NeighbourKind], options: QPLocalOptions, owner_weight: float = 1.0,
    ) -> None:
        s = own.settings
        slots = [_Slot(k.oriented, min(s.first_constrained_step, k.first_step),
                       s.horizon + 1 - min(s.first_constrained_step, k.first_step)) for k in kinds]
        if any(slot.first < 1 for slot in slots) or s.first_constrained_step < 1:
            raise ValueError("the footprint QP constrains poses from step 1 on")
        self.geo = _Geometry(own, slots, owner_weight, own.oriented)  # read once: the protocol check is slow
        self.own, self.slots, self.oriented, self.options = own, slots, self.geo.oriented, options
        self.round = _RoundQP(self.geo, options)

    # ---- one call ------------------------------------------------------------------------------
    def solve(
        self, params: dict[str, np.ndarray], plan: np.ndarray, inputs: np.ndarray | None,
        copies: Sequence[np.ndarray], pinned: bool = False,
    ) -> NLPSolution:
        """The local step from the plan ``plan`` (N+1, n) (and its ``inputs`` (N, m), else guessed
        from the plan) with copies ``copies`` (r_s, N) per slot, for the parameters of
        :func:`~swarmpc.formulation.footprint_local.build_footprint_local`. ``pinned``: the copies
        are held at ``copies`` (a repair) and the answer is checked against them. Returns the
        NLP's blocks (``X``, ``U``, ``C{s}``, soft slacks); ``success`` False when no QP had an
        answer or a hard-form plan failed the exact check."""
        started = time.perf_counter()
        s = self.own.settings
        lower, upper = s.model.input_bounds(s.accel, s.speed)
        U = np.clip(inputs_from_states(plan, s) if inputs is None else np.asarray(inputs, float), lower, upper)
        current = self._plan(params, U, [np.asarray(c, float).copy() for c in copies])
        loop, tol = _Loop(), max(self.options.plan_tol, PLAN_TOL_FLOOR)
        given = _Plan(np.asarray(plan, float), U, current.C)
        if self._overlaps(given, params) or self._overlaps(current, params):  # not the rounds' choice
            loop.status, loop.rounds = "start overlaps", self.options.max_rounds
        while loop.rounds < self.options.max_rounds and loop.tau >= MIN_TRUST:
            loop.rounds += 1
            answer = self.round.solve(params, current, loop.tau, pinned)
            loop.status, loop.iterations = answer.status, loop.iterations + answer.iterations
            if not (answer.solved or answer.status.startswith("maximum iterations")):
                break
            loop.answered = True
            candidate = self._plan(params, answer.x[self.round.layout.U].T,
                                   current.C if pinned else [answer.x[c] for c in self.round.layout.copies])
            moved = current.distance(candidate)
            if candidate.merit > current.merit - MERIT_DECREASE * (1.0 + abs(current.merit)):
                if moved < tol:  # settled: the QP's answer is the plan it started from
                    break
                loop.tau = SHRINK * self._step_size(current, candidate)  # misled: the next round stays closer
                continue
            if self._step_size(current, candidate) > 0.5 * loop.tau:  # the trust region bound: widen it
                loop.tau = min(TRUST_RADIUS, 2.0 * loop.tau)
            current = candidate
            if moved < tol:
                break
        blocks = self._blocks(current, params)
        success = loop.answered and (s.collision == "soft" or self._clear(current, params, pinned))
        return NLPSolution(
            x=blocks, x_vec=np.zeros(0), lam_x=np.zeros(0), lam_g=np.zeros(0),
            cost=self.objective(current, blocks, params), success=success, status=f"qp: {loop.status}",
            iterations=loop.iterations, solve_time=time.perf_counter() - started,
        )

    def _plan(self, params: dict[str, np.ndarray], U: np.ndarray, C: list[np.ndarray]) -> _Plan:
        """The plan of inputs U (clipped to their box) rolled out from x0, with copies C, and its merit."""
        s = self.own.settings
        lower, upper = s.model.input_bounds(s.accel, s.speed)
        U = np.clip(np.asarray(U, float), lower, upper)
        plan = _Plan(self.round.dynamics.rollout(np.asarray(params["x0"], float).ravel(), U), U, C)
        plan.merit = self.merit(plan, params)
        return plan

    def _step_size(self, old: _Plan, new: _Plan) -> float:
        """How far a round moved, in units of the trust radius: the largest heading change (the
        agent's and its car copies') or input change (as the share of TRUST_RADIUS its range's half
        is), whichever is larger."""
        s = self.own.settings
        low, high = s.model.input_bounds(s.accel, s.speed)
        inputs = float(np.max(np.abs(new.U - old.U) / (0.5 * (high - low)))) * TRUST_RADIUS
        return max(inputs, self._turn(old, new))

    def _turn(self, old: _Plan, new: _Plan) -> float:
        """The largest heading change between two plans: the agent's (a car) and its car copies'."""
        turns = [0.0]
        if self.oriented:
            row = self.round.heading_row
            turns.append(float(np.max(np.abs(new.X[:, row] - old.X[:, row]))))
        turns += [float(np.max(np.abs(b[2] - a[2])))
                  for slot, a, b in zip(self.slots, old.C, new.C, strict=True) if slot.oriented]
        return max(turns)

    # ---- the answer ----------------------------------------------------------------------------
    def _gaps(
        self, X: np.ndarray, C: Sequence[np.ndarray], params: dict[str, np.ndarray], pairs: bool = True,
        below: float = np.inf,
    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Exact signed distances of a plan's footprint: per slot (K_s,) to the copy's (none unless
        ``pairs``), per obstacle (K_o,) to the obstacle. A pair's step that the last round's normal
        already shows to be ``below`` apart or more is left at that lower bound (:meth:`_bound`)."""
        s = self.own.settings
        poses = self.geo.poses(X)
        gaps = []
        for slot, info in enumerate(self.slots if pairs else []):
            own, size = poses[info.first:], self.geo.copy_size(params, slot)
            other = _as_pose(C[slot][:, info.first - 1:])
            gap, near = self._bound(slot, own, other, size), np.ones(len(own), bool)
            if gap is not None:
                near = gap < below
            else:
                gap = np.full(len(own), np.inf)
            if near.any():
                gap[near] = rectangle_distance(own[near], self.own.size, other[near], size, signed=True)
            gaps.append(gap)
        first = s.first_constrained_step
        obstacles = [rectangle_polytope_distance(poses[first:], self.own.size, G, g, signed=True)
                     for G, g in s.obstacles]
        return gaps, obstacles

    def _overlaps(self, plan: _Plan, params: dict[str, np.ndarray]) -> bool:
        """True when the plan's footprint overlaps a copy's or an obstacle at some step (signed
        distance < 0). The best normal of an overlapping pair is its axis of least penetration, a
        guess at which way round the other the agent should go; a round would hold that guess as a
        constraint, and the rounds keep whatever side they start on. Such a call is the NLP's."""
        pairs, obstacles = self._gaps(plan.X, plan.C, params, below=0.0)
        return any(gap.size and float(np.min(gap)) < 0.0 for gap in [*pairs, *obstacles])

    def _outside(self, X: np.ndarray) -> float:
        """How far [m] the plan's reference point leaves the workspace, summed over the steps."""
        s = self.own.settings
        if s.lower is None or s.upper is None:
            return 0.0
        positions = s.model.position(X[s.first_constrained_step:])
        return float(np.sum(np.maximum(0.0, s.lower - positions) + np.maximum(0.0, positions - s.upper)))

    def merit(self, plan: _Plan, params: dict[str, np.ndarray]) -> float:
        """The local NLP's objective plus a price on what the plan lacks of d_min from its copies
        and obstacles and of the workspace (kappa in the soft form, :data:`HARD_PENALTY` in the
        hard form): the rounds keep a plan only when it lowers this."""
        pairs, obstacles = self._gaps(plan.X, plan.C, params, below=self.own.settings.d_min)
        d_min = self.own.settings.d_min
        short = sum(float(np.sum(np.maximum(0.0, d_min - gap))) for gap in [*pairs, *obstacles])
        return self.objective(plan, {}, params) + self.geo.price * (short + self._outside(plan.X))

    def _bound(self, slot: int, own: np.ndarray, other: np.ndarray, size: np.ndarray) -> np.ndarray | None:
        """A lower bound (K_s,) on the distance of a slot's footprints at each step: their gap
        along the last round's normals (weak duality); None before the first round."""
        if self.round.normals is None:
            return None
        return _gap_along(self.round.normals[slot], _vertices(own, self.own.size), _vertices(other, size))

    def _blocks(self, plan: _Plan, params: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The NLP's named blocks of an answer; in the soft form the slacks max(0, d_min - gap)
        of the exact gaps."""
        blocks = {"X": plan.X.T, "U": plan.U.T}
        for slot, copy in enumerate(plan.C):
            blocks[f"C{slot}"] = np.asarray(copy, float)
        s = self.own.settings
        if s.collision == "soft":
            pairs, obstacles = self._gaps(plan.X, plan.C, params)
            for slot, gap in enumerate(pairs):
                blocks[f"Ap{slot}"] = np.maximum(0.0, s.d_min - gap)[None, :]
            for o, gap in enumerate(obstacles):
                blocks[f"A_o{o}"] = np.maximum(0.0, s.d_min - gap)[None, :]
        return blocks

    def objective(self, plan: _Plan, blocks: dict[str, np.ndarray], params: dict[str, np.ndarray]) -> float:
        """The local NLP's objective at a plan: the quadratic cost, the consensus terms over the
        plan's poses and the copies, and kappa times the soft slacks in ``blocks``."""
        s = self.own.settings
        goal = np.asarray(params["goal"], float).ravel()
        rho = float(np.asarray(params["rho"]).ravel()[0])
        err = plan.X - goal
        cost = float(np.einsum("ki,ij,kj->", err[:-1], s.Q, err[:-1]) + np.einsum("ki,ij,kj->", plan.U, s.R, plan.U)
                     + err[-1] @ s.Qf @ err[-1])
        terms = [(consensus_block(self.own, plan.X), "", rho * self.geo.owner_weight)]
        terms += [(c, str(slot), rho) for slot, c in enumerate(plan.C)]
        for value, tag, penalty in terms:
            z, y = np.asarray(params[f"Z{tag}"], float), np.asarray(params[f"Y{tag}"], float)
            cost += 0.5 * penalty * float(np.sum((value - z + y / penalty) ** 2))
        return cost + s.kappa * sum(float(np.sum(v)) for k, v in blocks.items() if k.startswith("A"))

    def _clear(self, plan: _Plan, params: dict[str, np.ndarray], pinned: bool) -> bool:
        """The exact check of a hard-form plan: footprint against every obstacle, reference point
        within the workspace, and in a repair footprint against every pinned copy."""
        d_min = self.own.settings.d_min
        pairs, obstacles = self._gaps(plan.X, plan.C, params, pairs=pinned, below=d_min)
        gaps = [*obstacles, *pairs]
        if any(float(np.min(gap)) < d_min - CHECK_TOLERANCE for gap in gaps if gap.size):
            return False
        return self._outside(plan.X) <= CHECK_TOLERANCE


def _vertices(pose: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Counter-clockwise corners (K, 4, 2) of footprints of poses (K, 3) and one size (2,)
    (:func:`~swarmpc.model.footprint.footprint_vertices` for one size, without its generality)."""
    pose = np.asarray(pose, float)
    return pose[:, None, :2] + _turned(pose[:, 2], corner_offsets(size))[0]


def _set(values: np.ndarray, entries: tuple[np.ndarray, np.ndarray, np.ndarray | None], normal: np.ndarray,
         slope: np.ndarray) -> None:
    """Corner rows' coefficients: ``normal`` (K, 2) on the centre, ``slope`` (K, 4) on the heading."""
    values[entries[1]] = normal[:, None, :]
    if entries[2] is not None:
        values[entries[2]] = slope


def _gap_along(normal: np.ndarray, V_i: np.ndarray, V_j: np.ndarray) -> np.ndarray:
    """min_{P_j} n' y - max_{P_i} n' y (K,) of polygons V_i, V_j (K, c, 2) along normals (K, 2) (or
    one polygon V_j (c, 2)): the certificate's value along n, a lower bound on the distance."""
    V_j = np.broadcast_to(V_j, (len(normal), *V_j.shape[-2:]))
    low = np.min(np.einsum("kcd,kd->kc", V_j, normal), axis=1)
    return low - np.max(np.einsum("kcd,kd->kc", V_i, normal), axis=1)


def _steady(previous: np.ndarray, best: np.ndarray, V_i: np.ndarray, V_j: np.ndarray) -> np.ndarray:
    """The normals (K, 2) a round holds: the previous round's where its value is within
    :data:`NORMAL_HYSTERESIS` of the best one's, else the best. Two candidate directions of (nearly)
    equal value, as the edge normals of two footprints side by side, would otherwise take turns
    from round to round, and each turn moves the answer."""
    keep = _gap_along(previous, V_i, V_j) >= _gap_along(best, V_i, V_j) - NORMAL_HYSTERESIS
    return np.where(keep[:, None], previous, best)


def _as_pose(block: np.ndarray) -> np.ndarray:
    """Poses (K, 3) of a consensus block (r, K): a point agent's (2 rows) at heading 0."""
    block = np.asarray(block, float)
    if block.shape[0] == 3:
        return block.T
    return np.concatenate([block.T, np.zeros((block.shape[1], 1))], axis=1)


def _csc(pattern: sp.csc_matrix, data: np.ndarray) -> sp.csc_matrix:
    return sp.csc_matrix((data, pattern.indices, pattern.indptr), shape=pattern.shape)
