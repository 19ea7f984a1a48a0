"""The QP local step of car ADMM (:mod:`swarmpc.solvers.footprint_qp`): its expansion of a turning
corner, its answers against IPOPT's on the same local problems (same optimum), its exact checks,
and the calls it leaves to IPOPT.

Every distance is recomputed with the exact rectangle distance of :mod:`swarmpc.model.footprint`.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_footprint_ocp import D_MIN, GATE, car, point

from swarmpc.formulation.footprint_local import NeighbourKind, build_footprint_local, consensus_block, slot_size
from swarmpc.formulation.footprint_ocp import FootprintAgent
from swarmpc.model.footprint import rectangle_distance, rectangle_polytope_distance
from swarmpc.solvers import footprint_qp
from swarmpc.solvers.footprint_admm import footprint_local_guess
from swarmpc.solvers.footprint_central import straight_guess
from swarmpc.solvers.footprint_qp import FootprintLocalQP, _turned, corner_offsets
from swarmpc.solvers.qp_local import QPBackend, QPLocalOptions, qp_backend

HORIZON = 15


def _params(own: FootprintAgent, others: list[FootprintAgent], guess: np.ndarray, copies: list[np.ndarray],
            goal: np.ndarray, rho: float = 1.0) -> dict[str, np.ndarray]:
    rows = 3 if own.oriented else 2
    params = {"x0": guess[0], "goal": goal, "rho": np.array([[rho]]), "Z": consensus_block(own, guess),
              "Y": np.zeros((rows, HORIZON))}
    for slot, (other, copy) in enumerate(zip(others, copies, strict=True)):
        params.update({f"Z{slot}": copy, f"Y{slot}": np.zeros_like(copy), f"S{slot}": slot_size(own, other)})
    return params


def _both(own: FootprintAgent, others: list[FootprintAgent], start: np.ndarray, goal: np.ndarray,
          copies: list[np.ndarray], pinned: bool = False, owner_weight: float = 1.0,
          options: QPLocalOptions | None = None):  # type: ignore[no-untyped-def]
    """IPOPT's and the QP's answers to one local problem from the straight guess."""
    kinds = tuple(NeighbourKind.of(other) for other in others)
    guess = straight_guess(own, start, goal) if own.oriented else np.linspace(start, goal, HORIZON + 1)
    params = _params(own, others, guess, copies, goal)
    fixed = {f"C{slot}": copy for slot, copy in enumerate(copies)} if pinned else None
    nlp = build_footprint_local(own, kinds, owner_weight=owner_weight).solve(
        params, footprint_local_guess(own, guess, others, copies), fixed=fixed)
    options = options if options is not None else QPLocalOptions(max_rounds=50)
    qp = FootprintLocalQP(own, kinds, options, owner_weight).solve(params, guess, None, copies, pinned)
    return nlp, qp


@settings(max_examples=50, deadline=None)
@given(st.floats(-np.pi, np.pi), st.floats(0.1, 1.0), st.floats(0.05, 0.6))
def test_a_turned_corner_and_its_slope_match_the_rotation(theta: float, length: float, width: float) -> None:
    offsets = corner_offsets(np.array([length, width]))
    value, slope = _turned(np.array([theta]), offsets)
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    assert np.allclose(value[0], offsets @ rotation.T, atol=1e-12)
    h = 1e-6
    ahead, _ = _turned(np.array([theta + h]), offsets)
    behind, _ = _turned(np.array([theta - h]), offsets)
    assert np.allclose(slope[0], (ahead[0] - behind[0]) / (2 * h), atol=1e-8)


@pytest.mark.parametrize("owner_weight", [1.0, 5.0])
def test_a_car_passing_a_copy_reaches_the_nlp_optimum(owner_weight: float) -> None:
    """A car drives past a free copy of a car parked beside its way (closer than d_min to the
    straight way, not on it): both steps find one optimum."""
    own, other = car(horizon=HORIZON), car(horizon=HORIZON)
    parked = np.tile(np.array([[0.0], [0.55], [0.2]]), (1, HORIZON))
    nlp, qp = _both(own, [other], np.array([-2.0, 0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0, 0.0]), [parked],
                    owner_weight=owner_weight)
    assert nlp.success and qp.success
    assert qp.cost == pytest.approx(nlp.cost, rel=1e-3)
    assert np.abs(qp.x["X"] - nlp.x["X"]).max() < 1e-2
    assert np.abs(qp.x["C0"] - nlp.x["C0"]).max() < 1e-2


@pytest.mark.parametrize("pinned", [False, True])
@pytest.mark.parametrize("solver", ["osqp", "piqp"])
def test_either_qp_solver_reaches_the_nlp_optimum_and_prints_nothing(
    solver: str, pinned: bool, capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``solver.qp.solver`` (free copies) and ``solver.qp.repair_solver`` (pinned copies) choose the
    QP solver of a car's calls: both reach IPOPT's optimum. A free copy's positions are rows
    without bounds, which PIQP would zero with a message on every set-up: none is printed."""
    built: list[str] = []

    def spy(options: QPLocalOptions, pinned: bool = False) -> QPBackend:
        backend = qp_backend(options, pinned)
        built.append(type(backend).__name__)
        return backend

    monkeypatch.setattr(footprint_qp, "qp_backend", spy)
    own, other = car(horizon=HORIZON), car(horizon=HORIZON)
    parked = np.tile(np.array([[0.0], [0.55], [0.2]]), (1, HORIZON))
    options = QPLocalOptions(max_rounds=50, solver=solver, repair_solver=solver)
    nlp, qp = _both(own, [other], np.array([-2.0, 0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0, 0.0]), [parked],
                    pinned, options=options)
    assert nlp.success and qp.success
    assert qp.cost == pytest.approx(nlp.cost, rel=1e-3)
    assert np.abs(qp.x["X"] - nlp.x["X"]).max() < 1e-2
    assert built == [{"osqp": "OSQPBackend", "piqp": "PIQPBackend"}[solver]]
    captured = capfd.readouterr()
    assert "PIQP" not in captured.out + captured.err


def test_a_point_agent_between_a_car_and_a_point_copy_reaches_the_nlp_optimum() -> None:
    """Slow enough that the speed limit stays inactive (the QP's inner speed polytope is 2 %
    stricter than the NLP's disc where it binds)."""
    own, others = point(0.15, horizon=HORIZON), [car(horizon=HORIZON), point(0.1, horizon=HORIZON)]
    copies = [np.tile(np.array([[0.0], [0.5], [0.3]]), (1, HORIZON)), np.tile(np.array([[0.2], [-0.55]]), (1, HORIZON))]
    nlp, qp = _both(own, others, np.array([-0.8, 0.0, 0.0, 0.0]), np.array([0.8, 0.0, 0.0, 0.0]), copies)
    assert nlp.success and qp.success
    assert qp.cost == pytest.approx(nlp.cost, rel=1e-3)
    assert np.abs(qp.x["X"][:2] - nlp.x["X"][:2]).max() < 3e-2


def test_a_car_through_the_gate_keeps_clear_of_the_walls() -> None:
    """The gate's walls as static obstacles: the answer keeps d_min from both, by the exact
    distance between the footprint and each wall."""
    own = car(horizon=HORIZON, obstacles=GATE)
    nlp, qp = _both(own, [], np.array([-1.2, 0.0, 0.0, 0.0]), np.array([1.2, 0.0, 0.0, 0.0]), [])
    assert nlp.success and qp.success
    poses = own.poses(qp.x["X"].T[1:])
    for G, g in GATE:
        assert rectangle_polytope_distance(poses, own.size, G, g).min() >= D_MIN - 1e-6
    assert qp.cost == pytest.approx(nlp.cost, rel=1e-3)


@settings(max_examples=12, deadline=None)
@given(st.floats(-0.5, 0.5), st.floats(0.55, 1.2), st.floats(-0.6, 0.6))
def test_a_repair_answer_keeps_d_min_from_its_pinned_copy(x: float, y: float, theta: float) -> None:
    """A repair (copy pinned to a neighbour's plan): whenever the QP reports success, its plan
    keeps d_min from the pinned copy at every step by the exact rectangle distance."""
    own, other = car(horizon=HORIZON), car(horizon=HORIZON)
    pinned = np.tile(np.array([[x], [y], [theta]]), (1, HORIZON))
    _, qp = _both(own, [other], np.array([-2.0, 0.3, 0.0, 0.0]), np.array([2.0, 0.3, 0.0, 0.0]), [pinned], True)
    if qp.success:
        gaps = rectangle_distance(own.poses(qp.x["X"].T[1:]), own.size, pinned.T, other.size)
        assert gaps.min() >= D_MIN - 1e-6
    assert np.array_equal(qp.x["C0"], pinned)


def test_a_start_that_overlaps_a_copy_is_left_to_the_nlp() -> None:
    """The straight way runs through a car parked across it: which way round is the NLP's choice,
    so the QP answers that call failed (the ADMM then hands it to IPOPT), without running a QP."""
    own, other = car(horizon=HORIZON), car(horizon=HORIZON)
    parked = np.tile(np.array([[0.0], [0.05], [0.3]]), (1, HORIZON))
    nlp, qp = _both(own, [other], np.array([-2.0, 0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0, 0.0]), [parked], True)
    assert nlp.success
    assert not qp.success and qp.status == "qp: start overlaps" and qp.iterations == 0


def test_an_answer_flies_the_cars_own_dynamics() -> None:
    own, other = car(horizon=HORIZON), car(horizon=HORIZON)
    parked = np.tile(np.array([[0.0], [0.55], [0.2]]), (1, HORIZON))
    _, qp = _both(own, [other], np.array([-2.0, 0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0, 0.0]), [parked])
    states, inputs = qp.x["X"].T, qp.x["U"].T
    assert np.allclose(own.settings.model.rollout(states[0], inputs), states, atol=1e-9)
    lower, upper = own.settings.model.input_bounds(own.settings.accel, own.settings.speed)
    assert np.all(inputs >= lower - 1e-12) and np.all(inputs <= upper + 1e-12)
    assert np.all(np.abs(states[1:, 3]) <= own.settings.speed + 1e-5)
