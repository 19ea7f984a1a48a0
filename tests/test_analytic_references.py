"""Analytic references the solvers must meet exactly, computed here by hand and not recorded:

* a lone agent with no constraint that binds is finite-horizon LQ control, solved by the backward
  Riccati recursion on the error state;
* agents farther apart than any coupling reach are independent: ADMM's plans are each agent's
  plan when it is alone;
* the reach bound that decides which pairs can meet holds for every admissible input sequence.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.config import scenario_from_dict
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.dynamics import discrete_matrices
from swarmpc.simulation.controller import make_solver
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.solvers.admm import reach_candidates, reach_radius
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.qp_local import speed_polytope


def random_weights(rng: np.random.Generator, dim: int) -> dict[str, list]:
    """Symmetric Q, Qf >= 0 weighing every state and R > 0, as scenario matrices."""

    def spd(size: int, floor: float) -> np.ndarray:
        root = rng.normal(size=(size, size))
        matrix = root @ root.T / size + floor * np.eye(size)
        return (matrix + matrix.T) / 2

    return {"Q": spd(2 * dim, 0.05).tolist(), "R": spd(dim, 0.1).tolist(), "Qf": spd(2 * dim, 0.0).tolist()}


def riccati_gains(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, Qf: np.ndarray,
                  horizon: int) -> list[np.ndarray]:
    """K_0 .. K_{N-1} of the finite-horizon LQ problem, by the backward Riccati recursion:
    P_N = Qf, K_k = (R + B'P B)^-1 B'P A, P_k = Q + A'P A - A'P B K_k (P = P_{k+1})."""
    P, gains = Qf, []
    for _ in range(horizon):
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Q + A.T @ P @ A - A.T @ P @ B @ K
        gains.append(K)
    return gains[::-1]


# ------------------------------------------------------------------ lone agent = finite-horizon LQ
@given(
    dim=st.sampled_from([2, 3]),
    method=st.sampled_from(["euler", "zoh"]),
    horizon=st.integers(2, 20),
    dt=st.floats(0.05, 0.5),
    seed=st.integers(0, 2**32 - 1),
    error=st.lists(st.floats(-5.0, 5.0), min_size=6, max_size=6),
    velocity=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
)
@settings(max_examples=15, deadline=None)
def test_lone_agent_plan_is_the_finite_horizon_lq_solution(dim, method, horizon, dt, seed, error, velocity):
    rng = np.random.default_rng(seed)
    goal = np.concatenate([rng.uniform(-5.0, 5.0, dim), np.zeros(dim)])  # at rest: A goal = goal
    state = goal + np.concatenate([error[:dim], velocity[:dim]])
    scn = scenario_from_dict({
        "name": "lone", "dim": dim, "dt": dt, "horizon": horizon, "discretization": method,
        "weights": random_weights(rng, dim), "solver": {"method": "centralized"},
        "agents": [{"start": state.tolist(), "goal": goal[:dim].tolist()}],
    })  # no workspace, no limits, no obstacles: no constraint beyond the dynamics
    s = OCPSettings.from_scenario(scn)
    guess = np.repeat(state[None, None], horizon + 1, axis=1)
    plan = CentralizedSolver(s, 1, scn.bodies).plan(state[None], goal[None], guess)
    assert plan.failures == 0

    A, B = discrete_matrices(dim, dt, method)
    errors, inputs = [state - goal], []
    for K in riccati_gains(A, B, s.Q, s.R, s.Qf, horizon):
        inputs.append(-K @ errors[-1])
        errors.append(A @ errors[-1] + B @ inputs[-1])
    scale = 1.0 + np.max(np.abs(inputs))
    assert np.max(np.abs(plan.inputs[0, 0] - inputs[0])) <= 1e-7 * scale  # the MPC's input: -K_0 x
    assert np.max(np.abs(plan.inputs[0] - np.array(inputs))) <= 1e-7 * scale  # and the whole plan
    assert np.max(np.abs(plan.states[0] - goal - np.array(errors))) <= 1e-7 * (1.0 + np.max(np.abs(errors)))


# ------------------------------------------------------------------ far apart: ADMM = alone
FAR_AGENTS = [  # (start [p, v], goal p): 40 m apart, far beyond any coupling reach of a 1 s horizon
    ([0.0, 0.0, 0.3, -0.2], [2.0, 1.0]),
    ([40.0, 0.0, -0.6, 0.3], [32.0, -1.5]),  # an 8 m move: with limits, both bind
    ([0.0, 40.0, -0.5, 0.0], [1.0, 42.0]),
    ([40.0, 40.0, 0.0, 0.0], [41.0, 41.0]),
]
LIMITS = {"accel": 1.0, "speed": 0.8}


def far_scenario(agents: list, limits: dict | None, method: str = "admm", local: str = "ipopt") -> dict:
    return {"name": "far", "dim": 2, "limits": limits or {}, "solver": {"method": method, "local": local},
            "weights": {"Q": 1.0, "R": 0.1},  # stiff: with limits, the 8 m move saturates both
            "agents": [{"start": start, "goal": goal} for start, goal in agents]}


@pytest.mark.parametrize("local", ["ipopt", "qp"])
@pytest.mark.parametrize("limits", [None, LIMITS], ids=["unlimited", "limited"])
@pytest.mark.parametrize("count", [2, 3, 4])
def test_far_apart_agents_admm_plans_are_their_lone_plans(count, limits, local):
    """Against the lone agent's NLP; the QP step with a speed limit (an inner polytope of the
    NLP's ball) against the lone agent's own QP step."""
    agents = FAR_AGENTS[:count]
    scn = scenario_from_dict(far_scenario(agents, limits, local=local))
    s = OCPSettings.from_scenario(scn)
    states, goals = scn.start_states(), scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    if limits is not None:
        assert not reach_candidates(states, s, scn.bodies).any()  # no pair can meet in the horizon
    step = make_solver(scn, s).plan(states, goals, guess)
    assert step.failures == 0 and not step.fallback.any()
    assert not step.copies.any()  # nobody holds a copy of anybody

    for i, agent in enumerate(agents):
        reference = "admm" if local == "qp" and limits is not None else "centralized"
        alone = scenario_from_dict(far_scenario([agent], limits, reference, local))
        lone = make_solver(alone, OCPSettings.from_scenario(alone)).plan(states[i:i + 1], goals[i:i + 1],
                                                                          guess[i:i + 1])
        assert lone.failures == 0
        assert np.max(np.abs(step.inputs[i] - lone.inputs[0])) <= 1e-6
        assert np.max(np.abs(step.states[i] - lone.states[0])) <= 1e-6
    if limits is not None and count >= 2:  # the limits bind, so the comparison covers them
        assert np.max(np.abs(step.inputs)) >= LIMITS["accel"] - 1e-6
        ratio = 1.0 if local == "ipopt" else speed_polytope(2)[1]  # the QP's inner polygon of the ball
        assert np.max(np.linalg.norm(step.states[:, 1:, 2:], axis=2)) >= ratio * LIMITS["speed"] - 1e-4


# ------------------------------------------------------------------ the reach bound
def admissible_velocities(rng: np.random.Generator, velocity: np.ndarray, dt: float, horizon: int,
                          accel: np.ndarray | None, speed: float | None, samples: int) -> np.ndarray | None:
    """(samples, N + 1, d) random velocity sequences from the measured ``velocity`` that obey the
    limits (inputs within ``accel`` per axis, planned speeds after the measured one within
    ``speed``), biased towards full inputs; None when no admissible first step exists."""
    d = velocity.size
    current = np.repeat(velocity[None], samples, axis=0)
    sequence = [current]
    wide = 2.0 * max(speed or 0.0, float(np.max(np.abs(velocity))), 1.0)
    for _ in range(horizon):
        if accel is not None:
            target = current + dt * accel * np.clip(2.0 * rng.normal(size=(samples, d)), -1.0, 1.0)
        else:
            target = rng.uniform(-wide, wide, (samples, d))
        if speed is not None:
            # anchor: the nearest admissible speed; move from it towards the target as far as the limit allows
            norm = np.linalg.norm(current, axis=1, keepdims=True)
            anchor = current * np.minimum(1.0, speed / np.maximum(norm, 1e-300))
            if accel is not None and np.any(np.abs(anchor - current) > dt * accel):
                return None  # measured too fast to be brought within the speed limit in one step
            direction = target - anchor
            a, b, c = np.sum(direction**2, axis=1), np.sum(anchor * direction, axis=1), np.sum(anchor**2, axis=1)
            reach = (-b + np.sqrt(np.maximum(b * b - a * (c - speed**2), 0.0))) / np.maximum(a, 1e-300)
            target = anchor + np.clip(reach, 0.0, 1.0)[:, None] * direction
        current = target
        sequence.append(current)
    return np.stack(sequence, axis=1)


@st.composite
def limited_swarms(draw):
    dim = draw(st.sampled_from([2, 3]))
    kind = draw(st.sampled_from(["accel", "speed", "both"]))
    accel = None
    if kind != "speed":
        accel = np.array(draw(st.lists(st.floats(0.1, 5.0), min_size=dim, max_size=dim)))
    speed = draw(st.floats(0.1, 3.0)) if kind != "accel" else None
    agents = draw(st.integers(1, 4))
    velocities = draw(st.lists(st.floats(-4.0, 4.0), min_size=agents * dim, max_size=agents * dim))
    positions = draw(st.lists(st.floats(-10.0, 10.0), min_size=agents * dim, max_size=agents * dim))
    states = np.hstack([np.reshape(positions, (agents, dim)), np.reshape(velocities, (agents, dim))])
    s = OCPSettings(
        dim=dim, horizon=draw(st.integers(1, 25)), dt=draw(st.floats(0.01, 0.5)),
        discretization=draw(st.sampled_from(["euler", "zoh"])), Q=np.eye(2 * dim), R=np.eye(dim),
        Qf=np.eye(2 * dim), collision="hard", d_min=0.05, kappa=1000.0, lower=None, upper=None,
        accel=accel, speed=speed, obstacles=(),
    )
    return s, states


@given(case=limited_swarms(), seed=st.integers(0, 2**32 - 1))
@settings(max_examples=80, deadline=None)
def test_reach_radius_bounds_every_admissible_rollout(case, seed):
    s, states = case
    rng = np.random.default_rng(seed)
    d, N = s.dim, s.horizon
    A, B = discrete_matrices(d, s.dt, s.discretization)
    bound = reach_radius(states, s)
    assert bound.shape == (len(states),) and np.all(np.isfinite(bound))
    for i, state in enumerate(states):
        velocities = admissible_velocities(rng, state[d:], s.dt, N, s.accel, s.speed, samples=256)
        if velocities is None:
            continue
        if s.accel is not None:  # full thrust along the measured velocity, the case the bound is drawn for
            push = velocities[0, 0] + s.dt * s.accel * np.where(state[d:] >= 0, 1.0, -1.0) * np.arange(N + 1)[:, None]
            if s.speed is None:
                velocities = np.concatenate([velocities, push[None]])
        inputs = np.diff(velocities, axis=1) / s.dt  # (samples, N, d)
        if s.accel is not None:  # the sequences are admissible
            assert np.all(np.abs(inputs) <= s.accel * (1 + 1e-9))
        if s.speed is not None:
            assert np.all(np.linalg.norm(velocities[:, 1:], axis=2) <= s.speed * (1 + 1e-9))
        rolled = [np.repeat(state[None], len(inputs), axis=0)]
        for k in range(N):
            rolled.append(rolled[-1] @ A.T + inputs[:, k] @ B.T)
        rolled = np.stack(rolled, axis=1)  # (samples, N + 1, 2d)
        assert np.allclose(rolled[:, :, d:], velocities)  # the model's velocities are the sequences'
        moved = np.max(np.abs(rolled[:, :, :d] - state[:d]))
        assert moved <= bound[i] * (1 + 1e-9) + 1e-12, (moved, bound[i])
        if s.speed is None and s.discretization == "zoh":  # full thrust meets the bound: it is tight
            assert moved >= bound[i] * (1 - 1e-9) - 1e-12, (moved, bound[i])


def test_reach_radius_is_unbounded_without_limits():
    s = OCPSettings(dim=2, horizon=10, dt=0.1, discretization="euler", Q=np.eye(4), R=np.eye(2), Qf=np.eye(4),
                    collision="hard", d_min=0.05, kappa=1000.0, lower=None, upper=None, accel=None, speed=None,
                    obstacles=())
    assert np.all(np.isinf(reach_radius(np.zeros((3, 4)), s)))
