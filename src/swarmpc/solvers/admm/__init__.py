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
both below ``tol`` (metres) on plans that pass the pairwise checks, or at ``max_iter``. Each agent
then applies its OWN plan's first input, which is always dynamically feasible. Multipliers and the
agent's last solution are private to the agent; the coordinator sees only what an agent transmits
(its positions and its copies).

The parts:

* :mod:`~swarmpc.solvers.admm.config`: :class:`ADMMConfig`, the coupling defaults;
* :mod:`~swarmpc.solvers.admm.messages`: what the coordinator and the agents exchange;
* :mod:`~swarmpc.solvers.admm.ladders`: an agent's local problems, one per size (IPOPT, QP path);
* :mod:`~swarmpc.solvers.admm.agent`: the agent, its multipliers and its answer cache;
* :mod:`~swarmpc.solvers.admm.graph`: the per-step coupling graph (reach, copies, planes);
* :mod:`~swarmpc.solvers.admm.safety`: the pairwise checks of the plans;
* :mod:`~swarmpc.solvers.admm.consensus`: averaging, residuals, stop rule, penalty schedule;
* :mod:`~swarmpc.solvers.admm.repair`: the safety passes in order, the repair pass and stranded fallbacks;
* :mod:`~swarmpc.solvers.admm.selection`: the selection pass of a deadline stop;
* :mod:`~swarmpc.solvers.admm.settle`: the settling pass of fallback agents, which asks no agent;
* :mod:`~swarmpc.solvers.admm.replan`: re-plans against neighbours' plans held fixed;
* :mod:`~swarmpc.solvers.admm.schedule`: re-plans batched as the one-by-one order allows;
* :mod:`~swarmpc.solvers.admm.clock`: the critical path and the deadline;
* :mod:`~swarmpc.solvers.admm.solver`: :class:`ADMMSolver`, the coordinator.
"""

from swarmpc.solvers.admm.agent import (
    AnswerCache,
    ConsensusMultipliers,
    LocalAgent,
    LocalAgentFactory,
    trajectory_through,
)
from swarmpc.solvers.admm.clock import StepClock, TimedAgent, TimedAgentFactory
from swarmpc.solvers.admm.config import DEFAULT_COUPLING, ADMMConfig, default_coupling
from swarmpc.solvers.admm.graph import (
    PLANE_EXTRA,
    PLANE_GOAL_RADIUS,
    CouplingGraph,
    components,
    couple,
    reach_candidates,
    reach_radius,
    separating_planes,
)
from swarmpc.solvers.admm.ladders import AgentLadder, LocalSolverLadder, QPLocalSolverLadder
from swarmpc.solvers.admm.messages import (
    KEPT_PLAN,
    FallbackSolution,
    LocalRequest,
    LocalResult,
    TimedResult,
)
from swarmpc.solvers.admm.safety import SafetyChecks
from swarmpc.solvers.admm.solver import ADMMSolver

__all__ = [
    "DEFAULT_COUPLING",
    "KEPT_PLAN",
    "PLANE_EXTRA",
    "PLANE_GOAL_RADIUS",
    "ADMMConfig",
    "ADMMSolver",
    "AgentLadder",
    "AnswerCache",
    "ConsensusMultipliers",
    "CouplingGraph",
    "FallbackSolution",
    "LocalAgent",
    "LocalAgentFactory",
    "LocalRequest",
    "LocalResult",
    "LocalSolverLadder",
    "QPLocalSolverLadder",
    "SafetyChecks",
    "StepClock",
    "TimedAgent",
    "TimedAgentFactory",
    "TimedResult",
    "components",
    "couple",
    "default_coupling",
    "reach_candidates",
    "reach_radius",
    "separating_planes",
    "trajectory_through",
]
