"""What a run folder holds, as data: the single source of truth of ``docs/run-folder-reference.md``.

Every file of a run folder, every key of ``summary.json`` and every array of ``trajectory.npz``,
``steps.npz`` and ``admm.npz`` is one entry below, with its shape, units, when it is present and
what it means. The reference page is generated from these tuples (:mod:`swarmpc.docgen`), and
``tests/test_docs.py`` writes real run folders and checks that they hold exactly the documented
keys and arrays, with the documented shapes and dtypes: a key that is written but not documented
here (or documented but no longer written) fails the tests instead of going stale silently.

Shapes use T (closed-loop steps), M (agents), d (spatial dimension, 2 or 3), I (the most ADMM
iterations of any step) and fixed sizes written as numbers; ``when`` is one of :data:`CONDITIONS`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from swarmpc.config import Scenario

__all__ = [
    "ARRAYS",
    "CONDITIONS",
    "FILES",
    "SUMMARY_KEYS",
    "ArrayDoc",
    "FileDoc",
    "KeyDoc",
    "conditions_of",
    "expected_shapes",
]

CONDITIONS: Mapping[str, str] = MappingProxyType({
    "always": "every run",
    "admm": "ADMM runs (`solver.method: admm`)",
    "rrt": "runs that used the RRT planner (`solver.initial_guess: rrt`, or `auto` with obstacles)",
    "noise": "runs with process noise (`disturbance.process_position_std` or `process_velocity_std` > 0)",
    "cars": "runs with car agents (`agents[].model: car`)",
    "run": "written by `swarmpc run` (not by `write_run` alone)",
    "request": "written on request, by the command named",
})  # fmt: skip
"""When an entry is present: its code (the ``when`` of each entry) and what that means."""

DATA_CONDITIONS = frozenset({"always", "admm", "rrt", "noise", "cars"})
"""The conditions that depend on the run alone (what :func:`conditions_of` can decide)."""


@dataclass(frozen=True)
class FileDoc:
    """A file of a run folder."""

    name: str
    when: str
    meaning: str


@dataclass(frozen=True)
class KeyDoc:
    """A key of ``summary.json``; nested keys are dotted (``step_time_ms.median``).

    A key documented without dotted children (``disturbance``) is a leaf: its value's own keys
    are documented elsewhere (here: the scenario reference).
    """

    key: str
    type: str
    units: str
    when: str
    meaning: str


@dataclass(frozen=True)
class ArrayDoc:
    """An array of one of the run folder's ``.npz`` archives."""

    file: str
    name: str
    shape: str
    dtype: str
    units: str
    when: str
    meaning: str


FILES: tuple[FileDoc, ...] = (
    FileDoc("summary.json", "always", "The run's metrics and settings (the keys below)."),
    FileDoc(
        "trajectory.npz", "always",
        "The closed-loop trajectory: states, inputs, goals, Δ, bodies, dt, poses and footprints (arrays below).",
    ),
    FileDoc("steps.npz", "always", "Per-step solver records: solve times, failures, fallbacks, slack."),
    FileDoc("admm.npz", "admm", "ADMM residual histories and the neighbours each agent held, per step."),
    FileDoc(
        "scenario.yaml", "always",
        "The fully resolved scenario (every default filled in; see the "
        "[scenario reference](scenario-reference.md)). Re-running it reproduces the run.",
    ),
    FileDoc(
        ".swarmpc-run", "always",
        'Marker, written last: JSON `{"format": "swarmpc-run", "version": 1}`. Only folders with '
        "it are ever replaced (`--overwrite`).",
    ),
    FileDoc("trajectory.png", "run", "Figure of the trajectories (also `swarmpc plot`)."),
    FileDoc("convergence.png", "request", "`swarmpc plot` of an ADMM run: residuals per iteration."),
    FileDoc("animation.gif, animation.mp4", "request", "`swarmpc animate`."),
    FileDoc("view.html", "request", "`swarmpc view`: one self-contained interactive page."),
    FileDoc("run.csv, run.mcap", "request", "`swarmpc export` (formats below)."),
)

SUMMARY_KEYS: tuple[KeyDoc, ...] = (
    KeyDoc("scenario", "string", "–", "always", "Scenario name."),
    KeyDoc("method", "string", "–", "always", "`admm` or `centralized`."),
    KeyDoc("collision", "string", "–", "always", "`hard` or `soft` (the OBCA form)."),
    KeyDoc("num_agents", "integer", "–", "always", "Number of agents M."),
    KeyDoc("dim", "integer", "–", "always", "Spatial dimension d (2 or 3)."),
    KeyDoc("delta", "number or list of d numbers", "m", "always", "Δ as the scenario gives it (scalar or per axis)."),
    KeyDoc("steps", "integer", "–", "always", "Closed-loop steps T taken (inputs applied)."),
    KeyDoc("sim_time_s", "number", "s", "always", "Simulated time T·dt."),
    KeyDoc("all_reached", "boolean", "–", "always", "Every agent ended at its goal (see `reached`)."),
    KeyDoc(
        "reached", "list of M booleans", "–", "always",
        "Per agent: the final position is within `stop.goal_tolerance` (Euclidean) of the goal (a car's "
        "heading also within `stop.heading_tolerance_deg` of the goal's).",
    ),
    KeyDoc(
        "collisions", "integer", "–", "always",
        "Pairs (k, i < j) over the T+1 states whose bodies overlap: |p_i,a − p_j,a| < b_i,a + b_j,a on every axis a "
        "(b: body half-sizes, Δ/2 by default, so the test is ‖p_i − p_j‖_∞ < Δ; 1e-9 m tolerance). In a run with "
        "cars: pairs whose footprints (`trajectory.npz` `poses`, `footprints`) overlap by more than 1e-9 m by the "
        "exact distance between the rectangles.",
    ),
    KeyDoc(
        "min_separation_inf", "number or null", "m", "always",
        "Smallest ‖p_i − p_j‖_∞ over all states and pairs; null with one agent.",
    ),
    KeyDoc(
        "min_footprint_distance", "number or null", "m", "cars",
        "Smallest exact distance between two agents' footprints over all states and pairs (negative: minus the "
        "deepest overlap); null with one agent.",
    ),
    KeyDoc(
        "min_separation_ratio", "number or null", "–", "always",
        "Smallest max_a |p_i,a − p_j,a| / (b_i,a + b_j,a) (/ Δ_a with default bodies) over all states and pairs; "
        "< 1 is a collision; null with one agent.",
    ),
    KeyDoc(
        "max_obstacle_penetration", "number or null", "m", "always",
        "Deepest any agent's body reached into an obstacle (≤ 0: never inside); null without obstacles. A car's "
        "is its footprint's penetration depth by the exact distance (minus its least clearance when outside).",
    ),
    KeyDoc(
        "max_workspace_excursion", "number or null", "m", "always",
        "Farthest any agent's position (a car's reference point) got outside the workspace box over the run "
        "(0: never outside); null without a `workspace`.",
    ),
    KeyDoc(
        "time_to_goal_s", "list of M numbers or nulls", "s", "always",
        "Per agent: the first time from which it stays within `stop.goal_tolerance` of its goal to the end "
        "of the run; null if it never does.",
    ),
    KeyDoc(
        "makespan_s", "number or null", "s", "always",
        "The latest `time_to_goal_s`; null unless every agent reached.",
    ),
    KeyDoc(
        "overshoot_m", "list of M numbers", "m", "always",
        "Per agent: how far it went past its goal along its start-to-goal direction (0 if never).",
    ),
    KeyDoc("max_slack", "number", "m", "always", "Largest soft-constraint slack α of any solve (0 with `hard`)."),
    KeyDoc(
        "cost", "number", "–", "always",
        "Closed-loop cost Σ_k (s_k − s_g)ᵀQ(s_k − s_g) + u_kᵀRu_k over the applied steps, summed over agents.",
    ),
    KeyDoc("step_time_ms", "mapping", "ms", "always", "Wall time of one MPC step's solve (all agents)."),
    KeyDoc("step_time_ms.median", "number or null", "ms", "always", "Median over the steps; null when T = 0."),
    KeyDoc("step_time_ms.p95", "number or null", "ms", "always", "95th percentile over the steps."),
    KeyDoc("step_time_ms.max", "number or null", "ms", "always", "Slowest step."),
    KeyDoc(
        "agent_step_time_ms", "mapping", "ms", "always",
        "One agent's compute in one step: its whole local steps (solver calls and the bookkeeping "
        "around them, timed where the agent runs), summed over its ADMM iterations and safety passes; "
        "centralised: the step's time / M.",
    ),
    KeyDoc("agent_step_time_ms.median", "number or null", "ms", "always", "Median over steps and agents."),
    KeyDoc("agent_step_time_ms.p95", "number or null", "ms", "always", "95th percentile over steps and agents."),
    KeyDoc(
        "critical_path_ms", "mapping", "ms", "always",
        "Compute on one MPC step's critical path: what the step would take with one core per agent (ADMM: per "
        "batch of local steps the slowest agent's, plus the coordinator's own work, the repair pass's "
        "sequential re-plans in full; centralised: the whole solve). `steps.npz` `critical_path_s` per step.",
    ),
    KeyDoc("critical_path_ms.median", "number or null", "ms", "always", "Median over the steps; null when T = 0."),
    KeyDoc("critical_path_ms.p95", "number or null", "ms", "always", "95th percentile over the steps."),
    KeyDoc("critical_path_ms.p99", "number or null", "ms", "always", "99th percentile over the steps."),
    KeyDoc("critical_path_ms.max", "number or null", "ms", "always", "Slowest step."),
    KeyDoc(
        "deadline_s", "number", "s", "always",
        "The budget `deadline_misses` counts against: `solver.deadline`, or dt when the scenario sets none.",
    ),
    KeyDoc(
        "deadline_misses", "integer", "–", "always",
        "Steps whose critical path exceeded `deadline_s` (with a deadline: the first iteration or the "
        "safety passes alone overran it; their plans are still checked and repaired).",
    ),
    KeyDoc(
        "deadline_stops", "integer", "–", "always",
        "Steps whose ADMM iterations were cut short by `solver.deadline` (0 without one; `steps.npz` "
        "`deadline_stop`).",
    ),
    KeyDoc("admm_iterations", "mapping or null", "–", "always", "ADMM iterations per step; null for centralised runs."),
    KeyDoc("admm_iterations.median", "number or null", "–", "admm", "Median over the steps; null when T = 0."),
    KeyDoc("admm_iterations.mean", "number or null", "–", "admm", "Mean over the steps."),
    KeyDoc("admm_iterations.max", "integer or null", "–", "admm", "Most iterations of any step."),
    KeyDoc(
        "admm_iterations_after_first", "number or null", "–", "admm",
        "Median iterations over the steps after the first (the first starts cold).",
    ),
    KeyDoc("admm_tol", "number", "m", "admm", "`solver.tol`: the residual tolerance of ADMM."),
    KeyDoc("rho", "number", "–", "admm", "`solver.rho`: the ADMM penalty ρ (the starting value when adaptive)."),
    KeyDoc(
        "admm_repairs", "integer or null", "–", "always",
        "Steps whose ADMM plan needed the repair pass; null for centralised runs.",
    ),
    KeyDoc(
        "solver_failures", "integer", "–", "always",
        "Failed solve calls over the run (Σ of `steps.npz` `failures`).",
    ),
    KeyDoc(
        "fallback_steps", "integer", "–", "always",
        "Steps in which at least one agent applied a safe fallback plan.",
    ),
    KeyDoc("fallback_agent_steps", "integer", "–", "always", "(step, agent) pairs that applied a fallback plan."),
    KeyDoc(
        "local_fallbacks", "integer", "–", "always",
        "Local solves that the QP local step (`solver.local: qp`) failed and IPOPT answered instead "
        "(Σ of `steps.npz` `local_fallbacks`); 0 with `local: ipopt` and for centralised runs.",
    ),
    KeyDoc("deadlocks", "integer", "–", "always", "Deadlock events detected (and acted on) during the run."),
    KeyDoc(
        "disturbance", "mapping or null", "–", "always",
        "The scenario's `disturbance` section when any of it is non-zero, else null.",
    ),
    KeyDoc(
        "plant", "mapping", "–", "always",
        "What the inputs were applied to: the scenario's `plant` section (the defaults for the double "
        "integrator); a MuJoCo plant adds `substeps`, `mujoco_version`, `agent_contacts` and `obstacle_contacts`.",
    ),
    KeyDoc("rrt", "mapping", "–", "rrt", "How the RRT planner's initial guesses came about."),
    KeyDoc("rrt.fresh", "integer", "–", "rrt", "Paths planned anew."),
    KeyDoc("rrt.reused", "integer", "–", "rrt", "Guesses taken from a stored path."),
    KeyDoc("rrt.failed", "integer", "–", "rrt", "Fresh plans that found no path (a straight line was used)."),
    KeyDoc(
        "interrupted", "boolean", "–", "always",
        "The run was stopped early (Ctrl-C, SIGTERM); the folder holds what ran.",
    ),
    KeyDoc("wall_time_s", "number", "s", "always", "Wall time of the whole closed loop."),
)

ARRAYS: tuple[ArrayDoc, ...] = (
    ArrayDoc("trajectory.npz", "t", "(T+1,)", "float64", "s", "always", "Time of each state: k·dt."),
    ArrayDoc(
        "trajectory.npz", "states", "(T+1, M, 2d)", "float64", "m, m/s", "always",
        "State of each agent at each time, in its own model's layout (`agents[].model`): a point agent's "
        "[position, velocity], a car's [x, y, θ, v] (rear axle centre [m], heading [rad], signed speed [m/s]; "
        "cars are planar, so both are 4 wide); `states[0]` are the starts.",
    ),
    ArrayDoc(
        "trajectory.npz", "inputs", "(T, M, d)", "float64", "m/s²", "always",
        "Input applied from `t[k]` to `t[k+1]`, in the agent's model's layout: a point agent's acceleration, a "
        "car's [a, δ] (m/s², steering rad): `states[k+1]` is the agent's discrete dynamics applied to "
        "`states[k]`, `inputs[k]` (plus `disturbances[k]`).",
    ),
    ArrayDoc(
        "trajectory.npz", "goals", "(M, 2d)", "float64", "m, m/s", "always",
        "Goal state of each agent, in its model's layout (a car's heading in rad).",
    ),
    ArrayDoc(
        "trajectory.npz", "delta", "() or (d,)", "float64", "m", "always",
        "Δ: the clearance between two default bodies' centres (body half-size Δ/2); such agents collide when "
        "|p_i,a − p_j,a| < Δ_a on every axis a. A scalar is the same on every axis.",
    ),
    ArrayDoc(
        "trajectory.npz", "bodies", "(M, d)", "float64", "m", "always",
        "Half-size b_i of each agent's body per axis (the scenario's `agents[].body`, Δ/2 by default): agents i "
        "and j collide when |p_i,a − p_j,a| < b_i,a + b_j,a on every axis a. A car's row is half its footprint, "
        "[length/2, width/2] in its own frame.",
    ),
    ArrayDoc("trajectory.npz", "dt", "()", "float64", "s", "always", "Sampling time."),
    ArrayDoc(
        "trajectory.npz", "poses", "(T+1, M, 3)", "float64", "m, m, rad", "always",
        "Pose [x, y, θ] of each agent's footprint centre in the plane at each time. A point agent's is its "
        "position (in 3D its first two coordinates) with θ = 0; a car's is the centre of its rectangle and "
        "its heading.",
    ),
    ArrayDoc(
        "trajectory.npz", "footprints", "(M, 2)", "float64", "m", "always",
        "Footprint [length, width] of each agent in the plane, a rectangle centred on its pose and turned by θ. "
        "A point agent's is the box its body keeps clear on the x and y axes: 2·`bodies[i, :2]`.",
    ),
    ArrayDoc(
        "trajectory.npz", "disturbances", "(T, M, 2d)", "float64", "m, m/s", "noise",
        "Process noise added to the state after step k: `states[k+1] = f(states[k], inputs[k]) + disturbances[k]`.",
    ),
    ArrayDoc(
        "steps.npz", "step_time_s", "(T,)", "float64", "s", "always",
        "Wall time of each step's solve (all agents).",
    ),
    ArrayDoc(
        "steps.npz", "agent_time_s", "(T, M)", "float64", "s", "always",
        "Each agent's compute in each step (its whole local steps, timed where it runs), summed over its "
        "ADMM iterations and safety passes (centralised: step time / M).",
    ),
    ArrayDoc("steps.npz", "failures", "(T,)", "int64", "–", "always", "Failed solve calls in each step."),
    ArrayDoc(
        "steps.npz", "fallback", "(T, M)", "bool", "–", "always",
        "Which agents applied a safe fallback plan (their solve failed) in each step.",
    ),
    ArrayDoc(
        "steps.npz", "max_slack", "(T,)", "float64", "m", "always",
        "Largest soft-constraint slack α of each step's plan (0 with `hard`).",
    ),
    ArrayDoc(
        "steps.npz", "repaired", "(T,)", "bool", "–", "always",
        "Whether each step's ADMM plan needed the repair pass.",
    ),
    ArrayDoc(
        "steps.npz", "critical_path_s", "(T,)", "float64", "s", "always",
        "Compute on each step's critical path: Σ over the step's batches of local steps (ADMM iterations, "
        "repair re-plans) of the slowest agent's, plus the coordinator's own work; centralised: the step's solve.",
    ),
    ArrayDoc(
        "steps.npz", "deadline_stop", "(T,)", "bool", "–", "always",
        "Whether ADMM stopped iterating in each step because the next iteration would overrun `solver.deadline`.",
    ),
    ArrayDoc(
        "steps.npz", "local_fallbacks", "(T,)", "int64", "–", "always",
        "Local solves of each step (ADMM iterations and safety passes) that the QP local step failed and "
        "IPOPT answered instead; 0 with `solver.local: ipopt` and for centralised runs.",
    ),
    ArrayDoc(
        "admm.npz", "primal", "(T, I)", "float64", "m", "admm",
        "Primal residual per step and iteration: RMS of the plans' positions minus the consensus; NaN after "
        "the step converged.",
    ),
    ArrayDoc(
        "admm.npz", "dual", "(T, I)", "float64", "ρ·m", "admm",
        "Dual residual per step and iteration: ρ times the RMS change of the consensus; NaN after convergence.",
    ),
    ArrayDoc(
        "admm.npz", "rho", "(T, I)", "float64", "–", "admm",
        "Penalty ρ of each iteration; NaN after convergence.",
    ),
    ArrayDoc(
        "admm.npz", "iterations", "(T,)", "int64", "–", "admm",
        "ADMM iterations of each step (I is their maximum).",
    ),
    ArrayDoc(
        "admm.npz", "copies", "(T, M)", "int64", "–", "admm",
        "How many neighbours' plan copies each agent held at the end of each step.",
    ),
    ArrayDoc(
        "admm.npz", "planes", "(T, M)", "int64", "–", "admm",
        "How many separating planes each agent kept to at the end of each step (0 without `solver.plane_margin`).",
    ),
)


def conditions_of(scenario: Scenario) -> frozenset[str]:
    """The :data:`DATA_CONDITIONS` that hold for a run of ``scenario``: which conditional keys,
    arrays and files its folder has (mirrors :class:`swarmpc.simulation.guessing` for ``rrt``)."""
    held = {"always"}
    if scenario.solver.method == "admm":
        held.add("admm")
    guess = scenario.solver.initial_guess
    if guess == "rrt" or (guess == "auto" and scenario.obstacles):
        held.add("rrt")
    if scenario.disturbance.has_process_noise:
        held.add("noise")
    if scenario.has_cars:
        held.add("cars")
    return frozenset(held)


_SHAPE = re.compile(r"\(([^()]*)\)")


def expected_shapes(shape: str, sizes: Mapping[str, int]) -> list[tuple[int, ...]]:
    """The concrete shapes a documented ``shape`` (``"(T+1, M, 2d)"``, ``"() or (d,)"``,
    ``"(M, 2)"``) allows for the sizes ``T``, ``M``, ``d`` and ``I`` of a run; a number is a
    fixed size."""
    values = {"T+1": sizes["T"] + 1, "2d": 2 * sizes["d"], **sizes}
    shapes = []
    for inner in _SHAPE.findall(shape):
        tokens = [token.strip() for token in inner.split(",") if token.strip()]
        shapes.append(tuple(int(token) if token.isdigit() else values[token] for token in tokens))
    return shapes
