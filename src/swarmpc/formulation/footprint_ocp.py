"""The centralised OCP of a planar swarm whose agents have their own models and footprints: cars
(rotating rectangles) and point agents (axis-aligned boxes) in one problem.

:func:`swarmpc.formulation.ocp.build_centralized` holds one model for every agent and keeps each
pair's centres out of an axis-aligned box of half-size Delta_ij. That form is exact for boxes that
never turn; a car's rectangle turns with its heading, so a pair with a car is certified by the full
OBCA between the two footprints (:mod:`swarmpc.formulation.footprint_certificates`): the condition
is the dual of the distance between the two polygons at their current poses, so it holds iff the
footprints themselves are d_min apart, whatever their headings (reference formulation: Zhang,
Liniger, Borrelli 2017, the full-dimensional case). A car's bounding square would also do as a
box, but it blocks every gap narrower than the car's length, which the car passes by aligning.

Rows, per agent i (tag ``{i}``), for the steps k = first..N with ``first`` the model's
:attr:`~swarmpc.model.agent_model.AgentModel.first_constrained_step`:

* trajectory and cost as :func:`~swarmpc.formulation.ocp.add_agent` builds them for the agent's
  own settings: parameters ``x0{i}``, ``goal{i}`` (a goal STATE: [x, y, theta, v] for a car, its
  heading taken as given, nothing wrapped), variables ``X{i}``, ``U{i}``, rows ``init{i}``,
  ``dyn{i}``, ``speed{i}``, and the quadratic cost on the state error and the input (the
  workspace bounds the model's position rows: a car's reference point, not its whole footprint);
* against static obstacle n: a point agent's centre against the obstacle grown by its body (rows
  of ``add_agent`` on :meth:`~swarmpc.formulation.ocp.OCPSettings.for_body`, certificate
  ``L{i}_o{n}``, slack ``A{i}_o{n}``), as in ``build_centralized``; a car's footprint against the obstacle itself
  (:func:`~swarmpc.formulation.footprint_certificates.footprint_polytope_rows`): certificates
  ``L{i}_o{n}`` (4, K) of the footprint and ``Lo{n}_{i}`` (rows of G, K) of the obstacle, slack
  ``A{i}_o{n}`` (1, K) in the soft form, rows ``sep{i}_o{n}``, ``couple{i}_o{n}``,
  ``norm{i}_o{n}``. Growing by a box is exact only for an unturned box, hence the full rows.

Per pair i < j (tag ``{i}_{j}``), from the earlier of the two agents' first constrained steps:
a step where either position depends on the inputs needs the rows (a car's position at k = 1
moves with its first input even when an Euler point agent's is fixed by the measured state), and
a step where both are fixed has no free variable to constrain:

* both point agents: the point form of ``build_centralized``
  (:func:`~swarmpc.formulation.ocp.add_pair_avoidance`): certificate ``L{i}_{j}`` (2, K), slack
  ``A{i}_{j}``, Delta_ij = b_i + b_j from the parameter ``delta`` (2, P), one column per
  point-only pair in the order of :func:`~swarmpc.formulation.ocp.agent_pairs`. A swarm of point
  agents therefore builds exactly the problem of ``build_centralized`` (same blocks, same order);
* at least one car: the full OBCA between the two footprints
  (:func:`~swarmpc.formulation.footprint_certificates.footprint_pair_rows`), a point agent's
  footprint being its axis-aligned box (heading 0, centred on its position, size 2 b_i):
  certificates ``L{i}_{j}`` (4, K) of P_i and ``L{j}_{i}`` (4, K) of P_j, slack ``A{i}_{j}``
  (1, K) in the soft form, rows ``sep{i}_{j}``, ``couple{i}_{j}``, ``norm{i}_{j}``.

Every certificate is bounded below by 0 and every slack by 0 with kappa times its sum in the cost;
the hard form holds sep >= d_min, couple = 0, norm <= 1, the soft form sep + alpha >= d_min,
couple = 0, norm = 1. ``L{a}_{b}`` is always the multiplier of a's polygon in the certificate of
the pair (a, b), so the names read the same way for pairs and obstacles, and every certificate and
slack block starts with ``L`` or ``A``, as in ``build_centralized``. Initial values:
:func:`footprint_guess_blocks`, the closed-form best certificates of guessed poses.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import casadi as ca
import numpy as np

from swarmpc.formulation.footprint_certificates import (
    CertificateRows,
    PolytopeFootprintCertifier,
    footprint_pair_rows,
    footprint_polytope_rows,
    rectangle_pair_certificates,
)
from swarmpc.formulation.nlp import CompiledNLP, ProblemBuilder, builds_casadi
from swarmpc.formulation.ocp import (
    OCPSettings,
    add_agent,
    add_pair_avoidance,
    add_trajectory,
    agent_pairs,
    ipopt_options,
    pair_tag,
    quadratic_cost,
)

__all__ = [
    "FootprintAgent",
    "FootprintSwarm",
    "OrientedBody",
    "build_footprint_centralized",
    "footprint_guess_blocks",
]


@runtime_checkable
class OrientedBody(Protocol):
    """A model whose body is a rectangle that turns with the agent (the car): its size, and the
    pose of the rectangle's centre from states, in numpy and CasADi."""

    @property
    def footprint(self) -> tuple[float, float]:
        """(length, width) [m]."""
        ...

    def pose(self, states: np.ndarray) -> np.ndarray:
        """Poses (..., 3) [x_c, y_c, theta] of states (..., n)."""
        ...

    def casadi_pose(self, X: Any) -> Any:
        """Poses (3, K) of the CasADi states X (n, K)."""
        ...


@dataclass(frozen=True, eq=False)
class FootprintAgent:
    """One agent of a :class:`FootprintSwarm`: its OCP settings (its own model) and, for a point
    agent, its body half-size.

    Parameters
    ----------
    settings
        The agent's settings; ``settings.model`` decides its kind: an :class:`OrientedBody` (a
        car) carries its own footprint, any other planar model is a point agent.
    half_size
        A point agent's body half-size (b_x, b_y) >= 0 [m]: its footprint is the axis-aligned box
        of size 2 b centred on its position. None for a car (its model gives its footprint).
    """

    settings: OCPSettings
    half_size: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.settings.dim != 2:
            raise ValueError(f"footprint agents move in the plane (dim 2), got dim {self.settings.dim}")
        if self.oriented:
            if self.half_size is not None:
                raise ValueError("a car's footprint comes from its model: give no half_size")
            return
        if self.half_size is None:
            raise ValueError("a point agent needs its body half_size (b_x, b_y)")
        half = np.asarray(self.half_size, float)
        if half.shape != (2,) or not np.all(np.isfinite(half)) or np.any(half < 0):
            raise ValueError(f"half_size must be two finite values >= 0, got {self.half_size!r}")
        object.__setattr__(self, "half_size", (float(half[0]), float(half[1])))

    @property
    def oriented(self) -> bool:
        """True for a car (a footprint that turns with the agent)."""
        return isinstance(self.settings.model, OrientedBody)

    @property
    def body(self) -> np.ndarray:
        """A point agent's body half-size (2,); a ValueError for a car, whose body turns."""
        if self.half_size is None:
            raise ValueError("a car has no axis-aligned body: its footprint turns with it")
        return np.array(self.half_size, float)

    @property
    def size(self) -> np.ndarray:
        """(length, width) (2,) of the footprint: the car's, or 2 x a point agent's half-size."""
        model = self.settings.model
        if isinstance(model, OrientedBody):
            return np.array(model.footprint, float)
        return 2.0 * self.body

    @property
    def obstacle_settings(self) -> OCPSettings:
        """The settings whose obstacles the agent's rows use: a point agent's grown by its body
        (:meth:`OCPSettings.for_body`), a car's as they are (its footprint rows hold the body)."""
        if self.oriented:
            return self.settings
        return self.settings.for_body(self.body)

    def poses(self, states: np.ndarray) -> np.ndarray:
        """Footprint poses (..., 3) of states (..., n): a car's, or (position, 0) for a point agent."""
        model = self.settings.model
        if isinstance(model, OrientedBody):
            return model.pose(states)
        position = model.position(np.asarray(states, float))
        return np.concatenate([position, np.zeros((*position.shape[:-1], 1))], axis=-1)

    def casadi_poses(self, X: Any) -> Any:
        """Footprint poses (3, K) of the CasADi states X (n, K)."""
        model = self.settings.model
        if isinstance(model, OrientedBody):
            return model.casadi_pose(X)
        return ca.vertcat(X[model.position_rows, :], ca.DM.zeros(1, X.shape[1]))


@dataclass(frozen=True, eq=False)
class FootprintSwarm:
    """The agents of one centralised footprint OCP, in order (agent i is ``agents[i]``).

    All agents share the time grid (``horizon``, ``dt``) and the collision settings
    (``collision``, ``d_min``, ``kappa``), which the pair rows use; models, weights, limits and
    obstacles may differ per agent.
    """

    agents: tuple[FootprintAgent, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "agents", tuple(self.agents))
        if not self.agents:
            raise ValueError("a swarm needs at least one agent")
        first = self.agents[0].settings
        for i, agent in enumerate(self.agents[1:], start=1):
            for name in ("horizon", "dt", "collision", "d_min", "kappa"):
                if getattr(agent.settings, name) != getattr(first, name):
                    raise ValueError(f"agents share {name}: agent {i} has {getattr(agent.settings, name)!r}, "
                                     f"agent 0 has {getattr(first, name)!r}")

    @property
    def num_agents(self) -> int:
        return len(self.agents)

    @property
    def settings(self) -> OCPSettings:
        """Agent 0's settings: the shared horizon, dt and collision settings."""
        return self.agents[0].settings

    @property
    def pairs(self) -> list[tuple[int, int]]:
        """Every pair (i, j), i < j (:func:`~swarmpc.formulation.ocp.agent_pairs`)."""
        return agent_pairs(self.num_agents)

    def is_point_pair(self, i: int, j: int) -> bool:
        """True when neither agent is a car: the pair takes the point form."""
        return not (self.agents[i].oriented or self.agents[j].oriented)

    @property
    def point_pairs(self) -> list[tuple[int, int]]:
        """The point-only pairs, in the order of the columns of the parameter ``delta``."""
        return [(i, j) for i, j in self.pairs if self.is_point_pair(i, j)]

    @property
    def point_deltas(self) -> np.ndarray:
        """(2, P) Delta_ij = b_i + b_j of every point-only pair: the value of ``delta``."""
        columns = [self.agents[i].body + self.agents[j].body for i, j in self.point_pairs]
        return np.array(columns, float).reshape(-1, 2).T

    def pair_first_step(self, i: int, j: int) -> int:
        """The pair's first constrained step: the earlier of the two agents'."""
        return min(self.agents[i].settings.first_constrained_step, self.agents[j].settings.first_constrained_step)


def _impose(builder: ProblemBuilder, tag: str, rows: CertificateRows, slack: Any | None, kappa: float) -> None:
    """Add the rows of one footprint certificate under ``{name}{tag}`` and price the slack."""
    for name, expression, lower, upper in rows.blocks():
        builder.constrain(f"{name}{tag}", expression, lower, upper)
    if slack is not None:
        builder.cost += kappa * ca.sum2(slack)


def _slack(builder: ProblemBuilder, tag: str, steps: int, s: OCPSettings) -> Any | None:
    """The soft form's slack ``A{tag}`` (1, steps) >= 0, or None in the hard form."""
    return builder.variable(f"A{tag}", 1, steps, 0.0, np.inf) if s.collision == "soft" else None


def _add_car(builder: ProblemBuilder, tag: str, agent: FootprintAgent) -> ca.SX:
    """A car: trajectory, goal and cost as ``add_agent``, and its footprint against every static
    obstacle; returns X."""
    s = agent.settings
    X, U = add_trajectory(builder, tag, s)
    goal = builder.parameter(f"goal{tag}", s.model.state_dim)
    builder.cost += quadratic_cost(X, U, goal, s)
    first = s.first_constrained_step
    pose, steps = agent.casadi_poses(X[:, first:]), s.horizon + 1 - first
    for n, (G, g) in enumerate(s.obstacles):
        lam_car = builder.variable(f"L{tag}_o{n}", 4, steps, 0.0, np.inf)
        lam_obstacle = builder.variable(f"Lo{n}_{tag}", G.shape[0], steps, 0.0, np.inf)
        slack = _slack(builder, f"{tag}_o{n}", steps, s)
        rows = footprint_polytope_rows(pose, agent.size, G, g, lam_car, lam_obstacle, s.d_min, slack)
        _impose(builder, f"{tag}_o{n}", rows, slack, s.kappa)
    return X


def _add_footprint_pair(
    builder: ProblemBuilder, swarm: FootprintSwarm, i: int, j: int, X_i: ca.SX, X_j: ca.SX
) -> None:
    """The full OBCA between the footprints of agents i and j (at least one a car)."""
    s, first = swarm.settings, swarm.pair_first_step(i, j)
    steps = s.horizon + 1 - first
    tag = pair_tag(i, j)
    lam_ij = builder.variable(f"L{i}_{j}", 4, steps, 0.0, np.inf)
    lam_ji = builder.variable(f"L{j}_{i}", 4, steps, 0.0, np.inf)
    slack = _slack(builder, tag, steps, s)
    agent_i, agent_j = swarm.agents[i], swarm.agents[j]
    rows = footprint_pair_rows(agent_i.casadi_poses(X_i[:, first:]), agent_i.size,
                               agent_j.casadi_poses(X_j[:, first:]), agent_j.size, lam_ij, lam_ji, s.d_min, slack)
    _impose(builder, tag, rows, slack, s.kappa)


@builds_casadi
def build_footprint_centralized(swarm: FootprintSwarm, options: dict[str, Any] | None = None) -> CompiledNLP:
    """The global OCP of ``swarm`` (the rows and names of the module docstring), built once.

    Parameters: ``delta`` (2, P) (:attr:`FootprintSwarm.point_deltas`), and ``x0{i}``,
    ``goal{i}`` per agent. IPOPT's options are agent 0's ``ipopt`` section with ``options`` on top.
    """
    builder = ProblemBuilder()
    half = builder.parameter("delta", 2, len(swarm.point_pairs))
    trajectories = []
    for i, agent in enumerate(swarm.agents):
        if agent.oriented:
            trajectories.append(_add_car(builder, str(i), agent))
        else:
            trajectories.append(add_agent(builder, str(i), agent.obstacle_settings)[0])
    column = 0
    for i, j in swarm.pairs:
        if not swarm.is_point_pair(i, j):
            _add_footprint_pair(builder, swarm, i, j, trajectories[i], trajectories[j])
            continue
        first, rows = swarm.pair_first_step(i, j), swarm.agents[i].settings.model.position_rows
        offsets = trajectories[i][rows, first:] - trajectories[j][swarm.agents[j].settings.model.position_rows, first:]
        add_pair_avoidance(builder, pair_tag(i, j), offsets, half[:, column], swarm.settings)
        column += 1
    label = f"footprint_central_{swarm.num_agents}"
    return builder.build(label, "ipopt", {**ipopt_options(swarm.settings.ipopt), **(options or {})})


def _soft_slack(values: np.ndarray, s: OCPSettings) -> np.ndarray:
    """max(0, d_min - value) (1, K): the slack that makes each separation row hold at the guess."""
    return np.maximum(0.0, s.d_min - np.asarray(values, float))[None, :]


def footprint_guess_blocks(swarm: FootprintSwarm, guesses: Sequence[np.ndarray]) -> dict[str, np.ndarray]:
    """Initial values of the footprint certificates (and soft slacks) from guessed states.

    ``guesses[i]`` is agent i's (N+1, n_i) state guess. Every pair with a car and every car
    against every obstacle gets the closed-form best certificates of the guessed poses
    (:func:`~swarmpc.formulation.footprint_certificates.rectangle_pair_certificates`,
    :class:`~swarmpc.formulation.footprint_certificates.PolytopeFootprintCertifier`): they satisfy
    the coupling and norm rows exactly and certify the guess's signed distance, so the separation
    row holds wherever the guess keeps d_min (and, in the soft form, everywhere with the slack
    max(0, d_min - value)). The point form's blocks (point-only pairs, point agents against their
    grown obstacles) are not included: they have their own seeds.
    """
    s = swarm.settings
    blocks: dict[str, np.ndarray] = {}
    for i, agent in enumerate(swarm.agents):
        if not agent.oriented:
            continue
        first = agent.settings.first_constrained_step
        poses = agent.poses(np.asarray(guesses[i], float)[first:])
        for n, (G, g) in enumerate(agent.settings.obstacles):
            certificate = PolytopeFootprintCertifier(G, g)(poses, agent.size)
            blocks[f"L{i}_o{n}"], blocks[f"Lo{n}_{i}"] = certificate.lam_ij.T, certificate.lam_ji.T
            if s.collision == "soft":
                blocks[f"A{i}_o{n}"] = _soft_slack(certificate.value, s)
    for i, j in swarm.pairs:
        if swarm.is_point_pair(i, j):
            continue
        first = swarm.pair_first_step(i, j)
        pose_i = swarm.agents[i].poses(np.asarray(guesses[i], float)[first:])
        pose_j = swarm.agents[j].poses(np.asarray(guesses[j], float)[first:])
        certificate = rectangle_pair_certificates(pose_i, swarm.agents[i].size, pose_j, swarm.agents[j].size)
        blocks[f"L{i}_{j}"], blocks[f"L{j}_{i}"] = certificate.lam_ij.T, certificate.lam_ji.T
        if s.collision == "soft":
            blocks[f"A{pair_tag(i, j)}"] = _soft_slack(certificate.value, s)
    return blocks
