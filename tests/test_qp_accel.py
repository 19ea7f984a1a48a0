"""Repair calls of the QP local step under acceleration limits that no plan can meet.

In a repair pass the neighbours' plans are held fixed; under an acceleration limit they can close
in faster than the agent can get away, and then the problem has no feasible point. The QP path
proves that (swarmpc.solvers.qp_local.SeparationProof) instead of handing the call to IPOPT, which
could only fail on it, slowly. Checked here against independent answers:

(a) the union-of-boxes test on hand-made layouts whose answer is plain;
(b) a hand-built repair problem (an agent flying at a neighbour standing within its braking
    distance) is proven infeasible and answered without IPOPT, and every sampled input sequence
    within the box indeed breaks the separation (exact distances recomputed here);
(c) the proof stays silent wherever some plan keeps clear (the braking plan, checked here), and
    on problems with free copies or without an acceleration limit.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hyp_settings
from hypothesis import strategies as st

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.dynamics import discrete_matrices
from swarmpc.model.geometry import box_signed_distance
from swarmpc.solvers.admm import FallbackSolution, QPLocalSolverLadder
from swarmpc.solvers.qp_local import (
    PROVEN_INFEASIBLE,
    LocalShape,
    OSQPBackend,
    QPAnswer,
    QPLocalLadder,
    SeparationProof,
    box_covered,
    corners_covered,
    rollout_matrices,
)


def settings(dim: int, accel: float | None = 1.0) -> OCPSettings:
    """N = 10, dt = 0.1, hard OBCA with d_min = 0.05, acceleration limit ``accel`` per axis."""
    return OCPSettings(dim=dim, horizon=10, dt=0.1, discretization="euler", Q=0.1 * np.eye(2 * dim), R=np.eye(dim),
                       Qf=np.eye(2 * dim), collision="hard", d_min=0.05, kappa=1000.0, lower=None, upper=None,
                       accel=None if accel is None else np.full(dim, accel), speed=None, obstacles=())


def rollout(s: OCPSettings, state: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """States (2d, N+1) of the double integrator driven by ``inputs`` (d, N), by plain iteration."""
    A, B = discrete_matrices(s.dim, s.dt, s.discretization)
    states = [state]
    for k in range(s.horizon):
        states.append(A @ states[-1] + B @ inputs[:, k])
    return np.array(states).T


def repair_problem(dim: int, standing_at: float, accel: float | None = 1.0) -> tuple[OCPSettings, dict, dict, dict]:
    """An agent at the origin flying +x at 1 m/s, a neighbour standing on its path at
    x = ``standing_at`` (held fixed: a repair pass): settings, parameters, guess, pinned copy."""
    s = settings(dim, accel)
    K = s.num_constrained
    state = np.zeros(2 * dim)
    state[dim] = 1.0
    neighbour = np.zeros((dim, K))
    neighbour[0] = standing_at
    coast = rollout(s, state, np.zeros((dim, s.horizon)))
    zeros = np.zeros((dim, K))
    params = {"x0": state, "goal": np.zeros(2 * dim), "delta": np.full(dim, 0.3), "rho": 10.0, "owner_weight": 0.0,
              "Z": coast[:dim, s.first_constrained_step:], "Y": zeros, "Z0": neighbour, "Y0": zeros}
    guess = {"X": coast, "U": np.zeros((dim, s.horizon)), "C0": neighbour}
    return s, params, guess, {"C0": neighbour}


def clearance(s: OCPSettings, states: np.ndarray, neighbour: np.ndarray) -> float:
    """Least exact distance of the constrained positions to the neighbour's 0.3 box."""
    own = states[: s.dim, s.first_constrained_step:]
    return float(np.min(box_signed_distance(own - neighbour, np.full((s.dim, 1), 0.3), axis=0)))


class NoIPOPT:
    """An IPOPT ladder that must not be asked."""

    def solve(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("a proven-infeasible call was handed to IPOPT")


def test_box_covered_decides_unions_of_boxes():
    box = (np.zeros(2), np.ones(2))
    halves = (np.array([[-1.0, -1.0], [0.5, -1.0]]), np.array([[0.5, 2.0], [2.0, 2.0]]))
    assert box_covered(*box, *halves)  # two halves meeting at x = 0.5
    gap = (halves[0] + np.array([[0.0, 0.0], [0.1, 0.0]]), halves[1])
    assert not box_covered(*box, *gap)  # a strip 0.5 < x < 0.6 left open
    quarters = (np.array([[0, 0], [0.5, 0], [0, 0.5], [0.5, 0.5]], float),
                np.array([[0.5, 0.5], [1, 0.5], [0.5, 1], [1, 1]], float))
    assert box_covered(*box, *quarters)
    assert not box_covered(*box, quarters[0][:3], quarters[1][:3])  # one quarter missing
    assert box_covered(np.array([0.2, 0.2]), np.array([0.2, 0.9]), *quarters)  # a degenerate box (a segment)
    assert not box_covered(*box, np.zeros((0, 2)), np.zeros((0, 2)))


def covered_point_by_point(lower, upper, boxes_lower, boxes_upper):  # type: ignore[no-untyped-def]
    """The union test's reference: every cell centre of the cuts, checked box by box in Python."""
    centres = []
    for axis in range(len(lower)):
        cuts = sorted({min(max(v, lower[axis]), upper[axis]) for v in
                       [lower[axis], upper[axis], *boxes_lower[:, axis], *boxes_upper[:, axis]]})
        centres.append([0.5 * (a + b) for a, b in zip(cuts, cuts[1:], strict=False)] or cuts)
    points = np.stack(np.meshgrid(*centres, indexing="ij"), axis=-1).reshape(-1, len(lower))
    return all(any(np.all(bl <= p) and np.all(p <= bu) for bl, bu in zip(boxes_lower, boxes_upper, strict=True))
               for p in points)


@hyp_settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), dim=st.sampled_from([2, 3]), count=st.integers(1, 8))
def test_box_covered_agrees_with_a_point_by_point_check(seed, dim, count):
    """The vectorised union test (products of the axes' membership masks) decides as checking
    every cell centre against every box one by one does: boxes on a coarse grid, so that faces
    meet and corners touch exactly, and degenerate boxes among them."""
    rng = np.random.default_rng(seed)
    lower = rng.integers(0, 4, dim) * 0.25
    upper = lower + rng.integers(0, 4, dim) * 0.25
    boxes_lower = rng.integers(-2, 4, (count, dim)) * 0.25
    boxes_upper = boxes_lower + rng.integers(1, 6, (count, dim)) * 0.25
    assert box_covered(lower, upper, boxes_lower, boxes_upper) == covered_point_by_point(
        lower, upper, boxes_lower, boxes_upper)


@hyp_settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), dim=st.sampled_from([2, 3]), count=st.integers(0, 12))
def test_the_corner_filter_keeps_every_covered_box(seed, dim, count):
    """The proof's cheap filter (every corner in some box) drops only boxes the exact union test
    refuses too: random boxes on a coarse grid, so that faces meet and corners touch exactly."""
    rng = np.random.default_rng(seed)
    K = 6
    lower = rng.integers(0, 4, (K, dim)) * 0.25
    upper = lower + rng.integers(0, 4, (K, dim)) * 0.25
    boxes_lower = rng.integers(-2, 4, (K, count, dim)) * 0.25
    boxes_upper = boxes_lower + rng.integers(1, 6, (K, count, dim)) * 0.25
    kept = set(corners_covered(lower, upper, boxes_lower, boxes_upper).tolist())
    for k in range(K):
        if box_covered(lower[k], upper[k], boxes_lower[k], boxes_upper[k]):
            assert k in kept


def test_the_proof_decides_a_problem_posed_again_from_its_last_answer(monkeypatch):
    """A failed repair retried from the agent's own plan poses the same problem: the proof answers
    it again without deciding anew, and decides anew as soon as any input differs."""
    s, params, _, pinned = repair_problem(2, standing_at=0.55)
    proof = SeparationProof(s, *rollout_matrices(s), margin=1e-4)
    decided = []
    covered = proof._covered
    monkeypatch.setattr(proof, "_covered", lambda *args: decided.append(1) or covered(*args))
    copies, delta = pinned["C0"][None], np.full((2, 1), 0.3)
    assert proof.infeasible(params["x0"], copies, delta) and len(decided) == 1
    assert proof.infeasible(params["x0"].copy(), copies.copy(), delta.copy()) and len(decided) == 1
    assert not proof.infeasible(params["x0"], copies + np.array([[[0.0], [5.0]]]), delta) and len(decided) == 2


@pytest.mark.parametrize("dim", [2, 3])
def test_a_repair_call_no_plan_can_meet_is_proven_and_not_handed_to_ipopt(dim):
    """The neighbour stands within the agent's braking distance: no input sequence within the
    box keeps d_min from it, and the QP path says so without asking IPOPT."""
    s, params, guess, pinned = repair_problem(dim, standing_at=0.55)
    answer = QPLocalSolverLadder(QPLocalLadder(s), NoIPOPT()).solve(params, guess, pinned, copies=1)
    assert not answer.success and answer.status == PROVEN_INFEASIBLE
    assert not isinstance(answer, FallbackSolution)
    rng = np.random.default_rng(0)
    for _ in range(400):  # vertices and inner points of the input box, braking first
        inputs = rng.choice([-1.0, 0.0, 1.0], size=(dim, s.horizon)) * rng.random((dim, s.horizon)) ** 0.2
        inputs[0, : rng.integers(0, s.horizon + 1)] = -1.0
        assert clearance(s, rollout(s, params["x0"], inputs), pinned["C0"]) < s.d_min


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("standing_at", [0.95, 1.2, 3.0])
def test_the_proof_stays_silent_where_a_plan_keeps_clear(dim, standing_at):
    """Beyond the braking distance the braking plan keeps clear (checked here), so there is
    nothing to prove: the QP path answers the call itself."""
    s, params, guess, pinned = repair_problem(dim, standing_at)
    braking = np.zeros((dim, s.horizon))
    braking[0] = -np.minimum(1.0, np.maximum(1.0 - 0.1 * np.arange(s.horizon), 0.0) / 0.1)
    assert clearance(s, rollout(s, params["x0"], braking), pinned["C0"]) >= s.d_min
    ladder = QPLocalLadder(s)
    stepper = ladder.stepper(LocalShape(1, pinned=True))
    assert not stepper.proof.infeasible(params["x0"], pinned["C0"][None], np.full((dim, 1), 0.3))
    answer = QPLocalSolverLadder(ladder, NoIPOPT()).solve(params, guess, pinned, copies=1)
    assert answer.success and clearance(s, answer.x["X"], pinned["C0"]) >= s.d_min


def test_no_proof_without_pinned_copies_or_an_acceleration_limit():
    s, params, guess, pinned = repair_problem(2, standing_at=0.55, accel=None)
    assert QPLocalLadder(s).stepper(LocalShape(1, pinned=True)).proof.infeasible(
        params["x0"], pinned["C0"][None], np.full((2, 1), 0.3)) is False  # it can stop within a step
    s, params, guess, _ = repair_problem(2, standing_at=0.55)
    ladder = QPLocalLadder(s)
    assert ladder.stepper(LocalShape(1)).proof is None  # free copies: the neighbour can give way
    assert ladder.solve(params, guess, copies=1).status != PROVEN_INFEASIBLE


class RefusingOSQP(OSQPBackend):
    """OSQP that reports every solve failed."""

    def solve(self, x: np.ndarray, y: np.ndarray | None) -> QPAnswer:
        answer = super().solve(x, y)
        return QPAnswer(answer.x, answer.y, False, "refused", answer.iterations, answer.solver_time)


@pytest.mark.parametrize("dim", [2, 3])
def test_a_retry_of_the_same_problem_skips_the_restarts_that_failed(dim):
    """A failed call restarts from the coasting and the braking plan's certificates; a retry of
    the same problem from another start (a repair retried from the agent's own plan) does not
    run those two again, while a different problem does."""
    s, params, guess, pinned = repair_problem(dim, standing_at=3.0)
    stepper = QPLocalLadder(s, backend=RefusingOSQP).stepper(LocalShape(1, pinned=True))
    copy = pinned["C0"][None]
    assert not stepper.solve(params, guess, copy).success
    assert stepper.last_record.rounds == 3  # the guess's certificates, then coasting, then braking
    other_start = {**guess, "X": 0.5 * guess["X"]}
    assert not stepper.solve(params, other_start, copy).success
    assert stepper.last_record.rounds == 1
    moved = {**params, "x0": params["x0"] + 0.01}
    assert not stepper.solve(moved, guess, copy).success
    assert stepper.last_record.rounds == 3


@pytest.mark.parametrize("dim", [2, 3])
def test_a_call_without_restarts_answers_after_its_first_loop(dim):
    """``restarts=False`` (a quick call whose caller has a cheaper way out): a failed first loop is
    the answer, and it does not mark the problem's restarts as failed for a later call."""
    s, params, guess, pinned = repair_problem(dim, standing_at=3.0)
    stepper = QPLocalLadder(s, backend=RefusingOSQP).stepper(LocalShape(1, pinned=True))
    copy = pinned["C0"][None]
    assert not stepper.solve(params, guess, copy, restarts=False).success
    assert stepper.last_record.rounds == 1
    assert not stepper.solve(params, guess, copy).success
    assert stepper.last_record.rounds == 3
