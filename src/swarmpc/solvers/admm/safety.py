"""The coordinator's checks of the agents' own plans, pair by pair, before any plan is applied.

Consensus within ``tol`` bounds how far copies sit from the plans flown only on average, and pairs
without copies were left out on the strength of their guesses; these checks look at the plans
themselves: uncoupled candidate pairs that conflict, plane pairs that break their planes, coupled
pairs that do not keep half the OBCA separation, and fallbacks nobody planned against.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import box_exterior_distance, box_signed_distance, largest_pair_delta
from swarmpc.solvers.admm.graph import CouplingGraph, reach_radius
from swarmpc.solvers.admm.messages import LocalResult


def own_positions(results: Sequence[LocalResult]) -> np.ndarray:
    """(M, d, K) every agent's own positions at the constrained steps."""
    return np.array([r.own for r in results])


@dataclass(frozen=True, eq=False)
class SafetyChecks:
    """Pairwise checks of the agents' own plans for agents of ``bodies`` (M, d): pair (i, j) keeps
    Delta_ij = b_i + b_j."""

    settings: OCPSettings
    bodies: np.ndarray

    @cached_property
    def largest_delta(self) -> np.ndarray:
        """(M, M) the largest axis of each pair's Delta_ij."""
        return largest_pair_delta(self.bodies)

    def pair_delta(self, first: Any, second: Any) -> np.ndarray:
        """Delta_ij = b_i + b_j of agents ``first`` and ``second`` (indices or index arrays):
        (d,) for one pair, (n, d) for n pairs."""
        return self.bodies[first] + self.bodies[second]

    def conflicts(
        self, results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]],
        candidates: np.ndarray | None = None,
    ) -> list[tuple[int, int]]:
        """Uncoupled candidate pairs (i < j) whose own plans come closer than the coupling would allow
        (inf-norm below max(Delta_ij) + d_min at some constrained step); ``candidates`` None: every pair."""
        M = len(results)
        examine = np.triu(np.ones((M, M), bool) if candidates is None else candidates, k=1)
        for i, n in enumerate(neighbours):
            examine[i, list(n)] = False
        first, second = np.nonzero(examine)
        if first.size == 0:
            return []
        own = own_positions(results)
        gaps = np.max(np.abs(own[first] - own[second]), axis=1).min(axis=1)
        hit = gaps < self.largest_delta[first, second] + self.settings.d_min
        return list(zip(first[hit].tolist(), second[hit].tolist(), strict=True))

    def pairs_apart(self, results: Sequence[LocalResult], first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """Per pair k: whether agents ``first[k]`` and ``second[k]`` keep a Euclidean distance of
        the offset of their own plans to the pair's Delta_ij box of at least d_min / 2 at every
        constrained step. An RMS consensus within tol still lets single steps of two own plans
        differ from the copies by more: half of d_min is kept as the margin, contact is at 0."""
        if first.size == 0:
            return np.ones(0, bool)
        return np.all(self._outside(results, first, second) >= 0.5 * self.settings.d_min, axis=1)

    def _outside(self, results: Sequence[LocalResult], first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """(n, K) per pair and constrained step, the Euclidean distance of the offset of the two
        agents' own plans to the pair's Delta_ij box."""
        own = own_positions(results)
        half = self.pair_delta(first, second)[:, :, None]  # (n, d, 1)
        return box_exterior_distance(own[first] - own[second], half, axis=1)

    def plans_keep_d_min(
        self, results: Sequence[LocalResult], candidates: np.ndarray, states: np.ndarray, margin: float = 0.0,
    ) -> bool:
        """Every pair that can meet (``candidates`` (M, M), widened by :meth:`checked_pairs`) keeps
        the full OBCA separation at every constrained step: a Euclidean distance of at least
        d_min + ``margin`` from the offset of their own plans to the pair's Delta_ij box. With no
        margin the pair constraints of the joint problem hold at these plans as they are, with no
        copies and no slack for a consensus tolerance."""
        first, second = np.nonzero(np.triu(self.checked_pairs(candidates, states, results), k=1))
        if first.size == 0:
            return True
        return bool(np.all(self._outside(results, first, second) >= self.settings.d_min + margin))

    def first_close_steps(self, results: Sequence[LocalResult], agents: Sequence[int]) -> tuple[int, float]:
        """How close ``agents``' own plans come to every other plan: the first constrained step at
        which some pair of one of them with any other agent keeps less than d_min / 2 (the margin of
        :meth:`pairs_apart`; K when none does), and the shortfall from d_min / 2 summed over those
        pairs and steps (negative signed distance counts as depth)."""
        own = own_positions(results)
        first = np.repeat(np.asarray(agents, int), len(results))
        second = np.tile(np.arange(len(results)), len(agents))
        keep = (first != second) & ~(np.isin(second, agents) & (second < first))  # each pair once
        first, second = first[keep], second[keep]
        half = self.pair_delta(first, second)[:, :, None]  # (n, d, 1)
        signed = box_signed_distance(own[first] - own[second], half, axis=1)  # (n, K)
        short = np.maximum(0.5 * self.settings.d_min - signed, 0.0)
        close = np.flatnonzero(short.max(axis=0) > 0)
        return (int(close[0]) if close.size else own.shape[2]), float(short.sum())

    def coupled_plans_clear(self, results: Sequence[LocalResult], neighbours: Sequence[tuple[int, ...]]) -> bool:
        """Every coupled pair's own plans keep half the OBCA separation (:meth:`pairs_apart`).
        Each agent keeps d_min from its copies, and consensus within ``tol`` (an RMS) bounds how
        far the copies sit from the plans flown, not every single step: under a loose ``tol`` this
        check, not the tolerance, is what keeps the flown plans apart, and ADMM iterates on until
        it holds."""
        pairs = np.array([(i, j) for i, n in enumerate(neighbours) for j in n if i < j], int).reshape(-1, 2)
        return bool(np.all(self.pairs_apart(results, pairs[:, 0], pairs[:, 1])))

    def broken_planes(self, results: Sequence[LocalResult], graph: CouplingGraph) -> list[tuple[int, int]]:
        """Plane pairs (i < j) whose own plans do not keep half the OBCA separation (a fallback
        plan, or a solve that missed its plane): they are coupled with copies."""
        pairs = graph.plane_pairs()
        broken = ~self.pairs_apart(results, pairs[:, 0], pairs[:, 1])
        return [(int(i), int(j)) for i, j in pairs[broken]]

    def missing(
        self, results: Sequence[LocalResult], graph: CouplingGraph, checked: np.ndarray,
    ) -> list[tuple[int, int]]:
        """Pairs to couple before any plan is applied: ``checked`` pairs with neither copies nor a
        plane whose plans conflict, and plane pairs whose plans break the separation."""
        return self.conflicts(results, graph.with_plane_partners(), checked) + self.broken_planes(results, graph)

    def checked_pairs(
        self, candidates: np.ndarray, states: np.ndarray, results: Sequence[LocalResult],
    ) -> np.ndarray:
        """``candidates`` plus every pair of an agent whose plan moved farther than its reach bound
        (a replayed fallback under a speed limit, or solver tolerance), so the conflict check never
        relies on a bound a plan broke."""
        own = own_positions(results)
        moved = np.max(np.abs(own - self.settings.model.position(np.asarray(states))[:, :, None]), axis=(1, 2))
        escaped = moved > reach_radius(states, self.settings)
        if not escaped.any():
            return candidates
        checked = candidates | escaped[:, None] | escaped[None, :]
        np.fill_diagonal(checked, False)
        return checked

    def stranded_fallbacks(self, results: Sequence[LocalResult]) -> list[tuple[int, int]]:
        """(fallback agent, other agent) pairs whose plans come closer than d_min / 2 (signed
        distance to the pair's Delta_ij box) at a constrained step: a fallback nobody re-planned
        around, or two agents failing together, each blind to the other's fallback."""
        fell = [r.agent for r in results if r.fallback]
        if not fell:
            return []
        own = own_positions(results)
        pairs = []
        for i in fell:
            half = self.pair_delta(i, slice(None))[:, :, None]  # (M, d, 1)
            signed = box_signed_distance(own[i][None] - own, half, axis=1).min(axis=1)
            signed[i] = np.inf
            pairs += [(i, int(j)) for j in np.flatnonzero(signed < 0.5 * self.settings.d_min)]
        return pairs
