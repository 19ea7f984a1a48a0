"""One agent's local problem of consensus ADMM in a swarm with cars: its own trajectory and copies of
its neighbours' footprint poses, kept apart by the full OBCA.

The point-agent ADMM (:func:`swarmpc.formulation.ocp.build_local`) agrees on positions; a car's
footprint turns, so in a swarm with cars the agents agree on *poses*. Agent i's consensus block is
the pose of its footprint at the steps 1..N: ``(x, y, theta)`` for a car (3 rows), the position for
a point agent (2 rows, its box never turns). Agent i holds one copy per neighbour j, a free
variable ``C{s}`` of j's block's shape (slot s in the neighbour order), and keeps its own footprint
d_min away from the copy's at every step the pair constrains: the full OBCA of
:func:`~swarmpc.formulation.footprint_certificates.footprint_pair_rows` when either is a car, the
point form of :func:`~swarmpc.formulation.ocp.add_pair_avoidance` between two point agents. Its
static obstacles are its own rows, as in the centralised problem
(:mod:`swarmpc.formulation.footprint_ocp`).

Names: the agent's blocks have the empty tag (``X``, ``U``, ``x0``, ``goal``, ``L_o{n}``, ...);
per slot s: copy ``C{s}``, certificates ``Li{s}`` (own footprint) and ``Lj{s}`` (the copy's) or,
between point agents, ``Lp{s}``, soft slack ``Ap{s}``. Consensus parameters: ``rho`` (1, 1),
``Z`` and ``Y`` (own block), ``Z{s}`` and ``Y{s}`` per slot; the cost adds
``rho / 2 ||v - Z + Y / rho||^2`` over each copy v and the same with ``rho * owner_weight`` (a
build argument, default 1) over the own block (the scaled form of consensus ADMM: Y is the
block's multiplier). A slot's neighbour size is the parameter ``S{s}`` (:func:`slot_size`), so
one problem serves every neighbour of the same kind (:class:`NeighbourKind`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import casadi as ca
import numpy as np

from swarmpc.formulation.footprint_certificates import footprint_pair_rows
from swarmpc.formulation.footprint_ocp import FootprintAgent, _add_car, _impose, _slack
from swarmpc.formulation.nlp import CompiledNLP, ProblemBuilder, builds_casadi
from swarmpc.formulation.ocp import WARM_START_OPTIONS, add_agent, add_pair_avoidance, ipopt_options

__all__ = ["NeighbourKind", "block_rows", "build_footprint_local", "consensus_block", "pair_first_step", "slot_size"]


def block_rows(agent: FootprintAgent) -> int:
    """Rows of the agent's consensus block: 3 for a car (x, y, theta), 2 for a point agent."""
    return 3 if agent.oriented else 2


def consensus_block(agent: FootprintAgent, states: np.ndarray) -> np.ndarray:
    """The consensus block (rows, N) of a state trajectory (N+1, n): its poses at steps 1..N."""
    poses = agent.poses(np.asarray(states, float)[1:])
    return poses[:, : block_rows(agent)].T


class NeighbourKind(NamedTuple):
    """What a local problem's shape needs of a neighbour: car or point agent, and its first
    constrained step (a pair is constrained from the earlier of the two agents')."""

    oriented: bool
    first_step: int

    @classmethod
    def of(cls, agent: FootprintAgent) -> NeighbourKind:
        return cls(agent.oriented, agent.settings.first_constrained_step)


def pair_first_step(own: FootprintAgent, other: FootprintAgent) -> int:
    """The pair's first constrained step: the earlier of the two agents'."""
    return min(own.settings.first_constrained_step, other.settings.first_constrained_step)


def slot_size(own: FootprintAgent, other: FootprintAgent) -> np.ndarray:
    """The value of a slot's size parameter ``S{s}`` (2, 1) for neighbour ``other``."""
    if own.oriented or other.oriented:
        return other.size.reshape(2, 1)
    return (own.body + other.body).reshape(2, 1)


def _add_slot(
    builder: ProblemBuilder, slot: int, own: FootprintAgent, other: NeighbourKind, X: ca.SX, rho: ca.SX,
) -> None:
    """Copy ``C{slot}`` of a neighbour of kind ``other``, its consensus term and the pair's OBCA
    rows; the neighbour's size is the parameter ``S{slot}`` (2, 1): its (length, width) when
    either is a car, the pair's box half-size b_i + b_j between point agents."""
    s = own.settings
    N, first = s.horizon, min(s.first_constrained_step, other.first_step)
    rows = 3 if other.oriented else 2
    C = builder.variable(f"C{slot}", rows, N)
    Z = builder.parameter(f"Z{slot}", rows, N)
    Y = builder.parameter(f"Y{slot}", rows, N)
    size = builder.parameter(f"S{slot}", 2, 1)
    builder.cost += 0.5 * rho * ca.sumsqr(C - Z + Y / rho)
    steps = N + 1 - first
    copy = C[:, first - 1:]
    if not (own.oriented or other.oriented):
        add_pair_avoidance(builder, f"p{slot}", X[s.model.position_rows, first:] - copy, size, s)
        return
    lam_i = builder.variable(f"Li{slot}", 4, steps, 0.0, np.inf)
    lam_j = builder.variable(f"Lj{slot}", 4, steps, 0.0, np.inf)
    slack = _slack(builder, f"p{slot}", steps, s)
    pose = copy if other.oriented else ca.vertcat(copy, ca.DM.zeros(1, steps))
    pair = footprint_pair_rows(own.casadi_poses(X[:, first:]), own.size, pose, size, lam_i, lam_j, s.d_min, slack)
    _impose(builder, f"p{slot}", pair, slack, s.kappa)


@builds_casadi
def build_footprint_local(
    own: FootprintAgent, neighbours: Sequence[NeighbourKind], options: dict[str, Any] | None = None,
    owner_weight: float = 1.0,
) -> CompiledNLP:
    """Agent ``own``'s local problem against copies of neighbours of the given kinds (names in the
    module docstring), built once per sequence of kinds (sizes are parameters); IPOPT with the
    agent's ``ipopt`` section (the local tolerances) and ``options`` on top, and a warm-start
    variant."""
    builder = ProblemBuilder()
    rho = builder.parameter("rho", 1, 1)
    if own.oriented:
        X = _add_car(builder, "", own)
    else:
        X = add_agent(builder, "", own.obstacle_settings)[0]
    Z = builder.parameter("Z", block_rows(own), own.settings.horizon)
    Y = builder.parameter("Y", block_rows(own), own.settings.horizon)
    block = own.casadi_poses(X[:, 1:])[: block_rows(own), :]
    rho_own = rho * owner_weight
    builder.cost += 0.5 * rho_own * ca.sumsqr(block - Z + Y / rho_own)
    for slot, other in enumerate(neighbours):
        _add_slot(builder, slot, own, other, X, rho)
    kinds = "".join("c" if n.oriented else "p" for n in neighbours)
    label = f"footprint_local_{'c' if own.oriented else 'p'}_{kinds or 'alone'}"
    return builder.build(label, "ipopt", {**ipopt_options(own.settings.ipopt, local=True), **(options or {})},
                         warm_options=WARM_START_OPTIONS)
