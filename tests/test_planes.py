"""Separating planes for near, not engaged pairs: any two positions on their sides clear the box,
planes are drawn only from guesses a plan can follow, a pair whose plans break its plane is coupled
with copies, and a closed loop that uses planes stays collision-free."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import ScriptedExecutor, recount_collisions
from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.model.geometry import box_exterior_distance
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalResult, separating_planes
from swarmpc.solvers.guesses import inputs_from_states
from swarmpc.solvers.rrt import straight_line_guess


def _settings(dim: int = 2) -> OCPSettings:
    scn = builtin_scenario("random", agents=2, dim=3, seed=0)
    base = OCPSettings.from_scenario(scn)
    return replace(base, dim=dim, Q=np.eye(2 * dim) * 0.1, R=np.eye(dim), Qf=np.eye(2 * dim),
                   lower=None, upper=None, accel=np.ones(dim), speed=None, obstacles=())


@settings(max_examples=200, deadline=None)
@given(
    dim=st.sampled_from([2, 3]),
    steps=st.integers(1, 6),
    seed=st.integers(0, 2**31 - 1),
    clearance=st.floats(0.01, 0.1),
)
def test_any_positions_on_their_sides_clear_the_box(dim, steps, seed, clearance):
    """The law the planes rest on: whatever two agents do within their sides, the offset of their
    positions is at least ``clearance`` (Euclidean) outside the delta box at every step, and each
    guess is on its own side."""
    rng = np.random.default_rng(seed)
    delta = rng.uniform(0.1, 0.5, dim)
    second = rng.uniform(-2, 2, (dim, steps))
    axis = rng.integers(0, dim, steps)
    offset = rng.uniform(-0.6, 0.6, (dim, steps))
    need = delta[axis] + clearance + rng.uniform(0, 0.3, steps)
    offset[axis, np.arange(steps)] = rng.choice([-1.0, 1.0], steps) * need
    first = second + offset
    normals, first_offsets, second_offsets = separating_planes(first, second, delta, clearance)
    assert np.allclose(np.linalg.norm(normals, axis=0), 1.0)
    assert np.all((normals * first).sum(axis=0) >= first_offsets - 1e-12)
    assert np.all((-normals * second).sum(axis=0) >= second_offsets - 1e-12)
    for _ in range(20):
        p = first + rng.uniform(-1, 1, (dim, steps))
        q = second + rng.uniform(-1, 1, (dim, steps))
        # move each point onto its side along the normal where it is outside
        p += normals * np.maximum(first_offsets - (normals * p).sum(axis=0), 0.0)
        q -= normals * np.maximum(second_offsets + (normals * q).sum(axis=0), 0.0)
        outside = box_exterior_distance(p - q, delta[:, None], axis=0)
        assert np.all(outside >= clearance - 1e-9)


def test_a_local_solve_keeps_to_its_plane():
    """A plane across the agent's way to its goal: the plan stops at the plane, within the solver's
    tolerance; without it the plan crosses."""
    s = _settings(2)
    d, K = s.dim, s.num_constrained
    state, goal = np.array([0.0, 0.0, 0.5, 0.0]), np.array([1.0, 0.0, 0.0, 0.0])
    params = {"x0": state, "goal": goal, "delta": np.full(d, 0.3), "rho": 10.0, "owner_weight": 0.0,
              "Z": np.zeros((d, K)), "Y": np.zeros((d, K))}
    free = build_local(s, 0).solve(params, {})
    normals = np.tile(np.array([[-1.0], [0.0]]), (1, K))  # -x >= -0.2, i.e. x <= 0.2
    walled = build_local(s, 0, num_planes=1).solve({**params, "Hn0": normals, "Hb0": np.full((1, K), -0.2)}, {})
    assert free.success and walled.success
    assert free.x["X"][0].max() > 0.3
    assert walled.x["X"][0, s.first_constrained_step:].max() <= 0.2 + 1e-6


def test_planes_are_drawn_only_from_guesses_a_plan_can_follow():
    """A shifted plan of the model is followable and its last position coasts on; a straight line
    at cruising speed from rest is not (no input reaches it)."""
    s = _settings(2)
    solver = ADMMSolver(s, 2, np.full(2, 0.3), ADMMConfig(plane_margin=0.05))
    model = DoubleIntegrator(2, s.dt, s.discretization)
    start = np.array([0.0, 0.0, 0.3, 0.0])
    plan = [start]
    for k in range(s.horizon + 1):
        plan.append(model.step(plan[-1], np.array([0.5, -0.2 if k % 2 else 0.4])))
    plan = np.array(plan)
    shifted = np.vstack([plan[1:-1], plan[-2:-1]])  # the solver's shift: last state repeated
    straight = straight_line_guess(np.array([3.0, 0.0, 0.0, 0.0]), np.array([5.0, 0.0]), s.dt, s.horizon, 1.0)
    states = np.array([plan[1], [3.0, 0.0, 0.0, 0.0]])
    followable, positions = solver.reachable_guesses(states, np.array([shifted, straight]))
    assert followable.tolist() == [True, False]
    coast = shifted[-2, :2] + s.dt * shifted[-2, 2:]
    assert np.allclose(positions[0, -1], coast)
    assert np.allclose(inputs_from_states(shifted[:-1], s), inputs_from_states(plan[1:-1], s))
    solver.close()


def _resting(request, s: OCPSettings, shift: float = 0.0) -> LocalResult:
    d = s.dim
    states = np.tile(np.concatenate([request.state[:d] + np.array([shift, 0.0]), np.zeros(d)]), (s.horizon + 1, 1))
    states[0] = request.state
    return LocalResult(
        agent=request.agent, own=states[s.first_constrained_step:, :d].T.copy(), copies=request.z_neighbours.copy(),
        states=states, inputs=np.zeros((s.horizon, d)), success=True, fallback=False, solve_time=0.0,
        max_slack=0.0, cost=0.0,
    )


def test_a_pair_at_rest_gets_a_plane_and_is_coupled_once_its_plans_break_it():
    """Two agents at rest 0.5 m apart couple by the guess rule (within delta + d_min + 0.2 m) and
    clear the box by 0.2 m: they get a plane (no copies). Agent 0 answers as if it had none and
    closes in to 0.2 m: the check couples the pair with copies before any plan is applied."""
    s = _settings(2)
    states = np.array([[0.0, 0.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0]])
    guess = np.repeat(states[:, None], s.horizon + 1, axis=1)

    def respond(request):
        if request.agent == 0 and not request.neighbours:
            return _resting(request, s, shift=0.3)  # breaks its plane (x <= 0.25 - d_min / 2 ...)
        return _resting(request, s)

    executor = ScriptedExecutor(respond)
    solver = ADMMSolver(s, 2, np.full(2, 0.3), ADMMConfig(plane_margin=0.05, stall_window=None), executor)
    goals = states + np.array([0.0, 5.0, 0.0, 0.0])  # far from both: planes allowed
    step = solver.plan(states, goals, guess)
    first = executor.requests[:2]
    assert [r.neighbours for r in first] == [(), ()]
    assert [r.num_planes for r in first] == [1, 1]
    assert np.allclose(first[0].plane_normals[0][0], -1.0)  # agent 0 keeps to the left of the plane
    later = executor.requests[2:]
    assert later and all(r.neighbours == (1 - r.agent,) and r.num_planes == 0 for r in later)
    assert step.copies.tolist() == [1, 1] and step.planes.tolist() == [0, 0]
    solver.close()


@pytest.mark.loop
def test_closed_loop_with_planes_is_collision_free_and_uses_them():
    """Random 3D swarm with planes: planes do carry pairs, no collision recounted from the saved
    trajectory, every solve succeeds."""
    scn = builtin_scenario("random", agents=8, dim=3, seed=0).with_updates(
        **{"stop.max_steps": 40, "solver.plane_margin": 0.05})
    result = simulate(scn)
    planes = np.array([r.planes for r in result.records])
    assert planes.sum() > 0
    collisions, worst = recount_collisions(result.states, scn.delta_vector)
    assert collisions == 0 and worst >= 1.0
    assert result.summary["solver_failures"] == 0


def test_an_agent_near_its_goal_keeps_copies_not_planes():
    """The same pair with agent 1 parked at its goal: it must be able to move aside, so the pair
    keeps copies."""
    s = _settings(2)
    states = np.array([[0.0, 0.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0]])
    guess = np.repeat(states[:, None], s.horizon + 1, axis=1)
    executor = ScriptedExecutor(lambda request: _resting(request, s))
    solver = ADMMSolver(s, 2, np.full(2, 0.3), ADMMConfig(plane_margin=0.05, stall_window=None), executor)
    goals = np.array([[0.0, 5.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0]])
    step = solver.plan(states, goals, guess)
    assert [r.neighbours for r in executor.requests[:2]] == [(1,), (0,)]
    assert step.planes.tolist() == [0, 0]
    solver.close()
