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


@dataclass(frozen=True, eq=False)
class Blocks:
    """One iteration's consensus blocks as whole arrays, stacked once for the average and the
    residual: every answer's own positions and every copy the answers hold, in the answers' order."""

    own: np.ndarray
    """(R, d, K) each answer's own positions."""
    agents: np.ndarray
    """(R,) the agent of each answer."""
    copies: np.ndarray
    """(C, d, K) the copies, answer by answer and slot by slot (:func:`held_copies`)."""
    targets: np.ndarray
    """(C,) the agent each copy copies."""
    counts: np.ndarray
    """(R,) how many copies each answer holds."""

    @classmethod
    def of(cls, results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]]) -> Blocks:
        copies, targets = held_copies(results, neighbours)
        return cls(np.array([r.own for r in results]), np.array([r.agent for r in results], int), copies, targets,
                   np.array([len(neighbours[r.agent]) for r in results], int))

    def in_order(self, own: np.ndarray, copies: np.ndarray) -> np.ndarray:
        """Per-block values (``own`` (R,), ``copies`` (C,)) in the blocks' order: each answer's own
        block, then its copies."""
        first = np.arange(len(own)) + np.concatenate(([0], np.cumsum(self.counts)[:-1])).astype(int)
        ordered = np.empty(len(own) + len(copies))
        rest = np.ones(len(ordered), bool)
        rest[first] = False
        ordered[first], ordered[rest] = own, copies
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
    own = stacked.own
    weights = np.array([owner_weight if n else 1.0 for n in neighbours])
    coupled = np.array([bool(n) for n in neighbours])
    relaxed_own = own
    if previous is not None:
        relaxed_own = np.where(coupled[:, None, None], alpha * own + (1.0 - alpha) * previous, own)
    total = weights[:, None, None] * relaxed_own
    count = weights.copy()
    copies, holders = stacked.copies, stacked.targets
    if previous is not None:
        copies = alpha * copies + (1.0 - alpha) * previous[holders]
    # unbuffered adds in the copies' order: each z_j sums its copies as a loop over them would
    np.add.at(total, holders, copies)
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
    squared = 0.0
    for value in b.in_order(own, copies).tolist():  # summed block by block, in order, as the blocks come
        squared += value
    return float(np.sqrt(squared / max(b.own.size + b.copies.size, 1)))


def dual_residual(change: np.ndarray, weights: np.ndarray, neighbours: Sequence[tuple[int, ...]], rho: float) -> float:
    """RMS of rho_b (z - z_prev) over every consensus block (``change``: z - z_prev; block
    penalties rho_b: rho * owner_weight for own blocks, rho for copies). Agents nobody couples
    with hold no consensus block and do not count."""
    own = np.array([bool(n) for n in neighbours])
    copies = np.bincount([j for n in neighbours for j in n], minlength=len(neighbours))
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
