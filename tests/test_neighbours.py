"""Neighbour-sparse consensus: the reach bound is sound, and sparse coupling leaves no close pair
unconstrained (after convergence, after repair, in closed loop)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from conftest import ScriptedExecutor, recount_collisions
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import make_solver, simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalResult, reach_candidates, reach_radius
from swarmpc.solvers.base import braking_plan

HORIZON, DT = 10, 0.1


def base_settings(dim: int, discretization: str = "euler") -> OCPSettings:
    scn = builtin_scenario("random", agents=2, dim=dim, seed=0)
    return replace(OCPSettings.from_scenario(scn), horizon=HORIZON, dt=DT, discretization=discretization)


def finite(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


def ball_step(v: np.ndarray, target: np.ndarray, speed: float) -> np.ndarray:
    """The point farthest towards ``target`` on the segment from ``v`` (inside the speed ball)
    that stays inside the ball: keeps the input admissible (a fraction of it) and the speed within
    the limit."""
    e = target - v
    if np.linalg.norm(target) <= speed or not e.any():
        return target
    a, b, c = e @ e, v @ e, v @ v - speed**2
    t = (-b + np.sqrt(max(b * b - a * c, 0.0))) / a
    return v + min(max(t, 0.0), 1.0) * e


def solver_like_plans(state: np.ndarray, directions: list[np.ndarray], s: OCPSettings) -> list[np.ndarray]:
    """Position trajectories (N+1, d) an agent's plan can have, simulated with the model: the
    braking fallback, and for each ``directions`` (N, d) in [-1, 1] a trajectory obeying the limits
    exactly as the OCP imposes them (|u_axis| <= accel; ||v_k|| <= speed for k >= 1, the measured
    v_0 free). When no admissible first input reaches the speed ball, the local problem is
    infeasible and only the braking fallback is a possible plan."""
    d = s.dim
    model = DoubleIntegrator(d, s.dt, s.discretization)  # type: ignore[arg-type]
    plans = [braking_plan(state, s)[0][:, :d]]
    amax = s.accel if s.accel is not None else None
    for w in directions:
        v = state[d:].copy()
        inputs = []
        feasible = True
        for k in range(s.horizon):
            if s.speed is None:
                v_next = v + s.dt * amax * w[k]
            elif amax is None:
                v_next = w[k] * s.speed
                if np.linalg.norm(v_next) > s.speed:
                    v_next *= s.speed / np.linalg.norm(v_next)
            else:
                start = v
                if np.linalg.norm(v) > s.speed:  # k == 0 only: a measured speed above the limit
                    closest = np.clip(v * s.speed / np.linalg.norm(v), v - s.dt * amax, v + s.dt * amax)
                    if np.linalg.norm(closest) > s.speed:
                        feasible = False
                        break
                    start = closest
                v_next = ball_step(start, v + s.dt * amax * w[k], s.speed)
            inputs.append((v_next - v) / s.dt)
            v = v_next
        if feasible:
            plans.append(model.rollout(state, np.array(inputs))[:, :d])
    return plans


@st.composite
def swarms(draw):
    """Random states and limits; agent 1 is placed just beyond agent 0's candidate threshold, so
    every example holds a non-candidate pair at the edge of the bound."""
    dim = draw(st.sampled_from([2, 3]))
    agents = draw(st.integers(2, 5))
    limits = draw(st.sampled_from(["accel", "accel+speed", "speed"]))
    s = replace(
        base_settings(dim, draw(st.sampled_from(["euler", "zoh"]))),
        accel=draw(arrays(float, dim, elements=finite(0.1, 3.0))) if "accel" in limits else None,
        speed=draw(finite(0.1, 3.0)) if "speed" in limits else None,
        d_min=draw(finite(0.01, 0.2)),
    )
    delta = draw(arrays(float, dim, elements=finite(0.05, 0.5)))
    states = np.hstack([
        draw(arrays(float, (agents, dim), elements=finite(-4.0, 4.0))),
        draw(arrays(float, (agents, dim), elements=finite(-2.0, 2.0))),
    ])
    # the gap to agent 1 is large on one axis (small or not on the others)
    direction = draw(arrays(float, dim, elements=finite(-1.0, 1.0))) * draw(st.sampled_from([0.0, 0.05, 1.0]))
    direction[draw(st.integers(0, dim - 1))] = draw(st.sampled_from([-1.0, 1.0]))
    if draw(st.booleans()):  # agents 0 and 1 already heading for each other
        states[0, dim:] = np.sign(direction) * np.abs(states[0, dim:])
        states[1, dim:] = -np.sign(direction) * np.abs(states[1, dim:])
    reach = reach_radius(states, s)
    threshold = float(np.max(delta)) + s.d_min + reach[0] + reach[1]
    states[1, :dim] = states[0, :dim] + direction * threshold * draw(finite(1.0 + 1e-9, 1.2))
    random_inputs = draw(arrays(float, (agents, HORIZON, dim), elements=finite(-1.0, 1.0)))
    return s, delta, states, random_inputs


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(swarms())
def test_non_candidates_never_come_within_reach(case):
    s, delta, states, random_inputs = case
    d, limit = s.dim, float(np.max(delta)) + s.d_min
    candidates = reach_candidates(states, s, delta)
    assert np.array_equal(candidates, candidates.T) and not candidates.diagonal().any()
    assert not candidates[0, 1]  # placed beyond the threshold
    for i, j in zip(*np.nonzero(np.triu(~candidates, k=1)), strict=True):
        # each agent: random admissible inputs, full effort towards the other, braking
        toward = np.sign(states[j, :d] - states[i, :d])
        plans_i = solver_like_plans(states[i], [random_inputs[i], np.tile(toward, (HORIZON, 1))], s)
        plans_j = solver_like_plans(states[j], [random_inputs[j], np.tile(-toward, (HORIZON, 1))], s)
        for p_i in plans_i:
            for p_j in plans_j:
                gap = np.max(np.abs(p_i - p_j), axis=1).min()
                assert gap >= limit - 1e-9, (i, j, gap, limit)


def test_without_limits_every_pair_is_a_candidate():
    s = replace(base_settings(3), accel=None, speed=None)
    rng = np.random.default_rng(0)
    states = np.hstack([rng.uniform(-100, 100, (12, 3)), rng.uniform(-5, 5, (12, 3))])
    candidates = reach_candidates(states, s, np.full(3, 0.3))
    assert np.isinf(reach_radius(states, s)).all()
    assert np.array_equal(candidates, ~np.eye(12, dtype=bool))
    solver = ADMMSolver(s, 12, np.full(3, 0.3), executor=ScriptedExecutor(lambda request: None))
    guess = np.repeat(states[:, None], HORIZON + 1, axis=1)
    assert solver.neighbours(guess, candidates) == solver.neighbours(guess)


def test_speed_cap_and_accel_bound_combine_by_minimum():
    s = replace(base_settings(2), accel=np.array([1.0, 2.0]), speed=0.5)
    states = np.array([[0.0, 0.0, 0.2, -1.0], [0.0, 0.0, 0.0, 0.0]])
    T = HORIZON * DT
    accel_bound = np.abs(states[:, 2:]) * T + 0.5 * s.accel * T**2
    speed_bound = T * np.maximum(np.abs(states[:, 2:]), 0.5)  # a measured speed above the limit counts
    assert np.allclose(reach_radius(states, s), np.minimum(accel_bound, speed_bound).max(axis=1))
    assert np.allclose(reach_radius(states, replace(s, speed=None)), accel_bound.max(axis=1))
    assert np.allclose(reach_radius(states, replace(s, accel=None)), speed_bound.max(axis=1))


def resting_result(request, s: OCPSettings, offset=(0.0, 0.0), copy_error: float = 0.0) -> LocalResult:
    d = s.dim
    states = np.tile(np.concatenate([request.state[:d] + np.asarray(offset), np.zeros(d)]), (s.horizon + 1, 1))
    states[0] = request.state
    return LocalResult(
        agent=request.agent, own=states[s.first_constrained_step :, :d].T.copy(),
        copies=request.z_neighbours + copy_error, states=states, inputs=np.zeros((s.horizon, d)),
        success=True, fallback=False, solve_time=0.0, max_slack=0.0, cost=0.0,
    )


def test_repair_couples_candidate_pairs_whose_repaired_plans_conflict():
    """Agents 0 and 1 are reach candidates but their guesses are apart, so they are not coupled;
    agents 2 and 3 are coupled and never agree, so ADMM stops without consensus and repairs.
    Uncoupled, 0 and 1 plan to close in on each other (within their reach), and the first repair
    pass does not touch them (it re-plans only coupled agents); the check after it couples them
    and the second pass, over those two agents only, keeps them apart."""
    s = replace(base_settings(2), accel=np.ones(2), speed=None)  # reach 0.5 from rest, T = 1 s
    delta = np.full(2, 0.3)
    states = np.array([[0.0, 0, 0, 0], [1.0, 0, 0, 0], [5.0, 5, 0, 0], [5.5, 5, 0, 0]])

    def respond(request):
        if request.agent > 1:
            return resting_result(request, s, copy_error=0.1)
        if (1 - request.agent) in request.neighbours:
            return resting_result(request, s)
        return resting_result(request, s, offset=(0.4, 0.0) if request.agent == 0 else (-0.3, 0.0))

    executor = ScriptedExecutor(respond)
    solver = ADMMSolver(s, 4, delta, ADMMConfig(max_iter=3, stall_window=None), executor)
    candidates = reach_candidates(states, s, delta)
    assert candidates[0, 1] and not candidates[0, 2]
    guess = np.repeat(states[:, None], HORIZON + 1, axis=1)
    assert solver.neighbours(guess, candidates) == [(), (), (3,), (2,)]
    step = solver.plan(states, np.zeros_like(states), guess)
    assert step.repaired
    repairs = [r.agent for r in executor.requests if r.neighbour_plans is not None]
    assert repairs.count(2) == 1 and repairs.count(3) == 1  # the first pass: the coupled agents
    assert repairs.count(0) == 1 and repairs.count(1) == 1  # the second: the pair it coupled, no other
    last = [r for r in executor.requests if r.neighbour_plans is not None and r.agent == 0][-1]
    assert last.neighbours == (1,)
    gap = np.max(np.abs(step.states[0, :, :2] - step.states[1, :, :2]), axis=1).min()
    assert gap >= 0.3 + s.d_min


def test_conflict_check_examines_candidates_and_agents_beyond_their_reach():
    s = replace(base_settings(2), accel=np.ones(2), speed=None)
    delta = np.full(2, 0.3)
    states = np.array([[0.0, 0, 0, 0], [1.0, 0, 0, 0], [3.0, 0, 0, 0]])
    solver = ADMMSolver(s, 3, delta, executor=ScriptedExecutor(lambda request: None))
    candidates = reach_candidates(states, s, delta)
    assert candidates[0, 1] and not candidates[1, 2] and not candidates[0, 2]

    class Request:
        def __init__(self, agent):
            self.agent, self.state, self.z_neighbours = agent, states[agent], np.zeros((0, 2, s.num_constrained))

    # agent 2 "moves" 1.8 m, beyond its 0.5 m reach (only a plan breaking the limits can), onto 1
    results = [resting_result(Request(0), s), resting_result(Request(1), s),
               resting_result(Request(2), s, offset=(-1.8, 0.0))]
    neighbours = [(), (), ()]
    assert solver.conflicts(results, neighbours, candidates) == []
    assert solver.conflicts(results, neighbours, solver.safety.checked_pairs(candidates, states, results)) == [(1, 2)]
    assert solver.conflicts(results, neighbours) == [(1, 2)]  # no candidates given: every pair


@pytest.mark.loop
def test_closed_loop_random_swarm_has_no_collisions():
    """Seed 3: five of the 15 pairs start out of reach, agents meet within 20 steps (one step ends
    in a repair pass); ~9 s. (Seed 1 meets only after ~28 steps: ~26 s for 40 steps.)"""
    scn = builtin_scenario("random", agents=6, dim=3, seed=3).with_updates(
        **{"limits.accel": 1.0, "stop.max_steps": 20}
    )
    s = OCPSettings.from_scenario(scn)
    sparse = ~reach_candidates(scn.start_states(), s, scn.delta_vector)
    assert np.triu(sparse, k=1).any()  # some pairs need no coupling at the start
    result = simulate(scn)
    collisions, worst = recount_collisions(result.states, scn.delta_vector)
    assert collisions == 0 and worst >= 1.0


@pytest.mark.parametrize("dim", [2, 3])
def test_reach_candidates_vectorised_for_large_swarms(dim):
    s = replace(base_settings(dim), accel=np.full(dim, 1.0), speed=1.0)
    rng = np.random.default_rng(dim)
    states = np.hstack([rng.uniform(-10, 10, (128, dim)), rng.uniform(-1, 1, (128, dim))])
    delta = np.full(dim, 0.3)
    candidates = reach_candidates(states, s, delta)
    reach = reach_radius(states, s)
    limit = 0.3 + s.d_min
    for i in range(0, 128, 17):
        for j in range(128):
            gap = np.max(np.abs(states[i, :dim] - states[j, :dim]))
            assert candidates[i, j] == (i != j and gap < limit + reach[i] + reach[j])


@pytest.mark.parametrize(
    ("collision", "margin", "expected"),
    [("hard", None, (0.2, 0.1)), ("soft", None, (0.5, 0.0)), ("hard", 0.7, (0.7, 0.0)), ("soft", 0.0, (0.0, 0.0))],
)
def test_coupling_margin_follows_the_collision_form_unless_set(collision, margin, expected):
    scn = builtin_scenario("paper-2d").with_updates(collision=collision, **{"solver.coupling_margin": margin})
    solver = make_solver(scn, OCPSettings.from_scenario(scn))
    assert (solver.config.coupling_margin, solver.config.closing_time) == pytest.approx(expected)


@pytest.mark.parametrize(("tolerance", "relaxation"), [(0.0, 1.0), (3e-4, 1.6)])
def test_the_reuse_tolerance_and_relaxation_of_the_scenario_reach_the_solver(tolerance, relaxation):
    scn = builtin_scenario("paper-2d").with_updates(**{"solver.reuse_tol": tolerance, "solver.relaxation": relaxation})
    config = make_solver(scn, OCPSettings.from_scenario(scn)).config
    assert (config.reuse_tol, config.relaxation) == (tolerance, relaxation)


def test_pairs_closing_in_fast_couple_from_farther_away():
    scn = builtin_scenario("paper-2d")
    settings = OCPSettings.from_scenario(scn)
    N = settings.horizon
    # two agents 1.0 m apart on x, closing at 1 m/s each, held at that distance over the horizon
    guess = np.zeros((2, N + 1, 4))
    guess[0, :, 0], guess[1, :, 0] = -0.5, 0.5
    guess[0, :, 2], guess[1, :, 2] = 1.0, -1.0
    # gap 1.0 m: beyond 0.3 + 0.05 + 0.2, within that plus 0.3 s x 2 m/s
    slow = ADMMSolver(settings, 2, np.full(2, 0.3), ADMMConfig(coupling_margin=0.2))
    fast = ADMMSolver(settings, 2, np.full(2, 0.3), ADMMConfig(coupling_margin=0.2, closing_time=0.3))
    assert slow.neighbours(guess) == [(), ()]
    assert fast.neighbours(guess) == [(1,), (0,)]
