"""Rescue plans: an agent whose hard-constrained repair solves fail, and whose fallback plan would
break the separation from its neighbours' plans, flies the least-violating plan of the same
problem with soft pair constraints. Two situations had no way out before: two agents failing
together (each braking blind to the other), and a pair already inside each other's delta box
(every hard problem infeasible, both on fallbacks for the rest of the run). The separations are
recomputed from the applied states."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.config import scenario_from_dict
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.model.geometry import box_signed_distance, point_box_distance
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, default_coupling

PAIR = {
    "name": "pair",
    "dim": 2,
    "delta": 0.3,
    "workspace": {"lower": [-3, -3], "upper": [3, 3]},
    "limits": {"accel": 1.0},
    "agents": [{"start": [-1.0, 0.0], "goal": [1.5, 0.05]}, {"start": [1.0, 0.0], "goal": [-1.5, -0.05]}],
}


def closed_loop(states: np.ndarray, steps: int, rescue: bool) -> tuple[np.ndarray, int]:
    """Apply ``steps`` MPC steps of the ADMM solver from ``states`` (holding-still guesses);
    returns the applied positions (steps + 1, 2, 2) and how many agent-steps flew a fallback or
    rescue plan. ``rescue=False`` takes the rescue ladder away (the behaviour before it)."""
    scn = scenario_from_dict(PAIR)
    s = OCPSettings.from_scenario(scn)
    margin, closing = default_coupling("hard")
    solver = ADMMSolver(s, 2, scn.delta_vector, ADMMConfig(coupling_margin=margin, closing_time=closing))
    if not rescue:
        for agent in solver.executor._agents.values():  # type: ignore[attr-defined]
            agent.rescue = None
    model = DoubleIntegrator(2, s.dt, s.discretization)
    positions, fell = [states[:, :2].copy()], 0
    try:
        for _ in range(steps):
            guess = np.repeat(states[:, None], s.horizon + 1, axis=1)
            step = solver.plan(states, scn.goal_states(), guess)
            fell += int(step.fallback.sum())
            states = np.array([model.step(states[i], step.inputs[i][0]) for i in range(2)])
            positions.append(states[:, :2].copy())
    finally:
        solver.close()
    return np.array(positions), fell


def inf_gaps(positions: np.ndarray) -> np.ndarray:
    return np.max(np.abs(positions[:, 0] - positions[:, 1]), axis=1)


@pytest.mark.loop
def test_a_pair_inside_each_others_box_gets_out():
    inside = np.array([[0.0, 0.0, 0.0, 0.0], [0.2, 0.05, 0.0, 0.0]])  # 0.2 m apart, delta 0.3
    positions, fell = closed_loop(inside, 6, rescue=True)
    gaps = inf_gaps(positions)
    assert fell > 0  # the hard problems were infeasible: the rescue flew
    assert gaps[-1] > 0.3 and np.all(np.diff(gaps) >= -1e-9)  # out, and never pushed back in
    stuck, fell_before = closed_loop(inside, 6, rescue=False)
    assert fell_before == 12 and np.allclose(inf_gaps(stuck), 0.2, atol=1e-6)  # for good, before


@pytest.mark.loop
def test_two_agents_failing_together_swerve_instead_of_braking_into_each_other():
    # head-on at 1.5 m/s each, 2.2 m apart: braking alone (1 m/s^2) cannot stop them in time,
    # so each one's hard problem against the other's braking plan is infeasible
    head_on = np.array([[-1.1, 0.0, 1.5, 0.0], [1.1, 0.03, -1.5, 0.0]])
    positions, fell = closed_loop(head_on, 12, rescue=True)
    assert fell > 0
    assert inf_gaps(positions).min() >= 0.3  # recomputed: never inside the delta box
    braked, _ = closed_loop(head_on, 12, rescue=False)
    assert inf_gaps(braked).min() < 0.1  # before: both braked straight into each other


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-2, 2), min_size=3, max_size=3),
    st.lists(st.floats(0.05, 1.0), min_size=3, max_size=3),
)
def test_signed_box_distance_matches_the_pointwise_one(offset, half):
    expected = point_box_distance(np.array(offset), np.array(half))
    assert np.isclose(box_signed_distance(np.array([offset]), np.array(half))[0], expected)
