"""The QP local step's two solvers (OSQP, PIQP) answer the same QPs alike.

(a) Random strictly convex QPs with equality and two-sided inequality rows, feasible by
    construction: both backends reach the same optimum (objective and point), before and after
    an update of the vectors and matrix values, and after an equality row opens.
(b) An infeasible QP is reported as such by PIQP, without a primal point.
(c) The duals come back in OSQP's convention: positive on a row at its upper bound.
(d) A repair call (the neighbour's plan pinned) answered with PIQP keeps the exact clearance and
    lands on OSQP's plan; the scenario key picks the backend per shape.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from test_qp_accel import NoIPOPT, clearance, repair_problem

from swarmpc.solvers.qp_local import (
    LocalShape,
    OSQPBackend,
    PIQPBackend,
    QPLocalLadder,
    QPLocalOptions,
    qp_backend,
)

OPTIONS = QPLocalOptions(eps_abs=1e-8, eps_rel=1e-8, max_iter=100_000)


def random_qp(seed: int, n: int, eq: int, ineq: int) -> tuple[sp.csc_matrix, np.ndarray, sp.csc_matrix, np.ndarray,
                                                                np.ndarray]:
    """(P upper triangle, q, A, l, u) of a strictly convex QP with a feasible point: ``eq``
    equality rows first, then ``ineq`` rows two-sided around a random point (some one-sided)."""
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(n, n))
    P = sp.csc_matrix(np.triu(L @ L.T + 0.5 * np.eye(n)))
    A = rng.normal(size=(eq + ineq, n)) * (rng.random((eq + ineq, n)) < 0.6)
    A[np.arange(eq + ineq), rng.integers(0, n, eq + ineq)] += 1.0  # no empty row
    point = rng.normal(size=n)
    centre = A @ point
    lower = centre - rng.uniform(0.0, 1.0, eq + ineq)
    upper = centre + rng.uniform(0.0, 1.0, eq + ineq)
    lower[:eq] = upper[:eq] = centre[:eq]
    lower[eq: eq + ineq // 3] = -np.inf
    return P, rng.normal(size=n) * 3, sp.csc_matrix(A), lower, upper


def objective(P: sp.csc_matrix, q: np.ndarray, x: np.ndarray) -> float:
    full = P + sp.triu(P, 1).T
    return float(0.5 * x @ (full @ x) + q @ x)


def both(P, q, A, lower, upper):  # type: ignore[no-untyped-def]
    backends = [OSQPBackend(OPTIONS), PIQPBackend(OPTIONS)]
    for b in backends:
        b.setup(P, q, A, lower, upper)
    return backends


def assert_same_answer(backends, P, q, A, lower, upper):  # type: ignore[no-untyped-def]
    start = np.zeros(A.shape[1])
    answers = [b.solve(start, None) for b in backends]
    assert answers[1].solved, answers[1].status  # the QPs are feasible by construction
    assume(answers[0].solved)  # OSQP at 1e-8 may run out of iterations on a degenerate one: no reference
    for a in answers:
        rows = A @ a.x
        assert np.all(rows >= lower - 1e-6) and np.all(rows <= upper + 1e-6)
    values = [objective(P, q, a.x) for a in answers]
    assert values[1] == pytest.approx(values[0], rel=1e-6, abs=1e-6)
    # strongly convex (P >= 0.5 I): an objective within 1e-6 puts the points within ~1e-3
    np.testing.assert_allclose(answers[1].x, answers[0].x, atol=1e-3 * max(1.0, float(np.abs(answers[0].x).max())))


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 12), eq=st.integers(0, 2), ineq=st.integers(1, 15))
def test_both_backends_reach_the_same_optimum_before_and_after_an_update(seed, n, eq, ineq):
    eq = min(eq, n - 1)  # equalities that fix every variable leave a point, where OSQP crawls
    P, q, A, lower, upper = random_qp(seed, n, eq, ineq)
    backends = both(P, q, A, lower, upper)
    assert_same_answer(backends, P, q, A, lower, upper)
    # a later call: new linear term and bounds, new matrix values in the same pattern
    rng = np.random.default_rng(seed + 1)
    q2 = q + rng.normal(size=n)
    A2 = A.copy()
    A2.data = A.data * (1 + 0.1 * rng.normal(size=A.nnz))
    centre = A2 @ rng.normal(size=n)
    lower2 = np.where(np.isfinite(lower), centre - (upper - lower) / 2, -np.inf)
    upper2 = centre + (upper - np.where(np.isfinite(lower), lower, upper - 1.0)) / 2
    lower2[:eq] = upper2[:eq] = centre[:eq]
    P2 = P.copy()
    P2.data = P.data * 1.5
    for b in backends:
        b.update(q2, lower2, upper2, P2.data, A2.data)
    assert_same_answer(backends, P2, q2, A2, lower2, upper2)


def test_osqps_compiled_solver_called_directly_answers_as_its_interface_does() -> None:
    """OSQPBackend calls OSQP's compiled solver for updates and solves (its interface's
    bookkeeping costs as much as a vector update); the same calls through the public interface
    (an OSQP without the compiled object) give the same answers, bit for bit, before and after an
    update of vectors and matrix values, and on an infeasible QP."""
    P, q, A, lower, upper = random_qp(11, n=8, eq=2, ineq=9)
    direct, public = OSQPBackend(OPTIONS), OSQPBackend(OPTIONS)
    for b in (direct, public):
        b.setup(P, q, A, lower, upper)
    assert direct._core is not None
    public._core = None
    rng = np.random.default_rng(12)
    start = rng.normal(size=8)
    for call in [(q, lower, upper, None, None), (q + 1.0, lower - 0.1, upper + 0.1, P.data * 2.0, A.data * 1.1)]:
        answers = []
        for b in (direct, public):
            b.update(*call)
            answers.append(b.solve(start, None))
        assert answers[0].solved and answers[0].status == answers[1].status
        assert answers[0].iterations == answers[1].iterations
        np.testing.assert_array_equal(answers[0].x, answers[1].x)
        np.testing.assert_array_equal(answers[0].y, answers[1].y)
    # x0 >= 1 and x0 <= 0: infeasible, reported alike
    P, A = sp.csc_matrix(np.triu(np.eye(2))), sp.csc_matrix(np.array([[1.0, 0.0], [1.0, 0.0]]))
    bounds = (np.array([1.0, -np.inf]), np.array([np.inf, 0.0]))
    for b in (direct, public):
        b.setup(P, np.zeros(2), A, *bounds)
    public._core = None
    infeasible = [b.solve(np.zeros(2), None) for b in (direct, public)]
    assert not infeasible[0].solved and infeasible[0].status == infeasible[1].status


def test_an_equality_row_that_opens_is_taken_as_an_inequality():
    P, q, A, lower, upper = random_qp(3, n=6, eq=2, ineq=6)
    backends = both(P, q, A, lower, upper)
    lower2, upper2 = lower.copy(), upper.copy()
    lower2[0], upper2[0] = lower[0] - 0.5, upper[0] + 0.5  # row 0 was an equality at set-up
    for b in backends:
        b.update(q, lower2, upper2, None, None)
    assert_same_answer(backends, P, q, A, lower2, upper2)


def test_a_row_without_bounds_is_left_out_until_it_gets_one(capfd: pytest.CaptureFixture[str]) -> None:
    """A row with neither bound (a free copy's position in a car's QP) does not reach PIQP, which
    would zero it and say so on every set-up; bounded at a later call, it constrains again."""
    P, q, A, lower, upper = random_qp(5, n=6, eq=1, ineq=6)
    lower[3], upper[3] = -np.inf, np.inf
    backends = both(P, q, A, lower, upper)
    assert_same_answer(backends, P, q, A, lower, upper)
    answer = backends[1].solve(np.zeros(6), None)
    assert answer.y.shape == (7,) and answer.y[3] == 0.0
    lower2, upper2 = lower.copy(), upper.copy()
    upper2[3] = float((A @ answer.x)[3]) - 0.5  # a bound the last answer breaks
    for b in backends:
        b.update(q, lower2, upper2, None, None)
    assert_same_answer(backends, P, q, A, lower2, upper2)
    assert float((A @ backends[1].solve(np.zeros(6), None).x)[3]) <= upper2[3] + 1e-6
    captured = capfd.readouterr()
    assert "PIQP" not in captured.out + captured.err


def test_an_infeasible_qp_is_reported_without_a_point():
    P = sp.csc_matrix(np.triu(np.eye(2)))
    A = sp.csc_matrix(np.array([[1.0, 0.0], [1.0, 0.0]]))
    backend = PIQPBackend(OPTIONS)
    backend.setup(P, np.zeros(2), A, np.array([1.0, -np.inf]), np.array([np.inf, 0.0]))  # x0 >= 1 and x0 <= 0
    start = np.array([0.3, 0.7])
    answer = backend.solve(start, None)
    assert not answer.solved and answer.status == "primal infeasible"
    np.testing.assert_array_equal(answer.x, start)
    assert answer.y.shape == (2,)


def test_the_duals_follow_osqps_convention():
    """min (x - 4)^2 / 2 + y^2 / 2 s.t. x <= 1 (active at the upper bound) and x + y = 0: OSQP's signs."""
    P = sp.csc_matrix(np.triu(np.eye(2)))
    q = np.array([-4.0, 0.0])
    A = sp.csc_matrix(np.array([[1.0, 1.0], [1.0, 0.0]]))
    lower, upper = np.array([0.0, -np.inf]), np.array([0.0, 1.0])
    answers = [b.solve(np.zeros(2), None) for b in both(P, q, A, lower, upper)]
    assert answers[0].y[1] > 0.5
    np.testing.assert_allclose(answers[1].y, answers[0].y, atol=1e-5)


def test_the_options_name_a_backend_per_shape():
    options = QPLocalOptions(repair_solver="piqp")
    assert isinstance(qp_backend(options), OSQPBackend)
    assert isinstance(qp_backend(options, pinned=True), PIQPBackend)
    assert isinstance(qp_backend(QPLocalOptions(solver="piqp")), PIQPBackend)
    with pytest.raises(ValueError, match="unknown QP solver"):
        qp_backend(QPLocalOptions(solver="qpoases"))


@pytest.mark.parametrize("dim", [2, 3])
def test_a_repair_call_answered_by_piqp_keeps_clear_and_matches_osqp(dim):
    from swarmpc.solvers.admm import QPLocalSolverLadder

    s, params, guess, pinned = repair_problem(dim, standing_at=1.2)
    plans = []
    for name in ("osqp", "piqp"):
        ladder = QPLocalLadder(s, options=QPLocalOptions(repair_solver=name))
        assert isinstance(ladder.stepper(LocalShape(1, pinned=True)).qp.backend,
                          PIQPBackend if name == "piqp" else OSQPBackend)
        answer = QPLocalSolverLadder(ladder, NoIPOPT()).solve(params, guess, pinned, copies=1)
        assert answer.success
        assert clearance(s, answer.x["X"], pinned["C0"]) >= s.d_min
        plans.append(answer.x["X"])
    np.testing.assert_allclose(plans[1], plans[0], atol=1e-3)


def test_a_ctrl_c_during_an_osqp_solve_reaches_the_program_and_the_qp_is_still_solved() -> None:
    """OSQP holds SIGINT for itself while it solves (it stops, status "interrupted"): the backend
    hands the signal back to the program's handler and solves again, so Ctrl-C is never lost and
    no answer reads "interrupted". The signals are sent from another thread every 37 ms while
    the main thread solves a QP large enough that most of them land inside a solve."""
    import os
    import signal
    import threading
    import time

    P, q, A, lower, upper = random_qp(0, 120, 10, 200)
    backend = OSQPBackend(QPLocalOptions(eps_abs=1e-10, eps_rel=1e-10, max_iter=100_000, polish=False))
    backend.setup(P, q, A, lower, upper)
    zero_x, zero_y = np.zeros(P.shape[0]), np.zeros(A.shape[0])
    sent, received, answers = 12, [], []

    def interrupter() -> None:
        for _ in range(sent):
            time.sleep(0.037)
            os.kill(os.getpid(), signal.SIGINT)

    previous = signal.signal(signal.SIGINT, lambda *_: received.append(1))
    try:
        thread = threading.Thread(target=interrupter)
        thread.start()
        while thread.is_alive():
            answers.append(backend.solve(zero_x, zero_y))  # cold each time: every solve takes a while
        thread.join()
        time.sleep(0.05)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert len(received) == sent
    assert all(a.solved and a.status == "solved" for a in answers)
