"""Optimal-control problems in CasADi: costs, OBCA collision constraints, global and local OCPs.

Collision avoidance follows OBCA (Zhang, Liniger, Borrelli 2017). Against a polytope
{p : G p <= g} a point p keeps Euclidean distance >= d_min iff a certificate lambda >= 0 exists with

* hard:  (G p - g)^T lambda >= d_min,        ||G^T lambda||_2 <= 1;
* soft:  (G p - g)^T lambda >= d_min - alpha, ||G^T lambda||_2 = 1, alpha >= 0, kappa*alpha in cost.

Two traps of the paper's statement are designed around (docs/formulation.md, "The traps"):

* d_min = 0 in the hard form excludes nothing (lambda = 0 satisfies it). The hard form here always
  has d_min > 0 (validated; default 0.05 m).
* With Euler steps p(1) = p(0) + dt v(0) is fixed by the measured state, so a constraint at k = 1
  has no free variable. Collision constraints start at the agent model's first step whose position
  depends on the inputs (:attr:`~swarmpc.model.agent_model.AgentModel.first_constrained_step`):
  k = 2 for Euler (k = 1 was enforced as k = 2 of the previous solve) and k = 1 for the exact
  zero-order hold, where p(1) depends on u(0).

The agents' dynamics enter only through the settings' :class:`~swarmpc.model.agent_model.AgentModel`
(``OCPSettings.model``): its state and input sizes, its CasADi dynamics and speed, its input box
and the state rows that hold the position.

Agents have bodies (axis-aligned boxes of half-size b_i). A pair keeps its centres' offset out of
the box of half-size Delta_ij = b_i + b_j; an obstacle keeps the whole body out because each
agent's OCP holds the obstacles grown by its own body (:meth:`OCPSettings.for_body`).

Every builder runs once per problem shape; everything that changes between calls (states, goals,
each pair's Delta, consensus targets, multipliers, rho) is a parameter.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import casadi as ca
import numpy as np

from swarmpc.config import IpoptOptions, QPOptions, Scenario
from swarmpc.formulation.nlp import CompiledNLP, ProblemBuilder, builds_casadi
from swarmpc.model.agent_model import AgentModel, make_model
from swarmpc.model.geometry import inflate_polytope


@dataclass(frozen=True)
class OCPSettings:
    """Everything that fixes the shape and constants of an agent's OCP.

    The agent model is named (``model_name``, ``model_params``) and built from ``dim``, ``dt`` and
    ``discretization`` (:func:`swarmpc.model.agent_model.make_model`) into :attr:`model`, so a
    copy with another ``dt`` or ``discretization`` (``dataclasses.replace``) carries the model
    that goes with it. ``Q``, ``Qf`` are (n, n) and ``R`` (m, m) for the model's states and inputs.
    ``ipopt`` and ``qp`` are how the problems built from these settings are solved (a scenario's
    ``solver.ipopt`` and ``solver.qp`` sections; the defaults are today's solver options).
    """

    dim: int
    horizon: int
    dt: float
    discretization: str
    Q: np.ndarray
    R: np.ndarray
    Qf: np.ndarray
    collision: str
    d_min: float
    kappa: float
    lower: np.ndarray | None
    upper: np.ndarray | None
    accel: np.ndarray | None
    speed: float | None
    obstacles: tuple[tuple[np.ndarray, np.ndarray], ...]
    model_name: str = "double_integrator"
    model_params: tuple[tuple[str, Any], ...] = ()
    """Keyword arguments of the model's factory, as (name, value) pairs."""
    ipopt: IpoptOptions = field(default_factory=IpoptOptions)
    """IPOPT's options for every NLP built from these settings (:func:`ipopt_options`)."""
    qp: QPOptions = field(default_factory=QPOptions)
    """The QP local step's options (read by :class:`swarmpc.solvers.qp_local.QPLocalLadder`)."""
    model: AgentModel = field(init=False, repr=False, compare=False)
    """The agent's dynamics (built from the fields above)."""

    def __post_init__(self) -> None:
        model = make_model(self.model_name, self.dim, self.dt, self.discretization, **dict(self.model_params))
        object.__setattr__(self, "model", model)

    @classmethod
    def from_scenario(cls, scn: Scenario, model: str = "double_integrator", **params: Any) -> OCPSettings:
        """The settings of the scenario's agents with the registered model ``model`` (``params``
        to its factory); the weights are sized for that model's states and inputs."""
        agent = make_model(model, scn.dim, scn.dt, scn.discretization, **params)
        accel = None
        if scn.limits.accel is not None:
            accel = np.broadcast_to(np.asarray(scn.limits.accel, float), (scn.dim,)).copy()
        lower = upper = None
        if scn.workspace is not None:
            lower, upper = scn.bounds()
        return cls(
            dim=scn.dim,
            horizon=scn.horizon,
            dt=scn.dt,
            discretization=scn.discretization,
            Q=scn.matrix("Q", agent),
            R=scn.matrix("R", agent),
            Qf=scn.matrix("Qf", agent),
            collision=scn.collision,
            d_min=scn.d_min,
            kappa=scn.kappa,
            lower=lower,
            upper=upper,
            accel=accel,
            speed=scn.limits.speed,
            obstacles=tuple(scn.obstacle_halfspaces()),
            model_name=model,
            model_params=tuple(sorted(params.items())),
            ipopt=scn.solver.ipopt,
            qp=scn.solver.qp,
        )

    def for_body(self, half_size: np.ndarray) -> OCPSettings:
        """The settings of an agent whose body has ``half_size`` per axis: every obstacle grown by
        the body (:func:`swarmpc.model.geometry.inflate_polytope`), so that OBCA on the agent's
        centre keeps its whole body d_min away. The workspace still bounds the centre."""
        grown = tuple((G, inflate_polytope(G, g, half_size)) for G, g in self.obstacles)
        return replace(self, obstacles=grown)

    @property
    def first_constrained_step(self) -> int:
        """First horizon step with a free position (the model's): 2 for the Euler double
        integrator, 1 for the zero-order hold."""
        return self.model.first_constrained_step

    @property
    def num_constrained(self) -> int:
        return self.horizon + 1 - self.first_constrained_step


WARM_START_OPTIONS = {
    "ipopt.warm_start_init_point": "yes",
    "ipopt.warm_start_bound_push": 1e-6,
    "ipopt.warm_start_bound_frac": 1e-6,
    "ipopt.warm_start_slack_bound_push": 1e-6,
    "ipopt.warm_start_slack_bound_frac": 1e-6,
    "ipopt.warm_start_mult_bound_push": 1e-6,
    "ipopt.mu_init": 1e-4,
}
"""IPOPT options for a solve that starts from the previous solve's primal and dual point."""

def ipopt_options(section: IpoptOptions, local: bool = False) -> dict[str, Any]:
    """CasADi's options of an IPOPT solve with the settings of a ``solver.ipopt`` section.

    Silent (no banner, no timing, no iteration log). ``local``: the options of the agents' local
    ADMM problems, which also go without MUMPS's scaling of the KKT matrix (unless
    ``section.local_scaling``) and without the parameter multipliers nobody reads. A
    warm-started local solve takes one or two IPOPT iterations, so its time is mostly the linear
    solver's fixed cost, and these options cut that cost without changing the solutions (the
    centralised problem, large and badly scaled, keeps the scaling). Evidence: docs/lab/admm.md,
    "Local IPOPT options".
    """
    options: dict[str, Any] = {
        "expand": True,
        "print_time": False,
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "ipopt.max_iter": section.max_iter,
        "ipopt.tol": section.tol,
        "ipopt.acceptable_tol": section.acceptable_tol,
        "ipopt.mu_strategy": section.mu_strategy,
    }
    if local:
        if not section.local_scaling:
            options.update({"ipopt.mumps_scaling": 0, "ipopt.mumps_permuting_scaling": 0})
        options["calc_lam_p"] = False
    return options


IPOPT_OPTIONS = ipopt_options(IpoptOptions())
"""IPOPT options of the centralised problem with the default ``solver.ipopt`` section."""

LOCAL_IPOPT_OPTIONS = ipopt_options(IpoptOptions(), local=True)
"""IPOPT options of the agents' local ADMM problems with the default ``solver.ipopt`` section."""


def quadratic_cost(X: ca.SX, U: ca.SX, goal: ca.SX, s: OCPSettings) -> ca.SX:
    """Paper eq. (3): sum_k (s_k - s_g)' Q (s_k - s_g) + u_k' R u_k + (s_N - s_g)' Qf (s_N - s_g)
    over the model's states X (n, N+1) and inputs U (m, N)."""
    cost = ca.SX(0)
    for k in range(s.horizon):
        err = X[:, k] - goal
        cost += ca.mtimes([err.T, s.Q, err]) + ca.mtimes([U[:, k].T, s.R, U[:, k]])
    err = X[:, s.horizon] - goal
    return cost + ca.mtimes([err.T, s.Qf, err])


def add_trajectory(builder: ProblemBuilder, tag: str, s: OCPSettings) -> tuple[ca.SX, ca.SX]:
    """A dynamically feasible trajectory: parameter ``x0{tag}``, variables ``X{tag}`` (n, N+1) and
    ``U{tag}`` (m, N) of the settings' model with its dynamics, the workspace (on the position
    rows), the input box and the speed limit; returns (X, U)."""
    model, N = s.model, s.horizon
    n, rows = model.state_dim, model.position_rows
    lbx = np.full((n, N + 1), -np.inf)
    ubx = np.full((n, N + 1), np.inf)
    if s.lower is not None and s.upper is not None:
        first = s.first_constrained_step
        lbx[rows, first:] = s.lower[:, None]
        ubx[rows, first:] = s.upper[:, None]
    lower, upper = model.input_bounds(s.accel, s.speed)
    x0 = builder.parameter(f"x0{tag}", n)
    X = builder.variable(f"X{tag}", n, N + 1, lbx, ubx)
    U = builder.variable(f"U{tag}", model.input_dim, N, lower[:, None], upper[:, None])
    builder.constrain(f"init{tag}", X[:, 0] - x0, 0.0, 0.0)
    builder.constrain(f"dyn{tag}", X[:, 1:] - model.casadi_dynamics(X, U), 0.0, 0.0)
    if s.speed is not None:
        builder.constrain(f"speed{tag}", model.casadi_speed_sq(X, U), -np.inf, s.speed**2)
    return X, U


def add_agent(builder: ProblemBuilder, tag: str, s: OCPSettings) -> tuple[ca.SX, ca.SX]:
    """One agent: its trajectory (:func:`add_trajectory`), parameter ``goal{tag}``, its quadratic
    cost and OBCA against every static obstacle; returns (X, U)."""
    X, U = add_trajectory(builder, tag, s)
    goal = builder.parameter(f"goal{tag}", s.model.state_dim)
    builder.cost += quadratic_cost(X, U, goal, s)
    for n, (G, g) in enumerate(s.obstacles):
        positions = X[s.model.position_rows, s.first_constrained_step :]
        add_polytope_avoidance(builder, f"{tag}_o{n}", positions, G, g, s)
    return X, U


def certificate_terms(offsets: ca.SX, lam: ca.SX, half_size: ca.SX) -> tuple[ca.SX, ca.SX]:
    """(G q - g)^T lambda and ||G^T lambda||^2 for the box G = [I; -I], g = [half; half].

    ``offsets`` q = p_i - p_j is (d, K), ``lam`` (2d, K); both results are (1, K).
    """
    d = offsets.shape[0]
    direction = lam[:d, :] - lam[d:, :]
    size = lam[:d, :] + lam[d:, :]
    margin = ca.sum1(offsets * direction) - ca.sum1(size * ca.repmat(half_size, 1, offsets.shape[1]))
    return margin, ca.sum1(direction**2)


def add_certificate(
    builder: ProblemBuilder,
    tag: str,
    margin: ca.SX,
    norm_sq: ca.SX,
    s: OCPSettings,
) -> None:
    """Impose the hard or soft OBCA condition on precomputed (margin, ||G^T lambda||^2) rows."""
    if s.collision == "hard":
        builder.constrain(f"sep{tag}", margin, s.d_min, np.inf)
        builder.constrain(f"norm{tag}", norm_sq, -np.inf, 1.0)
    else:
        slack = builder.variable(f"A{tag}", 1, margin.shape[1], 0.0, np.inf)
        builder.constrain(f"sep{tag}", margin + slack, s.d_min, np.inf)
        builder.constrain(f"norm{tag}", norm_sq, 1.0, 1.0)
        builder.cost += s.kappa * ca.sum2(slack)


def add_pair_avoidance(
    builder: ProblemBuilder, tag: str, offsets: ca.SX, half_size: ca.SX, s: OCPSettings
) -> None:
    """OBCA between two agents: point offset q against the box of half-size Delta_ij (the pair's
    ``half_size``, b_i + b_j).

    Declares certificate ``L{tag}`` (2d, K) and, in the soft form, slack ``A{tag}`` (1, K).
    """
    lam = builder.variable(f"L{tag}", 2 * s.dim, offsets.shape[1], 0.0, np.inf)
    margin, norm_sq = certificate_terms(offsets, lam, half_size)
    add_certificate(builder, tag, margin, norm_sq, s)


def add_polytope_avoidance(
    builder: ProblemBuilder, tag: str, positions: ca.SX, G: np.ndarray, g: np.ndarray, s: OCPSettings
) -> None:
    """OBCA against a static polytope for positions (d, K); certificate ``L{tag}`` (rows of G, K)."""
    lam = builder.variable(f"L{tag}", G.shape[0], positions.shape[1], 0.0, np.inf)
    margin, norm_sq = polytope_certificate_terms(positions, lam, G, g)
    add_certificate(builder, tag, margin, norm_sq, s)


def polytope_certificate_terms(
    positions: ca.SX, lam: ca.SX, G: np.ndarray, g: np.ndarray
) -> tuple[ca.SX, ca.SX]:
    """(G p - g)^T lambda and ||G^T lambda||^2 per column of positions (d, K), lambda (rows, K)."""
    K = positions.shape[1]
    margin = ca.sum1((ca.mtimes(G, positions) - ca.repmat(g, 1, K)) * lam)
    return margin, ca.sum1(ca.mtimes(G.T, lam) ** 2)


def pair_tag(i: int, j: int) -> str:
    return f"{i}_{j}"


def agent_pairs(num_agents: int) -> list[tuple[int, int]]:
    """Every pair (i, j), i < j, in the order of the columns of the centralised ``delta``."""
    return [(i, j) for i in range(num_agents) for j in range(i + 1, num_agents)]


@builds_casadi
def build_centralized(
    s: OCPSettings, num_agents: int, options: dict[str, Any] | None = None, bodies: np.ndarray | None = None,
) -> CompiledNLP:
    """The global OCP: every agent's cost summed, every pair (i < j) coupled by OBCA.

    Parameter ``delta`` (d, P) holds each pair's Delta_ij, one column per pair of
    :func:`agent_pairs`. ``bodies`` (M, d): each agent's obstacles are grown by its own body
    (:meth:`OCPSettings.for_body`); None: the obstacles of ``s`` as they are.
    """
    builder = ProblemBuilder()
    pairs = agent_pairs(num_agents)
    half = builder.parameter("delta", s.dim, len(pairs))
    first, rows = s.first_constrained_step, s.model.position_rows
    trajectories = [
        add_agent(builder, str(i), s if bodies is None else s.for_body(bodies[i])) for i in range(num_agents)
    ]
    for column, (i, j) in enumerate(pairs):
        offsets = trajectories[i][0][rows, first:] - trajectories[j][0][rows, first:]
        add_pair_avoidance(builder, pair_tag(i, j), offsets, half[:, column], s)
    return builder.build(f"central_{num_agents}", "ipopt", {**ipopt_options(s.ipopt), **(options or {})})


@builds_casadi
def build_local(
    s: OCPSettings, num_copies: int, dynamic_copies: bool = False, options: dict[str, Any] | None = None,
    plugin: str = "ipopt", warm_start: bool = False, pair_collision: str | None = None, num_planes: int = 0,
) -> CompiledNLP:
    """Agent i's ADMM subproblem with ``num_copies`` local copies of other agents.

    Variables: own trajectory (``X``, ``U``), copies of the others' positions at the constrained
    steps, certificates ``L{c}``. Copies are either free positions ``C{c}`` (d, K) or, with
    ``dynamic_copies``, whole trajectories ``Xc{c}``/``Uc{c}`` from the neighbour's measured state
    ``x0c{c}`` obeying its dynamics and limits. Only the own trajectory is ever applied.
    Parameters: ``x0``, ``goal``, ``delta`` (d, num_copies: column c is the Delta_ij of the pair
    with copy c; a (d,) value is taken for every copy), ``rho``, ``owner_weight``, the consensus
    targets ``Z`` (own) and ``Z{c}``, and the multipliers ``Y`` and ``Y{c}`` (gamma). The static
    obstacles are those of ``s``: pass the agent's :meth:`OCPSettings.for_body`. One problem is
    built per neighbour count (:class:`swarmpc.solvers.admm.LocalSolverLadder`), so every copy is
    in use.

    Local objective (paper eq. 16): own cost + sum_b gamma_b'(v_b - z_b) + rho_b/2 ||v_b - z_b||^2,
    with rho_b = rho * owner_weight on the own block and rho on the copies (block-weighted consensus:
    the same problem with the own consensus rows scaled by sqrt(owner_weight)).

    ``pair_collision`` ("hard" / "soft") overrides the form of the constraints between the agent and
    its copies only (static obstacles keep ``s.collision``): the soft form with slack price
    ``s.kappa`` is the rescue problem of a hard-constrained agent, always feasible, whose optimum
    is the plan that violates the separation least (see ``LocalAgent``).

    ``num_planes`` half-space slots keep the own positions on one side of fixed separating planes
    (parameters ``Hn{p}`` (d, K), unit normals per step, and ``Hb{p}`` (1, K), offsets:
    ``Hn' p_k >= Hb_k``): the cheap constraint of a pair that is near but not engaged, which the
    coordinator splits between the two agents (:func:`swarmpc.solvers.admm.separating_planes`).
    """
    builder = ProblemBuilder()
    d, K, first, rows = s.dim, s.num_constrained, s.first_constrained_step, s.model.position_rows
    half = builder.parameter("delta", d, num_copies)
    rho = builder.parameter("rho", 1)
    owner_weight = builder.parameter("owner_weight", 1)
    X, _ = add_agent(builder, "", s)
    own = X[rows, first:]
    z_own = builder.parameter("Z", d, K)
    y_own = builder.parameter("Y", d, K)
    builder.cost += consensus_penalty(own, z_own, y_own, rho * owner_weight)
    pair_settings = s if pair_collision is None else replace(s, collision=pair_collision)
    for c in range(num_copies):
        if dynamic_copies:
            copy = add_trajectory(builder, f"c{c}", s)[0][rows, first:]
        else:
            copy = builder.variable(f"C{c}", d, K)
        z = builder.parameter(f"Z{c}", d, K)
        y = builder.parameter(f"Y{c}", d, K)
        builder.cost += consensus_penalty(copy, z, y, rho)
        lam = builder.variable(f"L{c}", 2 * d, K, 0.0, np.inf)
        margin, norm_sq = certificate_terms(own - copy, lam, half[:, c])
        add_certificate(builder, str(c), margin, norm_sq, pair_settings)
    for p in range(num_planes):
        normals = builder.parameter(f"Hn{p}", d, K)
        offsets = builder.parameter(f"Hb{p}", 1, K)
        builder.constrain(f"plane{p}", ca.sum1(normals * own) - offsets, 0.0, np.inf)
    label = f"local_{num_copies}_{num_planes}_{int(dynamic_copies)}_{pair_settings.collision}"
    if plugin != "ipopt":
        return builder.build(label, plugin, options or {})
    return builder.build(label, "ipopt", {**ipopt_options(s.ipopt, local=True), **(options or {})},
                         warm_options=WARM_START_OPTIONS if warm_start else None)


def consensus_penalty(v: ca.SX, z: ca.SX, y: ca.SX, rho: ca.SX) -> ca.SX:
    """gamma'(v - z) + rho/2 ||v - z||^2 over a (d, K) block."""
    diff = v - z
    return ca.sum1(ca.sum2(y * diff)) + 0.5 * rho * ca.sumsqr(diff)
