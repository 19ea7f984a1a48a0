"""Initial guesses: a straight line is trapped by a wall, the RRT default is not; seeds repeat."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import load_folder, recount_collisions, run_cli
from swarmpc.config import load_scenario
from swarmpc.model.geometry import obstacle_penetration

pytestmark = pytest.mark.loop  # whole runs through the command line


def final_goal_gaps(folder):
    _summary, arrays = load_folder(folder)
    d = arrays["states"].shape[2] // 2
    return np.linalg.norm(arrays["states"][-1, :, :d] - arrays["goals"][:, :d], axis=1)


@pytest.mark.parametrize(("scenario", "stuck_gap"), [("u-trap", 1.0), ("wall-door", 0.05)])
def test_straight_guess_is_stuck_where_rrt_reaches(scenario, stuck_gap, tmp_path):
    """u-trap: the straight guess parks in the U, > 1 m short. wall-door: it presses against the
    wall until the deadlock rule's detours slide it to the door, and is still short at 300 steps."""
    stuck, free = tmp_path / "straight", tmp_path / "auto"
    assert run_cli("run", scenario, "--initial-guess", "straight", "--max-steps", "300",
                   "--out", str(stuck), "--quiet").returncode == 0
    assert run_cli("run", scenario, "--out", str(free), "--quiet").returncode == 0
    assert np.all(final_goal_gaps(stuck) > stuck_gap)  # held up by the obstacle
    assert np.all(final_goal_gaps(free) <= 0.05 + 1e-9)
    summary, arrays = load_folder(free)
    assert recount_collisions(arrays["states"], arrays["delta"])[0] == 0
    scn = load_scenario(free / "scenario.yaml")
    positions = arrays["states"][:, :, : scn.dim]
    assert max(obstacle_penetration(positions, G, g).max() for G, g in scn.obstacle_halfspaces()) <= 1e-9
    assert summary["rrt"]["fresh"] >= 1


def test_same_seed_same_run(tmp_path):
    runs = []
    for name in ("a", "b"):
        out = tmp_path / name
        assert run_cli("run", "pillars", "--initial-guess", "rrt", "--seed", "3", "--max-steps", "80",
                       "--out", str(out), "--quiet").returncode == 0
        runs.append(load_folder(out)[1]["states"])
    assert np.array_equal(runs[0], runs[1])
