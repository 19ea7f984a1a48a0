"""One agent's local ADMM step as a short sequence of QPs with the OBCA certificates held fixed.

The local problem of :func:`swarmpc.formulation.ocp.build_local` (free copies, the default) is an
NLP only because its collision rows are bilinear in (position, certificate lambda). With lambda
fixed, a row (G q - g)^T lambda >= d_min is LINEAR in the own positions and the copies, and with a
dual-feasible lambda (lambda >= 0, ||G^T lambda||_2 <= 1) weak duality makes any plan meeting it
keep the Euclidean distance >= d_min (:mod:`swarmpc.formulation.certificates`): each QP's answer
is safe as it stands. The rest of the problem (quadratic cost, consensus terms, dynamics, input,
workspace and plane limits) is already a QP; the speed limit ||v_k||_2 <= v_max is replaced by an
INNER polytope (F unit normals a_f, a_f' v <= r v_max with r = 1 / max vertex norm of
{a_f' v <= 1}), so the true limit always holds (r = 0.981 for 16 facets in 2D, 0.886 for the 26
cube directions in 3D: the QP is that much more conservative where the limit is active).

Certificate loop (:class:`SequentialLocalQP`), a convex-restriction SCP:

1. lambda_0 = the best certificates of the guess (own plan against the copies / obstacles);
2. solve the QP with lambda_r fixed (warm-started from the previous round);
3. lambda_{r+1} = the best certificates of the new plan. Their values equal the exact distances,
   which the plan keeps >= d_min, so the plan stays feasible for the next QP: the cost never
   rises, and a fixed point (lambda = best certificate of the plan, plan optimal for lambda) is a
   KKT point of the OBCA NLP (the best certificate maximises the row over lambda, which is the
   NLP's stationarity in lambda);
4. stop after ``max_rounds`` or when the plan moved less than ``plan_tol`` or the certificates of
   the rows within ``active_band`` of their bound changed less than ``certificate_tol`` (inactive
   rows cannot change the answer while they stay inactive, and they do: their exact value only
   grows).

If the first QP is infeasible (the guess's certificates demand a separation the dynamics cannot
reach), the loop restarts from the certificates of the coasting and then the braking plan. A
repair call (copies pinned, hard pairs) that still fails is checked by :class:`SeparationProof`:
when every position the agent can reach at some step within its input box lies closer than
d_min to a held neighbour, no plan exists, and the call is reported :data:`PROVEN_INFEASIBLE`
(under acceleration limits most failed repair calls are of this kind).

The QP solver of the ADMM iterations' calls is OSQP through its own API: a sparse solver whose
matrix values can be updated in place, which the certificate rounds need, and whose warm start
from the last answer turns a slowly moving QP into a few iterations (an active-set solver such
as DAQP only pays off while nothing but vectors change and it keeps its own working set, which a
solver shared by agents cannot; benchmarks/qp_solvers.py compares the candidates). The repair
passes' calls (copies pinned: many rows at their bounds, some calls infeasible) go to PIQP, an
interior-point solver that takes about ten iterations whatever its start, where OSQP takes
hundreds and thousands to declare a QP infeasible (``solver.qp.solver`` and
``solver.qp.repair_solver`` choose; :func:`qp_backend`). Each is set up once per problem shape
(copies, planes, pinned copies, pair form); a call changes only vectors and, where certificates
or planes changed, matrix VALUES in a fixed sparsity pattern (explicit zeros kept), updated in
place. An answer violates rows by up to the solver's tolerance: OSQP's polishing makes it exact
on its active set in practice, every separation, workspace, plane and speed row is tightened by
``margin`` in case it does not, and the applied plan is rebuilt exactly (inputs clipped to their
box, states rolled out through the discrete dynamics) and checked: separations by the values of
its dual-feasible certificates (lower bounds on the distances, exact certificates if those fall
short), the rest directly. A hard-form plan that is not clear is reported failed.

The QP needs a linear agent model (:meth:`~swarmpc.model.agent_model.AgentModel.linear_matrices`)
whose velocity is a linear function of the state (the speed rows); positions are the model's
``position_rows``.

Interface: :class:`QPLocalLadder` has the ``solve`` signature of
:class:`swarmpc.solvers.admm.LocalSolverLadder` and returns :class:`NLPSolution` with the same
named blocks, so ``LocalAgent`` can call it in its place. Its ``x_vec`` is the QP's primal
vector followed by the certificates of the last round (as the NLP's vector carries its L blocks),
``lam_g`` the QP's multipliers: passed back as the next guess and ``duals`` they warm-start the
next ADMM iteration's solve and carry its certificates over. The parameter ``delta`` is that of
:func:`swarmpc.formulation.ocp.build_local`: one Delta_ij column per copy (or one (d,) value for
all). ``solver.local: qp`` puts it in the agents' hands through
:class:`swarmpc.solvers.admm.QPLocalSolverLadder`, which hands any call it fails to IPOPT
(:meth:`QPLocalLadder.guess_blocks` and :meth:`QPLocalLadder.solution_vector` translate the
starts and answers between the two layouts).
"""

from __future__ import annotations

import itertools
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, cast

import numpy as np
import scipy.sparse as sp
from scipy.spatial import HalfspaceIntersection

from swarmpc.config import QPOptions
from swarmpc.formulation.certificates import PolytopeCertifier, box_normals
from swarmpc.formulation.nlp import NLPSolution
from swarmpc.formulation.ocp import OCPSettings

__all__ = [
    "LocalShape",
    "OSQPBackend",
    "PIQPBackend",
    "PROVEN_INFEASIBLE",
    "PlanCheck",
    "QPAnswer",
    "QPBackend",
    "QPLocalLadder",
    "QPLocalOptions",
    "LocalQPProblem",
    "SeparationProof",
    "SequentialLocalQP",
    "SolutionLayout",
    "box_covered",
    "copy_deltas",
    "speed_polytope",
]


@dataclass(frozen=True)
class QPLocalOptions:
    """Tolerances of the QP local step (OSQP's, the margin, the certificate loop's).

    The fields are the keys of a scenario's ``solver.qp`` section, with the same names and
    defaults (:class:`swarmpc.config.QPOptions` describes and bounds them); :meth:`from_config`
    builds the options of that section. Built directly, the dataclass takes the fields unchecked.
    """

    eps_abs: float = 1e-6
    eps_rel: float = 1e-6
    max_iter: int = 4000
    polish: bool = True
    """OSQP's polishing: solves the KKT system of the guessed active set, so the answer meets its
    active rows to machine precision whenever the guess is right (the margin covers the rest)."""
    check_termination: int = 5
    """OSQP tests for termination every this many iterations: a warm-started solve that needs only
    a few iterations stops soon after them instead of running to OSQP's default check interval."""
    check_dualgap: bool = True
    """OSQP's duality-gap termination test (on top of the residual tests). The plan is rebuilt and
    checked whatever OSQP's stopping test, so turning it off trades only the optimum's accuracy."""
    margin: float = 1e-5
    """[m] tightening of every separation, plane, workspace and speed row: covers OSQP's primal
    tolerance (~eps_abs + eps_rel * |row| when polishing fails), so d_min itself is never eaten."""
    max_rounds: int = 5
    """Certificate rounds per call. Each round's plan is safe, so a capped loop is an inexact but
    safe local step; a few rounds settle the certificates of most calls, so a higher cap buys
    little."""
    iteration_rounds: int = 2
    """Certificate rounds per call of an ADMM iteration (copies free), at most ``max_rounds``: the
    next iteration's call starts from this one's plan and certificates, so the iterations carry
    the certificate loop on, and a call need not settle it (a repair call, whose answer is flown,
    may take ``max_rounds``)."""
    plan_tol: float = 1e-6
    """[m] stop when the QP's answer moved less than this from its start."""
    certificate_tol: float = 1e-6
    """Stop when no certificate normal of a row at (or near) its bound moved more than this."""
    active_band: float = 1e-3
    """[m] a row within this of its bound counts as near it for ``certificate_tol``."""
    speed_facets: int | None = None
    """Facets of the inner speed polytope; None: 16 in 2D, the 26 cube directions in 3D."""
    solver: str = "osqp"
    """QP solver of the calls whose copies are free (the ADMM iterations): "osqp" or "piqp"."""
    repair_solver: str = "piqp"
    """QP solver of the calls whose copies are pinned (the repair passes): "piqp" or "osqp"."""
    elastic: bool = True
    """A hard repair call whose certificate loops fail, and that may be handed to IPOPT (no
    deadline), is solved again with soft pair rows from its last plan (the least-violating plan,
    always feasible); a plan that needs no slack starts the hard loop again, whose answer is
    taken."""
    handover_slack: float | None = None
    """[m] With ``elastic``: a failed repair call is handed to IPOPT only when its soft plan falls
    short of d_min by at most this; None: every call the elastic phase does not answer is handed
    over (when the step allows it)."""

    @classmethod
    def from_config(cls, config: QPOptions) -> QPLocalOptions:
        """The options of a scenario's ``solver.qp`` section, field by field (the names are shared)."""
        return cls(**config.model_dump())


@dataclass(frozen=True)
class LocalShape:
    """What fixes the QP's size and sparsity: copy slots, plane slots, whether the copies are
    pinned constants (a repair pass) and the form of the pair rows ("hard" / "soft")."""

    copies: int
    planes: int = 0
    pinned: bool = False
    pair_collision: str = "hard"


def speed_polytope(dim: int, facets: int | None = None) -> tuple[np.ndarray, float]:
    """Unit normals (F, d) and ratio r of the inner polytope {a_f' v <= r v_max} of the speed ball.

    r = 1 / (largest vertex norm of {a_f' v <= 1}), so every vertex, hence the polytope, lies in
    the ball of radius v_max, and the polytope holds the ball of radius r v_max.
    """
    normals = _sphere_directions(dim, facets)
    halfspaces = np.hstack([normals, -np.ones((len(normals), 1))])
    vertices = HalfspaceIntersection(halfspaces, np.zeros(dim)).intersections
    return normals, float(1.0 / np.linalg.norm(vertices, axis=1).max())


def copy_deltas(delta: np.ndarray, copies: int, dim: int) -> np.ndarray:
    """The local problem's ``delta`` parameter as (d, copies): column c is the Delta_ij of the
    pair with copy c (b_i + b_j, the two bodies); a (d,) value is taken for every copy, as
    :func:`swarmpc.formulation.ocp.build_local` takes it."""
    array = np.asarray(delta, float)
    if array.ndim == 1 or array.shape == (dim, 1):
        return np.broadcast_to(array.reshape(dim, 1), (dim, copies))
    if array.shape != (dim, copies):
        raise ValueError(f"delta: expected ({dim},) or ({dim}, {copies}), got {array.shape}")
    return array


def _sphere_directions(dim: int, count: int | None) -> np.ndarray:
    """Evenly spread unit directions: a regular polygon in 2D; in 3D the 26 cube directions
    (count None or 26) or a Fibonacci sphere."""
    if dim == 2:
        angles = 2 * np.pi * np.arange(count or 16) / (count or 16)
        return np.column_stack([np.cos(angles), np.sin(angles)])
    if count in (None, 26):
        cube = np.array([v for v in itertools.product((-1, 0, 1), repeat=3) if any(v)], float)
        return cube / np.linalg.norm(cube, axis=1)[:, None]
    index = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1 - 2 * index / count), np.pi * (1 + 5**0.5) * index
    return np.column_stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)])


class IndexCounter:
    """Hands out consecutive indices in blocks of any shape (row-major over the given shape)."""

    def __init__(self) -> None:
        self.size = 0

    def take(self, *shape: int) -> np.ndarray:
        count = int(np.prod(shape)) if shape else 1
        block = np.arange(self.size, self.size + count).reshape(shape)
        self.size += count
        return block


class VariableLayout:
    """Indices of the QP's variables, in this order: the model's states ``X`` (s, N+1) and inputs
    ``U`` (m, N) step by step, copies ``C`` (n, d, K) step by step unless pinned, soft slacks of
    the pair rows (n, K) and of the obstacle rows (n_o, K)."""

    def __init__(self, s: OCPSettings, shape: LocalShape) -> None:
        d, N, K, n = s.dim, s.horizon, s.num_constrained, shape.copies
        counter = IndexCounter()
        self.X = counter.take(N + 1, s.model.state_dim).T
        self.U = counter.take(N, s.model.input_dim).T
        self.copy_start = counter.size
        self.C = np.zeros((n, d, K), int) if shape.pinned else np.transpose(counter.take(n, K, d), (0, 2, 1))
        self.slack_start = counter.size
        self.pair_slack = counter.take(n, K) if shape.pair_collision == "soft" else np.zeros((0, K), int)
        soft_obstacles = s.collision == "soft" and s.obstacles
        self.obstacle_slack = counter.take(len(s.obstacles), K) if soft_obstacles else np.zeros((0, K), int)
        self.own = self.X[s.model.position_rows, s.first_constrained_step:]
        self.size = counter.size


class TripletMatrix:
    """A sparse matrix with a fixed pattern whose entries are addressed by slot: entries are
    added once (explicit zeros kept, entries at the same place summed), then values set by
    slot are read out as CSC data (``data``), so solvers can update them in place."""

    def __init__(self, cols: int) -> None:
        self.cols = cols
        self._rows: list[np.ndarray] = []
        self._cols: list[np.ndarray] = []
        self._values: list[np.ndarray] = []
        self.count = 0
        self.position = np.zeros(0, int)
        self.nnz = 0

    def add(self, rows: np.ndarray, cols: np.ndarray, values: Any = 0.0) -> np.ndarray:
        """Add entries (broadcast together); returns their slots, shaped like the broadcast."""
        rows, cols, values = np.broadcast_arrays(np.asarray(rows), np.asarray(cols), np.asarray(values, float))
        slots = np.arange(self.count, self.count + rows.size).reshape(rows.shape)
        self._rows.append(rows.ravel())
        self._cols.append(cols.ravel())
        self._values.append(values.ravel())
        self.count += rows.size
        return slots

    def freeze(self, rows: int) -> tuple[sp.csc_matrix, np.ndarray]:
        """(CSC matrix with sorted indices, slot values); sets ``position``: slot -> data index."""
        r = np.concatenate(self._rows).astype(np.int64) if self._rows else np.zeros(0, np.int64)
        c = np.concatenate(self._cols).astype(np.int64) if self._cols else np.zeros(0, np.int64)
        values = np.concatenate(self._values) if self._values else np.zeros(0)
        unique, self.position = np.unique(c * rows + r, return_inverse=True)  # column-major order
        self.nnz = unique.size
        indptr = np.concatenate([[0], np.cumsum(np.bincount(unique // rows, minlength=self.cols))])
        matrix = sp.csc_matrix((self.data(values), unique % rows, indptr), shape=(rows, self.cols))
        return matrix, values

    def data(self, values: np.ndarray) -> np.ndarray:
        """CSC data of slot values (entries at the same place summed)."""
        return np.bincount(self.position, weights=values, minlength=self.nnz)


@dataclass(frozen=True)
class Linearisation:
    """Fixed certificates of one QP and the linear rows they make: per pair (n, ...) and per
    obstacle (n_o, ...), the normal G^T lambda (d, K), the constant and the certified value
    (signed distance at the positions they were computed at)."""

    pair_lam: np.ndarray
    pair_normal: np.ndarray
    pair_constant: np.ndarray
    pair_value: np.ndarray
    obstacle_lam: tuple[np.ndarray, ...]
    obstacle_normal: np.ndarray
    obstacle_constant: np.ndarray
    obstacle_value: np.ndarray


def add_rows(products: np.ndarray) -> np.ndarray:
    """Sum of (n, d, K) over its d axis, term by term in order (the sum ``einsum`` takes)."""
    return products.sum(1)


class Certifier:
    """Best certificates of an own plan against copies (delta boxes) and static obstacles, and
    the linear rows of given certificates."""

    def __init__(self, s: OCPSettings) -> None:
        self.dim, self.horizon = s.dim, s.num_constrained
        self.obstacles = [PolytopeCertifier(G, g) for G, g in s.obstacles]
        self.G = [np.asarray(G, float) for G, _ in s.obstacles]
        self.g = [np.asarray(g, float) for _, g in s.obstacles]
        self.size = 2 * s.dim + sum(len(g) for g in self.g)
        """Certificate entries per constrained step of one copy's pair rows plus all obstacles."""
        self._no_obstacle = (np.zeros((0, s.dim, s.num_constrained)), np.zeros((0, s.num_constrained)),
                             np.zeros((0, s.num_constrained)))
        """The (empty) obstacle rows of a problem without obstacles, shared by its linearisations."""

    def __call__(self, own: np.ndarray, copies: np.ndarray, delta: np.ndarray) -> Linearisation:
        """The best certificates for own positions (d, K) and copies (n, d, K); ``delta``: the
        pairs' Delta_ij, (d, n) one column per copy or (d,) for every copy."""
        d, K = own.shape
        return self.best(own, own[None] - copies, copy_deltas(delta, len(copies), d))

    def best(self, own: np.ndarray, offsets: np.ndarray, half: np.ndarray) -> Linearisation:
        """:meth:`__call__` from the offsets own - copies (n, d, K) and the pairs' Delta (d, n)."""
        d, K = own.shape
        n = len(offsets)
        lam = np.empty((n, 2 * d, K))
        certs = tuple(certifier(own).lam for certifier in self.obstacles)
        if not n:
            return self.rows_at(own, offsets, half, lam, certs)
        # every copy in one call, each against its pair's box
        direction, _ = box_normals(offsets, half.T[:, :, None])
        np.maximum(direction, 0.0, out=lam[:, :d])  # lambda_+, then lambda_-
        np.maximum(-direction, 0.0, out=lam[:, d:])
        # lambda_+ - lambda_- is the direction and lambda_+ + lambda_- its magnitude, bit for
        # bit (one of the two is zero), so the rows are those of rows_at without re-deriving them
        return self._rows(own, offsets, half, lam, direction, np.abs(direction), certs)

    def rows(self, own: np.ndarray, copies: np.ndarray, delta: np.ndarray, pair_lam: np.ndarray,
             obstacle_lam: tuple[np.ndarray, ...]) -> Linearisation:
        """The linear rows of fixed certificates, and their values at (own, copies); ``delta`` as
        in :meth:`__call__`. Per copy c the row is that of
        :func:`swarmpc.formulation.certificates.pair_rows` with its own Delta:
        n = lambda_+ - lambda_-, constant = Delta_c^T (lambda_+ + lambda_-)."""
        d, K = own.shape
        return self.rows_at(own, own[None] - copies, copy_deltas(delta, len(copies), d), pair_lam, obstacle_lam)

    def rows_at(self, own: np.ndarray, offsets: np.ndarray, half: np.ndarray, pair_lam: np.ndarray,
                obstacle_lam: tuple[np.ndarray, ...]) -> Linearisation:
        """:meth:`rows` from the offsets own - copies (n, d, K) and the pairs' Delta (d, n)."""
        d = len(own)
        plus, minus = pair_lam[:, :d], pair_lam[:, d:]
        return self._rows(own, offsets, half, pair_lam, plus - minus, plus + minus, obstacle_lam)

    def _rows(self, own: np.ndarray, offsets: np.ndarray, half: np.ndarray, pair_lam: np.ndarray,
              normal: np.ndarray, magnitude: np.ndarray, obstacle_lam: tuple[np.ndarray, ...]) -> Linearisation:
        """:meth:`rows_at` given the pair normals lambda_+ - lambda_- and magnitudes lambda_+ +
        lambda_- (n, d, K). Sums over the d axis are reductions of elementwise products, which
        add the d terms in order as ``einsum`` does on these shapes, without its dispatch."""
        constant = add_rows(half.T[:, :, None] * magnitude)
        if self.G:
            d, K = own.shape
            o_normal = np.array([G.T @ lam for G, lam in zip(self.G, obstacle_lam, strict=True)]).reshape(-1, d, K)
            o_constant = np.array([g @ lam for g, lam in zip(self.g, obstacle_lam, strict=True)]).reshape(-1, K)
            o_value = add_rows(o_normal * own) - o_constant
        else:  # no obstacles: empty rows
            o_normal, o_constant, o_value = self._no_obstacle
        return Linearisation(
            pair_lam=pair_lam, pair_normal=normal, pair_constant=constant,
            pair_value=add_rows(normal * offsets) - constant,
            obstacle_lam=obstacle_lam, obstacle_normal=o_normal, obstacle_constant=o_constant,
            obstacle_value=o_value,
        )

    def values_at(self, own: np.ndarray, offsets: np.ndarray, lin: Linearisation) -> Linearisation:
        """``lin``'s rows at other positions: :meth:`rows_at` of its certificates, whose normals
        and constants depend on the certificates and the pairs' Delta only and are taken as
        they are."""
        o_value = add_rows(lin.obstacle_normal * own) - lin.obstacle_constant if self.G else lin.obstacle_value
        return Linearisation(
            pair_lam=lin.pair_lam, pair_normal=lin.pair_normal, pair_constant=lin.pair_constant,
            pair_value=add_rows(lin.pair_normal * offsets) - lin.pair_constant,
            obstacle_lam=lin.obstacle_lam, obstacle_normal=lin.obstacle_normal,
            obstacle_constant=lin.obstacle_constant, obstacle_value=o_value,
        )

    def pack(self, lin: Linearisation) -> np.ndarray:
        """The certificates as one vector (to travel with a solution's primal vector)."""
        return np.concatenate([lin.pair_lam.ravel(), *[lam.ravel() for lam in lin.obstacle_lam]])

    def unpack(self, vector: np.ndarray, copies: int) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """(pair certificates (n, 2d, K), obstacle certificates) from :meth:`pack`'s vector."""
        d, K = self.dim, self.horizon
        stop = copies * 2 * d * K
        pair, rest, obstacles = vector[:stop].reshape(copies, 2 * d, K), vector[stop:], []
        for g in self.g:
            obstacles.append(rest[: len(g) * K].reshape(len(g), K))
            rest = rest[len(g) * K:]
        return pair, tuple(obstacles)


FIXED_COSTS_KEPT = 256
"""Goals whose fixed linear cost a :class:`LocalQPProblem` keeps (the oldest is dropped first)."""


class LocalQPProblem:
    """The QP data of one local-problem shape: minimise 1/2 x'Px + q'x s.t. l <= Ax <= u.

    Built once: the variable layout, the fixed sparsity patterns of P (upper triangle) and A,
    and every constant value. Per call it fills the vectors (``linear_cost``, ``bounds``) and the
    values that change (``cost_values``: rho and the owner weight; ``constraint_values``: the
    certificate and plane normals), all in the patterns' CSC order.
    """

    def __init__(self, s: OCPSettings, shape: LocalShape, options: QPLocalOptions) -> None:
        self.settings, self.shape, self.options = s, shape, options
        self.layout = VariableLayout(s, shape)
        self.speed_normals: np.ndarray | None
        self.speed_normals, ratio = speed_polytope(s.dim, options.speed_facets) if s.speed else (None, 1.0)
        self.speed_bound = ratio * s.speed - options.margin if s.speed else np.inf
        self._copy_keys = ([f"Y{c}" for c in range(shape.copies)], [f"Z{c}" for c in range(shape.copies)])
        self._goal_weights = (-2.0 * s.Q, -2.0 * s.Qf)
        """The goal's weights in q (states before the last, the last)."""
        self._fixed_costs: dict[bytes, np.ndarray] = {}
        """q's goal and slack terms per goal (:meth:`_fixed_cost`): agents of one shape share it."""
        self._cost_pattern()
        self._constraint_pattern()

    # --- cost -------------------------------------------------------------------------------
    def _cost_pattern(self) -> None:
        s, lay = self.settings, self.layout
        P = TripletMatrix(lay.size)
        for k in range(s.horizon + 1):
            self._add_block(P, lay.X[:, k], 2.0 * (s.Q if k < s.horizon else s.Qf))
        for k in range(s.horizon):
            self._add_block(P, lay.U[:, k], 2.0 * s.R)
        own = P.add(lay.own, lay.own)  # the consensus diagonal: slots of its own, summed on Q's
        copies = P.add(lay.C, lay.C) if not self.shape.pinned else np.zeros(0, int)
        self.P, base = P.freeze(lay.size)
        own_mask, copy_mask = np.zeros(P.count), np.zeros(P.count)
        own_mask[own.ravel()] = 1.0
        copy_mask[np.ravel(copies)] = 1.0
        self._P_parts = (P.data(base), P.data(own_mask), P.data(copy_mask))

    @staticmethod
    def _add_block(P: TripletMatrix, index: np.ndarray, block: np.ndarray) -> None:
        """Upper triangle of a dense block (its nonzeros and the diagonal) on variables ``index``."""
        rows, cols = np.nonzero(np.triu((block != 0) | np.eye(len(index), dtype=bool)))
        P.add(index[rows], index[cols], block[rows, cols])

    def cost_values(self, rho: float, owner_weight: float) -> np.ndarray:
        """P's data (CSC order of the upper triangle) for penalty rho and owner weight."""
        base, own, copy = self._P_parts
        return base + rho * owner_weight * own + rho * copy

    def copy_targets(self, params: dict[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
        """The copies' multipliers and consensus targets (``Y{c}``, ``Z{c}``) stacked (n, d, K)
        each; None without copies. A call reads them once for its linear cost and objective."""
        if not self.shape.copies:
            return None
        Y = np.array([params[key] for key in self._copy_keys[0]], float)
        return Y, np.array([params[key] for key in self._copy_keys[1]], float)

    def linear_cost(self, params: dict[str, Any],
                    targets: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """q: goal tracking, consensus (gamma - rho_b z per block) and slack prices, in the
        layout's order; ``targets``: :meth:`copy_targets` of ``params`` when the caller has them."""
        s, lay = self.settings, self.layout
        rho, weight = float(params["rho"]), float(params["owner_weight"])
        q = self._fixed_cost(np.asarray(params["goal"], float)).copy()
        states = q[: (s.horizon + 1) * s.model.state_dim].reshape(s.horizon + 1, s.model.state_dim)  # a view
        consensus = np.asarray(params["Y"], float) - rho * weight * np.asarray(params["Z"], float)
        states[s.first_constrained_step:, s.model.position_rows] += consensus.T
        if not self.shape.pinned and self.shape.copies:
            stacked = targets if targets is not None else self.copy_targets(params)
            assert stacked is not None  # there are copies
            Y, Z = stacked
            q[lay.C] = Y - rho * Z
        return q

    def _fixed_cost(self, goal: np.ndarray) -> np.ndarray:
        """q without the consensus terms: the goal's (-2 Q goal per state, -2 Qf goal for the
        last) and the slack prices kappa. Kept per goal (a few hundred at most), since the goal
        seldom changes between calls."""
        key = goal.tobytes()
        q = self._fixed_costs.get(key)
        if q is None:
            s, lay = self.settings, self.layout
            q = np.zeros(lay.size)
            states = q[: (s.horizon + 1) * s.model.state_dim].reshape(s.horizon + 1, s.model.state_dim)  # a view
            states[:-1] = self._goal_weights[0] @ goal
            states[-1] = self._goal_weights[1] @ goal
            q[lay.slack_start:] = s.kappa
            if len(self._fixed_costs) >= FIXED_COSTS_KEPT:
                self._fixed_costs.pop(next(iter(self._fixed_costs)))  # the oldest
            self._fixed_costs[key] = q
        return q

    # --- constraints ------------------------------------------------------------------------
    def _constraint_pattern(self) -> None:
        """Rows in blocks (named in ``rows``): initial state, dynamics, limits, collision rows,
        slack signs; fixed values set here, changing ones (``_*_slots``) left for each call."""
        self.rows: dict[str, np.ndarray] = {}
        self._lower: list[np.ndarray] = []
        self._upper: list[np.ndarray] = []
        self._row_counter = IndexCounter()
        A = TripletMatrix(self.layout.size)
        self._dynamics_rows(A)
        self._limit_rows(A)
        self._collision_rows(A)
        self.A, values = A.freeze(self._row_counter.size)
        self.base_lower, self.base_upper = np.concatenate(self._lower), np.concatenate(self._upper)
        self._A_base = A.data(values)
        """A's data with the changing entries (certificate and plane normals) at zero."""
        changing = [self._obstacle_slots, self._pair_slots, self._plane_slots]
        changing += [self._copy_slots] if self._copy_slots is not None else []
        places = np.concatenate([np.ravel(slots) for slots in changing])
        if np.any(np.bincount(A.position, minlength=A.nnz)[A.position[places]] != 1):
            raise AssertionError("a changing entry of A shares its place with another entry")
        self._obstacle_places, self._pair_places, self._plane_places = (A.position[slots] for slots in changing[:3])
        self._copy_places = A.position[self._copy_slots] if self._copy_slots is not None else None
        self._row_slices = {name: slice(int(index.min()), int(index.max()) + 1) if index.size else slice(0, 0)
                            for name, index in self.rows.items()}
        """Each block's rows as a slice (every block is a consecutive range)."""
        self._floor = self.settings.d_min + self.options.margin
        """The separation rows' bound before their certificates' constants."""

    def _block(self, name: str, *size: int, lower: Any = 0.0, upper: Any = np.inf) -> np.ndarray:
        """Row indices of a new block of rows, with their constant bounds."""
        index = self._row_counter.take(*size)
        self.rows[name] = index
        self._lower.append(np.broadcast_to(np.asarray(lower, float), index.shape).ravel())
        self._upper.append(np.broadcast_to(np.asarray(upper, float), index.shape).ravel())
        return index

    def _dynamics_rows(self, A: TripletMatrix) -> None:
        """x_0 = measured state; x_{k+1} - A x_k - B u_k = 0."""
        s, lay = self.settings, self.layout
        Ad, Bd = linear_matrices(s)
        n = s.model.state_dim
        A.add(self._block("init", n, lower=0.0, upper=0.0), lay.X[:, 0], 1.0)
        dyn = self._block("dyn", s.horizon, n, lower=0.0, upper=0.0).T  # (n, N)
        A.add(dyn, lay.X[:, 1:], 1.0)
        for i, j in zip(*np.nonzero(Ad), strict=True):
            A.add(dyn[i], lay.X[j, :-1], -Ad[i, j])
        for i, j in zip(*np.nonzero(Bd), strict=True):
            A.add(dyn[i], lay.U[j], -Bd[i, j])

    def _limit_rows(self, A: TripletMatrix) -> None:
        """Input box, workspace box (tightened by the margin), inner speed polytope."""
        s, lay, d = self.settings, self.layout, self.settings.dim
        N, K = s.horizon, s.num_constrained
        if s.accel is not None:
            lower, upper = s.model.input_bounds(s.accel, s.speed)
            A.add(self._block("accel", N, s.model.input_dim, lower=lower, upper=upper).T, lay.U, 1.0)
        if s.lower is not None and s.upper is not None:
            margin = self.options.margin
            rows = self._block("workspace", K, d, lower=s.lower + margin, upper=s.upper - margin)
            A.add(rows.T, lay.own, 1.0)
        if s.speed is not None and self.speed_normals is not None:
            # a_f' v(x_k) over the state entries the velocity depends on (v linear in the state)
            velocity = s.model.velocity(np.eye(s.model.state_dim))  # (s, d): row j is v(e_j)
            support = np.flatnonzero(np.any(velocity != 0, axis=1))
            normals = self.speed_normals @ velocity[support].T  # (F, entries)
            speed = self._block("speed", N, len(self.speed_normals), lower=-np.inf, upper=self.speed_bound)
            A.add(speed[:, :, None], lay.X[support, 1:].T[:, None, :], normals[None])

    def _collision_rows(self, A: TripletMatrix) -> None:
        """Obstacle, pair and plane rows (normals set per call), soft slacks and their signs."""
        s, lay, shape, K = self.settings, self.layout, self.shape, self.settings.num_constrained
        obstacles = self._block("obstacles", len(s.obstacles), K)
        self._obstacle_slots = A.add(obstacles[:, None, :], lay.own[None])  # (n_o, d, K)
        A.add(obstacles[: len(lay.obstacle_slack)], lay.obstacle_slack, 1.0)
        pairs = self._block("pairs", shape.copies, K)
        self._pair_slots = A.add(pairs[:, None, :], lay.own[None])
        self._copy_slots = A.add(pairs[:, None, :], lay.C) if not shape.pinned else None
        A.add(pairs[: len(lay.pair_slack)], lay.pair_slack, 1.0)
        planes = self._block("planes", shape.planes, K)
        self._plane_slots = A.add(planes[:, None, :], lay.own[None])
        A.add(self._block("pair_slack", *lay.pair_slack.shape), lay.pair_slack, 1.0)
        A.add(self._block("obstacle_slack", *lay.obstacle_slack.shape), lay.obstacle_slack, 1.0)

    def constraint_values(self, lin: Linearisation, params: dict[str, Any]) -> np.ndarray:
        """A's data (CSC order) with the certificates' normals and the planes' normals. Each of
        these entries has a place of its own in the pattern (checked at set-up) and is written
        there as 0.0 + value, the sum of its one slot (so a normal of -0.0 reads +0.0)."""
        data = self._A_base.copy()
        if self._obstacle_places.size:
            data[self._obstacle_places] = lin.obstacle_normal + 0.0
        data[self._pair_places] = lin.pair_normal + 0.0
        if self._copy_places is not None:
            data[self._copy_places] = 0.0 - lin.pair_normal  # = -n + 0.0, bit for bit
        for p in range(self.shape.planes):
            data[self._plane_places[p]] = np.asarray(params[f"Hn{p}"], float) + 0.0
        return data

    def bounds(
        self, lin: Linearisation, params: dict[str, Any], pinned: np.ndarray | None = None,
        slack_caps: dict[int, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(l, u): measured state, separation rows d_min + margin + constant (pinned copies move
        their n'c to the bound), plane offsets, and slack caps (a pinned slack's upper bound)."""
        rows = self._row_slices
        lower, upper = self.base_lower.copy(), self.base_upper.copy()
        lower[rows["init"]] = upper[rows["init"]] = np.asarray(params["x0"], float)
        if lin.obstacle_constant.size:
            lower[rows["obstacles"]] = (self._floor + lin.obstacle_constant).ravel()
        pair = self._floor + lin.pair_constant
        if pinned is not None:
            pair = pair + add_rows(lin.pair_normal * pinned)
        lower[rows["pairs"]] = pair.ravel()
        for p in range(self.shape.planes):
            lower[self.rows["planes"][p]] = np.ravel(params[f"Hb{p}"]) + self.options.margin
        for slot, cap in (slack_caps or {}).items():
            upper[self.rows["pair_slack"][slot]] = cap
        return lower, upper


@dataclass(frozen=True)
class QPAnswer:
    """One QP solve: primal x, dual y, whether it counts as solved, the solver's status, its
    iterations and its own reported time [s] (Python overhead excluded)."""

    x: np.ndarray
    y: np.ndarray
    solved: bool
    status: str
    iterations: int
    solver_time: float
    exact: bool = False
    """True when the answer meets its active rows exactly (OSQP: polishing succeeded)."""


class QPBackend(Protocol):
    """What the local step needs of a QP solver: set up once, then update data and warm-start."""

    def setup(self, P: sp.csc_matrix, q: np.ndarray, A: sp.csc_matrix, lower: np.ndarray,
              upper: np.ndarray) -> None: ...

    def update(self, q: np.ndarray, lower: np.ndarray, upper: np.ndarray, P_data: np.ndarray | None,
               A_data: np.ndarray | None) -> None: ...

    def solve(self, x: np.ndarray, y: np.ndarray | None) -> QPAnswer: ...


class OSQPBackend:
    """OSQP through its own Python API: P (upper triangle) and A set up once; later calls update
    vectors and, when given, matrix values in place (which refactors the KKT system)."""

    def __init__(self, options: QPLocalOptions) -> None:
        self.options = options
        self._solver: Any = None
        self._core: Any = None
        """OSQP's compiled solver object, called directly where the interface has one."""
        self._infinity = np.inf
        self._sigint_flag: Callable[[], int] | None = None

    def setup(self, P: sp.csc_matrix, q: np.ndarray, A: sp.csc_matrix, lower: np.ndarray,
              upper: np.ndarray) -> None:
        import osqp  # imported here: the IPOPT path must not need it

        o = self.options
        self._solver = osqp.OSQP()
        self._solver.setup(P, q, A, lower, upper, verbose=False, eps_abs=o.eps_abs, eps_rel=o.eps_rel,
                           max_iter=o.max_iter, polishing=o.polish, warm_starting=True,
                           polish_refine_iter=3, check_termination=o.check_termination,
                           check_dualgap=o.check_dualgap)
        self._core = getattr(self._solver, "_solver", None)
        self._infinity = float(self._solver.constant("OSQP_INFTY"))
        self._sigint_flag = osqp_sigint_flag()

    def update(self, q: np.ndarray, lower: np.ndarray, upper: np.ndarray, P_data: np.ndarray | None,
               A_data: np.ndarray | None) -> None:
        """New vectors and, where given, matrix values. Straight to OSQP's compiled solver: the
        Python interface's ``update`` adds bookkeeping for derivatives (unused here) that cost
        as much as the vector update itself; the bounds are clipped to OSQP's infinity as it
        clips them."""
        if self._core is None:  # an OSQP without the compiled object: its public interface
            matrices = {k: v for k, v in (("Px", P_data), ("Ax", A_data)) if v is not None}
            self._solver.update(q=q, l=lower, u=upper, **matrices)
            return
        self._core.update_data_vec(q=q, l=np.maximum(lower, -self._infinity), u=np.minimum(upper, self._infinity))
        if P_data is not None or A_data is not None:
            self._core.update_data_mat(P_x=P_data, P_i=None, A_x=A_data, A_i=None)

    def solve(self, x: np.ndarray, y: np.ndarray | None) -> QPAnswer:
        info, primal, dual = self._solve_once(x, y)
        while self._took_sigint(info):
            # OSQP takes SIGINT for itself while it solves (and stops, if it notices in time): the
            # Ctrl-C was meant for the program, which gets it back; a stopped QP is solved again
            signal.raise_signal(signal.SIGINT)
            if info.status != OSQP_INTERRUPTED:
                break
            info, primal, dual = self._solve_once(x, y)
        if primal is None or primal[0] is None:  # infeasible: no primal point
            return QPAnswer(x, np.zeros(self._solver.m), False, str(info.status), int(info.iter),
                            float(info.solve_time + info.update_time))
        return QPAnswer(
            x=np.array(primal, float), y=np.array(dual, float),
            solved=info.status in ("solved", "solved inaccurate"),
            status=str(info.status), iterations=int(info.iter),
            solver_time=float(info.solve_time + info.polish_time + info.update_time), exact=info.status_polish == 1,
        )

    def _took_sigint(self, info: Any) -> bool:
        """Whether a SIGINT reached OSQP's own handler during the last solve: its flag, read from
        the extension (a signal during polishing does not stop the solve, so the status alone
        would miss it), else the status."""
        if self._sigint_flag is None:
            return bool(info.status == OSQP_INTERRUPTED)
        return bool(self._sigint_flag())

    def _solve_once(self, x: np.ndarray, y: np.ndarray | None) -> tuple[Any, Any, Any]:
        """(info, primal, dual) of one solve from the start (x, y)."""
        start = self._core if self._core is not None else self._solver  # the interface only passes it on
        start.warm_start(x, y if y is not None else np.zeros(self._solver.m))
        if self._core is None:
            result = self._solver.solve(raise_error=False)
            return result.info, result.x, result.y
        self._core.solve()  # the interface's solve copies every field of the info into a namespace first
        solution = self._core.solution
        return self._core.info, solution.x, solution.y


OSQP_INTERRUPTED = "interrupted"
"""OSQP's status of a solve a SIGINT stopped (its own handler holds SIGINT while it solves)."""


def osqp_sigint_flag() -> Callable[[], int] | None:
    """OSQP's ``osqp_is_interrupted`` (nonzero when its handler caught a SIGINT during the last
    solve; reset when a solve begins), from the loaded extension; None where it is not exported."""
    import ctypes

    from osqp import ext_builtin

    try:
        flag = ctypes.CDLL(ext_builtin.__file__).osqp_is_interrupted
    except (OSError, AttributeError):
        return None
    flag.restype, flag.argtypes = ctypes.c_int, []
    return cast(Callable[[], int], flag)


PIQP_STATUS = {"PIQP_SOLVED": "solved", "PIQP_MAX_ITER_REACHED": "maximum iterations reached",
               "PIQP_PRIMAL_INFEASIBLE": "primal infeasible", "PIQP_DUAL_INFEASIBLE": "dual infeasible",
               "PIQP_NUMERICS": "numerics", "PIQP_UNSOLVED": "unsolved", "PIQP_INVALID_SETTINGS": "invalid settings"}
"""PIQP's statuses in OSQP's words (a failed call's status reads ``qp_<status>`` either way)."""


class PIQPBackend:
    """PIQP (sparse proximal interior point) through its own Python API.

    An interior-point method takes about ten iterations whatever its start, where OSQP's
    first-order iterations number in the hundreds on a QP with many rows at their bounds (a
    repair call against pinned neighbours) and in the thousands before OSQP declares such a QP
    infeasible; it cannot use a warm start, which OSQP turns into a few iterations on the ADMM
    iterations' slowly moving QPs. The rows whose bounds are equal at set-up (measured state,
    dynamics) are PIQP's equalities, the rest its two-sided inequalities; a later call that
    opens an equality row sets the solver up again. Rows without either bound (a free copy's
    positions in a car's QP) are left out, as PIQP would zero them (and say so on every set-up);
    a later call that bounds one sets the solver up again. The answer's multipliers are returned in
    OSQP's convention (one per row, positive at the upper bound) so either backend can start
    from them."""

    def __init__(self, options: QPLocalOptions) -> None:
        self.options = options
        self._solver: Any = None
        self._eq = self._ineq = np.zeros(0, int)
        self._free = np.zeros(0, bool)
        self._P: sp.csc_matrix | None = None
        self._A: sp.csc_matrix | None = None
        self._parts: tuple[sp.csc_matrix, sp.csc_matrix, np.ndarray, np.ndarray] | None = None

    def setup(self, P: sp.csc_matrix, q: np.ndarray, A: sp.csc_matrix, lower: np.ndarray,
              upper: np.ndarray) -> None:
        import piqp  # imported here: only this backend needs it

        self._P, self._A = P.copy(), A.copy()  # own copies: updates write their values in place
        self._eq = np.flatnonzero(lower == upper)
        self._free = np.isinf(lower) & np.isinf(upper)  # rows without a bound are left out
        self._ineq = np.flatnonzero((lower != upper) & ~self._free)
        marker = sp.csc_matrix((np.arange(1, A.nnz + 1, dtype=float), A.indices, A.indptr), shape=A.shape)
        eq, ineq = marker[self._eq].tocsc(), marker[self._ineq].tocsc()
        self._parts = (eq, ineq, eq.data.astype(int) - 1, ineq.data.astype(int) - 1)
        solver = piqp.SparseSolver()
        solver.settings.eps_abs, solver.settings.eps_rel = self.options.eps_abs, self.options.eps_rel
        solver.settings.compute_timings = True  # the answer's solver time (diagnostics)
        A_eq, A_in = self._split(A.data)
        solver.setup(P, q, A_eq, lower[self._eq], A_in, lower[self._ineq], upper[self._ineq])
        self._solver = solver

    def _split(self, data: np.ndarray) -> tuple[sp.csc_matrix, sp.csc_matrix]:
        """(equality rows, inequality rows) of A with values ``data`` (A's CSC order), written
        into this backend's own two matrices (PIQP copies what it is given)."""
        assert self._parts is not None
        eq, ineq, eq_map, in_map = self._parts
        eq.data[:], ineq.data[:] = data[eq_map], data[in_map]
        return eq, ineq

    def update(self, q: np.ndarray, lower: np.ndarray, upper: np.ndarray, P_data: np.ndarray | None,
               A_data: np.ndarray | None) -> None:
        assert self._P is not None and self._A is not None
        if P_data is not None:  # values written in place: a scipy matrix costs tens of microseconds
            self._P.data[:] = P_data
        if A_data is not None:
            self._A.data[:] = A_data
        if np.any(lower[self._eq] != upper[self._eq]) or np.any(np.isfinite(lower[self._free]) |
                                                               np.isfinite(upper[self._free])):
            self.setup(self._P, q, self._A, lower, upper)  # an equality row opened or a free row closed
            return
        changes: dict[str, Any] = {"c": q, "b": lower[self._eq], "h_l": lower[self._ineq], "h_u": upper[self._ineq]}
        if P_data is not None:
            changes["P"] = self._P
        if A_data is not None:
            changes["A"], changes["G"] = self._split(A_data)
        self._solver.update(**changes)

    def solve(self, x: np.ndarray, y: np.ndarray | None) -> QPAnswer:
        status = PIQP_STATUS.get(self._solver.solve().name, "unsolved")
        result, info = self._solver.result, self._solver.result.info
        time_spent = float(info.solve_time + info.update_time)
        duals = np.zeros(len(self._free))  # one per row; rows left out have none
        if status != "solved":
            return QPAnswer(x, duals, False, status, int(info.iter), time_spent)
        duals[self._eq] = result.y
        duals[self._ineq] = np.asarray(result.z_u) - np.asarray(result.z_l)
        return QPAnswer(np.array(result.x, float), duals, True, status, int(info.iter), time_spent)


def qp_backend(options: QPLocalOptions, pinned: bool = False) -> QPBackend:
    """The backend ``options`` name for a shape's calls: ``repair_solver`` when the copies are
    ``pinned`` (a repair pass), else ``solver``."""
    name = options.repair_solver if pinned else options.solver
    backends: dict[str, Callable[[QPLocalOptions], QPBackend]] = {"osqp": OSQPBackend, "piqp": PIQPBackend}
    if name not in backends:
        raise ValueError(f"solver.qp: unknown QP solver {name!r} (osqp or piqp)")
    return backends[name](options)


class LocalQP:
    """One shape's QP and its solver: set up on the first call, then updated in place."""

    def __init__(self, problem: LocalQPProblem, backend: QPBackend) -> None:
        self.problem = problem
        self.backend = backend
        self._ready = False
        self._P_key: tuple[float, float] | None = None
        self._A_data: np.ndarray | None = None

    def solve(
        self, params: dict[str, Any], lin: Linearisation, start: np.ndarray, y: np.ndarray | None,
        pinned: np.ndarray | None = None, slack_caps: dict[int, float] | None = None, q: np.ndarray | None = None,
    ) -> QPAnswer:
        """Solve with certificates ``lin`` from primal ``start`` (and dual ``y``); ``q``: the
        linear cost of ``params`` when the caller has it (it does not depend on ``lin``)."""
        pb = self.problem
        q = pb.linear_cost(params) if q is None else q
        lower, upper = pb.bounds(lin, params, pinned, slack_caps)
        key = (float(params["rho"]), float(params["owner_weight"]))
        P_data = pb.cost_values(*key) if key != self._P_key else None  # None: P's values unchanged
        A_data = pb.constraint_values(lin, params)
        if not self._ready:
            P_data = pb.cost_values(*key) if P_data is None else P_data
            self.backend.setup(sp.csc_matrix((P_data, pb.P.indices, pb.P.indptr), shape=pb.P.shape), q,
                               sp.csc_matrix((A_data, pb.A.indices, pb.A.indptr), shape=pb.A.shape), lower, upper)
            self._ready = True
        else:
            same_A = self._A_data is not None and bool((A_data == self._A_data).all())  # as np.array_equal
            self.backend.update(q, lower, upper, P_data, None if same_A else A_data)
        self._P_key, self._A_data = key, A_data
        return self.backend.solve(start, y)


def linear_matrices(s: OCPSettings) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of the settings' agent model; ValueError when it is not linear (the QP local step
    needs linear dynamics)."""
    matrices = s.model.linear_matrices()
    if matrices is None:
        raise ValueError(f"the QP local step needs a linear agent model, not {s.model.name}")
    return matrices


def rollout_matrices(s: OCPSettings) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, Gamma) with vec(X) = Phi x0 + Gamma vec(U) (column-major, states (s, N+1), inputs
    (m, N)) for the discrete dynamics: the exact rollout as one product."""
    A, B = linear_matrices(s)
    n, m, N = A.shape[0], B.shape[1], s.horizon
    Phi = np.zeros(((N + 1) * n, n))
    Gamma = np.zeros(((N + 1) * n, N * m))
    power = np.eye(n)
    for k in range(N + 1):
        Phi[k * n:(k + 1) * n] = power
        power = A @ power
    for k in range(1, N + 1):
        Gamma[k * n:(k + 1) * n] = A @ Gamma[(k - 1) * n:k * n]
        Gamma[k * n:(k + 1) * n, (k - 1) * m:k * m] = B
    return Phi, Gamma


def local_objective(blocks: dict[str, np.ndarray], params: dict[str, Any], s: OCPSettings, copies: int) -> float:
    """The NLP objective of :func:`swarmpc.formulation.ocp.build_local` at named blocks (X, U,
    C{c}, A{c}, A_o{n}): tracking cost + consensus terms + kappa * slacks."""
    stacked = None
    if copies:
        slots = range(copies)
        stacked = (np.array([blocks[f"C{c}"] for c in slots]), np.array([params[f"Y{c}"] for c in slots]),
                   np.array([params[f"Z{c}"] for c in slots]))
    return stacked_objective(blocks, params, s, stacked)


def stacked_objective(blocks: dict[str, np.ndarray], params: dict[str, Any], s: OCPSettings,
                      copies: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> float:
    """:func:`local_objective` with the copies, their multipliers and targets (C, Y, Z) stacked
    (n, d, K) each, C-contiguous (None: no copies): the local step has them stacked already."""
    first = s.first_constrained_step
    X, U, goal = blocks["X"], blocks["U"], np.asarray(params["goal"], float)
    err = X - goal[:, None]
    head, tail = err[:, :-1], err[:, -1]
    cost = float(((s.Q @ head) * head).sum() + tail @ s.Qf @ tail + ((s.R @ U) * U).sum())
    rho, weight = float(params["rho"]), float(params["owner_weight"])
    diff = X[s.model.position_rows, first:] - np.asarray(params["Z"], float)
    cost += float((np.asarray(params["Y"], float) * diff).sum() + 0.5 * rho * weight * (diff * diff).sum())
    if copies is not None:
        C, multipliers, Z = copies
        diff = C - Z
        cost += float((multipliers * diff).sum() + 0.5 * rho * (diff * diff).sum())
    slack = 0.0
    for key, value in blocks.items():
        if key.startswith("A"):
            slack += np.sum(value)
    return cost + s.kappa * float(slack)


VERIFY_TOL = 1e-7
"""Largest violation of a constraint a verified plan may show (:meth:`PlanCheck.verified`;
IPOPT's constraint tolerance in the reference check)."""

PROVEN_INFEASIBLE = "qp_proven_infeasible"
"""Status of a call whose problem has no feasible point at all (:class:`SeparationProof`): no
solver can answer it, so it is not handed to another one."""


def box_covered(lower: np.ndarray, upper: np.ndarray, boxes_lower: np.ndarray, boxes_upper: np.ndarray,
                max_cells: int = 4096) -> bool:
    """Whether the closed box [lower, upper] (d,) lies inside the union of the closed boxes
    [boxes_lower, boxes_upper] (B, d); False also when deciding would take more than ``max_cells``
    cells. The box is cut into cells at every box face inside it: a cell lies in a box as soon as
    its centre does (its faces are among the cuts), so testing the centres decides exactly."""
    meets = np.all((boxes_lower <= upper) & (boxes_upper >= lower), axis=1)
    boxes_lower, boxes_upper = boxes_lower[meets], boxes_upper[meets]
    if np.any(np.all((boxes_lower <= lower) & (boxes_upper >= upper), axis=1)):
        return True
    if not len(boxes_lower):
        return False
    centres = []
    for axis in range(len(lower)):
        faces = np.concatenate([[lower[axis], upper[axis]], boxes_lower[:, axis], boxes_upper[:, axis]])
        cuts = np.unique(np.clip(faces, lower[axis], upper[axis]))
        centres.append(0.5 * (cuts[1:] + cuts[:-1]) if len(cuts) > 1 else cuts)
    if np.prod([len(c) for c in centres]) > max_cells:
        return False
    # a cell centre lies in a box when each of its coordinates lies in the box's interval on that
    # axis: per box, the product of the axes' membership masks counts it; covered when every cell
    # is counted by some box (exact: sums of 0/1 products)
    counts = np.ones((len(boxes_lower), 1))
    for axis, c in enumerate(centres):
        member = (boxes_lower[:, axis, None] <= c[None]) & (c[None] <= boxes_upper[:, axis, None])  # (B, cells)
        counts = (counts[:, :, None] * member[:, None, :]).reshape(len(boxes_lower), -1)
    return bool(np.all(counts.sum(axis=0) > 0))


class SeparationProof:
    """A proof that a local problem with pinned copies (a repair pass) has no feasible point: at
    some constrained step every position the agent can reach lies closer than d_min to a pinned
    neighbour's body.

    The positions reachable at step k within the input box form the affine image of that box
    under the exact rollout; its bounding box (exact for a model whose axes do not couple, such
    as the double integrator) holds them all. Around a copy c, every position in the boxes
    c +- (Delta + (d_min - margin) e_i), i = 1..d, and c +- (Delta + (d_min - margin) / sqrt(d))
    is at most d_min - margin from the copy's body, so a reachable box inside their union
    (:func:`box_covered`) leaves no plan that keeps the separation, whatever the certificates or
    the solver. Problems of the kind arise in repair passes where the neighbours' held plans
    close in faster than the acceleration limit lets the agent get away. The other constraints
    only shrink the feasible set, so leaving them out keeps the proof sound.
    """

    def __init__(self, s: OCPSettings, transition: np.ndarray, response: np.ndarray, margin: float) -> None:
        self.settings, self.margin = s, margin
        self._last: tuple[bytes, bool] | None = None
        """The last problem decided and its answer: a repair retried from another start (the
        agent's own plan) poses the same problem again."""
        lower, upper = s.model.input_bounds(s.accel, s.speed)
        self.bounded = s.accel is not None and bool(np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)))
        n = s.model.state_dim
        rows = np.arange(n)[s.model.position_rows]
        steps = np.arange(s.first_constrained_step, s.horizon + 1)
        index = (steps[:, None] * n + rows[None]).ravel()  # (K * d,) rows of vec(X), step by step
        self.transition = transition[index]
        if self.bounded:
            mid = np.tile(0.5 * (lower + upper), s.horizon)
            half = np.tile(0.5 * (upper - lower), s.horizon)
            self.drift = response[index] @ mid
            self.spread = (np.abs(response[index]) @ half).reshape(len(steps), len(rows)).T  # (d, K)

    def infeasible(self, x0: np.ndarray, pinned: np.ndarray, delta: np.ndarray) -> bool:
        """True when the reachable positions of some constrained step lie inside the union of
        the pinned copies' (n, d, K) forbidden boxes; ``delta`` (d, n) the pairs' Delta_ij."""
        if not self.bounded or not len(pinned):
            return False
        key = b"".join(np.ascontiguousarray(a, float).tobytes() for a in (x0, pinned, delta))
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        answer = self._covered(np.asarray(x0, float), pinned, delta)
        self._last = (key, answer)
        return answer

    def _covered(self, x0: np.ndarray, pinned: np.ndarray, delta: np.ndarray) -> bool:
        """:meth:`infeasible`'s decision for a new problem."""
        d, K = self.spread.shape
        centre = (self.transition @ x0 + self.drift).reshape(K, d).T
        reach = self.settings.d_min - self.margin
        widths = np.concatenate([np.eye(d) * reach, np.full((1, d), reach / np.sqrt(d))])  # (d+1, d)
        half = (delta.T[:, None, :] + widths[None]).reshape(-1, d)  # (n (d+1), d)
        copies = np.repeat(np.transpose(pinned, (2, 0, 1)), d + 1, axis=1)  # (K, n (d+1), d)
        lower, upper = (centre - self.spread).T, (centre + self.spread).T  # (K, d)
        for k in corners_covered(lower, upper, copies - half, copies + half):
            if box_covered(lower[k], upper[k], copies[k] - half, copies[k] + half):
                return True
        return False


def corners_covered(lower: np.ndarray, upper: np.ndarray, boxes_lower: np.ndarray,
                     boxes_upper: np.ndarray) -> np.ndarray:
    """Indices k of the boxes [lower[k], upper[k]] ((K, d) each) whose every corner lies in one of
    the boxes [boxes_lower[k], boxes_upper[k]] ((K, B, d) each): a box with a corner outside their
    union is not covered (the corner is one of its points), so only these can be
    (:func:`box_covered` decides them)."""
    d = lower.shape[1]
    pick = (np.arange(2 ** d)[:, None] >> np.arange(d)[None]) & 1  # (2^d, d) corner choices
    corners = np.where(pick[None].astype(bool), upper[:, None], lower[:, None])  # (K, 2^d, d)
    inside = np.all((boxes_lower[:, None] <= corners[:, :, None]) & (corners[:, :, None] <= boxes_upper[:, None]),
                    axis=3)  # (K, 2^d, B)
    return np.flatnonzero(np.all(np.any(inside, axis=2), axis=1))


@dataclass(frozen=True)
class LoopRecord:
    """Diagnostics of one certificate loop: rounds, QP iterations, solver-reported and wall time."""

    rounds: int
    qp_iterations: int
    solver_time: float
    wall_time: float
    converged: bool
    exact_rounds: int = 0
    """Rounds whose QP answer was exact on its active set (OSQP: polished)."""


Call = tuple[dict[str, Any], tuple[np.ndarray, np.ndarray] | None, np.ndarray, list[Any], int]
"""What every certificate loop of a call shares: parameters, the copies' stacked multipliers and
targets, the pairs' Delta (d, n), the tally (rounds, QP iterations, solver time, exact answers), the round cap."""


def _row_change(old: np.ndarray, new: np.ndarray, near: np.ndarray) -> float:
    """Largest change between two certificate normals (rows, d, K) over the rows ``near`` (rows, K)
    their bound (0 when none is)."""
    if not near.any():
        return 0.0
    return max(0.0, float((np.abs(old - new) * near[:, None, :]).max()))


class SolutionLayout:
    """One shape's layouts and the conversions between them: the NLP's named blocks (X, U,
    C{c}, L{c}, A{c}, L_o{o}, A_o{o}), the QP's primal vector (:class:`VariableLayout`) and the
    solution vector (the primal vector, then the certificates it was linearised with last, as
    the NLP's vector carries its L blocks)."""

    def __init__(self, s: OCPSettings, shape: LocalShape, variables: VariableLayout, certify: Certifier) -> None:
        self.settings, self.shape, self.variables, self.certify = s, shape, variables, certify
        self.size = variables.size + shape.copies * 2 * s.dim * s.num_constrained + sum(
            len(g) for _, g in s.obstacles) * s.num_constrained
        """Length of a solution vector."""
        self._block_keys = [(f"C{c}", f"L{c}", f"A{c}") for c in range(shape.copies)]

    def positions(self, x: np.ndarray, pinned: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Own constrained positions (d, K) and the copies (n, d, K) of a primal vector."""
        lay = self.variables
        return x.take(lay.own), (pinned if pinned is not None else x.take(lay.C))

    def start_point(self, guess: dict[str, np.ndarray]) -> np.ndarray:
        """A primal vector in this QP's layout from named blocks (X, U, C{c})."""
        lay, x = self.variables, np.zeros(self.variables.size)
        x[lay.X] = np.asarray(guess["X"], float)
        if "U" in guess:
            x[lay.U] = np.asarray(guess["U"], float)
        if not self.shape.pinned:
            for c in range(self.shape.copies):
                x[lay.C[c]] = np.asarray(guess[f"C{c}"], float)
        return x

    def vector(self, x: np.ndarray, lin: Linearisation) -> np.ndarray:
        """The solution vector of primal ``x`` and the certificates of ``lin``."""
        return np.concatenate([x, self.certify.pack(lin)])

    def unpack(self, vector: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
        """(primal vector, pair certificates (n, 2d, K), obstacle certificates) of a solution
        vector, all views into it."""
        size = self.variables.size
        return (vector[:size], *self.certify.unpack(vector[size:], self.shape.copies))

    def vector_of(self, blocks: dict[str, np.ndarray], delta: np.ndarray) -> np.ndarray:
        """A solution vector of this layout from the named blocks of another solver's answer to
        this shape's problem (the IPOPT fallback): plan, copies (``C{c}``, present also where
        pinned) and slacks taken as they are, certificates the best ones of its positions, so
        that the next QP solve starts from that answer."""
        lay, s = self.variables, self.settings
        x = self.start_point(blocks)
        for c, row in enumerate(lay.pair_slack):
            x[row] = np.ravel(blocks.get(f"A{c}", 0.0))
        for o, row in enumerate(lay.obstacle_slack):
            x[row] = np.ravel(blocks.get(f"A_o{o}", 0.0))
        copies = np.array([np.asarray(blocks[f"C{c}"], float) for c in range(self.shape.copies)])
        copies = copies.reshape(self.shape.copies, s.dim, s.num_constrained)
        return self.vector(x, self.certify(x[lay.own], copies, delta))

    def blocks_of(self, vector: np.ndarray, params: dict[str, Any]) -> dict[str, np.ndarray]:
        """The named blocks of :func:`swarmpc.formulation.ocp.build_local`'s problem of a
        solution vector of this layout: the start of the IPOPT step when this one failed.
        Pinned copies are taken from ``params`` (Z{c})."""
        lay = self.variables
        x, pair, obstacles = self.unpack(vector)
        blocks = {"X": x[lay.X], "U": x[lay.U]}
        for c in range(self.shape.copies):
            blocks[f"C{c}"] = np.asarray(params[f"Z{c}"], float) if self.shape.pinned else x[lay.C[c]]
            blocks[f"L{c}"] = pair[c]
            if len(lay.pair_slack):
                blocks[f"A{c}"] = x[lay.pair_slack[c]][None, :]
        for o, lam in enumerate(obstacles):
            blocks[f"L_o{o}"] = lam
            if len(lay.obstacle_slack):
                blocks[f"A_o{o}"] = x[lay.obstacle_slack[o]][None, :]
        return blocks

    def blocks(self, X: np.ndarray, U: np.ndarray, copies: np.ndarray, lin: Linearisation) -> dict[str, np.ndarray]:
        """The named blocks of a plan (``X`` (s, N+1), ``U`` (m, N)), its copies (n, d, K) and
        certificates ``lin``, with the least slacks those certificates need."""
        s = self.settings
        blocks: dict[str, np.ndarray] = {"X": X, "U": U}
        soft = self.shape.pair_collision == "soft"
        for c, (C, L, A) in enumerate(self._block_keys):
            blocks[C] = copies[c]
            blocks[L] = lin.pair_lam[c]
            if soft:
                blocks[A] = np.maximum(s.d_min - lin.pair_value[c], 0.0)[None, :]
        for o, lam in enumerate(lin.obstacle_lam):
            blocks[f"L_o{o}"] = lam
            if s.collision == "soft":
                blocks[f"A_o{o}"] = np.maximum(s.d_min - lin.obstacle_value[o], 0.0)[None, :]
        return blocks


class PlanCheck:
    """The exact rebuild of a QP answer (inputs clipped to their box, states rolled out through
    the discrete dynamics) and the checks of a plan against one shape's hard claims."""

    def __init__(self, s: OCPSettings, shape: LocalShape, layout: SolutionLayout) -> None:
        self.settings, self.shape, self.layout, self.certify = s, shape, layout, layout.certify
        self.transition, self.response = rollout_matrices(s)
        lower, upper = s.model.input_bounds(s.accel, s.speed)
        self._input_box = (lower[:, None], upper[:, None])
        """The input box as columns (m, 1) (:meth:`rebuild` clips to it on every call)."""
        self._workspace = (s.lower[:, None], s.upper[:, None]) if s.lower is not None and s.upper is not None else None
        """The workspace box as columns (d, 1) (:meth:`violation` checks it on every call)."""

    def rebuild(self, state: np.ndarray, inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inputs (m, N) clipped to their box and the states (s, N+1) they drive from ``state``:
        the applied plan meets the dynamics and the input limits exactly."""
        s = self.settings
        U = np.clip(inputs, *self._input_box) if s.accel is not None else inputs.copy()
        X = (self.transition @ state + self.response @ U.ravel(order="F")).reshape(s.horizon + 1, s.model.state_dim).T
        return X, U

    def certified(
        self, params: dict[str, Any], x: np.ndarray, lin: Linearisation, pinned: np.ndarray | None,
        delta: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Linearisation, float]:
        """(X, U, copies, certificates, violation) of the rebuilt plan of primal ``x``: certified
        by ``lin``'s certificates (their values at the rebuilt positions are lower bounds on the
        distances, so a plan they clear is clear), or by the best certificates of the rebuilt
        plan if those do not clear it; ``delta``: the pairs' Delta (d, n)."""
        s, lay = self.settings, self.layout.variables
        X, U = self.rebuild(np.asarray(params["x0"], float), x.take(lay.U))
        own = X[s.model.position_rows, s.first_constrained_step:]
        copies = pinned if pinned is not None else x.take(lay.C)
        offsets = own[None] - copies
        final = self.certify.values_at(own, offsets, lin)
        violation = self.violation(X, final, params)
        if violation > 0.0:
            final = self.certify.best(own, offsets, delta)
            violation = self.violation(X, final, params)
        return X, U, copies, final, violation

    def violation(self, X: np.ndarray, lin: Linearisation, params: dict[str, Any]) -> float:
        """Largest shortfall of a plan against the hard claims (0 when all hold): separations
        (>= d_min) by the values of dual-feasible certificates (lower bounds on the distances),
        planes, workspace and speed by direct evaluation. Inputs are within their box and the
        states follow the dynamics by construction (:meth:`rebuild`)."""
        s, first = self.settings, self.settings.first_constrained_step
        gaps = [0.0]  # d_min - min(value) is max(d_min - value), bit for bit (rounding is monotone)
        if self.shape.pair_collision == "hard" and lin.pair_value.size:
            gaps.append(s.d_min - float(lin.pair_value.min()))
        if s.collision == "hard" and lin.obstacle_value.size:
            gaps.append(s.d_min - float(lin.obstacle_value.min()))
        own = X[s.model.position_rows, first:]
        for p in range(self.shape.planes):
            gaps.append(float(np.max(np.ravel(params[f"Hb{p}"]) - np.sum(np.asarray(params[f"Hn{p}"]) * own, axis=0))))
        if self._workspace is not None:
            gaps += [float((self._workspace[0] - own).max()), float((own - self._workspace[1]).max())]
        if s.speed is not None:
            gaps.append(float(np.linalg.norm(s.model.velocity(X[:, 1:].T), axis=1).max()) - s.speed)
        return max(gaps)

    def verified(self, params: dict[str, Any], X: np.ndarray, U: np.ndarray,
                 pinned: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray] | None:
        """(named blocks, solution vector) of the plan (``X`` (s, N+1), ``U`` (m, N)) as an answer
        of this shape against the ``pinned`` copies (n, d, K) when it meets the problem's
        constraints to :data:`VERIFY_TOL`: it flies the dynamics from the measured state within
        the input box, every pair keeps d_min (slack or not) and every hard claim of
        :meth:`violation` holds, by the best certificates of its positions; None otherwise. A
        repair keeps its agent's current plan this way when its solves fail."""
        s = self.settings
        X, U = np.asarray(X, float), np.asarray(U, float)
        rebuilt, clipped = self.rebuild(np.asarray(params["x0"], float), U)
        if np.max(np.abs(clipped - U), initial=0.0) > VERIFY_TOL or np.max(np.abs(rebuilt - X)) > VERIFY_TOL:
            return None
        own = X[s.model.position_rows, s.first_constrained_step:]
        lin = self.certify(own, pinned, copy_deltas(params["delta"], self.shape.copies, s.dim))
        if np.max(s.d_min - lin.pair_value, initial=0.0) > VERIFY_TOL or self.violation(X, lin, params) > VERIFY_TOL:
            return None
        blocks = self.layout.blocks(X, U, pinned, lin)
        return blocks, self.layout.vector_of(blocks, params["delta"])


CARRIED_KEPT = 256
"""Answers whose certificate rows a :class:`SequentialLocalQP` keeps (the oldest is dropped first)."""


class SequentialLocalQP:
    """One shape's local step: the certificate loop around :class:`LocalQP` (module docstring),
    then the exact rebuild and check of the plan (:class:`PlanCheck`). Returns
    :class:`NLPSolution` with the blocks the IPOPT local step returns (X, U, C{c}, L{c}, A{c},
    L_o{n}, A_o{n}), laid out by :class:`SolutionLayout`."""

    def __init__(self, s: OCPSettings, shape: LocalShape, options: QPLocalOptions,
                 backend: QPBackend | None = None) -> None:
        self.settings, self.shape, self.options = s, shape, options
        self.problem = LocalQPProblem(s, shape, options)
        self.qp = LocalQP(self.problem, backend or qp_backend(options, shape.pinned))
        self.certify = Certifier(s)
        self.layout = SolutionLayout(s, shape, self.problem.layout, self.certify)
        self.check = PlanCheck(s, shape, self.layout)
        self.proof = SeparationProof(s, self.check.transition, self.check.response, options.margin) if (
            shape.pinned and shape.pair_collision == "hard") else None
        """Decides failed repair calls that no solver can answer (:data:`PROVEN_INFEASIBLE`)."""
        self.last_record: LoopRecord | None = None
        self._failed_restarts: bytes | None = None
        """The problem (:meth:`_problem_key`) whose restarts failed last: a retry of the same
        problem from another start (a repair retried from the agent's own plan) skips them."""
        self.vector_size = self.layout.size
        """Length of a solution's ``x_vec`` (:class:`SolutionLayout`)."""
        self._carried: dict[bytes, Linearisation] = {}
        """The rows of the certificates that recent answers' vectors carry, by :meth:`_carry_key`:
        the next call of an agent starts from its last answer, whose rows :meth:`_start` would
        otherwise derive again from the same numbers."""

    # the layout's and the check's entry points that callers of the step use
    def positions(self, x: np.ndarray, pinned: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`SolutionLayout.positions`."""
        return self.layout.positions(x, pinned)

    def verified(self, params: dict[str, Any], X: np.ndarray, U: np.ndarray,
                 pinned: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray] | None:
        """:meth:`PlanCheck.verified`."""
        return self.check.verified(params, X, U, pinned)

    # the certificate loop
    def _carry_key(self, vector: np.ndarray, delta: np.ndarray, pinned: np.ndarray | None) -> bytes:
        """What the rows of a solution vector's certificates depend on: the vector, the pairs'
        Delta and the pinned copies (the shape fixes every length)."""
        pinned_bytes = b"" if pinned is None else np.ascontiguousarray(pinned, float).tobytes()
        return vector.tobytes() + np.ascontiguousarray(delta, float).tobytes() + pinned_bytes

    def _carry(self, vector: np.ndarray, delta: np.ndarray, pinned: np.ndarray | None, lin: Linearisation) -> None:
        """Keep ``lin``, the rows of the certificates ``vector`` carries, for :meth:`_start`."""
        if len(self._carried) >= CARRIED_KEPT:
            self._carried.pop(next(iter(self._carried)))  # the oldest
        self._carried[self._carry_key(vector, delta, pinned)] = lin

    def _start(
        self, guess: dict[str, np.ndarray] | np.ndarray, delta: np.ndarray, pinned: np.ndarray | None,
    ) -> tuple[np.ndarray, Linearisation]:
        """The QP's start and first certificates: those a solution vector carries, else the best
        certificates of the guessed blocks."""
        if isinstance(guess, np.ndarray):
            primal, pair, obstacles = self.layout.unpack(guess)
            x = primal.copy()
            rows = self._carried.get(self._carry_key(guess, delta, pinned))
            if rows is not None:  # the certificates as the vector holds them, their rows as derived before
                return x, Linearisation(pair, rows.pair_normal, rows.pair_constant, rows.pair_value, obstacles,
                                        rows.obstacle_normal, rows.obstacle_constant, rows.obstacle_value)
            own, copies = self.layout.positions(x, pinned)
            return x, self.certify.rows_at(own, own[None] - copies, delta, pair, obstacles)
        x = self.layout.start_point(guess)
        return x, self._certified(x, pinned, delta)[0]

    def _certified(self, x: np.ndarray, pinned: np.ndarray | None,
                   delta: np.ndarray) -> tuple[Linearisation, np.ndarray, np.ndarray]:
        """(best certificates, own positions (d, K), offsets own - copies (n, d, K)) of a primal
        vector; ``delta``: the pairs' Delta (d, n)."""
        own, copies = self.layout.positions(x, pinned)
        offsets = own[None] - copies
        return self.certify.best(own, offsets, delta), own, offsets

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, pinned: np.ndarray | None = None,
        slack_caps: dict[int, float] | None = None, y: np.ndarray | None = None, restarts: bool = True,
        rounds: int | None = None,
    ) -> NLPSolution:
        """The local step from ``guess`` (blocks or a vector of this layout); ``pinned`` (n, d, K):
        the copies' fixed positions; ``slack_caps``: pair slot -> upper bound of its slack;
        ``y``: the QP duals of a previous solve of this shape (warm start); ``restarts`` False: a
        failed first loop is the answer (a caller that has a cheaper way out than two more loops);
        ``rounds``: certificate rounds per loop at most (None: ``max_rounds``).

        If the first QP is infeasible (the guess's certificates ask for a separation the
        dynamics cannot reach, e.g. a guess that cuts through a pinned neighbour's plan), the
        loop restarts once from the certificates of each fallback plan (coasting, braking). A
        hard repair call that fails is reported :data:`PROVEN_INFEASIBLE` when
        :class:`SeparationProof` shows that no plan can keep clear of the pinned copies; such a
        call skips the restarts, which no certificates could make feasible, and so does a call of
        the very problem whose restarts failed last (a repair retried from another start)."""
        began = time.perf_counter()
        delta = copy_deltas(params["delta"], self.shape.copies, self.settings.dim)
        targets = self.problem.copy_targets(params)
        x, lin = self._start(guess, delta, pinned)
        tally: list[Any] = [0, 0, 0.0, 0]  # rounds, QP iterations, solver time, exact answers
        cap = self.options.max_rounds if rounds is None else min(rounds, self.options.max_rounds)
        call = (params, targets, delta, tally, cap)
        answer, x, lin, converged = self._loop(call, x, lin, y, (pinned, slack_caps))
        proven = (not answer.solved and self.proof is not None and pinned is not None
                  and self.proof.infeasible(params["x0"], pinned, delta))
        restart = restarts and not answer.solved and tally[0] == 1 and not proven  # none help a proven call
        key = self._problem_key(params, pinned, slack_caps) if restart else None
        for plan in self._fallback_plans(params) if restart and key != self._failed_restarts else []:
            start = x.copy()
            start[self.problem.layout.X] = plan
            lin = self._certified(start, pinned, delta)[0]
            answer, x, lin, converged = self._loop(call, start, lin, None, (pinned, slack_caps))
            if answer.solved:
                break
        if restart and not answer.solved:
            self._failed_restarts = key
        status = PROVEN_INFEASIBLE if proven else f"qp_{answer.status.replace(' ', '_')}"
        wall = time.perf_counter() - began
        self.last_record = LoopRecord(tally[0], tally[1], tally[2], wall, converged, tally[3])
        if not answer.solved:
            return self._failed(x, status, wall, tally[1])
        return self._result(params, x, lin, answer.y, pinned, wall, tally[0], converged, delta, targets)

    def _problem_key(
        self, params: dict[str, Any], pinned: np.ndarray | None, slack_caps: dict[int, float] | None,
    ) -> bytes:
        """What the restarts' QPs depend on besides the fallback plans (which follow from the
        measured state): the cost (its linear term, rho and the owner weight), the measured
        state, the pinned copies, the pairs' Delta, the planes and the slack caps."""
        parts = [self.problem.linear_cost(params), np.array([params["rho"], params["owner_weight"]], float),
                 np.asarray(params["x0"], float),
                 np.asarray(params["delta"], float), np.zeros(0) if pinned is None else pinned,
                 np.array(sorted((slack_caps or {}).items()), float).ravel()]
        parts += [np.asarray(params[f"{name}{p}"], float) for p in range(self.shape.planes) for name in ("Hn", "Hb")]
        return b"".join(np.ascontiguousarray(part, float).tobytes() for part in parts)

    def _loop(
        self, call: Call, x: np.ndarray, lin: Linearisation, y: np.ndarray | None,
        fixed: tuple[np.ndarray | None, dict[int, float] | None],
    ) -> tuple[QPAnswer, np.ndarray, Linearisation, bool]:
        """The certificate loop from (x, lin), ``call``'s rounds at most, with ``fixed`` = (pinned
        copies, slack caps): (last answer, plan, its best certificates, converged)."""
        params, targets, delta, tally, rounds = call
        pinned, slack_caps = fixed
        converged = False
        q = self.problem.linear_cost(params, targets)
        for _ in range(rounds):
            answer = self.qp.solve(params, lin, x, y, pinned, slack_caps, q)
            tally[0] += 1
            tally[1] += answer.iterations
            tally[2] += answer.solver_time
            tally[3] += answer.exact
            if not answer.solved:
                break
            new, own, offsets = self._certified(answer.x, pinned, delta)
            moved = float(np.abs(answer.x - x).max()) if x.size else 0.0
            x, y = answer.x, answer.y
            converged = moved <= self.options.plan_tol or self._settled(lin, new, own, offsets)
            lin = new
            if converged:
                break
        return answer, x, lin, converged

    def _fallback_plans(self, params: dict[str, Any]) -> list[np.ndarray]:
        """State trajectories (s, N+1) to take certificates from when the guess's fail: the
        measured state coasting (no input), and the model's braking plan
        (:meth:`~swarmpc.model.agent_model.AgentModel.braking_inputs`) within the input box."""
        s, model = self.settings, self.settings.model
        state = np.asarray(params["x0"], float)
        coast, _ = self.check.rebuild(state, np.zeros((model.input_dim, s.horizon)))
        brake = model.rollout(state, model.braking_inputs(state, s.horizon, s.accel)).T
        return [coast, brake]

    def _settled(self, old: Linearisation, new: Linearisation, own: np.ndarray, offsets: np.ndarray) -> bool:
        """True when the certificates of the rows the last QP held at (or near) their bound
        changed less than the tolerance. Rows it left clear stay clear under the new
        certificates (their exact value can only be larger), so only these can move the answer.
        ``own``: the plan's positions (d, K), ``offsets``: own - copies (n, d, K)."""
        o, s = self.options, self.settings
        bound = s.d_min + o.margin + o.active_band
        pair = add_rows(old.pair_normal * offsets) - old.pair_constant
        change = _row_change(old.pair_normal, new.pair_normal, pair <= bound)
        if len(old.obstacle_normal) and change <= o.certificate_tol:  # no obstacles: no rows to compare
            obstacle = add_rows(old.obstacle_normal * own) - old.obstacle_constant
            change = max(change, _row_change(old.obstacle_normal, new.obstacle_normal, obstacle <= bound))
        return change <= o.certificate_tol

    def _failed(self, x: np.ndarray, status: str, wall: float, iterations: int) -> NLPSolution:
        blocks = {"X": x[self.problem.layout.X], "U": x[self.problem.layout.U]}
        return NLPSolution(x=blocks, x_vec=np.zeros(0), lam_x=np.zeros(0), lam_g=np.zeros(self.problem.A.shape[0]),
                           cost=np.inf, success=False, status=status,
                           iterations=iterations, solve_time=wall)

    def _result(
        self, params: dict[str, Any], x: np.ndarray, lin: Linearisation, y: np.ndarray, pinned: np.ndarray | None,
        wall: float, rounds: int, converged: bool, delta: np.ndarray,
        targets: tuple[np.ndarray, np.ndarray] | None,
    ) -> NLPSolution:
        """The answer of the loop's plan ``x`` and certificates ``lin``: the rebuilt plan as
        :meth:`PlanCheck.certified` certifies it, its cost, and the solution vector of ``x`` and
        ``lin`` (whose rows are kept for a call that starts from it)."""
        X, U, copies, final, violation = self.check.certified(params, x, lin, pinned, delta)
        blocks = self.layout.blocks(X, U, copies, final)
        status = "solved" if converged else "max_rounds"
        if violation > 0.0:
            status = f"unsafe_{violation:.1e}"
        stacked = None if targets is None else (np.ascontiguousarray(copies, float), *targets)
        vector = self.layout.vector(x, lin)
        self._carry(vector, delta, pinned, lin)  # lin: the rows of the vector's certificates at x
        return NLPSolution(
            x=blocks, x_vec=vector,
            lam_x=np.zeros(0), lam_g=y, cost=stacked_objective(blocks, params, self.settings, stacked),
            success=violation <= 0.0, status=status,
            iterations=rounds, solve_time=wall,
        )


class QPLocalLadder:
    """The QP local steps of one agent set, one per shape, built on first use: the interface of
    :class:`swarmpc.solvers.admm.LocalSolverLadder` (``solve(params, guess, fixed, copies=...,
    planes=..., duals=...) -> NLPSolution``) so that it can stand in for it.

    Only free copies are supported (``dynamic_copies=False``, the default ADMM configuration).
    ``fixed`` may pin every copy (``C{c}``, a repair pass: the copies become constants) and the
    pair slacks (``A{c}``, an upper bound; the hard form has none); other blocks are refused.
    ``duals``: (unused, QP multipliers) of the previous solve of the same shape. A lock guards
    the built solvers (stateful OSQP objects) under threads; pickling keeps the recipe only and
    a worker process builds its own. ``options`` None: those of ``settings.qp`` (a scenario's
    ``solver.qp`` section, :meth:`QPLocalOptions.from_config`). ``backend``: the QP solver of
    every shape, made from the options; None: the one the options name for the shape
    (:func:`qp_backend`).
    """

    def __init__(self, settings: OCPSettings, pair_collision: str | None = None,
                 options: QPLocalOptions | None = None,
                 backend: Callable[[QPLocalOptions], QPBackend] | None = None) -> None:
        self.settings = settings
        self.pair_collision = pair_collision or settings.collision
        self.options = options or QPLocalOptions.from_config(settings.qp)
        self.backend = backend
        self._built: dict[LocalShape, SequentialLocalQP] = {}
        self._lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        return {"settings": self.settings, "pair_collision": self.pair_collision, "options": self.options,
                "backend": self.backend}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(**state)  # type: ignore[misc]

    def stepper(self, shape: LocalShape) -> SequentialLocalQP:
        """The built local step of ``shape`` (built now on first use)."""
        if shape not in self._built:
            backend = self.backend(self.options) if self.backend is not None else None
            self._built[shape] = SequentialLocalQP(self.settings, shape, self.options, backend)
        return self._built[shape]

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, fixed: dict[str, Any] | None = None,
        *, copies: int, planes: int = 0, duals: tuple[np.ndarray, np.ndarray] | None = None,
        restarts: bool = True, rounds: int | None = None,
    ) -> NLPSolution:
        """One local step; see the class docstring for ``fixed`` and ``duals``, and
        :meth:`SequentialLocalQP.solve` for ``restarts`` and ``rounds``."""
        fixed = fixed or {}
        unknown = [key for key in fixed if key[:1] not in ("C", "A") or not key[1:].isdigit()]
        if unknown:
            raise NotImplementedError(f"the QP local step cannot pin {unknown} (free copies and pair slacks only)")
        pinned = None
        if any(key.startswith("C") for key in fixed):
            pinned = self.pinned_copies(fixed, copies)
        caps = {c: float(np.max(fixed[f"A{c}"])) for c in range(copies)
                if f"A{c}" in fixed} if fixed and self.pair_collision == "soft" else {}
        with self._lock:
            shape = LocalShape(copies, planes, pinned is not None, self.pair_collision)
            stepper = self.stepper(shape)
            if isinstance(guess, np.ndarray) and guess.size != stepper.vector_size:
                guess = self._layout_of(shape, guess).layout.blocks_of(guess, params)
            y = duals[1] if duals is not None and duals[1].size == stepper.problem.A.shape[0] else None
            return stepper.solve(params, guess, pinned, caps, y, restarts=restarts, rounds=rounds)

    def _layout_of(self, shape: LocalShape, vector: np.ndarray) -> SequentialLocalQP:
        """The built step whose solution vectors ``vector`` is laid out for: ``shape``'s, or that
        of the same problem with the copies free instead of pinned or the other way round (a
        repair pass that starts from the agent's last answer)."""
        stepper = self.stepper(shape)
        if vector.size == stepper.vector_size:
            return stepper
        sibling = self._built.get(LocalShape(shape.copies, shape.planes, not shape.pinned, shape.pair_collision))
        if sibling is None or vector.size != sibling.vector_size:
            raise ValueError("a guess vector must come from a QP local step of the same problem")
        return sibling

    def verified(
        self, params: dict[str, Any], point: dict[str, np.ndarray], fixed: dict[str, Any], *, copies: int,
        planes: int = 0,
    ) -> tuple[dict[str, np.ndarray], np.ndarray] | None:
        """:meth:`SequentialLocalQP.verified` of the plan in ``point`` (X, U) against the copies
        ``fixed`` pins (``C{c}``), by the pinned shape's step."""
        pinned = self.pinned_copies(fixed, copies)
        with self._lock:
            stepper = self.stepper(LocalShape(copies, planes, True, self.pair_collision))
            return stepper.verified(params, point["X"], point["U"], pinned)

    def pinned_copies(self, fixed: dict[str, Any], copies: int) -> np.ndarray:
        """The copies' positions (n, d, K) that ``fixed`` pins (``C{c}``)."""
        pinned = np.array([np.asarray(fixed[f"C{c}"], float) for c in range(copies)])
        return pinned.reshape(copies, self.settings.dim, self.settings.num_constrained)

    def guess_blocks(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, *, copies: int, planes: int = 0,
        pinned: bool = False,
    ) -> dict[str, np.ndarray]:
        """The named blocks of a guess this ladder accepts (a solution vector of the problem, free
        or ``pinned`` copies, is unpacked with its certificates; blocks are returned as they
        are): the start another solver takes when this one failed."""
        if not isinstance(guess, np.ndarray):
            return guess
        with self._lock:
            stepper = self._layout_of(LocalShape(copies, planes, pinned, self.pair_collision), guess)
            return stepper.layout.blocks_of(guess, params)

    def solution_vector(
        self, blocks: dict[str, np.ndarray], params: dict[str, Any], *, copies: int, planes: int = 0,
        pinned: bool = False,
    ) -> np.ndarray:
        """A solution vector of this ladder's problem from the named blocks of another solver's
        answer (see :meth:`SolutionLayout.vector_of`), to be passed back as a later guess."""
        with self._lock:
            stepper = self.stepper(LocalShape(copies, planes, pinned, self.pair_collision))
            return stepper.layout.vector_of(blocks, params["delta"])
