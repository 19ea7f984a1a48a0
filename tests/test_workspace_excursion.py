"""How far agents got outside the workspace box (``summary.json`` ``max_workspace_excursion``):
hand-made trajectories with known answers, a property against a point-by-point reference, and a
closed loop whose summary holds the key."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from swarmpc.config import scenario_from_dict
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.metrics import workspace_excursion

RANDOM = builtin_scenario("random", agents=2, dim=3, seed=0)
"""A scenario with a workspace box."""


def states_at(positions: np.ndarray) -> np.ndarray:
    """(T+1, M, 6) double-integrator states at ``positions`` (T+1, M, 3), at rest."""
    return np.concatenate([positions, np.zeros_like(positions)], axis=-1)


def test_an_agent_that_coasts_past_a_wall_is_measured_by_its_farthest_point():
    lower, upper = RANDOM.bounds()
    inside = (lower + upper) / 2
    path = np.array([[inside, inside]] * 4)
    path[1, 0, 1] = lower[1] - 0.02
    path[2, 0, 1] = lower[1] - 0.063  # the farthest, on the low side of y
    path[3, 1, 2] = upper[2] + 0.01  # the other agent, just over the ceiling
    assert workspace_excursion(RANDOM, states_at(path)) == pytest.approx(0.063)


def test_a_run_inside_the_box_scores_zero_even_on_the_walls():
    lower, upper = RANDOM.bounds()
    path = np.array([[lower, upper]] * 3)  # both agents exactly on a corner of the box
    assert workspace_excursion(RANDOM, states_at(path)) == 0.0


def test_without_a_workspace_there_is_nothing_to_leave():
    data = builtin_scenario("paper-2d").model_dump(mode="json")
    data.pop("workspace")
    scn = scenario_from_dict(data)
    assert scn.workspace is None
    assert workspace_excursion(scn, np.zeros((2, scn.num_agents, 4))) is None


@settings(max_examples=60, deadline=None)
@given(arrays(float, (3, 2, 3), elements=st.floats(-4.0, 4.0)))
def test_the_excursion_is_the_largest_distance_of_a_position_from_the_box(positions):
    lower, upper = RANDOM.bounds()
    clipped = np.clip(positions, lower, upper)
    reference = np.abs(positions - clipped).max()  # inf-norm distance of each point from the box
    assert workspace_excursion(RANDOM, states_at(positions)) == pytest.approx(reference)
