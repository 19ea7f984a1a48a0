"""The agent-model seam: a toy model plugged in through the registry alone flies a centralised
and an ADMM closed loop, and the double integrator meets the facts its interface promises."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from typing import Any

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.config import scenario_from_dict
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.agent_model import (
    AgentModel,
    make_model,
    model_names,
    register_model,
    registered_model,
    unregister_model,
)
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.executors import SerialExecutor


@dataclass(frozen=True)
class SingleIntegrator:
    """Toy agent: the state is the position, the input the velocity, p_{k+1} = p_k + dt u_k."""

    dim: int
    dt: float
    discretization: str = "euler"  # exact for a constant input either way

    @property
    def name(self) -> str:
        return "single_integrator"

    @property
    def state_dim(self) -> int:
        return self.dim

    @property
    def input_dim(self) -> int:
        return self.dim

    @property
    def position_rows(self) -> slice:
        return slice(0, self.dim)

    @property
    def first_constrained_step(self) -> int:
        return 1

    def position(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)[..., : self.dim]

    def velocity(self, states: np.ndarray) -> np.ndarray:
        return np.zeros_like(np.asarray(states, float))

    def state_at(self, position: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
        return np.array(position, float)

    def step(self, state: np.ndarray, control: np.ndarray) -> np.ndarray:
        return np.asarray(state, float) + self.dt * np.asarray(control, float)

    def rollout(self, state: np.ndarray, controls: np.ndarray) -> np.ndarray:
        states = [np.asarray(state, float)]
        for control in controls:
            states.append(self.step(states[-1], control))
        return np.array(states)

    def guess_inputs(self, states: np.ndarray) -> np.ndarray:
        return np.diff(states, axis=0) / self.dt

    def input_bounds(self, accel: np.ndarray | None, speed: float | None) -> tuple[np.ndarray, np.ndarray]:
        bound = np.full(self.dim, np.inf if speed is None else speed)
        return -bound, bound

    def casadi_dynamics(self, X: Any, U: Any) -> Any:
        return X[:, :-1] + self.dt * U

    def casadi_speed_sq(self, X: Any, U: Any) -> Any:
        return ca.sum1(U**2)

    def braking_inputs(self, state: np.ndarray, horizon: int, accel_limit: np.ndarray | None) -> np.ndarray:
        return np.zeros((horizon, self.dim))

    def reach_bound(self, states: np.ndarray, steps: int, accel: np.ndarray | None,
                    speed: float | None) -> np.ndarray:
        reach = np.inf if speed is None else steps * self.dt * speed
        return np.full(np.shape(states)[:-1], reach)

    def linear_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        return np.eye(self.dim), self.dt * np.eye(self.dim)


SWAP = {
    "name": "toy-swap", "dim": 2, "dt": 0.1, "horizon": 10, "delta": 0.3,
    "weights": {"Q": 1.0, "R": 0.1, "Qf": 10.0}, "limits": {"speed": 1.0},
    "workspace": {"lower": [-3.0, -2.0], "upper": [3.0, 2.0]},
    "solver": {"method": "centralized", "initial_guess": "shifted"},
    "agents": [{"start": [-1.5, 0.1], "goal": [1.5, 0.1]}, {"start": [1.5, -0.1], "goal": [-1.5, -0.1]}],
}


def fly(scn: Any, settings_: OCPSettings, steps: int, solver: Any = None, fallbacks: bool = False) -> np.ndarray:
    """A closed loop on the settings' model alone: the true states (T+1, M, n). ``solver``: the
    planner (None: centralised); ``fallbacks``: whether a step may fly a fallback plan."""
    model = settings_.model
    solver = solver if solver is not None else CentralizedSolver(settings_, scn.num_agents, scn.bodies)
    guesser = GuessProvider(scn, settings_)
    states, goals = scn.start_states(model), scn.goal_states(model)
    trajectory, plan = [states], None
    for _ in range(steps):
        if np.all(np.linalg.norm(model.position(states) - model.position(goals), axis=1) <= 0.01):
            break
        plan = solver.plan(states, goals, guesser.guesses(states, goals, plan))
        assert fallbacks or not plan.fallback.any(), "a solve failed"
        states = model.step(states, plan.inputs[:, 0])
        trajectory.append(states)
    return np.array(trajectory)


def test_a_registered_toy_model_swaps_two_agents_without_collision():
    scn = scenario_from_dict(SWAP)
    with registered_model("single_integrator", SingleIntegrator):
        settings_ = OCPSettings.from_scenario(scn, "single_integrator")
        assert isinstance(settings_.model, SingleIntegrator) and settings_.Q.shape == (2, 2)
        states = fly(scn, settings_, 150)
    assert "single_integrator" not in model_names()
    assert states.shape[2] == 2  # the toy's own state: the position
    goals = scn.goal_states(SingleIntegrator(2, 0.1))
    assert np.all(np.linalg.norm(states[-1] - goals, axis=1) <= 0.01)
    gaps = np.max(np.abs(states[:, 0] - states[:, 1]), axis=1)  # inf-norm: bodies overlap below delta
    assert gaps.min() >= 0.3
    speeds = np.linalg.norm(np.diff(states, axis=0), axis=2) / 0.1
    assert speeds.max() <= 1.0 + 1e-6


CROSSING = {"start": [0.0, 1.5], "goal": [0.0, -1.5]}
"""A third agent crossing the swap's path."""


@pytest.mark.parametrize("crossing", [False, pytest.param(True, marks=pytest.mark.loop)])
def test_a_registered_toy_model_swaps_under_admm_without_collision(crossing):
    agents = [*SWAP["agents"], CROSSING] if crossing else SWAP["agents"]
    scn = scenario_from_dict({**SWAP, "agents": agents, "solver": {"method": "admm", "initial_guess": "shifted"}})
    with registered_model("single_integrator", SingleIntegrator):
        settings_ = OCPSettings.from_scenario(scn, "single_integrator")
        executor = SerialExecutor()
        solver = ADMMSolver(settings_, scn.num_agents, scn.bodies, ADMMConfig(), executor)  # IPOPT local steps
        try:
            # three agents meeting at once may need the repair pass's fallback (the toy stops)
            states = fly(scn, settings_, 150, solver, fallbacks=crossing)
        finally:
            executor.close()
    assert states.shape[2] == 2  # the toy's own state: the position
    goals = np.array([a["goal"] for a in agents])
    assert np.all(np.linalg.norm(states[-1] - goals, axis=1) <= 0.01)
    for i, j in itertools.combinations(range(len(agents)), 2):
        gaps = np.max(np.abs(states[:, i] - states[:, j]), axis=1)  # inf-norm: bodies overlap below delta
        assert gaps.min() >= 0.3
    speeds = np.linalg.norm(np.diff(states, axis=0), axis=2) / 0.1
    assert speeds.max() <= 1.0 + 1e-6


def test_registry_registers_refuses_duplicates_and_forgets():
    assert "double_integrator" in model_names()
    assert isinstance(make_model("double_integrator", 3, 0.1, "zoh"), AgentModel)
    with pytest.raises(ValueError, match="unknown agent model"):
        make_model("single_integrator", 2, 0.1)
    register_model("single_integrator", SingleIntegrator)
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_model("single_integrator", SingleIntegrator)
        assert isinstance(make_model("single_integrator", 2, 0.1), AgentModel)
    finally:
        unregister_model("single_integrator")
    with pytest.raises(KeyError):
        unregister_model("single_integrator")


def test_settings_follow_their_dt_and_discretization():
    scn = scenario_from_dict({**SWAP, "solver": {}})
    base = OCPSettings.from_scenario(scn)
    assert isinstance(base.model, DoubleIntegrator) and base.first_constrained_step == 2
    zoh = replace(base, discretization="zoh", dt=0.2)
    assert (zoh.model.method, zoh.model.dt, zoh.first_constrained_step) == ("zoh", 0.2, 1)


# ----------------------------------------------------------------- the double integrator's interface
finite = st.floats(-3, 3, allow_nan=False)
methods = st.sampled_from(["euler", "zoh"])


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 3), st.lists(finite, min_size=12, max_size=12), methods)
def test_positions_and_velocities_are_the_two_halves(dim, values, method):
    model = DoubleIntegrator(dim, 0.1, method)
    p, v = np.array(values[:dim]), np.array(values[6 : 6 + dim])
    state = model.state_at(p, v)
    assert state.shape == (2 * dim,)
    assert np.array_equal(model.position(state), p) and np.array_equal(model.velocity(state), v)
    stack = np.stack([state, model.state_at(p)])[None]  # leading shape (1, 2)
    assert np.array_equal(model.position(stack)[0, 1], p) and not model.velocity(stack)[0, 1].any()
    assert model.position_rows == slice(0, dim) and model.first_constrained_step == (2 if method == "euler" else 1)


@settings(max_examples=40, deadline=None)
@given(st.lists(finite, min_size=4, max_size=4), st.lists(finite, min_size=16, max_size=16), methods)
def test_rollout_is_repeated_step(state, inputs, method):
    model = DoubleIntegrator(2, 0.1, method)
    controls = np.array(inputs).reshape(8, 2)
    states = model.rollout(np.array(state), controls)
    current = np.array(state)
    for k, control in enumerate(controls):
        current = model.step(current, control)
        assert np.array_equal(states[k + 1], current)
    A, B = model.linear_matrices()
    assert np.allclose(states[1], A @ states[0] + B @ controls[0])
    assert np.allclose(model.guess_inputs(states), controls)  # the velocity update is exact


@pytest.mark.parametrize("method", ["euler", "zoh"])
def test_casadi_dynamics_and_speed_are_the_numpy_ones(method):
    model = DoubleIntegrator(3, 0.1, method)
    rng = np.random.default_rng(3)
    inputs = rng.normal(size=(6, 3))
    states = model.rollout(rng.normal(size=6), inputs)
    X, U = ca.SX.sym("X", 6, 7), ca.SX.sym("U", 3, 6)
    dynamics = ca.Function("f", [X, U], [model.casadi_dynamics(X, U), model.casadi_speed_sq(X, U)])
    following, speed_sq = (np.array(v) for v in dynamics(states.T, inputs.T))
    np.testing.assert_allclose(following, states[1:].T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(speed_sq.ravel(), np.sum(model.velocity(states[1:]) ** 2, axis=1), rtol=1e-12)
    lower, upper = model.input_bounds(np.array([1.0, 2.0, 3.0]), 5.0)
    assert np.array_equal(upper, [1.0, 2.0, 3.0]) and np.array_equal(lower, -upper)
    assert np.all(np.isinf(model.input_bounds(None, None)[1]))


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 3), st.lists(finite, min_size=3, max_size=3), st.floats(0.2, 5.0), methods)
def test_braking_stops_within_the_limits(dim, velocity, accel, method):
    model = DoubleIntegrator(dim, 0.1, method)
    v = np.array(velocity[:dim])
    steps = int(np.ceil(np.max(np.abs(v)) / (accel * 0.1))) + 1
    limit = np.full(dim, accel)
    inputs = model.braking_inputs(model.state_at(np.zeros(dim), v), steps + 3, limit)
    assert inputs.shape == (steps + 3, dim) and np.all(np.abs(inputs) <= limit)
    states = model.rollout(model.state_at(np.zeros(dim), v), inputs)
    assert np.all(np.abs(model.velocity(states[steps:])) <= 1e-12)
    speeds = np.linalg.norm(model.velocity(states), axis=1)
    assert np.all(np.diff(speeds) <= 1e-12)  # never speeds up
    unlimited = model.braking_inputs(model.state_at(np.zeros(dim), v), 2, None)
    assert np.all(np.abs(model.velocity(model.rollout(model.state_at(np.zeros(dim), v), unlimited)[1])) <= 1e-12)


def admissible_inputs(model: DoubleIntegrator, state: np.ndarray, raw: np.ndarray, accel: np.ndarray | None,
                      speed: float | None) -> np.ndarray:
    """Inputs within the box whose planned velocities keep within the speed limit: each raw input
    clipped to the box and shrunk towards zero until the next velocity is within the limit."""
    inputs, v = [], model.velocity(state)
    for u in raw:
        u = np.clip(u, -accel, accel) if accel is not None else u
        if speed is not None:
            lo, hi = 0.0, 1.0  # largest t with ||v + t dt u|| <= speed (t = 0 holds: ||v|| <= speed)
            if np.linalg.norm(v + model.dt * u) > speed:
                for _ in range(60):
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if np.linalg.norm(v + mid * model.dt * u) <= speed else (lo, mid)
                u = lo * u
        inputs.append(u)
        v = v + model.dt * u
    return np.array(inputs)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3), st.lists(st.floats(-10, 10), min_size=36, max_size=36),
       st.sampled_from(["accel", "speed", "both"]), st.floats(0.2, 4.0), st.floats(0.2, 2.0), methods)
def test_no_admissible_plan_leaves_the_reach_bound(velocity, raw, limits, accel, speed, method):
    model = DoubleIntegrator(3, 0.1, method)
    a = np.full(3, accel) if limits != "speed" else None
    s = speed if limits != "accel" else None
    v = np.array(velocity)
    if s is not None and np.linalg.norm(v) > s:
        v *= s / np.linalg.norm(v)  # the measured velocity within the limit, as plans keep it
    state = model.state_at(np.array([0.5, -1.0, 2.0]), v)
    inputs = admissible_inputs(model, state, np.array(raw).reshape(12, 3), a, s)
    states = model.rollout(state, inputs)
    moved = np.max(np.abs(model.position(states) - model.position(state)))
    assert moved <= model.reach_bound(state, 12, a, s) + 1e-9
    assert model.reach_bound(np.stack([state, state]), 12, a, s).shape == (2,)
    assert np.isinf(model.reach_bound(state, 12, None, None))
