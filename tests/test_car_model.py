"""The kinematic bicycle car: its numpy and CasADi steps agree, it drives straight lines and
constant-steering circles as the continuous model does, brakes within its limits, stays within its
reach bound, places its footprint where its geometry says, refuses bad parameters and meets the
AgentModel protocol through the registry."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.model.agent_model import AgentModel, make_model, model_names
from swarmpc.model.car import KinematicCar
from swarmpc.model.dynamics import lqr_terminal_weight

CAR = KinematicCar(2, 0.1)

headings = st.floats(-4.0, 4.0)
speeds = st.floats(-2.0, 2.0)
accels = st.floats(-1.0, 1.0)
steers = st.floats(-CAR.max_steer, CAR.max_steer)


def casadi_step(model: KinematicCar, states: np.ndarray, inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CasADi's following states (N, 4) and squared speeds (N,) of states (N+1, 4), inputs (N, 2)."""
    N = len(inputs)
    X, U = ca.SX.sym("X", 4, N + 1), ca.SX.sym("U", 2, N)
    f = ca.Function("f", [X, U], [model.casadi_dynamics(X, U), model.casadi_speed_sq(X, U)])
    following, speed_sq = f(states.T, inputs.T)
    return np.array(following).T, np.array(speed_sq).ravel()


# ----------------------------------------------------------------------------- the step itself
@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-5, 5), min_size=2, max_size=2), headings, speeds,
       st.lists(st.tuples(accels, steers), min_size=1, max_size=6), st.sampled_from([1, 2, 4]))
def test_numpy_and_casadi_steps_agree(position, theta, v, inputs, substeps):
    model = KinematicCar(2, 0.1, wheelbase=0.45, substeps=substeps)
    controls = np.array(inputs, float)
    states = model.rollout(np.array([*position, theta, v]), controls)
    following, speed_sq = casadi_step(model, states, controls)
    np.testing.assert_allclose(following, states[1:], rtol=0, atol=1e-12)
    np.testing.assert_allclose(speed_sq, states[1:, 3] ** 2, rtol=0, atol=1e-12)
    stacked = model.step(states[:-1], controls)  # a stack steps like one state at a time
    np.testing.assert_array_equal(stacked, states[1:])


@settings(max_examples=40, deadline=None)
@given(headings, speeds, st.integers(1, 30))
def test_straight_drive_at_constant_speed_is_exact(theta, v, steps):
    start = np.array([0.3, -1.2, theta, v])
    states = CAR.rollout(start, np.zeros((steps, 2)))
    t = np.arange(steps + 1) * CAR.dt
    expected = start[:2] + v * t[:, None] * np.array([math.cos(theta), math.sin(theta)])
    np.testing.assert_allclose(CAR.position(states), expected, rtol=0, atol=1e-12)
    assert np.all(states[:, 2] == theta) and np.all(states[:, 3] == v)


def circle_error(model: KinematicCar, v: float, delta: float, steps: int) -> float:
    """Largest distance of the reference point from the exact constant-steering path."""
    theta0 = 0.4
    states = model.rollout(np.array([1.0, 2.0, theta0, v]), np.tile([0.0, delta], (steps, 1)))
    radius = model.wheelbase / math.tan(delta)
    centre = np.array([1.0, 2.0]) + radius * np.array([-math.sin(theta0), math.cos(theta0)])
    theta = theta0 + v * np.arange(steps + 1) * model.dt / radius
    exact = centre + radius * np.stack([np.sin(theta), -np.cos(theta)], axis=1)
    np.testing.assert_allclose(states[:, 2], theta, rtol=0, atol=1e-12)  # RK4 integrates theta exactly
    return float(np.max(np.linalg.norm(CAR.position(states) - exact, axis=1)))


@pytest.mark.parametrize("v, delta", [(1.0, 0.3), (1.5, -CAR.max_steer), (-0.5, 0.5)])
def test_constant_steering_traces_a_circle_of_radius_wheelbase_over_tan_delta(v, delta):
    steps = 60  # six seconds: most of a lap at full lock
    fine, coarse = (circle_error(KinematicCar(2, 0.1, substeps=n), v, delta, steps) for n in (4, 2))
    # RK4's global error: C T h^4 with C from the path's derivatives (v kappa)^4 |v| / kappa
    kappa = abs(math.tan(delta)) / CAR.wheelbase
    h = CAR.dt / 4
    assert fine <= steps * CAR.dt * h**4 * (abs(v) * kappa) ** 4 * abs(v) / kappa
    assert fine < 1e-6 and 10 <= coarse / fine <= 20  # halving h divides the error by 2^4


# ----------------------------------------------------------------------------- state and inputs
@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-5, 5), min_size=2, max_size=2), st.lists(st.floats(-2, 2), min_size=2, max_size=2))
def test_state_at_and_velocity_agree(position, velocity):
    state = CAR.state_at(np.array(position), np.array(velocity))
    assert state.shape == (4,)
    np.testing.assert_allclose(CAR.position(state), position)
    np.testing.assert_allclose(CAR.velocity(state), velocity, atol=1e-12)
    rest = CAR.state_at(np.array([position, position]))
    assert rest.shape == (2, 4) and not rest[:, 2:].any()


@settings(max_examples=40, deadline=None)
@given(headings, speeds, st.lists(st.tuples(accels, steers), min_size=1, max_size=8))
def test_guess_inputs_reproduce_a_rollout(theta, v, inputs):
    controls = np.array(inputs, float)
    states = CAR.rollout(np.array([0.0, 0.0, theta, v]), controls)
    guessed = CAR.guess_inputs(states)
    np.testing.assert_allclose(CAR.rollout(states[0], guessed), states, rtol=0, atol=1e-9)
    lower, upper = CAR.input_bounds(None, None)
    assert np.all(guessed[:, 1] >= lower[1]) and np.all(guessed[:, 1] <= upper[1])


def test_guess_inputs_clip_the_steering_and_turn_in_place_at_full_lock():
    states = np.array([[0, 0, 0, 1.0], [0.1, 0, 1.0, 1.0], [0.1, 0, 1.02, 0.0], [0.1, 0, 1.02, 0.0]])
    guessed = CAR.guess_inputs(states)
    np.testing.assert_allclose(guessed[:, 0], [0.0, -10.0, 0.0])
    # tan(delta) = wheelbase dtheta / (dt mean v): 5 (beyond the lock), 0.2, and 0 at rest
    np.testing.assert_allclose(guessed[:, 1], [CAR.max_steer, math.atan(0.5 * 0.02 / 0.05), 0.0])
    at_rest = CAR.guess_inputs(np.array([[0, 0, 0, 0.0], [0, 0, -0.2, 0.0]]))
    np.testing.assert_allclose(at_rest, [[0.0, -CAR.max_steer]])


def test_input_bounds_hold_the_steering_and_the_smallest_axis_acceleration():
    lower, upper = CAR.input_bounds(np.array([2.0, 0.5]), 1.0)
    np.testing.assert_array_equal(upper, [0.5, CAR.max_steer])
    np.testing.assert_array_equal(lower, -upper)
    np.testing.assert_array_equal(CAR.input_bounds(None, None)[1], [CAR.default_accel, CAR.max_steer])


# ----------------------------------------------------------------------------- braking and reach
@settings(max_examples=60, deadline=None)
@given(headings, speeds, st.floats(0.2, 3.0))
def test_braking_stops_in_a_straight_line_within_the_limits(theta, v, accel):
    limit = np.array([accel, accel + 1.0])
    state = np.array([1.0, -1.0, theta, v])
    steps = int(np.ceil(abs(v) / (accel * CAR.dt))) + 1
    inputs = CAR.braking_inputs(state, steps + 3, limit)
    lower, upper = CAR.input_bounds(limit, None)
    assert inputs.shape == (steps + 3, 2) and np.all(inputs >= lower) and np.all(inputs <= upper)
    assert not inputs[:, 1].any()
    states = CAR.rollout(state, inputs)
    assert np.all(np.abs(states[steps:, 3]) <= 1e-12)
    assert np.all(np.diff(np.abs(states[:, 3])) <= 1e-12)  # never speeds up
    assert np.all(states[:, 2] == theta)  # wheels straight: the heading holds
    offsets = CAR.position(states) - state[:2]
    across = offsets @ np.array([-math.sin(theta), math.cos(theta)])
    assert np.all(np.abs(across) <= 1e-12)  # along the heading only
    assert CAR.braking_inputs(state, 2, None)[0, 0] == np.clip(-v / CAR.dt, -1.0, 1.0)  # default limit


def admissible_inputs(model: KinematicCar, v0: float, raw: np.ndarray, accel: np.ndarray | None,
                      speed: float | None) -> np.ndarray:
    """Raw inputs clipped to the box, the acceleration further to keep |v_{k+1}| <= speed."""
    lower, upper = model.input_bounds(accel, speed)
    inputs, v = [], v0
    for u in np.clip(raw, lower, upper):
        if speed is not None:
            u[0] = np.clip(u[0], (-speed - v) / model.dt, (speed - v) / model.dt)
        inputs.append(u)
        v = v + model.dt * u[0]
    return np.array(inputs)


def corners(model: KinematicCar, states: np.ndarray) -> np.ndarray:
    """The footprint's four corners (..., 4, 2)."""
    pose = model.pose(states)
    half_l, half_w = 0.5 * model.length, 0.5 * model.width
    local = np.array([[half_l, half_w], [half_l, -half_w], [-half_l, -half_w], [-half_l, half_w]])
    c, s = np.cos(pose[..., 2])[..., None], np.sin(pose[..., 2])[..., None]
    return pose[..., None, :2] + np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]], -1)


@settings(max_examples=80, deadline=None)
@given(headings, st.floats(-1.5, 1.5), st.lists(st.floats(-5, 5), min_size=24, max_size=24),
       st.sampled_from(["accel", "speed", "both", "none"]), st.floats(0.2, 3.0), st.floats(0.2, 2.0),
       st.floats(0.0, 0.7))
def test_no_admissible_plan_leaves_the_reach_bound(theta, v, raw, limits, accel, speed, overhang):
    model = KinematicCar(2, 0.1, rear_overhang=overhang)
    a = np.full(2, accel) if limits in ("accel", "both") else None
    s = speed if limits in ("speed", "both") else None
    v = float(np.clip(v, -s, s)) if s is not None else v  # the measured speed within the limit
    state = np.array([0.5, -1.0, theta, v])
    inputs = admissible_inputs(model, v, np.array(raw).reshape(12, 2), a, s)
    states = model.rollout(state, inputs)
    bound = model.reach_bound(state, 12, a, s)
    assert np.max(np.abs(model.position(states) - state[:2])) <= bound + 1e-9
    assert np.max(np.abs(corners(model, states) - corners(model, state))) <= bound + 1e-9
    assert np.max(np.abs(model.pose(states)[:, :2] - model.pose(state)[:2])) <= bound + 1e-9
    assert model.reach_bound(np.stack([state, state]), 12, a, s).shape == (2,)
    braking = model.rollout(state, model.braking_inputs(state, 12, a))
    assert np.max(np.abs(model.position(braking) - state[:2])) <= bound + 1e-9


# ----------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("theta", [0.0, math.pi / 2, -2.5])
def test_pose_puts_the_footprint_centre_ahead_of_the_rear_axle(theta):
    model = KinematicCar(2, 0.1, length=1.0, width=0.5, rear_overhang=0.2)
    assert model.footprint == (1.0, 0.5) and model.centre_offset == pytest.approx(0.3)
    state = np.array([2.0, -1.0, theta, 0.7])
    heading = np.array([math.cos(theta), math.sin(theta)])
    pose = model.pose(state)
    np.testing.assert_allclose(pose, [*(state[:2] + 0.3 * heading), theta])
    rear_bumper = pose[:2] - 0.5 * model.length * heading
    np.testing.assert_allclose(np.linalg.norm(rear_bumper - state[:2]), model.rear_overhang)
    assert model.pose(np.stack([state] * 3)[None]).shape == (1, 3, 3)
    behind = KinematicCar(2, 0.1, length=1.0, rear_overhang=0.9)  # reference point near the front
    np.testing.assert_allclose(behind.pose(state)[:2], state[:2] - 0.4 * heading)
    assert model.body_radius == pytest.approx(math.hypot(0.8, 0.25))


# ----------------------------------------------------------------------------- validation, protocol
@pytest.mark.parametrize("name, value", [
    ("dt", 0.0), ("wheelbase", 0.0), ("wheelbase", -1.0), ("length", 0.0), ("width", -0.1),
    ("rear_overhang", -0.1), ("rear_overhang", 0.8), ("max_steer", 0.0), ("max_steer", math.pi / 2),
    ("default_accel", 0.0), ("max_speed", 0.0), ("max_reverse_speed", -0.5), ("substeps", 0),
    ("substeps", 2.5), ("wheelbase", math.nan), ("discretization", "rk45"),
])
def test_bad_parameters_raise_naming_them(name, value):
    params = {name: value}
    dt, discretization = params.pop("dt", 0.1), params.pop("discretization", "euler")
    with pytest.raises(ValueError, match=name):
        make_model("car", 2, dt, discretization, **params)


def test_the_registered_car_meets_the_protocol():
    assert "car" in model_names()
    car = make_model("car", dim=2, dt=0.1, wheelbase=0.6, substeps=2)
    assert isinstance(car, AgentModel) and isinstance(car, KinematicCar)
    assert (car.name, car.state_dim, car.input_dim, car.position_rows) == ("car", 4, 2, slice(0, 2))
    assert car.first_constrained_step == 1 and car.linear_matrices() is None
    assert make_model("car", 2, 0.1, "zoh").dt == 0.1  # the scenario's discretisation: RK4 all the same
    with pytest.raises(ValueError, match="dim"):
        make_model("car", dim=3, dt=0.1)
    with pytest.raises(ValueError, match="not linear"):
        lqr_terminal_weight(car, np.eye(4), np.eye(2))
    assert CAR.speed_range == (-CAR.max_reverse_speed, CAR.max_speed)
