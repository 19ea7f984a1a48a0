"""Run metrics, recomputed from the saved arrays (the ``summary.json`` keys of
docs/run-folder-reference.md). Positions are read from the states through the scenario's agent
model (:meth:`swarmpc.config.Scenario.agent_model`).

Safety is measured between the agents' bodies (half-sizes ``Scenario.bodies``): a pair collides
when its bodies overlap, |p_i - p_j| < b_i + b_j on every axis (< delta with default bodies), and
an obstacle is entered when a body reaches into it."""

from __future__ import annotations

from typing import Any

import numpy as np

from swarmpc.config import Scenario
from swarmpc.model.geometry import (
    body_obstacle_penetration,
    body_separation_ratio,
    count_body_collisions,
    inf_separation_ratio,
)


def closed_loop_cost(states: np.ndarray, inputs: np.ndarray, scn: Scenario) -> float:
    """sum_t (s_t - s_g)' Q (s_t - s_g) + u_t' R u_t over the applied steps, summed over agents."""
    Q, R = scn.matrix("Q"), scn.matrix("R")
    errors = states[:-1] - scn.goal_states()[None]
    state_cost = np.einsum("tmi,ij,tmj->", errors, Q, errors)
    input_cost = np.einsum("tmi,ij,tmj->", inputs, R, inputs)
    return float(state_cost + input_cost)


def min_separation_inf(positions: np.ndarray) -> float:
    """Smallest inf-norm distance between any two agents over the run (inf for one agent)."""
    if positions.shape[1] < 2:
        return float("inf")
    ratio = inf_separation_ratio(positions, np.ones(positions.shape[2]))
    return float(ratio.min())


def final_goal_distance(states: np.ndarray, scn: Scenario) -> np.ndarray:
    """Per agent, the Euclidean distance of its last position to its goal."""
    model = scn.agent_model()
    return np.linalg.norm(model.position(states[-1]) - model.position(scn.goal_states(model)), axis=1)


def stats(values: np.ndarray | list[float], scale: float = 1.0) -> dict[str, float | None]:
    """Median, p95 and max (None when empty)."""
    array = np.asarray(values, float) * scale
    if array.size == 0:
        return {"median": None, "p95": None, "max": None}
    return {
        "median": float(np.median(array)),
        "p95": float(np.percentile(array, 95)),
        "max": float(np.max(array)),
    }


def summarize(
    scn: Scenario,
    method: str,
    states: np.ndarray,
    inputs: np.ndarray,
    step_times: np.ndarray,
    admm_iterations: np.ndarray | None,
    solver_failures: int,
    max_slack: float,
    deadlock_events: int,
    interrupted: bool,
    wall_time: float,
) -> dict[str, Any]:
    """The ``summary.json`` dictionary: every number recomputed from the trajectory."""
    d = scn.dim
    positions = scn.agent_model().position(states)
    bodies = scn.bodies
    reached = final_goal_distance(states, scn) <= scn.stop.goal_tolerance + 1e-9
    separation = min_separation_inf(positions)
    ratio = body_separation_ratio(positions, bodies).min() if scn.num_agents > 1 else float("inf")
    penetration = max(
        (float(body_obstacle_penetration(positions, bodies, G, g).max()) for G, g in scn.obstacle_halfspaces()),
        default=None,
    )
    return {
        "scenario": scn.name,
        "method": method,
        "collision": scn.collision,
        "num_agents": scn.num_agents,
        "dim": d,
        "delta": scn.delta if isinstance(scn.delta, (int, float)) else list(scn.delta),
        "steps": int(inputs.shape[0]),
        "sim_time_s": float(inputs.shape[0] * scn.dt),
        "all_reached": bool(reached.all()),
        "reached": [bool(r) for r in reached],
        "collisions": count_body_collisions(positions, bodies) if scn.num_agents > 1 else 0,
        "min_separation_inf": _finite_or_none(separation),
        "min_separation_ratio": _finite_or_none(float(ratio)),
        "max_obstacle_penetration": penetration,
        "max_slack": float(max_slack),
        "cost": closed_loop_cost(states, inputs, scn),
        "step_time_ms": stats(step_times, 1000.0),
        "admm_iterations": None
        if admm_iterations is None
        else {
            "median": float(np.median(admm_iterations)),
            "mean": float(np.mean(admm_iterations)),
            "max": int(np.max(admm_iterations)),
        }
        if len(admm_iterations)
        else {"median": None, "mean": None, "max": None},
        "solver_failures": int(solver_failures),
        "deadlocks": int(deadlock_events),
        "interrupted": bool(interrupted),
        "wall_time_s": float(wall_time),
    }


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
