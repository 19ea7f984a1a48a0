"""Closed-loop runs through the CLI, checked from the saved arrays alone."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import dynamics_error, load_folder, recount_collisions, run_cli
from swarmpc.config import load_scenario, scenario_to_yaml
from swarmpc.model.dynamics import discrete_matrices
from swarmpc.model.geometry import obstacle_penetration
from swarmpc.scenarios import builtin_scenario
from swarmpc.solvers.qp_local import speed_polytope


@pytest.fixture(scope="module", params=["paper-2d", pytest.param("paper-3d", marks=pytest.mark.loop)])
def centralized_run(request, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / request.param
    done = run_cli("run", request.param, "--method", "centralized", "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    return out


def test_centralized_reaches_goals_without_collision(centralized_run):
    summary, arrays = load_folder(centralized_run)
    states, goals = arrays["states"], arrays["goals"]
    d = states.shape[2] // 2
    final_gap = np.linalg.norm(states[-1, :, :d] - goals[:, :d], axis=1)
    assert np.all(final_gap <= 0.05 + 1e-9)
    collisions, ratio = recount_collisions(states, arrays["delta"])
    assert collisions == 0 and ratio >= 1.0
    assert summary["collisions"] == collisions and summary["all_reached"]
    assert dynamics_error(states, arrays["inputs"], float(arrays["dt"])) < 1e-9
    assert (centralized_run / "trajectory.png").stat().st_size > 10_000


def test_contract_keys_and_shapes(centralized_run):
    summary, arrays = load_folder(centralized_run)
    for key in ["scenario", "method", "collision", "num_agents", "dim", "delta", "steps", "all_reached",
                "reached", "collisions", "min_separation_inf", "max_slack", "cost", "step_time_ms",
                "admm_iterations", "solver_failures", "wall_time_s"]:
        assert key in summary
    T1, M, nx = arrays["states"].shape
    assert arrays["t"].shape == (T1,) and arrays["inputs"].shape == (T1 - 1, M, nx // 2)
    assert arrays["goals"].shape == (M, nx) and summary["steps"] == T1 - 1
    assert summary["method"] == "centralized" and summary["admm_iterations"] is None


@pytest.mark.loop
def test_static_obstacles_are_avoided(tmp_path):
    out = tmp_path / "door"
    done = run_cli("run", "wall-door", "--method", "centralized", "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    summary, arrays = load_folder(out)
    scn = load_scenario(out / "scenario.yaml")
    positions = arrays["states"][:, :, : scn.dim]
    for G, g in scn.obstacle_halfspaces():
        # clearance >= 0: no saved position is inside an obstacle
        assert obstacle_penetration(positions, G, g).max() <= 1e-9
    assert summary["all_reached"]


def _run_variant(tmp_path, name: str, **changes) -> tuple[dict, dict]:
    """paper-2d with ``changes`` applied, written to a YAML file and run through the CLI."""
    scn = builtin_scenario("paper-2d").with_updates(**changes)
    path = tmp_path / f"{name}.yaml"
    path.write_text(scenario_to_yaml(scn))
    out = tmp_path / name
    done = run_cli("run", str(path), "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    assert load_scenario(out / "scenario.yaml") == scn  # the run used exactly this scenario
    return load_folder(out)


def test_zoh_run_follows_the_exact_hold(tmp_path):
    summary, arrays = _run_variant(tmp_path, "zoh", discretization="zoh", **{"stop.max_steps": 20})
    states, inputs, dt = arrays["states"], arrays["inputs"], float(arrays["dt"])
    assert summary["steps"] == 20 and states.shape == (21, 4, 4) and inputs.shape == (20, 4, 2)
    # the project's ZOH matrices are the textbook ones ...
    A, B = discrete_matrices(2, dt, "zoh")
    eye = np.eye(2)
    np.testing.assert_array_equal(A, np.block([[eye, dt * eye], [0 * eye, eye]]))
    np.testing.assert_allclose(B, np.vstack([0.5 * dt**2 * eye, dt * eye]), rtol=0, atol=1e-15)
    # ... and the saved trajectory obeys them, both by the matrices and written out by hand
    predicted = states[:-1] @ A.T + inputs @ B.T
    assert np.max(np.abs(predicted - states[1:])) < 1e-9
    assert dynamics_error(states, inputs, dt, "zoh") < 1e-9
    # the Euler step would put the positions off by dt^2/2 |u|: a clear margin, not round-off
    assert np.max(np.abs(inputs)) > 0.2
    euler = dynamics_error(states, inputs, dt, "euler")
    assert euler > 1e-3 and euler == pytest.approx(0.5 * dt**2 * np.max(np.abs(inputs)), rel=1e-6)
    Ae, Be = discrete_matrices(2, dt, "euler")
    assert np.max(np.abs(states[:-1] @ Ae.T + inputs @ Be.T - states[1:])) > 1e-3
    collisions, _ = recount_collisions(states, arrays["delta"])
    assert collisions == 0 == summary["collisions"]


@pytest.mark.parametrize("local", ["ipopt", "qp"])
def test_accel_and_speed_limits_hold_and_bind(tmp_path, local):
    amax, vmax = 0.5, 0.6
    # with the paper's weights (Q = 0.1, R = 1) the inputs never exceed ~0.34, so the accel limit
    # would be idle; a heavier state cost makes the planner push against both limits
    summary, arrays = _run_variant(
        tmp_path, "limits", limits={"accel": amax, "speed": vmax},
        weights={"Q": 1.0, "R": 0.1, "Qf": 10.0}, **{"stop.max_steps": 20, "solver.local": local},
    )
    states, inputs, dt = arrays["states"], arrays["inputs"], float(arrays["dt"])
    assert summary["steps"] == 20 and inputs.shape == (20, 4, 2)
    assert np.max(np.abs(inputs)) <= amax + 1e-6  # every component of every applied input
    speeds = np.linalg.norm(states[:, :, 2:], axis=2)
    assert np.max(speeds) <= vmax + 1e-6  # every agent at every saved instant
    assert dynamics_error(states, inputs, dt) < 1e-9  # the limits are on the real trajectory
    per_step = np.max(np.abs(inputs), axis=(1, 2))
    assert np.any(per_step >= amax - 1e-3), per_step  # the acceleration limit binds ...
    # ... and so does the speed limit: the NLP's ball, or the QP's inner 16-gon of it
    reachable = vmax if local == "ipopt" else speed_polytope(2)[1] * vmax
    assert np.max(speeds) >= reachable - 1e-3, np.max(speeds)
    collisions, _ = recount_collisions(states, arrays["delta"])
    assert collisions == 0 == summary["collisions"]
