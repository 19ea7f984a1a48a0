"""Closed-loop runs through the CLI, checked from the saved arrays alone."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import dynamics_error, load_folder, recount_collisions, run_cli
from swarmpc.config import load_scenario
from swarmpc.model.geometry import obstacle_penetration


@pytest.fixture(scope="module", params=["paper-2d", "paper-3d"])
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
