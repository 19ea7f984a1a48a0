"""Built-in scenarios: valid, listed, and identical to their YAML copies in examples/."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.config import load_scenario
from swarmpc.model.geometry import inf_separation_ratio, point_box_distance
from swarmpc.scenarios import BUILTINS, builtin_scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.mark.parametrize("name", list(BUILTINS))
def test_example_yaml_matches_builtin(name):
    assert load_scenario(EXAMPLES / f"{name}.yaml") == builtin_scenario(name)


@pytest.mark.parametrize("agents,dim", [(2, 2), (8, 2), (16, 2), (8, 3), (32, 3)])
def test_circle_is_antipodal_and_separated(agents, dim):
    scn = builtin_scenario("circle", agents=agents, dim=dim)
    starts, goals = scn.start_states()[:, :dim], scn.goal_states()[:, :dim]
    midpoints = (starts + goals) / 2
    assert np.allclose(midpoints, midpoints[0], atol=1e-5)  # every swap passes through one centre
    assert inf_separation_ratio(starts, scn.delta_vector).min() >= 1.0


@pytest.mark.parametrize("seed", range(5))
def test_random_is_seeded(seed):
    a = builtin_scenario("random", agents=16, dim=3, seed=seed)
    b = builtin_scenario("random", agents=16, dim=3, seed=seed)
    assert a == b
    starts = a.start_states()[:, :3]
    gaps = np.linalg.norm(starts[:, None] - starts[None], axis=2) + np.eye(16) * 9
    assert gaps.min() >= 0.5


@given(seed=st.integers(0, 10_000), agents=st.integers(2, 24))
@settings(max_examples=15, deadline=None)
def test_random_goals_and_starts_leave_room_for_the_separation(seed, agents):
    """Every pair of starts and of goals keeps 0.1 m between a point and the other's delta box,
    so all goals can be held at once (the OBCA separation d_min is 0.05 m)."""
    scn = builtin_scenario("random", agents=agents, dim=3, seed=seed)
    for points in (scn.start_states()[:, :3], scn.goal_states()[:, :3]):
        for i in range(agents):
            for j in range(i + 1, agents):
                assert point_box_distance(points[i] - points[j], scn.delta_vector) >= 0.1 - 1e-3


@pytest.mark.parametrize("dim", [2, 3])
def test_spread_keeps_the_density_of_eight_agents_in_the_random_box(dim):
    base = builtin_scenario("random", agents=8, dim=dim, seed=1)
    lower, upper = base.bounds()
    room = np.prod(upper - lower) / 8
    for agents in (4, 16, 64):
        scn = builtin_scenario("spread", agents=agents, dim=dim, seed=1)
        lower, upper = scn.bounds()
        assert np.prod(upper - lower) / agents == pytest.approx(room, rel=1e-3)
        points = np.vstack([scn.start_states()[:, :dim], scn.goal_states()[:, :dim]])
        assert np.all(points >= lower) and np.all(points <= upper)
        assert scn.name.startswith("spread") and scn.stop.max_steps >= 600
    # the floor stays where drones take off; the box grows upwards
    assert builtin_scenario("spread", agents=64, seed=1).bounds()[0][2] == pytest.approx(0.2)


def test_scenarios_command_lists_every_builtin():
    from conftest import run_cli

    done = run_cli("scenarios")
    assert done.returncode == 0
    assert all(name in done.stdout for name in BUILTINS)
