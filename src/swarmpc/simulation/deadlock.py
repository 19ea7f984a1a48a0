"""Deadlock detection and resolution for symmetric encounters.

Agents that meet head-on (or four agents crossing a square) can settle into a symmetric
equilibrium of the MPC: every agent far from its goal, none moving. When an agent has stayed
slow and far from its goal, with another agent close by, for ``patience`` steps, its goal is temporarily replaced by a detour
point to the right of its goal direction (a right-hand rule: every blocked agent turns the same
way, so a jam unwinds like a roundabout) for ``hold`` steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DeadlockPolicy:
    speed_threshold: float = 0.05
    distance_threshold: float = 0.2
    patience: int = 4
    neighbour_radius: float = 1.0
    hold: int = 15
    detour: float = 1.0
    angle_deg: float = 75.0


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

    def __init__(self, num_agents: int, dim: int, policy: DeadlockPolicy = DeadlockPolicy()) -> None:
        self.policy = policy
        self.dim = dim
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
        stalled = (speeds < p.speed_threshold) & (distance > p.distance_threshold) & crowded
        self._stalled = np.where(stalled, self._stalled + 1, 0)
        out = goals.copy()
        for i in np.flatnonzero((self._stalled >= p.patience) & (self._detour_left == 0)):
            direction = right_turn(to_goal[i] / distance[i], np.radians(p.angle_deg))
            target = np.zeros_like(goals[i])
            target[:d] = positions[i] + p.detour * min(1.0, distance[i]) * direction
            self._detour_goal[int(i)] = target
            self._detour_left[i] = p.hold
            self._stalled[i] = 0
            self.events.append((step, int(i)))
        for i in np.flatnonzero(self._detour_left > 0):
            out[i] = self._detour_goal[int(i)]
            self._detour_left[i] -= 1
        return out
