"""Discretisations against independent closed forms."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from swarmpc.model.dynamics import DoubleIntegrator, continuous_matrices, discrete_matrices

finite = st.floats(-5, 5, allow_nan=False)


@pytest.mark.parametrize("dim", [2, 3])
def test_zoh_matches_matrix_exponential(dim):
    dt = 0.1
    A, B = continuous_matrices(dim)
    n, m = A.shape[0], B.shape[1]
    block = np.zeros((n + m, n + m))
    block[:n, :n], block[:n, n:] = A * dt, B * dt
    exact = expm(block)
    Ad, Bd = discrete_matrices(dim, dt, "zoh")
    assert np.allclose(Ad, exact[:n, :n])
    assert np.allclose(Bd, exact[:n, n:])


@settings(max_examples=50, deadline=None)
@given(st.lists(finite, min_size=9, max_size=9), st.floats(0.01, 0.5))
def test_one_step_closed_forms(values, dt):
    p, v, a = np.array(values[:3]), np.array(values[3:6]), np.array(values[6:])
    state = np.concatenate([p, v])
    euler = DoubleIntegrator(3, dt, "euler").step(state, a)
    zoh = DoubleIntegrator(3, dt, "zoh").step(state, a)
    assert np.allclose(euler, np.concatenate([p + dt * v, v + dt * a]))
    assert np.allclose(zoh, np.concatenate([p + dt * v + 0.5 * dt**2 * a, v + dt * a]))


def test_rollout_constant_input_zoh_is_exact_kinematics():
    model = DoubleIntegrator(2, 0.1, "zoh")
    state = np.array([0.0, 1.0, 0.5, -0.2])
    accel = np.array([0.3, -0.1])
    states = model.rollout(state, np.tile(accel, (20, 1)))
    t = 2.0
    assert np.allclose(states[-1, :2], state[:2] + state[2:] * t + 0.5 * accel * t**2)
    assert np.allclose(states[-1, 2:], state[2:] + accel * t)


def test_negative_dt_is_rejected():
    with pytest.raises(ValueError):
        discrete_matrices(2, -0.1)
