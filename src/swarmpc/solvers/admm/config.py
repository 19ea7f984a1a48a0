"""ADMM's parameters (:class:`ADMMConfig`) and the coupling defaults by collision form."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from swarmpc.config import SolverConfig

DEFAULT_COUPLING = {"hard": (0.2, 0.1), "soft": (0.5, 0.0)}
"""(coupling margin [m], closing time [s]) by collision form when the scenario leaves the margin
open. Hard constraints afford a small margin: a pair coupled too late is caught by the conflict
check after convergence, before any plan is applied, and costs an iteration. The closing-time
term lets pairs that approach fast (head-on swaps) couple a little earlier. Soft constraints do
not afford a small margin: a late pair's slack is paid for in the cost and no check undoes it
(evidence: docs/lab/admm.md#coupling-margin)."""


def default_coupling(collision: str) -> tuple[float, float]:
    """(coupling_margin, closing_time) for hard or soft collision constraints (:data:`DEFAULT_COUPLING`)."""
    return DEFAULT_COUPLING[collision]


@dataclass(frozen=True)
class ADMMConfig:
    """ADMM parameters (a scenario's ``solver`` section: :meth:`from_options`); checked when made
    (ValueError)."""

    rho: float = 10.0
    max_iter: int = 100
    tol: float = 1e-3
    dual_tol: float | None = None
    """Tolerance of the dual residual (the RMS of rho_b (z - z_previous) over the consensus blocks,
    compared at the step's starting rho); None: ``tol``, as in the paper. The dual residual measures
    how far z moved in the last iteration, weighted by the penalties: ``rho * tol`` lets a step
    stop once the consensus moves less than ``tol`` per iteration (own blocks: ``tol`` /
    ``owner_weight``) where ``tol`` asks for a tenth of that at rho = 10
    (evidence: docs/lab/admm.md#dual-tolerance)."""
    adaptive_rho: bool = False
    dynamic_copies: bool = False
    owner_weight: float = 5.0
    repair: bool = True
    repair_rounds: int = 3
    """Repair passes at most per step: after a pass, candidate pairs whose repaired plans conflict
    are coupled and their agents re-plan again."""
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
    counterpart was dropped acts as a constant force that can hold agents at rest short of free
    goals (evidence: docs/lab/admm.md#multipliers-across-steps)."""
    warm_start: bool = True
    """Start each ADMM iteration's local solve after the first of an MPC step from the previous
    iterate's multipliers too, not only its primal point (IPOPT warm start): the next iterate's
    problem differs only in its consensus targets, so IPOPT needs fewer iterations to the same
    solution (evidence: docs/lab/admm.md#multiplier-warm-start)."""
    local: Literal["qp", "ipopt"] = "ipopt"
    """The agents' local step. "ipopt": the OBCA NLP by IPOPT (the reference). "qp": the convex
    local step of :mod:`swarmpc.solvers.qp_local` (OBCA certificates held fixed per QP, OSQP, a
    short certificate loop), whose answers are safe as they stand; any call it fails is solved by
    IPOPT instead (:class:`~swarmpc.solvers.admm.ladders.QPLocalSolverLadder`, counted in
    ``LocalResult.local_fallbacks``). Needs free copies (``dynamic_copies`` False)."""
    relaxation: float = 1.0
    """Over-relaxation alpha of the consensus (Boyd et al. sec. 3.4.3): the average and the
    multipliers use alpha * v + (1 - alpha) * z_previous in place of each block's answer v.
    1: plain ADMM (the paper); the fixed points are the same for any alpha in (0, 2)
    (evidence: docs/lab/admm.md#over-relaxation)."""
    independent_first: bool = False
    """Before the iterations, ask every agent for its own optimum with no neighbour in it
    (:attr:`~swarmpc.solvers.admm.messages.LocalRequest.independent`). When those plans keep every
    pair that can meet d_min apart at every constrained step, the joint problem's pair constraints
    are slack there, so the plans are its optimum and ADMM's fixed point (every consensus
    multiplier zero): the step ends with them after one round of local steps. Otherwise the
    iterations run exactly as without the probe, which only adds its round to the step. A scenario
    that leaves ``solver.admm.independent_first`` out turns it on (:meth:`from_options`); the
    paper's algorithm, and this class's default, has no probe
    (evidence: docs/lab/admm.md#independent-first)."""
    reuse_tol: float = 1e-4
    """Within an MPC step, an agent whose consensus targets (z - gamma / rho_b, per block) all moved
    less than this [m] since its last solve, at the same penalty and neighbours, sends its last
    answer again instead of solving: that answer solves a problem whose targets differ by at most
    this much (0: always solve). An inexact local step, far below the consensus tolerance
    (evidence: docs/lab/admm.md#answer-reuse)."""
    plane_margin: float | None = None
    """None: every coupled pair holds copies of each other (OBCA and consensus). A margin [m]: a
    coupled pair whose guesses stay at least d_min + plane_margin beyond its Delta_ij box on one axis
    at every constrained step is kept apart by a fixed separating plane per step instead, each
    agent keeping to its side with half the spare room
    (:func:`~swarmpc.solvers.admm.graph.separating_planes`): no copies, no consensus, no
    iterations for that pair. A plane pair whose plans break the separation is coupled with
    copies (evidence: docs/lab/admm.md#separating-planes)."""
    deadline: float | None = None
    """Critical-path budget of one MPC step [s] (None: none): an iteration that would overrun it,
    counting what the last repair pass took (at most half the deadline) as a reserve, is not started and the step
    ends through the repair pass (:class:`~swarmpc.solvers.admm.clock.StepClock`,
    :meth:`ADMMSolver.plan`). With ``local`` "qp" a failed QP call is not handed to IPOPT, whose
    calls take longer than a step's budget (:attr:`LocalRequest.handover`)."""

    deadline_repair: Literal["sequential", "select", "budget"] = "sequential"
    """How a step stopped by the deadline is made safe. "sequential" (default): the repair pass
    (:meth:`~swarmpc.solvers.admm.repair.Repair.sequential`), every coupled agent re-planning one
    after another. "select": no agent re-plans unless it must; each flies its new plan or the plan
    it committed to at the last step, shifted, chosen pair by pair
    (:class:`~swarmpc.solvers.admm.selection.Selection`); one agent of each pair of committed
    plans that conflict re-plans, and so do agents sent back two steps in a row. "select"
    overruns the deadline less often but the swarm is slower: at M = 16 a quarter of the misses
    at a 16 % higher cost, at M = 64 1.2-2 times the time to the goals
    (evidence: docs/lab/admm.md#deadline-selection). "budget": the repair pass while the deadline
    allows (:class:`~swarmpc.solvers.admm.clock.BatchBudget`: a batch is asked only if the longest
    of the recent batches still fits), then the selection pass over what it left: agents it did
    not reach fly their last iterate or their committed plan, whichever keeps clear; a cut pass
    keeps the largest reserve for the next steps (evidence: docs/lab/admm.md#deadline-budget)."""

    repair_order: Literal["index", "colour"] = "index"
    """The order of the repair pass (:meth:`~swarmpc.solvers.admm.repair.Repair.sequential`).
    "index" (default): every coupled agent, highest index first; consecutive agents that hold no
    copy of each other re-plan in one batch. "colour": the classes of a greedy colouring of the
    coupling graph one after another (no two agents of a class are coupled), so each class is one
    batch and a pass costs the critical path one re-plan per colour, not per run of consecutive
    indices. Any order keeps every pair feasible when the solves succeed (each agent respects the
    plans of those before it and the plans those after it will respect)."""

    def __post_init__(self) -> None:
        problem = _first_problem(self)
        if problem is not None:
            raise ValueError(f"ADMMConfig.{problem}")

    @classmethod
    def from_options(cls, options: SolverConfig, collision: str) -> ADMMConfig:
        """The ADMM parameters of a scenario's ``solver`` section (its flat keys and its ``admm``
        sub-section) for ``collision`` ("hard" / "soft") constraints.

        The coupling margin and closing time follow the collision form (:func:`default_coupling`)
        unless the section sets them: a ``coupling_margin`` given is used as it is, with no
        closing-speed term unless ``admm.closing_time`` sets one.
        """
        margin, closing_time = default_coupling(collision)
        if options.coupling_margin is not None:  # the scenario's margin, as given
            margin, closing_time = options.coupling_margin, 0.0
        admm = options.admm
        return cls(
            rho=options.rho, max_iter=options.max_iter, tol=options.tol, dual_tol=admm.dual_tol,
            adaptive_rho=options.adaptive_rho,
            seed_duals=options.seed_duals, coupling_margin=margin, reuse_tol=options.reuse_tol,
            relaxation=options.relaxation, plane_margin=options.plane_margin, deadline=options.deadline,
            local=options.local,
            closing_time=closing_time if admm.closing_time is None else admm.closing_time,
            dynamic_copies=admm.dynamic_copies, owner_weight=admm.owner_weight, repair=admm.repair,
            repair_rounds=admm.repair_rounds, stall_window=admm.stall_window, stall_rho_factor=admm.stall_rho_factor,
            rho_bounds=(admm.rho_min, admm.rho_max), carry_multipliers=admm.carry_multipliers,
            warm_start=admm.warm_start, deadline_repair=admm.deadline_repair, repair_order=admm.repair_order,
            independent_first=admm.independent_first is not False,
        )


def _first_problem(cfg: ADMMConfig) -> str | None:
    """The first field of ``cfg`` outside its range, as ``name: what is wrong``; None when valid."""
    positive: dict[str, float] = {"rho": cfg.rho, "max_iter": cfg.max_iter, "tol": cfg.tol,
                                  "owner_weight": cfg.owner_weight, "repair_rounds": cfg.repair_rounds}
    for name, value in positive.items():
        if not value > 0:
            return f"{name}: must be > 0, got {value!r}"
    if cfg.dual_tol is not None and not cfg.dual_tol > 0:
        return f"dual_tol: must be > 0 or None, got {cfg.dual_tol!r}"
    non_negative: dict[str, float | None] = {"coupling_margin": cfg.coupling_margin, "plane_margin": cfg.plane_margin,
                                             "closing_time": cfg.closing_time, "reuse_tol": cfg.reuse_tol}
    for name, optional in non_negative.items():
        if optional is not None and not optional >= 0:
            return f"{name}: must be >= 0, got {optional!r}"
    if not 0 < cfg.relaxation < 2:
        return f"relaxation: must be in (0, 2), got {cfg.relaxation!r}"
    if cfg.deadline is not None and not cfg.deadline > 0:
        return f"deadline: must be > 0 or None, got {cfg.deadline!r}"
    if cfg.stall_window is not None and cfg.stall_window < 1:
        return f"stall_window: must be >= 1 or None, got {cfg.stall_window!r}"
    if cfg.stall_rho_factor is not None and not cfg.stall_rho_factor > 1:
        return f"stall_rho_factor: must be > 1 or None, got {cfg.stall_rho_factor!r}"
    low, high = cfg.rho_bounds
    if not 0 < low <= high:
        return f"rho_bounds: must be 0 < low <= high, got {cfg.rho_bounds!r}"
    if cfg.carry_multipliers not in ("stable", "always", "never"):
        return f"carry_multipliers: expected stable, always or never, got {cfg.carry_multipliers!r}"
    if cfg.deadline_repair not in ("sequential", "select", "budget"):
        return f"deadline_repair: expected sequential, select or budget, got {cfg.deadline_repair!r}"
    if cfg.repair_order not in ("index", "colour"):
        return f"repair_order: expected index or colour, got {cfg.repair_order!r}"
    if cfg.local not in ("qp", "ipopt"):
        return f"local: expected qp or ipopt, got {cfg.local!r}"
    return None
