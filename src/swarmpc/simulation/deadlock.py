"""Deadlock detection and resolution for symmetric encounters.

Agents that meet head-on (or four agents crossing a square) can settle into a symmetric
equilibrium of the MPC: every agent far from its goal, none moving. When an agent has stayed
slow and far from its goal, with another agent close by, for ``patience`` steps, its goal is temporarily replaced by a detour
point to the right of its goal direction (a right-hand rule: every blocked agent turns the same
way, so a jam unwinds like a roundabout) for ``hold`` steps.

An agent within ``approach_radius`` of its goal that still gets closer by ``min_progress`` per
step is approaching, not jammed, however slowly: with the paper's weights the last metre to the
goal is crawled at a few cm/s, and detouring such an agent (circle-16: the last agents squeezing
into their slots between parked neighbours) only pushes it away again.

An agent stuck alone, more than ``approach_radius`` from its goal (against the corner of a
static obstacle, where the straight line and the OBCA certificate form a local minimum), is
detoured the same way after ``lonely_patience`` steps, without a neighbour in sight.

Large symmetric swaps (circle, M = 16) can fall into a cycle: the same groups of agents detour
together, come back together and jam again. Once an agent has detoured ``escalate_after`` times,
its further detours are escalated and de-synchronised: the angle is jittered by up to ``jitter_deg`` and the
hold stretched by a random factor in [1, 1 + ``stretch``], drawn from a generator seeded by the
scenario seed, so the agents of a jam return at different times and pass one by one. Runs whose
agents detour fewer times draw nothing and are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DeadlockPolicy:
    """Thresholds of the detector and shape of the detour (m, m/s, steps, degrees)."""

    speed_threshold: float = 0.05
    distance_threshold: float = 0.2
    patience: int = 4
    neighbour_radius: float = 1.0
    hold: int = 15
    detour: float = 1.0
    angle_deg: float = 75.0
    approach_radius: float = 1.0
    lonely_patience: int = 12
    min_progress: float = 0.002
    escalate_after: int = 2
    jitter_deg: float = 30.0
    stretch: float = 2.0


def right_turn(direction: np.ndarray, angle: float) -> np.ndarray:
    """``direction`` rotated clockwise by ``angle`` about the vertical (z) axis.

    In 3D a purely vertical direction is turned about the x axis instead.
    """
    c, s = np.cos(angle), np.sin(angle)
    out = direction.copy()
    if np.linalg.norm(direction[:2]) < 1e-9 and direction.size == 3:
        out[1], out[2] = c * direction[1] + s * direction[2], -s * direction[1] + c * direction[2]
        out[1] = out[1] if np.linalg.norm(out) > 1e-9 else 1.0
        return out
    out[0], out[1] = c * direction[0] + s * direction[1], -s * direction[0] + c * direction[1]
    return out


class DeadlockResolver:
    """Tracks stalled agents and hands out the goals the MPC should use this step."""

    def __init__(
        self, num_agents: int, dim: int, policy: DeadlockPolicy = DeadlockPolicy(), seed: int = 0
    ) -> None:
        self.policy = policy
        self.dim = dim
        self._repeats = np.zeros(num_agents, int)
        self._rng = np.random.default_rng([seed, 0xD1])
        self._distance: np.ndarray | None = None
        self._stalled = np.zeros(num_agents, int)
        self._detour_left = np.zeros(num_agents, int)
        self._detour_goal: dict[int, np.ndarray] = {}
        self.events: list[tuple[int, int]] = []

    @property
    def active(self) -> np.ndarray:
        return self._detour_left > 0

    def goals(self, step: int, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Goals for this step: the true ones, or a detour for agents found deadlocked."""
        p, d = self.policy, self.dim
        positions, speeds = states[:, :d], np.linalg.norm(states[:, d:], axis=1)
        to_goal = goals[:, :d] - positions
        distance = np.linalg.norm(to_goal, axis=1)
        gaps = np.max(np.abs(positions[:, None] - positions[None, :]), axis=2)
        np.fill_diagonal(gaps, np.inf)
        crowded = gaps.min(axis=1) < p.neighbour_radius if len(positions) > 1 else np.zeros(1, bool)
        progress = self._distance - distance if self._distance is not None else np.zeros_like(distance)
        self._distance = distance
        approaching = (distance < p.approach_radius) & (progress >= p.min_progress)
        stalled = (speeds < p.speed_threshold) & (distance > p.distance_threshold) & ~approaching
        stalled &= crowded | (distance > p.approach_radius)
        self._stalled = np.where(stalled, self._stalled + 1, 0)
        due = np.where(crowded, self._stalled >= p.patience, self._stalled >= p.lonely_patience)
        out = goals.copy()
        for i in np.flatnonzero(due & (self._detour_left == 0)):
            angle, hold = p.angle_deg, p.hold
            if self._repeats[i] >= p.escalate_after:
                # the same agent jammed again: break the symmetry that brought it back
                angle += self._rng.uniform(-p.jitter_deg, p.jitter_deg)
                hold = int(round(hold * self._rng.uniform(1.0, 1.0 + p.stretch)))
            self._repeats[i] += 1
            direction = right_turn(to_goal[i] / distance[i], np.radians(angle))
            target = np.zeros_like(goals[i])
            target[:d] = positions[i] + p.detour * min(1.0, distance[i]) * direction
            self._detour_goal[int(i)] = target
            self._detour_left[i] = hold
            self._stalled[i] = 0
            self.events.append((step, int(i)))
        for i in np.flatnonzero(self._detour_left > 0):
            out[i] = self._detour_goal[int(i)]
            self._detour_left[i] -= 1
        return out
