"""The elastic phase of a failed repair call on the QP path (``solver.qp.elastic``).

A repair call holds the neighbours' plans fixed. Its hard certificate loop can fail where a plan
exists: the certificates of the start ask for separations on sides the plan cannot reach in
time. Solved again with soft pair rows from its last plan, the loop moves the plan out of the way
and, when the soft plan needs no slack, the hard loop from it answers the call without IPOPT.
Checked here against independent answers:

(a) a call recorded from a crowded 64-agent start (tests/data/make_elastic_case.py), which the hard
    loop alone fails: the elastic phase answers it, and the answer is checked from its own
    numbers (the dynamics rolled out here, the input box, the workspace and the exact distance to
    every held plan);
(b) ``handover_slack``: with a limit, a call whose soft plan stays far from d_min is not handed to
    IPOPT; with none (the default), or with the elastic phase off (the behaviour before it), it is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_qp_accel import repair_problem

from swarmpc.bench import BenchCase
from swarmpc.formulation.nlp import NLPSolution
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.dynamics import discrete_matrices
from swarmpc.model.geometry import box_signed_distance
from swarmpc.solvers.admm import FallbackSolution, QPLocalSolverLadder
from swarmpc.solvers.guesses import agent_guess_blocks
from swarmpc.solvers.qp_local import PROVEN_INFEASIBLE, QPLocalLadder, QPLocalOptions

RECORDED = Path(__file__).parent / "data" / "elastic-repair-call.npz"


class HandedOver(Exception):
    """IPOPT was asked."""


class NoIPOPT:
    """An IPOPT ladder that raises :class:`HandedOver` when asked."""

    def solve(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        raise HandedOver


def recorded_call() -> tuple[OCPSettings, dict, dict, dict, int]:
    """(settings, parameters, guess: the failed loop's last plan, pinned copies, copies)."""
    data = np.load(RECORDED)
    s = OCPSettings.from_scenario(BenchCase(family="random", agents=64, seed=0, local="qp").scenario())
    params = {key[2:]: data[key] for key in data.files if key.startswith("p:")}
    params.update({key: float(params[key]) for key in ("rho", "owner_weight")})
    fixed = {key[2:]: data[key] for key in data.files if key.startswith("f:")}
    guess = agent_guess_blocks("", data["failed_X"].T, s, seed_duals=False)
    return s, params, guess, fixed, int(data["copies"])


def ladder(s: OCPSettings, **options: object) -> QPLocalSolverLadder:
    return QPLocalSolverLadder(QPLocalLadder(s, options=QPLocalOptions(**options)), NoIPOPT())  # type: ignore[arg-type]


def check_plan(s: OCPSettings, answer: NLPSolution, params: dict, fixed: dict, copies: int) -> None:
    """The answer's plan meets the hard claims, recomputed here from its states and inputs."""
    X, U = np.asarray(answer.x["X"]), np.asarray(answer.x["U"])
    A, B = discrete_matrices(s.dim, s.dt, s.discretization)
    rolled = [np.asarray(params["x0"], float)]
    for k in range(s.horizon):
        rolled.append(A @ rolled[-1] + B @ U[:, k])
    np.testing.assert_allclose(np.array(rolled).T, X, atol=1e-8)
    assert s.accel is not None and np.all(np.abs(U) <= s.accel[:, None] + 1e-9)
    own = X[: s.dim, s.first_constrained_step:]
    assert s.lower is not None and s.upper is not None
    assert np.all(own >= s.lower[:, None] - 1e-9) and np.all(own <= s.upper[:, None] + 1e-9)
    delta = np.asarray(params["delta"], float)
    for c in range(copies):
        distance = box_signed_distance(own - fixed[f"C{c}"], delta[:, c:c + 1], axis=0)
        assert np.all(distance >= s.d_min - 1e-9), (c, distance.min())


def test_the_recorded_call_fails_without_the_elastic_phase():
    s, params, guess, fixed, copies = recorded_call()
    answer = ladder(s, elastic=False).solve(params, guess, fixed, copies=copies, handover=False)
    assert not answer.success and answer.status != PROVEN_INFEASIBLE
    with pytest.raises(HandedOver):
        ladder(s, elastic=False).solve(params, guess, fixed, copies=copies)


def test_the_elastic_phase_answers_the_recorded_call_without_ipopt():
    s, params, guess, fixed, copies = recorded_call()
    answer = ladder(s).solve(params, guess, fixed, copies=copies)
    assert answer.success and not isinstance(answer, FallbackSolution)
    check_plan(s, answer, params, fixed, copies)


def test_an_elastic_answer_counts_the_time_of_every_loop():
    s, params, guess, fixed, copies = recorded_call()
    failed = ladder(s, elastic=False).solve(params, guess, fixed, copies=copies, handover=False)
    answer = ladder(s).solve(params, guess, fixed, copies=copies)
    assert answer.solve_time > failed.solve_time > 0.0


@pytest.mark.parametrize("dim", [2, 3])
def test_a_call_whose_soft_plan_stays_short_is_not_handed_over(dim):
    """An agent flying at a neighbour just off its line, within reach of its braking: no plan
    keeps d_min (the soft plan falls short by more than 1e-4 m), yet no bounding box proves it.
    With ``handover_slack`` 1e-4 IPOPT is not asked; with the default (None), a larger limit, or
    the elastic phase off, it is."""
    s, params, guess, pinned = repair_problem(dim, standing_at=0.8)
    pinned["C0"][1] = 0.15
    answer = ladder(s, handover_slack=1e-4).solve(params, guess, pinned, copies=1)
    assert not answer.success and answer.status != PROVEN_INFEASIBLE
    for options in ({}, {"handover_slack": 1.0}, {"elastic": False, "handover_slack": 1e-4}):
        with pytest.raises(HandedOver):
            ladder(s, **options).solve(params, guess, pinned, copies=1)


def test_no_elastic_phase_in_the_iterations_or_the_soft_form():
    """Calls with free copies (ADMM iterations) and calls of the soft pair form go as before."""
    s, params, guess, pinned = repair_problem(2, standing_at=0.8)
    pinned["C0"][1] = 0.15
    soft = QPLocalSolverLadder(QPLocalLadder(s, "soft"), NoIPOPT())  # type: ignore[arg-type]
    assert soft.solve(params, guess, pinned, copies=1).success  # always feasible
    assert ladder(s)._soft is None
    iteration = ladder(s)
    iteration.solve(params, guess, copies=1)
    assert iteration._soft is None


def test_no_elastic_phase_where_no_call_may_be_handed_over():
    """Under a deadline (``handover`` False) a failed repair call goes without the phase, as
    before it: the recorded call stays failed, and no soft problem is built."""
    s, params, guess, fixed, copies = recorded_call()
    deadline = ladder(s)
    answer = deadline.solve(params, guess, fixed, copies=copies, handover=False)
    assert not answer.success and deadline._soft is None
