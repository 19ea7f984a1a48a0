"""Closed-loop quality: how fast and how cleanly the agents reach their goals.

Every metric is plain numpy on the arrays a run folder saves (``trajectory.npz``: ``states``,
``goals``, ``dt``, ``inputs``) and the scenario's goal tolerance, so it can be recomputed from the
folder alone (:func:`run_folder_quality`). The ``summary.json`` keys fixed by the design
(``time_to_goal_s``, ``makespan_s``, ``overshoot_m``) come from :func:`quality_summary`.

* time to goal: the first time an agent is within the goal tolerance and stays within it to the
  end of the run (a pass through the goal that leaves again does not count);
* makespan: the latest time to goal over the agents (undefined unless every agent reached);
* overshoot: how far an agent went past its goal along its start-to-goal direction;
* interaction ratio: the makespan of the swarm over the makespan its agents would have alone,
  each with the same controller, which is what the interaction between the agents costs.

Undefined values are NaN in the arrays and None (JSON null) in the summary.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from swarmpc.config import load_scenario

__all__ = [
    "GOAL_SLACK",
    "control_effort",
    "interaction_ratio",
    "makespan",
    "overshoot",
    "quality_summary",
    "run_folder_quality",
    "time_to_goal",
]

GOAL_SLACK = 1e-9
"""Added to the goal tolerance, as in the ``reached`` flags of the summary, so an agent reported as
reached always has a time to goal."""


def _positions(states: np.ndarray) -> np.ndarray:
    """(T+1, M, d) positions of (T+1, M, 2d) states."""
    states = np.asarray(states, float)
    return states[..., : states.shape[-1] // 2]


def time_to_goal(states: np.ndarray, goals: np.ndarray, dt: float, tolerance: float) -> np.ndarray:
    """Per agent, the first time from which it stays within ``tolerance`` of its goal to the end.

    Parameters
    ----------
    states
        (T+1, M, 2d) closed-loop states [position, velocity].
    goals
        (M, 2d) goal states (only the positions are used).
    dt
        Sampling time [s]; state k is at time k·dt.
    tolerance
        Goal tolerance on the Euclidean position error [m].

    Returns
    -------
    numpy.ndarray
        (M,) times [s]; NaN for an agent not within the tolerance at the end of the run.
    """
    positions = _positions(states)
    error = np.linalg.norm(positions - _positions(goals)[None], axis=-1)
    within = error <= tolerance + GOAL_SLACK
    stays = np.flip(np.logical_and.accumulate(np.flip(within, axis=0), axis=0), axis=0)
    first = np.argmax(stays, axis=0).astype(float)
    return np.where(stays[-1], first * dt, np.nan)


def makespan(times: np.ndarray) -> float:
    """The latest time to goal over the agents; NaN unless every agent has one."""
    times = np.asarray(times, float)
    if times.size == 0 or np.isnan(times).any():
        return float("nan")
    return float(times.max())


def overshoot(states: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """Per agent, the largest distance [m] it went past its goal along its start-to-goal direction.

    The direction runs from the first state's position to the goal; the overshoot is the largest
    component of (position − goal) along it over the run, and 0 when the agent never got past
    the goal (or starts at it, where there is no direction to overshoot along).

    Returns
    -------
    numpy.ndarray
        (M,) overshoots, each >= 0.
    """
    positions = _positions(states)
    goal = _positions(goals)
    move = goal - positions[0]
    length = np.linalg.norm(move, axis=-1)
    direction = np.divide(move, length[:, None], out=np.zeros_like(move), where=length[:, None] > 0)
    past = np.einsum("tmd,md->tm", positions - goal[None], direction)
    return np.maximum(past.max(axis=0), 0.0)


def control_effort(inputs: np.ndarray, dt: float) -> np.ndarray:
    """Per agent, Σ_k ‖u_k‖² dt over the applied inputs (T, M, d): the energy of the command."""
    inputs = np.asarray(inputs, float)
    return np.einsum("tmd,tmd->m", inputs, inputs) * dt


def interaction_ratio(swarm_makespan: float | None, lone_times: np.ndarray | list[float | None]) -> float | None:
    """The swarm's makespan over the latest of its agents' lone-agent times (same controller).

    1 means the agents did not slow each other down; 2, that the swarm took twice as long as its
    slowest agent would have alone. None when either side is undefined (an agent that never
    reached, alone or in the swarm) or every agent starts at its goal (nothing to compare).
    """
    lone = np.array([np.nan if t is None else t for t in lone_times], float)
    if swarm_makespan is None or not np.isfinite(swarm_makespan) or lone.size == 0 or np.isnan(lone).any():
        return None
    slowest = float(lone.max())
    return float(swarm_makespan) / slowest if slowest > 0 else None


def _or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def quality_summary(states: np.ndarray, goals: np.ndarray, dt: float, tolerance: float) -> dict[str, Any]:
    """The ``summary.json`` quality keys: ``time_to_goal_s`` (per agent, null if never),
    ``makespan_s`` (null unless every agent reached) and ``overshoot_m`` (per agent)."""
    times = time_to_goal(states, goals, dt, tolerance)
    return {
        "time_to_goal_s": [_or_none(t) for t in times],
        "makespan_s": _or_none(makespan(times)),
        "overshoot_m": [float(x) for x in overshoot(states, goals)],
    }


def run_folder_quality(folder: str | Path) -> dict[str, Any]:
    """:func:`quality_summary` recomputed from a run folder's ``trajectory.npz`` and the goal
    tolerance of its ``scenario.yaml``."""
    folder = Path(folder)
    tolerance = load_scenario(folder / "scenario.yaml").stop.goal_tolerance
    with np.load(folder / "trajectory.npz") as data:
        return quality_summary(data["states"], data["goals"], float(data["dt"]), tolerance)
