"""Run metrics, recomputed from the saved arrays (the ``summary.json`` keys of
docs/run-folder-reference.md). Positions are read from the states through the scenario's agent
model (:meth:`swarmpc.config.Scenario.agent_model`).

Safety is measured between the agents' bodies (half-sizes ``Scenario.bodies``): a pair collides
when its bodies overlap, |p_i - p_j| < b_i + b_j on every axis (< delta with default bodies), and
an obstacle is entered when a body reaches into it.

In a run with cars every pair is measured between footprints, by the exact distance between the
rectangles (:func:`swarmpc.model.footprint.rectangle_distance`; a point agent's footprint is its
body box): a pair collides when the footprints overlap by more than 1e-9 m (touching is not a
collision, as for boxes), and a car enters an obstacle when its rectangle does. A car reaches its
goal only with its heading within ``stop.heading_tolerance_deg`` of the goal's too."""

from __future__ import annotations

from typing import Any

import numpy as np

from swarmpc.config import Scenario
from swarmpc.model.footprint import footprint_vertices, polygon_distance, polygon_vertices, rectangle_distance
from swarmpc.model.geometry import (
    body_obstacle_penetration,
    body_separation_ratio,
    count_body_collisions,
    inf_separation_ratio,
)

COLLISION_TOLERANCE = 1e-9
"""Overlap [m] below which two bodies or footprints count as touching, not colliding."""


def heading_error(theta: np.ndarray | float, goal: np.ndarray | float) -> np.ndarray:
    """|theta - goal| wrapped into [0, pi] [rad]: how far a heading is from the goal heading."""
    difference = np.asarray(theta, float) - np.asarray(goal, float)
    return np.abs((difference + np.pi) % (2 * np.pi) - np.pi)


def footprint_poses(scn: Scenario, states: np.ndarray) -> np.ndarray:
    """(..., M, 3) pose of each agent's footprint centre from states (..., M, n): a car's own
    (:meth:`swarmpc.model.car.KinematicCar.pose`), a point agent's position with heading 0."""
    states = np.asarray(states, float)
    poses = np.zeros((*states.shape[:-1], 3))
    for i, model in enumerate(scn.agent_models()):
        own = getattr(model, "pose", None)
        poses[..., i, :] = own(states[..., i, :]) if callable(own) else np.concatenate(
            [states[..., i, :2], np.zeros((*states.shape[:-2], 1))], axis=-1)
    return poses


def footprint_distances(poses: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(T+1, P) signed exact distance between the footprints of every pair i < j (in the order
    of ``numpy.triu_indices``) at every state: negative where they overlap."""
    i, j = np.triu_indices(poses.shape[1], k=1)
    return rectangle_distance(poses[:, i], sizes[i], poses[:, j], sizes[j], signed=True)


def _obstacle_polygon(G: np.ndarray, g: np.ndarray, scn: Scenario) -> np.ndarray | None:
    """The obstacle's vertices clipped to the workspace grown by 100 m (finite for an unbounded
    polytope); None when it is empty or flat there."""
    lower, upper = scn.bounds()
    try:
        return polygon_vertices(np.vstack([G, np.eye(2), -np.eye(2)]), np.concatenate([g, upper + 100, 100 - lower]))
    except ValueError:
        return None


def car_safety(scn: Scenario, states: np.ndarray) -> dict[str, Any]:
    """``collisions``, ``min_footprint_distance`` and ``max_obstacle_penetration`` of a run with
    cars, by the exact distances between footprints (module docstring)."""
    poses, sizes = footprint_poses(scn, states), 2.0 * scn.bodies
    out: dict[str, Any] = {"collisions": 0, "min_footprint_distance": None}
    if scn.num_agents > 1:
        distances = footprint_distances(poses, sizes)
        out = {"collisions": int(np.sum(distances < -COLLISION_TOLERANCE)),
               "min_footprint_distance": float(distances.min())}
    positions, bodies = states[..., :2], scn.bodies
    cars = np.array([a.model.is_car for a in scn.agents])
    depths = []
    for G, g in scn.obstacle_halfspaces():
        if (~cars).any():
            depths.append(float(body_obstacle_penetration(positions[:, ~cars], bodies[~cars], G, g).max()))
        polygon = _obstacle_polygon(G, g, scn)
        if polygon is not None:
            distance = polygon_distance(footprint_vertices(poses[:, cars], sizes[cars]), polygon, signed=True)
            depths.append(-float(distance.min()))
    out["max_obstacle_penetration"] = max(depths, default=None)
    return out


def workspace_excursion(scn: Scenario, states: np.ndarray) -> float | None:
    """Farthest any agent's position (the state rows the workspace bounds: a point agent's centre,
    a car's reference point) got outside the workspace box over the run [m]; 0.0 when it never
    left it, None without a ``workspace``. The local problems hold the box from their first free
    step on, so an agent that cannot stop in time (no speed limit, a 1 s horizon) can still
    coast past a wall."""
    if scn.workspace is None:
        return None
    lower, upper = scn.bounds()
    positions = np.asarray(states, float)[..., : scn.dim]
    outside = np.maximum(lower - positions, positions - upper)
    return float(max(outside.max(), 0.0))


def closed_loop_cost(states: np.ndarray, inputs: np.ndarray, scn: Scenario) -> float:
    """sum_t (s_t - s_g)' Q (s_t - s_g) + u_t' R u_t over the applied steps, summed over agents
    (with cars: each agent's own weights, a car's heading error wrapped into [-pi, pi])."""
    if scn.has_cars:
        return _per_agent_cost(states, inputs, scn)
    Q, R = scn.matrix("Q"), scn.matrix("R")
    errors = states[:-1] - scn.goal_states()[None]
    state_cost = np.einsum("tmi,ij,tmj->", errors, Q, errors)
    input_cost = np.einsum("tmi,ij,tmj->", inputs, R, inputs)
    return float(state_cost + input_cost)


def _per_agent_cost(states: np.ndarray, inputs: np.ndarray, scn: Scenario) -> float:
    """:func:`closed_loop_cost` agent by agent with each agent's own model's weights."""
    total = 0.0
    for i, (model, agent, goal) in enumerate(zip(scn.agent_models(), scn.agents, scn.goal_states(), strict=True)):
        Q, R = scn.matrix("Q", model), scn.matrix("R", model)
        errors = states[:-1, i] - goal
        if agent.model.is_car:
            errors[:, 2] = (errors[:, 2] + np.pi) % (2 * np.pi) - np.pi
        step_inputs = inputs[:, i]
        total += float(np.einsum("ti,ij,tj->", errors, Q, errors)
                       + np.einsum("ti,ij,tj->", step_inputs, R, step_inputs))
    return total


def goal_errors_within(states: np.ndarray, scn: Scenario) -> np.ndarray:
    """Per agent, whether the last state is within ``stop.goal_tolerance`` of the goal position
    (and, for a car, within ``stop.heading_tolerance_deg`` of the goal heading)."""
    reached = final_goal_distance(states, scn) <= scn.stop.goal_tolerance + 1e-9
    if scn.has_cars:
        goals = scn.goal_states()
        for i, agent in enumerate(scn.agents):
            if agent.model.is_car:
                error = np.degrees(heading_error(states[-1, i, 2], goals[i, 2]))
                reached[i] &= bool(error <= scn.stop.heading_tolerance_deg + 1e-9)
    return reached


def min_separation_inf(positions: np.ndarray) -> float:
    """Smallest inf-norm distance between any two agents over the run (inf for one agent)."""
    if positions.shape[1] < 2:
        return float("inf")
    ratio = inf_separation_ratio(positions, np.ones(positions.shape[2]))
    return float(ratio.min())


def final_goal_distance(states: np.ndarray, scn: Scenario) -> np.ndarray:
    """Per agent, the Euclidean distance of its last position to its goal."""
    if scn.has_cars:  # every model in the plane holds the position in its first two entries
        return np.linalg.norm(states[-1][:, :2] - scn.goal_states()[:, :2], axis=1)
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
    reached = goal_errors_within(states, scn)
    separation = min_separation_inf(positions)
    ratio = body_separation_ratio(positions, bodies).min() if scn.num_agents > 1 else float("inf")
    penetration = max(
        (float(body_obstacle_penetration(positions, bodies, G, g).max()) for G, g in scn.obstacle_halfspaces()),
        default=None,
    )
    summary: dict[str, Any] = {
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
        "max_workspace_excursion": workspace_excursion(scn, states),
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
    if scn.has_cars:
        summary.update(car_safety(scn, states))
    return summary


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
