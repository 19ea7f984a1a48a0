"""The coordinator's side of consensus: averaging, residuals, the stop rule and the penalty schedule.

The consensus z_j of agent j's positions is the rho_b-weighted mean of every copy of them, its
own plan included (weight ``owner_weight``); the RMS primal residual ||v - z|| and the RMS dual
residual rho_b ||z - z_prev|| (Boyd et al. 2011 sec. 3.3, with block penalties) decide when to
stop. The penalty rho stiffens when the primal residual stalls and, with ``adaptive_rho``,
balances the two residuals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from swarmpc.solvers.admm.config import ADMMConfig
from swarmpc.solvers.admm.messages import LocalResult


@dataclass(frozen=True, eq=False)
class Carryover:
    """What the next MPC step starts from: the plans flown (its z, shifted), the final coupling
    (which multipliers carry over) and the penalty (with ``adaptive_rho``)."""

    z: np.ndarray
    """(M, d, K) the own positions of the plans applied."""
    neighbours: tuple[tuple[int, ...], ...]
    rho: float
    multipliers: bool = True
    """Whether the agents' multipliers are the step's to carry: False after a step answered by the
    agents' own optima (``ADMMConfig.independent_first``), whose consensus multipliers are all zero."""


def starting_consensus(positions: np.ndarray, previous: Carryover | None) -> np.ndarray:
    """z (M, d, K) at the start of a step: the previous step's applied plans shifted by one step
    (after a repair pass the last average is nobody's plan), or the guess's ``positions``
    (M, K, d) at the constrained steps."""
    if previous is None:
        return np.transpose(positions, (0, 2, 1)).copy()
    return np.concatenate([previous.z[:, :, 1:], previous.z[:, :, -1:]], axis=2)


def carried_blocks(
    mode: str, neighbours: Sequence[tuple[int, ...]], previous: Carryover | None,
) -> list[tuple[bool, ...]]:
    """Per agent, which of its multipliers (own block, then each neighbour's) the new step
    carries over (see ``ADMMConfig.carry_multipliers``); every holder of a block decides
    alike, so each block's multipliers keep summing to zero."""
    if previous is not None and not previous.multipliers:
        return [(False,) * (1 + len(n)) for n in neighbours]
    if mode == "always":
        return [(True,) * (1 + len(n)) for n in neighbours]
    if mode == "never" or previous is None:
        return [(False,) * (1 + len(n)) for n in neighbours]
    stable = [n == p for n, p in zip(neighbours, previous.neighbours, strict=True)]
    return [(stable[i], *(stable[j] for j in n)) for i, n in enumerate(neighbours)]


def occurrences(targets: np.ndarray) -> np.ndarray:
    """(C,) per entry of ``targets`` (C,), how many entries before it share its target: the
    layer of :func:`add_in_order` that adds it."""
    order = np.argsort(targets, kind="stable")
    ranked = targets[order]
    seen = np.empty(len(targets), int)
    seen[order] = np.arange(len(targets)) - np.searchsorted(ranked, ranked, side="left")
    return seen


def add_in_order(total: np.ndarray, targets: np.ndarray, values: np.ndarray, layers: np.ndarray) -> np.ndarray:
    """``total`` (M, ...) with each of ``values`` (C, ...) added to row ``targets`` (C,), one after
    another in the values' order: the bits of ``np.add.at`` (a loop over the values), at a few
    per cent of its cost on some thousand blocks.

    ``layers`` (C,): :func:`occurrences` of ``targets``. Layer r holds every target's r-th value,
    the rows without one padded with -0.0, which any float plus -0.0 is exactly; the layers are
    then added whole, in order.
    """
    if not len(targets):
        return total.copy()
    depth, rows = int(layers.max()) + 1, len(total)
    stacked = np.full((depth * rows, *total.shape[1:]), -0.0)
    stacked[layers * rows + targets] = values
    summed = total.copy()
    for layer in stacked.reshape(depth, *total.shape):
        summed += layer
    return summed


def sequential_sum(values: np.ndarray) -> float:
    """The float sum of ``values`` (n,) left to right, as a Python loop adds them (``np.sum``
    adds pairwise, with other bits); 0.0 when empty."""
    return float(np.cumsum(values)[-1]) if len(values) else 0.0


@dataclass(frozen=True, eq=False)
class BlockLayout:
    """Where every consensus block of an iteration sits, for answers of ``agents`` (in that order)
    on ``neighbours``: the same for every iteration on one coupling graph, so made once for them
    (:meth:`fits`) instead of from Python loops over the some thousand blocks at M = 64."""

    agents: tuple[int, ...]
    neighbours: tuple[tuple[int, ...], ...]
    targets: np.ndarray
    """(C,) the agent each copy copies, answer by answer and slot by slot."""
    counts: np.ndarray
    """(R,) how many copies each answer holds."""
    own_at: np.ndarray
    """(R,) where each answer's own block sits in the blocks' order (own block, then its copies)."""
    copies_at: np.ndarray
    """(C,) where each copy sits in that order."""
    layers: np.ndarray
    """(C,) :func:`occurrences` of ``targets``."""
    coupled: np.ndarray
    """(M,) whether anybody couples with each agent (it holds copies, so others hold its)."""
    held: np.ndarray
    """(M,) how many copies of each agent the agents hold."""

    @classmethod
    def of(cls, agents: Sequence[int], neighbours: Sequence[tuple[int, ...]]) -> BlockLayout:
        neighbours = tuple(neighbours)
        counts = np.array([len(neighbours[i]) for i in agents], int)
        targets = np.array([j for i in agents for j in neighbours[i]], int)
        own_at = np.arange(len(counts)) + np.concatenate(([0], np.cumsum(counts)[:-1])).astype(int)
        rest = np.ones(len(counts) + len(targets), bool)
        rest[own_at] = False
        everyone = np.array([j for n in neighbours for j in n], int)
        return cls(tuple(agents), neighbours, targets, counts, own_at, np.flatnonzero(rest), occurrences(targets),
                   np.array([bool(n) for n in neighbours]), np.bincount(everyone, minlength=len(neighbours)))

    def fits(self, results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]]) -> bool:
        """Whether this is the layout of ``results`` on ``neighbours``."""
        return self.neighbours == tuple(neighbours) and self.agents == tuple(r.agent for r in results)


@dataclass(frozen=True, eq=False)
class Blocks:
    """One iteration's consensus blocks as whole arrays, stacked once for the average and the
    residual: every answer's own positions and every copy the answers hold, in the answers' order."""

    own: np.ndarray
    """(R, d, K) each answer's own positions."""
    copies: np.ndarray
    """(C, d, K) the copies, answer by answer and slot by slot (:func:`held_copies`)."""
    layout: BlockLayout
    """Where each block sits (the agents of the answers, the targets of the copies)."""

    @property
    def agents(self) -> np.ndarray:
        """(R,) the agent of each answer."""
        return np.array(self.layout.agents, int)

    @property
    def targets(self) -> np.ndarray:
        """(C,) the agent each copy copies."""
        return self.layout.targets

    @property
    def counts(self) -> np.ndarray:
        """(R,) how many copies each answer holds."""
        return self.layout.counts

    @classmethod
    def of(
        cls, results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]], layout: BlockLayout | None = None,
    ) -> Blocks:
        """The answers stacked; ``layout``: the last iteration's, reused when it still fits."""
        if layout is None or not layout.fits(results, neighbours):
            layout = BlockLayout.of([r.agent for r in results], neighbours)
        copies = [r.copies[:n] for r, n in zip(results, layout.counts.tolist(), strict=True)]
        if not len(layout.targets):
            d, K = results[0].own.shape if results else (0, 0)
            return cls(np.array([r.own for r in results]), np.zeros((0, d, K)), layout)
        return cls(np.array([r.own for r in results]), np.concatenate(copies), layout)

    def in_order(self, own: np.ndarray, copies: np.ndarray) -> np.ndarray:
        """Per-block values (``own`` (R,), ``copies`` (C,)) in the blocks' order: each answer's own
        block, then its copies."""
        ordered = np.empty(len(own) + len(copies))
        ordered[self.layout.own_at], ordered[self.layout.copies_at] = own, copies
        return ordered


def average(
    results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]], owner_weight: float,
    relaxation: float, z_previous: np.ndarray | None = None, blocks: Blocks | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Consensus positions z (M, d, K) and the own-block weights (M,).

    z_j is the rho_b-weighted mean of every copy of agent j: its own plan (weight
    ``owner_weight``, or 1 for an agent nobody couples with, whose z is then its plan) and the
    copies its neighbours hold (weight 1), each over-relaxed towards ``z_previous`` when
    ``relaxation`` is not 1 (an agent nobody couples with keeps its plan as z). ``blocks``: the
    answers stacked (:meth:`Blocks.of`), when the caller has them already.
    """
    alpha = relaxation
    previous = z_previous if alpha != 1.0 else None  # None: no over-relaxation
    stacked = blocks if blocks is not None else Blocks.of(results, neighbours)
    own, coupled = stacked.own, stacked.layout.coupled
    weights = np.where(coupled, owner_weight, 1.0)
    relaxed_own = own
    if previous is not None:
        relaxed_own = np.where(coupled[:, None, None], alpha * own + (1.0 - alpha) * previous, own)
    total = weights[:, None, None] * relaxed_own
    count = weights.copy()
    copies, holders = stacked.copies, stacked.targets
    if previous is not None:
        copies = alpha * copies + (1.0 - alpha) * previous[holders]
    # each z_j sums its copies in their order, as a loop over them would
    total = add_in_order(total, holders, copies, stacked.layout.layers)
    np.add.at(count, holders, 1.0)
    return total / count[:, None, None], weights


def held_copies(
    results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]],
) -> tuple[np.ndarray, np.ndarray]:
    """Every copy the agents hold, stacked (C, d, K) in the order of ``results`` and slots, and
    the agent each one copies (C,): the coordinator's arithmetic on copies as whole arrays (a
    Python loop over some hundred copies costs milliseconds per iteration at M = 64)."""
    blocks = [r.copies[: len(neighbours[r.agent])] for r in results]
    targets = [j for r in results for j in neighbours[r.agent]]
    if not targets:
        d, K = results[0].own.shape if results else (0, 0)
        return np.zeros((0, d, K)), np.zeros(0, int)
    return np.concatenate(blocks), np.array(targets, int)


def primal_residual(
    results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]], z: np.ndarray, blocks: Blocks | None = None,
) -> float:
    """RMS of v - z over every consensus block (own plans and copies); ``blocks``: the answers
    stacked (:meth:`Blocks.of`), when the caller has them already."""
    if not results:
        return 0.0
    b = blocks if blocks is not None else Blocks.of(results, neighbours)
    own = np.sum((b.own - z[b.agents]) ** 2, axis=(1, 2))
    copies = np.sum((b.copies - z[b.targets]) ** 2, axis=(1, 2))
    squared = sequential_sum(b.in_order(own, copies))  # block by block, in order, as the blocks come
    return float(np.sqrt(squared / max(b.own.size + b.copies.size, 1)))


def dual_residual(
    change: np.ndarray, weights: np.ndarray, neighbours: Sequence[tuple[int, ...]], rho: float,
    blocks: Blocks | None = None,
) -> float:
    """RMS of rho_b (z - z_prev) over every consensus block (``change``: z - z_prev; block
    penalties rho_b: rho * owner_weight for own blocks, rho for copies). Agents nobody couples
    with hold no consensus block and do not count. ``blocks``: the iteration's (:meth:`Blocks.of`),
    whose layout counts the blocks, when the caller has them."""
    layout = blocks.layout if blocks is not None else None
    if layout is None or layout.neighbours != tuple(neighbours):
        layout = BlockLayout.of(range(len(neighbours)), neighbours)
    own, copies = layout.coupled, layout.held
    per_agent = (weights**2 * own + copies) * np.sum(change**2, axis=(1, 2))
    entries = (own + copies).sum() * change[0].size
    return float(rho * np.sqrt(per_agent.sum() / max(entries, 1)))


def consensus_met(primal: float, dual: float, rho: float, config: ADMMConfig) -> bool:
    """The paper's stop: the primal residual within ``tol`` and the dual residual within
    ``dual_tol`` (``tol`` when None, the paper's). A raised rho scales the dual residual, not the
    motion of z it measures: it is compared at the step's starting penalty, or raising rho would
    itself block convergence."""
    dual_tol = config.tol if config.dual_tol is None else config.dual_tol
    return primal <= config.tol and dual <= dual_tol * rho / config.rho


@dataclass
class Residuals:
    """The step's history, one entry per ADMM iteration: primal and dual residuals and the rho used."""

    primal: list[float] = field(default_factory=list)
    dual: list[float] = field(default_factory=list)
    rho: list[float] = field(default_factory=list)

    def add(self, primal: float, dual: float, rho: float) -> None:
        self.primal.append(primal)
        self.dual.append(float(dual))
        self.rho.append(rho)

    def __len__(self) -> int:
        return len(self.primal)


def stalled(primal: Sequence[float], window: int | None) -> bool:
    """No 10% progress of the primal residual over the last ``window`` iterations: more
    iterations will not reach consensus, so stop and let the repair pass finish the step."""
    if window is None or len(primal) <= window:
        return False
    return min(primal[-window:]) > 0.9 * min(primal[:-window])


class PenaltySchedule:
    """The penalty rho of one MPC step: ``rho`` for the next iteration, ``previous`` the one the
    last iteration used (the agents' multiplier step reads it)."""

    def __init__(self, config: ADMMConfig, rho: float) -> None:
        self.config = config
        self.rho = rho
        self.previous = rho
        self._window_start = 0
        """Where the stall window starts: the iteration after the last stiffening."""

    def advance(self, primal: Sequence[float], dual: float) -> bool:
        """Set rho for the next iteration after one with residuals ``primal[-1]`` and ``dual``;
        True when the iterations should stop instead. A stalled primal residual (:func:`stalled`)
        stiffens rho and restarts the window, or stops the iterations when rho cannot grow;
        ``adaptive_rho`` then balances the residuals."""
        cfg, rho, r_norm = self.config, self.rho, primal[-1]
        self.previous = rho
        if stalled(primal[self._window_start:], cfg.stall_window):
            if cfg.stall_rho_factor is None or rho >= cfg.rho_bounds[1]:
                return True
            # a stalled nonconvex ADMM often settles once the penalty is stiffer
            rho = min(rho * cfg.stall_rho_factor, cfg.rho_bounds[1])
            self._window_start = len(primal)
        if cfg.adaptive_rho:
            if r_norm > 10 * dual:
                rho = min(rho * 2, cfg.rho_bounds[1])
            elif dual > 10 * r_norm:
                rho = max(rho / 2, cfg.rho_bounds[0])
        self.rho = rho
        return False
